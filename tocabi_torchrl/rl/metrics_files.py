"""A run's metrics files: where they lie, the one reader of them, and the cut back to a checkpoint on resume.

Two layouts are read:

- torchrl's :class:`~torchrl.record.loggers.CSVLogger` (what runs write now): one file per scalar,
  ``<run>/metrics/scalars/<name>.csv``, each line ``iteration,value`` without a header (a name with ``/`` such as
  ``reward_terms/qpos`` is a sub-folder). The logger opens the files for appending, so a resumed run continues them.
- the wide ``metrics.csv`` of older runs (a header, then one row per logged iteration), which the committed runs
  under ``docs/training/`` keep.

:func:`read_metrics` turns either into the same rows (one dict of strings per logged iteration), so that every user
(plots, benchmarks, recipes, tests) reads through it and a change of layout touches this module alone.
"""

from __future__ import annotations

import csv
import io
import os
from collections import Counter
from pathlib import Path

from ..atomic import atomic_write_text

__all__ = ["LEGACY_CSV", "METRICS_DIR", "SCALARS", "metrics_sources", "read_metrics", "trim_metrics"]

#: The torchrl ``CSVLogger``'s experiment folder in a run folder (its ``exp_name``; ``log_dir`` is the run folder).
METRICS_DIR = "metrics"
#: The folder of one file per scalar inside a ``CSVLogger`` experiment folder.
SCALARS = "scalars"
#: The single wide file of runs logged before the torchrl loggers (and of the committed runs in docs/).
LEGACY_CSV = "metrics.csv"


def metrics_sources(path: str | os.PathLike) -> list[Path]:
    """The metrics files/folders ``path`` stands for, oldest first: a wide CSV file is itself; a ``CSVLogger``
    experiment folder (holding ``scalars/``) is itself; a run folder is its ``metrics.csv`` (a run started before the
    torchrl loggers) and then its ``metrics/`` folder, those of the two that exist. [] when there are none."""
    path = Path(path)
    if path.is_file():
        return [path]
    if (path / SCALARS).is_dir():
        return [path]
    return [p for p in (path / LEGACY_CSV, path / METRICS_DIR) if p.exists()]


def read_metrics(path: str | os.PathLike) -> list[dict[str, str]]:
    """The logged rows of a run as dicts of strings (``"iteration"`` and one key per metric), oldest first; [] when
    nothing is logged there.

    ``path``: a run folder, a ``CSVLogger`` experiment folder (``<run>/metrics``), or a wide ``metrics.csv``. A wide
    file's rows come in file order (repeated header lines, which older resumed runs appended, are skipped); the
    per-scalar files' rows in iteration order, with ``""`` for a metric not logged at that iteration. A run folder
    holding both (an older run resumed since) gives the wide file's rows, then the others'.
    """
    rows: list[dict[str, str]] = []
    for source in metrics_sources(path):
        rows += _read_scalars(source) if source.is_dir() else _read_wide(source)
    return rows


def trim_metrics(run_folder: str | os.PathLike, last_iteration: int) -> int:
    """Drop what a run folder logged after ``last_iteration`` (each file rewritten atomically), and lines cut short
    by a kill; returns how many lines were dropped. A resumed run calls it with its checkpoint's iteration, so the
    rows a killed run logged after its last checkpoint are not followed by a second set with the same numbers."""
    dropped = 0
    for source in metrics_sources(run_folder):
        if source.is_dir():
            dropped += sum(_trim_scalar_file(f, last_iteration) for f in sorted((source / SCALARS).rglob("*.csv")))
        else:
            dropped += _trim_wide(source, last_iteration)
    return dropped


# ------------------------------------------------------------------------------------------------ wide metrics.csv
def _read_wide(file: Path) -> list[dict[str, str]]:
    # A line cut short by a kill (a partial copy) is not read, as in the per-scalar files: a last line without its
    # newline (csv.writer ends each row with one) may end in a cut number, and a row of another field count than
    # the header lacks values (DictReader fills missing fields with None, keeps extra ones under the key None).
    with open(file, newline="") as f:
        lines = f.read().splitlines(keepends=True)
    if lines and not lines[-1].endswith("\n"):
        lines.pop()
    return [r for r in csv.DictReader(lines)
            if r.get("iteration") not in (None, "", "iteration") and None not in r and None not in r.values()]


def _trim_wide(file: Path, last_iteration: int) -> int:
    with open(file, newline="") as f:
        rows = list(csv.reader(f))
    if len(rows) < 2 or "iteration" not in rows[0]:
        return 0
    col = rows[0].index("iteration")
    # A row cut short by a kill has fewer fields than the header: it goes too.
    keep = [rows[0]] + [r for r in rows[1:] if len(r) == len(rows[0]) and (_int(r[col]) or 0) <= last_iteration]
    dropped = len(rows) - len(keep)
    if dropped:
        out = io.StringIO()
        csv.writer(out).writerows(keep)
        atomic_write_text(file, out.getvalue())
    return dropped


# ------------------------------------------------------------------------------------ torchrl CSVLogger's scalars
def _scalar_lines(file: Path) -> tuple[list[tuple[int, str, str]], int]:
    """The complete ``step,value`` lines of one scalar file as (iteration, step text, value text), and how many
    lines are not (the last one cut short by a kill, anything unparsable)."""
    good, bad = [], 0
    for line in file.read_text().splitlines(keepends=True):
        fields = line.rstrip("\r\n").split(",")
        step = _int(fields[0]) if len(fields) == 2 and line.endswith("\n") else None
        if step is None:
            bad += 1
        else:
            good.append((step, fields[0], fields[1]))
    return good, bad


def _read_scalars(folder: Path) -> list[dict[str, str]]:
    columns: dict[str, dict[tuple[int, int], str]] = {}
    labels: dict[tuple[int, int], str] = {}
    scalars = folder / SCALARS
    for file in sorted(scalars.rglob("*.csv")):
        values, seen = {}, Counter()
        for step, text, value in _scalar_lines(file)[0]:
            # The n-th line of an iteration in one file joins the n-th of the others (repeats only if not trimmed).
            key = (step, seen[step])
            seen[step] += 1
            values[key] = value
            labels.setdefault(key, text)
        columns[file.relative_to(scalars).with_suffix("").as_posix()] = values
    return [{"iteration": labels[key], **{name: values.get(key, "") for name, values in columns.items()}}
            for key in sorted(labels)]


def _trim_scalar_file(file: Path, last_iteration: int) -> int:
    lines, bad = _scalar_lines(file)
    keep = [f"{text},{value}\n" for step, text, value in lines if step <= last_iteration]
    dropped = bad + len(lines) - len(keep)
    if dropped:
        atomic_write_text(file, "".join(keep))
    return dropped


def _int(text: str) -> int | None:
    try:
        return int(float(text))
    except (ValueError, OverflowError):
        return None
