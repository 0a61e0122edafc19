"""lab/analysis/'s scripts: each loads, answers --help without running, and never writes over an existing report."""

from __future__ import annotations

import json
import os

import pytest


def test_drift_spread_loads_and_refuses_an_existing_out(tmp_path):
    # It imported its atomic writer from a module that no longer exists: the script did not start at all.
    from lab.analysis import drift_spread

    out = tmp_path / "drift_spread.json"
    out.write_text("{}\n")
    with pytest.raises(SystemExit, match="exists"):
        drift_spread.main(["no_such.pt", "--out", str(out)])
    assert out.read_text() == "{}\n"


@pytest.mark.parametrize("name, cases", [("mb_zero_action", 14), ("mb_residual_gain", 6)])
def test_model_based_scripts_parse_before_running_and_never_overwrite(name, cases, tmp_path, monkeypatch):
    # They ran every case (up to 40 minutes) before reading sys.argv[1]: --help ran them all and wrote a file named
    # "--help", no path ended in IndexError, and the documented command replaced the committed JSON (in place: a kill
    # mid-write left it cut short). mb_residual_gain.py imported a module that no longer exists.
    import importlib

    script = importlib.import_module(f"lab.analysis.{name}")
    ran = []
    monkeypatch.setattr(script, "run", lambda noise, steps, n, **kw: ran.append(kw) or {"mean_steps_alive": 1.0})
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as help_exit:
        script.main(["--help"])
    assert help_exit.value.code == 0
    with pytest.raises(SystemExit) as missing:
        script.main([])
    assert missing.value.code == 2
    committed = tmp_path / "committed.json"
    committed.write_text("{}\n")
    with pytest.raises(SystemExit) as refused:
        script.main([str(committed)])
    assert refused.value.code == 2 and committed.read_text() == "{}\n"
    assert ran == [] and sorted(p.name for p in tmp_path.iterdir()) == ["committed.json"]

    script.main([str(tmp_path / "new.json")])
    report = json.loads((tmp_path / "new.json").read_text())
    assert len(ran) == cases and len(report["results"]) == cases and "commit" in report


def test_model_based_scripts_never_replace_a_report_that_appears_while_they_run(tmp_path, monkeypatch, capsys):
    # out_path checked the path at the start; the write, minutes later, replaced a file that had appeared since, then
    # refused with FileExistsError (40 minutes of results lost). They go beside it now, and one line says where.
    from lab.analysis import mb_zero_action

    out = tmp_path / "new.json"

    def run(noise, steps, n, **kw):
        out.exists() or out.write_text("{}\n")  # another run's report, written meanwhile
        return {"mean_steps_alive": 1.0}

    monkeypatch.setattr(mb_zero_action, "run", run)
    mb_zero_action.main([str(out)])
    beside = tmp_path / f"new.{os.getpid()}.json"
    assert out.read_text() == "{}\n" and sorted(p.name for p in tmp_path.iterdir()) == [beside.name, "new.json"]
    assert len(json.loads(beside.read_text())["results"]) == 14
    warning = capsys.readouterr().err
    assert f"{out} appeared" in warning and str(beside) in warning
