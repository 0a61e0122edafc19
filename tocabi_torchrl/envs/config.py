"""Configuration of the TOCABI walking task: every constant of the task, with its unit, in one dataclass."""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field

from .. import robot
from ..cli import suggest_options
from ..control.config import ActuatorConfig
from ..sim.config import NCONMAX, RESET_PASSES
from ..sim.dynamics_config import DynamicsRandomization
from ..tree import OWN_NUMBER_CHECK, check_field_types
from ..value_rules import ENV_RULES, START_VEL_STD, check_env_value, plain_number
from .command_config import CommandConfig
from .push_config import PushConfig

__all__ = ["TocabiWalkConfig", "EnvSimConfig", "TaskConfig", "ControlConfig", "SceneConfig", "BoxObstacle", "PD_GAINS",
           "ENV_FLAT_PATHS", "CONTROL_MODES", "TORQUE_MODES", "UPPER_BODY_LAWS", "MB_OMEGA", "BACKENDS",
           "CPU_DEFAULT_BACKEND", "resolve_backend"]

CONTROL_MODES = ("torque", "pd", "pd_reference", "model_based", "pd_held")
#: The modes whose leg actuators are torque motors (the env computes the torque); the others make them MuJoCo
#: position servos.
TORQUE_MODES = ("torque", "model_based", "pd_held")
#: The upper body's control laws (``env.control.upper_body``): its servos hold the reference walk's pose.
UPPER_BODY_LAWS = ("pd_hold",)
#: Physics backends: mujoco-warp (``WarpSim``, GPU or warp's CPU device) or C MuJoCo on CPU threads (``MujocoSim``).
BACKENDS = ("warp", "mujoco", "auto")
#: ``backend="auto"`` on a CPU device. Measured by ``benchmarks/cpu_backends.py`` (retired; at commit dab4ad2),
#: docs/benchmarks/cpu_backends_*.md:
#: on a 2-core machine C MuJoCo stepped the bare env at 1800-3200 env-steps/s against mujoco-warp's CPU device's
#: 315-340 (5.7-9.8x) at 8-96 envs, and needs no minute-long kernel compile.
CPU_DEFAULT_BACKEND = "mujoco"


def resolve_backend(backend: str, device) -> str:
    """The backend that runs: ``"auto"`` is mujoco-warp on CUDA and :data:`CPU_DEFAULT_BACKEND` on the CPU."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose one of {BACKENDS}")
    on_cuda = str(device).startswith("cuda")
    if backend == "auto":
        return "warp" if on_cuda else CPU_DEFAULT_BACKEND
    if backend == "mujoco" and on_cuda:
        raise ValueError("backend='mujoco' steps C MuJoCo on the CPU; use device='cpu' with it, or backend='warp' "
                         "(or 'auto') on CUDA")
    return backend


#: The most start states per world ``env.sim.start_pool`` takes: the table holds each state's sensors, accelerations
#: and actuator forces per world (P × num_envs rows).
MAX_START_POOL = 64


@dataclass
class EnvSimConfig:
    """How the env's worlds are simulated (``TocabiWalkConfig.sim``).

    Attributes:
        backend: ``"warp"`` (mujoco-warp), ``"mujoco"`` (C MuJoCo on CPU threads, CPU only) or ``"auto"`` (warp on
            CUDA, :data:`CPU_DEFAULT_BACKEND` on the CPU).
        substeps: physics substeps per policy step (0.5 ms each: 8 -> 250 Hz policy).
        nconmax, njmax: contact/constraint buffers per world for mujoco-warp (None = the backend's measured defaults).
        nccdmax: mujoco-warp convex-collision pairs per world, pooled (None = the measured default,
            ``sim.buffers.NCCDMAX``); it sizes the EPA scratch, ~5 KB a slot.
        threads: CPU threads of the ``"mujoco"`` backend (None = every available core).
        reset_pass: what a mujoco-warp reset computes over all worlds (``SimConfig.reset_pass``): ``"reduced"``
            (default) only the position and velocity stages, with the rest of each start state (one per start row
            of the reference motion, registered when the env is built) taken from a table, bit-identical to the
            full pass in every trajectory on warp's CPU device and ~1 ms a step cheaper at 4,096 envs on an H100
            (docs/benchmarks.md, issue 25); ``"full"`` a full forward pass. The ``"mujoco"`` backend ignores it
            (its reset computes the reset worlds only).
        start_pool: P > 0: each world draws P start states once, when the env is built (start row, diverse start
            velocities, ``env.dynamics``' masses, damping, armature and friction), and every reset picks one of its
            P at random; their sensors and accelerations are computed then, so a reset with diverse starts or
            per-world dynamics takes the reduced pass (the full pass otherwise). 0 (default): a fresh draw at every
            reset. The draws' distributions are the same; the robots a run meets are num_envs × P instead of new
            ones at every reset. The actuator draws, sensor biases and kicks stay fresh per episode, and the pool
            stays that of the build seed (``set_seed`` does not redraw it). With pooled dynamics, worlds can not be
            made ideal (``TocabiWalk.set_randomized_worlds``). Inert without diverse starts or dynamics.
        solver_iterations: the Newton solver's iteration cap per substep (None: the model's, 20 in
            assets/tocabi/tocabi.xml). mujoco-warp iterates every world until the slowest has converged, so a lower
            cap cuts the slowest worlds' solves short: on C MuJoCo robots walking from diverse starts, a cap of 3
            needed 0.64x the lockstep iterations of the model's and moved the parity test's sequence by 1.3e-4 rad,
            but under the robust test's 1.0 m/s kicks the shipped robust policy kept 0.875 of its robots against
            0.969 (docs/benchmarks/solver_tolerance.json): hard impacts need the iterations. A physics change: the
            same on both backends.
    """

    backend: str = "auto"
    substeps: int = 8
    nconmax: int | None = None
    """mujoco-warp contacts per world; none = the measured default"""
    njmax: int | None = None
    """mujoco-warp constraint rows per world; none = the measured default"""
    nccdmax: int | None = None
    """mujoco-warp convex-collision pairs per world (pooled; sizes the EPA scratch); none = the measured default"""
    threads: int | None = None
    reset_pass: str = "reduced"
    start_pool: int = 0
    """start states drawn per world at build (diverse starts, dynamics) that resets pick from, letting them take the
    reduced pass; 0 = a fresh draw and the full pass at every reset"""
    solver_iterations: int | None = None
    """the Newton solver's iteration cap per substep; none = the model's (20)"""

    def validate(self) -> None:
        # Every number by its type first, as the whole tree does (a numpy int or a 0-d tensor kept as a plain int):
        # alone, a section named only the ints it checks below.
        check_field_types(self, "env.sim.")
        if self.backend not in BACKENDS:
            raise ValueError(f"unknown env.sim.backend {self.backend!r}; choose one of {BACKENDS}")
        if self.reset_pass not in RESET_PASSES:
            raise ValueError(f"unknown env.sim.reset_pass {self.reset_pass!r}; choose one of {RESET_PASSES}")
        pool = self.start_pool
        if isinstance(pool, bool) or not isinstance(pool, int) or not 0 <= pool <= MAX_START_POOL:
            raise ValueError(f"env.sim.start_pool must be an int in [0, {MAX_START_POOL}] (start states per world; "
                             f"0 = a fresh draw at every reset), got {pool!r}")
        # substeps has the env's shared rule (the policy contract's timing.substeps is checked with it too).
        check_env_value("sim.substeps", self.substeps)
        for name in ("nconmax", "njmax", "nccdmax", "threads", "solver_iterations"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
                alias = " (sim_threads)" if name == "threads" else ""
                raise ValueError(f"env.sim.{name}{alias} must be a positive int or None, got {v!r}")
        # Here, by its path: otherwise only the warp backend's SimConfig refused it, at the env's build, as
        # "SimConfig.nccdmax", and a config that names the mujoco backend (which ignores both) passed.
        nconmax = self.nconmax if self.nconmax is not None else NCONMAX
        if self.nccdmax is not None and self.nccdmax > nconmax:
            given = "env.sim.nconmax" if self.nconmax is not None else "the default env.sim.nconmax"
            raise ValueError(f"env.sim.nccdmax must be <= {given} ({nconmax}): mujoco-warp takes its "
                             f"convex-collision pairs from each world's contact pool, got {self.nccdmax}; lower "
                             f"env.sim.nccdmax or raise env.sim.nconmax to at least {self.nccdmax}")


@dataclass
class TaskConfig:
    """The episode: reference motion, phase clock, truncation and early termination (spec §9.1)
    (``TocabiWalkConfig.task``). Angles in rad, lengths in m.

    Attributes:
        max_episode_steps: policy steps before truncation (8000 = 32 s). The env is the one truncation clock:
            ``make_env``'s ``StepCounter`` only counts.
        motion: reference motion; None = the shipped generated cycle, or a path to a ``.npz`` / reference ``.txt``.
        model_path: robot model; None = the shipped assets/tocabi/tocabi.xml.
        phase_rate_gain: phase clock t += dt × (1 + phase_rate_gain × action[12]) per step (reference 1: 1× to 2×).
        min_pelvis_height, min_neck_height, max_neck_angle, terminate_on_forbidden_contact,
            terminate_on_self_collision: the early-termination conditions.
        start_joint_vel_std: std [rad/s] of Gaussian joint velocities a reset world starts with (0: at rest).
        start_base_vel_std: std [m/s] of the pelvis's Gaussian linear velocity (each axis) at reset (0: at rest).
            Either above 0 makes the starts diverse (the robust gait test) and the reset runs the full pass (unless
            ``sim.start_pool`` pools the start states).
        cycle_velocity: report ``cycle_vel_error``, the heading-frame velocity minus the command averaged over the
            last gait cycle (envs/cycle_velocity.py), which the ``cycle_vel`` reward term reads.
    """

    max_episode_steps: int = 8000
    motion: str | None = None
    model_path: str | None = None
    phase_rate_gain: float = 1.0
    min_pelvis_height: float = 0.6
    """episode ends below this pelvis height [m]"""
    min_neck_height: float = 0.8
    """episode ends below this neck height [m]"""
    max_neck_angle: float = 1.0
    """episode ends beyond this neck tilt [rad]"""
    terminate_on_forbidden_contact: bool = True
    """episode ends when a body other than the feet touches the ground or an obstacle"""
    terminate_on_self_collision: bool = True
    """episode ends on a self-collision"""
    start_joint_vel_std: float = 0.0
    start_base_vel_std: float = 0.0
    cycle_velocity: bool = False
    """report cycle_vel_error, the velocity-tracking error averaged over the last gait cycle [m/s] (the cycle_vel
    reward term reads it)"""

    def validate(self) -> None:
        # Every number by its type first, as the whole tree does (a numpy scalar or a 0-d tensor kept as a plain
        # number): alone, the section kept a tensor where the env's tree stored a float.
        check_field_types(self, "env.task.")
        m = self.max_episode_steps
        if isinstance(m, bool) or not isinstance(m, int) or m < 1:
            raise ValueError(f"env.task.max_episode_steps must be an int >= 1, got {m!r}")
        for name in ("min_pelvis_height", "min_neck_height", "max_neck_angle", "phase_rate_gain"):
            check_env_value(f"task.{name}", getattr(self, name))
        for name in ("start_joint_vel_std", "start_base_vel_std"):  # the runtime's StartVelocity has the same rule
            START_VEL_STD.check(getattr(self, name), f"env.task.{name} (a std)")
        motion = os.fspath(self.motion) if isinstance(self.motion, os.PathLike) else self.motion
        if motion is not None and (not isinstance(motion, str) or not motion.strip()):
            raise ValueError(f"env.task.motion must be a path to a .npz or reference .txt motion, or none for the "
                             f"shipped cycle, got {self.motion!r}")
        model = os.fspath(self.model_path) if isinstance(self.model_path, os.PathLike) else self.model_path
        if model is not None and (not isinstance(model, str) or not model.strip()):
            # 5 ended in a raw TypeError and "" in "robot model file not found: ."
            raise ValueError(f"env.task.model_path must be a path to a MuJoCo XML model of TOCABI, or none for the "
                             f"shipped model, got {self.model_path!r}")

    @property
    def diverse_starts(self) -> bool:
        """Whether a reset draws start velocities."""
        return self.start_joint_vel_std > 0 or self.start_base_vel_std > 0


#: The robot controller's leg gains, the PD modes' default (TocabiLab divides Kp by 9 and Kv by 3: ``"tocabilab"``).
PD_GAINS = {"robot": (tuple(float(v) for v in robot.LEG_KP), tuple(float(v) for v in robot.LEG_KV)),
            "tocabilab": (tuple(float(v) for v in robot.LEG_KP / 9.0), tuple(float(v) for v in robot.LEG_KV / 3.0))}

#: The ``model_based`` mode's default natural frequencies [rad/s], per leg joint: ``sqrt(LEG_KP / M_jj)`` with M_jj
#: the diagonal of the shipped model's leg inertia (armature included) at the initial pose, rounded. So at the
#: initial pose each joint's stiffness ``M_jj·ω²`` is the robot controller's Kp, the PD that tracks the reference in
#: the other modes (``tests/test_model_based.py`` recomputes them). With ``mb_zeta`` 0.7 (the default; a second-order
#: loop's least tracking error, and the 250 Hz hold keeps it at 0.70, see ``envs.model_based``), the law at zero
#: action tracked and survived best of the gains tried on the CPU (docs/training.md).
MB_OMEGA: tuple[float, ...] = (41.0, 29.0, 25.0, 38.0, 52.0, 89.0) * 2

#: A ``model_based`` residual gain [N·m per action unit], per leg joint, with the authority of the PD-residual modes:
#: ``pd_action_scale`` (0.5 rad) × the robot's Kp, the torque one action unit moves a ``pd_reference`` servo (and the
#: assisted torque mode at β = 1) by. 3-11× the torque limits, so |a| ≳ 0.1-0.3 saturates a joint, as it does there.
MB_RESIDUAL_GAIN_PD: tuple[float, ...] = tuple(0.5 * float(v) for v in robot.LEG_KP)


@dataclass
class ControlConfig:
    """What the 12 leg actions command (``TocabiWalkConfig.control``).

    Modes (``mode``):
      - ``"torque"`` (reference): leg torque = action[:12] × joint torque limit, held for all substeps.
      - ``"pd"`` (TocabiLab's position-based policy): action[:12] in [-1, 1] maps to a target angle
        ``pd_nominal + pd_action_scale × action`` clipped to the joint range, tracked in every physics substep by
        MuJoCo position servos with gains ``pd_kp``/``pd_kv``, force-limited to the torque limits.
      - ``"pd_reference"`` (the default): as ``"pd"`` with the target centred on the reference walk.
      - ``"model_based"``: leg torque = ``clip(τ_ff + g·action[:12], ±limit)``, a residual torque on top of a
        computed-torque law that tracks the reference walk from the simulator's own dynamics,
        ``τ_ff = M_LL(q)·(q̈_ref + Kp·(q_ref − q) + Kd·(q̇_ref − q̇)) + c_L(q, q̇)`` with ``Kp = ω²``,
        ``Kd = 2ζω`` (``mb_omega`` [rad/s], ``mb_zeta``, per leg joint), computed from the pre-step state and held
        for the step like a torque action (:class:`~tocabi_torchrl.envs.model_based.ComputedTorque` says where each
        term comes from and why the base coupling and contact forces are left to the policy). ``mb_ref_window`` [s]
        is the half-width of the central differences that give q̇_ref and q̈_ref. ``mb_residual_gain`` is g [N·m
        per action unit], per leg joint: by default the torque limits (as in torque mode); the ``model_based``
        preset gives it the PD-residual modes' authority, :data:`MB_RESIDUAL_GAIN_PD`.
      - ``"pd_held"``: the ``pd_reference`` target, unclipped, tracked by a PD computed once per policy step from the
        pre-step state and held as a torque, ``clip(pd_kp·(q_ref + pd_action_scale·a − q − b) − pd_kv·q̇, ±limit)``
        (:class:`~tocabi_torchrl.control.HeldPD`): the torque assist's law at β = 1, without the fade. ``b`` is each
        world's leg encoder bias (the law reads the positions the robot senses); the actuator layer acts on it.
    The upper body is held at the reference pose by MuJoCo position servos in every mode. The gains default to the
    robot controller's (:data:`PD_GAINS` ``"robot"``); the PD modes, ``pd_held`` and ``torque_assist`` use them, the
    ``torque`` and ``model_based`` modes do not. In ``model_based`` and ``pd_held`` mode the leg entries of
    ``applied_action`` (observation history, torque rewards) and ``leg_torque`` are the applied torque (over the
    limits / in N·m), as with ``torque_assist``; in ``model_based`` mode the ``leg_feedforward`` signal is τ_ff.

    ``torque_assist`` (torque mode only) is a training aid that morphs the action space: the leg torque is
    ``(1 − β)·a·limit + β·(pd_kp·(q_ref + pd_action_scale·a − q) − pd_kv·q̇)`` (clipped to the limits), so at β = 1
    the 12 leg actions are position residuals around the reference walk tracked by a PD at the policy rate (the
    ``pd_reference`` mode, which learns to walk), and at β = 0 they are the reference's normalised torques. β is
    the env's device scalar ``assist_scale`` (:meth:`TocabiWalk.set_torque_assist`, 0 at build), so a trainer can
    fade it without rebuilding or re-capturing. Adds the ``leg_assist`` signal: the action-independent part of the
    PD, ``(pd_kp·(q_ref − q) − pd_kv·q̇) / limit`` (num_envs, 12), from the pre-step state. The leg entries of
    ``applied_action`` (observation history, torque rewards) are the applied torque over the limits, the same at
    every β for the same torques (at β = 0 they equal the action, as in plain torque mode).
    """

    mode: str = "pd_reference"
    """what the 12 leg actions command: pd_reference (residuals on the reference walk's PD targets), pd (PD targets
    around a fixed pose), torque, model_based (residual torques on a computed-torque law) or pd_held (pd_reference's
    targets through a PD computed at the policy rate and held as a torque)"""
    pd_kp: tuple[float, ...] = PD_GAINS["robot"][0]
    """leg PD stiffness per joint [N·m/rad] (PD modes, torque assist); default: the robot's, TocabiLab used Kp/9"""
    pd_kv: tuple[float, ...] = PD_GAINS["robot"][1]
    """leg PD damping per joint [N·m·s/rad]; default: the robot's, TocabiLab used Kv/3"""
    pd_action_scale: float = 0.5
    """residual range of the PD modes [rad]: target = center + scale × action"""
    pd_nominal: tuple[float, ...] = tuple(float(v) for v in robot.INIT_JOINT_POS[:12])
    """centre of the 'pd' mode's leg targets [rad], one per leg joint"""
    torque_assist: bool = False
    """give every env the torque assist (the trainer sets it on its training env when ppo.torque_assist > 0)"""
    # validate() checks the per-joint model_based values itself, naming the joint.
    mb_omega: tuple[float, ...] = field(default=MB_OMEGA, metadata=OWN_NUMBER_CHECK)
    """model_based mode: the computed-torque loop's natural frequency ω per leg joint [rad/s] (Kp = ω²)"""
    mb_zeta: tuple[float, ...] = field(default=(0.7,) * robot.NUM_LEG_JOINTS, metadata=OWN_NUMBER_CHECK)
    """model_based mode: the loop's damping ratio ζ per leg joint (Kd = 2ζω)"""
    mb_ref_window: float = 0.008
    """model_based mode: half-width of the central differences that give the reference's velocity and
    acceleration [s]"""
    mb_residual_gain: tuple[float, ...] = field(default=tuple(float(v) for v in robot.LEG_TORQUE_LIMITS),
                                                metadata=OWN_NUMBER_CHECK)
    """model_based mode: torque per unit of the policy's residual action, per leg joint [N·m] (default: the torque
    limits)"""
    #: The upper body's control law (``envs.controllers.upper_body_law``): the model file's servos hold the reference.
    upper_body: str = "pd_hold"
    #: The actuator layer between the legs' torque commands and the joints (ideal by default; torque modes only).
    actuators: ActuatorConfig = field(default_factory=ActuatorConfig)

    @property
    def pd_senses_joints(self) -> bool:
        """Whether the legs' law is a PD that reads the sensed joint positions from the env's build on (``pd_held``:
        the robot's own law); the torque assist's PD does so only when asked (``TocabiWalk.sense_assist_joints``)."""
        return self.mode == "pd_held"

    def validate(self) -> None:
        check_field_types(self, "env.control.")  # as the task's: numbers stored as plain numbers, named by path
        if self.mode not in CONTROL_MODES:
            raise ValueError(f"unknown env.control.mode (control_mode) {self.mode!r}; choose one of {CONTROL_MODES}")
        for name in ("pd_kp", "pd_kv", "pd_nominal"):
            if len(getattr(self, name)) != robot.NUM_LEG_JOINTS:
                raise ValueError(f"env.control.{name} needs {robot.NUM_LEG_JOINTS} values (one per leg joint), got "
                                 f"{len(getattr(self, name))}")
        for name in ("pd_kp", "pd_kv", "pd_nominal", "pd_action_scale"):
            check_env_value(f"control.{name}", getattr(self, name))
        if self.upper_body not in UPPER_BODY_LAWS:
            raise ValueError(f"unknown env.control.upper_body {self.upper_body!r}; choose one of {UPPER_BODY_LAWS}")
        self.actuators.validate()
        if not self.actuators.ideal and self.mode not in TORQUE_MODES:
            raise ValueError(f"env.control.actuators act on torque commands, but control mode {self.mode!r} tracks "
                             f"targets with servos inside the physics; use a torque mode {TORQUE_MODES} or leave "
                             "env.control.actuators at its defaults")
        if self.torque_assist and self.mode != "torque":
            raise ValueError(f"env.control.torque_assist needs control_mode='torque' (env.control.mode; the PD modes "
                             f"already track with servos, and pd_held is the assist at β = 1), got {self.mode!r}")
        for name in ("mb_omega", "mb_zeta", "mb_residual_gain"):
            values = getattr(self, name)
            if isinstance(values, (str, bytes)) or not hasattr(values, "__len__"):
                raise ValueError(f"env.control.{name} needs {robot.NUM_LEG_JOINTS} numbers (one per leg joint), got "
                                 f"{values!r}")
            if len(values) != robot.NUM_LEG_JOINTS:
                raise ValueError(f"env.control.{name} needs {robot.NUM_LEG_JOINTS} values (one per leg joint), got "
                                 f"{len(values)}")
            rule = ENV_RULES[f"control.{name}"]
            bad = [(robot.JOINT_NAMES[j], v) for j, v in enumerate(values) if not rule.allows(v)]
            if bad:
                what = {"mb_omega": "natural frequency [rad/s]", "mb_zeta": "damping ratio",
                        "mb_residual_gain": "residual gain [N·m per action unit]"}[name]
                raise ValueError(f"env.control.{name}: every leg joint's {what} must be {rule.describe()}; got "
                                 + ", ".join(f"{joint}={v!r}" for joint, v in bad))
        window = self.mb_ref_window
        if not ENV_RULES["control.mb_ref_window"].allows(window):
            raise ValueError(f"env.control.mb_ref_window must be a finite number of seconds > 0 (the half-width of "
                             f"the reference's velocity/acceleration differences), got {window!r}")


def _floats(value, n: int, what: str) -> tuple[float, ...]:
    """``value`` as a tuple of ``n`` finite floats, or a ``ValueError`` naming ``what``."""
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be {n} numbers, got {value!r}") from None
    if len(out) != n:
        raise ValueError(f"{what} must be {n} numbers, got {len(out)}: {value!r}")
    if not all(math.isfinite(v) for v in out):
        raise ValueError(f"{what} must be finite, got {out}")
    return out


@dataclass(frozen=True)
class BoxObstacle:
    """A box resting on the ground (its bottom face at z = 0), axis-aligned with the world, added to the scene at
    build time (``TocabiWalkConfig.scene.obstacles``). Lengths in m, world frame (x forward, y left, z up; the robot
    starts with its pelvis at x = y = 0 facing +x).

    The box is a static, collidable body of the scene (a MuJoCo mocap body named ``obstacle_<k>`` with one box
    geom of the same name, k its index in ``scene.obstacles``). Contacts with it count like contacts with the
    ground: a foot on it is foot contact (``foot_contact``, and ``obstacle_contact``), any body of
    ``robot.GROUND_FORBIDDEN_BODIES`` touching it is forbidden contact (termination).

    Attributes:
        size: full length (x), width (y) and height (z) [m], each > 0.
        pos: (x, y) of the box centre [m] (its z centre is ``size[2] / 2``). The default (0.7, 0.1025) is 0.6 m
            ahead of the left sole's centre in the initial pose (:meth:`ahead_of_left_foot`).
        jitter: (x, y) half-ranges [m], >= 0, of a uniform per-world offset of ``pos``: world i's box is centred at
            ``pos + U(-jitter, jitter)``, drawn once per world when the env is built, from the env's ``seed`` (the
            same seed, world count and obstacles give the same positions; a reset keeps them, and ``set_seed`` after
            the build does not move them). ``TocabiWalk.obstacle_pos`` holds every world's box centres.
    """

    size: tuple[float, float, float] = (0.3, 0.6, 0.012)
    pos: tuple[float, float] = (0.7, 0.1025)
    jitter: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self):
        size = _floats(self.size, 3, "BoxObstacle.size (length, width, height in m)")
        if min(size) <= 0:
            raise ValueError(f"BoxObstacle.size (length, width, height in m) must be > 0, got {size}")
        jitter = _floats(self.jitter, 2, "BoxObstacle.jitter (x, y half-ranges in m)")
        if min(jitter) < 0:
            raise ValueError(f"BoxObstacle.jitter (x, y half-ranges in m) must be >= 0, got {jitter}")
        object.__setattr__(self, "size", size)
        object.__setattr__(self, "pos", _floats(self.pos, 2, "BoxObstacle.pos (x, y of the centre in m)"))
        object.__setattr__(self, "jitter", jitter)

    @classmethod
    def ahead_of_left_foot(cls, height: float, distance: float = 0.6, length: float = 0.3, width: float = 0.6,
                           jitter: tuple[float, float] = (0.0, 0.0), lateral: float = 0.0,
                           model_path: str | None = None) -> BoxObstacle:
        """A box ``height`` [m] high whose centre is ``distance`` [m] ahead (+x) of the left sole's centre in the
        robot's initial pose (``robot.INIT_QPOS``; found from the model, ``model_path`` or the shipped one: sole centre
        at (0.100, 0.1025) m), shifted ``lateral`` [m] to the left (+y). ``length`` (x) and ``width`` (y) in m; the
        default 0.6 m width spans both feet's tracks (a box only the left foot meets needs width < 0.2 m).
        ``jitter``: see :attr:`jitter`. The centre is rounded to 0.1 mm (readable configs)."""
        x, y = robot.initial_sole_centre(0, model_path)[:2]
        pos = (round(float(x) + float(distance), 4), round(float(y) + float(lateral), 4))
        return cls(size=(length, width, height), pos=pos, jitter=jitter)

    @property
    def half_size(self) -> tuple[float, float, float]:
        """Half length, width, height [m] (MuJoCo's box ``size``)."""
        return tuple(v / 2 for v in self.size)

    def validate(self) -> None:
        """Raise ``ValueError`` naming a bad value (the values are already checked when the box is made)."""
        type(self)(self.size, self.pos, self.jitter)


@dataclass
class SceneConfig:
    """What the robot's world holds besides the ground plane (``TocabiWalkConfig.scene``).

    Attributes:
        obstacles: :class:`BoxObstacle` boxes, added to the model at build time on every backend (none: the model
            is the plain robot scene, compiled exactly as without this section). On the command line a JSON list,
            e.g. ``--env.scene.obstacles '[{"size": [0.3, 0.6, 0.012], "pos": [0.7, 0.1], "jitter": [0.05, 0.05]}]'``.
    """

    obstacles: tuple[BoxObstacle, ...] = ()

    def validate(self) -> None:
        if not isinstance(self.obstacles, tuple):
            raise ValueError(f"env.scene.obstacles must be a tuple of BoxObstacle, got {type(self.obstacles).__name__}")
        for k, box in enumerate(self.obstacles):
            if not isinstance(box, BoxObstacle):
                raise ValueError(f"env.scene.obstacles[{k}] must be a BoxObstacle, got {type(box).__name__}")
            try:
                box.validate()
            except ValueError as err:
                raise ValueError(f"env.scene.obstacles[{k}]: {err}") from None


#: The flat keyword names ``TocabiWalk(...)``/``make_env(...)`` accept (and ``TocabiWalkConfig`` had before it was
#: split into sections) -> their path in the env tree.
ENV_FLAT_PATHS = {
    "control_mode": "control.mode", "pd_kp": "control.pd_kp", "pd_kv": "control.pd_kv",
    "pd_action_scale": "control.pd_action_scale", "pd_nominal": "control.pd_nominal",
    "torque_assist": "control.torque_assist", "mb_omega": "control.mb_omega", "mb_zeta": "control.mb_zeta",
    "mb_ref_window": "control.mb_ref_window", "mb_residual_gain": "control.mb_residual_gain",
    "substeps": "sim.substeps", "nconmax": "sim.nconmax", "njmax": "sim.njmax", "backend": "sim.backend",
    "sim_threads": "sim.threads", "reset_pass": "sim.reset_pass", "start_pool": "sim.start_pool",
    "obstacles": "scene.obstacles",
    **{name: f"task.{name}" for name in TaskConfig.__dataclass_fields__},
}


@dataclass
class TocabiWalkConfig:
    """The walking task's env config: one section per concern, every constant with its unit.

    The defaults are the task of the ``default`` training preset (``recipes/ppo_walk.py``): residual PD control
    around the reference walk with the robot's gains and TocabiLab's command schedule, so ``TocabiWalk()``,
    ``make_env()`` and the recipe agree. ``TocabiWalkConfig.reference()`` is the reference code's task (torque control,
    its command schedule).

    Attributes:
        num_envs: parallel worlds N (>= 1).
        sim: :class:`EnvSimConfig` (backend, substeps, buffers, threads).
        task: :class:`TaskConfig` (episode length, motion, terminations).
        command: :class:`~tocabi_torchrl.envs.command.CommandConfig` (velocity command schedule).
        control: :class:`ControlConfig` (what the leg actions command).
        scene: :class:`SceneConfig` (obstacles on the ground).
        dynamics: :class:`~tocabi_torchrl.sim.dynamics.DynamicsRandomization` (per-world link masses, joint damping,
            armature and friction, drawn at every reset; off by default).
        pushes: :class:`~tocabi_torchrl.envs.pushes.PushConfig` (kicks during an episode: a force on the pelvis or a
            velocity kick of the whole robot; off by default).
    """

    num_envs: int = 4096
    sim: EnvSimConfig = field(default_factory=EnvSimConfig)
    task: TaskConfig = field(default_factory=TaskConfig)
    command: CommandConfig = field(default_factory=CommandConfig)
    control: ControlConfig = field(default_factory=ControlConfig)
    scene: SceneConfig = field(default_factory=SceneConfig)
    pushes: PushConfig = field(default_factory=PushConfig)
    dynamics: DynamicsRandomization = field(default_factory=DynamicsRandomization)

    @classmethod
    def reference(cls, **flat) -> TocabiWalkConfig:
        """The reference code's task: torque control and its command schedule (U(-0.2, 0.8) with the linear ramp);
        ``flat`` as in :meth:`with_flat`."""
        cfg = cls(command=CommandConfig.reference(), control=ControlConfig(mode="torque"))
        return cfg.with_flat(**flat)

    def with_flat(self, **flat) -> TocabiWalkConfig:
        """A copy with keyword overrides: flat names (``control_mode="pd"``, ``max_episode_steps=1000``, see
        :data:`ENV_FLAT_PATHS`), section names (``command=CommandConfig.reference()``) or ``num_envs``. Raises
        ``TypeError`` naming an unknown keyword."""
        from ..tree import replace_paths

        sections = {f.name for f in dataclasses.fields(self)}
        unknown = sorted(set(flat) - set(ENV_FLAT_PATHS) - sections)
        if unknown:
            known = sorted(sections | set(ENV_FLAT_PATHS))
            close = {k: m[0] for k in unknown if (m := suggest_options(k, known, limit=1))}
            hint = "".join(f"; {k!r}: did you mean {v!r}?" for k, v in close.items())
            raise TypeError(f"unknown TocabiWalk option(s) {unknown}{hint}; use a section ("
                            f"{', '.join(f.name for f in dataclasses.fields(self))}) or one of "
                            f"{sorted(ENV_FLAT_PATHS)}")
        return replace_paths(self, {ENV_FLAT_PATHS.get(k, k): v for k, v in flat.items()})

    @property
    def torque_assist(self) -> bool:
        """``control.torque_assist``: whether the env has the assist (and its ``leg_assist`` signal)."""
        return self.control.torque_assist

    @property
    def start_pool(self) -> int:
        """The start states per world the env pools (``sim.start_pool``), or 0 where it has nothing to pool: no
        diverse starts and no dynamics randomisation."""
        return self.sim.start_pool if self.task.diverse_starts or self.dynamics.enabled else 0

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad option (as its path, e.g. ``env.control.mode``) and the fix."""
        n = plain_number(self.num_envs)  # a numpy or 0-d tensor integer, as every other int field takes it
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ValueError(f"env.num_envs must be a positive int, got {self.num_envs!r}")
        self.num_envs = n
        # Before the sections' own checks, which compare and convert these values: every switch is then a bool and
        # every number a finite real (or an int where one is declared), named by its path when it is not.
        check_field_types(self, "env.")
        self.sim.validate()
        self.task.validate()
        self.control.validate()
        self.command.validate()
        self.scene.validate()
        self.pushes.validate()
        self.dynamics.validate()
