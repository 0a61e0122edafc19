"""TorchRL environments of the TOCABI tasks."""

from .command import CommandConfig, VelocityCommand
from .config import CONTROL_MODES, TocabiWalkConfig
from .autoreset import SyncFreeResetEnv
from .tocabi_walk import TocabiWalk

__all__ = ["TocabiWalk", "TocabiWalkConfig", "CommandConfig", "VelocityCommand", "CONTROL_MODES", "SyncFreeResetEnv"]
