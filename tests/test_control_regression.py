"""Every control mode gives the same observations, rewards and dones as before the control laws became objects
(``tocabi_torchrl.control``), on the C MuJoCo backend, whose arithmetic did not change.

Observations and dones must match bit for bit. Rewards may differ by a few float32 ulp: their sums over terms are
vectorised by the CPU's ATen kernels, whose reduction order depends on the machine's vector width, so the same code
gives 1-2 ulp apart on two CPUs. A real change to a control law moves them by orders of magnitude more."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from control_regression import CASES, KEYS, rollout

RECORDED = Path(__file__).parent / "data" / "control_regression.pt"
_EPS = torch.finfo(torch.float32).eps  # 1.19e-07


@pytest.fixture(scope="module")
def recorded():
    return torch.load(RECORDED, map_location="cpu", weights_only=True)


@pytest.mark.parametrize("case", sorted(CASES))
def test_same_numbers_as_recorded(case, recorded):
    got, want = rollout(case), recorded[case]
    for key in KEYS:
        if key == "reward":
            ok = torch.allclose(got[key], want[key], rtol=4 * _EPS, atol=4 * _EPS)
        else:
            ok = torch.equal(got[key], want[key])
        assert ok, f"{case}: {key} differs from the recording, max |diff| = {_max_diff(got[key], want[key]):.3g}"



def _max_diff(got: torch.Tensor, want: torch.Tensor) -> float:
    return (got.double() - want.double()).abs().max().item()
