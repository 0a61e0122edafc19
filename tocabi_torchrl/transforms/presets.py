"""Named transform presets and the builder of the default ``Compose`` that turns env signals into policy input and
reward.

The default chain (``default_transforms("reference")``), in order:

1. :class:`PhaseEncoding`: ``phase`` -> ``phase_sin``, ``phase_cos`` (num_envs, harmonics)
2. :class:`BaseEulerAngles`: ``base_quat`` -> ``base_rpy`` (num_envs, 3)
3. :class:`ObservationAssembly`: signals -> ``obs_step`` (num_envs, 37), the reference order
   (with ``sensor_noise`` on, :class:`SensorNoise` then adds sensor biases and noise to ``obs_step``)
4. :class:`FixedNormalization` (or :class:`RunningNormalization`): ``obs_step`` -> ``obs_step_norm``
5. :class:`ObsActionHistory`: ``obs_step_norm`` + ``applied_action`` -> ``observation`` (num_envs, 237)
6. :class:`TaskReward`: ``reward`` (num_envs, 1) and ``("reward_terms", name)`` for the 13 reference terms
7. ``StepCounter``: ``step_count``, and truncation at ``max_episode_steps`` only when it is set; by default
   (``None``, as in ``make_env``) it only counts, and the env's own ``task.max_episode_steps`` is the one
   truncation clock
8. ``RewardSum``: ``episode_reward``, the running episode return

Every stage is an ordinary TorchRL transform: build your own ``Compose`` from them, or change one field here.
"""

from __future__ import annotations

import copy

from torchrl.envs.transforms import Compose, RewardSum, StepCounter, Transform

from tocabi_torchrl.transforms.history import ObsActionHistory
from tocabi_torchrl.transforms.layouts import layout_name
from tocabi_torchrl.transforms.normalize import FIXED_STATISTICS, FixedNormalization, RunningNormalization
from tocabi_torchrl.transforms.observation import ObservationAssembly
from tocabi_torchrl.transforms.orientation import BaseEulerAngles
from tocabi_torchrl.transforms.phase import PhaseEncoding
from tocabi_torchrl.transforms.reward import TaskReward
from tocabi_torchrl.transforms.reward_terms import RewardTerm, reference_terms
from tocabi_torchrl.transforms.sensor_noise import SensorNoise
# The config (plain values) lives in a module without torch, for the config tree; this path names it too.
from tocabi_torchrl.transforms.settings import HISTORIES, TransformConfig, TransformSettings, transform_config

__all__ = ["TransformConfig", "TransformSettings", "HISTORIES", "transform_config", "default_transforms"]


def _normalization(cfg: TransformConfig) -> Transform | None:
    if cfg.obs_mean is not None:
        mean, var = cfg.obs_mean, cfg.obs_var
    elif (name := layout_name(cfg.obs_layout)) is not None and cfg.phase_harmonics == 1:
        mean, var = FIXED_STATISTICS[name]
    else:
        mean = var = None  # a layout of one's own, or more harmonics, has no statistics of ours
    if cfg.normalization == "fixed":
        if mean is None:
            raise ValueError(
                "normalization='fixed' needs obs_mean/obs_var for an observation layout of one's own (not one of "
                "layouts.OBS_LAYOUTS) or phase_harmonics other than 1; "
                "pass them, or use normalization='running' or 'none'"
            )
        norm = FixedNormalization("obs_step", "obs_step_norm", mean=mean, var=var, clip=cfg.obs_clip)
    elif cfg.normalization == "running":
        norm = RunningNormalization("obs_step", "obs_step_norm", init_mean=mean, init_var=var, clip=cfg.obs_clip)
    else:
        return None
    if cfg.obs_mean is not None:  # a layout the config cannot size is checked once the env's spec is known
        norm.stats_source = "obs_mean/obs_var"
    return norm


def _reward_terms(cfg: TransformConfig) -> list[RewardTerm]:
    """The terms of ``cfg``, each with its ``reward_scales`` entry as its kernel's ``scale`` (a copy: a term instance
    the caller passed is not changed)."""
    terms = [reference_terms((t,))[0] if isinstance(t, str) else t for t in cfg.reward_terms]
    names = [getattr(t, "name", getattr(t, "__name__", None)) for t in terms]
    unknown = sorted(set(cfg.reward_scales) - set(names))
    if unknown:
        raise KeyError(f"reward_scales given for term(s) {unknown} that are not in use; terms: {names}")
    for i, name in enumerate(names):
        if name in cfg.reward_scales:
            if not hasattr(terms[i], "scale"):
                raise ValueError(f"reward_scales[{name!r}]: the term {terms[i]!r} has no kernel scale to set")
            terms[i] = copy.copy(terms[i])
            terms[i].scale = float(cfg.reward_scales[name])
    return terms


def default_transforms(base: str | TransformConfig = "reference", /, **overrides) -> Compose:
    """Build the default ``Compose`` for :class:`~tocabi_torchrl.envs.TocabiWalk` signals (see the module doc).

    Args:
        base: a history layout's name (:data:`HISTORIES`): ``"reference"`` (237-value input: 5 obs two steps
            apart + 4 actions), ``"tocabilab"`` (consecutive history), or a :class:`TransformConfig`.
        **overrides: :class:`TransformConfig` fields, e.g. ``history=HistoryLayout(num_obs=3, stride=1)``,
            ``reward_weights={"qpos": 0.5}``, ``reward_terms=("qpos", "body_vel", my_term)``,
            ``normalization="running"``.

    Returns:
        A fresh ``Compose`` (its history is stateful: use one per env).
    """
    cfg = transform_config(base, **overrides)
    stages: list[Transform] = [
        PhaseEncoding("phase", ("phase_sin", "phase_cos"), harmonics=cfg.phase_harmonics),
        BaseEulerAngles("base_quat", "base_rpy"),
        ObservationAssembly(cfg.obs_layout, out_key="obs_step"),
    ]
    if cfg.sensor_noise.enabled:  # off: no transform, so not a number changes
        stages.append(SensorNoise(cfg.sensor_noise, cfg.obs_layout, obs_key="obs_step"))
    norm = _normalization(cfg)
    if norm is not None:
        stages.append(norm)
    stages.append(
        ObsActionHistory(
            cfg.history,
            obs_key="obs_step_norm" if norm is not None else "obs_step",
            action_key="applied_action",
            out_key="observation",
        )
    )
    stages.append(
        TaskReward(
            _reward_terms(cfg),
            weights=cfg.reward_weights,
            zero_on_terminated=cfg.zero_reward_on_terminated,
            compile=cfg.compile_reward,
            kick_relax=cfg.kick_relax,
        )
    )
    stages.append(StepCounter(max_steps=cfg.max_episode_steps))
    if cfg.track_episode_return:
        stages.append(RewardSum(in_keys=["reward"], out_keys=["episode_reward"]))
    return Compose(*stages)
