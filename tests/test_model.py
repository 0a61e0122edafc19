"""The authored TOCABI model: structure, standing behaviour, parity with the reference robot, bad input."""

from __future__ import annotations

import re

import mujoco
import numpy as np
import pytest

from tocabi_torchrl import robot

from model_files import DEGREE_COMPILERS, shipped_model_in_degrees, shipped_model_mixing_units, shipped_model_read_as
from reference_data import load_reference_model


def _id(m, kind, name):
    return mujoco.mj_name2id(m, getattr(mujoco.mjtObj, f"mjOBJ_{kind}"), name)


def _foot_ids(m):
    return [_id(m, "BODY", b) for b in robot.FOOT_BODIES]


def test_structure(model):
    assert (model.nq, model.nv, model.nu) == (40, 39, 33)
    sensors = robot.FOOT_FORCE_SENSORS + robot.FOOT_TORQUE_SENSORS
    assert sum(model.sensor_dim[_id(model, "SENSOR", s)] for s in sensors) == 12
    assert model.body_mass.sum() == pytest.approx(104.487, rel=1e-4)
    assert model.opt.timestep == 0.0005
    assert model.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER
    assert model.opt.solver == mujoco.mjtSolver.mjSOL_NEWTON
    assert model.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
    np.testing.assert_allclose(model.actuator_ctrlrange[:12, 1], robot.LEG_TORQUE_LIMITS)
    np.testing.assert_allclose(model.actuator_forcerange[12:, 1], robot.TORQUE_LIMITS[12:])
    np.testing.assert_allclose(model.actuator_gainprm[12:, 0], robot.UPPER_KP)
    np.testing.assert_allclose(-model.actuator_biasprm[12:, 2], robot.UPPER_KV)
    visual = (model.geom_contype == 0) & (model.geom_conaffinity == 0)
    assert visual.sum() >= 20, "visual-only silhouette geoms are missing"


def test_loads_into_mujoco_warp_on_cpu(model):
    import mujoco_warp as mjw
    import warp as wp

    with wp.ScopedDevice("cpu"):
        m = mjw.put_model(model)
        d = mjw.make_data(model, nworld=2)
    assert m.nq == 40 and m.nu == 33
    assert d.qpos.shape == (2, 40) and d.sensordata.shape == (2, 12)


def _hold_legs(m, d, target):
    q, qd = d.qpos[7:19], d.qvel[6:18]
    d.ctrl[:12] = robot.LEG_KP * (target - q) - robot.LEG_KV * qd


def _init_state(m):
    d = mujoco.MjData(m)
    d.qpos[:] = robot.INIT_QPOS
    d.ctrl[12:] = robot.INIT_JOINT_POS[12:]
    mujoco.mj_forward(m, d)
    return d


def test_standing_two_seconds(model):
    d = _init_state(model)
    feet = _foot_ids(model)
    ground = _id(model, "GEOM", robot.GROUND_GEOM)
    z0 = d.qpos[2]
    for _ in range(4000):  # 2 s at 2 kHz
        _hold_legs(model, d, robot.INIT_JOINT_POS[:12])
        mujoco.mj_step(model, d)
    assert abs(d.qpos[2] - z0) < 0.02
    touching = {model.geom_bodyid[c.geom[1 - i]] for c in d.contact[: d.ncon] for i in (0, 1) if c.geom[i] == ground}
    assert set(feet) <= touching, "both feet must touch the ground"
    fz = [d.sensor(s).data[2] for s in robot.FOOT_FORCE_SENSORS]
    carried = (model.body_mass.sum() - sum(model.body_mass[f] for f in feet)) * robot.GRAVITY
    assert -sum(fz) == pytest.approx(carried, rel=0.05)
    assert all(f < 0 for f in fz), "a loaded foot reads a negative z force"


# --- parity with the reference robot (skipped when ../shared/reference is absent) ---------------------------------


@pytest.fixture(scope="module")
def reference():
    return load_reference_model()


def test_parity_joints_and_limits(model, reference):
    for j, name in enumerate(robot.JOINT_NAMES):
        a, b = _id(model, "JOINT", name), _id(reference, "JOINT", name)
        assert b >= 0 and reference.jnt_qposadr[b] == 7 + j, f"{name} order differs"
        np.testing.assert_allclose(model.jnt_axis[a], reference.jnt_axis[b], err_msg=name)
        np.testing.assert_allclose(model.jnt_range[a], reference.jnt_range[b], err_msg=name)
        da, db = model.jnt_dofadr[a], reference.jnt_dofadr[b]
        for field in ("dof_armature", "dof_damping", "dof_frictionloss"):
            assert getattr(model, field)[da] == getattr(reference, field)[db], f"{name} {field}"
        ref_limit = reference.actuator_ctrlrange[_id(reference, "ACTUATOR", robot.ACTUATOR_NAMES[j]), 1]
        assert robot.TORQUE_LIMITS[j] == ref_limit, f"{name} torque limit"


def test_parity_bodies_and_inertias(model, reference):
    assert model.nbody == reference.nbody
    for i in range(1, reference.nbody):
        name = reference.body(i).name
        k = _id(model, "BODY", name)
        assert k >= 0, f"body {name} missing"
        for field in ("body_mass", "body_inertia", "body_ipos", "body_pos", "body_quat"):
            np.testing.assert_allclose(getattr(model, field)[k], getattr(reference, field)[i], atol=1e-6,
                                       err_msg=f"{name} {field}")
        # The principal-axes frame is defined up to axis order/sign; compare the inertia tensors it produces.
        def tensor(m, b):
            rot = np.zeros(9)
            mujoco.mju_quat2Mat(rot, m.body_iquat[b])
            rot = rot.reshape(3, 3)
            return rot @ np.diag(m.body_inertia[b]) @ rot.T
        np.testing.assert_allclose(tensor(model, k), tensor(reference, i), atol=1e-6, err_msg=f"{name} inertia")


def test_parity_foot_sites(model, reference):
    rng = np.random.default_rng(0)
    da, db = mujoco.MjData(model), mujoco.MjData(reference)
    for _ in range(5):
        q = robot.INIT_QPOS.copy()
        q[:3] += rng.uniform(-0.5, 0.5, 3)
        quat = rng.normal(size=4)
        q[3:7] = quat / np.linalg.norm(quat)
        q[7:] = rng.uniform(-1.0, 1.0, 33)
        da.qpos[:], db.qpos[:] = q, q
        mujoco.mj_kinematics(model, da)
        mujoco.mj_kinematics(reference, db)
        for site in robot.FOOT_SITES:
            np.testing.assert_allclose(da.site(site).xpos, db.site(site).xpos, atol=1e-3)


def test_parity_motion(model, reference):
    """0.25 s of one fixed leg-torque sequence, upper body PD-held: both models move the same way."""
    rng = np.random.default_rng(1)
    steps = 62  # policy steps of 8 substeps: 0.248 s
    amplitude = 0.15 * robot.LEG_TORQUE_LIMITS
    torques = amplitude * np.sin(2 * np.pi * (np.arange(steps)[:, None] / 40 + rng.uniform(0, 1, 12)))
    da = _init_state(model)
    db = mujoco.MjData(reference)
    db.qpos[:] = robot.INIT_QPOS
    mujoco.mj_forward(reference, db)
    q_up = robot.INIT_JOINT_POS[12:]
    limits = robot.TORQUE_LIMITS[12:]
    for k in range(steps):
        for _ in range(8):
            da.ctrl[:12] = torques[k]
            db.ctrl[:12] = torques[k]
            pd = robot.UPPER_KP * (q_up - db.qpos[19:]) - robot.UPPER_KV * db.qvel[18:]
            db.ctrl[12:] = np.clip(pd, -limits, limits)
            mujoco.mj_step(model, da)
            mujoco.mj_step(reference, db)
    assert np.abs(da.qpos[7:] - robot.INIT_JOINT_POS).max() > 0.01, "the sequence should move the legs"
    np.testing.assert_allclose(da.qpos[7:], db.qpos[7:], atol=1e-3)


# --- bad input ----------------------------------------------------------------------------------------------------


def test_missing_asset_names_the_file(tmp_path):
    missing = tmp_path / "nope.xml"
    with pytest.raises(robot.RobotAssetError, match="nope.xml"):
        robot.load_model(missing)
    with pytest.raises(robot.RobotAssetError, match="nope.xml"):
        robot.load_spec(missing)


def test_malformed_asset_names_the_file(tmp_path):
    bad = tmp_path / "broken.xml"
    bad.write_text("<mujoco><worldbody><body></mujoco>")
    with pytest.raises(robot.RobotAssetError, match="broken.xml"):
        robot.load_model(bad)


def test_missing_names_are_listed(tmp_path):
    text = robot.asset_path("tocabi", "tocabi.xml").read_text()
    text = text.replace('name="L_Knee_Motor"', 'name="Knee_Motor_renamed"').replace(
        '<force name="LF_Force_sensor" site="LF_FT"/>', "")
    broken = tmp_path / "renamed.xml"
    broken.write_text(text)
    with pytest.raises(robot.RobotAssetError) as info:
        robot.load_model(broken)
    message = str(info.value)
    assert "'L_Knee_Motor'" in message and "'LF_Force_sensor'" in message and "renamed.xml" in message


@pytest.mark.parametrize("old,new,message", [
    ('<force name="LF_Force_sensor" site="LF_FT"/>', '<touch name="LF_Force_sensor" site="LF_FT"/>',
     "sensor 'LF_Force_sensor' must be a 3-axis <force> sensor, got a mjSENS_TOUCH of 1 values"),
    ('<force name="RF_Force_sensor" site="RF_FT"/>', '<force name="RF_Force_sensor" site="LF_FT"/>',
     "sensor 'RF_Force_sensor' must sit on site 'RF_FT'"),
])
def test_foot_sensors_of_another_kind_or_foot_are_refused(tmp_path, old, new, message):
    # Both built and stepped: the left foot_force then read a touch value and its neighbour's torques, or the right
    # foot read the left's forces.
    text = robot.asset_path("tocabi", "tocabi.xml").read_text()
    assert old in text
    path = tmp_path / "sensors.xml"
    path.write_text(text.replace(old, new))
    with pytest.raises(robot.RobotAssetError, match=re.escape(message)):
        robot.load_model(path)


def test_asset_path_exists():
    assert robot.asset_path("tocabi", "tocabi.xml").is_file()


def test_assets_folder_override(tmp_path, monkeypatch):
    import shutil

    shutil.copytree(robot.asset_path("tocabi"), tmp_path / "tocabi")
    monkeypatch.setenv("TOCABI_TORCHRL_ASSETS", str(tmp_path))
    assert robot.asset_path("tocabi", "tocabi.xml") == tmp_path / "tocabi" / "tocabi.xml"
    assert robot.load_model().nu == 33


def test_an_assets_folder_override_without_the_model_is_named(tmp_path, monkeypatch):
    # A mistyped $TOCABI_TORCHRL_ASSETS surfaced as "robot model file not found ... (pass an existing MJCF path, or
    # None for the default)" to a caller who had passed None, naming neither the variable nor its value.
    monkeypatch.setenv("TOCABI_TORCHRL_ASSETS", str(tmp_path / "asets"))
    with pytest.raises(robot.RobotAssetError, match=r"\$TOCABI_TORCHRL_ASSETS is .*asets'.*holds no tocabi/ folder"):
        robot.load_model()


def test_missing_names_checks_a_spec_without_compiling(tmp_path):
    assert robot.missing_names(robot.load_spec()) == [] and robot.missing_names(robot.load_model()) == []
    text = robot.asset_path("tocabi", "tocabi.xml").read_text().replace('name="L_Knee_Motor"', 'name="Other_Motor"')
    renamed = tmp_path / "renamed.xml"
    renamed.write_text(text)
    assert robot.missing_names(robot.load_spec(renamed)) == ["actuator 'L_Knee_Motor'"]


@pytest.mark.parametrize("mode", ["pd_reference", "torque"])
def test_env_refuses_a_model_that_is_not_tocabi(tmp_path, mode):
    from tocabi_torchrl import make_env

    tiny = tmp_path / "tiny.xml"
    tiny.write_text('<mujoco><worldbody><geom type="plane" size="1 1 .1"/></worldbody></mujoco>')
    # The PD modes used to fail inside the leg servos' spec edit with "'NoneType' object has no attribute 'set_to_position'".
    with pytest.raises(ValueError, match=r"tiny\.xml' is not a TOCABI model: it lacks joint 'L_HipYaw_Joint'.*"
                                         r"and \d+ more; pass a TOCABI MJCF .*JOINT_NAMES, ACTUATOR_NAMES"):
        make_env(1, "cpu", model_path=str(tiny), control_mode=mode)


@pytest.mark.parametrize("where,addition,message", [
    ("</worldbody>", '<body name="ball" pos="2 2 0.1"><freejoint name="ball_joint"/><geom type="sphere" size="0.05"/>'
     "</body></worldbody>", "has 47 qpos, 45 dofs and 33 actuators where TOCABI has 40, 39 and 33 (extra joints "
     "['ball_joint'])"),
    ("</actuator>", '<motor name="extra_motor" joint="L_Knee_Joint"/></actuator>',
     "has 40 qpos, 39 dofs and 34 actuators where TOCABI has 40, 39 and 33 (extra actuators ['extra_motor'])"),
])
def test_a_model_with_joints_or_actuators_beyond_tocabi_is_refused_by_name(tmp_path, where, addition, message):
    # A prop with a free joint after the robot failed in the env's build as "could not broadcast input array from
    # shape (40,) into shape (47,)", a second motor at the first reset as "ctrl must have shape (1, 34)".
    text = robot.asset_path("tocabi", "tocabi.xml").read_text()
    path = tmp_path / "extra.xml"
    path.write_text(text.replace(where, addition, 1))
    with pytest.raises(robot.RobotAssetError, match=re.escape(message)):
        robot.load_model(path)
    with pytest.raises(robot.RobotAssetError, match=r"extra\.xml has"):
        from tocabi_torchrl import make_env

        make_env(1, "cpu", model_path=str(path))


# --- the initial-pose caches --------------------------------------------------------------------------------------

_NECK = '<body name="Neck_Link" pos="-0.036 0 0.3795">'
_LEFT_SOLE = '<geom class="collision" type="box" size="0.15 0.085 0.0135" pos="0.03 0 -0.145"/>'


def _taller_neck_and_longer_left_sole(text: str) -> str:
    """The shipped MJCF with the neck 0.1 m higher and the left sole 2 cm further forward (same byte count)."""
    assert _NECK in text and _LEFT_SOLE in text
    return (text.replace(_NECK, _NECK.replace("0.3795", "0.4795"))
            .replace(_LEFT_SOLE, _LEFT_SOLE.replace('pos="0.03 ', 'pos="0.05 '), 1))


def test_initial_pose_facts_follow_a_model_file_rewritten_at_the_same_path(tmp_path):
    # The caches were keyed by the path: a model regenerated at the same path kept the first file's sole centre and
    # heights for the rest of the process. The rewrite keeps the size and may keep the modification time.
    shipped = robot.asset_path("tocabi", "tocabi.xml").read_text()
    path = tmp_path / "model.xml"
    path.write_text(shipped)
    sole = robot.initial_sole_centre(0, path)
    extents = robot.initial_sole_extents(0, str(path))
    neck = robot.initial_heights(str(path))["neck_height"]
    path.write_text(_taller_neck_and_longer_left_sole(shipped))
    np.testing.assert_allclose(robot.initial_sole_centre(0, path), sole + [0.02, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(robot.initial_sole_extents(0, str(path)), extents, atol=1e-12)
    np.testing.assert_allclose(robot.initial_sole_centre(1, path), robot.initial_sole_centre(1), atol=1e-12)
    assert robot.initial_heights(str(path))["neck_height"] == pytest.approx(neck + 0.1, abs=1e-9)
    path.write_text(shipped)  # and back: the first file's values again
    np.testing.assert_allclose(robot.initial_sole_centre(0, path), sole, atol=1e-12)


def test_initial_heights_follow_the_assets_folder_and_stay_unchanged_by_callers(tmp_path, monkeypatch):
    shipped = robot.initial_heights()
    shipped["neck_height"] = 0.0  # a caller's edit of its result used to change what every later call returned
    assert robot.initial_heights()["neck_height"] == pytest.approx(1.50723, abs=1e-5)
    # None is the shipped model as $TOCABI_TORCHRL_ASSETS finds it, not the first one found in the process.
    (tmp_path / "tocabi").mkdir()
    text = robot.asset_path("tocabi", "tocabi.xml").read_text()
    (tmp_path / "tocabi" / "tocabi.xml").write_text(_taller_neck_and_longer_left_sole(text))
    monkeypatch.setenv("TOCABI_TORCHRL_ASSETS", str(tmp_path))
    assert robot.initial_heights()["neck_height"] == pytest.approx(1.60723, abs=1e-5)
    assert robot.initial_sole_centre(0)[0] == pytest.approx(0.1199, abs=1e-4)



# --- angle units --------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("compiler", DEGREE_COMPILERS.values(), ids=DEGREE_COMPILERS.keys())
def test_a_model_read_in_degrees_with_ranges_in_radians_is_refused_naming_the_file(tmp_path, compiler):
    # Every range shrank by 180/π (±3.14 to ±0.055 rad) and the env then refused the shipped walk as "reference
    # motion ...tocabi_walk.npz: ... outside the model's range ... (a motion in degrees?)": the motion was blamed.
    path = shipped_model_read_as(tmp_path, compiler)
    message = (r"robot model .*in_degrees\.xml: it is compiled with <compiler angle=\"degree\"> \(MuJoCo's default "
               r"when <compiler> sets no angle\) but its joint ranges are written in radians: L_HipPitch_Joint "
               r"range=\"-3\.14 3\.14\" becomes \[-0\.055, 0\.055\] rad, which leaves out the initial pose's -0\.240 "
               r"rad .*Set <compiler angle=\"radian\"> in .*in_degrees\.xml")
    with pytest.raises(robot.RobotAssetError, match=message):
        robot.load_model(path)
    with pytest.raises(robot.RobotAssetError, match=message):
        robot.load_spec(path)


def test_a_model_in_degrees_mixing_in_radian_ranges_is_refused_naming_both_units(tmp_path):
    # The check gave up on any range beyond a full turn (only degrees make sense of it), so a file in degrees with
    # the legs' ranges left in radians compiled them to ±0.055 rad, and the env blamed the shipped walk ("reference
    # motion ... outside the model's range ... check R_Knee_Joint's range (radians, under angle=radian)").
    path = shipped_model_mixing_units(tmp_path)
    message = (r"robot model .*mixed\.xml: it is compiled with <compiler angle=\"degree\"> .* and mixes units in its "
               r"joint ranges: Waist1_Joint range=\"-119\.977 119\.977\" is in degrees, but L_HipPitch_Joint "
               r"range=\"-3\.14 3\.14\" becomes \[-0\.055, 0\.055\] rad, which leaves out the initial pose's -0\.240 "
               r"rad \(robot\.INIT_JOINT_POS\) and any walking motion: written in radians\? 5 more joints' ranges "
               r"look the same \(L_Knee_Joint, L_AnklePitch_Joint, R_HipPitch_Joint, R_Knee_Joint, "
               r"R_AnklePitch_Joint\)\. Write each such range in degrees too \(L_HipPitch_Joint: "
               r"range=\"-179\.909 179\.909\"\)")
    with pytest.raises(robot.RobotAssetError, match=message):
        robot.load_model(path)
    with pytest.raises(robot.RobotAssetError, match=message):
        robot.load_spec(path)
    # No false alarm: a joint of a file in degrees with a narrow range (±3 degrees) that holds the initial pose.
    narrow = shipped_model_mixing_units(tmp_path, "narrow.xml", narrow="Waist1_Joint")
    assert robot.load_model(narrow).joint("Waist1_Joint").range[1] == pytest.approx(np.radians(3.0))


def test_a_model_in_degrees_throughout_compiles_to_the_shipped_ranges(tmp_path, model):
    path = shipped_model_in_degrees(tmp_path)
    np.testing.assert_allclose(robot.load_model(path).jnt_range, model.jnt_range, atol=1e-7)
    assert robot.load_spec(path).compiler.degree
