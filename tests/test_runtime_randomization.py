"""The sim-to-sim driver's randomisation and pushes (``runtime/randomization.py``) against hand computations and
their distributions, the contract's ``trained_under`` section (written, checked, read; older contracts load as "not
stated"), and ``recipes/sim2sim.py``'s options. CPU, a few robots, short episodes."""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest

pytest.importorskip("onnxruntime")

from recipe_runner import load_recipe

from tocabi_torchrl import robot
from tocabi_torchrl.runtime import ContractError, load_contract
from tocabi_torchrl.runtime import randomization as rnd
from tocabi_torchrl.runtime.mujoco_driver import build_model, run_sim2sim

ROOT = Path(__file__).resolve().parents[1]
S = 8  # physics substeps per control period of the shipped policies
DT = 0.004  # control period [s]


def _contract(name: str) -> Path:
    return robot.asset_path("policies", f"tocabi_walk_{name}.json")


def _model(name: str = "torque") -> mujoco.MjModel:
    return build_model(load_contract(_contract(name)), robot.asset_path("tocabi", "tocabi.xml"))


def _with_section(tmp_path: Path, name: str, section: dict | None) -> Path:
    """A copy of a shipped contract (with its ONNX file beside it) holding ``section`` as ``trained_under``."""
    contract = json.loads(_contract(name).read_text())
    if section is not None:
        contract["trained_under"] = section
    out = tmp_path / f"tocabi_walk_{name}.json"
    out.write_text(json.dumps(contract))
    shutil.copy(_contract(name).with_suffix(".onnx"), tmp_path)
    return out


def _older(tmp_path: Path, name: str) -> Path:
    """A copy of a shipped contract as exported before it stated what training randomised (no section)."""
    contract = json.loads(_contract(name).read_text())
    contract.pop("trained_under", None)
    out = tmp_path / "older" / f"tocabi_walk_{name}.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(contract))
    shutil.copy(_contract(name).with_suffix(".onnx"), out.parent)
    return out


def _lab_section(**pushes) -> dict:
    return rnd.trained_under_section(rnd.TOCABI_LAB, rnd.PushSettings(**pushes), rnd.ROBUST_START, 0.0005, 104.5,
                                     (100, 1000))


# ------------------------------------------------------------------------------------------------- actuators
@pytest.mark.parametrize("k", [0, 1, 5, 8, 13, 20])
def test_delay_shifts_the_torque_by_exactly_k_substeps(k):
    layer = rnd.ActuatorLayer(rnd.ActuatorSettings(delay_substeps=(k, k), saturate=False), S, [1e9] * 2)
    layer.reset(np.random.default_rng(0), 1)
    commands = np.arange(1.0, 7.0)[:, None] * [1.0, -2.0]  # (periods, J): a new command every period
    out = np.concatenate([layer(cmd[None], np.zeros((1, 2)))[0] for cmd in commands])  # (periods * S, J)
    held = np.repeat(commands, S, axis=0)  # the undelayed command of every substep
    expected = np.concatenate([np.zeros((k, 2)), held[: len(held) - k]])  # zero torque before the first command
    np.testing.assert_array_equal(out, expected)


@pytest.mark.parametrize("k", [0, 3, 8, 20])
def test_delay_equals_the_training_actuator_stage(k):
    torch = pytest.importorskip("torch")
    from tocabi_torchrl.control.actuators import Delay
    from tocabi_torchrl.control.base import ControlContext, ControlInput

    stage = Delay(k, k, S)
    stage.setup(ControlContext(num_envs=1, device=torch.device("cpu"), joint_ids=(0, 1),
                               torque_limits=torch.tensor([1e9, 1e9]), joint_range=torch.tensor([[-1.0, 1.0]] * 2)))
    stage.reset(torch.ones(1, dtype=torch.bool), torch.zeros(1, 1))
    layer = rnd.ActuatorLayer(rnd.ActuatorSettings(delay_substeps=(k, k), saturate=False), S, [1e9] * 2)
    layer.reset(np.random.default_rng(0), 1)
    for cmd in np.random.default_rng(1).normal(size=(5, 1, 2)):
        ours = layer(cmd, np.zeros((1, 2)))
        theirs = stage(torch.tensor(cmd, dtype=torch.float32), ControlInput(action=None)).double().numpy()
        np.testing.assert_allclose(ours, theirs, rtol=1e-6)


def test_delay_draws_every_whole_substep_of_its_range():
    layer = rnd.ActuatorLayer(rnd.ActuatorSettings(delay_substeps=(4, 20)), S, [300.0] * 12)
    layer.reset(np.random.default_rng(0), 2000)
    assert set(layer.delay.tolist()) == set(range(4, 21))
    assert layer.history.shape == (2000, 4, 12)  # the newest command and ceil(20 / 8) = 3 before it


def test_a_delay_stride_draws_the_grid_alone_and_matches_the_training_stage():
    torch = pytest.importorskip("torch")
    from tocabi_torchrl.control.actuators import Delay

    layer = rnd.ActuatorLayer(rnd.ActuatorSettings(delay_substeps=(4, 20), delay_stride=8), S, [300.0] * 12)
    layer.reset(np.random.default_rng(0), 600)
    assert set(layer.delay.tolist()) == set(Delay(4, 20, S, stride=8).values()) == {4, 12, 20}
    assert len(set((layer.delay % S).tolist())) == 1  # every robot's torque changes in the same substep
    # The stride-1 draw is the same numbers as before the stride existed: U{low, ..., high} from rng.integers.
    one = rnd.ActuatorLayer(rnd.ActuatorSettings(delay_substeps=(4, 20)), S, [300.0] * 12)
    one.reset(np.random.default_rng(5), 50)
    np.testing.assert_array_equal(one.delay, np.random.default_rng(5).integers(4, 21, size=50))


def test_a_delay_stride_is_stated_and_read_back(tmp_path):
    lab = rnd.Randomization(dataclasses.replace(rnd.TOCABI_LAB.actuators, delay_stride=8), rnd.TOCABI_LAB.dynamics,
                            rnd.TOCABI_LAB.sensors)
    section = rnd.trained_under_section(lab, rnd.PushSettings(), rnd.ROBUST_START, 0.0005, 104.5)
    assert section["actuators"]["delay"]["stride_substeps"] == 8
    assert "stride_substeps" not in _lab_section()["actuators"]["delay"]  # a stride of 1 is the unstated default
    path = _with_section(tmp_path, "torque", json.loads(json.dumps(section)))
    assert rnd.from_contract(load_contract(path))[0] == lab
    for sub in ("bad", "zero"):
        (tmp_path / sub).mkdir()
    bad = _with_section(tmp_path / "bad", "torque", _edit(section, "actuators.delay.stride_substeps", 5))
    with pytest.raises(ContractError,
                       match=r"stride_substeps: stride 5 does not divide the delay range \(4, 20\).*re-export"):
        load_contract(bad)
    zero = _with_section(tmp_path / "zero", "torque", _edit(section, "actuators.delay.stride_substeps", 0))
    with pytest.raises(ContractError, match="stride_substeps is 0 but must be an int >= 1"):
        load_contract(zero)


@pytest.mark.parametrize("k", [0, 3, 8, 13, 16, 20])
def test_an_averaged_delay_equals_the_training_stage(k):
    torch = pytest.importorskip("torch")
    from tocabi_torchrl.control.actuators import AveragedDelay
    from tocabi_torchrl.control.base import ControlContext, ControlInput

    stage = AveragedDelay(k, max(k, 16), S)
    stage.setup(ControlContext(num_envs=1, device=torch.device("cpu"), joint_ids=(0, 1),
                               torque_limits=torch.tensor([1e9, 1e9]), joint_range=torch.tensor([[-1.0, 1.0]] * 2)))
    stage.reset(torch.ones(1, dtype=torch.bool), torch.zeros(1, 1))  # u = 0: k = low
    layer = rnd.ActuatorLayer(rnd.ActuatorSettings(delay_substeps=(k, k), delay_average=True, saturate=False), S,
                              [1e9] * 2)
    layer.reset(np.random.default_rng(0), 1)
    for cmd in np.random.default_rng(1).normal(size=(5, 1, 2)):
        ours = layer(cmd, np.zeros((1, 2)))
        theirs = stage(torch.tensor(cmd, dtype=torch.float32), ControlInput(action=None)).double().numpy()
        np.testing.assert_allclose(ours, np.broadcast_to(theirs[:, None], ours.shape), rtol=1e-6, atol=1e-7)


def test_an_averaged_delay_is_stated_and_read_back(tmp_path):
    lab = rnd.Randomization(dataclasses.replace(rnd.TOCABI_LAB.actuators, delay_average=True),
                            rnd.TOCABI_LAB.dynamics, rnd.TOCABI_LAB.sensors)
    section = rnd.trained_under_section(lab, rnd.PushSettings(), rnd.ROBUST_START, 0.0005, 104.5)
    assert section["actuators"]["delay"]["applied"] == "period_mean"
    assert "applied" not in _lab_section()["actuators"]["delay"]  # per substep is the unstated default
    path = _with_section(tmp_path, "torque", json.loads(json.dumps(section)))
    assert rnd.from_contract(load_contract(path))[0] == lab
    (tmp_path / "bad").mkdir()
    bad = _with_section(tmp_path / "bad", "torque", _edit(section, "actuators.delay.applied", "smoothed"))
    with pytest.raises(ContractError, match=r"delay.applied is 'smoothed' but must be one of \['substep', "
                                            r"'period_mean'\].*re-export"):
        load_contract(bad)


def test_motor_constant_friction_and_saturation_match_a_hand_computation():
    limits = np.array([100.0, 50.0, 10.0])
    settings = rnd.ActuatorSettings(motor_constant=(0.8, 1.2), coulomb=(0.5, 1.0), viscous=(0.1, 0.2))
    layer = rnd.ActuatorLayer(settings, S, limits)
    layer.reset(np.random.default_rng(2), 4)
    c, fc, fv = layer.motor_constant, layer.coulomb, layer.viscous
    assert c.shape == (4, 3) and (c >= 0.8).all() and (c <= 1.2).all() and len(np.unique(c)) == 12
    assert (fc >= 0.5).all() and (fc <= 1.0).all() and (fv >= 0.1).all() and (fv <= 0.2).all()
    tau = np.array([[90.0, -45.0, 9.0]] * 4)
    qd = np.array([[1.0, -2.0, 0.0]] * 4)
    out = layer(tau, qd)
    hand = np.clip(c * tau - (fc * np.sign(qd) + fv * qd), -limits, limits)
    assert out.shape == (4, S, 3)
    np.testing.assert_allclose(out, np.repeat(hand[:, None], S, axis=1))  # no delay: held for every substep
    assert (np.abs(out) <= limits).all() and (np.abs(c * tau) > limits).any()  # the clip did something


# -------------------------------------------------------------------------------------------------- dynamics
def test_dynamics_give_each_robot_its_own_model_within_the_ranges():
    m = _model()
    nominal = (m.body_mass.copy(), m.dof_damping.copy(), m.dof_armature.copy(), m.geom_friction.copy())
    settings = rnd.DynamicsSettings(mass_scale=(0.8, 1.2), joint_damping=(0.0, 2.9), armature_scale=(0.8, 1.2),
                                    friction_scale=(0.4, 1.0))
    dyn = rnd.WorldDynamics(settings, m)
    models = dyn.reset(np.random.default_rng(0), 3)
    assert len({id(w) for w in models}) == 3 and all(w is not m for w in models)
    for k, n in enumerate(nominal):  # the shared model is untouched
        np.testing.assert_array_equal(n, (m.body_mass, m.dof_damping, m.dof_armature, m.geom_friction)[k])
    robot_bodies = dyn.bodies
    assert len(robot_bodies) == m.nbody - 1
    for i, w in enumerate(models):
        ratio = w.body_mass[robot_bodies] / m.body_mass[robot_bodies]
        assert (ratio >= 0.8 - 1e-12).all() and (ratio <= 1.2 + 1e-12).all()
        np.testing.assert_allclose(w.body_inertia[robot_bodies], m.body_inertia[robot_bodies] * ratio[:, None])
        assert w.body_subtreemass[0] == pytest.approx(w.body_mass.sum())  # the whole robot's drawn mass
        added = w.dof_damping[dyn.dofs] - m.dof_damping[dyn.dofs]
        assert len(dyn.dofs) == robot.NUM_JOINTS and (added >= 0).all() and (added <= 2.9).all()
        np.testing.assert_array_equal(w.dof_damping[:6], m.dof_damping[:6])  # not the free joint
        scale = w.dof_armature[dyn.dofs] / np.where(m.dof_armature[dyn.dofs] > 0, m.dof_armature[dyn.dofs], np.nan)
        assert np.nanmin(scale) >= 0.8 - 1e-12 and np.nanmax(scale) <= 1.2 + 1e-12
        np.testing.assert_allclose(w.geom_friction[:, 0], m.geom_friction[:, 0] * dyn.friction_scale[i])
        np.testing.assert_array_equal(w.geom_friction[:, 1:], m.geom_friction[:, 1:])
    masses = [w.body_mass[robot_bodies] for w in models]
    assert not np.allclose(masses[0], masses[1]) and not np.allclose(masses[1], masses[2])
    assert 0.4 <= dyn.friction_scale.min() and dyn.friction_scale.max() <= 1.0


def test_dynamics_draws_are_uniform_over_the_range():
    m = _model()
    dyn = rnd.WorldDynamics(rnd.DynamicsSettings(mass_scale=(0.8, 1.2)), m)
    dyn.reset(np.random.default_rng(1), 40)
    s = dyn.mass_scale[:, dyn.bodies].ravel()  # 40 x 36 draws
    assert s.mean() == pytest.approx(1.0, abs=0.01) and s.std() == pytest.approx(0.4 / math.sqrt(12), rel=0.05)


# --------------------------------------------------------------------------------------------------- sensors
def _signals(n: int) -> dict:
    return {"joint_pos": np.zeros((n, 33), np.float32), "joint_vel": np.zeros((n, 33), np.float32),
            "base_rpy": np.zeros((n, 3), np.float32), "foot_force": np.zeros((n, 2, 3), np.float32),
            "foot_torque": np.zeros((n, 2, 3), np.float32), "command": np.zeros((n, 2), np.float32)}


def test_sensor_biases_are_in_range_and_constant_within_an_episode():
    lab = rnd.TOCABI_LAB.sensors
    bias_only = dataclasses.replace(lab, joint_pos_noise_std=0.0)
    model = rnd.SensorModel(bias_only, 33, np.random.default_rng(1))
    model.reset(np.random.default_rng(0), 500)
    halves = {"joint_pos": math.pi / 100, "base_rpy": math.pi / 150, "foot_force": 100.0, "foot_torque": 10.0}
    first = model(_signals(500))
    for name, half in halves.items():
        b = model.biases[name]
        assert np.abs(b).max() <= half and np.abs(b).max() > 0.95 * half  # U(-half, half), spread over the range
        assert b.mean() == pytest.approx(0.0, abs=0.03 * half)
        np.testing.assert_array_equal(first[name], b)  # added to the observed signal
    for _ in range(3):  # constant over the episode's periods
        later = model(_signals(500))
        for name in halves:
            np.testing.assert_array_equal(later[name], first[name])
    np.testing.assert_array_equal(later["joint_vel"], 0.0)  # untouched: no joint-velocity settings
    np.testing.assert_array_equal(later["command"], 0.0)
    old = model.biases["joint_pos"].copy()
    model.reset(np.random.default_rng(5), 500)  # a new episode draws new biases
    assert not np.array_equal(old, model.biases["joint_pos"])


def test_encoder_noise_has_its_std_and_clip_and_is_fresh_every_period():
    model = rnd.SensorModel(rnd.SensorSettings(joint_pos_noise_std=0.01, joint_pos_noise_clip=0.02,
                                               joint_vel_noise_std=0.5), 33, np.random.default_rng(3))
    model.reset(np.random.default_rng(0), 1000)
    a, b = model(_signals(1000)), model(_signals(1000))
    assert not np.array_equal(a["joint_pos"], b["joint_pos"])
    z = np.concatenate([a["joint_pos"], b["joint_pos"]]).ravel()
    assert np.abs(z).max() <= 0.02 + 1e-7 and (np.abs(z) >= 0.02 - 1e-7).mean() == pytest.approx(0.0455, abs=0.005)
    # N(0, σ²) clipped at 2σ: variance (P(|Z|<2) − 4φ(2) + 4·P(|Z|>2))σ² = 0.9205σ², std 0.9594σ
    assert z.std() == pytest.approx(0.01 * 0.9594, rel=0.02)
    assert a["joint_vel"].std() == pytest.approx(0.5, rel=0.02)
    np.testing.assert_array_equal(a["base_rpy"], 0.0)


def test_a_biased_heading_is_wrapped_back_into_minus_pi_pi():
    model = rnd.SensorModel(rnd.SensorSettings(base_rpy_bias=0.1), 33, np.random.default_rng(0))
    model.reset(np.random.default_rng(0), 200)
    signals = _signals(200)
    signals["base_rpy"][:] = np.float32(math.pi - 0.01)
    out = model(signals)["base_rpy"]
    assert (out > -math.pi).all() and (out <= math.pi).all() and (out < 0).any()


# ---------------------------------------------------------------------------------------------------- pushes
def test_push_schedule_times_directions_and_impulse():
    settings = rnd.PushSettings(count=3, window=(2.0, 7.0), speed=(0.5, 1.0), duration=(0.004, 0.1))
    kicks = rnd.PushSchedule(settings, DT, 104.5)
    kicks.reset(np.random.default_rng(0), 300)
    share = 5.0 / 3
    t = kicks.start_step * DT
    for j in range(3):  # kick j at a random time in the j-th share of the window
        lo, hi = 2.0 + j * share, 2.0 + (j + 1) * share
        assert (t[:, j] >= lo - DT / 2).all() and (t[:, j] <= hi + DT / 2).all()
        assert t[:, j].std() == pytest.approx(share / math.sqrt(12), rel=0.15)
    assert (kicks.steps >= 1).all() and (kicks.steps <= 25).all()
    impulse = np.linalg.norm(kicks.force, axis=-1) * kicks.steps * DT  # [N·s]
    np.testing.assert_allclose(impulse, kicks.speed * 104.5)
    assert (kicks.speed >= 0.5).all() and (kicks.speed <= 1.0).all()
    # Summed over the periods, each robot gets exactly its kicks' impulses, and nothing outside them.
    total = sum(kicks.at(step) for step in range(0, 2000)) * DT
    np.testing.assert_allclose(total, (kicks.force * kicks.steps[..., None]).sum(1) * DT, atol=1e-9)
    assert np.abs(kicks.at(int(1.9 / DT))).max() == 0.0
    angle = np.arctan2(kicks.force[..., 1], kicks.force[..., 0]).ravel()
    assert np.histogram(angle, bins=4, range=(-math.pi, math.pi))[0].min() > 150  # uniform direction


def test_a_calm_fraction_leaves_that_share_of_robots_unkicked_and_the_others_as_drawn():
    settings = rnd.PushSettings(count=3, window=(2.0, 7.0), speed=(0.5, 1.0))
    calm = dataclasses.replace(settings, calm_fraction=0.3)
    kicks, kept = rnd.PushSchedule(settings, DT, 104.5), rnd.PushSchedule(calm, DT, 104.5)
    kicks.reset(np.random.default_rng(0), 4000)
    kept.reset(np.random.default_rng(0), 4000)
    still = (kept.speed == 0).all(axis=1)
    assert still.mean() == pytest.approx(0.3, abs=0.025)  # binomial σ 0.007
    assert np.abs(kept.force[still]).max() == 0.0 and np.abs(sum(kept.at(s) for s in range(2000))[still]).max() == 0
    # The calm draw comes after the others: every kicked robot's kicks are those of the same seed without it.
    np.testing.assert_array_equal(kept.force[~still], kicks.force[~still])
    np.testing.assert_array_equal(kept.start_step[~still], kicks.start_step[~still])
    assert kept.start_step[still].min() > 10 ** 9  # no calm robot's kick ever begins (nor counts as started)
    with pytest.raises(ValueError, match=r"pushes.calm_fraction must be a finite number in \[0, 1\)"):
        rnd.PushSettings(count=1, calm_fraction=1.0).validate()


def test_a_calm_fraction_is_stated_only_when_used_and_read_back(tmp_path):
    assert "calm_fraction" not in _lab_section(count=3)["pushes"]
    section = json.loads(json.dumps(_lab_section(count=3, calm_fraction=0.25)))
    assert section["pushes"]["calm_fraction"] == 0.25 and "without kicks" in section["pushes"]["rule"]
    _, pushes, _ = rnd.from_contract(load_contract(_with_section(tmp_path, "torque", section)))
    assert pushes == rnd.PushSettings(count=3, calm_fraction=0.25)


def test_a_kick_through_xfrc_applied_changes_the_robots_momentum_by_its_impulse():
    # Zero gravity and the robot in the air: only the kick (an external force) changes the total momentum.
    m = _model()
    m.opt.gravity[:] = 0.0
    d = mujoco.MjData(m)
    d.qpos[:] = load_contract(_contract("torque"))["robot"]["initial_qpos"]
    d.qpos[2] += 2.0
    mujoco.mj_forward(m, d)
    base = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, robot.BASE_BODY)
    mass = float(m.body_subtreemass[base])
    kicks = rnd.PushSchedule(rnd.PushSettings(count=1, window=(0.0, 0.004), speed=(0.5, 0.5)), DT, mass)
    kicks.reset(np.random.default_rng(0), 1)

    def momentum():
        mujoco.mj_forward(m, d)  # after mj_step, cvel is still the last substep's start
        mujoco.mj_subtreeVel(m, d)
        return d.subtree_linvel[0] * m.body_subtreemass[0]

    before = momentum()
    d.xfrc_applied[base, :2] = kicks.at(int(kicks.start_step[0, 0]))[0]
    for _ in range(S):
        mujoco.mj_step(m, d)
    change = momentum() - before
    # The discrete momentum also drifts with the motion the kick sets off (4e-4 N·s in 8 substeps without a kick):
    # 0.03 N·s of a 52 N·s impulse.
    np.testing.assert_allclose(change[:2], kicks.force[0, 0] * DT, atol=0.03)
    assert np.linalg.norm(change[:2]) == pytest.approx(0.5 * mass, rel=1e-3) and abs(change[2]) < 0.03


def test_a_velocity_kick_changes_every_bodys_velocity_alike():
    # Zero gravity, the robot in the air: against the same robot unkicked (its upper-body servos move it a little
    # either way), the kick, a uniform field, changes the velocity of every body by the kick's speed (0.5 m/s) and
    # the joints' velocities not at all.
    m = _model()
    m.opt.gravity[:] = 0.0
    base = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, robot.BASE_BODY)
    kicks = rnd.PushSchedule(rnd.PushSettings(count=1, window=(0.0, 0.0), speed=(0.5, 0.5), kind="velocity"), DT,
                             float(m.body_subtreemass[base]))
    kicks.reset(np.random.default_rng(0), 1)
    forces = kicks.body_forces(0, base, m.body_mass[None])
    assert forces.shape == (1, m.nbody, 2)

    def after(kicked: bool):
        d = mujoco.MjData(m)
        d.qpos[:] = load_contract(_contract("torque"))["robot"]["initial_qpos"]
        d.qpos[2] += 2.0
        if kicked:
            d.xfrc_applied[:, :2] = forces[0]
        for _ in range(S):
            mujoco.mj_step(m, d)
        mujoco.mj_forward(m, d)
        out = np.zeros((m.nbody, 6))
        for b in range(1, m.nbody):
            mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_BODY, b, out[b], 0)
        return out[1:, 3:], d.qvel[6:].copy()  # each body's linear velocity (world frame), the joint velocities

    (kicked, kicked_joints), (calm, calm_joints) = after(True), after(False)
    direction = kicks.force[0, 0] / np.linalg.norm(kicks.force[0, 0])
    np.testing.assert_allclose((kicked - calm)[:, :2], np.broadcast_to(0.5 * direction, kicked[:, :2].shape),
                               atol=1e-4)
    np.testing.assert_allclose(kicked_joints, calm_joints, atol=1e-4)


def test_the_driver_kicks_every_robot_in_the_window():
    pushes = rnd.PushSettings(count=2, window=(0.02, 0.08), speed=(0.5, 0.5))
    result = run_sim2sim(_contract("torque"), seconds=0.1, num_robots=2, pushes=pushes, seed=4)
    assert result.perturbations["pushes"]["kicks_started"] == 4 and result.perturbations["pushes"]["kind"] == "force"
    velocity = run_sim2sim(_contract("torque"), seconds=0.1, num_robots=2, seed=4,
                           pushes=dataclasses.replace(pushes, kind="velocity"))
    assert velocity.per_robot_forward_m != result.per_robot_forward_m  # the same momentum, another push
    quiet = run_sim2sim(_contract("torque"), seconds=0.1, num_robots=2, seed=4)
    assert result.per_robot_forward_m != quiet.per_robot_forward_m or result.lateral_drift_m != quiet.lateral_drift_m


# -------------------------------------------------------------------------------------------- start velocity
def test_start_velocities_have_the_robust_tests_spread():
    qvel = rnd.start_velocities(np.random.default_rng(0), 2000, 39, rnd.ROBUST_START)
    assert qvel[:, :3].std() == pytest.approx(0.1, rel=0.03) and qvel[:, 6:].std() == pytest.approx(0.5, rel=0.02)
    np.testing.assert_array_equal(qvel[:, 3:6], 0.0)  # no angular velocity
    assert abs(qvel.mean()) < 0.01


# ------------------------------------------------------------------------------------------------ the driver
#: run_sim2sim(torque, seconds=0.3, num_robots=2, perturbation=1e-6, seed=3) before randomisation existed.
UNCHANGED = {"survival": 1.0, "forward_distance_m": 0.028484144024825117, "lateral_drift_m": 0.039543782309227615,
             "mean_speed_mps": 0.09494714674941707, "speed_tracking_error_mps": 0.4116036282657317,
             "knee_rms_rad": 0.05647536356157781, "per_robot_forward_m": [0.0298, 0.0272], "alive": [True, True]}


def test_randomize_none_leaves_the_drivers_numbers_as_they_were():
    result = run_sim2sim(_contract("torque"), seconds=0.3, num_robots=2, perturbation=1e-6, seed=3,
                         randomize="none", pushes=rnd.PushSettings(count=0), start_velocity=rnd.StartVelocity())
    got = result.as_dict()
    for key, value in UNCHANGED.items():
        assert got[key] == (pytest.approx(value, rel=1e-9) if isinstance(value, float) else value), key
    assert got["perturbations"] == {"randomize": "none", "seed": 3, "pushes": None, "start_noise": None}


def test_randomisation_is_seeded_and_each_piece_changes_the_run():
    kw = dict(seconds=0.1, num_robots=2)
    lab = run_sim2sim(_contract("torque"), randomize="tocabi_lab", seed=1, **kw)
    assert lab.as_dict() == run_sim2sim(_contract("torque"), randomize="tocabi_lab", seed=1, **kw).as_dict()
    assert lab.per_robot_forward_m != run_sim2sim(_contract("torque"), randomize="tocabi_lab", seed=2,
                                                  **kw).per_robot_forward_m
    plain = run_sim2sim(_contract("torque"), **kw).per_robot_forward_m
    pieces = [rnd.Randomization(actuators=rnd.ActuatorSettings(delay_substeps=(4, 4))),
              rnd.Randomization(dynamics=rnd.DynamicsSettings(mass_scale=(0.8, 1.2))),
              rnd.Randomization(sensors=rnd.SensorSettings(joint_pos_bias=0.03))]
    for piece in pieces:
        assert run_sim2sim(_contract("torque"), randomize=piece, **kw).per_robot_forward_m != plain, piece
    started = run_sim2sim(_contract("torque"), start_velocity=rnd.ROBUST_START, **kw)
    assert started.per_robot_forward_m != plain
    assert started.perturbations["start_noise"] == {"joint_std_radps": 0.5, "base_std_mps": 0.1}


def test_randomize_trained_applies_what_the_contract_states(tmp_path):
    section = rnd.trained_under_section(rnd.TOCABI_LAB, rnd.PushSettings(), rnd.StartVelocity(), 0.0005, 104.5)
    path = _with_section(tmp_path, "torque", section)
    kw = dict(seconds=0.05, num_robots=1, seed=7)
    trained = run_sim2sim(path, randomize="trained", **kw).as_dict()
    lab = run_sim2sim(path, randomize="tocabi_lab", **kw).as_dict()
    assert trained.pop("perturbations")["randomize"] == "trained" and lab.pop("perturbations")
    assert trained == lab


def test_a_capped_solver_is_stated_as_text_that_every_reader_accepts(tmp_path):
    # env.sim.solver_iterations: the section says the training's physics was cut short; the contract still loads
    # and states the same randomisation (no reader applies the cap), and without a cap nothing is said.
    plain = rnd.trained_under_section(rnd.TOCABI_LAB, rnd.PushSettings(), rnd.StartVelocity(), 0.0005, 104.5)
    capped = rnd.trained_under_section(rnd.TOCABI_LAB, rnd.PushSettings(), rnd.StartVelocity(), 0.0005, 104.5,
                                       solver_iterations=4)
    assert "solver" not in plain and "capped at 4 per physics substep" in capped["solver"]
    assert {k: v for k, v in capped.items() if k != "solver"} == plain
    loaded = load_contract(_with_section(tmp_path, "torque", capped))
    assert rnd.from_contract(loaded) == rnd.from_contract(load_contract(_with_section(tmp_path, "torque", plain)))


def test_the_actuator_layer_is_refused_for_a_pd_policy_and_trained_needs_the_section(tmp_path):
    with pytest.raises(ValueError, match="acts on torque commands only.*'pd_reference'"):
        run_sim2sim(_contract("ppo"), seconds=0.01, num_robots=1, randomize="tocabi_lab")
    with pytest.raises(ValueError, match="does not state what the policy was trained under.*re-export"):
        run_sim2sim(_older(tmp_path, "torque"), seconds=0.01, num_robots=1, randomize="trained")
    with pytest.raises(ValueError, match="choose one of"):
        run_sim2sim(_contract("torque"), seconds=0.01, num_robots=1, randomize="lab")
    # Dynamics and sensors alone are fine for a PD policy.
    pd = rnd.Randomization(dynamics=rnd.TOCABI_LAB.dynamics, sensors=rnd.TOCABI_LAB.sensors)
    assert run_sim2sim(_contract("ppo"), seconds=0.02, num_robots=1, randomize=pd).survival == 1.0


_A, _S = rnd.ActuatorSettings, rnd.SensorSettings


@pytest.mark.parametrize("kwargs, message", [
    # Each ran as given before the run checked them: a negative delay as none, a stride off the range's grid as its
    # low end alone, a negative motor constant reversed the torques, negative friction pushed the joints.
    (dict(randomize=rnd.Randomization(actuators=_A(delay_substeps=(-4, 2)))), r"randomize.actuators.delay_substeps"),
    (dict(randomize=rnd.Randomization(actuators=_A(delay_substeps=(2, 4), delay_stride=3))),
     r"randomize.actuators.delay_stride: stride 3 does not divide"),
    (dict(randomize=rnd.Randomization(actuators=_A(delay_substeps=(2, 4), delay_stride=0))),
     r"randomize.actuators.delay_stride: stride 0"),  # was a ZeroDivisionError
    (dict(randomize=rnd.Randomization(actuators=_A(motor_constant=(-1.0, 0.5)))),
     r"randomize.actuators.motor_constant must be \(low, high\) with 0 <= low"),
    (dict(randomize=rnd.Randomization(actuators=_A(coulomb=(-5.0, 0.0)))), r"randomize.actuators.coulomb"),
    (dict(randomize=rnd.Randomization(actuators=_A(delay_substeps=(0, 10**6)))), r"reaches past 400 substeps"),
    # A negative or NaN σ or bias was read as off; a negative clip added a constant -clip to every joint angle.
    (dict(randomize=rnd.Randomization(sensors=_S(joint_pos_noise_std=-0.1))), r"randomize.sensors.joint_pos_noise_std"),
    (dict(randomize=rnd.Randomization(sensors=_S(joint_pos_bias=math.nan))), r"randomize.sensors.joint_pos_bias"),
    (dict(randomize=rnd.Randomization(sensors=_S(joint_pos_noise_std=0.1, joint_pos_noise_clip=-1.0))),
     r"randomize.sensors.joint_pos_noise_clip must be a finite number > 0, or None"),
    # A NaN start velocity was refused as a failed sensor; a count of -1 ran without kicks.
    (dict(start_velocity=rnd.StartVelocity(joint_std=math.nan)), r"start_velocity.joint_std \[rad/s\] must be"),
    (dict(start_velocity=rnd.StartVelocity(base_std=-0.1)), r"start_velocity.base_std \[m/s\] must be"),
    (dict(pushes=rnd.PushSettings(count=-1)), r"pushes.count must be an int in \[0, 64\]"),
])
def test_a_given_randomisation_out_of_range_is_refused_by_name(kwargs, message):
    with pytest.raises(ValueError, match=message):
        run_sim2sim(_contract("torque"), seconds=0.004, num_robots=1, **kwargs)


def test_settings_of_another_type_are_refused_by_name_before_anything_is_built(tmp_path):
    # A dict of the fields failed with "AttributeError: 'dict' object has no attribute 'validate'" after the policy
    # was loaded. Missing files show that the check comes first.
    missing = {"contract_path": tmp_path / "missing.json", "model_path": tmp_path / "missing.xml"}
    for kwargs, message in (
            (dict(pushes={"count": 3}), r"pushes must be None or a PushSettings \(tocabi_torchrl.runtime."
                                        r"randomization.PushSettings\(count=3, .*\), got dict \{'count': 3\} \(for a "
                                        r"dict of its fields: PushSettings\(\*\*fields\)\)"),
            (dict(start_velocity={"joint_std": 0.5}), r"start_velocity must be None or a StartVelocity .*got dict"),
            (dict(start_velocity=0.5), r"start_velocity must be None or a StartVelocity .*ROBUST_START\), got float "
                                       r"0.5$")):
        with pytest.raises(ValueError, match=message):
            run_sim2sim(**missing, **kwargs)
    # A run config's PushConfig (its fields are PushSettings' own) is named with the conversion that takes it.
    from tocabi_torchrl.envs.push_config import PushConfig

    with pytest.raises(ValueError, match=r"for a training config's PushConfig: tocabi_torchrl.runtime.randomization"
                                         r".settings_from\(PushSettings, value, 'pushes'\)"):
        run_sim2sim(**missing, pushes=PushConfig(count=3))
    assert rnd.settings_from(rnd.PushSettings, PushConfig(count=3), "pushes") == rnd.PushSettings(count=3)


# ------------------------------------------------------------------------------------------------ the contract
def test_a_velocity_kick_contract_round_trips_and_an_unknown_kind_is_refused(tmp_path):
    section = json.loads(json.dumps(_lab_section(count=3, speed=(0.5, 1.0), kind="velocity")))
    assert section["pushes"]["kind"] == "velocity" and "on every body" in section["pushes"]["rule"]
    _, pushes, _ = rnd.from_contract(load_contract(_with_section(tmp_path, "torque", section)))
    assert pushes == rnd.PushSettings(count=3, speed=(0.5, 1.0), kind="velocity")
    section["pushes"]["kind"] = "impulse"
    with pytest.raises(ContractError, match="pushes.kind is 'impulse'.*re-export"):
        (tmp_path / "bad").mkdir()
        load_contract(_with_section(tmp_path / "bad", "torque", section))
    with pytest.raises(ValueError, match="pushes.kind"):
        rnd.PushSettings(count=1, kind="impulse").validate()


def test_a_contract_with_the_section_round_trips(tmp_path):
    section = _lab_section(count=3, speed=(0.5, 1.0))
    path = _with_section(tmp_path, "torque", json.loads(json.dumps(section)))
    randomization, pushes, start = rnd.from_contract(load_contract(path))
    assert randomization == rnd.TOCABI_LAB
    assert pushes == rnd.PushSettings(count=3, speed=(0.5, 1.0))
    assert start == rnd.ROBUST_START
    stated = load_contract(path)["trained_under"]
    assert stated["actuators"]["delay"]["ms"] == [2.0, 10.0] and stated["dynamics"]["friction_scale"] == "off"
    assert stated["pushes"]["ramp_env_steps"] == [100, 1000] and stated["sensor_noise"]["joint_vel_noise"] == "off"


@pytest.mark.parametrize("name", ["torque", "ppo"])
def test_an_older_contract_loads_as_not_stated_and_the_shipped_ones_state_no_randomisation(name, tmp_path):
    # A contract exported before the section existed: the shipped one without it.
    older = json.loads(_contract(name).read_text())
    older.pop("trained_under")
    path = tmp_path / _contract(name).name
    path.write_text(json.dumps(older))
    shutil.copy(_contract(name).with_suffix(".onnx"), tmp_path)
    assert "trained_under" not in load_contract(path)
    assert rnd.from_contract(load_contract(path)) is None
    # The shipped policies were trained on the ideal robot: every piece is stated as off.
    stated = load_contract(_contract(name))["trained_under"]
    assert stated["actuators"]["delay"] == "off" and stated["dynamics"]["mass_scale"] == "off"
    assert stated["pushes"] == "off" and stated["sensor_noise"]["joint_pos_bias"] == "off"


def _edit(section: dict, dotted: str, value) -> dict:
    out = copy.deepcopy(section)
    node = out
    *parents, last = dotted.split(".")
    for p in parents:
        node = node[p]
    node[last] = value
    return out


@pytest.mark.parametrize("dotted, value, message", [
    ("dynamics.mass_scale.range", [1.2, 0.8], r"trained_under.dynamics.mass_scale.range is \[1.2, 0.8\]: low > high"),
    ("dynamics.mass_scale.range", [0.0, 1.2], r"each end must be a finite number in \(0, 5\]"),
    ("dynamics.mass_scale.range", [0.8, 12.0], r"each end must be a finite number in \(0, 5\]; links above 5x"),
    ("dynamics.joint_damping.range", [-1.0, 2.9], r"each end must be a finite number in \[0, 100\]"),
    ("actuators.delay.substeps", [4.5, 20], r"each end must be an int in \[0, 400\]"),
    ("actuators.delay.ms", [2.0, 11.0], r"delay.ms is \[2.0, 11.0\] but substeps \[4, 20\]"),
    ("actuators.motor_constant", "on", r"motor_constant is 'on' but must be \"off\" or an object"),
    ("actuators.backlash", {"range": [0.0, 0.1]}, r"states \['backlash'\], which this reader cannot apply"),
    ("sensor_noise.joint_pos_noise.clip", 0.0, "clip is 0.0 but must be a finite number > 0"),
    ("sensor_noise.foot_force_bias.half_width", -1.0, "half_width is -1.0 but must be a finite number >= 0"),
    ("pushes.count", 0, "pushes.count is 0 but must be an int in \\[1, 64\\]"),
    ("pushes.speed_mps", [0.5], r"speed_mps is \[0.5\] but must be a \[low, high\] pair"),
    ("pushes.speed_mps", [0.4, 140.0], r"speed_mps is \[0.4, 140.0\] but each end .*\[0, 10\]; a kick above 10 m/s"),
    ("pushes.calm_fraction", 1.0, r"calm_fraction is 1.0 but must be a finite number in \[0, 1\)"),
    ("start_velocity.joint_std_radps", 11.0, r"joint_std_radps is 11.0 but must be a finite number in \[0, 10\]"),
    ("dynamics", None, "trained_under.dynamics is None, not an object"),
])
def test_bad_section_values_are_refused_by_name(tmp_path, dotted, value, message):
    path = _with_section(tmp_path, "torque", _edit(_lab_section(count=3), dotted, value))
    with pytest.raises(ContractError, match=message + ".*re-export"):
        load_contract(path)


def test_actuator_stages_are_refused_in_a_pd_contract(tmp_path):
    path = _with_section(tmp_path, "ppo", _lab_section())
    with pytest.raises(ContractError, match=r"states \['delay', 'motor_constant'\] for control mode 'pd_reference'"):
        load_contract(path)


def test_the_runtimes_tocabi_lab_is_the_training_sides():
    pytest.importorskip("torch")
    from tocabi_torchrl.randomize import tocabi_lab_paths

    paths = tocabi_lab_paths()
    assert rnd.settings_from(rnd.ActuatorSettings, paths["env.control.actuators"], "a") == rnd.TOCABI_LAB.actuators
    assert rnd.settings_from(rnd.DynamicsSettings, paths["env.dynamics"], "d") == rnd.TOCABI_LAB.dynamics
    assert rnd.settings_from(rnd.SensorSettings, paths["transforms.sensor_noise"], "s") == rnd.TOCABI_LAB.sensors
    from tocabi_torchrl.evaluation.robust import RobustTestConfig

    test = RobustTestConfig()
    assert (test.start_joint_vel_std, test.start_base_vel_std) == (rnd.ROBUST_START.joint_std,
                                                                   rnd.ROBUST_START.base_std)


def test_export_states_what_the_policy_was_trained_under(tmp_path):
    torch = pytest.importorskip("torch")
    pytest.importorskip("onnx")
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.envs.pushes import PushConfig
    from tocabi_torchrl.export.__main__ import main as export_main
    from tocabi_torchrl.randomize import tocabi_lab
    from tocabi_torchrl.rl.checkpoint import save_checkpoint
    from tocabi_torchrl.rl.trainer import build_agent, build_env

    cfg = tocabi_lab(preset_config("default", **{"env.control.mode": "torque", "env.num_envs": 1,
                     "ppo.minibatch_size": 48,
                                   "ppo.actor_hidden": (16,), "ppo.critic_hidden": (16,)}, device="cpu"))
    task = dataclasses.replace(cfg.env.task, start_joint_vel_std=0.5, start_base_vel_std=0.1)
    env_cfg = dataclasses.replace(cfg.env, task=task, pushes=PushConfig(count=2, speed=(0.3, 0.6)))
    cfg = dataclasses.replace(cfg, env=env_cfg, ppo=dataclasses.replace(cfg.ppo, push_ramp=(10, 20)))
    env = build_env(cfg, torch.device("cpu"), num_envs=1)
    agent = build_agent(cfg, 237, 13, torch.device("cpu"))
    ckpt = save_checkpoint(tmp_path / "run", 0, 0, agent, None, env, cfg)
    export_main(["--checkpoint", str(ckpt), "--out", str(tmp_path / "lab.onnx")])
    contract = load_contract(tmp_path / "lab.json")
    randomization, pushes, start = rnd.from_contract(contract)
    assert randomization == rnd.TOCABI_LAB
    assert pushes == rnd.PushSettings(count=2, speed=(0.3, 0.6)) and start == rnd.ROBUST_START
    section = contract["trained_under"]
    mass = env.base_env.sim.mj_model.body_subtreemass[env.base_env.sim.mj_model.body(robot.BASE_BODY).id]
    assert section["pushes"]["robot_mass_kg"] == pytest.approx(float(mass))
    assert section["pushes"]["ramp_env_steps"] == [10, 20]
    assert section["actuators"]["delay"] == {**section["actuators"]["delay"], "substeps": [4, 20], "ms": [2.0, 10.0]}
    assert section["actuators"]["saturation"] != "off" and section["actuators"]["friction"] == "off"
    assert section["dynamics"]["mass_scale"]["draw"].endswith(", at each reset")
    assert section["start_velocity"]["rule"].startswith("at each reset:")
    # A start pool (env.sim.start_pool) is stated where it acted: the dynamics and the start velocities.
    pooled = dataclasses.replace(cfg, env=dataclasses.replace(env_cfg, sim=dataclasses.replace(env_cfg.sim,
                                                                                                start_pool=3)))
    env = build_env(pooled, torch.device("cpu"), num_envs=1)
    ckpt = save_checkpoint(tmp_path / "pooled", 0, 0, agent, None, env, pooled)
    export_main(["--checkpoint", str(ckpt), "--out", str(tmp_path / "pooled.onnx")])
    section = load_contract(tmp_path / "pooled.json")["trained_under"]
    for text in (section["dynamics"]["armature_scale"]["draw"], section["start_velocity"]["rule"]):
        assert "3 draws per robot made when the training env was built, one of them picked at each reset" in text
    assert rnd.from_contract(load_contract(tmp_path / "pooled.json"))[0] == rnd.TOCABI_LAB


# ------------------------------------------------------------------------------------------------ the recipe
def test_the_recipe_runs_randomised_and_pushed_robots_without_torch():
    code = ("import json, runpy, sys; sys.argv = ['sim2sim.py', '--contract', "
            "'assets/policies/tocabi_walk_torque.json', "
            "'--randomize', 'tocabi_lab', '--pushes', '3', '--push_speed', '0.5', '--num_robots', '2', "
            "'--seconds', '7.2']; runpy.run_path('recipes/sim2sim.py', run_name='__main__'); "
            "print(json.dumps(sorted(m for m in ('torch', 'torchrl', 'tensordict') if m in sys.modules)))")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    *report, imported = proc.stdout.strip().splitlines()
    assert json.loads(imported) == []
    result = json.loads("\n".join(report))
    assert 0.0 <= result["survival"] <= 1.0 and len(result["alive"]) == 2
    assert result["perturbations"]["randomize"] == "tocabi_lab"
    # The recipe refuses a run shorter than the kicks' 2-7 s window, so every kick of a robot still up has started.
    pushes = result["perturbations"]["pushes"]
    assert pushes["count"] == 3 and pushes["kicks_started"] >= 3 * sum(result["alive"])


@pytest.mark.parametrize("argv, message", [
    (["--randomize", "lab"], "argument --randomize: invalid choice: 'lab'"),
    (["--pushes", "-1"], r"--pushes must be an int in \[0, 64\]"),
    (["--pushes", "2.5"], "argument --pushes: invalid int value"),
    (["--push_speed", "nan"], "--push_speed must be a finite velocity change >= 0"),
    (["--push_speed", "-0.5"], "--push_speed must be a finite velocity change >= 0"),
    (["--push_speed", "140"], r"--push_speed must be .* <= 10 \[m/s\], got 140.0; a kick above 10 m/s launches"),
    (["--seed", "-1"], r"--seed must be an int in \[0, 2\*\*63 - 1\]"),
])
def test_bad_option_values_are_one_error_line(argv, message, capsys):
    with pytest.raises(SystemExit) as info:
        load_recipe("sim2sim").main(["--contract", str(_contract("torque")), "--seconds", "0.02", *argv])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and ": error: " in err
    assert __import__("re").search(message, err), err


@pytest.mark.parametrize("name, randomize, message", [
    ("torque", "trained", "does not state what the policy was trained under"),
    ("ppo", "tocabi_lab", "acts on torque commands only"),
])
def test_an_unusable_randomisation_is_one_error_line(name, randomize, message, tmp_path):
    with pytest.raises(SystemExit) as info:
        load_recipe("sim2sim").main(["--contract", str(_older(tmp_path, name)), "--seconds", "0.02",
                                     "--num_robots", "1",
                                     "--randomize", randomize])
    text = str(info.value.code)
    assert text.startswith("error: ") and message in text and "\n" not in text


def test_the_pelvis_velocity_noise_round_trips_and_is_left_out_when_off(tmp_path):
    """The velocity items are stated only when on (a contract without them reads as before, off), read back exactly,
    and applied by the runtime's sensor model within their bounds."""
    sensors = dataclasses.replace(rnd.TOCABI_LAB.sensors, base_lin_vel_bias=0.05, base_lin_vel_noise_std=0.02,
                                  base_lin_vel_noise_clip=0.03, base_ang_vel_noise_std=0.1)
    section = rnd.trained_under_section(dataclasses.replace(rnd.TOCABI_LAB, sensors=sensors), rnd.PushSettings(),
                                        rnd.ROBUST_START, 0.0005, 104.5, (0, 0))
    stated = json.loads(json.dumps(section))["sensor_noise"]
    assert stated["base_lin_vel_bias"]["half_width"] == 0.05 and stated["base_ang_vel_noise"]["std"] == 0.1
    assert "base_ang_vel_bias" not in stated  # off: left out
    randomization, _, _ = rnd.from_contract(load_contract(_with_section(tmp_path, "torque", section)))
    assert randomization.sensors == sensors
    lab = json.loads(json.dumps(_lab_section(count=3, speed=(0.5, 1.0))))["sensor_noise"]
    assert not set(lab) & set(rnd.OPTIONAL_SENSOR_ITEMS)  # off: left out, so the shipped contracts read as before
    velocity_only = rnd.SensorSettings(**{k: v for k, v in dataclasses.asdict(sensors).items() if "base_" in k and
                                          "_vel_" in k})
    model = rnd.SensorModel(velocity_only, 33, np.random.default_rng(0))
    model.reset(np.random.default_rng(1), 64)
    zeros = {"base_lin_vel": np.zeros((64, 3), np.float32), "base_ang_vel": np.zeros((64, 3), np.float32),
             "joint_pos": np.zeros((64, 33), np.float32)}
    lin = np.stack([model(zeros)["base_lin_vel"] for _ in range(20)])
    assert np.abs(lin).max() <= 0.05 + 0.03 + 1e-6
    # The bias is constant within an episode, the noise is not: per robot and axis, the mean over the periods
    # stays within the bias's half-width and the spread is the noise's.
    assert np.abs(lin.mean(0)).max() <= 0.05 + 0.02 and 0.01 < lin.std(0).mean() < 0.03
    assert np.abs(model(zeros)["base_ang_vel"]).max() > 0.1  # unclipped N(0, 0.1²) over 192 draws


def test_a_velocity_noise_for_a_policy_that_does_not_observe_it_is_refused_by_name():
    model = rnd.SensorModel(rnd.SensorSettings(base_lin_vel_noise_std=0.01), 33, np.random.default_rng(0))
    model.reset(np.random.default_rng(1), 2)
    with pytest.raises(ValueError, match=r"SensorModel perturbs \['base_lin_vel'\], which this policy does not "
                                         r"observe .*set those ranges to 0"):
        model({"joint_pos": np.zeros((2, 33), np.float32)})
