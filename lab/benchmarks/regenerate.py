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


if __name__ == "__main__":
    for name in REPORTS:
        regenerate(name)
        print(f"rendered {common.DOCS / name}")
