"""The torque preset's training aid: the env's torque assist, its fade schedule, the absorbing loss, the trainer's
use of both, and the wall-clock checkpoints of time-to-walk runs."""

from __future__ import annotations

import math

import pytest
import torch
from captured_vs_eager import assert_captured_equals_eager
from tensordict import TensorDict

from tocabi_torchrl import robot
from tocabi_torchrl.envs import TocabiWalk
from tocabi_torchrl.rl import make_actor, preset_config
from tocabi_torchrl.rl.actors import gaussian_head
from tocabi_torchrl.rl.assist import AssistAbsorbLoss, AssistSchedule, AssistTeacher
from tocabi_torchrl.rl.curves import read_metrics

N = 3
LIMITS = torch.as_tensor(robot.LEG_TORQUE_LIMITS, dtype=torch.float32)


@pytest.fixture(scope="module", params=["warp", "mujoco"])
def assisted(request):
    return TocabiWalk(num_envs=N, device="cpu", seed=0, backend=request.param, control_mode="torque", torque_assist=True,
                      pd_kp=tuple(robot.LEG_KP), pd_kv=tuple(robot.LEG_KV))


def _step(env, action):
    return env.step(TensorDict({"action": action}, batch_size=[env.num_envs]))["next"]


def test_assist_morphs_position_residuals_into_torques(assisted):
    env = assisted
    env.reset()
    for _ in range(5):  # leave the reset pose: nonzero errors and velocities
        _step(env, torch.zeros(N, 13))
    q, qd = env.sim.qpos[:, 7:19].clone(), env.sim.qvel[:, 6:18].clone()
    q_ref = env.motion.joint_targets(env.time, env.init_row)[:, :12]
    kp, kv = torch.as_tensor(robot.LEG_KP, dtype=torch.float32), torch.as_tensor(robot.LEG_KV, dtype=torch.float32)
    action = torch.zeros(N, 13)
    action[:, :12] = 0.1
    beta, scale = 0.25, env.cfg.control.pd_action_scale
    env.set_torque_assist(beta)
    out = _step(env, action)
    # (1 − β) × the reference's torque action + β × the residual-PD preset's servo on q_ref + scale × action.
    pd = kp * (q_ref + scale * 0.1 - q) - kv * qd
    expected = torch.maximum(torch.minimum((1 - beta) * 0.1 * LIMITS + beta * pd, LIMITS), -LIMITS)
    torch.testing.assert_close(out["leg_torque"], expected, rtol=1e-4, atol=1e-3)
    torch.testing.assert_close(env.sim.ctrl[:, :12], expected, rtol=1e-4, atol=1e-3)
    torch.testing.assert_close(out["leg_assist"], (kp * (q_ref - q) - kv * qd) / LIMITS, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(env.assist_gain(0.0), LIMITS)
    torch.testing.assert_close(env.assist_gain(1.0), scale * kp)
    # History and torque rewards see the applied torque over the limits, whatever β made it; the phase is the action's.
    torch.testing.assert_close(out["applied_action"][:, :12], expected / LIMITS, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(out["applied_action"][:, 12], action[:, 12])


def test_assist_off_applies_the_policy_torque_alone(assisted):
    env = assisted
    env.reset()
    env.set_torque_assist(0.0)
    action = torch.zeros(N, 13)
    action[:, :12] = torch.linspace(-0.5, 0.5, 12)
    out = _step(env, action)
    torch.testing.assert_close(out["leg_torque"], action[:, :12] * LIMITS)
    assert out["leg_assist"].abs().sum() > 0  # still recorded for the loss, just not applied
    torch.testing.assert_close(out["applied_action"], action)  # as in plain torque mode


def test_equal_torques_at_two_betas_give_equal_observations_and_rewards():
    # The morph changes what an action means and nothing else: two worlds in the same state, one at β = 0.6 and one
    # at β = 0.3, given actions that apply the same torque, see the same next observation and reward.
    from tocabi_torchrl import make_env

    kw = dict(num_envs=2, device="cpu", backend="mujoco", seed=1, control_mode="torque", torque_assist=True,
              pd_kp=tuple(robot.LEG_KP), pd_kv=tuple(robot.LEG_KV))
    envs = [make_env(**kw), make_env(**kw)]
    outs = []
    for env in envs:  # the same start and the same four steps at β = 0.6
        env.base_env.set_torque_assist(0.6)
        td = env.reset()
        for _ in range(4):
            td = env.step(td.set("action", torch.zeros(2, 13)))["next"]
        outs.append(td)
    envs[1].base_env.set_torque_assist(0.3)
    base = envs[0].base_env
    action = torch.zeros(2, 13)
    action[:, :12] = torch.linspace(-0.03, 0.03, 12)
    loss = AssistAbsorbLoss(_NoPPO(), gaussian_head(make_actor(6, 13, hidden=(8,))), base.leg_torque_limits)
    loss.set_step(base.assist_gain(0.6), base.assist_gain(0.3), 0.6, 0.3, 1.0)
    first = envs[0].step(outs[0].set("action", action))["next"]
    moved = action.clone()
    moved[:, :12] = loss.target(action[:, :12], first["leg_assist"])
    assert (moved[:, :12] - action[:, :12]).abs().max() > 1e-3  # a different action ...
    second = envs[1].step(outs[1].set("action", moved))["next"]
    torch.testing.assert_close(second["leg_torque"], first["leg_torque"], rtol=1e-4, atol=1e-2)  # ... same torque,
    torch.testing.assert_close(second["observation"], first["observation"], rtol=1e-4, atol=1e-4)  # same input,
    torch.testing.assert_close(second["reward"], first["reward"], rtol=1e-4, atol=1e-4)  # same reward


def test_assist_is_reset_with_the_world(assisted):
    env = assisted
    env.reset()
    env.set_torque_assist(1.0)
    before = _step(env, torch.zeros(N, 13))["leg_assist"]
    reset = torch.tensor([True, False, False])
    td = env.reset(TensorDict({"_reset": reset.unsqueeze(-1)}, batch_size=[N]))
    assert torch.all(td["leg_assist"][0] == 0) and before[1:].abs().sum() > 0
    torch.testing.assert_close(env.leg_assist[1:], before[1:])  # the other worlds keep their value


def test_assist_needs_torque_mode_and_an_assisted_env():
    with pytest.raises(ValueError, match="torque_assist needs control_mode='torque'"):
        TocabiWalk(num_envs=1, device="cpu", backend="mujoco", control_mode="pd", torque_assist=True)
    plain = TocabiWalk(num_envs=1, device="cpu", backend="mujoco")
    assert "leg_assist" not in plain.observation_spec.keys()
    with pytest.raises(RuntimeError, match="torque_assist=True"):
        plain.set_torque_assist(1.0)


def test_assist_schedule_holds_then_fades_to_zero():
    s = AssistSchedule(1.0, fade_start=100, fade_end=300)
    assert [s(x) for x in (0, 100, 200, 300, 10**9)] == [1.0, 1.0, 0.5, 0.0, 0.0]
    with pytest.raises(ValueError, match="fade_start < fade_end"):
        AssistSchedule(1.0, fade_start=300, fade_end=300)
    with pytest.raises(ValueError, match="gain_ratio"):
        AssistSchedule(1.0, fade_start=0, fade_end=1, gain_ratio=0.5)


def test_geometric_fade_shrinks_the_action_gain_by_the_same_factor_each_step():
    r = 7.0
    s = AssistSchedule(1.0, fade_start=0, fade_end=100, gain_ratio=r)
    gain = [1.0 + s(x) * (r - 1.0) for x in range(0, 101, 10)]  # c(β) / c(0)
    steps = [a / b for a, b in zip(gain, gain[1:])]
    assert gain[0] == pytest.approx(r) and gain[-1] == pytest.approx(1.0)
    assert steps == pytest.approx([r ** 0.1] * 10)
    assert s(50) < 0.5  # β falls faster early, slower near 0 than a linear fade


def test_absorb_target_applies_the_same_torque_at_the_next_beta():
    # Two identical worlds: one steps an action at β, the other the loss's target action at the smaller β'. Where the
    # target lies inside [-1, 1] the applied (limit-clipped) torques agree; actions beyond the box, and torques
    # beyond the limits, are clipped as the env clips them.
    kw = dict(num_envs=2, device="cpu", backend="mujoco", seed=1, control_mode="torque", torque_assist=True,
              pd_kp=tuple(robot.LEG_KP),
              pd_kv=tuple(robot.LEG_KV))
    at_beta, at_next = TocabiWalk(**kw), TocabiWalk(**kw)
    beta, beta_next = 0.6, 0.5
    for env in (at_beta, at_next):
        env.reset()
        env.set_torque_assist(beta)
        for _ in range(5):
            _step(env, torch.zeros(2, 13))
    action = torch.zeros(2, 13)
    action[0, :12] = torch.linspace(-0.06, 0.06, 12)
    action[1, :12] = torch.tensor([1.5, -1.5] * 6)  # beyond the box: the env applies ±1
    out = _step(at_beta, action)
    loss = AssistAbsorbLoss(_NoPPO(), gaussian_head(make_actor(6, 13, hidden=(8,))), at_beta.leg_torque_limits)
    loss.set_step(at_beta.assist_gain(beta), at_beta.assist_gain(beta_next), beta, beta_next, 1.0)
    target = loss.target(action[:, :12], out["leg_assist"])
    at_next.set_torque_assist(beta_next)
    moved = torch.cat((target, action[:, 12:]), dim=-1)
    torque_next = _step(at_next, moved)["leg_torque"]
    inside = target.abs() < 1.0
    assert inside[0].all()  # small actions: every target is reachable
    torch.testing.assert_close(torque_next[inside], out["leg_torque"][inside], rtol=1e-4, atol=1e-2)
    # Beyond the box the target stays on the action's side of it (the env applies the edge either way).
    assert torch.all(target[~inside] * action[:, :12][~inside] >= 1.0)


def _applied(loss, x, leg_assist, beta, gain):
    # The env's leg torque at assist scale beta for actions x: actions clipped to the box, torques to the limits.
    torque = gain * x.clamp(-1.0, 1.0) + beta * loss.limits * leg_assist
    return torch.maximum(torch.minimum(torque, loss.limits), -loss.limits)


def test_absorb_target_is_the_nearest_action_applying_the_same_torque():
    # The step the H100 fade broke on (β 1 → 0.97 with the robot's gain ratio ~7): a PD asking for 3× the limit
    # saturates the torque, and any action that keeps it saturated at β' is as good as the rollout's.
    limits = torch.full((12,), 100.0)
    loss = AssistAbsorbLoss(_NoPPO(), gaussian_head(make_actor(6, 13, hidden=(8,))), limits)
    gain_now, gain_next = 7.0 * limits, 6.8 * limits
    loss.set_step(gain_now, gain_next, 1.0, 0.97, 1.0)
    loc = torch.zeros(1, 12)
    saturated = torch.full((1, 12), 3.0)
    torch.testing.assert_close(loss.target(loc, saturated), loc)  # no pull: still saturated at β'
    # Random frames: the target applies the rollout's torque at β' wherever some action can, it is the rollout's
    # own action whenever that already does, and otherwise it moves no further than to where it does.
    g = torch.Generator().manual_seed(0)
    loc = 1.5 * torch.randn(4096, 12, generator=g)
    leg_assist = 2.0 * torch.randn(4096, 12, generator=g)
    torque = _applied(loss, loc, leg_assist, 1.0, gain_now)
    target = loss.target(loc, leg_assist)
    torque_next = _applied(loss, target, leg_assist, 0.97, gain_next)
    reachable = (_applied(loss, torch.full_like(loc, -1.0), leg_assist, 0.97, gain_next) <= torque) & (
        torque <= _applied(loss, torch.ones_like(loc), leg_assist, 0.97, gain_next))
    assert 0.2 < reachable.float().mean() < 1.0  # both cases occur
    torch.testing.assert_close(torque_next[reachable], torque[reachable], rtol=1e-5, atol=1e-3)
    same = _applied(loss, loc, leg_assist, 0.97, gain_next) == torque
    assert same.float().mean() > 0.1 and torch.equal(target[same], loc[same])
    # Nearest: half-way back towards loc the torque at β' is already different (for frames that moved).
    moved = reachable & ~same & ((target - loc).abs() > 1e-4)
    halfway = _applied(loss, (target + loc) / 2, leg_assist, 0.97, gain_next)
    assert moved.any() and torch.all((halfway[moved] - torque[moved]).abs() > 0)


class _NoPPO(torch.nn.Module):
    in_keys = ("observation",)

    def forward(self, td):
        return TensorDict({}, batch_size=[])


def test_absorb_loss_moves_the_mean_to_its_target():
    torch.manual_seed(0)
    actor = make_actor(6, 13, hidden=(64, 64), init_std=0.1)
    head = gaussian_head(actor)
    loss = AssistAbsorbLoss(_NoPPO(), head, torch.full((12,), 2.0))
    obs = torch.randn(256, 6)
    with torch.no_grad():
        loc0, scale = head(obs)
    # Like the PD it stands for, the assist is a function of the state the actor sees.
    assist = torch.tanh(obs @ torch.randn(6, 12) * 0.5)
    td = TensorDict({"observation": obs, "loc": loc0, "scale": scale, "next": {"leg_assist": assist}},
                    batch_size=[256])
    gain_now, gain_next = torch.full((12,), 2.0), torch.full((12,), 1.0)
    loss.set_step(gain_now, gain_next, 0.2, 0.1, weight=0.0)
    assert loss(td)["loss_absorb"].item() == 0.0  # weight 0: no pull
    loss.set_step(gain_now, gain_next, 0.2, 0.1, weight=1.0)
    opt = torch.optim.Adam(head.parameters(), lr=3e-3)
    for _ in range(400):
        opt.zero_grad()
        loss(td)["loss_absorb"].backward()
        opt.step()
    with torch.no_grad():
        loc1, _ = head(obs)
    target = 2.0 * loc0[:, :12] + 0.2 * assist  # (2·loc + 0.2·2·assist − 0.1·2·assist) / 1, nothing clipped
    moved, wanted = loc1[:, :12] - loc0[:, :12], target - loc0[:, :12]
    # The mean reached its target on the legs (to a few % of the move) and left the phase action alone.
    assert (moved - wanted).abs().mean() < 0.1 * wanted.abs().mean()
    assert (loc1[:, 12] - loc0[:, 12]).abs().mean() < 0.01


@pytest.mark.parametrize("overrides, match", [
    ({"env.control.mode": "pd_reference"}, "needs control_mode='torque'"),
    ({"ppo.assist_fade_start": 5, "ppo.assist_fade_end": 5}, "assist_fade_start < assist_fade_end"),
    ({"ppo.torque_assist": -1.0}, "torque_assist must be in \\[0, 1\\]"),
    ({"ppo.torque_assist": 1.5}, "torque_assist must be in \\[0, 1\\]"),
])
def test_torque_preset_rejects_bad_assist_settings(overrides, match):
    with pytest.raises(ValueError, match=match):
        preset_config("torque_ideal", **overrides)


def test_torque_preset_is_the_reference_action_space_with_a_fading_assist():
    cfg = preset_config("torque_ideal")
    assert cfg.env.control.mode == "torque" and cfg.ppo.torque_assist == 1.0
    assert 0 < cfg.ppo.assist_fade_start < cfg.ppo.assist_fade_end < cfg.total_env_steps
    assert cfg.transforms.history == "reference"  # 13 reference reward terms, reference observation


def _sensed_env(sensed: bool, num_envs: int = 4, randomized=None):
    """The robust preset's assisted training env (CPU, the lab's encoder biases) with ``ppo.assist_pd_sensed``."""
    from tocabi_torchrl.rl.trainer import build_env

    cfg = preset_config("robust", **{"ppo.assist_pd_sensed": sensed, "env.sim.start_pool": 0, "env.pushes.count": 0})
    env = build_env(cfg, torch.device("cpu"), num_envs=num_envs, for_training=True)
    if randomized is not None:
        env.base_env.set_randomized_worlds(randomized)
    return env


def _noise(env):
    from tocabi_torchrl.transforms import SensorNoise

    return next(t for t in env.transform if isinstance(t, SensorNoise))


def test_assist_pd_reads_the_joint_positions_the_policy_senses():
    """ppo.assist_pd_sensed: the PD's offset is the observation's own encoder bias, world by world and episode by
    episode (redrawn with a world's reset, kept by the others), 0 in an ideal world; off, the PD reads the truth."""
    worlds = torch.tensor([True, True, True, False])
    env = _sensed_env(True, randomized=worlds)
    env.reset()
    base, noise = env.base_env, _noise(env)
    legs_bias = noise.biases["joint_pos"][:, :12] * worlds.unsqueeze(-1)
    torch.testing.assert_close(base.leg_controller.q_offset, legs_bias, rtol=0, atol=0)
    assert bool((base.leg_controller.q_offset[:3].abs() > 0).all()) and bool((base.leg_controller.q_offset[3] == 0).all())
    assert float(base.leg_controller.q_offset.abs().max()) <= math.pi / 100
    before = base.leg_controller.q_offset.clone()
    mask = torch.tensor([True, False, False, False])
    env.reset(TensorDict({"_reset": mask.unsqueeze(-1)}, batch_size=[4]))
    after = base.leg_controller.q_offset
    torch.testing.assert_close(after, noise.biases["joint_pos"][:, :12] * worlds.unsqueeze(-1), rtol=0, atol=0)
    assert not torch.equal(after[0], before[0]) and torch.equal(after[1:], before[1:])

    off = _sensed_env(False)
    off.reset()
    assert bool((off.base_env.leg_controller.q_offset == 0).all())


def test_sensed_assist_pd_follows_the_sync_free_resets_of_training():
    """Through the training env's sync-free masked resets (step_and_maybe_reset, the captured step's path), every
    reset world's PD offset is its new episode's observation bias, and the others keep theirs."""
    from tocabi_torchrl.rl.trainer import build_env

    cfg = preset_config("robust", **{"env.sim.start_pool": 0, "env.pushes.count": 0,
                                     "env.task.max_episode_steps": 3})
    env = build_env(cfg, torch.device("cpu"), num_envs=4, for_training=True, sync_free_resets=True)
    noise, offset = _noise(env), env.base_env.leg_controller.q_offset
    td = env.reset()
    seen = offset.clone()
    for _ in range(4):  # episodes of 3 steps: every world resets once in the loop
        td["action"] = torch.zeros(4, 13)
        _, td = env.step_and_maybe_reset(td)
        torch.testing.assert_close(offset, noise.biases["joint_pos"][:, :12], rtol=0, atol=0)
    assert not torch.equal(offset, seen) and bool((offset != seen).any(-1).all())


def test_sensed_assist_pd_subtracts_the_encoder_bias_times_the_stiffness():
    """Same worlds, same state, same action: the sensed PD differs from the true-position PD by exactly −kp·bias
    (over the limits)."""
    envs, out = (_sensed_env(True), _sensed_env(False)), []
    for env in envs:
        td = env.reset()
        env.base_env.set_torque_assist(1.0)
        td["action"] = torch.zeros(4, 13)
        out.append(env.step(td)["next"]["leg_assist"])
    kp = torch.as_tensor(robot.LEG_KP, dtype=torch.float32)
    offset = envs[0].base_env.leg_controller.q_offset
    torch.testing.assert_close(out[0] - out[1], -kp * offset / LIMITS, rtol=1e-4, atol=1e-5)
    assert float((out[0] - out[1]).abs().max()) > 0.1  # the bias matters: > 10 % of a limit


def test_teacher_options_need_the_teacher_target():
    # With assist_target "rollout" there is no teacher: the pull's decay and the hold through it trained exactly as
    # without them.
    for option, value in (("ppo.assist_anchor_decay", 1000), ("ppo.assist_lr_hold", "pull")):
        with pytest.raises(ValueError, match=r"about the teacher's pull, and ppo.assist_target='rollout' has no "):
            preset_config("torque_ideal", **{"ppo.assist_target": "rollout", option: value})
    preset_config("torque_ideal", **{"ppo.assist_target": "rollout", "ppo.assist_anchor_decay": 0})


def test_assist_pd_sensed_needs_the_assist():
    with pytest.raises(ValueError, match="assist_pd_sensed .* needs ppo.torque_assist > 0"):
        preset_config("default", **{"ppo.assist_pd_sensed": True})
    with pytest.raises(RuntimeError, match="torque_assist=True"):
        TocabiWalk(num_envs=1, device="cpu", control_mode="torque").sense_assist_joints()


@pytest.mark.parametrize("target", ["teacher", "rollout"])
def test_training_fades_the_assist_and_builds_evaluation_envs_without_it(tmp_path, target):
    from tocabi_torchrl.rl.trainer import build_env, train

    n, steps = 4, 8
    frames = n * steps
    cfg = preset_config("torque_ideal", device="cpu", **{"env.num_envs": n, "ppo.steps_per_env": steps,
                        "ppo.minibatch_size": 16, "ppo.epochs": 1},
                        total_env_steps=4 * frames, **{"ppo.assist_fade_start": frames,
                                                       "ppo.assist_fade_end": 3 * frames,
                        "ppo.assist_target": target, "ppo.assist_anchor_decay": frames if target == "teacher" else 0,
                        "ppo.actor_hidden": (16,), "ppo.critic_hidden": (16,)}, run_dir=str(tmp_path), name="t",
                        eval_at_end=False, progress_bar=False, checkpoint_every=1, checkpoint_keep_last=0,
                        **{"ppo.cuda_graph": "off"})
    result = train(cfg)
    rows = read_metrics(result.run_dir)
    # β each rollout ran with: 1, 1 (the fade starts after one iteration), halfway through the (geometric) fade, 0.
    # The fade is geometric in the env's action gain: c(1)/c(0) is the legs' mean of 0.5 rad · Kp / limit.
    r = math.exp(sum(math.log(0.5 * kp / lim) for kp, lim in zip(robot.LEG_KP, robot.LEG_TORQUE_LIMITS)) / 12)
    assert [float(row["torque_assist"]) for row in rows] == pytest.approx([1.0, 1.0, 1 / (math.sqrt(r) + 1), 0.0])
    absorb = [float(row["loss_absorb"]) for row in rows]
    assert absorb[0] == 0.0 and absorb[1] > 0 and absorb[2] > 0 and absorb[3] == 0.0
    # The teacher's pull ends anchor_decay steps after the fade (here at the last iteration).
    assert [float(row["absorb_weight"]) for row in rows] == [0.0, 1.0, 1.0, 0.0]
    lr = [float(row["lr"]) for row in rows]
    assert lr[1] == lr[0] and lr[2] == lr[0]  # held while the assist fades
    folder = result.run_dir / "checkpoints"
    first, last = (torch.load(folder / f"iter_{i:06d}.pt", weights_only=True)["agent"] for i in (1, 4))
    if target == "teacher":
        # Taken as the fade began (after iteration 1), at β = 1, and kept: the actor then moved away from it.
        assert not first["teacher"]["anchored"] and last["teacher"]["anchored"]
        assert float(last["teacher"]["beta"]) == 1.0
        key = next(k for k in last["teacher"] if k.startswith("mean_net") and k.endswith("weight"))
        actor_key = next(k for k in last["actor"] if k.endswith(key))
        assert not torch.equal(last["teacher"][key], last["actor"][actor_key])
    else:
        assert "teacher" not in last
    assert build_env(cfg, torch.device("cpu"), num_envs=2).base_env.cfg.torque_assist is False
    assert build_env(cfg, torch.device("cpu"), num_envs=2, for_training=True).base_env.cfg.torque_assist is True


@pytest.mark.parametrize("hold, bound", [("fade", 0.0), ("pull", 0.0), ("pull", 1e-4)])
def test_the_adaptive_rate_is_held_through_the_fade_or_also_the_teachers_pull(tmp_path, hold, bound):
    # A KL target no update meets (KL > 2e-12: the rate falls) unless it leaves the policy as it was (KL 0: rises), so
    # the adaptive rule changes the rate after every update where it is not held.
    from tocabi_torchrl.rl.trainer import train

    n, steps = 4, 8
    frames = n * steps
    cfg = preset_config("torque_ideal", device="cpu", **{"env.num_envs": n, "ppo.steps_per_env": steps,
                        "ppo.minibatch_size": 16, "ppo.epochs": 1, "ppo.desired_kl": 1e-12},
                        total_env_steps=6 * frames, **{"ppo.assist_fade_start": frames,
                                                       "ppo.assist_fade_end": 2 * frames,
                        "ppo.assist_anchor_decay": 3 * frames, "ppo.assist_lr_hold": hold,
                        "ppo.assist_lr_max": bound,
                        "ppo.actor_hidden": (16,), "ppo.critic_hidden": (16,)}, run_dir=str(tmp_path), name="t",
                        eval_at_end=False, progress_bar=False, checkpoint_every=1000, **{"ppo.cuda_graph": "off"})
    rows = read_metrics(train(cfg).run_dir)
    beta, weight = [float(r["torque_assist"]) for r in rows], [float(r["absorb_weight"]) for r in rows]
    lr = [float(r["lr"]) for r in rows]
    # β falls during iteration 1; the teacher's pull is 1 there, then decays over three iterations (gone at 4).
    assert beta[:3] == [1.0, 1.0, 0.0] and weight[:5] == pytest.approx([0, 1, 2 / 3, 1 / 3, 0])
    if hold == "fade":
        assert lr[2] != lr[1] and lr[3] != lr[2]  # the rule acts again as soon as β stops falling
    else:
        assert lr[1] == lr[2] == lr[3] and lr[4] != lr[3]  # held until the pull is gone, then the rule acts
    # Unbounded, the hold keeps what the rule reached in iteration 0 (1e-3 / 1.5); ppo.assist_lr_max caps it from
    # the hold's first update on, and the rule goes on from the cap once the hold ends.
    assert lr[0] == pytest.approx(1e-3 / 1.5)
    assert lr[1] == pytest.approx(bound or lr[0])
    if hold == "pull":  # one step of the rule (down, or up after an update that left the policy as it was)
        assert lr[4] / (bound or lr[0]) in (pytest.approx(1 / 1.5), pytest.approx(1.5))


def test_ppo_assist_lr_max_is_0_or_a_rate_between_the_floor_and_the_start():
    assert preset_config("robust").ppo.assist_lr_max == 7.5e-5  # run 9's held rate (docs/training/robust)
    assert preset_config("robust", **{"ppo.assist_lr_max": 0}).ppo.assist_lr_max == 0.0  # no bound
    assert preset_config("robust", **{"ppo.assist_lr_max": 1e-4}).ppo.assist_lr_max == 1e-4
    # Above ppo.lr (1e-3) is allowed: the rule may have raised the rate before the hold.
    assert preset_config("robust", **{"ppo.assist_lr_max": 2e-3}).ppo.assist_lr_max == 2e-3
    for bad in (1e-6, 2e-2, -1e-4, float("nan"), True):
        with pytest.raises(ValueError, match="ppo.assist_lr_max must be"):
            preset_config("robust", **{"ppo.assist_lr_max": bad})
    # A bound on a hold that never happens is refused: no adaptive rate, or no assist.
    with pytest.raises(ValueError, match="this run has no such hold"):
        preset_config("robust", **{"ppo.assist_lr_max": 1e-4, "ppo.lr_schedule": "linear"})
    with pytest.raises(ValueError, match="this run has no such hold"):
        preset_config("default", **{"ppo.assist_lr_max": 1e-4})
    # The robust preset's own bound stays valid under another schedule, as a preset's values do: only a bound the
    # caller sets is refused there.
    assert preset_config("robust", **{"ppo.lr_schedule": "linear"}).ppo.assist_lr_max == 7.5e-5


def test_a_resumed_run_keeps_its_teacher(tmp_path):
    from tocabi_torchrl.rl.trainer import train

    n, steps = 4, 8
    frames = n * steps
    kw = {"device": "cpu", "env.num_envs": n, "ppo.steps_per_env": steps, "ppo.minibatch_size": 16, "ppo.epochs": 1,
          "ppo.assist_fade_start": frames, "ppo.assist_fade_end": 5 * frames, "ppo.actor_hidden": (16,),
          "ppo.critic_hidden": (16,), "run_dir": str(tmp_path), "name": "r", "eval_at_end": False,
          "progress_bar": False, "checkpoint_every": 1, "checkpoint_keep_last": 0, "ppo.cuda_graph": "off"}
    first = train(preset_config("torque_ideal", total_env_steps=2 * frames, **kw))  # the teacher is taken in iteration 2
    folder = first.run_dir / "checkpoints"
    taken = torch.load(folder / "iter_000002.pt", weights_only=True)["agent"]["teacher"]
    assert taken["anchored"]
    train(preset_config("torque_ideal", total_env_steps=4 * frames, resume=str(folder / "latest.pt"), **kw))
    kept = torch.load(folder / "iter_000004.pt", weights_only=True)["agent"]
    for k, v in taken.items():
        torch.testing.assert_close(kept["teacher"][k], v, rtol=0, atol=0)  # not taken again from the moved actor


def test_teacher_target_is_the_action_applying_the_teacher_torque():
    # The teacher (another network) acted at β = 1; the actor is pulled to the action that applies the teacher's
    # torque at β', whatever the rollout's own action did.
    torch.manual_seed(0)
    limits = torch.full((12,), 100.0)
    actor, other = make_actor(6, 13, hidden=(8,)), make_actor(6, 13, hidden=(8,))
    teacher = AssistTeacher(gaussian_head(actor).mean_net, limits)
    assert not teacher.anchored
    teacher.anchor(gaussian_head(other).mean_net, 3.0 * limits, 1.0)
    assert teacher.anchored and float(teacher.beta) == 1.0
    obs = torch.randn(64, 6)
    leg_assist = 0.3 * torch.randn(64, 12)
    with torch.no_grad():
        teacher_loc = gaussian_head(other).mean_net(obs)[:, :12]
        own_loc = gaussian_head(actor).mean_net(obs)[:, :12]
    expected = (3.0 * limits * teacher_loc.clamp(-1, 1) + limits * leg_assist).clamp(-100.0, 100.0)
    torch.testing.assert_close(teacher.torque(obs, leg_assist, limits), expected)
    loss = AssistAbsorbLoss(_NoPPO(), gaussian_head(actor), limits, teacher=teacher)
    loss.set_step(2.0 * limits, 1.5 * limits, 0.5, 0.4, 1.0)
    target = loss.target(own_loc, leg_assist, teacher.torque(obs, leg_assist, limits))
    applied = (1.5 * limits * target.clamp(-1, 1) + 0.4 * limits * leg_assist).clamp(-100.0, 100.0)
    inside = target.abs() < 1.0
    assert inside.float().mean() > 0.5
    torch.testing.assert_close(applied[inside], expected[inside], rtol=1e-5, atol=1e-3)
    # The copy is frozen: the teacher's weights do not follow the network it was taken from.
    with torch.no_grad():
        for p in gaussian_head(other).mean_net.parameters():
            p.add_(1.0)
    torch.testing.assert_close(teacher.torque(obs, leg_assist, limits), expected)
    assert not any(p.requires_grad for p in teacher.parameters())


class _MeanSquarePPO(torch.nn.Module):
    """A stand-in PPO loss of the actor's own mean (so its gradients are what a step applies), with the statistics a
    mini-batch step reads (zeros)."""

    in_keys = ("observation",)

    def __init__(self, head):
        super().__init__()
        self.mean_net = head.mean_net

    def forward(self, td):
        loc = self.mean_net(td["observation"])
        zero = loc.new_zeros(())
        return TensorDict({"loss_objective": loc.square().mean(), "loss_critic": zero, "kl_approx": zero,
                           "clip_fraction": zero}, batch_size=[])


def test_at_weight_zero_the_absorb_term_is_skipped_and_the_update_is_unchanged():
    """Before the fade the term's weight is 0: the loss skips the actor's second forward and the teacher's, and an
    optimiser step gives bit for bit the parameters the computed-and-zeroed term gives. The step captures again when
    the term switches (graph_key)."""
    limits = torch.full((12,), 2.0)
    obs, assist = torch.randn(64, 6, generator=torch.Generator().manual_seed(0)), 0.3 * torch.ones(64, 12)

    def one_step(skip: bool) -> tuple[torch.Tensor, int, int]:
        torch.manual_seed(0)
        actor = make_actor(6, 13, hidden=(16,), init_std=0.1)
        head, teacher = gaussian_head(actor), AssistTeacher(gaussian_head(make_actor(6, 13, hidden=(8,))).mean_net,
                                                            limits)
        calls = {"head": 0, "teacher": 0}
        head.register_forward_hook(lambda *_: calls.__setitem__("head", calls["head"] + 1))
        torque = teacher.torque

        def counted_torque(*args):
            calls["teacher"] += 1
            return torque(*args)

        teacher.torque = counted_torque

        loss = AssistAbsorbLoss(_MeanSquarePPO(head), head, limits, teacher=teacher)
        loss.set_step(limits, 0.5 * limits, 1.0, 0.9, weight=0.0)
        assert loss.graph_key is False
        if not skip:
            loss._active = True  # the term computed at weight 0, as before it was skipped
        with torch.no_grad():
            loc, scale = head(obs)
        calls["head"] = 0
        td = TensorDict({"observation": obs, "loc": loc, "scale": scale, "next": {"leg_assist": assist}},
                        batch_size=[64])
        opt = torch.optim.Adam(actor.parameters(), lr=1e-2)
        out = loss(td)
        assert out["loss_absorb"].item() == 0.0
        (out["loss_objective"] + out["loss_absorb"]).backward()
        opt.step()
        return torch.cat([p.detach().flatten() for p in actor.parameters()]), calls["head"], calls["teacher"]

    skipped, computed = one_step(skip=True), one_step(skip=False)
    assert skipped[1:] == (0, 0) and computed[1:] == (1, 1)
    torch.testing.assert_close(skipped[0], computed[0], rtol=0, atol=0)


def test_an_infinite_rollout_mean_leaves_the_absorb_gradients_finite():
    """A frame whose rollout mean is infinite (a broken world; the rollout guard checks the action, not ``loc``)
    pulls towards a finite target: its squared distance would otherwise overflow and 0 × inf reach the gradients."""
    torch.manual_seed(0)
    head = gaussian_head(make_actor(6, 13, hidden=(8,), init_std=0.1))
    limits = torch.full((12,), 2.0)
    loss = AssistAbsorbLoss(_NoPPO(), head, limits)
    obs = torch.randn(16, 6)
    with torch.no_grad():
        loc, scale = head(obs)
    loc[3, :] = float("inf")
    loc[5, :] = -float("inf")
    td = TensorDict({"observation": obs, "loc": loc, "scale": scale, "next": {"leg_assist": torch.zeros(16, 12)}},
                    batch_size=[16])
    loss.set_step(limits, 0.5 * limits, 1.0, 0.9, weight=1.0)
    out = loss(td)
    out["loss_absorb"].backward()
    assert torch.isfinite(out["loss_absorb"])
    assert all(torch.isfinite(p.grad).all() for p in head.parameters() if p.grad is not None)


def test_the_update_step_captures_again_when_the_absorb_term_switches():
    from graph_emulation import EmulatedCapture

    from tocabi_torchrl.rl.update_step import MinibatchStep

    torch.manual_seed(0)
    actor = make_actor(6, 13, hidden=(8,))
    head = gaussian_head(actor)

    limits = torch.full((12,), 2.0)
    loss = AssistAbsorbLoss(_MeanSquarePPO(head), head, limits)
    opt = torch.optim.Adam(actor.parameters(), lr=1e-3)
    step = MinibatchStep(loss, opt, list(actor.parameters()), 1.0, use_graph=True, warmup=1,
                         capturer=EmulatedCapture())
    obs = torch.randn(32, 6)
    with torch.no_grad():
        loc, scale = head(obs)
    mb = TensorDict({"observation": obs, "loc": loc, "scale": scale, "next": {"leg_assist": torch.zeros(32, 12)}},
                    batch_size=[32])
    loss.set_step(limits, limits, 1.0, 1.0, weight=0.0)
    for _ in range(3):  # one warm-up step, the capture, a replay
        step(mb)
    assert step.captured and step._capture.capturer.captures == ["joined"]
    loss.set_step(limits, 0.5 * limits, 1.0, 0.9, weight=1.0)  # the fade begins: the term is computed from now on
    step(mb)
    assert not step.captured  # warming up again
    step(mb)
    assert step.captured and step._capture.capturer.captures == ["joined", "joined"]
    assert "loss_absorb" in step.stat_keys
    loss.set_step(limits, 0.5 * limits, 0.9, 0.8, weight=0.5)  # the pull decays: the same operations, no capture
    step(mb)
    assert step.captured and len(step._capture.capturer.captures) == 2
    loss.set_step(limits, limits, 0.0, 0.0, weight=0.0)  # the pull has gone: skipped again, captured again
    step(mb)
    assert not step.captured
    step(mb)
    assert step.captured and len(step._capture.capturer.captures) == 3


def test_teacher_weight_holds_through_the_fade_then_decays():
    s = AssistSchedule(1.0, fade_start=100, fade_end=300, anchor_decay=100)
    assert [s.teacher_weight(x) for x in (0, 100, 101, 300, 350, 400, 10**9)] == [0.0, 0.0, 1.0, 1.0, 0.5, 0.0, 0.0]
    assert AssistSchedule(1.0, fade_start=0, fade_end=1).teacher_weight(2) == 0.0
    with pytest.raises(ValueError, match="anchor_decay"):
        AssistSchedule(1.0, fade_start=0, fade_end=1, anchor_decay=-1)
    with pytest.raises(ValueError, match="assist_target"):
        preset_config("torque_ideal", **{"ppo.assist_target": "teachr"})
    with pytest.raises(ValueError, match="assist_anchor_decay"):
        preset_config("torque_ideal", **{"ppo.assist_anchor_decay": -5})


def test_wall_clock_checkpoints_carry_the_training_time(tmp_path, monkeypatch):
    from tocabi_torchrl.rl import trainer

    clock = iter(range(0, 10**6, 50))  # every perf_counter() call advances 50 s
    monkeypatch.setattr(trainer.time, "perf_counter", lambda: float(next(clock)))
    cfg = preset_config("cpu_smoke", device="cpu", run_dir=str(tmp_path), name="w", progress_bar=False,
                        checkpoint_minutes=2.0, checkpoint_every=100, total_env_steps=8 * 16 * 4)
    result = trainer.train(cfg)
    folder = result.run_dir / "checkpoints"
    walls = sorted(p.name for p in folder.glob("wall_*.pt"))
    assert walls and all(name.endswith("s.pt") for name in walls)
    states = [torch.load(folder / name, weights_only=True) for name in walls]
    marks = [int(name[5:10]) for name in walls]
    assert all(s["train_seconds"] >= m for s, m in zip(states, marks))
    assert marks == sorted(set(marks)) and all(m % 120 == 0 for m in marks)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.filterwarnings("error:SyncFreeResetEnv")  # a failed capture or an eager fallback fails the test
def test_gpu_captured_assisted_step_follows_beta_and_never_syncs():
    def set_beta(i, eager, graphed):
        beta = 1.0 - i / 11  # changed between replays: the graph must read it from the device
        eager.base_env.set_torque_assist(beta)
        graphed.base_env.set_torque_assist(beta)

    assert_captured_equals_eager(dict(num_envs=64, device="cuda", seed=3, control_mode="torque", torque_assist=True,
                                      pd_kp=tuple(robot.LEG_KP), pd_kv=tuple(robot.LEG_KV)),
                                 ("leg_torque", "leg_assist", "observation", "reward"), before_step=set_beta)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_gpu_torque_preset_trains_with_the_captured_absorbing_update(tmp_path):
    from tocabi_torchrl.rl.trainer import train

    n, steps = 512, 16
    frames = n * steps
    cfg = preset_config("torque_ideal", device="cuda", **{"env.num_envs": n, "ppo.steps_per_env": steps,
                        "ppo.minibatch_size": frames // 4},
                        total_env_steps=5 * frames, **{"ppo.assist_fade_start": frames,
                                                       "ppo.assist_fade_end": 4 * frames,
                        "ppo.assist_anchor_decay": frames},
                        run_dir=str(tmp_path), name="g", eval_at_end=False, progress_bar=False)
    with _no_capture_warning():  # the absorbing loss must be captured with the update, not fall back to eager
        result = train(cfg)
    rows = read_metrics(result.run_dir)
    betas = [float(r["torque_assist"]) for r in rows]
    r = math.exp(sum(math.log(0.5 * kp / lim) for kp, lim in zip(robot.LEG_KP, robot.LEG_TORQUE_LIMITS)) / 12)
    geometric = [(r ** (1 - u) - 1) / (r - 1) for u in (0, 0, 1 / 3, 2 / 3, 1)]  # β each rollout ran with
    assert betas == pytest.approx(geometric, rel=1e-5)
    absorb = [float(r["loss_absorb"]) for r in rows]
    assert absorb[0] == 0.0 and all(a > 0 for a in absorb[1:4]) and absorb[4] == 0.0
    assert all(torch.isfinite(torch.tensor([float(r["loss_policy"]), float(r["loss_value"])])).all() for r in rows)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_gpu_captured_update_matches_eager_across_the_absorb_switches():
    """The captured step replays what the eager step computes while the absorb term switches on (a new capture), its
    weight changes (the same graph) and it switches off again (another capture)."""
    from tocabi_torchrl.rl.update_step import MinibatchStep, make_capturable_adam

    def build(use_graph: bool):
        torch.manual_seed(0)
        actor = make_actor(6, 13, hidden=(32,), init_std=0.1).cuda()
        head = gaussian_head(actor)

        loss = AssistAbsorbLoss(_MeanSquarePPO(head), head, torch.full((12,), 2.0, device="cuda"))
        params = list(actor.parameters())
        opt = make_capturable_adam([{"params": params, "lr": 1e-3}], eps=1e-8, device=torch.device("cuda"))
        return actor, loss, MinibatchStep(loss, opt, params, 1.0, use_graph=use_graph)

    g = torch.Generator().manual_seed(1)
    obs = torch.randn(256, 6, generator=g).cuda()
    runs = []
    for use_graph in (False, True):
        actor, loss, step = build(use_graph)
        with torch.no_grad():
            loc, scale = gaussian_head(actor)(obs)
        mb = TensorDict({"observation": obs, "loc": loc, "scale": scale,
                         "next": {"leg_assist": 0.3 * torch.ones(256, 12, device="cuda")}}, batch_size=[256])
        limits = loss.limits
        absorbs = []
        for weight in [0.0] * 5 + [1.0] * 5 + [0.5] * 3 + [0.0] * 5:
            loss.set_step(limits, 0.5 * limits, 1.0, 0.9, weight=weight)
            stats = step(mb)
            absorbs.append(float(stats[list(step.stat_keys).index("loss_absorb")]))
        runs.append((torch.cat([p.detach().flatten() for p in actor.parameters()]), absorbs, step))
    (eager_params, eager_absorb, _), (graph_params, graph_absorb, graphed) = runs
    assert graphed.captured
    assert graph_absorb == pytest.approx(eager_absorb, rel=1e-4, abs=1e-6) and max(graph_absorb) > 0
    torch.testing.assert_close(graph_params, eager_params, rtol=1e-4, atol=1e-5)


def _no_capture_warning():
    import contextlib
    import warnings

    @contextlib.contextmanager
    def ctx():
        with warnings.catch_warnings():
            warnings.filterwarnings("error", message="MinibatchStep: capturing")
            yield

    return ctx()


def test_schedules_past_the_budget_are_named_with_their_values_and_the_budget():
    from tocabi_torchrl.config import schedule_past_budget

    for name in ("default", "torque", "robust", "reference", "model_based", "model_based_ideal", "pd", "cpu_smoke"):
        assert schedule_past_budget(preset_config(name)) == [], name  # every preset's schedules fit its budget
    # The robust preset's fade ends at 120 M and its kicks reach full strength at 35 M env steps.
    found = schedule_past_budget(preset_config("robust", total_env_steps=20_000_000))
    assert len(found) == 3
    assert found[0].startswith("ppo.assist_fade_start 60,000,000") and "the assist never fades" in found[0]
    assert found[1].startswith("ppo.assist_fade_end 120,000,000") and "total_env_steps 20,000,000" in found[1]
    assert found[2].startswith("ppo.push_ramp[1] 35,000,000") and "40 % of their strength" in found[2]
    [fade_end] = schedule_past_budget(preset_config("robust", total_env_steps=100_000_000))
    assert "67 % through the fade" in fade_end
    # Without an assist or kicks their schedules act not at all, and nothing is said about them.
    assert schedule_past_budget(preset_config("torque_ideal", total_env_steps=1_000, **{"ppo.torque_assist": 0.0})) == []
    assert schedule_past_budget(preset_config("robust", total_env_steps=100_000_000, **{
        "env.pushes.count": 0, "transforms.kick_relax.seconds": 0.0})) == [fade_end]


def test_a_run_whose_schedules_end_past_its_budget_warns_once_at_its_start(tmp_path, monkeypatch):
    from tocabi_torchrl.rl import trainer

    class Built(Exception):
        """Raised where the env is built: the run got as far as its start, and trains nothing."""

    def stop(*args, **kwargs):
        raise Built

    monkeypatch.setattr(trainer, "build_env", stop)
    kw = {"device": "cpu", "run_dir": str(tmp_path), "eval_at_end": False, "progress_bar": False}
    cfg = preset_config("torque_ideal", total_env_steps=80_000_000, name="past", **kw)
    with pytest.warns(UserWarning, match="schedules end past its budget") as caught, pytest.raises(Built):
        trainer.train(cfg)
    [warning] = [w for w in caught if "past its budget" in str(w.message)]
    message = str(warning.message)
    assert "ppo.assist_fade_end 110,000,000" in message and "total_env_steps 80,000,000" in message
    assert "raise total_env_steps" in message
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a run within its budget starts without the warning
        with pytest.raises(Built):
            trainer.train(preset_config("torque_ideal", total_env_steps=200_000_000, name="within", **kw))
