"""docs/benchmarks.md is generated from the committed reports: the page equals its regeneration, and every result
on it carries the command, date and hardware of its measurement."""

from __future__ import annotations

import importlib
import re



def _page_module():
    return importlib.import_module("lab.benchmarks.page")


def test_the_committed_page_equals_its_regeneration():
    page = _page_module()
    assert page.PAGE.read_text() == page.render(), "docs/benchmarks.md is stale: run python -m lab.benchmarks.page"


def test_every_section_states_command_date_and_hardware():
    page = _page_module()
    for section in page.SECTIONS:
        text = "\n".join(section(page.DOCS))
        assert re.search(r"command", text), f"{section.__name__}: no command"
        assert re.search(r"\b20\d\d-\d\d-\d\d\b", text), f"{section.__name__}: no date"
        assert re.search(r"H100|H200|CPU cores|GPU", text), f"{section.__name__}: no hardware"


def test_check_mode_reports_a_stale_page(tmp_path, monkeypatch, capsys):
    page = _page_module()
    monkeypatch.setattr(page, "PAGE", tmp_path / "benchmarks.md")
    (tmp_path / "benchmarks.md").write_text("# Benchmarks\n\nedited by hand\n")
    assert page.main(["--check"]) == 1 and "stale" in capsys.readouterr().out
    assert page.main([]) == 0 and page.main(["--check"]) == 0
