"""The robust gait test (evaluation/robust.py, docs/evaluation.md): every case reported with its distributions and
verdicts, diverse starts, the standard test's numbers unchanged beside it, thresholds enforced per case, plot and
strict JSON written, and play.py's --test option end to end and refusing bad values in one line. One small robust
evaluation of the shipped policy (8 robots, 0.5 s per case, C MuJoCo on the CPU), made through play.py, serves
every test that reads a report."""

from __future__ import annotations

import contextlib
import copy
import io
import json
import math
from pathlib import Path

import pytest
import torch
from test_runs import recipe

REPO = Path(__file__).resolve().parents[1]
SHIPPED_POLICY = REPO / "assets" / "policies" / "tocabi_walk_ppo.pt"
needs_policy = pytest.mark.skipif(not SHIPPED_POLICY.is_file(), reason="shipped policy not present")
ROBOTS, SECONDS = 8, 0.5


def _strict(text: str):
    """``json.loads`` that refuses NaN/Infinity tokens (not JSON)."""
    def refuse(token):
        raise ValueError(f"non-JSON token {token}")
    return json.loads(text, parse_constant=refuse)


@pytest.fixture(scope="module")
def robust_run(tmp_path_factory):
    """play.py --test robust on the shipped policy: (output folder, report read back, printed text)."""
    if not SHIPPED_POLICY.is_file():
        pytest.skip("shipped policy not present")
    out = tmp_path_factory.mktemp("robust") / "eval"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        recipe("play").main(["--checkpoint", str(SHIPPED_POLICY), "--test", "robust", "--num_envs", str(ROBOTS),
                             "--seconds", str(SECONDS), "--device", "cpu", "--out", str(out)])
    return out, _strict((out / "robust.json").read_text()), printed.getvalue()


def test_report_has_every_case_with_its_distributions_and_verdicts(robust_run):
    from tocabi_torchrl.evaluation.gait_test import ROBUST_CRITERIA
    from tocabi_torchrl.evaluation.robust import CASES, EVAL_SEED, robust_passes

    _, report, printed = robust_run
    assert report["test"] == "robust" and report["seed"] == EVAL_SEED and list(report["cases"]) == list(CASES)
    assert report["settings"]["num_envs"] == ROBOTS and report["settings"]["seconds"] == SECONDS
    stats = {"forward_distance_m": {"mean", "p5", "p50", "p95"}, "lateral_drift_m": {"mean", "p50", "p95"},
             "instant_speed_error_mps": {"mean", "p95"}, "knee_rms_rad": {"mean", "p95"}}
    for name, case in report["cases"].items():
        assert case["num_envs"] == ROBOTS and 0.0 <= case["survival"] <= 1.0
        for metric, keys in stats.items():
            values = case[metric].values()
            assert set(case[metric]) == keys and all(isinstance(v, float) for v in values), (name, metric)
        # Half a second is shorter than one gait cycle (1.8 s): no robot has a cycle-mean velocity yet, so the
        # tracking error has no value (null), and the commands case's check on it fails.
        assert case["tracking_error_mps"] == {"mean": None, "p95": None}, name
        d = case["forward_distance_m"]
        assert d["p5"] <= d["p50"] <= d["p95"]
        assert set(case["checks"]) == set(ROBUST_CRITERIA[name])
        assert case["passes"] == all(c["pass"] for c in case["checks"].values())
    assert report["cases"]["robust_1.0"]["randomized"] and report["cases"]["robust_1.0"]["push_speed_mps"] == 1.0
    assert not report["cases"]["nominal"]["randomized"] and "randomization" not in report["cases"]["nominal"]
    # The shipped policy is a pd_reference one: its servos get the lab's dynamics and sensor noise, no actuator model.
    assert report["cases"]["robust_0.5"]["randomization"].startswith("tocabi_lab without its actuator model")
    assert report["passes"] == robust_passes(report)
    # Half a second from rest cannot cover 2.6 m: the verdict is "does not walk yet", and says why.
    assert not report["passes"] and "does not walk yet" in printed.splitlines()[1]
    assert "forward_distance_m.mean" in printed and "FAIL" in printed
    instant = report["cases"]["nominal"]["instant_speed_error_mps"]["mean"]
    assert f"tracking (cycle mean / instantaneous) - / {instant:.3f} m/s" in printed


def test_starts_are_diverse(robust_run):
    # The standard test's robots share two start rows at rest: two trajectories. Kicked starts give each robot its
    # own, in every case.
    _, report, _ = robust_run
    for name, case in report["cases"].items():
        d, drift = case["forward_distance_m"], case["lateral_drift_m"]
        assert d["p95"] - d["p5"] > 1e-3 and drift["p95"] - drift["p50"] > 1e-4, name


@needs_policy
def test_standard_test_numbers_are_unchanged(tmp_path):
    from tocabi_torchrl.evaluation.gait_test import GAIT_CRITERIA, evaluate_run

    assert GAIT_CRITERIA == {"survival": 0.95, "forward_distance_m": 2.6, "lateral_drift_m": 0.3, "knee_rms_rad": 0.15}
    direct = evaluate_run(SHIPPED_POLICY, num_envs=ROBOTS, device="cpu", seconds=SECONDS, video_envs=0,
                          out_dir=tmp_path / "direct", progress=False)
    with contextlib.redirect_stdout(io.StringIO()):
        recipe("play").main(["--checkpoint", str(SHIPPED_POLICY), "--test", "standard", "--num_envs", str(ROBOTS),
                             "--seconds", str(SECONDS), "--video_envs", "0", "--device", "cpu", "--out",
                             str(tmp_path / "play")])
    played = _strict((tmp_path / "play" / "summary.json").read_text())
    assert played["num_envs"] == ROBOTS
    assert {k: v for k, v in played.items() if k != "video"} == _strict(json.dumps(
        {k: v for k, v in direct.items() if k != "video"}))


def test_thresholds_fail_the_right_case(robust_run):
    from tocabi_torchrl.evaluation.gait_test import ROBUST_CRITERIA
    from tocabi_torchrl.evaluation.robust import case_checks, robust_passes

    good = copy.deepcopy(robust_run[1])
    for case in good["cases"].values():  # every value on the passing side of its threshold
        case["survival"] = 1.0
        case["forward_distance_m"]["mean"] = 3.0
        case["lateral_drift_m"]["p95"] = 0.1
        case["tracking_error_mps"]["mean"] = 0.05
    assert robust_passes(good)
    for name, criteria in ROBUST_CRITERIA.items():
        for path, (op, limit) in criteria.items():
            bad = copy.deepcopy(good)
            metric, _, stat = path.partition(".")
            value = limit - 0.01 if op == ">=" else limit + 0.01
            if stat:
                bad["cases"][name][metric][stat] = value
            else:
                bad["cases"][name][metric] = value
            assert not robust_passes(bad), (name, path)
            failed = {(n, p) for n in ROBUST_CRITERIA for p, c in case_checks(n, bad["cases"][n]).items()
                      if not c["pass"]}
            assert failed == {(name, path)}
            if stat:  # a value the file holds as null fails too
                bad["cases"][name][metric][stat] = None
                assert not case_checks(name, bad["cases"][name])[path]["pass"]
    missing = copy.deepcopy(good)
    del missing["cases"]["robust_1.0"]
    assert not robust_passes(missing)
    assert ROBUST_CRITERIA["nominal"]["survival"] == (">=", 0.99) and ROBUST_CRITERIA["robust_1.0"] == {
        "survival": (">=", 0.85)}
    assert math.isclose(ROBUST_CRITERIA["commands"]["tracking_error_mps.mean"][1], 0.12)


def test_plot_and_strict_json_are_written_atomically(robust_run):
    out, _, printed = robust_run
    assert (out / "robust.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    _strict((out / "robust.json").read_text())
    assert sorted(p.name for p in out.iterdir()) == ["robust.json", "robust.png"]  # no temporary file left
    assert f"results: {out / 'robust.json'}, {out / 'robust.png'}" in printed


@pytest.mark.parametrize("flags, message", [
    (["--test", "fast"], "argument --test: invalid choice: 'fast'"),
    (["--test", "robust", "--vx", "0.3"], "--vx/--vy set the standard test's command"),
    (["--test", "robust", "--num_envs", "0"], "--num_envs must be >= 1"),
])
def test_play_refuses_bad_test_values_in_one_line(flags, message, capsys):
    with pytest.raises(SystemExit) as info:
        recipe("play").main(["--checkpoint", "missing.pt", *flags])
    err = capsys.readouterr().err
    assert info.value.code == 2 and message in err and len(err.strip().splitlines()) == 1


def test_eval_test_is_a_checked_config_option():
    from tocabi_torchrl.config import RunConfig, preset_config

    assert RunConfig().eval_test == "standard"
    assert preset_config("cpu_smoke", eval_test="robust").eval_test == "robust"
    with pytest.raises(ValueError, match="eval_test must be one of"):
        preset_config("cpu_smoke", eval_test="fast")


def test_time_to_walk_gait_tests_snapshots_with_the_robust_test(robust_run, tmp_path, monkeypatch):
    # The wiring only: the robust report of each snapshot (here the fixture's) decides "walks", apart from the
    # standard test's evals.json, and the report part renders it.
    import shutil

    from lab.benchmarks import time_to_walk
    from tocabi_torchrl.evaluation import robust as robust_eval

    calls = []

    def fake(state, path, out_dir, test, device, envs, progress):
        calls.append((Path(path).name, test.num_envs, test.seconds))
        return robust_run[1]

    monkeypatch.setattr(robust_eval, "evaluate_robust_checkpoint", fake)
    read = time_to_walk.common.read_checkpoint  # a wall-clock snapshot also records its training time and steps
    monkeypatch.setattr(time_to_walk.common, "read_checkpoint", lambda path: {
        **read(path), "train_seconds": 60.0, "env_steps": 1_000_000, "iteration": 10})
    monkeypatch.chdir(tmp_path)
    checkpoints = tmp_path / "runs/time_to_walk/x/checkpoints"
    checkpoints.mkdir(parents=True)
    shutil.copy(SHIPPED_POLICY, checkpoints / "wall_00060s.pt")
    (checkpoints.parent / "train.json").write_text(json.dumps({"preset": "default", "gpus": 1, "gpu": "cpu"}))
    with contextlib.redirect_stdout(io.StringIO()):
        time_to_walk.main(["eval", "--name", "x", "--device", "cpu", "--test", "robust", "--seconds", "0.5"])
    assert calls == [("wall_00060s.pt", time_to_walk.ROBUST_ENVS, 0.5)]
    folder = tmp_path / "runs/time_to_walk/x"
    record = _strict((folder / "evals_robust.json").read_text())
    entry = record["evaluations"]["wall_00060s"]
    assert entry["test"] == "robust" and entry["walks"] is False and set(entry["cases"]) == set(robust_eval.CASES)
    assert not (folder / "evals.json").exists()
    with contextlib.redirect_stdout(io.StringIO()):
        time_to_walk.main(["report", "--runs", str(folder), "--test", "robust", "--out", str(tmp_path / "docs")])
    page = next((tmp_path / "docs").rglob("time_to_walk_robust.md")).read_text()
    assert "robust gait test" in page and "| wall_00060s |" in page and "survival (push 1.0 m/s)" in page


def test_training_ends_with_the_robust_test_when_asked(tmp_path, capsys):
    from test_runs import tiny_args

    recipe("ppo_walk").main(tiny_args(tmp_path, eval_at_end=True, eval_test="robust", eval_envs=2, eval_seconds=0.1))
    out = capsys.readouterr().out
    # A short test says that its thresholds are the 8 s test's, and that its kicks (2-7 s) never came.
    assert ("robust gait test (0.1 s, 2 robots per case): does not walk yet (the thresholds are set for the 8 s "
            "test); no kick falls within 0.1 s (they come at 2-7 s); 2 robots per case, the test asks for 1,024") in out
    # A test that ends inside the kick window, too (robust_passes once said True for one that never kicked).
    from tocabi_torchrl.evaluation.robust import robust_report_text

    report = _strict((tmp_path / "run" / "eval" / "robust.json").read_text())
    report["settings"].update(seconds=4.0, num_envs=1024)
    assert robust_report_text(report).splitlines()[0].endswith(
        "(the thresholds are set for the 8 s test); the kicks come at 2-7 s, so some robots met fewer than 3 in 4 s")
    # Some cases alone: each may pass, and the headline said "does not walk yet" without why.
    partial = json.loads(json.dumps(report))
    partial["cases"] = {"robust_0.5": partial["cases"]["robust_0.5"]}
    assert robust_report_text(partial).splitlines()[0].endswith(
        "; not run: nominal, commands, robust_1.0 (the verdict needs every case)")
    # A rounding that read as the other verdict: 0.9697 shown as 0.970 beside "needs >= 0.97 FAIL".
    check = {"value": 0.9697, "needs": ">= 0.97", "pass": False}
    partial["cases"]["robust_0.5"]["checks"] = {"survival": check}
    assert "survival                   0.9697  needs >= 0.97  FAIL" in robust_report_text(partial)
    report = _strict((tmp_path / "run" / "eval" / "robust.json").read_text())
    assert list(report["cases"]) == ["nominal", "commands", "robust_0.5", "robust_1.0"]
    assert report["checkpoint"] == str(tmp_path / "run" / "checkpoints" / "latest.pt")  # which policy it tested
    assert not (tmp_path / "run" / "eval" / "summary.json").exists()  # the standard test did not run as well


def test_the_report_describes_the_kicks_it_ran_and_its_headline_names_settings_not_the_tests():
    # The case lines were fixed strings: a test of one force kick in 0.2-0.8 s still read "3 kicks of 0.5 m/s in
    # 2-7 s" beside its own settings, and its headline said "walks" with no word of the weaker kicks.
    from tocabi_torchrl.evaluation.robust import (CASES, RobustTestConfig, case_summary, report_settings,
                                                  robust_report_text)

    committed = {"nominal": "command (0.5, 0) m/s", "commands": "training command range re-drawn every 2 s",
                 "robust_0.5": "command (0.5, 0) m/s, tocabi_lab randomisation, 3 kicks of 0.5 m/s in 2-7 s",
                 "robust_1.0": "command (0.5, 0) m/s, tocabi_lab randomisation, 3 kicks of 1.0 m/s in 2-7 s"}
    assert {n: c.describe(RobustTestConfig(), 0.004) for n, c in CASES.items()} == committed  # as reports quote it
    weak = RobustTestConfig(num_envs=1024, push_count=1, push_window=(0.2, 0.8), push_kind="force",
                            start_joint_vel_std=0.0)
    per_env = {k: torch.ones(1) for k in ("forward_m", "lateral_m", "tracking_error_mps", "instant_speed_error_mps",
                                          "knee_rms_rad", "heading_change_rad")}
    per_env["alive"] = torch.ones(1, dtype=torch.bool)
    cases = {n: {**case_summary(c, per_env, weak, 0.004), "checks": {}} for n, c in CASES.items()}
    assert cases["robust_1.0"]["description"].endswith(", 1 force kick of 1.0 m/s in 0.2-0.8 s")
    assert cases["nominal"]["description"] == committed["nominal"]
    headline = robust_report_text({"settings": report_settings(weak), "passes": True, "cases": cases}).splitlines()[0]
    assert headline == ("robust gait test (8 s, 1024 robots per case): walks; not the test's settings: 1 force kick "
                        "in 0.2-0.8 s (the test: 3 velocity kicks in 2-7 s); start velocity std 0 rad/s (joints) and "
                        "0.1 m/s (pelvis) (the test: 0.5 and 0.1)")
    # Without a pushed case the kicks are no part of the verdict; the test's own settings add nothing.
    unpushed = {"settings": report_settings(weak), "passes": True, "cases": {"nominal": cases["nominal"]}}
    assert "kick" not in robust_report_text(unpushed).splitlines()[0]
    test = {"settings": report_settings(RobustTestConfig()), "passes": True, "cases": cases}
    assert robust_report_text(test).splitlines()[0] == "robust gait test (8 s, 1024 robots per case): walks"


def test_the_distribution_panels_show_a_case_of_one_robot_on_a_fraction_axis(tmp_path):
    # One robot per case drew a CDF of a single point, which a step line does not show, on a y axis autoscaled to
    # 0.95-1.05: robust.png's three distribution panels were empty.
    import numpy as np

    from tocabi_torchrl.evaluation.plots import MARKED_ROBOTS, ecdf, plot_robust, robust_figure

    keys = ("forward_m", "lateral_m", "tracking_error_mps", "instant_speed_error_mps")
    per_case = {"nominal": {"alive": np.array([True]), **{k: np.array([0.4]) for k in keys}},
                "commands": {"alive": np.array([True] * 40), **{k: np.linspace(0.1, 0.5, 40) for k in keys}}}
    report = {"settings": {"seconds": 0.5, "num_envs": 1}, "passes": False,
              "cases": {"nominal": {"checks": {"lateral_drift_m.p95": {"needs": "<= 0.3"}}}, "commands": {}}}
    fig = robust_figure(per_case, report)
    for ax in fig.axes[1:]:
        assert ax.get_ylim() == (0.0, 1.0)
        cdfs = {c: [line for line in ax.lines if line.get_color() == c and line.get_drawstyle() == "steps-post"]
                for c in ("C0", "C1")}  # nominal's and commands' (the dotted thresholds are plain lines)
        for one in cdfs["C0"]:
            assert list(one.get_xdata()) == [0.4, 0.4] and list(one.get_ydata()) == [0.0, 1.0]  # a rise, 0 to 1
            assert one.get_marker() == "o" and list(one.get_markevery()) == [1]  # the robot itself, not the rise
        assert cdfs["C0"] and cdfs["C1"] and all(line.get_marker() in (None, "None", "") for line in cdfs["C1"])
    assert MARKED_ROBOTS < 40
    x, y = ecdf([np.nan])
    assert x.size == 0 and y.size == 0
    assert plot_robust(per_case, report, tmp_path / "robust.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_heading_frame_velocity_removes_the_yaw_only():
    import torch

    from tocabi_torchrl.evaluation.robust import heading_frame_velocity

    half = math.pi / 4  # a pelvis turned 90° left, then also pitched 0.3 rad about its own y axis
    yaw = torch.tensor([[math.cos(half), 0.0, 0.0, math.sin(half)]])
    assert torch.allclose(heading_frame_velocity(yaw, torch.tensor([[1.0, 0.0, 0.0]])), torch.tensor([[1.0, 0.0]]),
                          atol=1e-6)
    pitch = torch.tensor([[math.cos(0.15), 0.0, math.sin(0.15), 0.0]])
    w1, v1, w2, v2 = yaw[:, :1], yaw[:, 1:], pitch[:, :1], pitch[:, 1:]
    both = torch.cat((w1 * w2 - (v1 * v2).sum(-1, keepdim=True), w1 * v2 + w2 * v1 + torch.linalg.cross(v1, v2)), -1)
    # Forward along the pitched pelvis x: horizontally cos(0.3) of it, still straight ahead in the heading frame.
    got = heading_frame_velocity(both, torch.tensor([[1.0, 0.0, 0.0]]))
    assert torch.allclose(got, torch.tensor([[math.cos(0.3), 0.0]]), atol=1e-6)


def test_the_tracking_window_is_one_reference_gait_cycle():
    from tocabi_torchrl.evaluation.gait_test import policy_dt
    from tocabi_torchrl.evaluation.robust import gait_cycle_steps
    from tocabi_torchrl.motion import ReferenceMotion

    period = ReferenceMotion.default().period
    assert period == pytest.approx(1.7995) and gait_cycle_steps(period, policy_dt()) == 450


def test_the_cycle_mean_error_sees_the_speed_not_the_sway():
    # A pelvis that walks 0.45 m/s forward and 0.03 m/s sideways on average, surging ±0.15 m/s twice per cycle and
    # swaying ±0.12 m/s once per cycle, under command (0.5, 0): its cycle-mean error is the average's, 0.058 m/s;
    # its instantaneous error is dominated by the sway.
    from tocabi_torchrl.evaluation.robust import CycleMeanTracking

    window, steps, n = 50, 400, 3
    tracker = CycleMeanTracking(n, window)
    command = torch.tensor([0.5, 0.0]).expand(n, 2)
    phase = torch.tensor([0.0, 1.0, 2.5])  # each robot's own phase in the cycle
    instant = []
    for k in range(steps):
        angle = 2 * math.pi * k / window + phase
        velocity = torch.stack((0.45 + 0.15 * torch.sin(2 * angle), 0.03 + 0.12 * torch.cos(angle)), -1)
        tracker.update(velocity, command, torch.ones(n, dtype=torch.bool))
        instant.append((velocity - command).norm(dim=-1))
    cycle_mean = tracker.per_env()
    torch.testing.assert_close(cycle_mean, torch.full((n,), math.hypot(0.05, 0.03)), atol=1e-6, rtol=0)
    assert torch.all(tracker.steps == steps - window + 1)
    assert torch.all(torch.stack(instant).mean(0) > 1.8 * cycle_mean)


def test_the_cycle_mean_tracking_example_runs():
    import doctest

    from tocabi_torchrl.evaluation import robust

    tests = doctest.DocTestFinder().find(robust.CycleMeanTracking, globs={"torch": torch, **vars(robust)})
    runner = doctest.DocTestRunner()
    for test in tests:
        runner.run(test)
    assert runner.summarize(verbose=False).attempted > 0 and runner.summarize(verbose=False).failed == 0


def test_a_robot_that_falls_within_its_first_cycle_has_no_cycle_mean_error():
    from tocabi_torchrl.evaluation.robust import CycleMeanTracking

    window = 10
    falls_at = torch.tensor([5, 25, 10**6])  # within the first window, after it, never (alive until the first fall)
    tracker = CycleMeanTracking(3, window)
    for k in range(40):
        tracker.update(torch.full((3, 2), 0.3), torch.zeros(3, 2), k < falls_at)
    per_env = tracker.per_env()
    assert math.isnan(per_env[0]) and tracker.steps.tolist() == [0, 25 - window + 1, 40 - window + 1]
    torch.testing.assert_close(per_env[1:], torch.full((2,), math.hypot(0.3, 0.3)))
    # A robot alive again after a fall (an env that resets it) counts only after a whole window alive again.
    tracker = CycleMeanTracking(1, window)
    for k in range(40):
        tracker.update(torch.ones(1, 2), torch.zeros(1, 2), torch.tensor([k != 20]))
    assert tracker.steps.tolist() == [(20 - window + 1) + (40 - 21 - window + 1)]
    # A rollout shorter than a window gives no robot a value.
    tracker = CycleMeanTracking(2, window)
    for _ in range(window - 1):
        tracker.update(torch.ones(2, 2), torch.zeros(2, 2), torch.ones(2, dtype=torch.bool))
    assert torch.isnan(tracker.per_env()).all()


def test_the_rolling_means_are_the_direct_means():
    # 2,000 float32 steps of a random walk at a 10 m/s offset (a hard case for a rolling float32 sum), window 450:
    # at every step the rolling means equal the float64 means of the last 450 values, and the per-robot result
    # equals the directly computed mean error.
    from tocabi_torchrl.evaluation.robust import CycleMeanTracking

    gen = torch.Generator().manual_seed(0)
    window, steps, n = 450, 2000, 4
    vel = (10.0 + 0.3 * torch.randn(steps, n, 2, generator=gen)).float()
    cmd = torch.rand(steps, n, 2, generator=gen).float()
    alive = torch.ones(steps, n, dtype=torch.bool)
    alive[1500:, 1] = False  # one robot falls at step 1,500
    tracker = CycleMeanTracking(n, window)
    worst = 0.0
    for k in range(steps):
        tracker.update(vel[k], cmd[k], alive[k])
        lo = max(0, k + 1 - window)
        worst = max(worst, float((tracker.mean_velocity() - vel[lo:k + 1].double().mean(0)).abs().max()),
                    float((tracker.mean_command() - cmd[lo:k + 1].double().mean(0)).abs().max()))
    assert worst < 1e-12
    windows = vel.double().unfold(0, window, 1).mean(-1) - cmd.double().unfold(0, window, 1).mean(-1)  # (T-W+1, N, 2)
    errors = windows.norm(dim=-1)
    direct = torch.stack((errors[:, 0].mean(), errors[:1500 - window + 1, 1].mean(), errors[:, 2].mean(),
                          errors[:, 3].mean())).float()
    torch.testing.assert_close(tracker.per_env(), direct, atol=1e-6, rtol=0)


@pytest.mark.parametrize("mode", ["pd_reference", "torque"])
def test_case_configs_hold_what_each_case_says(mode):
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.evaluation.robust import EVAL_SEED, case_config
    from tocabi_torchrl.randomize import TOCABI_LAB_ACTUATORS, TOCABI_LAB_DYNAMICS

    cfg = preset_config("cpu_smoke", **{"env.control.mode": mode})
    nominal, commands, pushed = (case_config(cfg, name) for name in ("nominal", "commands", "robust_1.0"))
    for case in (nominal, commands, pushed):
        case.validate()
        assert case.seed == EVAL_SEED and case.env.task.start_joint_vel_std == 0.5
        assert case.env.task.start_base_vel_std == 0.1
    assert nominal.env.command.vx_range == (0.5, 0.5) and nominal.env.command.vy_range == (0.0, 0.0)
    assert nominal.env.pushes.count == 0 and nominal.env.dynamics == cfg.env.dynamics
    assert commands.env.command.resample_every == 500 and commands.env.command.vx_range == (0.0, 0.7)
    assert pushed.env.pushes.count == 3 and pushed.env.pushes.speed == (1.0, 1.0)
    assert pushed.env.pushes.window == (2.0, 7.0) and pushed.env.pushes.duration == (0.004, 0.004)
    assert pushed.env.dynamics == TOCABI_LAB_DYNAMICS and pushed.transforms.sensor_noise.enabled
    assert pushed.env.control.actuators == (TOCABI_LAB_ACTUATORS if mode == "torque" else cfg.env.control.actuators)


def test_every_case_starts_from_the_ideal_robot_whatever_the_policy_trained_under():
    # A robust-preset policy trained with kicks, randomisation and sensor noise: nominal and commands test the
    # nominal robot without them; the randomised cases add the test's own set and kicks.
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.evaluation.robust import batch_config, case_config

    trained = preset_config("robust")
    for name in ("nominal", "commands"):
        cfg = case_config(trained, name)
        assert cfg.env.pushes.count == 0 and not cfg.env.dynamics.enabled
        assert cfg.env.control.actuators.ideal and not cfg.transforms.sensor_noise.enabled
    pushed = case_config(trained, "robust_1.0")
    assert pushed.env.pushes.count == 3 and pushed.env.pushes.speed == (1.0, 1.0)
    assert pushed.env.dynamics.enabled and pushed.transforms.sensor_noise.enabled
    # A delay trained on a coarser grid (env.control.actuators.delay_stride) is tested on the lab's every substep,
    from tocabi_torchrl.randomize import TOCABI_LAB_ACTUATORS
    from tocabi_torchrl.tree import replace_paths

    grid = replace_paths(trained, {"env.control.actuators.delay_stride": 8})
    assert case_config(grid, "robust_0.5").env.control.actuators == TOCABI_LAB_ACTUATORS
    assert TOCABI_LAB_ACTUATORS.delay_stride == 1
    # So is one trained on the delay's mean over each step (env.control.actuators.delay_average).
    averaged = replace_paths(trained, {"env.control.actuators.delay_average": True})
    tested = case_config(averaged, "robust_1.0").env.control.actuators
    assert tested == TOCABI_LAB_ACTUATORS and not tested.delay_average
    assert tested.build(8).per_substep
    # And one trained with the Newton solver capped (env.sim.solver_iterations) meets the model's own solver.
    capped = replace_paths(trained, {"env.sim.solver_iterations": 4})
    for name in ("nominal", "commands", "robust_0.5", "robust_1.0"):
        assert case_config(capped, name).env.sim.solver_iterations is None
    assert batch_config(capped).env.sim.solver_iterations is None


def test_the_standard_test_runs_on_the_nominal_robot_whatever_the_policy_trained_under(tmp_path, monkeypatch):
    # The standard test built the env of the checkpoint's own config: the shipped robust policy met its training's
    # 16 kicks, draws and sensor noise, drifted 0.86 m and "did not walk yet"; at rest on the nominal robot, 0.10 m.
    from tocabi_torchrl.adapters import evaluate as adapters_evaluate
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.evaluation import gait_test
    from tocabi_torchrl.evaluation.record import nominal_config
    from tocabi_torchrl.transforms import SensorNoise
    from tocabi_torchrl.tree import replace_paths

    robust = Path(SHIPPED_POLICY).with_name("tocabi_walk_robust.pt")
    if not robust.is_file():
        pytest.skip("the shipped robust policy is not present")
    built = []
    monkeypatch.setattr(gait_test, "evaluate_policy", lambda actor, cfg, out, **k: built.append(k["env"]) or {})
    gait_test.evaluate_run(robust, num_envs=2, device="cpu", seconds=0.1, out_dir=tmp_path / "eval")
    base = built[0].base_env
    assert base.cfg.pushes.count == 0 and not base.cfg.dynamics.enabled and base.cfg.control.actuators.ideal
    assert not base.cfg.task.diverse_starts and base.cfg.sim.start_pool == 0
    assert not any(isinstance(t, SensorNoise) for t in built[0].transform)
    capped = nominal_config(replace_paths(preset_config("robust"), {"env.sim.solver_iterations": 4}))
    assert capped.env.sim.solver_iterations is None and not capped.transforms.sensor_noise.enabled
    seen = []  # the library recipes' test too
    monkeypatch.setattr(adapters_evaluate, "evaluate_policy", lambda actor, cfg, out, **k: seen.append(cfg) or {})
    monkeypatch.setattr(adapters_evaluate, "gait_passes", lambda summary: False)
    adapters_evaluate.evaluate_actions(lambda obs: obs[:, :13], tmp_path / "a", preset="robust", num_envs=2,
                                       device="cpu")
    assert seen[0].env.pushes.count == 0 and not seen[0].transforms.sensor_noise.enabled


def test_bad_case_lists_are_named():
    # A single name as a string was read as its letters: "unknown robust-test case(s) ['n', 'o', ...]".
    from tocabi_torchrl.evaluation.robust import RobustTestConfig

    for cases, message in (("nominal", "cases must be a tuple of case names, e.g. \\('nominal',\\)"),
                           (("robust_1.0", "nominal"), "must be distinct and in the test's order"),
                           (("nominl",), r"unknown robust-test case\(s\) \['nominl'\]")):
        with pytest.raises(ValueError, match=message):
            RobustTestConfig(cases=cases).validate(0.004)
    from tocabi_torchrl.evaluation.robust import evaluate_robust_run

    with pytest.raises(ValueError, match="got the string 'nominal'"):  # split into letters before the check
        evaluate_robust_run(SHIPPED_POLICY, num_envs=2, seconds=0.1, cases="nominal")
    with pytest.raises(ValueError, match=r"unknown robust-test case\(s\) \(none given\)"):  # once: all four
        evaluate_robust_run(SHIPPED_POLICY, num_envs=2, seconds=0.1, cases=[])


def test_bad_test_settings_are_named_before_anything_is_built():
    # A float seed ran as int(seed) while the report kept 1.5; a bad kick count, window or start std failed in the
    # env's build under a path the caller never set (push_count -1: "env.pushes.count must be an int in [0, 64]").
    from tocabi_torchrl.evaluation.robust import RobustTestConfig

    for setting, message in (({"seed": 1.5}, r"seed must be an int in \[0, 2\*\*63 - 1\]"),
                             ({"push_count": -1}, r"push_count must be an int in \[1, 64\]"),
                             ({"push_count": 2.0}, "push_count must be an int"),
                             ({"push_window": (7.0, 2.0)}, r"push_window must be \(start, end\)"),
                             ({"push_window": (2.0,)}, "push_window must be"),
                             ({"push_window": (-1.0, 2.0)}, "push_window must be"),
                             ({"start_joint_vel_std": -0.5}, "start_joint_vel_std must be a finite number >= 0"),
                             ({"start_base_vel_std": float("nan")}, "start_base_vel_std must be a finite number")):
        with pytest.raises(ValueError, match=message):
            RobustTestConfig(**setting).validate(0.004)
    RobustTestConfig(seconds=1.0).validate(0.004)  # a quick check keeps the test's window (2, 7) s


def test_a_quick_check_of_a_short_episode_policy_keeps_its_kicks_in_the_episode():
    # A policy trained on 4 s episodes, checked for 2 s: the kicks keep the test's (2, 7) s window, and the env
    # refused a window past its episode's end.
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.evaluation.robust import RobustTestConfig, batch_env, case_config

    cfg = preset_config("cpu_smoke")
    cfg.env.task.max_episode_steps = 1000
    test = RobustTestConfig(num_envs=1, seconds=2.0)
    assert case_config(cfg, "robust_1.0", test).env.task.max_episode_steps >= 7.0 / 0.004
    env = batch_env(cfg, "cpu", test)
    assert env.batch_size.numel() == 4


def test_the_env_cache_keeps_one_env_per_kind_of_policy():
    # The key was the test's size and cases alone: a PD policy tested after a torque one ran in the torque env and
    # fell in every case.
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.evaluation.robust import RobustTestConfig, batch_key

    test = RobustTestConfig(num_envs=2, seconds=1.0)
    torque, pd = preset_config("torque_ideal"), preset_config("default")
    assert batch_key(test, torque, "cpu") != batch_key(test, pd, "cpu")
    same = preset_config("torque_ideal", **{"ppo.lr": 1e-3})
    assert batch_key(test, torque, "cpu") == batch_key(test, same, torch.device("cpu"))  # same env
    privileged = preset_config("torque_ideal", **{"ppo.critic_privileged": True})
    assert batch_key(test, torque, "cpu") != batch_key(test, privileged, "cpu")


def test_the_env_cache_keeps_one_env_per_device(monkeypatch):
    # The key held no device: a cache shared by tests on two devices handed the first device's env to the second.
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.evaluation.robust import RobustTestConfig, batch_key

    test, cfg = RobustTestConfig(num_envs=2, seconds=1.0), preset_config("torque_ideal")
    assert batch_key(test, cfg, "cpu") != batch_key(test, cfg, "cuda:0")
    assert batch_key(test, cfg, "cuda:0") != batch_key(test, cfg, "cuda:1")
    assert batch_key(test, cfg, "cuda:1") == batch_key(test, cfg, torch.device("cuda", 1))
    # "cuda" is the current GPU: the same key as its index, not a second large env for the same card.
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 1)
    assert batch_key(test, cfg, "cuda") == batch_key(test, cfg, "cuda:1")


def test_saved_normaliser_statistics_follow_their_transform_when_sensor_noise_shifts_the_chain():
    from tocabi_torchrl import make_env
    from tocabi_torchrl.rl.checkpoint import align_transform_state
    from tocabi_torchrl.transforms import SensorNoiseConfig

    trained = make_env(num_envs=1, device="cpu", normalization="running").transform.state_dict()
    noisy = make_env(num_envs=1, device="cpu", normalization="running",
                     sensor_noise=SensorNoiseConfig.tocabi_lab()).transform.state_dict()
    trained = {k: v + 1.0 if k.endswith(("mean", "var", "count")) else v for k, v in trained.items()}
    moved = align_transform_state(trained, noisy)
    assert set(moved) == set(noisy)
    for name in ("mean", "var", "count"):
        src = next(v for k, v in trained.items() if k.endswith(name))
        dst = next(v for k, v in moved.items() if k.endswith(name))
        assert torch.equal(src, dst)
    # a transform the chain no longer has is left out, not loaded into another one
    assert align_transform_state({"transforms.9.other": torch.zeros(1), **trained}, noisy).keys() == noisy.keys()


def test_a_push_ramp_that_is_a_step_does_not_divide_by_zero():
    from tocabi_torchrl.rl.trainer import push_scale

    assert [push_scale((1000, 1000), s) for s in (0, 999, 1000)] == [0.0, 0.0, 1.0]


def test_the_captured_path_gives_the_eager_path_numbers():
    """run_case through ``step_and_maybe_reset`` (how a captured CUDA graph steps on the GPU: fallen robots are reset
    and walk on) gives the numbers of the eager ``env.step`` (fallen robots lie where they fell). Actions pinned at
    +1 topple the robots within the case, so resets happen on the first path."""
    from tocabi_torchrl.config import preset_tree
    from tocabi_torchrl.evaluation.robust import RobustTestConfig, case_config, run_case
    from tocabi_torchrl.rl.trainer import build_env

    test = RobustTestConfig(num_envs=6, seconds=1.2)
    cfg = case_config(preset_tree("torque_ideal"), "robust_1.0", test)
    env = build_env(cfg, torch.device("cpu"), num_envs=6, sync_free_resets=True)

    def actor(td):
        return td.set("action", torch.ones(td.batch_size[0], env.action_spec.shape[-1]))

    out = {}
    for autoreset in (False, True):
        env.set_seed(test.seed)
        out[autoreset] = run_case(actor, env, test.seconds, progress=False, autoreset=autoreset)
    eager, captured = out[False], out[True]
    assert not eager["alive"].all(), "the pinned actions should topple some robots (else no reset is exercised)"
    # How far each robot turned, frozen at its fall: finite (every robot had alive steps), not all 0 (they topple).
    assert torch.isfinite(eager["heading_change_rad"]).all() and eager["heading_change_rad"].max() > 0
    for key, value in eager.items():
        torch.testing.assert_close(captured[key], value, equal_nan=True, msg=key)


def _batch(num_envs: int = 3):
    from tocabi_torchrl.config import preset_tree
    from tocabi_torchrl.evaluation.robust import RobustTestConfig, batch_env

    test = RobustTestConfig(num_envs=num_envs, seconds=0.2)
    cfg = preset_tree("torque_ideal")
    return cfg, test, batch_env(cfg, "cpu", test)


def test_one_batch_holds_each_case_in_its_own_worlds():
    """The batch env gives each case's worlds what the case says: the robust cases' worlds their own dynamics,
    actuator and sensor draws and kicks of their speed; the nominal and commands worlds the ideal robot, no kicks,
    exact sensors; the nominal worlds the fixed command."""
    from tocabi_torchrl.evaluation.robust import case_worlds

    _, test, env = _batch()
    env.set_seed(test.seed)
    td = env.reset()
    base, rows = env.base_env, case_worlds(test)
    mass = base.dynamics.mass_scale[:, 1:]
    delay = base.leg_actuators.stages[0].delay if hasattr(base.leg_actuators.stages[0], "delay") else None
    for name in ("nominal", "commands"):
        assert torch.all(mass[rows[name]] == 1.0), name
        assert torch.all(base.pushes.world_scale[rows[name]] == 0.0), name
        assert not base.randomized_worlds[rows[name]].any()
    for name, speed in (("robust_0.5", 0.5), ("robust_1.0", 1.0)):
        assert torch.all(mass[rows[name]] != 1.0), name
        torch.testing.assert_close(base.pushes.world_scale[rows[name]], torch.full((test.num_envs,), speed))
        assert base.randomized_worlds[rows[name]].all()
    if delay is not None:
        assert torch.all(delay[rows["nominal"]] == 0) and torch.all(delay[rows["robust_0.5"]] >= 4)
    scales = [s for s in base.leg_actuators.stages if type(s).__name__ == "MotorConstant"]
    for stage in scales:
        assert torch.all(stage.scale[rows["commands"]] == 1.0) and torch.all(stage.scale[rows["robust_1.0"]] != 1.0)
    command = td["command"]
    torch.testing.assert_close(command[rows["nominal"]], torch.tensor([[0.5, 0.0]]).expand(test.num_envs, 2))
    assert command[rows["commands"]].std(0).sum() > 0, "the commands case's worlds draw their own commands"
    noise = next(t for t in env.transform if type(t).__name__ == "SensorNoise")
    assert noise._worlds is not None and torch.equal(noise._worlds.squeeze(-1), base.randomized_worlds)


def test_the_nominal_worlds_of_the_batch_are_the_nominal_case_env():
    """No draw of the randomised worlds reaches an ideal one: the nominal case's worlds of the batch env (worlds
    0..n-1, keyed like the nominal case's own env) follow its own env's trajectories exactly."""
    from tocabi_torchrl.evaluation.robust import case_env, case_worlds, run_case

    cfg, test, env = _batch()
    alone = case_env(cfg, "nominal", "cpu", test.num_envs, test)

    def actor(td):
        return td.set("action", 0.3 * torch.ones(td.batch_size[0], env.action_spec.shape[-1]))

    results = []
    for e in (env, alone):
        e.set_seed(test.seed)
        results.append(run_case(actor, e, test.seconds, progress=False))
    batch, single = results
    rows = case_worlds(test)["nominal"]
    for key, value in single.items():
        torch.testing.assert_close(batch[key][rows], value, equal_nan=True, atol=1e-6, rtol=0, msg=key)


def test_a_pinned_command_survives_resampling():
    """VelocityCommand.pin: the pinned envs keep their command through resets and resamples; the others draw."""
    from tocabi_torchrl.envs.command import VelocityCommand
    from tocabi_torchrl.envs.command_config import CommandConfig

    gen = torch.Generator().manual_seed(0)
    cmd = VelocityCommand(CommandConfig(resample_every=2), 6, torch.device("cpu"), gen)
    pinned = torch.tensor([True, False, True, False, False, False])
    cmd.pin(pinned, (0.4, -0.1))
    cmd.reset(torch.ones(6, dtype=torch.bool))
    seen = []
    for step in range(40):
        cmd.update(torch.full((6,), step, dtype=torch.int64))
        seen.append(cmd.value.clone())
    seen = torch.stack(seen)
    torch.testing.assert_close(seen[:, pinned], torch.tensor([0.4, -0.1]).expand(40, 2, 2))
    assert seen[:, ~pinned].std(0).min() > 0


def test_set_randomized_worlds_refuses_a_wrong_mask():
    from tocabi_torchrl import make_env

    env = make_env(num_envs=2, device="cpu", seed=0)
    with pytest.raises(ValueError, match=r"\(2,\) bool tensor"):
        env.base_env.set_randomized_worlds(torch.tensor([1, 0]))
    with pytest.raises(ValueError, match=r"\(2,\) bool tensor"):
        env.base_env.set_randomized_worlds(torch.tensor([True, False, True]))


@needs_policy
def test_checkpoint_case_gives_the_shipped_policy_in_a_case_env_seeded_for_the_test():
    """robust.checkpoint_case: the checkpoint as read, its config, the case's env (the test's seed, the nominal
    command pinned, no start pool) and the agent holding the checkpoint's weights; run_case rolls it out."""
    from tocabi_torchrl.evaluation import robust
    from tocabi_torchrl.rl.checkpoint import read_checkpoint

    test = robust.RobustTestConfig(num_envs=2, seconds=0.2)
    state, cfg, env, agent = robust.checkpoint_case(SHIPPED_POLICY, "nominal", "cpu", test)
    saved = read_checkpoint(SHIPPED_POLICY)
    assert state["env_steps"] == saved["env_steps"] and cfg.env.control.mode == "pd_reference"
    assert env.num_envs == 2 and env.base_env._seed == robust.EVAL_SEED and env.base_env._pool == 0
    actor = agent.actor.state_dict()
    assert all(torch.equal(actor[k], v) for k, v in saved["agent"]["actor"].items())
    per_env = robust.run_case(agent.actor, env, test.seconds, progress=False)
    assert bool(per_env["alive"].all())  # the shipped policy stands through 0.2 s


@needs_policy
def test_checkpoint_case_as_trained_acts_with_the_assist_its_training_had(tmp_path):
    """A torque-assisted run's checkpoint, as_trained: the case env has the assist at β(env steps) of the run's
    schedule (here a copy of the shipped torque checkpoint as if saved mid-fade); by default its legs are pure
    torque."""
    from tocabi_torchrl.evaluation import robust
    from tocabi_torchrl.rl.assist import AssistSchedule

    saved = torch.load(REPO / "assets" / "policies" / "tocabi_walk_torque.pt", map_location="cpu", weights_only=True)
    saved["env_steps"] = 80_000_000  # the preset fades from 50 M to 110 M env steps
    path = tmp_path / "mid_fade.pt"
    torch.save(saved, path)
    test = robust.RobustTestConfig(num_envs=2, seconds=0.1)
    _, cfg, env, _ = robust.checkpoint_case(path, "robust_1.0", "cpu", test, as_trained=True)
    beta = float(env.base_env.assist_scale)
    ratio = float((env.base_env.assist_gain(1.0) / env.base_env.assist_gain(0.0)).log().mean().exp())
    expected = AssistSchedule(cfg.ppo.torque_assist, cfg.ppo.assist_fade_start, cfg.ppo.assist_fade_end, ratio)
    assert 0 < beta < 1 and beta == pytest.approx(expected(80_000_000))
    _, _, plain, _ = robust.checkpoint_case(path, "robust_1.0", "cpu", test)
    assert plain.base_env.assist_scale is None and plain.base_env.pushes.cfg.kind == "velocity"
    _, _, forced, _ = robust.checkpoint_case(path, "robust_1.0", "cpu", robust.RobustTestConfig(
        num_envs=2, seconds=0.1, push_kind="force"))
    assert forced.base_env.pushes.cfg.kind == "force"
    with pytest.raises(ValueError, match="push_kind"):
        robust.RobustTestConfig(push_kind="impulse").validate(0.004)


@needs_policy
def test_checkpoint_case_with_train_solver_runs_the_cap_the_run_trained_with(tmp_path):
    """A run trained with the Newton solver capped (here a copy of the shipped torque checkpoint saved as if capped
    at 4 iterations): its case runs the model's 20 iterations, as every test does, and the cap only with
    train_solver; a run without a cap keeps the model's solver either way."""
    from tocabi_torchrl.evaluation import robust

    saved = torch.load(REPO / "assets" / "policies" / "tocabi_walk_torque.pt", map_location="cpu", weights_only=True)
    saved["config"]["env"]["sim"]["solver_iterations"] = 4
    path = tmp_path / "capped.pt"
    torch.save(saved, path)
    test = robust.RobustTestConfig(num_envs=2, seconds=0.1)
    _, cfg, tested, _ = robust.checkpoint_case(path, "nominal", "cpu", test)
    _, _, as_trained, _ = robust.checkpoint_case(path, "nominal", "cpu", test, train_solver=True)
    assert cfg.env.sim.solver_iterations == 4
    assert tested.base_env.sim.mj_model.opt.iterations == 20
    assert as_trained.base_env.sim.mj_model.opt.iterations == 4
    plain = REPO / "assets" / "policies" / "tocabi_walk_torque.pt"
    _, _, uncapped, _ = robust.checkpoint_case(plain, "nominal", "cpu", test, train_solver=True)
    assert uncapped.base_env.sim.mj_model.opt.iterations == 20


def test_cases_run_once_each_in_the_test_order_and_a_subset_is_judged_on_its_cases():
    # A case's robots are a block of world indices whose draws are hashed by index: out of order or twice, a case
    # would meet other robots (or none) than in the whole test.
    from tocabi_torchrl.evaluation.robust import RobustTestConfig, robust_passes

    for cases, message in ((("nominal", "nominal"), "distinct"), (("commands", "nominal"), "in the test's order")):
        with pytest.raises(ValueError, match=message):
            RobustTestConfig(cases=cases).validate(0.004)
    from tocabi_torchrl.evaluation.robust import evaluate_robust_run

    with pytest.raises(ValueError, match="got the string 'nominal'"):  # split into letters before the check
        evaluate_robust_run(SHIPPED_POLICY, num_envs=2, seconds=0.1, cases="nominal")
    RobustTestConfig(cases=("nominal", "commands")).validate(0.004)
    report = {"cases": {"nominal": {"survival": 1.0, "forward_distance_m": {"mean": 3.0},
                                    "lateral_drift_m": {"p95": 0.1}}}}
    assert robust_passes(report, ("nominal",)) and not robust_passes(report)
    with pytest.raises(ValueError, match="no cases to judge"):
        robust_passes(report, ())


def test_the_unperturbed_cases_alone_give_the_numbers_of_the_whole_test(tmp_path):
    # time_to_walk --test diverse runs nominal and commands alone, or reads them from a four-case report: the same
    # robots, the same values either way, up to float32 rounding (the four-case batch env also builds the pushed
    # cases' machinery, which these worlds pass through as identities).
    from tocabi_torchrl import robot
    from tocabi_torchrl.evaluation.robust import evaluate_robust_run

    policy = robot.asset_path("policies", "tocabi_walk_torque.pt")
    if not policy.is_file():
        pytest.skip("shipped policy not present")
    run = lambda out, cases: evaluate_robust_run(policy, num_envs=2, device="cpu", out_dir=tmp_path / out,
                                                 seconds=0.5, cases=cases, progress=False)
    whole, alone = run("whole", None), run("alone", ["commands", "nominal"])  # any order given: the test's order
    assert list(alone["cases"]) == ["nominal", "commands"]
    for case in ("nominal", "commands"):
        for key in ("survival", "forward_distance_m", "lateral_drift_m", "tracking_error_mps"):
            a, b = alone["cases"][case][key], whole["cases"][case][key]
            assert a == pytest.approx(b, rel=1e-5, abs=1e-6, nan_ok=True), (case, key)


def test_the_gait_tests_refuse_an_env_whose_running_normaliser_never_saw_a_step(tmp_path):
    # An env built from a running-normalisation run's config starts with the normaliser's initial statistics, not
    # the checkpoint's: the standard test's numbers of such a policy came out wrong (0.00 survival against 0.25 on
    # the checkpoint's env) without a word.
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.evaluation.gait_test import evaluate_policy
    from tocabi_torchrl.evaluation.record import fixed_command, nominal_config
    from tocabi_torchrl.evaluation.robust import RobustTestConfig, evaluate_robust
    from tocabi_torchrl.rl.trainer import build_agent, build_env

    cfg = preset_config("cpu_smoke", device="cpu", **{"transforms.normalization": "running"})
    agent = build_agent(cfg, 237, 13, torch.device("cpu"))
    with pytest.raises(ValueError, match="starting statistics, not the checkpoint's.*nominal=True"):
        evaluate_policy(agent.actor, nominal_config(cfg), tmp_path / "a", num_envs=2, device="cpu", seconds=0.1,
                        video_envs=0, progress=False)
    test = RobustTestConfig(num_envs=1, seconds=0.1, cases=("nominal",))
    with pytest.raises(ValueError, match="starting statistics"):
        evaluate_robust(agent.actor, cfg, tmp_path / "b", test=test, device="cpu", progress=False)
    env = build_env(nominal_config(cfg), torch.device("cpu"), num_envs=2, command=fixed_command((0.5, 0.0)))
    env.rollout(2, agent.actor)  # statistics that have seen steps, as a trained policy's have
    summary = evaluate_policy(agent.actor, cfg, tmp_path / "c", device="cpu", seconds=0.1, video_envs=0, env=env,
                              progress=False)
    assert summary["seconds"] == 0.1


def test_a_test_length_under_one_policy_step_is_refused_as_its_message_says():
    from tocabi_torchrl.evaluation.record import policy_steps

    with pytest.raises(ValueError, match="pass at least 0.004"):
        policy_steps(0.003, 0.004)  # rounded up to one 4 ms step before
    assert policy_steps(0.004, 0.004) == 1 and policy_steps(8.0, 0.004) == 2000


def test_the_gait_tests_check_device_and_out_folder_before_building_or_making_anything(tmp_path, monkeypatch):
    # On a CPU-only machine the default device ("cuda") ended in torch's "not compiled with CUDA" and left an empty
    # folder; "auto" was refused; an out_dir that is a file failed after the env was built.
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.evaluation import gait_test, robust
    from tocabi_torchrl.rl.trainer import build_agent

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    cfg = preset_config("cpu_smoke", device="cpu")
    agent = build_agent(cfg, 237, 13, torch.device("cpu"))
    test = robust.RobustTestConfig(num_envs=1, seconds=0.1, cases=("nominal",))
    with pytest.raises(RuntimeError, match="pass device='cpu'"):
        robust.evaluate_robust(agent.actor, cfg, tmp_path / "r", test=test, device="cuda", progress=False)
    with pytest.raises(RuntimeError, match="pass device='cpu'"):
        gait_test.evaluate_policy(agent.actor, cfg, tmp_path / "g", num_envs=1, device="cuda", progress=False)
    assert not (tmp_path / "r").exists() and not (tmp_path / "g").exists()
    summary = gait_test.evaluate_policy(agent.actor, cfg, tmp_path / "a", num_envs=1, device="auto", seconds=0.1,
                                        video_envs=0, progress=False)
    assert summary["seconds"] == 0.1
    (tmp_path / "f").write_text("")
    monkeypatch.setattr(gait_test, "load_policy", lambda *a, **k: pytest.fail("built before the checks"))
    policy = Path(__file__).resolve().parents[1] / "assets" / "policies" / "tocabi_walk_ppo.pt"
    with pytest.raises(ValueError, match="is a file, not a folder"):
        gait_test.evaluate_run(policy, num_envs=1, device="cpu", out_dir=tmp_path / "f")
    with pytest.raises(ValueError, match="video_envs must be an int >= 0"):
        gait_test.evaluate_run(policy, num_envs=1, device="cpu", out_dir=tmp_path / "v", video_envs=-1)


def test_the_gait_tests_judge_falls_by_the_tasks_rules_whatever_the_policy_trained_with():
    # The fall rules came from the tested policy's own config: a policy trained with a lower pelvis limit or without
    # the contact terminations was judged by them, and survived falls every other policy failed on.
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.envs.config import TaskConfig
    from tocabi_torchrl.evaluation.record import FALL_RULES, nominal_config
    from tocabi_torchrl.evaluation.robust import CASES, case_config
    from tocabi_torchrl.tree import replace_paths

    loose = {"env.task.min_pelvis_height": 0.3, "env.task.min_neck_height": 0.4, "env.task.max_neck_angle": 2.5,
             "env.task.terminate_on_forbidden_contact": False, "env.task.terminate_on_self_collision": False}
    cfg = replace_paths(preset_config("robust"), loose)
    assert all(getattr(cfg.env.task, name) != getattr(TaskConfig, name) for name in FALL_RULES)
    for judged in (nominal_config(cfg), *(case_config(cfg, case) for case in CASES)):
        assert {name: getattr(judged.env.task, name) for name in FALL_RULES} == {
            name: getattr(TaskConfig, name) for name in FALL_RULES}


@needs_policy
def test_a_shared_test_env_gives_each_checkpoint_the_built_state_it_does_not_hold(tmp_path):
    """Checkpoints tested one after another in one cached env (``envs=``): transform state loads leniently, so a
    checkpoint without a buffer (here one saved without its env, ``save_checkpoint(..., env=None)``: no transform
    state) kept what the checkpoint before it had loaded (here fixed normaliser statistics of its own) instead of
    the value the env was built with, which a fresh env gives it."""
    from tocabi_torchrl.evaluation.robust import RobustTestConfig, evaluate_robust_checkpoint
    from tocabi_torchrl.rl.checkpoint import read_checkpoint
    from tocabi_torchrl.rl.symmetry import find_normalization
    from tocabi_torchrl.transforms.normalize import FixedNormalization

    saved = torch.load(REPO / "assets" / "policies" / "tocabi_walk_torque.pt", map_location="cpu", weights_only=True)
    own = {k: v + 1.0 if k.endswith((".loc", ".scale")) else v for k, v in saved["transforms"].items()}
    torch.save({**saved, "transforms": own}, tmp_path / "own_stats.pt")
    torch.save({**saved, "transforms": {}}, tmp_path / "no_env.pt")
    test = RobustTestConfig(num_envs=1, seconds=0.02, cases=("nominal",))
    envs: dict = {}
    for name in ("own_stats", "no_env"):
        path = tmp_path / f"{name}.pt"
        evaluate_robust_checkpoint(read_checkpoint(path), path, tmp_path / name, test=test, device="cpu", envs=envs,
                                   progress=False)
    (env,) = envs.values()
    norm, built = find_normalization(env), FixedNormalization()
    assert torch.equal(norm.loc, built.loc) and torch.equal(norm.scale, built.scale)
