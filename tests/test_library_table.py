"""recipes/library_table.py split over calls: a second ``--minutes`` call continues the same row and run (cumulative
training time and env steps), the gait tests run on the snapshots, and a final row is left alone (CPU, tiny)."""

from __future__ import annotations

import json

import pytest
from recipe_runner import load_recipe


def files(tmp_path) -> list[str]:
    """The table's run folder, json and md under ``tmp_path``."""
    return ["--runs", str(tmp_path / "runs"), "--json", str(tmp_path / "table.json"), "--md", str(tmp_path / "table.md")]


def test_a_snapshot_period_under_a_second_is_refused(tmp_path, capsys):
    table = load_recipe("library_table")
    with pytest.raises(SystemExit):
        table.main(["--libraries", "torchrl", "--device", "cpu", "--checkpoint_minutes", "0.01", *files(tmp_path)])
    assert "named by whole seconds" in capsys.readouterr().err and not (tmp_path / "table.json").exists()


def test_a_second_minutes_call_continues_the_same_row(tmp_path):
    pytest.importorskip("rsl_rl")
    table = load_recipe("library_table")
    common = ["--libraries", "rsl_rl", "--num_envs", "2", "--device", "cpu", "--max_minutes", "0.06",
              "--checkpoint_minutes", str(1 / 60), "--eval_envs", "2", "--eval_seconds", "0.05",
              "--recipe_args", "--steps_per_env 4 --hidden 16", *files(tmp_path)]
    table.main([*common, "--minutes", "0.025", "--no_eval"])
    [row] = json.loads((tmp_path / "table.json").read_text())
    assert row["status"] == "training" and row["calls"] == 1 and row["tested"] == {}
    first_s, first_steps, run = row["train_seconds"], row["env_steps"], row["run"]
    assert 1.5 <= first_s < 3.0 and first_steps > 0 and len(row["snapshots"]) >= 1
    assert "pending" in (tmp_path / "table.md").read_text()

    table.main([*common, "--minutes", "0.025", "--no_eval"])  # continues: same run folder, cumulative counters
    [row] = json.loads((tmp_path / "table.json").read_text())
    assert row["run"] == run and row["calls"] == 2 and row["status"] == "training"
    assert row["train_seconds"] >= first_s + 1.5 and row["env_steps"] > first_steps
    seconds = [table.snapshot_seconds(s) for s in row["snapshots"]]
    assert seconds == sorted(seconds) and len(set(seconds)) == len(seconds) and seconds[-1] > first_s

    table.main([*common, "--minutes", "0.025"])  # the last 0.6 s of the cap, then the gait tests: final
    [row] = json.loads((tmp_path / "table.json").read_text())
    assert row["run"] == run and row["calls"] == 3 and row["status"] == "final"
    assert row["train_seconds"] >= 0.99 * 60 * 0.06 and row["walks_minutes"] is None
    assert set(row["tested"]) == {p.rsplit("/", 1)[1][:-3] for p in row["snapshots"]}
    assert "OnPolicyRunner.load" in row["notes"] and "no (≤ 0.06)" in (tmp_path / "table.md").read_text()
    table.main([*common, "--minutes", "0.025"])  # a final row is left as it is
    assert json.loads((tmp_path / "table.json").read_text()) == [row]
