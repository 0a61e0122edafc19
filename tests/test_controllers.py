"""The controller interface: the user-defined controller of docs/concepts/controllers.md builds an env, steps it and
trains two PPO iterations on the CPU; a bad controller is refused by name."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from doc_blocks import python_blocks

from tocabi_torchrl import robot
from tocabi_torchrl.control import Controller, DirectTorque
from tocabi_torchrl.envs import TocabiWalk

DOC = Path(__file__).resolve().parents[1] / "docs" / "concepts" / "controllers.md"


def _doc_example() -> dict:
    """Run the python block of docs/concepts/controllers.md that defines PDFeedForward; return its namespace."""
    blocks = python_blocks(DOC)
    block = next(b for b in blocks if "class PDFeedForward" in b)
    namespace: dict = {}
    exec(compile(block, str(DOC), "exec"), namespace)  # noqa: S102 - the project's own documentation
    return namespace


@pytest.fixture(scope="module")
def example():
    return _doc_example()


def test_doc_controller_applies_its_law(example):
    env = example["env"].base_env
    assert env.leg_controller.__class__.__name__ == "PDFeedForward"
    env.sim.forward()
    td = example["env"].reset()
    action = torch.zeros(8, 13)
    action[:, :12] = 0.2
    q = env.sim.qpos[:, 7:19].clone()
    qd = env.sim.qvel[:, 6:18].clone()
    bias = env.sim.qfrc_bias[:, 6:18].clone()
    q_ref = env.motion.joint_targets(env.time, env.init_row)[:, :12]
    td = example["env"].step(td.set("action", action))
    limits = env.leg_torque_limits
    want = torch.clamp(400.0 * (q_ref + 0.5 * 0.2 - q) - 20.0 * qd + bias, -limits, limits)
    torch.testing.assert_close(td["next", "leg_torque"], want)
    torch.testing.assert_close(td["next", "applied_action"][:, :12], want / limits)
    assert torch.isfinite(td["next", "observation"]).all()


def test_doc_controller_trains_two_iterations_on_the_cpu(example, tmp_path):
    from tocabi_torchrl.rl import preset_config
    from tocabi_torchrl.rl.trainer import build_env, train

    cfg = preset_config("cpu_smoke", device="cpu", **{"env.num_envs": 4, "ppo.steps_per_env": 8,
                        "ppo.minibatch_size": 16},
                        total_env_steps=2 * 4 * 8, run_dir=str(tmp_path), name="pdff", progress_bar=False,
                        eval_at_end=False, **{"env.control.mode": "torque"})
    env = build_env(cfg, torch.device("cpu"), for_training=True, leg_controller=example["PDFeedForward"]())
    result = train(cfg, env=env)
    assert result.iterations == 2 and result.env_steps == 64
    assert (tmp_path / "pdff" / "checkpoints" / "latest.pt").is_file()


class _Bad(Controller):
    action_dim = 3

    def compute(self, inp):
        return inp.action


def test_a_controller_of_the_wrong_kind_or_width_is_refused():
    with pytest.raises(TypeError, match="Controller"):
        TocabiWalk(num_envs=1, device="cpu", leg_controller=object())
    with pytest.raises(ValueError, match="action_dim"):
        TocabiWalk(num_envs=1, device="cpu", leg_controller=_Bad())


class _ServoWithoutGains(Controller):
    servo = True
    action_dim = 12

    def compute(self, inp):
        return inp.q_ref[:, :12] + 0.5 * inp.action


def test_a_controller_reused_without_servo_gains_or_with_the_assist_is_refused():
    # Each was built: a reused law computed for the other env's simulator (or failed inside the law on other
    # sizes), a servo law's angles [rad] went to the leg motors as torques [N·m], and the assist failed at its first
    # set_torque_assist with an AttributeError.
    law = DirectTorque()
    TocabiWalk(num_envs=2, device="cpu", control_mode="torque", leg_controller=law)
    with pytest.raises(ValueError, match="this DirectTorque is already set up for another env .*pass a new instance"):
        TocabiWalk(num_envs=3, device="cpu", control_mode="torque", leg_controller=law)
    with pytest.raises(ValueError, match=r"servo_gains\(\) gives None: the legs' actuators .* are torque motors"):
        TocabiWalk(num_envs=1, device="cpu", leg_controller=_ServoWithoutGains())
    with pytest.raises(ValueError, match="torque_assist adds its PD .* leg_controller replaces that law"):
        TocabiWalk(num_envs=1, device="cpu", control_mode="torque", torque_assist=True, leg_controller=DirectTorque())


class _TorqueWithGains(DirectTorque):
    def servo_gains(self):
        return robot.LEG_KP, robot.LEG_KV


def test_a_torque_controller_that_gives_servo_gains_is_refused():
    # The env made the leg motors servos for any law with gains: a torque law's N·m became targets in rad, and
    # leg_torque reported the command (0 at a zero action) while the servos applied up to the limits.
    with pytest.raises(ValueError, match=r"_TorqueWithGains has servo = False .* but servo_gains\(\) gives gains: "
                                         r"the legs' motors would become position servos"):
        TocabiWalk(num_envs=1, device="cpu", control_mode="torque", leg_controller=_TorqueWithGains())


class _ServoAtReference(Controller):
    servo = True
    action_dim = 12

    def servo_gains(self):
        return robot.LEG_KP, robot.LEG_KV

    def compute(self, inp):
        return inp.q_ref[:, :12] + 0.1 * inp.action


def test_a_servo_law_without_a_rest_of_its_own_starts_its_servos_at_the_start_pose():
    # The base reset_command gave zeros to servo laws too: every reset drove their legs' servos to 0 rad.
    env = TocabiWalk(num_envs=2, device="cpu", leg_controller=_ServoAtReference())
    env.reset()
    legs = torch.as_tensor(robot.INIT_JOINT_POS[list(robot.LEG_JOINT_IDS)], dtype=torch.float32)
    torch.testing.assert_close(torch.as_tensor(env.sim.ctrl)[:, :12].float().cpu(), legs.expand(2, -1))


def test_a_user_controller_replaces_the_configured_one():
    env = TocabiWalk(num_envs=2, device="cpu", control_mode="pd_reference", leg_controller=DirectTorque())
    # a torque law: the leg motors stay motors (no servos), so a zero action applies no leg torque
    assert int(env.sim.mj_model.actuator_biastype[list(robot.LEG_JOINT_IDS)].sum()) == 0
    td = env.reset()
    td = env.step(td.set("action", torch.zeros(2, 13)))
    assert float(td["next", "leg_torque"].abs().max()) == 0.0


def test_the_config_names_a_law_per_joint_group():
    from tocabi_torchrl.control import PDHold
    from tocabi_torchrl.envs.config import ControlConfig, TocabiWalkConfig

    env = TocabiWalk(num_envs=1, device="cpu", control_mode="torque")
    assert isinstance(env.upper_controller, PDHold) and env.cfg.control.upper_body == "pd_hold"
    assert type(env.leg_controller) is DirectTorque
    with pytest.raises(ValueError, match="unknown env.control.upper_body 'impedance'; choose one of"):
        TocabiWalkConfig(control=ControlConfig(upper_body="impedance")).validate()


def test_an_env_other_than_its_config_is_refused_by_train(tmp_path):
    # train(cfg, env=...) saved cfg whatever the env was: a torque policy with running statistics was saved as a PD
    # policy with fixed ones, and every evaluation, play and export rebuilt the wrong env from it.
    from tocabi_torchrl.envs import TocabiWalk
    from tocabi_torchrl.rl import preset_config
    from tocabi_torchrl.rl.trainer import build_env, train
    from tocabi_torchrl.transforms.layouts import TOCABILAB_HISTORY
    from tocabi_torchrl.transforms.privileged import PrivilegedState
    from tocabi_torchrl.transforms.sensor_noise_config import SensorNoiseConfig

    cfg = preset_config("cpu_smoke", device="cpu", **{"env.num_envs": 4, "ppo.steps_per_env": 8,
                        "ppo.minibatch_size": 16}, total_env_steps=32, run_dir=str(tmp_path), name="x",
                        progress_bar=False, eval_at_end=False)
    cpu = torch.device("cpu")
    privileged_env = build_env(cfg, cpu, for_training=False)
    privileged_env.append_transform(PrivilegedState())
    for env, message in ((build_env(cfg, cpu, for_training=True, control_mode="torque"),
                          r"env.control.mode: 'torque' in the env, 'pd_reference' in cfg"),
                         (build_env(cfg, cpu, for_training=True, normalization="running"),
                          "normalises with running statistics, cfg.transforms.normalization is 'fixed'"),
                         (build_env(cfg, cpu, num_envs=2, for_training=True), "has 2 worlds, cfg.env.num_envs 4"),
                         (TocabiWalk(num_envs=4, device="cpu"), "has no 'observation'"),
                         # Inputs of the same width (237) built otherwise: the run would save another input.
                         (build_env(cfg, cpu, for_training=True, history=TOCABILAB_HISTORY),
                          r"builds its policy input otherwise than cfg \(history: HistoryLayout\(num_obs=5, stride=1"),
                         (build_env(cfg, cpu, for_training=True, sensor_noise=SensorNoiseConfig.tocabi_lab()),
                          "sensor noise: a SensorNoiseConfig of its own in the env, none in cfg"),
                         (build_env(cfg, cpu, for_training=True, obs_clip=5.0),
                          "observation clip: 5.0 in the env, none in cfg"),
                         # What build_env adds from cfg besides the env section.
                         (build_env(dataclasses.replace(cfg, seed=cfg.seed + 1), cpu, for_training=True),
                          f"seeded with {cfg.seed + 1}, cfg.seed is {cfg.seed}"),
                         (privileged_env, r"gives 'privileged' \(the asymmetric critic's input\), "
                                          "cfg.ppo.critic_privileged is False")):
        with pytest.raises(ValueError, match=message):
            train(cfg, env=env)
    assert not (tmp_path / "x").exists()
    # A reward of one's own is a task's (docs/extending.md): not refused.
    from tocabi_torchrl.rl.trainer import check_given_env

    check_given_env(cfg, build_env(cfg, cpu, for_training=True, reward_terms=("body_vel", "orientation")))


def test_the_robust_presets_assist_and_critic_need_build_env(tmp_path):
    # make_env with the run's env and transform sections leaves out what build_env sets from cfg.ppo: the robust
    # preset trained with its assist PD on the true joints (saved as sensed), or died in a tensordict KeyError.
    from tocabi_torchrl import make_env
    from tocabi_torchrl.rl import preset_config
    from tocabi_torchrl.rl.trainer import build_env, check_given_env, env_config

    cfg = preset_config("robust", device="cpu", **{"env.num_envs": 2, "ppo.minibatch_size": 16})
    assert cfg.ppo.assist_pd_sensed and cfg.ppo.critic_privileged and env_config(cfg, True).control.torque_assist
    plain = make_env(2, "cpu", seed=cfg.seed, config=env_config(cfg, True), transforms=cfg.transforms)
    with pytest.raises(ValueError, match=r"assist PD read the true joint positions, cfg.ppo.assist_pd_sensed is True"):
        check_given_env(cfg, plain)
    plain.base_env.sense_assist_joints()
    with pytest.raises(ValueError, match=r"has no 'privileged'.*cfg.ppo.critic_privileged is True"):
        check_given_env(cfg, plain)
    check_given_env(cfg, build_env(cfg, torch.device("cpu"), for_training=True))


def test_a_controller_returning_the_wrong_shape_is_named():
    # (1, 12) was broadcast to every world without a word; (N, 6) failed in the ctrl write naming no controller.
    from tocabi_torchrl.control import Controller
    from tocabi_torchrl.envs import TocabiWalk

    class Narrow(Controller):
        action_dim = 12

        def __init__(self, rows: int, width: int):
            self.rows, self.width = rows, width

        def compute(self, inp):
            return torch.zeros(self.rows, self.width, device=inp.action.device)

    for rows, width in ((1, 12), (3, 6)):
        env = TocabiWalk(num_envs=3, device="cpu", control_mode="torque", leg_controller=Narrow(rows, width))
        env.reset()
        with pytest.raises(ValueError, match=rf"leg controller Narrow.compute returned \({rows}, {width}\); it must "
                                             r"return a \(3, 12\) tensor"):
            env.rand_step()


def test_bad_per_joint_gains_of_a_law_are_named():
    # A wrong count failed as a raw reshape or index error (or was cut to the first 12 servo gains), and NaN or a
    # negative kp (a servo that pushes away from its target) was taken without a word.
    import math

    from tocabi_torchrl.control import AssistedTorque, ComputedTorqueResidual, JointPD
    from tocabi_torchrl.control.base import ControlContext

    kp, kv, nominal = robot.LEG_KP, robot.LEG_KV, robot.INIT_JOINT_POS[:12]
    refused = [
        (JointPD(kp[:6], kv, 0.5, nominal), r"JointPD.servo_gains\(\) kp \[N·m/rad\] must be 12 numbers, one per "
                                            r"joint of the group, got shape \(6,\)"),
        (JointPD(400.0, kv, 0.5, nominal), r"JointPD.servo_gains\(\) kp .* got shape \(\)"),
        (JointPD(-kp, kv, 0.5, nominal), r"JointPD.servo_gains\(\) kp \[N·m/rad\]: each joint's value must be a "
                                         r"finite number >= 0, got \[0\] = -2000.0"),
        (JointPD(kp, kv, 0.5, nominal[:3]), r"JointPD nominal \[rad\] must be 12 numbers"),
    ]
    for law, message in refused:
        with pytest.raises(ValueError, match=message):
            TocabiWalk(num_envs=1, device="cpu", leg_controller=law)
    with pytest.raises(ValueError, match=r"JointPD scale \[rad per action unit\] must be a finite number, got nan"):
        JointPD(kp, kv, math.nan, nominal)
    ctx = ControlContext(num_envs=2, device=torch.device("cpu"), joint_ids=(0, 1), torque_limits=torch.ones(2),
                         joint_range=torch.tensor([[-1.0, 1.0]] * 2))
    for law, message in ((AssistedTorque([1.0, math.nan], [1.0, 1.0], 0.5), r"AssistedTorque kp .*\[1\] = nan"),
                         (AssistedTorque([1.0] * 3, [1.0, 1.0], 0.5), r"AssistedTorque kp .* got shape \(3,\)"),
                         (ComputedTorqueResidual([1.0, -1.0], lambda ctx: None),
                          r"ComputedTorqueResidual gain .* >= 0, got \[1\] = -1.0")):
        with pytest.raises(ValueError, match=message):
            law.setup(ctx)


def test_a_controller_with_learnable_gains_steps_without_autograd():
    # Its torques required grad: the C MuJoCo backend failed at the first step ("Can't call numpy() on Tensor that
    # requires grad"), and the graph reached leg_torque and the observation.
    from tocabi_torchrl.control import clip_torque

    class LearnedPD(Controller):
        action_dim = 12

        def __init__(self):
            self.kp = torch.nn.Parameter(torch.full((12,), 300.0))

        def compute(self, inp):
            return clip_torque(self.kp * (inp.q_ref + 0.5 * inp.action - inp.q), self.ctx.torque_limits)

    env = TocabiWalk(num_envs=2, device="cpu", control_mode="torque", backend="mujoco", leg_controller=LearnedPD())
    td = env.rollout(2, break_when_any_done=False)
    assert not td["next", "leg_torque"].requires_grad and not env.sim.ctrl.requires_grad
    assert float(td["next", "leg_torque"].abs().max()) > 0


def test_a_pd_nominal_pose_outside_the_joint_range_is_refused():
    # A pose in degrees was taken: the reset's servos chased it and the pd mode's centre was clipped to the
    # range's end, driving the legs to their limits.
    import numpy as np

    degrees = tuple(float(v) for v in np.degrees(robot.INIT_JOINT_POS[:12]))
    for mode in ("pd", "pd_reference"):
        with pytest.raises(ValueError, match=r"JointPD nominal \(env.control.pd_nominal\) is outside the model's "
                                             r"joint range: L_HipPitch_Joint = -13.751 rad .*give radians"):
            TocabiWalk(num_envs=1, device="cpu", control_mode=mode, pd_nominal=degrees)
    TocabiWalk(num_envs=1, device="cpu", control_mode="pd")  # the default pose is in range


def _leg_context(ranges, model_file="narrow.xml"):
    """A ControlContext of the 12 leg joints with ``ranges`` (12, 2) [rad] as the model's joint ranges."""
    from tocabi_torchrl.control import ControlContext

    return ControlContext(num_envs=1, device=torch.device("cpu"), joint_ids=robot.LEG_JOINT_IDS,
                          torque_limits=torch.as_tensor(robot.LEG_TORQUE_LIMITS, dtype=torch.float32),
                          joint_range=torch.as_tensor(ranges, dtype=torch.float32), model_file=model_file)


def test_a_model_range_that_leaves_out_the_start_pose_is_blamed_not_the_pd_nominal_pose():
    # Knee ranges of ±0.5 rad left out the default nominal (the start pose's 0.6 rad), and the message said "give
    # radians (not degrees)", sending the user to a good pd_nominal.
    from tocabi_torchrl.control import JointPD

    ranges = [[-3.14, 3.14]] * 12
    for knee in (3, 9):
        ranges[knee] = [-0.5, 0.5]
    law = JointPD(robot.LEG_KP, robot.LEG_KV, 0.5, robot.INIT_JOINT_POS[:12], centre="nominal")
    with pytest.raises(ValueError) as info:
        law.setup(_leg_context(ranges))
    assert str(info.value) == (
        "JointPD nominal (env.control.pd_nominal) is outside the model's joint range: L_Knee_Joint = 0.600 rad (range "
        "[-0.500, 0.500]), R_Knee_Joint = 0.600 rad (range [-0.500, 0.500]), the ranges of narrow.xml; the range of "
        "L_Knee_Joint, R_Knee_Joint leaves out the robot's initial pose (robot.INIT_JOINT_POS) too: check them in "
        "narrow.xml")
    # A pose in degrees as well: each joint gets its own check.
    nominal = robot.INIT_JOINT_POS[:12].copy()
    nominal[2] = float(np.degrees(nominal[2]))
    law = JointPD(robot.LEG_KP, robot.LEG_KV, 0.5, nominal, centre="nominal")
    with pytest.raises(ValueError, match=r"L_HipPitch_Joint = -13\.751 rad .*; give radians \(not degrees\) within "
                                         r"each joint's range, in robot\.JOINT_NAMES order; the range of L_Knee_Joint, "
                                         r"R_Knee_Joint leaves out the robot's initial pose"):
        law.setup(_leg_context(ranges))


def test_the_env_names_its_model_file_when_a_range_leaves_out_the_pd_nominal_pose(tmp_path):
    # A hip yaw range of [0.005, 0.5] rad: the walk (hip yaw 0) stays within the motion check's 0.01 rad, while the
    # default nominal (0) is outside; the message named no model file.
    text = robot.asset_path("tocabi", "tocabi.xml").read_text()
    old = '<joint name="L_HipYaw_Joint" axis="0 0 1" range="-3.14 3.14"'
    assert text.count(old) == 1
    model = tmp_path / "yaw.xml"
    model.write_text(text.replace(old, old.replace('"-3.14 3.14"', '"0.005 0.5"')))
    with pytest.raises(ValueError, match=r"L_HipYaw_Joint = 0\.000 rad \(range \[0\.005, 0\.500\]\), the ranges of "
                                         r".*yaw\.xml; the range of L_HipYaw_Joint leaves out the robot's initial "
                                         r"pose \(robot\.INIT_JOINT_POS\) too: check it in .*yaw\.xml$"):
        TocabiWalk(num_envs=1, device="cpu", control_mode="pd", model_path=str(model))
