"""The one place the adapters build the walking task: every adapter, recipe and evaluation goes through
:func:`build_env`, so a change in how the task is configured is made here once."""

from __future__ import annotations

import dataclasses
import numbers

import torch
from torchrl.envs import EnvBase

from ..config import RunConfig, preset_config
from ..envs.config import ENV_FLAT_PATHS
from ..transforms.settings import RewardWeights
from ..value_rules import positive_count

__all__ = ["build_env", "env_device", "task_config"]

#: env_options that are sections of the env config (TocabiWalkConfig): reported as env.<section>.
_ENV_SECTIONS = ("sim", "task", "command", "control", "scene", "pushes", "dynamics")
#: make_env's transform options that are run-config transform settings of the same meaning: transforms.<name>.
_TRANSFORM_SETTINGS = ("normalization", "obs_clip", "zero_reward_on_terminated", "compile_reward", "sensor_noise",
                       "kick_relax")
#: The terms transforms.reward_weights holds a weight for (RewardWeights' fields).
_REWARD_WEIGHT_NAMES = tuple(f.name for f in dataclasses.fields(RewardWeights))


def task_config(preset: str = "default", num_envs: int = 4096, **task) -> RunConfig:
    """The run config of a training preset (its ``env`` and ``transforms`` sections are the task: control mode, PD
    gains, commands, reward weights, episode length) for ``num_envs`` envs. ``task``: options of
    :func:`tocabi_torchrl.config.preset_config` (dotted paths, e.g. ``seed=1``, ``**{"env.control.mode": "torque"}``)
    or the env's keywords as ``make_env`` takes them (``max_episode_steps=1000``, ``control_mode="torque"``:
    ``envs.config.ENV_FLAT_PATHS``); the ``ppo`` section is ignored by the adapters, whose library trains."""
    # The adapters never use the ppo section's update: shrink the mini-batch so a few envs validate.
    paths = {(f"env.{ENV_FLAT_PATHS[k]}" if k in ENV_FLAT_PATHS else k): v for k, v in task.items()}
    paths.setdefault("ppo.minibatch_size", 1)
    return preset_config(preset, **{"env.num_envs": num_envs}, **paths)


def env_device(device: str | torch.device | int | None) -> torch.device:
    """The device an adapter or gait test runs on: ``"cpu"``, ``"cuda"``, ``"cuda:K"``, ``"auto"`` or ``None`` (the
    first CUDA GPU torch sees, else the CPU; ``None`` is SB3's and skrl's "no preference"), a ``torch.device`` or a
    GPU index. Any other type is a ``TypeError`` naming these; a CUDA device where torch sees none is a
    ``RuntimeError``."""
    from ..rl.trainer import resolve_device

    if device is None:
        device = "auto"
    elif isinstance(device, numbers.Integral) and not isinstance(device, bool):  # torch's GPU index
        device = f"cuda:{int(device)}"
    elif not isinstance(device, (str, torch.device)):
        raise TypeError(f"device must be 'cpu', 'cuda', 'cuda:K', 'auto', a torch.device, a GPU index or None "
                        f"(auto), got {device!r}")
    return resolve_device(device if isinstance(device, str) else str(device))


def build_env(num_envs: int, device: str | torch.device | int | None = "cpu", preset: str = "default",
              for_training: bool = True, env_options: dict | None = None, **task) -> tuple[EnvBase, RunConfig]:
    """The walking task of ``preset`` over ``num_envs`` envs on ``device``, as a TorchRL env, and its config.

    The env is :func:`tocabi_torchrl.rl.trainer.build_env`'s: ``observation`` (num_envs, 237), ``reward``
    (num_envs, 1), ``terminated``/``truncated`` (num_envs, 1) bool, ``("reward_terms", name)`` (num_envs, 1) per
    reward term, ``episode_reward`` (num_envs, 1) and ``step_count`` (num_envs, 1). ``for_training`` drops the raw
    signals nobody reads during training (the gait test builds its own env with them). ``env_options``: fields of
    :class:`~tocabi_torchrl.envs.TocabiWalkConfig` or the transform config beyond the preset's (``make_env``'s
    options, e.g. ``{"min_pelvis_height": 0.7}``, ``{"pushes": PushConfig(count=4)}``); those the run config holds
    (env fields and sections, the transform settings) are in the returned config.
    """
    from ..rl.trainer import build_env as _trainer_env

    # Any integer type (numpy's, a 0-d tensor's: counts often come from arrays), but not bool, which is an int to
    # Python, nor a shaped array
    num_envs = positive_count(num_envs)
    dev = env_device(device)
    options = dict(env_options or {})
    own = [k for k in options if k in ("num_envs", "seed", "device", "config", "transforms")]
    if own:
        raise ValueError(f"env_options {own}: the adapter sets these from its own arguments and preset (num_envs, "
                         "device, seed=..., preset=...); give env config fields or make_env options instead")
    if "track_episode_return" in options:  # the adapters report returns from the env's episode_reward
        raise ValueError("env_options track_episode_return: the adapter reads the env's episode returns; leave it out")
    # What the run config can hold goes into the task config, so that the config the adapter reports (task_config,
    # rsl_rl's env.cfg) is the env it runs, not the preset's: the env's fields and sections, and the transform
    # settings of the same name and kind. The rest (a leg controller, reward terms of one's own, a history layout
    # object, observation statistics) reach the env alone.
    for key in list(options):
        if key in ENV_FLAT_PATHS:
            path = key
        elif key in _ENV_SECTIONS:
            path = f"env.{key}"
        elif (key in _TRANSFORM_SETTINGS or (key == "history" and isinstance(options[key], str))
              or (key == "reward_weights" and isinstance(options[key], dict)
                  and set(options[key]) <= set(_REWARD_WEIGHT_NAMES))):
            # Weights of terms the config names no weight for (heading, a term of one's own) reach the env alone.
            path = f"transforms.{key}"
        else:
            continue
        if key in task or path in task:
            given = task.get(key, task.get(path))
            raise ValueError(f"{key} given twice, {given!r} as a keyword and {options[key]!r} in env_options; "
                             "give it once")
        task[path] = options.pop(key)
    cfg = task_config(preset, num_envs=num_envs, device=str(dev), **task)
    env = _trainer_env(cfg, dev, num_envs=num_envs, for_training=for_training, **options)
    return env, cfg
