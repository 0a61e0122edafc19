"""The run folder ``<run_dir>/<name>/``: never silently overwritten, continued only by ``--resume``.

A new run refuses a folder that already holds a run (``config.json``, ``metrics.csv`` or ``checkpoints/``) and says
how to go on: ``--resume`` it, or pick another ``--name``. A resumed run writes into its own folder (or a new one) and
cuts ``metrics.csv`` back to the checkpoint's iteration, so rows logged after the last checkpoint by a run that was
killed are not followed by a second set with the same iteration numbers.
"""

from __future__ import annotations

import csv
import io
import os
from dataclasses import dataclass
from pathlib import Path

from ..config import RunConfig
from .atomic import atomic_write_text, remove_stale_temp_files
from .checkpoint import checkpoint_file, config_from_checkpoint, read_checkpoint, run_folder_of
from .resume import check_resume_config

__all__ = ["RunDirError", "RunFolder", "open_run", "holds_run", "trim_metrics"]

_RUN_FILES = ("config.json", "metrics.csv", "checkpoints")


class RunDirError(RuntimeError):
    """The run folder holds an earlier run that this one would overwrite."""


@dataclass
class RunFolder:
    """Where a run writes, and (resuming) the checkpoint state it continues from."""

    path: Path
    resume_state: dict | None = None
    resume_file: Path | None = None

    @property
    def start_iteration(self) -> int:
        return self.resume_state["iteration"] if self.resume_state else 0

    @property
    def start_env_steps(self) -> int:
        return self.resume_state["env_steps"] if self.resume_state else 0


def holds_run(folder: str | os.PathLike) -> bool:
    """Whether ``folder`` holds the files of a run."""
    return any((Path(folder) / name).exists() for name in _RUN_FILES)


def open_run(cfg: RunConfig, writer: bool = True) -> RunFolder:
    """Check that ``cfg`` may write to its run folder and, for ``cfg.resume``, read and check the checkpoint.

    Raises :class:`RunDirError` if a new run would overwrite an earlier one, and
    :class:`~tocabi_torchrl.rl.checkpoint.CheckpointError` /
    :class:`~tocabi_torchrl.rl.resume.ResumeConfigError` for a bad checkpoint or a changed setting.
    ``writer=False`` (the ranks of a data-parallel run other than rank 0, which write nothing): only read and check
    the resumed checkpoint; the folder is rank 0's to check and tidy.
    """
    path = Path(cfg.run_dir) / cfg.name
    if not writer:
        if not cfg.resume:
            return RunFolder(path)
        file = checkpoint_file(cfg.resume)
        state = read_checkpoint(file)
        check_resume_config(config_from_checkpoint(state, file), cfg, file)
        return RunFolder(path, state, file)
    if not cfg.resume:
        if holds_run(path):
            raise RunDirError(
                f"run folder {path} already holds a run; it is not overwritten. Continue it with --resume {path}, "
                f"or start a new run with another --name (or delete the folder)")
        return RunFolder(path)
    file = checkpoint_file(cfg.resume)
    state = read_checkpoint(file)
    check_resume_config(config_from_checkpoint(state, file), cfg, file)
    source = run_folder_of(file)
    if holds_run(path) and source.resolve() != path.resolve():
        raise RunDirError(
            f"run folder {path} holds another run than the one resumed ({file}); resume into that run's own folder "
            f"(--name {source.name} --run_dir {source.parent}) or into a new one (--name NEW)")
    remove_stale_temp_files(path / "checkpoints")
    trim_metrics(path / "metrics.csv", state["iteration"])
    return RunFolder(path, state, file)


def trim_metrics(csv_path: str | os.PathLike, last_iteration: int) -> int:
    """Drop the rows of ``metrics.csv`` logged after ``last_iteration`` (atomically); returns how many were dropped."""
    csv_path = Path(csv_path)
    if not csv_path.is_file():
        return 0
    with open(csv_path, newline="") as f:
        rows = list(csv.reader(f))
    if len(rows) < 2 or "iteration" not in rows[0]:
        return 0
    col = rows[0].index("iteration")
    # A row cut short by a kill has fewer fields than the header: it goes too.
    keep = [rows[0]] + [r for r in rows[1:] if len(r) == len(rows[0]) and _int(r[col]) <= last_iteration]
    dropped = len(rows) - len(keep)
    if dropped:
        out = io.StringIO()
        csv.writer(out).writerows(keep)
        atomic_write_text(csv_path, out.getvalue())
    return dropped


def _int(text: str) -> int:
    try:
        return int(float(text))
    except ValueError:
        return 0
