"""A ``gymnasium.vector.VectorEnv`` over the walking task (gymnasium 1.x), registered as ``TocabiWalk-v0``.

    import gymnasium, tocabi_torchrl.adapters
    envs = gymnasium.make_vec("TocabiWalk-v0", num_envs=4096, device="cuda")

Autoreset mode: ``AutoresetMode.SAME_STEP`` (``metadata["autoreset_mode"]``). An env whose episode ends in a
``step`` is reset inside that same call: the returned observation is the reset one, and the episode's last
observation is in ``infos["final_obs"]`` (rows flagged by ``infos["_final_obs"]``). That is TorchRL's
``step_and_maybe_reset``, so no step is spent on a dummy transition.

Devices: by default every array stays a torch tensor on the env's device. In numpy mode (``numpy=True``) a step
copies what it returns to the host packed into one transfer (the observation, reward, termination and truncation
flags, every reward term (the reference's 13; the robust preset adds two), the done flags and the episode
statistics): on a GPU that is one synchronisation per step.
A step where episodes ended copies those envs' last observations alone in a second transfer; the other rows of
``infos["final_obs"]`` are the observation's (their episodes go on).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from gymnasium.vector import AutoresetMode, VectorEnv

from ._build import build_env
from ._core import StepResult, TensorStepper, real_actions, to_host
from .spaces import box_from_spec

__all__ = ["TocabiVectorEnv", "make_vector_env"]


class TocabiVectorEnv(VectorEnv):
    """The walking task as a gymnasium vector env of ``num_envs`` robots on ``device``.

    Args:
        num_envs: robots simulated at once.
        device: ``"cpu"``, ``"cuda"``, ``"cuda:K"`` or ``"auto"``.
        numpy: return numpy arrays on the host (for numpy-based libraries and gymnasium's checks); by default
            every returned array is a torch tensor on ``device``. The mode sets what ``step`` and ``reset`` return,
            not what ``step`` takes: both modes take the same actions and check them alike (below).
        preset: the task preset (control mode, gains, commands, rewards) of
            :data:`tocabi_torchrl.rl.config.PRESETS`; ``task``: single fields of it (e.g. ``seed=1``).
        episode_statistics: fill ``infos["episode"]``/``["_episode"]`` (below) from the env's own counters, on
            ``device``. Pass ``False`` to wrap the env in gymnasium's ``RecordEpisodeStatistics`` instead (numpy mode),
            which refuses to overwrite those keys.

    ``step`` returns ``obs`` (num_envs, 237) float32, ``reward`` (num_envs,) float32, ``terminated`` and
    ``truncated`` (num_envs,) bool (a fall vs. the episode time limit; never both), and ``infos`` with:
    ``"reward_terms"`` {name: (num_envs,)} the 13 weighted terms summing to the reward; ``"final_obs"`` and
    ``"_final_obs"`` (see the module docstring); with ``episode_statistics``, ``"episode"`` {``"r"``: return,
    ``"l"``: length [steps]} (num_envs,) for the envs whose episode ended, flagged by ``"_episode"`` (the layout of
    gymnasium's ``RecordEpisodeStatistics``, without its ``"t"``).

    Order of calls, as gymnasium's envs: ``step`` before the first ``reset`` is a ``gymnasium.error.ResetNeeded``,
    and ``step`` or ``reset`` after ``close`` a ``RuntimeError`` (gymnasium's ``ClosedEnvironmentError`` too).

    Actions, in either mode: (num_envs, 13) real numbers, as a numpy array (or nested sequence) or a torch tensor
    on the host or on ``device``, cast to float32 and detached. A wrong shape is a ``ValueError``; booleans, complex
    numbers or text a ``TypeError`` (a float32 cast would read ``True`` as 1.0). Actions on the host (an array, a
    sequence or a CPU tensor) have their values checked there, which costs no synchronisation: a NaN or ±inf is a
    ``ValueError`` naming the env rows. A tensor on a GPU is not read (that would synchronise every step): there NaN
    acts as 0 and ±inf is clipped to the action bounds.
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(self, num_envs: int = 4096, device: str | torch.device = "auto", numpy: bool = False,
                 preset: str = "default", env_options: dict | None = None, episode_statistics: bool = True, **task):
        for name, value in (("numpy", numpy), ("episode_statistics", episode_statistics)):
            if not isinstance(value, (bool, np.bool_)):  # bool("no") is True
                raise ValueError(f"{name} must be True or False, got {value!r}")  # noqa: TRY004 (an option value)
        env, self.task_config = build_env(num_envs, device, preset=preset, env_options=env_options, **task)
        self.stepper = TensorStepper(env, name=type(self).__name__)
        self.num_envs = self.stepper.num_envs
        self.device = self.stepper.device
        self.numpy = bool(numpy)
        self.episode_statistics = bool(episode_statistics)
        self.single_observation_space = box_from_spec(env.observation_spec["observation"], batched=False)
        self.single_action_space = box_from_spec(env.action_spec, batched=False)
        self.observation_space = box_from_spec(env.observation_spec["observation"], batched=True)
        self.action_space = box_from_spec(env.action_spec, batched=True)
        self.render_mode = None
        self.closed = False

    @property
    def torchrl_env(self):
        """The wrapped TorchRL env."""
        return self.stepper.env

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Reset every env (``seed``: reseed first; an int, or a list whose first entry is used: the envs share
        one generator and draw their episodes from (seed, env index)). Returns ``(obs, infos)``."""
        if options:
            raise ValueError(f"TocabiVectorEnv.reset takes no options, got {sorted(options)}")
        if isinstance(seed, (list, tuple)):
            if not seed:
                raise ValueError("TocabiVectorEnv.reset: seed is an empty list; pass an int (or a list of them)")
            seed = seed[0]
        obs = self.stepper.reset(seed)
        if seed is not None:  # gymnasium's own generator (np_random) too, as VectorEnv.reset(seed=...) seeds it
            super().reset(seed=int(seed))  # checked by the env already: an integer, numpy's too
        return self._out(obs), {}

    def step(self, actions):
        """Step every env with ``actions`` (num_envs, 13): an array or a tensor, in either mode; see the class
        docstring. Returns ``(obs, reward, terminated, truncated, infos)``."""
        self.stepper.check_ready("step()")  # before the actions: a step out of order is no bad action
        if not isinstance(actions, torch.Tensor):
            actions = real_actions(actions)
        elif actions.is_complex() or actions.dtype == torch.bool:
            raise TypeError(f"actions must be real numbers (float32), got a tensor of {actions.dtype}")
        actions = torch.as_tensor(actions, dtype=torch.float32)
        # On the host already, whatever the mode: reading the values costs no synchronisation.
        if actions.device.type == "cpu":
            self.stepper.check_finite(self.stepper.check_action(actions))
        r = self.stepper.step(actions.to(self.device))
        return self._host_step(r) if self.numpy else self._device_step(r)

    def _episode(self, r: StepResult) -> dict[str, torch.Tensor]:
        # 0 where no episode ended, as RecordEpisodeStatistics has it (the running values once sat there, and a mean
        # over the rows logged partial returns). The key is there every step: leaving it out of steps with no ended
        # episode would read the device.
        return {"r": torch.where(r.done, r.episode_return, 0.0), "l": torch.where(r.done, r.episode_length, 0)}

    def _device_step(self, r: StepResult) -> tuple:
        """``step``'s results as tensors on the env's device (fresh each step, never views of the env's state)."""
        infos = {"reward_terms": dict(r.reward_terms), "final_obs": r.final_obs, "_final_obs": r.done}
        if self.episode_statistics:
            infos["episode"], infos["_episode"] = self._episode(r), r.done
        return r.obs, r.reward, r.terminated, r.truncated, infos

    def _host_step(self, r: StepResult) -> tuple:
        """``step``'s results as numpy arrays, equal bit for bit to each tensor's own ``.cpu().numpy()``, from one
        device->host copy, and a second one of the ended envs' last observations on a step where episodes ended (a
        copy per array was one synchronisation each on a GPU, some 20 a step)."""
        names = list(r.reward_terms)
        episode = list(self._episode(r).values()) if self.episode_statistics else []
        obs, reward, terminated, truncated, done, *rest = to_host(
            r.obs, r.reward, r.terminated, r.truncated, r.done, *r.reward_terms.values(), *episode)
        terms, episode = rest[:len(names)], rest[len(names):]
        # Where no episode ended, the last observation is the one to act on: TorchRL's partial reset keeps those
        # rows as they were (``step_and_maybe_reset``), so only the ended rows need reading.
        final_obs = obs.copy()
        ended = np.flatnonzero(done)
        if ended.size:
            # Their index is on the host already, so selecting them on the device reads nothing back.
            rows = torch.as_tensor(ended, device=self.device)
            final_obs[ended] = to_host(r.final_obs[rows])[0]
        infos = {"reward_terms": dict(zip(names, terms)), "final_obs": final_obs, "_final_obs": done}
        if self.episode_statistics:
            infos["episode"], infos["_episode"] = dict(zip(("r", "l"), episode)), done
        return obs, reward, terminated, truncated, infos

    def _out(self, x: torch.Tensor):
        # Fresh tensors from the env each step (never views of its state), so handing them out is safe.
        return x.cpu().numpy() if self.numpy else x

    def close_extras(self, **kwargs) -> None:
        self.stepper.close()


def make_vector_env(num_envs: int = 4096, **kwargs) -> TocabiVectorEnv:
    """gymnasium's ``vector_entry_point`` for ``TocabiWalk-v0``; ``kwargs`` go to :class:`TocabiVectorEnv`."""
    render_mode = kwargs.pop("render_mode", None)
    if render_mode is not None:  # said, not dropped: nothing would render
        raise ValueError(f"TocabiWalk-v0 does not render (render_mode={render_mode!r}); leave render_mode unset and "
                         "record videos with recipes/play.py")
    kwargs.pop("vectorization_mode", None)
    return TocabiVectorEnv(num_envs=num_envs, **kwargs)


def single_env_entry_point(**kwargs):
    """``TocabiWalk-v0``'s ``entry_point``: there is no single env, so ``gymnasium.make`` or
    ``make_vec(..., vectorization_mode="sync"/"async")`` end with an error saying what to call instead."""
    raise ValueError("TocabiWalk-v0 is a batched env simulating all its robots at once: use "
                     "gymnasium.make_vec('TocabiWalk-v0', num_envs=N) (its vector entry point), not gymnasium.make "
                     "or vectorization_mode='sync'/'async'")

