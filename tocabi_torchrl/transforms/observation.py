"""Observation assembly: concatenate named env signals into the per-step observation vector (spec §7.1).

A layout is a tuple of :class:`ObsComponent`, each naming a key and the part of it to take. The reference layout
gives the 37 values in the reference order; a researcher changes the observation by passing another tuple.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Composite, Unbounded

from tocabi_torchrl import robot
from tocabi_torchrl.transforms._base import CallOnReset
from tocabi_torchrl.transforms._checks import require_spec

__all__ = ["ObsComponent", "REFERENCE_OBS_LAYOUT", "ObservationAssembly"]

_ALL = slice(None)


@dataclass(frozen=True)
class ObsComponent:
    """One block of the observation vector.

    Attributes:
        name: label of the block (for docs and :attr:`ObservationAssembly.slices`).
        key: tensordict key to read, shape (num_envs, *signal_shape).
        index: index into the signal dimensions (not the batch), made of ints and slices only so that no index
            tensor is copied to the device each step; e.g. ``(slice(0, 12),)`` for the leg joints of a (N, 33)
            signal, ``(slice(None), 2)`` for the z components of a (N, 2, 3) signal. The result is flattened.
    """

    name: str
    key: NestedKey
    index: tuple = ()

    def __post_init__(self):
        for i in self.index:
            if not (isinstance(i, slice) or i is Ellipsis or (isinstance(i, int) and not isinstance(i, bool))):
                raise TypeError(
                    f"ObsComponent {self.name!r}: index entries must be ints, slices or Ellipsis, got {i!r}; "
                    "split a scattered selection into several components"
                )


#: The reference per-step observation (spec §7.1): 3 + 12 + 12 + 1 + 1 + 2 + 2 + 2 + 2 = 37 values.
REFERENCE_OBS_LAYOUT: tuple[ObsComponent, ...] = (
    ObsComponent("base_rpy", "base_rpy"),  # 0-2: roll, pitch, yaw of the pelvis
    ObsComponent("leg_joint_pos", "joint_pos", (robot.LEGS,)),  # 3-14
    ObsComponent("leg_joint_vel", "joint_vel", (robot.LEGS,)),  # 15-26
    ObsComponent("phase_sin", "phase_sin"),  # 27
    ObsComponent("phase_cos", "phase_cos"),  # 28
    ObsComponent("command", "command"),  # 29-30: vx, vy
    ObsComponent("foot_force_z", "foot_force", (_ALL, 2)),  # 31-32: Fz_L, Fz_R
    ObsComponent("foot_torque_x", "foot_torque", (_ALL, 0)),  # 33-34: Mx_L, Mx_R
    ObsComponent("foot_torque_y", "foot_torque", (_ALL, 1)),  # 35-36: My_L, My_R
)


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
            slices[c.name] = slice(start, start + probe.shape[-1])
            start += probe.shape[-1]
        self.slices = slices
        observation_spec[self.out_keys[0]] = Unbounded(
            shape=(*batch, start), dtype=torch.float32, device=observation_spec.device
        )
        return observation_spec
