"""skrl adapter (skrl 2.x): the wrapper interface on device tensors, autoreset with the terminal observation, and
2 iterations of recipes/train_skrl.py end to end with the gait test (CPU, tiny)."""

from __future__ import annotations

import json

import pytest
import torch

pytest.importorskip("skrl")

from recipe_runner import load_recipe
from skrl.envs.wrappers.torch.base import Wrapper

from tocabi_torchrl.adapters import TocabiSkrlEnv

N = 2


def test_wrapper_interface_and_autoreset():
    env = TocabiSkrlEnv(N, "cpu", max_episode_steps=2)
    try:
        assert isinstance(env, Wrapper)
        assert env.num_envs == N and env.observation_space.shape == (237,) and env.action_space.shape == (13,)
        assert env.state_space is None and env.state() is None
        obs, _ = env.reset()
        assert obs.shape == (N, 237) and obs.device == env.device
        obs, reward, terminated, truncated, infos = env.step(torch.zeros(N, 13))
        assert reward.shape == terminated.shape == truncated.shape == (N, 1)
        assert not (terminated | truncated).any()
        assert set(infos["log"]) == {f"Reward / {k}" for k in env.stepper.term_names}
        obs, reward, terminated, truncated, infos = env.step(torch.zeros(N, 13))
        assert truncated.all() and not terminated.any() and infos["_final_obs"].all()
        assert not torch.equal(infos["final_obs"], obs)
    finally:
        env.close()


def test_recipe_trains_two_iterations_and_gait_tests(tmp_path):
    recipe = load_recipe("train_skrl")
    out = tmp_path / "run"
    result = recipe.main(["--out", str(out), "--device", "cpu", "--num_envs", "2", "--iterations", "2",
                          "--rollouts", "4", "--hidden", "16", "--eval_envs", "2", "--eval_seconds", "0.1"])
    assert result["train"]["env_steps"] == 2 * 2 * 4
    summary = json.loads((out / "eval" / "summary.json").read_text())
    assert summary["num_envs"] == 2 and "passes" in result["eval"]
    # The gait test's actor is the saved policy network: its action is the network's output (the Gaussian mean).
    from tocabi_torchrl.adapters.policy_file import load_policy

    _, state = load_policy(out / "policy.pt", "skrl")
    assert state["net.0.weight"].shape == (16, 237)
    _, act = recipe.load_actor(out / "policy.pt")
    obs = torch.randn(3, 237)
    hidden = torch.nn.functional.elu(obs @ state["net.0.weight"].T + state["net.0.bias"])
    torch.testing.assert_close(act(obs), hidden @ state["net.2.weight"].T + state["net.2.bias"])
