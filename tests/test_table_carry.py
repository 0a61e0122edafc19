"""benchmarks/table_carry.py: what an unfinished per-library table row needs to resume on a fresh GPU machine."""

import json
import os
from pathlib import Path

import pytest

from benchmarks import table_carry


def _row(root: Path, name: str, calls: int) -> Path:
    run = root / "runs" / "library_table" / name
    (run / "resume").mkdir(parents=True)
    (run / "checkpoints").mkdir()
    for k in range(1, calls + 1):
        (run / "resume" / f"state_call{k}.pt").write_bytes(bytes(k))
    (run / "checkpoints" / "wall_00120s.pt").write_bytes(b"snapshot")
    (run / "resume.json").write_text(json.dumps({"calls": calls, "state": f"resume/state_call{calls}.pt"}))
    (run / "result.json").write_text("{}")
    return run.relative_to(root)


def test_carries_the_table_and_each_rows_latest_resume_state_only(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    table = Path("runs/library_table/h100.json")
    rsl = _row(tmp_path, "rsl_rl_torque_4096_x", calls=2)
    torchrl = Path("runs/library_table/torchrl_torque_4096_y")
    (torchrl / "checkpoints").mkdir(parents=True)
    (torchrl / "checkpoints" / "latest.pt").write_bytes(b"latest")
    (torchrl / "checkpoints" / "wall_00120s.pt").write_bytes(b"snapshot")
    table.write_text("[]")
    table_carry.main([str(table), str(rsl), str(torchrl), "--out", "carry"])
    carried = sorted(str(p.relative_to("carry")) for p in Path("carry").rglob("*") if p.is_file())
    assert carried == sorted([str(table), str(rsl / "resume.json"), str(rsl / "resume/state_call2.pt"),
                              str(rsl / "result.json"), str(torchrl / "checkpoints/latest.pt")])
    assert (Path("carry") / rsl / "resume/state_call2.pt").read_bytes() == bytes(2)


def test_refuses_what_it_cannot_carry_before_copying_anything(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rsl = _row(tmp_path, "rsl_rl_torque_4096_x", calls=1)
    empty = Path("runs/library_table/sb3_torque_256_z")
    empty.mkdir()
    cases = {
        (str(empty),): "nothing to resume from",
        ("runs/library_table/missing",): "no such file or run folder",
        (str(tmp_path / rsl),): "relative to the repository root",
    }
    for out in (".", "runs", str(rsl)):  # would delete what it carries
        with pytest.raises(SystemExit, match="holds what it would carry"):
            table_carry.main([str(rsl), "--out", out, "--replace"])
        assert (rsl / "resume.json").is_file()
    for args, message in cases.items():
        with pytest.raises(SystemExit, match=message):
            table_carry.main([str(rsl), *args, "--out", "carry"])
        assert not Path("carry").exists()
    with pytest.raises(SystemExit, match="over --max_mib"):
        table_carry.main([str(rsl), "--out", "carry", "--max_mib", "1e-9"])
    (rsl / "resume.json").write_text("{")
    with pytest.raises(SystemExit, match="not a resume point its recipe wrote"):
        table_carry.main([str(rsl), "--out", "carry"])
    (rsl / "resume.json").write_text(json.dumps({"calls": 1, "state": "resume/state_call1.pt"}))
    os.remove(rsl / "resume/state_call1.pt")
    with pytest.raises(SystemExit, match="which is not there"):
        table_carry.main([str(rsl), "--out", "carry"])


def test_an_existing_folder_is_replaced_only_when_asked(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rsl = _row(tmp_path, "rsl_rl_torque_4096_x", calls=1)
    Path("carry").mkdir()
    (Path("carry") / "old.txt").write_text("kept")
    with pytest.raises(SystemExit, match="--replace"):
        table_carry.main([str(rsl), "--out", "carry"])
    assert (Path("carry") / "old.txt").read_text() == "kept"
    table_carry.main([str(rsl), "--out", "carry", "--replace"])
    assert not (Path("carry") / "old.txt").exists() and (Path("carry") / rsl / "resume.json").is_file()


def test_a_size_cap_that_is_not_a_positive_number_is_refused(tmp_path, monkeypatch, capsys):
    # NaN once switched the cap off (a comparison with NaN is false) and carried everything.
    monkeypatch.chdir(tmp_path)
    rsl = _row(tmp_path, "rsl_rl_torque_4096_x", calls=1)
    for cap in ("nan", "0", "-1"):
        with pytest.raises(SystemExit) as exit_:
            table_carry.main([str(rsl), "--out", "carry", "--max_mib", cap])
        assert exit_.value.code == 2 and "--max_mib must be a positive number" in capsys.readouterr().err
        assert not Path("carry").exists()
