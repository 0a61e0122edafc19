"""The model_based control mode (issue 23): on a held robot the env applies exactly the computed torque a hand
calculation with C MuJoCo gives (both backends), the residual and the clip, the reference's derivatives, the gains'
validation, the signal, and the preset through the config tree, a tiny training run and its checkpoint. CPU only,
except the last test (the captured step on CUDA)."""

from __future__ import annotations

import json
import math

import mujoco
import numpy as np
import pytest
import torch
from captured_vs_eager import assert_captured_equals_eager
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from tocabi_torchrl import robot
from tocabi_torchrl.config import config_from_dict, preset_config
from tocabi_torchrl.envs import TocabiWalk
from tocabi_torchrl.envs.config import MB_OMEGA, MB_RESIDUAL_GAIN_PD, ControlConfig
from tocabi_torchrl.envs.model_based import sampled_loop_radius
from tocabi_torchrl.motion import ReferenceMotion
from tocabi_torchrl.sim.inertia import DenseBlock, csr_block_index

N = 2
LEGS = robot.LEGS
LIMITS = np.asarray(robot.LEG_TORQUE_LIMITS, dtype=np.float64)


@pytest.fixture(scope="module", params=["mujoco", "warp"])
def env(request):
    # warp runs on its CPU device (kernels cached after the first build of the test run).
    return TocabiWalk(num_envs=N, device="cpu", seed=0, backend=request.param, control_mode="model_based",
                      max_episode_steps=10**6)


def _step(env, action):
    return env.step(TensorDict({"action": action}, batch_size=[env.num_envs]))["next"]


def _hold(env, time=(0.37025, 1.21013), init_row=(0, 1800)):
    """Put every world in one non-trivial state: the robot held 0.3 m up (no contact), the free joint at rest, legs
    off the reference with non-zero joint velocities, the phase clock mid-cycle. Returns (qpos, qvel) float32."""
    env.reset()
    qpos = torch.as_tensor(robot.INIT_QPOS, dtype=torch.float32).repeat(N, 1)
    qpos[:, 2] += 0.3
    rng = np.random.default_rng(7)
    clock = torch.tensor(time, dtype=torch.float32)
    rows = torch.tensor(init_row, dtype=torch.int64)
    q_ref = env.motion.joint_targets(clock, rows)
    qpos[:, 7:] = q_ref + torch.as_tensor(rng.uniform(-0.02, 0.02, (N, robot.NUM_JOINTS)), dtype=torch.float32)
    qvel = torch.zeros(N, env.sim.nv)
    qvel[:, 6:] = torch.as_tensor(rng.uniform(-0.4, 0.4, (N, robot.NUM_JOINTS)), dtype=torch.float32)
    env.sim.reset(torch.ones(N, dtype=torch.bool), qpos, qvel, env.sim.ctrl.clone())
    env.time.copy_(clock)
    env.init_row.copy_(rows)
    return env.sim.qpos.clone(), env.sim.qvel.clone()


def _reference_by_hand(motion: ReferenceMotion, t: float, init_row: int, h: int):
    """q_ref, q̇_ref, q̈_ref of the legs at clock t, from the table's rows in float64: row idx and fraction s as
    the spec says, the zero-velocity cubic between rows, central differences over ±h rows (the tables of the
    shipped motion close exactly, so no seam term is needed away from the seam)."""
    table = motion.joint_pos.double().numpy()[:, LEGS]
    n = motion.cycle_rows
    u = (t / motion.row_dt) % n
    idx, s = (init_row + int(math.floor(u))) % n, u - math.floor(u)
    w = s * s * (3 - 2 * s)

    def at(row):
        return table[row % n]

    def deriv(row):
        v = (at(row + h) - at(row - h)) / (2 * h * motion.row_dt)
        a = (at(row + h) - 2 * at(row) + at(row - h)) / (h * motion.row_dt) ** 2
        return v, a

    (v0, a0), (v1, a1) = deriv(idx), deriv(idx + 1)
    q = table[idx] + (table[idx + 1] - table[idx]) * w
    return q, v0 + (v1 - v0) * w, a0 + (a1 - a0) * w


def test_held_robot_gets_the_hand_computed_torque(env):
    """τ = clip(M_LL(q̈_ref + ω²(q_ref − q) + 2ζω(q̇_ref − q̇)) + c_L + limit·a, ±limit), M and c from C MuJoCo's
    mj_forward of the same state (mj_fullM, qfrc_bias), the phase rate scaling q̇_ref and q̈_ref."""
    qpos, qvel = _hold(env)
    action = torch.zeros(N, 13)
    action[:, :12] = torch.linspace(-0.3, 0.3, 12)
    action[1, 12] = 0.5  # world 1 runs the clock at 1.5×: q̇_ref × 1.5, q̈_ref × 2.25
    rates = [1.0, 1.0 + env.cfg.task.phase_rate_gain * 0.5]
    ctrl = env.computed_torque
    omega, zeta = np.asarray(MB_OMEGA), np.asarray(env.cfg.control.mb_zeta)
    assert ctrl.half_width == 16  # 8 ms at 2 kHz

    m = env.sim.mj_model
    d = mujoco.MjData(m)
    expected_ff, expected = [], []
    for w in range(N):
        d.qpos[:], d.qvel[:] = qpos[w].double().numpy(), qvel[w].double().numpy()
        mujoco.mj_forward(m, d)
        full = np.zeros((m.nv, m.nv))
        mujoco.mj_fullM(m, d, full)
        q_ref, v_ref, a_ref = _reference_by_hand(env.motion, float(env.time[w]), int(env.init_row[w]), 16)
        r = rates[w]
        q, qd = d.qpos[7:19], d.qvel[6:18]
        desired = r * r * a_ref + omega**2 * (q_ref - q) + 2 * zeta * omega * (r * v_ref - qd)
        tau_ff = full[6:18, 6:18] @ desired + d.qfrc_bias[6:18]
        expected_ff.append(tau_ff)
        expected.append(np.clip(tau_ff + LIMITS * action[w, :12].double().numpy(), -LIMITS, LIMITS))
    expected_ff = torch.as_tensor(np.array(expected_ff), dtype=torch.float32)
    expected = torch.as_tensor(np.array(expected), dtype=torch.float32)
    assert expected_ff.abs().max() > 20 and (expected_ff - torch.as_tensor(d.qfrc_bias[6:18])).abs().max() > 20

    out = _step(env, action)
    torch.testing.assert_close(out["leg_feedforward"], expected_ff, rtol=1e-4, atol=2e-3)
    torch.testing.assert_close(env.sim.ctrl[:, LEGS], expected, rtol=1e-4, atol=2e-3)
    torch.testing.assert_close(out["leg_torque"], expected, rtol=1e-4, atol=2e-3)
    # The history and the torque rewards see the applied torque over the limits, as in torque mode.
    lim = torch.as_tensor(LIMITS, dtype=torch.float32)
    torch.testing.assert_close(out["applied_action"][:, LEGS], expected / lim, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(out["applied_action"][:, 12], action[:, 12])


def test_residual_adds_limit_times_action_and_the_sum_is_clipped(env):
    lim = torch.as_tensor(LIMITS, dtype=torch.float32)
    _hold(env)
    ff = _step(env, torch.zeros(N, 13))["leg_feedforward"]
    torch.testing.assert_close(env.sim.ctrl[:, LEGS], ff.clamp(-lim, lim))
    _hold(env)
    small = torch.zeros(N, 13)
    small[:, :12] = 0.05
    out = _step(env, small)
    torch.testing.assert_close(out["leg_feedforward"], ff)  # same state: same law
    torch.testing.assert_close(env.sim.ctrl[:, LEGS], (ff + 0.05 * lim).clamp(-lim, lim), rtol=1e-5, atol=1e-3)
    _hold(env)
    full = torch.zeros(N, 13)
    full[:, :12] = torch.tensor([1.0, -1.0] * 6)  # ± the limit on top of τ_ff: one side of every joint saturates
    out = _step(env, full)
    applied = env.sim.ctrl[:, LEGS]
    assert (applied.abs() <= lim + 1e-3).all()
    torch.testing.assert_close(applied, (ff + full[:, :12] * lim).clamp(-lim, lim), rtol=1e-5, atol=1e-3)
    saturated = (applied.abs() - lim).abs() < 1e-3
    assert saturated.sum() >= 6
    assert (out["applied_action"][:, LEGS].abs() <= 1.0 + 1e-6).all()


def test_residual_gain_scales_each_joints_action():
    """g = env.control.mb_residual_gain: clip(τ_ff + g·a, ±limit), g per joint, here a few N·m so nothing clips."""
    gain = tuple(float(v) for v in np.arange(1, 13))
    e = TocabiWalk(num_envs=N, device="cpu", seed=0, backend="mujoco", control_mode="model_based",
                   mb_residual_gain=gain, max_episode_steps=10**6)
    lim = torch.as_tensor(LIMITS, dtype=torch.float32)
    _hold(e)
    ff = _step(e, torch.zeros(N, 13))["leg_feedforward"]
    _hold(e)
    action = torch.zeros(N, 13)
    action[:, :12] = torch.tensor([1.0, -0.5] * 6)
    out = _step(e, action)
    torch.testing.assert_close(out["leg_feedforward"], ff)
    expected = (ff + torch.tensor(gain) * action[:, :12]).clamp(-lim, lim)
    assert (expected.abs() < lim).all()  # the gains are small: no joint saturates, so g is seen exactly
    torch.testing.assert_close(e.sim.ctrl[:, LEGS], expected, rtol=1e-5, atol=1e-3)
    torch.testing.assert_close(out["applied_action"][:, LEGS], expected / lim, rtol=1e-5, atol=1e-5)


def test_zero_action_walk_stays_finite_and_resets_clear_the_feedforward(env):
    env.reset()
    for _ in range(10):
        out = _step(env, torch.zeros(N, 13))
    assert torch.isfinite(out["leg_feedforward"]).all() and out["leg_feedforward"].abs().sum() > 0
    td = env.reset()
    assert torch.all(td["leg_feedforward"] == 0) and torch.all(td["applied_action"] == 0)


def test_specs_and_the_signal_exist_in_model_based_mode_only():
    e = TocabiWalk(num_envs=N, device="cpu", seed=0, backend="mujoco", control_mode="model_based")
    check_env_specs(e, seed=0)
    assert e.signal_flags() == {"torque_assist": False, "model_based": True, "obstacles": False, "pushes": False,
                                "cycle_velocity": False}
    assert "leg_feedforward" in e.observation_spec.keys()
    plain = TocabiWalk(num_envs=N, device="cpu", seed=0, backend="mujoco", control_mode="torque")
    assert "leg_feedforward" not in plain.observation_spec.keys() and plain.computed_torque is None
    # The leg actuators stay torque motors (the PD modes turn them into position servos).
    m = e.sim.mj_model
    assert all(m.actuator_biastype[j] == mujoco.mjtBias.mjBIAS_NONE for j in range(12))


def test_default_omegas_match_the_robot_gains_at_the_initial_pose(model):
    d = mujoco.MjData(model)
    d.qpos[:] = robot.INIT_QPOS
    mujoco.mj_forward(model, d)
    full = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, d, full)
    np.testing.assert_allclose(MB_OMEGA, np.sqrt(robot.LEG_KP / np.diag(full)[6:18]), atol=0.5)
    # Held for 4 ms, the loop stays stable and its errors decay about as fast as the continuous loop's (ζ = 0.7).
    omega = np.asarray(MB_OMEGA)
    radius = sampled_loop_radius(omega, np.full(12, 0.7), 0.004)
    assert (radius < 1).all() and (radius <= np.exp(-0.65 * omega * 0.004)).all()
    assert sampled_loop_radius(np.array([900.0]), np.array([0.7]), 0.004)[0] > 1


def test_dense_block_equals_mj_fullM(model):
    d = mujoco.MjData(model)
    d.qpos[:] = robot.INIT_QPOS
    d.qpos[7:] += np.random.default_rng(3).uniform(-0.3, 0.3, model.nv - 6)
    mujoco.mj_forward(model, d)
    full = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, d, full)
    dofs = [14, 6, 7, 20, 38]  # any order, across branches (structural zeros) and the upper body
    block = DenseBlock(model, dofs, num_worlds=1, device="cpu")
    got = block(torch.as_tensor(d.M, dtype=torch.float32).unsqueeze(0))[0].double().numpy()
    np.testing.assert_allclose(got, full[np.ix_(dofs, dofs)], rtol=1e-6, atol=1e-6)
    _, stored = csr_block_index(model, range(6, 18))
    assert not stored[:6, 6:].any()  # the two legs are different branches of the tree
    with pytest.raises(ValueError, match="out of range"):
        csr_block_index(model, [0, model.nv])


def test_reference_derivatives_are_the_motions_own_and_survive_an_open_seam():
    # A cycle q = sin(2πt/T) + 0.003·t/T: the table does not close (a 3 mrad jump at the seam, as the reference's).
    rows, dt = 801, 0.0005
    n = rows - 1
    period = n * dt
    t = np.arange(rows) * dt
    q = np.sin(2 * np.pi * t / period) + 0.003 * t / period
    motion = ReferenceMotion(joint_pos=torch.as_tensor(np.repeat(q[:, None], 33, 1), dtype=torch.float32),
                             foot_force=torch.zeros(rows, 2), stance=torch.zeros(rows, dtype=torch.int64),
                             init_rows=torch.zeros(1, dtype=torch.int64), row_dt=dt)
    vel, acc = motion.joint_derivatives(16)
    k = 2 * np.pi / period
    v_true = k * np.cos(k * t) + 0.003 / period  # the drift's slope is the seam-extended sequence's too
    a_true = -k * k * np.sin(k * t)
    np.testing.assert_allclose(vel[:, 0].numpy(), v_true, atol=5e-3 * k)
    np.testing.assert_allclose(acc[:, 0].numpy(), a_true, atol=5e-3 * k * k + 2.0)
    torch.testing.assert_close(vel[-1], vel[0])  # the end point repeats row 0
    # Read through interpolate at any clock: continuous, close to the analytic derivative.
    clock = torch.linspace(0.0, 2 * period, 97)
    got = motion.interpolate(vel, clock, torch.zeros(97, dtype=torch.int64))[:, 0].numpy()
    want = k * np.cos(k * np.remainder(clock.numpy(), period)) + 0.003 / period
    np.testing.assert_allclose(got, want, atol=1e-2 * k)
    with pytest.raises(ValueError, match="half_width"):
        motion.joint_derivatives(0)


@pytest.mark.parametrize("change, match", [
    (dict(mb_omega=(40.0,) * 11), r"env.control.mb_omega needs 12 values"),
    (dict(mb_zeta=(0.7,) * 13), r"env.control.mb_zeta needs 12 values"),
    (dict(mb_omega=(40.0,) * 11 + (-1.0,)), r"mb_omega: every leg joint's natural frequency \[rad/s\] must be a "
                                            r"finite number >= 0; got R_AnkleRoll_Joint=-1.0"),
    (dict(mb_zeta=(float("nan"),) + (0.7,) * 11), r"mb_zeta: every leg joint's damping ratio .* L_HipYaw_Joint=nan"),
    (dict(mb_omega="fast"), r"env.control.mb_omega needs 12 numbers"),
    (dict(mb_ref_window=0.0), r"env.control.mb_ref_window must be a finite number of seconds > 0"),
    (dict(mb_residual_gain=(100.0,) * 12 + (1.0,)), r"env.control.mb_residual_gain needs 12 values"),
    (dict(mb_residual_gain=(100.0,) * 2 + (-5.0,) + (100.0,) * 9),
     r"mb_residual_gain: every leg joint's residual gain \[N·m per action unit\] .* L_HipPitch_Joint=-5.0"),
])
def test_bad_gains_are_named(change, match):
    with pytest.raises(ValueError, match=match):
        ControlConfig(mode="model_based", **change).validate()
    with pytest.raises(ValueError, match=match):
        preset_config("model_based", **{f"env.control.{k}": v for k, v in change.items()})


def test_gains_too_high_for_the_250_hz_hold_are_refused_when_the_env_is_built():
    omega = list(MB_OMEGA)
    omega[3] = 900.0  # L knee: ω·dt = 3.6
    with pytest.raises(ValueError, match=r"unstable for L_Knee_Joint \(ω = 900 rad/s"):
        TocabiWalk(num_envs=1, device="cpu", backend="mujoco", control_mode="model_based", mb_omega=tuple(omega))


def test_a_reference_window_wider_than_half_the_cycle_is_refused_in_seconds():
    with pytest.raises(ValueError, match=r"env.control.mb_ref_window 1 s is longer .* use at most 0.899 s"):
        TocabiWalk(num_envs=1, device="cpu", backend="mujoco", control_mode="model_based", mb_ref_window=1.0)


def test_omega_zero_means_no_feedback_and_is_built():
    # ω = 0: feed-forward and bias compensation only (a double integrator, radius exactly 1), a natural ablation
    # that the config accepts; the env must build it rather than call it unstable and advise lowering ω.
    omega = list(MB_OMEGA)
    omega[3] = 0.0
    env = TocabiWalk(num_envs=1, device="cpu", backend="mujoco", control_mode="model_based", mb_omega=tuple(omega))
    assert env.computed_torque.kp[3] == 0 and env.computed_torque.kd[3] == 0
    assert env.computed_torque.kp[2] > 0


def test_the_recipe_refuses_bad_model_based_settings_before_the_run_starts(tmp_path, capsys):
    import runpy
    from pathlib import Path

    main = runpy.run_path(str(Path(__file__).parents[1] / "recipes" / "ppo_walk.py"))["main"]
    base = ["--device", "cpu", "--preset", "cpu_smoke", "--run_dir", str(tmp_path), "--name", "mb",
            "--env.control.mode", "model_based", "--eval_at_end", "false"]
    for extra, match in ((["--env.control.mb_ref_window", "10"], "mb_ref_window 10 s is longer"),
                         (["--env.control.mb_omega", *["900"] * 12], "unstable for L_HipYaw_Joint")):
        with pytest.raises(SystemExit) as info:
            main(base + extra)
        assert str(info.value.code).startswith("error: ") and match in str(info.value.code)
        assert "training mb" not in capsys.readouterr().out and not (tmp_path / "mb").exists()


def test_preset_round_trips_through_the_tree_a_tiny_run_and_its_checkpoint(tmp_path, capsys):
    from tocabi_torchrl.export.__main__ import main as export_main
    from tocabi_torchrl.rl.checkpoint import config_from_checkpoint, read_checkpoint
    from tocabi_torchrl.rl.config import parse_args
    from tocabi_torchrl.rl.trainer import build_env, train

    # The robust recipe on the computed-torque law, and the perfect-robot recipe of before it.
    cfg, ideal = preset_config("model_based"), preset_config("model_based_ideal")
    for preset in (cfg, ideal):
        assert preset.env.control.mode == "model_based" and preset.ppo.torque_assist == 0.0
        # The residual has the PD-residual modes' authority: 0.5 rad of the robot's Kp per action unit.
        assert preset.env.control.mb_residual_gain == tuple(0.5 * float(k) for k in robot.LEG_KP)
        assert config_from_dict(json.loads(json.dumps(preset.to_dict()))) == preset
    assert cfg.env.pushes.count == 16 and cfg.env.dynamics.enabled and cfg.transforms.sensor_noise.enabled
    assert ideal.env.pushes.count == 0 and not ideal.env.dynamics.enabled and ideal.env.num_envs == 4096
    assert ControlConfig().mb_residual_gain == tuple(LIMITS)
    parsed, _ = parse_args(["--preset", "model_based", "--env.control.mb_zeta", *["1.0"] * 12,
                            "--env.control.mb_ref_window", "0.004"])
    assert parsed.env.control.mb_zeta == (1.0,) * 12 and parsed.env.control.mb_ref_window == 0.004

    tiny = preset_config("model_based", device="cpu", **{"env.num_envs": 4, "ppo.steps_per_env": 8,
                         "ppo.minibatch_size": 16},
                         total_env_steps=64, run_dir=str(tmp_path), name="mb", checkpoint_every=1, progress_bar=False,
                         eval_at_end=False, **{"ppo.actor_hidden": (16,), "ppo.critic_hidden": (16,),
                                               "env.control.mb_zeta": (0.9,) * 12, "ppo.push_ramp": (0, 64)})
    result = train(tiny)
    assert result.iterations == 2 and result.env_steps == 64
    path = tmp_path / "mb" / "checkpoints" / "latest.pt"
    saved = config_from_checkpoint(read_checkpoint(path), path)
    assert saved == tiny and saved.env.control.mb_zeta == (0.9,) * 12
    env = build_env(saved, torch.device("cpu"), num_envs=1)
    assert env.base_env.cfg.control.mode == "model_based" and env.base_env.computed_torque is not None
    # The torch-free runtime has no computed-torque law yet: export refuses instead of writing a wrong contract.
    with pytest.raises(SystemExit, match="'model_based' cannot be exported yet"):
        export_main(["--checkpoint", str(path), "--out", str(tmp_path / "mb.onnx")])
    assert not (tmp_path / "mb.onnx").exists()


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.filterwarnings("error:SyncFreeResetEnv")  # a failed capture or an eager fallback fails the test
def test_gpu_captured_model_based_step_equals_eager_and_never_syncs():
    assert_captured_equals_eager(dict(num_envs=64, device="cuda", seed=3, control_mode="model_based",
                                      mb_residual_gain=MB_RESIDUAL_GAIN_PD),
                                 ("leg_torque", "leg_feedforward", "observation", "reward"))
