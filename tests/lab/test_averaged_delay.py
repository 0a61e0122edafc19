"""lab/analysis/averaged_delay.py: the shipped robust policy under the lab's delay per substep and averaged."""

from __future__ import annotations

import dataclasses
import doctest
import json

import pytest

pytest.importorskip("onnxruntime")

from lab.analysis import averaged_delay
from tocabi_torchrl.runtime import randomization as rnd


def test_docstring_examples_run():
    result = doctest.testmod(averaged_delay)
    assert result.attempted >= 1 and result.failed == 0


def test_the_variants_differ_only_in_how_the_delay_is_applied():
    per_substep, averaged = averaged_delay.variants().values()
    assert per_substep == rnd.TOCABI_LAB and averaged.actuators.delay_average
    assert dataclasses.replace(averaged.actuators, delay_average=False) == per_substep.actuators
    assert (averaged.dynamics, averaged.sensors) == (per_substep.dynamics, per_substep.sensors)


@pytest.mark.skipif(not averaged_delay.CONTRACT.is_file(), reason="shipped robust policy not present")
def test_a_small_run_reports_both_variants_with_its_command_and_never_overwrites(tmp_path):
    out = tmp_path / "avg.json"
    averaged_delay.main(["--num_robots", "2", "--speeds", "0.5", "--out", str(out)])
    report = json.loads(out.read_text())
    assert report["command"].startswith("PYTHONPATH=. python lab/analysis/averaged_delay.py --num_robots 2")
    assert [r["variant"] for r in report["results"]] == list(averaged_delay.runs())
    for r in report["results"]:
        assert r["kick_speed_mps"] == 0.5 and 0.0 <= r["survival"] <= 1.0 and len(r["alive"]) == 2
        assert r["outcomes_changed"] == averaged_delay.changed(report["results"][0]["alive"], r["alive"])
    assert report["results"][0]["outcomes_changed"] == 0
    with pytest.raises(SystemExit):
        averaged_delay.main(["--num_robots", "2", "--speeds", "0.5", "--out", str(out)])
