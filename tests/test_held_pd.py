"""The ``pd_held`` control mode: the torque assist's law at β = 1 as a law of its own (control.HeldPD)."""

from __future__ import annotations

import pytest
import torch

from tocabi_torchrl import robot
from tocabi_torchrl.control import AssistedTorque, ControlContext, ControlInput, HeldPD
from tocabi_torchrl.rl import preset_config

LIMITS = torch.as_tensor(robot.LEG_TORQUE_LIMITS, dtype=torch.float32)
#: The robust recipe in pd_held mode, without the torque assist (what a PD run of that recipe sets).
PD_HELD = {"env.control.mode": "pd_held", "ppo.torque_assist": 0.0, "ppo.assist_fade_start": 0,
           "ppo.assist_fade_end": 0, "ppo.assist_anchor_decay": 0, "ppo.assist_lr_hold": "fade",
           "ppo.assist_lr_max": 0.0, "ppo.assist_pd_sensed": False}
#: Small CPU envs of the robust recipe: no kicks, fresh draws at each reset.
SMALL = {"env.sim.start_pool": 0, "env.pushes.count": 0, "env.num_envs": 4, "ppo.minibatch_size": 12}


def _ctx(n: int) -> ControlContext:
    return ControlContext(num_envs=n, device=torch.device("cpu"), joint_ids=tuple(range(12)), torque_limits=LIMITS,
                          joint_range=torch.tensor([[-3.0, 3.0]] * 12))


def test_the_law_is_the_torque_assists_at_full_beta():
    gen = torch.Generator().manual_seed(0)
    n = 64
    held, assisted = HeldPD(robot.LEG_KP, robot.LEG_KV, 0.5), AssistedTorque(robot.LEG_KP, robot.LEG_KV, 0.5)
    for law in (held, assisted):
        law.setup(_ctx(n))
    assisted.set_beta(1.0)
    offset = 0.03 * torch.randn(n, 12, generator=gen)
    mask = torch.rand(n, generator=gen) < 0.5
    held.set_q_offset(mask, offset)
    assisted.set_q_offset(mask, offset)
    inp = ControlInput(action=torch.rand(n, 12, generator=gen) * 2 - 1, q=0.2 * torch.randn(n, 12, generator=gen),
                       qd=torch.randn(n, 12, generator=gen), q_ref=0.2 * torch.randn(n, 12, generator=gen))
    tau = held.compute(inp)
    torch.testing.assert_close(tau, assisted.compute(inp), rtol=1e-5, atol=1e-3)
    assert bool((tau.abs() <= LIMITS).all()) and bool((tau.abs() == LIMITS).any())  # saturates, within the limits
    torch.testing.assert_close(held.applied_action(inp, tau), tau / LIMITS)
    # The sensed offset moves the torque by -kp·offset where it does not saturate.
    bare = HeldPD(robot.LEG_KP, robot.LEG_KV, 0.5)
    bare.setup(_ctx(n))
    free = (tau.abs() < LIMITS) & (bare.compute(inp).abs() < LIMITS) & mask.unsqueeze(-1)
    assert int(free.sum()) > 10
    kp = torch.as_tensor(robot.LEG_KP, dtype=torch.float32).expand(n, 12)
    torch.testing.assert_close((tau - bare.compute(inp))[free], (-kp * offset)[free], rtol=1e-4, atol=1e-2)


def test_pd_held_trains_the_torque_preset_phase_it_copies():
    """The robust recipe's training env in pd_held mode steps as its assisted env at β = 1 does: the same applied
    leg torques and the same trajectory, the PD reading the same sensed joint positions."""
    from tocabi_torchrl.rl.trainer import build_env, check_given_env

    held_cfg = preset_config("robust", **SMALL, **PD_HELD)
    assisted_cfg = preset_config("robust", **SMALL)
    held = build_env(held_cfg, torch.device("cpu"), num_envs=4, for_training=True)
    check_given_env(held_cfg, held)  # the trainer takes it: its PD reads the sensed positions from the build
    assisted = build_env(assisted_cfg, torch.device("cpu"), num_envs=4, for_training=True)
    assisted.base_env.set_torque_assist(1.0)
    assert held.base_env.assist_reads_sensed and assisted.base_env.assist_reads_sensed
    gen = torch.Generator().manual_seed(1)
    actions = [torch.rand(4, 13, generator=gen) * 0.4 - 0.2 for _ in range(4)]
    outs = []
    for env in (held, assisted):
        td, seen = env.reset(), []
        for action in actions:
            td["action"] = action.clone()
            td = env.step(td)
            tau = td["next", "applied_action"][:, :12] * LIMITS  # the applied torque over the limits, in N·m
            seen.append((tau, env.base_env.sim.qpos.clone()))
            td = td["next"]
        outs.append(seen)
    # Every world reads its own encoder bias, which the lab's randomisation makes non-zero.
    offset = held.base_env.leg_controller.q_offset
    assert bool((offset != 0).any(-1).all())
    torch.testing.assert_close(offset, assisted.base_env.leg_controller.q_offset, rtol=0, atol=0)
    for (tau_h, q_h), (tau_a, q_a) in zip(*outs):
        torch.testing.assert_close(tau_h, tau_a, rtol=1e-4, atol=1e-2)
        torch.testing.assert_close(q_h, q_a, rtol=1e-4, atol=1e-4)
    assert float(outs[0][0][0].abs().max()) > 10.0  # the PD acts: tens of N·m


def test_pd_held_takes_the_actuator_model_and_pd_reference_refuses_it():
    from tocabi_torchrl.envs.config import TORQUE_MODES

    assert "pd_held" in TORQUE_MODES
    lab = preset_config("robust", **PD_HELD)
    assert lab.env.control.actuators.delay_substeps == (4, 20)  # the lab's 2-10 ms delay, kept
    with pytest.raises(ValueError, match="servos inside the physics; use a torque mode"):
        preset_config("robust", **{**PD_HELD, "env.control.mode": "pd_reference"})


def test_sensing_can_be_turned_off_and_other_modes_refuse_it():
    from tocabi_torchrl.envs import TocabiWalk

    env = TocabiWalk(num_envs=2, device="cpu", control_mode="pd_held")
    assert env.assist_reads_sensed
    settings = env.graph_settings
    env.sense_assist_joints(True)  # no change: a captured step stays valid
    assert env.graph_settings == settings
    env.sense_assist_joints(False)
    assert not env.assist_reads_sensed and bool((env.leg_controller.q_offset == 0).all())
    # A captured masked reset holds the flag (SensorNoise reads it there): the env asks for a new capture.
    assert env.graph_settings == settings + 1
    with pytest.raises(RuntimeError, match="torque_assist=True \\(torque mode\\) or in pd_held mode"):
        TocabiWalk(num_envs=1, device="cpu", control_mode="pd_reference").sense_assist_joints()


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.filterwarnings("error:SyncFreeResetEnv")  # a failed capture or an eager fallback fails the test
def test_gpu_captured_pd_held_step_follows_the_sensed_bias_and_never_syncs():
    """The captured step replays the eager one, the law and the sensed offset the SensorNoise transform writes at
    each masked reset included (episodes of 4 steps: every world resets in the 12), with no host sync."""
    from captured_vs_eager import assert_captured_equals_eager

    from tocabi_torchrl.transforms import SensorNoise, SensorNoiseConfig

    envs = {}

    def keep(i, eager, graphed):
        envs.update(eager=eager, graphed=graphed)

    assert_captured_equals_eager(dict(num_envs=64, device="cuda", seed=3, control_mode="pd_held", max_episode_steps=4,
                                      sensor_noise=SensorNoiseConfig.tocabi_lab()),
                                 ("leg_torque", "observation", "reward"), before_step=keep)
    for env in envs.values():
        noise = next(t for t in env.transform if isinstance(t, SensorNoise))
        torch.testing.assert_close(env.base_env.leg_controller.q_offset, noise.biases["joint_pos"][:, :12],
                                   rtol=0, atol=0)
