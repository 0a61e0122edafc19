"""``--resume``: continue a run with the config saved in its checkpoint.

A resumed run is the same run: its networks, task, rewards and learning settings come from the checkpoint. Options
given again may change only what :data:`~tocabi_torchrl.rl.options.RESUME_SAFE` lists (budget, logging, checkpoint
cadence and retention, evaluation, device, graph and storage switches); any other difference is refused with a
:class:`ResumeConfigError` naming the field, the saved value and the given one.
"""

from __future__ import annotations

import os

from ..config import RunConfig, flat_to_paths
from ..tree import get_path, leaf_paths, replace_paths
from .checkpoint import checkpoint_file, config_from_checkpoint, read_checkpoint, run_folder_of
from .options import RESUME_SAFE

__all__ = ["ResumeConfigError", "resume_config", "check_resume_config"]


class ResumeConfigError(ValueError):
    """A resumed run was given options that would change what the saved run is."""


def _differences(saved: RunConfig, given: dict) -> list[tuple[str, object, object]]:
    """``(option, saved value, given value)`` of each given option outside :data:`RESUME_SAFE` that differs; an
    option is named as it was given (a dotted path, or a flat name of before the tree)."""
    out = []
    for name, value in given.items():
        for path, now in flat_to_paths({name: value}).items():
            if path in RESUME_SAFE:
                continue
            was = get_path(saved, path)
            if now != was:
                out.append((name, was, now))
    return out


def _refuse(path, diffs: list[tuple[str, object, object]]) -> ResumeConfigError:
    lines = "; ".join(f"{name}: saved {was!r}, given {now!r}" for name, was, now in diffs)
    return ResumeConfigError(
        f"cannot resume {path} with other settings than the run was trained with ({lines}). Drop these options to "
        f"continue the run as saved, or start a new run with --name. On --resume only these may change: "
        f"{', '.join(sorted(RESUME_SAFE - {'resume'}))}"
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
    path = checkpoint_file(resume)
    saved = config_from_checkpoint(read_checkpoint(path), path)
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
