"""lab.benchmarks.time_to_walk on the CPU at toy size: train, resume, evaluate and report a cpu_smoke run, train it on
two gloo ranks under torchrun, and the GPU names and refusals its records depend on."""

from __future__ import annotations

import functools
import json
import math
import os
import shutil
import subprocess
import sys
from types import SimpleNamespace

import pytest
import torch

from lab.benchmarks import common, time_to_walk
from tocabi_torchrl.config import wall_seconds


#: A robust report's settings as the full robust gait test writes them (evaluation/robust.py).
FULL_TEST = {"num_envs": 1024, "seconds": 8.0, "push_count": 3, "push_window_s": [2.0, 7.0], "push_kind": "velocity"}


def _time_to_walk(cwd, *args, code=0, nproc=0) -> str:
    """``python -m lab.benchmarks.time_to_walk ARGS`` in ``cwd`` (under torchrun with ``nproc`` ranks): its output."""
    launch = ["-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(nproc)] if nproc else []
    env = {**os.environ, "PYTHONPATH": str(common.DOCS.parents[1])}  # the run's cwd is a temporary folder
    proc = subprocess.run([sys.executable, *launch, "-m", "lab.benchmarks.time_to_walk", *args], cwd=cwd, text=True,
                          capture_output=True, env=env, check=False, timeout=600)
    assert proc.returncode == code, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc.stdout + proc.stderr


def _time_to_walk_here(capsys, *args, error: str | None = None) -> str:
    """``time_to_walk.main(ARGS)`` in this process and its current folder (``runs/`` is relative to it): what it
    printed. With ``error``, the call must end as the command line ends on a refused run: ``sys.exit("error: ...")``
    (one line on stderr, exit status 1), its message holding ``error``. A fresh interpreter per call cost ~6 s of
    imports each; the module's own command line is run under torchrun below."""
    if error is None:
        time_to_walk.main(list(args))
    else:
        with pytest.raises(SystemExit) as stop:
            time_to_walk.main(list(args))
        message = stop.value.code
        assert isinstance(message, str) and message.startswith("error: ") and error in message, message
    printed = capsys.readouterr()
    return printed.out + printed.err


def test_time_to_walk_train_resume_eval_report(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    run = functools.partial(_time_to_walk_here, capsys)
    # 20 iterations (~2.5 s on a CPU) pass a 1 s snapshot mark; the first call stops at 1.8 s, the second resumes
    train = ["train", "--preset", "cpu_smoke", "--device", "cpu", "--every", "0.017", "--log_every", "1",
             "--set", f"total_env_steps={8 * 16 * 20}"]
    run(*train, "--minutes", "0.03", "--budget_minutes", "1")
    assert "training from runs/time_to_walk/cpu_smoke/checkpoints/latest.pt" in run(*train, "--budget_minutes", "1")
    folder = tmp_path / "runs/time_to_walk/cpu_smoke"
    walls = sorted(p.stem for p in (folder / "checkpoints").glob("wall_*.pt"))
    # Only the last mark first (--from_minutes at its training second), then the rest: each is tested once.
    last_s = wall_seconds(walls[-1])
    run("eval", "--preset", "cpu_smoke", "--device", "cpu", "--num_envs", "2", "--seconds", "0.1", "--from_minutes",
        str(last_s / 60))
    assert sorted(json.loads((folder / "evals.json").read_text())["evaluations"]) == [walls[-1]]
    summary = json.loads((folder / "eval" / walls[-1] / "0.5_0.0" / "summary.json").read_text())
    assert summary["checkpoint"].endswith(f"{walls[-1]}.pt")  # the file each report is of, beside the others
    run("eval", "--preset", "cpu_smoke", "--device", "cpu", "--num_envs", "2", "--seconds", "0.1")
    record = {**json.loads((folder / "train.json").read_text()), **json.loads((folder / "evals.json").read_text())}
    assert walls and sorted(record["evaluations"]) == walls and len(record["commands"]) == 2
    assert record["overrides"] == {"total_env_steps": 8 * 16 * 20}
    # Continuing it with other overrides would mix two configs in one time-to-walk record.
    run("train", "--preset", "cpu_smoke", "--device", "cpu", "--every", "0",
        error="trained with --set total_env_steps=2560 so far, this call has --set (none)")
    for entry in record["evaluations"].values():  # 0.1 s cannot cover 2.6 m
        assert 0.0 <= entry["commands"]["0.5,0.0"]["survival"] <= 1.0 and entry["walks"] is False
        assert entry["device"] == "cpu"
    text = run("report", "--runs", str(folder), "--curves", str(folder), "--out", str(tmp_path / "d"))
    assert record["time_to_walk"] is None and "| cpu_smoke | cpu | not within" in text
    # With its last marks untested, the cell says how far the tests reached, not that the whole run missed.
    evals = json.loads((folder / "evals.json").read_text())
    last = max(e["train_seconds"] for e in evals["evaluations"].values())
    partial = {**record, "train_seconds": last + 60 * record["config"]["checkpoint_minutes"] + 1}
    assert f"not by {last / 60:.1f} min, the last tested of " in time_to_walk._not_within(partial)
    assert "| no | cpu |" in text  # each checkpoint's row says where it was tested
    assert (tmp_path / "d/time_to_walk.png").is_file() and (tmp_path / "d/time_to_walk_curves.png").is_file()
    # The robust test's results of a GPU run (lab.benchmarks.robust_policies --out DIR) read in, not re-tested:
    # the verdict re-checked from the values (a report's own "passes" is not trusted), the GPU's name kept, a
    # checkpoint without a report left out, and --reports refused without --test robust (or diverse).
    reports = tmp_path / "verdict"
    cases = {"nominal": {"survival": 1.0, "forward_distance_m": {"mean": 4.0}, "lateral_drift_m": {"p95": 0.29}},
             "commands": {"survival": 1.0, "tracking_error_mps": {"mean": 0.1}},
             "robust_0.5": {"survival": 0.99}, "robust_1.0": {"survival": 0.9}}
    toppled = {**cases, "robust_1.0": {"survival": 0.5}}  # fails the kicks alone: not robust, walks by "diverse"
    later = "wall_09999s"  # a second mark: the first's checkpoint under a later name
    shutil.copy(folder / "checkpoints" / f"{walls[0]}.pt", folder / "checkpoints" / f"{later}.pt")
    for stem, its_cases in ((walls[0], cases), (later, toppled)):
        (reports / stem).mkdir(parents=True)
        (reports / stem / "robust.json").write_text(json.dumps(
            {"test": "robust", "passes": True, "tested_on": "NVIDIA H200", "settings": FULL_TEST, "cases": its_cases}))
    # The second mark's verdict came from a second robust_policies call, into a folder of its own.
    (tmp_path / "verdict2").mkdir()
    (reports / later).rename(tmp_path / "verdict2" / later)
    text = run("eval", "--preset", "cpu_smoke", "--device", "cpu", "--test", "robust", "--reports", str(reports),
               str(tmp_path / "verdict2"))
    shutil.copytree(tmp_path / "verdict2" / later, reports / later)
    robust = json.loads((folder / "evals_robust.json").read_text())
    assert {k: (e["walks"], e["device"]) for k, e in robust["evaluations"].items()} == \
        {walls[0]: (True, "NVIDIA H200"), later: (False, "NVIDIA H200")}
    assert all(f"{w}: no " in text for w in walls[1:])
    assert robust["time_to_walk"]["iteration"] == robust["evaluations"][walls[0]]["iteration"]
    # --test diverse (issue 50's verdict): the same reports' nominal and commands cases alone decide.
    run("eval", "--preset", "cpu_smoke", "--device", "cpu", "--test", "diverse", "--reports", str(reports))
    diverse = json.loads((folder / "evals_diverse.json").read_text())
    assert {k: e["walks"] for k, e in diverse["evaluations"].items()} == {walls[0]: True, later: True}
    assert all(set(e["cases"]) == {"nominal", "commands"} and e["test"] == "diverse"
               for e in diverse["evaluations"].values())
    text = run("report", "--test", "diverse", "--runs", str(folder), "--out", str(tmp_path / "d"))
    assert "unperturbed cases" in text and "push 1.0" not in text and "drift p95 [m]" in text
    assert (tmp_path / "d" / "time_to_walk_diverse.md").is_file()
    # A report of the two unperturbed cases alone cannot decide the robust test: left out, not a "no".
    partial = tmp_path / "verdict_partial" / walls[0]
    partial.mkdir(parents=True)
    (partial / "robust.json").write_text(json.dumps({"test": "robust", "tested_on": "NVIDIA H200",
                                                     "settings": FULL_TEST,
                                                     "cases": {k: cases[k] for k in ("nominal", "commands")}}))
    (folder / "evals_robust.json").rename(tmp_path / "evals_robust.json")
    text = run("eval", "--preset", "cpu_smoke", "--device", "cpu", "--test", "robust", "--reports", str(partial.parent))
    assert "lacks the case(s) robust_0.5, robust_1.0 of the robust test; left out" in text
    # Nor can a quick screen of fewer robots: it was once recorded as the mark's verdict.
    (partial / "robust.json").write_text(json.dumps({"test": "robust", "tested_on": "NVIDIA H200",
                                                     "settings": {**FULL_TEST, "num_envs": 64}, "cases": cases}))
    text = run("eval", "--preset", "cpu_smoke", "--device", "cpu", "--test", "robust", "--reports", str(partial.parent))
    assert "was tested with num_envs 64 (the test's 1024); left out (pass --num_envs/--seconds" in text
    # A report of other kicks is of another test: no option of this command records it.
    (partial / "robust.json").write_text(json.dumps({"test": "robust", "tested_on": "NVIDIA H200",
                                                     "settings": {**FULL_TEST, "push_count": 1}, "cases": cases}))
    text = run("eval", "--preset", "cpu_smoke", "--device", "cpu", "--test", "robust", "--reports", str(partial.parent))
    assert "left out (its kicks are not the test's: test the checkpoint again)" in text
    # A mark's report copied back without its checkpoint was left out without a word.
    orphan = partial.parent / "wall_99999s"
    orphan.mkdir()
    (orphan / "robust.json").write_text(json.dumps({"test": "robust", "tested_on": "NVIDIA H200",
                                                    "settings": FULL_TEST, "cases": cases}))
    text = run("eval", "--preset", "cpu_smoke", "--device", "cpu", "--test", "robust", "--reports", str(partial.parent))
    missing = "runs/time_to_walk/cpu_smoke/checkpoints/wall_99999s.pt"
    assert f"wall_99999s: a report in {partial.parent} but no {missing}; left out" in text
    assert f"{walls[0]}: a report" not in text
    shutil.rmtree(orphan)
    assert not (folder / "evals_robust.json").exists()  # each mark left out: nothing recorded, nothing written
    (tmp_path / "evals_robust.json").replace(folder / "evals_robust.json")
    (folder / "evals_diverse.json").unlink()  # tested here: only the two unperturbed cases run
    run("eval", "--preset", "cpu_smoke", "--device", "cpu", "--test", "diverse", "--num_envs", "2", "--seconds", "0.2")
    diverse = json.loads((folder / "evals_diverse.json").read_text())
    assert all(set(e["cases"]) == {"nominal", "commands"} and e["device"] == "cpu" and e["settings"]["num_envs"] == 2
               for e in diverse["evaluations"].values())
    (folder / "evals_robust.json").unlink()  # two folders with one checkpoint's report: which one is named
    run("eval", "--preset", "cpu_smoke", "--device", "cpu", "--test", "robust", "--reports", str(reports),
        str(tmp_path / "verdict2"), error=f"{later}: a report in each of {reports / later / 'robust.json'}")
    (folder / "evals_robust.json").unlink(missing_ok=True)  # read again: a corrupt report is named, not a bare error
    (reports / later / "robust.json").write_text("{not json")
    run("eval", "--preset", "cpu_smoke", "--device", "cpu", "--test", "robust", "--reports", str(reports),
        error=f"{reports / later / 'robust.json'} is not valid JSON")
    with pytest.raises(SystemExit) as stop:
        time_to_walk.main(["eval", "--preset", "cpu_smoke", "--device", "cpu", "--reports", str(reports)])
    assert stop.value.code == 2 and "pass --test robust (or diverse) with it" in capsys.readouterr().err


def test_time_to_walk_names_the_gpu_of_any_cuda_device_string(monkeypatch):
    import torch

    from tocabi_torchrl.evaluation.gait_test import tested_on  # what time_to_walk and the library table record

    seen = []
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda dev: seen.append(dev) or f"GPU {dev.index}")
    assert tested_on("cpu") == "cpu" and not seen
    assert tested_on("cuda:1") == "GPU 1" and tested_on("cuda") == "GPU None"


def test_time_to_walk_trains_on_two_ranks_under_torchrun(tmp_path, monkeypatch, capsys):
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
    monkeypatch.chdir(tmp_path)  # the same call on one rank, in this process (no torchrun: one rank)
    _time_to_walk_here(capsys, *train, error="was trained on 2 rank(s) so far, this call has 1")


def _stand_in_training(tmp_path, monkeypatch) -> list[str]:
    """The trainer, the raw ceiling and a GPU as stand-ins, ``runs/`` under ``tmp_path``: the devices the raw
    ceiling is measured on (filled as it is)."""
    monkeypatch.chdir(tmp_path)
    cfg = SimpleNamespace(resume="", max_minutes=1.0, env=SimpleNamespace(num_envs=4096),
                          to_dict=lambda: {"env": {"num_envs": 4096}})
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
    return raw_on


def test_time_to_walk_train_on_any_cuda_device_records_its_gpu_and_raw_ceiling(tmp_path, monkeypatch):
    # `--device cuda:1` once recorded the GPU as "cpu" and skipped the raw ceiling; the report then went to
    # runs/benchmarks_cpu as a CPU smoke run's. The trainer and the GPU are stand-ins here.
    raw_on = _stand_in_training(tmp_path, monkeypatch)
    time_to_walk.main(["train", "--preset", "default", "--device", "cuda:1", "--every", "0"])
    record = json.loads((tmp_path / "runs/time_to_walk/default/train.json").read_text())
    assert record["gpu"] == "GPU 1" and raw_on == ["cuda:1"] and record["raw_policy_steps_per_s"] == 180_000.0
    time_to_walk.main(["report", "--runs", "runs/time_to_walk/default", "--out", str(tmp_path / "docs")])
    assert "| default | GPU 1 |" in (tmp_path / "docs/time_to_walk.md").read_text()


def test_time_to_walk_on_a_machine_without_cuda_is_one_error_line(monkeypatch, capsys):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(SystemExit) as stop:
        time_to_walk.main(["train", "--preset", "torque"])
    assert stop.value.code == 2 and "--device cpu" in capsys.readouterr().err


def test_time_to_walk_help_gives_each_default_and_its_errors_say_error(tmp_path, capsys):
    # Several options left their defaults out of --help, the subcommands had no description, and a missing run
    # folder or an unknown --set path ended without the "error:" the other refusals have.
    for part, skip in (("train", {"name", "set"}), ("eval", {"name", "num_envs", "from_minutes", "reports"}),
                       ("report", {"runs", "curves"})):
        with pytest.raises(SystemExit):
            time_to_walk.main([part, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert text.startswith(f"usage: python -m lab.benchmarks.time_to_walk {part}")
        text = text.split("options:", 1)[1]  # the options' help, after the usage line
        for option in {"train": ("preset", "device", "minutes", "budget_minutes", "every", "log_every", "raw_steps"),
                       "eval": ("preset", "device", "seconds", "test", "follow_pid"),
                       "report": ("out", "test")}[part]:
            assert option not in skip
            after = text.split(f"--{option} ", 1)[1].split(" --", 1)[0]
            assert "(default:" in after, f"{part} --{option} does not say its default"
    with pytest.raises(SystemExit) as stop:
        time_to_walk.main(["report", "--runs", str(tmp_path / "nope"), "--out", str(tmp_path)])
    assert str(stop.value.code).startswith(f"error: {tmp_path / 'nope'}: no train.json")
    with pytest.raises(SystemExit) as stop:
        common.parse_overrides(["ppo.lrr=1"])
    assert str(stop.value.code).startswith("error: --set ppo.lrr=1: the training config has no option 'ppo.lrr'; "
                                           "did you mean ppo.lr")


def test_time_to_walk_renders_a_robust_report_with_a_missing_case_and_a_first_pass(tmp_path, monkeypatch):
    """The robust report: its table, the pushed cases' panel, a case an evaluation lacks (shown as "-", plotted as
    a gap), the first passing checkpoint, and runs screened on a CPU marked so."""
    pytest.importorskip("matplotlib")

    def case(survival, **extra):
        return {"survival": survival, **extra}

    def evaluation(minutes, walks, pushed_10):
        cases = {"nominal": case(1.0, forward_distance_m={"mean": 3.0}, lateral_drift_m={"p95": 0.2}),
                 "commands": case(1.0, tracking_error_mps={"mean": 0.08}), "robust_0.5": case(0.98)}
        if pushed_10 is not None:
            cases["robust_1.0"] = case(pushed_10)
        return {"train_seconds": 60.0 * minutes, "env_steps": int(minutes * 1e7), "iteration": minutes,
                "device": "cpu", "test": "robust", "cases": cases, "walks": walks}

    record = {"preset": "robust", "name": "robust_x", "gpu": "NVIDIA H200", "train_seconds": 1800.0,
              "evaluations": {"wall_00180s": evaluation(3, False, None), "wall_00360s": evaluation(6, True, 0.9)},
              "time_to_walk": {"train_minutes": 6.0, "env_steps": 60_000_000, "iteration": 6}}
    text = time_to_walk.render({"command": "x", "test": "robust", "records": [record]}, tmp_path)
    assert "| robust_x | NVIDIA H200 | 6.0 | 60.0 M |" in text and "| wall_00180s | 3.0 |" in text
    row = next(line for line in text.splitlines() if line.startswith("| wall_00180s"))
    assert "| - |" in row and row.endswith("| no | cpu |")
    assert (tmp_path / "time_to_walk_robust.png").stat().st_size > 0
    drawn = {}
    monkeypatch.setattr(time_to_walk.common, "plot", lambda path, panels, title="": drawn.update(panels=panels))
    time_to_walk.render({"command": "x", "test": "robust", "records": [record]}, tmp_path)
    pushed = drawn["panels"][2]
    x, y = pushed["lines"]["robust_x (tested on a CPU), robust_1.0"]
    assert x == [3.0, 6.0] and math.isnan(y[0]) and y[1] == pytest.approx(90.0)
    assert pushed["lines"]["robust_x (tested on a CPU), robust_0.5"][1] == pytest.approx([98.0, 98.0])
    assert [(h[0], h[2]) for h in pushed["hlines"]] == [(97.0, "--"), (85.0, ":")] and pushed["vlines"] == [6.0]


def test_time_to_walk_eval_of_no_checkpoint_says_so(tmp_path, monkeypatch, capsys):
    # A run folder copied back without its checkpoints (the robust reports beside it), or a --from_minutes past the
    # last mark, once ended on "time to walk: null" as if every mark had been tested and failed.
    monkeypatch.chdir(tmp_path)
    folder = tmp_path / "runs/time_to_walk/r"
    (folder / "checkpoints").mkdir(parents=True)
    (folder / "train.json").write_text(json.dumps({"preset": "robust", "train_seconds": 120.0}))
    (tmp_path / "verdict").mkdir()
    run = functools.partial(_time_to_walk_here, capsys, "eval", "--name", "r", "--test", "robust", "--reports",
                            str(tmp_path / "verdict"))
    run(error="holds no wall_*.pt checkpoint to test")
    (folder / "checkpoints" / "wall_00060s.pt").write_bytes(b"")  # not read: no mark is of minute 5 or later
    run("--from_minutes", "5", error="no checkpoint of runs/time_to_walk/r is of minute 5 or later (--from_minutes); "
                                     "its last is wall_00060s (1 min)")
    assert not (folder / "evals_robust.json").exists()


def test_time_to_walk_report_shows_a_survival_of_zero_and_a_dash_for_a_command_not_run(tmp_path, monkeypatch):
    # A checkpoint whose robots all fell at (0.7, 0.1) read "-" there, as if that command had not run.
    monkeypatch.setattr(time_to_walk.common, "plot", lambda *args, **kwargs: None)
    main = {"seconds": 8.0, "num_envs": 256, "survival": 1.0, "forward_distance_m": 3.0, "lateral_drift_m": 0.1,
            "knee_rms_rad": 0.08}
    commands = {"0.5,0.0": main, "0.7,0.1": {**main, "survival": 0.0}}
    evaluation = {"train_seconds": 60.0, "env_steps": 100, "iteration": 1, "device": "cpu", "walks": False,
                  "commands": commands}
    record = {"preset": "default", "gpu": "cpu", "train_seconds": 60.0, "evaluations": {"wall_00060s": evaluation}}
    text = time_to_walk.render({"command": "x", "records": [record]}, tmp_path)
    row = next(line for line in text.splitlines() if line.startswith("| wall_00060s"))
    assert row.split(" | ")[7:9] == ["-", "0.000"]  # (0.2, 0) not run, (0.7, 0.1) all fell


def test_time_to_walk_report_says_how_long_and_on_how_many_robots_a_screen_tested(tmp_path, monkeypatch):
    # A CPU screen's report (eval --num_envs 4 --seconds 0.5) read "survival over 8 s" on its plots, and its text
    # gave the 8 s, 256-robot test as what its checkpoints had passed or not.
    drawn = {}
    monkeypatch.setattr(time_to_walk.common, "plot", lambda path, panels, title="": drawn.update(panels=panels))
    main = {"seconds": 0.5, "num_envs": 4, "survival": 0.0, "forward_distance_m": 0.1, "lateral_drift_m": 0.0,
            "knee_rms_rad": 0.5}
    evaluation = {"train_seconds": 60.0, "env_steps": 100, "iteration": 1, "device": "cpu", "walks": False,
                  "commands": {"0.5,0.0": main}}
    record = {"preset": "torque", "gpu": "cpu", "train_seconds": 60.0, "evaluations": {"wall_00060s": evaluation}}
    text = time_to_walk.render({"command": "x", "records": [record]}, tmp_path)
    assert "Tested with 4 robots for 0.5 s, not the test's 256 for 8 s: a screen" in text
    assert [p["ylabel"] for p in drawn["panels"]] == ["survival over 0.5 s at (0.5, 0) m/s [%]",
                                                      "forward distance in 0.5 s [m]"]
    robust = {**evaluation, "test": "robust", "settings": {"num_envs": 64, "seconds": 8.0},
              "cases": {"nominal": {"survival": 0.5}}}
    text = time_to_walk.render({"command": "x", "test": "robust",
                                "records": [{**record, "evaluations": {"wall_00060s": robust}}]}, tmp_path)
    assert "Tested with 64 robots per case for 8 s, not the test's 1,024 for 8 s" in text
    assert drawn["panels"][2]["ylabel"] == "survival over 8 s under three kicks [%]"
    # The test's own sizes (every committed report): no note.
    full = {**robust, "settings": {"num_envs": 1024, "seconds": 8.0}}
    text = time_to_walk.render({"command": "x", "test": "robust",
                                "records": [{**record, "evaluations": {"wall_00060s": full}}]}, tmp_path)
    assert "Tested with" not in text


def _run_with_one_mark(tmp_path, monkeypatch, content: bytes):
    """``runs/time_to_walk/r`` under ``tmp_path`` (the working folder from now on) with one 1-minute mark holding
    ``content``; returns the run folder."""
    monkeypatch.chdir(tmp_path)
    folder = tmp_path / "runs/time_to_walk/r"
    (folder / "checkpoints").mkdir(parents=True)
    (folder / "checkpoints" / "wall_00060s.pt").write_bytes(content)
    return folder


def test_time_to_walk_eval_keeps_one_size_of_test_in_a_record(tmp_path, monkeypatch, capsys):
    # A CPU screen (4 robots, 0.5 s) recorded its marks in evals_robust.json; a later call at the test's sizes skipped
    # them as tested, so the record mixed the screen's verdicts with the test's and its time to walk could be a
    # screen's.
    folder = _run_with_one_mark(tmp_path, monkeypatch, b"")
    screen = {"train_seconds": 60.0, "env_steps": 1, "iteration": 1, "device": "cpu", "test": "robust",
              "settings": {"num_envs": 4, "seconds": 0.5}, "cases": {}, "walks": True}
    (folder / "evals_robust.json").write_text(json.dumps({"evaluations": {"wall_00060s": screen}}))
    (tmp_path / "verdict/wall_00060s").mkdir(parents=True)  # the screened mark's report, not read again
    (tmp_path / "verdict/wall_00060s/robust.json").write_text("{}")
    run = functools.partial(_time_to_walk_here, capsys, "eval", "--name", "r", "--test", "robust", "--reports",
                            str(tmp_path / "verdict"))
    run(error="holds wall_00060s tested with 4 robots for 0.5 s, this call tests 1024 for 8 s: pass --num_envs 4 "
              "--seconds 0.5")
    assert "eval_commands" not in json.loads((folder / "evals_robust.json").read_text())
    assert "time to walk" in run("--num_envs", "4", "--seconds", "0.5")  # the same sizes go on with it


def _gpu_run(folder, preset: str) -> str:
    """A run folder as the train part leaves it on a GPU (no evaluations yet): its path."""
    folder.mkdir(parents=True)
    (folder / "train.json").write_text(json.dumps({"preset": preset, "gpu": "NVIDIA H200", "train_seconds": 60.0,
                                                   "commands": [f"python -m x {preset}"], "config": {}}))
    return str(folder)


def test_time_to_walk_report_replaces_an_existing_report_only_with_overwrite(tmp_path, monkeypatch, capsys):
    # With its default --out, a report of one run silently replaced the committed report of five (and its plots).
    monkeypatch.setattr(time_to_walk.common, "plot", lambda path, panels, title="": path.write_text("plot"))
    out = tmp_path / "out"
    first, second = _gpu_run(tmp_path / "a", "torque"), _gpu_run(tmp_path / "b", "default")
    _time_to_walk_here(capsys, "report", "--runs", first, second, "--out", str(out))
    kept = (out / "time_to_walk.json").read_text()
    _time_to_walk_here(capsys, "report", "--runs", second, "--out", str(out),
                       error=f"{out} holds time_to_walk.json, time_to_walk.md, time_to_walk.png already; pass "
                             "--overwrite to replace them")
    assert (out / "time_to_walk.json").read_text() == kept
    # Another test's report has files of its own: not refused.
    _time_to_walk_here(capsys, "report", "--runs", second, "--test", "robust", "--out", str(out))
    _time_to_walk_here(capsys, "report", "--overwrite", "--runs", second, "--out", str(out))
    assert [r["preset"] for r in json.loads((out / "time_to_walk.json").read_text())["records"]] == ["default"]


def test_a_new_time_to_walk_report_renders_on_the_benchmarks_page(tmp_path, monkeypatch):
    # train.json recorded no date, so docs/benchmarks.md failed on a report of a new run with KeyError: 'date'.
    from lab.benchmarks import page

    _stand_in_training(tmp_path, monkeypatch)
    time_to_walk.main(["train", "--preset", "default", "--device", "cuda", "--every", "0"])
    docs = tmp_path / "docs"
    time_to_walk.main(["report", "--runs", "runs/time_to_walk/default", "--out", str(docs / "benchmarks")])
    for report in page.RUN_TIME_TO_WALK:  # the section's other reports, as committed
        ((docs / report).parent).mkdir(parents=True)
        shutil.copy(page.DOCS / report, docs / report)
    date = json.loads((tmp_path / "runs/time_to_walk/default/train.json").read_text())["date"]
    row = next(line for line in page.time_to_walk(docs) if line.startswith("| `default`"))
    assert row.endswith(f"| {date} |") and "| 4,096 |" in row


def test_time_to_walk_eval_that_records_nothing_adds_no_command(tmp_path, monkeypatch, capsys):
    # An eval whose marks were all tested already, or left out for want of a report, still added its command to
    # the record's eval_commands, which the report lists as the commands that made it.
    monkeypatch.chdir(tmp_path)
    folder = tmp_path / "runs/time_to_walk/r"
    (folder / "checkpoints").mkdir(parents=True)
    for stem in ("wall_00060s", "wall_00120s"):  # the second has no report to read: left out
        (folder / "checkpoints" / f"{stem}.pt").write_bytes(b"")
    tested = {"train_seconds": 60.0, "env_steps": 1, "iteration": 1, "device": "cpu", "test": "robust",
              "settings": {"num_envs": 1024, "seconds": 8.0}, "cases": {}, "walks": False}
    (folder / "evals_robust.json").write_text(json.dumps({"evaluations": {"wall_00060s": tested}}))
    (tmp_path / "verdict/wall_00060s").mkdir(parents=True)  # the tested mark's report, not read again
    (tmp_path / "verdict/wall_00060s/robust.json").write_text("{}")
    monkeypatch.setattr(common, "read_checkpoint", lambda path: {})
    text = _time_to_walk_here(capsys, "eval", "--name", "r", "--test", "robust", "--reports", str(tmp_path / "verdict"))
    assert "eval_commands" not in json.loads((folder / "evals_robust.json").read_text()), "a command recorded nothing"
    assert "wall_00120s: no " in text and "nothing recorded" in text


def test_time_to_walk_train_says_when_it_skips_the_raw_ceiling(tmp_path, monkeypatch, capsys):
    # On the CPU --raw_steps was skipped without a word: train.json then had no raw rate and no train / raw.
    raw_on = _stand_in_training(tmp_path, monkeypatch)
    text = _time_to_walk_here(capsys, "train", "--preset", "default", "--device", "cpu", "--every", "0")
    assert raw_on == [] and "--raw_steps 200 skipped: the raw mujoco-warp ceiling is timed on a GPU only" in text
    assert "skipped" not in _time_to_walk_here(capsys, "train", "--preset", "default", "--device", "cpu", "--every",
                                               "0", "--raw_steps", "0", "--name", "asked")  # asked for: no word


def test_time_to_walk_report_of_a_run_without_train_json_says_so(tmp_path, capsys):
    # Evaluations written beside a run's first training call (eval --follow_pid), before its train.json: the report
    # ended on KeyError: 'preset'.
    folder = tmp_path / "r"
    folder.mkdir()
    (folder / "evals.json").write_text(json.dumps({"evaluations": {}}))
    _time_to_walk_here(capsys, "report", "--runs", str(folder), "--out", str(tmp_path / "out"),
                       error=f"{folder}: no training result, only evals.json; the train part records it when a "
                             "training call ends")


def test_time_to_walk_a_call_stopped_while_training_keeps_its_command(tmp_path, monkeypatch, capsys):
    # A first call killed after its last checkpoint, before it wrote train.json, left no record of its command: the
    # resumed run's record named the second call alone. The record is written before training now.
    _stand_in_training(tmp_path, monkeypatch)
    train = common.train
    folder = tmp_path / "runs/time_to_walk/default"

    def stopped(cfg):
        raise KeyboardInterrupt  # as a kill would end it: after the command was recorded, before the result

    def failed(cfg):
        raise RuntimeError("CUDA out of memory")  # before any checkpoint: the call trained nothing

    monkeypatch.setattr(common, "train", failed)
    with pytest.raises(RuntimeError):
        time_to_walk.main(["train", "--preset", "default", "--device", "cuda", "--every", "0", "--minutes", "1.0"])
    assert not (folder / "train.json").exists()  # the failed first call left no record of a run
    monkeypatch.setattr(common, "train", stopped)
    with pytest.raises(KeyboardInterrupt):
        time_to_walk.main(["train", "--preset", "default", "--device", "cuda", "--every", "0", "--minutes", "7.5"])
    record = json.loads((folder / "train.json").read_text())
    assert [c.split("--minutes ")[1][:3] for c in record["commands"]] == ["7.5"] and "train_seconds" not in record
    monkeypatch.setattr(common, "train", failed)
    with pytest.raises(RuntimeError):
        time_to_walk.main(["train", "--preset", "default", "--device", "cuda", "--every", "0", "--minutes", "2.0"])
    assert json.loads((folder / "train.json").read_text()) == record  # put back as the stopped call left it
    _time_to_walk_here(capsys, "report", "--runs", str(folder), "--out", str(tmp_path / "out"),
                       error="no training result, a train.json of a training call that has not ended")
    monkeypatch.setattr(common, "train", train)
    time_to_walk.main(["train", "--preset", "default", "--device", "cuda", "--every", "0", "--minutes", "4.5"])
    record = json.loads((folder / "train.json").read_text())
    assert [c.split("--minutes ")[1][:3] for c in record["commands"]] == ["7.5", "4.5"]
    assert record["train_seconds"] == 10.5 and record["raw_policy_steps_per_s"] == 180_000.0


def test_time_to_walk_names_a_damaged_run_file_and_how_to_write_it_again(tmp_path, monkeypatch, capsys):
    # Invalid JSON in train.json or evals.json (a copy cut short, a hand edit) ended on the decoder's message alone,
    # "error: Expecting value: line 1 column 1 (char 0)", which named neither the file nor what to do.
    monkeypatch.chdir(tmp_path)
    folder = tmp_path / "runs/time_to_walk/r"
    (folder / "checkpoints").mkdir(parents=True)
    (folder / "train.json").write_text("{,")
    (folder / "evals.json").write_text(json.dumps({"evaluations": {}}))
    report = functools.partial(_time_to_walk_here, capsys, "report", "--runs", str(folder), "--out",
                               str(tmp_path / "out"))
    damaged = "is not valid JSON (Expecting property name enclosed in double quotes: line 1 column 2 (char 1)): the " \
              "file is damaged; move it away and run the {} part again"
    report(error=f"runs/time_to_walk/r/train.json {damaged.format('train')}, which writes it anew")
    (folder / "train.json").write_text(json.dumps({"preset": "cpu_smoke"}))
    (folder / "evals_robust.json").write_text("{,")
    report("--test", "robust", error=f"runs/time_to_walk/r/evals_robust.json {damaged.format('eval')} (--test robust)")
    (folder / "evals.json").write_text("{,")
    _time_to_walk_here(capsys, "eval", "--name", "r", "--device", "cpu",
                       error=f"runs/time_to_walk/r/evals.json {damaged.format('eval')}, which writes it anew")


def test_time_to_walk_report_of_an_untested_run_says_not_tested(tmp_path, monkeypatch, capsys):
    # A robust run reported without --test robust (its evaluations in evals_robust.json, none in evals.json) read
    # "not within 1.0 min", as if each of its checkpoints had failed the standard gait test.
    monkeypatch.setattr(time_to_walk.common, "plot", lambda path, panels, title="": path.write_text("plot"))
    folder = _gpu_run(tmp_path / "r", "robust")
    (tmp_path / "r" / "evals_robust.json").write_text(json.dumps({"evaluations": {"wall_00060s": {
        "train_seconds": 60.0, "env_steps": 1, "iteration": 1, "test": "robust", "cases": {}, "walks": True}}}))
    text = _time_to_walk_here(capsys, "report", "--runs", folder, "--out", str(tmp_path / "out"))
    assert "| robust | NVIDIA H200 | not tested |" in text and "not within" not in text
    text = _time_to_walk_here(capsys, "report", "--test", "robust", "--runs", folder, "--out", str(tmp_path / "out"))
    assert "| robust | NVIDIA H200 | 1.0 |" in text


def test_time_to_walk_eval_refuses_a_reports_folder_without_reports(tmp_path, monkeypatch, capsys):
    # --reports at the folder above robust_policies' --out (verdicts/ rather than verdicts/g00960) left every mark
    # out and ended on "time to walk: null", exit status 0, as if no checkpoint had passed.
    folder = _run_with_one_mark(tmp_path, monkeypatch, b"")
    (tmp_path / "verdicts/g00060/wall_00060s").mkdir(parents=True)
    (tmp_path / "verdicts/g00060/wall_00060s/robust.json").write_text("{}")
    monkeypatch.setattr(common, "read_checkpoint", lambda path: {})
    _time_to_walk_here(capsys, "eval", "--name", "r", "--test", "robust", "--reports", "verdicts",
                       error="--reports verdicts holds no <checkpoint>/robust.json, so nothing of runs/time_to_walk/r "
                             "was read: pass the folder lab.benchmarks.robust_policies --out wrote (reports lie in "
                             "verdicts/g00060)")
    assert not (folder / "evals_robust.json").exists()


def test_time_to_walk_report_into_a_file_is_refused(tmp_path, capsys):
    # --out naming a file (the report's .md, say) ended on a FileExistsError traceback from mkdir.
    (tmp_path / "time_to_walk.md").write_text("kept")
    with pytest.raises(SystemExit) as stop:
        time_to_walk.main(["report", "--runs", _gpu_run(tmp_path / "r", "torque"), "--out",
                           str(tmp_path / "time_to_walk.md")])
    assert stop.value.code == 2 and "is a file: the report is a folder" in capsys.readouterr().err
    assert (tmp_path / "time_to_walk.md").read_text() == "kept"


def test_time_to_walk_report_names_curves_it_cannot_read(tmp_path, monkeypatch, capsys):
    # --curves of a path that does not exist (or holds no logged row) drew an empty figure unsaid; one whose run
    # logged no qpos term ended on KeyError: 'reward_terms/qpos' after the report was written.
    plotted = {}
    monkeypatch.setattr(time_to_walk.common, "plot", lambda path, panels, title="": plotted.update({path.name: panels}))
    run, out = _gpu_run(tmp_path / "r", "torque"), tmp_path / "out"
    report = functools.partial(_time_to_walk_here, capsys, "report", "--runs", run, "--out", str(out), "--curves")
    report(str(tmp_path / "nope"), error=f"--curves {tmp_path / 'nope'}: no such run folder or metrics file")
    (tmp_path / "empty").mkdir()
    report(str(tmp_path / "empty"), error="holds no metric rows")
    assert not plotted and not (out.exists() and any(out.iterdir()))
    (tmp_path / "m.csv").write_text("iteration,env_steps,reward\n1,10,0.5\n2,20,0.75\n")  # no reward_terms/qpos
    report(str(tmp_path / "m.csv"))
    reward, qpos = plotted["time_to_walk_curves.png"]
    assert reward["lines"] == {"m": ([10.0, 20.0], [0.5, 0.75])} and qpos["lines"] == {}


def test_time_to_walk_eval_names_a_reports_file_as_a_file(tmp_path, capsys):
    # --reports at robust_policies' robust_policies.json, a file there, was refused as "no such folder".
    (tmp_path / "robust_policies.json").write_text("{}")
    for given, said in (("robust_policies.json", "a file, not a folder: pass the folder holding it"),
                        ("nope", "no such folder")):
        with pytest.raises(SystemExit) as stop:
            time_to_walk.main(["eval", "--test", "robust", "--reports", str(tmp_path / given)])
        assert stop.value.code == 2 and f"--reports {tmp_path / given}: {said}" in capsys.readouterr().err


def test_time_to_walk_eval_names_a_damaged_checkpoint_in_one_line(tmp_path, monkeypatch, capsys):
    # A wall_*.pt copied in part ended the eval on a DamagedCheckpointError traceback.
    _run_with_one_mark(tmp_path, monkeypatch, b"PK\x03\x04 cut short")
    (tmp_path / "verdict/wall_00060s").mkdir(parents=True)
    _time_to_walk_here(capsys, "eval", "--name", "r", "--test", "robust", "--reports", "verdict",
                       error="cannot read checkpoint runs/time_to_walk/r/checkpoints/wall_00060s.pt: not a complete")


def test_time_to_walk_report_refuses_a_run_named_twice(tmp_path, capsys):
    # `--runs X X/` listed the one run twice in the table.
    run = _gpu_run(tmp_path / "r", "torque")
    with pytest.raises(SystemExit) as stop:
        time_to_walk.main(["report", "--runs", run, run + "/", "--out", str(tmp_path / "out")])
    assert stop.value.code == 2 and "the same run more than once" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
