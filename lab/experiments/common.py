"""What the experiments (``lab/experiments/compare_gaits.py``, ``lab/experiments/obstacle_test.py``) share besides the
rollout (:mod:`.gait_record`), the figures (:mod:`tocabi_torchrl.evaluation.plots`) and the frames
(:mod:`tocabi_torchrl.evaluation.video`): the controllers named
on the command line, the output folder's no-overwrite rule, the table written as markdown and JSON, and resuming a
run from its table."""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import secrets
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from tocabi_torchrl import robot
from tocabi_torchrl.atomic import TEMP_SUFFIX, atomic_write_bytes
from tocabi_torchrl.evaluation.output import OutputExistsError, json_safe

__all__ = ["Controller", "ExperimentOutputError", "SHIPPED_POLICIES", "checkpoint_record", "display_path",
           "earlier_table", "parse_controllers", "prepare_out_dir", "replace_atomically", "slug", "write_atomic",
           "write_table"]

#: The policies shipped with the package, the experiments' default controllers: label -> file name.
SHIPPED_POLICIES = {"PD (pd_reference)": "tocabi_walk_ppo.pt", "torque": "tocabi_walk_torque.pt",
                    "model_based": "tocabi_walk_model_based.pt"}


#: The output folder holds earlier results that this run would overwrite (the gait test's error, under the name the
#: experiments' callers catch).
ExperimentOutputError = OutputExistsError


@dataclass(frozen=True)
class Controller:
    """A controller to compare: its label in tables and figures and its checkpoint (a .pt file or run folder)."""

    label: str
    path: Path


def parse_controllers(values: list[str] | None) -> list[Controller]:
    """``LABEL=PATH`` or ``PATH`` (labelled by its file or folder name) per controller; none: the shipped policies.
    A value that exists as a path, or whose part before the first ``=`` holds a folder separator, is a ``PATH``
    (run names may contain ``=``: ``runs/lr=3e-4``). Raises ``ValueError`` for a repeated label."""
    if not values:
        return [Controller(label, robot.asset_path("policies", name)) for label, name in SHIPPED_POLICIES.items()]
    out = []
    for value in values:
        label, sep, path = value.partition("=")
        if not sep or "/" in label or "\\" in label or Path(value).exists():
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


def prepare_out_dir(path: str | os.PathLike, overwrite: bool = False, resume: bool = False) -> Path:
    """Create ``path``; an existing folder that is not empty is refused (:class:`ExperimentOutputError`) unless
    ``overwrite`` or ``resume``, so results are never replaced silently. With either the run writes into the folder:
    its own files replace those of the same name, and any other file there is left alone (nothing is deleted); with
    ``resume`` the caller keeps the earlier table's rows (:func:`earlier_table`)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ExperimentOutputError(f"{path} is a file, not a folder; choose another --out")
    if path.exists() and any(path.iterdir()) and not (overwrite or resume):
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
    md = write_atomic(out_dir / f"{stem}.md", "\n".join(lines) + "\n")
    js = write_atomic(out_dir / f"{stem}.json",
                      json.dumps(json_safe({"meta": meta or {}, "columns": columns, "rows": rows}), indent=2) + "\n")
    return md, js


def write_atomic(path: str | os.PathLike, data: str | bytes) -> Path:
    """Write ``data`` (text as UTF-8) to ``path`` atomically (:mod:`tocabi_torchrl.atomic`: a temporary file
    of its own beside it, fsynced, renamed over ``path``): a run killed meanwhile leaves the earlier file whole, and two writers of one
    folder never share a temporary file."""
    return atomic_write_bytes(path, data if isinstance(data, bytes) else data.encode("utf-8"))


def replace_atomically(path: str | os.PathLike, write: Callable[[Path], object]) -> Path:
    """For writers that take a path, not bytes (an image library): ``write(tmp)`` to a new temporary file beside
    ``path`` whose name ends in ``path``'s suffix (writers pick the format from it), then fsync it and rename it
    over ``path``. On failure the temporary file is removed and ``path`` is left as it was."""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.{secrets.token_hex(6)}{TEMP_SUFFIX}{path.suffix}")
    try:
        write(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


# ------------------------------------------------------------------------------------------------------ resuming
def checkpoint_record(controller: Controller) -> dict:
    """What identifies a controller's checkpoint across calls: ``path`` as the tables show it, the ``file`` it
    resolves to (a run folder's ``latest.pt``) and that file's ``sha256`` (``None`` while it does not exist)."""
    from tocabi_torchrl.rl.checkpoint import CheckpointError, checkpoint_file

    try:
        file = checkpoint_file(controller.path)
    except CheckpointError:
        return {"path": display_path(controller.path), "file": None, "sha256": None}
    digest = hashlib.sha256()
    with open(file, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return {"path": display_path(controller.path), "file": str(file.resolve()), "sha256": digest.hexdigest()}


def _same_checkpoint(earlier: dict, now: dict) -> bool:
    """Same path (as shown, or resolved: the run may be resumed from another working directory or machine) and,
    where both are known, the same contents."""
    same_path = earlier.get("path") == now["path"] or (now["file"] is not None and earlier.get("file") == now["file"])
    same_bytes = None in (earlier.get("sha256"), now["sha256"]) or earlier.get("sha256") == now["sha256"]
    return same_path and same_bytes


def earlier_table(out_dir: str | os.PathLike, experiment: str, settings: dict, checkpoints: dict[str, dict],
                  stem: str = "table") -> tuple[list[dict], dict]:
    """The rows and meta of ``<out_dir>/<stem>.json`` written by an earlier run of ``experiment`` that this run may
    continue; ``([], {})`` when there is none. Its ``meta`` must hold the ``"experiment"``, the ``"settings"``
    (option -> value: every one that changes what a row measures) and the ``"checkpoints"`` (controller label ->
    :func:`checkpoint_record`) it was made with. Raises :class:`ExperimentOutputError` naming every setting that
    differs and the fix: a table of another experiment, an unreadable one, other settings, a label whose checkpoint
    differs, or a controller with rows there that this run does not name."""
    path = Path(out_dir) / f"{stem}.json"
    if not path.is_file():
        return [], {}
    fix = "choose another --out, or pass --overwrite instead of --resume to replace its rows"
    try:
        table = json.loads(path.read_text())
        meta, rows = table["meta"], table["rows"]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise ExperimentOutputError(f"cannot resume from {path}: not a readable results table ({err}); {fix}") from err
    if meta.get("experiment") != experiment:
        raise ExperimentOutputError(f"cannot resume from {path}: it holds the results of "
                                    f"{meta.get('experiment')!r}, not of {experiment!r}; {fix}")
    if "settings" not in meta or "checkpoints" not in meta:
        raise ExperimentOutputError(f"cannot resume from {path}: it does not record the settings it was made with "
                                    f"(an earlier version of the recipe), so they cannot be checked; {fix}")
    problems = [f"{key} {meta['settings'].get(key, 'unset')} there, {value} here" for key, value in settings.items()
                if meta["settings"].get(key) != value]
    for label, now in checkpoints.items():
        before = meta["checkpoints"].get(label)
        if before is not None and not _same_checkpoint(before, now):
            what = "contents (sha256)" if before.get("path") == now["path"] else "path"
            problems.append(f"controller {label!r}: checkpoint {before.get('path')} there, {now['path']} here "
                            f"(another {what}; give it another label, or the earlier checkpoint)")
    missing = list(dict.fromkeys(row["controller"] for row in rows if row["controller"] not in checkpoints))
    if missing:
        problems.append(f"controllers {missing} measured there are not named here (name them again with "
                        "--policy LABEL=PATH)")
    if problems:
        raise ExperimentOutputError(f"cannot resume from {path}: it was made with other settings: "
                                    f"{'; '.join(problems)}. Rerun with the earlier values to resume it, or {fix}")
    return rows, meta
