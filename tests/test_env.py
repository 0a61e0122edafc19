"""TocabiWalk on both physics backends: specs, rollouts with resets, phase clock, commands, terminations,
truncation, PD mode, backend selection, bad input."""

from __future__ import annotations

import dataclasses
import math
import re

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from tocabi_torchrl import robot
from tocabi_torchrl.envs import CommandConfig, TocabiWalk, TocabiWalkConfig, VelocityCommand
from tocabi_torchrl.envs.config import CPU_DEFAULT_BACKEND, resolve_backend
from tocabi_torchrl.envs.termination import termination_flags
from tocabi_torchrl.envs.tocabi_walk import quat_rotate_inverse
from tocabi_torchrl.sim import MujocoSim

N = 4


@pytest.fixture(scope="module", params=["warp", "mujoco"])
def backend(request) -> str:
    """Every env test runs on both physics backends: mujoco-warp's CPU device and C MuJoCo."""
    return request.param


@pytest.fixture(scope="module")
def env(backend):
    return TocabiWalk(num_envs=N, device="cpu", seed=0, backend=backend, control_mode="torque")


@pytest.fixture(scope="module")
def pd_env(backend):
    # The robot controller's full gains: a stiff PD, so the gravity load leaves only a small tracking error.
    return TocabiWalk(num_envs=2, device="cpu", seed=0, control_mode="pd", pd_kp=tuple(robot.LEG_KP),
                      pd_kv=tuple(robot.LEG_KV), backend=backend)


def _zero_action(e, phase_rate=0.0):
    a = torch.zeros(e.num_envs, 13)
    a[:, 12] = phase_rate
    return TensorDict({"action": a}, batch_size=[e.num_envs])


def test_specs_torque(env):
    check_env_specs(env, seed=0)


def test_specs_pd(pd_env):
    check_env_specs(pd_env, seed=0)


def test_initial_state(env):
    td = env.reset()
    init = torch.as_tensor(robot.INIT_JOINT_POS, dtype=torch.float32)
    torch.testing.assert_close(td["joint_pos"], init.expand(N, -1))
    torch.testing.assert_close(td["base_pos"][:, 2], torch.full((N,), 0.92983))
    assert torch.all(td["joint_vel"] == 0) and torch.all(td["applied_action"] == 0)
    assert torch.all(td["episode_step"] == 0) and not td["done"].any()
    assert set(env.init_row.tolist()) <= set(env.motion.init_rows.tolist())
    vx, vy = td["command"].unbind(-1)
    assert torch.all((vx >= 0.2) & (vx <= 0.7)) and torch.all(vy.abs() <= 0.2)
    # The feet start just above the ground: no contact, (almost) no load on the F/T sensors.
    assert not td["foot_contact"].any()
    assert td["foot_force"].abs().max() < 60.0
    torch.testing.assert_close(td["ref_joint_pos"], env.motion.joint_targets(torch.zeros(N), env.init_row))


def test_phase_clock(env):
    env.reset()
    rows = env.motion.cycle_rows
    start = env.init_row.clone()
    rate = torch.tensor([0.0, 0.5, 1.0, 0.25])
    a = torch.zeros(N, 13)
    a[:, 12] = rate
    for k in range(1, 6):
        td = env.step(TensorDict({"action": a}, batch_size=[N]))["next"]
        t = k * env.dt * (1.0 + rate)
        expected = ((start + t / env.motion.row_dt) % rows) / rows
        torch.testing.assert_close(td["phase"].squeeze(-1), expected.float(), atol=2e-5, rtol=0)
    assert torch.all(td["episode_step"].squeeze(-1) == 5)
    torch.testing.assert_close(td["applied_action"], a)


def test_rollout_resets_only_fallen_worlds(env):
    env.set_seed(3)
    env.reset()
    torch.manual_seed(0)
    # Worlds 0-1 get full random torques and fall; worlds 2-3 get no leg torque and fall later (< 200 steps too).
    roll = env.rollout(200, break_when_any_done=False)
    done = roll["next", "done"].squeeze(-1)  # (N, T)
    assert done.any(), "random torques should make some world fall within 0.8 s"
    steps = roll["episode_step"].squeeze(-1)  # root: the state each action was applied to
    for w in range(N):
        for t in range(1, 200):
            if done[w, t - 1]:
                assert steps[w, t] == 0, "a done world restarts from a reset state"
                torch.testing.assert_close(roll["joint_pos"][w, t],
                                           torch.as_tensor(robot.INIT_JOINT_POS, dtype=torch.float32))
            else:
                assert steps[w, t] == steps[w, t - 1] + 1, "a running world keeps its episode"


def test_masked_reset_touches_only_flagged(env):
    env.reset()
    for _ in range(5):
        env.step(_zero_action(env))
    before = env._observe()
    mask = torch.tensor([True, False, True, False]).unsqueeze(-1)
    # TorchRL fills the rows that are not reset from the input tensordict: pass the current one, as collectors do.
    after = env.reset(before.clone().set("_reset", mask))
    for key in ("joint_pos", "joint_vel", "base_pos", "foot_force", "command", "episode_step", "phase"):
        assert torch.equal(after[key][1], before[key][1]) and torch.equal(after[key][3], before[key][3]), key
    assert torch.all(after["episode_step"][[0, 2]] == 0)
    assert not torch.equal(after["joint_vel"][0], before["joint_vel"][0])


@pytest.mark.parametrize("flags, got", [
    (torch.tensor([[0.5], [0.0]]), r"\(2, 1\) torch.float32 on cpu"),  # was cast to bool: world 0 restarted
    (torch.tensor([[1], [0]]), r"\(2, 1\) torch.int64"),
    (torch.ones(2, 2, dtype=torch.bool), r"\(2, 2\) torch.bool"),  # failed in a reshape
    (torch.ones(1, 2, dtype=torch.bool), r"\(1, 2\) torch.bool"),  # was reshaped to (2,) without a word
    (torch.ones(4, dtype=torch.bool), r"\(4,\) torch.bool"),
    (torch.ones(2, 1, dtype=torch.bool, device="meta"), r"\(2, 1\) torch.bool on meta"),  # failed mid-reset
])
def test_a_reset_mask_of_another_shape_dtype_or_device_is_refused_before_anything_moves(flags, got):
    e = TocabiWalk(num_envs=2, device="cpu", seed=0, backend="mujoco", control_mode="torque")
    e.reset()
    e.step(_zero_action(e))
    steps, episodes = e.episode_step.clone(), e.episode_count.clone()
    with pytest.raises(ValueError, match=rf"'_reset' mask must be a \(2, 1\) bool tensor on cpu.*got {got}"):
        e._reset(TensorDict({"_reset": flags}, batch_size=[]), seed=5)
    assert torch.equal(e.episode_step, steps) and torch.equal(e.episode_count, episodes)
    assert e._seed == 0  # the refused reset's seed was not taken either
    # Both of TorchRL's layouts of a good mask still reset just the flagged worlds.
    for good in (torch.tensor([[True], [False]]), torch.tensor([True, False])):
        e.step(_zero_action(e))
        e._reset(TensorDict({"_reset": good}, batch_size=[]))
        assert e.episode_step.tolist() == [0, int(e.episode_step[1])] and int(e.episode_step[1]) > 0


def test_truncation_with_short_episodes(backend):
    e = TocabiWalk(num_envs=2, device="cpu", seed=0, max_episode_steps=5, backend=backend, control_mode="torque")
    e.reset()
    for k in range(5):
        out = e.step(_zero_action(e))["next"]
        assert bool(out["truncated"].all()) == (k == 4)
        assert not out["terminated"].any()
    assert torch.equal(out["done"], out["truncated"])


def test_neck_yaw_terminates(env):
    """A standing robot turned 1.2 rad about z: only the neck-orientation condition fires."""
    env.reset()
    q = env.sim.qpos.clone()
    q[0, 3:7] = torch.tensor([math.cos(0.6), 0.0, 0.0, math.sin(0.6)])
    env.sim.reset(torch.tensor([True, False, False, False]), q, torch.zeros_like(env.sim.qvel),
                  env.sim.ctrl.clone())
    out = env.step(_zero_action(env))["next"]
    assert out["terminated"].squeeze(-1).tolist() == [True, False, False, False]


def test_termination_conditions_on_constructed_states():
    n = 7
    kwargs = dict(min_pelvis_height=0.6, min_neck_height=0.8, max_neck_angle=1.0)
    pelvis = torch.full((n,), 0.92)
    neck = torch.full((n,), 1.5)
    quat = torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1)
    forbidden = torch.zeros(n, dtype=torch.bool)
    self_col = torch.zeros(n, dtype=torch.bool)
    healthy = torch.ones(n, dtype=torch.bool)
    pelvis[1] = 0.59
    neck[2] = 0.79
    quat[3] = torch.tensor([math.cos(0.51), math.sin(0.51), 0, 0])  # 1.02 rad roll
    forbidden[4] = True
    self_col[5] = True
    healthy[6] = False
    f = termination_flags(pelvis_height=pelvis, neck_height=neck, neck_quat=quat, forbidden_ground_contact=forbidden,
                          self_collision=self_col, healthy=healthy, **kwargs)
    assert f["any"].tolist() == [False] + [True] * 6
    for name, row in [("pelvis_low", 1), ("neck_low", 2), ("neck_tilt", 3), ("forbidden_contact", 4),
                      ("self_collision", 5), ("unhealthy", 6)]:
        assert f[name].nonzero().flatten().tolist() == [row], name
    quat[3] = torch.tensor([math.cos(0.49), math.sin(0.49), 0, 0])  # 0.98 rad: below the limit
    f = termination_flags(pelvis_height=pelvis, neck_height=neck, neck_quat=quat, forbidden_ground_contact=forbidden,
                          self_collision=self_col, healthy=healthy, **kwargs)
    assert not f["neck_tilt"][3]


def test_pd_mode_tracks_constant_target(pd_env):
    pd_env.reset()
    target = 0.2
    a = torch.zeros(2, 13)
    a[:, 3] = target  # left knee: nominal + 0.5 * 0.2 = 0.7 rad
    for _ in range(60):
        out = pd_env.step(TensorDict({"action": a}, batch_size=[2]))["next"]
    knee = out["joint_pos"][:, 3]
    expected = robot.INIT_JOINT_POS[3] + pd_env.cfg.control.pd_action_scale * target
    assert torch.all((knee - expected).abs() < 0.03), knee
    # The reported leg torque is the PD output, bounded by the limits.
    assert torch.all(out["leg_torque"].abs() <= torch.as_tensor(robot.LEG_TORQUE_LIMITS, dtype=torch.float32) + 1e-3)


def test_pd_reference_mode_targets_the_reference_motion(backend):
    """pd_reference: target = reference leg angles at the pre-step clock + scale × action (clipped to the range)."""
    e = TocabiWalk(num_envs=2, device="cpu", seed=0, control_mode="pd_reference", pd_kp=tuple(robot.LEG_KP),
                   pd_kv=tuple(robot.LEG_KV), backend=backend)
    e.reset()
    a = torch.zeros(2, 13)
    a[1, :12] = 0.1
    for _ in range(3):
        t0, row0 = e.time.clone(), e.init_row.clone()
        out = e.step(TensorDict({"action": a}, batch_size=[2]))["next"]
        q_ref = e.motion.joint_targets(t0, row0)[:, :12]
        expected = torch.maximum(torch.minimum(q_ref + e.cfg.control.pd_action_scale * a[:, :12], e._leg_range[:, 1]),
                                 e._leg_range[:, 0])
        torch.testing.assert_close(e.sim.ctrl[:, :12].float(), expected, atol=1e-6, rtol=0)
        torch.testing.assert_close(out["ref_joint_pos"][:, :12], q_ref)
    # Open-loop replay of the walk with stiff gains keeps the robot up for these steps.
    assert not out["terminated"].any()


def test_base_velocity_in_pelvis_frame():
    q = torch.tensor([[math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)]])  # 90° yaw
    v = torch.tensor([[1.0, 0.0, 0.0]])
    torch.testing.assert_close(quat_rotate_inverse(q, v), torch.tensor([[0.0, -1.0, 0.0]]), atol=1e-6, rtol=0)


# --- command schedule -----------------------------------------------------------------------------------------


def _command(cfg, n=512, seed=0):
    g = torch.Generator().manual_seed(seed)
    c = VelocityCommand(cfg, n, torch.device("cpu"), g)
    c.reset(torch.ones(n, dtype=torch.bool))
    return c


def test_command_tocabilab_preset():
    cfg = CommandConfig(resample_every=10)
    c = _command(cfg)
    vx, vy = c.value.unbind(-1)
    assert vx.min() >= 0.2 and vx.max() <= 0.7 and vy.abs().max() <= 0.2
    first = c.value.clone()
    for step in range(10):
        c.update(torch.full((512,), step))
        # Unchanged until step 9 (9 % 10 == 9), where the new command applies at once.
        assert torch.equal(c.value, first) == (step < 9)
    assert c.value[:, 0].min() >= 0.0 and c.value[:, 0].max() <= 0.7
    assert c.value[:, 0].min() < 0.2, "re-samples use the full U(0, 0.7) range"


def test_command_reference_ramp():
    cfg = CommandConfig.reference()
    cfg.resample_every = 5
    c = _command(cfg, seed=1)
    assert c.value[:, 0].min() >= -0.2 and c.value[:, 0].max() <= 0.8
    s0 = c.value.clone()
    c.update(torch.full((512,), 4))  # due (4 % 5 == 4): the ramp starts at position 0, value unchanged
    torch.testing.assert_close(c.value, s0)
    d, final = c.ramp_len.clone(), c.final.clone()
    assert d.min() >= 1 and d.max() <= 249 and len(d.unique()) > 100
    for _ in range(300):
        c.update(torch.full((512,), 5))  # not due: the ramp only advances
    # The reference's ramp stops one step short: at (D - 1) / D of the change (D = 1: no change at all).
    expected = s0 + (final - s0) * ((d - 1).float() / d.float()).unsqueeze(-1)
    torch.testing.assert_close(c.value, expected)


def test_command_reference_ramp_survives_reset():
    cfg = CommandConfig.reference()
    c = _command(cfg, n=64, seed=2)
    c.update(torch.full((64,), 1999))
    pos = c.ramp_pos.clone()
    c.reset(torch.ones(64, dtype=torch.bool))
    assert torch.equal(c.ramp_pos, pos), "the reference keeps its ramp state across resets"
    c2 = _command(CommandConfig(max_ramp_steps=50), n=64, seed=2)
    c2.update(torch.full((64,), 1999))
    c2.reset(torch.ones(64, dtype=torch.bool))
    assert torch.equal(c2.ramp_pos, c2.ramp_len), "the default preset ends a ramp at reset"


def test_pin_refuses_a_mask_of_another_shape_and_hold_and_pin_a_command_that_is_no_speed():
    c = _command(CommandConfig(), n=3, seed=0)
    before = [t.clone() for t in (*c._range, *c._initial_range, c.value)]
    for envs in (torch.tensor([True]), torch.tensor([[True], [False], [False]]), torch.tensor([1, 0, 0])):
        # The (1,) mask broadcast to every env and pinned all three; the (3, 1) one failed in a where.
        with pytest.raises(ValueError, match=r"pin takes a \(3,\) bool tensor"):
            c.pin(envs, (0.4, -0.1))
    for bad in ((math.nan, 0.0), (0.5, math.inf), (50.0, 0.0)):  # NaN reached every observation; 50: km/h?
        with pytest.raises(ValueError, match=r"finite speeds in m/s within ±10"):
            c.pin(torch.tensor([True, False, False]), bad)
        with pytest.raises(ValueError, match=r"finite speeds in m/s within ±10"):
            c.hold(*bad)
    for kept, was in zip((*c._range, *c._initial_range, c.value), before):
        assert torch.equal(kept, was)
    c.pin(torch.tensor([False, True, False]), (0.4, -0.1))  # a good mask pins its env alone
    c.reset(torch.ones(3, dtype=torch.bool))
    assert c.value[1].tolist() == pytest.approx([0.4, -0.1]) and c.value[0].tolist() != pytest.approx([0.4, -0.1])


# --- bad input ------------------------------------------------------------------------------------------------


def test_bad_actions(env):
    env.reset()
    with pytest.raises(ValueError, match=r"shape \(num_envs, 13\)"):
        env._step(TensorDict({"action": torch.zeros(N, 12)}, batch_size=[N]))
    with pytest.raises(TypeError, match="floating-point"):
        env._step(TensorDict({"action": torch.zeros(N, 13, dtype=torch.int64)}, batch_size=[N]))
    with pytest.raises(ValueError, match="move it with"):
        env._step(TensorDict({"action": torch.zeros(N, 13, device="meta")}, batch_size=[N]))


def test_nan_actions_act_as_zero(env):
    env.reset()
    a = torch.full((N, 13), float("nan"))
    out = env.step(TensorDict({"action": a}, batch_size=[N]))["next"]
    assert torch.all(out["applied_action"] == 0) and torch.all(out["leg_torque"] == 0)
    assert torch.isfinite(out["joint_pos"]).all()


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(num_envs=0), ValueError, "num_envs"),
        (dict(num_envs=-3), ValueError, "num_envs"),
        (dict(num_envs=2, control_mode="velocity"), ValueError, "control_mode"),
        (dict(num_envs=2, max_episode_steps=0), ValueError, "max_episode_steps"),
        (dict(num_envs=2, min_pelvis_height=float("nan")), ValueError, "min_pelvis_height"),
        (dict(num_envs=2, pd_kp=(1.0,) * 3), ValueError, "pd_kp"),
        (dict(num_envs=2, not_an_option=1), TypeError, "not_an_option"),
        (dict(num_envs=2, device="tpu"), ValueError, "device"),
        (dict(num_envs=2, backend="bullet"), ValueError, "backend"),
        (dict(num_envs=2, sim_threads=0), ValueError, "sim_threads"),
    ],
)
def test_bad_construction(kwargs, error, match):
    kwargs.setdefault("device", "cpu")
    with pytest.raises(error, match=match):
        TocabiWalk(**kwargs)


def test_backend_selection():
    assert resolve_backend("auto", "cpu") == CPU_DEFAULT_BACKEND == "mujoco"
    assert resolve_backend("auto", "cuda:0") == "warp" and resolve_backend("warp", "cpu") == "warp"
    with pytest.raises(ValueError, match="use device='cpu'"):
        resolve_backend("mujoco", "cuda")
    e = TocabiWalk(num_envs=3, device="cpu", seed=0, sim_threads=2, control_mode="torque")
    assert e.backend == "mujoco" and isinstance(e.sim, MujocoSim) and e.sim.threads == 2
    assert "backend='mujoco'" in repr(e)


def test_bad_command_schedule():
    with pytest.raises(ValueError, match="unknown command schedule"):
        CommandConfig.named("fast")
    with pytest.raises(ValueError, match="vx_range"):
        CommandConfig(vx_range=(0.5, 0.1)).validate()


# --- GPU ------------------------------------------------------------------------------------------------------


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("options", [{}, {"cycle_velocity": True}, {"pushes": "calm"}],
                         ids=["plain", "cycle_velocity", "calm_kicks"])
def test_gpu_step_and_reset_never_sync(options):
    if options.get("pushes") == "calm":  # kicks from the first step, half the episodes calm
        from tocabi_torchrl.envs.pushes import PushConfig

        options = {"config": dataclasses.replace(TocabiWalkConfig(), pushes=PushConfig(
            count=2, window=(0.0, 0.02), speed=(0.5, 1.0), kind="velocity", calm_fraction=0.5))}
    e = TocabiWalk(num_envs=64, device="cuda", seed=0, control_mode="torque", **options)
    check_env_specs(e, seed=0)
    td = e.reset()
    action = torch.zeros(64, 13, device="cuda")
    mask = (torch.arange(64, device="cuda") % 3 == 0).unsqueeze(-1)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(3):
            td = e.step(td.set("action", action))["next"]
        # The env's own masked reset. TorchRL's EnvBase.reset adds a `_reset.all()` merge check on top (a framework
        # host read outside this env); a full reset takes no such path.
        e._reset(td.clone().set("_reset", mask))
        e.reset()
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert td["joint_pos"].device.type == "cuda"


def test_one_hash_pass_draws_every_stream_as_its_own_call_would():
    """EpisodeDraws (the reset's and the sensor noise's one pass over several streams) gives each stream exactly the
    numbers of its own episode_uniform call, whatever other streams share the pass, and its normals episode_normal's."""
    from tocabi_torchrl.envs.episode_random import EpisodeDraws, box_muller, episode_normal, episode_uniform

    ids, episode = torch.arange(257), torch.randint(0, 2**40, (257,), generator=torch.Generator().manual_seed(3))
    streams = {0: 3, 1: 24, 2: 99, 16: 72, 17: 32, 40: 34}
    seed = torch.tensor(2**31 + 9)
    together = EpisodeDraws(streams, "cpu")(seed, ids, episode)
    assert list(together) == list(streams)
    for stream, k in streams.items():
        assert torch.equal(together[stream], episode_uniform(seed, ids, episode, stream, k)), stream
        alone = EpisodeDraws({stream: k, 5: 0}, "cpu")(seed, ids, episode)  # an empty stream is left out
        assert list(alone) == [stream] and torch.equal(alone[stream], together[stream])
    assert torch.equal(box_muller(together[16]), episode_normal(seed, ids, episode, 16, 36))
    # The numbers themselves, as the per-stream hash drew them before the one-pass draw existed (values × 2**24).
    pinned = EpisodeDraws({0: 3, 2: 2, 17: 2, 33: 2}, "cpu")(seed, torch.tensor([0, 5, 4095]),
                                                            torch.tensor([0, 7, 2**40 + 3]))
    assert {s: (u * (1 << 24)).long().tolist() for s, u in pinned.items()} == {
        0: [[14082174, 14779758, 15450096], [6053201, 15535796, 16084843], [12652417, 5375057, 11739389]],
        2: [[3560581, 12969962], [9374992, 13786362], [5712760, 8868444]],
        17: [[1768404, 374026], [11605394, 14184731], [5814443, 11169919]],
        33: [[15950955, 16757830], [7618500, 10566801], [16462573, 12674182]]}
    assert EpisodeDraws({3: 0}, "cpu")(seed, ids, episode) == {}  # nothing to draw: no hash at all
    with pytest.raises(ValueError, match="256"):
        EpisodeDraws({4: 257}, "cpu")
    # Streams differ from each other (disjoint lanes), and from the same stream of the next episode.
    assert (together[1][:, :3] != together[0]).float().mean() > 0.99
    nxt = EpisodeDraws(streams, "cpu")(seed, ids, episode + 1)
    assert (nxt[2] != together[2]).float().mean() > 0.99
    # Explicit lanes in an order of one's own (the sensor noise's layout): each column is its lane's uniform.
    from tocabi_torchrl.envs.episode_random import LaneDraws, stream_lanes

    lanes = torch.cat((stream_lanes(17, 8, "cpu")[4:], stream_lanes(0, 3, "cpu"), stream_lanes(17, 8, "cpu")[:4]))
    mixed = LaneDraws(lanes)(seed, ids, episode)
    assert torch.equal(mixed, torch.cat((together[17][:, 4:8], together[0], together[17][:, :4]), dim=-1))
    with pytest.raises(ValueError, match="int64"):
        LaneDraws(lanes.float())


def test_the_one_kernel_hash_gives_the_torch_hash_bit_for_bit():
    # The warp kernel that LaneDraws runs for eager CUDA steps, here on warp's CPU device: the same uint64 arithmetic,
    # keys far beyond 32 bits (episode << 32 + step), large env ids and seeds up to 2**63 - 1.
    from tocabi_torchrl.envs.episode_hash import hash_uniforms
    from tocabi_torchrl.envs.episode_random import _hash, stream_lanes

    g = torch.Generator().manual_seed(0)
    ids = torch.randint(0, 1 << 17, (3000,), generator=g)
    key = (torch.randint(0, 1 << 20, (3000,), generator=g) << 32) + torch.randint(0, 1 << 31, (3000,), generator=g)
    lanes = torch.cat([stream_lanes(s, 40, "cpu") for s in (0, 17, 33, 52)])
    for seed in (0, 7, 2**40 + 3, 2**63 - 1):
        s = torch.tensor(seed, dtype=torch.int64)
        assert torch.equal(hash_uniforms(s, ids, key, lanes, lanes * 0xC2B2AE3D), _hash(s, ids, key, lanes,
                                                                                     lanes * 0xC2B2AE3D)), seed
    assert hash_uniforms(torch.tensor(0), ids[:0], key[:0], lanes, lanes).shape == (0, lanes.shape[0])


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_gpu_lane_draws_run_one_kernel_eagerly_with_the_torch_numbers_and_no_sync():
    from tocabi_torchrl.envs.episode_random import LaneDraws, _hash, stream_lanes

    lanes = torch.cat([stream_lanes(s, 40, "cuda") for s in (0, 33, 52)])
    draws = LaneDraws(lanes)
    ids = torch.arange(4096, device="cuda")
    key = (torch.arange(4096, device="cuda") << 32) + 17
    seed = torch.tensor(5, dtype=torch.int64, device="cuda")
    torch.cuda.synchronize()
    draws(seed, ids, key)  # the kernel's module loads here
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
            u = draws(seed, ids, key)
    finally:
        torch.cuda.set_sync_debug_mode(0)
    top = [e.name for e in prof.events() if e.name.startswith("aten::")
           and (e.cpu_parent is None or not e.cpu_parent.name.startswith("aten::"))]
    assert len(top) <= 6, top  # the output's allocation and views, no arithmetic (the torch hash: ~30 ops)
    assert torch.equal(u, _hash(seed, ids, key, draws.lanes, lanes * 0xC2B2AE3D))


def test_episode_random_numbers_depend_on_episode_not_call_order():
    from tocabi_torchrl.envs.episode_random import episode_uniform

    ids = torch.arange(4096)
    first = episode_uniform(7, ids, torch.zeros(4096, dtype=torch.int64), stream=0, k=3)
    again = episode_uniform(7, ids, torch.zeros(4096, dtype=torch.int64), stream=0, k=3)
    assert torch.equal(first, again)
    assert first.min() >= 0 and first.max() < 1 and abs(first.mean().item() - 0.5) < 0.02
    later = episode_uniform(7, ids, torch.ones(4096, dtype=torch.int64), stream=0, k=3)
    other_seed = episode_uniform(8, ids, torch.zeros(4096, dtype=torch.int64), stream=0, k=3)
    assert (first != later).float().mean() > 0.99 and (first != other_seed).float().mean() > 0.99
    # A seed held as a device tensor (what the env passes, so that a captured graph follows set_seed): same numbers.
    for seed in (7, 2**31 + 5):
        as_tensor = episode_uniform(torch.tensor(seed), ids, torch.zeros(4096, dtype=torch.int64), stream=0, k=3)
        assert torch.equal(as_tensor, episode_uniform(seed, ids, torch.zeros(4096, dtype=torch.int64), stream=0, k=3))
    # Extra resets of other envs (or no-op resets) leave an env's next episode unchanged.
    e = TocabiWalk(num_envs=2, device="cpu", seed=11, control_mode="torque")
    e.reset()
    e._reset(TensorDict({"_reset": torch.tensor([[False], [True]])}, batch_size=[2]))
    e._reset(TensorDict({"_reset": torch.tensor([[False], [False]])}, batch_size=[2]))
    e._reset(TensorDict({"_reset": torch.tensor([[True], [False]])}, batch_size=[2]))
    f = TocabiWalk(num_envs=2, device="cpu", seed=11, control_mode="torque")
    f.reset()
    f._reset(TensorDict({"_reset": torch.tensor([[True], [False]])}, batch_size=[2]))
    assert torch.equal(e.command.value[0], f.command.value[0]) and e.init_row[0] == f.init_row[0]


def test_set_seed_then_reset_repeats_the_same_episodes():
    # Start rows and commands are keyed on (seed, env, episode number); set_seed restarts the numbering, so an
    # evaluation seeded again after a rollout (whose resets advanced the numbers) sees the same episodes.
    e = TocabiWalk(num_envs=3, device="cpu", seed=0, control_mode="torque")
    zero = torch.zeros(3, 13)

    def run():
        td = e.reset()
        start = (e.init_row.clone(), e.command.value.clone(), td["joint_pos"].clone())
        for _ in range(3):
            td = e.step(td.set("action", zero))["next"]
        return start, td["joint_pos"]

    e.set_seed(3)
    first = run()
    e.rollout(5)  # more resets: the episode numbers move on
    e.set_seed(3)
    again = run()
    for a, b in zip((*first[0], first[1]), (*again[0], again[1])):
        assert torch.equal(a, b)
    e.set_seed(4)
    assert not torch.equal(run()[0][0], first[0][0]) or not torch.equal(e.command.value, first[0][1])


def test_seeds_that_differ_only_above_32_bits_draw_other_episodes():
    # The per-episode hash read only a seed's low 32 bits: seeds 1 and 2**32 + 1 drew the same starts, commands,
    # dynamics, kicks and sensor biases. Below 2**32 the key is the seed itself (every committed result unchanged).
    from tocabi_torchrl.envs.episode_random import hash_seed

    assert [hash_seed(s) for s in (0, 1, 2**32 - 1)] == [0, 1, 2**32 - 1]
    assert len({hash_seed(s) for s in (1, 2**32 + 1, 2**33 + 1, 2**63 - 1)}) == 4
    assert all(0 <= hash_seed(s) < 2**32 for s in (2**32, 2**62 + 5, 2**63 - 1))
    rows = []
    for seed in (1, 2**32 + 1):
        e = TocabiWalk(num_envs=8, device="cpu", seed=seed, control_mode="torque")
        e.reset()
        rows.append(e.init_row.clone())
    assert not torch.equal(*rows)
    e.set_seed(1)
    e.reset()
    e.set_seed(2**32 + 1)  # set_seed keys the draws the same way as the constructor
    e.reset()
    assert torch.equal(e.init_row, rows[1])


def test_a_step_without_an_action_names_the_key_and_its_shape():
    # It ended in AttributeError: 'NoneType' object has no attribute 'detach'.
    e = TocabiWalk(num_envs=2, device="cpu", seed=0, backend="mujoco", control_mode="torque")
    with pytest.raises(KeyError, match=r"no 'action' tensor .* shape \(num_envs, 13\) = \(2, 13\)"):
        e.step(e.reset())
    with pytest.raises(KeyError, match=r"no 'action' tensor \(got NonTensorData\)"):
        e.step(e.reset().set_non_tensor("action", [0.0] * 13))


def test_a_step_before_the_first_reset_is_refused():
    # It stepped the model's initial state with a 0 m/s command (outside the configured ranges) and no start row.
    e = TocabiWalk(num_envs=2, device="cpu", seed=0, backend="mujoco", control_mode="torque")
    with pytest.raises(RuntimeError, match=r"step before the first reset.*call env.reset\(\) first"):
        e.step(_zero_action(e))
    assert int(e.episode_step.sum()) == 0  # nothing moved
    # A first reset that leaves a world out would let that world step unstarted: refused, and a full mask is fine.
    partial = TensorDict({"_reset": torch.tensor([[True], [False]])}, batch_size=[2])
    with pytest.raises(ValueError, match=r"first reset must restart every world .*flags 1 of 2"):
        e.reset(partial)
    with pytest.raises(RuntimeError, match="step before the first reset"):
        e.step(_zero_action(e))
    e.reset(TensorDict({"_reset": torch.ones(2, 1, dtype=torch.bool)}, batch_size=[2]))
    assert e.step(_zero_action(e))["next", "episode_step"].tolist() == [[1], [1]]
    e.reset(partial)  # later partial resets are what autoreset does


def test_close_stops_the_simulators_worker_threads():
    # torchrl's close only set is_closed: the CPU backend's thread pool lived on until garbage collection.
    env = TocabiWalk(num_envs=4, device="cpu", sim_threads=2, backend="mujoco")
    env.rollout(3)
    pool = env.sim._pool
    threads = list(pool._threads)
    assert threads and all(t.is_alive() for t in threads)
    env.close()
    assert env.sim._pool is None and not any(t.is_alive() for t in threads) and env.is_closed
    env.close(raise_if_closed=False)  # a second close is harmless


def test_copying_an_env_with_simulator_threads_says_what_to_do_instead():
    import copy

    env = TocabiWalk(num_envs=2, device="cpu", sim_threads=2, backend="mujoco")
    with pytest.raises(TypeError, match="cannot be copied or pickled .* pass an env factory"):
        copy.deepcopy(env)
    single = copy.deepcopy(TocabiWalk(num_envs=2, device="cpu", sim_threads=1, backend="mujoco"))
    assert single.reset()["base_pos"].shape == (2, 3)


def test_set_seed_repeats_the_episodes_of_a_command_ramp_that_survives_resets():
    # The ramp's state lived on through set_seed + reset: the commands differed from a fresh env's by up to 0.09.
    kw = dict(command=CommandConfig(vx_range=(-0.2, 0.8), vx_initial_range=(-0.2, 0.8), resample_every=5,
                                    max_ramp_steps=50, ramp_survives_reset=True))
    zero = lambda td: td.set("action", torch.zeros(2, 13))  # noqa: E731
    fresh = TocabiWalk(num_envs=2, device="cpu", seed=0, backend="mujoco", **kw).rollout(
        20, zero, break_when_any_done=False)
    used = TocabiWalk(num_envs=2, device="cpu", seed=0, backend="mujoco", **kw)
    used.rollout(13, zero, break_when_any_done=False)
    used.set_seed(0)
    again = used.rollout(20, zero, break_when_any_done=False)
    torch.testing.assert_close(again["next", "command"], fresh["next", "command"], rtol=0, atol=0)


@pytest.mark.parametrize("setting, message", [
    (dict(min_pelvis_height=5.0), "min_pelvis_height 5.0 (the start pose's pelvis height is 0.930 m)"),
    (dict(min_neck_height=1.6), "min_neck_height 1.6 (the start pose's neck height is 1.507 m)"),
    (dict(max_neck_angle=-0.1), None)])  # refused by the value check before the env is built
def test_termination_thresholds_the_start_pose_trips_are_said(setting, message):
    # min_pelvis_height=5 ended every episode at its first step without a word (a warning: a test may want that).
    if message is None:
        with pytest.raises(ValueError, match="max_neck_angle"):
            TocabiWalk(num_envs=1, device="cpu", backend="mujoco", **setting)
        return
    with pytest.warns(UserWarning, match=re.escape(message) + ".* every episode ends at its first step"):
        env = TocabiWalk(num_envs=1, device="cpu", backend="mujoco", **setting)
    assert env.rollout(2, break_when_any_done=False)["next", "terminated"].all()
