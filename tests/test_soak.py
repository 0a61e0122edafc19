"""benchmarks/soak.py at a tiny CPU size: faults stay in their worlds, training stays finite, a killed run resumes."""

from __future__ import annotations

import json
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCH))

import pytest  # noqa: E402
import soak  # noqa: E402


@pytest.mark.slow  # ~45 s on 2 cores: two training processes (one killed, one resumed) and a faulty training run
def test_tiny_soak_on_the_cpu(tmp_path):
    # 15 s: at 0.1 min a loaded 2-core machine finished only one rollout before the time limit, and the memory
    # series needs two.
    code = soak.main(["--num_envs", "8", "--minutes", "0.25", "--device", "cpu", "--fault_every", "40",
                      "--out", str(tmp_path / "out"), "--run_dir", str(tmp_path / "runs")])
    report = json.loads((tmp_path / "out" / "soak.json").read_text())
    failed = [c for c in report["results"] if not c["ok"]]
    assert code == 0 and not failed, failed
    faults = report["meta"]["faults"]
    assert faults["fault_events"] >= 1 and faults["monitor"]["nan_worlds"] == faults["fault_events"]
    kill = report["meta"]["kill_resume"]
    assert kill["killed"] and kill["metrics_iterations"][-1] == kill["last_checkpoint_iteration"] + 2
    assert (tmp_path / "out" / "soak.md").read_text().startswith("# Soak: 8 envs")
    series = faults["memory_series"]
    assert len(series) >= 2 and [r["rollout"] for r in series] == list(range(1, len(series) + 1))
    assert (tmp_path / "out" / "soak_memory.png").stat().st_size > 1000
    # One mode per command (a 10-minute device call each): the other mode's results stay in soak.json.
    meta = {}
    kept = soak.keep_other_modes(tmp_path / "out" / "soak.json", ("faults",), meta)
    assert kept and {c["mode"] for c in kept} == {"kill_resume"} and meta["kill_resume"] == kill


@pytest.mark.skipif(__import__("torch").cuda.is_available(), reason="needs a machine without CUDA")
def test_kill_resume_reports_a_training_that_died_by_itself(tmp_path):
    # On a CPU-only machine --device cuda makes the trainer exit at once: the soak must say so, with its log.
    code = soak.main(["--mode", "kill_resume", "--device", "cuda", "--num_envs", "8", "--out", str(tmp_path),
                      "--run_dir", str(tmp_path / "runs")])
    report = json.loads((tmp_path / "soak.json").read_text())
    assert code == 1
    assert report["results"][0]["value"] == "exited by itself with code 1"
    assert "torch sees no CUDA GPU" in report["meta"]["kill_resume"]["training_log_tail"]
