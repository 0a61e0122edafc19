"""The one device check (tocabi_torchrl/device.py)."""

from __future__ import annotations

import pytest
import torch

from tocabi_torchrl.device import check_device


@pytest.mark.parametrize("name", ["cpu", "cpu:0", "cpu:3", torch.device("cpu", 1)])
def test_any_cpu_index_is_the_one_cpu_device(name):
    # "cpu:0" used to reach the env as itself: the policy's actions (on "cpu") were refused at the first step.
    assert check_device(name) == torch.device("cpu") and check_device(name).index is None


@pytest.mark.parametrize("name", ["gpu", "mps", "cpu:x"])
def test_other_devices_are_refused_with_the_accepted_names(name):
    with pytest.raises(ValueError, match="use 'cuda', 'cuda:K' or 'cpu'"):
        check_device(name)
