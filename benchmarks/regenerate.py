"""Re-render every committed benchmark report (markdown and plots) from its committed JSON.

    python -m benchmarks.regenerate [--out DIR]     # default: in place, under docs/benchmarks

``tests/test_benchmarks.py`` renders each into a temporary folder and compares the markdown with the committed one.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from . import common, env_throughput, scaling, sim_throughput, soak, time_to_walk
from . import train_throughput as train

#: report page -> (its JSON, or results folder, under docs/benchmarks; render(data or folder, out) -> markdown)
REPORTS = {
    "sim_throughput.md": ("sim_throughput.json", sim_throughput.render),
    "env_throughput.md": ("env_throughput.json", env_throughput.render),
    "train_throughput.md": ("train_throughput.json", train.render),
    "env_graph.md": ("env_graph", train.render_env_graph),
    "scaling.md": ("scaling", scaling.render),
    "soak.md": ("soak.json", soak.render),
    "time_to_walk.md": ("time_to_walk.json", time_to_walk.render),
}


def regenerate(page: str, docs: Path, out: Path) -> str:
    """Render ``page`` from its source under ``docs`` into ``out`` (plots too); returns the markdown."""
    source, render = REPORTS[page]
    path = docs / source
    text = render(json.loads(path.read_text()) if path.suffix == ".json" else path, out)
    common.atomic_write_text(out / page, text)
    return text


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=str(common.DOCS))
    args = parser.parse_args(argv)
    for page in REPORTS:
        regenerate(page, common.DOCS, Path(args.out))
        print(f"rendered {Path(args.out) / page}")


if __name__ == "__main__":
    main()
