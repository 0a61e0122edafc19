"""``make_env``: the default ``TransformedEnv(TocabiWalk(...), Compose(...))`` of the walking task."""

from __future__ import annotations

import dataclasses

import torch
from torchrl.envs import TransformedEnv

from .cuda_graphs import env_graph_blockers
from .device import check_device
from .envs import TocabiWalk, TocabiWalkConfig
from .envs.autoreset import SyncFreeResetEnv
from .envs.config import ENV_FLAT_PATHS
from .transforms import TransformConfig, TransformSettings, default_transforms
from .transforms.presets import HISTORIES
from .value_rules import check_seed

__all__ = ["make_env"]

_TRANSFORM_FIELDS = {f.name for f in dataclasses.fields(TransformConfig)} - {"max_episode_steps"}
_ENV_KEYWORDS = set(ENV_FLAT_PATHS) | {f.name for f in dataclasses.fields(TocabiWalkConfig)} | {"leg_controller"}


def make_env(
    num_envs: int | None = None,
    device: str | torch.device = "cuda",
    preset: str | None = None,
    seed: int | None = None,
    sync_free_resets: bool | None = None,
    cuda_graph: bool = False,
    *,
    config: TocabiWalkConfig | None = None,
    transforms: TransformSettings | None = None,
    **overrides,
) -> TransformedEnv:
    """The walking task as the policy sees it: ``observation`` (num_envs, 237; 267 with ``transforms.observation``
    base_vel, the ``torque`` preset's), ``reward`` (num_envs, 1), ``("reward_terms", name)`` per term,
    ``step_count``, ``episode_reward`` and the env's raw signals.

    With no arguments this is the task of the ``default`` training preset (the env and transform sections of
    ``tocabi_torchrl.config.preset_tree("default")``), on CUDA.

    Args:
        num_envs: parallel worlds (default: ``config.num_envs``, 4096).
        device, seed: see :class:`~tocabi_torchrl.envs.TocabiWalk`.
        config: the env section (:class:`~tocabi_torchrl.envs.TocabiWalkConfig`; default: its defaults).
        transforms: the transform section (:class:`~tocabi_torchrl.transforms.TransformSettings`; default: its
            defaults: the reference observation and rewards with the velocity term tripled).
        preset: a training preset, as on the command line and in the adapters' ``make_vec`` (``"default"``,
            ``"torque"``, ``"robust"``, ``"torque_ideal"``, ``"model_based"``, ``"model_based_ideal"``,
            ``"pd"``, ``"reference"``, ``"cpu_smoke"``:
            :data:`tocabi_torchrl.config.PRESETS`):
            the env is built from that preset's env and transform sections (``num_envs`` defaults to the preset's),
            so it cannot be given with ``config``/``transforms``. The trainer's training aids are not part of a
            preset's env (the torque preset's assist: pass ``torque_assist=True``). The transforms' history layout
            is ``transforms=TransformSettings(history="tocabilab")`` (see :data:`tocabi_torchrl.transforms.HISTORIES`).
        sync_free_resets: return a :class:`~tocabi_torchrl.envs.autoreset.SyncFreeResetEnv`, whose
            ``step_and_maybe_reset`` (the collectors' step) resets done envs without host reads (default: on CUDA).
        cuda_graph: capture that ``step_and_maybe_reset`` as one CUDA graph after two eager calls and replay it
            (CUDA and ``sync_free_resets`` only). Off by default here; the trainer turns it on at small env counts,
            where the step is launch-bound (``ppo.cuda_graph``, measured in ``docs/benchmarks/env_graph.md``).
            See :class:`~tocabi_torchrl.envs.autoreset.SyncFreeResetEnv` for what a capture freezes.
        overrides: env options as flat names (e.g. ``control_mode="pd"``, ``max_episode_steps=1000``, see
            ``envs.config.ENV_FLAT_PATHS``) or sections (``command=CommandConfig.reference()``), a user-defined
            ``leg_controller`` (:class:`~tocabi_torchrl.control.Controller`, docs/concepts/controllers.md), and fields
            of :class:`~tocabi_torchrl.transforms.TransformConfig` (e.g. ``reward_weights={"qpos": 0.5}``, which
            re-weights the named terms on top of the settings' weights, ``normalization="running"``,
            ``history=HistoryLayout(...)``); a name in neither raises.
            ``reward_terms`` replaces every reward term, and a list that leaves out a term beyond the reference's
            that the transform settings switch on (the robust preset's ``heading`` and ``foot_gap``: its
            ``heading_weight``, ``foot_gap_weight``, ``cycle_vel_weight`` > 0) raises ``ValueError`` naming them,
            rather than dropping them silently: keep them with ``reward_terms=(..., *settings.extra_reward_terms())``
            (``settings = tocabi_torchrl.config.preset_tree(preset).transforms``), or leave them out by passing
            ``config=`` and ``transforms=`` of that tree with their weights set to 0.

    The env's ``task.max_episode_steps`` is the one truncation clock: the transforms' ``StepCounter`` only counts.
    """
    device = check_device(device)  # before anything reads it: a bad name gets TocabiWalk's clear message
    if seed is not None:
        seed = check_seed(seed)
    for name, value in (("sync_free_resets", sync_free_resets), ("cuda_graph", cuda_graph)):
        if not (isinstance(value, bool) or (value is None and name == "sync_free_resets")):
            # Text such as "no" is truthy: it would silently turn the switch on.
            raise TypeError(f"make_env {name} must be True or False, got {value!r}")
    if transforms is not None and not isinstance(transforms, TransformSettings):
        raise TypeError(f"make_env transforms= takes a TransformSettings (the run config's transforms section), got "
                        f"{type(transforms).__name__}; pass TransformConfig fields as keywords (reward_weights=..., "
                        f"history=...) or build the chain with default_transforms(TransformConfig(...))")
    unknown = set(overrides) - _ENV_KEYWORDS - _TRANSFORM_FIELDS
    if unknown:
        raise TypeError(f"make_env got unknown option(s) {sorted(unknown)}; valid options are the env's "
                        f"{sorted(_ENV_KEYWORDS)} and TransformConfig's {sorted(_TRANSFORM_FIELDS)}")
    env_kwargs = {k: v for k, v in overrides.items() if k in _ENV_KEYWORDS}
    tf_kwargs = {k: v for k, v in overrides.items() if k not in _ENV_KEYWORDS}
    config, transforms = _preset_sections(preset, config, transforms)
    settings = transforms if transforms is not None else TransformSettings()
    tf_config = settings.transform_config(**tf_kwargs)
    if sync_free_resets is None:
        sync_free_resets = device.type == "cuda"
    blockers = env_graph_blockers(device, sync_free_resets, tf_config.compile_reward) if cuda_graph else []
    if blockers:
        raise ValueError("; ".join(blockers))
    base = TocabiWalk(num_envs=num_envs, device=device, config=config, seed=seed, **env_kwargs)
    transforms_ = default_transforms(tf_config)
    if sync_free_resets:
        return SyncFreeResetEnv(base, transforms_, cuda_graph=cuda_graph)
    return TransformedEnv(base, transforms_)


def _preset_sections(preset: str | None, config: TocabiWalkConfig | None,
                     transforms: TransformSettings | None) -> tuple[TocabiWalkConfig | None, TransformSettings | None]:
    """The env and transform sections of the training preset ``preset``; ``config``/``transforms`` as given when
    there is none. Raises naming the training presets for an unknown name."""
    if preset is None:
        return config, transforms
    from .config import PRESETS, preset_tree

    if preset not in PRESETS:
        # "tocabilab" named the transforms' history layout here before: say where it went.
        hint = (f"; {preset!r} is a transforms history layout: pass transforms=TransformSettings(history={preset!r})"
                if preset in HISTORIES else "")
        raise ValueError(f"unknown training preset {preset!r}; choose one of {sorted(PRESETS)}{hint}")
    if config is not None or transforms is not None:
        raise TypeError(f"make_env takes preset={preset!r} or the sections config=/transforms=, not both (the preset "
                        "is its env and transform sections); change single options with keywords instead, e.g. "
                        "control_mode=..., max_episode_steps=..., reward_weights=...")
    tree = preset_tree(preset)
    return tree.env, tree.transforms
