"""``PolicyRuntime``: run an exported policy from raw robot signals at the control rate, without torch.

Per control period (4 ms, 250 Hz for the shipped policies) the caller passes the robot's state after the previous
command was applied; the runtime advances its phase clock by the previous phase-rate action, builds the observation,
pushes it into the history, runs the ONNX policy and returns the next leg commands and upper-body targets. The steps
are those of ``TocabiWalk._step`` and the default transforms, in the same order (``docs/deploying.md``).
"""

from __future__ import annotations

import numbers
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .contract import ContractError, folder_note, load_contract
from .motion import RuntimeMotion, file_sha256
from .observation import History, ObservationBuilder, quat_to_rpy

__all__ = ["Command", "PolicyRuntime", "RobotState", "resolve_onnx"]

_F32 = np.float32
#: The state's signals only some policies read (``transforms.observation`` base_vel), with what each is.
_OPTIONAL_SIGNALS = {"base_lin_vel": "the pelvis linear velocity [m/s] in the pelvis frame",
                     "base_ang_vel": "the pelvis angular velocity [rad/s] in the pelvis frame"}


@dataclass
class RobotState:
    """Raw signals of N robots, float arrays; joints in the contract's ``robot.joint_names`` order.

    Attributes:
        base_quat: (N, 4) pelvis (base body) orientation in the world, (w, x, y, z).
        joint_pos: (N, J) joint angles [rad].
        joint_vel: (N, J) joint velocities [rad/s].
        foot_force: (N, 2, 3) [left, right] foot F/T sensor forces [N] in the sensor site frame (loaded: z < 0).
        foot_torque: (N, 2, 3) [left, right] foot F/T sensor torques [N·m] in the sensor site frame.
        base_lin_vel: (N, 3) pelvis linear velocity [m/s] in the pelvis frame (a state estimator's); needed only by a
            policy whose contract reads it (``transforms.observation`` base_vel), else None.
        base_ang_vel: (N, 3) pelvis angular velocity [rad/s] in the pelvis frame (the IMU's gyro); likewise.
    """

    base_quat: np.ndarray
    joint_pos: np.ndarray
    joint_vel: np.ndarray
    foot_force: np.ndarray
    foot_torque: np.ndarray
    base_lin_vel: np.ndarray | None = None
    base_ang_vel: np.ndarray | None = None


@dataclass
class Command:
    """What to apply for the next control period.

    Attributes:
        action: (N, A) float32 clipped policy action (the value the history stores), a copy the caller may edit.
        leg: (N, L) float32 leg commands: torques [N·m] (``leg_kind == "torque"``) or target angles [rad] for a PD
            with the contract's ``action.leg.kp``/``kv``, force-limited to ``torque_limits_nm`` (``"position"``).
        leg_kind: ``"torque"`` or ``"position"``.
        upper_targets: (N, U) float32 upper-body target angles [rad] for the upper-body PD.
        reference: (N, J) float32 reference joint angles [rad] at this period's start (for logging/metrics).

    ``upper_targets`` is a view of ``reference[:, L:]`` (the upper body's reference columns), not a copy: an
    in-place edit of one (e.g. clipping the upper-body targets) changes the other, so log ``reference`` before such
    an edit or edit a copy (``cmd.upper_targets = cmd.upper_targets.copy()`` first). The runtime keeps neither: its
    next step is the same either way. ``action`` and ``leg`` are arrays of their own.
    """

    action: np.ndarray
    leg: np.ndarray
    leg_kind: str
    upper_targets: np.ndarray
    reference: np.ndarray


def _onnx_session(path: Path, threads: int, as_exported: bool = False, opset: int | None = None):
    """An onnxruntime session of ``path`` on the CPU; ``ContractError`` when onnxruntime cannot load it.
    ``as_exported``: the file's hash is its contract's, so a failure may be this onnxruntime's (too old for the
    graph's ``opset``) as well as the file's; the error says both."""
    try:
        import onnxruntime as ort
    except ImportError as err:  # an optional dependency: say which extra brings it
        raise ImportError("running an exported policy needs onnxruntime, which is not installed: "
                          'pip install -e ".[export]" in the repository (or pip install onnxruntime)') from err

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    try:
        return ort.InferenceSession(str(path), sess_options=options, providers=["CPUExecutionProvider"])
    except Exception as err:  # onnxruntime's own errors (InvalidProtobuf, InvalidArgument, ...) share no base class
        said = f"{type(err).__name__}: {str(err).strip()[:200]}"
        if as_exported:  # the file is the one the contract names: the export's, or both replaced together
            raise ContractError(f"onnxruntime {ort.__version__} cannot load {path} ({said}); its sha256 is its "
                                f"contract's, so this onnxruntime may be too old for the graph's opset {opset} "
                                "(pip install -U onnxruntime), or the file and its contract were both replaced "
                                "(export it again with python -m tocabi_torchrl.export)") from err
        raise ContractError(f"{path} is not an ONNX model onnxruntime can load ({said}); export it again with "
                            "python -m tocabi_torchrl.export") from err


def _same(said, found) -> bool:
    """A contract's value equals the file's (floats to 1e-9 relative: both are written from the same float64)."""
    if isinstance(found, list):
        return isinstance(said, list) and len(said) == len(found) and all(map(_same, said, found))
    if isinstance(said, bool) or not isinstance(said, (int, float)):
        return False
    return said == found if isinstance(found, int) else abs(said - found) <= 1e-9 * max(1.0, abs(found))


def resolve_onnx(contract_path: Path, contract: dict, onnx: str | os.PathLike | None = None,
                 check_hash: bool = True) -> Path:
    """The ONNX file a contract (read from ``contract_path``) runs: ``onnx`` when given, else the ``.onnx`` of the
    contract's stem beside it when that exists, else the file the contract's ``policy.onnx_file`` names beside it.

    A renamed pair (``my.onnx`` + ``my.json``) keeps the old name in ``policy.onnx_file``; a file of that old name
    may still lie beside it holding another policy, so the recorded name is only the fallback, never a substitute
    for the file the user named. With ``check_hash`` the chosen file must have the contract's ``onnx_sha256``, else
    :class:`ContractError` naming that file."""
    recorded = contract_path.parent / contract["policy"]["onnx_file"]
    if onnx is not None:
        chosen = Path(onnx)
        if not chosen.is_file():
            raise ContractError(folder_note(chosen, "ONNX file", ".onnx") or f"ONNX file {chosen} not found")
    else:
        stem = contract_path.with_suffix(".onnx")
        chosen = stem if stem.is_file() else recorded
        if not chosen.is_file():
            raise ContractError(f"{contract_path}: ONNX file {recorded.name} (the contract's policy.onnx_file) not "
                                f"found beside the contract, nor {stem.name}; pass the .onnx it belongs to")
    if check_hash and contract["policy"]["onnx_sha256"] != file_sha256(chosen):
        renamed = (f" (the contract records {recorded.name}: a renamed pair is fine, but the .onnx must be the one "
                   "exported with it)" if chosen.name != recorded.name else "")
        raise ContractError(f"{chosen} does not match the sha256 in {contract_path}{renamed}: the contract belongs to "
                            "another export; re-export both together")
    return chosen


class PolicyRuntime:
    """An exported policy with its contract, its phase clock and its observation history for N robots.

    Args:
        contract: path of the contract JSON.
        onnx: the ONNX file to run; default: the one beside the contract, of the contract's own stem when there is
            one (a pair renamed together: the contract still records its old ``policy.onnx_file``), else the file
            ``policy.onnx_file`` names. Whichever runs must have the contract's ``policy.onnx_sha256``: a file of
            the recorded name is never run in place of the one of the contract's stem or the one given.
        motion: the reference motion file; default: the file of the name the contract gives (``reference_motion.name``)
            beside the ONNX file (where the export copies a motion of the run's own), else the shipped motion of that
            name (also when the one beside it has another hash). Its sha256 must match the contract's.
        threads: onnxruntime intra-op threads, an int >= 0 (0: onnxruntime's own default); ``ValueError``
            otherwise.
        check_onnx_hash: check the ONNX file against the contract's ``policy.onnx_sha256`` (which every contract
            must give); pass False only to run an ONNX file knowingly swapped in beside the contract.
        sensors: optional callable that maps the observation's signals ``{name: (N, *shape)}`` (in the contract's
            units) to the signals the policy observes, e.g. a simulation's sensor biases and noise
            (:class:`~tocabi_torchrl.runtime.randomization.SensorModel`). The state is checked before it runs, and what
            it returns after: every signal in its shape, finite in float32. A ``pd_held`` policy's PD reads the
            sensed joint positions and velocities too.

    Raises :class:`~tocabi_torchrl.runtime.contract.ContractError` for a bad contract, a missing or mismatched
    ONNX file (hash, input or output name and width) or motion, a robot state that is not a :class:`RobotState`
    (or an object with its fields) of N rows of finite float32-representable readings with unit-length quaternions,
    and a policy output with no finite entry for some robot.
    """

    def __init__(self, contract: str | os.PathLike, motion: str | os.PathLike | None = None, threads: int = 1,
                 check_onnx_hash: bool = True, sensors=None, onnx: str | os.PathLike | None = None):
        # Before anything is loaded: onnxruntime's TypeError for "2" names no argument, and it takes -1 silently.
        if isinstance(threads, bool) or not isinstance(threads, numbers.Integral) or threads < 0:
            raise ValueError(f"threads must be an int >= 0 (onnxruntime's intra-op threads; 0: its own default), got "
                             f"{type(threads).__name__} {threads!r}; pass e.g. threads=1")
        path = Path(contract)
        self.sensors = sensors
        self.contract = c = load_contract(path)
        self.onnx_path = resolve_onnx(path, c, onnx, check_onnx_hash)
        self.session = _onnx_session(self.onnx_path, int(threads), as_exported=check_onnx_hash,
                                     opset=c["policy"].get("opset"))
        pol = c["policy"]
        for kind, ios, name, dim in (("input", self.session.get_inputs(), pol["input_name"], pol["input_dim"]),
                                     ("output", self.session.get_outputs(), pol["output_name"], pol["output_dim"])):
            # The batch dimension may be symbolic ("batch"); the width must be the contract's.
            if (len(ios) != 1 or ios[0].name != name or len(ios[0].shape) != 2 or ios[0].shape[-1] != dim
                    or ios[0].type != "tensor(float)"):
                got = ", ".join(f"{io.name!r} {io.type} {io.shape}" for io in ios) or "nothing"
                raise ContractError(f"{self.onnx_path}: {kind} {got} does not match the contract's one {name!r} of "
                                    f"(batch, {dim}) float32 values: the ONNX file is not this contract's policy; "
                                    "re-export both together")
        rob, act = c["robot"], c["action"]
        self.joint_names = rob["joint_names"]
        self.num_legs = len(rob["leg_joint_names"])
        self.dt = _F32(c["timing"]["control_dt_s"])
        self.low = np.asarray(act["low"], dtype=_F32)
        self.high = np.asarray(act["high"], dtype=_F32)
        self.rate_index = int(act["phase_rate"]["index"])
        self.rate_gain = float(act["phase_rate"]["gain"])
        self.mode = act["control_mode"]
        leg = act["leg"]
        self.leg_kind = leg["kind"]  # check_contract: the mode's ("torque" or "position")
        self.torque_limits = np.asarray(leg["torque_limits_nm"], dtype=_F32)
        if self.mode != "torque":
            self.action_scale = _F32(leg["action_scale"])
        if self.leg_kind == "position":
            rng = np.asarray(leg["joint_range"], dtype=_F32)
            self.range_low, self.range_high = rng[:, 0], rng[:, 1]
            self.nominal = np.asarray(leg.get("nominal", [0.0] * self.num_legs), dtype=_F32)
        if self.mode == "pd_held":  # the PD runs here, at the control rate, on the sensed joints
            self.kp = np.asarray(leg["kp"], dtype=_F32)
            self.kv = np.asarray(leg["kv"], dtype=_F32)
        self.motion = self._load_motion(c["reference_motion"], motion)
        self.observation = ObservationBuilder(c["observation"])
        # The state's optional signals this policy reads (its contract's observation), fixed for the runtime's life.
        self._optional = tuple(name for name in _OPTIONAL_SIGNALS if name in self.observation.signals)
        hist = c["observation"]["history"]
        self.history = History(hist["obs_ages"], hist["action_ages"])
        self.time: np.ndarray | None = None  # (N,) float32 phase clock [s], kept modulo the motion period
        self.init_row: np.ndarray | None = None  # (N,) int64 start row of each robot
        self.command: np.ndarray | None = None  # (N, 2) float32 velocity command [m/s]
        self._pending: np.ndarray | None = None  # the action of the running period
        # What the history stores for it: the action, or in pd_held mode with the legs' torques over the limits.
        self._applied: np.ndarray | None = None

    def _load_motion(self, spec: dict, motion) -> RuntimeMotion:
        if motion is None:
            # Beside the contract first (where a policy trained on a motion of its own brings it, as the contract's
            # check says), then the shipped motions; a file of the name beside it with another hash (an old copy)
            # does not hide a shipped one that matches.
            from ..robot import asset_path  # numpy-only module

            beside, shipped = self.onnx_path.with_name(spec["name"]), asset_path("motions", spec["name"])
            motion = beside if beside.is_file() else shipped
            if motion == beside and shipped.is_file() and file_sha256(beside) != spec["sha256"]:
                motion = shipped if file_sha256(shipped) == spec["sha256"] else beside
            if not motion.is_file():
                raise ContractError(f"reference motion {spec['name']} is neither beside the policy ({beside}) nor "
                                    f"among the shipped motions ({shipped.parent}): copy the motion the policy was "
                                    "trained on beside the .onnx (python -m tocabi_torchrl.export copies it there)")
        loaded = RuntimeMotion.from_file(motion, self.joint_names, spec["sha256"])
        # What the contract states of the motion besides its hash: a controller may run its clock from these.
        stated = {"rows": (spec.get("rows"), loaded.cycle_rows + 1), "row_dt_s": (spec.get("row_dt_s"), loaded.row_dt),
                  "period_s": (spec.get("period_s"), loaded.period),
                  "init_rows": (spec.get("init_rows"), loaded.init_rows.tolist())}
        for key, (said, found) in stated.items():
            if said is not None and not _same(said, found):
                raise ContractError(f"reference_motion.{key} is {said!r} in the contract, but the motion {motion} "
                                    f"(of the contract's hash) has {found!r}: the contract was edited; re-export the "
                                    "policy")
        return loaded

    # --------------------------------------------------------------------------------------------- public API
    @property
    def num_robots(self) -> int:
        """Robots this runtime drives, set by :meth:`reset` (0 before it)."""
        return 0 if self.time is None else int(self.time.shape[0])

    def reset(self, state: RobotState, command, init_row=None) -> Command:
        """Start an episode for every robot from ``state`` (the initial pose): clock 0 at ``init_row`` (N,) (default:
        the motion's first start row; one integer is used for every robot), history filled with this observation
        and zero actions. ``command`` (N, 2) or (2,) is the velocity command [m/s] (vx, vy). Returns the command for
        the first period.

        A refused state, start row or command (:class:`ContractError`), or a ``sensors`` callable that fails, leaves
        the running episode as it was."""
        n = self._check_state(state)
        rows = self.motion.init_rows[0] if init_row is None else init_row
        init_row = self._check_init_row(rows, n)
        command = self._check_command(command, n)
        time = np.zeros(n, dtype=_F32)
        obs, joints = self._observe(state, time, init_row, command)
        # Only now that everything passed: a refused reset must not restart the clock or change the robot count.
        self.init_row, self.time, self.command = init_row, time, command
        self.history.reset(obs, np.zeros((n, len(self.low)), dtype=_F32))
        return self._act(joints)

    def step(self, state: RobotState, command=None) -> Command:
        """``state`` after one control period of the last command; returns the command for the next period.
        ``command`` (optional) replaces the velocity command from this observation on.

        A refused state or command (:class:`ContractError`), or a ``sensors`` callable that fails, leaves the clock,
        the command and the history as they were: the step may be retried with sound readings."""
        if self._pending is None:
            raise RuntimeError("PolicyRuntime.step without a running episode (before reset, or after a policy output "
                               "with no finite entry): call reset(state, command) first")
        self._check_state(state, self.num_robots)
        command = self.command if command is None else self._check_command(command, self.num_robots)
        rate = _F32(1.0) + _F32(self.rate_gain) * self._pending[:, self.rate_index]
        time = np.remainder(self.time + self.dt * rate, _F32(self.motion.period)).astype(_F32)
        obs, joints = self._observe(state, time, self.init_row, command)
        self.time, self.command = time, command
        self.history.push(obs, self._applied)
        return self._act(joints)

    def set_command(self, command) -> None:
        """Velocity command (vx, vy) [m/s], (N, 2) or (2,), used from the next observation on."""
        if self._pending is None:
            raise RuntimeError("PolicyRuntime.set_command without a running episode (before reset, or after a "
                               "policy output with no finite entry): pass the command to reset(state, command)")
        self.command = self._check_command(command, self.num_robots)

    def policy_input(self) -> np.ndarray:
        """(N, input_dim) float32: the current policy input (for tests and logging)."""
        if self._pending is None:
            raise RuntimeError("PolicyRuntime.policy_input without a running episode (before reset, or after a "
                               "policy output with no finite entry): there is no input until reset(state, command) "
                               "has built one")
        return self.history.read()

    # --------------------------------------------------------------------------------------------- internals
    @staticmethod
    def _check_command(command, n: int) -> np.ndarray:
        """(n, 2) float32 velocity command from ``command`` (2,) or (n, 2), finite in float32."""
        value = np.asarray(command)
        if value.dtype.kind not in "iuf":
            raise ContractError(f"command has dtype {value.dtype}, not numbers: pass the velocity command (vx, vy) "
                                "[m/s] as floats")
        with np.errstate(over="ignore"):  # a float64 beyond float32's range becomes inf, refused below
            value = value.astype(_F32)
        if value.shape not in ((2,), (n, 2)):
            raise ContractError(f"command has shape {value.shape}, expected (2,) or ({n}, 2): the velocity command "
                                "(vx, vy) [m/s], one row per robot or one for all")
        if not np.isfinite(value).all():
            raise ContractError(f"command holds NaN or inf in float32 ({value.tolist()}): pass finite speeds [m/s]")
        return np.broadcast_to(value, (n, 2)).copy()

    def _check_init_row(self, rows, n: int) -> np.ndarray:
        """(n,) int64 start rows from ``rows``: one integer or n of them, each a row of the motion's cycle (the
        motion indexes rows modulo its cycle, so an out-of-range row would silently start elsewhere)."""
        value = np.asarray(rows)
        last = self.motion.cycle_rows - 1
        if value.shape not in ((), (1,), (n,)):
            problem = f"has shape {value.shape}"
        elif value.dtype.kind not in "iu":  # not bool: True is no row; not float: 0.7 would be truncated
            problem = f"has dtype {value.dtype}, not integers"
        elif not ((value >= 0) & (value <= last)).all():
            problem = f"has rows {np.unique(value[(value < 0) | (value > last)])[:8].tolist()} outside [0, {last}]"
        else:
            return np.broadcast_to(value.astype(np.int64), (n,)).copy()
        raise ContractError(f"init_row {problem}: pass one integer or {n} (one per robot) in [0, {last}], rows of "
                            f"the reference motion's cycle (its start rows are {self.motion.init_rows.tolist()})")

    def _check_state(self, state: RobotState, n: int | None = None) -> int:
        if not isinstance(state, RobotState):  # one isinstance per step; an object with the fields is read as one
            missing = [f for f in ("base_quat", "joint_pos", "joint_vel", "foot_force", "foot_torque")
                       if not hasattr(state, f)]
            if missing:  # a dict or None failed with AttributeError: 'dict' object has no attribute 'base_quat'
                as_dict = " (for a dict of its fields: RobotState(**fields))" if isinstance(state, dict) else ""
                raise ContractError(f"state must be a RobotState (tocabi_torchrl.runtime.RobotState(base_quat=..., "
                                    "joint_pos=..., joint_vel=..., foot_force=..., foot_torque=...), one row per "
                                    f"robot), got {type(state).__name__}{as_dict} without {', '.join(missing)}")
        j = len(self.joint_names)
        shapes = {"base_quat": (4,), "joint_pos": (j,), "joint_vel": (j,), "foot_force": (2, 3),
                  "foot_torque": (2, 3)}
        for name in self._optional:  # only a policy that reads one needs it
            if getattr(state, name, None) is None:
                raise ContractError(f"RobotState.{name} is None, but this policy observes it (its contract's "
                                    f"observation reads {name!r}, {_OPTIONAL_SIGNALS[name]}): pass it, one row per "
                                    "robot")
            shapes[name] = (3,)
        if n is None:
            quat = np.shape(state.base_quat)
            if len(quat) != 2 or quat[0] < 1:
                raise ContractError(f"RobotState.base_quat has shape {quat}, expected (N, 4) with N >= 1 robots: "
                                    "every field holds one row per robot, even for a single robot")
        count = np.shape(state.base_quat)[0] if n is None else n
        for name, shape in shapes.items():
            value = np.asarray(getattr(state, name))
            if value.shape != (count, *shape):
                why = (f"the contract's robot has {j} joints ({self.joint_names[0]}, …) and " if name in
                       ("joint_pos", "joint_vel") else "")
                raise ContractError(f"RobotState.{name} has shape {value.shape}, expected {(count, *shape)}: "
                                    f"{why}this runtime runs {count} robot(s)")
            if value.dtype.kind not in "iuf":  # strings, objects, complex or bools are no sensor readings
                raise ContractError(f"RobotState.{name} has dtype {value.dtype}: pass real numbers (a float array)")
            # Checked in float32, the precision the observation is built in: 1e39 is finite in float64 only.
            with np.errstate(over="ignore"):
                value = value.astype(_F32)
            # A failed sensor must stop the controller, not be normalised into a plausible-looking observation.
            finite = np.isfinite(value).reshape(count, -1).all(-1)
            if not finite.all():
                raise ContractError(f"RobotState.{name} is not finite in float32 (NaN, inf or beyond ±3.4e38) for "
                                    f"robot(s) {np.flatnonzero(~finite).tolist()}: check those sensors; the policy is "
                                    "not run on invalid readings")
        # quat_to_rpy is scale-invariant, so a zero (dropped-out IMU) or garbage quaternion would read as some
        # orientation, e.g. upright: only a unit quaternion is an orientation reading.
        norm = np.linalg.norm(np.asarray(state.base_quat, dtype=np.float64), axis=-1)
        bad = np.abs(norm - 1.0) > 0.1
        if bad.any():
            raise ContractError(f"RobotState.base_quat is not a unit quaternion (|q| = "
                                f"{np.round(norm[bad][:8], 4).tolist()}, allowed 1 ± 0.1) for robot(s) "
                                f"{np.flatnonzero(bad).tolist()}: check the IMU; the policy is not run on invalid "
                                "readings")
        return count

    def _observe(self, state: RobotState, time: np.ndarray, init_row: np.ndarray,
                 command: np.ndarray) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
        """(N, D) float32 normalised observation of ``state`` at clock ``time`` (N,) [s] from start rows
        ``init_row`` (N,) under ``command`` (N, 2) [m/s], and the joint positions [rad] and velocities [rad/s]
        (N, J) it read (through ``sensors``, when set); the caller commits these only once this succeeded."""
        phase = self.motion.phase(time, init_row)
        sin, cos = self.observation.phase_features(phase)
        signals = {
            "base_rpy": quat_to_rpy(state.base_quat),
            "joint_pos": state.joint_pos,
            "joint_vel": state.joint_vel,
            "phase_sin": sin,
            "phase_cos": cos,
            "command": command,
            "foot_force": state.foot_force,
            "foot_torque": state.foot_torque,
        }
        for name in self._optional:
            signals[name] = getattr(state, name)
        if self.sensors is not None:
            signals = self._sensed(signals)
        joints = (np.asarray(signals["joint_pos"], dtype=_F32), np.asarray(signals["joint_vel"], dtype=_F32))
        return self.observation.normalize(self.observation.raw(signals)), joints

    def _sensed(self, signals: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The ``sensors`` callable's view of ``signals`` {name: (N, *shape)}: every signal back with its shape, as
        finite float32 numbers, else :class:`ContractError` (a wrong shape would fail deep in the observation, or be
        read silently; a NaN would reach the policy and be reported as a broken network)."""
        out = self.sensors(signals)
        if not isinstance(out, dict):
            raise ContractError(f"the sensors callable returned {type(out).__name__}, not a dict: return "
                                "{name: (N, *shape)} with every signal it was given, in its shape")
        for name, value in signals.items():
            got = np.shape(out[name]) if name in out else "nothing"
            if got != np.shape(value):
                raise ContractError(f"the sensors callable returned {got} for signal {name!r}, expected its input's "
                                    f"shape {np.shape(value)}: return every signal it was given, in its shape (one "
                                    f"row per robot; this runtime runs {np.shape(value)[0]})")
            sensed = np.asarray(out[name])
            if sensed.dtype.kind not in "iuf":
                raise ContractError(f"the sensors callable returned dtype {sensed.dtype} for signal {name!r}: return "
                                    "real numbers (a float array)")
            with np.errstate(over="ignore"):  # beyond float32's range is inf in the observation
                finite = np.isfinite(sensed.astype(_F32)).reshape(len(sensed), -1).all(-1)
            if not finite.all():
                raise ContractError(f"the sensors callable returned NaN or inf (in float32) for signal {name!r} of "
                                    f"robot(s) {np.flatnonzero(~finite).tolist()}, whose true readings are finite: fix "
                                    "the sensors callable (its bias or noise); the policy is not run on them")
        return out

    def _act(self, joints: tuple[np.ndarray, np.ndarray]) -> Command:
        """The command for the period that starts at the state whose sensed joint positions and velocities (N, J)
        are ``joints`` (read by the held PD of ``pd_held`` mode)."""
        obs = self.history.read()
        pol = self.contract["policy"]
        raw = self.session.run([pol["output_name"]], {pol["input_name"]: obs})[0].astype(_F32)
        # A single NaN entry counts as 0 (the contract's rule); a row with no finite entry is a broken policy, not
        # a glitch, and zeroing it would quietly command zero torque or the bare reference.
        dead = ~np.isfinite(raw).any(-1)
        if dead.any():
            # The clock and the history have moved on to a period that has no command: no step may follow it.
            self._pending = None
            raise ContractError(f"the policy's output is NaN or inf in every entry for robot(s) "
                                f"{np.flatnonzero(dead).tolist()}: the exported network is broken (non-finite "
                                "weights?) or its input was; stop these robots and re-export the policy from a sound "
                                "checkpoint (the episode has ended: reset() starts another)")
        action = np.clip(np.nan_to_num(raw, nan=0.0), self.low, self.high)
        self._pending = self._applied = action
        ref = self.motion.joint_targets(self.time, self.init_row)
        a_leg = action[:, : self.num_legs]
        if self.mode == "torque":
            leg = a_leg * self.torque_limits
        elif self.mode == "pd_held":
            # control.HeldPD: one torque per period from the state at its start, on the joints the robot senses.
            q, qd = joints[0][:, : self.num_legs], joints[1][:, : self.num_legs]
            target = ref[:, : self.num_legs] + self.action_scale * a_leg
            tau = self.kp * (target - q) - self.kv * qd
            leg = np.maximum(np.minimum(tau, self.torque_limits), -self.torque_limits)
            self._applied = action.copy()
            self._applied[:, : self.num_legs] = leg / self.torque_limits
        else:
            center = self.nominal if self.mode == "pd" else ref[:, : self.num_legs]
            leg = np.clip(center + self.action_scale * a_leg, self.range_low, self.range_high)
        # The caller's copy: the runtime keeps its own for the next step's clock and history, which an in-place
        # edit of the returned command (e.g. zeroing a robot's action) must not reach.
        return Command(action=action.copy(), leg=leg.astype(_F32), leg_kind=self.leg_kind,
                       upper_targets=ref[:, self.num_legs :], reference=ref)
