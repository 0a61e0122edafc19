"""The velocity-tracking error averaged over the last gait cycle: the rolling window (envs/cycle_velocity.py), the
env's cycle_vel_error signal (env.task.cycle_velocity) and the cycle_vel reward term that reads it."""

from __future__ import annotations

import doctest

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import step_mdp

from tocabi_torchrl.envs import TocabiWalk
from tocabi_torchrl.envs.command_config import CommandConfig
from tocabi_torchrl.envs import cycle_velocity
from tocabi_torchrl.envs.cycle_velocity import CycleVelocityError, heading_velocity


def test_docstring_examples_run():
    from tocabi_torchrl.transforms.reward_terms import CycleVelTracking

    result = doctest.testmod(cycle_velocity)
    assert result.attempted >= 4 and result.failed == 0
    runner = doctest.DocTestRunner()
    for test in doctest.DocTestFinder().find(CycleVelTracking, "CycleVelTracking",
                                             globs={"CycleVelTracking": CycleVelTracking}):
        runner.run(test)
    assert runner.summarize(verbose=False).failed == 0 and runner.tries >= 3


def test_the_rolling_mean_is_the_mean_of_each_worlds_last_window_since_its_reset():
    """Three worlds, window 5, 40 steps of random errors, each world reset at its own times: every step's mean is
    the plain mean of the world's errors since its reset, over the last 5 of them."""
    gen = torch.Generator().manual_seed(0)
    n, window = 3, 5
    rolling = CycleVelocityError(n, window, "cpu")
    resets = {0: (), 1: (7, 8, 30), 2: (12,)}  # world -> steps before which it resets
    history = [[] for _ in range(n)]
    step = torch.zeros(n, dtype=torch.int64)
    for k in range(40):
        mask = torch.tensor([k in resets[w] for w in range(n)])
        rolling.reset(mask)
        step.masked_fill_(mask, 0)
        for w in range(n):
            if mask[w]:
                history[w] = []
        step += 1
        velocity, command = torch.randn(n, 2, generator=gen), torch.randn(n, 2, generator=gen)
        rolling.update(velocity, command, step)
        got = rolling.mean(step)
        for w in range(n):
            history[w].append(velocity[w] - command[w])
            want = torch.stack(history[w][-window:]).mean(0)
            torch.testing.assert_close(got[w], want, atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="window must be an int >= 1"):
        CycleVelocityError(2, 0, "cpu")
    # An overflowing step counts as 0 and does not stay in the window beyond its own episode.
    rolling = CycleVelocityError(1, 3, "cpu")
    rolling.update(torch.tensor([[float("inf"), 0.0]]), torch.zeros(1, 2), torch.tensor([1]))
    rolling.reset(torch.tensor([True]))
    for k in range(1, 5):
        rolling.update(torch.tensor([[0.2, 0.1]]), torch.zeros(1, 2), torch.tensor([k]))
        torch.testing.assert_close(rolling.mean(torch.tensor([k])), torch.tensor([[0.2, 0.1]]))


def test_heading_velocity_turns_the_world_velocity_by_the_yaw_alone():
    """A pelvis rolled or pitched but facing +x: the heading frame is the world's; turned by ψ, a velocity along
    its heading reads as forward."""
    half = torch.tensor(0.1)  # 0.2 rad of roll, then of pitch
    rolled = torch.tensor([[torch.cos(half), torch.sin(half), 0.0, 0.0]])
    pitched = torch.tensor([[torch.cos(half), 0.0, torch.sin(half), 0.0]])
    v = torch.tensor([[0.4, -0.1, 0.05], [0.4, -0.1, 0.05]])
    torch.testing.assert_close(heading_velocity(torch.cat([rolled, pitched]), v), v[:, :2], atol=1e-6, rtol=0)
    psi = torch.tensor(0.6)
    turned = torch.stack([torch.cos(psi / 2), torch.tensor(0.0), torch.tensor(0.0), torch.sin(psi / 2)]).unsqueeze(0)
    along = torch.stack([0.5 * torch.cos(psi), 0.5 * torch.sin(psi), torch.tensor(0.0)]).unsqueeze(0)
    torch.testing.assert_close(heading_velocity(turned, along), torch.tensor([[0.5, 0.0]]), atol=1e-6, rtol=0)
    # A quaternion a little off unit (as an integrator leaves it) gives the same heading.
    torch.testing.assert_close(heading_velocity(turned * 1.001, along), torch.tensor([[0.5, 0.0]]), atol=1e-5, rtol=0)


def test_the_env_signal_is_the_robust_tests_cycle_mean_and_restarts_at_a_reset():
    """From diverse starts with zero torques and a command re-drawn every 100 steps, the env's cycle_vel_error is,
    at every step, the mean heading-frame velocity minus the mean command over the same window that the robust
    test's tracking error reads (CycleMeanTracking); a partial reset zeroes the reset world's, keeps the others' and
    restarts its window. Without the option the signal is absent."""
    from tocabi_torchrl.evaluation.robust import CycleMeanTracking, heading_frame_velocity

    assert "cycle_vel_error" not in TocabiWalk(num_envs=2, device="cpu", seed=0).reset().keys()
    env = TocabiWalk(num_envs=3, device="cpu", seed=0, control_mode="torque", cycle_velocity=True,
                     start_joint_vel_std=0.5, start_base_vel_std=0.1, command=CommandConfig(resample_every=100))
    window = env.cycle_velocity.window
    assert window == 450  # the reference motion's 1.7995 s at 4 ms
    td = env.reset()
    assert td["cycle_vel_error"].shape == (3, 2) and not td["cycle_vel_error"].any()
    reference = CycleMeanTracking(3, window)
    action = torch.zeros(3, 13)
    for k in range(window + 20):  # past one window, so values leave it
        td = env.step(td.set("action", action))
        nxt = td["next"]
        reference.update(heading_frame_velocity(nxt["base_quat"], nxt["base_lin_vel"]), nxt["command"],
                         torch.ones(3, dtype=torch.bool))
        if k in (0, 9, window - 1, window + 19):
            want = (reference.mean_velocity() - reference.mean_command()).float()
            torch.testing.assert_close(nxt["cycle_vel_error"], want, atol=1e-5, rtol=0)
        td = step_mdp(td)
    before = td["cycle_vel_error"].clone()
    assert before.abs().min() > 0
    td = env._reset(td.clone().set("_reset", torch.tensor([[False], [True], [False]])))
    assert not td["cycle_vel_error"][1].any()
    torch.testing.assert_close(td["cycle_vel_error"][[0, 2]], before[[0, 2]])
    restarted = CycleMeanTracking(1, window)  # world 1's new episode, from its first step
    for _ in range(5):
        td = env.step(td.set("action", action))
        nxt = td["next"]
        restarted.update(heading_frame_velocity(nxt["base_quat"][1:2], nxt["base_lin_vel"][1:2]), nxt["command"][1:2],
                         torch.ones(1, dtype=torch.bool))
        torch.testing.assert_close(nxt["cycle_vel_error"][1:2],
                                   (restarted.mean_velocity() - restarted.mean_command()).float(), atol=1e-5, rtol=0)
        td = step_mdp(td)


def test_the_cycle_vel_term_reads_the_signal_and_the_run_config_asks_for_both_switches():
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.transforms.reward_terms import CycleVelTracking
    from tocabi_torchrl.transforms.settings import REFERENCE_TERM_NAMES, TransformSettings

    term = CycleVelTracking(weight=0.5, scale=100.0)
    error = torch.tensor([[0.0, 0.0], [0.0, 0.05], [0.1, 0.0], [0.3, -0.2]])
    values = term(None, TensorDict({"cycle_vel_error": error}, [4])).flatten()
    torch.testing.assert_close(values, 0.5 * torch.exp(-100.0 * error.square().sum(-1)))
    assert values[0] == 0.5 and 0.38 < values[1] < 0.4 and values[3] < 1e-5  # 0.05 m/s: exp(-0.25)
    assert term.next_keys == ("cycle_vel_error",)
    # The run config: 0 (the default) adds no term; a weight adds it, and needs the env's signal.
    assert all(not isinstance(t, CycleVelTracking) for t in TransformSettings().transform_config().reward_terms)
    terms = TransformSettings(cycle_vel_weight=0.4, cycle_vel_scale=50.0).transform_config().reward_terms
    assert terms[:13] == REFERENCE_TERM_NAMES and terms[13] == CycleVelTracking(weight=0.4, scale=50.0)
    for name, bad in (("cycle_vel_weight", -0.1), ("cycle_vel_weight", float("nan")), ("cycle_vel_scale", 0.0),
                      ("cycle_vel_weight", True)):
        with pytest.raises(ValueError, match=f"transforms.{name} must be a finite number"):
            TransformSettings(**{name: bad}).validate()
    with pytest.raises(ValueError, match="set env.task.cycle_velocity=true as well"):
        preset_config("robust", **{"transforms.cycle_vel_weight": 0.5})
    cfg = preset_config("robust", **{"transforms.cycle_vel_weight": 0.5, "env.task.cycle_velocity": True})
    assert cfg.env.task.cycle_velocity and not preset_config("robust").env.task.cycle_velocity
    with pytest.raises(ValueError, match="env.task.cycle_velocity must be"):
        preset_config("robust", **{"env.task.cycle_velocity": 1})
    # Built by hand without the signal, the term names the env option that turns it on.
    from tocabi_torchrl import make_env

    with pytest.raises(KeyError, match="reports 'cycle_vel_error' only with its option 'cycle_velocity' on"):
        make_env(num_envs=2, device="cpu", seed=0, transforms=TransformSettings(cycle_vel_weight=0.5)).rollout(1)


def test_a_trainer_env_pays_the_term_from_the_signal(tmp_path):
    """The robust preset's env, as the trainer builds it, with the term on (a mild scale, so that the early errors
    of a standing start give values far from 0): the logged cycle_vel term is its weight times the kernel of the
    env's signal at every step."""
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.rl.trainer import build_env

    cfg = preset_config("robust", **{"transforms.cycle_vel_weight": 0.5, "transforms.cycle_vel_scale": 1.0,
                                     "env.task.cycle_velocity": True, "env.num_envs": 2, "ppo.minibatch_size": 24,
                                     "env.sim.start_pool": 0, "device": "cpu"})
    env = build_env(cfg, torch.device("cpu"), num_envs=2)
    nxt = env.rollout(5)["next"]
    error = nxt["cycle_vel_error"]
    want = 0.5 * torch.exp(-error.square().sum(-1, keepdim=True))
    alive = ~nxt["terminated"]
    assert alive.any() and (want[alive] > 0.1).all()
    torch.testing.assert_close(nxt["reward_terms", "cycle_vel"][alive], want[alive])


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_a_captured_step_keeps_the_rolling_window_as_the_eager_one_without_syncs():
    """The graphed env (cuda_graph=True) replays the window's gather, scatter and masked reset in place: its signal
    and the reward with the term on match the eager env's step by step, with no host sync after the warm-up."""
    from captured_vs_eager import assert_captured_equals_eager

    from tocabi_torchrl.transforms import TransformSettings

    assert_captured_equals_eager(dict(num_envs=64, device="cuda", seed=3, control_mode="torque", cycle_velocity=True,
                                      transforms=TransformSettings(cycle_vel_weight=0.5)),
                                 ("cycle_vel_error", "reward", "done"), steps=20)
