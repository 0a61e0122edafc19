"""Stable-Baselines3 adapter: SB3's VecEnv interface and checks (spaces, NaN check wrapper, episode monitor),
terminal observation and truncation on a crafted episode, and 2 iterations of recipes/train_sb3.py end to end with
the gait test (CPU, tiny)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

pytest.importorskip("stable_baselines3")

from recipe_runner import load_recipe
from stable_baselines3.common.utils import check_for_correct_spaces
from stable_baselines3.common.vec_env import VecCheckNan, VecEnv, VecMonitor

from tocabi_torchrl.adapters import TocabiSB3VecEnv
from tocabi_torchrl.adapters.policy_file import load_policy

N = 2


@pytest.fixture(scope="module")
def env():
    e = TocabiSB3VecEnv(N, "cpu", max_episode_steps=2, reward_terms_in_infos=True)
    yield e
    e.close()


def test_vecenv_interface_passes_sb3_checks(env):
    assert isinstance(env, VecEnv)
    check_for_correct_spaces(env, env.observation_space, env.action_space)
    assert env.observation_space.shape == (237,) and env.action_space.shape == (13,)
    checked = VecMonitor(VecCheckNan(env, raise_exception=True))  # SB3's wrappers run on top of it
    obs = checked.reset()
    assert isinstance(obs, np.ndarray) and obs.shape == (N, 237) and obs.dtype == np.float32
    actions = np.stack([env.action_space.sample() for _ in range(N)])
    obs, rewards, dones, infos = checked.step(actions)
    assert rewards.shape == (N,) and dones.dtype == bool and len(infos) == N
    assert len(infos[0]["reward_terms"]) == 13
    assert math.isclose(sum(infos[0]["reward_terms"].values()), float(rewards[0]), rel_tol=1e-4, abs_tol=1e-5)
    assert env.get_attr("render_mode") == [None] * N and env.env_is_wrapped(VecMonitor) == [False] * N


def test_truncation_gives_terminal_observation_and_episode(env):
    env.seed(5)
    env.reset()
    zeros = np.zeros((N, 13), dtype=np.float32)
    obs, _, dones, infos = env.step(zeros)
    assert not dones.any() and "terminal_observation" not in infos[0]
    obs, _, dones, infos = env.step(zeros)
    assert dones.all()
    for i, info in enumerate(infos):
        assert info["TimeLimit.truncated"] is True  # SB3's PPO bootstraps the value of truncated episodes
        assert info["terminal_observation"].shape == (237,)
        assert not np.allclose(info["terminal_observation"], obs[i])  # obs is the reset one
        assert info["episode"]["l"] == 2


def test_step_wait_without_actions_is_refused(env):
    with pytest.raises(RuntimeError, match="step_async"):
        env.step_wait()
    with pytest.raises(ValueError, match="actions must have shape"):
        env.step_async(np.zeros((N, 3), dtype=np.float32))


def test_recipe_trains_two_iterations_with_the_reference_schedule(tmp_path):
    recipe = load_recipe("train_sb3")
    out = tmp_path / "run"
    result = recipe.main(["--out", str(out), "--device", "cpu", "--num_envs", "2", "--iterations", "2",
                          "--n_steps", "4", "--batch_size", "4", "--hidden", "16", "--eval_envs", "2",
                          "--eval_seconds", "0.1"])
    assert result["train"]["env_steps"] == 2 * 2 * 4
    assert (out / "sb3_model.zip").is_file() and result["eval"]["num_envs"] == 2
    _, state = load_policy(out / "policy.pt", "sb3")
    # The scheduled std: halfway through (2 of 2 rollouts done = progress 0) it sits at the end value 0.05.
    np.testing.assert_allclose(state["log_std"].numpy(), math.log(0.05), rtol=1e-6)
    assert recipe.LinearLR(1e-5, 2e-7)(0.5) == pytest.approx(5.1e-6)
    # The gait test ran SB3's own trained policy: the rebuilt network's mean action is that of SB3's saved model
    # (our own zip, written above; the schedules are replaced so that nothing of the recipe is unpickled).
    model = recipe.reference_ppo_class().load(out / "sb3_model.zip", device="cpu",
                     custom_objects={"learning_rate": 0.0, "lr_schedule": recipe.LinearLR(0.0, 0.0)})
    _, act = recipe.load_actor(out / "policy.pt")
    obs = torch.randn(3, 237)
    torch.testing.assert_close(act(obs), model.policy._predict(obs, deterministic=True))
