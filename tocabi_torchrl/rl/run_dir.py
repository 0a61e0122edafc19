"""The run folder ``<run_dir>/<name>/``: never silently overwritten, continued only by ``--resume``.

A new run refuses a folder that already holds a run (``config.json``, ``metrics/``, an older run's ``metrics.csv`` or
``checkpoints/``) and says how to go on: ``--resume`` it, or pick another ``--name``. A folder whose run saved no
checkpoint (killed before its first one) cannot be resumed: it is refused with that said, and the choice of another
``--name`` or removing the folder (never removed here). A resumed run writes into its own
folder (or a new one) and cuts its metrics files back to the checkpoint's iteration
(:func:`~tocabi_torchrl.rl.metrics_files.trim_metrics`), so rows logged after the last checkpoint by a run that was
killed are not followed by a second set with the same iteration numbers. Resuming an older iteration file into its own
folder, one that holds newer checkpoints, is refused: that run's later files would be overwritten or pruned
and its later metrics rows cut. Continue it from its newest checkpoint, or branch into a new folder (``--name NEW``).
"""

from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

from ..atomic import check_writable, claim_path, release_claim
from ..atomic import remove_stale_temp_files
from ..config import RunConfig
from .checkpoint import (
    _ITER_FILE,
    CheckpointError,
    checkpoint_file,
    config_from_checkpoint,
    read_checkpoint,
    run_folder_of,
)
from ..integrity import zip_damage
from .metrics_files import LEGACY_CSV, METRICS_DIR, trim_metrics
from .resume import check_resume_config, holds_checkpoint, no_checkpoint_message

__all__ = ["RunDirError", "RunFolder", "check_run_name", "claim_run_folder", "holds_checkpoint", "holds_run",
           "open_run", "refuse_run_without_checkpoint", "release_claim", "trim_metrics"]

_RUN_FILES = ("config.json", METRICS_DIR, LEGACY_CSV, "checkpoints")


class RunDirError(RuntimeError):
    """The run folder holds an earlier run that this one would overwrite."""


@dataclass
class RunFolder:
    """Where a run writes, and (resuming) the checkpoint state it continues from. ``claim``: the file that keeps a
    second run out of ``path`` while this one runs (:func:`claim_run_folder`), which :meth:`release` removes."""

    path: Path
    resume_state: dict | None = None
    resume_file: Path | None = None
    claim: Path | None = None

    def release(self) -> None:
        """Let other runs into the folder again (the run has ended); idempotent."""
        if self.claim is not None:
            release_claim(self.claim)
            self.claim = None

    @property
    def start_iteration(self) -> int:
        return self.resume_state["iteration"] if self.resume_state else 0

    @property
    def start_env_steps(self) -> int:
        return self.resume_state["env_steps"] if self.resume_state else 0


def claim_run_folder(path: Path) -> Path:
    """Claim the run folder ``path`` for this process (:func:`~tocabi_torchrl.atomic.claim_path`), so that a second
    run started with the same name before this one has written its files is refused instead of writing into the
    same folder (:class:`RunDirError` naming the other process). A claim file that cannot be opened (another user's
    in a shared folder, or a folder this user may not write in) is a :class:`RunDirError` too, saying which and the
    fix. Returns the claim file."""
    try:
        claim, owner = claim_path(path)
    except PermissionError as err:
        raise RunDirError(f"{err.strerror}. To write this run elsewhere, pass --run_dir (and --name) naming a folder "
                          "you can write") from None
    if claim is None:
        who = f"process {owner}" if owner is not None else "a process starting now"
        raise RunDirError(f"another run ({who}) is writing into {path} (it holds {path.parent / f'.{path.name}.claim'}"
                          "); wait for it to end, or start this one with another --name")
    return claim


def holds_run(folder: str | os.PathLike) -> bool:
    """Whether ``folder`` holds the files of a run."""
    return any((Path(folder) / name).exists() for name in _RUN_FILES)


def refuse_run_without_checkpoint(resume: str | os.PathLike) -> None:
    """:class:`RunDirError` if ``resume`` names a run folder that holds a run but no checkpoint (what a run killed
    before its first checkpoint leaves): a clearer refusal than the missing ``latest.pt``."""
    folder = Path(resume)
    if folder.is_dir() and holds_run(folder) and not holds_checkpoint(folder):
        raise RunDirError(no_checkpoint_message(folder))


def _newer_checkpoint(folder: Path, iteration: int) -> tuple[int, Path] | None:
    """A checkpoint of the run folder ``folder`` newer than ``iteration``, as ``(its iteration, file)``, or ``None``:
    the highest intact ``iter_*.pt`` (its iteration read from the name; a file that is not a whole zip archive, cut
    short or damaged, is passed over, as the resume hint passes it over), else ``latest.pt`` (newer after a tagged
    save), read through :func:`read_checkpoint` only then and passed over if unreadable (a damaged ``latest.pt`` must
    not stop a resume from an iteration file)."""
    checkpoints = folder / "checkpoints"
    found = [(int(m.group(1)), p) for p in checkpoints.glob("iter_*.pt") if (m := _ITER_FILE.match(p.name))]
    for newest in sorted(found, reverse=True):
        if newest[0] <= iteration:
            break
        if zipfile.is_zipfile(newest[1]) and zip_damage(newest[1]) is None:
            return newest
    latest = checkpoints / "latest.pt"
    if latest.is_file():
        try:
            latest_iteration = int(read_checkpoint(latest)["iteration"])
        except CheckpointError:
            return None
        if latest_iteration > iteration:
            return latest_iteration, latest
    return None


def check_run_name(name: str) -> None:
    """``RunDirError`` unless ``name`` is one folder name, so that ``run_dir/name`` stays inside ``run_dir`` (the
    benchmarks clear that folder before timing). Checked for a new run and for a resume into a folder that holds no
    run (new or not), not on load or a resume into the run's existing folder: a run made before the rule under a name
    like ``sweeps/lr3`` still loads, resumes and exports."""
    if not isinstance(name, str) or name in ("", ".", "..") or "/" in name or "\\" in name:
        raise RunDirError(f"name must be one folder name inside run_dir (no '/', '..' or absolute path), got "
                          f"{name!r}; put the folder's parent in run_dir instead")


def check_run_writable(path: Path) -> None:
    """``RunDirError`` unless a file can be created in ``path`` or, while it does not exist, in its nearest existing
    parent (a probe file, created and removed at once): said before the env is built, not as a traceback from the
    logger's first write."""
    try:
        check_writable(path)
    except OSError as err:
        raise RunDirError(f"cannot write the run into {path}: {err.filename} is not writable ({err.strerror}); "
                          "pass --run_dir (and --name) naming a folder you can write") from None


def open_run(cfg: RunConfig, writer: bool = True) -> RunFolder:
    """Check that ``cfg`` may write to its run folder and, for ``cfg.resume``, read and check the checkpoint.

    Raises :class:`RunDirError` if a new run would overwrite an earlier one, if a folder to create is named outside
    ``run_dir`` (:func:`check_run_name`), or if a resumed iteration file older than its folder's newest checkpoint
    would be continued in that folder (it would overwrite, prune and cut the newer files; ``latest.pt`` itself is
    always resumable), and
    :class:`~tocabi_torchrl.rl.checkpoint.CheckpointError` /
    :class:`~tocabi_torchrl.rl.resume.ResumeConfigError` for a bad checkpoint or a changed setting.
    ``writer=False`` (the ranks of a data-parallel run other than rank 0, which write nothing): only read and check
    the resumed checkpoint; the folder is rank 0's to check and tidy. The writer claims the folder first
    (:func:`claim_run_folder`: a second run of the same name started at the same time is refused, not let in before
    the first has written its files); ``RunFolder.release`` (:func:`~tocabi_torchrl.rl.trainer.train` calls it when
    the run ends) or the end of the process lets it go.
    """
    path = Path(cfg.run_dir) / cfg.name
    # The exception is for a run folder (a resume into another run's is refused below): any existing folder would let
    # ``--name ../elsewhere`` write a run outside run_dir.
    if writer and not (cfg.resume and path.is_dir() and holds_run(path)):
        check_run_name(cfg.name)
    for folder in (Path(cfg.run_dir), path):
        if writer and folder.exists() and not folder.is_dir():
            raise RunDirError(f"{folder} is a file, not a folder: the run cannot be written there; pass --run_dir "
                              f"and --name that name a folder")
    if writer:
        for folder in (path, path / "checkpoints", path / METRICS_DIR):  # a resumed run writes into all three
            if folder == path or folder.is_dir():
                check_run_writable(folder)
        claim = claim_run_folder(path)
        try:
            run = _open_claimed(cfg, path)
        except BaseException:
            release_claim(claim)
            raise
        run.claim = claim
        return run
    if not cfg.resume:
        return RunFolder(path)
    return RunFolder(path, *_resumed_checkpoint(cfg))


def _resumed_checkpoint(cfg: RunConfig) -> tuple[dict, Path]:
    """The state and file of ``cfg.resume``, read and checked against ``cfg``'s settings."""
    refuse_run_without_checkpoint(cfg.resume)
    file = checkpoint_file(cfg.resume)
    state = read_checkpoint(file)
    check_resume_config(config_from_checkpoint(state, file, strict=True), cfg, file)
    return state, file


def _open_claimed(cfg: RunConfig, path: Path) -> RunFolder:
    """:func:`open_run`'s checks of the folder ``path`` that this process has claimed."""
    if not cfg.resume:
        if holds_run(path) and not holds_checkpoint(path):
            raise RunDirError(no_checkpoint_message(path))
        if holds_run(path):
            raise RunDirError(
                f"run folder {path} already holds a run; it is not overwritten. Continue it with --resume {path}, "
                f"or start a new run with another --name (or delete the folder)")
        return RunFolder(path)
    state, file = _resumed_checkpoint(cfg)
    source = run_folder_of(file)
    if holds_run(path) and source.resolve() != path.resolve():
        raise RunDirError(
            f"run folder {path} holds another run than the one resumed ({file}); resume into that run's own folder "
            f"(--name {source.name} --run_dir {source.parent}) or into a new one (--name NEW)")
    if source.resolve() == path.resolve() and file.resolve() != (path / "checkpoints" / "latest.pt").resolve():
        # An older checkpoint resumed into its own folder would overwrite the newer iteration files, have its own
        # pruned at once (the newer ones count as newest), set latest.pt back and cut the newer metrics rows.
        iteration = int(state["iteration"])
        newest = _newer_checkpoint(path, iteration)
        if newest is not None:
            raise RunDirError(
                f"{file} holds iteration {iteration}, but its run folder {path} goes on to iteration {newest[0]} "
                f"({newest[1]}); resuming it there would overwrite or delete that run's later checkpoints and metrics, "
                f"so nothing was changed. Continue the run from its newest checkpoint with --resume {path}, or branch "
                f"from iteration {iteration} into a new folder with --resume {file} --name NEW")
    remove_stale_temp_files(path / "checkpoints")
    trim_metrics(path, state["iteration"])
    return RunFolder(path, state, file)
