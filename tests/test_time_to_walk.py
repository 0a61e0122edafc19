"""benchmarks/time_to_walk.py end to end on the CPU at toy size: resumed training with wall-clock checkpoints, the
gait test of each, the report."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "time_to_walk.py"


def _run(cwd, *args):
    proc = subprocess.run([sys.executable, str(SCRIPT), *args], cwd=cwd, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc.stdout


def test_time_to_walk_train_resume_eval_report(tmp_path):
    train = ["train", "--preset", "cpu_smoke", "--device", "cpu", "--every", "0.002", "--log_every", "1"]
    _run(tmp_path, *train, "--minutes", "0.004", "--budget_minutes", "1")
    out = _run(tmp_path, *train, "--minutes", "1", "--budget_minutes", "1")  # resumes to the end of the preset
    assert "training from runs/time_to_walk/cpu_smoke/checkpoints/latest.pt" in out
    run = tmp_path / "runs/time_to_walk/cpu_smoke"
    walls = sorted(p.stem for p in (run / "checkpoints").glob("wall_*.pt"))
    assert walls, "no wall-clock checkpoint was written"
    _run(tmp_path, "eval", "--preset", "cpu_smoke", "--device", "cpu", "--num_envs", "2", "--seconds", "0.1")
    record = {**json.loads((run / "train.json").read_text()), **json.loads((run / "evals.json").read_text())}
    assert sorted(record["evaluations"]) == walls and len(record["commands"]) == 2
    for entry in record["evaluations"].values():
        main = entry["commands"]["0.5,0.0"]
        assert 0.0 <= main["survival"] <= 1.0 and entry["walks"] is False  # 0.1 s cannot cover 2.6 m
    assert record["time_to_walk"] is None
    text = _run(tmp_path, "report", "--runs", str(run), "--curves", str(run / "metrics.csv"),
                "--out", str(tmp_path / "docs"))
    assert "| cpu_smoke | cpu | not within" in text
    assert (tmp_path / "docs/time_to_walk.png").is_file() and (tmp_path / "docs/time_to_walk_curves.png").is_file()
