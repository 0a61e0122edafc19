"""Clear errors for impossible sizes and devices, raised before anything is allocated."""

from __future__ import annotations

import pytest
import torch

from tocabi_torchrl import make_env


@pytest.mark.parametrize("device", ["banana", None, "tpu", 3.5])
def test_make_env_rejects_a_bad_device_like_tocabiwalk(device):
    from tocabi_torchrl.envs import TocabiWalk

    with pytest.raises(ValueError, match="device .*use 'cuda', 'cuda:K' or 'cpu'"):
        make_env(num_envs=2, device=device)
    with pytest.raises(ValueError, match="device .*use 'cuda', 'cuda:K' or 'cpu'"):
        TocabiWalk(num_envs=2, device=device)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message without CUDA")
def test_make_env_on_cuda_without_a_gpu_says_so():
    with pytest.raises(RuntimeError, match="torch sees no CUDA GPU; pass device='cpu'"):
        make_env(num_envs=2, device="cuda")


@pytest.mark.parametrize("backend, name", [("mujoco", "C MuJoCo"), ("warp", "mujoco-warp")])
def test_a_huge_num_envs_is_refused_with_an_estimate_before_allocating(backend, name):
    with pytest.raises(ValueError, match=rf"1,000,000,000 {name} worlds need about [\d,.]+ GiB \([\d,]+ KiB per "
                                         r"world, estimated from the model\) but only [\d,.]+ [GM]iB of host "
                                         r"memory is available"):
        make_env(num_envs=10**9, device="cpu", backend=backend)


def test_the_estimates_are_plausible(model):
    from tocabi_torchrl.sim.buffers import NCONMAX, NJMAX
    from tocabi_torchrl.sim.memory import available_bytes, mujoco_world_bytes, warp_world_bytes

    # Measured: ~0.64 MB resident per C MuJoCo world; mujoco-warp's Data ~0.11 MB per world with the TOCABI buffers.
    assert 200_000 < mujoco_world_bytes(model) < 4_000_000
    assert 50_000 < warp_world_bytes(model, NCONMAX, NJMAX) < 2_000_000
    assert available_bytes(torch.device("cpu")) > 0
