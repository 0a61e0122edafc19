"""The batched step every adapter shares: a TorchRL env driven with plain tensors, resetting finished envs in the
same call (TorchRL's ``step_and_maybe_reset``), with the terminal observation kept apart.

Everything stays on the env's device; the adapters convert (or not) for their library.

The order of calls is checked here once for every adapter: a ``step`` before the first ``reset`` is
:class:`ResetNeededError` (gymnasium's ``ResetNeeded``: there is no observation the caller has acted on yet), unless
the adapter's library expects an env that is ready once built (rsl_rl); any call after ``close`` is
:class:`EnvClosedError` (the simulator is released).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from gymnasium.error import ClosedEnvironmentError, ResetNeeded
from tensordict import TensorDictBase
from torchrl.envs import EnvBase

__all__ = ["EnvClosedError", "ResetNeededError", "StepResult", "TensorStepper", "real_actions", "to_host"]


class ResetNeededError(ResetNeeded, RuntimeError):
    """``step`` before the first ``reset`` (gymnasium's ``ResetNeeded``, and a ``RuntimeError``)."""


class EnvClosedError(ClosedEnvironmentError, RuntimeError):
    """A call on an env after its ``close`` (gymnasium's ``ClosedEnvironmentError``, and a ``RuntimeError``)."""


def real_actions(actions) -> np.ndarray:
    """``actions`` (a numpy array or nested sequence, e.g. (num_envs, 13)) as a float32 array, or a ``TypeError``
    unless its values are real numbers (float, int or unsigned). A float32 conversion would drop a complex value's
    imaginary part with numpy's warning alone, read ``True`` as 1.0 (a full-scale action) and parse text such as
    ``"0.5"``: none of them is a policy output, so each adapter that takes host arrays refuses them here."""
    raw = np.asarray(actions)
    if raw.dtype.kind not in "fiu":
        raise TypeError(f"actions must be real numbers (float32), got an array of {raw.dtype}")
    return raw.astype(np.float32, copy=False)


#: Each tensor's bytes start at a multiple of this in :func:`to_host`'s buffer, so that every array viewing its span
#: is aligned for its dtype (8: the widest of float64, int64).
_HOST_ALIGN = 8


def to_host(*tensors: torch.Tensor) -> list[np.ndarray]:
    """Numpy arrays of ``tensors`` (all on one device, any shapes, dtypes numpy has) from one device->host copy.

    The tensors' bytes are packed into one uint8 tensor on their device and copied once; each array views its own span
    of that host buffer, with its tensor's shape and dtype. No value is cast on the way, so every array equals
    ``tensor.cpu().numpy()`` bit for bit (NaN payloads and -0.0 included). On a GPU that is one synchronisation
    where a copy per tensor would be one each. The arrays are fresh (never views of the env's tensors) and
    C-contiguous."""
    if not tensors:
        return []
    parts, spans, at = [], [], 0
    for t in tensors:
        raw = t.detach().contiguous().reshape(-1).view(torch.uint8)
        parts.append(raw)
        pad = -raw.numel() % _HOST_ALIGN
        if pad:
            parts.append(raw.new_zeros(pad))
        spans.append((at, raw.numel()))
        at += raw.numel() + pad
    host = torch.cat(parts).cpu().numpy()
    return [host[start:start + size].view(_numpy_dtype(t.dtype)).reshape(tuple(t.shape))
            for t, (start, size) in zip(tensors, spans)]


def _numpy_dtype(dtype: torch.dtype) -> np.dtype:
    return torch.empty(0, dtype=dtype).numpy().dtype


@dataclass
class StepResult:
    """One batched step, every tensor on the env's device.

    ``obs`` (num_envs, obs_dim): the observation to act on next (a reset one where the episode ended);
    ``final_obs`` (num_envs, obs_dim): the last observation of the episode that ended (rows where ``done``; the
    other rows equal ``obs``); ``reward`` (num_envs,) float32; ``terminated``/``truncated``/``done`` (num_envs,)
    bool, truncation (the episode's time limit) never overlapping termination (a fall); ``reward_terms``
    {name: (num_envs,)} the weighted reward terms summing to ``reward``; ``episode_return`` (num_envs,) and
    ``episode_length`` (num_envs,) int64: the return and length [policy steps] of the episode that ended (rows
    where ``done``; elsewhere the running values).
    """

    obs: torch.Tensor
    final_obs: torch.Tensor
    reward: torch.Tensor
    terminated: torch.Tensor
    truncated: torch.Tensor
    done: torch.Tensor
    reward_terms: dict[str, torch.Tensor]
    episode_return: torch.Tensor
    episode_length: torch.Tensor


class TensorStepper:
    """Drives a TorchRL env of the walking task (:func:`tocabi_torchrl.adapters._build.build_env`) with action
    tensors. ``reset()`` resets all envs; ``step(action)`` steps all and resets the finished ones at once.

    ``name``: the adapter's class, named in the errors. ``reset_on_first_use``: a ``step`` (or
    :attr:`observation`) before any ``reset()`` resets first, for a library whose env is ready once built (rsl_rl's
    ``VecEnv`` has no reset its runner calls); otherwise that ``step`` is a :class:`ResetNeededError`."""

    def __init__(self, env: EnvBase, obs_key: str = "observation", name: str = "env",
                 reset_on_first_use: bool = False):
        self.env = env
        self.name = name
        self.reset_on_first_use = bool(reset_on_first_use)
        #: Set by :meth:`close`; every later call is an :class:`EnvClosedError`.
        self.closed = False
        self.obs_key = obs_key
        self.num_envs = int(env.batch_size[0])
        self.device = env.device
        self.obs_dim = int(env.observation_spec[obs_key].shape[-1])
        self.action_dim = int(env.action_spec.shape[-1])
        self.term_names = [k[1] for k in env.observation_spec.keys(True, True)
                           if isinstance(k, tuple) and k[0] == "reward_terms"]
        self._td: TensorDictBase | None = None
        #: Called with no arguments after every step (the recipes' wall-clock checkpoints and time limit).
        self.step_hooks: list = []
        #: Env steps taken (num_envs per call), counted on the host.
        self.env_steps = 0

    def check_open(self, call: str) -> None:
        """:class:`EnvClosedError` naming ``call`` (e.g. ``"step()"``) if the env is closed."""
        if self.closed:
            raise EnvClosedError(f"{self.name}.{call} called after close(): the env is closed and its simulator "
                                 f"released; build a new {self.name} to go on")

    def check_ready(self, call: str = "step()") -> None:
        """What a step needs: an open env and, unless ``reset_on_first_use``, a ``reset()`` since it was built
        (:class:`ResetNeededError` otherwise). Adapters that check their actions before stepping call this first, so
        that a step out of order is reported as such, not as a bad action."""
        self.check_open(call)
        if self._td is None and not self.reset_on_first_use:
            raise ResetNeededError(f"{self.name}.{call} called before reset(): call reset() first (it returns the "
                                   "observation to choose the first actions from)")

    @property
    def observation(self) -> torch.Tensor:
        """(num_envs, obs_dim): the observation to act on next; with ``reset_on_first_use``, resets all envs on
        first use."""
        self.check_ready("observation")
        if self._td is None:
            self.reset()
        return self._td.get(self.obs_key)

    def reset(self, seed: int | None = None) -> torch.Tensor:
        """Reset every env (reseeding first when ``seed`` is given); returns the observation (num_envs, obs_dim)."""
        self.check_open("reset()")
        if seed is not None:
            # TocabiWalk restarts its episode numbering on set_seed, so reset(seed=s) repeats the same episodes, as
            # gymnasium expects of a seeded reset.
            self.env.set_seed(seed)  # the env's own check names a bool, a float or text (int() would take 1.9 as 1)
        self._td = self.env.reset()
        return self._td.get(self.obs_key)

    def check_action(self, action: torch.Tensor) -> torch.Tensor:
        """``action`` if it is (num_envs, action_dim), else a ``ValueError`` naming both shapes (every adapter's
        step goes through this, so each library's user gets the same message)."""
        if not isinstance(action, torch.Tensor):  # rsl_rl's and skrl's loops pass tensors; a numpy array lacks .detach
            raise TypeError(f"actions must be a torch.Tensor of shape ({self.num_envs}, {self.action_dim}), got "
                            f"{type(action).__name__}; wrap an array with torch.as_tensor(actions, device=env.device)")
        if tuple(action.shape) != (self.num_envs, self.action_dim):
            raise ValueError(f"actions must have shape ({self.num_envs}, {self.action_dim}) (num_envs, action_dim), "
                             f"got {tuple(action.shape)}")
        return action

    def check_finite(self, action: torch.Tensor) -> torch.Tensor:
        """``action`` (num_envs, action_dim) on the host if every value is finite, else a ``ValueError`` naming the env
        rows that hold NaN or ±inf. For actions already on the host (SB3's, gymnasium's numpy mode) only: on a GPU
        this read would synchronise every step, so device tensors are left to the env's rule (NaN acts as 0, ±inf
        is clipped to the action bounds)."""
        bad = (~torch.isfinite(action).all(dim=-1)).nonzero().flatten().tolist()
        if bad:
            rows = ", ".join(str(i) for i in bad[:10]) + (f", ... ({len(bad)} rows)" if len(bad) > 10 else "")
            raise ValueError(f"actions must be finite, but env rows [{rows}] hold NaN or inf (the env would act on NaN "
                             "as 0 and clip inf to the action bounds); fix the policy output that produced them")
        return action

    def step(self, action: torch.Tensor) -> StepResult:
        """Step every env with ``action`` (num_envs, action_dim) on the env's device, then reset finished envs.

        The action is detached: the env writes it into its own buffers, which must never join the caller's
        gradient graph (they would keep it alive and every later step would fail or leak)."""
        self.check_ready("step()")
        action = self.check_action(action).detach()
        if self._td is None:  # reset_on_first_use: the library's env is ready once built
            self.reset()
        td = self._td.set("action", action)
        td, self._td = self.env.step_and_maybe_reset(td)
        nxt = td.get("next")
        terminated = nxt.get("terminated").reshape(self.num_envs)
        truncated = nxt.get("truncated").reshape(self.num_envs)
        terms = nxt.get("reward_terms", None)
        self.env_steps += self.num_envs
        result = StepResult(
            obs=self._td.get(self.obs_key),
            final_obs=nxt.get(self.obs_key),
            reward=nxt.get("reward").reshape(self.num_envs),
            terminated=terminated,
            truncated=truncated & ~terminated,
            done=terminated | truncated,
            reward_terms={} if terms is None else {k: terms.get(k).reshape(self.num_envs) for k in self.term_names},
            episode_return=nxt.get("episode_reward").reshape(self.num_envs),
            episode_length=nxt.get("step_count").reshape(self.num_envs),
        )
        for hook in self.step_hooks:
            hook()
        return result

    def close(self) -> None:
        """Release the simulator; closing again does nothing, any other call then is an :class:`EnvClosedError`."""
        self.closed = True
        if not self.env.is_closed:
            self.env.close()
