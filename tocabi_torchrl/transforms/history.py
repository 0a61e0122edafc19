"""Observation + action history: the policy input built from the last K observations and M past actions.

Time convention: ``obs_τ`` is the observation after policy step τ (``obs_0`` after reset) and ``a_τ`` the action
applied in step τ (``next["applied_action"]``, so ``a_0`` is the reset value, zeros). A :class:`HistoryLayout`
selects observations ``obs_{τ - s·(K-1)}, …, obs_{τ - s}, obs_τ`` and actions
``a_{τ+1 - s·M}, …, a_{τ+1 - s}``: action slot j holds the action the policy chose from the observation
``s·(M - j)`` steps back, so each stored action is paired with an older stored observation. Layout of the output:
all observations oldest → newest, then all actions oldest → newest.

* Reference (spec §7.4, :data:`REFERENCE_HISTORY`, K=5, s=2, M=4): obs after τ−8, τ−6, τ−4, τ−2, τ and actions
  a_{τ−7}, a_{τ−5}, a_{τ−3}, a_{τ−1}; the action just applied (a_τ) is not included. 5·37 + 4·13 = 237 values.
* TocabiLab consecutive (:data:`TOCABILAB_HISTORY`, K=5, s=1, M=4): obs after τ−4 … τ and the last four applied
  actions a_{τ−3} … a_τ (the "5 observations + 4 previous actions" of the TocabiLab report). Also 237 values.

On reset, flagged envs have their whole history refilled with their first observation and their reset action, as
the reference does; other envs are untouched. The buffers are rings with one shared write position (all envs step
together), updated with ``torch.where`` and precomputed index tensors, so neither step nor reset reads device values
on the host.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

from tocabi_torchrl.transforms._base import check_specs_once
from tocabi_torchrl.transforms._checks import require_spec
# The layout is config (it lives in a module without torch, for the config tree); this path names it too.
from tocabi_torchrl.transforms.layouts import REFERENCE_HISTORY, TOCABILAB_HISTORY, HistoryLayout

__all__ = ["HistoryLayout", "REFERENCE_HISTORY", "TOCABILAB_HISTORY", "ObsActionHistory"]


class _Ring:
    """(…, L, D) history ordered newest first: slot ``k`` holds the entry from ``k`` steps ago.

    A push shifts every slot by one and writes slot 0. The positions read are fixed (the layout's ages), so no
    host-side write position changes from step to step: the same launches are valid on every step, which lets a
    captured CUDA graph of the env step replay them (a moving host index would be frozen at its capture value).
    Shifting costs one copy of a (num_envs, L, D) buffer per step (a few MB at 4096 envs).
    """

    def __init__(self, first: torch.Tensor, ages: tuple[int, ...]):
        self.length = max(ages) + 1
        self.buf = first.unsqueeze(-2).expand(*first.shape[:-1], self.length, first.shape[-1]).clone()
        # The layout lists ages oldest first, so reading them in order gives the output oldest first.
        self.index = torch.tensor(list(ages), dtype=torch.long, device=first.device)

    def matches(self, x: torch.Tensor) -> bool:
        return self.buf.shape[:-2] == x.shape[:-1] and self.buf.shape[-1] == x.shape[-1] and self.buf.device == x.device

    def push(self, x: torch.Tensor) -> None:
        self.buf.copy_(torch.roll(self.buf, 1, dims=-2))
        self.buf.select(-2, 0).copy_(x)

    def refill(self, x: torch.Tensor, mask: torch.Tensor) -> None:
        """Rows where ``mask`` (…, 1, 1) is True get every slot set to ``x`` (…, D); other rows keep theirs."""
        torch.where(mask, x.unsqueeze(-2), self.buf, out=self.buf)

    def read(self) -> torch.Tensor:
        """(…, n·D): the entries at the layout's ages, oldest first."""
        return torch.index_select(self.buf, -2, self.index).flatten(-2)


class ObsActionHistory(Transform):
    """Stack the last observations and actions of a :class:`HistoryLayout` into the policy input.

    Reads ``obs_key`` (num_envs, D) and ``action_key`` (num_envs, A) at reset and at every step; writes ``out_key``
    (num_envs, K·D + M·A) float32. On reset it reads ``reset_key`` (num_envs, 1) bool from the reset input (absent:
    every env resets) and refills only the flagged envs' history. Stateful: one instance per env.

    Args:
        layout: K, stride and M (default :data:`REFERENCE_HISTORY`).
        obs_key: per-step observation, normally the normalised one.
        action_key: raw action applied in the step (the reference stores raw clipped actions).
        out_key: the policy input key.
        reset_key: TorchRL's partial-reset mask key.
    """

    def __init__(
        self,
        layout: HistoryLayout = REFERENCE_HISTORY,
        obs_key: NestedKey = "obs_step_norm",
        action_key: NestedKey = "applied_action",
        out_key: NestedKey = "observation",
        reset_key: NestedKey = "_reset",
    ):
        if not isinstance(layout, HistoryLayout):
            raise TypeError(f"ObsActionHistory layout must be a HistoryLayout, got {layout!r}")
        in_keys = [obs_key, action_key] if layout.num_actions else [obs_key]
        super().__init__(in_keys=in_keys, out_keys=[out_key])
        self.layout = layout
        self.obs_key, self.action_key, self.reset_key = obs_key, action_key, reset_key
        self._obs: _Ring | None = None
        self._act: _Ring | None = None

    def _inputs(self, td: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor | None]:
        obs = td.get(self.obs_key).to(torch.float32)
        act = td.get(self.action_key).to(torch.float32) if self.layout.num_actions else None
        return obs, act

    def _output(self) -> torch.Tensor:
        parts = [self._obs.read()]
        if self._act is not None:
            parts.append(self._act.read())
        return torch.cat(parts, dim=-1)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        check_specs_once(self)
        obs, act = self._inputs(tensordict_reset)
        fresh = self._obs is None or not self._obs.matches(obs)
        fresh = fresh or (act is not None and (self._act is None or not self._act.matches(act)))
        if fresh:
            # No usable history yet (first reset, or new batch size/device): every env starts from this observation.
            self._obs = _Ring(obs, self.layout.obs_ages)
            self._act = _Ring(act, self.layout.action_ages) if act is not None else None
        else:
            reset = tensordict.get(self.reset_key, None) if tensordict is not None else None
            if reset is None:
                mask = torch.ones((*obs.shape[:-1], 1, 1), dtype=torch.bool, device=obs.device)
            else:
                mask = reset.reshape(*obs.shape[:-1], 1, 1)
            self._obs.refill(obs, mask)
            if self._act is not None:
                self._act.refill(act, mask)
        tensordict_reset.set(self.out_keys[0], self._output())
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        if self._obs is None:
            raise RuntimeError("ObsActionHistory has no history yet: call env.reset() before env.step()")
        obs, act = self._inputs(next_tensordict)
        if not self._obs.matches(obs):
            raise RuntimeError(
                f"ObsActionHistory: {self.obs_key!r} has shape {tuple(obs.shape)} on {obs.device} but the history "
                f"holds {tuple(self._obs.buf.shape[:-2])} x {self._obs.buf.shape[-1]} on {self._obs.buf.device}; "
                "call env.reset() after changing the batch size or device"
            )
        self._obs.push(obs)
        if self._act is not None:
            self._act.push(act)
        next_tensordict.set(self.out_keys[0], self._output())
        return next_tensordict

    def clone(self) -> ObsActionHistory:
        """A copy with no history yet: its first reset fills its own buffers."""
        copy = super().clone()
        # torchrl's clone is shallow: the copy shared these rings, whose buffers are written in place, so a second
        # env's resets and steps rewrote the first env's history.
        copy._obs = copy._act = None
        return copy

    def __repr__(self) -> str:
        lay = self.layout
        return (
            f"{type(self).__name__}(num_obs={lay.num_obs}, stride={lay.stride}, num_actions={lay.num_actions}, "
            f"obs_key={self.obs_key!r}, action_key={self.action_key!r}, out_key={self.out_keys[0]!r})"
        )

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        obs_spec = require_spec(observation_spec, self.obs_key, self)
        if len(obs_spec.shape) != len(observation_spec.shape) + 1:
            raise ValueError(
                f"ObsActionHistory expects {self.obs_key!r} of shape (num_envs, D), got {tuple(obs_spec.shape)}; "
                "flatten it first (e.g. with ObservationAssembly)"
            )
        action_dim = 0
        if self.layout.num_actions:
            act_spec = require_spec(observation_spec, self.action_key, self)
            if len(act_spec.shape) != len(observation_spec.shape) + 1:
                raise ValueError(
                    f"ObsActionHistory expects {self.action_key!r} of shape (num_envs, A), got {tuple(act_spec.shape)}"
                )
            action_dim = act_spec.shape[-1]
        size = self.layout.size(obs_spec.shape[-1], action_dim)
        observation_spec[self.out_keys[0]] = Unbounded(
            shape=(*observation_spec.shape, size), dtype=torch.float32, device=observation_spec.device
        )
        return observation_spec
