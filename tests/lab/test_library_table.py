"""The per-library table (lab/library_table/table.py) split over calls: a second ``--minutes`` call continues the same row and run (cumulative
training time and env steps), the gait tests run on the snapshots, and a final row is left alone (rsl_rl on the CPU,
tiny). The other tests fake ``recipes/ppo_walk.py`` (:class:`FakePpoWalk`) and the gait test, so they need no RL
library and take no training time: recipe budgets, orphan snapshots, killed first calls, old rows, --recipe_args."""

from __future__ import annotations

import argparse
import csv
import json
import lzma
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
from recipe_runner import load_recipe

from tocabi_torchrl.config import preset_config, wall_tag

#: A gait-test summary that fails every threshold.
FALLS = {"survival": 0.0, "forward_distance_m": 0.0, "lateral_drift_m": 1.0, "knee_rms_rad": 1.0}


def files(tmp_path) -> list[str]:
    """The table's run folder, json and md under ``tmp_path``."""
    return ["--runs", str(tmp_path / "runs"), "--json", str(tmp_path / "table.json"),
            "--md", str(tmp_path / "table.md")]


def rows(tmp_path) -> list[dict]:
    return json.loads((tmp_path / "table.json").read_text())


class FakePpoWalk:
    """Stands in for ``recipes/ppo_walk.py`` as the table runs it, in training seconds instead of wall-clock: each
    call trains iterations of ``iteration_s`` seconds and 96 env steps until its ``--max_minutes`` are spent (then
    ends the iteration, as the trainer does) or its ``total_env_steps`` are done, saving ``wall_XXXXXs.pt`` at the
    ``--checkpoint_minutes`` marks with ``latest.pt`` after each. Checkpoints are JSON (see ``torchrl_table``)."""

    def __init__(self, total_env_steps: int = 10**9, iteration_s: float = 0.25):
        self.commands: list[list[str]] = []
        self.iteration_s = iteration_s
        self.cfg = preset_config("default", **{"env.num_envs": 2, "ppo.steps_per_env": 48, "ppo.minibatch_size": 96,
                                               "total_env_steps": total_env_steps})

    def __call__(self, cmd, check=True, cwd=None):
        self.commands.append(cmd)
        parser = argparse.ArgumentParser()
        for option in ("--resume", "--run_dir", "--name"):
            parser.add_argument(option)
        for option in ("--max_minutes", "--checkpoint_minutes"):
            parser.add_argument(option, type=float)
        opts, _ = parser.parse_known_args(cmd[2:])
        if opts.resume:
            run = Path(opts.resume).parent.parent
            state = json.loads(Path(opts.resume).read_text())
        else:
            run = Path(opts.run_dir) / opts.name
            if run.exists():  # ppo_walk never writes into an existing run folder
                raise subprocess.CalledProcessError(1, cmd)
            (run / "checkpoints").mkdir(parents=True)
            state = {"iteration": 0, "env_steps": 0, "train_seconds": 0.0, "config": self.cfg.to_dict()}
        save = lambda name: (run / "checkpoints" / name).write_text(json.dumps(state))
        start, mark = state["train_seconds"], 60.0 * opts.checkpoint_minutes
        next_mark = (int(start // mark) + 1) * mark
        while state["iteration"] < self.cfg.iterations and state["train_seconds"] - start <= 60.0 * opts.max_minutes:
            state = {**state, "iteration": state["iteration"] + 1, "env_steps": state["env_steps"] + 96,
                     "train_seconds": state["train_seconds"] + self.iteration_s}
            if state["train_seconds"] >= next_mark:
                save(f"{wall_tag(next_mark)}.pt")
                save("latest.pt")
                next_mark = (int(state["train_seconds"] // mark) + 1) * mark
        save("latest.pt")


@pytest.fixture
def torchrl_table(monkeypatch):
    """The table with ``recipes/ppo_walk.py`` faked (``table.ppo_walk``, a :class:`FakePpoWalk`), checkpoints read as
    JSON, and a gait test that always falls and records what it tested (``table.tested``: snapshot names)."""
    table = load_recipe("library_table")
    table.ppo_walk, table.tested = FakePpoWalk(), []
    monkeypatch.setattr(table, "subprocess", SimpleNamespace(run=lambda *a, **k: table.ppo_walk(*a, **k)))
    monkeypatch.setattr(table, "read_torchrl_state", lambda path: json.loads(Path(path).read_text()))

    def gait(library, snapshot, out, args, command):
        table.tested.append(Path(snapshot).name)
        return FALLS

    monkeypatch.setattr(table, "gait", gait)
    return table


def torchrl_args(tmp_path, *more) -> list[str]:
    """A torchrl row at 2 envs with a 10 s cap and a snapshot every second."""
    return ["--libraries", "torchrl", "--num_envs", "2", "--device", "cpu", "--max_minutes", str(10 / 60),
            "--checkpoint_minutes", str(1 / 60), *files(tmp_path), *more]


def test_recipe_args_go_to_the_library_recipes_only(torchrl_table, tmp_path, capsys):
    torchrl_table.main(torchrl_args(tmp_path, "--minutes", str(2 / 60), "--recipe_args", "--hidden 16"))
    [cmd] = torchrl_table.ppo_walk.commands
    assert cmd[1].endswith("ppo_walk.py") and "--hidden" not in cmd
    assert "--recipe_args '--hidden 16' is for the rsl_rl, skrl and sb3 recipes" in capsys.readouterr().out
    [row] = rows(tmp_path)
    assert row["calls"] == 1 and row["train_seconds"] >= 2.0
    assert torchrl_table.tested == ["wall_00001s.pt", "wall_00002s.pt"]


def test_a_snapshot_period_under_a_second_is_refused(tmp_path, capsys):
    table = load_recipe("library_table")
    with pytest.raises(SystemExit):
        table.main(["--libraries", "torchrl", "--device", "cpu", "--checkpoint_minutes", "0.01", *files(tmp_path)])
    assert "named by whole seconds" in capsys.readouterr().err and not (tmp_path / "table.json").exists()


def recipe_in_this_process(cmd, check=True, cwd=None) -> None:
    """``subprocess.run(cmd, check=True)`` of a ``[python, recipes/train_<library>.py, ARGS]`` command as a call of
    the recipe's ``main(ARGS)`` here; a non-zero exit status raises as ``check`` makes it (CalledProcessError)."""
    assert cmd[0] == sys.executable and Path(cmd[1]).parent.name == "recipes", cmd
    recipe = load_recipe(Path(cmd[1]).stem)
    status = recipe.exit_status(recipe.main(cmd[2:]))
    if check and status:
        raise subprocess.CalledProcessError(status, cmd)


def test_a_second_minutes_call_continues_the_same_row(tmp_path, capsys, monkeypatch):
    # Only what the table decides is asserted, never how long a call took (a loaded 2-core machine may stall a
    # step): whether a call trains, the --max_minutes it gives the recipe (whose clock stops at or past it), the
    # counters' growth, the snapshot names and their order.
    pytest.importorskip("rsl_rl")
    table = load_recipe("library_table")
    # The table's recipe command runs in this process (its main, from the command's own arguments): three fresh
    # interpreters cost ~20 s of imports. test_a_library_recipe_reports_its_used_budget runs it as a subprocess.
    monkeypatch.setattr(table, "subprocess", SimpleNamespace(run=recipe_in_this_process))
    cap_s, minutes = 60 * 0.06, 0.025
    common = ["--libraries", "rsl_rl", "--num_envs", "2", "--device", "cpu", "--max_minutes", "0.06",
              "--checkpoint_minutes", str(1 / 60), "--eval_envs", "2", "--eval_seconds", "0.05", "--minutes",
              str(minutes), "--recipe_args", "--steps_per_env 4 --hidden 16", *files(tmp_path)]

    def call(*more) -> dict:
        before = rows(tmp_path)[0] if (tmp_path / "table.json").is_file() else {
            "calls": 0, "train_seconds": 0.0, "env_steps": 0, "snapshots": []}
        table.main([*common, *more])
        [row] = rows(tmp_path)
        printed = capsys.readouterr().out
        if before["train_seconds"] < cap_s:  # trains: at most --minutes more, never past the cap
            limit = f"{(before['train_seconds'] + min(60 * minutes, cap_s - before['train_seconds'])) / 60:.6g}"
            assert f"--max_minutes {limit} " in printed and row["calls"] == before["calls"] + 1
            assert row["train_seconds"] >= 60 * float(limit) and row["env_steps"] >= before["env_steps"]
        else:
            assert "--max_minutes" not in printed
            assert [row[k] for k in ("calls", "train_seconds", "env_steps")] == [
                before[k] for k in ("calls", "train_seconds", "env_steps")]
        # Earlier snapshots kept as they were; new ones after them, named by cumulative whole training seconds.
        assert row["snapshots"][: len(before["snapshots"])] == before["snapshots"]
        seconds = [table.snapshot_seconds(s) for s in row["snapshots"]]
        assert seconds == sorted(set(seconds)) and all(s == round(s) for s in seconds)
        new = seconds[len(before["snapshots"]):]
        assert all(before["train_seconds"] - 0.5 < s <= row["train_seconds"] + 0.5 for s in new)
        return row

    row = call("--no_eval")
    assert row["status"] == "training" and row["calls"] == 1 and row["tested"] == {} and row["env_steps"] > 0
    assert table.snapshot_seconds(row["snapshots"][0]) == 1.0  # trained >= 1.5 s: the 1 s mark was passed
    assert "pending" in (tmp_path / "table.md").read_text()
    run = row["run"]

    row = call("--no_eval")  # continues (call() checks it trained): same run folder, cumulative counters
    assert row["run"] == run and row["status"] == "training" and row["calls"] == 2

    row = call()  # the rest of the cap (if any is left), then the gait tests: final
    assert row["run"] == run and row["status"] == "final" and row["walks_minutes"] is None
    assert row["train_seconds"] >= 0.99 * cap_s
    assert set(row["tested"]) == {p.rsplit("/", 1)[1][:-3] for p in row["snapshots"]}
    assert {e["device"] for e in row["tested"].values()} == {"cpu"}  # where each gait test ran
    assert "OnPolicyRunner.load" in row["notes"] and "no (≤ 0.06)" in (tmp_path / "table.md").read_text()
    table.main(common)  # a final row is left as it is
    assert rows(tmp_path) == [row]


def test_a_killed_calls_orphan_snapshot_is_kept_aside_and_not_gait_tested(torchrl_table, tmp_path, capsys):
    torchrl_table.main(torchrl_args(tmp_path, "--minutes", str(3 / 60), "--no_eval"))
    [row] = rows(tmp_path)
    checkpoints = Path(row["run"]) / "checkpoints"
    resume_s = json.loads((checkpoints / "latest.pt").read_text())["train_seconds"]
    # A call killed after writing the 4 s snapshot but before latest.pt: trained past the resume point.
    orphan = {**json.loads((checkpoints / "latest.pt").read_text()), "train_seconds": 4.0}
    (checkpoints / "wall_00004s.pt").write_text(json.dumps(orphan))
    torchrl_table.main(torchrl_args(tmp_path, "--minutes", str(0.5 / 60)))  # resumes, stops short of 4 s, tests
    [row] = rows(tmp_path)
    assert resume_s < row["train_seconds"] < 4.0
    assert torchrl_table.tested == ["wall_00001s.pt", "wall_00002s.pt", "wall_00003s.pt"]
    assert [Path(p).name for p in row["snapshots"]] == torchrl_table.tested
    assert json.loads((checkpoints / "wall_00004s_unresumed0.pt").read_text()) == orphan
    assert "wall_00004s.pt was trained past the run's resume point" in capsys.readouterr().out
    torchrl_table.main(torchrl_args(tmp_path, "--minutes", str(1 / 60)))  # reaches 4 s: its own snapshot, tested
    assert torchrl_table.tested[3] == "wall_00004s.pt" and (checkpoints / "wall_00004s_unresumed0.pt").is_file()


def test_a_row_whose_recipe_budget_ends_before_the_cap_turns_final(torchrl_table, tmp_path):
    torchrl_table.ppo_walk = FakePpoWalk(total_env_steps=4 * 96)  # 4 iterations: 1 s of the 10 s cap
    torchrl_table.main(torchrl_args(tmp_path))
    [row] = rows(tmp_path)
    assert row["status"] == "final" and row["recipe_budget_done"] and row["env_steps"] == 4 * 96
    assert torchrl_table.tested == ["wall_00001s.pt"] and len(torchrl_table.ppo_walk.commands) == 1
    torchrl_table.main(torchrl_args(tmp_path))  # final: no more recipe calls
    assert rows(tmp_path) == [row] and len(torchrl_table.ppo_walk.commands) == 1


def test_the_policy_a_recipe_budget_ended_with_is_tested_too(torchrl_table, tmp_path, capsys):
    # 7 iterations of 0.25 s: the budget ends at 1.75 s, between the marks at 1 and 2 s. The policy training ended
    # with (latest.pt) is the snapshot wall_00002s.pt (whole seconds, rounded) and is tested after the 1 s mark.
    torchrl_table.ppo_walk = FakePpoWalk(total_env_steps=7 * 96)
    torchrl_table.main(torchrl_args(tmp_path))
    [row] = rows(tmp_path)
    checkpoints = Path(row["run"]) / "checkpoints"
    assert row["status"] == "final" and row["recipe_budget_done"] and row["train_seconds"] == 1.75
    assert torchrl_table.tested == ["wall_00001s.pt", "wall_00002s.pt"]
    assert (checkpoints / "wall_00002s.pt").read_text() == (checkpoints / "latest.pt").read_text()
    assert [Path(p).name for p in row["snapshots"]] == torchrl_table.tested
    # A row made final before the table tested that policy (as rows of earlier versions were) is opened again,
    # tests it, and is final again; the end snapshot is written from latest.pt if missing.
    (checkpoints / "wall_00002s.pt").unlink()
    row.update(snapshots=row["snapshots"][:1], tested={"wall_00001s": row["tested"]["wall_00001s"]})
    (tmp_path / "table.json").write_text(json.dumps([row]))
    torchrl_table.tested.clear()
    capsys.readouterr()
    torchrl_table.main(torchrl_args(tmp_path, "--eval_only"))
    assert "that last policy is gait-tested too, so the row is open again" in capsys.readouterr().out
    [again] = rows(tmp_path)
    assert torchrl_table.tested == ["wall_00002s.pt"] and again["status"] == "final"
    assert set(again["tested"]) == {"wall_00001s", "wall_00002s"} and len(torchrl_table.ppo_walk.commands) == 1
    torchrl_table.main(torchrl_args(tmp_path, "--eval_only"))  # nothing more to test: left alone
    assert torchrl_table.tested == ["wall_00002s.pt"] and rows(tmp_path) == [again]


def test_the_end_snapshot_of_a_library_recipe_and_its_name_clashes(tmp_path, capsys):
    # The library recipes' last policy is policy.pt; the end snapshot is named by the row's training seconds, and a
    # mark of that name that is listed or already tested (within half a second of the end) is not replaced.
    table = load_recipe("library_table")
    out = tmp_path / "run"
    (out / "checkpoints").mkdir(parents=True)
    (out / "policy.pt").write_bytes(b"last policy")
    row = {"library": "rsl_rl", "preset": "default", "num_envs": 2, "recipe_budget_done": True,
           "train_seconds": 75.4, "snapshots": [str(out / "checkpoints" / "wall_00060s.pt")], "tested": {}}
    assert table.end_snapshot(row, out) == out / "checkpoints" / "wall_00075s.pt"
    assert table.add_end_snapshot("rsl_rl", row, out)
    assert (out / "checkpoints" / "wall_00075s.pt").read_bytes() == b"last policy"
    assert row["snapshots"][-1] == str(out / "checkpoints" / "wall_00075s.pt")
    assert not table.add_end_snapshot("rsl_rl", row, out)  # listed now: once only
    tested_mark = {**row, "train_seconds": 60.3, "snapshots": [], "tested": {"wall_00060s": {}}}
    assert table.end_snapshot(tested_mark, out) is None and not table.add_end_snapshot("rsl_rl", tested_mark, out)
    assert table.end_snapshot({**row, "recipe_budget_done": False, "train_seconds": 90.0}, out) is None
    (out / "policy.pt").unlink()
    missing = {**row, "train_seconds": 99.0, "snapshots": []}
    assert not table.add_end_snapshot("rsl_rl", missing, out) and missing["snapshots"] == []
    assert "its last policy" in capsys.readouterr().out and not (out / "checkpoints" / "wall_00099s.pt").exists()


def test_a_final_row_is_not_opened_again_by_a_call_with_another_cap(torchrl_table, tmp_path):
    torchrl_table.ppo_walk = FakePpoWalk(total_env_steps=7 * 96)
    torchrl_table.main(torchrl_args(tmp_path))
    [row] = rows(tmp_path)
    checkpoints = Path(row["run"]) / "checkpoints"
    (checkpoints / "wall_00002s.pt").unlink()  # as a row of before the end snapshot
    row.update(snapshots=row["snapshots"][:1], tested={"wall_00001s": row["tested"]["wall_00001s"]})
    (tmp_path / "table.json").write_text(json.dumps([row]))
    with pytest.raises(SystemExit):
        torchrl_table.main([*torchrl_args(tmp_path, "--eval_only"), "--max_minutes", "1"])
    assert rows(tmp_path) == [row] and not (checkpoints / "wall_00002s.pt").exists()  # left as it was


def test_a_library_recipe_reports_its_used_budget(tmp_path):
    # The recipe's frozen clock reports a few ms more than it trained; its iteration count tells the budget is used.
    pytest.importorskip("rsl_rl")
    table = load_recipe("library_table")
    args = ["--libraries", "rsl_rl", "--num_envs", "2", "--device", "cpu", "--max_minutes", "1", "--checkpoint_minutes",
            "1", "--eval_envs", "2", "--eval_seconds", "0.5", "--recipe_args",
            "--steps_per_env 4 --hidden 16 --iterations 1", *files(tmp_path)]
    table.main(args)
    [row] = rows(tmp_path)
    assert row["status"] == "final" and row["recipe_budget_done"] and row["calls"] == 1
    assert "no (≤ 1)" in (tmp_path / "table.md").read_text()
    table.main(args)  # left alone: the recipe is not started again
    assert rows(tmp_path) == [row]


def test_eval_only_keeps_and_upgrades_a_row_of_before_resumable_rows(tmp_path, capsys):
    old = {"library": "rsl_rl", "version": "5.5.1", "preset": "default", "num_envs": 4096, "env_steps_per_s": 250000.0,
           "env_steps": 450000000, "train_seconds": 1800.0, "walks_minutes": 12.0,
           "walk": {"snapshot": "runs/r/checkpoints/wall_00720s.pt", "minutes": 12.0, "main": {}, "others": {}},
           "cap_minutes": 30.0, "run": str(tmp_path / "runs" / "r"), "device": "NVIDIA H100 80GB HBM3",
           "command": "python recipes/library_table.py --libraries rsl_rl"}  # the format of before --minutes
    (tmp_path / "table.json").write_text(json.dumps([old]))
    table = load_recipe("library_table")
    table.main(["--libraries", "rsl_rl", "--num_envs", "4096", "--device", "cpu", "--eval_only", *files(tmp_path)])
    [row] = rows(tmp_path)
    assert {k: row[k] for k in old} == old and row["status"] == "final" and row["commands"] == [old["command"]]
    assert "kept as a final row" in capsys.readouterr().out
    assert "| rsl_rl | 5.5.1 | default | 4,096 | 250,000 | 12.0 | 30.0 | 1 |" in (tmp_path / "table.md").read_text()


def test_a_killed_first_call_is_set_aside_and_the_next_call_starts_over(torchrl_table, tmp_path, capsys):
    def killed(cmd, check=True, cwd=None):  # ppo_walk made its run folder; the call died before a checkpoint
        run = Path(cmd[cmd.index("--run_dir") + 1]) / cmd[cmd.index("--name") + 1]
        run.mkdir(parents=True)
        (run / "config.json").write_text("{}")
        raise KeyboardInterrupt

    args = torchrl_args(tmp_path, "--minutes", str(2 / 60), "--no_eval")
    torchrl_table.ppo_walk = killed
    with pytest.raises(KeyboardInterrupt):
        torchrl_table.main(args)
    [row] = rows(tmp_path)  # on record, though no call completed
    run = Path(row["run"])
    assert row["status"] == "training" and row["calls"] == 0 and (run / "config.json").is_file()
    torchrl_table.report([row], tmp_path / "table.md")  # no rate of 0 env-steps/s for a row that never trained
    assert (f"| torchrl | {row['version']} | default | 2 | - | not trained yet (no call has finished) | 0.0 | 0 |"
            in (tmp_path / "table.md").read_text())
    torchrl_table.ppo_walk = FakePpoWalk()
    torchrl_table.main(args)  # nothing to resume and nothing recorded: the folder is kept aside, the row starts over
    [row] = rows(tmp_path)
    assert row["run"] == str(run) and row["calls"] == 1 and row["set_aside"] == [f"{run}_killed1"]
    assert (Path(f"{run}_killed1") / "config.json").read_text() == "{}"
    assert (run / "checkpoints" / "latest.pt").is_file()
    assert f"Kept that folder as {run}_killed1" in capsys.readouterr().out
    # A row with completed calls whose run lost its resume point is not started over: the error names the fix.
    (run / "checkpoints" / "latest.pt").rename(run / "latest.pt.moved")
    with pytest.raises(SystemExit, match=r"no resume point \(checkpoints/latest.pt\) .* pass --new"):
        torchrl_table.main(args)
    assert (run / "latest.pt.moved").is_file() and rows(tmp_path)[0]["calls"] == 1


def test_calls_running_side_by_side_keep_each_others_rows(tmp_path):
    """Two calls on two GPUs share one --json: each writes only its own rows, and a stale copy of the other call's
    row (read when it started) is never written back over the newer one."""
    table = load_recipe("library_table")
    path = tmp_path / "table.json"
    rsl, skrl = ("rsl_rl", "default", 4096), ("skrl", "default", 4096)

    def row(key, status):
        return {"library": key[0], "preset": key[1], "num_envs": key[2], "status": status}

    ours = [row(rsl, "training")]
    table.save_rows(path, ours, {rsl})
    theirs = [row(rsl, "training"), row(skrl, "training")]  # the second call read the file after the first saved
    table.save_rows(path, theirs, {skrl})
    ours[0]["status"] = "final"
    merged = table.save_rows(path, ours, {rsl})
    assert [(r["library"], r["status"]) for r in merged] == [("rsl_rl", "final"), ("skrl", "training")]
    theirs[1]["status"] = "final"  # theirs still holds the stale "training" copy of the rsl_rl row
    merged = table.save_rows(path, theirs, {skrl})
    assert [(r["library"], r["status"]) for r in merged] == [("rsl_rl", "final"), ("skrl", "final")]
    assert json.loads(path.read_text()) == merged


def _lab_tool(name: str):
    """A script of lab/analysis/ (not a package) loaded as a module."""
    import importlib.util

    path = Path(__file__).resolve().parents[2] / "lab" / "analysis" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    return tool


def test_rsl_rl_console_logs_become_one_csv_row_per_iteration(tmp_path):
    # lab/analysis/rsl_rl_log_csv.py: rsl_rl's iteration blocks over two calls of one row (the second resumes the
    # iteration count, its "Total steps" restarts); a value not printed stays empty; a log without blocks is refused.
    tool = _lab_tool("rsl_rl_log_csv")

    def block(it, steps, length=None):
        lines = [f"\x1b[1m   Learning iteration {it}/1000000   \x1b[0m", f"   Total steps: {steps} ",
                 "   Steps per second: 90000 ", "   Mean value loss: 6.4451", "   Mean reward: -3.5",
                 "   /reward/qpos: 0.0351", "   /reward/body_vel: 0.5832", "   Mean action std: 0.05",
                 "   Time elapsed: 0:07:35"]
        return lines + ([f"   Mean episode length: {length}"] if length else [])

    # Two calls' logs of one row, the second xz-compressed as committed: its calls number on from the first's.
    first = ["+ python3 recipes/train_rsl_rl.py --out r", *block(0, 196608), *block(1, 393216, 41.5),
             "rsl_rl: --max_minutes 2 reached"]
    second = ["+ python3 recipes/train_rsl_rl.py --out r", *block(2, 196608, 4314.96)]
    (tmp_path / "a.log").write_text("\n".join(first) + "\n")
    with lzma.open(tmp_path / "b.log.xz", "wt") as fh:
        fh.write("\n".join(second) + "\n")
    assert tool.main([str(tmp_path / "a.log"), str(tmp_path / "b.log.xz"), str(tmp_path / "r.csv")]) == 0
    rows = list(csv.DictReader((tmp_path / "r.csv").open()))
    assert [(r["iteration"], r["call"], r["call_steps"]) for r in rows] == [
        ("0", "1", "196608"), ("1", "1", "393216"), ("2", "2", "196608")]
    assert [r["episode_length"] for r in rows] == ["", "41.5", "4314.96"]
    assert rows[2]["episode_reward"] == "-3.5" and rows[2]["qpos"] == "0.0351" and rows[2]["value_loss"] == "6.4451"
    (tmp_path / "other.log").write_text("no blocks here\n")
    assert tool.main([str(tmp_path / "other.log"), str(tmp_path / "o.csv")]) == 1
    assert not (tmp_path / "o.csv").exists()
    # Two logs and no OUT.csv: the last log was taken for the output and replaced by the CSV.
    log = (tmp_path / "a.log").read_text()
    assert tool.main([str(tmp_path / "a.log"), str(tmp_path / "other.log")]) == 2
    assert (tmp_path / "other.log").read_text() == "no blocks here\n" and (tmp_path / "a.log").read_text() == log
    # An existing CSV: once replaced without a word, now refused unless --overwrite.
    (tmp_path / "kept.csv").write_text("hand-made\n")
    assert tool.main([str(tmp_path / "a.log"), str(tmp_path / "kept.csv")]) == 2
    assert (tmp_path / "kept.csv").read_text() == "hand-made\n"
    assert tool.main(["--overwrite", str(tmp_path / "a.log"), str(tmp_path / "kept.csv")]) == 0
    assert len(list(csv.DictReader((tmp_path / "kept.csv").open()))) == 2


def test_skrl_scalars_of_a_row_become_one_csv_row_per_call_and_timestep(tmp_path):
    # lab/analysis/skrl_events_csv.py: skrl's TensorBoard folders of one row (ppo/ for call 1, ppo_call<k>/ after),
    # each call's timesteps from 0 again; a tag not written at a timestep stays empty; a folder without skrl
    # scalars is refused without writing the CSV.
    pytest.importorskip("tensorboard")
    from torch.utils.tensorboard import SummaryWriter

    tool = _lab_tool("skrl_events_csv")
    run = tmp_path / "skrl_torque_4096_x"
    for folder, values in (("ppo_call2", {48: 1.9, 96: 2.0}), ("ppo", {48: 1.5}), ("ppo_notes", {48: 9.0})):
        with SummaryWriter(str(run / "skrl" / folder)) as writer:
            for step, reward in values.items():
                writer.add_scalar("Reward / Instantaneous reward (mean)", reward, step)
                writer.add_scalar("Policy / Standard deviation", 0.05, step)
            if 96 in values:  # an episode ended only by call 2's second write
                writer.add_scalar("Episode / Total timesteps (mean)", 8000.0, 96)
    out = tmp_path / "r.csv"
    assert tool.main([str(run), str(out)]) == 0
    rows = list(csv.DictReader(out.open()))
    assert [(r["call"], r["timestep"], r["step_reward"]) for r in rows] == [
        ("1", "48", "1.5"), ("2", "48", "1.9"), ("2", "96", "2")]
    assert [r["episode_length"] for r in rows] == ["", "", "8000"]
    assert rows[0]["action_std"] == "0.05" and rows[0]["value_loss"] == ""
    assert tool.main([str(tmp_path / "empty"), str(tmp_path / "o.csv")]) == 1
    assert not (tmp_path / "o.csv").exists()
    # An existing CSV: once replaced without a word, now refused unless --overwrite; an output not ending in .csv
    # (the arguments swapped, say) is refused too.
    out.write_text("hand-made\n")
    assert tool.main([str(run), str(out)]) == 2 and out.read_text() == "hand-made\n"
    assert tool.main([str(run), str(tmp_path / "notes.txt")]) == 2 and not (tmp_path / "notes.txt").exists()
    assert tool.main(["--overwrite", str(run), str(out)]) == 0 and len(list(csv.DictReader(out.open()))) == 3


#: A gait-test summary that passes every threshold.
WALKS = {"survival": 1.0, "forward_distance_m": 3.5, "lateral_drift_m": 0.1, "knee_rms_rad": 0.05}


def test_a_snapshot_fails_at_its_first_failing_command_and_the_rest_are_not_run(torchrl_table, tmp_path):
    runs = []

    def gait(library, snapshot, out, args, command):  # passes at (0.5, 0), falls at (0.2, 0)
        runs.append((Path(snapshot).stem, command))
        return WALKS if command == (0.5, 0.0) else {**WALKS, "survival": 0.9}

    torchrl_table.gait = gait
    torchrl_table.main(torchrl_args(tmp_path, "--max_minutes", str(2 / 60)))
    [row] = rows(tmp_path)
    assert runs == [("wall_00001s", (0.5, 0.0)), ("wall_00001s", (0.2, 0.0)),  # (0.7, 0.1) of neither is run
                    ("wall_00002s", (0.5, 0.0)), ("wall_00002s", (0.2, 0.0))]
    assert row["tested"]["wall_00001s"]["others"] == {"0.2_0.0": 0.9} and not row["tested"]["wall_00001s"]["passes"]
    assert row["walk"] is None and row["status"] == "final" and "testing" not in row


def test_a_call_that_ends_mid_snapshot_leaves_only_its_missing_commands_to_the_next(torchrl_table, tmp_path):
    torchrl_table.main(torchrl_args(tmp_path, "--max_minutes", str(1 / 60), "--no_eval"))
    runs = []

    def gait(library, snapshot, out, args, command):  # every command passes; the call is killed in the third
        if len(runs) == 2:
            raise KeyboardInterrupt
        runs.append(command)
        return WALKS

    torchrl_table.gait = gait
    with pytest.raises(KeyboardInterrupt):
        torchrl_table.main(torchrl_args(tmp_path, "--max_minutes", str(1 / 60), "--eval_only"))
    [row] = rows(tmp_path)
    assert set(row["testing"]["wall_00001s"]) == {"0.5_0.0", "0.2_0.0"} and "wall_00001s" not in row["tested"]
    runs.clear()
    runs.append(None)  # the next call's gait test is not killed (three runs in all)
    torchrl_table.main(torchrl_args(tmp_path, "--max_minutes", str(1 / 60), "--eval_only"))
    [row] = rows(tmp_path)
    assert runs == [None, (0.7, 0.1)]  # only the command the killed call had not finished
    assert row["walks_minutes"] == pytest.approx(1 / 60) and row["status"] == "final" and "testing" not in row
    assert row["walk"]["others"] == {"0.2_0.0": 1.0, "0.7_0.1": 1.0} and row["walk"]["main"] == WALKS


def test_eval_minutes_spent_between_commands_keeps_the_finished_ones_for_the_next_call(torchrl_table, tmp_path,
                                                                                      monkeypatch, capsys):
    import time

    torchrl_table.main(torchrl_args(tmp_path, "--max_minutes", str(1 / 60), "--no_eval"))
    clock, runs = {"now": 0.0}, []

    def gait(library, snapshot, out, args, command):  # every command passes and takes a minute of the clock
        runs.append(command)
        clock["now"] += 60.0
        return WALKS

    torchrl_table.gait = gait
    monkeypatch.setattr(torchrl_table, "time", SimpleNamespace(monotonic=lambda: clock["now"], strftime=time.strftime))
    torchrl_table.main(torchrl_args(tmp_path, "--max_minutes", str(1 / 60), "--eval_only", "--eval_minutes", "1.5"))
    [row] = rows(tmp_path)
    assert runs == [(0.5, 0.0), (0.2, 0.0)]  # the third would start after the 1.5 minutes
    assert set(row["testing"]["wall_00001s"]) == {"0.5_0.0", "0.2_0.0"} and row["status"] != "final"
    assert "--eval_minutes spent; the next call goes on from wall_00001s" in capsys.readouterr().out
    clock["now"] = 0.0
    torchrl_table.main(torchrl_args(tmp_path, "--max_minutes", str(1 / 60), "--eval_only", "--eval_minutes", "1.5"))
    [row] = rows(tmp_path)
    assert runs[2:] == [(0.7, 0.1)] and row["walks_minutes"] == pytest.approx(1 / 60) and "testing" not in row


def test_a_missing_snapshot_stops_the_rows_gait_tests_there_and_says_so(torchrl_table, tmp_path, capsys):
    torchrl_table.main(torchrl_args(tmp_path, "--max_minutes", str(3 / 60), "--no_eval"))
    [row] = rows(tmp_path)
    gone = [s for s in row["snapshots"] if Path(s).name == "wall_00002s.pt"]
    assert len(row["snapshots"]) == 3 and len(gone) == 1
    Path(gone[0]).unlink()  # as when a call's packing left it on the GPU machine
    torchrl_table.main(torchrl_args(tmp_path, "--max_minutes", str(3 / 60), "--eval_only"))
    [row] = rows(tmp_path)
    assert torchrl_table.tested == ["wall_00001s.pt"]  # not the 3 s one after the gap
    assert set(row["tested"]) == {"wall_00001s"} and row["status"] != "final" and "testing" not in row
    assert f"snapshot {gone[0]} is missing" in capsys.readouterr().out


#: A table row with what the table shows of it (a row that walks at 3 minutes).
SHOWN = {"library": "rsl_rl", "version": "5.5.1", "preset": "default", "num_envs": 8, "env_steps_per_s": 100.0,
         "walks_minutes": 3.0, "train_seconds": 180.0, "status": "final", "device": "cpu", "commands": ["c"]}


def test_report_refuses_a_missing_json_and_leaves_the_md_alone(tmp_path, capsys):
    # A mistyped --json once rendered [] over the committed table: header only, exit 0.
    table = load_recipe("library_table")
    (tmp_path / "table.md").write_text("the committed table\n")
    with pytest.raises(SystemExit) as exit_:
        table.main(["--report", "--json", str(tmp_path / "tabel.json"), "--md", str(tmp_path / "table.md")])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and "error: --json" in err and "tabel.json: no such file" in err
    assert (tmp_path / "table.md").read_text() == "the committed table\n"


@pytest.mark.parametrize("text, said", [
    ('[{"library": "rsl_rl"', "is not a table json: Expecting"),
    ('{"library": "rsl_rl"}', "not a list of rows"),
    (json.dumps([{k: v for k, v in SHOWN.items() if k != "preset"}]), "row 1 has no 'preset'"),
    (json.dumps([SHOWN, {k: v for k, v in SHOWN.items() if k != "device"}]), "row 2 (rsl_rl default 8) has no 'device'"),
    (json.dumps([{**SHOWN, "num_envs": "many"}]), "row 1 (rsl_rl default many)"),
])
def test_report_names_the_file_of_a_malformed_json_or_row(tmp_path, capsys, text, said):
    table = load_recipe("library_table")
    (tmp_path / "table.json").write_text(text)
    (tmp_path / "table.md").write_text("the committed table\n")
    with pytest.raises(SystemExit) as exit_:
        table.main(["--report", *files(tmp_path)])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and str(tmp_path / "table.json") in err and said in err
    assert (tmp_path / "table.md").read_text() == "the committed table\n"


def test_report_rewrites_the_md_and_says_from_what(tmp_path, capsys):
    table = load_recipe("library_table")
    (tmp_path / "table.json").write_text(json.dumps([SHOWN]))
    table.main(["--report", *files(tmp_path)])
    assert "| rsl_rl | 5.5.1 | default | 8 | 100 | 3.0 | 3.0 | 1 | cpu | `c` |" in (tmp_path / "table.md").read_text()
    assert f"{tmp_path / 'table.md'}: 1 row(s) from {tmp_path / 'table.json'}" in capsys.readouterr().out


def test_relative_paths_are_from_the_current_folder_and_the_defaults_in_the_repository(torchrl_table, tmp_path,
                                                                                         monkeypatch):
    table = torchrl_table
    assert table.given_path(None, table.DEFAULT_JSON) == table.ROOT / "docs" / "adapters_table.json"
    assert table.given_path(None, table.DEFAULT_RUNS) == table.ROOT / "runs" / "library_table"
    here = tmp_path / "here"
    here.mkdir()
    monkeypatch.chdir(here)
    assert table.given_path("../t.json", table.DEFAULT_JSON) == tmp_path / "t.json"
    (here / "mine.json").write_text(json.dumps([SHOWN]))
    table.main(["--report", "--json", "mine.json", "--md", "mine.md"])
    assert "| rsl_rl |" in (here / "mine.md").read_text() and not (table.ROOT / "mine.md").exists()
    # A training call: its run folder, json and md where the relative paths say.
    table.main(["--libraries", "torchrl", "--num_envs", "2", "--device", "cpu", "--max_minutes", str(1 / 60),
                "--checkpoint_minutes", str(1 / 60), "--runs", "r", "--json", "t.json", "--md", "t.md"])
    [row] = json.loads((here / "t.json").read_text())
    assert Path(row["run"]).parent == here / "r" and (here / "t.md").is_file()
    assert not (table.ROOT / "t.json").exists() and not (table.ROOT / "r").exists()


@pytest.mark.parametrize("bad, said", [
    (["--libraries", "torchrl,rsl-rl"], ("--libraries torchrl,rsl-rl: unknown library 'rsl-rl'; give "
                                         "comma-separated names of torchrl, rsl_rl, skrl, sb3")),
    (["--libraries", "torchrl,"], "--libraries torchrl,: unknown library ''"),
    (["--num_envs", "2,abc"], "--num_envs 2,abc: 'abc' is not an env count"),
    (["--num_envs", "0"], "--num_envs 0: '0' is not an env count; give comma-separated whole numbers >= 1"),
    (["--num_envs", "2,-8"], "--num_envs 2,-8: '-8' is not an env count"),
    (["--minutes", "-5"], "--minutes -5: give a finite number >= 0 (0: up to --max_minutes)"),
    (["--minutes", "inf"], "--minutes inf: give a finite number >= 0"),
    (["--max_minutes", "0"], "--max_minutes 0: give a finite number > 0"),
    (["--max_minutes", "nan"], "--max_minutes nan: give a finite number > 0"),
    (["--eval_minutes", "-1"], "--eval_minutes -1: give a finite number >= 0 (0: test all)"),
    (["--checkpoint_minutes", "inf"], "--checkpoint_minutes inf: give a finite number > 0"),
    (["--eval_seconds", "0"], "--eval_seconds 0: give a finite number > 0"),
    (["--eval_envs", "0"], "--eval_envs 0: give a number of robots >= 1"),
    (["--preset", "torq"], "--preset torq: unknown preset; choose from"),
])
def test_arguments_are_checked_before_any_row_runs(torchrl_table, tmp_path, capsys, bad, said):
    # Before: the torchrl row trained (up to 30 minutes) before 'rsl-rl' was found unknown; --minutes -5 was no limit.
    with pytest.raises(SystemExit) as exit_:
        torchrl_table.main(torchrl_args(tmp_path, *bad))
    out, err = capsys.readouterr()
    assert exit_.value.code == 2 and f"error: {said}" in err and out == ""
    assert torchrl_table.ppo_walk.commands == [] and torchrl_table.tested == []
    assert not (tmp_path / "table.json").exists() and not (tmp_path / "runs").exists()


def test_a_malformed_json_is_refused_before_any_row_runs(torchrl_table, tmp_path, capsys):
    (tmp_path / "table.json").write_text("[")
    with pytest.raises(SystemExit):
        torchrl_table.main(torchrl_args(tmp_path))
    assert f"error: --json: {tmp_path / 'table.json'} is not a table json" in capsys.readouterr().err
    assert torchrl_table.ppo_walk.commands == [] and (tmp_path / "table.json").read_text() == "["


@pytest.mark.parametrize("extra, said", [
    (["--checkpoint_minutes", "0"], "--checkpoint_minutes 0: give a finite number > 0"),
    (["--checkpoint_minutes", "31"], "longer than the cap"),
    (["--eval_only", "--new"], "--eval_only --new"),
])
def test_settings_that_would_leave_a_row_untested_are_refused(tmp_path, capsys, extra, said):
    table = load_recipe("library_table")
    with pytest.raises(SystemExit):
        table.main(["--libraries", "torchrl", "--device", "cpu", *extra, *files(tmp_path)])
    assert said in capsys.readouterr().err and not (tmp_path / "table.json").exists()


def test_a_rows_snapshots_are_all_gait_tested_alike_and_a_shorter_test_is_named(torchrl_table, tmp_path):
    # A 1 s test fails a policy that walks: its "no" must say so, and later calls may not mix in another setting.
    torchrl_table.main(torchrl_args(tmp_path, "--minutes", str(3 / 60), "--eval_seconds", "1", "--eval_envs", "2"))
    [row] = rows(tmp_path)
    assert row["gait_test"] == {"seconds": 1.0, "num_envs": 2}
    with pytest.raises(SystemExit, match="--eval_seconds 1 --eval_envs 2"):
        torchrl_table.main(torchrl_args(tmp_path, "--eval_only"))
    torchrl_table.main(torchrl_args(tmp_path, "--eval_seconds", "1", "--eval_envs", "2"))  # to the cap, alike
    [row] = rows(tmp_path)
    assert row["status"] == "final"
    assert "no (≤ 0.166667) (gait test 1 s, 2 robots)" in (tmp_path / "table.md").read_text()


def test_eval_minutes_bound_the_whole_calls_testing_and_nan_survival_fails(torchrl_table, tmp_path, monkeypatch):
    clock = [0.0]
    monkeypatch.setattr(torchrl_table.time, "monotonic", lambda: clock[0])
    walks = {"survival": 1.0, "forward_distance_m": 4.0, "forward_distance_survivors_m": 4.0,
             "lateral_drift_m": 0.0, "speed_tracking_error_mps": 0.0, "knee_rms_rad": 0.0}

    def gait(library, snapshot, out, args, command):  # one minute a test; the main command walks, the others NaN
        clock[0] += 60.0
        torchrl_table.tested.append(Path(snapshot).name)
        return walks if command == torchrl_table.MAIN else {**walks, "survival": float("nan")}

    monkeypatch.setattr(torchrl_table, "gait", gait)
    torchrl_table.main(torchrl_args(tmp_path, "--num_envs", "2,3", "--minutes", str(3 / 60), "--eval_minutes", "2.5"))
    assert len(torchrl_table.tested) == 3  # 2.5 minutes for the call: three tests started, not three a row
    assert all(r.get("walks_minutes") is None for r in rows(tmp_path))  # NaN survival at a second command fails


def test_rows_of_a_renamed_preset_read_as_its_name_now_and_keep_the_one_they_ran_under(tmp_path):
    # The torque preset of before 2026-12-06 is torque_ideal now: its rows are that preset's, not the new torque's.
    table = load_recipe("library_table")
    row = {"library": "skrl", "version": "2.1.1", "preset": "torque", "num_envs": 4096, "env_steps_per_s": 109749.0,
           "train_seconds": 1800.0, "cap_minutes": 30.0, "status": "final", "calls": 4, "device": "NVIDIA H200",
           "commands": ["python recipes/library_table.py --libraries skrl --preset torque"]}
    old = {**row, "run": str(tmp_path / "runs" / "skrl_torque_4096_20261128_092928")}
    new = {**row, "run": str(tmp_path / "runs" / "skrl_torque_4096_20261207_101010")}
    (tmp_path / "table.json").write_text(json.dumps([old, new]))
    first, second = table.load_rows(tmp_path / "table.json")
    assert (first["preset"], first["preset_then"]) == ("torque_ideal", "torque")
    assert second["preset"] == "torque" and "preset_then" not in second
    assert first["commands"] == old["commands"]  # what was run, as it was run
    assert table.row_key(first) != table.row_key(second)
    # The same row under both names is refused: saving would keep one of them.
    ideal = {**row, "preset": "torque_ideal", "run": str(tmp_path / "runs" / "skrl_torque_ideal_4096_20261207_1")}
    (tmp_path / "both.json").write_text(json.dumps([ideal, old]))
    with pytest.raises(ValueError, match=r"rows 1 and 2 are both skrl torque_ideal 4096 \(row 2 ran as torque"):
        table.load_rows(tmp_path / "both.json")
    table.report([first, second], tmp_path / "table.md")
    text = (tmp_path / "table.md").read_text()
    assert "| skrl | 2.1.1 | torque_ideal (run as torque) | 4,096 |" in text
    assert "| skrl | 2.1.1 | torque | 4,096 |" in text


def test_a_torchrl_rows_mini_batch_fits_the_presets_own_rollout(torchrl_table, tmp_path):
    # The torque preset collects 12 steps per env (the default 48): 2 envs make a rollout of 24, not 96.
    for preset, size in (("default", "96"), ("torque", "24")):
        torchrl_table.ppo_walk.commands.clear()
        torchrl_table.main(torchrl_args(tmp_path / preset, "--minutes", str(1 / 60), "--preset", preset))
        cmd = torchrl_table.ppo_walk.commands[0]
        assert cmd[cmd.index("--ppo.minibatch_size") + 1] == size, preset
