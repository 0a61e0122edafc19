"""Measure the structure of a walking cycle: foot clearance, step length, sway, joint ranges, and kinematic soundness.

Structure numbers use the analytic leg kinematics with the pelvis fixed and level, as the spec measures the
reference (§3.5), so a generated cycle and the reference file are compared the same way. The soundness checks
(stance-foot slide and tilt, self-penetration) run the project's MuJoCo model along the planned pelvis path.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tocabi_torchrl.robot import GROUND_GEOM, NUM_LEG_JOINTS

from .kinematics import LegGeometry, legs_fk
from .schedule import LEFT_STANCE, RIGHT_STANCE

__all__ = ["GaitMetrics", "gait_metrics", "StanceDrift", "stance_foot_drift", "self_contacts"]


@dataclass
class GaitMetrics:
    """Structure of a two-step cycle (lengths in m, angles in rad).

    Attributes:
        clearance: (2,) highest lift of each ankle above the other ankle, [left swing, right swing].
        clearance_row: (2,) row of that apex.
        step_length: mean forward ankle-to-ankle distance at the start rows (mid double support).
        step_width: mean lateral ankle-to-ankle distance.
        sway: half the range of the feet's mean lateral position relative to the pelvis.
        pelvis_height: mean height of the pelvis above the lower ankle plus the sole depth.
        leg_min, leg_max: (12,) per-joint extremes of the leg joints.
    """

    clearance: np.ndarray
    clearance_row: np.ndarray
    step_length: float
    step_width: float
    sway: float
    pelvis_height: float
    leg_min: np.ndarray
    leg_max: np.ndarray

    @property
    def leg_range(self) -> np.ndarray:
        return self.leg_max - self.leg_min

    def summary(self) -> dict:
        """Plain-Python numbers for printing or JSON."""
        r = lambda x: np.round(np.asarray(x, dtype=float), 4).tolist()  # noqa: E731
        return {
            "clearance_m": r(self.clearance),
            "clearance_row": np.asarray(self.clearance_row).tolist(),
            "step_length_m": r(self.step_length),
            "step_width_m": r(self.step_width),
            "sway_m": r(self.sway),
            "pelvis_height_m": r(self.pelvis_height),
            "leg_min_rad": r(self.leg_min),
            "leg_max_rad": r(self.leg_max),
        }


def gait_metrics(joint_pos: np.ndarray, init_rows, geometry: LegGeometry = LegGeometry()) -> GaitMetrics:
    """Measure a cycle from its joint table.

    Args:
        joint_pos: (R, >=12) joint positions [rad], robot order.
        init_rows: rows in the middle of the double supports (where the step length is read).
    """
    joint_pos = np.asarray(joint_pos, dtype=np.float64)
    ankle, _ = legs_fk(joint_pos, geometry)
    lift = np.stack([ankle[:, 0, 2] - ankle[:, 1, 2], ankle[:, 1, 2] - ankle[:, 0, 2]], axis=1)
    rows = np.asarray(init_rows)
    mid_y = ankle[:, :, 1].mean(axis=1)
    return GaitMetrics(
        clearance=lift.max(axis=0),
        clearance_row=lift.argmax(axis=0),
        step_length=float(np.abs(ankle[rows, 0, 0] - ankle[rows, 1, 0]).mean()),
        step_width=float((ankle[:, 0, 1] - ankle[:, 1, 1]).mean()),
        sway=float((mid_y.max() - mid_y.min()) / 2),
        pelvis_height=float(-ankle[:, :, 2].min(axis=1).mean() + geometry.sole_depth),
        leg_min=joint_pos[:, :NUM_LEG_JOINTS].min(axis=0),
        leg_max=joint_pos[:, :NUM_LEG_JOINTS].max(axis=0),
    )


@dataclass
class StanceDrift:
    """Worst motion of the stance foot over each single support (m, rad), keyed "right" / "left"."""

    slide: dict[str, float]
    lift: dict[str, float]
    tilt: dict[str, float]


def _runs(mask: np.ndarray) -> list[np.ndarray]:
    """Contiguous runs of True rows (longer than one row: the reward's single-row quirks are not phases)."""
    rows = np.flatnonzero(mask)
    runs = np.split(rows, np.flatnonzero(np.diff(rows) > 1) + 1) if rows.size else []
    return [r for r in runs if r.size > 1]


def _world_poses(model, joint_pos: np.ndarray, base_pos: np.ndarray, bodies: tuple[str, ...]):
    import mujoco

    data = mujoco.MjData(model)
    ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, b) for b in bodies]
    pos = np.empty((joint_pos.shape[0], len(ids), 3))
    rot = np.empty((joint_pos.shape[0], len(ids), 3, 3))
    for k in range(joint_pos.shape[0]):
        data.qpos[:3] = base_pos[k]
        data.qpos[3:7] = (1.0, 0.0, 0.0, 0.0)
        data.qpos[7:] = joint_pos[k]
        mujoco.mj_kinematics(model, data)
        pos[k] = data.xpos[ids]
        rot[k] = data.xmat[ids].reshape(-1, 3, 3)
    return pos, rot


def stance_foot_drift(model, joint_pos: np.ndarray, base_pos: np.ndarray, stance: np.ndarray) -> StanceDrift:
    """How far the stance foot slides, lifts and tilts over each single support, with the pelvis on ``base_pos``.

    Args:
        model: MuJoCo model with ``L_Foot_Link`` / ``R_Foot_Link``.
        joint_pos: (R, 33) joints [rad]; base_pos: (R, 3) pelvis positions [m] (level pelvis); stance: (R,) codes.
    Returns:
        per side, the largest horizontal displacement from the phase's first row (slide), the vertical one (lift),
        and the largest angle between the foot's z axis and the world vertical (tilt).
    """
    from tocabi_torchrl.robot import FOOT_BODIES

    pos, rot = _world_poses(model, np.asarray(joint_pos), np.asarray(base_pos), FOOT_BODIES)
    out = StanceDrift({}, {}, {})
    for side, foot, code in (("right", 1, RIGHT_STANCE), ("left", 0, LEFT_STANCE)):
        slide = lift = tilt = 0.0
        for rows in _runs(np.asarray(stance) == code):
            p = pos[rows, foot]
            slide = max(slide, float(np.linalg.norm(p[:, :2] - p[0, :2], axis=1).max()))
            lift = max(lift, float(np.abs(p[:, 2] - p[0, 2]).max()))
            tilt = max(tilt, float(np.arccos(np.clip(rot[rows, foot, 2, 2], -1.0, 1.0)).max()))
        out.slide[side], out.lift[side], out.tilt[side] = slide, lift, tilt
    return out


def self_contacts(
    model, joint_pos: np.ndarray, base_pos: np.ndarray, every: int = 1
) -> list[tuple[int, str, str, float]]:
    """Penetrating pairs of collision geoms (ground excluded) along the cycle: ``(row, body1, body2, distance)``.

    Contacts come from MuJoCo's own collision pipeline, so the model's contype/conaffinity and parent-child
    filtering apply exactly as in simulation. ``every``: check every ``every``-th row (an int >= 1); ``ValueError``
    otherwise.
    """
    import mujoco

    if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1:
        raise ValueError(f"self_contacts: every must be an int >= 1 (1 checks every row), got {every!r}")

    data = mujoco.MjData(model)
    ground = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, GROUND_GEOM)
    body = lambda g: mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, model.geom_bodyid[g])  # noqa: E731
    found = []
    for k in range(0, joint_pos.shape[0], every):
        data.qpos[:3] = base_pos[k]
        data.qpos[3:7] = (1.0, 0.0, 0.0, 0.0)
        data.qpos[7:] = joint_pos[k]
        mujoco.mj_fwdPosition(model, data)
        for (g1, g2), dist in zip(data.contact.geom[: data.ncon], data.contact.dist[: data.ncon]):
            if ground not in (g1, g2) and dist < 0:
                found.append((k, body(g1), body(g2), float(dist)))
    return found
