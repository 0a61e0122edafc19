"""PPO for TOCABI: actors (scheduled or learned std), critic, training loop, checkpoints, evaluation."""

from .actors import GaussianHead, action_std, make_actor, set_action_std
from .config import PRESETS, PPOConfig, RunConfig, parse_args, preset_config
from .std_schedule import StdSchedule

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
