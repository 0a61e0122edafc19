"""The buffer benchmark's command line (python -m lab.sim_measure.measure_buffers): bad arguments are refused
before anything is measured, and a failure writes nothing. ``measure`` itself needs mujoco-warp and minutes; these
tests replace it with a stub that records its calls."""

from __future__ import annotations

import json
from dataclasses import asdict

import pytest

from lab.sim_measure import measure_buffers
from lab.sim_measure.measure_buffers import SCENARIOS, BufferUsage, main


def _usage(scenario: str, num_worlds: int = 2, steps: int = 1) -> BufferUsage:
    return BufferUsage(scenario, num_worlds, 8 * steps, 12, 11.0, 6.5, 40.0, 90, 88.0, 3, 1.5)


@pytest.fixture
def measured(monkeypatch):
    """Replace ``measure`` by a stub; the list holds the scenarios it was asked for, in order."""
    calls = []

    def fake(scenario, num_worlds=16, steps=300, seed=0, device="cpu"):
        calls.append(scenario)
        return _usage(scenario, num_worlds, steps)

    monkeypatch.setattr(measure_buffers, "measure", fake)
    return calls


def _exit_code(argv, capsys) -> tuple[int, str]:
    with pytest.raises(SystemExit) as stop:
        main(argv)
    return stop.value.code, capsys.readouterr().err


@pytest.mark.parametrize(
    "argv,message",
    [
        (["--scenarios", "standing", "limpx"], "invalid choice: 'limpx'"),
        (["--scenarios"], "--scenarios: expected at least one argument"),
        (["--steps", "0"], "--steps: must be at least 1, got 0"),
        (["--num-worlds", "-2"], "--num-worlds: must be at least 1, got -2"),
        (["--steps", "many"], "--steps: expected an integer >= 1"),
    ],
)
def test_bad_arguments_are_refused_before_measuring(tmp_path, capsys, measured, argv, message):
    out = tmp_path / "bench"
    code, err = _exit_code(["--out", str(out), *argv], capsys)
    assert code == 2 and message in err, err
    assert measured == []  # nothing ran ...
    assert not out.exists()  # ... and nothing was written


def test_out_must_be_a_folder(tmp_path, capsys, measured):
    out = tmp_path / "file.txt"
    out.write_text("keep me")
    code, err = _exit_code(["--out", str(out), "--scenarios", "standing"], capsys)
    assert code == 2 and "is not a folder" in err
    assert measured == [] and out.read_text() == "keep me"


def test_measures_the_named_scenarios_and_writes_both_files(tmp_path, measured):
    out = tmp_path / "new" / "bench"
    main(["--out", str(out), "--scenarios", "limp", "standing", "--steps", "3", "--num-worlds", "2"])
    assert measured == ["limp", "standing"]
    rows = json.loads((out / "sim_buffers.json").read_text())
    assert [r["scenario"] for r in rows] == ["limp", "standing"]
    assert "| limp |" in (out / "sim_buffers.md").read_text()


def test_a_failed_render_overwrites_nothing(tmp_path, monkeypatch, measured):
    """The markdown is made before either file is written: a failure there keeps the previous pair."""
    out = tmp_path / "bench"
    out.mkdir()
    (out / "sim_buffers.json").write_text("previous json")
    (out / "sim_buffers.md").write_text("previous md")

    def broken(rows):
        raise RuntimeError("render failed")

    monkeypatch.setattr(measure_buffers, "_markdown", broken)
    with pytest.raises(RuntimeError, match="render failed"):
        main(["--out", str(out), "--scenarios", "standing"])
    assert (out / "sim_buffers.json").read_text() == "previous json"
    assert (out / "sim_buffers.md").read_text() == "previous md"


def test_from_json_creates_the_out_folder(tmp_path):
    source = tmp_path / "sim_buffers.json"
    source.write_text(json.dumps([asdict(_usage(name)) for name in SCENARIOS]))
    out = tmp_path / "missing" / "folder"
    main(["--from-json", str(source), "--out", str(out)])
    text = (out / "sim_buffers.md").read_text()
    assert all(f"| {name} |" in text for name in SCENARIOS)
    assert not (out / "sim_buffers.json").exists()


@pytest.mark.parametrize(
    "content,message",
    [
        ("[]", "holds no measured scenarios"),
        ("{not json", "cannot read"),
        ('[{"scenario": "standing"}]', "is not a sim_buffers.json of this version"),
        (json.dumps([asdict(_usage("limpx"))]), "unknown scenarios ['limpx']"),
        (None, "cannot read"),  # no such file
    ],
)
def test_from_json_refuses_a_file_without_rows(tmp_path, capsys, content, message):
    source = tmp_path / "sim_buffers.json"
    if content is not None:
        source.write_text(content)
    out = tmp_path / "bench"
    code, err = _exit_code(["--from-json", str(source), "--out", str(out)], capsys)
    assert code == 2 and "--from-json" in err and message in err, err
    assert not out.exists()


def test_measure_refuses_what_measures_nothing():
    with pytest.raises(ValueError, match="unknown scenario 'limpx'"):
        measure_buffers.measure("limpx")
    with pytest.raises(ValueError, match="steps must be at least 1"):
        measure_buffers.measure("standing", steps=0)
