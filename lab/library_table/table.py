"""The per-library table (issue 22): for each RL library, training env-steps/s on the walking task and the training
time at which its policy first passes the 8 s gait test (30-minute cap). Meant for one H100.

    python -m lab.library_table --libraries torchrl,rsl_rl,skrl --num_envs 4096      # all in one call
    python -m lab.library_table --libraries sb3 --num_envs 8,256,1024
    python -m lab.library_table --report                 # rebuild the table from the saved rows only

Each library trains in its own process through its recipe (``recipes/ppo_walk.py`` for TorchRL,
``recipes/train_<library>.py`` otherwise) with a policy snapshot every ``--checkpoint_minutes`` of training time;
then the snapshots are gait-tested in time order (256 robots, 8 s, at (0.5, 0) m/s against the thresholds of
``adapters.evaluate.GAIT_CRITERIA``, and survival >= 95 % at (0.2, 0) and (0.7, 0.1)) until one passes. Rows
accumulate in ``--json`` (one per library, env count and preset) and ``--md`` is rewritten from all of them. The
env-steps/s are whole training (collection + update) divided by training time; SB3's include its host copies
(observations, rewards, done flags to the host and the actions back every step).

Split over calls (a long training in short sittings): ``--minutes M`` trains each listed
row at most M more minutes, continuing the row's own run (``--resume`` of its recipe: the library's own checkpoint,
with the training seconds, env steps and iterations summed over calls), never past ``--max_minutes`` in total; the
snapshots are named by cumulative training seconds, so the time to walk is in cumulative training minutes. At the
end of a call the row's untested snapshots are gait-tested (``--eval_minutes`` bounds that; ``--no_eval`` leaves it
to a later ``--eval_only`` call). A row is ``final`` once a snapshot walks, or the cap is reached (or, before it,
the recipe's own iteration budget, by the iterations it reports, with the policy it ended with among the
snapshots) and every snapshot is tested; later calls leave a final row alone (``--new`` starts it over in a new run
folder), except to test the last policy of a row whose budget ended before this table tested it. A row written before rows were resumable (one call
each) is kept, as a final row. What a resumed call does not carry over (env state, random-number state, the rollout
in progress) is in each row's notes. One row in calls of a few minutes each (repeat each line until the row says
``"status": "final"``):

    python -m lab.library_table --libraries rsl_rl --num_envs 4096 --minutes 7 --eval_minutes 1.5
    python -m lab.library_table --libraries rsl_rl --num_envs 4096 --eval_only --eval_minutes 8

The row's run folder (``--runs``) and ``--json`` must survive between calls (the same machine, or copied out and
back). Calls for different rows may run at the same time, one per GPU (``CUDA_VISIBLE_DEVICES=0 python -m
lab.library_table ... & CUDA_VISIBLE_DEVICES=1 python -m lab.library_table ...``): each writes only its
own rows into ``--json``, under a file lock. Relative ``--runs``, ``--json`` and ``--md`` paths are from the current
folder; their defaults are the repository's (``runs/library_table``, ``docs/adapters_table.{json,md}`` under it).
A ``--report`` call needs an existing ``--json``.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

from tocabi_torchrl.cli import RecipeParser

#: The repository root (this file is lab/library_table/table.py).
ROOT = Path(__file__).resolve().parents[2]
MAIN = (0.5, 0.0)
OTHERS = ((0.2, 0.0), (0.7, 0.1))
LIBRARIES = ("torchrl", "rsl_rl", "skrl", "sb3")
#: What a resumed TorchRL call carries over (ppo_walk --resume restores the whole trainer state).
TORCHRL_NOTES = ("resumes recipes/ppo_walk.py's checkpoint (--resume): networks, optimizer, LR and std schedule "
                 "positions, observation statistics and counters; each call starts its envs from a reset")


def train(library: str, num_envs: int, out: Path, args, used_s: float, budget_s: float) -> dict:
    """Train one library in a subprocess for up to ``budget_s`` more seconds of training, continuing the run in
    ``out`` when it has ``used_s`` > 0 seconds already; returns its cumulative {env_steps, train_seconds,
    env_steps_per_s, snapshots, calls, resume_notes} and ``budget_done``: whether the recipe's own iteration budget
    is used, from the iterations or env steps it reports (its clock, frozen a few ms after the last step, reports
    more seconds even for a call that had nothing left to train)."""
    resume = run_used_seconds(library, out) is not None
    if library == "torchrl":
        if args.recipe_args:  # ppo_walk's options are other ones, and on --resume it takes only a few again
            print(f"torchrl: --recipe_args {args.recipe_args!r} is for the rsl_rl, skrl and sb3 recipes; "
                  "recipes/ppo_walk.py does not get it", flush=True)
        # ppo_walk's --max_minutes is this call's; its checkpoints and snapshot names carry the summed train time.
        common = ["--max_minutes", f"{budget_s / 60.0:.6g}", "--checkpoint_minutes", str(args.checkpoint_minutes),
                  "--eval_at_end", "false", "--progress_bar", "false", "--device", args.device,
                  "--run_dir", str(out.parent), "--name", out.name]
        if resume:
            # Before ppo_walk writes those names again: it would replace a killed call's orphan without a word.
            torchrl_snapshots(out, float(read_torchrl_state(out / "checkpoints" / "latest.pt")["train_seconds"]))
            cmd = [sys.executable, str(ROOT / "recipes/ppo_walk.py"), "--resume",
                   str(out / "checkpoints" / "latest.pt"), *common]
        else:
            from tocabi_torchrl.config import preset_config

            # The preset's mini-batch, but no more than the rollout at this env count.
            ppo = preset_config(args.preset).ppo
            size = min(ppo.minibatch_size, ppo.steps_per_env * num_envs)
            cmd = [sys.executable, str(ROOT / "recipes/ppo_walk.py"), "--preset", args.preset,
                   "--env.num_envs", str(num_envs), "--ppo.minibatch_size", str(size), *common]
    else:
        # The library recipes' --max_minutes caps the training time summed over --resume calls.
        cmd = [sys.executable, str(ROOT / f"recipes/train_{library}.py"), "--out", str(out), "--num_envs",
               str(num_envs), "--preset", args.preset, "--device", args.device, "--eval_envs", "0",
               "--iterations", "1000000", "--max_minutes", f"{(used_s + budget_s) / 60.0:.6g}",
               "--checkpoint_minutes", str(args.checkpoint_minutes), *(["--resume"] if resume else []),
               *shlex.split(args.recipe_args)]
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, cwd=ROOT)
    if library == "torchrl":
        from tocabi_torchrl.rl.checkpoint import config_from_checkpoint

        latest = out / "checkpoints" / "latest.pt"
        state = read_torchrl_state(latest)
        cfg = config_from_checkpoint(state, latest)
        steps, seconds = int(state["env_steps"]), float(state["train_seconds"])
        return {"env_steps": steps, "train_seconds": seconds, "env_steps_per_s": steps / max(seconds, 1e-9),
                "snapshots": torchrl_snapshots(out, seconds), "resume_notes": TORCHRL_NOTES,
                "budget_done": steps // cfg.frames_per_batch >= cfg.iterations}  # ppo_walk's own 'finished' test
    trained = json.loads((out / "result.json").read_text())["train"]
    trained["budget_done"] = int(trained["iterations"]) >= int(trained.get("iterations_budget", sys.maxsize))
    return trained


def read_torchrl_state(path: Path) -> dict:
    """A TorchRL checkpoint's state, as ``rl.checkpoint.read_checkpoint`` reads it (tensors only, checked); the
    table's one reader of them, which its tests replace."""
    from tocabi_torchrl.rl.checkpoint import read_checkpoint

    return read_checkpoint(path)


def torchrl_snapshots(out: Path, latest_seconds: float) -> list[str]:
    """The ``wall_XXXXXs.pt`` snapshots of the TorchRL run in ``out`` that its ``latest.pt`` (at ``latest_seconds``
    of training) accounts for, in time order. The trainer writes each snapshot and then ``latest.pt``: a call killed
    in between leaves one trained past the resume point, which the next call retrains differently. Such an orphan is
    not the row's training, so it is renamed ``wall_XXXXXs_unresumed<k>.pt`` (as the library recipes do) and never
    gait-tested; the renaming is printed."""
    kept = []
    for path in sorted((out / "checkpoints").glob("wall_*.pt"), key=lambda p: p.name):
        if not re.fullmatch(r"wall_\d+s", path.stem):
            continue  # set aside earlier
        # Names are rounded seconds: only one within half a second of the resume point can be past it.
        if (snapshot_seconds(str(path)) >= latest_seconds - 0.5
                and float(read_torchrl_state(path)["train_seconds"]) > latest_seconds):
            k = 0
            while (aside := path.with_name(f"{path.stem}_unresumed{k}.pt")).exists():
                k += 1
            path.rename(aside)
            print(f"torchrl: {path.name} was trained past the run's resume point ({latest_seconds:.1f} s) by a call "
                  f"that was killed; kept as {aside.name}, not gait-tested")
            continue
        kept.append(str(path))
    return kept


def end_snapshot(row: dict, out: Path) -> Path | None:
    """For a row whose recipe's own budget ended before the cap, the snapshot ``wall_XXXXXs.pt`` at the row's
    training seconds that :func:`add_end_snapshot` would add; None when the budget is not used, or when a snapshot of
    that name is listed or already tested (a mark within half a second of the end: the same policy but for at most
    one iteration). Writes nothing."""
    from tocabi_torchrl.config import wall_tag

    if not row.get("recipe_budget_done"):
        return None
    end = out / "checkpoints" / f"{wall_tag(row['train_seconds'])}.pt"
    if end.stem in row.get("tested", {}) or any(Path(s).name == end.name for s in row.get("snapshots", [])):
        return None
    return end


def add_end_snapshot(library: str, row: dict, out: Path) -> bool:
    """The policy a run ended with when its recipe's own budget ended before the cap (TorchRL: ``latest.pt``; the
    library recipes: ``policy.pt``) becomes the snapshot :func:`end_snapshot` names, so it is gait-tested like the
    marks every ``--checkpoint_minutes`` (the end falls between two marks, and is what the run hands a user).
    Returns whether it added one to ``row["snapshots"]``; False when the row needs none or when the run's last
    policy is not here (printed)."""
    from tocabi_torchrl.atomic import atomic_write_bytes

    end = end_snapshot(row, out)
    if end is None:
        return False
    if not end.exists():
        source = out / "checkpoints" / "latest.pt" if library == "torchrl" else out / "policy.pt"
        if not source.is_file():
            print(f"{library} {row['preset']} {row['num_envs']}: its last policy ({source}) is not here; the policy "
                  "its training ended with is not gait-tested")
            return False
        atomic_write_bytes(end, source.read_bytes())
    row.setdefault("snapshots", []).append(str(end))
    return True


def run_used_seconds(library: str, out: Path) -> float | None:
    """Training seconds the run in ``out`` has saved (what its next call resumes from); None if it has nothing to
    resume. Read from the run, not the row: a call killed after the recipe saved but before the row was written
    loses nothing."""
    if library == "torchrl":
        latest = out / "checkpoints" / "latest.pt"
        if not latest.is_file():
            return None
        return float(read_torchrl_state(latest).get("train_seconds", 0.0))
    state = out / "resume.json"
    return float(json.loads(state.read_text())["train_seconds"]) if state.is_file() else None


def snapshot_seconds(snapshot: str) -> float:
    """Cumulative training seconds of a ``wall_XXXXXs.pt`` snapshot (every library names them so: the mark rounded
    to whole seconds, ``config.wall_tag``)."""
    return float(Path(snapshot).stem.split("_")[1].rstrip("s"))


def gait(library: str, snapshot: str, out: Path, args, command) -> dict:
    """One gait test of one snapshot at ``command``."""
    if library == "torchrl":
        from tocabi_torchrl.evaluation.gait_test import evaluate_run

        # replace: a command whose test a killed call left unrecorded is tested again into its own folder
        return evaluate_run(snapshot, num_envs=args.eval_envs, device=args.device, out_dir=out, command=command,
                            video_envs=0, progress=False, seconds=args.eval_seconds, replace=True)
    import importlib.util

    spec = importlib.util.spec_from_file_location(f"train_{library}", ROOT / f"recipes/train_{library}.py")
    recipe = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(recipe)
    return recipe.evaluate(snapshot, out, num_envs=args.eval_envs, device=args.device, seconds=args.eval_seconds, command=command)


def gait_once(library: str, snap: str, out: Path, args, done: dict, deadline: float,
              command: tuple[float, float]) -> dict | None:
    """The gait-test summary of ``snap`` at ``command``: from ``done`` (command tag -> summary), or tested now,
    added to ``done`` and saved with the rows; None if it is not in ``done`` and ``deadline`` (monotonic) is past."""
    tag = f"{command[0]}_{command[1]}"
    if tag not in done:
        if time.monotonic() >= deadline:
            return None
        done[tag] = gait(library, snap, out / "gait" / Path(snap).stem / tag, args, command)
        args.save_rows()  # a call killed during the next command keeps this one
    return done[tag]


def gait_test_snapshots(library: str, row: dict, out: Path, args) -> None:
    """Gait-test the row's snapshots not tested yet, in training-time order, until one passes; records each in
    ``row["tested"]`` (by snapshot name) and the first pass in ``row["walk"]``/``row["walks_minutes"]``.

    A snapshot fails at its first failing command: the two other commands run only after the main one passes, and
    the second only if the first kept its robots up. Each finished command is saved at once (``row["testing"]``,
    until its snapshot is decided), so that a call that ends mid-snapshot (killed, or ``--eval_minutes`` spent)
    leaves it to the next call, which runs only the commands still missing. A snapshot file that is missing stops
    the row's tests there (named), since the first pass could lie behind it."""
    from tocabi_torchrl.adapters.evaluate import GAIT_CRITERIA, gait_passes
    from tocabi_torchrl.evaluation.gait_test import tested_on

    tested = row.setdefault("tested", {})
    # --eval_minutes bound the call's testing, over all its rows: started at the call's first test.
    if "eval_deadline" not in vars(args):
        args.eval_deadline = time.monotonic() + 60.0 * args.eval_minutes if args.eval_minutes > 0 else float("inf")
    deadline = args.eval_deadline
    # A row's snapshots are all tested alike: a shorter test (a smoke setting) would fail a policy that walks, and
    # the row's verdict would read as the 8 s test's.
    setting = {"seconds": float(args.eval_seconds), "num_envs": int(args.eval_envs)}
    if row.setdefault("gait_test", setting) != setting:
        raise SystemExit(f"error: {library} {row['num_envs']}: its snapshots were gait-tested for "
                         f"{row['gait_test']['seconds']:g} s on {row['gait_test']['num_envs']} robots; test the rest "
                         f"alike (--eval_seconds {row['gait_test']['seconds']:g} --eval_envs "
                         f"{row['gait_test']['num_envs']}), or start the row over with --new")
    for snap in sorted(row["snapshots"], key=snapshot_seconds):
        name = Path(snap).stem
        if row.get("walk") is not None:
            return
        if name in tested:
            continue
        if not Path(snap).is_file():  # e.g. left on the machine that trained the row
            print(f"{library} {row['num_envs']}: snapshot {snap} is missing; without it the later snapshots cannot "
                  "show when the row first walks, so its gait tests stop here (copy the file back to go on)")
            return
        done = row.setdefault("testing", {}).setdefault(name, {})  # command tag -> summary, this snapshot's so far
        run = functools.partial(gait_once, library, snap, out, args, done, deadline)
        main = run(MAIN)
        # Where the deciding command ran (earlier commands may have run in an earlier call, on another machine: the
        # test is the same).
        entry = {"minutes": snapshot_seconds(snap) / 60.0, "main_passes": main is not None and bool(gait_passes(main)),
                 "passes": False, "device": tested_on(args.device)}
        unfinished = main is None
        if entry["main_passes"]:
            others = {}
            for command in OTHERS:
                summary = run(command)
                if summary is None:
                    unfinished = True
                    break
                others[f"{command[0]}_{command[1]}"] = summary["survival"]
                if not summary["survival"] >= GAIT_CRITERIA["survival"]:  # NaN (no robot) fails too
                    break  # the snapshot fails here; the commands after it cannot change that
            else:
                entry["passes"] = True
            entry["others"] = others
            if entry["passes"]:
                row["walk"] = {"snapshot": snap, "minutes": entry["minutes"], "main": main, "others": others}
                row["walks_minutes"] = entry["minutes"]
        if unfinished:
            print(f"{library} {row['num_envs']}: --eval_minutes spent; the next call goes on from {name}")
        else:
            tested[name] = entry
        if not done or not unfinished:  # decided, or nothing of it run: nothing to keep for the next call
            del row["testing"][name]
        if not row["testing"]:
            del row["testing"]
        # Saved after every snapshot: a call killed mid-test repeats only the commands it had not finished.
        args.save_rows()
        if unfinished:
            return


def start_over_if_killed_first(row: dict, out: Path, args) -> None:
    """For a row whose run in ``out`` has no resume point (``resume.json``; TorchRL: ``checkpoints/latest.pt``). If
    no call of the row completed, its first call was killed (or failed) before the recipe saved one: nothing in
    ``out`` can be resumed and the row records nothing of it, so ``out`` is renamed ``<run>_killed<k>`` (kept, not
    deleted), the rename is printed and recorded in ``row["set_aside"]``, and the row trains anew in ``out``. A row
    that records completed calls has lost its run: ``SystemExit`` saying so, with ``--new`` as the fix."""
    what = "checkpoints/latest.pt" if row["library"] == "torchrl" else "resume.json"
    name = f"{row['library']} {row['preset']} {row['num_envs']}"
    if row.get("calls", 0) > 0:
        raise SystemExit(f"error: {name}: its run folder {out} has no resume point ({what}) although the row records "
                         f"{row['calls']} training call(s); put the run folder back, or pass --new to train the row "
                         "anew in a new run folder (the old folder is left as it is)")
    if not out.exists():
        return
    k = 1
    while (aside := out.with_name(f"{out.name}_killed{k}")).exists():
        k += 1
    out.rename(aside)
    row.setdefault("set_aside", []).append(str(aside))
    args.save_rows()
    print(f"{name}: {out} has no resume point ({what}): the row's first call ended (killed or failed) before its "
          f"recipe saved one. Kept that folder as {aside}; training the row anew in {out}", flush=True)


def upgrade_old_row(row: dict) -> bool:
    """Bring a row written before rows were resumable (it has no ``status``) to the current format, keeping every
    field it has; True if it was one. Such a row is a whole run: one call trained it to its cap, then gait-tested its
    snapshots in time order until one passed (its ``walk``), so it is final. It recorded neither its snapshots nor
    which were tested; those are in its run folder."""
    if "status" in row:
        return False
    for key, value in {"status": "final", "calls": 1, "commands": [row["command"]] if row.get("command") else [],
                       "snapshots": [], "tested": {}, "notes": "",
                       "upgraded_from": "a row of before resumable rows (one call; snapshots and gait tests in its "
                                        "run folder only)"}.items():
        row.setdefault(key, value)
    return True


def row_key(row: dict) -> tuple:
    return row["library"], row["preset"], row["num_envs"]


def load_rows(path: Path) -> list[dict]:
    """The rows of the table json ``path`` ([] when there is no such file). ``ValueError`` naming the file when it
    is not JSON, not a list of JSON objects, or has a row without the ``library``, ``preset`` and ``num_envs`` that
    identify it."""
    if not path.is_file():
        return []
    try:
        rows = json.loads(path.read_text())
    except ValueError as err:  # JSONDecodeError, UnicodeDecodeError
        raise ValueError(f"{path} is not a table json: {err}") from None
    if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
        raise ValueError(f"{path} is not a table json: not a list of rows (JSON objects)")
    for i, row in enumerate(rows, 1):
        missing = [k for k in ("library", "preset", "num_envs") if k not in row]
        if missing:
            raise ValueError(f"{path}: row {i} has no {', '.join(map(repr, missing))}")
    renamed = [i for i, row in enumerate(rows, 1) if rename_old_preset(row)]
    for i in renamed:  # now keyed as a row of the preset's name now: saving would keep only one of two such rows
        row = rows[i - 1]
        twin = next((j for j, other in enumerate(rows, 1) if j != i and row_key(other) == row_key(row)), None)
        if twin is not None:
            raise ValueError(f"{path}: rows {min(i, twin)} and {max(i, twin)} are both {row_name(row)} (row {i} ran "
                             f"as {row['preset_then']}, the preset's name before a rename); saving would keep one of "
                             "them: remove one, or move it to another json")
    return rows


def run_date(row: dict) -> str | None:
    """The day a row's run began (ISO, ``YYYY-MM-DD``), from its folder's stamp
    (``<library>_<preset>_<envs>_<YYYYMMDD>_<HHMMSS>``); None for a folder named otherwise."""
    stamp = Path(str(row.get("run", ""))).name.split("_")[-2:-1]
    if not stamp or len(stamp[0]) != 8 or not stamp[0].isdigit():
        return None
    return f"{stamp[0][:4]}-{stamp[0][4:6]}-{stamp[0][6:]}"


def rename_old_preset(row: dict) -> bool:
    """Give a row of a preset renamed since its run (``config.RENAMED_PRESETS``, by :func:`run_date`) the preset's
    name now, keeping the name it ran under as ``preset_then`` (its commands keep it too); True if it was one."""
    from tocabi_torchrl.config import preset_now

    date = run_date(row)
    now = row["preset"] if date is None else preset_now(row["preset"], date)
    if now == row["preset"]:
        return False
    row["preset_then"], row["preset"] = row["preset"], now
    return True


def save_rows(json_path: Path, rows: list[dict], mine: set[tuple], md_path: Path | None = None) -> list[dict]:
    """Write this call's rows (keys in ``mine``) into ``json_path``, keeping every other row as the file has it now,
    and return the merged rows (also rendered into ``md_path`` when given). The files are read and written under an
    exclusive lock (``<json>.lock``, ignored by git), so that calls running at once (one row per GPU, e.g.
    ``CUDA_VISIBLE_DEVICES=1``) do not drop each other's rows."""
    import fcntl

    from tocabi_torchrl.atomic import atomic_write_text

    json_path.parent.mkdir(parents=True, exist_ok=True)
    with open(json_path.with_name(json_path.name + ".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        on_disk = load_rows(json_path)
        ours = {row_key(r): r for r in rows if row_key(r) in mine}
        merged = [ours.pop(row_key(r), r) if row_key(r) in mine else r for r in on_disk]
        merged += [r for r in rows if row_key(r) in ours]  # this call's new rows, in its order
        atomic_write_text(json_path, json.dumps(merged, indent=2))
        if md_path is not None:
            report(merged, md_path)
    return merged


def report(rows: list[dict], path: Path) -> None:
    """Render ``rows`` into the table ``path``. ``ValueError`` naming the row (by its place in ``rows``, from 1) and
    the field when one lacks a field the table shows; ``path`` is then left as it is."""
    from tocabi_torchrl.atomic import atomic_write_text

    intro = ("Training env-steps/s (collection + update over training wall-clock) and the training time at which the "
             "policy first passes the 8 s gait test (30-minute cap). Written by `python -m lab.library_table`; "
             "each row's commands are as they were run (`recipes/library_table.py` is the same script's earlier "
             "place).")
    lines = ["# Per-library table (issue 22)", "", intro, "",
             ("| library | version | preset | envs | env-steps/s | walks at (min) | trained (min) | calls | device | "
              "commands |"),
             "|---|---|---|---|---|---|---|---|---|---|"]
    notes, cells = {}, []
    for i, r in enumerate(rows, 1):
        try:
            cells.append(((str(r["preset"]), str(r["library"]), float(r["num_envs"])), table_row(r)))
        except KeyError as err:
            raise ValueError(f"row {i} ({row_name(r)}) has no {err.args[0]!r}") from None
        except (TypeError, ValueError, AttributeError) as err:
            raise ValueError(f"row {i} ({row_name(r)}): {err}") from None
    for _, (line, note) in sorted(cells, key=lambda c: c[0]):
        lines.append(line)
        if note:
            notes[note[0]] = note[1]
    if notes:
        lines += ["", ("Training split over calls (`--minutes`): the time to walk is in cumulative training minutes. "
                       "What a resumed call carries over:"), ""]
        lines += [f"- {lib}: {text}" for lib, text in sorted(notes.items())]
    atomic_write_text(path, "\n".join(lines) + "\n")


def row_name(row) -> str:
    """``library preset num_envs`` of a row, ``?`` for what it lacks."""
    get = row.get if isinstance(row, dict) else (lambda key, default: default)
    return " ".join(str(get(k, "?")) for k in ("library", "preset", "num_envs"))


def table_row(r: dict) -> tuple[str, tuple[str, str] | None]:
    """A row's line of the table, and its (library, notes) when it has notes."""
    rate = f"{r['env_steps_per_s']:,.0f}"
    if r.get("walks_minutes") is not None:
        walks = f"{r['walks_minutes']:.1f}"
    elif r.get("status", "final") == "final":
        walks = f"no (≤ {r['cap_minutes']:g})"
    elif not r.get("train_seconds"):  # every call so far was stopped before its recipe saved
        rate, walks = "-", "not trained yet (no call has finished)"
    else:
        walks = "pending (training or untested snapshots)"
    test = r.get("gait_test")
    if test and (test["seconds"], test["num_envs"]) != (8.0, 256):  # not the table's test: say which it was
        walks += f" (gait test {test['seconds']:g} s, {test['num_envs']} robots)"
    commands = r.get("commands") or [r.get("command", "")]
    preset = f"{r['preset']} (run as {r['preset_then']})" if r.get("preset_then") else r["preset"]
    line = (f"| {r['library']} | {r.get('version', '')} | {preset} | {r['num_envs']:,} | "
            f"{rate} | {walks} | {r.get('train_seconds', 0) / 60:.1f} | "
            f"{r.get('calls', 1)} | {r['device'] or '-'} | {'; '.join(f'`{c}`' for c in commands)} |")
    return line, ((r["library"], r["notes"]) if r.get("notes") else None)


DEFAULT_RUNS, DEFAULT_JSON, DEFAULT_MD = "runs/library_table", "docs/adapters_table.json", "docs/adapters_table.md"


def given_path(given: str | None, default: str) -> Path:
    """An absolute path: ``given`` (relative: from the current folder, as any command's), else ``default`` in the
    repository. The table's commands run from the repository root, where both read alike."""
    return ROOT / default if given is None else Path(os.path.abspath(given))


def check_args(parser: argparse.ArgumentParser, args) -> None:
    """Every check of a call's arguments, before any row trains or is tested (``parser.error`` naming the flag, the
    value and what it takes); sets ``args.library_list`` and ``args.num_envs_list`` (parsed, duplicates dropped)."""
    if args.no_eval and args.eval_only:
        parser.error("--no_eval and --eval_only exclude each other")
    libraries = [x.strip() for x in args.libraries.split(",")]
    for library in libraries:
        if library not in LIBRARIES:
            parser.error(f"--libraries {args.libraries}: unknown library {library!r}; give comma-separated names of "
                         f"{', '.join(LIBRARIES)}")
    args.library_list = list(dict.fromkeys(libraries))
    envs = []
    for text in args.num_envs.split(","):
        try:
            envs.append(int(text))
        except ValueError:
            envs.append(0)
        if envs[-1] < 1:
            parser.error(f"--num_envs {args.num_envs}: {text.strip()!r} is not an env count; give comma-separated "
                         "whole numbers >= 1 (e.g. 8,256)")
    args.num_envs_list = list(dict.fromkeys(envs))
    for flag, value, positive, means in (
            ("--max_minutes", args.max_minutes, True, "the training cap of a row"),
            ("--minutes", args.minutes, False, "0: up to --max_minutes"),
            ("--checkpoint_minutes", args.checkpoint_minutes, True, "the snapshot period: snapshots are tested"),
            ("--eval_minutes", args.eval_minutes, False, "0: test all"),
            ("--eval_seconds", args.eval_seconds, True, "the length of a gait test")):
        if not (math.isfinite(value) and (value > 0 if positive else value >= 0)):
            parser.error(f"{flag} {value:g}: give a finite number {'> 0' if positive else '>= 0'} ({means})")
    if args.eval_envs < 1:
        parser.error(f"--eval_envs {args.eval_envs}: give a number of robots >= 1")
    if args.checkpoint_minutes > args.max_minutes:
        parser.error(f"--checkpoint_minutes {args.checkpoint_minutes:g} is longer than the cap --max_minutes "
                     f"{args.max_minutes:g}: the row would have no snapshot to gait-test; give a shorter period")
    if args.eval_only and args.new:
        parser.error("--eval_only --new: --new starts a row over by training it, --eval_only trains nothing; "
                     "leave one out")
    if args.report:
        return
    from tocabi_torchrl.config import PRESETS, check_snapshot_minutes

    if args.preset not in PRESETS:
        parser.error(f"--preset {args.preset}: unknown preset; choose from {', '.join(sorted(PRESETS))}")
    try:  # a period under 1 s could give two snapshots one name
        check_snapshot_minutes(args.checkpoint_minutes, "--checkpoint_minutes")
    except ValueError as err:
        parser.error(str(err))


def main(argv=None) -> None:
    parser = RecipeParser(prog="python -m lab.library_table", description=__doc__.split("\n\n")[0])
    parser.add_argument("--libraries", default="torchrl,rsl_rl,skrl,sb3", help="comma-separated, of " +
                        ", ".join(LIBRARIES))
    parser.add_argument("--num_envs", default="4096", help="comma-separated env counts (default: 4096)")
    parser.add_argument("--preset", default="default", help="task preset, a name of tocabi_torchrl.config.PRESETS (default: default)")
    parser.add_argument("--device", default="cuda", help="device of the training and the gait tests: cuda or cpu "
                        "(default: cuda)")
    parser.add_argument("--max_minutes", type=float, default=30.0,
                        help="training cap of a row [min], summed over calls (default: 30)")
    parser.add_argument("--minutes", type=float, default=0.0,
                        help="train each listed row at most this many more minutes in this call, continuing its "
                             "run (0 = up to --max_minutes); a row is final once a snapshot walks or the cap is "
                             "reached")
    parser.add_argument("--checkpoint_minutes", type=float, default=1.0,
                        help="snapshot period [min], at least 1/60: the snapshots are named by whole seconds "
                             "(default: 1)")
    parser.add_argument("--eval_envs", type=int, default=256, help="robots in each gait test (default: 256)")
    parser.add_argument("--eval_seconds", type=float, default=8.0, help="length of the gait test [s] (default: 8)")
    parser.add_argument("--eval_minutes", type=float, default=0.0,
                        help="start no new gait test (one snapshot at one command) after this many minutes of "
                             "testing in this call (0 = test all); the next call goes on where this one stopped")
    parser.add_argument("--no_eval", action="store_true", help="train only; gait-test later with --eval_only")
    parser.add_argument("--eval_only", action="store_true",
                        help="no training: gait-test the snapshots of the listed rows not tested yet")
    parser.add_argument("--new", action="store_true",
                        help="start the listed rows anew in new run folders (their old runs are kept on disk)")
    parser.add_argument("--recipe_args", default="",
                        help="extra options for the rsl_rl, skrl and sb3 recipes (recipes/train_<library>.py), e.g. "
                             "'--hidden 16' for a smoke test; not passed to recipes/ppo_walk.py (torchrl rows)")
    where = " (a relative path is from the current folder; default: {} in the repository)"
    parser.add_argument("--runs", help="training runs go here (one folder per row)" + where.format(DEFAULT_RUNS))
    parser.add_argument("--json", help="the table's rows, read and updated" + where.format(DEFAULT_JSON))
    parser.add_argument("--md", help="the table, rewritten from --json" + where.format(DEFAULT_MD))
    parser.add_argument("--report", action="store_true",
                        help="only rewrite --md from --json, which must exist; trains and tests nothing")
    args = parser.parse_args(argv)
    check_args(parser, args)
    json_path, md_path = given_path(args.json, DEFAULT_JSON), given_path(args.md, DEFAULT_MD)
    runs = given_path(args.runs, DEFAULT_RUNS)
    if args.report:
        if not json_path.is_file():  # never an empty table over the committed one, as a mistyped --json gave
            parser.error(f"--json {args.json or DEFAULT_JSON}: no such file ({json_path}); --report rewrites --md "
                         "from an existing table json")
        try:
            rows = load_rows(json_path)
        except ValueError as err:  # it names the file
            parser.error(f"--json: {err}; --md {md_path} left as it is")
        try:
            report(rows, md_path)
        except ValueError as err:
            parser.error(f"--json {json_path}: {err}; --md {md_path} left as it is")
        print(f"{md_path}: {len(rows)} row(s) from {json_path}")
        return
    try:
        rows = load_rows(json_path)
    except ValueError as err:  # it names the file
        parser.error(f"--json: {err}")
    command = shlex.join(["python", "-m", "lab.library_table", *(sys.argv[1:] if argv is None else argv)])
    from importlib import metadata

    import torch

    mine: set[tuple] = set()  # the rows this call handles; the others may belong to a call running beside it
    args.save_rows = lambda: save_rows(json_path, rows, mine, md_path)  # the md never lags the json
    dists = {"torchrl": "torchrl", "rsl_rl": "rsl-rl-lib", "skrl": "skrl", "sb3": "stable-baselines3"}
    cap_s = 60.0 * args.max_minutes
    for library in args.library_list:
        for n in args.num_envs_list:
            key = (library, args.preset, n)
            mine.add(key)
            row = next((r for r in rows if row_key(r) == key), None)
            if row is not None and args.new:
                rows.remove(row)
                row = None
            if row is not None and upgrade_old_row(row):
                print(f"{library} {args.preset} {n}: a row of before resumable rows (trained and gait-tested in "
                      "one call), kept as a final row of the current format")
                args.save_rows()
            if row is None:
                if args.eval_only:
                    print(f"{library} {args.preset} {n}: no row to gait-test; train it first")
                    continue
                stamp = time.strftime("%Y%m%d_%H%M%S")
                row = {"library": library, "version": metadata.version(dists[library]), "preset": args.preset,
                       "num_envs": n, "status": "training", "run": str(runs / f"{library}_{args.preset}_{n}_{stamp}"),
                       "env_steps": 0, "train_seconds": 0.0, "env_steps_per_s": 0.0, "snapshots": [],
                       "tested": {}, "walks_minutes": None, "walk": None, "cap_minutes": args.max_minutes,
                       "device": None, "commands": [], "notes": "", "calls": 0}
                rows.append(row)
            # A row made final before the table tested where a recipe's budget ended: that policy is tested now
            # (the cap is checked first, so that a refused call leaves the row as it was).
            reopen = row["status"] == "final" and row.get("walk") is None and end_snapshot(row, Path(row["run"]))
            if (row["status"] != "final" or reopen) and row["cap_minutes"] != args.max_minutes:
                parser.error(f"{library} {args.preset} {n} trains to a {row['cap_minutes']:g}-minute cap, not "
                             f"{args.max_minutes:g}; give that --max_minutes or --new")
            if reopen and add_end_snapshot(library, row, Path(row["run"])):
                row["status"] = "training"
                print(f"{library} {args.preset} {n}: its recipe's budget ended at {row['train_seconds'] / 60:.1f} "
                      "min, between two snapshots; that last policy is gait-tested too, so the row is open again")
                args.save_rows()
            if row["status"] == "final":
                print(f"{library} {args.preset} {n}: final ({row['run']}); pass --new to train it anew")
                continue
            out = Path(row["run"])
            row["commands"].append(command)
            # Saved before training: a call killed from here on still leaves the row and its run on record.
            args.save_rows()
            used = run_used_seconds(library, out)
            if used is None and not args.eval_only and not row.get("recipe_budget_done"):  # none trains again
                start_over_if_killed_first(row, out, args)
            used = used or 0.0
            left = cap_s - used
            if not args.eval_only and left > 0 and row.get("walk") is None and not row.get("recipe_budget_done"):
                budget = min(60.0 * args.minutes, left) if args.minutes > 0 else left
                trained = train(library, n, out, args, used, budget)
                if trained["budget_done"]:  # before the cap: nothing is left for later calls to train
                    row["recipe_budget_done"] = True
                    print(f"{library} {args.preset} {n}: the recipe's own iteration budget is used")
                snapshots = trained["snapshots"]
                row.update(env_steps=int(trained["env_steps"]), train_seconds=float(trained["train_seconds"]),
                           env_steps_per_s=float(trained["env_steps_per_s"]), snapshots=snapshots,
                           calls=trained.get("calls", row.get("calls", 0) + 1),
                           notes=trained.get("resume_notes", ""),
                           device=torch.cuda.get_device_name() if torch.cuda.is_available() else "cpu")
                add_end_snapshot(library, row, out)
                args.save_rows()
            if not args.no_eval:
                gait_test_snapshots(library, row, out, args)
            # Final: a snapshot walks, or the cap is reached (within 1 %: ppo_walk stops at an iteration's end
            # by its own clock, which also counts its start-up) or the recipe's budget is used, and every
            # snapshot is tested.
            capped = row["train_seconds"] >= 0.99 * cap_s or row.get("recipe_budget_done", False)
            untested = [s for s in row["snapshots"] if Path(s).stem not in row.get("tested", {})]
            if row.get("walk") is not None or (capped and not untested):
                row["status"] = "final"
            args.save_rows()
            print(json.dumps({k: row[k] for k in ("library", "num_envs", "status", "train_seconds",
                                                  "env_steps_per_s", "walks_minutes")}))
    save_rows(json_path, rows, mine, md_path)  # the table: with the rows of calls that ran beside this one
    print(f"table: {json_path}, {md_path}")


if __name__ == "__main__":
    main()
