"""What ``--policy`` names: a policy shipped with the package (``ppo``, ``torque``, ``model_based``, or the file's
stem ``tocabi_walk_ppo``), a run folder, or a checkpoint / exported policy file."""

from __future__ import annotations

import os
from pathlib import Path

from .. import robot

__all__ = ["shipped_policies", "resolve_policy"]

_PREFIX = "tocabi_walk_"


def shipped_policies() -> dict[str, Path]:
    """Short name (``ppo``, ``torque``, ...) -> the shipped checkpoint (``assets/policies/tocabi_walk_<name>.pt``)."""
    folder = robot.asset_path("policies")
    return {p.stem.removeprefix(_PREFIX): p for p in sorted(folder.glob("*.pt"))}


def resolve_policy(name: str | os.PathLike) -> Path:
    """The file or run folder ``name`` stands for: an existing path as given, else a shipped policy by its short
    name or file stem (``ppo`` or ``tocabi_walk_ppo``; ``ppo.onnx`` for its exported model). Raises ``ValueError``
    listing the shipped names when it is neither."""
    if not str(name).strip():  # Path("") is the current folder, which would then be looked up as a run
        raise ValueError("--policy is empty: give a shipped policy (" + ", ".join(shipped_policies()) + "), a run "
                         "folder or a checkpoint file")
    path = Path(name)
    if path.exists():
        return path
    text = str(name)
    stem, suffix = (text[:-5], ".onnx") if text.endswith(".onnx") else (text.removesuffix(".pt"), ".pt")
    shipped = shipped_policies()
    key = stem.removeprefix(_PREFIX)
    if key in shipped:
        found = shipped[key].with_suffix(suffix)
        if found.exists():
            return found
    raise ValueError(f"--policy {text!r} is neither an existing run folder or file nor a shipped policy; the shipped "
                     f"ones are {', '.join(shipped)} (add .onnx for the exported model where there is one)")
