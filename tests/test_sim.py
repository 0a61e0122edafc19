"""WarpSim on warp's CPU device: zero-copy views, masked reset, contact signals, foot forces, health, errors.

One module-scoped simulator of 4 worlds serves most tests (the first build compiles mujoco-warp's kernels, ~1 min on
a cold cache); every test starts by resetting the worlds it uses. The interface tests (reset, contacts, health,
forward) only use the public tensors, so ``test_sim_mujoco.py`` runs them against ``MujocoSim`` too.
"""

from __future__ import annotations

import math

import mujoco
import mujoco_warp as mjw
import numpy as np
import pytest
import torch
import warp as wp

from tocabi_torchrl import robot
from tocabi_torchrl.sim import (
    ContactSensorError,
    MujocoSim,
    SimConfig,
    SimOverflowError,
    WarpSim,
    add_contact_sensors,
)
from tocabi_torchrl.sim.buffers import permanent_constraint_rows
from tocabi_torchrl.sim.kernel_cache import announce_compile_if_cold, quiet_warp_info
from tocabi_torchrl.sim.model import compile_model

from warp_substeps import after_each_substep

N = 4
LEGS = slice(0, robot.NUM_LEG_JOINTS)
UPPER = slice(robot.NUM_LEG_JOINTS, robot.NUM_JOINTS)


@pytest.fixture(scope="module")
def sim() -> WarpSim:
    return WarpSim(SimConfig(num_worlds=N, device="cpu"))


def _init_qpos(n: int = N) -> torch.Tensor:
    return torch.as_tensor(robot.INIT_QPOS, dtype=torch.float32).repeat(n, 1)


def _upper_ctrl(n: int = N) -> torch.Tensor:
    ctrl = torch.zeros(n, robot.NUM_JOINTS)
    ctrl[:, UPPER] = torch.as_tensor(robot.INIT_JOINT_POS[UPPER], dtype=torch.float32)
    return ctrl


def _reset_standing(sim: WarpSim, mask: torch.Tensor | None = None) -> None:
    mask = torch.ones(sim.num_worlds, dtype=torch.bool) if mask is None else mask
    sim.reset(mask, _init_qpos(sim.num_worlds), torch.zeros(sim.nv), _upper_ctrl(sim.num_worlds))


def _pd_hold(sim: WarpSim) -> None:
    """Legs PD-held on the initial pose (torque written once per control step), upper body on its servo targets."""
    kp = torch.as_tensor(robot.LEG_KP, dtype=torch.float32)
    kv = torch.as_tensor(robot.LEG_KV, dtype=torch.float32)
    q0 = torch.as_tensor(robot.INIT_JOINT_POS[LEGS], dtype=torch.float32)
    sim.ctrl[:, LEGS] = kp * (q0 - sim.qpos[:, 7:19]) - kv * sim.qvel[:, 6:18]
    sim.ctrl[:, UPPER] = _upper_ctrl(sim.num_worlds)[:, UPPER]


def _quat(axis, angle) -> list[float]:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return [math.cos(angle / 2), *(math.sin(angle / 2) * axis)]


def _contact_geoms(sim) -> tuple[np.ndarray, np.ndarray]:
    """(ncon, 2) geom pairs and (ncon,) world ids of every active contact, from either backend."""
    if isinstance(sim, MujocoSim):
        pairs = [(d.contact.geom[: d.ncon][d.contact.exclude[: d.ncon] == 0], w) for w, d in enumerate(sim.mj_data)]
        geoms = np.concatenate([g for g, _ in pairs]).reshape(-1, 2)
        return geoms, np.concatenate([np.full(len(g), w) for g, w in pairs]).astype(int)
    d = sim.wp_data
    nacon = int(d.nacon.numpy()[0])
    return d.contact.geom.numpy()[:nacon], d.contact.worldid.numpy()[:nacon]


def _scan_contacts(sim) -> np.ndarray:
    """(N, 4) counts of (left foot, right foot, forbidden ground, self) contacts in the engine's contact list."""
    m = sim.mj_model
    geoms, worlds = _contact_geoms(sim)
    body = lambda n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n)  # noqa: E731
    feet = [body(b) for b in robot.FOOT_BODIES]
    forbidden = {body(b) for b in robot.GROUND_FORBIDDEN_BODIES}
    self_bodies = {body(b) for b in robot.SELF_COLLISION_BODIES}
    counts = np.zeros((sim.num_worlds, 4))
    for (g1, g2), w in zip(geoms, worlds):
        b1, b2 = m.geom_bodyid[g1], m.geom_bodyid[g2]
        if 0 in (b1, b2):
            other = b2 if b1 == 0 else b1
            counts[w] += [other == feet[0], other == feet[1], other in forbidden, 0]
        elif b1 in self_bodies and b2 in self_bodies:
            counts[w, 3] += 1
    return counts


def _signal_counts(sim: WarpSim) -> np.ndarray:
    lay = sim.contact_layout
    return sim.contact_counts.numpy() @ lay.weights.T


# ---------------------------------------------------------------------------------------------------- memory
def test_views_alias_warp_memory(sim):
    d = sim.wp_data
    for view, arr in ((sim.qpos, d.qpos), (sim.qvel, d.qvel), (sim.ctrl, d.ctrl), (sim.sensordata, d.sensordata)):
        assert view.data_ptr() == arr.ptr
    assert sim.xpos.data_ptr() == d.xpos.ptr and sim.xquat.data_ptr() == d.xquat.ptr
    assert sim.xpos.shape == (N, sim.mj_model.nbody, 3) and sim.xquat.shape == (N, sim.mj_model.nbody, 4)
    # Writes through torch are what warp reads, and the reverse.
    sim.ctrl[2, 5] = 12.5
    assert d.ctrl.numpy()[2, 5] == 12.5
    sim.ctrl[2, 5] = 0.0
    # Derived views are windows into the same buffers, not copies.
    sd_lo, sd_hi = sim.sensordata.data_ptr(), sim.sensordata.data_ptr() + sim.sensordata.numel() * 4
    for v in (sim.foot_force, sim.foot_torque, sim.contact_counts):
        assert sd_lo <= v.data_ptr() < sd_hi
    fid = mujoco.mj_name2id(sim.mj_model, mujoco.mjtObj.mjOBJ_SENSOR, robot.FOOT_FORCE_SENSORS[1])
    adr = sim.mj_model.sensor_adr[fid]
    assert torch.equal(sim.foot_force[:, 1], sim.sensordata[:, adr : adr + 3])
    base = mujoco.mj_name2id(sim.mj_model, mujoco.mjtObj.mjOBJ_BODY, robot.BASE_BODY)
    assert sim.base_pos.data_ptr() == sim.xpos[:, base].data_ptr()
    assert sim.healthy.dtype == torch.bool and sim.healthy.shape == (N,)
    assert sim.foot_contact.shape == (N, 2) and sim.foot_contact.dtype == torch.bool


def test_step_is_bit_identical_to_raw_mujoco_warp(sim):
    """step() = substeps x mujoco_warp.step, then a forward pass (positions and sensors of the new state) whose
    constraint solution warm-starts the next step."""
    _reset_standing(sim)
    raw = mjw.make_data(sim.mj_model, nworld=N, nconmax=sim.config.nconmax, njmax=sim.config.njmax)
    wp.copy(raw.qpos, sim.wp_data.qpos)
    wp.copy(raw.ctrl, sim.wp_data.ctrl)

    def forward_and_warm_start():  # the backend's forward passes leave their solution as the solver's warm start
        mjw.forward(sim.wp_model, raw)
        wp.copy(raw.qacc_warmstart, raw.qacc)

    forward_and_warm_start()
    rng = np.random.default_rng(0)
    for _ in range(6):
        ctrl = _upper_ctrl()
        ctrl[:, LEGS] = torch.as_tensor(rng.uniform(-1, 1, (N, 12)) * robot.LEG_TORQUE_LIMITS, dtype=torch.float32)
        sim.ctrl.copy_(ctrl)
        raw.ctrl.assign(ctrl.numpy())
        sim.step()
        for _ in range(sim.config.substeps):
            mjw.step(sim.wp_model, raw)
        applied = raw.actuator_force.numpy().copy()  # on the CPU device .numpy() is a view
        forward_and_warm_start()
    assert np.array_equal(sim.applied_actuator_force.numpy(), applied)
    assert np.array_equal(sim.qpos.numpy(), raw.qpos.numpy())
    assert np.array_equal(sim.qvel.numpy(), raw.qvel.numpy())
    assert np.array_equal(sim.sensordata.numpy(), raw.sensordata.numpy())
    assert np.array_equal(sim.xpos.numpy(), raw.xpos.numpy())
    assert np.allclose(sim.time.numpy(), 6 * sim.control_dt)


def test_recorded_graphs_and_eager_calls_agree(sim):
    """use_graph=False runs the very same functions launch by launch; the replayed recording matches it bit for bit."""
    eager = WarpSim(SimConfig(num_worlds=N, use_graph=False))
    assert eager._step_graph.graph is None and sim._step_graph.graph is not None
    rng = np.random.default_rng(3)
    for s_ in (sim, eager):
        _reset_standing(s_)
    for k in range(4):
        ctrl = _upper_ctrl()
        ctrl[:, LEGS] = torch.as_tensor(rng.uniform(-1, 1, (N, 12)) * robot.LEG_TORQUE_LIMITS, dtype=torch.float32)
        mask = torch.tensor([k % 2 == 0, False, True, False])
        for s_ in (sim, eager):
            s_.ctrl.copy_(ctrl)
            s_.step()
            s_.reset(mask, _init_qpos(), torch.zeros(s_.nv), _upper_ctrl())
    for name in ("qpos", "qvel", "sensordata", "xpos", "foot_contact", "healthy", "applied_actuator_force"):
        assert torch.equal(getattr(sim, name), getattr(eager, name)), name


def test_warm_start_is_the_solution_of_the_current_state(sim):
    """After a step the solver's warm start is the post-step solution, so a masked reset's forward pass re-solves
    the untouched worlds in one iteration (from the last substep's acceleration they took up to 5), and the
    reset worlds keep their own solution as warm start for the next step."""
    _reset_standing(sim)
    rng = np.random.default_rng(7)
    for _ in range(5):  # uneven contacts in every world
        sim.ctrl[:, LEGS] = torch.as_tensor(rng.uniform(-0.3, 0.3, (N, 12)) * robot.LEG_TORQUE_LIMITS)
        sim.step()
    d = sim.wp_data
    assert np.array_equal(d.qacc_warmstart.numpy(), d.qacc.numpy())
    warm_before = d.qacc_warmstart.numpy().copy()
    mask = torch.tensor([True, False, True, False])
    sim.reset(mask, _init_qpos(), torch.zeros(sim.nv), _upper_ctrl())
    untouched = (~mask).numpy()
    assert np.all(d.solver_niter.numpy()[untouched] <= 1), d.solver_niter.numpy()
    assert np.array_equal(d.qacc_warmstart.numpy()[untouched], warm_before[untouched])
    assert np.array_equal(d.qacc_warmstart.numpy()[mask.numpy()], d.qacc.numpy()[mask.numpy()])


def test_masked_reset_leaves_the_future_of_untouched_worlds_bit_identical(sim):
    """Twin simulators take the same controls; one resets worlds 0 and 2 midway. Worlds 1 and 3 then step on
    exactly as in the twin: the reset's forward pass over every world leaves their warm start alone."""
    twin = WarpSim(SimConfig(num_worlds=N, device="cpu"))
    rng = np.random.default_rng(11)
    controls = [torch.as_tensor(rng.uniform(-0.3, 0.3, (N, 12)) * robot.LEG_TORQUE_LIMITS, dtype=torch.float32)
                for _ in range(8)]
    for s_ in (sim, twin):
        _reset_standing(s_)
    for k, ctrl in enumerate(controls):
        for s_ in (sim, twin):
            s_.ctrl[:, LEGS] = ctrl
            s_.step()
        if k == 3:
            sim.reset(torch.tensor([True, False, True, False]), _init_qpos(), torch.zeros(sim.nv), _upper_ctrl())
    for name in ("qpos", "qvel", "sensordata"):
        assert torch.equal(getattr(sim, name)[[1, 3]], getattr(twin, name)[[1, 3]]), name
    assert not torch.equal(sim.qpos[[0, 2]], twin.qpos[[0, 2]])


# ----------------------------------------------------------------------------------------------------- reset
def test_masked_reset_touches_only_flagged_worlds(sim):
    _reset_standing(sim)
    rng = np.random.default_rng(1)
    for _ in range(5):  # make every world different
        sim.ctrl[:, LEGS] = torch.as_tensor(rng.uniform(-0.3, 0.3, (N, 12)) * robot.LEG_TORQUE_LIMITS)
        sim.step()
    views = ("qpos", "qvel", "ctrl", "sensordata", "xpos", "xquat", "time", "foot_contact", "healthy", "overflow")
    before = {k: getattr(sim, k).clone() for k in views}

    mask = torch.tensor([True, False, True, False])
    qpos = _init_qpos()
    qpos[:, 0] = torch.arange(N, dtype=torch.float32)  # a distinct x per world: only flagged rows may be read
    qvel = torch.zeros(N, sim.nv)
    qvel[:, 6] = 0.25
    ctrl = _upper_ctrl()
    sim.reset(mask, qpos, qvel, ctrl)

    for k in views:
        assert torch.equal(getattr(sim, k)[~mask], before[k][~mask]), f"{k} changed in an untouched world"
    assert torch.equal(sim.qpos[mask], qpos[mask])
    assert torch.equal(sim.qvel[mask], qvel[mask])
    assert torch.equal(sim.ctrl[mask], ctrl[mask])
    assert torch.all(sim.time[mask] == 0)
    # The forward pass ran for the reset worlds: the base body sits where qpos put it.
    assert torch.allclose(sim.base_pos[mask], qpos[mask, :3], atol=1e-6)
    # Row inputs broadcast, and ctrl defaults to zeros.
    sim.reset(torch.tensor([False, True, False, False]), qpos[0], torch.zeros(sim.nv))
    assert torch.equal(sim.qpos[1], qpos[0]) and torch.all(sim.ctrl[1] == 0)


def test_reset_rejects_bad_arguments(sim):
    mask, qpos, qvel = torch.ones(N, dtype=torch.bool), _init_qpos(), torch.zeros(N, sim.nv)
    cases = [
        ((mask[:3], qpos, qvel), ValueError, r"mask must have shape \(4,\)"),
        ((mask.float(), qpos, qvel), ValueError, "mask must have dtype torch.bool"),
        ((mask, qpos[:, :39], qvel), ValueError, r"qpos must have shape \(4, 40\) or \(40,\)"),
        ((mask, qpos, qvel[:2]), ValueError, r"qvel must have shape \(4, 39\)"),
        ((mask, qpos.long(), qvel), ValueError, "qpos must be a floating-point tensor"),
        ((mask, qpos.numpy(), qvel), TypeError, "qpos must be a torch.Tensor"),
    ]
    for args, error, message in cases:
        with pytest.raises(error, match=message):
            sim.reset(*args)
    with pytest.raises(ValueError, match=r"ctrl must have shape \(4, 33\)"):
        sim.reset(mask, qpos, qvel, torch.zeros(N, 12))


def test_reset_refuses_a_non_finite_state_of_a_flagged_world(sim):
    # On the CPU, where reading it costs no device sync. Such a world started diverged without a word: unhealthy, and
    # on C MuJoCo put back to the model's default pose (not the one asked for) by its next step.
    _reset_standing(sim)
    before = sim.qpos.clone()
    mask, qpos, qvel = torch.ones(N, dtype=torch.bool), _init_qpos(), torch.zeros(N, sim.nv)
    qpos[2, 2] = float("nan")
    with pytest.raises(ValueError, match=r"qpos holds NaN or inf for 1 flagged world\(s\) \(2\); .*pass finite"):
        sim.reset(mask, qpos, qvel)
    with pytest.raises(ValueError, match=r"qvel holds NaN or inf for 4 flagged world\(s\) \(0, 1, 2, 3\)"):
        sim.reset(mask, _init_qpos(), torch.full((sim.nv,), float("inf")))
    with pytest.raises(ValueError, match=r"ctrl holds NaN or inf for 1 flagged world\(s\) \(1\)"):
        sim.reset(mask, _init_qpos(), qvel, torch.zeros(N, sim.nu).index_fill_(0, torch.tensor([1]), float("nan")))
    assert torch.equal(sim.qpos, before) and sim.healthy.all(), "a refused reset writes nothing"
    sim.reset(torch.tensor([True, True, False, True]), qpos, qvel)  # an unflagged row is not read
    assert sim.healthy.all()


# -------------------------------------------------------------------------------------------------- contacts
def test_standing_robot_feet_in_contact_and_forces_carry_the_weight(sim):
    _reset_standing(sim)
    assert not sim.foot_contact.any(), "the soles start 1.3 mm above the ground"
    for _ in range(250):  # 1 s of PD standing
        _pd_hold(sim)
        sim.step()
    assert sim.foot_contact.all()
    assert not sim.forbidden_ground_contact.any() and not sim.self_collision.any()
    assert sim.healthy.all()
    assert torch.all((sim.base_pos[:, 2] > 0.9) & (sim.base_pos[:, 2] < 0.95))
    # Each F/T site sits in its Foot_Link: the two sensors carry everything but the feet (spec §1.5).
    m = sim.mj_model
    feet = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, b) for b in robot.FOOT_BODIES]
    weight_above = (m.body_subtreemass[0] - m.body_subtreemass[feet].sum()) * -m.opt.gravity[2]
    fz = sim.foot_force[:, :, 2].sum(dim=1)
    assert torch.all(fz < 0), "a loaded foot reads a negative z force"
    assert torch.allclose(-fz, torch.full((N,), weight_above, dtype=torch.float32), rtol=0.05), (fz, weight_above)
    assert torch.all(sim.foot_force[:, :, 2] < -0.3 * weight_above), "both feet carry load"
    np.testing.assert_array_equal(_signal_counts(sim), _scan_contacts(sim))

    # A world reset into this standing state reads the same forces right away (reset runs a forward pass).
    standing = (sim.qpos.clone(), sim.qvel.clone(), sim.ctrl.clone(), sim.foot_force.clone())
    mask = torch.tensor([False, True, False, False])
    sim.reset(mask, standing[0][0], standing[1][0], standing[2][0])
    assert torch.allclose(sim.foot_force[1], standing[3][0], atol=0.5)
    assert torch.equal(sim.foot_contact[1], torch.tensor([True, True]))


def test_robot_dropped_on_its_back_reports_forbidden_contact(sim):
    _reset_standing(sim)
    qpos = _init_qpos()
    qpos[0, 3:7] = torch.tensor(_quat((0, 1, 0), -math.pi / 2))  # face up: the pelvis back points down
    qpos[0, 2] = 0.3
    sim.reset(torch.tensor([True, False, False, False]), qpos, torch.zeros(sim.nv), _upper_ctrl())
    assert not sim.forbidden_ground_contact[0]
    landed = False
    for _ in range(100):
        _pd_hold(sim)
        sim.step()
        if sim.forbidden_ground_contact[0]:
            landed = True
            break
    assert landed, "the pelvis never touched the ground"
    assert not sim.forbidden_ground_contact[1:].any()
    assert sim.healthy.all() and not sim.self_collision.any()
    np.testing.assert_array_equal(_signal_counts(sim), _scan_contacts(sim))


def test_crossed_legs_report_self_collision(sim):
    qpos = _init_qpos()
    qpos[:, 2] = 2.0  # in the air: only the legs can touch
    j = {n: 7 + i for i, n in enumerate(robot.JOINT_NAMES)}
    qpos[2, j["L_HipRoll_Joint"]], qpos[2, j["R_HipRoll_Joint"]] = -0.25, 0.25  # legs swing across each other
    sim.reset(torch.ones(N, dtype=torch.bool), qpos, torch.zeros(sim.nv), _upper_ctrl())
    assert sim.self_collision.tolist() == [False, False, True, False]
    assert not sim.forbidden_ground_contact.any() and not sim.foot_contact.any()
    np.testing.assert_array_equal(_signal_counts(sim), _scan_contacts(sim))
    sim.step()  # stays flagged while the legs are crossed
    assert bool(sim.self_collision[2])


# ---------------------------------------------------------------------------------------------------- health
def test_infinite_velocity_flags_only_that_world(sim):
    _reset_standing(sim)
    sim.qvel[2, 10] = float("inf")
    _pd_hold(sim)
    sim.ctrl[2].zero_()  # the PD of an infinite velocity is not the point here
    sim.step()
    assert sim.healthy.tolist() == [True, True, False, True]
    sim.reset(torch.tensor([False, False, True, False]), _init_qpos(), torch.zeros(sim.nv), _upper_ctrl())
    assert sim.healthy.all()
    assert torch.isfinite(sim.qpos).all()


def test_forward_refreshes_after_direct_writes(sim):
    _reset_standing(sim)
    sim.qpos[3, 2] = 1.5
    sim.forward()
    assert sim.base_pos[3, 2] == pytest.approx(1.5)
    assert sim.neck_pos[3, 2] > sim.base_pos[3, 2]


def test_constraint_overflow_marks_only_that_world_with_a_clear_error():
    # After construction the worlds hold the model's default pose (straight legs, soles in the ground), which needs
    # 57 constraint rows (33 friction-loss rows + contacts); a robot in the air needs 33.
    sim = WarpSim(SimConfig(num_worlds=2, njmax=45))
    assert not sim.healthy.any()
    assert int(sim.overflow[0]) & int(mjw.OverflowType.NEFC)
    qpos = _init_qpos(2)
    qpos[0, 2] = 2.0
    sim.reset(torch.tensor([True, False]), qpos, torch.zeros(sim.nv), _upper_ctrl(2))
    assert sim.healthy.tolist() == [True, False]
    with pytest.raises(SimOverflowError, match=r"1 world\(s\).*worlds 1;.*njmax=45.*NEFC.*raise SimConfig.njmax"):
        sim.check_overflow()


def test_njmax_below_the_rows_of_every_state_is_refused_at_construction():
    # TOCABI has 33 friction-loss rows in every state. Below that the simulator was built with every world
    # overflowed and unhealthy, so every episode ended at its first step without a word.
    assert permanent_constraint_rows(compile_model(None, SimConfig())) == 33
    with pytest.raises(ValueError, match=r"njmax=32 cannot hold the 33 constraint rows .*friction loss.*raise njmax"):
        WarpSim(SimConfig(num_worlds=1, njmax=32))


def test_contact_pool_overflow_marks_every_world_unhealthy():
    # 16 pooled contacts per world: two robots lying on their backs need more.
    sim = WarpSim(SimConfig(num_worlds=2, nconmax=16))
    _reset_standing(sim)
    assert sim.healthy.all()
    sim.check_overflow()
    qpos = _init_qpos(2)
    qpos[:, 3:7] = torch.tensor(_quat((0, 1, 0), -math.pi / 2))
    qpos[:, 2] = 0.05  # pelvis and feet on the ground
    sim.reset(torch.ones(2, dtype=torch.bool), qpos, torch.zeros(sim.nv), _upper_ctrl(2))
    # The pool is shared, so an overflow can drop any world's contacts: every world is flagged.
    assert not sim.healthy.any()
    assert int(sim.overflow[1]) & int(mjw.OverflowType.NARROWPHASE)
    with pytest.raises(SimOverflowError, match=r"nconmax=16.*NARROWPHASE.*raise SimConfig.nconmax"):
        sim.check_overflow()
    _reset_standing(sim)
    assert sim.healthy.all(), "a reset clears the flags once the contacts fit again"


# ---------------------------------------------------------------------------------------------------- errors
@pytest.mark.parametrize(
    "config, message",
    [
        (SimConfig(num_worlds=0), "num_worlds must be a positive int"),
        (SimConfig(num_worlds=-3), "num_worlds must be a positive int"),
        (SimConfig(num_worlds=2.5), "num_worlds must be a positive int"),
        (SimConfig(substeps=0), "substeps must be a positive int"),
        (SimConfig(njmax=0), "njmax must be a positive int"),
        (SimConfig(device="tpu"), "unknown device 'tpu'"),
        (SimConfig(device="cuda:x"), "unknown device 'cuda:x'"),
    ],
)
def test_bad_configuration_is_refused(config, message):
    with pytest.raises(ValueError, match=message):
        WarpSim(config)


@pytest.mark.skipif(wp.is_cuda_available(), reason="checks the message on a machine without CUDA")
def test_cuda_without_a_gpu_is_refused():
    with pytest.raises(ValueError, match="no CUDA device"):
        WarpSim(SimConfig(device="cuda:0"))


def test_solver_overrides_are_explicit_and_leave_the_callers_model_alone():
    model = add_contact_sensors(robot.load_spec()).compile()
    sim = WarpSim(SimConfig(num_worlds=1, solver_iterations=7, solver_tolerance=1e-6), model=model)
    assert sim.mj_model.opt.iterations == 7 and sim.wp_model.opt.iterations == 7
    assert sim.mj_model.opt.tolerance == pytest.approx(1e-6)
    assert model.opt.iterations == robot.load_model().opt.iterations, "the caller's model was modified"
    plain = WarpSim(SimConfig(num_worlds=1), model=model)
    assert plain.mj_model.opt.iterations == model.opt.iterations, "no override: the model file's solver settings"


def _substep_iterations(monkeypatch, sim: WarpSim, policy_steps: int, seed: int = 0) -> list[int]:
    """Step ``sim`` (eager: ``use_graph=False``) under random full-scale leg torques and return, for every physics
    substep, the most Newton iterations any world took (``solver_niter`` read right after ``mjw.step``/``step2``,
    before the step's closing forward pass overwrites it)."""
    seen = []
    after_each_substep(monkeypatch, lambda d: seen.append(int(d.solver_niter.numpy().max())))
    _reset_standing(sim)
    rng = np.random.default_rng(seed)
    for _ in range(policy_steps):
        sim.ctrl[:, LEGS] = torch.as_tensor(rng.uniform(-1, 1, (N, 12)) * robot.LEG_TORQUE_LIMITS, dtype=torch.float32)
        sim.step()
    monkeypatch.undo()
    assert len(seen) == policy_steps * sim.config.substeps, "one record per substep"
    return seen


def test_an_iteration_cap_bounds_every_substep_of_a_step(monkeypatch):
    """``solver_iterations`` reaches the sensor-free model the substeps run with: capped at 4, no substep of stumbling
    robots iterates more; with the model's own cap (20) some substep of the same robots does."""
    capped = _substep_iterations(monkeypatch, WarpSim(SimConfig(num_worlds=N, use_graph=False, solver_iterations=4)), 6)
    free = _substep_iterations(monkeypatch, WarpSim(SimConfig(num_worlds=N, use_graph=False)), 6)
    assert 1 <= max(capped) <= 4, capped
    assert max(free) > 4, free


def test_bad_model_is_refused():
    with pytest.raises(ContactSensorError, match="add_contact_sensors"):
        WarpSim(SimConfig(), model=robot.load_model())
    with pytest.raises(TypeError, match="model must be"):
        WarpSim(SimConfig(), model=42)


def test_cold_kernel_cache_prints_one_line(tmp_path, capsys, monkeypatch):
    device = wp.get_device("cpu")
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path))
    assert announce_compile_if_cold(device)
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and "compiling mujoco-warp kernels" in out[0] and str(tmp_path) in out[0]


@pytest.mark.skipif(not hasattr(wp.config, "log_level"), reason="this warp has quiet, not log_level")
def test_warps_default_info_lines_are_lowered_to_warnings_and_a_users_level_is_kept(monkeypatch):
    # At warp's default level every simulator built printed a banner and ~50 "Module ... load on device" lines.
    monkeypatch.setattr(wp.config, "log_level", wp.LOG_INFO)
    quiet_warp_info()
    assert wp.config.log_level == wp.LOG_WARNING
    monkeypatch.setattr(wp.config, "log_level", wp.LOG_DEBUG)
    quiet_warp_info()
    assert wp.config.log_level == wp.LOG_DEBUG
    # What a simulator does before warp initialises.
    from tocabi_torchrl.sim import warp_backend

    monkeypatch.setattr(wp.config, "log_level", wp.LOG_INFO)
    warp_backend._resolve_device("cpu")
    assert wp.config.log_level == wp.LOG_WARNING


def _tangled_qpos(n: int, seed: int = 0) -> torch.Tensor:
    """Robots in the air with random joint angles (sd 0.6 rad): limbs close to each other, the state that gives the
    convex narrowphase (box and cylinder pairs) the most candidates (lab.sim_measure.measure_buffers' tangled)."""
    rng = np.random.default_rng(seed)
    qpos = _init_qpos(n)
    qpos[:, 7:] += torch.as_tensor(rng.normal(0.0, 0.6, (n, robot.NUM_JOINTS)), dtype=torch.float32)
    qpos[:, 2] = 1.5
    return qpos


def test_convex_collision_slots_default_to_the_measured_count_and_overflow_names_their_setting():
    from tocabi_torchrl.sim.buffers import NCCDMAX, NCONMAX
    from tocabi_torchrl.sim.memory import epa_slot_bytes, warp_world_bytes

    assert SimConfig().ccd_per_world == NCCDMAX < NCONMAX
    assert SimConfig(nconmax=8).ccd_per_world == 8  # never above the contact pool it is taken from
    for bad, message in ((0, "nccdmax must be a positive int"), (NCONMAX + 1, r"nccdmax \(49\) must be <= nconmax")):
        with pytest.raises(ValueError, match=message):
            SimConfig(nccdmax=bad).validate()
    # The EPA scratch is counted in the memory estimate: ~5 KB per slot for TOCABI (35 EPA iterations).
    sim = WarpSim(SimConfig(num_worlds=2, nccdmax=1))
    assert sim.wp_data.naccdmax == 2
    mj = sim.mj_model
    assert 4000 < epa_slot_bytes(mj) < 6000
    assert warp_world_bytes(mj, NCONMAX, 224, 16) - warp_world_bytes(mj, NCONMAX, 224, 0) == 16 * epa_slot_bytes(mj)
    # Two tangled robots ask for more convex-collision pairs of one geom-type pair than one slot per world.
    qpos = _tangled_qpos(2)
    sim.reset(torch.ones(2, dtype=torch.bool), qpos, torch.zeros(sim.nv), _upper_ctrl(2))
    assert int(sim.overflow[0]) & int(mjw.OverflowType.CCD) and not sim.healthy.any()
    with pytest.raises(SimOverflowError, match=r"CCD.*raise SimConfig.nccdmax \(env.sim.nccdmax\)"):
        sim.check_overflow()
    # The measured default holds them.
    roomy = WarpSim(SimConfig(num_worlds=2))
    roomy.reset(torch.ones(2, dtype=torch.bool), qpos, torch.zeros(roomy.nv), _upper_ctrl(2))
    assert roomy.wp_data.naccdmax == 2 * NCCDMAX
    assert not any(int(bits) & int(mjw.OverflowType.CCD) for bits in roomy.overflow)
