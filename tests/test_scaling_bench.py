"""The scaling suite (benchmarks/scaling.py, scaling_report.py) on the CPU: one real tiny measurement in its own
process, the driver's resume and sweep logic with a fake launcher, and the report from synthetic results."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCH))

import scaling
import scaling_report

# ------------------------------------------------------------------------------------------------ sizing


@pytest.mark.parametrize("n, steps, minibatch", [(8, 256, 512), (32, 64, 512), (96, 48, 1152), (4096, 48, 49152),
                                                 (16384, 48, 49152), (65536, 48, 49152)])
def test_ppo_sizing(n, steps, minibatch):
    # The default preset's 48 steps and 49,152-frame mini-batches, but rollouts of at least 2,048 frames.
    assert scaling.ppo_sizing(n) == (steps, minibatch)


def test_recipe_excludes_sizing_and_flags_other_recipes():
    rec = scaling.recipe()
    assert rec["control_mode"] == "pd_reference" and "num_envs" not in rec and "steps_per_env" not in rec
    assert rec == scaling.recipe(scaling.RunSpec("time", "gpu", 4096).ppo_config())  # sizing is not the recipe
    assert not scaling.is_stale({"kind": "time", "recipe": rec})
    assert scaling.is_stale({"kind": "time", "recipe": {**rec, "gamma": 0.99}})
    assert scaling.is_stale({"kind": "memory"})  # measured before recipes were recorded
    assert not scaling.is_stale({"kind": "raw"})  # the raw ceiling has no training recipe


def test_a_result_of_another_env_step_mode_is_stale():
    """The env-step mode (CUDA graph or eager) is not part of the recipe, but a result measured in another mode than
    the default now picks for its backend and env count does not describe what users run."""
    from tocabi_torchrl.rl.config import ENV_GRAPH_AUTO_MAX_ENVS

    small, large = 8, ENV_GRAPH_AUTO_MAX_ENVS * 2
    before = {**scaling.recipe(), "cuda_graph": False}  # results from before the mode was recorded

    def result(backend, n, **extra):
        return {"kind": "time", "backend": backend, "num_envs": n, "recipe": before, **extra}

    assert scaling.planned_env_graph(scaling.RunSpec("time", "gpu", small))
    assert not scaling.planned_env_graph(scaling.RunSpec("time", "gpu", large))
    assert not scaling.planned_env_graph(scaling.RunSpec("time", "cpu", small))
    assert scaling.is_stale(result("gpu", small))  # measured eager, the default now captures the step
    assert not scaling.is_stale(result("gpu", large)) and not scaling.is_stale(result("cpu", small))
    assert not scaling.is_stale(result("gpu", small, env_graph_planned=True))
    assert scaling.is_stale(result("gpu", large, env_graph_planned=True))
    # the CPU never captures its step, whatever an old record's flag says; a malformed count is never current
    assert not scaling.is_stale({**result("cpu", small), "recipe": {**scaling.recipe(), "cuda_graph": True}})
    assert scaling.is_stale(result("gpu", "many")) and scaling.is_stale(result("gpu", -1))


def test_merged_segments_show_graph_only_if_every_segment_ran_captured():
    base = {"kind": "time", "backend": "gpu", "num_envs": 8, "total_env_steps": 300, "env_steps": 100,
            "train_wall_s": 1.0, "setup_s": 1.0, "total_wall_s": 2.0, "env_steps_per_s": 100.0, "status": "partial"}
    first = scaling.merge_segments({**base, "env_graph": True}, {**base, "env_graph": False})
    assert first["env_graph"] is False and [s["env_graph"] for s in first["segments"]] == [True, False]
    assert scaling.merge_segments(first, {**base, "env_graph": True})["env_graph"] is False
    legacy = scaling.merge_segments(base, {**base, "env_graph": True})  # the first segment predates the record
    assert legacy["env_graph"] is True


def test_every_default_count_is_a_valid_config():
    """PPOConfig.validate() accepts the sizing at every env count the suite runs."""
    for kind, backend, counts in scaling.PARTS.values():
        if kind == "raw":
            continue
        for n in counts:
            cfg = scaling.RunSpec(kind, backend, n).ppo_config()
            assert cfg.minibatch_size <= cfg.frames_per_batch
            assert cfg.frames_per_batch >= scaling.MIN_ROLLOUT
            assert cfg.iterations * cfg.frames_per_batch >= cfg.total_env_steps


def test_chunks_are_in_the_usage_text():
    for chunk in scaling.CHUNKS:
        assert chunk in scaling.__doc__


def test_spec_round_trips_through_the_command_line():
    spec = scaling.RunSpec("memory", "gpu", 2048, memory_iterations=4, hidden=(32, 16), raw_steps=50)
    args = scaling.build_parser().parse_args(["--one", *spec.to_argv()])
    again = scaling.RunSpec(args.kind, args.backend, args.num_envs[0], total_env_steps=args.total_env_steps,
                            memory_iterations=args.memory_iterations, hidden=args.hidden,
                            min_rollout=args.min_rollout, raw_steps=args.raw_steps, max_minutes=args.max_minutes,
                            run_dir=args.run_dir)
    assert again == spec
    with pytest.raises(ValueError):
        scaling.RunSpec("raw", "cpu", 8)


# ------------------------------------------------------------------------------------------------ one real run


def test_one_cpu_measurement_writes_a_sane_json(tmp_path):
    """The --one measurement of the CPU backend, in its own process, at 4 envs with tiny networks."""
    out = tmp_path / "time_cpu_0000004.json"
    cmd = [sys.executable, str(BENCH / "scaling.py"), "--one", "--kind", "time", "--backend", "cpu", "--num_envs", "4",
           "--total_env_steps", "384", "--min_rollout", "32", "--hidden", "16,16", "--out", str(out),
           "--run_dir", str(tmp_path / "runs")]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    r = json.loads(out.read_text())
    assert r["status"] == "ok" and r["num_envs"] == 4 and r["backend"] == "cpu"
    assert r["config"]["steps_per_env"] == 48 and r["config"]["actor_hidden"] == [16, 16]
    assert r["env_steps"] == 384 and r["iterations"] == 2
    assert r["recipe"] is None  # tiny test networks: never taken for the current recipe
    assert 0 < r["train_wall_s"] < r["total_wall_s"]
    assert r["env_steps_per_s"] == pytest.approx(r["env_steps"] / r["train_wall_s"], rel=1e-6)
    assert r["host"]["peak_rss_gib"] > 0.05
    assert r["cpu"]["cores_used_mean"] > 0 and r["cpu"]["samples"] >= 2
    assert r["meta"]["available_cores"] >= 1 and r["meta"]["versions"]["torch"]
    assert "gpu" not in r


def test_a_partial_time_run_trains_on_from_its_checkpoint(tmp_path):
    """A run its clock stopped after one of two iterations continues in a second process (--continue) from the
    checkpoint it left; the result adds both segments up, as TocabiLab's timer would have counted one run."""
    out = tmp_path / "time_cpu_0000004.json"
    base = [sys.executable, str(BENCH / "scaling.py"), "--one", "--kind", "time", "--backend", "cpu", "--num_envs",
            "4", "--total_env_steps", "384", "--min_rollout", "32", "--hidden", "16,16", "--out", str(out),
            "--run_dir", str(tmp_path / "runs")]
    first = subprocess.run([*base, "--max_minutes", "0.0001"], capture_output=True, text=True, timeout=120)
    assert first.returncode == 0, first.stdout + first.stderr
    r1 = json.loads(out.read_text())
    assert r1["status"] == "partial" and r1["env_steps"] == 192 and r1["iterations"] == 1
    spec = scaling.RunSpec("time", "cpu", 4, total_env_steps=384, min_rollout=32, hidden=(16, 16),
                           run_dir=str(tmp_path / "runs"))
    assert scaling.checkpoint_path(spec).is_file()
    second = subprocess.run([*base, "--continue"], capture_output=True, text=True, timeout=120)
    assert second.returncode == 0, second.stdout + second.stderr
    assert "resumed from" in second.stdout
    r2 = json.loads(out.read_text())
    assert r2["status"] == "ok" and r2["env_steps"] == 384 and r2["iterations"] == 2
    assert [seg["env_steps"] for seg in r2["segments"]] == [192, 192]
    assert r2["train_wall_s"] == pytest.approx(r1["train_wall_s"] + r2["segments"][1]["train_wall_s"])
    assert r2["env_steps_per_s"] == pytest.approx(384 / r2["train_wall_s"])
    assert len(r2["cpu_segments"]) == 2 and r2["cpu"]["window_s"] > r1["cpu"]["window_s"]
    # a finished run has nothing to continue
    third = subprocess.run([*base, "--continue"], capture_output=True, text=True, timeout=120)
    assert third.returncode != 0 and "needs a partial time result" in third.stderr


def test_a_continuation_that_does_not_chain_keeps_the_partial_result(tmp_path):
    """A continuation with other settings than the partial result ran with, without a checkpoint, or from a
    checkpoint that is not where the result ended is refused; the partial result stays, with the failure noted."""
    import torch

    spec = scaling.RunSpec("time", "cpu", 4, total_env_steps=384, min_rollout=32, run_dir=str(tmp_path / "runs"))
    cfg = spec.ppo_config()
    out = tmp_path / f"{spec.name}.json"
    config = {"frames_per_batch": cfg.frames_per_batch, "total_env_steps_target": 384,
              "actor_hidden": list(cfg.actor_hidden), "critic_hidden": list(cfg.critic_hidden)}
    partial = {"kind": "time", "backend": "cpu", "num_envs": 4, "status": "partial", "env_steps": 192,
               "total_env_steps": 384, "train_wall_s": 1.0, "recipe": scaling.recipe(), "config": config}
    scaling.write_json(out, {**partial, "config": {**config, "frames_per_batch": 2048}})
    record = scaling.run_one(spec, out, resume=True)
    assert "other settings" in record["continue_failed"]["error"] and "frames_per_batch" in record["continue_failed"]["error"]
    scaling.write_json(out, partial)
    record = scaling.run_one(spec, out, resume=True)
    assert record["status"] == "partial" and record["env_steps"] == 192
    assert "no checkpoint" in record["continue_failed"]["error"]
    scaling.checkpoint_path(spec).parent.mkdir(parents=True)
    torch.save({"env_steps": 96}, scaling.checkpoint_path(spec))
    record = scaling.run_one(spec, out, resume=True)
    assert "do not chain" in record["continue_failed"]["error"]
    assert {k: v for k, v in json.loads(out.read_text()).items() if k != "continue_failed"} == partial
    # the driver does not retry the same checkpoint, and shows why; a newer checkpoint is tried
    fake = FakeLauncher()
    outcome = scaling.drive([spec], scaling.DriveOptions(results=tmp_path), fake)
    assert fake.calls == [] and "its last continuation failed" in outcome[spec.name]
    assert "is at 96 env-steps" in scaling._brief(out)
    torch.save({"env_steps": 192}, scaling.checkpoint_path(spec))
    failed = json.loads(out.read_text())
    failed["continue_failed"]["time"] = scaling.checkpoint_path(spec).stat().st_mtime - 1.0
    scaling.write_json(out, failed)
    scaling.drive([spec], scaling.DriveOptions(results=tmp_path), fake)
    assert fake.resumed == [spec.name]


def test_segments_merge_into_one_result():
    def seg(steps, train, setup, cores, window, rss, date):
        return {"kind": "time", "status": "partial", "total_env_steps": 300, "env_steps": steps, "iterations": 1,
                "train_wall_s": train, "setup_s": setup, "total_wall_s": train + setup, "env_steps_per_s": steps / train,
                "cpu": {"cores_used_mean": cores, "window_s": window, "samples": 3, "rss_peak_sampled_gib": rss},
                "host": {"peak_rss_gib": rss}, "meta": {"date": date}, "part_command": f"cmd {date}"}

    one = scaling.merge_segments(seg(100, 10.0, 5.0, 2.0, 10.0, 1.0, "d1"), seg(100, 30.0, 5.0, 4.0, 30.0, 1.5, "d2"))
    assert one["env_steps"] == 200 and one["train_wall_s"] == 40.0 and one["setup_s"] == 10.0
    assert one["env_steps_per_s"] == pytest.approx(5.0) and one["status"] == "partial"
    assert one["cpu"]["cores_used_mean"] == pytest.approx((2.0 * 10 + 4.0 * 30) / 40) and one["cpu"]["samples"] == 6
    assert one["host"]["peak_rss_gib"] == 1.5
    two = scaling.merge_segments(one, seg(100, 20.0, 5.0, 1.0, 20.0, 1.2, "d3"))
    assert two["status"] == "ok" and two["env_steps"] == 300 and two["train_wall_s"] == 60.0
    assert [s["date"] for s in two["segments"]] == ["d1", "d2", "d3"]
    assert two["cpu"]["cores_used_mean"] == pytest.approx((20 + 120 + 20) / 60)
    # the report lists each segment's command
    ran = scaling_report.commands_run([{**two, "backend": "cpu", "num_envs": 8}])
    assert [c for c, _ in ran] == ["cmd d1", "cmd d2", "cmd d3"]
    assert scaling_report._status(two) == "ok (3 segments)"
    assert scaling_report._status(one) == "partial (200 steps, time extrapolated) (2 segments)"
    # steady windows add up; GPU peaks are peaks, the rest is the latest segment's reading
    a, b = seg(100, 10.0, 5.0, 2.0, 10.0, 1.0, "d1"), seg(100, 30.0, 5.0, 4.0, 30.0, 1.5, "d2")
    a.update(steady_window={"env_steps": 50.0, "wall_s": 5.0},
             gpu={"torch_peak_allocated_gib": 3.0, "torch_peak_reserved_gib": 4.0, "device_used_end_gib": 6.0})
    b.update(steady_window={"env_steps": 90.0, "wall_s": 15.0},
             gpu={"torch_peak_allocated_gib": 2.0, "torch_peak_reserved_gib": 5.0, "device_used_end_gib": 5.5})
    b["cpu"]["cores_used_max"] = None
    merged = scaling.merge_segments(a, b)
    assert merged["steady_env_steps_per_s"] == pytest.approx(140 / 20) and "steady_window" not in merged
    assert merged["gpu"] == {"torch_peak_allocated_gib": 3.0, "torch_peak_reserved_gib": 5.0,
                             "device_used_end_gib": 5.5}
    assert merged["cpu"]["cores_used_max"] is None
    assert scaling._weighted_cpu([None, {}, {"window_s": 0.0}]) == {}


def test_steady_rate_spans_resumed_segments(tmp_path):
    """Each process's steady window starts at its own first logged row (the merged rate never spans the gap
    between two processes, even where a segment's clock does not restart below the one before)."""
    csv_path = tmp_path / "metrics.csv"
    # segment 1: 100 -> 300 steps in 2 s; segment 2 appended after it: 400 -> 700 in 3 s
    csv_path.write_text("env_steps,wall_s\n100,1\n200,2\n300,3\n400,5\n550,6.5\n700,8\n")
    rows = scaling._metrics_rows(csv_path)
    first, second = scaling._steady_window(rows[:3]), scaling._steady_window(rows[3:])
    assert first == {"env_steps": 200.0, "wall_s": 2.0} and second == {"env_steps": 300.0, "wall_s": 3.0}
    assert scaling._steady_rate([first, None, second]) == pytest.approx(500 / 5)
    assert scaling._steady_window(rows[:1]) is None and scaling._steady_rate([]) is None
    assert scaling._metrics_rows(tmp_path / "none.csv") == []


def test_a_failed_measurement_keeps_its_recipe(tmp_path, monkeypatch):
    """An out-of-memory result says which recipe ran out of memory, so the report counts it (not as stale)."""
    def out_of_memory(spec, deadline, sampler, previous=None):  # after two logged iterations, as 98,304 envs did on the H100
        metrics = Path(spec.run_dir) / spec.name / "metrics.csv"
        metrics.parent.mkdir(parents=True)
        metrics.write_text("iteration,env_steps,wall_s\n1,100,1.0\n2,200,2.0\n")
        raise RuntimeError("Graph launch error: Warp CUDA error 2: out of memory")

    monkeypatch.setattr(scaling, "measure_training", out_of_memory)
    spec = scaling.RunSpec("memory", "cpu", 8, run_dir=str(tmp_path / "runs"))
    record = scaling.run_one(spec, tmp_path / f"{spec.name}.json")
    assert record["status"] == "oom" and "out of memory" in record["error"]
    assert record["iterations_logged"] == 2  # it failed while training, not at set-up
    assert record["recipe"] == scaling.recipe() and not scaling.is_stale(record)
    assert json.loads((tmp_path / f"{spec.name}.json").read_text())["recipe"] == scaling.recipe()
    # the report takes it as the count that did not fit
    graphed = scaling.planned_env_graph(scaling.RunSpec("memory", "gpu", 8))  # the same for 16
    scaling.write_json(tmp_path / "memory_gpu_0000016.json",
                       {**record, "backend": "gpu", "num_envs": 16, "env_graph_planned": graphed})
    scaling.write_json(tmp_path / "memory_gpu_0000008.json",
                       {"kind": "memory", "backend": "gpu", "num_envs": 8, "status": "ok", "recipe": scaling.recipe(),
                        "env_graph_planned": graphed})
    idx = scaling_report.index(scaling_report.load_results(tmp_path))
    assert scaling_report.largest_fit(idx) == (8, 16)
    # test networks and the raw ceiling never carry the current recipe
    assert scaling.spec_recipe(scaling.RunSpec("time", "cpu", 8, hidden=(16,))) is None
    assert scaling.spec_recipe(scaling.RunSpec("raw", "gpu", 8)) is None


class _FakeRun:
    """Stands in for ``subprocess.run`` of a measurement process that dies before writing its JSON."""

    def __init__(self, log_text: str = "", returncode: int | None = 1):
        self.log_text, self.returncode, self.cmd = log_text, returncode, None

    def __call__(self, cmd, stdout, **kwargs):
        self.cmd = cmd
        stdout.write(self.log_text)
        if self.returncode is None:
            raise subprocess.TimeoutExpired(cmd, kwargs["timeout"])
        return subprocess.CompletedProcess(cmd, self.returncode)


def test_launch_records_a_process_that_died_without_a_result(tmp_path, monkeypatch):
    """A measurement process killed by the driver (no JSON of its own) still leaves a dated failure record with its
    recipe and the command that launched it, so the report counts it and names that command."""
    spec = scaling.RunSpec("memory", "gpu", 98304)
    out = tmp_path / "results" / f"{spec.name}.json"
    part = "python3 benchmarks/scaling.py --part memory --num_envs 98304 --bundle=/root/out/b.json"
    fake = _FakeRun("iteration 1\nRuntimeError: CUDA error: out of memory\n", returncode=1)
    monkeypatch.setattr(scaling.subprocess, "run", fake)
    status = scaling.launch(spec, out, deadline=scaling.time.time() + 60, record_timeout=False, resume=False,
                            log_dir=str(tmp_path / "logs"), part_command=part)
    assert status == "oom" and "--one" in fake.cmd
    record = json.loads(out.read_text())
    assert record["status"] == "oom" and "out of memory" in record["error"] and record["returncode"] == 1
    assert record["recipe"] == scaling.recipe() and not scaling.is_stale(record)
    assert record["part_command"] == part and record["meta"]["date"].startswith("20")
    loaded = scaling_report.load_results(out.parent)
    assert scaling_report.largest_fit(scaling_report.index(loaded)) == (None, 98304)
    assert scaling_report.commands_run(loaded) == [("python3 benchmarks/scaling.py --part memory --num_envs 98304",
                                                    "memory GPU at 98,304 envs")]
    # any other death is an error
    monkeypatch.setattr(scaling.subprocess, "run", _FakeRun("Segmentation fault\n", returncode=-11))
    assert scaling.launch(spec, tmp_path / "e.json", scaling.time.time() + 60, False, log_dir=str(tmp_path / "logs")) == "error"
    # killed at its deadline: the measurement's own time limit is a result, the command's budget is not (rerun it)
    monkeypatch.setattr(scaling.subprocess, "run", _FakeRun(returncode=None))
    assert scaling.launch(spec, tmp_path / "t.json", scaling.time.time() + 60, True, log_dir=str(tmp_path / "logs")) == "timeout"
    assert scaling.launch(spec, tmp_path / "c.json", scaling.time.time() + 60, False, log_dir=str(tmp_path / "logs")) == "cut"
    assert not (tmp_path / "c.json").exists()


def test_launch_takes_only_a_result_its_own_process_wrote(tmp_path, monkeypatch):
    """A count measured again (a partial memory run, --redo) still has its old result file while the new process
    runs: a process that dies without writing must not pass the old status off as its own."""
    logs = str(tmp_path / "logs")
    spec = scaling.RunSpec("memory", "gpu", 98304)
    out = tmp_path / f"{spec.name}.json"
    old = {"kind": "memory", "backend": "gpu", "num_envs": 98304, "status": "partial", "recipe": scaling.recipe()}
    scaling.write_json(out, old)
    monkeypatch.setattr(scaling.subprocess, "run", _FakeRun("CUDA error: out of memory\n", returncode=-6))
    assert scaling.launch(spec, out, scaling.time.time() + 60, False, log_dir=logs) == "oom"
    assert json.loads(out.read_text())["status"] == "oom"
    scaling.write_json(out, old)  # cut by the command's budget: no result, the old one stays for the rerun
    monkeypatch.setattr(scaling.subprocess, "run", _FakeRun(returncode=None))
    assert scaling.launch(spec, out, scaling.time.time() + 60, False, log_dir=logs) == "cut"
    assert json.loads(out.read_text()) == old
    # a continuation that died: the partial result stays as it was, the log says why
    time_spec = scaling.RunSpec("time", "gpu", 8)
    partial = tmp_path / f"{time_spec.name}.json"
    scaling.write_json(partial, {**old, "kind": "time", "num_envs": 8})
    crash = _FakeRun("Segmentation fault\n", returncode=-11)
    monkeypatch.setattr(scaling.subprocess, "run", crash)
    status = scaling.launch(time_spec, partial, scaling.time.time() + 60, False, resume=True, log_dir=logs)
    assert status.startswith("error (the continuation wrote nothing") and "--continue" in crash.cmd
    assert json.loads(partial.read_text())["status"] == "partial"


# ------------------------------------------------------------------------------------------------ the driver


class FakeLauncher:
    """Writes a result with the status ``statuses`` gives an env count (default ok) and records the calls."""

    def __init__(self, statuses: dict[int, str] | None = None):
        self.statuses = statuses or {}
        self.calls: list[str] = []
        self.resumed: list[str] = []

    def __call__(self, spec, path, deadline, record_timeout, resume=False):
        self.calls.append(spec.name)
        if resume:
            self.resumed.append(spec.name)
        status = self.statuses.get(spec.num_envs, "ok")
        scaling.write_json(path, {"kind": spec.kind, "backend": spec.backend, "num_envs": spec.num_envs,
                                  "status": status, "recipe": scaling.recipe(spec.ppo_config()),
                                  "env_graph_planned": scaling.planned_env_graph(spec)})
        return status


def test_driver_skips_finished_measurements(tmp_path):
    specs = scaling.plan(["cpu_time"], [8, 32, 96], run_dir=str(tmp_path / "runs"))
    current = {"kind": "time", "recipe": scaling.recipe()}
    scaling.write_json(tmp_path / "time_cpu_0000032.json", {"status": "ok", **current})
    scaling.write_json(tmp_path / "time_cpu_0000096.json", {"status": "partial", **current})
    opts = scaling.DriveOptions(results=tmp_path, bundle=tmp_path / "out" / "bundle.json")
    fake = FakeLauncher()
    outcome = scaling.drive(specs, opts, fake)
    assert fake.calls == ["time_cpu_0000008"]
    assert outcome["time_cpu_0000032"] == "skipped (ok)"
    assert outcome["time_cpu_0000096"].startswith("skipped (partial; no checkpoint at ")
    bundle = json.loads((tmp_path / "out" / "bundle.json").read_text())["results"]
    assert set(bundle) == {"time_cpu_0000008.json", "time_cpu_0000032.json", "time_cpu_0000096.json"}
    # a second pass launches nothing; --redo partial repeats the partial one from scratch
    again = FakeLauncher()
    scaling.drive(specs, opts, again)
    assert again.calls == []
    opts.redo = ("partial",)
    scaling.drive(specs, opts, again)
    assert again.calls == ["time_cpu_0000096"] and again.resumed == []
    # a partial run with a checkpoint trains on from it, unless told not to (--no_continue)
    opts.redo = ()
    scaling.write_json(tmp_path / "time_cpu_0000096.json", {"status": "partial", **current})
    checkpoint = scaling.checkpoint_path(specs[-1])
    checkpoint.parent.mkdir(parents=True)
    checkpoint.write_bytes(b"x")
    opts.continue_partial = False
    again = FakeLauncher()
    assert scaling.drive(specs, opts, again)["time_cpu_0000096"] == "skipped (partial)" and again.calls == []
    opts.continue_partial = True
    scaling.drive(specs, opts, again)
    assert again.resumed == ["time_cpu_0000096"]
    # a result of an older recipe is measured again
    opts.redo = ()
    scaling.write_json(tmp_path / "time_cpu_0000032.json", {"status": "ok", "kind": "time", "recipe": {"gamma": 0.9}})
    again = FakeLauncher()
    scaling.drive(specs, opts, again)
    assert again.calls == ["time_cpu_0000032"]
    # a bundle unpacks into an empty results folder
    names = scaling.unpack_bundle(tmp_path / "out" / "bundle.json", tmp_path / "copy")
    assert len(names) == 3 and scaling.load_status(tmp_path / "copy" / "time_cpu_0000008.json") == "ok"


def test_memory_sweep_stops_at_the_first_count_that_does_not_fit(tmp_path):
    specs = scaling.plan(["memory"], [256, 8, 64, 32, 128])
    assert [s.num_envs for s in specs] == [8, 32, 64, 128, 256]
    scaling.write_json(tmp_path / "time_gpu_0000032.json",  # a time run already covers 32
                       {"status": "ok", "kind": "time", "recipe": scaling.recipe()})
    fake = FakeLauncher({64: "oom"})
    outcome = scaling.drive(specs, scaling.DriveOptions(results=tmp_path), fake)
    assert fake.calls == ["memory_gpu_0000008", "memory_gpu_0000064"]
    assert outcome["memory_gpu_0000128"] == "skipped (64 envs did not fit)"
    assert outcome["memory_gpu_0000032"].startswith("skipped (the time run")
    # a time run that ran out of memory also ends the sweep above it
    other = tmp_path / "other"
    scaling.write_json(other / "time_gpu_0000064.json", {"status": "oom", "recipe": scaling.recipe()})
    fake = FakeLauncher()
    scaling.drive(scaling.plan(["memory"], [32, 128]), scaling.DriveOptions(results=other), fake)
    assert fake.calls == ["memory_gpu_0000032"]
    # ... unless it ran with an older recipe
    scaling.write_json(other / "time_gpu_0000064.json", {"status": "oom", "recipe": {"gamma": 0.9}})
    fake = FakeLauncher()
    scaling.drive(scaling.plan(["memory"], [128]), scaling.DriveOptions(results=other), fake)
    assert fake.calls == ["memory_gpu_0000128"]


def test_memory_sweep_bisects_to_the_largest_count_that_fits(tmp_path):
    """65,536 fits and 98,304 does not: 81,920 and then 90,112 are tried; the gap then is one refinement step."""
    fits = lambda n: n <= 90112  # noqa: E731 - the fake GPU's capacity
    fake = FakeLauncher({n: ("ok" if fits(n) else "oom") for n in range(8192, 262145, 8192)})
    specs = scaling.plan(["memory", "cpu_time"], None)
    specs = [s for s in specs if s.kind != "memory" or s.num_envs >= 32768]  # keep the test's sweep short
    scaling.drive(scaling.with_refinement(specs, tmp_path), scaling.DriveOptions(results=tmp_path), fake)
    memory_calls = [c for c in fake.calls if c.startswith("memory")]
    assert memory_calls == ["memory_gpu_0032768", "memory_gpu_0065536", "memory_gpu_0098304",
                            "memory_gpu_0081920", "memory_gpu_0090112"]
    assert fake.calls[len(memory_calls):] == ["time_cpu_0000096", "time_cpu_0000032", "time_cpu_0000008"]
    assert scaling.refine_count(tmp_path) is None
    # nothing failed yet: no bisection
    assert scaling.refine_count(tmp_path / "empty") is None
    # a failure below every fit does not bound the search, nor does an OOM of an older recipe above it
    other = tmp_path / "other"
    current, older = scaling.recipe(), {**scaling.recipe(), "gamma": 0.9}
    scaling.write_json(other / "memory_gpu_0008192.json", {"kind": "memory", "status": "error", "recipe": current})
    scaling.write_json(other / "memory_gpu_0065536.json", {"kind": "memory", "status": "ok", "recipe": current})
    scaling.write_json(other / "memory_gpu_0081920.json", {"kind": "memory", "status": "oom", "recipe": older})
    assert scaling.refine_count(other) is None
    scaling.write_json(other / "time_gpu_0131072.json", {"kind": "time", "status": "oom", "recipe": current})
    assert scaling.refine_count(other) == 98304
    # a count the budget cut (no result) is not offered twice
    cut = tmp_path / "cut"
    scaling.write_json(cut / "memory_gpu_0065536.json", {"status": "ok", "recipe": scaling.recipe()})
    scaling.write_json(cut / "memory_gpu_0131072.json", {"status": "oom", "recipe": scaling.recipe()})
    offered = itertools.islice(scaling.with_refinement(scaling.plan(["memory"], [65536]), cut), 10)
    assert [s.num_envs for s in offered] == [65536, 98304]


def test_a_memory_run_stopped_early_proves_nothing(tmp_path):
    """Out-of-memory can strike late in training, so a memory run its deadline stopped before its iterations were
    done is neither a fit nor a failure: the sweep bisects around it, the driver measures it again, the report does
    not count it. A deadline-stopped time run that did more iterations than a memory run does count as a fit."""
    current = scaling.recipe()
    scaling.write_json(tmp_path / "memory_gpu_0065536.json", {"kind": "memory", "status": "ok", "recipe": current})
    scaling.write_json(tmp_path / "memory_gpu_0131072.json", {"kind": "memory", "status": "oom", "recipe": current})
    scaling.write_json(tmp_path / "memory_gpu_0098304.json", {"kind": "memory", "status": "partial", "iterations": 2,
                                                               "memory_iterations": 3, "recipe": current})
    assert scaling._result_counts(tmp_path, "gpu") == ([65536], [131072])
    assert scaling.refine_count(tmp_path) == 98304
    fake = FakeLauncher()
    outcome = scaling.drive(scaling.plan(["memory"], [65536, 98304]), scaling.DriveOptions(results=tmp_path), fake)
    assert fake.calls == ["memory_gpu_0098304"] and outcome["memory_gpu_0065536"] == "skipped (ok)"
    assert scaling.refine_count(tmp_path) == 114688  # 98,304 fits now
    # the report: partial memory runs are not fits; long partial time runs are
    records = [_record("memory", "gpu", 1024, used=2.0),
               {**_record("memory", "gpu", 2048, status="partial", used=3.0), "iterations": 2, "memory_iterations": 3},
               {**_record("time", "gpu", 8, status="partial", rate=600.0), "iterations": 39, "memory_iterations": 3}]
    idx = scaling_report.index(records)
    assert scaling_report.largest_fit(idx) == (1024, None)
    assert scaling.shows_fit(records[2]) and not scaling.shows_fit(records[1])
    # where a time run at that count finished, its numbers stand in for the memory run stopped early
    idx[("time", "gpu", 2048)] = _record("time", "gpu", 2048, rate=80_000.0, used=3.1)
    assert scaling_report.memory_record(idx, 2048)["kind"] == "time"
    assert scaling_report.largest_fit(idx) == (2048, None)


def test_driver_stops_when_the_budget_is_spent(tmp_path):
    fake = FakeLauncher()
    outcome = scaling.drive(scaling.plan(["cpu_time"]), scaling.DriveOptions(results=tmp_path, budget_s=0.0), fake)
    assert fake.calls == [] and outcome["time_cpu_0000096"] == "not started (budget)"
    # enough for the first launch but not for a second time run: one measurement, then stop
    fake = FakeLauncher()
    scaling.drive(scaling.plan(["cpu_time"]), scaling.DriveOptions(results=tmp_path / "b", budget_s=100.0), fake)
    assert fake.calls == ["time_cpu_0000096"]  # the quickest first


def test_oom_text_is_recognised():
    assert scaling._is_oom("torch.OutOfMemoryError: CUDA out of memory. Tried to allocate 2.00 GiB")
    assert scaling._is_oom("RuntimeError: Warp error: Failed to allocate 1073741824 bytes on device 'cuda:0'")
    assert not scaling._is_oom("ValueError: minibatch_size 512 exceeds the rollout")


# ------------------------------------------------------------------------------------------------ the report


def _record(kind, backend, n, status="ok", rate=None, rss=1.0, used=None, before=0.5, cores=1.5, raw=None):
    r = {"kind": kind, "backend": backend, "num_envs": n, "status": status, "host": {"peak_rss_gib": rss},
         "cpu": {"cores_used_mean": cores, "system_busy_cores_mean": cores + 0.1},
         "meta": {"gpu": "Test GPU 80GB" if backend == "gpu" else None, "available_cores": 16, "cpu_model": "test",
                  "date": "2026-01-01 00:00:00", "host": "h", "versions": {"torch": "x"}}}
    if kind != "raw":
        r["recipe"] = scaling.recipe()
    if rate is not None:
        steps = scaling.TARGET_ENV_STEPS
        r.update(env_steps=steps, train_wall_s=steps / rate, total_wall_s=steps / rate + 20.0, env_steps_per_s=rate,
                 config={"steps_per_env": scaling.ppo_sizing(n)[0], "minibatch_size": scaling.ppo_sizing(n)[1]})
    if used is not None:
        r["gpu"] = {"device_used_end_gib": used, "device_used_before_gib": before, "torch_peak_allocated_gib": used / 2,
                    "torch_peak_reserved_gib": used / 1.5, "device_total_gib": 79.2}
    if raw is not None:
        r["raw_policy_steps_per_s"] = raw
    return r


def _write(folder: Path, records: list[dict]) -> None:
    for r in records:
        scaling.write_json(folder / f"{r['kind']}_{r['backend']}_{r['num_envs']:07d}.json", r)


def _synthetic(gpu4096_over_cpu: float) -> list[dict]:
    cpu_best = 5000.0
    return [
        _record("time", "cpu", 8, rate=2000.0, cores=3.0),
        _record("time", "cpu", 96, rate=cpu_best, cores=12.0),
        _record("time", "gpu", 1024, rate=60_000.0, used=3.0, rss=2.00),
        _record("time", "gpu", 4096, rate=gpu4096_over_cpu * cpu_best, used=5.0, rss=2.05),
        _record("memory", "gpu", 16384, rate=120_000.0, used=17.0, rss=2.10),
        _record("memory", "gpu", 131072, status="oom"),
        _record("raw", "gpu", 4096, raw=180_000.0),
    ]


def _check(records, name_start):
    return next(c for c in scaling_report.checks(records) if c.name.startswith(name_start))


def test_checks_pass_and_fail_from_the_numbers():
    good, bad = _synthetic(20.0), _synthetic(5.0)
    assert _check(good, "GPU training at 4,096 envs vs the CPU").passed is True
    assert _check(good, "GPU training at 4,096 envs vs the CPU").value == pytest.approx(20.0)
    assert _check(bad, "GPU training at 4,096 envs vs the CPU").passed is False
    # 20 x 5,000 = 100,000 env-steps/s = 86x TocabiLab's 1,157: below the 100x target; 5x: far below
    assert _check(good, "GPU training at 4,096 envs vs TocabiLab").passed is False
    assert _check(good, "GPU training at 4,096 envs vs TocabiLab").value == pytest.approx(100_000 / 1157)
    assert _check(_synthetic(30.0), "GPU training at 4,096 envs vs TocabiLab").passed is True
    ram = _check(good, "Host RAM growth")
    assert ram.value == pytest.approx(0.05) and ram.passed is True
    per_env = scaling_report.gpu_memory_per_env(scaling_report.index(good))
    # device use 3 / 5 / 17 GiB at 1,024 / 4,096 / 16,384 envs: (17 - 3) GiB over 15,360 envs
    assert per_env["delta_1024_16384_mib_per_env"] == pytest.approx(14 * 1024 / 15360)
    assert per_env["slope_mib_per_env"] > 0
    assert scaling_report.largest_fit(scaling_report.index(good)) == (16384, 131072)


def test_checks_without_numbers_are_not_measured():
    records = [_record("time", "gpu", 4096, rate=1e5, used=5.0)]  # no CPU run, no 1,024/16,384
    assert _check(records, "GPU training at 4,096 envs vs the CPU").passed is None
    assert _check(records, "Host RAM growth").measured == scaling_report.NOT_MEASURED
    assert _check(records, "GPU training at 4,096 envs vs TocabiLab").passed is False  # 86x


def test_report_renders_markdown_json_and_figures(tmp_path):
    results = tmp_path / "scaling"
    _write(results, _synthetic(20.0))
    text = scaling_report.write_report(results, tmp_path)
    for name in ("scaling.md", "scaling.json", "scaling_time.png", "scaling_rate.png", "scaling_memory.png",
                 "scaling_cpu.png"):
        assert (tmp_path / name).stat().st_size > 0, name
    assert (tmp_path / "scaling.md").read_text() == text
    assert "**pass**" in text and "**fail**" in text
    assert "| GPU (mujoco-warp) | 8 |" in text and scaling_report.NOT_MEASURED in text  # 8 envs was not run
    assert "| 131,072 | short run | oom |" in text
    assert "raw_policy_steps_per_second" in text and "0.56" in text  # train/raw at 4096: 100,000 / 180,000
    assert "eq. 5.1" in text and scaling.CHUNKS[0] in text
    summary = json.loads((tmp_path / "scaling.json").read_text())
    assert len(summary["results"]) == 7 and summary["meta"]["gpu"] == "Test GPU 80GB"
    # the commands that ran, with what each measured, in the order they ran (no device bundle path)
    records = _synthetic(20.0)
    for i, r in enumerate(records):
        r["meta"]["date"] = f"2026-01-01 00:00:{i:02d}"
        r["part_command"] = f"python3 benchmarks/scaling.py --part {r['kind']} --bundle /root/out/b.json"
    records[-1]["part_command"] = "python3 benchmarks/scaling.py --part time --num_envs 8"  # the raw one, last
    stale = _record("memory", "gpu", 512)
    stale.update(status="stale", part_command="python3 benchmarks/scaling.py --part memory --num_envs 512")
    unrecorded = {**_record("memory", "gpu", 256), "part_command": "", "command": ""}
    undated = {**_record("memory", "gpu", 128), "part_command": "python3 benchmarks/scaling.py --part memory --x"}
    undated["meta"] = {}
    ran = scaling_report.commands_run([undated, *records, stale, unrecorded])
    assert ran[0] == ("python3 benchmarks/scaling.py --part time",
                      "time CPU at 8, 96 envs; time GPU at 1,024, 4,096 envs")
    assert [c for c, _ in ran] == ["python3 benchmarks/scaling.py --part time",
                                   "python3 benchmarks/scaling.py --part memory",
                                   "python3 benchmarks/scaling.py --part time --num_envs 8",
                                   "python3 benchmarks/scaling.py --part memory --x"]  # undated: last
    assert ran[1][1] == "memory GPU at 16,384, 131,072 envs" and ran[2][1] == "raw GPU at 4,096 envs"
    assert "## Commands that produced these results" in text
    assert summary["host_ram_growth_1024_16384"] == pytest.approx(0.05)


def test_report_with_no_results(tmp_path):
    text = scaling_report.write_report(tmp_path / "empty", tmp_path)
    assert text.count(scaling_report.NOT_MEASURED) > 10 and "**pass**" not in text


def test_report_leaves_out_stale_results(tmp_path):
    results = tmp_path / "scaling"
    records = _synthetic(20.0)
    records[3]["recipe"] = {**records[3]["recipe"], "gamma": 0.9}  # the 4,096-env GPU time run: older recipe
    _write(results, records)
    loaded = scaling_report.index(scaling_report.load_results(results))
    assert loaded[("time", "gpu", 4096)]["status"] == "stale"
    assert loaded[("time", "gpu", 4096)]["measured_status"] == "ok"
    assert _check(list(loaded.values()), "GPU training at 4,096 envs vs the CPU").passed is None
    text = scaling_report.write_report(results, tmp_path)
    assert "| GPU (mujoco-warp) | 4,096 |" in text and "stale" in text
