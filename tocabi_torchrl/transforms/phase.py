"""Phase encoding: sin/cos harmonics of the env's gait phase, written under named keys."""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Bounded, Composite

from tocabi_torchrl.transforms._base import CallOnReset
from tocabi_torchrl.transforms._checks import check_positive_int, require_spec

__all__ = ["PhaseEncoding"]


class PhaseEncoding(CallOnReset):
    """Encode the gait phase as sin(2π·k·phase), cos(2π·k·phase) for k = 1..harmonics.

    Reads ``in_key`` (num_envs, 1), the observation phase in [0, 1) (spec §3.2, post-step time).
    Writes ``out_keys[0]`` (num_envs, harmonics) sines and ``out_keys[1]`` (num_envs, harmonics) cosines, float32,
    column k-1 holding harmonic k. With ``harmonics=1`` these are the reference observation entries 27 and 28.

    Args:
        in_key: phase key.
        out_keys: (sin key, cos key).
        harmonics: number of harmonics (>= 1).
    """

    def __init__(
        self,
        in_key: NestedKey = "phase",
        out_keys: tuple[NestedKey, NestedKey] = ("phase_sin", "phase_cos"),
        harmonics: int = 1,
    ):
        harmonics = check_positive_int(harmonics, "PhaseEncoding harmonics",
                                       "use harmonics=1 for the reference sin/cos pair")
        # A str is refused, not split: "sc" would have passed the length check as the keys 's' and 'c'.
        if isinstance(out_keys, str) or not isinstance(out_keys, (tuple, list)) or len(out_keys) != 2:
            raise ValueError(f"PhaseEncoding needs two out_keys (sin key, cos key), e.g. ('phase_sin', 'phase_cos'), "
                             f"got {out_keys!r}")
        super().__init__(in_keys=[in_key], out_keys=list(out_keys))
        self.harmonics = harmonics
        # A buffer so that TransformedEnv moves it to the env's device once, instead of a copy every step.
        self.register_buffer("_angular_freq", 2.0 * math.pi * torch.arange(1, harmonics + 1, dtype=torch.float32))

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        phase = next_tensordict.get(self.in_keys[0])
        angle = phase.to(torch.float32) * self._angular_freq.to(phase.device)
        next_tensordict.set(self.out_keys[0], torch.sin(angle))
        next_tensordict.set(self.out_keys[1], torch.cos(angle))
        return next_tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Apply to stored data (e.g. a replay buffer sample), any batch shape."""
        return self._call(tensordict)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        spec = require_spec(observation_spec, self.in_keys[0], self, last_dim=1)
        for key in self.out_keys:
            observation_spec[key] = Bounded(
                low=-1.0,
                high=1.0,
                shape=(*spec.shape[:-1], self.harmonics),
                dtype=torch.float32,
                device=observation_spec.device,
            )
        return observation_spec
