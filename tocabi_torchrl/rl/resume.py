"""``--resume``: continue a run with the config saved in its checkpoint.

A resumed run is the same run: its networks, task, rewards and learning settings come from the checkpoint. Options
given again may change only what :data:`~tocabi_torchrl.rl.options.RESUME_SAFE` lists (budget, logging, checkpoint
cadence and retention, evaluation, device, and how the same computation runs: CUDA graphs, gradient sync, stored env
signals, CPU threads, reset pass); any other difference is refused with a :class:`ResumeConfigError` naming the field,
the saved value and the given one. Values are compared as values: ``transforms.reward_weights`` by the weight each
term gets, not by how its entries are written.
"""

from __future__ import annotations

import os
from pathlib import Path

from ..config import RunConfig, flat_to_paths
from ..tree import get_path, leaf_paths, replace_paths
from .checkpoint import checkpoint_file, config_from_checkpoint, read_checkpoint, run_folder_of
from .options import RESUME_SAFE, resume_safe_text

__all__ = ["ResumeConfigError", "resume_config", "check_resume_config", "holds_checkpoint", "no_checkpoint_message"]


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


def _differences(saved: RunConfig, given: dict) -> list[tuple[str, object, object]]:
    """``(option, saved value, given value)`` of each given option outside :data:`RESUME_SAFE` that differs; an
    option is named as it was given (a dotted path, or a flat name of before the tree)."""
    out = []
    for name, value in given.items():
        for path, now in flat_to_paths({name: value}).items():
            if path in RESUME_SAFE:
                continue
            was = get_path(saved, path)
            if not _same(path, was, now):
                out.append((name, was, now))
    return out


def _same(path: str, was, now) -> bool:
    """Whether the saved and the given value of ``path`` set the same thing."""
    if now == was:
        return True
    if path == "transforms.reward_weights":
        # 'body_vel=0.9' and 'body_vel=0.90' (or the entries in another order) are the same weights.
        from ..transforms.presets import TransformSettings

        try:
            return (TransformSettings(reward_weights=tuple(was)).reward_weight_map()
                    == TransformSettings(reward_weights=tuple(now)).reward_weight_map())
        except (TypeError, ValueError):  # a malformed entry differs; validate() names it
            return False
    return False


def _refuse(path, diffs: list[tuple[str, object, object]]) -> ResumeConfigError:
    lines = "; ".join(f"{name}: saved {was!r}, given {now!r}" for name, was, now in diffs)
    return ResumeConfigError(
        f"cannot resume {path} with other settings than the run was trained with ({lines}). Drop these options to "
        f"continue the run as saved, or start a new run with --name. On --resume only these may change: "
        f"{resume_safe_text()}"
    )


def check_resume_config(saved: RunConfig, given: RunConfig, path: str | os.PathLike = "<checkpoint>") -> None:
    """Raise :class:`ResumeConfigError` if ``given`` differs from ``saved`` in an option a resume may not change."""
    diffs = _differences(saved, {p: get_path(given, p) for p in leaf_paths(given)})
    if diffs:
        raise _refuse(path, diffs)


def resume_config(resume: str | os.PathLike, overrides: dict) -> RunConfig:
    """The config saved with ``resume`` (a run folder or checkpoint file) with the command line's explicit
    ``overrides`` applied; ``overrides`` (dotted paths or the flat names of before the tree) may hold ``preset``
    (compared by name) and any option."""
    folder = Path(resume)
    if folder.is_dir() and (folder / "config.json").is_file() and not holds_checkpoint(folder):
        raise ResumeConfigError(no_checkpoint_message(folder))
    path = checkpoint_file(resume)
    # Strict: the run trains on with these values, so one that breaks a rule of this version is refused here.
    saved = config_from_checkpoint(read_checkpoint(path), path, strict=True)
    diffs = _differences(saved, overrides)
    if diffs:
        raise _refuse(path, diffs)
    safe = {k: v for k, v in flat_to_paths(overrides).items() if k in RESUME_SAFE}
    if path.parent.name == "checkpoints":
        # The run goes on where its checkpoint is (or, given --name alone, branches beside it): the saved run_dir is
        # relative to where the run started, so from another folder (or after the run folder moved) it would name
        # a new folder and split the run in two.
        run = run_folder_of(path)
        safe.setdefault("run_dir", str(run.parent))
        safe.setdefault("name", run.name)
    return replace_paths(saved, {**safe, "resume": str(resume)}).validated()
