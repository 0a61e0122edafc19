"""Analytic leg kinematics of TOCABI: forward and closed-form inverse, vectorised over samples (numpy, float64).

Each leg is hip yaw (z), hip roll (x), hip pitch (y) meeting at the hip center, a knee pitch (y) one thigh below,
and ankle pitch (y) then roll (x) meeting at the ankle center one shank below (spec §1.2-1.3). At zero angles the
leg hangs straight down and every frame is aligned with the pelvis. Both legs use the same axes and signs; only the
hip position is mirrored. Positions and rotations are in the pelvis (``base_link``) frame unless a function says
otherwise. The inverse is the classic closed form for this joint layout (Kajita et al., *Introduction to Humanoid
Robotics*, §2.5); tests check it against these forward kinematics and against MuJoCo on the project's model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["LegGeometry", "SIDES", "rot_x", "rot_y", "rot_z", "leg_fk", "leg_ik", "legs_fk"]

#: Leg order used everywhere in this package: joint columns 0-5 are the left leg, 6-11 the right.
SIDES = ("left", "right")


@dataclass(frozen=True)
class LegGeometry:
    """Leg dimensions [m] of the TOCABI model (spec §1.2, §1.6).

    Attributes:
        hip: left hip center in the pelvis frame; the right hip mirrors y.
        thigh: hip center to knee axis.
        shank: knee axis to ankle center.
        sole_depth: ankle center to the sole plane, along the foot's −z.
    """

    hip: tuple[float, float, float] = (0.11, 0.1025, -0.1025)
    thigh: float = 0.35
    shank: float = 0.35
    sole_depth: float = 0.1585

    def hip_position(self, side: str) -> np.ndarray:
        """(3,) hip center of ``side`` ("left" or "right") in the pelvis frame."""
        x, y, z = self.hip
        return np.array([x, y if _side_sign(side) > 0 else -y, z])


def _side_sign(side: str) -> float:
    if side not in SIDES:
        raise ValueError(f"side must be one of {SIDES}, got {side!r}")
    return 1.0 if side == "left" else -1.0


def _rot(angle: np.ndarray, axis: int) -> np.ndarray:
    a = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    out = np.zeros(a.shape + (3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    out[..., axis, axis] = 1.0
    out[..., i, i] = c
    out[..., j, j] = c
    out[..., i, j] = -s
    out[..., j, i] = s
    return out


def rot_x(angle: np.ndarray) -> np.ndarray:
    """Rotation matrices about x, shape ``angle.shape + (3, 3)``."""
    return _rot(angle, 0)


def rot_y(angle: np.ndarray) -> np.ndarray:
    """Rotation matrices about y, shape ``angle.shape + (3, 3)``."""
    return _rot(angle, 1)


def rot_z(angle: np.ndarray) -> np.ndarray:
    """Rotation matrices about z, shape ``angle.shape + (3, 3)``."""
    return _rot(angle, 2)


def leg_fk(q: np.ndarray, side: str, geometry: LegGeometry = LegGeometry()) -> tuple[np.ndarray, np.ndarray]:
    """Ankle center pose of one leg in the pelvis frame.

    Args:
        q: (n, 6) joint angles [rad]: hip yaw, hip roll, hip pitch, knee, ankle pitch, ankle roll.
        side: "left" or "right".
    Returns:
        position (n, 3) [m] and rotation (n, 3, 3) of the ankle-roll (= foot) frame.
    """
    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    hip_rot = rot_z(q[:, 0]) @ rot_x(q[:, 1]) @ rot_y(q[:, 2])
    knee_rot = hip_rot @ rot_y(q[:, 3])
    down = np.array([0.0, 0.0, -1.0])
    pos = geometry.hip_position(side) + geometry.thigh * hip_rot @ down + geometry.shank * knee_rot @ down
    rot = knee_rot @ rot_y(q[:, 4]) @ rot_x(q[:, 5])
    return pos, rot


def legs_fk(joint_pos: np.ndarray, geometry: LegGeometry = LegGeometry()) -> tuple[np.ndarray, np.ndarray]:
    """Both ankle poses for joint rows in robot order.

    Args:
        joint_pos: (n, >=12) joint angles [rad]; columns 0-5 left leg, 6-11 right leg.
    Returns:
        positions (n, 2, 3) and rotations (n, 2, 3, 3), [left, right], pelvis frame.
    """
    joint_pos = np.asarray(joint_pos, dtype=np.float64)
    poses = [leg_fk(joint_pos[:, 6 * i : 6 * i + 6], side, geometry) for i, side in enumerate(SIDES)]
    return np.stack([p for p, _ in poses], axis=1), np.stack([r for _, r in poses], axis=1)


def leg_ik(
    ankle_pos: np.ndarray, ankle_rot: np.ndarray, side: str, geometry: LegGeometry = LegGeometry()
) -> np.ndarray:
    """Joint angles that put one ankle center at a pose given in the pelvis frame.

    Args:
        ankle_pos: (n, 3) ankle center [m].
        ankle_rot: (n, 3, 3) foot orientation.
        side: "left" or "right".
    Returns:
        (n, 6) angles [rad] (hip yaw, roll, pitch, knee >= 0, ankle pitch, roll), the knee-forward solution.
    Raises:
        ValueError if a target is out of reach (hip to ankle longer than thigh + shank), naming the first sample.
    """
    ankle_pos = np.atleast_2d(np.asarray(ankle_pos, dtype=np.float64))
    ankle_rot = np.asarray(ankle_rot, dtype=np.float64).reshape(-1, 3, 3)
    a, b = geometry.thigh, geometry.shank
    # Hip center seen from the ankle, in the foot frame: the ankle joints alone orient this vector.
    r = np.einsum("nji,nj->ni", ankle_rot, geometry.hip_position(side) - ankle_pos)
    c = np.linalg.norm(r, axis=1)
    too_far = c > a + b - 1e-12
    if too_far.any():
        k = int(np.argmax(too_far))
        raise ValueError(f"{side} ankle target {ankle_pos[k]} is {c[k]:.4f} m from the hip, beyond reach {a + b} m")
    knee = np.arccos(np.clip((c**2 - a**2 - b**2) / (2.0 * a * b), -1.0, 1.0))
    alpha = np.arcsin(np.clip(a / c * np.sin(np.pi - knee), -1.0, 1.0))
    ankle_roll = np.arctan2(r[:, 1], r[:, 2])
    ankle_pitch = -np.arctan2(r[:, 0], np.sign(r[:, 2]) * np.hypot(r[:, 1], r[:, 2])) - alpha
    # What is left for the hip: R_hip = Rz(yaw) Rx(roll) Ry(pitch).
    rest = ankle_rot @ rot_x(-ankle_roll) @ rot_y(-ankle_pitch - knee)
    yaw = np.arctan2(-rest[:, 0, 1], rest[:, 1, 1])
    roll = np.arctan2(rest[:, 2, 1], -rest[:, 0, 1] * np.sin(yaw) + rest[:, 1, 1] * np.cos(yaw))
    pitch = np.arctan2(-rest[:, 2, 0], rest[:, 2, 2])
    return np.stack([yaw, roll, pitch, knee, ankle_pitch, ankle_roll], axis=1)
