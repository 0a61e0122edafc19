"""``--resume``: continue a run with the config saved in its checkpoint.

A resumed run is the same run: its networks, task, rewards and learning settings come from the checkpoint. Options
given again may change only what :data:`RESUME_SAFE` lists (budget, logging, checkpoint cadence and retention,
evaluation, device, and how the same computation runs: CUDA graphs, gradient sync, stored env signals, CPU threads,
reset pass); any other difference is refused with a :class:`ResumeConfigError` naming the option, the saved value
and the given one. The command line is parsed over the saved config (``rl.config.resume_config``), so an option
given with its saved value is no change.
"""

from __future__ import annotations

import os
from pathlib import Path

from ..config import RunConfig
from ..tree import get_path, leaf_paths, replace_paths
from .checkpoint import (
    CheckpointError,
    _ITER_FILE,
    DamagedCheckpointError,
    checkpoint_file,
    config_from_checkpoint,
    is_run_checkpoint,
    read_checkpoint,
    run_folder_of,
)

__all__ = ["ResumeConfigError", "RESUME_SAFE", "saved_config", "resume_safe_text", "check_resume_config",
           "holds_checkpoint", "no_checkpoint_message"]

#: Paths a ``--resume`` may change: they set the budget, logging, checkpoints, evaluation, where it runs, or how
#: the same computation is executed (CUDA graphs, gradient sync, stored env signals, CPU threads, reset pass). Every
#: other option must equal the saved run's: a schedule's end point (``ppo.lr_end``) is not among them, since changing
#: it mid-run makes the rate jump to another line. ``RunConfig.resume``'s help lists them too (a test compares).
RESUME_SAFE = frozenset({
    "name", "run_dir", "device", "resume",
    "total_env_steps", "max_minutes",
    "log_every", "loggers", "progress_bar",
    "checkpoint_every", "checkpoint_keep_last", "checkpoint_keep_every", "checkpoint_minutes",
    "eval_at_end", "eval_envs", "eval_seconds", "eval_test",
    "ppo.cuda_graph", "ppo.update_graph", "ppo.grad_sync", "ppo.store_env_signals", "ppo.symmetric_policy",
    "env.sim.threads", "env.sim.reset_pass",
    "viewer.enabled", "viewer.host", "viewer.port", "viewer.worlds", "viewer.every",
})


def resume_safe_text() -> str:
    """The options a ``--resume`` may give other values (:data:`RESUME_SAFE` but ``resume``), as the refusal of a
    changed option lists them."""
    return ", ".join(sorted(RESUME_SAFE - {"resume"}))


class ResumeConfigError(ValueError):
    """A resumed run was given options that would change what the saved run is."""


def holds_checkpoint(folder: str | os.PathLike) -> bool:
    """Whether the run folder ``folder`` holds a checkpoint a ``--resume`` can start from (``latest.pt`` or an
    iteration file; a wall-clock snapshot is not taken for one)."""
    checkpoints = Path(folder) / "checkpoints"
    return (checkpoints / "latest.pt").is_file() or any(checkpoints.glob("iter_*.pt"))


def no_checkpoint_message(folder: Path) -> str:
    """Why the run folder ``folder``, which holds a run but no checkpoint, can be neither resumed nor reused, and
    what to do instead (it is never removed for the user)."""
    return (f"run folder {folder} holds a run that saved no checkpoint (it stopped before its first one), so it cannot "
            f"be resumed; it is not overwritten either. Start the run under another --name, or remove the folder "
            f"(rm -r {folder}) to use this name again")


def _differences(saved: RunConfig, given: RunConfig) -> list[tuple[str, object, object]]:
    """``(path, saved value, given value)`` of each option outside :data:`RESUME_SAFE` that differs."""
    return [(path, get_path(saved, path), get_path(given, path)) for path in leaf_paths(saved)
            if path not in RESUME_SAFE and get_path(saved, path) != get_path(given, path)]


def _refuse(path, diffs: list[tuple[str, object, object]]) -> ResumeConfigError:
    lines = "; ".join(f"{name}: saved {was!r}, given {now!r}" for name, was, now in diffs)
    return ResumeConfigError(
        f"cannot resume {path} with other settings than the run was trained with ({lines}). Drop these options to "
        f"continue the run as saved (from Python: tocabi_torchrl.rl.resume.saved_config(run) is the saved config, set "
        f"to resume), or start a new run with --name. On --resume only these may change: {resume_safe_text()}"
    )


#: How many of a damaged checkpoint's neighbours :func:`_intact_alternative` reads at most of each kind (the
#: iteration files, the others); each is read whole.
_ALTERNATIVES_READ = 2


def _intact_alternative(damaged: Path) -> str:
    """A hint for a damaged checkpoint: the readable checkpoint beside it with the highest iteration, among the
    :data:`_ALTERNATIVES_READ` highest ``iter_*.pt`` files (by the iteration in their names) and the as many newest
    ``wall_*.pt`` / ``latest.pt`` files (by write time), so a wall-clock save later than the last iteration file is
    named when it is the newest."""
    # A run's own checkpoint names only: a folder of other policies (assets/policies) names no run to continue.
    others = [p for p in damaged.parent.glob("*.pt") if p != damaged and p.is_file() and is_run_checkpoint(p)]
    # File times alone put iteration 13 first after `cp -r` (which writes every copy anew, in any order).
    numbered = sorted((p for p in others if _ITER_FILE.match(p.name)),
                      key=lambda p: -int(_ITER_FILE.match(p.name).group(1)))
    timed = sorted((p for p in others if not _ITER_FILE.match(p.name)), key=lambda p: -p.stat().st_mtime)
    found = []
    for other in (*numbered[:_ALTERNATIVES_READ], *timed[:_ALTERNATIVES_READ]):
        try:
            found.append((int(read_checkpoint(other)["iteration"]), other))
        except CheckpointError:
            continue
    if not found:
        return ""
    iteration, other = max(found, key=lambda f: f[0])  # the first of equal ones: an iteration file
    return (f". The newest readable checkpoint beside it is {other.name} (iteration {iteration}): continue from "
            f"it with --resume {other}")


def check_resume_config(saved: RunConfig, given: RunConfig, path: str | os.PathLike = "<checkpoint>") -> None:
    """Raise :class:`ResumeConfigError` if ``given`` differs from ``saved`` in an option a resume may not change."""
    diffs = _differences(saved, given)
    if diffs:
        raise _refuse(path, diffs)


def saved_config(resume: str | os.PathLike) -> RunConfig:
    """The config saved with ``resume`` (a run folder or checkpoint file), set to go on where its checkpoint is:
    ``resume`` set, and ``run_dir``/``name`` naming the checkpoint's run folder."""
    folder = Path(resume)
    if folder.is_dir() and (folder / "config.json").is_file() and not holds_checkpoint(folder):
        raise ResumeConfigError(no_checkpoint_message(folder))
    path = checkpoint_file(resume)
    try:
        state = read_checkpoint(path)
    except DamagedCheckpointError as err:  # another checkpoint of the run can stand in; other refusals stay as raised
        raise DamagedCheckpointError(f"{err}{_intact_alternative(path)}") from err
    # Strict: the run trains on with these values, so one that breaks a rule of this version is refused here.
    saved = config_from_checkpoint(state, path, strict=True)
    where = {"resume": str(resume)}
    if path.parent.name == "checkpoints":
        # The run goes on where its checkpoint is (or, given --name alone, branches beside it): the saved run_dir is
        # relative to where the run started, so from another folder (or after the run folder moved) it would name
        # a new folder and split the run in two.
        run = run_folder_of(path)
        where.update(run_dir=str(run.parent), name=run.name)
    return replace_paths(saved, where)
