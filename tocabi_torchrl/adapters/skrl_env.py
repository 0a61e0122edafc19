"""skrl's environment ``Wrapper`` (skrl 2.x, torch) over the walking task: tensors on the env's device.

skrl was chosen over rl_games as the fourth library: it is pure PyTorch on gymnasium spaces and takes device tensors
straight from the env (rl_games still builds on the unmaintained ``gym`` package and its own env registry, and
pins old dependencies), and it is the other library Isaac Lab ships recipes for besides rsl_rl and SB3.
"""

from __future__ import annotations

from typing import Any

import torch

from ._versions import require

require("skrl")
from skrl.envs.wrappers.torch.base import Wrapper

from ._build import build_env
from ._core import TensorStepper
from .spaces import box_from_spec

__all__ = ["TocabiSkrlEnv"]


class TocabiSkrlEnv(Wrapper):
    """The walking task as an skrl env of ``num_envs`` robots on ``device`` (vectorised, autoresetting).

    ``step(actions)`` takes (num_envs, 13) on ``device`` and returns ``(obs, reward, terminated, truncated,
    infos)``: ``obs`` (num_envs, 237), the other three (num_envs, 1) (skrl's layout); finished envs are already
    reset, their last observation is ``infos["final_obs"]``; ``infos["log"]`` holds the mean of each weighted
    reward term as a scalar tensor (``"Reward / <term>"``). skrl's trainer logs it with
    ``cfg={"environment_info": "log"}``, reading each value on the host every step (13 synchronisations per step on
    a GPU), so it is not under skrl's default key ``"episode"``.

    ``reset()`` comes first, as skrl's trainers call it: ``step`` before it is a ``gymnasium.error.ResetNeeded``, and
    ``step``/``reset`` after ``close`` a ``RuntimeError``.
    """

    def __init__(self, num_envs: int = 4096, device: str | torch.device = "auto", preset: str = "default",
                 env_options: dict | None = None, **task):
        env, self.task_config = build_env(num_envs, device, preset=preset, env_options=env_options, **task)
        self.stepper = TensorStepper(env, name=type(self).__name__)
        super().__init__(env)
        self._device = self.stepper.device  # skrl's base reads `device` from the env; keep ours explicit
        self._observation_space = box_from_spec(env.observation_spec["observation"], batched=False)
        self._action_space = box_from_spec(env.action_spec, batched=False)

    @property
    def num_envs(self) -> int:
        return self.stepper.num_envs

    @property
    def observation_space(self):
        return self._observation_space

    @property
    def action_space(self):
        return self._action_space

    @property
    def state_space(self):
        return None

    def reset(self) -> tuple[torch.Tensor, dict[str, Any]]:
        # skrl resets once at the start; the env resets finished episodes itself after that.
        return self.stepper.reset(), {}

    def step(self, actions: torch.Tensor):
        r = self.stepper.step(actions)
        infos = {"final_obs": r.final_obs, "_final_obs": r.done,
                 "log": {f"Reward / {k}": v.mean() for k, v in r.reward_terms.items()}}
        return (r.obs, r.reward.unsqueeze(-1), r.terminated.unsqueeze(-1), r.truncated.unsqueeze(-1), infos)

    def state(self) -> None:
        return None

    def render(self, *args, **kwargs) -> None:
        return None

    def close(self) -> None:
        self.stepper.close()
