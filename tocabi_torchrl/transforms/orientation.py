"""The transform that turns the base quaternion into Euler angles.

The quaternion math lives in :mod:`tocabi_torchrl.rotations` (shared with the env); ``quat_to_rpy`` and
``quat_rotation_angle`` are re-exported here for their old import path.
"""

from __future__ import annotations

import torch
from tensordict.utils import NestedKey
from torchrl.data import Composite, Unbounded

from tocabi_torchrl.rotations import quat_rotation_angle, quat_to_rpy
from tocabi_torchrl.transforms._base import CallOnReset
from tocabi_torchrl.transforms._checks import require_spec

__all__ = ["quat_to_rpy", "quat_rotation_angle", "BaseEulerAngles"]


class BaseEulerAngles(CallOnReset):
    """Writes the pelvis roll, pitch, yaw (fixed-XYZ Euler angles, spec §7.2) from the base quaternion.

    Reads ``in_key`` (num_envs, 4) (w, x, y, z); writes ``out_key`` (num_envs, 3) float32 [roll, pitch, yaw] in rad.
    Yaw is the absolute world heading, as in the reference observation.
    """

    def __init__(self, in_key: NestedKey = "base_quat", out_key: NestedKey = "base_rpy"):
        super().__init__(in_keys=[in_key], out_keys=[out_key])

    def _apply_transform(self, quat: torch.Tensor) -> torch.Tensor:
        return quat_to_rpy(quat.to(torch.float32))

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        spec = require_spec(observation_spec, self.in_keys[0], self, last_dim=4)
        observation_spec[self.out_keys[0]] = Unbounded(
            shape=(*spec.shape[:-1], 3), dtype=torch.float32, device=observation_spec.device
        )
        return observation_spec
