"""lab/analysis/step_ops.py: its op and kernel counts, its refusal to overwrite, and the page's table of them."""

from __future__ import annotations

import json

import pytest
import torch

from lab.analysis import step_ops
from lab.benchmarks import page
from tocabi_torchrl.config import preset_tree
from tocabi_torchrl.tree import replace_paths


def test_kernels_leave_out_views_casts_and_the_simulator():
    torch.set_num_threads(1)
    off = replace_paths(preset_tree("robust"), step_ops.OFF)
    ops, kernels, top = step_ops.ops_per_step(off, num_envs=4, steps=2)
    assert 0 < kernels < ops and sum(top.values()) <= ops
    # With the sensor noise on, the step does more work outside the simulator: its hash, Box-Muller and adds.
    noisy = replace_paths(off, {"transforms.sensor_noise": preset_tree("robust").transforms.sensor_noise})
    assert step_ops.ops_per_step(noisy, num_envs=4, steps=2)[1] > kernels + 50


def test_it_refuses_to_overwrite_without_being_asked(tmp_path):
    out = tmp_path / "step_ops.json"
    out.write_text("{}")
    with pytest.raises(SystemExit):
        step_ops.main(["--out", str(out)])
    assert out.read_text() == "{}"


def test_a_report_that_appears_during_the_count_is_not_replaced(tmp_path, monkeypatch, capsys):
    # The check ran at the start and the write, after the count, replaced whatever had appeared at --out since; then
    # it refused with FileExistsError, losing the count. The results go beside it now, and one line says where.
    out = tmp_path / "step_ops.json"

    def count(cfg, num_envs, steps):
        out.exists() or out.write_text("{}")  # another run's report, written while this one counts
        return 10.0, 5.0, {}

    monkeypatch.setattr(step_ops, "ops_per_step", count)
    step_ops.main(["--out", str(out)])
    assert out.read_text() == "{}"
    beside = sorted(tmp_path.glob("step_ops.*.json"))
    assert len(beside) == 1 and json.loads(beside[0].read_text())["results"]
    warning = capsys.readouterr().err
    assert f"{out} appeared" in warning and str(beside[0]) in warning
    step_ops.main(["--out", str(out), "--overwrite"])  # asked for: replaced
    assert json.loads(out.read_text())["results"]


def test_the_page_shows_kernels_where_the_report_has_them(tmp_path):
    name = tmp_path / "benchmarks" / "randomization" / "step_ops.json"
    name.parent.mkdir(parents=True)
    meta = {"command": "c", "code": "abc", "date": "d", "hardware": "CPU", "num_envs": 32, "torch": "t"}
    old = {"what": "nothing", "ops_per_step": 10.0, "over_nothing": 0.0}
    name.write_text(json.dumps({"meta": meta, "results": [old]}))
    text = "\n".join(page.step_ops(tmp_path))
    assert "| nothing | 10 (+0) |" in text and "kernels" not in text
    new = {**old, "kernels_per_step": 6.0, "kernels_over_nothing": 0.0, "ops_per_step_before": 12.0,
           "kernels_per_step_before": None}
    name.write_text(json.dumps({"meta": {**meta, "before": {"code": "old", "what": "w"}}, "results": [new]}))
    lines = page.step_ops(tmp_path)
    head = next(line for line in lines if line.startswith("| switched on"))
    assert head.count("|") - 1 == 5 and "| nothing | 10 (+0) | 6 (+0) | 12 | - |" in lines


@pytest.mark.parametrize("text", [None, "not json", '{"results": []}', "[1, 2]",
                                  '{"meta": {"code": "a"}, "results": [{}]}'])
def test_a_before_report_that_is_not_one_is_refused_before_the_count(text, tmp_path, monkeypatch, capsys):
    # It was read with json.loads at the start (a traceback for a missing or non-JSON file) and its meta and rows
    # only after the count: a KeyError after a minute of work, and no report written.
    monkeypatch.setattr(step_ops, "ops_per_step", lambda *a, **k: pytest.fail("counted before checking --before"))
    before = tmp_path / "before.json"
    if text is not None:
        before.write_text(text)
    with pytest.raises(SystemExit) as refused:
        step_ops.main(["--before", str(before), "--out", str(tmp_path / "out.json")])
    assert refused.value.code == 2 and f"--before {before}" in capsys.readouterr().err
    assert not (tmp_path / "out.json").exists()
