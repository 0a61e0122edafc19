"""Quaternion math for observations and rewards, and the transform that turns the base quaternion into Euler angles.

Quaternions are MuJoCo's (w, x, y, z) in the last dimension; every function is batched over leading dimensions and
uses only elementwise torch ops (no host synchronisation).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

from tocabi_torchrl.transforms._checks import require_spec

__all__ = ["quat_to_rpy", "quat_rotation_angle", "BaseEulerAngles"]


def quat_to_rpy(quat: torch.Tensor) -> torch.Tensor:
    """Fixed-XYZ (= ZYX roll-pitch-yaw) Euler angles of a (w, x, y, z) quaternion, spec §7.2.

    ``R = Rz(yaw)·Ry(pitch)·Rx(roll)``; roll = atan2(R21, R22), pitch = atan2(-R20, sqrt(R00² + R10²)),
    yaw = atan2(R10, R00). At the gimbal lock (sqrt(R00² + R10²) <= 4·eps) the reference switches to
    yaw = atan2(-R01, R11), roll = 0; both branches are computed and selected with ``torch.where`` so the function
    never branches on device values.

    Args:
        quat: (..., 4) quaternion (w, x, y, z); need not be unit length (the matrix uses s = 2/|q|², as gym does).

    Returns:
        (..., 3) [roll, pitch, yaw] in rad.
    """
    if quat.shape[-1] != 4:
        raise ValueError(f"quat_to_rpy expects (..., 4) quaternions (w, x, y, z), got shape {tuple(quat.shape)}")
    w, x, y, z = quat.unbind(-1)
    # gym's quat2mat scales by 2/|q|², so slightly non-unit quaternions still give a rotation matrix.
    s = 2.0 / (w * w + x * x + y * y + z * z).clamp_min(torch.finfo(quat.dtype).tiny)
    r00 = 1.0 - s * (y * y + z * z)
    r01 = s * (x * y - w * z)
    r10 = s * (x * y + w * z)
    r11 = 1.0 - s * (x * x + z * z)
    r20 = s * (x * z - w * y)
    r21 = s * (y * z + w * x)
    r22 = 1.0 - s * (x * x + y * y)
    cy = torch.sqrt(r00 * r00 + r10 * r10)
    # The reference uses float64's 4·eps; in float32 the rounding of cy near the lock is ~1e-7, so use this dtype's.
    locked = cy <= 4.0 * torch.finfo(quat.dtype).eps
    pitch = torch.atan2(-r20, cy)
    roll = torch.where(locked, torch.zeros_like(cy), torch.atan2(r21, r22))
    yaw = torch.where(locked, torch.atan2(-r01, r11), torch.atan2(r10, r00))
    return torch.stack((roll, pitch, yaw), dim=-1)


def quat_rotation_angle(quat: torch.Tensor) -> torch.Tensor:
    """Absolute rotation angle of a (w, x, y, z) quaternion relative to identity, in [0, π] rad.

    Equals ``abs(pyquaternion.Quaternion(q).angle)``: pyquaternion returns wrap(2·atan2(|v|, w)) in (-π, π], whose
    absolute value is 2·atan2(|v|, |w|) (q and -q are the same rotation).

    Args:
        quat: (..., 4) quaternion (w, x, y, z); scale-invariant.

    Returns:
        (..., 1) angle in rad.
    """
    if quat.shape[-1] != 4:
        raise ValueError(f"quat_rotation_angle expects (..., 4) quaternions (w, x, y, z), got {tuple(quat.shape)}")
    vec_norm = torch.linalg.vector_norm(quat[..., 1:], dim=-1, keepdim=True)
    return 2.0 * torch.atan2(vec_norm, quat[..., :1].abs())


class BaseEulerAngles(Transform):
    """Writes the pelvis roll, pitch, yaw (fixed-XYZ Euler angles, spec §7.2) from the base quaternion.

    Reads ``in_key`` (num_envs, 4) (w, x, y, z); writes ``out_key`` (num_envs, 3) float32 [roll, pitch, yaw] in rad.
    Yaw is the absolute world heading, as in the reference observation.
    """

    def __init__(self, in_key: NestedKey = "base_quat", out_key: NestedKey = "base_rpy"):
        super().__init__(in_keys=[in_key], out_keys=[out_key])

    def _apply_transform(self, quat: torch.Tensor) -> torch.Tensor:
        return quat_to_rpy(quat.to(torch.float32))

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        spec = require_spec(observation_spec, self.in_keys[0], self, last_dim=4)
        observation_spec[self.out_keys[0]] = Unbounded(
            shape=(*spec.shape[:-1], 3), dtype=torch.float32, device=observation_spec.device
        )
        return observation_spec
