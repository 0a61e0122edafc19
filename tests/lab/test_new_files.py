"""lab/new_files.py: a report whose name was taken while its script measured goes beside it, never over it."""

from __future__ import annotations

import json
import os

from lab.benchmarks import common
from lab.new_files import write_new_files


def test_a_page_that_appears_keeps_the_json_and_its_page_a_pair_beside_it(tmp_path, capsys):
    # publish wrote the JSON, then refused the page that had appeared meanwhile (FileExistsError): a JSON without
    # its page at the wanted name and the measurement's page lost. Both names are checked before either is written.
    (tmp_path / "r.md").write_text("another run's page\n")
    common.publish(tmp_path, "r", {"x": 1.0}, lambda data, out: f"x is {data['x']}\n", replace=False)
    tag = os.getpid()
    assert (tmp_path / "r.md").read_text() == "another run's page\n" and not (tmp_path / "r.json").exists()
    assert json.loads((tmp_path / f"r.{tag}.json").read_text()) == {"x": 1.0}
    assert (tmp_path / f"r.{tag}.md").read_text() == "x is 1.0\n"
    err = capsys.readouterr().err
    assert f"{tmp_path / 'r.md'} appeared" in err and f"r.{tag}.json" in err and f"r.{tag}.md" in err


def test_a_taken_name_beside_is_skipped_and_free_names_are_written_as_asked(tmp_path, capsys):
    out = tmp_path / "a.json"
    out.write_text("first\n")
    (tmp_path / f"a.{os.getpid()}.json").write_text("second\n")
    assert write_new_files({out: "mine\n"}) == [tmp_path / f"a.{os.getpid()}-1.json"]
    assert out.read_text() == "first\n" and (tmp_path / f"a.{os.getpid()}.json").read_text() == "second\n"
    assert (tmp_path / f"a.{os.getpid()}-1.json").read_text() == "mine\n"
    capsys.readouterr()
    assert write_new_files({tmp_path / "b.json": "b\n"}) == [tmp_path / "b.json"]
    assert capsys.readouterr().err == ""


def test_a_name_taken_between_the_check_and_the_write_moves_the_results_beside_it(tmp_path, monkeypatch, capsys):
    # The hard link that refuses a taken name raised FileExistsError and the temporary file with the results went.
    import lab.new_files as new_files

    out, real = tmp_path / "c.json", new_files.atomic_write_text

    def racing(path, text, replace=True):
        path == out and out.write_text("raced\n")
        return real(path, text, replace)

    monkeypatch.setattr(new_files, "atomic_write_text", racing)
    assert write_new_files({out: "mine\n"}) == [tmp_path / f"c.{os.getpid()}.json"]
    assert out.read_text() == "raced\n" and (tmp_path / f"c.{os.getpid()}.json").read_text() == "mine\n"
    assert f"{out} appeared" in capsys.readouterr().err
