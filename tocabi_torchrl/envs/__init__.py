"""TorchRL environments of the TOCABI tasks."""

from .._lazy import lazy_names

__all__ = ["TocabiWalk", "TocabiWalkConfig", "EnvSimConfig", "TaskConfig", "ControlConfig", "CommandConfig",
           "VelocityCommand", "CONTROL_MODES", "SyncFreeResetEnv"]

# Each name loads its submodule when first read: importing any submodule (a config dataclass for the run config
# tree and --help) runs this file first, and must not load the torch, torchrl and mujoco-warp code of the others.
__getattr__, __dir__ = lazy_names(globals(), {
    "command_config": ("CommandConfig",),
    "command": ("VelocityCommand",),
    "config": ("CONTROL_MODES", "ControlConfig", "EnvSimConfig", "TaskConfig", "TocabiWalkConfig"),
    "autoreset": ("SyncFreeResetEnv",),
    "tocabi_walk": ("TocabiWalk",),
})
