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


def test_a_cuda_index_past_the_gpus_torch_sees_is_refused_with_those_it_sees(monkeypatch):
    # "--device cuda:1" on a one-GPU machine passed the check, claimed the run folder and failed inside the env
    # build with torch's "invalid device ordinal" traceback.
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    with pytest.raises(RuntimeError, match=r"'cuda:1' requested but torch sees 1 CUDA GPU \(cuda:0\); pass one"):
        check_device("cuda:1")
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    with pytest.raises(RuntimeError, match=r"sees 2 CUDA GPUs \(cuda:0 to cuda:1\)"):
        check_device(torch.device("cuda", 5))
    assert check_device("cuda:1") == torch.device("cuda", 1) and check_device("cuda") == torch.device("cuda")
