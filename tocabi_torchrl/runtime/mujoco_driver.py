"""Sim-to-sim: C MuJoCo TOCABI robots driven through :class:`PolicyRuntime`, with the gait-test metrics.

Imports numpy, mujoco, the runtime and the numpy-only ``robot`` facts (no torch). The robot model is the authored
``assets/tocabi/tocabi.xml`` or any MJCF with the contract's joint, actuator, body and sensor names, e.g. the
reference ``dyros_tocabi.xml`` with its mesh geoms removed (:func:`strip_meshes`). Actuators are set up from the
contract: leg motors stay motors where the legs are commanded in torques (the torque and pd_held modes) and become
position servos with the contract's gains in the servo modes (pd, pd_reference); upper-body motors (the reference
model has no servos) become position servos with ``upper_body.kp``/``kv``, force-limited to their ctrlrange.

Each control period repeats the training env's simulator step (``sim/mujoco_backend.py``): ``substeps`` × ``mj_step``
with the command held, then ``mj_forward`` with its constraint solution kept as the next warm start. Terminations are
the env's (``envs/termination.py``, ``sim/contacts.py``), found here from the contact list, plus the training env's
health check: a robot whose MuJoCo warning counters fired (C MuJoCo resets a diverged world itself) has fallen.

Optionally (:func:`run_sim2sim`'s ``randomize``, ``pushes``, ``start_velocity``) each robot draws the training env's
randomisation at its reset, in numpy (:mod:`.randomization`): an actuator layer whose torque is written into ``ctrl``
substep by substep, its own ``MjModel`` copy with drawn dynamics, sensor biases and noise on what the policy
observes, kicks through ``MjData.xfrc_applied`` (on the pelvis, or on every body by its mass for a velocity kick),
and start velocities.
"""

from __future__ import annotations

import math
import numbers
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Callable

import mujoco
import numpy as np

from .. import robot  # numpy-only (mujoco imported in its functions): robot facts, model-file checks
from ..value_rules import check_seed
from . import randomization as rnd
from .policy import PolicyRuntime, RobotState

__all__ = ["HEALTH_WARNINGS", "RANDOMIZE", "Sim2SimResult", "build_model", "missing_names", "resolve_randomization",
           "run_sim2sim", "strip_meshes"]

#: The named randomisations of :func:`run_sim2sim` (``recipes/sim2sim.py --randomize``): none, what the contract's
#: ``trained_under`` section states, or the TOCABI lab's set (``runtime.randomization.TOCABI_LAB``).
RANDOMIZE = ("none", "trained", "tocabi_lab")

_W = mujoco.mjtWarning
#: The warnings of ``sim/mujoco_health.MUJOCO_HEALTH_WARNINGS`` (listed again because importing ``sim`` loads torch;
#: ``tests/test_runtime.py`` checks the two agree): dropped contacts or constraint rows, and MuJoCo's own reset of a
#: diverged world to the model's default pose, after which the state is finite again.
HEALTH_WARNINGS: tuple[mujoco.mjtWarning, ...] = (
    _W.mjWARN_CONTACTFULL, _W.mjWARN_CNSTRFULL, _W.mjWARN_BADQPOS, _W.mjWARN_BADQVEL, _W.mjWARN_BADQACC,
)


def strip_meshes(path: str | os.PathLike) -> str:
    """MJCF text of ``path`` without mesh assets and visual (``class="viz"`` or mesh) geoms, and without the
    inertial ``quat`` that modern MuJoCo rejects beside ``fullinertia`` (the reference model's case; the spec says
    meshes are visual only)."""
    root = ET.parse(path).getroot()
    compiler = root.find("compiler")
    if compiler is not None:
        compiler.attrib.pop("meshdir", None)
    for parent in root.iter():
        for child in list(parent):
            if child.tag == "mesh" or (child.tag == "geom" and (child.get("class") == "viz" or "mesh" in child.attrib)):
                parent.remove(child)
            elif child.tag == "inertial" and "fullinertia" in child.attrib:
                child.attrib.pop("quat", None)
    return ET.tostring(root, encoding="unicode")


def missing_names(spec: mujoco.MjSpec, contract: dict) -> list[str]:
    """The names the contract needs that ``spec`` lacks, as ``"actuator 'L_Knee_Motor'"`` etc.: its joints, their
    ``_Motor`` actuators, the base and neck bodies and the foot F/T sensors (empty for a TOCABI model)."""
    rob = contract["robot"]
    needed = {
        "joint": rob["joint_names"],
        "actuator": [n.replace("_Joint", "_Motor") for n in rob["joint_names"]],
        "body": [rob["base_body"], rob["neck_body"]],
        "sensor": [*rob["foot_force_sensors"], *rob["foot_torque_sensors"]],
    }
    return [f"{kind} {n!r}" for kind, names in needed.items() for n in names if getattr(spec, kind)(n) is None]


def build_model(contract: dict, model_path: str | os.PathLike, remove_meshes: bool = False) -> mujoco.MjModel:
    """Compile ``model_path`` with the actuators the contract's control mode needs (see the module docstring).

    Raises ``ValueError`` when MuJoCo cannot read ``model_path`` as a model, naming what the model lacks when it is
    not a TOCABI model with the contract's names, when it reads its radian joint ranges as degrees (no
    ``<compiler angle="radian">``): every range would be 180/π times too narrow and leave out the start pose, or
    when a joint range leaves out the contract's start pose (``robot.initial_qpos``) in any unit."""
    try:
        spec = (mujoco.MjSpec.from_string(strip_meshes(model_path)) if remove_meshes
                else mujoco.MjSpec.from_file(str(model_path)))
    except ValueError as err:  # MuJoCo's own words ("could not find decoder for resource ...") name no fix
        detail = " ".join(str(err).split())  # an XML error spans lines
        raise ValueError(f"{model_path}: MuJoCo cannot read it as an MJCF model ({detail}); pass a TOCABI MJCF "
                         "(.xml)") from err
    missing = missing_names(spec, contract)
    if missing:
        shown = ", ".join(missing[:8]) + (", ..." if len(missing) > 8 else "")
        raise ValueError(f"{model_path} lacks {len(missing)} name(s) the policy contract needs ({shown}): pass a "
                         "TOCABI MJCF with the contract's robot.joint_names, a <joint>_Motor actuator for each, "
                         "robot.base_body, robot.neck_body and the robot.foot_force_sensors/foot_torque_sensors")
    rob, leg = contract["robot"], contract["action"]["leg"]
    # As robot.load_model does for the env: the joint limits would hold every robot away from its start pose, and
    # nothing after this would name the file or its unit.
    problem = robot.angle_unit_problem(spec, str(model_path), rob["joint_names"], rob["initial_qpos"][7:],
                                       "the contract's robot.initial_qpos")
    if problem is not None:
        raise ValueError(problem)
    # leg.kind: the contract's check holds it to what the control mode commands (pd_held's PD runs in the runtime
    # and sends torques).
    position = leg["kind"] == "position"
    motors = [n.replace("_Joint", "_Motor") for n in rob["joint_names"]]
    for i, name in enumerate(motors[: len(rob["leg_joint_names"])]):
        act = spec.actuator(name)
        if position:
            limit = float(leg["torque_limits_nm"][i])
            act.set_to_position(kp=float(leg["kp"][i]), kv=float(leg["kv"][i]))
            act.ctrllimited, act.forcelimited, act.forcerange = 0, 1, [-limit, limit]
    upper = contract["upper_body"]
    for i, name in enumerate(motors[len(rob["leg_joint_names"]) :]):
        act = spec.actuator(name)
        if act.gaintype == mujoco.mjtGain.mjGAIN_FIXED and act.biastype == mujoco.mjtBias.mjBIAS_NONE:  # a motor
            limit = float(max(abs(act.ctrlrange[0]), abs(act.ctrlrange[1])))
            act.set_to_position(kp=float(upper["kp"][i]), kv=float(upper["kv"][i]))
            act.ctrllimited, act.forcelimited, act.forcerange = 0, 1, [-limit, limit]
    model = spec.compile()
    for j, name in enumerate(rob["joint_names"]):
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid < 0 or model.jnt_qposadr[jid] != 7 + j or model.actuator(motors[j]).id != j:
            raise ValueError(f"{model_path}: joint/actuator {name!r} is missing or out of the contract's order")
    # A radian model whose ranges leave out the start pose (a knee limited to ±0.5 rad, the pose bending it 0.6 rad)
    # ran on, every robot held off its start pose by the limit, and reported the limit's gait as the policy's.
    problem = robot.initial_pose_range_problem(model, str(model_path), rob["joint_names"], rob["initial_qpos"][7:],
                                               "the contract's robot.initial_qpos")
    if problem is not None:
        raise ValueError(problem)
    return model


@dataclass
class Sim2SimResult:
    """Gait-test metrics (as ``evaluation/gait_test.py`` defines them) of a sim-to-sim run; distances in m."""

    num_robots: int
    #: The simulated time: whole control periods, the requested seconds rounded to the nearest.
    seconds: float
    survival: float
    forward_distance_m: float
    lateral_drift_m: float
    mean_speed_mps: float
    speed_tracking_error_mps: float
    knee_rms_rad: float
    per_robot_forward_m: list = field(default_factory=list)
    alive: list = field(default_factory=list)
    #: What the run randomised and perturbed: ``randomize`` (its name), ``seed``, ``pushes`` (count per robot,
    #: speed [m/s], kicks that started within the run), ``start_noise`` (the start velocities' σ or None).
    perturbations: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return dict(self.__dict__)


class _Terminations:
    """The env's early-termination checks on one MjData (contact sets from the robot facts of ``robot.py``), and
    the env's health check (:data:`HEALTH_WARNINGS`)."""

    def __init__(self, model: mujoco.MjModel, contract: dict):
        body = lambda n: mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n)
        self.base, self.neck = body(contract["robot"]["base_body"]), body(contract["robot"]["neck_body"])
        self.forbidden = {body(n) for n in robot.GROUND_FORBIDDEN_BODIES} - {-1}
        self.self_bodies = {body(n) for n in robot.SELF_COLLISION_BODIES} - {-1}
        self.term = contract["termination"]

    def __call__(self, m: mujoco.MjModel, d: mujoco.MjData) -> bool:
        t = self.term
        if d.xpos[self.base, 2] < t["min_pelvis_height"] or d.xpos[self.neck, 2] < t["min_neck_height"]:
            return True
        q = d.xquat[self.neck]
        if 2.0 * np.arctan2(np.linalg.norm(q[1:]), abs(q[0])) > t["max_neck_angle"]:
            return True
        if not (np.isfinite(d.qpos).all() and np.isfinite(d.qvel).all()):
            return True
        # MuJoCo resets a diverged robot to the default pose and only counts a warning: its state is finite and
        # standing again, so only the counters (zero in a fresh MjData, never cleared here) show that it fell.
        if any(d.warning[w].number > 0 for w in HEALTH_WARNINGS):
            return True
        for c in d.contact[: d.ncon]:
            b1, b2 = m.geom_bodyid[c.geom1], m.geom_bodyid[c.geom2]
            if t.get("forbidden_contact", True) and (b1 == 0 or b2 == 0) and (b1 + b2) in self.forbidden:
                return True
            if (t.get("self_collision", True) and b1 != 0 and b2 != 0 and b1 in self.self_bodies
                    and b2 in self.self_bodies):
                return True
        return False


def _state(m: mujoco.MjModel, datas: list, sensors: tuple[np.ndarray, np.ndarray]) -> RobotState:
    qpos = np.stack([d.qpos for d in datas]).astype(np.float32)
    qvel = np.stack([d.qvel for d in datas]).astype(np.float32)
    sd = np.stack([d.sensordata for d in datas]).astype(np.float32)
    force, torque = sensors
    # The free joint's linear velocity is in the world frame, its angular velocity in the pelvis's own.
    lin = np.stack([_rotate_inverse(d.qpos[3:7], d.qvel[:3]) for d in datas]).astype(np.float32)
    return RobotState(base_quat=qpos[:, 3:7], joint_pos=qpos[:, 7:], joint_vel=qvel[:, 6:],
                      foot_force=sd[:, force], foot_torque=sd[:, torque], base_lin_vel=lin,
                      base_ang_vel=qvel[:, 3:6].copy())


def _sensor_columns(m: mujoco.MjModel, names: list[str]) -> np.ndarray:
    cols = []
    for n in names:
        sid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SENSOR, n)
        if sid < 0:
            raise ValueError(f"the model has no sensor {n!r}, which the contract's observation reads")
        cols.append(np.arange(m.sensor_adr[sid], m.sensor_adr[sid] + 3))
    return np.stack(cols)  # (2, 3)


def resolve_randomization(randomize, contract: dict) -> rnd.Randomization:
    """The :class:`~tocabi_torchrl.runtime.randomization.Randomization` that ``randomize`` names (one of
    :data:`RANDOMIZE`, or an instance) for a policy with ``contract``. Raises ``ValueError`` saying what to use
    instead for an unknown name, ``"trained"`` with a contract that does not state what the policy was trained
    under, actuator stages for a servo-mode policy (the training env applies them to torque commands only), and an
    instance whose values the training config would refuse (:meth:`~tocabi_torchrl.runtime.randomization.Randomization
    .validate`, naming the field)."""
    if isinstance(randomize, rnd.Randomization):
        chosen, name = randomize, "the given randomisation"
    elif randomize == "none":
        return rnd.Randomization()
    elif randomize == "trained":
        stated = rnd.from_contract(contract)
        if stated is None:
            raise ValueError("randomize='trained': the contract does not state what the policy was trained under (it "
                             "has no trained_under section; exported before the section existed): use 'none' or "
                             "'tocabi_lab', or re-export the policy with `python -m tocabi_torchrl.export`")
        chosen, name = stated[0], "the contract's trained_under"
    elif randomize == "tocabi_lab":
        chosen, name = rnd.TOCABI_LAB, "tocabi_lab"
    else:
        raise ValueError(f"randomize is {randomize!r}; choose one of {list(RANDOMIZE)} or pass a "
                         "tocabi_torchrl.runtime.randomization.Randomization")
    # Before anything is built: a negative motor constant or friction, a NaN bias or a negative clip ran as given.
    chosen.validate()
    mode = contract["action"]["control_mode"]
    if chosen.actuators.enabled and contract["action"]["leg"]["kind"] != "torque":
        raise ValueError(f"{name} has an actuator layer (delay, motor constant, friction), which acts on torque "
                         f"commands only, but this policy's control mode is {mode!r} (PD servos): use a torque "
                         "policy (torque or pd_held), or randomise without the actuator layer")
    return chosen


def _check_run(seconds, dt: float, num_robots, perturbation, seed) -> int:
    """Control periods of ``dt`` [s] in ``seconds`` [s]; ``ValueError`` naming the argument and the fix for a
    length under one period, a robot count that is not an int >= 1, a negative or non-finite ``perturbation``
    [rad] or a seed outside [0, 2**63 - 1] (numpy's own errors, e.g. 'scale < 0', name neither)."""
    if isinstance(num_robots, bool) or not isinstance(num_robots, numbers.Integral) or num_robots < 1:
        raise ValueError(f"num_robots must be an int >= 1 (the robots to simulate), got {num_robots!r}; pass e.g. "
                         "num_robots=4")
    if (isinstance(perturbation, bool) or not isinstance(perturbation, numbers.Real) or not math.isfinite(perturbation)
            or perturbation < 0):
        raise ValueError(f"perturbation must be a finite number >= 0 (the std [rad] of each robot's initial joint "
                         f"offsets), got {perturbation!r}; pass 0 for none or e.g. 1e-6")
    check_seed(seed, "seed")
    # Below one period the run would still simulate one and report the shorter length.
    if (isinstance(seconds, bool) or not isinstance(seconds, numbers.Real) or not math.isfinite(seconds)
            or seconds < dt * (1.0 - 1e-9)):
        raise ValueError(f"seconds={seconds!r} is shorter than one control period ({dt * 1000:g} ms) or not finite; "
                         f"pass at least {dt:g}")
    return round(seconds / dt)


def run_sim2sim(contract_path: str | os.PathLike | PolicyRuntime, model_path: str | os.PathLike | None = None,
                seconds: float = 8.0, num_robots: int = 4, command: tuple[float, float] = (0.5, 0.0), init_rows=None,
                remove_meshes: bool = False, motion: str | os.PathLike | None = None, perturbation: float = 0.0,
                seed: int = 0, randomize: str | rnd.Randomization = "none", pushes: rnd.PushSettings | None = None,
                start_velocity: rnd.StartVelocity | None = None,
                on_step: Callable[[int, mujoco.MjModel, list], None] | None = None,
                onnx: str | os.PathLike | None = None) -> Sim2SimResult:
    """Drive ``num_robots`` C MuJoCo robots through the exported policy for ``seconds`` at ``command`` (vx, vy) m/s.

    ``model_path``: MJCF (default: the shipped authored model); ``remove_meshes`` strips mesh geoms first (the
    reference model). ``seconds``: at least one control period, run in whole periods (the result's ``seconds``).
    ``command``: (2,) for every robot or (num_robots, 2), one row per robot, as ``PolicyRuntime`` takes it.
    ``init_rows``: (num_robots,) start rows of the reference motion (default: the motion's start rows in turn). A
    robot that meets a termination condition stops counting (as in the gait test) but keeps being simulated.

    ``perturbation`` > 0 offsets each robot's initial joint angles by N(0, perturbation²) rad (``seed``): a
    walking gait is chaotic, so a 1e-6 rad offset (or the ~1e-6 difference between ONNX and torch arithmetic) gives
    another sample of it, and averages over such robots are what two implementations can be compared on.

    Randomisation and perturbations (``docs/concepts/randomization.md``, "Sim-to-sim with randomisation"), drawn per
    robot at the reset from numpy generators of ``seed`` (one stream per piece, ``randomization.generator``):

    * ``randomize``: ``"none"`` (default: the nominal robot, numbers exactly as without these options),
      ``"trained"`` (what the contract's ``trained_under`` section states), ``"tocabi_lab"``, or a
      :class:`~tocabi_torchrl.runtime.randomization.Randomization`. Actuator layer: the leg torques go through
      delay, motor constant, friction and saturation, written into ``ctrl`` substep by substep. Dynamics: one
      ``MjModel`` copy per robot. Sensors: biases and noise on what the policy observes (and, in ``pd_held``, on
      what its PD reads).
    * ``pushes``: kicks through ``MjData.xfrc_applied`` (``PushSettings``: ``kind`` "force" on the pelvis,
      "velocity" on every body by the robot's own masses; None or count 0: none).
    * ``start_velocity``: start joint and pelvis velocities (``StartVelocity``, e.g. ``ROBUST_START``; None: at rest).

    ``onnx``: the ONNX file to run (default: the one beside the contract, as :class:`PolicyRuntime` resolves it);
    it must have the contract's sha256.

    ``contract_path`` may instead be a :class:`PolicyRuntime` already built (a caller that checked the policy first
    need not load it again): the run uses its contract, ONNX session and motion, and :meth:`PolicyRuntime.reset`
    starts its episode for ``num_robots`` robots, so a runtime built but never stepped, or one left by an earlier
    run, gives exactly the numbers of the path-based call. Its ``motion`` and ONNX file were fixed when it was built:
    ``motion`` must then be None and ``onnx`` None or that same file (ValueError otherwise), and it must have no
    ``sensors`` of its own (the run sets them from ``randomize`` and puts None back when it ends).

    ``on_step(step, model, datas)``: called after each control period with its 0-based index, the compiled model and
    the robots' ``MjData`` (read them, do not write; the live viewer draws them: docs/viewer.md). Every argument is
    checked before its first call. A viewer is the caller's, though: its page is served when the caller starts it,
    before this call, so a policy given here as a path would be checked only after that page is up (and a bad one
    would leave a page that never shows a robot). Check the policy first, by building the runtime, then start the
    viewer and pass the runtime, as ``recipes/sim2sim.py --viewer`` does::

        runtime = PolicyRuntime("policy.json")  # contract, ONNX file and hash, onnxruntime, motion: raises here
        server = start_server(host, port)  # tocabi_torchrl.viewer.server: the page from here on
        run_sim2sim(runtime, on_step=ExportedWatch(server, runtime.contract["timing"]["control_dt_s"]))
    """
    _check_hook(on_step)  # before the policy, the model and the robots are built
    _check_settings(pushes, start_velocity)
    if not isinstance(contract_path, PolicyRuntime):
        runtime = PolicyRuntime(contract_path, motion=motion, onnx=onnx)
    else:
        runtime = _given_runtime(contract_path, motion, onnx)
    try:
        return _run(runtime, model_path, seconds, num_robots, command, init_rows, remove_meshes, perturbation, seed,
                    randomize, pushes, start_velocity, on_step)
    finally:
        runtime.sensors = None  # the run's sensor model (if any) does not outlive it


def _check_hook(on_step) -> None:
    """``ValueError`` (the driver's error for a bad argument) for an ``on_step`` that is neither None nor callable:
    it was first called after the model and every robot were built and a control period was simulated, and failed
    there with Python's bare "'int' object is not callable"."""
    if on_step is not None and not callable(on_step):
        raise ValueError(f"on_step must be None or a callable on_step(step, model, datas) called after each control "
                         f"period, got {type(on_step).__name__} {on_step!r:.80}; pass a function (or the viewer's "
                         "ExportedWatch), or None")


def _check_settings(pushes, start_velocity) -> None:
    """``ValueError`` for ``pushes``/``start_velocity`` that are neither None nor the settings classes: a dict of
    their fields failed with "'dict' object has no attribute 'validate'" (the values are checked in the run)."""
    for name, value, cls, example in (("pushes", pushes, rnd.PushSettings, "PushSettings(count=3, window=(2.0, 7.0))"),
                                      ("start_velocity", start_velocity, rnd.StartVelocity,
                                       "StartVelocity(joint_std=0.5, base_std=0.1), or ROBUST_START")):
        if value is not None and not isinstance(value, cls):
            fields_given = (f" (for a dict of its fields: {cls.__name__}(**fields))" if isinstance(value, dict)
                            else f" (for a training config's {type(value).__name__}: tocabi_torchrl.runtime."
                                 f"randomization.settings_from({cls.__name__}, value, '{name}'))"
                            if is_dataclass(value) else "")
            raise ValueError(f"{name} must be None or a {cls.__name__} (tocabi_torchrl.runtime.randomization."
                             f"{example}), got {type(value).__name__} {value!r:.80}{fields_given}")


def _given_runtime(runtime: PolicyRuntime, motion, onnx) -> PolicyRuntime:
    """``runtime`` for :func:`run_sim2sim`, once no other argument contradicts it."""
    if motion is not None:
        raise ValueError(f"run_sim2sim: motion={str(motion)!r} with a PolicyRuntime, whose motion was loaded when it "
                         "was built: pass motion= to PolicyRuntime, or the contract path here")
    if onnx is not None and Path(onnx).resolve() != Path(runtime.onnx_path).resolve():
        raise ValueError(f"run_sim2sim: onnx={str(onnx)!r} with a PolicyRuntime that runs {runtime.onnx_path}: leave "
                         "onnx out (the runtime's file runs), or pass the contract path here")
    if runtime.sensors is not None:
        raise ValueError("run_sim2sim: the PolicyRuntime has sensors of its own; the run sets them from randomize= "
                         "(build the runtime with sensors=None)")
    return runtime


def _run(runtime: PolicyRuntime, model_path, seconds, num_robots, command, init_rows, remove_meshes, perturbation,
         seed, randomize, pushes, start_velocity, on_step) -> Sim2SimResult:
    c = runtime.contract
    dt = float(c["timing"]["control_dt_s"])
    steps = _check_run(seconds, dt, num_robots, perturbation, seed)
    runtime._check_command(command, num_robots)  # ContractError: (2,) or (num_robots, 2) finite speeds
    # Each robot's commanded forward speed [m/s], in float64 as given (the tracking error's reference).
    vx = np.broadcast_to(np.asarray(command, dtype=np.float64), (num_robots, 2))[:, 0]
    chosen = resolve_randomization(randomize, c)
    if pushes is not None:  # a count of -1 read as no kicks
        pushes.validate()
    pushes = pushes if pushes is not None and pushes.count > 0 else None
    if start_velocity is not None:  # a NaN std read as none, then failed as a sensor
        start_velocity.validate()
    start_velocity = start_velocity if start_velocity is not None and start_velocity.enabled else None
    if model_path is None:
        model_path = robot.asset_path("tocabi", "tocabi.xml")
    m = build_model(c, Path(model_path), remove_meshes)
    # As the env does: a motion beyond the model's ranges would have its targets clipped by the joint limits.
    problem = robot.motion_range_problem(m, str(model_path), runtime.motion.joint_pos, runtime.motion.source,
                                         c["robot"]["joint_names"], c["robot"]["initial_qpos"][7:],
                                         "the contract's robot.initial_qpos", "the contract's robot.joint_names")
    if problem is not None:
        raise ValueError(problem)
    substeps = int(c["timing"]["substeps"])
    if abs(m.opt.timestep * substeps - c["timing"]["control_dt_s"]) > 1e-9:
        raise ValueError(f"{model_path}: timestep {m.opt.timestep} × {substeps} substeps is not the contract's "
                         f"control period {c['timing']['control_dt_s']} s")
    sensors = (_sensor_columns(m, c["robot"]["foot_force_sensors"]),
               _sensor_columns(m, c["robot"]["foot_torque_sensors"]))
    terminated = _Terminations(m, c)
    n_leg = len(c["robot"]["leg_joint_names"])
    knees = [c["robot"]["joint_names"].index(k) for k in ("L_Knee_Joint", "R_Knee_Joint")]
    if init_rows is None:
        rows = runtime.motion.init_rows
        init_rows = rows[np.arange(num_robots) % len(rows)]
    init_rows = runtime._check_init_row(init_rows, num_robots)  # before they index the motion below
    init_qpos = np.asarray(c["robot"]["initial_qpos"])
    reset_leg = (np.zeros(n_leg) if c["action"]["leg"]["kind"] == "torque"
                 else np.asarray(c["action"]["leg"].get("nominal", init_qpos[7 : 7 + n_leg])))

    # Randomisation and perturbations, drawn per robot at this (the episode's only) reset. With none of them the
    # loop below is the plain one: one shared model, the command held for every substep, no forces.
    models = [m] * num_robots
    actuators = kicks = None
    if chosen.dynamics.enabled:
        models = rnd.WorldDynamics(chosen.dynamics, m).reset(rnd.generator(seed, "dynamics"), num_robots)
    if chosen.actuators.enabled:
        actuators = rnd.ActuatorLayer(chosen.actuators, substeps, c["action"]["leg"]["torque_limits_nm"])
        actuators.reset(rnd.generator(seed, "actuators"), num_robots)
    if chosen.sensors.enabled:
        runtime.sensors = rnd.SensorModel(chosen.sensors, len(c["robot"]["joint_names"]),
                                          rnd.generator(seed, "sensor_noise"))
        runtime.sensors.reset(rnd.generator(seed, "sensor_bias"), num_robots)
    if pushes is not None:
        # The kick changes the whole robot's velocity by `speed`: impulse = speed × the model's robot mass.
        base = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, c["robot"]["base_body"])
        kicks = rnd.PushSchedule(pushes, float(c["timing"]["control_dt_s"]), float(m.body_subtreemass[base]))
        kicks.reset(rnd.generator(seed, "pushes"), num_robots)
        body_mass = np.stack([mi.body_mass for mi in models])  # (N, nbody) each robot's own (drawn) masses
    start_qvel = (rnd.start_velocities(rnd.generator(seed, "start_velocity"), num_robots, m.nv, start_velocity)
                  if start_velocity is not None else None)

    datas = [mujoco.MjData(m) for _ in range(num_robots)]
    first_ref = runtime.motion.joint_targets(np.zeros(num_robots, np.float32), np.asarray(init_rows))
    offsets = np.random.default_rng(seed).normal(0.0, perturbation, (num_robots, len(init_qpos) - 7))
    for i, d in enumerate(datas):
        d.qpos[:] = init_qpos
        d.qpos[7:] += offsets[i]
        if start_qvel is not None:
            d.qvel[:] = start_qvel[i]
        d.ctrl[:n_leg] = reset_leg
        d.ctrl[n_leg:] = first_ref[i, n_leg:]
        mujoco.mj_forward(models[i], d)
        d.qacc_warmstart[:] = d.qacc
    held = _state(m, datas, sensors)  # each robot's last finite state
    cmd = runtime.reset(held, command, init_row=init_rows)
    start = np.stack([d.qpos[:3].copy() for d in datas])
    last = start.copy()
    alive = np.ones(num_robots, dtype=bool)
    knee_sq = np.zeros(num_robots)
    vel_err = np.zeros(num_robots)
    alive_steps = np.zeros(num_robots)
    kicked = 0
    for step in range(steps):
        # The actuator layer's torque of every substep of this period (the joint velocity at its start for friction).
        torques = (actuators(cmd.leg, np.stack([d.qvel[6 : 6 + n_leg] for d in datas]))
                   if actuators is not None else None)
        if kicks is not None:
            forces = kicks.body_forces(step, base, body_mass)  # held for the whole period, as the env's xfrc_applied
            kicked += int((kicks.start_step == step).sum())
        for i, d in enumerate(datas):
            mi = models[i]
            d.ctrl[:n_leg] = cmd.leg[i]
            d.ctrl[n_leg:] = cmd.upper_targets[i]
            if kicks is not None:
                d.xfrc_applied[:, :2] = forces[i]
            if torques is None:
                for _ in range(substeps):
                    mujoco.mj_step(mi, d)
            else:
                for s in range(substeps):
                    d.ctrl[:n_leg] = torques[i, s]
                    mujoco.mj_step(mi, d)
            mujoco.mj_forward(mi, d)
            d.qacc_warmstart[:] = d.qacc
            if alive[i] and terminated(mi, d):
                alive[i] = False
        state, finite = _hold_finite(_state(m, datas, sensors), held)
        alive &= finite  # a diverged robot is a fallen one: it no longer counts, and the others go on
        held = state
        pos = np.stack([d.qpos[:3] for d in datas])
        last = np.where(alive[:, None], pos, last)
        a = alive.astype(np.float64)
        knee_sq += a * ((state.joint_pos[:, knees] - cmd.reference[:, knees]) ** 2).mean(-1)
        vel_err += a * np.abs(state.base_lin_vel[:, 0].astype(np.float64) - vx)
        alive_steps += a
        cmd = runtime.step(state)
        if on_step is not None:
            on_step(step, m, datas)
    dt = float(c["timing"]["control_dt_s"])
    dist = last - start
    return Sim2SimResult(
        num_robots=int(num_robots),
        seconds=round(steps * dt, 9),
        survival=float(alive.mean()),
        forward_distance_m=float(dist[:, 0].mean()),
        lateral_drift_m=float(np.abs(dist[:, 1]).mean()),
        mean_speed_mps=float((dist[:, 0] / np.maximum(alive_steps * dt, dt)).mean()),
        # As the env's gait test: a robot with no alive step has no knee RMS or speed error, left out of the means.
        speed_tracking_error_mps=_mean_per_alive_step(vel_err, alive_steps),
        knee_rms_rad=_mean_per_alive_step(knee_sq, alive_steps, root=True),
        per_robot_forward_m=dist[:, 0].round(4).tolist(),
        alive=alive.tolist(),
        perturbations={
            "randomize": randomize if isinstance(randomize, str) else "custom",
            "seed": int(seed),
            "pushes": ({"count": pushes.count, "speed_mps": list(pushes.speed), "window_s": list(pushes.window),
                        "duration_s": list(pushes.duration), "kind": pushes.kind, "kicks_started": kicked,
                        **({"calm_fraction": pushes.calm_fraction} if pushes.calm_fraction > 0 else {})}
                       if pushes is not None else None),
            "start_noise": ({"joint_std_radps": start_velocity.joint_std, "base_std_mps": start_velocity.base_std}
                            if start_velocity is not None else None),
        },
    )


def _hold_finite(state: RobotState, held: RobotState) -> tuple[RobotState, np.ndarray]:
    """``state`` with each robot whose readings hold NaN or inf replaced by its ``held`` (last finite) rows, and the
    (N,) bool mask of the robots that were finite: the runtime refuses non-finite readings, as a real controller
    must, while here a diverged robot is only one fallen robot of many."""
    names = [f.name for f in fields(RobotState) if getattr(state, f.name) is not None]
    n = len(state.base_quat)
    finite = np.ones(n, dtype=bool)
    for name in names:
        finite &= np.isfinite(getattr(state, name)).reshape(n, -1).all(-1)
    if finite.all():
        return state, finite
    rows = {name: np.where(finite.reshape(-1, *[1] * (getattr(state, name).ndim - 1)), getattr(state, name),
                           getattr(held, name)) for name in names}
    return RobotState(**rows), finite


def _rotate_inverse(quat: np.ndarray, vec: np.ndarray) -> np.ndarray:
    out = np.empty(3)
    mujoco.mju_rotVecQuat(out, vec, np.array([quat[0], -quat[1], -quat[2], -quat[3]]))
    return out


def _mean_per_alive_step(total: np.ndarray, alive_steps: np.ndarray, root: bool = False) -> float:
    """The mean over the robots with an alive step of ``total`` / their alive steps (its square root first with
    ``root``); NaN when no robot has one. A robot that fell in its first step is left out, not counted as 0."""
    measured = alive_steps > 0
    if not measured.any():
        return float("nan")
    per = total[measured] / alive_steps[measured]
    return float((np.sqrt(per) if root else per).mean())
