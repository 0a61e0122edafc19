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


def test_the_cpu_estimate_counts_each_worlds_own_model_and_field_rows(monkeypatch):
    # With per-world model fields (dynamics randomisation) the C MuJoCo estimate counted each world's model copy at
    # its bare nbuffer and its field rows not at all: about 10 % below the memory the worlds took.
    import os

    from tocabi_torchrl.sim import MujocoSim, SimConfig, mujoco_backend
    from tocabi_torchrl.sim.config import PER_WORLD_FIELDS

    def resident() -> int:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

    estimates = []
    check_fits = mujoco_backend.check_fits
    monkeypatch.setattr(mujoco_backend, "check_fits",
                        lambda n, per_world, *args: estimates.append(per_world) or check_fits(n, per_world, *args))
    MujocoSim(SimConfig(num_worlds=2, device="cpu", threads=1))
    MujocoSim(SimConfig(num_worlds=2, device="cpu", threads=1, per_world_fields=PER_WORLD_FIELDS))  # one-time costs
    n = 150
    before = resident()
    sim = MujocoSim(SimConfig(num_worlds=n, device="cpu", threads=1, per_world_fields=PER_WORLD_FIELDS))
    measured = (resident() - before) / n
    # Memory freed earlier in the process and taken again can only make the measured growth smaller.
    assert estimates[-1] >= 0.95 * measured, (estimates[-1], measured)
    # What the fields add: each world's model (its buffer, and 1.21× that resident, measured) and its two float64
    # rows of the fields (those written and those its model took).
    rows = sum(t[0].nbytes for t in (*sim.model_fields.values(), *sim._fields_taken.values()))
    assert estimates[-1] - estimates[0] >= 1.2 * sim._world_models[0].nbuffer + rows
