"""Analytic leg kinematics (against MuJoCo on the project's model) and the periodic LIPM CoM plan."""

import mujoco
import numpy as np
import pytest

from tocabi_torchrl import robot
from tocabi_torchrl.motion.kinematics import SIDES, LegGeometry, leg_fk, leg_ik, legs_fk, rot_x, rot_y, rot_z
from tocabi_torchrl.motion.lipm import lipm_zmp, periodic_lipm_com


def random_leg_angles(n: int, seed: int = 0) -> np.ndarray:
    """Angles around walking poses, knee bent (the IK returns the knee-forward branch)."""
    rng = np.random.default_rng(seed)
    lo = np.array([-0.3, -0.3, -1.0, 0.05, -0.8, -0.3])
    hi = np.array([0.3, 0.3, 0.5, 1.5, 0.5, 0.3])
    return rng.uniform(lo, hi, size=(n, 6))


def test_rotations_are_right_handed():
    np.testing.assert_allclose(rot_z(np.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(rot_x(np.pi / 2) @ [0, 1, 0], [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(rot_y(np.pi / 2) @ [0, 0, 1], [1, 0, 0], atol=1e-15)


def test_zero_pose_hangs_straight_down():
    pos, rot = leg_fk(np.zeros((1, 6)), "right")
    np.testing.assert_allclose(pos[0], [0.11, -0.1025, -0.1025 - 0.7])
    np.testing.assert_allclose(rot[0], np.eye(3))


@pytest.mark.parametrize("side", SIDES)
def test_ik_inverts_fk(side):
    q = random_leg_angles(2000)
    pos, rot = leg_fk(q, side)
    np.testing.assert_allclose(leg_ik(pos, rot, side), q, atol=1e-10)


def test_ik_rejects_targets_out_of_reach():
    with pytest.raises(ValueError, match="left ankle target .* beyond reach 0.7 m"):
        leg_ik(np.array([[0.11, 0.1025, -0.9]]), np.eye(3)[None], "left")
    with pytest.raises(ValueError, match="side must be"):
        leg_fk(np.zeros((1, 6)), "middle")


def test_fk_matches_mujoco_on_the_project_model(model):
    """Foot body poses from MuJoCo equal the analytic ankle poses: the leg geometry constants are the model's."""
    q = np.tile(robot.INIT_JOINT_POS, (300, 1))
    q[:, :6] = random_leg_angles(300, seed=1)
    q[:, 6:12] = random_leg_angles(300, seed=2)
    pos, rot = legs_fk(q)
    data = mujoco.MjData(model)
    for k in range(q.shape[0]):
        data.qpos[:7] = (0, 0, 0, 1, 0, 0, 0)
        data.qpos[7:] = q[k]
        mujoco.mj_kinematics(model, data)
        for i, body in enumerate(robot.FOOT_BODIES):
            np.testing.assert_allclose(data.body(body).xpos, pos[k, i], atol=1e-9)
            np.testing.assert_allclose(data.body(body).xmat.reshape(3, 3), rot[k, i], atol=1e-9)


def test_sole_depth_matches_the_model_sole(model):
    """The lowest point of each foot's collision box lies sole_depth below the ankle center."""
    geometry = LegGeometry()
    for body in robot.FOOT_BODIES:
        bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
        boxes = [
            g for g in range(model.ngeom)
            if model.geom_bodyid[g] == bid and model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX
            and model.geom_contype[g]
        ]  # fmt: skip
        bottom = min(model.geom_pos[g][2] - model.geom_size[g][2] for g in boxes)
        assert bottom == pytest.approx(-geometry.sole_depth, abs=1e-9)


def test_periodic_lipm_com_reproduces_its_zmp():
    n, period, zc = 3599, 1.8, 0.88
    t = np.arange(n) * period / n
    wave = np.sin(2 * np.pi * t / period)
    zmp = np.column_stack([0.24 * t / period + 0.02 * wave, 0.125 * np.sign(wave)])
    drift = np.array([0.24, 0.0])
    com = periodic_lipm_com(zmp, period, zc, drift=drift)
    # The LIPM ODE holds: c - c''/w^2 gives the ZMP back (square wave included, away from its jumps).
    back = lipm_zmp(com, period, zc, drift=drift)
    smooth = np.abs(wave) > 0.05
    np.testing.assert_allclose(back[smooth], zmp[smooth], atol=2e-3)
    # A ramp ZMP is tracked exactly; a square lateral ZMP gives a sway below its amplitude.
    ramp = 0.1 * t[:, None] / period
    np.testing.assert_allclose(periodic_lipm_com(ramp, period, zc, drift=[0.1]), ramp, atol=1e-12)
    assert 0.05 < com[:, 1].max() < 0.125
