"""benchmarks/env_graph_report.py: pairs graph-on and graph-off throughput results into the ablation page."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import env_graph_report


def _result(path: Path, rates: dict[int, float], mode: str) -> None:
    path.write_text(json.dumps({
        "meta": {"gpu": "Test GPU", "date": "2026-11-24", "command": f"train_throughput.py --set cuda_graph={mode}"},
        "results": [{"num_envs": n, "train_env_steps_per_s": r, "raw_policy_steps_per_s": 2 * r}
                    for n, r in rates.items()],
    }))


def test_pairs_become_rows_sorted_by_env_count(tmp_path):
    _result(tmp_path / "graph_on_big.json", {512: 90.0}, "on")
    _result(tmp_path / "graph_off_big.json", {512: 100.0}, "off")
    _result(tmp_path / "graph_on_small.json", {8: 30.0}, "on")
    _result(tmp_path / "graph_off_small.json", {8: 20.0}, "off")
    text = env_graph_report.write(tmp_path, tmp_path / "out")
    assert [r["num_envs"] for r in env_graph_report.load_pairs(tmp_path)] == [8, 512]
    assert "| 8 | 30 | 20 | 1.50 |" in text and "| 512 | 90 | 100 | 0.90 |" in text
    assert "--set cuda_graph=off" in text and (tmp_path / "out" / "env_graph.png").stat().st_size > 0


def test_a_result_without_its_eager_counterpart_is_refused(tmp_path):
    _result(tmp_path / "graph_on_x.json", {8: 30.0}, "on")
    with pytest.raises(FileNotFoundError, match="graph_off_x.json"):
        env_graph_report.load_pairs(tmp_path)
    _result(tmp_path / "graph_off_x.json", {16: 30.0}, "off")
    with pytest.raises(ValueError, match="lacks 8 envs"):
        env_graph_report.load_pairs(tmp_path)
