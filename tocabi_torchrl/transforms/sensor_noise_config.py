"""``SensorNoiseConfig``: the sensor biases and noise on the policy's observation (``transforms.sensor_noise``), in
a module without torch so that the config tree reads without it. ``transforms.sensor_noise`` has the table of what
each value perturbs and ``SensorNoise``, the transform that applies them."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from tocabi_torchrl import robot
from tocabi_torchrl.value_rules import check_sensor_noise

__all__ = ["SensorNoiseConfig", "SENSORS"]

#: The signals :class:`SensorNoise` perturbs: key -> its shape per world (without the batch dimension).
SENSORS: Mapping[str, tuple[int, ...]] = {
    "joint_pos": (robot.NUM_JOINTS,),
    "joint_vel": (robot.NUM_JOINTS,),
    "base_rpy": (3,),
    "foot_force": (2, 3),
    "foot_torque": (2, 3),
    # Last: each signal's random streams follow its position here (sensor_noise.BIAS_STREAMS), so the ones above keep
    # their numbers.
    "base_lin_vel": (3,),
    "base_ang_vel": (3,),
}


@dataclass(frozen=True)
class SensorNoiseConfig:
    """Sensor biases and noise on the policy's observation (the run config's ``transforms.sensor_noise``). Every
    value defaults to 0, which perturbs nothing: with all of them 0 no transform is added and no number changes.

    Attributes:
        joint_pos_bias: half-width [rad] of the joint-position bias, U(±b) per world and joint, drawn at reset.
        joint_pos_noise_std: σ [rad] of the encoder noise added to the joint positions every step.
        joint_pos_noise_clip: the encoder noise is clipped to ±clip [rad]; None: not clipped.
        joint_vel_noise_std: σ [rad/s] of the noise added to the joint velocities every step.
        joint_vel_noise_clip: the joint-velocity noise is clipped to ±clip [rad/s]; None: not clipped.
        base_rpy_bias: half-width [rad] of the IMU orientation bias, U(±b) per world and roll/pitch/yaw axis, drawn
            at reset and added to the observed Euler angles.
        foot_force_bias: half-width [N] of the F/T force bias, U(±b) per world, foot and axis, drawn at reset.
        foot_torque_bias: half-width [N·m] of the F/T moment bias, U(±b) per world, foot and axis, drawn at reset.
        base_lin_vel_bias: half-width [m/s] of the pelvis linear velocity's bias (a state estimator's offset), U(±b)
            per world and axis, drawn at reset; read only by the ``base_vel`` observation.
        base_lin_vel_noise_std: σ [m/s] of the noise added to the pelvis linear velocity every step.
        base_lin_vel_noise_clip: that noise is clipped to ±clip [m/s]; None: not clipped.
        base_ang_vel_bias: half-width [rad/s] of the gyro's bias, U(±b) per world and axis, drawn at reset.
        base_ang_vel_noise_std: σ [rad/s] of the noise added to the pelvis angular velocity every step.
        base_ang_vel_noise_clip: that noise is clipped to ±clip [rad/s]; None: not clipped.
    """

    joint_pos_bias: float = 0.0
    joint_pos_noise_std: float = 0.0
    joint_pos_noise_clip: float | None = None
    joint_vel_noise_std: float = 0.0
    joint_vel_noise_clip: float | None = None
    base_rpy_bias: float = 0.0
    foot_force_bias: float = 0.0
    foot_torque_bias: float = 0.0
    base_lin_vel_bias: float = 0.0
    base_lin_vel_noise_std: float = 0.0
    base_lin_vel_noise_clip: float | None = None
    base_ang_vel_bias: float = 0.0
    base_ang_vel_noise_std: float = 0.0
    base_ang_vel_noise_clip: float | None = None

    def __post_init__(self):
        self.validate()

    @classmethod
    def tocabi_lab(cls) -> SensorNoiseConfig:
        """The TOCABI lab's numbers, as its real-robot training draws them: joint-position bias U(±π/100) rad,
        IMU bias U(±π/150) rad per axis, F/T bias U(±100) N and U(±10) N·m per axis and foot, and encoder noise
        σ = 0.00016/3 rad clipped at ±0.00016 rad (3σ) every step. The joint velocities are left alone, and so is the
        pelvis velocity, which the lab's policies of that model did not observe."""
        return cls(joint_pos_bias=math.pi / 100, joint_pos_noise_std=0.00016 / 3, joint_pos_noise_clip=0.00016,
                   base_rpy_bias=math.pi / 150, foot_force_bias=100.0, foot_torque_bias=10.0)

    def validate(self, prefix: str = "transforms.sensor_noise.") -> None:
        """Raise ``ValueError`` naming the first bad value by its path (``transforms.sensor_noise.<name>``)."""
        check_sensor_noise(self, prefix)

    @property
    def enabled(self) -> bool:
        """True when some bias or noise is not 0 (a clip alone changes nothing)."""
        return any(self.bias(name) > 0 or self.noise(name)[0] > 0 for name in SENSORS)

    def bias(self, signal: str) -> float:
        """The bias half-width of ``signal`` (a key of :data:`SENSORS`) in its unit; 0 for none."""
        return float(getattr(self, f"{signal}_bias", 0.0))

    def noise(self, signal: str) -> tuple[float, float | None]:
        """(σ, clip) of ``signal``'s per-step noise in its unit; σ = 0 for none."""
        return float(getattr(self, f"{signal}_noise_std", 0.0)), getattr(self, f"{signal}_noise_clip", None)

    def perturbed(self) -> tuple[str, ...]:
        """The signals with a bias or noise, in :data:`SENSORS` order."""
        return tuple(name for name in SENSORS if self.bias(name) > 0 or self.noise(name)[0] > 0)
