"""The TOCABI lab's uncertainty model as one named set, and the robust preset that trains under it."""

from __future__ import annotations

import math

import torch

from tocabi_torchrl.config import preset_config, preset_tree
from tocabi_torchrl.envs import TocabiWalkConfig
from tocabi_torchrl.randomize import tocabi_lab


def test_tocabi_lab_switches_on_every_piece_with_the_labs_numbers():
    cfg = tocabi_lab(preset_tree("torque_ideal"))
    act, dyn, sensors = cfg.env.control.actuators, cfg.env.dynamics, cfg.transforms.sensor_noise
    assert act.delay_substeps == (4, 20) and cfg.env.sim.substeps == 8  # 2-10 ms in 0.5 ms substeps
    assert act.motor_constant == (0.8, 1.2)
    assert dyn.mass_scale == (0.8, 1.2) and dyn.joint_damping == (0.0, 2.9) and dyn.armature_scale == (0.8, 1.2)
    assert math.isclose(sensors.joint_pos_bias, math.pi / 100) and math.isclose(sensors.base_rpy_bias, math.pi / 150)
    assert (sensors.foot_force_bias, sensors.foot_torque_bias) == (100.0, 10.0)
    assert math.isclose(sensors.joint_pos_noise_std, 0.00016 / 3) and sensors.joint_pos_noise_clip == 0.00016
    # an env config gets the env's share; the existing presets keep every piece off
    env = tocabi_lab(TocabiWalkConfig(control=cfg.env.control))
    assert env.dynamics == dyn and env.control.actuators == act
    plain = preset_tree("torque_ideal")
    assert plain.env.control.actuators.ideal and not plain.env.dynamics.enabled
    assert not plain.transforms.sensor_noise.enabled and plain.env.pushes.count == 0


def test_the_robust_preset_builds_an_env_with_everything_on_and_steps_it():
    from tocabi_torchrl.rl.trainer import build_env

    cfg = preset_config("robust", device="cpu", **{"env.num_envs": 4, "ppo.minibatch_size": 48})
    assert cfg.env.control.mode == "torque" and cfg.ppo.torque_assist == 1.0  # the torque preset's training
    assert cfg.env.pushes.count > 0 and cfg.ppo.push_ramp[1] > cfg.ppo.push_ramp[0] > 0
    assert cfg.eval_test == "robust" and cfg.eval_envs == 1024  # its verdict is the robust gait test, at full size
    env = build_env(cfg, torch.device("cpu"), for_training=True)
    base = env.base_env
    assert len(base.leg_actuators) == 3 and base.dynamics is not None and base.pushes is not None
    td = env.reset()
    for _ in range(5):
        out, td = env.step_and_maybe_reset(td.set("action", torch.zeros(4, 13)))
    assert torch.isfinite(out["next", "observation"]).all()
    # The heading-hold term's premise: every episode, diverse start or not, begins facing the world's +x, so one
    # step after a reset the term pays (almost) its whole weight.
    first, _ = env.step_and_maybe_reset(env.reset().set("action", torch.zeros(4, 13)))
    torch.testing.assert_close(first["next", "reward_terms", "heading"],
                               torch.full((4, 1), cfg.transforms.heading_weight), rtol=1e-3, atol=0.0)
