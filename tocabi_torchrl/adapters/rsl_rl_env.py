"""rsl_rl's ``VecEnv`` (rsl-rl-lib 5.x) over the walking task: tensors stay on the env's device, zero-copy.

rsl_rl 5 reads observations as a ``TensorDict`` of groups and maps them to the actor and critic through the
runner's ``obs_groups``; this env returns ``"policy"`` (the 237-value observation) and ``"critic"`` (the same tensor,
not a copy), so the default ``obs_groups={"actor": ["policy"], "critic": ["critic"]}`` works unchanged.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict

from ._versions import require

require("rsl_rl")
from rsl_rl.env import VecEnv

from ._build import build_env
from ._core import TensorStepper

__all__ = ["TocabiRslRlEnv"]


class TocabiRslRlEnv(VecEnv):
    """The walking task as an rsl_rl ``VecEnv`` of ``num_envs`` robots on ``device``.

    ``step(actions)`` takes (num_envs, 13) on ``device`` and returns ``(obs, rewards, dones, extras)``: ``obs`` a
    TensorDict {``"policy"``, ``"critic"``: (num_envs, 237)}, ``rewards`` (num_envs,) float32, ``dones`` (num_envs,)
    long (an env whose episode ended is already reset, as rsl_rl expects), ``extras["time_outs"]`` (num_envs,) bool:
    the episode hit its time limit (rsl_rl bootstraps those), and ``extras["log"]`` the mean of each weighted reward
    term (``"/reward/<term>"``), scalars on the device (rsl_rl's logger reads them once per iteration).

    rsl_rl's runner never calls ``reset()``: the env is ready once built, as its ``VecEnv`` expects, and resets all
    envs at the first ``get_observations()`` or ``step``. Any call after ``close`` is a ``RuntimeError``.
    """

    def __init__(self, num_envs: int = 4096, device: str | torch.device = "auto", preset: str = "default",
                 env_options: dict | None = None, **task):
        env, self.task_config = build_env(num_envs, device, preset=preset, env_options=env_options, **task)
        # rsl_rl's VecEnv is ready once built (its runner starts with get_observations, never reset).
        self.stepper = TensorStepper(env, name=type(self).__name__, reset_on_first_use=True)
        self.num_envs = self.stepper.num_envs
        self.num_actions = self.stepper.action_dim
        self.device = self.stepper.device
        self.max_episode_length = int(self.task_config.env.task.max_episode_steps)
        self.cfg = {"preset": preset, "num_envs": self.num_envs, "device": str(self.device),
                    "task": self.task_config.to_dict()}

    @property
    def episode_length_buf(self) -> torch.Tensor:
        """(num_envs,) int64: policy steps of each env's current episode (the env's own counter)."""
        return self.stepper.env.base_env.episode_step

    @episode_length_buf.setter
    def episode_length_buf(self, value) -> None:
        raise NotImplementedError(
            "TocabiRslRlEnv does not randomise episode lengths: call runner.learn(..., init_at_random_ep_len=False) "
            "(each episode already starts at a random row of the reference walk)")

    def _groups(self, obs: torch.Tensor) -> TensorDict:
        return TensorDict({"policy": obs, "critic": obs}, batch_size=[self.num_envs], device=self.device)

    def get_observations(self) -> TensorDict:
        self.stepper.check_open("get_observations()")
        return self._groups(self.stepper.observation)

    def reset(self) -> tuple[TensorDict, dict]:
        """Reset every env; returns the observation groups and empty extras."""
        return self._groups(self.stepper.reset()), {}

    def step(self, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict]:
        r = self.stepper.step(actions)
        log = {f"/reward/{k}": v.mean() for k, v in r.reward_terms.items()}
        extras = {"time_outs": r.truncated, "log": log}
        return self._groups(r.obs), r.reward, r.done.long(), extras

    def close(self) -> None:
        self.stepper.close()
