"""The actuator layer (tocabi_torchrl.control.actuators) against hand computations, in the simulator and in the env."""

from __future__ import annotations

import dataclasses
import inspect
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch
from doc_blocks import python_blocks

from tocabi_torchrl import make_env, robot
from tocabi_torchrl.control import (ActuatorChain, ActuatorConfig, ControlInput, Delay, Friction, MotorConstant,
                                    Saturation)
from tocabi_torchrl.control.actuators import AveragedDelay
from tocabi_torchrl.control.base import ControlContext
from tocabi_torchrl.envs import TocabiWalk, TocabiWalkConfig
from tocabi_torchrl.sim import MujocoSim, SimConfig

ALL = torch.ones(3, dtype=torch.bool)
DOC = Path(__file__).resolve().parents[1] / "docs" / "concepts" / "controllers.md"


def context(n=3, limits=(100.0, 50.0)):
    j = len(limits)
    return ControlContext(num_envs=n, device=torch.device("cpu"), joint_ids=tuple(range(j)),
                          torque_limits=torch.tensor(limits), joint_range=torch.tensor([[-1.0, 1.0]] * j))


def built(stage, ctx=None, u=None):
    ctx = ctx or context()
    stage.setup(ctx)
    if u is None:
        u = torch.rand(ctx.num_envs, stage.draws, generator=torch.Generator().manual_seed(0))
    stage.reset(torch.ones(ctx.num_envs, dtype=torch.bool), u)
    return stage


def test_motor_constant_scales_each_world_and_joint_by_its_draw():
    u = torch.tensor([[0.0, 0.5], [1.0 - 2**-24, 0.25], [0.75, 0.0]])
    stage = built(MotorConstant(0.8, 1.2), u=u)
    tau = torch.tensor([[10.0, -20.0], [10.0, -20.0], [10.0, -20.0]])
    want = tau * (0.8 + 0.4 * u)
    torch.testing.assert_close(stage(tau, ControlInput(action=None)), want)
    assert 0.8 - 1e-6 <= float(stage.scale.min()) and float(stage.scale.max()) <= 1.2 + 1e-6


def test_friction_subtracts_coulomb_and_viscous_resistance_against_the_velocity():
    u = torch.tensor([[0.0, 1.0 - 2**-24, 0.0, 0.0], [0.5, 0.5, 0.5, 0.5], [1.0 - 2**-24, 0.0, 1.0 - 2**-24, 1.0]])
    stage = built(Friction(coulomb=(0.0, 4.0), viscous=(1.0, 3.0)), u=u)
    qd = torch.tensor([[2.0, -1.0], [0.0, 3.0], [-0.5, 0.25]])
    tau = torch.full((3, 2), 7.0)
    fc, fv = 4.0 * u[:, :2], 1.0 + 2.0 * u[:, 2:]
    by_hand = [[7.0 - (float(fc[w, j]) * float(np.sign(float(qd[w, j]))) + float(fv[w, j] * qd[w, j])) for j in range(2)]
               for w in range(3)]
    torch.testing.assert_close(stage(tau, ControlInput(action=None, qd=qd)), torch.tensor(by_hand))
    # At rest only the command remains (sign(0) = 0: no Coulomb term).
    assert float(stage(tau, ControlInput(action=None, qd=torch.zeros(3, 2)))[1, 0]) == 7.0



def test_friction_without_the_joint_velocity_says_what_it_needs():
    # A ControlInput without qd died as a raw TypeError inside torch.sign; a (N, 1) qd broadcast silently, every
    # joint of a world then resisting the first joint's velocity.
    stage = built(Friction(coulomb=(0.0, 4.0), viscous=(1.0, 3.0)))
    tau = torch.full((3, 2), 7.0)
    with pytest.raises(ValueError, match=r"Friction needs the joint velocity before the step, ControlInput.qd of "
                                         r"shape \(N, J\) = \(3, 2\) \[rad/s\]"):
        stage(tau, ControlInput(action=None))
    for qd in (torch.zeros(3, 1), torch.zeros(1, 2), torch.zeros(3, 8, 2)):
        with pytest.raises(ValueError, match=r"Friction takes ControlInput.qd .* of shape \(N, J\) = \(3, 2\), got"):
            stage(tau, ControlInput(action=None, qd=qd))


@pytest.mark.parametrize("make", [lambda: MotorConstant(0.8, 1.2), lambda: Friction((0.0, 1.0), (0.0, 1.0)),
                                  Saturation, lambda: Delay(0, 8, 8), lambda: AveragedDelay(0, 8, 8),
                                  lambda: ActuatorChain([MotorConstant(0.8, 1.2), Saturation()])])
def test_stages_refuse_a_torque_of_the_wrong_shape_or_device(make):
    # A (N, 1) or (1, J) torque broadcast silently against the (N, J) parameters: every joint (or world) got one
    # joint's (world's) command. A torque on another device failed inside torch without naming the stage.
    stage = built(make())
    name = type(stage).__name__
    inp = ControlInput(action=None, qd=torch.zeros(3, 2))
    for tau in (torch.ones(3, 1), torch.ones(1, 2), torch.ones(3, 3), torch.ones(6), torch.ones(3, 1, 2, 2)):
        with pytest.raises(ValueError, match=rf"{name} takes tau of shape \(N, J\) = \(3, 2\).*, got "):
            stage(tau, inp)
    with pytest.raises(ValueError, match=rf"{name} got tau on meta, its parameters are on cpu"):
        stage(torch.ones(3, 2, device="meta"), inp)
    assert stage(torch.ones(3, 2), inp).shape[0] == 3  # the right shape still runs


def test_stages_after_a_delay_take_its_substeps_and_a_delay_takes_one_torque():
    chain = built(ActuatorChain([Delay(0, 8, 8), MotorConstant(0.8, 1.2), Saturation()]))
    assert chain(torch.ones(3, 2), ControlInput(action=None)).shape == (3, 8, 2)
    with pytest.raises(ValueError, match=r"Delay takes tau of shape \(N, J\) = \(3, 2\), got \(3, 8, 2\)"):
        built(Delay(0, 8, 8))(torch.ones(3, 8, 2), ControlInput(action=None))


def test_a_chain_takes_stage_instances_and_saturation_its_joints_limits():
    # A class (or a config) in place of a stage was accepted and failed only at setup or in the first step.
    for bad in (MotorConstant, ActuatorConfig(motor_constant=(0.8, 1.2))):
        with pytest.raises(ValueError, match="an actuator chain takes Actuator instances"):
            ActuatorChain([Saturation(), bad])
    # One limit for two joints broadcast: both joints clipped at the first joint's limit.
    with pytest.raises(ValueError, match=r"Saturation takes ControlContext.torque_limits of shape \(J,\) = \(2,\)"):
        Saturation().setup(dataclasses.replace(context(), torque_limits=torch.tensor([100.0])))

def test_saturation_clips_at_the_joint_limits():
    stage = built(Saturation())
    tau = torch.tensor([[150.0, -60.0], [-150.0, 10.0], [99.0, 50.0]])
    assert stage(tau, ControlInput(action=None)).tolist() == [[100.0, -50.0], [-100.0, 10.0], [99.0, 50.0]]


@pytest.mark.parametrize("substeps", [8, 3])
def test_delay_shifts_the_torque_by_exactly_k_substeps_per_world(substeps):
    # Different k in different worlds, below, at and above one policy step; u picks k = low + floor(u·span).
    low, high = 0, 2 * substeps + 3
    ks = [0, 1, substeps, substeps + 2, high]
    span = high - low + 1
    u = torch.tensor([[(k - low + 0.5) / span] for k in ks])
    stage = built(Delay(low, high, substeps), ctx=context(n=len(ks), limits=(100.0,)), u=u)
    assert stage.delay.tolist() == ks
    commands = [float(t + 1) for t in range(8)]  # step t commands t + 1 N·m (0 before the first step)
    per_substep = []  # what each world gets, substep by substep
    for c in commands:
        out = stage(torch.full((len(ks), 1), c), ControlInput(action=None))
        assert out.shape == (len(ks), substeps, 1)
        per_substep.append(out[..., 0])
    got = torch.cat(per_substep, dim=1)  # (worlds, steps × substeps)
    undelayed = torch.tensor(commands).repeat_interleave(substeps)
    for w, k in enumerate(ks):
        want = torch.cat((torch.zeros(k), undelayed[: len(undelayed) - k]))
        assert torch.equal(got[w], want), f"world {w} (k={k})"


def test_reset_redraws_only_the_flagged_worlds_and_clears_their_delay_history():
    chain = ActuatorChain([Delay(0, 16, 8), MotorConstant(0.8, 1.2)])
    chain.setup(context())
    gen = torch.Generator().manual_seed(1)
    chain.reset(ALL, torch.rand(3, chain.draws, generator=gen))
    chain(torch.full((3, 2), 5.0), ControlInput(action=None))
    delay, motor = chain.stages
    before_k, before_c = delay.delay.clone(), motor.scale.clone()
    mask = torch.tensor([False, True, False])
    chain.reset(mask, torch.rand(3, chain.draws, generator=gen))
    assert torch.equal(delay.delay[~mask], before_k[~mask]) and torch.equal(motor.scale[~mask], before_c[~mask])
    assert not torch.equal(motor.scale[1], before_c[1])
    assert float(delay.history[1].abs().sum()) == 0.0 and float(delay.history[0].abs().sum()) > 0.0



@pytest.mark.parametrize("make", [lambda: MotorConstant(0.8, 1.2), lambda: Friction((0.0, 1.0), (0.0, 1.0)),
                                  lambda: Delay(0, 16, 8), lambda: AveragedDelay(0, 16, 8),
                                  lambda: ActuatorChain([Delay(0, 16, 8), MotorConstant(0.8, 1.2), Saturation()])])
def test_reset_refuses_draws_and_masks_of_the_wrong_shape(make):
    # A (N, 1) u gave every joint the same draw, a (1, draws) one every world the same, and a wider one was cut
    # without a word; a mask of the wrong shape or dtype broadcast or failed inside torch.where.
    stage = built(make())
    name, draws = type(stage).__name__, stage.draws
    for u in (torch.rand(3, 1) if draws > 1 else torch.rand(3, 2), torch.rand(1, draws), torch.rand(3, draws + 1),
              torch.rand(3), torch.zeros(3, draws, dtype=torch.int64)):
        with pytest.raises(ValueError, match=rf"{name}.reset takes u of shape \(N, draws\) = \(3, {draws}\)"):
            stage.reset(ALL, u)
    with pytest.raises(ValueError, match=rf"{name}.reset got u on meta"):
        stage.reset(ALL, torch.rand(3, draws, device="meta"))
    u = torch.rand(3, draws)
    for mask in (torch.ones(3), torch.ones(1, dtype=torch.bool), torch.ones(3, 1, dtype=torch.bool)):
        with pytest.raises(ValueError, match=rf"{name}.reset takes mask of shape \(N,\) = \(3,\) torch.bool"):
            stage.reset(mask, u)
        with pytest.raises(ValueError, match=rf"{name}.nominal takes mask of shape \(N,\) = \(3,\) torch.bool"):
            stage.nominal(mask)
    stage.reset(ALL, u)  # the right shapes still redraw
    stage.nominal(torch.tensor([True, False, False]))


def test_a_narrow_draw_is_refused_before_any_joint_is_written():
    # The defect the shape check closes: one column per world was broadcast over the joints.
    stage = built(MotorConstant(0.8, 1.2), ctx=context(limits=(100.0, 50.0, 20.0)))
    before = stage.scale.clone()
    with pytest.raises(ValueError, match=r"MotorConstant.reset takes u of shape \(N, draws\) = \(3, 3\)"):
        stage.reset(ALL, torch.tensor([[0.0], [0.5], [1.0 - 2**-24]]))
    assert torch.equal(stage.scale, before)  # refused before anything was written

def test_draws_are_in_range_and_differ_between_worlds():
    stage = built(MotorConstant(0.8, 1.2), ctx=context(n=4096))
    scale = stage.scale
    assert 0.8 - 1e-6 <= float(scale.min()) and float(scale.max()) <= 1.2 + 1e-6
    assert abs(float(scale.mean()) - 1.0) < 0.01 and abs(float(scale.std()) - 0.4 / 12**0.5) < 0.01
    delay = built(Delay(4, 20, 8), ctx=context(n=4096))
    counts = torch.bincount(delay.delay, minlength=21)[4:]
    assert int(counts.min()) > 4096 / 17 * 0.7 and len(counts) == 17


def test_config_builds_the_stages_it_names_and_nothing_when_ideal():
    assert len(ActuatorConfig().build(8)) == 0
    chain = ActuatorConfig(delay_substeps=(4, 20), motor_constant=(0.8, 1.2), viscous=(0.0, 1.0)).build(8)
    assert [type(s).__name__ for s in chain.stages] == ["Delay", "MotorConstant", "Friction", "Saturation"]
    for bad in (dict(delay_substeps=(5, 2)), dict(motor_constant=(-1.0, 1.0)), dict(coulomb=(0.0, float("nan"))),
                dict(delay_substeps=(0.5, 2))):
        with pytest.raises(ValueError, match="env.control.actuators"):
            ActuatorConfig(**bad).validate()
    # Accepted, and the delay's history would then have held 10**9 past torques of every world.
    with pytest.raises(ValueError, match=r"delay_substeps \(0, 1000000000\) reaches past 400 substeps"):
        ActuatorConfig(delay_substeps=(0, 10 ** 9)).validate()
    # Options of a delay without one were accepted and did nothing.
    for shaping in (dict(delay_average=True), dict(delay_stride=8)):
        with pytest.raises(ValueError, match=r"shape a torque delay, but delay_substeps is \(0, 0\)"):
            ActuatorConfig(**shaping).validate()
    strided = ActuatorConfig(delay_substeps=(4, 20), delay_stride=8).build(8).stages[0]
    assert strided.values() == [4, 12, 20]
    for stride, message in ((5, "does not divide the delay range"), (0, ">= 1"), (True, ">= 1")):
        with pytest.raises(ValueError, match=f"env.control.actuators.delay_stride.*{message}"):
            ActuatorConfig(delay_substeps=(4, 20), delay_stride=stride).validate()


def test_bad_actuator_ranges_are_named_and_numpy_delays_taken():
    # A scalar or a wrong count failed as a raw unpack error ("cannot unpack non-iterable float object"), a negative
    # motor constant (the torque's sign flipped) was taken by the stage though the config refused it, and a numpy
    # integer delay was refused as not "whole substeps".
    for bad in (1.2, (0.8, 1.0, 1.2), None):
        with pytest.raises(ValueError, match=r"env.control.actuators.motor_constant must be two numbers \(low, high\)"):
            ActuatorConfig(motor_constant=bad).validate()
    refused = ((lambda: MotorConstant(-1.0, -1.0), r"MotorConstant scale must be \(low, high\) with 0 <= low"),
               (lambda: MotorConstant("a", 1.0), r"MotorConstant scale must be two numbers"),
               (lambda: Friction(1.0, (0.0, 0.0)), r"Friction coulomb must be two numbers \(low, high\), got 1.0"),
               (lambda: Friction((0.0, 0.0), (-1.0, 0.0)), r"Friction viscous must be \(low, high\) with 0 <= low"),
               (lambda: Delay(2.0, 4, 8), r"Delay low takes a whole number of substeps, got 2.0"))
    for build, message in refused:
        with pytest.raises(ValueError, match=message):
            build()
    assert Delay(np.int64(4), np.int64(20), np.int64(8), stride=np.int64(8)).values() == [4, 12, 20]


def test_a_strided_delay_draws_its_grid_alone_and_each_value_of_it():
    delay = built(Delay(4, 20, 8, stride=8), ctx=context(n=3000))
    counts = torch.bincount(delay.delay, minlength=21)
    assert set(torch.nonzero(counts).flatten().tolist()) == {4, 12, 20}
    assert int(counts[[4, 12, 20]].min()) > 3000 / 3 * 0.8
    with pytest.raises(ValueError, match="divides high - low"):
        Delay(4, 20, 8, stride=3)


@pytest.mark.parametrize("substeps", [8, 3])
def test_an_averaged_delay_holds_the_delayed_torque_s_mean_over_each_step(substeps):
    # Every k of a range that ends on a whole step (no older slot for k = high) and one that does not.
    for low, high in ((0, 2 * substeps), (1, 2 * substeps + 3)):
        ks = list(range(low, high + 1))
        u = torch.tensor([[(k - low + 0.5) / len(ks)] for k in ks])
        ctx = context(n=len(ks), limits=(100.0,))
        exact = built(Delay(low, high, substeps), ctx=ctx, u=u)
        mean = built(AveragedDelay(low, high, substeps), ctx=ctx, u=u)
        assert exact.delay.tolist() == mean.delay.tolist() == ks
        gen = torch.Generator().manual_seed(substeps)
        for _ in range(6):
            tau = torch.randn(len(ks), 1, generator=gen)
            got = mean(tau, ControlInput(action=None))
            assert got.shape == (len(ks), 1)
            torch.testing.assert_close(got, exact(tau, ControlInput(action=None)).mean(dim=1))
    # k = 6 of 8: the older command in 6 substeps, the newer in 2.
    stage = built(AveragedDelay(6, 6, 8), ctx=context(n=1, limits=(100.0,)))
    assert stage(torch.tensor([[8.0]]), ControlInput(action=None)).tolist() == [[2.0]]
    assert stage(torch.tensor([[16.0]]), ControlInput(action=None)).tolist() == [[10.0]]  # 6/8·8 + 2/8·16


def test_an_averaged_delay_is_one_torque_per_step_and_resets_like_the_delay():
    cfg = ActuatorConfig(delay_substeps=(4, 20), motor_constant=(0.8, 1.2), delay_average=True)
    chain = cfg.build(8)
    assert [type(s).__name__ for s in chain.stages] == ["AveragedDelay", "MotorConstant", "Saturation"]
    assert not chain.per_substep and chain.substeps == 1
    assert ActuatorConfig(delay_substeps=(4, 20)).build(8).per_substep
    chain.setup(context())
    gen = torch.Generator().manual_seed(2)
    chain.reset(ALL, torch.rand(3, chain.draws, generator=gen))
    assert chain(torch.full((3, 2), 5.0), ControlInput(action=None)).shape == (3, 2)
    delay = chain.stages[0]
    mask = torch.tensor([False, True, False])
    before = delay._weights.clone()
    chain.reset(mask, torch.rand(3, chain.draws, generator=gen))
    assert torch.equal(delay._weights[~mask], before[~mask])
    assert float(delay.history[1].abs().sum()) == 0.0 and float(delay.history[0].abs().sum()) > 0.0
    torch.testing.assert_close(delay._weights.sum(dim=1), torch.ones(3))  # every world's shares add up to one
    with pytest.raises(ValueError, match="delay_average must be True or False"):
        ActuatorConfig(delay_substeps=(4, 20), delay_average=1).validate()



def test_the_doc_s_own_stage_runs_in_a_chain_and_the_env_takes_only_the_config_s_stages():
    # The guide promised a place for "your own actuator model", but the env builds its layer from ActuatorConfig
    # alone. The guide's example stage must run in a chain of its own as written, and the env must still refuse
    # any Actuator object (else the guide's "outside the env" is stale).
    blocks = python_blocks(DOC)
    block = next((b for b in blocks if "class TorqueOffset(Actuator)" in b), None)
    assert block is not None, "docs/concepts/controllers.md has no example of a stage of one's own"
    ns: dict = {}
    exec(compile(block, str(DOC), "exec"), ns)  # noqa: S102 - the project's own documentation
    chain, tau = ns["chain"], ns["tau"]
    motor, offset = chain.stages
    assert chain.draws == 24 and tau.shape == (4, 12)
    torch.testing.assert_close(tau, 10.0 * motor.scale + offset.offset)
    assert float(offset.offset.abs().max()) <= 2.0 and float(offset.offset.abs().min()) > 0.0
    chain.nominal(torch.tensor([True, False, False, False]))
    assert float(offset.offset[0].abs().max()) == 0.0 and float(motor.scale[0].sub(1.0).abs().max()) == 0.0
    # After a Delay, the stage gets (and returns) one torque per substep; only the built-in Delay makes it so.
    delayed = ActuatorChain([Delay(0, 8, 8), ns["TorqueOffset"](2.0)])
    delayed.setup(ns["ctx"])
    delayed.reset(torch.ones(4, dtype=torch.bool), torch.rand(4, delayed.draws))
    assert delayed.per_substep and delayed(torch.ones(4, 12), ControlInput(action=None)).shape == (4, 8, 12)
    cfg = TocabiWalkConfig()
    with pytest.raises(ValueError, match="env.control.actuators must be a ActuatorConfig"):
        dataclasses.replace(cfg, control=dataclasses.replace(cfg.control, mode="torque", actuators=chain)).validate()
    for build in (TocabiWalk.__init__, make_env):
        assert not [p for p in inspect.signature(build).parameters if "actuator" in p], build

def test_actuators_are_refused_on_servo_modes():
    cfg = TocabiWalkConfig()
    cfg = dataclasses.replace(cfg, control=dataclasses.replace(cfg.control, actuators=ActuatorConfig(
        motor_constant=(0.9, 1.1))))
    with pytest.raises(ValueError, match="torque commands"):
        cfg.validate()


def test_simulator_applies_substep_controls_in_their_substep():
    # MujocoSim with a per-substep schedule against MuJoCo stepped by hand with the same controls.
    cols = (0, 3)
    sim = MujocoSim(SimConfig(num_worlds=2, substeps=4, threads=1, substep_ctrl=cols))
    schedule = torch.tensor([[[10.0, -5.0], [20.0, 0.0], [-30.0, 5.0], [0.0, 40.0]],
                             [[-10.0, 5.0], [0.0, 0.0], [30.0, -5.0], [15.0, 15.0]]])
    sim.substep_ctrl.copy_(schedule)
    sim.ctrl[:, 1] = 7.0
    qpos0 = sim.qpos.clone()
    sim.step()
    m = sim.mj_model
    for w in range(2):
        d = mujoco.MjData(m)
        d.qpos[:] = qpos0[w].double().numpy()
        mujoco.mj_forward(m, d)
        d.qacc_warmstart[:] = d.qacc
        for s in range(4):
            d.ctrl[:] = 0.0
            d.ctrl[1] = 7.0
            d.ctrl[list(cols)] = schedule[w, s].double().numpy()
            mujoco.mj_step(m, d)
        mujoco.mj_forward(m, d)
        np.testing.assert_allclose(sim.qpos[w].numpy(), d.qpos.astype(np.float32), rtol=0, atol=1e-6)


def _torque_env(actuators: ActuatorConfig, n=4, **kw):
    cfg = TocabiWalkConfig()
    control = dataclasses.replace(cfg.control, mode="torque", actuators=actuators)
    return TocabiWalk(num_envs=n, device="cpu", seed=0, config=dataclasses.replace(cfg, control=control), **kw)


def test_env_delays_each_worlds_torque_by_its_own_k():
    env = _torque_env(ActuatorConfig(delay_substeps=(0, 20)), n=6, sim_threads=1)
    env.reset()
    ks = env.leg_actuators.stages[0].delay.tolist()
    assert len(set(ks)) > 1, ks  # the worlds drew different delays
    schedules = []
    for t in range(4):
        action = torch.zeros(6, 13)
        action[:, :12] = 0.01 * (t + 1)
        env.step(_td(env, action))
        schedules.append(env.sim.substep_ctrl.clone())
    got = torch.cat(schedules, dim=1)  # (6, 4·8, 12)
    limits = torch.as_tensor(robot.LEG_TORQUE_LIMITS, dtype=torch.float32)
    undelayed = torch.cat([torch.full((8, 12), 0.01 * (t + 1)) * limits for t in range(4)])
    for w, k in enumerate(ks):
        want = torch.cat((torch.zeros(k, 12), undelayed))[: 4 * 8]
        torch.testing.assert_close(got[w], want, rtol=0, atol=0)
    # leg_torque reports what the joints got in the last substep.
    torch.testing.assert_close(env.leg_torque, got[:, -1])


def test_env_with_an_averaged_delay_applies_each_worlds_step_mean_through_the_step():
    env = _torque_env(ActuatorConfig(delay_substeps=(0, 20), delay_average=True), n=6, sim_threads=1)
    assert env.sim.substep_ctrl is None  # one torque per step: no per-substep controls
    env.reset()
    ks = env.leg_actuators.stages[0].delay.tolist()
    assert len(set(ks)) > 1, ks
    limits = torch.as_tensor(robot.LEG_TORQUE_LIMITS, dtype=torch.float32)
    undelayed = torch.cat([torch.full((8, 12), 0.01 * (t + 1)) * limits for t in range(4)])
    for t in range(4):
        action = torch.zeros(6, 13)
        action[:, :12] = 0.01 * (t + 1)
        env.step(_td(env, action))
        for w, k in enumerate(ks):  # the mean of what Delay would apply in this step's 8 substeps
            want = torch.cat((torch.zeros(k, 12), undelayed))[8 * t: 8 * t + 8].mean(dim=0)
            torch.testing.assert_close(env.leg_torque[w], want)


def _td(env, action):
    from tensordict import TensorDict

    return TensorDict({"action": action}, batch_size=[env.num_envs])


def test_ideal_actuator_runs_nothing_and_a_full_set_changes_the_torque():
    ideal = _torque_env(ActuatorConfig(), sim_threads=1)
    assert len(ideal.leg_actuators) == 0 and ideal.sim.substep_ctrl is None
    full = _torque_env(ActuatorConfig(motor_constant=(0.5, 0.5), coulomb=(1.0, 1.0)), sim_threads=1)
    ideal.reset(), full.reset()
    action = torch.full((4, 13), 0.1)
    ideal.step(_td(ideal, action)), full.step(_td(full, action))
    limits = torch.as_tensor(robot.LEG_TORQUE_LIMITS, dtype=torch.float32)
    torch.testing.assert_close(ideal.leg_torque, (0.1 * limits).expand(4, 12))
    # motor constant 0.5, then 1 N·m of Coulomb friction against the pre-step velocity (at rest after the reset)
    torch.testing.assert_close(full.leg_torque, (0.05 * limits).expand(4, 12))
    assert torch.equal(full.applied_action, ideal.applied_action)  # the policy's command, not the joint torque


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("cuda_graph", [False, True])
@pytest.mark.parametrize("average", [False, True])
def test_gpu_actuators_never_sync_and_follow_resets(cuda_graph, average):
    cfg = TocabiWalkConfig()
    control = dataclasses.replace(cfg.control, mode="torque", actuators=ActuatorConfig(
        delay_substeps=(4, 20), motor_constant=(0.8, 1.2), coulomb=(0.0, 2.0), viscous=(0.0, 1.0),
        delay_average=average))
    e = make_env(num_envs=128, device="cuda", seed=0, cuda_graph=cuda_graph,
                 config=dataclasses.replace(cfg, control=control, task=dataclasses.replace(cfg.task,
                                                                                         max_episode_steps=3)))
    td = e.reset()
    action = (torch.rand(128, 13, device="cuda") * 2 - 1) * 0.3
    for _ in range(3):
        _, td = e.step_and_maybe_reset(td.set("action", action))
    assert e.graph_captured == cuda_graph
    scale = e.base_env.leg_actuators.stages[1].scale
    before = scale.clone()
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(6):  # crosses the 3-step truncation: every world resets and redraws its parameters
            step, td = e.step_and_maybe_reset(td.set("action", action))
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert bool(step["next", "truncated"].any())
    assert not torch.equal(scale, before)  # redrawn in place, inside the (captured) step
    assert 0.8 - 1e-6 <= float(scale.min()) and float(scale.max()) <= 1.2 + 1e-6


@pytest.mark.parametrize("backend", ["mujoco", "warp"])
def test_applied_body_force_pushes_the_robot_and_clears_at_reset(backend):
    # A 1 kN push along +y on the pelvis for one policy step (4 ms, 4 N·s) moves the pelvis along +y, in that world
    # only; a reset zeroes the force, as MuJoCo's reset does.
    if backend == "warp":
        pytest.importorskip("warp")
    from tocabi_torchrl.sim import WarpSim

    make = MujocoSim if backend == "mujoco" else WarpSim
    sim = make(SimConfig(num_worlds=2, threads=1))
    base = sim.mj_model.body(robot.BASE_BODY).id
    sim.step()
    before = sim.qvel[:, 1].clone()
    sim.xfrc_applied[0, base, 1] = 1000.0
    sim.step()
    dv = sim.qvel[:, 1] - before
    assert float(dv[0]) > 0.02 and abs(float(dv[1])) < 0.005, dv
    sim.reset(torch.tensor([True, False]), sim.qpos.clone(), torch.zeros(sim.nv))
    assert float(sim.xfrc_applied[0].abs().max()) == 0.0 and float(sim.xfrc_applied[1].abs().max()) == 0.0
