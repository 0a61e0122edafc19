"""Observation + action history: exact placement (step indices written into the signals) and partial resets."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from mock_env import MockTocabiWalk
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs, step_mdp

from tocabi_torchrl.transforms import (
    REFERENCE_HISTORY,
    TOCABILAB_HISTORY,
    HistoryLayout,
    ObsActionHistory,
    PhaseEncoding,
)

N = 4
OBS_DIM = 2  # the mock's "command": every entry of env i after its step k equals k + 100·i
ACT_DIM = 13
ACT_UNIT = 0.01  # the action applied in an env's step k is k·ACT_UNIT in every entry (a_0 = 0: reset)


def _expected(layout: HistoryLayout, tau: int, env: int) -> torch.Tensor:
    """Policy input after an env's step τ under the layout's definition (entries before the episode = step 0)."""
    obs = [float(max(tau - a, 0) + 100 * env) for a in layout.obs_ages for _ in range(OBS_DIM)]
    act = [ACT_UNIT * max(tau - a, 0) for a in layout.action_ages for _ in range(ACT_DIM)]
    return torch.tensor(obs + act)


def _env(layout: HistoryLayout, **kwargs) -> TransformedEnv:
    return TransformedEnv(
        MockTocabiWalk(N, mode="counter", **kwargs), ObsActionHistory(layout, obs_key="command")
    )


def _act(td):
    """Each env's action is (its next step index)·ACT_UNIT, so a_k = k·ACT_UNIT in that env's episode."""
    k = (td["episode_step"] + 1).float()
    td["action"] = (ACT_UNIT * k).expand(N, ACT_DIM).clone()
    return td


def _check(td_next, layout):
    taus = td_next["episode_step"].squeeze(-1).tolist()
    for i, tau in enumerate(taus):
        torch.testing.assert_close(td_next["observation"][i], _expected(layout, tau, i), msg=f"env {i}, τ={tau}")


def test_reference_layout_definition():
    assert REFERENCE_HISTORY.obs_ages == (8, 6, 4, 2, 0)
    assert REFERENCE_HISTORY.action_ages == (7, 5, 3, 1)
    assert REFERENCE_HISTORY.size(37, 13) == 237
    assert REFERENCE_HISTORY.describe() == [
        "obs[t-8]", "obs[t-6]", "obs[t-4]", "obs[t-2]", "obs[t]",
        "action[t-7]", "action[t-5]", "action[t-3]", "action[t-1]",
    ]  # fmt: skip
    assert TOCABILAB_HISTORY.obs_ages == (4, 3, 2, 1, 0)
    assert TOCABILAB_HISTORY.action_ages == (3, 2, 1, 0)
    assert TOCABILAB_HISTORY.size(37, 13) == 237


def test_reference_history_places_each_observation_and_action():
    env = _env(REFERENCE_HISTORY)
    td = env.reset()
    assert td["observation"].shape == (N, 5 * OBS_DIM + 4 * ACT_DIM)
    _check(td, REFERENCE_HISTORY)  # τ = 0: five copies of obs_0, four zero actions
    for tau in range(1, 13):
        td = env.step(_act(td))
        _check(td["next"], REFERENCE_HISTORY)
        if tau == 12:
            # Spelled out for env 1: obs after steps 4, 6, 8, 10, 12 and actions a_5, a_7, a_9, a_11.
            row = td["next", "observation"][1]
            assert row[0 : 5 * OBS_DIM : OBS_DIM].tolist() == [104.0, 106.0, 108.0, 110.0, 112.0]
            acts = row[5 * OBS_DIM :: ACT_DIM]
            torch.testing.assert_close(acts, torch.tensor([0.05, 0.07, 0.09, 0.11]))
        td = step_mdp(td)


@pytest.mark.parametrize(
    "layout", [TOCABILAB_HISTORY, HistoryLayout(num_obs=1), HistoryLayout(num_obs=3, stride=3, num_actions=1)]
)
def test_other_layouts(layout):
    env = _env(layout)
    td = env.reset()
    _check(td, layout)
    for _ in range(9):
        td = env.step(_act(td))
        _check(td["next"], layout)
        td = step_mdp(td)


def test_partial_reset_refills_only_flagged_envs():
    env = _env(REFERENCE_HISTORY)
    td = env.reset()
    for _ in range(5):
        td = step_mdp(env.step(_act(td)))
    before = td["observation"].clone()
    flagged = torch.tensor([True, False, True, False])
    td["_reset"] = flagged.unsqueeze(-1)
    td = env.reset(td)
    # Flagged envs: history refilled with their first observation and zero actions; the others untouched.
    assert td["episode_step"].squeeze(-1).tolist() == [0, 5, 0, 5]
    torch.testing.assert_close(td["observation"][~flagged], before[~flagged], rtol=0, atol=0)
    _check(td, REFERENCE_HISTORY)
    # Keep stepping: every env follows its own episode, so the unflagged envs' buffers were not disturbed.
    for _ in range(9):
        td = env.step(_act(td))
        _check(td["next"], REFERENCE_HISTORY)
        td = step_mdp(td)


def test_auto_resets_in_rollout_follow_each_envs_episode():
    env = _env(REFERENCE_HISTORY, max_episode_steps=4)  # truncates every 4 steps
    ro = env.rollout(11, policy=_act, break_when_any_done=False)
    assert ro["next", "truncated"].any()
    for t in range(11):
        _check(ro[:, t]["next"], REFERENCE_HISTORY)
        _check(ro[:, t], REFERENCE_HISTORY)  # root: after a reset, the refilled history


def test_a_clone_of_a_used_history_keeps_its_own_buffers():
    # torchrl's clone is shallow: a clone of a history that had run shared its rings, so a second env's reset and
    # steps rewrote the first env's history in place.
    first = _env(REFERENCE_HISTORY)
    td = first.reset()
    for _ in range(3):
        td = step_mdp(first.step(_act(td)))
    history = first.transform
    before = history._obs.buf.clone(), history._act.buf.clone()
    second = TransformedEnv(MockTocabiWalk(N, mode="random"), history.clone())
    second.rollout(3)
    assert torch.equal(history._obs.buf, before[0]) and torch.equal(history._act.buf, before[1])
    for _ in range(9):  # the first env's policy input still follows its own episodes only
        td = first.step(_act(td))
        _check(td["next"], REFERENCE_HISTORY)
        td = step_mdp(td)


def test_counts_take_numpy_and_0d_integers_as_plain_ints():
    # The config tree reads a sweep's np.int64 or a 0-d tensor as the int it holds; the transforms' own checks
    # refused them, so HistoryLayout(num_obs=np.int64(5)) failed while the same value passed through the tree.
    layout = HistoryLayout(num_obs=np.int64(5), stride=torch.tensor(2), num_actions=np.array(4))
    assert layout == REFERENCE_HISTORY
    assert all(type(v) is int for v in (layout.num_obs, layout.stride, layout.num_actions))
    assert type(HistoryLayout(num_obs=np.int32(3)).num_actions) is int
    assert type(PhaseEncoding(harmonics=np.int64(2)).harmonics) is int
    for bad in (True, np.bool_(True), 5.0, np.float64(5.0), np.int64(0), torch.tensor([5])):
        with pytest.raises(ValueError, match="num_obs"):
            HistoryLayout(num_obs=bad)


def test_history_specs_and_errors():
    check_env_specs(_env(REFERENCE_HISTORY))
    with pytest.raises(ValueError, match="num_obs"):
        HistoryLayout(num_obs=0)
    with pytest.raises(ValueError, match="stride"):
        HistoryLayout(num_obs=5, stride=0)
    with pytest.raises(ValueError, match="num_actions"):
        HistoryLayout(num_obs=5, num_actions=-1)
    with pytest.raises(TypeError, match="HistoryLayout"):
        ObsActionHistory((5, 2))
    env = _env(REFERENCE_HISTORY)
    td = env.full_observation_spec.zero()
    td["action"] = torch.zeros(N, ACT_DIM)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(td)
    bad = TransformedEnv(MockTocabiWalk(N), ObsActionHistory(obs_key="foot_force"))
    with pytest.raises(ValueError, match=r"\(num_envs, D\)"):
        bad.observation_spec
