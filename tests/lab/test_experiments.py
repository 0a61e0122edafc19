"""Issue 23's experiment recipes and their library: the applied-torque read-out against the simulator's own fields,
the recorded rollout and its metrics (the gait test's numbers), the obstacle analysis' definitions on made-up
records, the fixed camera, the no-overwrite rule, resuming an obstacle run, rendering at most until its first
failure, and both recipes end to end on tiny settings (C MuJoCo on the CPU). The obstacle recipe needs the env's
obstacles (``BoxObstacle``); without them its tests skip."""

from __future__ import annotations

import json
import math
import re
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch
from recipe_runner import load_recipe

from tocabi_torchrl import robot
from lab.experiments.gait_record import CRITICAL, CRITICAL_JOINTS, GaitRecord, applied_leg_torque, torque_stats

REPO = Path(__file__).resolve().parents[2]
PD_POLICY = REPO / "assets" / "policies" / "tocabi_walk_ppo.pt"
TORQUE_POLICY = REPO / "assets" / "policies" / "tocabi_walk_torque.pt"
MODEL_BASED_POLICY = REPO / "assets" / "policies" / "tocabi_walk_model_based.pt"
needs_policies = pytest.mark.skipif(not all(p.is_file() for p in (PD_POLICY, TORQUE_POLICY, MODEL_BASED_POLICY)),
                                    reason="shipped policies not present")
try:
    from tocabi_torchrl.envs.config import BoxObstacle  # noqa: F401

    HAS_OBSTACLES = True
except ImportError:
    HAS_OBSTACLES = False
needs_obstacles = pytest.mark.skipif(not HAS_OBSTACLES, reason="the env has no obstacles (BoxObstacle) yet")


# ------------------------------------------------------------------------------------------------ torque read-out
def _env(mode: str):
    from tocabi_torchrl.envs import TocabiWalk

    return TocabiWalk(num_envs=2, device="cpu", control_mode=mode, backend="mujoco", sim_threads=1, seed=0)


def _mujoco_actuator_force(env, qpos, qvel, ctrl) -> np.ndarray:
    """The legs' actuator_force of C MuJoCo's own forward pass on (qpos, qvel, ctrl), outside the env."""
    model = env.sim.mj_model
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:], data.ctrl[:] = qpos, qvel, ctrl
    mujoco.mj_forward(model, data)
    return data.actuator_force[robot.LEGS].copy()


def test_applied_torque_is_the_servo_force_in_pd_mode():
    env = _env("pd_reference")
    env.reset()
    # a known state: knees and hips away from their servo targets, moving
    qpos = torch.as_tensor(robot.INIT_QPOS, dtype=torch.float32).repeat(2, 1)
    qvel = torch.zeros(2, env.sim.nv)
    legs = slice(7, 7 + robot.NUM_LEG_JOINTS)
    qpos[:, legs] += torch.linspace(-0.05, 0.05, 12)
    qvel[:, 6:18] = torch.linspace(0.3, -0.3, 12)
    ctrl = env.sim.ctrl.clone()
    ctrl[:, robot.LEGS] = torch.as_tensor(robot.INIT_JOINT_POS[:12], dtype=torch.float32) + 0.02
    env.sim.reset(torch.ones(2, dtype=torch.bool), qpos, qvel, ctrl)
    got = applied_leg_torque(env)
    assert got.shape == (2, 12) and got.dtype == torch.float32
    # the simulator's own field, C MuJoCo's forward pass outside the env, and the servo law all agree
    torch.testing.assert_close(got, env.sim.applied_actuator_force[:, robot.LEGS])
    mj = _mujoco_actuator_force(env, qpos[0].double().numpy(), qvel[0].double().numpy(), ctrl[0].double().numpy())
    np.testing.assert_allclose(got[0].numpy(), mj, rtol=1e-4, atol=1e-3)
    kp, kv = np.array(env.cfg.control.pd_kp), np.array(env.cfg.control.pd_kv)
    law = kp * (ctrl[0, :12].numpy() - qpos[0, legs].numpy()) - kv * qvel[0, 6:18].numpy()
    np.testing.assert_allclose(got[0].numpy(), np.clip(law, -robot.LEG_TORQUE_LIMITS, robot.LEG_TORQUE_LIMITS),
                               rtol=1e-4, atol=1e-2)
    assert got[0].abs().max() > 10  # the state is far enough from the targets to matter
    # after a step it is the env's own leg_torque signal
    td = env.step(env.reset().set("action", torch.full((2, 13), 0.3)))
    torch.testing.assert_close(applied_leg_torque(env), td["next", "leg_torque"])
    torch.testing.assert_close(applied_leg_torque(env), env.sim.applied_actuator_force[:, robot.LEGS])


def test_applied_torque_is_the_commanded_torque_in_torque_mode():
    env = _env("torque")
    td = env.reset()
    action = torch.linspace(-0.9, 0.9, 13).repeat(2, 1)
    action[:, 12] = 0.5
    td = env.step(td.set("action", action))
    got = applied_leg_torque(env)
    want = action[:, :12] * torch.as_tensor(robot.LEG_TORQUE_LIMITS, dtype=torch.float32)
    torch.testing.assert_close(got, want)
    torch.testing.assert_close(got, env.sim.ctrl[:, robot.LEGS])
    torch.testing.assert_close(got, td["next", "leg_torque"])
    # the motors apply it unchanged (gear 1, within the limits): the simulator's actuator force is the same
    torch.testing.assert_close(got, env.sim.applied_actuator_force[:, robot.LEGS], rtol=1e-5, atol=1e-3)
    state = env.sim.qpos[0].double().numpy(), env.sim.qvel[0].double().numpy(), env.sim.ctrl[0].double().numpy()
    np.testing.assert_allclose(_mujoco_actuator_force(env, *state), want[0].numpy(), rtol=1e-5, atol=1e-3)


# ------------------------------------------------------------------------------------------------ made-up records
def _record(tau: torch.Tensor, alive: torch.Tensor, **extra) -> GaitRecord:
    t, n = alive.shape
    zeros = torch.zeros(t, n, 12)
    base = dict(dt=0.004, command=(0.5, 0.0), seconds=t * 0.004, control_mode="torque", joint_pos=zeros,
                ref_joint_pos=zeros, leg_torque=tau, base_pos=torch.zeros(t, n, 3), sole_pos=torch.zeros(t, n, 2, 3),
                foot_contact=torch.ones(t, n, 2, dtype=torch.bool), alive=alive, start_pos=torch.zeros(n, 3),
                termination_step=torch.full((n,), -1), snapshot_times=[0.0], snapshots=torch.zeros(1, n, 40),
                termination_qpos=torch.full((n, 40), float("nan")),
                sole_half_size=np.array([[0.15, 0.085, 0.0135]] * 2))
    base.update(extra)
    return GaitRecord(**base)


def test_torque_stats_follow_their_definitions():
    t = 6
    tau = torch.zeros(t, 2, 12)
    tau[:, 0, :] = torch.tensor([0.0, 2.0, -2.0, 4.0, 4.0, 100.0]).view(-1, 1)  # env 0: falls at step 5
    tau[:, 1, 3] = torch.arange(t, dtype=torch.float32) * 12  # env 1: one joint ramps 12 N·m per step
    alive = torch.ones(t, 2, dtype=torch.bool)
    alive[5:, 0] = False
    stats = torque_stats(_record(tau, alive))
    assert stats["mean_abs"][0] == pytest.approx(12 / 5)  # steps 0-4, every joint
    assert stats["smoothness"][0] == pytest.approx((2 + 4 + 6 + 0) / 4)  # the 4 alive pairs
    assert stats["smoothness"][1] == pytest.approx(12 / 12)  # one of 12 joints changes by 12 per step
    assert stats["peak"].shape == (2, 12) and stats["peak"][0, 0] == 4.0  # the fallen step's 100 is left out
    window = torch.zeros(t, 2, dtype=torch.bool)
    window[2:4] = True
    inside = torque_stats(_record(tau, alive), joints=CRITICAL, window=window)
    assert inside["smoothness"][0] == pytest.approx(6.0) and inside["mean_abs"][0] == pytest.approx(3.0)
    assert torch.isnan(torque_stats(_record(tau, alive), window=torch.zeros(t, 2, dtype=torch.bool))["mean_abs"]).all()


def test_footfalls_count_swings_not_bounces_and_the_window_spans_three():
    from lab.experiments.obstacle_eval import footfalls, step_window

    contact = torch.ones(60, 1, 2, dtype=torch.bool)
    contact[5:20, 0, 0] = False  # left swing, 15 steps: a footfall at 20
    contact[22:24, 0, 0] = False  # a 2-step bounce: not a footfall
    contact[25:40, 0, 1] = False  # right swing: a footfall at 40
    contact[42:55, 0, 0] = False  # left again: 55
    falls = footfalls(contact, min_air_steps=10)
    assert torch.nonzero(falls[:, 0]).flatten().tolist() == [20, 40, 55]
    alive = torch.ones(60, 1, dtype=torch.bool)
    window = step_window(torch.tensor([20]), falls, alive, steps=2)  # from the first contact to the 2nd footfall after
    assert torch.nonzero(window[:, 0]).flatten().tolist() == list(range(20, 55))
    assert not step_window(torch.tensor([-1]), falls, alive).any()
    alive[30:] = False
    assert torch.nonzero(step_window(torch.tensor([20]), falls, alive)[:, 0]).flatten().tolist() == list(range(20, 30))


def test_obstacle_analysis_classifies_robots():
    from lab.experiments.obstacle_eval import analyse_obstacle, pick_example

    t, n = 100, 3
    alive = torch.ones(t, n, dtype=torch.bool)
    alive[60:, 1] = False  # robot 1 falls at step 60, after stepping on the box
    alive[10:, 2] = False  # robot 2 falls at step 10, before reaching it
    x = torch.linspace(0.0, 1.5, t).view(-1, 1).expand(t, n)
    sole = torch.zeros(t, n, 2, 3)
    sole[..., 0] = x.unsqueeze(-1) + torch.tensor([0.1, -0.1])  # left sole ahead
    sole[..., 1] = torch.tensor([0.1, -0.1])
    sole[..., 2] = 0.03  # above a 12 mm box's top by 4 mm (the sole's half height is 13.5 mm)
    base = torch.zeros(t, n, 3)
    base[..., 0] = x
    base[..., 1] = torch.linspace(0, 0.2, t).view(-1, 1)
    rec = _record(torch.randn(t, n, 12), alive, sole_pos=sole, base_pos=base,
                  termination_step=torch.tensor([-1, 60, 10]), per_env={"lateral_m": base[-1, :, 1],
                                                                       "forward_m": base[-1, :, 0]})
    centre = torch.tensor([[0.7, 0.0, 0.006]] * n)
    out = analyse_obstacle(rec, centre, (0.3, 0.6, 0.012))
    assert out.contact_source == "sole geometry"
    assert out.passed.tolist() == [True, False, False]
    assert out.failed_on_obstacle.tolist() == [False, True, False]
    assert out.failed_before.tolist() == [False, False, True]
    assert out.reached.tolist() == [True, True, False] and out.crossed.tolist() == [True, False, False]
    assert out.first_contact[0] > 0 and out.first_contact[2] == -1
    assert out.lateral_after[0] == pytest.approx(0.2 * (1 - 0.7 / 1.5), abs=0.01) and torch.isnan(out.lateral_after[2])
    assert out.summary["pass_rate"] == pytest.approx(1 / 3)
    assert out.summary["failed_on_obstacle_rate"] == pytest.approx(1 / 3)
    assert pick_example(out, True) == 0 and pick_example(out, False) == 1
    # the env's own contact signal wins over the geometry when there is a real box
    signal = torch.zeros(t, n, 2, dtype=torch.bool)
    signal[50, 0, 0] = True
    out = analyse_obstacle(_record(rec.leg_torque, alive, sole_pos=sole, base_pos=base, obstacle_contact=signal,
                                   termination_step=rec.termination_step), centre, (0.3, 0.6, 0.012))
    assert out.contact_source == "obstacle_contact signal" and out.first_contact.tolist() == [50, -1, -1]


# ------------------------------------------------------------------------------------------------ camera, files
def test_free_camera_sits_where_asked(model):
    from tocabi_torchrl.evaluation.video import CAMERA_POS, free_camera

    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    scene = mujoco.MjvScene(model, maxgeom=1000)
    lookat = np.array([0.3, -0.1, 0.9])
    mujoco.mjv_updateScene(model, data, mujoco.MjvOption(), None, free_camera(CAMERA_POS, lookat),
                           mujoco.mjtCatBit.mjCAT_ALL, scene)
    eye = np.mean([scene.camera[i].pos for i in range(2)], axis=0)
    np.testing.assert_allclose(eye, CAMERA_POS, atol=1e-4)
    forward = np.array(scene.camera[0].forward)
    np.testing.assert_allclose(forward, (lookat - eye) / np.linalg.norm(lookat - eye), atol=1e-4)


def test_output_folders_are_never_overwritten_silently(tmp_path):
    from lab.experiments.common import ExperimentOutputError, parse_controllers, prepare_out_dir

    assert prepare_out_dir(tmp_path / "new").is_dir()
    assert prepare_out_dir(tmp_path / "new").is_dir()  # empty: fine
    (tmp_path / "new" / "table.md").write_text("earlier results")
    with pytest.raises(ExperimentOutputError, match="not overwritten"):
        prepare_out_dir(tmp_path / "new")
    prepare_out_dir(tmp_path / "new", overwrite=True)
    labels = [c.label for c in parse_controllers(["a=x.pt", "runs/b/checkpoints/latest.pt", "runs/c"])]
    assert labels == ["a", "b", "c"]
    # A run named with '=' (a sweep's lr=3e-4) is a path, not LABEL=PATH split at its first '='.
    swept = parse_controllers(["runs/lr=3e-4/policy.pt", "x=runs/lr=3e-4"])
    assert [(c.label, str(c.path)) for c in swept] == [("policy", "runs/lr=3e-4/policy.pt"), ("x", "runs/lr=3e-4")]
    (tmp_path / "lr=3e-4").mkdir()
    assert parse_controllers([str(tmp_path / "lr=3e-4")])[0].label == "lr=3e-4"
    shipped = parse_controllers(None)  # the defaults: every shipped policy, each file present
    assert [c.label for c in shipped] == ["PD (pd_reference)", "torque", "model_based"]
    assert all(c.path.is_file() for c in shipped)
    with pytest.raises(ValueError, match="labels must differ"):
        parse_controllers(["a=x.pt", "a=y.pt"])
    # the recipe refuses before rolling anything out
    stale = tmp_path / "stale"
    stale.mkdir()
    (stale / "table.json").write_text("{}")
    with pytest.raises(SystemExit) as info:
        load_recipe("compare_gaits").main(["--device", "cpu", "--out", str(stale)])
    assert "not overwritten" in str(info.value.code) and (stale / "table.json").read_text() == "{}"


# ------------------------------------------------------------------------------------------------ end to end
@needs_policies
def test_a_robot_that_falls_in_its_first_step_has_no_knee_rms_or_speed_error():
    # 0/0 once read as a perfect 0, pulling the summary's knee RMS, one of the pass criteria, towards 0.
    from tocabi_torchrl.evaluation.record import KNEES, GaitMetrics
    from tocabi_torchrl.runtime.mujoco_driver import _mean_per_alive_step

    metrics = GaitMetrics(torch.zeros(2, 3), (0.5, 0.0), 0.004)
    joint_pos, ref = torch.zeros(2, 12), torch.zeros(2, 12)
    joint_pos[:, list(KNEES)] = 0.2  # both robots' knees 0.2 rad off the reference
    nxt = {"base_pos": torch.zeros(2, 3), "joint_pos": joint_pos, "ref_joint_pos": ref,
           "base_lin_vel": torch.full((2, 3), 0.3), "terminated": torch.tensor([[True], [False]])}
    for _ in range(3):
        metrics.update(nxt)
    per_env = metrics.per_env()
    assert torch.isnan(per_env["knee_rms_rad"][0]) and per_env["knee_rms_rad"][1] == pytest.approx(0.2)
    summary = metrics.summary(8.0)
    assert summary["knee_rms_rad"] == pytest.approx(0.2) and summary["speed_tracking_error_mps"] == pytest.approx(0.2)
    assert summary["survival"] == 0.5
    # The sim-to-sim driver's summary counts the same way.
    assert _mean_per_alive_step(np.array([0.0, 3 * 0.04]), np.array([0, 3]), root=True) == pytest.approx(0.2)
    assert math.isnan(_mean_per_alive_step(np.zeros(2), np.zeros(2)))


def test_recorded_rollout_reports_the_gait_test_numbers(tmp_path):
    from tocabi_torchrl.evaluation.gait_test import evaluate_policy
    from lab.experiments.gait_record import load_policy, record_rollout

    first = load_policy(TORQUE_POLICY, 2, torch.device("cpu"))
    summary = evaluate_policy(first.actor, first.cfg, tmp_path, device="cpu", env=first.env, seconds=0.2,
                              video_envs=0, progress=False)
    second = load_policy(TORQUE_POLICY, 2, torch.device("cpu"))
    rec = record_rollout(second.actor, second.env, seconds=0.2, snapshot_every=0.1, progress=False)
    assert {k: v for k, v in summary.items() if k != "video"} == rec.metrics
    assert rec.leg_torque.shape == (50, 2, 12) and torch.isfinite(rec.leg_torque).all()
    assert rec.snapshot_times == pytest.approx([0.0, 0.1, 0.2])
    assert rec.snapshots.shape == (3, 2, second.env.base_env.sim.nq)
    torch.testing.assert_close(rec.snapshots[-1], second.env.base_env.sim.qpos)


def _images_or_skip(table: dict, paths: list[Path], size: tuple[int, int]):
    from PIL import Image

    if str(table["meta"]["frames"]).startswith("not rendered"):
        pytest.skip(f"no offscreen rendering here: {table['meta']['frames']}")
    for path in paths:
        with Image.open(path) as image:
            assert image.size == size, path


@needs_policies
def test_compare_gaits_end_to_end(tmp_path):
    out = tmp_path / "gaits"
    out.mkdir()
    (out / "old.txt").write_text("replaced with --overwrite")
    result = load_recipe("compare_gaits").main([
        "--device", "cpu", "--num_envs", "2", "--seconds", "1.0", "--frame_every", "0.5", "--knee_seconds", "0.8",
        "--torque_seconds", "0.4", "--frame_width", "96", "--frame_height", "64", "--out", str(out), "--overwrite"])
    table = json.loads((out / "table.json").read_text())
    assert [row["controller"] for row in table["rows"]] == ["PD (pd_reference)", "torque", "model_based"]
    assert [row["control_mode"] for row in table["rows"]] == ["pd_reference", "torque", "model_based"]
    md = (out / "table.md").read_text()
    assert "| PD (pd_reference) | pd_reference | 2 |" in md and "| torque | torque | 2 |" in md
    assert "| model_based | model_based | 2 |" in md
    assert "torque smoothness" in md and "pending" not in md
    for row in table["rows"]:
        for key in ("survival", "forward_distance_m", "lateral_drift_m", "knee_rms_rad", "mean_abs_torque_Nm",
                    "torque_smoothness_Nm_per_step"):
            assert isinstance(row[key], float) and np.isfinite(row[key]), key
        assert 0 < row["mean_abs_torque_Nm"] < 300 and row["torque_smoothness_Nm_per_step"] > 0
    traces = np.load(out / "traces.npz")
    for slug in ("PD_pd_reference", "torque", "model_based"):
        torque = traces[f"{slug}__leg_torque"]
        assert torque.shape == (250, 12) and np.isfinite(torque).all()
        assert np.abs(torque).max() <= robot.LEG_TORQUE_LIMITS.max() + 1e-3
        assert traces[f"{slug}__knee"].shape == (200, 2)
    assert list(traces["critical_joints"]) == list(CRITICAL_JOINTS)
    for name in ("knee_left.png", "knee_right.png", "torques.png"):
        assert (out / name).stat().st_size > 10_000, name
    # the returned rows are what table.json holds (compared through JSON: tuples become lists there)
    assert json.loads(json.dumps(result["rows"])) == table["rows"]
    _images_or_skip(table, [out / f"frames_{slug}.png" for slug in ("PD_pd_reference", "torque", "model_based")],
                    (3 * 96, 64))
    _images_or_skip(table, [out / "frames.png"], (3 * 96, 3 * 64))
    _images_or_skip(table, [out / "timelapse_torque.png"], (2 * 96, 64))


@needs_policies
@needs_obstacles
def test_obstacle_test_end_to_end(tmp_path):
    out = tmp_path / "obstacles"
    # heights 0 (no box) then 12 mm: --fail_below 0 never counts a failure, so the escalation goes on to the cap
    result = load_recipe("obstacle_test").main([
        "--policy", f"torque={TORQUE_POLICY}", "--device", "cpu", "--num_envs", "2", "--seconds", "2.0",
        "--heights_mm", "0", "--step_mm", "12", "--max_mm", "12", "--fail_below", "0", "--frame_width", "96",
        "--frame_height", "64", "--out", str(out)])
    assert result["heights_mm"] == [0.0, 12.0] and "cap" in result["stopped_after"]
    table = json.loads((out / "table.json").read_text())
    rows = table["rows"]
    assert [(row["controller"], row["height_mm"]) for row in rows] == [("torque", 0.0), ("torque", 12.0)]
    assert rows[0]["contact_source"] == "sole geometry" and rows[1]["contact_source"] == "obstacle_contact signal"
    for row in rows:
        assert 0.0 <= row["pass_rate"] <= 1.0 and row["num_envs"] == 2
        shares = row["pass_rate"] + row["failed_on_obstacle_rate"] + row["failed_before_obstacle_rate"]
        assert shares == pytest.approx(1)
        assert row["reached_rate"] == 1.0  # 2 s at 0.5 m/s reaches a box 0.6 m ahead
        peak = row["peak_torque_on_obstacle_Nm"]
        assert peak is None or 0 < peak <= robot.LEG_TORQUE_LIMITS.max() + 1e-3
    md = (out / "table.md").read_text()
    assert "| torque | 0 | 2 |" in md and "| torque | 12 | 2 |" in md
    for name in ("pass_rate.png", "lateral_deviation.png", "peak_torque.png"):
        assert (out / name).is_file(), name
    assert any(out.glob("torques_*mm.png"))
    strips = sorted(out.glob("frames_torque_*mm_*.png"))
    if not any(entry.startswith("not rendered") for entry in table["meta"]["frames"]):
        assert strips
    from PIL import Image

    for path in strips:
        with Image.open(path) as image:
            assert image.size[1] == 64 and image.size[0] % 96 == 0 and image.size[0] >= 2 * 96
    with pytest.raises(SystemExit) as info:  # the same folder again: refused
        load_recipe("obstacle_test").main(["--device", "cpu", "--out", str(out)])
    assert "not overwritten" in str(info.value.code)


@pytest.mark.parametrize("flags, message", [
    (["--steps_on_obstacle", "0"], "--steps_on_obstacle must be >= 1"),
    (["--step_mm", "1e-7"], "--step_mm must be 0 .* or a finite step of at least 1e-6 mm"),
    (["--step_mm", "inf"], "--step_mm must be 0 .* or a finite step"),
    (["--max_mm", "nan"], "--max_mm must be a finite height >= 0"),  # never stopped a controller that kept passing
    (["--max_mm", "inf"], "--max_mm must be a finite height"),
    (["--fail_below", "nan"], "--fail_below must be a number"),
    (["--heights_mm", "0,nan"], "--heights_mm must be finite numbers"),
])
def test_obstacle_test_refuses_an_empty_torque_window_or_a_step_that_never_raises_the_box(flags, message, capsys):
    # Before: --steps_on_obstacle 0 crashed after the rollout (an empty window), and a step below the heights'
    # 1e-6 mm rounding looped for ever on the same height.
    with pytest.raises(SystemExit):
        load_recipe("obstacle_test").main(["--device", "cpu", *flags])
    assert re.search(message, capsys.readouterr().err)


@pytest.mark.parametrize("flags, message", [
    (["--distance", "nan"], "--distance must be a finite distance"),
    (["--box_length", "-0.3"], "--box_length must be a finite length > 0"),
    (["--box_width", "0"], "--box_width must be a finite length > 0"),
    (["--jitter", "-0.05"], "--jitter must be a finite half-range >= 0"),
])
def test_obstacle_test_refuses_a_bad_box_before_making_its_folder(flags, message, tmp_path, capsys):
    # Before: the box's sizes were checked only when the first height was measured, after --out had been made, so
    # a bad value left a folder behind and its error named BoxObstacle's fields, not the flag.
    out = tmp_path / "out"
    with pytest.raises(SystemExit):
        load_recipe("obstacle_test").main(["--device", "cpu", "--out", str(out), *flags])
    assert re.search(message, capsys.readouterr().err)
    assert not out.exists()


# ------------------------------------------------------------------------------------------------ resuming
def _tiny_obstacle_run(out: Path, heights: str, *extra: str) -> list[str]:
    """The cheapest obstacle run that exercises the recipe: one robot, 0.2 s (it does not reach the box), tiny
    frames, only the listed heights."""
    return ["--policy", f"torque={TORQUE_POLICY}", "--device", "cpu", "--num_envs", "1", "--seconds", "0.2",
            "--heights_mm", heights, "--step_mm", "0", "--frame_width", "48", "--frame_height", "32",
            "--out", str(out), *extra]


class _Killed(BaseException):
    """Stands for the run being killed (a timeout): nothing in the recipe catches it."""


def _counting(recipe, monkeypatch, stop_at: float | None = None, stop_label: str | None = None
              ) -> list[tuple[str, float]]:
    """Wrap the recipe's run_one: record every (label, height) it measures; at ``stop_at`` mm (for ``stop_label``
    only, if given) act like a kill."""
    measured, run_one = [], getattr(recipe.run_one, "original", recipe.run_one)  # not an earlier wrapper

    def counted(controller, height_mm, args, device):
        if height_mm == stop_at and stop_label in (None, controller.label):
            raise _Killed(f"killed at {height_mm:g} mm")
        measured.append((controller.label, height_mm))
        return run_one(controller, height_mm, args, device)

    counted.original = run_one
    monkeypatch.setattr(recipe, "run_one", counted)
    return measured


@needs_policies
@needs_obstacles
def test_obstacle_resume_measures_the_controller_a_kill_left_out_and_redraws_the_height(tmp_path, monkeypatch):
    """Killed between two controllers at one height, the resume measures only the second; killed after both rows
    were saved but before the height's torque figure, the resume measures nothing and still draws the figure."""
    recipe = load_recipe("obstacle_test")
    monkeypatch.setattr(recipe, "rendering_unavailable", lambda: "not needed here")
    out = tmp_path / "obstacles"
    both = ["--policy", f"PD={PD_POLICY}"]
    measured = _counting(recipe, monkeypatch, stop_at=12.0, stop_label="PD")
    with pytest.raises(_Killed):
        recipe.main(_tiny_obstacle_run(out, "12", *both))
    assert measured == [("torque", 12.0)]

    def killed_while_plotting(out_dir, height_mm, controllers, args):
        raise _Killed("killed while drawing the torque figure")

    monkeypatch.setattr(recipe, "plot_torques", killed_while_plotting)
    measured = _counting(recipe, monkeypatch)
    with pytest.raises(_Killed):
        recipe.main(_tiny_obstacle_run(out, "12", *both, "--resume"))
    assert measured == [("PD", 12.0)]
    rows = json.loads((out / "table.json").read_text())["rows"]
    assert sorted(r["controller"] for r in rows) == ["PD", "torque"]
    drawn = []
    monkeypatch.setattr(recipe, "plot_torques", lambda out_dir, height_mm, controllers, args: drawn.append(
        (height_mm, [c.label for c in controllers])))
    measured = _counting(recipe, monkeypatch)
    recipe.main(_tiny_obstacle_run(out, "12", *both, "--resume"))
    assert measured == [] and drawn == [(12.0, ["torque", "PD"])]


@needs_policies
@needs_obstacles
def test_obstacle_test_resumes_only_the_missing_pairs(tmp_path, monkeypatch):
    recipe = load_recipe("obstacle_test")
    monkeypatch.setattr(recipe, "rendering_unavailable", lambda: "not needed here")  # frames: another test's
    out = tmp_path / "obstacles"
    measured = _counting(recipe, monkeypatch)
    recipe.main(_tiny_obstacle_run(out, "0"))
    assert measured == [("torque", 0.0)]
    first = json.loads((out / "table.json").read_text())
    assert first["meta"]["complete"] and first["meta"]["settings"]["--num_envs"] == 1
    # a second call, killed at 20 mm: the 0 mm row is kept, 12 mm measured and already written
    measured = _counting(recipe, monkeypatch, stop_at=20.0)
    with pytest.raises(_Killed):
        recipe.main(_tiny_obstacle_run(out, "0,12,20", "--resume"))
    assert measured == [("torque", 12.0)]
    killed = json.loads((out / "table.json").read_text())
    assert [(r["controller"], r["height_mm"]) for r in killed["rows"]] == [("torque", 0.0), ("torque", 12.0)]
    assert killed["rows"][0] == first["rows"][0] and not killed["meta"]["complete"]
    assert not list(out.glob(".*.tmp"))  # written atomically: no temporary file left
    # the third call measures only 20 mm and draws the plots from every row
    plotted = []
    monkeypatch.setattr(recipe, "plot_vs_height", lambda rows, key, *a, **k: plotted.append((key, list(rows))))
    measured = _counting(recipe, monkeypatch)
    result = recipe.main(_tiny_obstacle_run(out, "0,12,20", "--resume"))
    assert measured == [("torque", 20.0)] and result["measured"] == [("torque", 20.0)]
    table = json.loads((out / "table.json").read_text())
    assert [r["height_mm"] for r in table["rows"]] == [0.0, 12.0, 20.0] and table["meta"]["complete"]
    assert table["rows"][:2] == killed["rows"]
    assert [[h for _, h in call["measured"]] for call in table["meta"]["calls"]] == [[0.0], [12.0], [20.0]]
    assert {key for key, _ in plotted} == {"pass_rate", "lateral_deviation_after_m", "peak_torque_on_obstacle_Nm"}
    assert all([r["height_mm"] for r in rows] == [0.0, 12.0, 20.0] for _, rows in plotted)
    md = (out / "table.md").read_text()
    assert all(f"| torque | {h} | 1 |" in md for h in (0, 12, 20))
    # the escalation reads the earlier rows: every pass rate is below 1.1 at 20 mm, so it stops without a rollout
    measured = _counting(recipe, monkeypatch)
    result = recipe.main(_tiny_obstacle_run(out, "0,20", "--resume", "--step_mm", "10", "--fail_below", "1.1"))
    assert measured == [] and result["stopped_after"].endswith("below 1.1 at 20 mm")
    assert len(json.loads((out / "table.json").read_text())["rows"]) == 3
    # other settings, or another checkpoint under the same label, are refused before anything runs
    before = (out / "table.json").read_text()
    for flag, value, named in (("--num_envs", "2", "--num_envs 1 there, 2 here"),
                               ("--seconds", "0.4", "--seconds 0.2 there, 0.4 here"),
                               ("--jitter", "0", "--jitter 0.05 there, 0.0 here")):
        with pytest.raises(SystemExit) as info:
            recipe.main(_tiny_obstacle_run(out, "0", "--resume", flag, value))
        assert named in str(info.value.code) and "Rerun with the earlier values" in str(info.value.code)
    argv = _tiny_obstacle_run(out, "0", "--resume")
    argv[1] = f"torque={PD_POLICY}"
    with pytest.raises(SystemExit) as info:
        recipe.main(argv)
    assert "controller 'torque': checkpoint" in str(info.value.code) and "another label" in str(info.value.code)
    argv[1] = f"pd={PD_POLICY}"  # a new label is fine in itself, but the earlier 'torque' rows need their controller
    with pytest.raises(SystemExit) as info:
        recipe.main(argv)
    assert "['torque'] measured there are not named here" in str(info.value.code)
    with pytest.raises(SystemExit) as info:
        recipe.main(_tiny_obstacle_run(out, "0", "--resume", "--overwrite"))
    assert info.value.code == 2  # a usage error: "--resume keeps the earlier table's rows, --overwrite replaces them"
    assert (out / "table.json").read_text() == before and measured == []


def test_earlier_table_checks_what_it_was_made_with(tmp_path):
    from lab.experiments.common import (
        Controller,
        ExperimentOutputError,
        checkpoint_record,
        earlier_table,
        write_table,
    )

    assert earlier_table(tmp_path, "exp", {"--n": 1}, {}) == ([], {})  # nothing to resume: start afresh
    ckpt = tmp_path / "a.pt"
    ckpt.write_bytes(b"weights")
    record = checkpoint_record(Controller("a", ckpt))
    assert record["sha256"] and record["file"] == str(ckpt.resolve())
    rows = [{"controller": "a", "height_mm": 0.0, "pass_rate": float("nan")}]
    meta = {"experiment": "exp", "settings": {"--n": 1, "--s": 0.5}, "checkpoints": {"a": record}}
    write_table(rows, {"controller": "c"}, tmp_path, meta=meta)
    got_rows, got_meta = earlier_table(tmp_path, "exp", {"--n": 1, "--s": 0.5}, {"a": record})
    assert got_rows == [{"controller": "a", "height_mm": 0.0, "pass_rate": None}] and got_meta == meta
    b = checkpoint_record(Controller("b", ckpt))
    assert earlier_table(tmp_path, "exp", {"--n": 1, "--s": 0.5}, {"a": record, "b": b})[0]  # a new label: fine
    refusals = {
        "--n 1 there, 2 here; --s 0.5 there, 1 here": ("exp", {"--n": 2, "--s": 1}, {"a": record}),
        "not of 'other'": ("other", {"--n": 1}, {"a": record}),
        "['a'] measured there are not named here": ("exp", {"--n": 1, "--s": 0.5}, {}),
    }
    ckpt.write_bytes(b"retrained")  # the same path, other contents
    refusals["another contents (sha256)"] = ("exp", {"--n": 1, "--s": 0.5}, {"a": checkpoint_record(
        Controller("a", ckpt))})
    for message, call in refusals.items():
        with pytest.raises(ExperimentOutputError, match=re.escape(message)):
            earlier_table(tmp_path, *call)
    write_table(rows, {"controller": "c"}, tmp_path, meta={"experiment": "exp"})
    with pytest.raises(ExperimentOutputError, match="does not record the settings"):
        earlier_table(tmp_path, "exp", {"--n": 1}, {"a": record})
    (tmp_path / "table.json").write_text("{ cut short")
    with pytest.raises(ExperimentOutputError, match="not a readable results table"):
        earlier_table(tmp_path, "exp", {"--n": 1}, {"a": record})


# ------------------------------------------------------------------------------------------------ rendering
@needs_policies
@needs_obstacles
def test_obstacle_test_tries_rendering_only_once(tmp_path, monkeypatch, capsys):
    from tocabi_torchrl.evaluation import video as eval_video

    monkeypatch.setattr(eval_video, "_failure", None)  # this process' rendering state, restored afterwards
    recipe = load_recipe("obstacle_test")
    monkeypatch.setattr(recipe, "rendering_unavailable", lambda: None)  # as on a machine that may render
    calls = []

    def broken(*args, **kwargs):  # like a GLFW start without a display; a second try could abort the process
        calls.append(1)
        raise RuntimeError("gladLoadGL error")

    monkeypatch.setattr(recipe, "render_stills", broken)
    result = recipe.main(_tiny_obstacle_run(tmp_path / "obstacles", "0,12"))
    assert len(calls) == 1 and len(result["rows"]) == 2
    assert result["frames"] == ["not rendered: torque, 0 mm: RuntimeError: gladLoadGL error",
                                "not rendered: torque, 12 mm: RuntimeError: gladLoadGL error"]
    assert capsys.readouterr().out.count("frames skipped") == 1
    # rendering that is off from the start (MUJOCO_GL=disable: no display, no EGL) is not tried at all
    monkeypatch.setattr(recipe, "rendering_unavailable", lambda: "no OpenGL here; install libegl1")
    result = recipe.main(_tiny_obstacle_run(tmp_path / "off", "0"))
    assert len(calls) == 1 and result["frames"] == ["not rendered: torque, 0 mm: no OpenGL here; install libegl1"]


@pytest.mark.parametrize("flag", ["--knee_seconds", "--torque_seconds", "--seconds", "--frame_every"])
def test_compare_gaits_refuses_spans_that_are_not_positive_before_running(flag, capsys):
    # A negative span sliced the traces from their end: the plots showed other seconds, with no error.
    with pytest.raises(SystemExit):
        load_recipe("compare_gaits").main(["--device", "cpu", flag, "-0.1"])
    assert f"{flag} must be a finite number > 0" in capsys.readouterr().err


def test_compare_gaits_refuses_controllers_of_different_control_periods(tmp_path, monkeypatch):
    # The plots, traces.npz and the per-step smoothness column share the first controller's time step.
    recipe = load_recipe("compare_gaits")
    steps = {"a": 0.004, "b": 0.002}
    monkeypatch.setattr(recipe, "read_controller", lambda c: {})
    monkeypatch.setattr(recipe, "run_controller", lambda c, *a, **k: {"dt": steps[c.label], "row": {}})
    with pytest.raises(SystemExit) as info:
        recipe.main(["--device", "cpu", "--policy", "a=x.pt", "--policy", "b=y.pt", "--out", str(tmp_path / "o")])
    assert "b steps every 2 ms and a every 4 ms" in str(info.value.code)


def test_compare_gaits_skips_frames_when_rendering_is_off(tmp_path, monkeypatch):
    recipe = load_recipe("compare_gaits")
    monkeypatch.setattr(recipe, "rendering_unavailable", lambda: "no OpenGL here; install libegl1")
    monkeypatch.setattr(recipe, "render_stills", lambda *a, **k: pytest.fail("rendering was tried"))
    args = recipe.build_parser().parse_args([])
    assert recipe.render_frames({"x": {}}, args, tmp_path) == "not rendered: no OpenGL here; install libegl1"


def test_render_functions_give_up_after_the_first_failure(model, monkeypatch, tmp_path):
    from tocabi_torchrl.evaluation import video as eval_video

    monkeypatch.setattr(eval_video, "_failure", None)
    monkeypatch.delenv("MUJOCO_GL", raising=False)  # rendering is not off by the settings: it is tried
    calls = []

    def broken(*args, **kwargs):
        calls.append(1)
        raise RuntimeError("glfw init failed")

    monkeypatch.setattr(mujoco, "Renderer", broken)
    assert eval_video.rendering_unavailable() is None
    with pytest.raises(RuntimeError, match="glfw init failed"):
        eval_video.render_stills(model, model.qpos0[None])
    for render in (lambda: eval_video.render_stills(model, model.qpos0[None]),
                   lambda: eval_video.render_timelapse(model, model.qpos0[None]),
                   lambda: eval_video.render_video(model, model.qpos0[None, None], 30, tmp_path)):
        with pytest.raises(eval_video.RenderingUnavailable, match=r"earlier render .*glfw init failed"):
            render()
    assert len(calls) == 1 and "glfw init failed" in eval_video.rendering_unavailable()
    assert eval_video.render_stills.__doc__.startswith("One (height, width, 3)")  # the wrapper keeps the docs


def test_a_failure_outside_opengl_leaves_rendering_on(model, monkeypatch):
    from tocabi_torchrl.evaluation import video as eval_video

    monkeypatch.setattr(eval_video, "_failure", None)
    monkeypatch.delenv("MUJOCO_GL", raising=False)

    class Renderer:  # an OpenGL side that works
        def __init__(self, model, height, width, **kwargs):
            self.shape = (height, width, 3)

        def update_scene(self, *args, **kwargs):
            pass

        def render(self):
            return np.zeros(self.shape, np.uint8)

        def close(self):
            pass

    monkeypatch.setattr(mujoco, "Renderer", Renderer)
    q = model.qpos0[None]
    with pytest.raises(ValueError, match="coincide"):  # a camera looking at itself: the caller's mistake
        eval_video.render_stills(model, q, camera_pos=q[0, :3], lookat=q[0, :3])
    assert eval_video.rendering_unavailable() is None
    assert eval_video.render_stills(model, q)[0].shape == (360, 480, 3)
    monkeypatch.undo()  # MuJoCo's own renderer refuses an image beyond its offscreen buffer, before any OpenGL
    monkeypatch.setattr(eval_video, "_failure", None)
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    with pytest.raises(ValueError, match="framebuffer width"):
        eval_video.render_stills(model, q, width=int(model.vis.global_.offwidth) + 1)
    assert eval_video._failure is None


def test_an_opengl_render_failure_is_remembered(model, monkeypatch):
    import types

    from tocabi_torchrl.evaluation import video as eval_video

    # render_video's writer comes with the viz extra, which CI does not install; the render fails before it writes.
    writer = types.ModuleType("imageio.v2")
    monkeypatch.setitem(sys.modules, "imageio", types.SimpleNamespace(v2=writer))
    monkeypatch.setitem(sys.modules, "imageio.v2", writer)

    monkeypatch.setattr(eval_video, "_failure", None)
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    closed = []

    class Renderer:  # starts, then fails to draw
        def __init__(self, model, height, width, **kwargs):
            pass

        def update_scene(self, *args, **kwargs):
            pass

        def render(self):
            raise RuntimeError("eglMakeCurrent failed")

        def close(self):
            closed.append(1)

    monkeypatch.setattr(mujoco, "Renderer", Renderer)
    with pytest.raises(RuntimeError, match="eglMakeCurrent"):
        eval_video.render_video(model, model.qpos0[None, None], 30, Path("unused"), progress=False)
    assert closed == [1] and "eglMakeCurrent failed" in eval_video.rendering_unavailable()


def test_no_display_and_no_egl_turn_rendering_off_with_the_fix(monkeypatch):
    import ctypes.util
    import platform

    from tocabi_torchrl import render_gl

    monkeypatch.setattr(ctypes.util, "find_library", lambda name: None)  # no libEGL, no libOSMesa
    monkeypatch.setattr(platform, "system", lambda: "Linux")
    environ = {}
    assert render_gl.choose_gl_backend(environ) == "disable" and environ == {"MUJOCO_GL": "disable"}
    reason = render_gl.offscreen_unavailable(environ)
    assert "no display and no EGL library" in reason and "libegl1" in reason and "MUJOCO_GL=osmesa" in reason
    assert render_gl.offscreen_unavailable({"MUJOCO_GL": "off", "DISPLAY": ":0"}).startswith("MUJOCO_GL=off turns")
    for environ in ({"DISPLAY": ":0"}, {"WAYLAND_DISPLAY": "wayland-0"}):  # a desktop: MuJoCo's default (GLFW)
        assert render_gl.choose_gl_backend(environ) is None and render_gl.offscreen_unavailable(environ) is None
    monkeypatch.setattr(platform, "system", lambda: "Darwin")  # macOS: MuJoCo's CGL needs no display variable
    assert render_gl.choose_gl_backend({}) is None
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: "libEGL.so.1" if name == "EGL" else None)
    monkeypatch.setattr(platform, "system", lambda: "Linux")
    environ = {}
    assert render_gl.choose_gl_backend(environ) == "egl" and render_gl.offscreen_unavailable(environ) is None
    environ = {"WAYLAND_DISPLAY": "wayland-0"}  # no X display: EGL, as before the no-EGL case existed
    assert render_gl.choose_gl_backend(environ) == "egl" and environ["MUJOCO_GL"] == "egl"


@needs_policies
def test_compare_gaits_checks_every_controller_before_rolling_any_out(tmp_path, monkeypatch):
    # A bad last controller used to end the run only after the first ones had walked (minutes at 256 robots).
    recipe = load_recipe("compare_gaits")
    monkeypatch.setattr(recipe, "run_controller", lambda *a, **k: pytest.fail("a controller ran before the check"))
    diverged = tmp_path / "diverged.pt"
    state = torch.load(PD_POLICY, weights_only=True)
    next(iter(state["agent"]["actor"].values())).fill_(float("nan"))
    torch.save(state, diverged)
    for bad, message in ((tmp_path / "missing.pt", "bad: checkpoint not found"), (diverged, "diverged")):
        with pytest.raises(SystemExit) as info:
            recipe.main(["--device", "cpu", "--policy", f"good={PD_POLICY}", "--policy", f"bad={bad}",
                         "--out", str(tmp_path / "out")])
        assert message in str(info.value.code)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("flags, message", [
    (["--frame_every", "0.001"], "--frame_every must be at least one policy step (4 ms), got 0.001"),
    (["--knee_seconds", "0.001"], "--knee_seconds must be at least one policy step (4 ms)"),
    (["--torque_seconds", "0.002"], "--torque_seconds must be at least one policy step (4 ms)"),
    (["--frame_every", "0.1"], "gives 81 frames per controller, more than 25; pass --frame_every 0.336 or more"),
])
def test_compare_gaits_refuses_spans_below_one_policy_step_and_too_many_frames(flags, message, capsys):
    # Shorter spans gave empty traces and snapshots labelled with times never simulated; tiny frame steps an
    # unbounded number of renders.
    with pytest.raises(SystemExit):
        load_recipe("compare_gaits").main(["--device", "cpu", "--policy", "x=missing.pt", *flags])
    assert message in capsys.readouterr().err


def test_compare_gaits_rounds_frame_every_to_whole_policy_steps(capsys):
    recipe = load_recipe("compare_gaits")
    parser = recipe.build_parser()
    args = parser.parse_args(["--frame_every", "0.005", "--seconds", "0.05"])
    recipe.check_spans(args, parser, 0.004)
    assert args.frame_every == pytest.approx(0.004)
    assert "not a whole number of policy steps (4 ms): frames every 0.004 s instead" in capsys.readouterr().out


def test_snapshots_are_labelled_with_the_simulated_time():
    from lab.experiments.gait_record import load_policy, record_rollout

    policy = load_policy(TORQUE_POLICY, 1, torch.device("cpu"))
    # 6 ms is 1.5 steps of 4 ms: the states kept are those after steps 2, 3 and 4 (8, 12, 16 ms), not 6, 12, 18 ms.
    rec = record_rollout(policy.actor, policy.env, seconds=0.02, snapshot_every=0.006, progress=False)
    assert rec.snapshot_times == pytest.approx([0.0, 0.008, 0.012, 0.016])
    with pytest.raises(ValueError, match="shorter than one policy step"):
        record_rollout(policy.actor, policy.env, seconds=0.02, snapshot_every=0.001, progress=False)


def test_experiment_files_are_replaced_whole_or_not_at_all(tmp_path, monkeypatch):
    from tocabi_torchrl import atomic
    from lab.experiments.common import replace_atomically, write_atomic

    synced = []
    real_fsync = atomic.os.fsync
    monkeypatch.setattr(atomic.os, "fsync", lambda fd: synced.append(fd) or real_fsync(fd))
    path = write_atomic(tmp_path / "table.md", "first · version")
    assert path.read_text(encoding="utf-8") == "first · version" and synced  # durable before the rename

    def crash(*args):
        raise OSError("disk full")

    monkeypatch.setattr(atomic.os, "replace", crash)
    with pytest.raises(OSError, match="disk full"):
        write_atomic(path, "second")
    assert path.read_text(encoding="utf-8") == "first · version"
    monkeypatch.undo()

    # Writers that take a path (images): the temporary file keeps the suffix they pick the format from.
    image = tmp_path / "frames.png"
    image.write_bytes(b"earlier")
    seen = []

    def half_written(tmp):
        seen.append(tmp.suffix)
        tmp.write_bytes(b"half")
        raise RuntimeError("renderer died")

    with pytest.raises(RuntimeError, match="renderer died"):
        replace_atomically(image, half_written)
    assert image.read_bytes() == b"earlier" and seen == [".png"]
    assert replace_atomically(image, lambda tmp: tmp.write_bytes(b"new")).read_bytes() == b"new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames.png", "table.md"]


def test_obstacle_frame_strips_are_replaced_atomically(tmp_path, monkeypatch):
    # save_strip wrote straight into frames_<label>_<h>mm_<kind>.png: a write cut short (killed, disk full) left a
    # broken image in place of a resumed run's earlier strip; compare_gaits' strips were already atomic.
    import argparse

    recipe = load_recipe("obstacle_test")
    monkeypatch.setattr(recipe, "render_stills", lambda *a, **k: [np.zeros((4, 4, 3), np.uint8)])
    monkeypatch.setattr(recipe, "label_image", lambda image, text: image)

    def cut_short(images, path):
        Path(path).write_bytes(b"half a png")
        raise OSError("No space left on device")

    monkeypatch.setattr(recipe, "save_strip", cut_short)
    earlier = tmp_path / "frames_torque_12mm_pass.png"
    earlier.write_bytes(b"the earlier strip")
    result = {"model": None, "examples": {"pass": {"qpos": np.zeros((1, 3)), "labels": ["start"], "env": 0,
                                                   "mocap_pos": None}}}
    args = argparse.Namespace(frame_width=4, frame_height=4, fovy=25.0)
    with pytest.raises(OSError, match="No space"):
        recipe.render_examples(result, "torque", 12.0, args, tmp_path)
    assert earlier.read_bytes() == b"the earlier strip" and [p.name for p in tmp_path.iterdir()] == [earlier.name]
