"""MujocoSim (C MuJoCo on CPU threads): the WarpSim interface, exact C stepping, threads, health, errors.

The interface tests of ``test_sim.py`` (masked reset, contact signals against a scan of the contact list, foot F/T
against the weight, health, forward after direct writes, reset argument errors) only read the public tensors; they are
imported below and run here against this module's ``sim`` fixture, a MujocoSim of 4 worlds.
"""

from __future__ import annotations

import math
import re

import mujoco
import numpy as np
import pytest
import torch

from test_sim import (  # noqa: F401  (imported tests run against this module's `sim` fixture)
    LEGS,
    N,
    _init_qpos,
    _pd_hold,
    _reset_standing,
    _upper_ctrl,
    test_crossed_legs_report_self_collision,
    test_forward_refreshes_after_direct_writes,
    test_infinite_velocity_flags_only_that_world,
    test_masked_reset_touches_only_flagged_worlds,
    test_reset_rejects_bad_arguments,
    test_reset_refuses_a_non_finite_state_of_a_flagged_world,
    test_robot_dropped_on_its_back_reports_forbidden_contact,
    test_standing_robot_feet_in_contact_and_forces_carry_the_weight,
)
from tocabi_torchrl import robot
from tocabi_torchrl.sim import MujocoSim, SimConfig, SimOverflowError, add_contact_sensors
from tocabi_torchrl.sim.config import available_cores


@pytest.fixture(scope="module")
def sim() -> MujocoSim:
    return MujocoSim(SimConfig(num_worlds=N, threads=2))


def _random_legs(rng: np.random.Generator, n: int = N, scale: float = 1.0) -> torch.Tensor:
    ctrl = _upper_ctrl(n)
    ctrl[:, LEGS] = torch.as_tensor(rng.uniform(-scale, scale, (n, 12)) * robot.LEG_TORQUE_LIMITS, dtype=torch.float32)
    return ctrl


def test_views_have_the_warp_backends_shapes_and_dtypes(sim):
    m = sim.mj_model
    shapes = {
        "qpos": (N, m.nq), "qvel": (N, m.nv), "ctrl": (N, m.nu), "sensordata": (N, m.nsensordata),
        "xpos": (N, m.nbody, 3), "xquat": (N, m.nbody, 4), "base_pos": (N, 3), "base_quat": (N, 4),
        "neck_pos": (N, 3), "neck_quat": (N, 4), "foot_pos": (N, 2, 3), "foot_force": (N, 2, 3),
        "foot_torque": (N, 2, 3),
        "contact_counts": (N, sim.contact_layout.count), "time": (N,), "applied_actuator_force": (N, m.nu),
    }
    for name, shape in shapes.items():
        t = getattr(sim, name)
        assert t.shape == shape and t.dtype == torch.float32 and t.device.type == "cpu", name
    for name, shape in {"foot_contact": (N, 2), "forbidden_ground_contact": (N,), "self_collision": (N,),
                        "healthy": (N,)}.items():
        assert getattr(sim, name).shape == shape and getattr(sim, name).dtype == torch.bool, name
    assert sim.overflow.dtype == torch.int32 and sim.overflow.shape == (N,)
    assert sim.device == torch.device("cpu") and sim.control_dt == pytest.approx(8 * sim.physics_dt)
    # Derived tensors are windows into the primary buffers, as in WarpSim.
    fid = mujoco.mj_name2id(sim.mj_model, mujoco.mjtObj.mjOBJ_SENSOR, robot.FOOT_FORCE_SENSORS[1])
    adr = sim.mj_model.sensor_adr[fid]
    assert torch.equal(sim.foot_force[:, 1], sim.sensordata[:, adr : adr + 3])
    base = mujoco.mj_name2id(sim.mj_model, mujoco.mjtObj.mjOBJ_BODY, robot.BASE_BODY)
    assert sim.base_pos.data_ptr() == sim.xpos[:, base].data_ptr()
    left, right = (mujoco.mj_name2id(sim.mj_model, mujoco.mjtObj.mjOBJ_BODY, b) for b in robot.FOOT_BODIES)
    assert torch.equal(sim.foot_pos, sim.xpos[:, [left, right]])
    assert sim.foot_pos.data_ptr() == sim.xpos[:, left].data_ptr()  # a window: it follows every step


def _forward_and_warm_start(m, d):
    """mj_forward whose constraint solution warm-starts the next step, as the backend's forward passes do."""
    mujoco.mj_forward(m, d)
    d.qacc_warmstart[:] = d.qacc


def test_step_is_mj_step_times_substeps_then_forward(sim):
    """Float64 C stepping, published as float32: equal to raw mj_step x 8 + mj_forward cast to float32, each forward
    pass's constraint solution warm-starting the next step."""
    _reset_standing(sim)
    m = sim.mj_model
    raw = [mujoco.MjData(m) for _ in range(N)]
    for w, d in enumerate(raw):
        d.qpos[:] = sim.qpos[w].numpy()  # the reset took these float32 values exactly
        d.ctrl[:] = sim.ctrl[w].numpy()
        _forward_and_warm_start(m, d)
    rng = np.random.default_rng(0)
    for _ in range(6):
        ctrl = _random_legs(rng)
        sim.ctrl.copy_(ctrl)
        sim.step()
        for w, d in enumerate(raw):
            d.ctrl[:] = ctrl[w].numpy()
            for _ in range(sim.config.substeps):
                mujoco.mj_step(m, d)
        applied = np.stack([d.actuator_force for d in raw])
        for d in raw:
            _forward_and_warm_start(m, d)
    for name, field in (("qpos", "qpos"), ("qvel", "qvel"), ("sensordata", "sensordata"), ("xpos", "xpos")):
        expected = torch.from_numpy(np.stack([getattr(d, field) for d in raw])).float()
        assert torch.equal(getattr(sim, name), expected), name
    assert torch.equal(sim.applied_actuator_force, torch.from_numpy(applied).float())
    # The state inside each world stays float64 (no rounding to the float32 tensors between steps).
    for w, d in enumerate(raw):
        assert np.array_equal(sim.mj_data[w].qpos, d.qpos)
    assert torch.allclose(sim.time, torch.full((N,), 6 * sim.control_dt))


def test_reset_of_other_worlds_keeps_float64_state(sim):
    """A masked reset neither rounds the untouched worlds to float32 nor changes their future."""
    _reset_standing(sim)
    rng = np.random.default_rng(2)
    sim.ctrl.copy_(_random_legs(rng, scale=0.3))
    sim.step()
    before = [d.qpos.copy() for d in sim.mj_data]
    sim.reset(torch.tensor([True, False, False, False]), _init_qpos(), torch.zeros(sim.nv), _upper_ctrl())
    for w in (1, 2, 3):
        assert np.array_equal(sim.mj_data[w].qpos, before[w])
        assert not np.array_equal(sim.mj_data[w].qpos, sim.mj_data[w].qpos.astype(np.float32)), "float64 kept"


def test_thread_count_does_not_change_results():
    assert MujocoSim(SimConfig(num_worlds=3)).threads == min(available_cores(), 3)
    sims = [MujocoSim(SimConfig(num_worlds=5, threads=t)) for t in (1, 2, 3)]
    assert [s.threads for s in sims] == [1, 2, 3]
    rng = np.random.default_rng(4)
    for s in sims:
        _reset_standing(s)
    for k in range(4):
        ctrl = _random_legs(rng, n=5, scale=0.5)
        for s in sims:
            s.ctrl.copy_(ctrl)
            s.step()
            s.reset(torch.tensor([k == 2, False, True, False, False]), _init_qpos(5), torch.zeros(s.nv), _upper_ctrl(5))
    for name in ("qpos", "qvel", "sensordata", "foot_contact", "healthy"):
        assert torch.equal(getattr(sims[0], name), getattr(sims[1], name)), name
        assert torch.equal(getattr(sims[0], name), getattr(sims[2], name)), name
    for s in sims:
        s.close()


def test_diverged_world_is_unhealthy_until_reset_with_a_clear_error(sim):
    _reset_standing(sim)
    sim.check_overflow()
    sim.qvel[1, 10] = float("inf")
    _pd_hold(sim)
    sim.ctrl[1].zero_()
    sim.step()
    # C MuJoCo reset world 1 to the default pose itself: finite, but flagged through its warning counter.
    assert torch.isfinite(sim.qpos).all()
    assert sim.healthy.tolist() == [True, False, True, True]
    assert int(sim.overflow[1]) & (1 << int(mujoco.mjtWarning.mjWARN_BADQVEL))
    with pytest.raises(SimOverflowError, match=r"1 world\(s\).*worlds 1\).*mjWARN_BADQVEL"):
        sim.check_overflow()
    sim.step()
    assert not sim.healthy[1], "the flag is sticky until the world is reset"
    _reset_standing(sim, torch.tensor([False, True, False, False]))
    assert sim.healthy.all()
    sim.check_overflow()


def test_sensors_every_substep_changes_nothing_visible(sim):
    every = MujocoSim(SimConfig(num_worlds=N, threads=1, sensors_every_substep=True))
    rng = np.random.default_rng(5)
    for s in (sim, every):
        _reset_standing(s)
    for _ in range(3):
        ctrl = _random_legs(rng, scale=0.3)
        for s in (sim, every):
            s.ctrl.copy_(ctrl)
            s.step()
    assert torch.equal(sim.sensordata, every.sensordata) and torch.equal(sim.qpos, every.qpos)


@pytest.mark.parametrize(
    "config, error, message",
    [
        (SimConfig(num_worlds=0), ValueError, "num_worlds must be a positive int"),
        (SimConfig(threads=0), ValueError, "threads must be a positive int"),
        (SimConfig(threads=1.5), ValueError, "threads must be a positive int"),
        (SimConfig(device="cuda"), ValueError, "C engine on the CPU.*WarpSim"),
        (SimConfig(device="tpu"), ValueError, "unknown device 'tpu'"),
        # These were taken: "no" is truthy (sensors in every substep), an infinite tolerance stopped the solver after
        # one iteration, True set it to 1.0, and text failed as a raw comparison error.
        (SimConfig(sensors_every_substep="no"), ValueError, "SimConfig.sensors_every_substep must be True or False"),
        (SimConfig(use_graph="false"), ValueError, "SimConfig.use_graph must be True or False, got 'false'"),
        (SimConfig(health_overflow_mask=1.5), ValueError, r"SimConfig.health_overflow_mask must be an int.*got 1.5"),
        (SimConfig(solver_tolerance=math.inf), ValueError, r"SimConfig.solver_tolerance must be a finite number >= 0"),
        (SimConfig(solver_tolerance=True), ValueError, r"SimConfig.solver_tolerance must be .*got True"),
        (SimConfig(solver_tolerance="1e-8"), ValueError, r"SimConfig.solver_tolerance must be .*got '1e-8'"),
    ],
)
def test_bad_configuration_is_refused(config, error, message):
    with pytest.raises(error, match=message):
        MujocoSim(config)


def test_models_and_solver_overrides_as_in_warp():
    model = add_contact_sensors(robot.load_spec()).compile()
    s = MujocoSim(SimConfig(num_worlds=1, solver_iterations=7), model=model)
    assert s.mj_model.opt.iterations == 7 and model.opt.iterations != 7
    with pytest.raises(ValueError, match="add_contact_sensors"):
        MujocoSim(SimConfig(), model=robot.load_model())


def test_a_model_of_another_robot_is_refused_as_not_tocabi(tmp_path):
    # These failed looking up the contact sensors' bodies: a long list with base_link twice, naming neither the file
    # nor that the model is not TOCABI (an MjModel was told to add the contact sensors, which then failed so).
    other = tmp_path / "other.xml"
    other.write_text('<mujoco><worldbody><body name="ball"><freejoint/><geom size="0.1"/></body></worldbody></mujoco>')
    sources = ((other, re.escape(repr(str(other)))), (mujoco.MjSpec.from_file(str(other)), "mujoco.MjSpec"),
               (mujoco.MjModel.from_xml_path(str(other)), "mujoco.MjModel"))
    for source, where in sources:
        with pytest.raises(robot.RobotAssetError, match=f"{where}.* is not a TOCABI model: it lacks joint "
                                                         r"'L_HipYaw_Joint'.* and \d+ more; pass a TOCABI MJCF"):
            MujocoSim(SimConfig(), model=source)


def test_per_substep_controls_are_left_in_ctrl_after_a_step_as_in_warp():
    # WarpSim's substeps write the substep_ctrl columns of ctrl itself (the memory its physics reads), so after a step
    # they hold the last substep's controls, which the post-step forward pass used. Here they kept the caller's
    # values, so a forward() of the unchanged state recomputed it with other torques: the foot F/T moved by 12 N.
    sim = MujocoSim(SimConfig(num_worlds=2, threads=1, substep_ctrl=(0, 1)))
    _reset_standing(sim)
    _pd_hold(sim)
    sim.substep_ctrl.copy_(torch.linspace(-50.0, 50.0, 8).view(1, 8, 1).expand(2, 8, 2))
    sim.step()
    assert torch.equal(sim.ctrl[:, :2], torch.full((2, 2), 50.0))
    after_step = sim.foot_force.clone()
    sim.forward()
    torch.testing.assert_close(sim.foot_force, after_step, rtol=0, atol=1e-3)
