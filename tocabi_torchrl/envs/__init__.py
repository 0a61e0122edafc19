"""TorchRL environments of the TOCABI tasks."""

from .command import CommandConfig, VelocityCommand
from .config import CONTROL_MODES, ControlConfig, EnvSimConfig, TaskConfig, TocabiWalkConfig
from .autoreset import SyncFreeResetEnv
from .tocabi_walk import TocabiWalk

__all__ = ["TocabiWalk", "TocabiWalkConfig", "EnvSimConfig", "TaskConfig", "ControlConfig", "CommandConfig",
           "VelocityCommand", "CONTROL_MODES", "SyncFreeResetEnv"]
