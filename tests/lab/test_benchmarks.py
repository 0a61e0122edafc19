"""The benchmark harness on the CPU: every committed report regenerates from its JSON, and every benchmark runs end
to end at toy size (``--device cpu``); their GPU paths reuse the same helpers. Time to walk's runs are in
test_benchmarks_time_to_walk.py, the training benchmarks run in child processes and under torchrun in
test_benchmarks_training.py: the test run gives each file to one worker, and one file of all three kept one worker
busy for longer than the rest of the suite took on the other."""

from __future__ import annotations

import json
import re
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from lab.benchmarks import (
    common,
    env_throughput,
    mjlab_peer,
    overlap_probe,
    regenerate,
    scaling,
    soak,
    solver_load,
    step_timeline,
    time_to_walk,
    train_throughput,
    viewer_overhead,
    viewer_play,
)


@pytest.mark.parametrize("page", sorted(regenerate.REPORTS))
def test_committed_report_regenerates_from_its_json(page, tmp_path):
    pytest.importorskip("matplotlib")
    text = regenerate.regenerate(page, common.DOCS, tmp_path)
    assert text == (common.DOCS / page).read_text(), f"{page} differs from what its JSON renders"
    # the throughput tables (ours, and the mjlab peer's) are the only pages without a figure
    assert bool(list(tmp_path.rglob("*.png"))) == (regenerate.REPORTS[page][1] not in (train_throughput.render,
                                                                                      mjlab_peer.render,
                                                                                      viewer_play.render))


def test_regenerate_help_and_a_bad_page_write_nothing(monkeypatch, capsys):
    # --help was no option: it re-rendered every committed page.
    monkeypatch.setattr(regenerate, "regenerate", lambda *a, **k: pytest.fail("rendered a page"))
    with pytest.raises(SystemExit) as done:
        regenerate.main(["--help"])
    assert done.value.code == 0 and "pages under docs/benchmarks to render" in capsys.readouterr().out
    with pytest.raises(SystemExit) as done:
        regenerate.main(["nope.md"])
    assert done.value.code == 2 and "no such report page: nope.md" in capsys.readouterr().err


def test_unknown_override_is_named():
    with pytest.raises(SystemExit, match="no option 'cuda_grpah'"):
        common.parse_overrides(["cuda_grpah=on"])
    with pytest.raises(SystemExit, match="no option 'cuda_graph'.*dotted paths"):  # the flat names are gone
        common.parse_overrides(["cuda_graph=on"])
    assert common.parse_overrides(["ppo.cuda_graph=on", "ppo.actor_hidden=8 8", "total_env_steps=2e3"]) == {
        "ppo.cuda_graph": "on", "ppo.actor_hidden": (8, 8), "total_env_steps": 2000}


def test_a_set_path_given_twice_keeps_the_last_and_says_so(capsys):
    # --set ppo.lr=1e-4 ppo.lr=2e-4 kept 2e-4 without a word; a script may append overrides on purpose, so it is a
    # warning, not a refusal.
    got = common.parse_overrides(["ppo.lr=1e-4", "ppo.actor_hidden=8 8", "ppo.lr=2e-4", "ppo.lr=3e-4"])
    assert got == {"ppo.lr": 3e-4, "ppo.actor_hidden": (8, 8)}
    assert capsys.readouterr().err.splitlines() == [
        "warning: --set ppo.lr is given 3 times; the last applies: ppo.lr=3e-4"]
    common.parse_overrides(["ppo.lr=1e-4", "ppo.actor_hidden=8 8"])
    assert capsys.readouterr().err == ""


def test_a_set_value_splits_only_for_a_tuple_and_a_tuple_takes_commas():
    # Every value was split at spaces: JSON with spaces (as --help writes env.scene.obstacles) or a name with a space
    # broke into stray arguments, and a tuple written 4,20 (the committed reports' commands) did not parse.
    box = '[{"size": [0.3, 0.6, 0.012], "pos": [0.7, 0.1]}]'
    got = common.parse_overrides([f"env.scene.obstacles={box}", "name=my run", "env.task.motion=/tmp/a b.npz",
                                  "env.control.actuators.delay_substeps=4,20", "env.pushes.speed=(0.4, 1.4)",
                                  "ppo.actor_hidden=[64,32]", "ppo.critic_hidden=16 8", "loggers=csv,tensorboard"])
    assert [(b.size, b.pos) for b in got["env.scene.obstacles"]] == [((0.3, 0.6, 0.012), (0.7, 0.1))]
    assert (got["name"], got["env.task.motion"]) == ("my run", "/tmp/a b.npz")
    assert (got["env.control.actuators.delay_substeps"], got["env.pushes.speed"]) == ((4, 20), (0.4, 1.4))
    assert (got["ppo.actor_hidden"], got["ppo.critic_hidden"]) == ((64, 32), (16, 8))
    assert got["loggers"] == ("csv", "tensorboard")


def test_a_cpu_measurement_does_not_replace_the_published_gpu_reports(tmp_path, monkeypatch, capsys):
    # docs/benchmarks.md gives CPU commands whose default --out is docs/benchmarks: a report measured on the CPU goes
    # to runs/benchmarks_cpu instead. GPU results merged or re-rendered on a CPU machine (mjlab_peer's merge,
    # time_to_walk's report of runs copied back) still go where they are told.
    docs, cpu = tmp_path / "docs", tmp_path / "cpu"
    docs.mkdir()
    (docs / "env_throughput.json").write_text("published")
    monkeypatch.setattr(common, "DOCS", docs)
    monkeypatch.setattr(common, "CPU_OUT", cpu)
    common.publish(docs, "env_throughput", {"meta": {}, "results": []}, lambda data, out: "page", measured_on="cpu")
    assert (docs / "env_throughput.json").read_text() == "published" and not (docs / "env_throughput.md").exists()
    assert (cpu / "env_throughput.md").read_text() == "page" and "not " + str(docs) in capsys.readouterr().out
    for on in (None, "cuda", "cuda:1"):
        assert common.report_dir(docs, on) == docs
    assert common.report_dir(tmp_path / "elsewhere", "cpu") == tmp_path / "elsewhere"  # asked for: honoured
    # A folder inside the published results too (robust_policies' default, docs/benchmarks/robust).
    assert common.report_dir(docs / "robust", "cpu") == cpu / "robust"
    assert common.report_dir(docs / "robust", "cuda") == docs / "robust"
    # time_to_walk's report: runs trained on the GPU are published; CPU smoke runs are not, their curves neither.
    for gpu, expected in (("NVIDIA H100 80GB HBM3", docs), ("cpu", cpu)):
        run = tmp_path / f"run_{gpu[:3]}"
        run.mkdir()
        (run / "train.json").write_text(json.dumps({"preset": "cpu_smoke", "gpu": gpu}))
        monkeypatch.setattr(time_to_walk, "render", lambda data, out: "ttw")
        monkeypatch.setattr(time_to_walk, "plot_curves", lambda metrics, path: path.write_text("curves"))
        time_to_walk.report_part(SimpleNamespace(runs=[str(run)], out=str(docs), curves=["m.csv"]), "cmd")
        assert (expected / "time_to_walk.md").read_text() == "ttw" and (expected / "time_to_walk_curves.png").is_file()
    if torch.cuda.is_available():
        return
    for bad in (["--steps", "0"], ["--num_envs", "0"], []):  # [] asks for CUDA by default: named, not a traceback
        with pytest.raises(SystemExit):
            env_throughput.main([*bad, "--out", str(tmp_path / "x")])
        assert "error:" in capsys.readouterr().err


def test_env_throughput_smoke(tmp_path):
    env_throughput.main(["--device", "cpu", "--num_envs", "2", "--steps", "3", "--raw_steps", "0", "--out",
                         str(tmp_path)])
    (r,) = json.loads((tmp_path / "env_throughput.json").read_text())["results"]
    assert r["env_steps_per_s"] > 0 and r["make_env_steps_per_s"] > 0 and r["raw_policy_steps_per_s"] is None
    assert "| 2 | - |" in (tmp_path / "env_throughput.md").read_text()
    # The reset-pass A/B writes its own report beside it (warp's CPU device: the reduced pass is warp's).
    env_throughput.main(["--device", "cpu", "--backend", "warp", "--num_envs", "2", "--steps", "3", "--raw_steps",
                         "0", "--reset_pass", "reduced", "--name", "env_reduced", "--out", str(tmp_path)])
    (r,) = json.loads((tmp_path / "env_reduced.json").read_text())["results"]
    assert r["reset_pass"] == "reduced" and r["autoreset_steps_per_s"] > 0
    assert "env_reduced.png" in (tmp_path / "env_reduced.md").read_text()


def test_overlap_probe_runs_on_the_cpu_and_its_update_trains(tmp_path, capsys):
    # The probe's GPU question (two CUDA streams) has no CPU answer; on the CPU it runs serially end to end.
    data = overlap_probe.main(["--device", "cpu", "--num_envs", "2", "--repeats", "1", "--out", str(tmp_path)])
    (r,) = data["results"]
    assert r["policy_steps"] == 48 and r["update_steps"] == 5  # 5 epochs x one mini-batch of 2 x 48 frames
    assert min(r["physics_s"], r["update_s"], r["both_s"]) > 0
    assert r["hidden"] == pytest.approx((r["physics_s"] + r["update_s"] - r["both_s"]) / r["update_s"])
    assert "| 2 | 48 | 5 |" in (tmp_path / "overlap_probe.md").read_text()
    step, steps, params = overlap_probe.update_stand_in("default", 64, "cpu")
    assert steps == 5 and overlap_probe.update_stand_in("default", 4096, "cpu")[1] == 20  # 5 epochs x 4 of 49,152
    before = [p.detach().clone() for p in params]
    step()
    assert all(not torch.equal(b, p) for b, p in zip(before, params))  # every layer of both networks moved
    if torch.cuda.is_available():
        return
    with pytest.raises(SystemExit):
        overlap_probe.main(["--num_envs", "2", "--out", str(tmp_path)])  # cuda asked, none here: named, not a trace
    assert "--device cuda: torch sees no CUDA GPU here" in capsys.readouterr().err


def test_step_timeline_marks_every_phase_of_the_real_trainer(tmp_path, monkeypatch):
    # Off CUDA the marks are host clocks. The env is made sync-free, as GPU training's is, so that its masked reset
    # runs every step and every phase is marked.
    from tocabi_torchrl.rl import trainer

    originals = {k: getattr(trainer, k) for k in ("make_collector", "make_loss", "guard_rollout", "_update_stats")}
    build_env = trainer.build_env
    monkeypatch.setattr(trainer, "build_env",
                        lambda cfg, device, **kw: build_env(cfg, device, **{"sync_free_resets": True, **kw}))
    args = ["--device", "cpu", "--num_envs", "8", "--iterations", "2", "--warmup", "1", "--raw_steps", "0",
            "--out", str(tmp_path), "--run_dir", str(tmp_path / "runs"), "--set", "ppo.steps_per_env=8",
            "ppo.actor_hidden=8 8"]
    data = step_timeline.main(args)
    (r,) = data["results"]
    ms = r["ms_per_policy_step"]
    assert list(ms) == [*step_timeline.STEP_PHASES, *step_timeline.ITERATION_PHASES]
    assert all(v > 0 for v in ms.values()), ms  # each phase was marked, in the window of the 2 timed iterations
    assert r["step_ms"] == pytest.approx(sum(ms.values()))
    assert r["train_env_steps_per_s"] == pytest.approx(8e3 / r["step_ms"])
    assert "| masked reset: simulator |" in (tmp_path / "step_timeline.md").read_text()
    assert {k: getattr(trainer, k) for k in originals} == originals  # the trainer is itself again
    with pytest.raises(SystemExit, match="cuda_graph"):  # a captured step has no points to mark: named, not run
        step_timeline.main([*args, "cuda_graph=on"])


def test_solver_load_counts_the_trainer_and_the_raw_ceiling_on_warps_cpu(tmp_path, capsys):
    from warp_cpu import warp_cpu_available

    from tocabi_torchrl.rl import trainer

    if not warp_cpu_available():
        pytest.skip("warp's CPU device is not available here")
    originals = {k: getattr(trainer, k) for k in ("make_collector", "_update_stats")}
    args = ["--device", "cpu", "--num_envs", "4", "--iterations", "2", "--warmup", "1", "--raw_steps", "3",
            "--out", str(tmp_path), "--run_dir", str(tmp_path / "runs"), "--set", "ppo.steps_per_env=6",
            "ppo.actor_hidden=8 8"]
    (r,) = solver_load.main(args)["results"]
    train, raw = r["training"], r["standing (raw ceiling)"]
    assert r["overrides"]["env.sim.backend"] == "warp"  # the counts are mujoco-warp's, also on the CPU
    assert train["steps"] == 12 and raw["steps"] == 3  # the two timed iterations' steps, not the warm-up's
    for s in (train, raw):
        assert s["ms_per_policy_step"] > 0 and 1 <= s["niter_mean"] <= s["niter_max_over_worlds"] <= s["niter_max_seen"]
        assert s["constraint_rows_per_world"] > 0 and s["contacts_per_world"] >= 0
    # The standing worlds are identical copies: the slowest is the mean. The trainer's are not.
    assert raw["niter_max_over_worlds"] == pytest.approx(raw["niter_mean"])
    assert r["physics_ratio_standing_over_training"] == pytest.approx(raw["ms_per_policy_step"]
                                                                       / train["ms_per_policy_step"])
    assert "| standing (raw ceiling) |" in (tmp_path / "solver_load.md").read_text()
    assert {k: getattr(trainer, k) for k in originals} == originals  # the trainer is itself again

    # As another benchmark's child (randomization_cost --physics): one env count, reported as the RESULT line
    # common.run_child reads, nothing published.
    out = tmp_path / "child"
    child = solver_load.main(["--child", *args[:args.index("--iterations")], "--iterations", "1", "--warmup", "1",
                              "--raw_steps", "1", "--out", str(out), "--run_dir", str(tmp_path / "runs_child"),
                              "--set", "ppo.steps_per_env=6", "ppo.actor_hidden=8 8"])
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("RESULT ")]
    assert len(lines) == 1 and json.loads(lines[0][len("RESULT "):]) == json.loads(json.dumps(child["results"][0]))
    assert child["results"][0]["training"]["steps"] == 6 and not out.exists()


def test_step_timeline_puts_back_every_wrapper_and_hook_also_after_an_error(monkeypatch):
    from types import SimpleNamespace

    from tocabi_torchrl.rl import trainer

    class Env:  # the three methods the timeline wraps, on a class like the real env's
        def step_and_maybe_reset(self, td):
            return td

        def _reset(self, td):
            return td

    sim = SimpleNamespace(step=lambda: None, reset_to_start=lambda: None)  # instance attributes, as wrappers find
    env, actor = Env(), torch.nn.Linear(2, 2)
    env.base_env = SimpleNamespace(sim=sim)
    inner_step, inner_reset = sim.step, sim.reset_to_start
    monkeypatch.setattr(trainer, "make_collector", lambda cfg, env, actor, *a, **k: "collector")
    timeline = step_timeline.Timeline(torch.device("cpu"))
    with pytest.raises(RuntimeError, match="midway"), step_timeline.marked_trainer(timeline):
        assert trainer.make_collector(None, env, actor) == "collector"
        env.step_and_maybe_reset(None), actor(torch.zeros(2)), sim.step(), env._reset(None), sim.reset_to_start()
        assert [phase for phase, _ in timeline.marks] == [
            "env before the physics", "collector storage", "policy forward", "collector between policy and env",
            "physics (sim.step)", "signals, rewards, transforms, step_mdp", "masked reset: env before the simulator",
            "reset merge", "masked reset: simulator", "masked reset: observation"]
        raise RuntimeError("midway")
    assert trainer.make_collector(None, env, actor) == "collector"  # the trainer's own function again
    assert "step_and_maybe_reset" not in vars(env) and "_reset" not in vars(env) and sim.step is inner_step
    assert sim.reset_to_start is inner_reset
    assert not actor._forward_hooks and not actor._forward_pre_hooks
    n = len(timeline.marks)
    env.step_and_maybe_reset(None), actor(torch.zeros(2)), sim.step(), env._reset(None), sim.reset_to_start()
    assert len(timeline.marks) == n  # nothing marks any more


@pytest.fixture
def nothing_measured(tmp_path, monkeypatch):
    """Run in ``tmp_path`` with every measuring entry point (training, child runs, the soak's faults) failing the
    test if reached: refused arguments must stop before any of them."""
    def measured(*args, **kwargs):
        raise AssertionError("measured")

    monkeypatch.chdir(tmp_path)
    for module, name in ((common, "train"), (common, "run_child"), (soak, "run_faults")):
        monkeypatch.setattr(module, name, measured)


def test_a_zero_minute_time_limit_is_refused_not_read_as_no_limit(nothing_measured, capsys):
    # The config reads max_minutes 0 as no wall-clock limit: time_to_walk once trained far past its budget, the soak
    # for ever.
    for main, args in ((time_to_walk.main, ["train", "--preset", "cpu_smoke", "--device", "cpu", "--minutes", "0"]),
                       (soak.main, ["--device", "cpu", "--minutes", "0", "--out", "o"]),
                       (soak.main, ["--device", "cpu", "--minutes", "nan", "--out", "o"]),
                       (scaling.main, ["--backend", "cpu", "--max_minutes", "0", "--results", "s"])):
        with pytest.raises(SystemExit) as exit_:
            main(args)
        assert exit_.value.code == 2 and "minutes" in capsys.readouterr().err, args


def test_train_throughput_renders_a_raw_only_row_and_a_failed_render_replaces_nothing(tmp_path):
    # --iterations 0 --warmup 0 measures only the raw ceiling: its page once failed (KeyError) after its JSON had
    # replaced the report's, leaving the old page beside it.
    row = {"num_envs": 2, "gpus": 1, "overrides": {}, "device_used_at_start_gib": None, "device_name": "cpu",
           "raw_policy_steps_per_s": 1234.0, "ratio_train_over_raw": None}
    data = {"meta": {"gpu": "cpu", "date": "2026-12-01", "command": "c"}, "results": [row]}
    assert "| 2 | - | 1,234 | - | - | - | - |" in train_throughput.render(data, tmp_path)
    (tmp_path / "report.json").write_text("the published report")

    def render(data, out):
        raise KeyError("a field this page needs")

    with pytest.raises(KeyError):
        common.publish(tmp_path, "report", data, render)
    assert (tmp_path / "report.json").read_text() == "the published report"


def test_a_soak_shorter_than_its_memory_baseline_measures_no_growth():
    # The baseline is rollout 10's row; a shorter run once compared the end with itself: growth 0, a pass.
    row = lambda k, device=1.0: {"rollout": k, "device_used_gib": device, "host_rss_mib": 500.0}
    start, (device, rss) = soak.memory_checks([row(k) for k in range(1, 4)], (1.5, 600.0))  # a GPU run of 3 rollouts
    assert start == (None, None) and device[3] is False and rss[3] is True
    assert "not measured (the run ended at rollout 3, the baseline is rollout 10)" == device[1] == rss[1]
    _, (device, _) = soak.memory_checks([row(k, None) for k in range(1, 4)], (None, 600.0))  # the CPU has none
    assert device[1:] == ("n/a", "<= 1", True)
    start, (device, rss) = soak.memory_checks([row(k) for k in range(1, 12)], (1.005, 510.0))
    assert start == (1.0, 500.0) and device[1:] == ("0.50", "<= 1", True) and rss[1] == "2.0"


def test_bad_arguments_are_refused_in_one_line(nothing_measured, tmp_path, monkeypatch, capsys):
    # Each once ran on into a traceback (a division by zero, an unknown preset, no CUDA) or measured nothing silently.
    cpu = ["--device", "cpu", "--out", "o"]
    cases = [(scaling.main, ["--num_envs", "0", "--results", "s"]),
             (scaling.main, ["--backend", "cpu", "--redo", "partal", "--results", "s"]),
             (soak.main, [*cpu, "--fault_every", "0"]), (soak.main, [*cpu, "--num_envs", "0"]),
             (soak.main, [*cpu, "--preset", "bogus"]), (overlap_probe.main, [*cpu, "--preset", "bogus"]),
             (step_timeline.main, [*cpu, "--num_envs", "0"]), (solver_load.main, [*cpu, "--num_envs", "0"]),
             (train_throughput.main, [*cpu, "--num_envs", "0"])]
    if not torch.cuda.is_available():
        cases.append((train_throughput.main, ["--num_envs", "8", "--out", "o"]))  # --device cuda by default
    for main, args in cases:
        with pytest.raises(SystemExit) as exit_:
            main(args)
        assert exit_.value.code == 2 and "error:" in capsys.readouterr().err, args
    # An eval of a run folder that is not there (a misspelt --preset) once reported "time to walk: null" into it.
    with pytest.raises(SystemExit, match="runs/time_to_walk/torqeu: no such run folder"):
        time_to_walk.main(["eval", "--preset", "torqeu", "--device", "cpu"])
    assert not Path("runs").exists() and not Path("s").exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
@pytest.mark.parametrize("main, args", [
    (train_throughput.main, ["--num_envs", "8"]), (overlap_probe.main, []), (env_throughput.main, ["--steps", "1"]),
    (step_timeline.main, []), (solver_load.main, []), (time_to_walk.main, ["train", "--preset", "cpu_smoke"]),
    (viewer_overhead.main, [])], ids=lambda v: getattr(v, "__module__", "").rsplit(".", 1)[-1] or None)
def test_a_gpu_script_without_a_gpu_ends_in_one_line_naming_the_fix(main, args, nothing_measured, capsys):
    # Each once ran into a traceback from deep inside the env build; common.require_cuda says it before anything runs.
    with pytest.raises(SystemExit) as exit_:
        main([*args, "--device", "cuda", *(["--out", "o"] if main is not time_to_walk.main else [])])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and "--device cuda: torch sees no CUDA GPU here; " in err and "--device cpu" in err


def test_override_path():
    # a dotted config path with its value, checked against the config tree's choices
    from lab.benchmarks.common import parse_overrides
    from tocabi_torchrl.config import field_choices

    assert parse_overrides(["env.sim.reset_pass=reduced"]) == {"env.sim.reset_pass": "reduced"}
    assert field_choices()["env.sim.reset_pass"] == ("full", "reduced")


def test_robust_policies_table_names_each_case_and_its_verdict(tmp_path, capsys):
    """lab.benchmarks.robust_policies on the CPU (2 robots per case, 0.1 s): one row per policy and case, a ✗ on a
    missed threshold, each policy's own report beside the table."""
    import json

    from lab.benchmarks import robust_policies

    policy = robust_policies.POLICIES / "tocabi_walk_ppo.pt"
    if not policy.is_file():
        pytest.skip("shipped policy not present")
    robust_policies.main(["--policies", str(policy), "--num_envs", "2", "--seconds", "0.1", "--device", "cpu",
                          "--out", str(tmp_path)])
    # Strict JSON: a 0.1 s case has no tracking error (NaN), once written as a bare NaN token and shown as "nan".
    data = json.loads((tmp_path / "robust_policies.json").read_text(), parse_constant=lambda name: 1 / 0)
    (row,) = data["results"]
    assert row["cases"]["nominal"]["tracking_error_mps.mean"] is None
    assert row["policy"] == "tocabi_walk_ppo" and set(row["cases"]) == {"nominal", "commands", "robust_0.5",
                                                                         "robust_1.0"}
    assert row["passes"] is False  # 0.1 s cannot cover the 2.6 m the nominal case asks for
    page = (tmp_path / "robust_policies.md").read_text()
    assert "| tocabi_walk_ppo | nominal |" in page and "✗" in page and "python -m lab.benchmarks.robust_policies" in page
    assert "nan" not in page
    assert (tmp_path / "tocabi_walk_ppo" / "robust.json").is_file()
    assert "does not pass the robust test; " in page and "for its four cases" in page
    # A file that is no checkpoint is named before any policy runs (it once ended the call after those before it).
    (tmp_path / "notes.pt").write_text("not a checkpoint")
    with pytest.raises(SystemExit) as stop:
        robust_policies.main(["--policies", str(policy), str(tmp_path / "notes.pt"), "--device", "cpu", "--out",
                              str(tmp_path / "again")])
    assert stop.value.code == 2 and not (tmp_path / "again").exists()
    assert f"cannot read checkpoint {tmp_path / 'notes.pt'}" in capsys.readouterr().err


def test_robust_policies_builds_one_env_for_the_marks_of_a_run_and_each_gets_its_numbers_alone(tmp_path,
                                                                                                monkeypatch):
    """The marks of one run (one kind of policy) are tested in one env, built once (on the GPU its build and capture
    took longer than the test of a mark); each mark's report is the one it gets tested alone."""
    import json
    import shutil

    from lab.benchmarks import robust_policies
    from tocabi_torchrl.evaluation import robust

    policy = robust_policies.POLICIES / "tocabi_walk_robust.pt"
    if not policy.is_file():
        pytest.skip("shipped policy not present")
    marks = [tmp_path / f"mark_{i}.pt" for i in range(2)]
    for mark in marks:
        shutil.copyfile(policy, mark)
    built = []
    real = robust.batch_env
    monkeypatch.setattr(robust, "batch_env", lambda *a, **k: built.append(1) or real(*a, **k))
    argv = ["--num_envs", "2", "--seconds", "0.3", "--device", "cpu", "--cases", "nominal", "robust_1.0"]
    robust_policies.main(["--policies", *map(str, marks), *argv, "--out", str(tmp_path / "both")])
    assert len(built) == 1
    robust_policies.main(["--policies", str(marks[1]), *argv, "--out", str(tmp_path / "alone")])

    def cases(folder):
        return json.loads((folder / "robust.json").read_text())["cases"]

    assert cases(tmp_path / "both" / "mark_1") == cases(tmp_path / "alone" / "mark_1")
    assert cases(tmp_path / "both" / "mark_0") == cases(tmp_path / "both" / "mark_1")  # same weights, same robots


def test_robust_policies_keeps_the_table_of_the_policies_it_finished(tmp_path, monkeypatch):
    """A call stopped partway (here the second policy's test raises, as a time limit's signal would stop it) leaves
    the table of the first policy, marked partial; a finished call's table is not marked."""
    import json

    from lab.benchmarks import robust_policies
    from tocabi_torchrl.evaluation import robust

    def run(policy, num_envs, device, out_dir, seconds, cases, replace, envs=None):
        if policy.stem == "second":
            raise KeyboardInterrupt
        case = {"passes": True, "survival": 1.0, "forward_distance_m": {"mean": 4.0},
                "checks": {"survival": {"value": 1.0, "needs": ">= 0.99", "pass": True}}}
        return {"passes": True, "settings": {"push_kind": "velocity"}, "cases": {name: case for name in cases}}

    monkeypatch.setattr(robust, "evaluate_robust_run", run)
    monkeypatch.setattr(robust_policies, "check_policy", lambda path: None)  # stand-in files, not checkpoints
    for name in ("first", "second", "third"):
        (tmp_path / f"{name}.pt").touch()
    argv = ["--cases", "nominal", "--device", "cpu", "--out", str(tmp_path)]
    with pytest.raises(KeyboardInterrupt):
        robust_policies.main(["--policies", str(tmp_path / "first.pt"), str(tmp_path / "second.pt"),
                              str(tmp_path / "third.pt"), *argv])
    data = json.loads((tmp_path / "robust_policies.json").read_text())
    assert [r["policy"] for r in data["results"]] == ["first"] and data["meta"]["untested"] == 2
    page = (tmp_path / "robust_policies.md").read_text()
    assert "| first | nominal |" in page and "Partial: 2 more policies of the command not tested yet" in page
    robust_policies.main(["--policies", str(tmp_path / "first.pt"), *argv, "--overwrite"])
    data = json.loads((tmp_path / "robust_policies.json").read_text())
    assert "untested" not in data["meta"] and "Partial" not in (tmp_path / "robust_policies.md").read_text()


def test_robust_policies_stop_on_fail_tests_a_run_back_to_its_first_failing_mark(tmp_path, monkeypatch, capsys):
    """--stop_on_fail: a run's marks from the last back are tested until one fails; the marks before it are left
    untested and the table says where it stopped. Without the option every mark is tested."""
    import json

    from lab.benchmarks import robust_policies
    from tocabi_torchrl.evaluation import robust

    tested = []

    def run(policy, num_envs, device, out_dir, seconds, cases, replace, envs=None):
        tested.append(policy.stem)
        ok = policy.stem != "wall_00600s"  # 12 and 11 minutes pass, 10 does not, 9 would pass again
        check = {"value": 1.0 if ok else 0.5, "needs": ">= 0.99", "pass": ok}
        case = {"passes": ok, "survival": check["value"], "forward_distance_m": {"mean": 4.0},
                "lateral_drift_m": {"p95": 0.1}, "checks": {"survival": check}}
        return {"passes": ok, "settings": {"push_kind": "velocity"}, "cases": {name: case for name in cases}}

    monkeypatch.setattr(robust, "evaluate_robust_run", run)
    monkeypatch.setattr(robust_policies, "check_policy", lambda path: None)  # stand-in files, not checkpoints
    marks = [tmp_path / f"wall_00{s}s.pt" for s in (720, 660, 600, 540)]
    for mark in marks:
        mark.touch()
    argv = ["--policies", *map(str, marks), "--cases", "nominal", "--device", "cpu"]
    robust_policies.main([*argv, "--stop_on_fail", "--out", str(tmp_path / "a")])
    assert tested == ["wall_00720s", "wall_00660s", "wall_00600s"]
    data = json.loads((tmp_path / "a/robust_policies.json").read_text())
    assert data["meta"]["untested"] == 1 and data["meta"]["stopped_on_fail"] == "wall_00600s"
    page = (tmp_path / "a/robust_policies.md").read_text()
    assert "Stopped on the first policy that did not pass, wall_00600s (--stop_on_fail): 1 more policy" in page
    assert "Partial" not in page and "stopped after wall_00600s" in capsys.readouterr().out
    tested.clear()
    robust_policies.main([*argv, "--out", str(tmp_path / "b")])
    assert len(tested) == 4 and "untested" not in json.loads((tmp_path / "b/robust_policies.json").read_text())["meta"]


def test_robust_policies_tells_same_named_files_apart_and_never_replaces_a_table_unasked(tmp_path, monkeypatch,
                                                                                        capsys):
    """Two runs' latest.pt used to share one report folder and one row name; a second call into the same --out
    replaced its table. Missing files, no robots and a CUDA device without CUDA are one usage line each."""
    import json

    from lab.benchmarks import robust_policies
    from tocabi_torchrl.evaluation import robust

    def run(policy, num_envs, device, out_dir, seconds, cases, replace, envs=None):
        out_dir.mkdir(parents=True)  # as the test writes its report: a second policy here would collide
        case = {"passes": True, "survival": 1.0, "checks": {"survival": {"value": 1.0, "needs": ">= 0.99",
                                                                          "pass": True}}}
        return {"passes": True, "settings": {"push_kind": "velocity"}, "cases": {name: case for name in cases}}

    monkeypatch.setattr(robust, "evaluate_robust_run", run)
    monkeypatch.setattr(robust_policies, "check_policy", lambda path: None)  # stand-in files, not checkpoints
    files = []
    for run_name in ("runA", "runB"):
        (tmp_path / run_name / "checkpoints").mkdir(parents=True)
        files.append(tmp_path / run_name / "checkpoints" / "latest.pt")
        files[-1].touch()
    out = tmp_path / "out"
    argv = ["--cases", "nominal", "--device", "cpu", "--out", str(out)]
    robust_policies.main(["--policies", *map(str, files), *argv])
    rows = json.loads((out / "robust_policies.json").read_text())["results"]
    assert [r["policy"] for r in rows] == ["runA_latest", "runB_latest"]
    assert (out / "runA_latest").is_dir() and (out / "runB_latest").is_dir()
    assert robust_policies.labels([files[0], files[0]]) == ["runA_latest_1", "runA_latest_2"]
    assert robust_policies.labels([files[0], tmp_path / "x.pt"]) == ["latest", "x"]
    taken = [Path("a/run/checkpoints/latest.pt"), Path("b/run/checkpoints/latest.pt"), Path("c/run_latest_1.pt")]
    assert len(set(robust_policies.labels(taken))) == 3  # a numbered label never meets a file of that name
    for bad, said in ((["--policies", *map(str, files), *argv], "holds a table already"),
                      (["--policies", str(tmp_path / "nope.pt"), *argv], "no such file or run folder"),
                      (["--policies", str(files[0]), "--num_envs", "0", *argv], "--num_envs must be >= 1"),
                      # Once a traceback, and only on reaching that policy, after the ones before it had run:
                      (["--policies", str(files[0]), "--seconds", "inf", *argv[:-1], str(tmp_path / "inf")],
                       "must be a finite number of seconds")):
        with pytest.raises(SystemExit):
            robust_policies.main(bad)
        assert said in capsys.readouterr().err
    if not torch.cuda.is_available():
        with pytest.raises(SystemExit):
            robust_policies.main(["--policies", str(files[0]), "--out", str(tmp_path / "gpu")])
        assert "--device cuda: torch sees no CUDA GPU here; pass --device cpu" in capsys.readouterr().err


def test_robust_policies_refuses_an_unknown_device_before_any_test(tmp_path, monkeypatch, capsys):
    """--device gpu (a misspelling) once passed every check and ended the call with a traceback from the first
    policy's test; it is one usage line now, and no test runs."""
    from lab.benchmarks import robust_policies
    from tocabi_torchrl.evaluation import robust

    monkeypatch.setattr(robust, "evaluate_robust_run", lambda *a, **k: pytest.fail("a test ran"))
    monkeypatch.setattr(robust_policies, "check_policy", lambda path: None)  # a stand-in file, not a checkpoint
    (tmp_path / "a.pt").touch()
    with pytest.raises(SystemExit) as stop:
        robust_policies.main(["--policies", str(tmp_path / "a.pt"), "--device", "gpu", "--out", str(tmp_path / "o")])
    assert stop.value.code == 2 and not (tmp_path / "o").exists()
    assert "--device: unknown device 'gpu'" in capsys.readouterr().err


def test_robust_policies_refuses_one_checkpoint_named_twice(tmp_path, monkeypatch, capsys):
    """A run folder and its latest.pt (or one path twice) were tested twice, two rows of the same numbers under
    made-up names; now refused before any test. Two runs' latest.pt stay two policies."""
    from lab.benchmarks import robust_policies
    from tocabi_torchrl.evaluation import robust

    monkeypatch.setattr(robust, "evaluate_robust_run", lambda *a, **k: pytest.fail("a test ran"))
    monkeypatch.setattr(robust_policies, "check_policy", lambda path: None)  # stand-in files, not checkpoints
    (tmp_path / "run" / "checkpoints").mkdir(parents=True)
    (tmp_path / "run" / "checkpoints" / "latest.pt").touch()
    (tmp_path / "b.pt").touch()
    for policies in (["run", "run/checkpoints/latest.pt"], ["b.pt", "b.pt"]):
        with pytest.raises(SystemExit) as stop:
            robust_policies.main(["--policies", *(str(tmp_path / p) for p in policies), "--device", "cpu", "--out",
                                  str(tmp_path / "o")])
        assert stop.value.code == 2 and not (tmp_path / "o").exists()
        assert "--policies names one checkpoint more than once" in capsys.readouterr().err


def test_robust_policies_refuses_an_out_that_cannot_be_made_before_any_test(tmp_path, monkeypatch, capsys):
    """An --out below a file once passed every check and ended the call with a NotADirectoryError traceback from
    inside the first policy's test (after its env build); it is one usage line now, before any test."""
    from lab.benchmarks import robust_policies
    from tocabi_torchrl.evaluation import robust

    monkeypatch.setattr(robust, "evaluate_robust_run", lambda *a, **k: pytest.fail("a test ran"))
    monkeypatch.setattr(robust_policies, "check_policy", lambda path: None)  # a stand-in file, not a checkpoint
    (tmp_path / "a.pt").touch()
    with pytest.raises(SystemExit) as stop:
        robust_policies.main(["--policies", str(tmp_path / "a.pt"), "--device", "cpu", "--out",
                              str(tmp_path / "a.pt" / "reports")])
    assert stop.value.code == 2
    assert f"--out {tmp_path / 'a.pt' / 'reports'}: cannot create the folder" in capsys.readouterr().err


def test_robust_policies_refuses_an_empty_out(tmp_path, monkeypatch, capsys):
    """--out "" (an unset variable in --out "$DIR") once wrote the reports and the table into the current folder;
    it is refused now, before any test."""
    from lab.benchmarks import robust_policies
    from tocabi_torchrl.evaluation import robust

    monkeypatch.setattr(robust, "evaluate_robust_run", lambda *a, **k: pytest.fail("a test ran"))
    monkeypatch.setattr(robust_policies, "check_policy", lambda path: None)  # a stand-in file, not a checkpoint
    (tmp_path / "a.pt").touch()
    monkeypatch.setattr(robust_policies.common, "publish", lambda *a, **k: pytest.fail("a table was written"))
    with pytest.raises(SystemExit) as stop:
        robust_policies.main(["--policies", str(tmp_path / "a.pt"), "--device", "cpu", "--out", ""])
    assert stop.value.code == 2 and "--out is empty" in capsys.readouterr().err


def test_robust_policies_runs_the_cases_asked_for_and_judges_those(tmp_path, monkeypatch, capsys):
    """--cases: only those cases run, and a policy passes or fails those cases (not the whole test, which a report of
    two cases can never pass); an unknown case is refused by name."""
    import json

    from lab.benchmarks import robust_policies
    from tocabi_torchrl.evaluation import robust

    seen = {}

    def run(policy, num_envs, device, out_dir, seconds, cases, replace, envs=None):
        seen["cases"] = cases
        case = {"passes": True, "survival": 1.0, "checks": {"survival": {"value": 1.0, "needs": ">= 0.99",
                                                                          "pass": True}}}
        good = {"survival": 1.0, "forward_distance_m": {"mean": 4.0}, "lateral_drift_m": {"p95": 0.2},
                "tracking_error_mps": {"mean": 0.05}}
        return {"passes": False, "settings": {"push_kind": "velocity"},
                "cases": {name: {**case, **good} for name in cases}}

    monkeypatch.setattr(robust, "evaluate_robust_run", run)
    monkeypatch.setattr(robust_policies, "check_policy", lambda path: None)  # stand-in files, not checkpoints
    (tmp_path / "p.pt").touch()
    robust_policies.main(["--policies", str(tmp_path / "p.pt"), "--cases", "nominal", "commands", "--device", "cpu",
                          "--out", str(tmp_path)])
    assert seen["cases"] == ("nominal", "commands")
    (row,) = json.loads((tmp_path / "robust_policies.json").read_text())["results"]
    assert row["passes"] is True and set(row["cases"]) == {"nominal", "commands"}
    page = (tmp_path / "robust_policies.md").read_text()
    assert "- p: passes the cases nominal, commands; 0 s for its two cases" in page
    robust_policies.main(["--policies", str(tmp_path / "p.pt"), "--cases", "robust_1.0", "--device", "cpu",
                          "--out", str(tmp_path / "one")])
    one = (tmp_path / "one/robust_policies.md").read_text()
    assert "- p: passes the case robust_1.0; 0 s for its one case (" in one
    with pytest.raises(SystemExit):
        robust_policies.main(["--cases", "nominal", "kicked", "--device", "cpu", "--out", str(tmp_path)])
    assert "unknown case(s) ['kicked']" in capsys.readouterr().err


def test_robust_policies_cells_never_round_a_miss_to_read_as_its_limit(tmp_path):
    # A drift p95 of 0.3032 against <= 0.3 was published as "0.30 ✗".
    from lab.benchmarks.robust_policies import _cell

    assert _cell(0.3032, {"needs": "<= 0.3", "pass": False}, ".2f") == "0.303 ✗"
    assert _cell(0.9697, {"needs": ">= 0.97", "pass": False}, ".3f") == "0.9697 ✗"
    assert _cell(0.29, {"needs": "<= 0.3", "pass": True}, ".2f") == "0.29"
    assert _cell(None, {"needs": ">= 0.97", "pass": False}, ".3f") == "- ✗" and _cell(4.1, None, ".2f") == "4.10"


def test_robust_policies_refuses_an_out_that_is_a_file_before_any_test(tmp_path, capsys):
    from lab.benchmarks import robust_policies

    policy = robust_policies.POLICIES / "tocabi_walk_ppo.pt"
    if not policy.is_file():
        pytest.skip("shipped policy not present")
    (tmp_path / "f").write_text("")
    with pytest.raises(SystemExit) as stop:
        robust_policies.main(["--policies", str(policy), "--device", "cpu", "--num_envs", "1", "--out",
                              str(tmp_path / "f")])
    assert stop.value.code == 2 and f"--out {tmp_path / 'f'} is a file, not a folder" in capsys.readouterr().err


def test_steady_rate_skips_rows_without_time_and_never_divides_by_zero(tmp_path):
    # The benchmarks' env-steps/s (time_to_walk, train_throughput) ended in a ZeroDivisionError for two rows logged
    # at one wall_s, and in a ValueError for a row whose wall_s cell is empty.
    from lab.benchmarks.time_to_walk import steady_rate
    from tocabi_torchrl.rl.curves import read_metrics

    path = tmp_path / "metrics.csv"
    path.write_text("iteration,wall_s,env_steps\n1,1.0,100\n2,,200\n3,2.0,300\n4,4.0,700\n")
    rows = read_metrics(path)
    assert rows[1]["wall_s"] == ""
    assert steady_rate(rows, skip=1) == pytest.approx((700 - 300) / (4.0 - 2.0))  # the row without a time left out
    same = [{"wall_s": "3.0", "env_steps": "100"}, {"wall_s": "5.0", "env_steps": "200"},
            {"wall_s": "5.0", "env_steps": "300"}]
    assert steady_rate(same, skip=1) is None  # no time between the two rows measured
    assert steady_rate(same, skip=0) == pytest.approx((300 - 100) / (5.0 - 3.0))
    assert steady_rate([{"wall_s": "", "env_steps": ""}] * 4, skip=1) is None


def test_a_damaged_result_file_of_scaling_or_mjlab_peer_is_one_line_naming_it(tmp_path):
    # Invalid JSON in a measurement's result file (a copy cut short, a hand edit) ended in a JSONDecodeError
    # traceback that named no file.
    results = tmp_path / "scaling"
    results.mkdir()
    damaged = results / "time_gpu_0004096.json"
    damaged.write_text("{,")
    args = SimpleNamespace(results=str(results), redo=[])
    for call in (lambda: scaling.main(["--report", "--results", str(results)]),
                 lambda: scaling.run("time", "gpu", 4096, args)):
        with pytest.raises(SystemExit, match=rf"^error: {re.escape(str(damaged))} is not valid JSON \(.*\): the file "
                                             r"is damaged; remove it and run that measurement again"):
            call()
    ours, peer = tmp_path / "ours.json", tmp_path / "peer.json"
    ours.write_text(json.dumps({"results": []}))
    peer.write_text("")
    with pytest.raises(SystemExit, match=rf"^mjlab_peer: {re.escape(str(peer))} is not valid JSON \(.*\): the file "
                                         r"is damaged; write it again with lab.benchmarks.mjlab_peer$"):
        mjlab_peer.merge(peer, ours)


def test_gait_test_keeps_an_env_per_checkpoint_config_and_gives_each_its_built_state(tmp_path):
    """common.gait_test caches its envs across a run's checkpoints. Keyed by the command alone, a PD checkpoint after
    a torque one got the torque env; and transform state loads leniently, so a checkpoint saved without its env kept
    the normaliser statistics the checkpoint before it had loaded."""
    from tocabi_torchrl.rl.checkpoint import read_checkpoint
    from tocabi_torchrl.rl.symmetry import find_normalization
    from tocabi_torchrl.transforms.normalize import FixedNormalization

    policies = Path(common.__file__).parents[2] / "assets" / "policies"
    saved = torch.load(policies / "tocabi_walk_torque.pt", map_location="cpu", weights_only=True)
    own = {k: v + 1.0 if k.endswith((".loc", ".scale")) else v for k, v in saved["transforms"].items()}
    torch.save({**saved, "transforms": own}, tmp_path / "own_stats.pt")
    torch.save({**saved, "transforms": {}}, tmp_path / "no_env.pt")
    envs: dict = {}
    for name in ("own_stats", "no_env"):
        path = tmp_path / f"{name}.pt"
        common.gait_test(read_checkpoint(path), path, (0.5, 0.0), tmp_path / name, 1, 0.02, "cpu", envs)
    (env,) = envs.values()
    norm, built = find_normalization(env), FixedNormalization()
    assert torch.equal(norm.loc, built.loc) and torch.equal(norm.scale, built.scale)
    pd = policies / "tocabi_walk_ppo.pt"
    common.gait_test(read_checkpoint(pd), pd, (0.5, 0.0), tmp_path / "pd", 1, 0.02, "cpu", envs)
    modes = sorted(e.base_env.cfg.control.mode for e in envs.values())
    assert len(envs) == 2 and len(set(modes)) == 2, modes
