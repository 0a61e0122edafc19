"""TocabiWalk: the batched, GPU-native TorchRL environment of the TOCABI walking task.

N TOCABI worlds step at once in mujoco-warp on ``device`` (or, with ``backend="mujoco"``, in C MuJoCo on CPU threads);
every tensor this env reads or returns stays on ``device``. The env returns raw, physically named signals
(``docs/concepts/env-and-signals.md``); the policy observation and the reward are composed from them by transforms
(``tocabi_torchrl.transforms``, ``tocabi_torchrl.make_env``).

One step (spec §11): clip the action; look the reference targets up at the pre-step phase clock; update the
velocity command; write leg commands and upper-body targets into the simulator's controls; run the physics (one
captured CUDA graph on GPU); advance the phase clock by dt·(1 + a13); evaluate terminations; return signals.
"""

from __future__ import annotations

import warnings

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded
from torchrl.envs import EnvBase

from .. import robot
from ..control import ActuatorChain, ControlContext, ControlInput, Controller
from ..control.joint_pd import per_joint
from ..device import check_device
from ..motion import ReferenceMotion
from ..rotations import quat_rotate_inverse
from ..signals import EPISODE_FLAGS, REWARD, SIGNALS, SignalTable
from ..sim import MujocoSim, SimBackend, SimConfig, WarpSim
from ..sim.dynamics import WorldDynamics
from ..value_rules import positive_count
from .command import VelocityCommand
from .config import TocabiWalkConfig, resolve_backend
from .controllers import leg_actuator_chain, leg_law, upper_body_law
from .cycle_velocity import CycleVelocityError, gait_cycle_steps, heading_velocity
from .episode_random import EpisodeDraws, box_muller, hash_seed
from .obstacles import add_obstacles, check_clear_of_start, world_obstacle_centres
from .pushes import Pushes
from .termination import termination_flags

__all__ = ["TocabiWalk", "quat_rotate_inverse"]

ACTION_DIM = robot.NUM_LEG_JOINTS + 1


def _finite(x: torch.Tensor) -> torch.Tensor:
    """A copy of ``x`` with NaN and ±inf replaced by 0 (finite values unchanged; no host sync)."""
    return torch.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)


def _check_tocabi_spec(spec, model_path) -> None:
    """Refuse a model that is not TOCABI before anything edits it by name (``_servo_spec``, the contact sensors)."""
    missing = robot.missing_names(spec)
    if missing:
        path = model_path if model_path is not None else robot.asset_path("tocabi", "tocabi.xml")
        shown = ", ".join(missing[:3]) + (f" and {len(missing) - 3} more" if len(missing) > 3 else "")
        raise ValueError(
            f"model_path {str(path)!r} is not a TOCABI model: it lacks {shown}; pass a TOCABI MJCF with the joint, "
            "actuator, sensor, body, site and geom names of tocabi_torchrl.robot (JOINT_NAMES, ACTUATOR_NAMES, ...), "
            "or model_path=None for the shipped assets/tocabi/tocabi.xml"
        )


def _check_start_survives(task, model_path) -> None:
    """Warn of termination thresholds that the initial pose already trips: every episode ends at its first step, and
    training would run on without a word (e.g. ``min_pelvis_height=5``). A warning, not an error: a test may want
    every step to be a fall."""
    start = robot.initial_heights(None if model_path is None else str(model_path))
    tripped = [f"{name} {getattr(task, name)!r} (the start pose's {what} is {start[key]:.3f} {unit})"
               for name, key, what, unit, trips in (
                   ("min_pelvis_height", "pelvis_height", "pelvis height", "m", lambda v, s: s < v),
                   ("min_neck_height", "neck_height", "neck height", "m", lambda v, s: s < v),
                   ("max_neck_angle", "neck_angle", "neck angle", "rad", lambda v, s: s > v))
               if trips(float(getattr(task, name)), start[key])]
    if tripped:
        warnings.warn(f"env.task: {'; '.join(tripped)}: the robot's start pose already terminates, so every episode "
                      "ends at its first step; set the threshold past the start pose's value", stacklevel=4)


def _leg_servo_gains(law: Controller, gains) -> tuple:
    """``law.servo_gains()``, checked to be two sequences of 12 gains >= 0, else a ``ValueError`` naming the law:
    MuJoCo took a negative kp (a servo that pushes away from its target) or NaN without a word, and a wrong count
    failed as an index error or was cut to the first 12. The values go on as given (float64 into the model)."""
    name = f"{type(law).__name__}.servo_gains()"
    if isinstance(gains, torch.Tensor) or not isinstance(gains, (tuple, list)) or len(gains) != 2:
        raise ValueError(f"{name} must give (kp, kv), two sequences of {robot.NUM_LEG_JOINTS} gains, got {gains!r}")
    per_joint(gains[0], robot.NUM_LEG_JOINTS, f"{name} kp [N·m/rad]", minimum=0.0)
    per_joint(gains[1], robot.NUM_LEG_JOINTS, f"{name} kv [N·m·s/rad]", minimum=0.0)
    return tuple(gains)


def _servo_spec(spec, joint_ids, gains):
    """Turn the motors of ``joint_ids`` into position servos with ``gains`` = (kp, kv) (PD inside every physics
    substep), force-limited to the joints' torque limits."""
    kp, kv = gains
    for i, j in enumerate(joint_ids):
        act = spec.actuator(robot.ACTUATOR_NAMES[j])
        limit = float(robot.TORQUE_LIMITS[j])
        act.set_to_position(kp=float(kp[i]), kv=float(kv[i]))
        act.ctrllimited = 0
        act.forcelimited = 1
        act.forcerange = [-limit, limit]
    return spec


def _check_leg_controller(law) -> Controller:
    """``law`` if it can drive the 12 leg joints, else a ``TypeError``/``ValueError`` saying what it lacks."""
    if not isinstance(law, Controller):
        raise TypeError(f"leg_controller must be a tocabi_torchrl.control.Controller, got {type(law).__name__}; "
                        "subclass Controller and implement compute() (docs/concepts/controllers.md)")
    if law.action_dim != robot.NUM_LEG_JOINTS:
        raise ValueError(f"leg_controller reads action_dim={law.action_dim} actions, but the env's action has "
                         f"{robot.NUM_LEG_JOINTS} leg entries (and one phase rate); set action_dim = 12")
    ctx = getattr(law, "ctx", None)
    if ctx is not None:  # it would go on computing for the other env, or fail there inside the law on other sizes
        raise ValueError(f"this {type(law).__name__} is already set up for another env ({ctx.num_envs} worlds on "
                         f"{ctx.device}): a controller holds one env's simulator and buffers; pass a new instance "
                         f"to each env")
    if law.servo and law.servo_gains() is None:
        raise ValueError(f"{type(law).__name__} has servo = True but servo_gains() gives None: the legs' actuators "
                         "in the model file are torque motors, which would take its targets [rad] as torques [N·m]; "
                         "return (kp, kv) from servo_gains(), or set servo = False and return torques")
    if not law.servo and law.servo_gains() is not None:
        # The env turns the leg motors into servos whenever a law gives gains: its torques [N·m] would be servo
        # targets [rad], and leg_torque would report them, not the servos' force.
        raise ValueError(f"{type(law).__name__} has servo = False (it returns torques) but servo_gains() gives gains: "
                         "the legs' motors would become position servos that take its torques [N·m] as targets "
                         "[rad]; return None from servo_gains(), or set servo = True and return targets")
    return law


def _check_motion_in_range(motion: ReferenceMotion, model, model_file: str) -> None:
    """``ValueError`` with :func:`robot.motion_range_problem`'s message, if it finds one: a reference motion whose
    joint targets leave a limited joint's range in ``model`` (the compiled ``model_file``)."""
    problem = robot.motion_range_problem(model, model_file, motion.joint_pos.cpu().numpy(), motion.source or "(arrays)")
    if problem is not None:
        raise ValueError(problem)


def _check_motion_period(motion: ReferenceMotion, dt: float) -> None:
    """``ValueError`` for a reference cycle shorter than two policy steps. The env samples the phase clock once a
    step, so such a cycle is aliased: phase, targets and stance jump to unrelated rows at every step, and training
    runs on without a word. The usual cause is a ``sample_rate`` in another unit (rows per ms, or a period in µs)."""
    if motion.period >= 2.0 * dt:
        return
    rate = 1.0 / motion.row_dt
    raise ValueError(f"reference motion {motion.source or '(arrays)'}: its cycle of {motion.num_rows} rows at "
                     f"{rate:g} rows/s lasts {motion.period:g} s, shorter than two policy steps ({2.0 * dt:g} s; one "
                     f"step is {dt:g} s): the env would skip through the cycle. sample_rate is rows per second; set "
                     f"it to at most {motion.cycle_rows / (2.0 * dt):g} so the cycle lasts {2.0 * dt:g} s or more")


class TocabiWalk(EnvBase):
    """TOCABI walking task over ``num_envs`` simulated worlds (mujoco-warp or C MuJoCo).

    Args:
        num_envs: number of parallel worlds N (> 0); None = the config's ``num_envs`` (4096).
        device: ``"cuda"``, ``"cuda:K"`` or ``"cpu"``. The physics backend is the config's ``backend``: ``"auto"``
            (default) runs mujoco-warp on CUDA and C MuJoCo on the CPU (``envs.config.CPU_DEFAULT_BACKEND``, the
            faster one there as measured); ``"warp"`` on the CPU is warp's CPU device (slow, compiles ~1 min).
        config: the env config tree (``TocabiWalkConfig``: sim, task, command, control; default: the ``default``
            training preset's task); keyword ``overrides`` replace single values by their flat names
            (``control_mode="torque"``, ``max_episode_steps=1000``, see ``envs.config.ENV_FLAT_PATHS``) or whole
            sections (``command=CommandConfig.reference()``).
        seed: seed of the env's own torch generator (initial phase, commands) and of the obstacles' per-world jitter
            (drawn once, at build: see ``BoxObstacle.jitter``); None = a random seed.
        leg_controller: a :class:`~tocabi_torchrl.control.Controller` for the 12 leg joints that replaces the one
            ``env.control.mode`` names (docs/concepts/controllers.md); it reads the action's first 12 entries. None =
            the config's.

    Action (N, 13): 12 leg commands in [-1, 1] (torques as a fraction of the limits, or PD targets, see the
    config's ``control.mode``) and one phase-rate action in [0, 1]. Actions outside the bounds are clipped; NaN
    entries are treated as 0 (checking for them would need a host synchronisation).

    Output keys and units: ``docs/concepts/env-and-signals.md``. ``done``/``terminated``/``truncated`` are (N, 1) bool;
    the reward of the bare env is 0 (the task reward is the ``TaskReward`` transform). Resets follow TorchRL's
    ``"_reset"`` mask, (N, 1) bool on ``device``, and touch only the flagged worlds, without host synchronisation; a
    step before the first reset raises ``RuntimeError``.
    """

    batch_locked = True
    #: The signals the env returns (docs/concepts/env-and-signals.md): its observation spec is made from this table, and
    #: :meth:`_observe` must compute exactly its rows enabled by the config (checked when the env is built). A
    #: subclass adds a signal with ``signal_table = SIGNALS.with_rows(Signal(...))`` and an ``_observe`` that
    #: adds it to ``super()._observe()``.
    signal_table: SignalTable = SIGNALS
    #: The physics (``WarpSim`` or ``MujocoSim``), used only through the backend interface.
    sim: SimBackend

    def __init__(
        self,
        num_envs: int | None = None,
        device: str | torch.device = "cuda",
        config: TocabiWalkConfig | None = None,
        seed: int | None = None,
        leg_controller: Controller | None = None,
        **overrides,
    ):
        if num_envs is not None:
            num_envs = positive_count(num_envs)
        device = check_device(device)
        if config is not None and not isinstance(config, TocabiWalkConfig):
            raise TypeError(f"config must be a TocabiWalkConfig, got {type(config).__name__}; pass settings as "
                            "keywords (TocabiWalk(num_envs=..., control_mode='torque')) or build one with "
                            "TocabiWalkConfig().with_flat(...)")
        cfg = config if config is not None else TocabiWalkConfig()
        if num_envs is not None:
            overrides["num_envs"] = num_envs
        if overrides:
            cfg = cfg.with_flat(**overrides)
        cfg.validate()
        num_envs = cfg.num_envs
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        self.cfg = cfg
        self.num_envs = num_envs
        control, sim = cfg.control, cfg.sim

        from ..value_rules import check_seed

        self._seed = check_seed(seed) if seed is not None else int(torch.randint(0, 2**31 - 1, ()).item())
        #: The control laws of the two joint groups, and the legs' actuator layer (``tocabi_torchrl.control``).
        if leg_controller is not None and control.torque_assist:
            raise ValueError("env.control.torque_assist adds its PD to the config's torque law, and leg_controller "
                             "replaces that law: set torque_assist False (or ppo.torque_assist 0), or leave "
                             "leg_controller out")
        self.leg_controller = (_check_leg_controller(leg_controller) if leg_controller is not None
                               else leg_law(control))
        self.upper_controller = upper_body_law(control)
        self.leg_actuators: ActuatorChain = leg_actuator_chain(control, sim.substeps)
        if self.leg_controller.servo and len(self.leg_actuators):
            raise ValueError(f"{type(self.leg_controller).__name__} writes servo targets, which the physics tracks "
                             "inside every substep; env.control.actuators act on torque commands only")
        spec = robot.load_spec(cfg.task.model_path)
        # Messages about a joint range name the file it came from (the motion or the model may be at fault).
        self._model_file = str(cfg.task.model_path if cfg.task.model_path is not None
                               else robot.asset_path("tocabi", "tocabi.xml"))
        _check_tocabi_spec(spec, cfg.task.model_path)
        _check_start_survives(cfg.task, cfg.task.model_path)
        gains = self.leg_controller.servo_gains()
        if gains is not None:
            spec = _servo_spec(spec, robot.LEG_JOINT_IDS, _leg_servo_gains(self.leg_controller, gains))
        obstacles = cfg.scene.obstacles
        check_clear_of_start(obstacles, cfg.task.model_path)
        #: The seed the obstacles' per-world offsets were drawn from (the build seed: ``set_seed`` does not move them).
        self.scene_seed = self._seed
        centres = world_obstacle_centres(obstacles, num_envs, self.scene_seed)
        mocap = dict(zip(add_obstacles(spec, obstacles), centres.transpose(1, 0, 2)))
        #: (num_envs, K, 3) float32 centre [m] of each world's K obstacle boxes (``cfg.scene.obstacles`` order,
        #: jitter included; the bottom face at z = 0), fixed at build.
        self.obstacle_pos = torch.as_tensor(centres, dtype=torch.float32, device=device)
        self.backend = resolve_backend(sim.backend, device)
        # A delayed actuator changes the legs' torques inside the step: the simulator applies them substep by substep.
        substep_ctrl = tuple(robot.LEG_JOINT_IDS) if self.leg_actuators.per_substep else ()
        # Per-world dynamics (env.dynamics): the model fields it draws get one row per world in the simulator, and
        # the reset runs the full pass (the reduced pass's start-state table holds the nominal model's sensors and
        # accelerations, which a world's own masses, damping, armature and friction change).
        world_fields = cfg.dynamics.sim_fields
        # A pool of start states drawn at build (env.sim.start_pool) has its sensors and accelerations in the
        # reduced pass's table, per world, so per-world dynamics and diverse starts keep the reduced pass with it.
        self._pool = cfg.start_pool
        reset_pass = "full" if world_fields and not self._pool else sim.reset_pass
        if self.backend == "warp":
            buffers = {k: v for k, v in (("nconmax", sim.nconmax), ("njmax", sim.njmax), ("nccdmax", sim.nccdmax))
                       if v is not None}
            sim_cfg = SimConfig(num_worlds=num_envs, device=str(device), substeps=sim.substeps,
                                reset_pass=reset_pass, substep_ctrl=substep_ctrl, per_world_fields=world_fields,
                                solver_iterations=sim.solver_iterations, **buffers)
            self.sim = WarpSim(sim_cfg, model=spec, mocap_pos=mocap)
        else:
            sim_cfg = SimConfig(num_worlds=num_envs, device="cpu", substeps=sim.substeps, threads=sim.threads,
                                substep_ctrl=substep_ctrl, per_world_fields=world_fields,
                                solver_iterations=sim.solver_iterations)
            self.sim = MujocoSim(sim_cfg, model=spec, mocap_pos=mocap)
        self.dt = self.sim.mj_model.opt.timestep * sim.substeps
        #: Each world's link masses, joint damping, armature and friction, drawn at every reset (``env.dynamics``,
        #: ``tocabi_torchrl.sim.dynamics``), or None when every range is off (nothing is drawn or written).
        self.dynamics: WorldDynamics | None = None
        if cfg.dynamics.enabled:
            self.dynamics = WorldDynamics(cfg.dynamics)
            self.dynamics.setup(self.sim)
        motion = cfg.task.motion
        self.motion = ReferenceMotion.default() if motion is None else ReferenceMotion.from_file(motion)
        _check_motion_in_range(self.motion, self.sim.mj_model, self._model_file)
        _check_motion_period(self.motion, self.dt)
        self.motion = self.motion.to(device)

        self.rng = torch.Generator(device=device)
        self.rng.manual_seed(self._seed)
        # The reset's per-episode draws read the seed from the device, so a captured step graph follows set_seed.
        self._seed_t = torch.tensor(hash_seed(self._seed), dtype=torch.int64, device=device)  # the draws' key
        self.command = VelocityCommand(cfg.command, num_envs, device, self.rng)
        #: The episode's kicks (``env.pushes``), or None when they are off.
        self.pushes: Pushes | None = None
        if cfg.pushes.count > 0:
            episode_s = cfg.task.max_episode_steps * self.dt
            if cfg.pushes.window[1] > episode_s + 1e-9:  # the later shares' kicks would never come
                raise ValueError(f"env.pushes.window ends at {cfg.pushes.window[1]:g} s, after the episode's "
                                 f"{episode_s:g} s (env.task.max_episode_steps {cfg.task.max_episode_steps} x "
                                 f"{self.dt * 1e3:g} ms): the kicks of its last shares would never come. End the "
                                 f"window by {episode_s:g} s or lengthen the episode")
            mass = float(self.sim.mj_model.body_subtreemass[self.sim.mj_model.body(robot.BASE_BODY).id])
            self.pushes = Pushes(cfg.pushes, num_envs, device, self.dt, mass)
            #: [kg] the body masses a "velocity" kick accelerates: the simulator's own per-world field (N, nbody),
            #: which env.dynamics rewrites in place at each reset, where it draws masses; the model's (nbody,) else.
            drawn = self.dynamics is not None and "body_mass" in self.dynamics.fields
            self._kick_mass = (self.dynamics.fields["body_mass"] if drawn else
                               torch.as_tensor(self.sim.mj_model.body_mass, dtype=torch.float32, device=device))
        self._base_body = self.sim.mj_model.body(robot.BASE_BODY).id
        #: (N,) bool: the worlds that get ``env.dynamics``, the actuator draws and the sensor noise; the others are
        #: the ideal robot (all True unless :meth:`set_randomized_worlds` says otherwise).
        self.randomized_worlds = torch.ones(num_envs, dtype=torch.bool, device=device)
        self._some_nominal = False
        #: Counts changes of the Python-side settings a captured step reads (today: whether some world is ideal,
        #: :meth:`set_randomized_worlds`); ``SyncFreeResetEnv`` captures its step again when it moves.
        self.graph_settings = 0
        #: Whether the legs' PD at the policy rate (the torque assist's, or ``pd_held``'s) reads the sensed joint
        #: positions (:meth:`sense_assist_joints`): from the start in ``pd_held`` mode, whose law is the robot's own.
        self.assist_reads_sensed = self.cfg.control.pd_senses_joints and hasattr(self.leg_controller, "set_q_offset")
        self._init_buffers()
        #: The reduced reset pass (``env.sim.reset_pass="reduced"``, mujoco-warp only): the start states, one per
        #: start row of the reference motion, are registered with the simulator here.
        # Diverse starts (random start velocities) are not in the start-state table unless drawn from a pool: they
        # take the full pass.
        self._reduced_reset = self.backend == "warp" and sim.reset_pass == "reduced"
        self._reduced_reset = self._reduced_reset and (self._pool > 0 or not cfg.task.diverse_starts)
        self._reduced_reset = self._reduced_reset and reset_pass == "reduced"  # see world_fields above
        # (nv,) the diverse starts' std per velocity coordinate [m/s, rad/s]: pelvis linear, none angular, joints.
        self._start_std = torch.zeros(self.sim.nv, dtype=torch.float32, device=device)
        self._start_std[:3], self._start_std[6:] = cfg.task.start_base_vel_std, cfg.task.start_joint_vel_std
        if self._pool:
            self._draw_pool()
        if self._reduced_reset:
            self._register_start_states()
        # Every per-episode draw of a reset, keyed on (seed, env, episode), in one hash pass: stream 0 the start
        # row and first command (and, with a pool, which of its world's start states), 1 the actuators, 2 the
        # dynamics, 16 the start velocities (Box-Muller pairs), 17 the kicks, 18 whether the episode is calm (no
        # kicks). The pool's draws replace 2 and 16.
        pooled = self._pool > 0
        self._draws = EpisodeDraws({
            0: 4 if pooled else 3, 1: self.leg_actuators.draws,
            2: self.dynamics.draws if self.dynamics is not None and not pooled else 0,
            16: 2 * (3 + robot.NUM_JOINTS) if cfg.task.diverse_starts and not pooled else 0,
            17: self.pushes.draws if self.pushes is not None else 0,
            18: self.pushes.calm_draws if self.pushes is not None else 0}, device)
        self._make_specs()

    # ------------------------------------------------------------------------------------------------ set-up
    def _init_buffers(self) -> None:
        n, dev, f32 = self.num_envs, self.device, torch.float32
        self._init_qpos = torch.as_tensor(robot.INIT_QPOS, dtype=f32, device=dev)
        self._init_qvel = torch.zeros(self.sim.mj_model.nv, dtype=f32, device=dev)
        self._act_low = torch.tensor([-1.0] * robot.NUM_LEG_JOINTS + [0.0], device=dev)
        self._act_high = torch.ones(ACTION_DIM, device=dev)
        self._leg_limits = torch.as_tensor(robot.LEG_TORQUE_LIMITS, dtype=f32, device=dev)
        mj = self.sim.mj_model
        leg_range = mj.jnt_range[[mj.joint(name).id for name in robot.JOINT_NAMES[robot.LEGS]]]
        self._leg_range = torch.as_tensor(leg_range, dtype=f32, device=dev)
        self._pd_kp = torch.as_tensor(self.cfg.control.pd_kp, dtype=f32, device=dev)
        upper = [mj.joint(name).id for name in robot.JOINT_NAMES[robot.UPPER_BODY]]
        contexts = (
            (self.leg_controller, robot.LEG_JOINT_IDS, self._leg_limits, self._leg_range),
            (self.upper_controller, tuple(range(robot.NUM_LEG_JOINTS, robot.NUM_JOINTS)),
             torch.as_tensor(robot.TORQUE_LIMITS[robot.UPPER_BODY], dtype=f32, device=dev),
             torch.as_tensor(mj.jnt_range[upper], dtype=f32, device=dev)),
        )
        for law, joints, limits, ranges in contexts:
            ctx = ControlContext(num_envs=n, device=dev, joint_ids=tuple(joints), torque_limits=limits,
                                 joint_range=ranges, dt=self.dt, sim=self.sim, motion=self.motion,
                                 model_file=self._model_file)
            law.setup(ctx)
            if law is self.leg_controller:
                self.leg_actuators.setup(ctx)
        # Leg controls a reset world starts with: no torque, or the servos' nominal target.
        self._reset_leg_ctrl = self.leg_controller.reset_command()
        self._init_rows = torch.as_tensor(self.motion.init_rows, dtype=torch.int64, device=dev)
        # Task state, (num_envs, ...): phase clock [s] (kept modulo the motion period), its start row, step count.
        self.time = torch.zeros(n, dtype=f32, device=dev)
        self.init_row = torch.zeros(n, dtype=torch.int64, device=dev)
        self.episode_step = torch.zeros(n, dtype=torch.int64, device=dev)
        # Signals of the last step, kept so that a partial reset can return every env's current values.
        self.applied_action = torch.zeros(n, ACTION_DIM, dtype=f32, device=dev)
        self.leg_torque = torch.zeros(n, robot.NUM_LEG_JOINTS, dtype=f32, device=dev)
        self.ref_joint_pos = torch.zeros(n, robot.NUM_JOINTS, dtype=f32, device=dev)
        self.ref_foot_force = torch.zeros(n, 2, dtype=f32, device=dev)
        self.stance = torch.zeros(n, dtype=torch.int64, device=dev)
        self._all = torch.ones(n, dtype=torch.bool, device=dev)
        # Episodes started per env: with the env index and the seed it keys the reset's random draws.
        self._env_ids = torch.arange(n, dtype=torch.int64, device=dev)
        self._leg_cmd_checked = False  # the leg controller's output shape, checked at the first step
        self._was_reset = False  # a host flag: a step before the first reset is refused (see _step)
        self.episode_count = torch.zeros(n, dtype=torch.int64, device=dev)
        #: With ``env.task.cycle_velocity``: the rolling error over each world's last gait cycle, whose mean at
        #: ``episode_step`` is the ``cycle_vel_error`` signal, (N, 2) [m/s]; None without it.
        self.cycle_velocity = None
        if self.cfg.task.cycle_velocity:
            self.cycle_velocity = CycleVelocityError(n, gait_cycle_steps(self.motion.period, self.dt), dev)

    def _draw_pool(self) -> None:
        """Draw each world's ``env.sim.start_pool`` start states, keyed on (build seed, env, state index) in streams
        of their own: the start row's index, the start velocities, the dynamics' uniforms (whichever are on). Like
        the obstacles' offsets, the pool stays that of the build seed (:attr:`pool_seed`): ``set_seed`` moves every
        per-episode draw, including which pooled state a reset picks, but not the pooled states themselves."""
        p, n, nv = self._pool, self.num_envs, self.sim.nv
        diverse, dyn = self.cfg.task.diverse_starts, self.dynamics is not None
        #: The seed the start pool was drawn from (the build seed).
        self.pool_seed = self._seed
        draws = EpisodeDraws({50: 1, 49: 2 * (3 + robot.NUM_JOINTS) if diverse else 0,
                              48: self.dynamics.draws if dyn else 0}, self.device)
        u = {stream: torch.empty(p, n, k, dtype=torch.float32, device=self.device)
             for stream, k in draws.streams.items()}  # (P, N, k) each, filled state by state (no P-fold peak)
        for k in range(p):
            state = draws(self._seed_t, self._env_ids, torch.full((n,), k, dtype=torch.int64, device=self.device))
            for stream, values in state.items():
                u[stream][k].copy_(values)
        rows = len(self._init_rows)
        #: (P, N) int64 each pooled start state's index into the motion's start rows.
        self._pool_pick = (u[50][..., 0] * rows).long().clamp_(max=rows - 1)
        #: (P, N, nv) each pooled start state's velocities (zero without diverse starts).
        self._pool_qvel = (self._start_velocities(u[49].flatten(0, 1)).reshape(p, n, nv) if diverse
                           else self._init_qvel.expand(p, n, nv).clone())
        #: (P, N, draws) each pooled start state's dynamics uniforms (``WorldDynamics.reset``), or None.
        self._pool_dyn = u[48] if dyn else None

    def _register_start_states(self) -> None:
        """Register with the simulator the start state of each start row, as :meth:`_reset` builds it: the initial
        pose at rest, leg controls ``_reset_leg_ctrl``, upper-body targets of the reference at the row's time 0. With
        a start pool, each world's pooled states instead, with their velocities and dynamics."""
        def start_ctrl(rows: torch.Tensor) -> torch.Tensor:  # (M,) motion rows -> (M, nu) controls at time 0
            q_ref = self.motion.joint_targets(torch.zeros(len(rows), dtype=torch.float32, device=self.device), rows)
            return torch.cat((self._reset_leg_ctrl.expand(len(rows), -1), q_ref[:, robot.UPPER_BODY]), dim=-1)

        if self._pool:
            p, n = self._pool, self.num_envs
            ctrl = start_ctrl(self._init_rows[self._pool_pick].reshape(-1)).reshape(p, n, -1)
            set_fields = None
            if self._pool_dyn is not None:
                def set_fields(k: int) -> None:
                    self.dynamics.reset(self._all, self._pool_dyn[k])
            self.sim.register_start_states(self._init_qpos.expand(p, -1), self._pool_qvel, ctrl, set_fields)
            return
        k = len(self._init_rows)
        self.sim.register_start_states(self._init_qpos.expand(k, -1), self._init_qvel.expand(k, -1),
                                       start_ctrl(self._init_rows))

    def _make_specs(self) -> None:
        n, dev = self.num_envs, self.device
        self.observation_spec = self.signal_table.composite(n, dev, self.signal_flags())
        self.action_spec = Bounded(
            low=self._act_low.expand(n, ACTION_DIM).clone(),
            high=self._act_high.expand(n, ACTION_DIM).clone(),
            shape=(n, ACTION_DIM),
            device=dev,
        )
        self.reward_spec = REWARD.spec(n, dev)
        self.done_spec = EPISODE_FLAGS.composite(n, dev)
        self._check_observe_matches_table()

    def signal_flags(self) -> dict[str, bool]:
        """The options that turn the signal table's conditional rows on (``Signal.requires``)."""
        extra = self.leg_controller.signals()
        return {"torque_assist": "leg_assist" in extra, "model_based": "leg_feedforward" in extra,
                "obstacles": bool(self.cfg.scene.obstacles), "pushes": self.pushes is not None,
                "cycle_velocity": self.cycle_velocity is not None}

    def _check_observe_matches_table(self) -> None:
        """Raise a clear error, once at construction, when :meth:`_observe` and the signal table disagree.

        Compares keys, shapes and dtypes only (metadata: no host synchronisation).
        """
        got = self._observe()
        rows = self.signal_table.enabled(self.signal_flags())
        want = {row.name for row in rows}
        extra, missing = sorted(set(got.keys()) - want), sorted(want - set(got.keys()))
        if extra or missing:
            raise KeyError(
                f"{type(self).__name__}._observe returns {extra} that the signal table lacks, and lacks {missing} "
                "that it lists; add a row to the table (tocabi_torchrl.signals.SIGNALS, or the class's signal_table) "
                "for every signal _observe computes, and compute every row"
            )
        for row in rows:
            value = got.get(row.name)
            if tuple(value.shape) != (self.num_envs, *row.shape) or value.dtype != row.dtype:
                raise ValueError(
                    f"{type(self).__name__}._observe returns {row.name!r} as {tuple(value.shape)} {value.dtype}, "
                    f"but the signal table says (num_envs, *{row.shape}) {row.dtype}; fix one of the two"
                )

    # ------------------------------------------------------------------------------------------------ stepping
    def _check_action(self, action: torch.Tensor | None) -> None:
        # Metadata only: shape, dtype and device checks never read device values.
        if not isinstance(action, torch.Tensor):
            raise KeyError(
                f"the step's tensordict has no 'action' tensor (got {type(action).__name__}): set 'action' to a "
                f"float32 tensor of shape (num_envs, {ACTION_DIM}) = ({self.num_envs}, {ACTION_DIM}), 12 leg "
                f"commands in [-1, 1] and one phase rate in [0, 1] per env, e.g. td.set('action', "
                f"env.action_spec.zero())"
            )
        if action.shape != (self.num_envs, ACTION_DIM):
            raise ValueError(
                f"action must have shape (num_envs, {ACTION_DIM}) = ({self.num_envs}, {ACTION_DIM}), got "
                f"{tuple(action.shape)}: 12 leg commands in [-1, 1] and one phase rate in [0, 1] per env"
            )
        if not action.is_floating_point():
            raise TypeError(f"action must be a floating-point tensor (float32), got {action.dtype}")
        if action.device != self.device:
            raise ValueError(f"action is on {action.device} but the env runs on {self.device}; move it with .to()")

    # No autograd in the step: the physics is not differentiable, and a control law with learnable parameters
    # (nn.Parameter gains) put its graph into the simulator's controls and the signals, which the C MuJoCo backend
    # failed to read ("Can't call numpy() on Tensor that requires grad") and which grew a graph across steps.
    @torch.no_grad()
    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action")
        self._check_action(action)
        if not self._was_reset:
            # Before it, the worlds hold the model's initial state with no command drawn (0 m/s, outside every
            # range), no start row and the upper-body servos at 0: a step ran from there without a word.
            raise RuntimeError("TocabiWalk.step before the first reset: no episode has started (no start row or "
                               "velocity command drawn yet); call env.reset() first (rollout() and collectors do)")
        action = action.detach()  # a policy's output: its graph must not reach the sim buffers
        a = torch.nan_to_num(action.to(torch.float32), nan=0.0).clamp(self._act_low, self._act_high)

        # Reference at the pre-step clock: targets for the whole step, row for force reference and stance.
        row, q_ref = self.motion.row_and_targets(self.time, self.init_row)
        self.command.update(self.episode_step)
        rate = 1.0 + self.cfg.task.phase_rate_gain * a[:, -1]

        # The controllers (tocabi_torchrl.control) map the action to joint commands; the legs' torques pass
        # through the actuator layer on their way to the joints.
        nl = robot.NUM_LEG_JOINTS
        legs = ControlInput(action=a[:, robot.LEGS], q=self.sim.qpos[:, 7:7 + nl], qd=self.sim.qvel[:, 6:6 + nl],
                            q_ref=q_ref[:, robot.LEGS], time=self.time, init_row=self.init_row, rate=rate)
        leg_cmd = self.leg_controller.compute(legs)
        if not self._leg_cmd_checked:  # once, eagerly (the first step runs before any capture): a host flag
            self._check_leg_command(leg_cmd)
        leg_out = self._actuate(leg_cmd, legs)
        upper = ControlInput(action=a[:, nl:nl], q_ref=q_ref[:, robot.UPPER_BODY], time=self.time,
                             init_row=self.init_row, rate=rate)
        ctrl = self.sim.ctrl
        ctrl[:, robot.LEGS] = leg_out
        ctrl[:, robot.UPPER_BODY] = self.upper_controller.compute(upper)
        if self.pushes is not None:
            if self.pushes.cfg.kind == "velocity":  # every body: its (drawn) mass × the kick's acceleration
                self.sim.xfrc_applied[:, :, :2] = self.pushes.body_forces(self.episode_step, self._kick_mass)
            else:
                self.sim.xfrc_applied[:, self._base_body, :2] = self.pushes.at(self.episode_step)
        self.sim.step()

        # Task state is updated in place (never rebound): a captured CUDA graph of this step keeps writing to the
        # same tensors on every replay (see envs.autoreset).
        self.time.copy_(torch.remainder(self.time + self.dt * rate, self.motion.period))
        self.episode_step.add_(1)
        self.applied_action.copy_(a)
        # What the history and the torque rewards see of the legs: the action itself, or (torque assist,
        # model_based) the commanded torque over the limits, so that a policy that commands the same torques gets
        # the same observations and rewards whatever the law's parametrisation.
        leg_applied = self.leg_controller.applied_action(legs, leg_cmd)
        if leg_applied is not legs.action:
            self.applied_action[:, robot.LEGS].copy_(leg_applied)
        # The torque the legs got: the servos' force, or the actuator layer's output (its last substep's).
        self.leg_torque.copy_(self.sim.applied_actuator_force[:, robot.LEGS] if self.leg_controller.servo
                              else leg_out)
        self.ref_joint_pos.copy_(q_ref)
        self.ref_foot_force.copy_(self.motion.force_reference(row))
        self.stance.copy_(self.motion.stance_at(row))
        if self.cycle_velocity is not None:
            velocity = heading_velocity(_finite(self.sim.qpos[:, 3:7]), _finite(self.sim.qvel[:, :3]))
            self.cycle_velocity.update(velocity, self.command.value, self.episode_step)

        sim, cfg = self.sim, self.cfg.task
        flags = termination_flags(
            pelvis_height=sim.base_pos[:, 2],
            neck_height=sim.neck_pos[:, 2],
            neck_quat=sim.neck_quat,
            forbidden_ground_contact=sim.forbidden_ground_contact,
            self_collision=sim.self_collision,
            healthy=sim.healthy,
            min_pelvis_height=cfg.min_pelvis_height,
            min_neck_height=cfg.min_neck_height,
            max_neck_angle=cfg.max_neck_angle,
            use_forbidden_contact=cfg.terminate_on_forbidden_contact,
            use_self_collision=cfg.terminate_on_self_collision,
        )
        terminated = flags["any"].unsqueeze(-1)
        truncated = (self.episode_step >= cfg.max_episode_steps).unsqueeze(-1) & ~terminated
        out = self._observe()
        out.update(
            {
                "reward": torch.zeros(self.num_envs, 1, device=self.device),
                "terminated": terminated,
                "truncated": truncated,
                "done": terminated | truncated,
            }
        )
        return out

    def _actuate(self, command: torch.Tensor, inp: ControlInput) -> torch.Tensor:
        """(N, 12) what goes into the legs' controls: a servo's targets or an ideal actuator's torques as they are,
        else the actuator layer's output; a delayed layer's per-substep torques (N, S, 12) go to the simulator's
        ``substep_ctrl``, and its last substep's torque is returned."""
        if not len(self.leg_actuators):
            return command
        out = self.leg_actuators(command, inp)
        if self.leg_actuators.per_substep:
            self.sim.substep_ctrl.copy_(out)
            return out[:, -1]
        return out

    @property
    def computed_torque(self):
        """The ``model_based`` mode's feed-forward law (``envs.model_based.ComputedTorque``), or None."""
        return getattr(self.leg_controller, "law", None)

    @property
    def leg_assist(self) -> torch.Tensor | None:
        """(N, 12) the torque assist's ``leg_assist`` signal (``AssistedTorque``), or None in the other modes."""
        return self.leg_controller.signals().get("leg_assist")

    @property
    def leg_feedforward(self) -> torch.Tensor | None:
        """(N, 12) [N·m] the ``model_based`` mode's τ_ff, or None in the other modes."""
        return self.leg_controller.signals().get("leg_feedforward")

    @property
    def assist_scale(self) -> torch.Tensor | None:
        """β of the torque assist, a 0-d device tensor (``AssistedTorque.assist_scale``), or None without it."""
        return getattr(self.leg_controller, "assist_scale", None)

    @property
    def leg_torque_limits(self) -> torch.Tensor:
        """(12,) N·m, the leg joints' torque limits on the env's device (the scale of a torque-mode action)."""
        return self._leg_limits

    def assist_gain(self, beta: float | torch.Tensor) -> torch.Tensor:
        """(12,) N·m of leg torque per unit of leg action at assist scale ``beta``: ``(1 − β)·limit + β·pd_action_scale
        ·pd_kp`` (the torque limit at β = 0, the PD's stiffness times the residual range at β = 1)."""
        return (1.0 - beta) * self._leg_limits + beta * self.cfg.control.pd_action_scale * self._pd_kp

    def set_torque_assist(self, scale: float) -> None:
        """Set β of the torque assist (config ``torque_assist``) for the following steps; 0 = pure torque."""
        if not self.cfg.control.torque_assist:
            raise RuntimeError("set_torque_assist needs an env built with torque_assist=True (torque mode)")
        if not 0.0 <= float(scale) <= 1.0:
            raise ValueError(f"torque assist scale must be in [0, 1], got {scale!r}")
        self.leg_controller.set_beta(float(scale))

    def sense_assist_joints(self, on: bool = True) -> None:
        """Make the torque assist's PD (or ``pd_held`` mode's) read the leg joint positions the policy senses, biased
        encoders included (``on``), or the true ones again.

        The env's ``SensorNoise`` transform (``transforms.sensor_noise``), which draws each world's encoder bias at
        every reset, then writes the legs' part of it into the PD's offset too (``leg_controller.q_offset``, (N, 12)
        rad): the very values the observation carries, episode by episode, with no second draw. Ideal worlds
        (:meth:`set_randomized_worlds`) read the true positions, as their sensors are exact; without encoder biases
        the offset stays 0. It takes effect at each world's next reset.

        Why (``ppo.assist_pd_sensed``): the fade copies the assisted policy into a torque policy that sees only its
        biased encoders; a PD on the true positions is feedback it cannot copy (the TOCABI lab's ±π/100 rad is up
        to 0.2-0.7 of a leg's torque limit through the PD's stiffness), and the robust preset's fifth run lost its
        kick recoveries where the PD faded (docs/training/robust/h200_run5).

        >>> import dataclasses
        >>> from tocabi_torchrl import make_env
        >>> from tocabi_torchrl.envs import TocabiWalkConfig
        >>> from tocabi_torchrl.transforms import SensorNoiseConfig
        >>> cfg = TocabiWalkConfig()
        >>> cfg = dataclasses.replace(cfg, control=dataclasses.replace(cfg.control, mode="torque", torque_assist=True))
        >>> env = make_env(num_envs=2, device="cpu", config=cfg, sensor_noise=SensorNoiseConfig.tocabi_lab())
        >>> env.base_env.sense_assist_joints()
        >>> _ = env.reset()
        >>> offset = env.base_env.leg_controller.q_offset  # (num_envs, 12) rad
        >>> tuple(offset.shape), bool(offset.abs().max() <= 3.1416 / 100), bool(offset.abs().sum() > 0)
        ((2, 12), True, True)
        """
        if not hasattr(self.leg_controller, "set_q_offset"):
            raise RuntimeError("sense_assist_joints needs an env built with torque_assist=True (torque mode) or in "
                               "pd_held mode: only their PD at the policy rate reads joint positions")
        if bool(on) != self.assist_reads_sensed:
            # The SensorNoise transform reads the flag in the masked reset, which a captured step holds: capture again.
            self.graph_settings += 1
        self.assist_reads_sensed = bool(on)
        if not on:
            self.leg_controller.set_q_offset(self._all, torch.zeros_like(self.leg_controller.q_offset))

    def _observe(self) -> TensorDict:
        """Current signals of every env as fresh tensors (never views of simulator memory).

        A world whose physics went non-finite (``healthy`` False; it terminates) reports 0 for every NaN/inf value,
        so its terminal observation, and everything transforms compute from it, stays finite.
        """
        sim = self.sim
        qpos, qvel = _finite(sim.qpos), _finite(sim.qvel)
        base_quat = qpos[:, 3:7].clone()
        signals = {
            "joint_pos": qpos[:, 7:].clone(),
            "joint_vel": qvel[:, 6:].clone(),
            "base_pos": qpos[:, :3].clone(),
            "base_quat": base_quat,
            "base_lin_vel": quat_rotate_inverse(base_quat, qvel[:, :3]),
            "base_ang_vel": qvel[:, 3:6].clone(),
            "neck_pos": _finite(sim.neck_pos),
            "neck_quat": _finite(sim.neck_quat),
            "foot_pos": _finite(sim.foot_pos),
            "foot_force": _finite(sim.foot_force),
            "foot_torque": _finite(sim.foot_torque),
            "foot_contact": sim.foot_contact.clone(),
            "phase": self.motion.phase(self.time, self.init_row).unsqueeze(-1),
            "ref_joint_pos": self.ref_joint_pos.clone(),
            "ref_foot_force": self.ref_foot_force.clone(),
            "stance": self.stance.unsqueeze(-1).clone(),
            "command": self.command.value.clone(),
            "applied_action": self.applied_action.clone(),
            "leg_torque": _finite(self.leg_torque),
            "episode_step": self.episode_step.unsqueeze(-1).clone(),
            "healthy": sim.healthy.unsqueeze(-1).clone(),
        }
        for name, value in self.leg_controller.signals().items():
            signals[name] = _finite(value)
        if self.cfg.scene.obstacles:
            signals["obstacle_contact"] = sim.obstacle_contact.clone()
        if self.pushes is not None:
            signals["kick_age"], signals["kick_speed"] = self.pushes.latest(self.episode_step)
        if self.cycle_velocity is not None:  # 0 right after a reset: the world's sum is 0
            signals["cycle_vel_error"] = self.cycle_velocity.mean(self.episode_step)
        return TensorDict(signals, batch_size=self.batch_size, device=self.device)

    # ------------------------------------------------------------------------------------------------ resets
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = self._reset_mask(tensordict)  # checked before any state moves: a refused reset changes nothing
        if not self._was_reset and mask is not self._all and not bool(mask.all()):
            # One read, at the first reset only: a first reset that left worlds out let them step from the model's
            # initial state with no command drawn, which the step-before-reset refusal exists to catch.
            raise ValueError("the env's first reset must restart every world (its '_reset' mask flags "
                             f"{int(mask.sum())} of {self.num_envs}); call env.reset() without a mask first")
        seed = kwargs.pop("seed", None)
        if seed is not None:  # reset(seed=s) is set_seed(s) then the reset (it was ignored, without a word)
            self._set_seed(seed)
        # Random start row and first command from (seed, env, episode): identical whichever reset path runs.
        draws = self._draws(self._seed_t, self._env_ids, self.episode_count)
        u = draws[0]
        if self._pool:  # one of the world's pooled start states (row, velocities, dynamics): state k of world w
            state = (u[:, 3] * self._pool).long().clamp_(max=self._pool - 1)
            flat = state * self.num_envs + self._env_ids
        if self.leg_actuators.draws:  # each episode's actuator parameters, keyed like the start row
            self.leg_actuators.reset(mask, draws[1])
        if self.dynamics is not None:  # each episode's masses, damping, armature and friction, keyed the same way
            self.dynamics.reset(mask, self._pool_dyn.flatten(0, 1)[flat] if self._pool else draws[2])
        if self._some_nominal:  # the ideal robot in the worlds set_randomized_worlds left out (same draws above)
            ideal = mask & ~self.randomized_worlds
            self.leg_actuators.nominal(ideal)
            if self.dynamics is not None:
                self.dynamics.nominal(ideal)
        if self.pushes is not None:
            self.pushes.reset(mask, draws[17], draws.get(18))
        if self._pool:
            qvel, pick = self._pool_qvel.flatten(0, 1)[flat], self._pool_pick.flatten()[flat]
        else:
            qvel = self._start_velocities(draws[16]) if self.cfg.task.diverse_starts else self._init_qvel
            pick = (u[:, 0] * len(self._init_rows)).long().clamp_(max=len(self._init_rows) - 1)
        self.episode_count.add_(mask.long())
        torch.where(mask, self._init_rows[pick], self.init_row, out=self.init_row)
        self.time.masked_fill_(mask, 0.0)
        self.episode_step.masked_fill_(mask, 0)
        m = mask.unsqueeze(-1)
        self.applied_action.masked_fill_(m, 0.0)
        self.leg_torque.masked_fill_(m, 0.0)
        self.leg_controller.reset(mask)
        self.upper_controller.reset(mask)
        self.command.reset(mask, u[:, 1:3])
        if self.cycle_velocity is not None:
            self.cycle_velocity.reset(mask)
        # Upper-body servos start on the initial pose so the reset state's forward pass sees no PD transient.
        row, q_ref = self.motion.row_and_targets(self.time, self.init_row)
        torch.where(m, q_ref, self.ref_joint_pos, out=self.ref_joint_pos)
        torch.where(m, self.motion.force_reference(row), self.ref_foot_force, out=self.ref_foot_force)
        torch.where(mask, self.motion.stance_at(row), self.stance, out=self.stance)
        if self._reduced_reset:  # the same start state, registered as row `pick` or pooled state (see above)
            self.sim.reset_to_start(mask, state if self._pool else pick)
        else:
            upper = self.ref_joint_pos[:, robot.UPPER_BODY]
            ctrl = torch.cat((self._reset_leg_ctrl.expand(self.num_envs, -1), upper), dim=-1)
            self.sim.reset(mask, self._init_qpos, qvel, ctrl)
        out = self._observe()
        false = torch.zeros(self.num_envs, 1, dtype=torch.bool, device=self.device)
        out.update({"terminated": false, "truncated": false.clone(), "done": false.clone()})
        self._was_reset = True
        return out

    def _reset_mask(self, tensordict: TensorDictBase | None) -> torch.Tensor:
        """(num_envs,) bool: the worlds a reset restarts, every world or the input's ``"_reset"`` flags, which must be
        (num_envs, 1) or (num_envs,) bool on the env's device. Metadata only, no host synchronisation. A float or int
        mask was cast to bool without a word (0.5 restarted its world), a wrong size failed in a reshape, and a mask
        on another device failed part way through the reset, in an op that named neither."""
        if tensordict is None or "_reset" not in tensordict.keys():
            return self._all
        flags, n = tensordict.get("_reset"), self.num_envs
        shape = tuple(flags.shape) if isinstance(flags, torch.Tensor) else None
        if shape not in ((n, 1), (n,)) or flags.dtype != torch.bool or flags.device != self.device:
            got = f"{shape} {flags.dtype} on {flags.device}" if shape is not None else type(flags).__name__
            raise ValueError(f"the reset's '_reset' mask must be a ({n}, 1) bool tensor on {self.device}, one flag per "
                             f"world (True: restart it), got {got}; e.g. td.set('_reset', done) with the step's "
                             "(num_envs, 1) done flags")
        return flags.reshape(n)

    def _start_velocities(self, u: torch.Tensor) -> torch.Tensor:
        """(M, nv) start velocities from (M, 2·(3 + joints)) uniforms (one row per world's episode, or per pooled
        state): N(0, start_base_vel_std) on the pelvis's linear velocity, N(0, start_joint_vel_std) on every joint,
        none on its angular velocity."""
        z = box_muller(u)  # u: (M, 2·(3 + joints)) uniforms: stream 16's, or the pool's stream 49's
        qvel = torch.zeros(u.shape[0], self.sim.nv, dtype=torch.float32, device=self.device)
        qvel[:, :3], qvel[:, 6:] = z[:, :3], z[:, 3:]
        return qvel * self._start_std

    def set_randomized_worlds(self, worlds: torch.Tensor) -> None:
        """Choose which worlds are randomised: ``worlds`` (N,) bool, True for a world that gets ``env.dynamics``, the
        actuator draws (``env.control.actuators``) and the sensor noise of ``transforms.sensor_noise``; a False world
        is the ideal robot (the model's dynamics, ideal actuators, exact sensors) from its next reset on. Kicks are
        set per world with ``pushes.world_scale``. One env can so hold nominal and randomised robots side by side
        (the robust gait test runs its cases in one batch). In place: a captured step follows it
        (``SyncFreeResetEnv`` captures again when the first world turns ideal or the last back).

        >>> import torch
        >>> from tocabi_torchrl import make_env
        >>> from tocabi_torchrl.sim.dynamics_config import DynamicsRandomization
        >>> env = make_env(num_envs=2, device="cpu", seed=0, dynamics=DynamicsRandomization(mass_scale=(0.8, 1.2)))
        >>> env.base_env.set_randomized_worlds(torch.tensor([True, False]))
        >>> _ = env.reset()
        >>> scale = env.base_env.dynamics.mass_scale[:, 1]
        >>> bool(scale[0] != 1.0), float(scale[1])
        (True, 1.0)
        """
        if not isinstance(worlds, torch.Tensor) or worlds.dtype != torch.bool or tuple(worlds.shape) != (
                self.num_envs,):
            raise ValueError(f"set_randomized_worlds takes a ({self.num_envs},) bool tensor (one flag per world), "
                             f"got {getattr(worlds, 'dtype', type(worlds).__name__)} "
                             f"{tuple(getattr(worlds, 'shape', ()))}")
        if self._pool and self._pool_dyn is not None and not bool(worlds.all()):
            raise ValueError(f"set_randomized_worlds: this env draws its robots from a start pool (env.sim.start_pool="
                             f"{self._pool}), whose states hold randomised dynamics; build the env with "
                             "env.sim.start_pool=0 to hold ideal robots beside randomised ones")
        self.randomized_worlds.copy_(worlds.to(self.device))
        some_nominal = not bool(worlds.all())  # a host read, here at set-up, never in a step
        if some_nominal != self._some_nominal:
            # The reset's nominal() branch is Python: a step captured before this would keep giving the new
            # ideal worlds drawn dynamics and actuators (only the sensor flags, a tensor, would follow).
            self.graph_settings += 1
        self._some_nominal = some_nominal

    def set_push_scale(self, scale: float) -> None:
        """Scale every kick of ``env.pushes`` by ``scale`` in [0, 1] from the next step on (a curriculum; in place,
        so a captured step follows it)."""
        if self.pushes is None:
            raise RuntimeError("set_push_scale needs an env built with pushes (env.pushes.count > 0)")
        if not 0.0 <= float(scale) <= 1.0:
            raise ValueError(f"push scale must be in [0, 1], got {scale!r}")
        self.pushes.scale.fill_(float(scale))

    def _reset_check_done(self, tensordict, tensordict_reset) -> None:
        # TorchRL re-checks that reset envs are not done with `done.any()`, a host synchronisation on every reset.
        # `_reset` returns all-False done flags by construction, so the check can only pass; skip it.
        return None

    def close(self, *, raise_if_closed: bool = True) -> None:
        """Release the simulator's worker threads (the CPU backend's pool; they went only at garbage collection),
        then close as torchrl does. A closed env still steps, on the calling thread."""
        release = getattr(self.sim, "close", None)
        if release is not None:
            release()
        super().close(raise_if_closed=raise_if_closed)

    def _set_seed(self, seed: int | None) -> None:
        if seed is not None:
            from ..value_rules import check_seed

            self._seed = check_seed(seed)
            self.rng.manual_seed(self._seed)
            self._seed_t.fill_(hash_seed(self._seed))
            # Start rows and first commands are keyed on (seed, env, episode number): restart the numbering so that
            # set_seed(s) followed by reset() repeats the same episodes.
            self.episode_count.zero_()
            self.command.restart()  # a ramp that survives resets would carry the old episodes' commands over

    def to(self, device) -> TocabiWalk:
        """Only the device it was built on: the simulator's worlds and the env's state live there, and moving the
        specs alone would fail later, inside a step. Build the env on the other device instead."""
        target = check_device(device)  # "cpu:0" is the cpu
        if target.type == "cuda" and target.index is None and self.device.type == "cuda":
            target = torch.device("cuda", torch.cuda.current_device())  # where EnvBase.to would put "cuda"
        if target != self.device:
            raise RuntimeError(f"TocabiWalk cannot move from {self.device} to {target}: its simulator and state "
                               f"live where it was built; build it there, e.g. TocabiWalk(device={str(target)!r}) or "
                               "make_env(device=...)")
        return super().to(self.device)  # the same device, as the env names it (not "cpu:0" for "cpu")

    def _check_leg_command(self, cmd) -> None:
        """A leg controller's output must be (num_envs, 12) per-world commands: a (1, 12) one broadcast to every world
        without a word, a wrong width failed in the ctrl write without naming the controller."""
        want = (self.num_envs, robot.NUM_LEG_JOINTS)
        shape = tuple(cmd.shape) if isinstance(cmd, torch.Tensor) else type(cmd).__name__
        if shape != want:
            raise ValueError(f"leg controller {type(self.leg_controller).__name__}.compute returned {shape}; it must "
                             f"return a {want} tensor, one command per world and leg joint (docs/concepts/"
                             "controllers.md)")
        self._leg_cmd_checked = True

    def cuda_graph_generators(self) -> list[torch.Generator]:
        """The CUDA generators a step draws from besides torch's default one (command resampling), which a
        captured step graph must advance on every replay."""
        return [self.rng] if self.rng.device.type == "cuda" else []

    def recorded_graphs(self) -> list:
        """The simulator's recorded physics graphs a step launches, which a captured step graph must hold
        (:func:`tocabi_torchrl.cuda_graphs.capture_graph`)."""
        return self.sim.recorded_graphs()

    @property
    def period(self) -> float:
        """Reference-motion cycle period [s]."""
        return float(self.motion.period)

    def __repr__(self) -> str:
        return (f"TocabiWalk(num_envs={self.num_envs}, device={self.device}, backend={self.backend!r}, control_mode="
                f"{self.cfg.control.mode!r}, dt={self.dt:.4f} s, period={self.period:.4f} s)")

