"""Training runs side by side at equal env steps: each metric's median over the logged iterations in spans of env
steps, one markdown table per metric (a span as a row, a run as a column).

How a new run is screened against one that passed, before it gets more training time: run 22's tables of falls per
env step, learning rate, KL and reward per step against runs 9 and 21 (docs/training/robust/h200_run22/README.md)::

    PYTHONPATH=. python lab/analysis/run_compare.py docs/training/robust/h200_run9 docs/training/robust/h100_run21 \\
        docs/training/robust/h200_run22 --spans 0 10 20 40 60 80 --metrics terminated_frac lr kl reward

A run is a run folder (``runs/time_to_walk/<name>``), its ``metrics/`` folder or a committed copy of either; the
metrics are read as ``python -m tocabi_torchrl.rl.curves`` reads them. A span in which a run logged no iteration, or a
metric a run did not log, is a ``-``. ``--out`` also writes the tables to a markdown file (never overwritten).

>>> from pathlib import Path
>>> nine = Path(__file__).resolve().parents[2] / "docs" / "training" / "robust" / "h200_run9"
>>> print(compare([nine], [20e6, 40e6], ["lr"]))
### lr
<BLANKLINE>
| env steps | h200_run9 |
|---|---:|
| 20-40 M | 4.44e-04 |
"""

from __future__ import annotations

import argparse
import math
import statistics
from collections.abc import Sequence
from pathlib import Path

from tocabi_torchrl.rl.curves import metric_columns


def span_medians(columns: dict[str, list[float]], spans: Sequence[float], metric: str) -> list[float | None]:
    """The median of ``metric`` over the iterations whose ``env_steps`` lie in each span ``[spans[k], spans[k+1])``;
    None for a span without a finite value (or a metric the run did not log)."""
    steps, values = columns.get("env_steps"), columns.get(metric)
    if steps is None or values is None:
        return [None] * (len(spans) - 1)
    out = []
    for lo, hi in zip(spans[:-1], spans[1:]):
        inside = [v for s, v in zip(steps, values) if lo <= s < hi and math.isfinite(v)]
        out.append(statistics.median(inside) if inside else None)
    return out


def _cell(value: float | None) -> str:
    if value is None:
        return "-"
    return f"{value:.2e}" if value != 0 and (abs(value) < 0.1 or abs(value) >= 1e5) else f"{value:.4g}"


def _span(lo: float, hi: float) -> str:
    return f"{lo / 1e6:g}-{hi / 1e6:g} M"


def compare(runs: Sequence[str | Path], spans: Sequence[float], metrics: Sequence[str]) -> str:
    """The markdown tables: for each of ``metrics``, a row per span of env steps (``spans``: increasing bounds) and
    a column per run (named by its folder), each cell the span's median (:func:`span_medians`)."""
    if len(spans) < 2 or any(not b > a for a, b in zip(spans[:-1], spans[1:])):
        raise ValueError(f"spans must be two or more increasing env-step bounds, got {list(spans)}")
    if not runs or not metrics:
        raise ValueError("give at least one run and one metric")
    # A run is its folder, given as such or as its metrics/ folder, wherever the path was typed from.
    folders = [Path(r).resolve().parent if Path(r).resolve().name == "metrics" else Path(r).resolve() for r in runs]
    twice = sorted({str(r) for r, f in zip(runs, folders) if folders.count(f) > 1})
    if twice:
        raise ValueError(f"{', '.join(twice)} name the same run; give each run once")
    columns = {Path(r): metric_columns(r) for r in runs}
    logged = set().union(*(c.keys() for c in columns.values()))
    unknown = [m for m in metrics if m not in logged]
    if unknown:
        raise ValueError(f"no run logged {unknown}; the runs log: {', '.join(sorted(logged))}")
    names = [f.name for f in folders]
    # Two runs of one name (h200/robust_v1, h100/robust_v1) get their parent folder in the header too.
    names = [f"{f.parent.name}/{n}" if names.count(n) > 1 else n for f, n in zip(folders, names)]
    tables = []
    for metric in metrics:
        cells = [span_medians(c, spans, metric) for c in columns.values()]
        rows = [f"| {_span(lo, hi)} | " + " | ".join(_cell(col[k]) for col in cells) + " |"
                for k, (lo, hi) in enumerate(zip(spans[:-1], spans[1:]))]
        tables.append("\n".join([f"### {metric}", "", "| env steps | " + " | ".join(names) + " |",
                                 "|---|" + "---:|" * len(names), *rows]))
    return "\n\n".join(tables)


def main(argv: Sequence[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="run folders (or their metrics/ folders), one column each")
    parser.add_argument("--spans", type=float, nargs="+", default=[0, 10, 20, 40, 60, 80],
                        help="increasing span bounds in millions of env steps (default: 0 10 20 40 60 80)")
    parser.add_argument("--metrics", nargs="+", default=["terminated_frac", "reward", "lr", "kl"],
                        help="logged metrics to compare, one table each (default: terminated_frac reward lr kl)")
    parser.add_argument("--out", type=Path, default=None, help="also write the tables to this markdown file "
                        "(must not exist yet)")
    args = parser.parse_args(argv)
    if args.out is not None and args.out.exists():
        parser.error(f"--out {args.out} exists already; give a new file")
    try:
        text = compare(args.runs, [1e6 * s for s in args.spans], args.metrics)
    except (ValueError, FileNotFoundError) as err:
        parser.error(str(err))
    print(text)
    if args.out is not None:
        from tocabi_torchrl.atomic import atomic_write_text

        atomic_write_text(args.out, text + "\n")
    return text


if __name__ == "__main__":
    main()
