"""make_env: the default transformed walking env on the real simulator, both physics backends."""

from __future__ import annotations

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from tocabi_torchrl import make_env
from tocabi_torchrl.transforms import REFERENCE_TERMS


@pytest.fixture(scope="module", params=["warp", "mujoco"])
def backend(request) -> str:
    return request.param


@pytest.fixture(scope="module")
def env(backend):
    return make_env(num_envs=3, device="cpu", seed=0, backend=backend)


def test_check_env_specs(env):
    check_env_specs(env, seed=0)


def test_policy_input_reward_and_terms(env):
    td = env.rollout(12, break_when_any_done=False)
    assert td["next", "observation"].shape == (3, 12, 237)
    assert td["next", "observation"].dtype == torch.float32
    terms = td["next", "reward_terms"]
    assert set(REFERENCE_TERMS) <= set(terms.keys())
    total = sum(terms[k] for k in terms.keys())
    alive = ~td["next", "terminated"]
    torch.testing.assert_close(td["next", "reward"] * alive, total * alive, rtol=1e-5, atol=1e-6)
    assert torch.all(td["next", "reward"] <= 2.4 + 1e-5)
    assert torch.all(td["next", "step_count"][:, -1] >= 1)
    assert ("next", "episode_reward") in td.keys(True)


def test_overrides_reach_env_and_transforms(backend):
    e = make_env(num_envs=2, device="cpu", control_mode="pd", max_episode_steps=7,
                 reward_weights={"qpos": 0.0}, backend=backend, sim_threads=1)
    assert e.base_env.cfg.control_mode == "pd" and e.base_env.cfg.max_episode_steps == 7
    assert e.base_env.backend == backend
    td = e.rollout(7, break_when_any_done=False)
    assert torch.all(td["next", "reward_terms", "qpos"] == 0)
    assert td["next", "truncated"][:, -1].all()
    with pytest.raises(TypeError, match="unknown option"):
        make_env(num_envs=2, device="cpu", history_length=3)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_gpu_transformed_step_never_syncs():
    e = make_env(num_envs=128, device="cuda", seed=0)
    td = e.reset()
    action = torch.zeros(128, 13, device="cuda")
    for _ in range(2):  # warm-up: lazy initialisations may sync once
        td = e.step(td.set("action", action))["next"]
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(3):
            td = e.step(td.set("action", action))["next"]
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert td["observation"].shape == (128, 237)

