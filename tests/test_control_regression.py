"""Every control mode gives the same observations, rewards and dones as before the control laws became objects
(``tocabi_torchrl.control``): bit for bit on the C MuJoCo backend, whose arithmetic did not change."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from control_regression import CASES, KEYS, rollout

RECORDED = Path(__file__).parent / "data" / "control_regression.pt"


@pytest.fixture(scope="module")
def recorded():
    return torch.load(RECORDED, map_location="cpu", weights_only=True)


@pytest.mark.parametrize("case", sorted(CASES))
def test_same_numbers_as_recorded(case, recorded):
    got, want = rollout(case), recorded[case]
    for key in KEYS:
        assert torch.equal(got[key], want[key]), (
            f"{case}: {key} differs from the recording, max |diff| = {(got[key] - want[key]).abs().max():.3g}")
