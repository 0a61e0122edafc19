"""The 8 s gait test of ``recipes/play.py`` (:func:`tocabi_torchrl.evaluation.gait_test.evaluate_policy`) for a policy
of any library, given as a function from observations to deterministic actions."""

from __future__ import annotations

import os
from collections.abc import Callable

import torch

from ..evaluation.gait_test import GAIT_CRITERIA, evaluate_policy, gait_passes
from ..evaluation.plots import check_plotting
from ..evaluation.record import nominal_config
from ._build import env_device, task_config
from .policy_file import require_meta

__all__ = ["GAIT_CRITERIA", "check_plotting", "evaluate_actions", "evaluate_policy_file", "gait_passes"]

# GAIT_CRITERIA and gait_passes are the gait test's own (tocabi_torchrl.evaluation.gait_test), check_plotting its
# figures' (evaluation.plots), re-exported here.


def evaluate_actions(act: Callable[[torch.Tensor], torch.Tensor], out_dir: str | os.PathLike,
                     preset: str = "default", num_envs: int = 256, device: str | torch.device | int | None = "auto",
                     seconds: float = 8.0, command: tuple[float, float] = (0.5, 0.0), video_envs: int = 0,
                     progress: bool = False, task: dict | None = None,
                     source: str | os.PathLike | None = None) -> dict:
    """Run the gait test on ``act``: (num_envs, 237) observations -> (num_envs, 13) actions on the same device,
    deterministic (the policy's mean). ``preset``/``task`` must be the ones the policy trained on. Writes
    ``summary.json`` (with ``"checkpoint": source`` when given: the file the policy came from) and ``knees.png`` to
    ``out_dir``, replacing files of those names there (the recipes pass a fresh folder; pass one to keep earlier
    results), and returns the summary with ``"passes"`` added. Without matplotlib an ``ImportError`` names the
    install command before anything runs (:func:`check_plotting`)."""
    check_plotting()
    dev = env_device(device)  # as the adapters take it: None is "auto", an int a GPU index
    cfg = nominal_config(task_config(preset, num_envs=num_envs, **(task or {})))  # the robot, not training's draws

    def actor(td):
        return td.set("action", act(td.get("observation")))

    summary = evaluate_policy(actor, cfg, out_dir, num_envs=num_envs, device=dev, seconds=seconds, command=command,
                              video_envs=video_envs, progress=progress, source=source)
    summary["passes"] = gait_passes(summary)
    return summary


def evaluate_policy_file(load_actor, policy: str, out_dir, num_envs: int = 256,
                         device: str | torch.device | int | None = "auto",
                         seconds: float = 8.0, command: tuple[float, float] = (0.5, 0.0),
                         progress: bool = True) -> dict:
    """The 8 s gait test of a recipe's ``policy.pt``: ``load_actor(policy)`` (the recipe's loader) gives its metadata
    (preset, task) and a deterministic ``act(obs) -> action``, which :func:`evaluate_actions` runs. ``progress``: a
    progress bar of the rollout (on by default: the recipes' gait test runs for minutes on a CPU).

    A metadata without a ``preset`` (str) or ``task`` (dict) is a :class:`~.policy_file.PolicyFileError` naming the
    file, the field and how to add it, before anything runs."""
    meta, act = load_actor(policy)
    _check_task_fields(policy, meta)
    return evaluate_actions(act, out_dir, preset=meta["preset"], num_envs=num_envs, device=device, seconds=seconds,
                            command=command, progress=progress, task=meta["task"], source=policy)


#: The metadata fields the gait test rebuilds a policy's task from: {name: (kind, what it holds)}.
_TASK_FIELDS = {"preset": ("text", "the name of the preset the policy trained on, e.g. 'default'"),
                "task": ("object", "the task options it trained with, e.g. {'seed': 0}")}


def _check_task_fields(policy, meta) -> None:
    """A :class:`~.policy_file.PolicyFileError` (:func:`~.policy_file.require_meta`'s) unless ``meta`` holds
    ``preset`` (str) and ``task`` (dict of str keys). The recipes always write both; a hand-made or older file may
    lack them, which ended in a bare ``KeyError``."""
    require_meta(meta, _TASK_FIELDS, policy, "the gait test needs to rebuild the policy's task")
