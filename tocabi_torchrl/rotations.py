"""Quaternion and Euler-angle helpers shared by the environment and the transforms.

Quaternions are MuJoCo's (w, x, y, z) in the last dimension. Every function is batched over leading dimensions and
uses only elementwise torch ops and constants cached per device, so it runs inside the env step and a captured CUDA
graph without a host synchronisation or a host-to-device copy.
"""

from __future__ import annotations

import functools

import torch

__all__ = ["quat_rotate_inverse", "quat_rotation_angle", "quat_to_rpy"]


def quat_rotate_inverse(quat: torch.Tensor, vec: torch.Tensor) -> torch.Tensor:
    """Rotate world vectors (..., 3) into the frame of (w, x, y, z) quaternions (..., 4): ``R(q)ᵀ · v``."""
    w, u = quat[..., :1], quat[..., 1:]
    t = 2.0 * torch.linalg.cross(u, vec, dim=-1)
    return vec - w * t + torch.linalg.cross(u, t, dim=-1)


# Rows: the 16 products q_a·q_b (a, b in w, x, y, z, row-major). Columns: |q|²·R for the seven rotation-matrix
# entries the angles need, R00, R01, R10, R11, R20, R21, R22 (gym's quat2mat, using 1 = (ww + xx + yy + zz)/|q|²).
_W, _X, _Y, _Z = range(4)
_R_TERMS = (
    {(_W, _W): 1, (_X, _X): 1, (_Y, _Y): -1, (_Z, _Z): -1},  # R00
    {(_X, _Y): 2, (_W, _Z): -2},  # R01
    {(_X, _Y): 2, (_W, _Z): 2},  # R10
    {(_W, _W): 1, (_X, _X): -1, (_Y, _Y): 1, (_Z, _Z): -1},  # R11
    {(_X, _Z): 2, (_W, _Y): -2},  # R20
    {(_Y, _Z): 2, (_W, _X): 2},  # R21
    {(_W, _W): 1, (_X, _X): -1, (_Y, _Y): -1, (_Z, _Z): 1},  # R22
)


@functools.lru_cache(maxsize=8)
def _rotation_basis(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    # Built once per device: a tensor made from host data inside the step loop would be a blocking copy.
    basis = torch.zeros(16, len(_R_TERMS), dtype=torch.float64)
    for col, terms in enumerate(_R_TERMS):
        for (a, b), c in terms.items():
            basis[4 * a + b, col] = c
    return basis.to(dtype=dtype, device=device)


def quat_to_rpy(quat: torch.Tensor) -> torch.Tensor:
    """Fixed-XYZ (= ZYX roll-pitch-yaw) Euler angles of a (w, x, y, z) quaternion, spec §7.2.

    ``R = Rz(yaw)·Ry(pitch)·Rx(roll)``; roll = atan2(R21, R22), pitch = atan2(-R20, sqrt(R00² + R10²)),
    yaw = atan2(R10, R00). At the gimbal lock (sqrt(R00² + R10²) <= 4·eps) the reference switches to
    yaw = atan2(-R01, R11), roll = 0; both branches are computed and selected with ``torch.where`` so the function
    never branches on device values.

    Args:
        quat: (..., 4) quaternion (w, x, y, z); need not be unit length (R is that of q/|q|, as in gym's quat2mat).

    Returns:
        (..., 3) [roll, pitch, yaw] in rad.
    """
    if quat.shape[-1] != 4:
        raise ValueError(f"quat_to_rpy expects (..., 4) quaternions (w, x, y, z), got shape {tuple(quat.shape)}")
    # |q|²·R from one outer product and one matmul: few kernels, as this runs every step for every env. atan2 is
    # scale-invariant, so the angles need no division by |q|²; only the gimbal threshold is scaled.
    products = (quat.unsqueeze(-1) * quat.unsqueeze(-2)).flatten(-2)
    r00, r01, r10, r11, r20, r21, r22 = (products @ _rotation_basis(quat.dtype, quat.device)).unbind(-1)
    cy = torch.hypot(r00, r10)
    angles = torch.atan2(torch.stack((r21, -r20, r10, -r01), -1), torch.stack((r22, cy, r00, r11), -1))
    # The reference uses float64's 4·eps; in float32 the rounding of cy near the lock is ~1e-7, so use this dtype's.
    locked = (cy <= 4.0 * torch.finfo(quat.dtype).eps * products[..., 0 :: 5].sum(-1)).unsqueeze(-1)
    at_lock = torch.stack((torch.zeros_like(cy), angles[..., 1], angles[..., 3]), -1)
    return torch.where(locked, at_lock, angles[..., :3])


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
