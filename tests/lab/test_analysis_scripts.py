"""lab/analysis/'s scripts: each loads, answers --help without running, and never writes over an existing report."""

from __future__ import annotations

import json

import pytest


def test_drift_spread_loads_and_refuses_an_existing_out(tmp_path):
    # It imported its atomic writer from a module that no longer exists: the script did not start at all.
    from lab.analysis import drift_spread

    out = tmp_path / "drift_spread.json"
    out.write_text("{}\n")
    with pytest.raises(SystemExit, match="exists"):
        drift_spread.main(["no_such.pt", "--out", str(out)])
    assert out.read_text() == "{}\n"
