"""The benchmark harness on the CPU: every committed report regenerates from its JSON, and every benchmark runs end
to end at toy size (``--device cpu``); their GPU paths reuse the same helpers."""

from __future__ import annotations

import functools
import json
import os
import shutil
import subprocess
import sys
import time
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


def test_unknown_override_is_named():
    with pytest.raises(SystemExit, match="no option 'cuda_grpah'"):
        common.parse_overrides(["cuda_grpah=on"])
    with pytest.raises(SystemExit, match="no option 'cuda_graph'.*dotted paths"):  # the flat names are gone
        common.parse_overrides(["cuda_graph=on"])
    assert common.parse_overrides(["ppo.cuda_graph=on", "ppo.actor_hidden=8 8", "total_env_steps=2e3"]) == {
        "ppo.cuda_graph": "on", "ppo.actor_hidden": (8, 8), "total_env_steps": 2000}


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


def test_overlap_probe_runs_on_the_cpu_and_its_update_trains(tmp_path):
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


def test_step_timeline_marks_every_phase_of_the_real_trainer(tmp_path, monkeypatch):
    # Off CUDA the marks are host clocks. The env is made sync-free, as GPU training's is, so that its masked reset
    # runs every step and every phase is marked.
    from tocabi_torchrl.rl import trainer

    originals = {k: getattr(trainer, k) for k in ("make_collector", "make_loss", "guard_rollout", "_update")}
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


def test_solver_load_counts_the_trainer_and_the_raw_ceiling_on_warps_cpu(tmp_path):
    from warp_cpu import warp_cpu_available

    from tocabi_torchrl.rl import trainer

    if not warp_cpu_available():
        pytest.skip("warp's CPU device is not available here")
    originals = {k: getattr(trainer, k) for k in ("make_collector", "_update")}
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


def test_train_throughput_smoke_in_a_child_process_and_on_two_ranks(tmp_path):
    train_throughput.main(["--device", "cpu", "--num_envs", "8", "--iterations", "2", "--warmup", "1", "--nproc", "1",
                           "2", "--raw_steps", "0", "--set", "ppo.steps_per_env=8", "ppo.actor_hidden=8 8", "--out",
                           str(tmp_path), "--run_dir", str(tmp_path / "runs")])
    one, two = json.loads((tmp_path / "train_throughput.json").read_text())["results"]
    for r, k in ((one, 1), (two, 2)):
        assert r["num_envs"] == 8 and r["train_env_steps_per_s"] > 0 and r["overrides"]["ppo.actor_hidden"] == [8, 8]
        # 3 iterations of K x 8 envs x 8 steps: torchrun's K gloo ranks, counted together by rank 0
        assert r["gpus"] == k and r["iterations"] == 3 and r["env_steps"] == 3 * k * 64
    speedup = two["train_env_steps_per_s"] / one["train_env_steps_per_s"]
    assert f"| 2 | {speedup:.2f} | 8 |" in (tmp_path / "train_throughput.md").read_text()


@pytest.mark.slow
def test_scaling_measures_in_a_child_process_and_reports(tmp_path):
    args = ["--kind", "time", "--backend", "cpu", "--num_envs", "8", "--hidden", "8", "--max_minutes", "0.02",
            "--results", str(tmp_path / "scaling"), "--run_dir", str(tmp_path / "runs")]
    scaling.main(args)
    first = json.loads((tmp_path / "scaling" / "time_cpu_0000008.json").read_text())
    assert first["status"] == "partial" and 0 < first["env_steps"] < scaling.TARGET and first["host"]["peak_rss_gib"]
    scaling.main(args)  # an existing result is kept unless its status is redone
    assert json.loads((tmp_path / "scaling" / "time_cpu_0000008.json").read_text()) == first
    scaling.main(["--report", "--results", str(tmp_path / "scaling")])
    assert "| CPU (C MuJoCo) | 8 | 256 / 512 | - |" in (tmp_path / "scaling.md").read_text()


def test_scaling_keeps_a_failed_measurement_as_a_status_says_so_and_still_reports(tmp_path, monkeypatch, capsys):
    # A time or raw run that failed or ran out of memory has no rates: --report once died on its record (KeyError),
    # and a failed measurement exited 0 without its cause.
    results, base = tmp_path / "scaling", ["--results", str(tmp_path / "scaling"), "--run_dir", str(tmp_path / "runs")]
    shutil.copytree(common.DOCS / "scaling", results)  # the committed results, plus the failures below

    def child(module, args, env=None, nproc=None):
        oom = args[args.index("--num_envs") + 1] == "131072"
        raise RuntimeError("python -m lab.benchmarks.train_throughput --child ... failed (1):\nTraceback (...)\n"
                           + ("torch.OutOfMemoryError: CUDA out of memory" if oom else
                              "AssertionError: Torch not compiled with CUDA enabled"))

    monkeypatch.setattr(common, "run_child", child)
    with pytest.raises(SystemExit, match="failed at 8192 envs"):
        scaling.main(["--kind", "time", "--num_envs", "8192", "131072", *base])
    out = capsys.readouterr().out
    assert "time_gpu_0008192.json: the measurement failed: AssertionError: Torch not compiled with CUDA" in out
    assert "time_gpu_0131072.json: oom" in out  # a result: no failure
    with pytest.raises(SystemExit, match="failed at 2048 envs"):
        scaling.main(["--kind", "raw", "--num_envs", "2048", *base])
    with pytest.raises(SystemExit, match="failed at 8192 envs"):  # kept, not measured again: still failed
        scaling.main(["--kind", "time", "--num_envs", "8192", *base])
    assert "kept time_gpu_0008192.json (status error; --redo error measures it again)" in capsys.readouterr().out
    scaling.main(["--report", *base[:2]])
    text = (tmp_path / "scaling.md").read_text()
    for n, status in (("8,192", "error"), ("131,072", "oom")):
        assert f"| GPU (mujoco-warp) | {n} |{' - |' * 8} {status} |" in text
    assert "| 4,096 | 116,255 |" in text  # the measured rows as before


@pytest.mark.slow  # a faulty training run of 15 s (two rollouts at least on a loaded 2-core machine)
def test_tiny_soak_on_the_cpu(tmp_path):
    code = soak.main(["--num_envs", "8", "--minutes", "0.25", "--device", "cpu", "--fault_every", "40",
                      "--out", str(tmp_path), "--run_dir", str(tmp_path / "runs")])
    report = json.loads((tmp_path / "soak.json").read_text())
    assert code == 0 and report["results"] and not [c for c in report["results"] if not c["ok"]]
    faults = report["meta"]["faults"]
    assert faults["fault_events"] >= 1 and faults["monitor"]["nan_worlds"] == faults["fault_events"]
    assert [r["rollout"] for r in faults["memory_series"]] == list(range(1, len(faults["memory_series"]) + 1))
    assert (tmp_path / "soak_memory.png").stat().st_size > 1000


def _time_to_walk(cwd, *args, code=0, nproc=0) -> str:
    """``python -m lab.benchmarks.time_to_walk ARGS`` in ``cwd`` (under torchrun with ``nproc`` ranks): its output."""
    launch = ["-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(nproc)] if nproc else []
    env = {**os.environ, "PYTHONPATH": str(common.DOCS.parents[1])}  # the run's cwd is a temporary folder
    proc = subprocess.run([sys.executable, *launch, "-m", "lab.benchmarks.time_to_walk", *args], cwd=cwd, text=True,
                          capture_output=True, env=env, check=False, timeout=600)
    assert proc.returncode == code, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc.stdout + proc.stderr


def test_time_to_walk_train_resume_eval_report(tmp_path):
    run = functools.partial(_time_to_walk, tmp_path)
    # 20 iterations (~2.5 s on a CPU) pass a 1 s snapshot mark; the first call stops at 1.8 s, the second resumes
    train = ["train", "--preset", "cpu_smoke", "--device", "cpu", "--every", "0.017", "--log_every", "1",
             "--set", f"total_env_steps={8 * 16 * 20}"]
    run(*train, "--minutes", "0.03", "--budget_minutes", "1")
    assert "training from runs/time_to_walk/cpu_smoke/checkpoints/latest.pt" in run(*train, "--budget_minutes", "1")
    folder = tmp_path / "runs/time_to_walk/cpu_smoke"
    walls = sorted(p.stem for p in (folder / "checkpoints").glob("wall_*.pt"))
    run("eval", "--preset", "cpu_smoke", "--device", "cpu", "--num_envs", "2", "--seconds", "0.1")
    record = {**json.loads((folder / "train.json").read_text()), **json.loads((folder / "evals.json").read_text())}
    assert walls and sorted(record["evaluations"]) == walls and len(record["commands"]) == 2
    assert record["overrides"] == {"total_env_steps": 8 * 16 * 20}
    # Continuing it with other overrides would mix two configs in one time-to-walk record.
    assert "trained with --set total_env_steps=2560 so far, this call has --set (none)" in run(
        "train", "--preset", "cpu_smoke", "--device", "cpu", "--every", "0", code=1)
    for entry in record["evaluations"].values():  # 0.1 s cannot cover 2.6 m
        assert 0.0 <= entry["commands"]["0.5,0.0"]["survival"] <= 1.0 and entry["walks"] is False
        assert entry["device"] == "cpu"
    text = run("report", "--runs", str(folder), "--curves", str(folder), "--out", str(tmp_path / "d"))
    assert record["time_to_walk"] is None and "| cpu_smoke | cpu | not within" in text
    assert "| no | cpu |" in text  # each checkpoint's row says where it was tested
    assert (tmp_path / "d/time_to_walk.png").is_file() and (tmp_path / "d/time_to_walk_curves.png").is_file()


def test_time_to_walk_names_the_gpu_of_any_cuda_device_string(monkeypatch):
    import torch

    from tocabi_torchrl.evaluation.gait_test import tested_on  # what time_to_walk and the library table record

    seen = []
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda dev: seen.append(dev) or f"GPU {dev.index}")
    assert tested_on("cpu") == "cpu" and not seen
    assert tested_on("cuda:1") == "GPU 1" and tested_on("cuda") == "GPU None"


def test_time_to_walk_trains_on_two_ranks_under_torchrun(tmp_path):
    """The 2-GPU command of docs/training.md on gloo ranks: rank 0 alone keeps the named run's record."""
    train = ["train", "--preset", "cpu_smoke", "--name", "smoke_2gpu", "--device", "cpu", "--minutes", "0.004"]
    out = _time_to_walk(tmp_path, *train, "--every", "0", "--log_every", "1", nproc=2)
    record = json.loads((tmp_path / "runs/time_to_walk/smoke_2gpu/train.json").read_text())
    assert (record["preset"], record["name"], record["gpus"]) == ("cpu_smoke", "smoke_2gpu", 2)
    assert record["commands"][0].startswith("torchrun --standalone --nproc_per_node 2 -m lab.benchmarks.time_to_walk")
    latest = torch.load(tmp_path / "runs/time_to_walk/smoke_2gpu/checkpoints/latest.pt", weights_only=True)
    assert record["env_steps"] == latest["env_steps"] == 2 * 8 * 16 * latest["iteration"]  # both ranks' steps
    assert out.count("training from scratch on 2 rank(s)") == 1 and out.count("[train took") == 1
    # A run is continued on the rank count it was trained on (its rate and ratio are per rank count).
    assert "was trained on 2 rank(s) so far, this call has 1" in _time_to_walk(tmp_path, *train, code=1)


def test_train_throughput_counts_the_whole_set_up_and_the_cores_of_the_timed_training_only(tmp_path, monkeypatch):
    # setup_s once counted only the argument parsing (the set-up happens inside train(), before its clock starts),
    # and cores_used_mean divided the set-up's CPU time too by the training's wall time. Here train() keeps a core
    # busy for 0.4 s setting up, then its timed training idles for 0.3 s.
    from tocabi_torchrl.rl import trainer

    def train(cfg):
        end = time.process_time() + 0.4
        while time.process_time() < end:  # building the env, compiling, the agent
            pass
        trainer.make_collector(cfg, None, None, None, 0)  # the trainer starts its clock right after
        time.sleep(0.3)
        rows = [{"env_steps": str(64 * k), "wall_s": str(0.1 * k), "update_s": "0.01"} for k in (1, 2, 3)]
        return SimpleNamespace(env_steps=192, wall_seconds=0.3, iterations=3, env_graph=False), rows

    monkeypatch.setattr(trainer, "make_collector", lambda *a, **k: "collector")
    monkeypatch.setattr(common, "train", train)
    monkeypatch.setattr(train_throughput, "STARTED", time.perf_counter())  # as if this process started now
    r = train_throughput.measure(8, 2, 1, 0, "cpu", str(tmp_path), {})
    assert r["train_wall_s"] == 0.3 and r["setup_s"] >= 0.4 and r["cores_used_mean"] < 0.5, r
    assert trainer.make_collector(None) == "collector"  # the trainer is itself again


def test_time_to_walk_train_on_any_cuda_device_records_its_gpu_and_raw_ceiling(tmp_path, monkeypatch):
    # `--device cuda:1` once recorded the GPU as "cpu" and skipped the raw ceiling; the report then went to
    # runs/benchmarks_cpu as a CPU smoke run's. The trainer and the GPU are stand-ins here.
    monkeypatch.chdir(tmp_path)
    cfg = SimpleNamespace(resume="", max_minutes=1.0, env=SimpleNamespace(num_envs=4096), to_dict=dict)
    rows = [{"env_steps": str(4096 * 48 * i), "wall_s": str(1.5 * i)} for i in range(1, 8)]
    raw_on = []
    monkeypatch.setattr(common, "config", lambda preset, **kw: cfg)
    monkeypatch.setattr(common, "train", lambda c: (SimpleNamespace(env_steps=4096 * 48 * 7, wall_seconds=10.5), rows))
    monkeypatch.setattr(common, "raw_policy_steps_per_second",
                        lambda n, steps, device="cuda": raw_on.append(device) or 180_000.0)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda dev=None: f"GPU {getattr(dev, 'index', None)}")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(common, "DOCS", tmp_path / "docs")
    monkeypatch.setattr(common, "CPU_OUT", tmp_path / "cpu")
    time_to_walk.main(["train", "--preset", "default", "--device", "cuda:1", "--every", "0"])
    record = json.loads((tmp_path / "runs/time_to_walk/default/train.json").read_text())
    assert record["gpu"] == "GPU 1" and raw_on == ["cuda:1"] and record["raw_policy_steps_per_s"] == 180_000.0
    time_to_walk.main(["report", "--runs", "runs/time_to_walk/default", "--out", str(tmp_path / "docs")])
    assert "| default | GPU 1 |" in (tmp_path / "docs/time_to_walk.md").read_text()


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


def test_time_to_walk_on_a_machine_without_cuda_is_one_error_line(monkeypatch, capsys):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(SystemExit) as stop:
        time_to_walk.main(["train", "--preset", "torque"])
    assert stop.value.code == 2 and "--device cpu" in capsys.readouterr().err


def test_override_path():
    # a dotted config path with its value, checked against the config tree's choices
    from lab.benchmarks.common import parse_overrides
    from tocabi_torchrl.config import field_choices

    assert parse_overrides(["env.sim.reset_pass=reduced"]) == {"env.sim.reset_pass": "reduced"}
    assert field_choices()["env.sim.reset_pass"] == ("full", "reduced")


def test_robust_policies_table_names_each_case_and_its_verdict(tmp_path):
    """lab.benchmarks.robust_policies on the CPU (2 robots per case, 0.1 s): one row per policy and case, a ✗ on a
    missed threshold, each policy's own report beside the table."""
    import json

    from lab.benchmarks import robust_policies

    policy = robust_policies.POLICIES / "tocabi_walk_ppo.pt"
    if not policy.is_file():
        pytest.skip("shipped policy not present")
    robust_policies.main(["--policies", str(policy), "--num_envs", "2", "--seconds", "0.1", "--device", "cpu",
                          "--out", str(tmp_path)])
    data = json.loads((tmp_path / "robust_policies.json").read_text())
    (row,) = data["results"]
    assert row["policy"] == "tocabi_walk_ppo" and set(row["cases"]) == {"nominal", "commands", "robust_0.5",
                                                                         "robust_1.0"}
    assert row["passes"] is False  # 0.1 s cannot cover the 2.6 m the nominal case asks for
    page = (tmp_path / "robust_policies.md").read_text()
    assert "| tocabi_walk_ppo | nominal |" in page and "✗" in page and "python -m lab.benchmarks.robust_policies" in page
    assert (tmp_path / "tocabi_walk_ppo" / "robust.json").is_file()
