"""lab/analysis/run_compare.py: runs side by side at equal env steps, from the committed robust runs' metrics."""
from __future__ import annotations

import doctest
import shutil
from pathlib import Path

import pytest

from lab.analysis import run_compare

ROBUST = Path(__file__).resolve().parents[2] / "docs" / "training" / "robust"


def test_docstring_example_runs():
    result = doctest.testmod(run_compare)
    assert result.attempted and not result.failed


def test_each_span_is_the_median_of_its_logged_iterations_and_an_empty_span_is_a_dash():
    runs = [ROBUST / "h200_run9", ROBUST / "h200_run22" / "metrics"]  # a run folder and a metrics folder
    text = run_compare.compare(runs, [20e6, 40e6, 60e6, 1e9, 2e9], ["lr", "terminated_frac"])
    lines = text.splitlines()
    assert lines[2] == "| env steps | h200_run9 | h200_run22 |"  # a metrics folder is named by its run
    assert lines[4] == "| 20-40 M | 4.44e-04 | 1.22e-04 |"  # the medians run 22's README quotes
    assert lines[6] == "| 60-1000 M | 7.50e-05 | 1.13e-04 |"
    assert lines[7] == "| 1000-2000 M | - | - |"  # no run reached a billion env steps
    assert "### terminated_frac" in text


def test_bad_spans_and_unknown_metrics_are_refused_naming_what_is_there():
    with pytest.raises(ValueError, match="increasing"):
        run_compare.compare([ROBUST / "h200_run9"], [40e6, 20e6], ["lr"])
    with pytest.raises(ValueError, match=r"no run logged \['lrr'\].*\blr\b"):
        run_compare.compare([ROBUST / "h200_run9"], [0, 20e6], ["lrr"])


def test_out_is_written_and_never_overwritten(tmp_path, capsys):
    out = tmp_path / "compare.md"
    text = run_compare.main([str(ROBUST / "h200_run9"), "--spans", "0", "20", "--metrics", "kl", "--out", str(out)])
    assert out.read_text() == text + "\n"
    with pytest.raises(SystemExit):
        run_compare.main([str(ROBUST / "h200_run9"), "--metrics", "kl", "--out", str(out)])
    assert "exists already" in capsys.readouterr().err


def test_a_run_named_twice_is_refused_and_same_named_runs_get_their_parent_in_the_header(tmp_path, monkeypatch):
    for again in (str(ROBUST / "h200_run9") + "/", ROBUST / "h200_run9" / "metrics"):
        with pytest.raises(ValueError, match="name the same run"):
            run_compare.compare([ROBUST / "h200_run9", again], [0, 20e6], ["lr"])
    for gpu in ("a", "b"):  # one run's metrics copied under two folders of the same run name
        shutil.copytree(ROBUST / "h200_run9" / "metrics", tmp_path / gpu / "h200_run9" / "metrics")
    text = run_compare.compare([tmp_path / "a" / "h200_run9", tmp_path / "b" / "h200_run9" / "metrics"],
                               [0, 20e6], ["lr"])
    assert text.splitlines()[2] == "| env steps | a/h200_run9 | b/h200_run9 |"
    monkeypatch.chdir(tmp_path / "a")  # typed relative to the current folder: named by the real parent still
    text = run_compare.compare(["h200_run9", tmp_path / "b" / "h200_run9"], [0, 20e6], ["lr"])
    assert text.splitlines()[2] == "| env steps | a/h200_run9 | b/h200_run9 |"
