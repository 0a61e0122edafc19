"""The gait tests of ``recipes/play.py`` for a policy of any library, given as a function from observations to
deterministic actions: the standard 8 s test (:func:`tocabi_torchrl.evaluation.gait_test.evaluate_policy`) or the
robust one (:func:`tocabi_torchrl.evaluation.robust.evaluate_robust`, docs/evaluation.md)."""

from __future__ import annotations

import os
from collections.abc import Callable

import torch

from ..cli import GAIT_TESTS
from ..evaluation.gait_test import GAIT_CRITERIA, evaluate_policy, gait_passes
from ..evaluation.plots import check_plotting
from ..evaluation.record import nominal_config
from ._build import env_device, task_config
from .policy_file import require_meta

__all__ = ["GAIT_CRITERIA", "TESTS", "check_plotting", "evaluate_actions", "evaluate_policy_file", "gait_passes"]

#: The gait tests a policy can be given (``test=``), as ``recipes/play.py --test`` names them.
TESTS = GAIT_TESTS

# GAIT_CRITERIA and gait_passes are the gait test's own (tocabi_torchrl.evaluation.gait_test), check_plotting its
# figures' (evaluation.plots), re-exported here.


def evaluate_actions(act: Callable[[torch.Tensor], torch.Tensor], out_dir: str | os.PathLike,
                     preset: str = "default", num_envs: int = 256, device: str | torch.device | int | None = "auto",
                     seconds: float = 8.0, command: tuple[float, float] = (0.5, 0.0), video_envs: int = 0,
                     progress: bool = False, task: dict | None = None,
                     source: str | os.PathLike | None = None, test: str = "standard") -> dict:
    """Run the gait test on ``act``: (num_envs, 237) observations -> (num_envs, 13) actions on the same device,
    deterministic (the policy's mean). ``preset``/``task`` must be the ones the policy trained on. Writes
    ``summary.json`` (with ``"checkpoint": source`` when given: the file the policy came from) and ``knees.png`` to
    ``out_dir``, replacing files of those names there (the recipes pass a fresh folder; pass one to keep earlier
    results), and returns the summary with ``"passes"`` added. Without matplotlib an ``ImportError`` names the
    install command before anything runs (:func:`check_plotting`).

    ``test="robust"``: the robust gait test instead (diverse starts; nominal, changing-command, randomised and
    pushed cases of ``num_envs`` robots each, ``seconds`` long), which writes ``robust.json`` and ``robust.png`` and
    returns its report (``"passes"`` its verdict over every case). Its commands are its cases', so ``command`` and
    ``video_envs`` (it records no video) must stay at their defaults."""
    _check_test(test, command, video_envs)
    check_plotting()
    dev = env_device(device)  # as the adapters take it: None is "auto", an int a GPU index
    if test == "robust":
        return _evaluate_robust(act, preset, num_envs, dev, seconds, progress, task, source, out_dir)
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
                         progress: bool = True, test: str = "standard") -> dict:
    """The 8 s gait test of a recipe's ``policy.pt``: ``load_actor(policy)`` (the recipe's loader) gives its metadata
    (preset, task) and a deterministic ``act(obs) -> action``, which :func:`evaluate_actions` runs. ``progress``: a
    progress bar of the rollout (on by default: the recipes' gait test runs for minutes on a CPU). ``test``:
    ``"standard"`` or ``"robust"`` (:func:`evaluate_actions`; ``num_envs`` robots per case in the robust test).

    A metadata without a ``preset`` (str) or ``task`` (dict) is a :class:`~.policy_file.PolicyFileError` naming the
    file, the field and how to add it, before anything runs."""
    _check_test(test, command)  # before the policy loads
    meta, act = load_actor(policy)
    _check_task_fields(policy, meta)
    return evaluate_actions(act, out_dir, preset=meta["preset"], num_envs=num_envs, device=device, seconds=seconds,
                            command=command, progress=progress, task=meta["task"], source=policy, test=test)


def _check_test(test, command, video_envs: int = 0) -> None:
    """``ValueError`` for a test name other than :data:`TESTS`, or a standard-test option given to the robust test
    (it would be ignored without a word)."""
    if test not in TESTS:
        raise ValueError(f"test must be 'standard' (the 8 s test at one command) or 'robust' (diverse starts, "
                         f"changing commands, randomised and pushed cases), got {test!r}")
    if test == "robust" and tuple(command) != (0.5, 0.0):
        raise ValueError(f"command={tuple(command)!r} sets the standard test's command; the robust test's commands "
                         "are its cases' (leave command out, or pass test='standard')")
    if test == "robust" and video_envs != 0:
        raise ValueError(f"video_envs={video_envs!r} sets the standard test's video; the robust test records none "
                         "(leave video_envs out, or pass test='standard')")


def _evaluate_robust(act, preset, num_envs, device, seconds, progress, task, source, out_dir) -> dict:
    """:func:`evaluate_actions`' robust test: :func:`~tocabi_torchrl.evaluation.robust.evaluate_robust` of ``act``.
    It takes the policy's training config, as ``evaluate_robust_run`` passes a checkpoint's: its cases start from
    that config's nominal robot themselves and the randomised ones add the test's own draws."""
    from ..evaluation.robust import RobustTestConfig, evaluate_robust

    cfg = task_config(preset, num_envs=num_envs, **(task or {}))

    def actor(td):
        return td.set("action", act(td.get("observation")))

    return evaluate_robust(actor, cfg, out_dir, test=RobustTestConfig(num_envs=num_envs, seconds=seconds),
                           device=device, progress=progress, source=source)


#: The metadata fields the gait test rebuilds a policy's task from: {name: (kind, what it holds)}.
_TASK_FIELDS = {"preset": ("text", "the name of the preset the policy trained on, e.g. 'default'"),
                "task": ("object", "the task options it trained with, e.g. {'seed': 0}")}


def _check_task_fields(policy, meta) -> None:
    """A :class:`~.policy_file.PolicyFileError` (:func:`~.policy_file.require_meta`'s) unless ``meta`` holds
    ``preset`` (str) and ``task`` (dict of str keys). The recipes always write both; a hand-made or older file may
    lack them, which ended in a bare ``KeyError``."""
    require_meta(meta, _TASK_FIELDS, policy, "the gait test needs to rebuild the policy's task")
