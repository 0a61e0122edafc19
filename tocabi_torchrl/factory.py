"""``make_env``: the default ``TransformedEnv(TocabiWalk(...), Compose(...))`` of the walking task."""

from __future__ import annotations

import dataclasses

import torch
from torchrl.envs import TransformedEnv

from .device import check_device
from .envs import TocabiWalk, TocabiWalkConfig
from .envs.autoreset import SyncFreeResetEnv
from .transforms import TransformConfig, default_transforms, transform_config

__all__ = ["make_env"]

_TRANSFORM_FIELDS = {f.name for f in dataclasses.fields(TransformConfig)}


def make_env(
    num_envs: int = 4096,
    device: str | torch.device = "cuda",
    preset: str = "reference",
    seed: int | None = None,
    sync_free_resets: bool | None = None,
    cuda_graph: bool = False,
    **overrides,
) -> TransformedEnv:
    """The walking task as the policy sees it: ``observation`` (num_envs, 237), ``reward`` (num_envs, 1),
    ``("reward_terms", name)`` per term, ``step_count``, ``episode_reward`` and the env's raw signals.

    Args:
        num_envs, device, seed: see :class:`~tocabi_torchrl.envs.TocabiWalk`.
        preset: transform preset (``"reference"``: 5 observations two steps apart + 4 actions, fixed reference
            normalisation, the 13 reference reward terms, reward 0 on terminating steps; ``"tocabilab"``: the
            consecutive history layout). See :data:`tocabi_torchrl.transforms.PRESETS`.
        sync_free_resets: return a :class:`~tocabi_torchrl.envs.autoreset.SyncFreeResetEnv`, whose
            ``step_and_maybe_reset`` (the collectors' step) resets done envs without host reads (default: on CUDA).
        cuda_graph: capture that ``step_and_maybe_reset`` as one CUDA graph after two eager calls and replay it
            (CUDA and ``sync_free_resets`` only). Off by default here; the trainer turns it on at small env counts,
            where the step is launch-bound (``PPOConfig.cuda_graph``, measured in ``docs/benchmarks/env_graph.md``).
            See :class:`~tocabi_torchrl.envs.autoreset.SyncFreeResetEnv` for what a capture freezes.
        overrides: fields of :class:`~tocabi_torchrl.envs.TocabiWalkConfig` (e.g. ``control_mode="pd"``,
            ``max_episode_steps=1000``) and of :class:`~tocabi_torchrl.transforms.TransformConfig`
            (e.g. ``reward_weights={"qpos": 0.5}``, ``normalization="running"``); a name in neither raises.
    """
    device = check_device(device)  # before anything reads it: a bad name gets TocabiWalk's clear message
    env_fields = set(TocabiWalkConfig.__dataclass_fields__)
    unknown = set(overrides) - env_fields - _TRANSFORM_FIELDS
    if unknown:
        raise TypeError(f"make_env got unknown option(s) {sorted(unknown)}; valid options are the fields of "
                        "TocabiWalkConfig and TransformConfig")
    env_kwargs = {k: v for k, v in overrides.items() if k in env_fields}
    tf_kwargs = {k: v for k, v in overrides.items() if k in _TRANSFORM_FIELDS}
    if cuda_graph and transform_config(preset, **tf_kwargs).compile_reward:
        raise ValueError("compile_reward=True and cuda_graph=True do not combine (a recompile inside the capture "
                         "would break it); the CUDA graph already removes the launches torch.compile saves")
    on_cuda = device.type == "cuda"
    if sync_free_resets is None:
        sync_free_resets = on_cuda
    if cuda_graph and not on_cuda:
        raise ValueError(f"cuda_graph=True needs a CUDA device, got device={str(device)!r}; pass cuda_graph=False")
    if cuda_graph and not sync_free_resets:
        raise ValueError("cuda_graph=True needs sync_free_resets=True: a step that reads device values on the host "
                         "cannot be captured")
    base = TocabiWalk(num_envs=num_envs, device=device, seed=seed, **env_kwargs)
    # One truncation clock: the transforms' step counter follows the env's episode length.
    tf_kwargs.setdefault("max_episode_steps", base.cfg.max_episode_steps)
    transforms = default_transforms(preset, **tf_kwargs)
    if sync_free_resets:
        return SyncFreeResetEnv(base, transforms, cuda_graph=cuda_graph)
    return TransformedEnv(base, transforms)
