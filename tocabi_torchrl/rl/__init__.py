"""PPO for TOCABI: actors (scheduled or learned std), critic, training loop, checkpoints, run folders, logging (the
gait tests are :mod:`tocabi_torchrl.evaluation`'s)."""

from .._lazy import lazy_names

__all__ = [
    "GaussianHead",
    "make_actor",
    "set_action_std",
    "action_std",
    "PPOConfig",
    "RunConfig",
    "PRESETS",
    "preset_config",
    "parse_args",
    "StdSchedule",
]

# Each name loads its submodule when first read: importing any submodule (a config dataclass for the run config
# tree and --help) runs this file first, and must not load the torch, torchrl and mujoco-warp code of the others.
__getattr__, __dir__ = lazy_names(globals(), {
    "actors": ("GaussianHead", "action_std", "make_actor", "set_action_std"),
    "config": ("PRESETS", "PPOConfig", "RunConfig", "parse_args", "preset_config"),
    "std_schedule": ("StdSchedule",),
})
