"""Observation assembly: concatenate named env signals into the per-step observation vector (spec §7.1).

A layout is a tuple of :class:`ObsComponent`, each naming a key and the part of it to take. The reference layout
gives the 37 values in the reference order; a researcher changes the observation by passing another tuple.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Composite, Unbounded

from tocabi_torchrl.transforms._base import CallOnReset
from tocabi_torchrl.transforms._checks import require_spec
# The layout is config (it lives in a module without torch, for the config tree); this path names it too.
from tocabi_torchrl.transforms.layouts import REFERENCE_OBS_LAYOUT, ObsComponent

__all__ = ["ObsComponent", "REFERENCE_OBS_LAYOUT", "ObservationAssembly"]


class ObservationAssembly(CallOnReset):
    """Concatenate the layout's blocks into one float32 vector.

    Reads every ``component.key``; writes ``out_key`` (num_envs, D) float32, D = sum of the block sizes (37 for
    :data:`REFERENCE_OBS_LAYOUT`). Runs on reset and on every step. ``slices`` maps each block name to its columns
    once the transform is attached to an env.

    Args:
        layout: the blocks, in output order.
        out_key: where the vector is written.
    """

    def __init__(self, layout: tuple[ObsComponent, ...] = REFERENCE_OBS_LAYOUT, out_key: NestedKey = "obs_step"):
        layout = tuple(layout)
        if not layout:
            raise ValueError("ObservationAssembly needs at least one ObsComponent in its layout")
        for c in layout:
            if not isinstance(c, ObsComponent):
                raise TypeError(f"ObservationAssembly layout entries must be ObsComponent, got {c!r}")
        names = [c.name for c in layout]
        if len(set(names)) != len(names):
            raise ValueError(f"ObservationAssembly layout has duplicate block names: {names}")
        in_keys = list(dict.fromkeys(c.key for c in layout))
        super().__init__(in_keys=in_keys, out_keys=[out_key])
        self.layout = layout
        self.slices: dict[str, slice] = {}

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        nb = next_tensordict.batch_dims
        lead = (slice(None),) * nb
        parts = [next_tensordict.get(c.key)[lead + c.index].flatten(nb).to(torch.float32) for c in self.layout]
        next_tensordict.set(self.out_keys[0], torch.cat(parts, dim=-1))
        return next_tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Apply to stored data (e.g. a replay buffer sample), any batch shape."""
        return self._call(tensordict)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        batch = tuple(observation_spec.shape)
        lead = (slice(None),) * len(batch)
        start = 0
        slices = {}
        for c in self.layout:
            spec = require_spec(observation_spec, c.key, self)
            try:
                # Size the block on the meta device: no data is touched.
                probe = torch.empty(tuple(spec.shape), device="meta")[lead + c.index].flatten(len(batch))
            except IndexError as err:
                raise ValueError(
                    f"ObservationAssembly block {c.name!r}: index {c.index!r} does not fit {c.key!r} of shape "
                    f"{tuple(spec.shape)} ({err}); index the signal dimensions only, not the batch"
                ) from err
            if probe.shape[-1] == 0:  # an index past the signal's end selects nothing, which slicing allows
                raise ValueError(f"ObservationAssembly block {c.name!r}: index {c.index!r} selects no element of "
                                 f"{c.key!r} of shape {tuple(spec.shape)}; index elements that exist")
            slices[c.name] = slice(start, start + probe.shape[-1])
            start += probe.shape[-1]
        self.slices = slices
        observation_spec[self.out_keys[0]] = Unbounded(
            shape=(*batch, start), dtype=torch.float32, device=observation_spec.device
        )
        return observation_spec
