"""Contact sensors (C MuJoCo, no warp): the signed count sums equal a scan of the contact list."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from tocabi_torchrl import robot
from tocabi_torchrl.sim import ContactSensorError, add_contact_sensors, contact_layout, has_contact_sensors
from tocabi_torchrl.sim.contacts import SIGNAL_NAMES


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return add_contact_sensors(robot.load_spec()).compile()


def _scan_counts(m: mujoco.MjModel, d: mujoco.MjData) -> np.ndarray:
    """(left foot-ground, right foot-ground, forbidden ground, self collision) counts, straight from spec §9.1."""
    body = lambda n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n)  # noqa: E731
    feet = [body(b) for b in robot.FOOT_BODIES]
    forbidden = {body(b) for b in robot.GROUND_FORBIDDEN_BODIES}
    self_bodies = {body(b) for b in robot.SELF_COLLISION_BODIES}
    counts = np.zeros(4)
    for c in d.contact[: d.ncon]:
        if c.exclude:
            continue
        b1, b2 = m.geom_bodyid[c.geom1], m.geom_bodyid[c.geom2]
        if 0 in (b1, b2):
            other = b2 if b1 == 0 else b1
            counts += [other == feet[0], other == feet[1], other in forbidden, 0]
        elif b1 in self_bodies and b2 in self_bodies:
            counts[3] += 1
    return counts


def test_layout_is_derived_from_the_robot_lists(model):
    lay = contact_layout(model)
    assert lay.weights.shape == (len(SIGNAL_NAMES), lay.count)
    names = [n.split("/", 1)[1] for n in lay.names]
    # Allowed on the ground: the two ankle chains (AnkleCenter subtree holds AnkleRoll and Foot) and the neck/head.
    assert {"ground/L_AnkleCenter_Link", "ground/R_AnkleCenter_Link", "ground/Neck_Link"} <= set(names)
    assert "self/Neck_Link" in names  # the only bodies outside SELF_COLLISION_BODIES
    forbidden = dict(zip(names, lay.weights[2]))
    assert forbidden["ground/all"] == 1 and forbidden["ground/Neck_Link"] == -1
    ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, n) for n in lay.names]
    assert model.sensor_needstage[ids].max() == 1  # position stage: found needs no forces
    assert "self_collision = +self/all -self/Neck_Link > 0" in lay.describe()


def test_add_is_idempotent_and_model_without_sensors_is_refused():
    spec = robot.load_spec()
    assert not has_contact_sensors(spec)
    n = len(add_contact_sensors(spec).sensors)
    assert len(add_contact_sensors(spec).sensors) == n
    with pytest.raises(ContactSensorError, match="add_contact_sensors"):
        contact_layout(robot.load_model())


def test_counts_match_a_scan_of_the_contact_list(model):
    """Random falls, drops and tangled poses: every count equals the scan, and every signal fires at least once."""
    d = mujoco.MjData(model)
    lay = contact_layout(model)
    rng = np.random.default_rng(0)
    fired = np.zeros(4)
    for episode in range(8):
        mujoco.mj_resetData(model, d)
        d.qpos[:] = robot.INIT_QPOS
        if episode % 2:
            d.qpos[7:] += rng.normal(0.0, 0.6, robot.NUM_JOINTS)
        if episode % 3:
            axis = rng.normal(size=3)
            angle = rng.uniform(-1.6, 1.6)
            d.qpos[3:7] = np.concatenate(([np.cos(angle / 2)], np.sin(angle / 2) * axis / np.linalg.norm(axis)))
            d.qpos[2] = 0.6
        for _ in range(120):
            d.ctrl[: robot.NUM_LEG_JOINTS] = rng.uniform(-0.5, 0.5, robot.NUM_LEG_JOINTS) * robot.LEG_TORQUE_LIMITS
            d.ctrl[robot.NUM_LEG_JOINTS :] = robot.INIT_JOINT_POS[robot.NUM_LEG_JOINTS :]
            for _ in range(4):
                mujoco.mj_step(model, d)
            counts = lay.weights @ d.sensordata[lay.adr]
            np.testing.assert_array_equal(counts, _scan_counts(model, d))
            fired += counts > 0
    assert (fired > 0).all(), f"some signal never fired: {dict(zip(SIGNAL_NAMES, fired))}"
