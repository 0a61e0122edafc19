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



def test_sync_free_resets_match_torchrl_resets():
    """The sync-free reset path gives the same rollout as TorchRL's own (same seeds, falls and resets included)."""
    torch.manual_seed(0)
    actions = torch.rand(40, 3, 13) * 2 - 1
    rollouts, carries = [], []
    for sync_free in (False, True):
        e = make_env(num_envs=3, device="cpu", seed=5, sync_free_resets=sync_free, max_episode_steps=15)
        assert (type(e).__name__ == "SyncFreeResetEnv") == sync_free
        td = e.reset()
        steps, carry = [], []
        for a in actions:
            step, td = e.step_and_maybe_reset(td.set("action", a))
            steps.append(step)
            carry.append(td.exclude("action"))
        rollouts.append(torch.stack(steps, dim=1))
        carries.append(torch.stack(carry, dim=1))
    a, b = rollouts
    assert a["next", "truncated"].any() and a["next", "terminated"].any(), "the comparison must include both resets"
    for key in (("next", "observation"), ("next", "reward"), ("next", "done"), ("next", "step_count"),
                ("next", "episode_reward"), "observation", "episode_step", "step_count"):
        torch.testing.assert_close(a[key], b[key], msg=str(key))
    assert set(carries[0].keys(True, True)) == set(carries[1].keys(True, True))
    for key in carries[0].keys(True, True):
        torch.testing.assert_close(carries[0][key], carries[1][key], msg=str(key))


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_gpu_step_and_maybe_reset_never_syncs():
    e = make_env(num_envs=128, device="cuda", seed=0, max_episode_steps=3)
    td = e.reset()
    action = torch.rand(128, 13, device="cuda") * 2 - 1  # random torques: some robots fall
    for _ in range(2):  # warm-up: lazy initialisations may sync once
        _, td = e.step_and_maybe_reset(td.set("action", action))
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(6):  # crosses the 3-step truncation: automatic, masked resets included
            step, td = e.step_and_maybe_reset(td.set("action", action))
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert td["observation"].shape == (128, 237)
    assert bool(step["next", "truncated"].any() or step["next", "terminated"].any())
