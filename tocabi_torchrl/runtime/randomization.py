"""What a policy was trained under, stated in its contract, and the same randomisation and pushes in numpy for the
sim-to-sim driver.

The contract's ``trained_under`` section (written by :func:`trained_under_section`, read by :func:`from_contract`,
checked by ``value_rules.trained_under_problems``) states the training env's actuator layer
(``control/actuators.py``), per-world dynamics (``sim/dynamics.py``), sensor biases and noise
(``transforms/sensor_noise.py``), pushes (``envs/pushes.py``) and start velocities (``TaskConfig.start_*_vel_std``),
each with its unit, ``"off"`` where training did not use it. A contract without the section (exported before it
existed) states nothing: :func:`from_contract` returns None.

The numpy side reproduces each piece's distribution and semantics, not torch's random numbers (another generator):

=========================== ================================================================= ====================
piece                       what the driver does                                              drawn
=========================== ================================================================= ====================
:class:`ActuatorLayer`      leg torque → delay of k physics substeps (zero torque before the  per robot at reset
                            episode) → × motor constant c → − friction → clip at the limits
:class:`WorldDynamics`      one ``MjModel`` copy per robot: masses and inertias × s, joint    per robot at reset
                            damping + d, armature × a, every geom's sliding friction × f
:class:`SensorModel`        the policy's observation signals + bias (fixed per episode) +     biases at reset,
                            noise (fresh every control period, clipped); the metrics and      noise every period
                            terminations read the true state
:class:`PushSchedule`       horizontal kicks of impulse speed × robot mass, held for whole    per robot at reset
                            control periods in ``MjData.xfrc_applied``: on the pelvis
                            (``kind`` "force") or on every body by its mass (``kind``
                            "velocity", the robust gait test's)
:func:`start_velocities`    N(0, σ²) joint velocities and pelvis linear velocity at reset     per robot at reset
=========================== ================================================================= ====================

Every draw comes from a ``numpy.random.Generator`` of its own stream (:func:`generator`: seed and stream), so turning
one piece on or off leaves the others' numbers as they were. numpy and mujoco only: never torch.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, fields

import mujoco
import numpy as np

from ..value_rules import (CALM_NEVER_S, DELAY_APPLIED, DYNAMICS_OFF, OPTIONAL_ITEMS, START_VEL_STD,
                           check_actuator_ranges, check_dynamics_ranges, check_push_settings, check_sensor_noise)

__all__ = ["ROBUST_START", "STREAMS", "TOCABI_LAB", "ActuatorLayer", "ActuatorSettings", "DynamicsSettings",
           "PushSchedule", "PushSettings", "Randomization", "SensorModel", "SensorSettings", "StartVelocity",
           "WorldDynamics", "from_contract", "generator", "settings_from", "start_velocities",
           "trained_under_section"]

#: The random stream of each piece (:func:`generator`).
STREAMS = {"actuators": 1, "dynamics": 2, "sensor_bias": 3, "sensor_noise": 4, "pushes": 5, "start_velocity": 6}


def generator(seed: int, piece: str) -> np.random.Generator:
    """The generator of ``piece`` (a key of :data:`STREAMS`) for ``seed``: independent of every other piece's."""
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(STREAMS[piece],)))


# ----------------------------------------------------------------------------------------------------- settings
@dataclass(frozen=True)
class ActuatorSettings:
    """The legs' actuator layer (``ActuatorConfig``'s fields): delay k ~ U{low, low + stride, ..., high} physics
    substeps per robot (``delay_average``: the delayed torque's mean over each control period), motor constant
    c ~ U(low, high) per robot and leg joint, Coulomb friction [N·m] and viscous friction [N·m·s/rad] ~ U(low, high)
    per robot and leg joint, then a clip at the torque limits (``saturate``, when any other stage runs). The defaults
    are the ideal actuator."""

    delay_substeps: tuple[int, int] = (0, 0)
    delay_stride: int = 1
    delay_average: bool = False
    motor_constant: tuple[float, float] = (1.0, 1.0)
    coulomb: tuple[float, float] = (0.0, 0.0)
    viscous: tuple[float, float] = (0.0, 0.0)
    saturate: bool = True

    def validate(self, prefix: str = "actuators.") -> None:
        """Raise ``ValueError`` naming the first bad field and what it takes (``ActuatorConfig.validate``'s rules):
        a negative motor constant or friction, or a delay off its stride's grid, would otherwise run as given."""
        check_actuator_ranges(self, prefix)

    @property
    def delay_on(self) -> bool:
        return tuple(self.delay_substeps) != (0, 0)

    @property
    def motor_on(self) -> bool:
        return tuple(self.motor_constant) != (1.0, 1.0)

    @property
    def friction_on(self) -> bool:
        return tuple(self.coulomb) != (0.0, 0.0) or tuple(self.viscous) != (0.0, 0.0)

    @property
    def enabled(self) -> bool:
        """Whether any stage runs (the training env builds an empty chain otherwise, saturation included)."""
        return self.delay_on or self.motor_on or self.friction_on


@dataclass(frozen=True)
class DynamicsSettings:
    """Per-robot dynamics (``DynamicsRandomization``'s fields), each ``(low, high)`` of a uniform draw: body mass
    and inertia scale, joint damping added [N·m·s/rad], joint armature scale, sliding friction scale of every geom.
    The defaults change nothing."""

    mass_scale: tuple[float, float] = (1.0, 1.0)
    joint_damping: tuple[float, float] = (0.0, 0.0)
    armature_scale: tuple[float, float] = (1.0, 1.0)
    friction_scale: tuple[float, float] = (1.0, 1.0)

    _OFF = DYNAMICS_OFF

    def validate(self, prefix: str = "dynamics.") -> None:
        """Raise ``ValueError`` naming the first bad range and what it takes (``DynamicsRandomization.validate``'s
        rules): a given ``Randomization`` is checked as the training config and a contract are."""
        check_dynamics_ranges(self, prefix)

    def on(self, name: str) -> bool:
        return tuple(float(v) for v in getattr(self, name)) != self._OFF[name]

    @property
    def enabled(self) -> bool:
        return any(self.on(name) for name in self._OFF)


#: The signals with a bias (``<signal>_bias``) and with per-period noise (``<signal>_noise_std``/``_clip``), and their
#: units as a contract states them.
BIASED = {"joint_pos": "rad", "base_rpy": "rad", "foot_force": "N", "foot_torque": "N*m", "base_lin_vel": "m/s",
          "base_ang_vel": "rad/s"}
NOISY = {"joint_pos": "rad", "joint_vel": "rad/s", "base_lin_vel": "m/s", "base_ang_vel": "rad/s"}
#: The contract's sensor items that may be left out (then off): added with the pelvis-velocity observation.
OPTIONAL_SENSOR_ITEMS = OPTIONAL_ITEMS["sensor_noise"]


@dataclass(frozen=True)
class SensorSettings:
    """Sensor biases (half-widths of U(±b), drawn per robot at reset) and per-period noise (σ, clip or None) on the
    observation's signals (``SensorNoiseConfig``'s fields): joint positions [rad], joint velocities [rad/s], base
    roll/pitch/yaw [rad], foot forces [N], foot torques [N·m], the pelvis's linear [m/s] and angular [rad/s]
    velocity. All 0: nothing."""

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

    def validate(self, prefix: str = "sensors.") -> None:
        """Raise ``ValueError`` naming the first bad value and what it takes (``SensorNoiseConfig.validate``'s
        rules): a negative or NaN bias or σ would otherwise be read as off, a negative clip as a constant offset."""
        check_sensor_noise(self, prefix)

    @property
    def enabled(self) -> bool:
        return any(getattr(self, n) > 0 for n in (*(f"{s}_bias" for s in BIASED), *(f"{s}_noise_std" for s in NOISY)))


@dataclass(frozen=True)
class PushSettings:
    """Horizontal kicks (``PushConfig``'s fields): ``count`` per episode, kick j at a uniform time in the j-th of
    ``count`` equal shares of ``window`` [s], a uniform direction, a velocity change ~ U(``speed``) [m/s] of the whole
    robot, forces held for ~ U(``duration``) [s] rounded to whole control periods (>= 1): on the pelvis alone
    (``kind`` "force") or on every body by its mass (``kind`` "velocity", the robust gait test's); each robot's
    episode without any kick with probability ``calm_fraction``."""

    count: int = 0
    window: tuple[float, float] = (2.0, 7.0)
    speed: tuple[float, float] = (0.5, 0.5)
    duration: tuple[float, float] = (0.004, 0.004)
    kind: str = "force"
    calm_fraction: float = 0.0

    def validate(self, prefix: str = "pushes.") -> None:
        """Raise ``ValueError`` naming the first bad field and what it takes (``PushConfig.validate``'s rules)."""
        check_push_settings(self, prefix)


@dataclass(frozen=True)
class StartVelocity:
    """Start velocities drawn per robot at reset: joint velocities ~ N(0, ``joint_std``²) [rad/s], pelvis linear
    velocity ~ N(0, ``base_std``²) [m/s] per world axis, no angular velocity (``TocabiWalk._start_velocities``)."""

    joint_std: float = 0.0
    base_std: float = 0.0

    def validate(self, prefix: str = "start_velocity.") -> None:
        """Raise ``ValueError`` unless both stds are in [0, 10] (``TaskConfig.start_*_vel_std``'s rule): a NaN one
        would start every robot with NaN velocities, refused later as a failed sensor."""
        for name, unit in (("joint_std", "rad/s"), ("base_std", "m/s")):
            START_VEL_STD.check(getattr(self, name), f"{prefix}{name} [{unit}]")

    @property
    def enabled(self) -> bool:
        return self.joint_std > 0 or self.base_std > 0


@dataclass(frozen=True)
class Randomization:
    """The randomisation of a sim-to-sim run: actuator layer, dynamics and sensors (each may be at its identity)."""

    actuators: ActuatorSettings = ActuatorSettings()
    dynamics: DynamicsSettings = DynamicsSettings()
    sensors: SensorSettings = SensorSettings()

    def validate(self, prefix: str = "randomize.") -> None:
        """Raise ``ValueError`` naming the first bad field of any piece (``{prefix}actuators.<name>`` etc.)."""
        self.actuators.validate(f"{prefix}actuators.")
        self.dynamics.validate(f"{prefix}dynamics.")
        self.sensors.validate(f"{prefix}sensors.")

    @property
    def enabled(self) -> bool:
        return self.actuators.enabled or self.dynamics.enabled or self.sensors.enabled


#: The TOCABI lab's uncertainty model (``tocabi_torchrl.randomize.tocabi_lab``; ``tests/test_runtime_randomization
#: .py`` checks the two agree): torque delay 2-10 ms, motor constant ×U(0.8, 1.2), link mass ×U(0.8, 1.2), joint
#: damping +U(0, 2.9) N·m·s/rad, armature ×U(0.8, 1.2), joint-position bias U(±π/100) rad, IMU bias
#: U(±π/150) rad, F/T bias U(±100) N and U(±10) N·m, encoder noise σ = 0.00016/3 rad clipped at ±0.00016 rad.
TOCABI_LAB = Randomization(
    actuators=ActuatorSettings(delay_substeps=(4, 20), motor_constant=(0.8, 1.2)),
    dynamics=DynamicsSettings(mass_scale=(0.8, 1.2), joint_damping=(0.0, 2.9), armature_scale=(0.8, 1.2)),
    sensors=SensorSettings(joint_pos_bias=math.pi / 100, joint_pos_noise_std=0.00016 / 3,
                           joint_pos_noise_clip=0.00016, base_rpy_bias=math.pi / 150, foot_force_bias=100.0,
                           foot_torque_bias=10.0),
)
#: The robust gait test's start velocities (``evaluation.robust.RobustTestConfig``): N(0, 0.5 rad/s), N(0, 0.1 m/s).
ROBUST_START = StartVelocity(joint_std=0.5, base_std=0.1)


def settings_from(cls, values, where: str):
    """``cls`` (a settings dataclass above) from ``values`` (a training config dataclass or a mapping with the same
    field names). Raises ``ValueError`` for a field the settings do not know: the contract could not state it."""
    items = dataclasses.asdict(values) if dataclasses.is_dataclass(values) else dict(values)
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(items) - known)
    if unknown:
        raise ValueError(f"{where} has {unknown}, which the contract's trained_under section cannot state: add them "
                         f"to {cls.__name__} in tocabi_torchrl/runtime/randomization.py (writer, reader and driver)")
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in items.items()})


# ------------------------------------------------------------------------------------------- contract section
def _pair(values) -> list[float]:
    return [float(values[0]), float(values[1])]


def _delay_item(act: ActuatorSettings, physics_dt_s: float) -> dict:
    """The contract's ``actuators.delay`` item; ``stride_substeps`` only where the grid is coarser than 1 and
    ``applied`` only where the torque is averaged (a contract without them states a stride of 1, per substep)."""
    stride = int(act.delay_stride)
    grid = "{low, ..., high}" if stride == 1 else "{low, low + stride_substeps, ..., high}"
    how = ("the torque held through each control period is the mean over its physics substeps of the command of k "
           "substeps earlier" if act.delay_average else
           "the torque in each physics substep is the command of k substeps earlier")
    return {"substeps": [int(v) for v in act.delay_substeps],
            "ms": [round(int(v) * physics_dt_s * 1000.0, 9) for v in act.delay_substeps],
            **({"stride_substeps": stride} if stride != 1 else {}),
            **({"applied": DELAY_APPLIED[1]} if act.delay_average else {}),
            "unit": "physics substeps (and ms)",
            "draw": f"k ~ U{grid} per robot at each reset; {how} (zero torque before the episode's first command)"}


def trained_under_section(randomization: Randomization, pushes: PushSettings, start: StartVelocity,
                          physics_dt_s: float, robot_mass_kg: float, push_ramp=(0, 0), start_pool: int = 0,
                          solver_iterations: int | None = None) -> dict:
    """The contract's ``trained_under`` section (``docs/deploying.md``): each piece with its unit and draw, ``"off"``
    where training did not use it. ``physics_dt_s``: the physics step, for the delay in ms; ``robot_mass_kg``: the
    mass the kicks' impulse is computed with; ``push_ramp``: ``ppo.push_ramp`` (start, full) env steps;
    ``start_pool``: ``env.sim.start_pool`` as it acted (0 = dynamics and start velocities drawn at each reset);
    ``solver_iterations``: ``env.sim.solver_iterations``, the training's cap on the Newton solver per physics substep
    (None: the model's own, and no ``solver`` text in the section)."""
    act, dyn, sen = randomization.actuators, randomization.dynamics, randomization.sensors
    # How the dynamics and start velocities were drawn: afresh at each reset, or from a pool drawn at build.
    when = (f"{int(start_pool)} draws per robot made when the training env was built, one of them picked at each "
            "reset" if start_pool else "at each reset")
    actuators = {
        "applies_to": "the leg torques of the torque control modes (the PD modes' servos take none), in this order: "
                      "delay, motor_constant, friction, saturation",
        "delay": _delay_item(act, physics_dt_s) if act.delay_on else "off",
        "motor_constant": {"range": _pair(act.motor_constant), "unit": "1",
                           "draw": "c ~ U(low, high) per robot and leg joint at each reset; torque * c"}
        if act.motor_on else "off",
        "friction": {"coulomb_nm": _pair(act.coulomb), "viscous_nms_per_rad": _pair(act.viscous),
                     "draw": "F_c, F_v ~ U(low, high) per robot and leg joint at each reset; torque - (F_c * "
                             "sign(qdot) + F_v * qdot), qdot the joint velocity at the control period's start"}
        if act.friction_on else "off",
        "saturation": {"rule": "clip(torque, +-action.leg.torque_limits_nm) after the other stages"}
        if act.enabled and act.saturate else "off",
    }
    units = {"mass_scale": ("1", "body mass and inertia tensor * s, s ~ U(low, high) per robot and body (not the "
                                 "world or mocap bodies)"),
             "joint_damping": ("N*m*s/rad", "joint dof damping + d, d ~ U(low, high) per robot and joint (not the free "
                                            "joint)"),
             "armature_scale": ("1", "joint dof armature * a, a ~ U(low, high) per robot and joint"),
             "friction_scale": ("1", "sliding friction of every geom * f, f ~ U(low, high) per robot")}
    dynamics = {name: {"range": _pair(getattr(dyn, name)), "unit": unit, "draw": f"{draw}, {when}"}
                if dyn.on(name) else "off" for name, (unit, draw) in units.items()}
    sensors = {}
    for signal, unit in BIASED.items():
        half = float(getattr(sen, f"{signal}_bias"))
        sensors[f"{signal}_bias"] = ({"half_width": half, "unit": unit,
                                      "draw": "U(-half_width, half_width) per robot and element at each reset, "
                                              "added to the observed signal"} if half > 0 else "off")
    for signal, unit in NOISY.items():
        std, clip = float(getattr(sen, f"{signal}_noise_std")), getattr(sen, f"{signal}_noise_clip")
        sensors[f"{signal}_noise"] = ({"std": std, "clip": None if clip is None else float(clip), "unit": unit,
                                       "draw": "N(0, std^2) per element every control period, clipped to +-clip "
                                               "(null: not clipped), added to the observed signal"}
                                      if std > 0 else "off")
    # The pelvis velocity's items are written only when on: a contract of a policy without them reads as before.
    sensors = {k: sensors[k] for k in ("joint_pos_bias", "joint_pos_noise", "joint_vel_noise", "base_rpy_bias",
                                       "foot_force_bias", "foot_torque_bias", *OPTIONAL_SENSOR_ITEMS)
               if k not in OPTIONAL_SENSOR_ITEMS or sensors[k] != "off"}
    # Text, not an object: no reader applies it (a deployment's simulator keeps its own solver), it says how the
    # training's physics was cut short.
    solver = ({"solver": f"Newton iterations capped at {int(solver_iterations)} per physics substep in training "
                         "(env.sim.solver_iterations); the model file's own settings everywhere else"}
              if solver_iterations is not None else {})
    return {
        "note": "what the training env randomised and perturbed; \"off\" = not used. The metrics and terminations "
                "read the true state; only the policy's observation reads the sensor biases and noise",
        **solver,
        "actuators": actuators,
        "dynamics": dynamics,
        "sensor_noise": sensors,
        "pushes": {"count": int(pushes.count), "window_s": _pair(pushes.window), "speed_mps": _pair(pushes.speed),
                   "duration_s": _pair(pushes.duration), "robot_mass_kg": float(robot_mass_kg),
                   "ramp_env_steps": [int(v) for v in push_ramp], "kind": pushes.kind,
                   "rule": "kick j at t ~ U over the j-th of count equal shares of window_s, direction ~ U(0, 2pi) "
                           "in the horizontal plane, for n = max(1, round(duration / control_dt_s)) control periods "
                           + ("a force speed * robot_mass_kg / (n * control_dt_s) on the pelvis (world frame)"
                              if pushes.kind == "force" else
                              "a force body_mass * speed / (n * control_dt_s) on every body (world frame, the "
                              "robot's own masses): the whole robot's velocity changes by speed")
                           + "; ramp_env_steps: training scaled every kick from 0 at the first to 1 at the second"
                           + ("; calm_fraction: the probability, drawn per episode, of an episode without kicks"
                              if pushes.calm_fraction > 0 else ""),
                   **({"calm_fraction": float(pushes.calm_fraction)} if pushes.calm_fraction > 0 else {})}
        if pushes.count > 0 else "off",
        "start_velocity": {"joint_std_radps": float(start.joint_std), "base_std_mps": float(start.base_std),
                           "rule": f"{when}: joint velocities ~ N(0, joint_std^2), pelvis linear velocity ~ "
                                   "N(0, base_std^2) per world axis, no angular velocity"}
        if start.enabled else "off",
    }


def from_contract(contract: dict) -> tuple[Randomization, PushSettings, StartVelocity] | None:
    """What the contract's ``trained_under`` section states (checked by ``load_contract``): the randomisation, the
    pushes and the start velocities; None when the contract does not state it (exported before the section)."""
    section = contract.get("trained_under")
    if section is None:
        return None
    act, dyn, sen = section["actuators"], section["dynamics"], section["sensor_noise"]

    def pair(item, key, off):
        return off if item == "off" else tuple(item[key])

    actuators = ActuatorSettings(
        delay_substeps=tuple(int(v) for v in pair(act["delay"], "substeps", (0, 0))),
        delay_stride=1 if act["delay"] == "off" else int(act["delay"].get("stride_substeps", 1)),
        delay_average=act["delay"] != "off" and act["delay"].get("applied", DELAY_APPLIED[0]) == DELAY_APPLIED[1],
        motor_constant=pair(act["motor_constant"], "range", (1.0, 1.0)),
        coulomb=pair(act["friction"], "coulomb_nm", (0.0, 0.0)),
        viscous=pair(act["friction"], "viscous_nms_per_rad", (0.0, 0.0)),
        saturate=act["saturation"] != "off")
    dynamics = DynamicsSettings(**{name: pair(dyn[name], "range", off) for name, off in DynamicsSettings._OFF.items()})
    values = {}
    for name in (f"{signal}_bias" for signal in BIASED):
        item = sen.get(name, "off")  # an optional item left out is off
        values[name] = 0.0 if item == "off" else float(item["half_width"])
    for signal in NOISY:
        item = sen.get(f"{signal}_noise", "off")
        if item != "off":
            values[f"{signal}_noise_std"], values[f"{signal}_noise_clip"] = float(item["std"]), item["clip"]
    push = section["pushes"]
    pushes = PushSettings() if push == "off" else PushSettings(
        count=int(push["count"]), window=tuple(push["window_s"]), speed=tuple(push["speed_mps"]),
        duration=tuple(push["duration_s"]), kind=str(push.get("kind", "force")),
        calm_fraction=float(push.get("calm_fraction", 0.0)))
    st = section["start_velocity"]
    start = StartVelocity() if st == "off" else StartVelocity(float(st["joint_std_radps"]), float(st["base_std_mps"]))
    return Randomization(actuators, dynamics, SensorSettings(**values)), pushes, start


# -------------------------------------------------------------------------------------------------- actuators
class ActuatorLayer:
    """The legs' actuator chain of ``control/actuators.py`` in numpy, for N robots.

    Args:
        settings: the ranges (:class:`ActuatorSettings`; ``enabled`` must be True).
        substeps: S, physics substeps per control period.
        torque_limits: (J,) the joints' torque limits [N·m] (the saturation's).

    Attributes (after :meth:`reset`): ``delay`` (N,) int substeps, ``motor_constant``, ``coulomb``, ``viscous``
    (N, J).
    """

    def __init__(self, settings: ActuatorSettings, substeps: int, torque_limits):
        self.settings, self.substeps = settings, int(substeps)
        self.limits = np.asarray(torque_limits, dtype=np.float64)
        # The newest command and the ceil(high / S) before it: enough for a delay of `high` substeps.
        self.depth = -(-int(settings.delay_substeps[1]) // self.substeps) + 1

    def reset(self, rng: np.random.Generator, n: int) -> None:
        """Draw each robot's delay, motor constants and friction, and clear the command history to zero torque."""
        s, j = self.settings, len(self.limits)
        lo, hi, stride = (int(v) for v in (*s.delay_substeps, s.delay_stride))
        self.delay = (lo + stride * rng.integers(0, (hi - lo) // stride + 1, size=n) if s.delay_on
                      else np.zeros(n, dtype=np.int64))
        self.motor_constant = rng.uniform(*s.motor_constant, size=(n, j)) if s.motor_on else np.ones((n, j))
        if s.friction_on:
            self.coulomb, self.viscous = rng.uniform(*s.coulomb, size=(n, j)), rng.uniform(*s.viscous, size=(n, j))
        else:
            self.coulomb, self.viscous = np.zeros((n, j)), np.zeros((n, j))
        self.history = np.zeros((n, self.depth, j))
        # The history slot substep s of a period reads: the command of ceil(max(k - s, 0) / S) periods ago, i.e. the
        # command stream shifted by exactly k substeps (Delay._set_lag).
        sub = np.arange(self.substeps)
        self.lag = (np.clip(self.delay[:, None] - sub, 0, None) + self.substeps - 1) // self.substeps

    def __call__(self, tau, qd) -> np.ndarray:
        """(N, S, J) torque [N·m] per physics substep of this period from the commanded torque ``tau`` (N, J) and
        the joint velocity ``qd`` (N, J) [rad/s] at the period's start."""
        tau, qd = np.asarray(tau, dtype=np.float64), np.asarray(qd, dtype=np.float64)
        self.history = np.roll(self.history, 1, axis=1)
        self.history[:, 0] = tau
        out = self.history[np.arange(len(tau))[:, None], self.lag]  # (N, S, J)
        if self.settings.delay_average:  # AveragedDelay: the period's mean, held through it
            out = np.broadcast_to(out.mean(axis=1, keepdims=True), out.shape)
        out = out * self.motor_constant[:, None]
        out = out - (self.coulomb * np.sign(qd) + self.viscous * qd)[:, None]
        if self.settings.saturate:
            out = np.clip(out, -self.limits, self.limits)
        return out


# ---------------------------------------------------------------------------------------------------- dynamics
class WorldDynamics:
    """One ``MjModel`` per robot with its own masses, damping, armature and friction (``sim/dynamics.py``'s draws).

    ``dof_invweight0``/``body_invweight0`` stay the nominal model's, as in training. Attributes (after
    :meth:`reset`): ``models`` (one copy per robot), ``mass_scale`` (N, nbody) (1 for the world and mocap bodies),
    ``joint_damping`` (N, D) [N·m·s/rad], ``armature_scale`` (N, D), ``friction_scale`` (N,), with D the joint dofs
    (``dofs``: every dof but the free joint's)."""

    def __init__(self, settings: DynamicsSettings, model: mujoco.MjModel):
        settings.validate()
        self.settings, self.model = settings, model
        self.bodies = np.array([b for b in range(1, model.nbody) if model.body_mocapid[b] < 0], dtype=np.int64)
        self.dofs = np.array([d for d in range(model.nv) if model.jnt_type[model.dof_jntid[d]]
                              != mujoco.mjtJoint.mjJNT_FREE], dtype=np.int64)
        self.models: list[mujoco.MjModel] = []

    def reset(self, rng: np.random.Generator, n: int) -> list[mujoco.MjModel]:
        """Draw each robot's dynamics and write them into its model copy (made at the first reset); returns them."""
        s, m, nd = self.settings, self.model, len(self.dofs)
        if len(self.models) != n:
            self.models = [copy.copy(m) for _ in range(n)]
        self.mass_scale = np.ones((n, m.nbody))
        if s.on("mass_scale"):
            self.mass_scale[:, self.bodies] = rng.uniform(*s.mass_scale, size=(n, len(self.bodies)))
        self.joint_damping = rng.uniform(*s.joint_damping, size=(n, nd)) if s.on("joint_damping") else np.zeros((n, nd))
        self.armature_scale = (rng.uniform(*s.armature_scale, size=(n, nd)) if s.on("armature_scale")
                               else np.ones((n, nd)))
        self.friction_scale = rng.uniform(*s.friction_scale, size=n) if s.on("friction_scale") else np.ones(n)
        for i, world in enumerate(self.models):
            mass = m.body_mass * self.mass_scale[i]
            world.body_mass[:] = mass
            world.body_inertia[:] = m.body_inertia * self.mass_scale[i][:, None]
            # Subtree masses (which subtree_com divides by) from the drawn masses: children come after parents.
            subtree = mass.copy()
            for b in range(m.nbody - 1, 0, -1):
                subtree[m.body_parentid[b]] += subtree[b]
            world.body_subtreemass[:] = subtree
            world.dof_damping[:] = m.dof_damping
            world.dof_damping[self.dofs] += self.joint_damping[i]
            world.dof_armature[:] = m.dof_armature
            world.dof_armature[self.dofs] *= self.armature_scale[i]
            world.geom_friction[:] = m.geom_friction
            world.geom_friction[:, 0] *= self.friction_scale[i]
        return self.models


# ----------------------------------------------------------------------------------------------------- sensors
class SensorModel:
    """Sensor biases and noise on the observation's signals (``transforms/sensor_noise.py``), for N robots.

    :meth:`reset` draws each robot's biases (constant over the episode); each call adds them and fresh noise to
    the signals the policy observes, float32 as in the env, a biased roll/pitch/yaw wrapped back into (-π, π]. Give
    it to ``PolicyRuntime(sensors=...)``: the runtime checks the true state, then observes the perturbed one.

    Attributes (after :meth:`reset`): ``biases`` {signal: (N, *shape)} float32 in the signal's unit.
    """

    SHAPES = {"joint_pos": None, "base_rpy": (3,), "foot_force": (2, 3), "foot_torque": (2, 3), "base_lin_vel": (3,),
              "base_ang_vel": (3,)}

    def __init__(self, settings: SensorSettings, num_joints: int, noise_rng: np.random.Generator):
        settings.validate()
        self.settings, self.num_joints, self.noise_rng = settings, int(num_joints), noise_rng
        self.biases: dict[str, np.ndarray] = {}

    def reset(self, rng: np.random.Generator, n: int) -> None:
        self.biases = {}
        for name, shape in self.SHAPES.items():
            half = float(getattr(self.settings, f"{name}_bias"))
            if half > 0:
                shape = (self.num_joints,) if shape is None else shape
                self.biases[name] = rng.uniform(-half, half, size=(n, *shape)).astype(np.float32)

    def __call__(self, signals: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        perturbed = [*self.biases, *(n for n in NOISY if getattr(self.settings, f"{n}_noise_std") > 0)]
        unread = [n for n in perturbed if n not in signals]
        if unread:  # a KeyError from deep inside otherwise; only a policy that observes a signal is given it
            raise ValueError(f"SensorModel perturbs {unread}, which this policy does not observe (it is given "
                             f"{sorted(signals)}); set those ranges to 0")
        out = dict(signals)
        for name, bias in self.biases.items():
            value = np.asarray(out[name], dtype=np.float32)
            if value.shape != bias.shape:  # numpy's broadcast error would name neither the robots nor the fix
                raise ValueError(f"SensorModel: signal {name!r} has shape {value.shape}, expected {bias.shape}: its "
                                 f"biases were drawn for {len(bias)} robot(s); call reset(rng, n) with this "
                                 "episode's robot count first")
            out[name] = value + bias
        for name in NOISY:
            std, clip = float(getattr(self.settings, f"{name}_noise_std")), getattr(self.settings,
                                                                                   f"{name}_noise_clip")
            if std > 0:
                value = np.asarray(out[name], dtype=np.float32)
                z = std * self.noise_rng.standard_normal(value.shape)
                if clip is not None:
                    z = np.clip(z, -clip, clip)
                out[name] = value + z.astype(np.float32)
        if "base_rpy" in self.biases:
            rpy = out["base_rpy"]
            two_pi = np.float32(2.0 * math.pi)
            out["base_rpy"] = np.where(rpy > math.pi, rpy - two_pi, np.where(rpy <= -math.pi, rpy + two_pi, rpy))
        return out


# ------------------------------------------------------------------------------------------------------ pushes
class PushSchedule:
    """The kicks of N robots (``envs/pushes.py``).

    Args:
        settings: :class:`PushSettings` (``count`` > 0).
        dt: the control period [s].
        mass: the robot's mass [kg] (impulse = speed × mass).

    Attributes (after :meth:`reset`): ``start_step`` (N, count) the control period each kick starts in (0 = the
    episode's first), ``steps`` (N, count) how many periods it lasts, ``force`` (N, count, 2) [N] world x, y.
    """

    def __init__(self, settings: PushSettings, dt: float, mass: float):
        settings.validate()
        self.settings, self.dt, self.mass = settings, float(dt), float(mass)

    def reset(self, rng: np.random.Generator, n: int) -> None:
        s, k = self.settings, self.settings.count
        share = (s.window[1] - s.window[0]) / k
        when = s.window[0] + share * (np.arange(k) + rng.uniform(size=(n, k)))
        angle = rng.uniform(0.0, 2.0 * math.pi, size=(n, k))
        speed = rng.uniform(*s.speed, size=(n, k))
        steps = np.maximum(np.round(rng.uniform(*s.duration, size=(n, k)) / self.dt).astype(np.int64), 1)
        if s.calm_fraction > 0:  # drawn only then, so that the other draws of a seed stay as they were
            still = rng.uniform(size=(n, 1)) < s.calm_fraction  # a calm episode: no kick ever begins
            speed, when = np.where(still, 0.0, speed), np.where(still, CALM_NEVER_S, when)
        magnitude = speed * self.mass / (steps * self.dt)
        self.start_step = np.round(when / self.dt).astype(np.int64)
        self.steps = steps
        self.speed = speed
        self.force = magnitude[..., None] * np.stack((np.cos(angle), np.sin(angle)), axis=-1)

    def at(self, step: int) -> np.ndarray:
        """(N, 2) the horizontal force [N] of a "force" kick on the pelvis during control period ``step`` (0 = the
        first), world frame; a "velocity" kick's acceleration [m/s²] is this over :attr:`mass`."""
        active = (step >= self.start_step) & (step < self.start_step + self.steps)
        return (self.force * active[..., None]).sum(axis=1)

    def body_forces(self, step: int, base: int, body_mass: np.ndarray) -> np.ndarray:
        """(N, nbody, 2) the horizontal force [N] on every body during control period ``step``, world frame, for
        ``MjData.xfrc_applied[:, :2]``: a "force" kick on body ``base`` (the pelvis) alone, a "velocity" kick on
        every body by its mass (``body_mass`` (N, nbody) [kg], each robot's own model's) × the kick's
        acceleration (``envs/pushes.py``)."""
        force = self.at(step)
        if self.settings.kind == "velocity":
            return body_mass[:, :, None] * (force / self.mass)[:, None, :]
        out = np.zeros((*body_mass.shape, 2))
        out[:, base] = force
        return out


def start_velocities(rng: np.random.Generator, n: int, nv: int, start: StartVelocity) -> np.ndarray:
    """(N, nv) start velocities: N(0, base_std²) on the free joint's linear velocity (``qvel[:3]``, world frame),
    N(0, joint_std²) on every joint (``qvel[6:]``), none on the angular velocity."""
    z = rng.standard_normal((n, nv))
    qvel = np.zeros((n, nv))
    qvel[:, :3] = start.base_std * z[:, :3]
    qvel[:, 6:] = start.joint_std * z[:, 6:]
    return qvel
