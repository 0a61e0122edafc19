"""Stable-Baselines3's ``VecEnv`` (stable-baselines3 2.x) over the walking task: numpy arrays on the host.

SB3 runs its policy on numpy observations, so every step copies the observation (num_envs × 237 float32), the
rewards and the done flags (and the reward terms with ``reward_terms_in_infos``) from the env's device to the host,
packed into one transfer, and the actions back: on a GPU that is one synchronisation per step (the per-library
table states it). A step where episodes ended copies the last observation, return, length and truncation flag of
those envs alone in a second transfer. ``infos`` follow SB3's conventions:
``"terminal_observation"`` and ``"TimeLimit.truncated"`` for envs whose episode ended (SB3's PPO bootstraps the
truncated ones) and ``"episode"`` {``"r"``, ``"l"``, ``"t"``}, which SB3's logger reads (``rollout/ep_rew_mean``).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import torch

from ._versions import require

require("stable_baselines3")
from stable_baselines3.common.vec_env import VecEnv

from ._build import build_env
from ._core import TensorStepper, real_actions, to_host
from .spaces import box_from_spec

__all__ = ["TocabiSB3VecEnv"]


class TocabiSB3VecEnv(VecEnv):
    """The walking task as an SB3 ``VecEnv`` of ``num_envs`` robots simulated on ``device``.

    ``reward_terms_in_infos``: also put each env's weighted reward terms {name: float} in its info dict every step
    (off by default: num_envs dicts of 13 floats per step cost more than the step on a GPU).

    Actions are numpy on the host, so their values are checked there: a NaN or ±inf is a ``ValueError`` naming the
    env rows (not silently acted on as 0 or the bound), and an array of booleans, complex numbers or text a
    ``TypeError``, as ``TocabiVectorEnv.step`` has it. ``set_options`` is refused, as ``TocabiVectorEnv.reset``
    refuses options: the env's reset takes none.

    Each ended episode's info holds ``"episode": {"r", "l", "t"}``, as a ``Monitor`` would add: SB3's logger reads
    it without a ``VecMonitor`` (which would compute the same). ``evaluate_policy`` reads that key only under a
    ``Monitor``, which this env reports it is not (``env_is_wrapped``): it sums the rewards up to each done flag
    instead, the same episodes (every done is an episode's end); its warning that no ``Monitor`` wraps the env can
    be silenced with ``evaluate_policy(..., warn=False)``.

    Order of calls, as SB3's ``DummyVecEnv`` over gymnasium envs: ``step_async`` before the first ``reset`` is a
    ``gymnasium.error.ResetNeeded``, and ``step``/``reset`` after ``close`` a ``RuntimeError``.
    """

    def __init__(self, num_envs: int = 8, device: str | torch.device = "auto", preset: str = "default",
                 reward_terms_in_infos: bool = False, env_options: dict | None = None, **task):
        if not isinstance(reward_terms_in_infos, (bool, np.bool_)):  # bool("no") is True
            raise ValueError(f"reward_terms_in_infos must be True or False, got {reward_terms_in_infos!r}")
        env, self.task_config = build_env(num_envs, device, preset=preset, env_options=env_options, **task)
        self.stepper = TensorStepper(env, name=type(self).__name__)
        self.device = self.stepper.device
        self.reward_terms_in_infos = bool(reward_terms_in_infos)
        self.render_mode = None  # read by VecEnv.__init__
        super().__init__(self.stepper.num_envs, box_from_spec(env.observation_spec["observation"], batched=False),
                         box_from_spec(env.action_spec, batched=False))
        self._actions: torch.Tensor | None = None
        self._start = time.time()

    def reset(self) -> np.ndarray:
        seed = next((s for s in self._seeds if s is not None), None)  # set by VecEnv.seed(); envs share one seed
        obs = self.stepper.reset(seed)
        self._reset_seeds()
        self._reset_options()
        return obs.cpu().numpy()

    def set_options(self, options: list[dict] | dict | None = None) -> None:
        # SB3 would hand them to the next reset, which has no use for them: refused here rather than dropped there.
        given = [options] if isinstance(options, dict) else list(options or [])
        if any(given):
            raise ValueError(f"TocabiSB3VecEnv.reset takes no options, got {options!r}; configure the task when "
                             "building the env (preset, env_options or task fields such as max_episode_steps=...)")
        super().set_options(options)

    def step_async(self, actions: np.ndarray) -> None:
        # Checked here, not at step_wait, so the error points at the call that passed the actions.
        self.stepper.check_ready("step_async()")
        host = self.stepper.check_action(torch.as_tensor(real_actions(actions)))
        self._actions = self.stepper.check_finite(host).to(self.device)

    def step_wait(self):
        self.stepper.check_open("step_wait()")
        if self._actions is None:
            raise RuntimeError("step_wait() called without step_async(actions)")
        r = self.stepper.step(self._actions)
        self._actions = None
        terms = list(r.reward_terms.items()) if self.reward_terms_in_infos else []
        # One device->host copy for what every step returns (a copy per array was one synchronisation each on a GPU).
        obs, reward, done, *term_values = to_host(r.obs, r.reward, r.done, *(v for _, v in terms))
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        if terms:
            for i, info in enumerate(infos):
                info["reward_terms"] = {k: float(v[i]) for (k, _), v in zip(terms, term_values)}
        ended = np.flatnonzero(done)
        if ended.size:
            # A second copy only on a step where episodes ended, of those envs' rows alone: their index is on the
            # host already, so selecting them on the device reads nothing back.
            rows = torch.as_tensor(ended, device=self.device)
            final_obs, truncated, ret, length = to_host(r.final_obs[rows], r.truncated[rows], r.episode_return[rows],
                                                        r.episode_length[rows])
            elapsed = round(time.time() - self._start, 6)
            for j, i in enumerate(ended):
                infos[i]["terminal_observation"] = final_obs[j]
                infos[i]["TimeLimit.truncated"] = bool(truncated[j])
                infos[i]["episode"] = {"r": float(ret[j]), "l": int(length[j]), "t": elapsed}
        return obs, reward, done, infos

    def close(self) -> None:
        self._actions = None
        self.stepper.close()

    # The single-process VecEnv API: one batched simulator, so attributes are the same for every env index.
    def _indices_list(self, indices) -> list[int]:
        if indices is None:
            return list(range(self.num_envs))
        return [indices] if isinstance(indices, int) else list(indices)

    def _all_indices(self, indices, what: str) -> list[int]:
        """The indices, refused unless they are every env: a set or a call acts on the one batched simulator."""
        chosen = self._indices_list(indices)
        if sorted(int(i) for i in chosen) != list(range(self.num_envs)):
            raise ValueError(f"{what} with indices={indices!r}: TocabiSB3VecEnv is one batched simulator, so an "
                             f"attribute or method acts on all {self.num_envs} envs at once; call it without indices")
        return chosen

    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        value = getattr(self, attr_name)
        return [value for _ in self._indices_list(indices)]

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        self._all_indices(indices, f"set_attr({attr_name!r})")
        setattr(self, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list[Any]:
        chosen = self._all_indices(indices, f"env_method({method_name!r})")
        result = getattr(self, method_name)(*method_args, **method_kwargs)
        return [result for _ in chosen]

    def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
        return [False for _ in self._indices_list(indices)]

    def get_images(self):
        raise NotImplementedError("TocabiSB3VecEnv does not render; use recipes/play.py for a video")
