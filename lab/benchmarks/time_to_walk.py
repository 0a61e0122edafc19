"""Time to walk: train a preset from scratch, gait-test its checkpoints saved every ``--every`` training minutes, and
report the first training time (and env steps) at which the gait test passes.

    python -m lab.benchmarks.time_to_walk train --preset torque --minutes 9.5   # resumes; repeat until the budget is used
    python -m lab.benchmarks.time_to_walk eval --preset torque                  # gait tests of every wall-clock checkpoint
    python -m lab.benchmarks.time_to_walk eval --preset torque --test robust    # the robust gait test (evals_robust.json)
    python -m lab.benchmarks.time_to_walk eval --preset robust --test robust --from_minutes 15   # skip earlier marks
    python -m lab.benchmarks.time_to_walk eval --preset torque --test diverse   # its nominal and commands cases only
    python -m lab.benchmarks.time_to_walk report --overwrite --runs runs/time_to_walk/torque ...   # time_to_walk.*
    torchrun --standalone --nproc_per_node 2 -m lab.benchmarks.time_to_walk train --preset default --name default_2gpu

``train`` resumes ``runs/time_to_walk/<name>`` until ``--budget_minutes`` of training are used, data-parallel under
torchrun (rank 0 writes ``train.json``: the call's command before it trains, so that a call stopped partway is
still listed, its results when it ends; ``train_over_raw`` divides by ranks x one GPU's raw rate). ``eval`` writes the
gait tests of each ``wall_*.pt`` to ``evals.json`` beside it, so both parts may run at once; ``--test robust`` runs
the robust gait test (docs/evaluation.md) instead and keeps its results apart, in ``evals_robust.json`` (``report
--test robust`` reads those). ``report`` refuses to replace a report that ``--out`` holds already (the committed one
holds several runs; a report holds only its ``--runs``) unless ``--overwrite``. More: docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

from tocabi_torchrl.config import wall_seconds
from tocabi_torchrl.evaluation.gait_test import GAIT_CRITERIA as CRITERIA
from tocabi_torchrl.evaluation.gait_test import ROBUST_CRITERIA, tested_on
from tocabi_torchrl.evaluation.gait_test import gait_passes as passes_main
from tocabi_torchrl.rl.checkpoint import CheckpointError
from tocabi_torchrl.rl.curves import metric_columns, steady_rate
from tocabi_torchrl.rl.distributed import DistInfo, ending, from_environment

from . import common

MAIN_COMMAND = (0.5, 0.0)
OTHER_COMMANDS = ((0.2, 0.0), (0.7, 0.1))
RUNS = Path("runs/time_to_walk")
key = lambda c: f"{c[0]:.1f},{c[1]:.1f}"


#: The evaluations file of each gait test (docs/evaluation.md): the two tests' verdicts are never mixed in one record.
EVALS = {"standard": "evals.json", "robust": "evals_robust.json", "diverse": "evals_diverse.json"}
#: The robust test's cases each test decides "walks" by: "diverse" is the robust test without its randomised, kicked
#: cases (diverse starts, the fixed command and the changing ones: the verdict of how fast a preset learns to walk).
TEST_CASES = {"robust": ("nominal", "commands", "robust_0.5", "robust_1.0"), "diverse": ("nominal", "commands")}
#: Robots per case of the robust test when --num_envs is left out (the standard test's is 256).
ROBUST_ENVS = 1024
#: Each test's robots (per case) and length [s] as specified; eval's --num_envs and --seconds may screen with others.
SIZES = {"standard": (256, 8.0), "robust": (ROBUST_ENVS, 8.0), "diverse": (ROBUST_ENVS, 8.0)}


def walks(evaluation: dict) -> bool:
    """Whether one checkpoint's evaluation passes the whole gait test (all three commands)."""
    runs = evaluation["commands"]
    return (key(MAIN_COMMAND) in runs and passes_main(runs[key(MAIN_COMMAND)])
            and all(key(c) in runs and runs[key(c)]["survival"] >= CRITERIA["survival"] for c in OTHER_COMMANDS))


def _load(path: Path, fix: str) -> dict:
    """The record ``path`` holds, ``{}`` where there is none; ``ValueError`` naming it and ``fix`` where it is no
    JSON."""
    return common.read_json(path, fix) if path.is_file() else {}


def _rewrite(part: str, test: str = "standard") -> str:
    """How a damaged record of ``part`` ("train" or "eval", of the gait test ``test``) is written again."""
    again = f" (--test {test})" if test != "standard" else ""
    return f"move it away and run the {part} part again{again}, which writes it anew"


def _as_set(overrides: dict) -> str:
    return " ".join(f"{k}={v}" for k, v in overrides.items()) or "(none)"


def _restore(path: Path, before: dict) -> None:
    """``train.json`` as it was before a train call that left no checkpoint: removed where there was none."""
    if before:
        common.write_json(path, before)
    else:
        path.unlink(missing_ok=True)


def run_mechanics(args, latest: Path, left_min: float) -> dict:
    """The run-config fields each train call sets for itself: where and how long it runs, not what it trains (a
    run's recorded config differs from its preset's in these and its ``--set`` overrides alone)."""
    return {"run_dir": str(RUNS), "name": args.name, "device": args.device, "eval_at_end": False,
            "progress_bar": False, "log_every": args.log_every, "checkpoint_minutes": args.every,
            "max_minutes": min(args.minutes, left_min), "resume": str(latest) if latest.is_file() else ""}


def train_part(args, command: str) -> None:
    run_dir, info = RUNS / args.name, from_environment()
    record, latest = _load(run_dir / "train.json", _rewrite("train")), run_dir / "checkpoints" / "latest.pt"
    prior_s = float(common.read_checkpoint(latest).get("train_seconds", 0.0)) if latest.is_file() else 0.0
    left_min = args.budget_minutes - prior_s / 60.0
    if left_min <= 0:  # every rank reads the same checkpoint, so all stop here alike
        if info.is_main:
            print(f"{args.name}: the {args.budget_minutes}-minute training budget is used ({prior_s:.0f} s); "
                  "run the eval part")
        return
    if record.get("gpus", info.world_size) != info.world_size:  # its rate and ratio are per rank count
        raise ValueError(f"{args.name} was trained on {record['gpus']} rank(s) so far, this call has "
                         f"{info.world_size}: continue it with {record['gpus']} (torchrun --nproc_per_node), or start "
                         "another run with --name")
    overrides = common.parse_overrides(args.set)
    recorded = json.loads(json.dumps(overrides))  # as train.json keeps it (tuples become lists)
    if record.get("overrides", recorded) != recorded:  # one run trains one config from scratch to the end
        raise ValueError(f"{args.name} was trained with --set {_as_set(record['overrides'])} so far, this call has "
                         f"--set {_as_set(overrides)}: continue it with the same, or start another run with --name")
    cfg = common.config(args.preset, **{**overrides, **run_mechanics(args, latest, left_min)})
    if info.is_main:
        print(f"{args.name}: training {'from ' + str(latest) if cfg.resume else 'from scratch'} on {info.world_size} "
              f"rank(s), {prior_s / 60:.1f} of {args.budget_minutes} min used, this call up to {cfg.max_minutes:.1f} "
              "min", flush=True)
    if info.enabled:  # what launched this call, as it must be repeated
        command = command.replace("python -m", f"torchrun --standalone --nproc_per_node {info.world_size} -m", 1)
    named = {"name": args.name} if args.name != args.preset else {}  # a run in its preset's folder is named by it
    before = record  # as the last call left it ({} before the first)
    record = {"preset": args.preset, **named, "gpus": info.world_size, "overrides": recorded, "config": cfg.to_dict(),
              "commands": [], **record}  # what the first call recorded stays
    record["commands"] = [*record["commands"], command]
    if info.is_main:  # before training: a call killed after its last checkpoint still names itself in the record
        common.write_json(run_dir / "train.json", record)
    def saved_at() -> int | None:
        return latest.stat().st_mtime_ns if latest.is_file() else None

    saved = saved_at()
    try:
        result, rows = common.train(cfg)
    except Exception:
        # A call that failed before its first checkpoint (a bad device, out of memory at the build) trained nothing
        # the run keeps: the record goes back to what it was. One stopped by a signal or Ctrl-C stays listed.
        if info.is_main and saved_at() == saved:
            _restore(run_dir / "train.json", before)
        raise
    if not info.is_main:  # rank 0 logged the rows and keeps the record
        return
    # Any CUDA device string ("cuda", "cuda:1") is a GPU run: its GPU named, its raw ceiling measured on it.
    # The date the training last ran: docs/benchmarks.md gives each run's date beside its result.
    record.update(gpu=tested_on(args.device), env_steps=result.env_steps, train_seconds=prior_s + result.wall_seconds,
                  train_env_steps_per_s=steady_rate(rows, skip=3), date=time.strftime("%Y-%m-%d"))
    if "raw_policy_steps_per_s" not in record and args.raw_steps > 0 and args.device.startswith("cuda"):
        record["raw_policy_steps_per_s"] = common.raw_policy_steps_per_second(cfg.env.num_envs, args.raw_steps,
                                                                              args.device)
    elif "raw_policy_steps_per_s" not in record and args.raw_steps > 0:
        print(f"--raw_steps {args.raw_steps} skipped: the raw mujoco-warp ceiling is timed on a GPU only, so "
              "train.json gets no raw rate and no train / raw on this device", flush=True)
    if record.get("train_env_steps_per_s") and record.get("raw_policy_steps_per_s"):
        record["train_over_raw"] = record["train_env_steps_per_s"] / (record["gpus"] * record["raw_policy_steps_per_s"])
    common.write_json(run_dir / "train.json", record)
    print(json.dumps({k: record.get(k) for k in ("env_steps", "train_seconds", "train_env_steps_per_s",
                                                 "raw_policy_steps_per_s", "train_over_raw")}), flush=True)


def eval_part(args, command: str) -> None:
    run_dir = RUNS / args.name
    if not run_dir.is_dir() and not args.follow_pid:  # a trainer being followed may not have made it yet
        raise ValueError(f"{run_dir}: no such run folder; name the trained run with --name (or --preset)")
    test = getattr(args, "test", "standard")
    evals_file = run_dir / EVALS[test]
    record = _load(evals_file, _rewrite("eval", test))
    evals, envs = record.setdefault("evaluations", {}), {}
    _refuse_other_sizes(evals, evals_file, test, args)
    recorded = []  # the marks this call adds (a mark without a robust report is left out)
    while True:
        # Checkpoints are written atomically (a temporary file, then a rename): a wall_*.pt is complete.
        # Marks before --from_minutes are left out: a GPU's test of each costs about a minute, and a screen may
        # already have shown that they cannot pass (a torque run before its assist has faded). Marks are whole
        # seconds: half a second of slack for a minute count that floating point puts a hair past one.
        walls = sorted((run_dir / "checkpoints").glob("wall_*.pt"))
        marks = [p for p in walls if wall_seconds(p.stem) + 0.5 >= 60.0 * args.from_minutes]
        for ckpt in [p for p in marks if p.stem not in evals]:
            (_evaluate_robust if test in TEST_CASES else _evaluate)(ckpt, evals, envs, args)
            if ckpt.stem in evals:
                recorded.append(ckpt.stem)
                common.write_json(evals_file, record)
        if args.follow_pid and _alive(args.follow_pid):
            time.sleep(10.0)
        elif args.follow_pid:
            args.follow_pid = 0  # the trainer has ended: one more pass for what it wrote last
        else:
            break
    if not marks:  # else it ended on "time to walk: null", as if every mark had been tested and failed
        raise ValueError(
            f"{run_dir / 'checkpoints'} holds no wall_*.pt checkpoint to test (train with --every > 0; a run "
            "copied from another machine needs them too, also with --reports: each mark's training time and env "
            "steps are read from its checkpoint)" if not walls else
            f"no checkpoint of {run_dir} is of minute {args.from_minutes:g} or later (--from_minutes); its last is "
            f"{walls[-1].stem} ({wall_seconds(walls[-1].stem) / 60:g} min)")
    _say_reports_without_checkpoints(args.reports or (), walls, run_dir)
    if not recorded:
        _refuse_empty_reports(args.reports or (), run_dir)
    record["time_to_walk"] = first_walk(record)
    if recorded:  # the record lists the commands that made it: one that added nothing is none of them
        record.setdefault("eval_commands", []).append(command)
        common.write_json(evals_file, record)
    else:
        print(f"nothing recorded: each checkpoint to test is in {evals_file} already or was left out", flush=True)
    print("time to walk:", json.dumps(record["time_to_walk"]))


def _refuse_other_sizes(evals: dict, evals_file: Path, test: str, args) -> None:
    """Raise ``ValueError`` when a checkpoint of ``evals`` was tested with other robots or another length than this
    call tests: its marks are skipped as tested, so a screen's verdicts (a CPU's 4 robots for 0.5 s) would stand in
    one record beside the test's, and could be its time to walk."""
    want = (args.num_envs or SIZES[test][0], args.seconds)
    for name, e in sorted(evals.items()):
        ran = e.get("settings") if test in TEST_CASES else e.get("commands", {}).get(key(MAIN_COMMAND))
        had = ((ran or {}).get("num_envs"), (ran or {}).get("seconds"))
        if None not in had and had != want:
            raise ValueError(f"{evals_file} holds {name} tested with {had[0]} robots for {had[1]:g} s, this call "
                             f"tests {want[0]} for {want[1]:g} s: pass --num_envs {had[0]} --seconds {had[1]:g} to "
                             "go on with that record, or move the file away to start another")


def _say_reports_without_checkpoints(folders, walls: list[Path], run_dir: Path) -> None:
    """Name each mark of ``--reports`` whose checkpoint the run folder lacks: its training time and env steps are
    read from the checkpoint, so it is left out (a mark copied back without its ``wall_*.pt``)."""
    from tocabi_torchrl.evaluation.robust import ROBUST_JSON

    have = {p.stem for p in walls}
    for folder in folders:
        for report in sorted(Path(folder).glob(f"wall_*s/{ROBUST_JSON}")):
            mark = report.parent.name
            if mark not in have:
                print(f"{mark}: a report in {folder} but no {run_dir / 'checkpoints' / mark}.pt; left out (its "
                      "training time and env steps are read from the checkpoint: copy it into the run)", flush=True)


def _refuse_empty_reports(folders, run_dir: Path) -> None:
    """Raise ``ValueError`` for a ``--reports`` folder without any ``<checkpoint>/robust.json``: a call that read
    nothing from it (the folder above robust_policies' --out, say) would end on "time to walk: null"."""
    from tocabi_torchrl.evaluation.robust import ROBUST_JSON

    for folder in map(Path, folders):
        if not any(folder.glob(f"*/{ROBUST_JSON}")):
            below = sorted({str(p.parent.parent) for p in folder.glob(f"*/*/{ROBUST_JSON}")})
            raise ValueError(f"--reports {folder} holds no <checkpoint>/{ROBUST_JSON}, so nothing of {run_dir} was "
                             "read: pass the folder lab.benchmarks.robust_policies --out wrote"
                             + (f" (reports lie in {', '.join(below)})" if below else ""))


def _alive(pid: int) -> bool:
    try:
        return os.kill(pid, 0) is None  # signal 0: only whether the process exists
    except OSError:
        return False


def _evaluate(ckpt: Path, evals: dict, envs: dict, args) -> None:
    """Gait tests of one wall-clock checkpoint into ``evals[ckpt.stem]``."""
    state = common.read_checkpoint(ckpt)
    entry = {"train_seconds": state["train_seconds"], "env_steps": state["env_steps"], "iteration": state["iteration"],
             "device": tested_on(args.device), "commands": {}}
    for command in (MAIN_COMMAND, *OTHER_COMMANDS):
        if command != MAIN_COMMAND and not passes_main(entry["commands"][key(MAIN_COMMAND)]):
            break
        out = ckpt.parent.parent / "eval" / ckpt.stem / f"{command[0]:.1f}_{command[1]:.1f}"
        summary = common.gait_test(state, ckpt, command, out, args.num_envs or 256, args.seconds, args.device, envs)
        entry["commands"][key(command)] = {k: v for k, v in summary.items() if isinstance(v, (int, float))}
    entry["walks"] = walks(entry)
    evals[ckpt.stem] = entry
    m = entry["commands"][key(MAIN_COMMAND)]
    print(f"{ckpt.stem}: {entry['train_seconds'] / 60:5.1f} min, {entry['env_steps'] / 1e6:6.1f} M steps: survival "
          f"{m['survival']:.3f}, forward {m['forward_distance_m']:.2f} m, drift {m['lateral_drift_m']:.2f} m, knee RMS "
          f"{m['knee_rms_rad']:.3f} rad -> {'WALKS' if entry['walks'] else 'no'}", flush=True)


def _evaluate_robust(ckpt: Path, evals: dict, envs: dict, args) -> None:
    """The robust gait test (``--test robust``) or its unperturbed cases (``--test diverse``) of one wall-clock
    checkpoint into ``evals[ckpt.stem]``; ``envs`` keeps the cases' envs across checkpoints."""
    from tocabi_torchrl.evaluation.gait_test import summary_json
    from tocabi_torchrl.evaluation.robust import (ROBUST_JSON, RobustTestConfig, evaluate_robust_checkpoint,
                                                  robust_passes)

    state = common.read_checkpoint(ckpt)
    if args.reports:
        # Several folders: the verdicts of one run written by several robust_policies calls (a group of marks each).
        candidates = [Path(folder) / ckpt.stem / ROBUST_JSON for folder in args.reports]
        found = [path for path in candidates if path.is_file()]
        if len(found) > 1:
            raise ValueError(f"{ckpt.stem}: a report in each of {', '.join(map(str, found))}; pass the folders so "
                             "that one holds each checkpoint's report")
        if not found:
            print(f"{ckpt.stem}: no {' or '.join(map(str, candidates))}; left out", flush=True)
            return
        found = found[0]
        report = _load(found, "write it again with lab.benchmarks.robust_policies")
        if not report:
            print(f"{ckpt.stem}: {found} is empty; left out", flush=True)
            return
        if report.get("test") != "robust" or not isinstance(report.get("cases"), dict):
            raise ValueError(f"{found} is not a robust gait test report")
        missing = [c for c in TEST_CASES[args.test] if c not in report["cases"]]
        if missing:  # a report of fewer cases (robust_policies --cases) cannot decide this test
            print(f"{ckpt.stem}: {found} lacks the case(s) {', '.join(missing)} of the {args.test} test; left out",
                  flush=True)
            return
        # A report of another size or length (a quick screen) is no verdict of the test this record holds.
        want = RobustTestConfig(num_envs=args.num_envs or ROBUST_ENVS, seconds=args.seconds)
        expected = {"num_envs": want.num_envs, "seconds": want.seconds, "push_count": want.push_count,
                    "push_window_s": list(want.push_window), "push_kind": want.push_kind}
        settings = report.get("settings") or {}
        differ = [f"{k} {settings.get(k)!r} (the test's {v!r})" for k, v in expected.items() if settings.get(k) != v]
        if differ:
            # Only the size and length are this command's to set: a report of other kicks is of another test.
            fix = ("pass --num_envs/--seconds of that report to record it as such"
                   if all(k in ("num_envs", "seconds") for k in expected if settings.get(k) != expected[k]) else
                   "its kicks are not the test's: test the checkpoint again")
            print(f"{ckpt.stem}: {found} was tested with {', '.join(differ)}; left out ({fix})", flush=True)
            return
        device = report.get("tested_on", "?")
    else:
        test = RobustTestConfig(num_envs=args.num_envs or ROBUST_ENVS, seconds=args.seconds,
                                cases=TEST_CASES[args.test])
        report = evaluate_robust_checkpoint(state, ckpt, ckpt.parent.parent / "eval" / ckpt.stem / args.test,
                                            test=test, device=args.device, envs=envs, progress=False)
        device = tested_on(args.device)
    entry = {"train_seconds": state["train_seconds"], "env_steps": state["env_steps"], "iteration": state["iteration"],
             "device": device, "test": args.test, "settings": report["settings"],
             "cases": json.loads(summary_json({name: c for name, c in report["cases"].items()
                                               if name in TEST_CASES[args.test]})),
             "walks": robust_passes(report, TEST_CASES[args.test])}
    evals[ckpt.stem] = entry
    cases = ", ".join(f"{name} {c['survival']:.3f}" for name, c in entry["cases"].items())
    print(f"{ckpt.stem}: {entry['train_seconds'] / 60:5.1f} min, {entry['env_steps'] / 1e6:6.1f} M steps: {args.test} "
          f"test survival {cases} -> {'WALKS' if entry['walks'] else 'no'}", flush=True)


def first_walk(record: dict) -> dict | None:
    """The earliest checkpoint (by training time) that passes the gait test, or None."""
    passing = [e for e in record.get("evaluations", {}).values() if e.get("walks")]
    first = min(passing, key=lambda e: e["train_seconds"], default=None)
    return None if first is None else {"train_minutes": first["train_seconds"] / 60.0, "env_steps": first["env_steps"],
                                       "iteration": first["iteration"]}


def read_run(folder: Path, test: str = "standard") -> dict:
    """A run's ``train.json`` and the evaluations of ``test`` (:data:`EVALS`: ``evals.json``, ``evals_robust.json``
    or ``evals_diverse.json``) as one record (``time_to_walk`` recomputed from the evaluations)."""
    train = _load(folder / "train.json", _rewrite("train"))
    record = {**train, **_load(folder / EVALS[test], _rewrite("eval", test))}
    if not record:
        raise SystemExit(f"error: {folder}: no train.json or {EVALS[test]} (run the train and eval parts first)")
    if not train or ("commands" in train and "train_seconds" not in train):  # the first call has not ended yet
        have = "only " + EVALS[test] if not train else "a train.json of a training call that has not ended"
        raise SystemExit(f"error: {folder}: no training result, {have}; the train part records it when a training "
                         "call ends: report after that (a stopped call: run the train part again, it resumes from "
                         "the last checkpoint), or copy train.json with the run")
    return {**record, "time_to_walk": first_walk(record)}


def _label(r: dict) -> str:
    """A run's name in the report: its preset, or its folder name where that differs (a 2-GPU run of a preset)."""
    return r.get("name", r["preset"])


def _gpus(r: dict) -> str:
    return f"{r['gpus']} x {r.get('gpu', '?')}" if r.get("gpus", 1) > 1 else r.get("gpu", "?")


#: The robust test's columns in the report: case, metric path, header, format.
ROBUST_COLUMNS = (("nominal", "survival", "survival", ".3f"),
                  ("nominal", "forward_distance_m.mean", "forward [m]", ".2f"),
                  ("nominal", "lateral_drift_m.p95", "drift p95 [m]", ".2f"),
                  ("commands", "survival", "survival (commands)", ".3f"),
                  ("commands", "tracking_error_mps.mean", "tracking error, cycle mean [m/s]", ".3f"),
                  ("commands", "instant_speed_error_mps.mean", "instantaneous speed error [m/s]", ".3f"),
                  ("robust_0.5", "survival", "survival (push 0.5 m/s)", ".3f"),
                  ("robust_1.0", "survival", "survival (push 1.0 m/s)", ".3f"))


def _value(e: dict, case: str, path: str):
    """A robust evaluation's value of ``case`` at ``path`` ("lateral_drift_m.p95"); None if it has none."""
    value = e.get("cases", {}).get(case)
    for part in path.split("."):
        value = value.get(part) if isinstance(value, dict) else None
    return value


def _headline(e: dict, k: str) -> float:
    """The plotted survival or forward distance of an evaluation: the standard test's at (0.5, 0), or the robust
    test's nominal case (mean distance); NaN for a value the file holds as null."""
    if e.get("test") in TEST_CASES:
        v = _value(e, "nominal", "forward_distance_m.mean" if k == "forward_distance_m" else k)
    else:
        v = e["commands"][key(MAIN_COMMAND)][k]
    return math.nan if v is None else v


def _robust_table(evals: list, test: str = "robust") -> str:
    """The per-checkpoint table of a run's robust (or diverse) evaluations (:data:`ROBUST_COLUMNS` of the test's
    cases)."""
    columns = [c for c in ROBUST_COLUMNS if c[0] in TEST_CASES[test]]
    rows = [(name, f"{e['train_seconds'] / 60:.1f}", f"{e['env_steps'] / 1e6:.1f} M",
             *("-" if (v := _value(e, case, path)) is None else format(v, spec) for case, path, _, spec in
               columns), "yes" if e.get("walks") else "no", e.get("device", "-")) for name, e in evals]
    return common.table(("checkpoint", "minutes", "env steps", *(h for _, _, h, _ in columns), "walks",
                         "tested on"), rows)


def _not_within(r: dict) -> str:
    """The time-to-walk cell of a run with no passing checkpoint: "not within" its training minutes, or, when
    checkpoints of its last training minutes were not tested yet, only up to the last tested one; "not tested" when
    none was (its evaluations of another test only, or the eval part not run yet)."""
    trained = r.get("train_seconds", 0)
    if not r.get("evaluations"):  # no checkpoint tested: not a miss (a report without --test robust of a robust run)
        return "not tested"
    tested = max((e["train_seconds"] for e in r.get("evaluations", {}).values()), default=trained)
    every = 60 * (r.get("config", {}).get("checkpoint_minutes") or 0)
    if every and tested + every < trained:  # a later mark exists, untested
        return f"not by {tested / 60:.1f} min, the last tested of {trained / 60:.1f} trained"
    return f"not within {trained / 60:.1f} min"


def _tested(records: list[dict], test: str) -> tuple[list[int], list[float]]:
    """The robot counts and lengths [s] the records' evaluations of ``test`` ran with, each sorted and distinct; the
    test's own (:data:`SIZES`) where no evaluation says."""
    robots, seconds = set(), set()
    for r in records:
        for e in r.get("evaluations", {}).values():
            ran = e.get("settings") if test in TEST_CASES else e.get("commands", {}).get(key(MAIN_COMMAND))
            robots.add((ran or {}).get("num_envs"))
            seconds.add((ran or {}).get("seconds"))
    robots, seconds = sorted(robots - {None}), sorted(seconds - {None})
    return robots or [SIZES[test][0]], seconds or [SIZES[test][1]]


def render(data: dict, out: Path) -> str:
    # A dash for a value not measured (None) alone: a survival of 0 is a result, not a blank.
    records, num = data["records"], lambda x, spec=",.0f": "-" if x is None else format(x, spec)
    test = data.get("test", "standard")
    robust = test in TEST_CASES
    # The plots and the text say how long the tests ran: a CPU screen of 0.5 s once read "survival over 8 s".
    robots, seconds = _tested(records, test)
    length = "/".join(f"{x:g}" for x in seconds)
    screened = "" if (robots, seconds) == ([SIZES[test][0]], [SIZES[test][1]]) else (
        f" Tested with {'/'.join(f'{n:,}' for n in robots)} robots{' per case' if robust else ''} for {length} s, "
        f"not the test's {SIZES[test][0]:,} for {SIZES[test][1]:g} s: a screen, whose verdicts are not the test's.")
    rows = [(_label(r), _gpus(r), f"{t['train_minutes']:.1f}" if (t := r.get("time_to_walk")) else
             _not_within(r), f"{t['env_steps'] / 1e6:.1f} M" if t else "-",
             num(r.get("train_env_steps_per_s")), num(r.get("raw_policy_steps_per_s")), num(r.get("train_over_raw"),
             ".2f")) for r in records]
    passing = ("the robust gait test (docs/evaluation.md: diverse starts; nominal, changing-command, randomised and "
               "pushed cases, each against its thresholds in ROBUST_CRITERIA)" if test == "robust" else
               "the robust gait test's unperturbed cases (docs/evaluation.md: diverse starts; the nominal and "
               "changing-command cases against their thresholds in ROBUST_CRITERIA; no randomisation, no kicks)"
               if test == "diverse" else
               "the 8 s gait test on 256 envs: at (0.5, 0) m/s survival >= 95 %, forward >= 2.6 m, drift <= 0.3 m, "
               "knee RMS <= 0.15 rad; at (0.2, 0) and (0.7, 0.1) survival >= 95 %")
    text = ("# Time to walk (issue 19)\n\nTraining wall-clock (summed over resumed calls; no evaluation, no kernel "
            f"compilation) until a checkpoint first passes {passing}.{screened}"
            + (" A run on K GPUs (data-parallel, K x the envs) reports one GPU's raw rate and divides by K x raw."
               if any(r.get("gpus", 1) > 1 for r in records) else "") + "\n\n"
            + common.table(("run", "GPU", "time to walk [min]", "env steps then", "training env-steps/s",
                            "raw mujoco-warp policy steps/s (same run)", "train / raw"), rows))
    limits = ((100 * ROBUST_CRITERIA["nominal"]["survival"][1], f"survival over {length} s, robust test's nominal "
               "case [%]"), (ROBUST_CRITERIA["nominal"]["forward_distance_m.mean"][1],
                             f"mean forward distance in {length} s, nominal [m]")
              ) if robust else ((100 * CRITERIA["survival"], f"survival over {length} s at (0.5, 0) m/s [%]"),
                                (CRITERIA["forward_distance_m"], f"forward distance in {length} s [m]"))
    panels = [{"lines": {}, "vlines": [], "hlines": [(y, "pass")], "xlabel": "training minutes", "ylabel": label}
              for y, label in limits]
    # The robust test's pushed cases beside them: survival under three kicks, each speed against its own threshold.
    pushed = ("robust_0.5", "robust_1.0") if test == "robust" else ()
    if pushed:
        panels.append({"lines": {}, "vlines": [], "xlabel": "training minutes",
                       "ylabel": f"survival over {length} s under three kicks [%]",
                       "hlines": [(100 * ROBUST_CRITERIA[c]["survival"][1], f"pass {c}", ls)
                                  for c, ls in zip(pushed, ("--", ":"), strict=True)]})
    for r in records:
        evals = sorted(r.get("evaluations", {}).items())
        text += f"\n\n## {_label(r)}\n\nCommands:\n\n" + "".join(
            f"- `{c}`\n" for c in r.get("commands", []) + r.get("eval_commands", [])) + "\n" + (
            _robust_table(evals, test) if robust else common.table(
            ("checkpoint", "minutes", "env steps", "survival", "forward [m]", "drift [m]", "knee RMS [rad]",
             "survival (0.2, 0)", "survival (0.7, 0.1)", "walks", "tested on"),
            [(name, f"{e['train_seconds'] / 60:.1f}", f"{e['env_steps'] / 1e6:.1f} M", *(
                f"{e['commands'][key(MAIN_COMMAND)][k]:{spec}}" for k, spec in (
                    ("survival", ".3f"), ("forward_distance_m", ".2f"), ("lateral_drift_m", ".2f"),
                    ("knee_rms_rad", ".3f"))), *(num(e["commands"].get(key(c), {}).get("survival"), ".3f")
                                                 for c in OTHER_COMMANDS), "yes" if e.get("walks") else "no",
             e.get("device", "-"))
             for name, e in evals]))
        # A run whose checkpoints were tested on a CPU (a screen with fewer robots) says so in the plots too.
        label = _label(r) + (" (tested on a CPU)" if any(e.get("device") == "cpu" for _, e in evals) else "")
        for panel, k, scale in zip(panels[:2], ("survival", "forward_distance_m"), (100, 1), strict=True):
            panel["lines"][label] = ([e["train_seconds"] / 60 for _, e in evals],
                                     [scale * _headline(e, k) for _, e in evals])
            panel["vlines"] += [r["time_to_walk"]["train_minutes"]] if r.get("time_to_walk") else []
        for case in pushed:
            values = [_value(e, case, "survival") for _, e in evals]
            panels[2]["lines"][f"{label}, {case}"] = ([e["train_seconds"] / 60 for _, e in evals],
                                                          [math.nan if v is None else 100 * v for v in values])
        if pushed and r.get("time_to_walk"):
            panels[2]["vlines"].append(r["time_to_walk"]["train_minutes"])
    common.plot(out / (f"time_to_walk_{test}.png" if robust else "time_to_walk.png"), panels,
                "Gait test of checkpoints against training time (dotted: first pass)")
    return text + "\n"


def plot_curves(metrics: list[Path], path: Path) -> None:
    """Reward per step and the imitation (qpos) reward against env steps, one line per run (TocabiLab figs 4.2-4.3);
    a run that did not log a panel's column is left out of that panel. ``ValueError`` naming a path that is no run
    folder or metrics file, or holds no logged row: the plot would be empty for it, unsaid."""
    runs = {}
    for p in metrics:
        if not p.exists():
            raise ValueError(f"--curves {p}: no such run folder or metrics file")
        runs[p.stem] = metric_columns(p)  # ValueError naming p when it holds no metric rows
    path.parent.mkdir(parents=True, exist_ok=True)
    common.plot(path, [{"lines": {name: (c["env_steps"], c[column]) for name, c in runs.items()
                                  if column in c and "env_steps" in c},
                        "xscale": "log", "xlabel": "env steps", "ylabel": y}
                       for column, y in (("reward", "reward per step"),
                                             ("reward_terms/qpos", "imitation reward per step (qpos term, max 0.35)"))])


def report_part(args, command: str) -> None:
    test = getattr(args, "test", "standard")
    data = {"command": command, "test": test, "records": [read_run(Path(p), test) for p in args.runs]}
    # Runs trained on the CPU (smoke runs) are kept out of the published GPU results; GPU runs copied back are not.
    cpu = data["records"] and all(r.get("gpu") == "cpu" for r in data["records"])
    out = common.report_dir(args.out, "cpu" if cpu else None)
    name = "time_to_walk" if test == "standard" else f"time_to_walk_{test}"
    # The committed report holds several runs: one of fewer runs would replace it (and its plots) unsaid.
    taken = [out / f for f in (f"{name}.json", f"{name}.md", f"{name}.png",
                               *(["time_to_walk_curves.png"] if args.curves else [])) if (out / f).exists()]
    if taken and not getattr(args, "overwrite", False):
        raise ValueError(f"{out} holds {', '.join(p.name for p in taken)} already; pass --overwrite to replace "
                         "them (the report holds only the --runs given: name every run it should keep), or --out "
                         "another folder")
    if args.curves:  # first: a --curves path it cannot read leaves no report written
        plot_curves([Path(p) for p in args.curves], out / "time_to_walk_curves.png")
    text = common.publish(out, name, data, render, replace=bool(getattr(args, "overwrite", False)))
    print(text)


def main(argv=None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog="python -m lab.benchmarks.time_to_walk", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="part", required=True)
    run = argparse.ArgumentParser(add_help=False)  # which run, where: the train and eval parts take them alike
    run.add_argument("--preset", default="torque", help="a name of tocabi_torchrl.config.PRESETS (default: torque)")
    run.add_argument("--name", default=None, help="the run's folder under runs/time_to_walk (default: the preset)")
    run.add_argument("--device", default="cuda",
                     help="cuda, or cpu (a smoke test; eval beside a GPU trainer) (default: cuda)")
    what = "train (or resume) a preset for up to --minutes"
    t = sub.add_parser("train", parents=[run], help=what, description=what)
    t.add_argument("--minutes", type=float, default=9.0, help="training minutes in this call (default: 9)")
    t.add_argument("--budget_minutes", type=float, default=30.0,
                   help="training minutes in all, summed over calls (default: 30)")
    t.add_argument("--every", type=float, default=2.0,
                   help="minutes between evaluated checkpoints (default: 2; 0: none)")
    t.add_argument("--log_every", type=int, default=5, help="iterations between logged rows (default: 5)")
    t.add_argument("--raw_steps", type=int, default=200,
                   help="raw mujoco-warp steps timed, on a GPU only (default: 200; 0: skip)")
    t.add_argument("--set", nargs="*", default=[], metavar="PATH=VALUE",
                   help="config overrides on top of the preset (ablations); a run continues only with the same ones")
    what = "gait tests of every wall-clock checkpoint of a preset's run"
    e = sub.add_parser("eval", parents=[run], help=what, description=what)
    e.add_argument("--num_envs", type=int, default=None,
                   help=f"robots in the gait test, per case in the robust one (default: 256, robust and diverse "
                        f"{ROBUST_ENVS})")
    e.add_argument("--seconds", type=float, default=8.0, help="length of each gait test [s] (default: 8)")
    e.add_argument("--test", choices=tuple(EVALS), default="standard",
                   help="which gait test decides 'walks': standard (3 commands), robust (docs/evaluation.md) or "
                        "diverse (the robust test's nominal and commands cases: diverse starts, no kicks) "
                        "(default: standard)")
    e.add_argument("--follow_pid", type=int, default=0,
                   help="keep evaluating while this process (the trainer) runs (default: 0, none)")
    e.add_argument("--from_minutes", type=float, default=0.0,
                   help="test only the checkpoints of this training minute and later (default: all)")
    e.add_argument("--reports", nargs="+", default=None, metavar="DIR",
                   help="with --test robust or diverse: read each checkpoint's results from "
                        "DIR/<checkpoint>/robust.json (as lab.benchmarks.robust_policies --out DIR writes them; "
                        "several DIRs: the one that has it) instead of testing it again; checkpoints without one "
                        "(or without the test's cases) are left out")
    what = "tables and plots from the runs' train.json and evals.json"
    r = sub.add_parser("report", help=what, description=what)
    r.add_argument("--runs", nargs="+", required=True, help="run folders holding train.json / evals.json")
    r.add_argument("--curves", nargs="*", default=[],
                   help="run folders or metrics.csv files to plot the reward curves of")
    r.add_argument("--out", default=str(common.DOCS), help="folder of the tables and plots (default: docs/benchmarks)")
    r.add_argument("--test", choices=tuple(EVALS), default="standard",
                   help="which gait test's evaluations to report (default: standard)")
    r.add_argument("--overwrite", action="store_true",
                   help="replace report files that --out holds already (default: refuse)")
    args = parser.parse_args(argv)
    if args.part == "train" and not 0 < args.minutes < math.inf:  # the config reads max_minutes 0 as no time limit
        parser.error(f"--minutes must be a positive number of training minutes, got {args.minutes}")
    reports = getattr(args, "reports", None)  # an eval option only
    if reports and args.test not in TEST_CASES:
        parser.error("--reports reads robust gait test reports: pass --test robust (or diverse) with it")
    for folder in reports or ():
        if not Path(folder).is_dir():  # a file given (its robust_policies.json, say) is not "no such folder"
            what = "a file, not a folder: pass the folder holding it" if Path(folder).exists() else "no such folder"
            parser.error(f"--reports {folder}: {what} (the --out of lab.benchmarks.robust_policies)")
    if args.part == "report" and len({Path(p).resolve() for p in args.runs}) < len(args.runs):
        parser.error(f"--runs {' '.join(args.runs)} names the same run more than once (each would be a row of the "
                     "table); give each run once")
    if args.part == "report" and Path(args.out).exists() and not Path(args.out).is_dir():
        parser.error(f"--out {args.out} is a file: the report is a folder of tables and plots; name a folder")
    if args.part != "report" and not reports:
        common.require_cuda(parser, args.device, "time to walk is measured on a GPU (pass --device cpu for a smoke "
                                                 "test of the script)")
    if args.part != "report" and args.name is None:
        args.name = args.preset
    t0 = time.time()
    command = " ".join(["python -m lab.benchmarks.time_to_walk", *argv])
    info = from_environment() if args.part == "train" else DistInfo()  # only training runs data-parallel
    try:
        # Every rank ends, also on a failure (NCCL: the process, here); a damaged checkpoint (a wall_*.pt copied in
        # part) is said in one line, as a refused input is.
        with ending(info, expected=(ValueError, CheckpointError)):
            {"train": train_part, "eval": eval_part, "report": report_part}[args.part](args, command)
            if info.is_main:
                print(f"[{args.part} took {time.time() - t0:.0f} s]", flush=True)
    except (ValueError, CheckpointError) as err:
        sys.exit(1 if info.enabled else f"error: {err}")  # ending() has said it on each rank


if __name__ == "__main__":
    main()
