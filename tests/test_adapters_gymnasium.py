"""gymnasium adapter: registration, spaces from the TorchRL specs, gymnasium's own space and data checks, and the
SAME_STEP autoreset, truncation and termination on crafted episodes (CPU, 2 envs)."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_space_limit, data_equivalence
from gymnasium.vector import AutoresetMode

import tocabi_torchrl.adapters  # noqa: F401  (registers TocabiWalk-v0)
from tocabi_torchrl.adapters import TocabiVectorEnv

N = 2


@pytest.fixture(scope="module")
def envs():
    env = gymnasium.make_vec("TocabiWalk-v0", num_envs=N, device="cpu", numpy=True, max_episode_steps=3)
    yield env
    env.close()


def _zero(envs):
    return np.zeros(envs.action_space.shape, dtype=np.float32)


def test_make_vec_builds_the_adapter_with_same_step_autoreset(envs):
    assert isinstance(envs.unwrapped, TocabiVectorEnv)
    assert envs.num_envs == N
    assert envs.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP


def test_spaces_match_the_torchrl_specs(envs):
    env = envs.unwrapped.torchrl_env
    obs_spec, act_spec = env.observation_spec["observation"], env.action_spec
    assert envs.single_observation_space.shape == tuple(obs_spec.shape[1:]) == (237,)
    assert envs.observation_space.shape == tuple(obs_spec.shape)
    assert envs.single_action_space.shape == (13,)
    np.testing.assert_array_equal(envs.single_action_space.low, act_spec.space.low[0].numpy())
    np.testing.assert_array_equal(envs.single_action_space.high, act_spec.space.high[0].numpy())
    assert envs.single_action_space.low[-1] == 0.0 and envs.single_action_space.low[0] == -1.0  # phase rate >= 0
    for space, kind in ((envs.single_observation_space, "observation"), (envs.single_action_space, "action")):
        check_space_limit(space, kind)  # gymnasium's own check (warns on a badly scaled bounded space)


def test_reset_and_step_return_gymnasium_types_in_the_spaces(envs):
    obs, info = envs.reset(seed=3)
    assert isinstance(info, dict) and obs.dtype == np.float32 and envs.observation_space.contains(obs)
    action = envs.action_space.sample()
    obs, reward, terminated, truncated, infos = envs.step(action)
    assert envs.observation_space.contains(obs)
    assert reward.shape == (N,) and reward.dtype == np.float32
    assert terminated.dtype == bool and truncated.dtype == bool
    terms = infos["reward_terms"]
    assert len(terms) == 13
    np.testing.assert_allclose(sum(terms.values()), reward, rtol=1e-5, atol=1e-5)


def test_reset_with_a_seed_is_deterministic(envs):
    # gymnasium's env checker asks the same of single envs (check_reset_seed_determinism); data_equivalence is its.
    a, _ = envs.reset(seed=7)
    step_a = envs.step(_zero(envs))[0]
    b, _ = envs.reset(seed=7)
    step_b = envs.step(_zero(envs))[0]
    assert data_equivalence(a, b) and data_equivalence(step_a, step_b)


def test_truncation_at_the_time_limit_resets_in_the_same_step(envs):
    envs.reset(seed=0)
    for _ in range(2):
        obs, _, terminated, truncated, infos = envs.step(_zero(envs))
        assert not truncated.any() and not infos["_final_obs"].any() and not infos["_episode"].any()
    obs, _, terminated, truncated, infos = envs.step(_zero(envs))
    assert truncated.all() and not terminated.any()
    assert infos["_final_obs"].all() and infos["_episode"].all()
    np.testing.assert_array_equal(infos["episode"]["l"], [3, 3])
    assert not np.allclose(infos["final_obs"], obs)  # the returned obs is the reset one, not the terminal one
    # A fresh episode: the next step is its first, not a dummy transition.
    _, _, terminated, truncated, infos = envs.step(_zero(envs))
    assert not (terminated | truncated).any() and not infos["_episode"].any()


def test_termination_is_not_truncation_and_returns_the_episode():
    # A pelvis height limit above the robot makes every first step a fall; a 1-step limit makes it also the time
    # limit: termination wins, and truncation stays False.
    env = TocabiVectorEnv(N, "cpu", numpy=False, max_episode_steps=1, env_options={"min_pelvis_height": 5.0})
    try:
        env.reset(seed=1)
        obs, reward, terminated, truncated, infos = env.step(torch.zeros(N, 13))
        assert isinstance(obs, torch.Tensor) and obs.device == env.device
        assert terminated.all() and not truncated.any()
        assert infos["_episode"].all()
        assert torch.equal(infos["episode"]["l"], torch.ones(N, dtype=torch.int64))
        torch.testing.assert_close(infos["episode"]["r"], reward)
        assert not torch.equal(infos["final_obs"], obs)
    finally:
        env.close()


def test_bad_actions_and_options_are_refused(envs):
    envs.reset(seed=0)
    with pytest.raises(ValueError, match="actions must have shape"):
        envs.step(np.zeros((N, 12), dtype=np.float32))
    with pytest.raises(ValueError, match="takes no options"):
        envs.reset(options={"x": 1})


@pytest.mark.parametrize("kwargs, match", [
    ({"render_mode": "human"}, "does not render"),  # said, not silently dropped
    ({"numpy": "no"}, "numpy must be True or False"),  # bool("no") is True
    ({"vectorization_mode": "sync"}, "is a batched env .* use gymnasium.make_vec"),
])
def test_make_vec_names_what_the_env_cannot_do(kwargs, match):
    with pytest.raises(ValueError, match=match):
        gymnasium.make_vec("TocabiWalk-v0", num_envs=1, device="cpu", **kwargs)
    with pytest.raises(ValueError, match="is a batched env"):
        gymnasium.make("TocabiWalk-v0")


def test_make_vec_imports_the_adapters_itself_with_the_module_prefix():
    env = gymnasium.make_vec("tocabi_torchrl.adapters:TocabiWalk-v0", num_envs=1, device="cpu")
    try:
        assert isinstance(env.unwrapped, TocabiVectorEnv) and env.num_envs == 1
    finally:
        env.close()
