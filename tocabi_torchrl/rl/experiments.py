"""What the experiment recipes (``recipes/compare_gaits.py``, ``recipes/obstacle_test.py``) share besides the rollout
(:mod:`.gait_record`), the figures (:mod:`.eval_plots`) and the frames (:mod:`.eval_video`): the controllers named
on the command line, the output folder's no-overwrite rule, and the table written as markdown and JSON."""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

from .. import robot

__all__ = ["Controller", "ExperimentOutputError", "SHIPPED_POLICIES", "display_path", "parse_controllers",
           "prepare_out_dir", "slug", "write_table"]

#: The two policies shipped with the package, the experiments' default controllers: label -> file name.
SHIPPED_POLICIES = {"PD (pd_reference)": "tocabi_walk_ppo.pt", "torque": "tocabi_walk_torque.pt"}


class ExperimentOutputError(RuntimeError):
    """The output folder holds earlier results that this run would overwrite."""


@dataclass(frozen=True)
class Controller:
    """A controller to compare: its label in tables and figures and its checkpoint (a .pt file or run folder)."""

    label: str
    path: Path


def parse_controllers(values: list[str] | None) -> list[Controller]:
    """``LABEL=PATH`` or ``PATH`` (labelled by its file or folder name) per controller; none: the shipped policies.
    Raises ``ValueError`` for a repeated label."""
    if not values:
        return [Controller(label, robot.asset_path("policies", name)) for label, name in SHIPPED_POLICIES.items()]
    out = []
    for value in values:
        label, sep, path = value.partition("=")
        if not sep:
            path = value
            p = Path(value)
            label = p.parent.parent.name if p.parent.name == "checkpoints" else (p.stem if p.suffix else p.name)
        out.append(Controller(label.strip(), Path(path)))
    labels = [c.label for c in out]
    if len(set(labels)) != len(labels) or len({slug(label) for label in labels}) != len(labels):
        raise ValueError(f"controller labels must differ (also as file names: {[slug(x) for x in labels]}), got "
                         f"{labels}; name them with LABEL=PATH")
    return out


def display_path(path: str | os.PathLike) -> str:
    """``path`` relative to the working directory when it lies below it (tables stay readable on another
    machine), else as given."""
    path = Path(path)
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def slug(label: str) -> str:
    """A file-name-safe form of a label."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", label).strip("_") or "controller"


def prepare_out_dir(path: str | os.PathLike, overwrite: bool = False) -> Path:
    """Create ``path``; an existing folder that is not empty is refused (:class:`ExperimentOutputError`) unless
    ``overwrite``, so results are never replaced silently. With ``overwrite`` the run writes into the folder: its own
    files replace those of the same name, and any other file there is left alone (nothing is deleted)."""
    path = Path(path)
    if path.exists() and (not path.is_dir() or any(path.iterdir())) and not overwrite:
        raise ExperimentOutputError(f"{path} already holds results; they are not overwritten. Choose another --out, "
                                    "or pass --overwrite to replace them")
    path.mkdir(parents=True, exist_ok=True)
    return path


def _cell(value) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.3g}" if abs(value) < 1000 else f"{value:.0f}"
    return str(value)


def _clean(value):
    """JSON-safe: NaN -> None, recursively."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    return value


def write_table(rows: list[dict], columns: dict[str, str], out_dir: Path, stem: str = "table", title: str = "",
                notes: list[str] | None = None, meta: dict | None = None) -> tuple[Path, Path]:
    """Write ``rows`` as ``<stem>.md`` (the ``columns``: key -> header, then ``notes`` as a list) and ``<stem>.json``
    (``{"meta": meta, "columns": columns, "rows": rows}``, every key of every row, NaN as null). Returns both
    paths."""
    out_dir = Path(out_dir)
    lines = [f"# {title}", ""] if title else []
    lines += ["| " + " | ".join(columns.values()) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(_cell(row.get(key)) for key in columns) + " |" for row in rows]
    if notes:
        lines += [""] + [f"- {note}" for note in notes]
    md = out_dir / f"{stem}.md"
    md.write_text("\n".join(lines) + "\n")
    js = out_dir / f"{stem}.json"
    js.write_text(json.dumps(_clean({"meta": meta or {}, "columns": columns, "rows": rows}), indent=2) + "\n")
    return md, js
