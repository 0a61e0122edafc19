"""``python -m lab.benchmarks.regenerate``: re-render every committed report (markdown, plots) from its committed JSON."""

from __future__ import annotations

import json
from pathlib import Path

from . import (common, env_throughput, mjlab_peer, robust_policies, scaling, soak, time_to_walk, train_throughput,
               viewer_overhead, viewer_play)

#: page under docs/benchmarks -> (its JSON file or results folder there, render(data or folder, out) -> markdown)
REPORTS = {"env_throughput.md": ("env_throughput.json", env_throughput.render), "soak.md": ("soak.json", soak.render),
           "train_throughput.md": ("train_throughput.json", train_throughput.render),
           "train_throughput_16k_memfix.md": ("train_throughput_16k_memfix.json", train_throughput.render),
           "multi_gpu.md": ("multi_gpu.json", train_throughput.render),
           "scaling.md": ("scaling", scaling.render), "time_to_walk.md": ("time_to_walk.json", time_to_walk.render),
           "mjlab_peer.md": ("mjlab_peer.json", mjlab_peer.render),
           "robust/robust_policies.md": ("robust/robust_policies.json", robust_policies.render),
           "viewer_overhead/viewer_overhead.md": ("viewer_overhead/viewer_overhead.json", viewer_overhead.render),
           "viewer_overhead/viewer_play.md": ("viewer_overhead/viewer_play.json", viewer_play.render)}


def regenerate(page: str, docs: Path = common.DOCS, out: Path = common.DOCS) -> str:
    """Render ``page`` from its source under ``docs`` into ``out`` (plots too); returns the markdown."""
    path, render = docs / REPORTS[page][0], REPORTS[page][1]
    where = out / Path(page).parent  # a page in a subfolder keeps its plots beside it
    where.mkdir(parents=True, exist_ok=True)
    text = render(json.loads(path.read_text()) if path.suffix == ".json" else path, where)
    common.atomic_write_text(out / page, text)
    return text


def main(argv: list[str] | None = None) -> None:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("``: ", 1)[-1])
    parser.add_argument("pages", nargs="*", metavar="PAGE",
                        help="pages under docs/benchmarks to render (default: all of them): " + ", ".join(REPORTS))
    pages = parser.parse_args(argv).pages
    unknown = [p for p in pages if p not in REPORTS]
    if unknown:
        parser.error(f"no such report page: {', '.join(unknown)} (the pages: {', '.join(REPORTS)})")
    for name in pages or REPORTS:
        regenerate(name)
        print(f"rendered {common.DOCS / name}")


if __name__ == "__main__":
    main()
