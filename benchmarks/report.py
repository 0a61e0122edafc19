"""Shared output of the benchmark scripts: run metadata, then JSON and a markdown table under docs/benchmarks/."""

from __future__ import annotations

import json
import platform
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import torch


def rss_bytes() -> int:
    """Current resident set of this process (VmRSS), 0 where /proc is missing."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def run_meta(script: str, argv: Sequence[str] | None) -> dict:
    """Hardware, versions, date and the exact command line of this run."""
    args = list(argv) if argv is not None else sys.argv[1:]
    device = torch.cuda.get_device_name() if torch.cuda.is_available() else platform.processor() or "cpu"
    return {"gpu": device, "torch": torch.__version__, "python": platform.python_version(),
            "command": " ".join([f"python benchmarks/{script}", *args]), "date": time.strftime("%Y-%m-%d")}


def write_report(out_dir: str | Path, name: str, title: str, meta: dict, results: list[dict],
                 header: Sequence[str], row: Callable[[dict], Sequence[str]]) -> str:
    """Write ``<name>.json`` (meta + results) and ``<name>.md`` (a table, one ``row(result)`` per result)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(json.dumps({"meta": meta, "results": results}, indent=2))
    lines = [f"# {title} ({meta['gpu']})", "", f"Command: `{meta['command']}`", "",
             "| " + " | ".join(header) + " |", "|" + "---:|" * len(header)]
    lines += ["| " + " | ".join(row(r)) + " |" for r in results]
    text = "\n".join(lines) + "\n"
    (out / f"{name}.md").write_text(text)
    return text
