"""What the analysis scripts share: checking their input and output paths, and writing their JSON report with the
command that made it (atomically, never over an existing file)."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from tocabi_torchrl.atomic import atomic_write_text


def check_paths(parser: argparse.ArgumentParser, checkpoints: Sequence[Path], out: Path | None) -> None:
    """Exit through ``parser`` naming every checkpoint that is not a file, or an ``out`` that exists already."""
    missing = [str(c) for c in checkpoints if not Path(c).is_file()]
    if missing:
        parser.error(f"no such checkpoint: {', '.join(missing)}")
    if out is not None and out.exists():
        parser.error(f"{out} exists; pass another --out or remove it first")


def write_report(out: Path, script: str, argv: Sequence[str] | None, results: list, meta: dict | None = None) -> None:
    """Write ``{"command", "results"}`` (and ``"meta"`` when given: date, hardware, versions) to ``out`` atomically;
    the command is ``script`` (its path from the project root) run with ``argv`` (the process's own arguments when
    None)."""
    command = f"PYTHONPATH=. python {script} " + " ".join(sys.argv[1:] if argv is None else argv)
    report = {"command": command, **({"meta": meta} if meta else {}), "results": results}
    atomic_write_text(out, json.dumps(report, indent=2) + "\n")
    print(f"wrote {out}")
