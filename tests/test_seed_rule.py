"""One seed rule and one message wherever a seed enters: an int in [0, 2**63 - 1] (numpy ints too; bools, floats and
text refused), named ``value_rules.check_seed``. ``TocabiWalk(seed=-1)`` used to build with a wrapped seed while
``set_seed(-1)`` failed in numpy ("expected non-negative integer") and ``set_seed(2**70)`` in torch ("Overflow"), and
``reset(seed=...)`` ignored its seed."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tocabi_torchrl import make_env
from tocabi_torchrl.config import preset_config
from tocabi_torchrl.envs import TocabiWalk
from tocabi_torchrl.value_rules import MAX_SEED, check_seed

BAD = [-1, 2**63, 2**70, True, 1.0, "3"]
MESSAGE = r"seed must be an int in \[0, 2\*\*63 - 1\] \(the env keeps it as a 64-bit int; not a bool, a float or text\)"


@pytest.fixture(scope="module")
def env():
    return TocabiWalk(num_envs=2, device="cpu", seed=0, backend="mujoco", control_mode="torque")


def test_the_rule():
    assert check_seed(0) == 0 and check_seed(MAX_SEED) == MAX_SEED
    assert check_seed(np.int64(7)) == 7 and type(check_seed(np.uint32(7))) is int
    for seed in BAD:
        with pytest.raises(ValueError, match=MESSAGE):
            check_seed(seed)


@pytest.mark.parametrize("seed", BAD, ids=repr)
def test_the_env_constructor_and_make_env_refuse_a_bad_seed(seed):
    with pytest.raises(ValueError, match=MESSAGE):
        TocabiWalk(num_envs=1, device="cpu", seed=seed, backend="mujoco")
    with pytest.raises(ValueError, match=MESSAGE):
        make_env(num_envs=1, device="cpu", seed=seed, backend="mujoco")


@pytest.mark.parametrize("seed", BAD, ids=repr)
def test_set_seed_and_a_seeded_reset_refuse_a_bad_seed_and_keep_the_old_one(env, seed):
    env.set_seed(5)
    with pytest.raises(ValueError, match=MESSAGE):
        env.set_seed(seed)
    with pytest.raises(ValueError, match=MESSAGE):
        env.reset(seed=seed)
    assert env._seed == 5 and int(env._seed_t) == 5


def test_the_largest_seed_is_taken_everywhere(env):
    from tocabi_torchrl.envs.episode_random import hash_seed

    env.set_seed(MAX_SEED)
    env.reset(seed=MAX_SEED)
    # The draws' key is the seed's 32-bit hash key (episode_random.hash_seed): the seed itself below 2**32.
    assert env._seed == MAX_SEED and int(env._seed_t) == hash_seed(MAX_SEED)


def test_a_seeded_reset_is_set_seed_then_reset(env):
    def first_episode(**reset_kwargs):
        td = env.reset(**reset_kwargs)
        return env.init_row.clone(), env.command.value.clone(), td["joint_pos"].clone()

    env.set_seed(3)
    want = first_episode()
    env.rollout(3)
    got = first_episode(seed=3)
    assert all(torch.equal(a, b) for a, b in zip(want, got))


def test_the_run_config_and_the_recipes_seed_use_the_rule():
    # ppo_walk's --seed is the run config's seed (tests/test_runs.py runs the recipe with -1 and 2**63).
    for seed in (-1, 2**63, True, 1.5):
        with pytest.raises(ValueError, match=MESSAGE):
            preset_config("cpu_smoke", seed=seed)
    assert type(preset_config("cpu_smoke", seed=np.int64(4)).seed) is int


def test_make_envs_reset_and_set_seed_use_the_rule():
    transformed = make_env(num_envs=1, device="cpu", seed=0, backend="mujoco", sync_free_resets=True)
    for seed in (-1, 2**70):
        with pytest.raises(ValueError, match=MESSAGE):
            transformed.reset(seed=seed)
        with pytest.raises(ValueError, match=MESSAGE):
            transformed.set_seed(seed)
