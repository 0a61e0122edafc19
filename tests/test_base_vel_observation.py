"""The ``base_vel`` observation (``transforms.observation``): the reference's 37 values and the pelvis's linear and
angular velocity, 43 values a step (transforms/layouts.py). Its columns, statistics, config checks and a training
run that saves and reloads it; the mirror rules are checked against the physics in tests/test_symmetry.py."""

from __future__ import annotations

import math

import pytest
import torch

from tocabi_torchrl import make_env
from tocabi_torchrl.config import ConfigError, config_from_dict, field_choices, preset_config
from tocabi_torchrl.transforms import FixedNormalization, SensorNoiseConfig, TransformSettings
from tocabi_torchrl.transforms.layouts import BASE_VEL_OBS_LAYOUT, OBS_LAYOUTS, REFERENCE_OBS_LAYOUT
from tocabi_torchrl.transforms.normalize import BASE_VEL_OBS_MEAN, BASE_VEL_OBS_VAR, REFERENCE_OBS_MEAN
from tocabi_torchrl.transforms.settings import transform_config


def _env(**settings):
    return make_env(num_envs=3, device="cpu", seed=0, transforms=TransformSettings(observation="base_vel", **settings))


def test_the_last_six_columns_are_the_pelvis_velocity_and_the_first_37_the_reference_observation():
    env, ref = _env(), make_env(num_envs=3, device="cpu", seed=0)
    td, td_ref = env.reset(), ref.reset()
    assert td["observation"].shape == (3, 5 * 43 + 4 * 13) and td["obs_step"].shape == (3, 43)
    torch.manual_seed(1)
    actions = 0.3 * torch.randn(4, 3, 13)
    for a in actions:
        td["action"], td_ref["action"] = a, a.clone()
        td, td_ref = env.step(td)["next"], ref.step(td_ref)["next"]
    # The same worlds: the added columns change nothing of the reference's 37, and hold the env's raw signals.
    assert torch.equal(td["obs_step"][:, :37], td_ref["obs_step"])
    assert torch.equal(td["obs_step"][:, 37:40], td["base_lin_vel"])
    assert torch.equal(td["obs_step"][:, 40:43], td["base_ang_vel"])
    assert td["base_lin_vel"].abs().max() > 1e-3  # moving: the check above compares numbers, not zeros


def test_the_sensor_noise_leaves_the_velocity_columns_exact():
    """The TOCABI lab's set perturbs the joint encoders, IMU angles and F/T sensors, not the pelvis velocity: its own
    options (``base_lin_vel_*``, ``base_ang_vel_*``) are off there, and the velocity columns stay the true state."""
    env = _env(sensor_noise=SensorNoiseConfig.tocabi_lab())
    td = env.reset()
    torch.manual_seed(2)
    for _ in range(4):
        td["action"] = 0.3 * torch.randn(3, 13)
        td = env.step(td)["next"]
    assert td["base_lin_vel"].abs().max() > 1e-3 and td["base_ang_vel"].abs().max() > 1e-3  # moving
    assert torch.equal(td["obs_step"][:, 37:40], td["base_lin_vel"])
    assert torch.equal(td["obs_step"][:, 40:43], td["base_ang_vel"])
    assert not torch.equal(td["obs_step"][:, 3:15], td["joint_pos"][:, :12])  # the encoder biases do reach theirs


def test_fixed_statistics_cover_the_43_values():
    env = _env()
    norm = next(t for t in env.transform if isinstance(t, FixedNormalization))
    assert norm.loc.shape == (43,)
    assert torch.allclose(norm.loc, torch.tensor(BASE_VEL_OBS_MEAN, dtype=torch.float32))
    # What the policy's history receives: the velocity columns normalised by the added statistics.
    td = env.reset()
    td["action"] = torch.zeros(3, 13)
    td = env.step(td)["next"]
    mean, var = torch.tensor(BASE_VEL_OBS_MEAN[37:]), torch.tensor(BASE_VEL_OBS_VAR[37:])
    expected = (td["obs_step"][:, 37:] - mean) / torch.sqrt(var + 1e-8)
    torch.testing.assert_close(td["obs_step_norm"][:, 37:], expected)
    # Mirror-symmetric statistics: sideways velocity, roll and yaw rates have mean 0.
    assert [BASE_VEL_OBS_MEAN[i] for i in (38, 40, 42)] == [0.0, 0.0, 0.0]
    assert all(v > 0 and math.isfinite(v) for v in BASE_VEL_OBS_VAR[37:])


def test_the_config_names_the_layout_and_checks_it():
    assert field_choices()["transforms.observation"] == ("reference", "base_vel")
    for name in ("torque", "model_based", "pd"):  # the presets for the real robot sense the pelvis velocity
        cfg = preset_config(name)
        assert cfg.transforms.transform_config().obs_layout == BASE_VEL_OBS_LAYOUT, name
        assert config_from_dict(cfg.to_dict()) == cfg
    # Every other preset keeps the reference's observation, the shipped policies' input.
    for name in ("default", "robust", "torque_ideal", "model_based_ideal", "reference", "cpu_smoke"):
        assert preset_config(name).transforms.transform_config().obs_layout == REFERENCE_OBS_LAYOUT, name
    with pytest.raises((ValueError, ConfigError), match=r"transforms\.observation.*'base_vel'"):
        preset_config("torque", **{"transforms.observation": "velocity"})


def test_the_statistics_length_is_checked_against_the_layout():
    assert transform_config(obs_layout=OBS_LAYOUTS["base_vel"]).step_obs_size() == 43
    assert transform_config(obs_layout=OBS_LAYOUTS["base_vel"], phase_harmonics=2).step_obs_size() == 45
    with pytest.raises(ValueError, match=r"has 43 \(the base_vel obs_layout: 41 values"):
        transform_config(obs_layout=BASE_VEL_OBS_LAYOUT, obs_mean=REFERENCE_OBS_MEAN,
                         obs_var=tuple(1.0 for _ in REFERENCE_OBS_MEAN))


def test_a_training_run_saves_the_layout_and_its_policy_loads_with_it(tmp_path):
    from tocabi_torchrl.evaluation.record import load_policy
    from tocabi_torchrl.rl.trainer import train

    cfg = preset_config("cpu_smoke", device="cpu", **{"transforms.observation": "base_vel", "ppo.symmetry": "augment",
                                                      "env.num_envs": 4, "ppo.steps_per_env": 8,
                                                      "ppo.minibatch_size": 16},
                        total_env_steps=64, run_dir=str(tmp_path), name="bv", progress_bar=False, eval_at_end=False)
    result = train(cfg)
    assert result.iterations == 2 and math.isfinite(result.last_metrics["loss_policy"])
    policy = load_policy(tmp_path / "bv" / "checkpoints" / "iter_000002.pt", num_envs=2, device="cpu",
                         backend="mujoco")
    td = policy.env.reset()
    assert td["observation"].shape == (2, 267)
    assert policy.agent.actor(td)["action"].shape == (2, 13)


def test_the_velocity_noise_reaches_the_velocity_columns_within_its_bounds():
    noise = SensorNoiseConfig(base_lin_vel_bias=0.05, base_lin_vel_noise_std=0.02, base_lin_vel_noise_clip=0.03,
                              base_ang_vel_noise_std=0.1, base_ang_vel_noise_clip=0.2)
    env = _env(sensor_noise=noise)
    td = env.reset()
    lin, ang = [], []
    for _ in range(6):
        td["action"] = torch.zeros(3, 13)
        td = env.step(td)["next"]
        lin.append(td["obs_step"][:, 37:40] - td["base_lin_vel"])
        ang.append(td["obs_step"][:, 40:43] - td["base_ang_vel"])
    lin, ang = torch.stack(lin), torch.stack(ang)
    assert lin.abs().max() <= 0.05 + 0.03 + 1e-5 and ang.abs().max() <= 0.2 + 1e-5
    assert lin.std(0).mean() > 1e-3 and ang.abs().max() > 0.01  # fresh every step, not a constant
    # A bias alone: constant within the episode, within ±b, and nothing else of the observation moves.
    env, clean = _env(sensor_noise=SensorNoiseConfig(base_lin_vel_bias=0.05, base_ang_vel_bias=0.1)), _env()
    td, ref = env.reset(), clean.reset()
    offsets = []
    for _ in range(4):
        td["action"], ref["action"] = torch.zeros(3, 13), torch.zeros(3, 13)
        td, ref = env.step(td)["next"], clean.step(ref)["next"]
        assert torch.equal(td["obs_step"][:, :37], ref["obs_step"][:, :37])
        offsets.append(td["obs_step"][:, 37:] - torch.cat((td["base_lin_vel"], td["base_ang_vel"]), -1))
    offsets = torch.stack(offsets)
    torch.testing.assert_close(offsets, offsets[:1].expand_as(offsets), atol=1e-6, rtol=0)
    assert offsets[0, :, :3].abs().max() <= 0.05 and offsets[0, :, 3:].abs().max() <= 0.1
    assert offsets[0].abs().min() > 0  # drawn, not zero
    # The reference observation reads no velocity: a velocity noise there is refused, naming the fix.
    with pytest.raises(ValueError, match=r"SensorNoise perturbs \['base_lin_vel', 'base_ang_vel'\], which the "
                                         r"observation layout does not read"):
        make_env(num_envs=2, device="cpu", seed=0, transforms=TransformSettings(sensor_noise=noise)).reset()


def test_the_robust_cases_keep_the_policys_own_velocity_noise():
    """The pushed cases (one env per case, and the one batch env of every case) add the lab's set to the ideal
    robot, whose config has no sensor noise: the velocity's noise must come from the policy's own training."""
    from tocabi_torchrl.evaluation.robust import (RobustTestConfig, batch_config, case_config, randomization_applied,
                                                  robust_case_config)

    cfg = preset_config("torque", **{"transforms.sensor_noise.base_lin_vel_noise_std": 0.02,
                                     "transforms.sensor_noise.base_ang_vel_bias": 0.01})
    for built in (case_config(cfg, "robust_0.5"), case_config(cfg, "robust_1.0"), batch_config(cfg, RobustTestConfig()),
                  robust_case_config(cfg, 1.0)):
        noise = built.transforms.sensor_noise
        assert noise.base_lin_vel_noise_std == 0.02 and noise.base_ang_vel_bias == 0.01
        assert noise.joint_pos_bias == SensorNoiseConfig.tocabi_lab().joint_pos_bias  # the lab's set besides
    assert case_config(cfg, "nominal").transforms.sensor_noise == SensorNoiseConfig()  # unpushed cases: none at all
    assert "the pelvis velocity's sensor noise of the policy's training" in randomization_applied(cfg)
    plain = preset_config("torque")
    assert case_config(plain, "robust_1.0").transforms.sensor_noise == SensorNoiseConfig.tocabi_lab()
    assert "pelvis velocity" not in randomization_applied(plain)
