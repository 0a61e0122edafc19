"""Pushes (kicks: a force on the pelvis, or a velocity kick of the whole robot) and diverse starts: the schedule, the
impulse, the effect on the robot."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from tocabi_torchrl.envs import TocabiWalk, TocabiWalkConfig
from tocabi_torchrl.envs.pushes import PushConfig, Pushes


def test_kicks_fall_in_their_share_of_the_window_and_carry_the_exact_impulse():
    cfg = PushConfig(count=3, window=(2.0, 7.0), speed=(0.5, 1.0), duration=(0.004, 0.1))
    pushes = Pushes(cfg, num_envs=512, device=torch.device("cpu"), dt=0.004, mass=100.0)
    u = torch.rand(512, pushes.draws, generator=torch.Generator().manual_seed(0))
    pushes.reset(torch.ones(512, dtype=torch.bool), u)
    t = pushes.start_step * 0.004
    for j, (lo, hi) in enumerate(((2.0, 3 + 2 / 3), (3 + 2 / 3, 5 + 1 / 3), (5 + 1 / 3, 7.0))):
        assert float(t[:, j].min()) >= lo - 0.004 and float(t[:, j].max()) <= hi + 0.004
    # Summed over the episode's steps, each world's force gives each kick's impulse, speed x mass.
    total = torch.zeros(512, 2)
    for step in range(int(7.5 / 0.004)):
        total += pushes.at(torch.full((512,), step)) * 0.004
    per_kick = pushes.force * (pushes.steps * 0.004).unsqueeze(-1)
    torch.testing.assert_close(total, per_kick.sum(dim=1), rtol=1e-4, atol=1e-3)
    speed = per_kick.norm(dim=-1) / 100.0
    assert 0.5 - 1e-5 <= float(speed.min()) and float(speed.max()) <= 1.0 + 1e-5
    angle = torch.atan2(pushes.force[..., 1], pushes.force[..., 0])
    assert float(angle.std()) > 1.5  # directions spread over the circle


def test_a_reset_redraws_only_the_flagged_worlds_and_the_scale_multiplies():
    pushes = Pushes(PushConfig(count=2), num_envs=4, device=torch.device("cpu"), dt=0.004, mass=100.0)
    gen = torch.Generator().manual_seed(1)
    pushes.reset(torch.ones(4, dtype=torch.bool), torch.rand(4, pushes.draws, generator=gen))
    before = pushes.force.clone(), pushes.start_step.clone()
    mask = torch.tensor([False, True, False, False])
    pushes.reset(mask, torch.rand(4, pushes.draws, generator=gen))
    assert torch.equal(pushes.force[~mask], before[0][~mask]) and torch.equal(pushes.start_step[~mask],
                                                                              before[1][~mask])
    assert not torch.equal(pushes.force[1], before[0][1])
    step = pushes.start_step[:, 0]
    full = pushes.at(step)
    pushes.scale.fill_(0.25)
    torch.testing.assert_close(pushes.at(step), 0.25 * full)


def test_latest_kick_reports_its_age_and_scaled_speed_per_world():
    pushes = Pushes(PushConfig(count=3, window=(0.0, 0.3), speed=(0.4, 1.4)), num_envs=64,
                    device=torch.device("cpu"), dt=0.004, mass=100.0)
    pushes.reset(torch.ones(64, dtype=torch.bool), torch.rand(64, pushes.draws,
                                                               generator=torch.Generator().manual_seed(2)))
    pushes.world_scale[::2] = 0.5
    pushes.scale.fill_(0.8)
    for done in range(0, 90, 7):  # policy steps done; the kick of start step k acts in the step taken at k
        age, speed = (v.squeeze(-1) for v in pushes.latest(torch.full((64,), done)))
        for w in range(64):
            begun = [j for j in range(3) if int(pushes.start_step[w, j]) < done]
            if not begun:
                assert float(age[w]) == pytest.approx(done * 0.004) and float(speed[w]) == 0.0
                continue
            j = begun[-1]
            assert float(age[w]) == pytest.approx((done - int(pushes.start_step[w, j])) * 0.004)
            want = float(pushes.speed[w, j]) * 0.8 * (0.5 if w % 2 == 0 else 1.0)
            assert float(speed[w]) == pytest.approx(want, rel=1e-6)
    assert 0.4 <= float(pushes.speed.min()) and float(pushes.speed.max()) <= 1.4


def test_a_calm_fraction_leaves_that_share_of_episodes_without_kicks():
    cfg = PushConfig(count=3, window=(2.0, 7.0), speed=(0.5, 1.0))
    n, gen = 4000, torch.Generator().manual_seed(3)
    u, calm = torch.rand(n, 12, generator=gen), torch.rand(n, 1, generator=gen)
    kicked, mixed = (Pushes(c, n, torch.device("cpu"), 0.004, 100.0) for c in (cfg, dataclasses.replace(
        cfg, calm_fraction=0.3)))
    assert (kicked.calm_draws, mixed.calm_draws) == (0, 1)
    everyone = torch.ones(n, dtype=torch.bool)
    kicked.reset(everyone, u)
    mixed.reset(everyone, u, calm)
    still = (calm < 0.3).squeeze(-1)
    assert float(still.float().mean()) == pytest.approx(0.3, abs=0.025)
    # A calm episode has no kick at any step and reports none; every other episode's kicks are as drawn without it.
    assert float(mixed.speed[still].abs().max()) == 0.0
    assert float(sum(mixed.at(torch.full((n,), s)).abs() for s in range(1800))[still].max()) == 0.0
    assert torch.equal(mixed.force[~still], kicked.force[~still]) and torch.equal(mixed.speed[~still],
                                                                                  kicked.speed[~still])
    # ... and reads like an episode before its first kick: its age is the episode's time.
    age, speed = (v.squeeze(-1) for v in mixed.latest(torch.full((n,), 1800)))
    assert float(speed[still].abs().max()) == 0.0 and torch.allclose(age[still], torch.full_like(age[still], 7.2))
    assert float(age[~still].max()) < 7.2 - 5.0  # every kicked episode has begun its last kick by 7 s
    with pytest.raises(ValueError, match=r"needs `calm`, a \(4000, 1\) float tensor of uniforms, got None"):
        mixed.reset(everyone, u)


def test_an_env_draws_each_episodes_calm_from_its_own_stream():
    # The calm draw is a stream of its own: the kicks of the kicked worlds stay those of the same seed without it.
    cfg = PushConfig(count=2, window=(1.0, 3.0), speed=(0.5, 1.0), kind="velocity")
    base, mixed = (_env(c, n=32) for c in (cfg, dataclasses.replace(cfg, calm_fraction=0.5)))
    base.reset()
    mixed.reset()
    still = (mixed.pushes.speed == 0).all(dim=1)
    assert 4 <= int(still.sum()) <= 28  # worlds differ: some calm, some kicked (binomial(32, 0.5))
    assert torch.equal(mixed.pushes.speed[~still], base.pushes.speed[~still])
    assert torch.equal(mixed.pushes.start_step[~still], base.pushes.start_step[~still])
    assert int(mixed.pushes.start_step[still].min()) > 10 ** 9  # a calm episode's kicks never begin


def test_an_env_with_kicks_reports_the_latest_one():
    env = TocabiWalk(num_envs=2, device="cpu", seed=0, sim_threads=1, config=dataclasses.replace(
        TocabiWalkConfig(), pushes=PushConfig(count=1, window=(0.02, 0.02), speed=(0.7, 0.7), kind="velocity")))
    from tensordict import TensorDict

    td = env.reset()
    assert float(td["kick_speed"].abs().max()) == 0.0 and td["kick_age"].shape == (2, 1)
    action = TensorDict({"action": torch.zeros(2, 13)}, batch_size=[2])
    for _ in range(8):
        td = env.step(action)["next"]
    # The kick acted in the step taken at episode step 5 (0.02 s): three steps later it is 3 steps old.
    torch.testing.assert_close(td["kick_age"], torch.full((2, 1), 0.012))
    torch.testing.assert_close(td["kick_speed"], torch.full((2, 1), 0.7))
    assert "kick_age" not in TocabiWalk(num_envs=1, device="cpu", sim_threads=1).reset().keys()


@pytest.mark.parametrize("bad", [dict(count=-1), dict(count=True), dict(speed=(1.0, 0.5)),
                                 dict(window=(0.0, float("inf"))), dict(kind="impulse"), dict(calm_fraction=1.0),
                                 dict(calm_fraction=-0.1), dict(calm_fraction=float("nan"))])
def test_bad_push_settings_are_refused_by_name(bad):
    with pytest.raises(ValueError, match="env.pushes"):
        PushConfig(**bad).validate()


@pytest.mark.parametrize("bad, message", [
    (dict(speed=1.0), r"env.pushes.speed must be \(low, high\).*\[m/s\], got 1.0; for one value give it twice, "
                      r"e.g. \(1.0, 1.0\)"),
    (dict(window=(1.0, 2.0, 3.0)), r"env.pushes.window must be \(low, high\).*\[s\], got \(1.0, 2.0, 3.0\)"),
    (dict(duration=("0.004", "0.004")), r"env.pushes.duration must be \(low, high\).*got \('0.004', '0.004'\)"),
    (dict(window=(True, 5.0)), r"env.pushes.window must be \(low, high\).*got \(True, 5.0\)"),
    (dict(speed=(1.4, 0.4)), r"env.pushes.speed must be .*got \(1.4, 0.4\); swapped\? give \(0.4, 1.4\)"),
])
def test_a_push_range_that_is_no_ordered_pair_is_refused_by_name(bad, message):
    # A lone number, three numbers or text failed as a raw unpack or comparison error that named no field, and a
    # bool passed as 0 or 1. The torch-free runtime's PushSettings has the same rule.
    from tocabi_torchrl.runtime.randomization import PushSchedule, PushSettings

    with pytest.raises(ValueError, match=message):
        PushConfig(count=2, **bad).validate()
    with pytest.raises(ValueError, match=message.replace("env.pushes", "pushes")):
        PushSchedule(PushSettings(count=2, **bad), dt=0.004, mass=100.0)


def test_a_kick_past_the_sanity_bound_is_refused_alike_by_the_env_the_runtime_and_a_contract():
    # speed=(0.4, 140), a typo for 1.4, ran and launched the robot. One rule (value_rules.PUSH_SPEED) for the
    # training config, the torch-free runtime's settings and a contract's trained_under.pushes.speed_mps.
    from tocabi_torchrl.runtime import randomization as rnd
    from tocabi_torchrl.value_rules import trained_under_problems

    def stated(speed):
        section = rnd.trained_under_section(rnd.Randomization(), rnd.PushSettings(count=2), rnd.StartVelocity(),
                                            0.0005, 104.5)
        return trained_under_problems({**section, "pushes": {**section["pushes"], "speed_mps": list(speed)}})

    PushConfig(count=2, speed=(0.4, 10.0)).validate()
    rnd.PushSettings(count=2, speed=(0.4, 10.0)).validate()
    assert stated((0.4, 10.0)) == []
    why = r"above the bound 10 m/s; a kick above 10 m/s launches the 104.5 kg robot .*a typo\?"
    with pytest.raises(ValueError, match=rf"env.pushes.speed is \(0.4, 140\), {why}"):
        PushConfig(count=2, speed=(0.4, 140)).validate()
    with pytest.raises(ValueError, match=rf"^pushes.speed is \(0.4, 140\), {why}"):
        rnd.PushSchedule(rnd.PushSettings(count=2, speed=(0.4, 140)), dt=0.004, mass=104.5)
    (problem,) = stated((0.4, 140))
    assert problem.startswith("trained_under.pushes.speed_mps is [0.4, 140] but each end must be a finite number in "
                              "[0, 10]; a kick above 10 m/s") and problem.endswith("a typo?")


def _env(pushes: PushConfig, n=2, **task):
    cfg = TocabiWalkConfig()
    cfg = dataclasses.replace(cfg, pushes=pushes, task=dataclasses.replace(cfg.task, **task))
    return TocabiWalk(num_envs=n, device="cpu", seed=0, config=cfg, sim_threads=1)


def test_a_push_window_past_the_episode_end_is_refused():
    # 250 steps of 4 ms = 1 s: a window to 2 s would leave its second kick's share past every episode's end.
    with pytest.raises(ValueError, match=r"env.pushes.window ends at 2 s, after the episode's 1 s"):
        _env(PushConfig(count=2, window=(0.5, 2.0)), max_episode_steps=250)
    assert _env(PushConfig(count=2, window=(0.5, 1.0)), max_episode_steps=250).pushes is not None


def test_a_kick_changes_the_robots_velocity_by_about_its_speed():
    # One kick of 0.5 m/s in the first share of a 0.2-0.204 s window (policy step 50), the residual-PD robot holding
    # the reference pose (zero action). Compared with the same env without kicks.
    kicked, calm = _env(PushConfig(count=1, window=(0.2, 0.204), speed=(0.5, 0.5))), _env(PushConfig())
    kicked.reset(), calm.reset()
    step = int(kicked.pushes.start_step[0, 0])
    direction = kicked.pushes.force[:, 0] / kicked.pushes.force[:, 0].norm(dim=-1, keepdim=True)
    action = torch.zeros(2, 13)
    from tensordict import TensorDict

    for _ in range(step + 3):
        kicked.step(TensorDict({"action": action}, batch_size=[2]))
        calm.step(TensorDict({"action": action}, batch_size=[2]))
    dv = (kicked.sim.qvel[:, :2] - calm.sim.qvel[:, :2])
    along = (dv * direction).sum(dim=-1)
    assert float(along.min()) > 0.3 and float(along.max()) < 1.0, along
    kicked.set_push_scale(0.0)
    with pytest.raises(ValueError, match="push scale"):
        kicked.set_push_scale(2.0)
    with pytest.raises(RuntimeError, match="pushes"):
        calm.set_push_scale(0.5)


def _kick_response(kind: str, **env_overrides):
    """(pelvis velocity change along the kick [m/s], joint velocity change [rad/s] RMS) of each of 4 worlds one
    policy step after a 1.0 m/s kick of ``kind``, against the same env without kicks."""
    from tensordict import TensorDict

    def env(pushes):
        cfg = dataclasses.replace(TocabiWalkConfig(), pushes=pushes, **env_overrides)
        return TocabiWalk(num_envs=4, device="cpu", seed=0, config=cfg, sim_threads=1)

    kicked = env(PushConfig(count=1, window=(0.2, 0.2), speed=(1.0, 1.0), kind=kind))  # every world at step 50
    calm = env(PushConfig())
    kicked.reset(), calm.reset()
    step = int(kicked.pushes.start_step[0, 0])
    direction = kicked.pushes.force[:, 0] / kicked.pushes.force[:, 0].norm(dim=-1, keepdim=True)
    action = TensorDict({"action": torch.zeros(4, 13)}, batch_size=[4])
    for _ in range(step + 1):  # through the kick's one step
        kicked.step(action), calm.step(action)
    dv = ((kicked.sim.qvel[:, :2] - calm.sim.qvel[:, :2]) * direction).sum(dim=-1)
    dq = (kicked.sim.qvel[:, 6:] - calm.sim.qvel[:, 6:]).pow(2).mean(dim=-1).sqrt()
    return dv, dq


def test_a_velocity_kick_moves_the_whole_robot_and_a_force_kick_jerks_the_pelvis():
    # The same momentum either way; the velocity kick gives every body the kick's speed (no joint is kicked), the
    # force on the pelvis alone sends the pelvis ahead of its limbs and upper body, which lag on their joints.
    dv_vel, dq_vel = _kick_response("velocity")
    dv_force, dq_force = _kick_response("force")
    # A little less than 1.0 m/s where a stance foot's friction holds the robot back during the kick's 4 ms.
    assert 0.85 < float(dv_vel.min()) and float(dv_vel.max()) <= 1.01, dv_vel
    assert float(dv_force.min()) > 1.5, dv_force
    # The joints still move a little under a velocity kick (the stance foot's friction holds the leg back), a quarter
    # of what the force on the pelvis gives them or less (measured: 0.17-0.33 against 1.22-1.29 rad/s RMS).
    assert float(dq_vel.max()) < 0.35 * float(dq_force.min()), (dq_vel, dq_force)


def test_a_velocity_kick_of_one_world_leaves_the_others_exactly_as_they_were():
    # Worlds 0 and 2 kicked, 1 and 3 not (world_scale 0): the unkicked worlds follow the unkicked env bit for bit.
    from tensordict import TensorDict

    def env(pushes):
        return TocabiWalk(num_envs=4, device="cpu", seed=0, config=dataclasses.replace(TocabiWalkConfig(),
                          pushes=pushes), sim_threads=1)

    kicked = env(PushConfig(count=1, window=(0.02, 0.02), speed=(1.0, 1.0), kind="velocity"))
    calm = env(PushConfig())
    kicked.pushes.world_scale.copy_(torch.tensor([1.0, 0.0, 1.0, 0.0]))
    kicked.reset(), calm.reset()
    action = TensorDict({"action": torch.zeros(4, 13)}, batch_size=[4])
    for _ in range(10):
        kicked.step(action), calm.step(action)
    assert torch.equal(kicked.sim.qvel[1::2], calm.sim.qvel[1::2])
    assert torch.equal(kicked.sim.qpos[1::2], calm.sim.qpos[1::2])
    assert float((kicked.sim.qvel[0::2, :2] - calm.sim.qvel[0::2, :2]).norm(dim=-1).min()) > 0.5


def test_a_velocity_kick_uses_each_worlds_drawn_masses():
    # Lighter and heavier worlds alike: each body's force is its own drawn mass × the acceleration.
    from tocabi_torchrl.sim.dynamics_config import DynamicsRandomization

    dv, dq = _kick_response("velocity", dynamics=DynamicsRandomization(mass_scale=(0.8, 1.2)))
    assert 0.85 < float(dv.min()) and float(dv.max()) <= 1.01, dv
    assert float(dq.max()) < 0.5, dq


def test_diverse_starts_draw_each_worlds_start_velocity():
    env = _env(PushConfig(), n=64, start_joint_vel_std=0.5, start_base_vel_std=0.1)
    env.reset()
    # The reset's forward pass keeps the drawn velocities (qvel is the state, not a result of the pass).
    qvel = env.sim.qvel
    assert 0.35 < float(qvel[:, 6:].std()) < 0.65 and 0.06 < float(qvel[:, :3].std()) < 0.14
    assert float(qvel[:, 3:6].abs().max()) == 0.0
    first = qvel.clone()
    env.reset()  # the next episode draws anew
    assert not torch.equal(env.sim.qvel, first)
    at_rest = _env(PushConfig(), n=2)
    at_rest.reset()
    assert float(at_rest.sim.qvel.abs().max()) == 0.0


def test_training_ramps_the_pushes_by_env_steps(tmp_path):
    from tocabi_torchrl.rl import preset_config
    from tocabi_torchrl.rl.metrics_files import read_metrics
    from tocabi_torchrl.rl.trainer import build_env, push_scale, train

    assert [push_scale((10, 20), s) for s in (0, 10, 15, 20, 30)] == [0.0, 0.0, 0.5, 1.0, 1.0]
    cfg = preset_config("cpu_smoke", device="cpu", **{"env.num_envs": 4, "ppo.steps_per_env": 8,
                        "ppo.minibatch_size": 16},
                        total_env_steps=3 * 32, run_dir=str(tmp_path), name="pushed", progress_bar=False,
                        eval_at_end=False, log_every=1, **{"env.pushes.count": 2, "env.pushes.window": (0.0, 0.1),
                                                           "ppo.push_ramp": (0, 64)})
    env = build_env(cfg, torch.device("cpu"), for_training=True)
    train(cfg, env=env)
    rows = read_metrics(tmp_path / "pushed")
    # Each iteration's rollout ran with the scale of the env steps before it: 0, 32/64, then full.
    assert [float(r["push_scale"]) for r in rows] == [0.0, 0.5, 1.0]
    assert float(env.base_env.pushes.scale) == 1.0
    with pytest.raises(ValueError, match="push_ramp"):
        preset_config("cpu_smoke", **{"ppo.push_ramp": (10, 5)})


def test_training_env_relaxes_the_reward_after_its_kicks(tmp_path):
    from tocabi_torchrl.rl import preset_config
    from tocabi_torchrl import make_env
    from tocabi_torchrl.rl.trainer import build_env, train
    from tocabi_torchrl.transforms import KickRelax, TaskReward

    kicks = {"env.pushes.count": 2, "env.pushes.window": (0.0, 0.1), "env.pushes.speed": (1.0, 1.0),
             "env.pushes.kind": "velocity", "transforms.kick_relax.seconds": 1.0}
    cfg = preset_config("cpu_smoke", device="cpu", **{"env.num_envs": 4, "ppo.steps_per_env": 8,
                        "ppo.minibatch_size": 16}, total_env_steps=2 * 32, run_dir=str(tmp_path), name="relaxed",
                        progress_bar=False, eval_at_end=False, **kicks)
    env = build_env(cfg, torch.device("cpu"), for_training=True)
    reward = next(t for t in env.transform if isinstance(t, TaskReward))
    assert reward.kick_relax == cfg.transforms.kick_relax and float(reward._relaxed.sum()) == 6
    plain = build_env(preset_config("cpu_smoke", device="cpu", **{"env.num_envs": 4, **kicks,
                                    "transforms.kick_relax.seconds": 0.0}), torch.device("cpu"), for_training=True)
    def zeros(td):
        return td.set("action", torch.zeros(4, 13))

    # Same physics (the reward does not act on it): the relaxed terms shrink after the kicks (window 0-0.1 s, the
    # first 25 steps), the others do not change.
    relaxed_td, plain_td = env.rollout(60, zeros, break_when_any_done=False), plain.rollout(60, zeros,
                                                                                           break_when_any_done=False)
    assert reward.kick_relax is not None  # the env reports its kicks: relaxation on
    ratio = relaxed_td["next", "reward_terms", "qpos"] / plain_td["next", "reward_terms", "qpos"]
    assert float(ratio[:, 5:40].min()) < 0.2 and float(ratio.max()) <= 1.0 + 1e-6
    torch.testing.assert_close(relaxed_td["next", "reward_terms", "body_vel"],
                               plain_td["next", "reward_terms", "body_vel"])
    train(cfg, env=env)  # and a run trains with it
    # An env without kicks (a gait test builds the trained env without them) takes it and relaxes nothing; a run
    # config that asks for it without kicks would train as without it, and is refused.
    calm = make_env(2, "cpu", kick_relax=KickRelax(seconds=1.0))
    calm.reset()
    assert next(t for t in calm.transform if isinstance(t, TaskReward)).kick_relax is None  # no kicks: nothing
    with pytest.raises(ValueError, match="env.pushes.count is 0 .no kicks.: set env.pushes.count > 0, or "
                                         "transforms.kick_relax.seconds=0"):
        preset_config("cpu_smoke", device="cpu", **{"transforms.kick_relax.seconds": 1.0})



def test_kick_and_assist_options_set_without_kicks_or_assist_are_refused_but_a_presets_own_values_are_not():
    from tocabi_torchrl.config import PRESETS, preset_config

    # They were accepted and changed nothing, where kick_relax without kicks was refused.
    for options, match in (({"env.pushes.speed": (2.0, 3.0)}, r"env.pushes.count is 0 \(no kicks\), so the kicks' "
                                                               r"env.pushes.speed would change nothing"),
                           ({"ppo.push_ramp": (0, 1000)}, r"the kicks' ppo.push_ramp would change nothing"),
                           ({"ppo.assist_fade_start": 5, "ppo.assist_fade_end": 10},
                            r"ppo.torque_assist is 0 \(no assist\), so the assist's schedule ppo.assist_fade_start, "
                            r"ppo.assist_fade_end would change nothing: set ppo.torque_assist > 0")):
        with pytest.raises(ValueError, match=match):
            preset_config("cpu_smoke", **options)
    with pytest.raises(ValueError, match="the kicks' env.pushes.speed"):  # another value than the preset's too
        preset_config("robust", **{"env.pushes.count": 0, "env.pushes.speed": (2.0, 3.0)})
    for name in PRESETS:  # every preset as it is, and with its kicks or assist off, keeps its own values
        preset_config(name)
    preset_config("robust", **{"env.pushes.count": 0})
    preset_config("torque_ideal", **{"ppo.torque_assist": 0.0})
    preset_config("cpu_smoke", **{"env.pushes.count": 2, "env.pushes.speed": (2.0, 3.0), "ppo.push_ramp": (0, 64)})
