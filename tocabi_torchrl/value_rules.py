"""The rules a config value must obey, each written once: the env config (``envs/config.py``), the run config
(``config.py``), the env's seed entry points and the policy contract reader (``runtime/contract.py``) all check with
these, so a value one of them refuses cannot reach the robot through another.

Standard library only: the torch-free runtime imports it to check a contract before loading anything else.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, fields, replace
from typing import Any

__all__ = ["DELAY_APPLIED", "ENV_RULES", "FINITE", "MAX_SEED", "NON_NEGATIVE", "POSITIVE", "POSITIVE_INT",
           "PUSH_KINDS", "PUSH_SPEED", "DYNAMICS_OFF", "DYNAMICS_RANGES", "START_VEL_STD", "Range",
           "check_actuator_ranges", "check_dynamics_ranges", "check_push_settings", "check_sensor_noise",
           "TRAINED_UNDER_RULES", "OPTIONAL_ITEMS", "check_env_value", "check_seed", "plain_number", "positive_count",
           "trained_under_problems"]


def plain_number(value: Any) -> Any:
    """``value`` as a plain Python value where it is a numpy scalar, or a 0-d numpy array or torch tensor
    (``value.item()``), else ``value`` itself. Every number check of the configs reads values through this, so a
    sweep's ``np.float32(0.5)`` or ``torch.tensor(0.5)`` is taken alike on every path (the whole tree, one section,
    the runtime's settings) and stored as a plain number. Duck-typed: this module imports neither numpy nor torch."""
    if getattr(value, "ndim", None) == 0 and callable(getattr(value, "item", None)):
        try:
            return value.item()
        except (TypeError, ValueError, RuntimeError):  # e.g. a tensor without data (device "meta"): left to refuse
            return value
    return value


def positive_count(num_envs: Any, fix: str = "") -> int:
    """``num_envs`` as a plain int >= 1, read as the config reads numbers (:func:`plain_number`: a numpy integer or a
    0-d integer array or tensor is the int it holds), or a ``ValueError`` naming the value, then ``fix`` (the
    caller's advice, e.g. "; None for the run's env.num_envs"). ``operator.index`` would also take
    ``torch.tensor(True)`` (1 world) and a 1-element tensor of shape (1,), which the config refuses."""
    plain = plain_number(num_envs)
    if isinstance(plain, bool) or not isinstance(plain, int) or plain <= 0:
        shaped = getattr(num_envs, "ndim", 0) or 0
        hint = f" (an array or tensor of shape {tuple(num_envs.shape)}: pass the count itself)" if shaped else ""
        raise ValueError(f"num_envs must be a positive int (a numpy integer or 0-d integer tensor is taken too), got "
                         f"{num_envs!r}{hint}{fix}")
    return plain


@dataclass(frozen=True)
class Range:
    """A real number in ``[low, high]`` (an end excluded where ``low_open``/``high_open``), always finite, and an
    int where ``integer``. A bool is refused either way: ``True`` is not a gain. ``why``: what a value beyond a
    sanity bound would do, said in the messages (:meth:`because`)."""

    low: float = -math.inf
    high: float = math.inf
    low_open: bool = False
    high_open: bool = False
    integer: bool = False
    why: str = ""

    def allows(self, value: Any) -> bool:
        """Whether ``value`` obeys the rule (text, NaN, inf and bools do not; numpy scalars and 0-d arrays or tensors
        are read as the plain number they hold, :func:`plain_number`)."""
        value = plain_number(value)
        if isinstance(value, bool) or not isinstance(value, numbers.Integral if self.integer else numbers.Real):
            return False
        try:
            if not math.isfinite(value):
                return False
        except OverflowError:  # an int too large for a float is beyond any range here
            return False
        above = value > self.low if self.low_open else value >= self.low
        below = value < self.high if self.high_open else value <= self.high
        return above and below

    def describe(self) -> str:
        """The allowed values in words, e.g. ``"a finite number >= 0"``, ``"a finite number in [0, 100)"``."""
        kind = "an int" if self.integer else "a finite number"
        low, high = _text(self.low), _text(self.high)
        if self.low == -math.inf and self.high == math.inf:
            return kind
        if self.high == math.inf:
            return f"{kind} {'>' if self.low_open else '>='} {low}"
        if self.low == -math.inf:
            return f"{kind} {'<' if self.high_open else '<='} {high}"
        return f"{kind} in {'(' if self.low_open else '['}{low}, {high}{')' if self.high_open else ']'}"

    def because(self, *values: Any) -> str:
        """``"; <why>"`` where one of ``values`` is a finite number above the upper bound and the rule says why it
        has that bound, else ``""``: a message's ending (a NaN or text is wrong for another reason)."""
        above = [v for v in map(plain_number, values) if isinstance(v, numbers.Real) and not isinstance(v, bool)
                 and math.isfinite(v) and (v >= self.high if self.high_open else v > self.high)]
        return f"; {self.why}" if self.why and above else ""

    def check(self, value: Any, where: str) -> None:
        """Raise ``ValueError`` naming ``where``, the allowed values and ``value`` unless the rule allows it."""
        if not self.allows(value):
            raise ValueError(f"{where} must be {self.describe()}, got {value!r}{self.because(value)}")


def _text(bound: float) -> str:
    return str(int(bound)) if float(bound).is_integer() else repr(bound)


FINITE = Range()
NON_NEGATIVE = Range(low=0.0)
POSITIVE = Range(low=0.0, low_open=True)
POSITIVE_INT = Range(low=1, integer=True)

#: The rule of each numeric env config value, by its path in the env tree (``TocabiWalkConfig``); a tuple value's
#: rule holds for every entry. ``runtime/contract.py`` checks the contract fields that carry these values with the
#: same rules (its ``ENV_FIELDS``).
ENV_RULES: dict[str, Range] = {
    "sim.substeps": POSITIVE_INT,
    "task.phase_rate_gain": Range(low=0.0, high=100.0, high_open=True),
    "task.min_pelvis_height": NON_NEGATIVE,
    "task.min_neck_height": NON_NEGATIVE,
    "task.max_neck_angle": Range(low=0.0, high=math.pi, why="the neck's rotation from upright (yaw included) is at "
                                 "most π rad (180°), so a larger threshold never ends an episode: give it in rad "
                                 "(1.0 rad is 57°)"),
    "control.pd_kp": NON_NEGATIVE,
    "control.pd_kv": NON_NEGATIVE,
    "control.pd_action_scale": NON_NEGATIVE,
    "control.pd_nominal": FINITE,
    "control.mb_omega": NON_NEGATIVE,
    "control.mb_zeta": NON_NEGATIVE,
    "control.mb_residual_gain": NON_NEGATIVE,
    "control.mb_ref_window": POSITIVE,
}


def check_env_value(path: str, value: Any, where: str | None = None) -> None:
    """Raise ``ValueError`` unless ``value`` (every entry of a tuple or list) obeys the rule of the env config value
    at ``path`` (:data:`ENV_RULES`); the message names ``where`` (default ``env.<path>``), entry ``[i]`` included."""
    rule = ENV_RULES[path]
    where = where or f"env.{path}"
    if isinstance(value, (tuple, list)):
        for i, v in enumerate(value):
            rule.check(v, f"{where}[{i}]")
    else:
        rule.check(value, where)


#: The largest seed: the env keeps its seed in an int64 tensor (``envs/tocabi_walk.py``).
MAX_SEED = 2**63 - 1
#: How a kick acts (``PushConfig.kind``, the contract's ``trained_under.pushes.kind``): "force" on the pelvis alone, or
#: "velocity", every body's mass × one acceleration (envs/pushes.py).
PUSH_KINDS = ("force", "velocity")


#: ``SensorNoiseConfig.base_rpy_bias`` [rad]: a half-width beyond π would bias an angle by more than one turn, which
#: the (−π, π] wrap of the observed angles cannot take back (a bias of π already reaches every angle).
RPY_BIAS = Range(low=0.0, high=math.pi)

#: ``PushConfig.calm_fraction``: the probability of an episode without kicks; 1 would be no kicks (``count`` 0).
CALM_FRACTION = Range(low=0.0, high=1.0, high_open=True)

#: The fastest kick [m/s] (``PushConfig.speed``, ``PushSettings.speed``, a contract's ``trained_under.pushes
#: .speed_mps``): a sanity bound, far above any kick a walking robot recovers from, that catches a typo such as
#: ``speed=(0.4, 140)``, which ran and launched the robot.
PUSH_SPEED = Range(low=0.0, high=10.0, why="a kick above 10 m/s launches the 104.5 kg robot (the robust gait test "
                   "kicks at 0.5 and 1 m/s, the TOCABI lab's largest impulse, 250 N·s, is about 2.4 m/s): a typo?")

#: The identity of each range of the per-world dynamics (``DynamicsRandomization``, ``DynamicsSettings``): the value
#: that changes nothing.
DYNAMICS_OFF = {"mass_scale": (1.0, 1.0), "joint_damping": (0.0, 0.0), "armature_scale": (1.0, 1.0),
                "friction_scale": (1.0, 1.0)}
#: The rule of each end of each range of the per-world dynamics: the env's ``DynamicsRandomization``, the torch-free
#: runtime's ``DynamicsSettings`` and a contract's ``trained_under.dynamics.<name>.range`` all check with these. The
#: upper bounds are sanity bounds, generous against any randomisation (the TOCABI lab's: mass and armature ×0.8-1.2,
#: damping +0-2.9 N·m·s/rad), that catch a typo such as ``mass_scale=(0.8, 12)``, which ran and simulated nonsense.
DYNAMICS_RANGES: dict[str, Range] = {
    "mass_scale": Range(low=0.0, low_open=True, high=5.0,
                        why="links above 5x their mass (a robot of over 500 kg) leave the leg motors (166-333 N·m) "
                            "nothing to walk with: a typo?"),
    "joint_damping": Range(low=0.0, high=100.0,
                           why="100 N·m·s/rad added already resists a joint at 3 rad/s with 300 N·m, about a leg "
                               "motor's whole torque (166-333 N·m): a typo?"),
    "armature_scale": Range(low=0.0, high=5.0,
                            why="above 5x the model's reflected rotor inertia (up to 1.09 kg·m² at a knee) the "
                                "joints answer their motors like no motor of this robot: a typo?"),
    "friction_scale": Range(low=0.0, high=5.0,
                            why="above 5x the model's sliding friction (1.0) the feet are glued to the floor: a "
                                "typo?"),
}


def _pair_problem(pair: Any, rule: Range) -> str | None:
    """What is wrong with ``(low, high)`` under ``rule`` (each end obeys it, low <= high), or None: ``"shape"``
    (not two entries), ``"ends"`` (an end breaks the rule below or is no finite number), ``"bound"`` (only above
    ``rule.high``, the sanity bound), ``"order"`` (low > high)."""
    if isinstance(pair, (str, bytes)) or not hasattr(pair, "__len__") or len(pair) != 2:
        return "shape"
    if not all(replace(rule, high=math.inf, high_open=False).allows(v) for v in pair):
        return "ends"
    if not all(rule.allows(v) for v in pair):
        return "bound"
    return "order" if plain_number(pair[0]) > plain_number(pair[1]) else None


def check_dynamics_ranges(dynamics: Any, prefix: str) -> None:
    """Raise ``ValueError`` naming the first bad range (``{prefix}<name>``) of the per-world dynamics and what it
    takes (:data:`DYNAMICS_RANGES`), as ``DynamicsRandomization`` (the env's) and ``DynamicsSettings`` (the
    torch-free runtime's) both hold them: each ``(low, high)`` with both ends obeying the range's rule, low <= high."""
    for name, rule in DYNAMICS_RANGES.items():
        value = getattr(dynamics, name)
        problem = _pair_problem(value, rule)
        if problem == "bound":
            raise ValueError(f"{prefix}{name} is {value!r}, above the bound {_text(rule.high)}{rule.because(*value)}")
        if problem is not None:
            low = f"0 {'<' if rule.low_open else '<='} low"
            raise ValueError(f"{prefix}{name} must be (low, high) with {low} <= high <= {_text(rule.high)}, finite, "
                             f"got {value!r} ({DYNAMICS_OFF[name]} turns it off)")


#: The start time [s] of a calm episode's kicks, past any episode: the env's ``Pushes`` and the torch-free runtime's
#: ``PushSchedule`` both give a calm episode's kicks this time, so that none ever begins.
CALM_NEVER_S = 1.0e9


def check_push_settings(pushes: Any, prefix: str) -> None:
    """Raise ``ValueError`` naming the first bad field (``{prefix}<name>``) of a kicks' settings and what it takes:
    ``count``, ``window``, ``speed``, ``duration``, ``kind`` and ``calm_fraction`` as ``PushConfig`` (the env's) and
    ``PushSettings`` (the torch-free runtime's) both hold them."""
    count = plain_number(pushes.count)
    if isinstance(count, bool) or not isinstance(count, int) or not 0 <= count <= 64:
        raise ValueError(f"{prefix}count must be an int in [0, 64] (kicks per episode), got {count!r}")
    for name, unit, rule in (("window", "s", NON_NEGATIVE), ("speed", "m/s", PUSH_SPEED),
                             ("duration", "s", NON_NEGATIVE)):
        pair = getattr(pushes, name)
        # Checked whole, not unpacked: a lone number (speed=1.0), three numbers or text failed as a raw unpack or
        # comparison error without the field's name, and a bool passed as 0 or 1.
        problem = _pair_problem(pair, rule)
        if problem == "bound":
            raise ValueError(f"{prefix}{name} is {pair!r}, above the bound {_text(rule.high)} {unit}"
                             f"{rule.because(*pair)}")
        if problem is not None:
            fix = (f"; swapped? give ({pair[1]!r}, {pair[0]!r})" if problem == "order" else
                   f"; for one value give it twice, e.g. ({pair!r}, {pair!r})" if rule.allows(pair) else "")
            raise ValueError(f"{prefix}{name} must be (low, high) with 0 <= low <= high, finite [{unit}], got "
                             f"{pair!r}{fix}")
    if pushes.kind not in PUSH_KINDS:
        raise ValueError(f"{prefix}kind must be one of {PUSH_KINDS} (force: on the pelvis; velocity: the whole "
                         f"robot's velocity), got {pushes.kind!r}")
    if not CALM_FRACTION.allows(pushes.calm_fraction):
        raise ValueError(f"{prefix}calm_fraction must be {CALM_FRACTION.describe()} (the probability of an episode "
                         f"without kicks; for no kicks at all set count 0), got {pushes.calm_fraction!r}")


#: A contract's ``trained_under.actuators.delay.applied``: how the delayed torque reaches the joint, in each
#: physics substep (``Delay``; the value when the field is left out) or as its mean over each control period
#: (``AveragedDelay``, ``ActuatorConfig.delay_average``).
DELAY_APPLIED = ("substep", "period_mean")


def delay_grid_problem(low: int, high: int, stride: Any) -> str | None:
    """What is wrong with a torque delay grid ``{low, low + stride, ..., high}`` [substeps], or None: the stride is a
    whole number >= 1 that divides ``high - low``. The one rule of the training config
    (``ActuatorConfig.delay_stride``) and a contract's ``trained_under.actuators.delay.stride_substeps``."""
    if isinstance(stride, bool) or not isinstance(stride, numbers.Integral) or stride < 1:
        return f"stride {stride!r} must be a whole number of substeps >= 1"
    if (int(high) - int(low)) % int(stride):
        example = low + stride * max(1, (high - low) // stride)
        return (f"stride {stride} does not divide the delay range ({low}, {high}) (high - low = {high - low}); pick "
                f"a range whose width is a multiple of it, e.g. ({low}, {example})")
    return None


def check_seed(seed: Any, where: str = "seed") -> int:
    """``seed`` as a plain int, or a ``ValueError`` naming ``where``: a seed is an int in [0, 2**63 - 1] (numpy
    ints too; bools, floats and text are refused). The one rule of every place a seed enters: the env's constructor,
    ``set_seed``, ``reset(seed=...)``, ``make_env`` and the run config's ``seed``."""
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or not 0 <= seed <= MAX_SEED:
        raise ValueError(f"{where} must be an int in [0, 2**63 - 1] (the env keeps it as a 64-bit int; not a bool, "
                         f"a float or text), got {seed!r}; give e.g. {where}=0")
    return int(seed)


#: The longest torque delay [physics substeps] the actuator layer takes (``ActuatorConfig.delay_substeps``, a
#: contract's ``trained_under.actuators.delay.substeps``): it keeps that many past torques of every robot.
MAX_DELAY_SUBSTEPS = 400


def check_actuator_ranges(actuators: Any, prefix: str) -> None:
    """Raise ``ValueError`` naming the first bad field (``{prefix}<name>``) of the legs' actuator layer and what it
    takes, as ``ActuatorConfig`` (the env's) and ``ActuatorSettings`` (the torch-free runtime's) both hold it: each
    range (low, high) with 0 <= low <= high, finite; the delay in whole substeps up to :data:`MAX_DELAY_SUBSTEPS`, on
    a grid its stride divides; ``delay_average`` a bool; neither it nor a stride without a delay."""
    for name in ("delay_substeps", "motor_constant", "coulomb", "viscous"):
        try:  # a scalar or a wrong count failed as a raw unpack error
            low, high = (float(v) for v in getattr(actuators, name))
        except (TypeError, ValueError):
            raise ValueError(f"{prefix}{name} must be two numbers (low, high), got "
                             f"{getattr(actuators, name)!r}") from None
        if not (math.isfinite(low) and math.isfinite(high)) or low < 0 or low > high:
            raise ValueError(f"{prefix}{name} must be (low, high) with 0 <= low <= high, finite, "
                             f"got {getattr(actuators, name)!r}")
    delay = actuators.delay_substeps
    if any(isinstance(v, bool) or int(v) != v for v in delay):
        raise ValueError(f"{prefix}delay_substeps takes whole substeps, got {delay!r}")
    if delay[1] > MAX_DELAY_SUBSTEPS:
        raise ValueError(f"{prefix}delay_substeps {delay!r} reaches past "
                         f"{MAX_DELAY_SUBSTEPS} substeps (0.2 s at 0.5 ms): the delay keeps that many past torques "
                         "of every world in memory; the TOCABI lab's delay is 4-20 substeps")
    problem = delay_grid_problem(*(int(v) for v in delay), actuators.delay_stride)
    if problem:
        raise ValueError(f"{prefix}delay_stride: {problem}")
    if not isinstance(actuators.delay_average, bool):
        raise ValueError(f"{prefix}delay_average must be True or False, got {actuators.delay_average!r}")
    if tuple(delay) == (0, 0) and (actuators.delay_average or actuators.delay_stride != 1):
        # Both shape the delay; without one they would be silently ignored.
        raise ValueError(f"{prefix}delay_average {actuators.delay_average} / delay_stride "
                         f"{actuators.delay_stride} shape a torque delay, but delay_substeps is (0, 0): set a delay "
                         "(e.g. delay_substeps=(4, 20)) or leave them at False / 1")


def check_sensor_noise(sensors: Any, prefix: str) -> None:
    """Raise ``ValueError`` naming the first bad value (``{prefix}<name>``) of the sensor biases and noise, as
    ``SensorNoiseConfig`` (the env's) and ``SensorSettings`` (the torch-free runtime's) both hold them (dataclasses of
    the same fields): every bias and σ a finite number >= 0, every clip None or > 0, the IMU bias at most π."""
    for f in fields(sensors):
        value = getattr(sensors, f.name)
        if value is None and f.name.endswith("_clip"):
            continue
        ok = (not isinstance(value, bool) and isinstance(value, numbers.Real) and math.isfinite(value)
              and (value > 0 if f.name.endswith("_clip") else value >= 0))
        if not ok:
            what = ("a finite number > 0, or None for no clip" if f.name.endswith("_clip")
                    else "a finite number >= 0 (0 = off)")
            raise ValueError(f"{prefix}{f.name} must be {what}, got {value!r}")
    RPY_BIAS.check(sensors.base_rpy_bias, f"{prefix}base_rpy_bias")


#: The std of the start velocities (``TaskConfig.start_joint_vel_std`` [rad/s] and ``start_base_vel_std`` [m/s], the
#: runtime's ``StartVelocity``, a contract's ``trained_under.start_velocity``).
START_VEL_STD = Range(low=0.0, high=10.0)

#: The ``trained_under`` section of a policy contract (what the policy was trained under: actuator layer, dynamics,
#: sensor noise, pushes, start velocities; ``runtime/randomization.py`` writes and reads it) -> per item, the rule of
#: each numeric field, and whether the field is a ``[low, high]`` pair (then low <= high too), may be null or may be
#: left out ("optional": its default then). An item
#: is the text ``"off"`` or an object with these fields (other fields are descriptive text). The bounds are the
#: training config's own (``ActuatorConfig``, ``DynamicsRandomization``, ``SensorNoiseConfig``, ``PushConfig``,
#: ``TaskConfig.start_*_vel_std``), so a value training refuses is refused in a contract too.
TRAINED_UNDER_RULES: dict[str, dict[str, dict[str, tuple[Range, str]]]] = {
    "actuators": {
        "delay": {"substeps": (Range(low=0, high=MAX_DELAY_SUBSTEPS, integer=True), "pair"),
                  "ms": (NON_NEGATIVE, "pair"),
                  "stride_substeps": (Range(low=1, integer=True), "optional")},
        "motor_constant": {"range": (NON_NEGATIVE, "pair")},
        "friction": {"coulomb_nm": (NON_NEGATIVE, "pair"), "viscous_nms_per_rad": (NON_NEGATIVE, "pair")},
        "saturation": {},
    },
    "dynamics": {name: {"range": (rule, "pair")} for name, rule in DYNAMICS_RANGES.items()},
    "sensor_noise": {
        "joint_pos_bias": {"half_width": (NON_NEGATIVE, "one")},
        "joint_pos_noise": {"std": (NON_NEGATIVE, "one"), "clip": (POSITIVE, "nullable")},
        "joint_vel_noise": {"std": (NON_NEGATIVE, "one"), "clip": (POSITIVE, "nullable")},
        "base_rpy_bias": {"half_width": (RPY_BIAS, "one")},
        "foot_force_bias": {"half_width": (NON_NEGATIVE, "one")},
        "foot_torque_bias": {"half_width": (NON_NEGATIVE, "one")},
        "base_lin_vel_bias": {"half_width": (NON_NEGATIVE, "one")},
        "base_lin_vel_noise": {"std": (NON_NEGATIVE, "one"), "clip": (POSITIVE, "nullable")},
        "base_ang_vel_bias": {"half_width": (NON_NEGATIVE, "one")},
        "base_ang_vel_noise": {"std": (NON_NEGATIVE, "one"), "clip": (POSITIVE, "nullable")},
    },
    "pushes": {
        "pushes": {"count": (Range(low=1, high=64, integer=True), "one"), "window_s": (NON_NEGATIVE, "pair"),
                   "speed_mps": (PUSH_SPEED, "pair"), "duration_s": (NON_NEGATIVE, "pair"),
                   "robot_mass_kg": (POSITIVE, "one"), "ramp_env_steps": (Range(low=0, integer=True), "pair"),
                   "calm_fraction": (CALM_FRACTION, "optional")},
    },
    "start_velocity": {
        "start_velocity": {"joint_std_radps": (START_VEL_STD, "one"), "base_std_mps": (START_VEL_STD, "one")},
    },
}


#: Items of a ``trained_under`` group that may be left out, read as "off": added after contracts were first written
#: (the pelvis velocity's sensor noise), so a contract of before, or of a policy without them, states nothing of them.
OPTIONAL_ITEMS: dict[str, tuple[str, ...]] = {
    "sensor_noise": ("base_lin_vel_bias", "base_lin_vel_noise", "base_ang_vel_bias", "base_ang_vel_noise")}


def trained_under_problems(section: Any, where: str = "trained_under") -> list[str]:
    """What is wrong with a contract's ``trained_under`` section, each as ``"<path> is <value> but must be ..."``
    (empty when nothing is): every group of :data:`TRAINED_UNDER_RULES` present, each item ``"off"`` or an object
    with its numeric fields finite, obeying their rule, and each ``[low, high]`` pair ordered (low <= high); an
    unknown item or group that is an object (a randomisation this reader would not apply) is refused, text beside is
    not. The ``pushes`` and ``start_velocity`` groups are one item each, written directly as the group's value."""
    if not isinstance(section, dict):
        return [f"{where} is {type(section).__name__}, not an object"]
    problems = []
    unknown = sorted(k for k in set(section) - set(TRAINED_UNDER_RULES) if isinstance(section[k], dict))
    if unknown:  # a group of randomisation this reader does not know: as an unknown item, refused
        problems.append(f"{where} states {unknown}, which this reader cannot apply (it knows "
                        f"{sorted(TRAINED_UNDER_RULES)})")
    for group, items in TRAINED_UNDER_RULES.items():
        if group not in section:
            problems.append(f"{where}.{group} is missing")
            continue
        single = list(items) == [group]
        node = {group: section[group]} if single else section[group]
        path = where if single else f"{where}.{group}"
        if not isinstance(node, dict):
            problems.append(f"{path} is {node!r}, not an object of items")
            continue
        # Text beside the items describes them; an unknown item that is on states something the reader would miss.
        unknown = sorted(k for k in set(node) - set(items) if isinstance(node[k], dict))
        if unknown:
            problems.append(f"{path} states {unknown}, which this reader cannot apply (it knows {sorted(items)})")
        for item, rules in items.items():
            value = node.get(item, "off" if item in OPTIONAL_ITEMS.get(group, ()) else None)
            if value == "off":
                continue
            if not isinstance(value, dict):
                problems.append(f"{path}.{item} is {value!r} but must be \"off\" or an object")
                continue
            for name, (rule, shape) in rules.items():
                problems.extend(_field_problems(value.get(name, "missing"), rule, shape, f"{path}.{item}.{name}"))
    return problems


def _field_problems(value: Any, rule: Range, shape: str, where: str) -> list[str]:
    if (shape == "nullable" and value is None) or (shape == "optional" and value == "missing"):
        return []
    if shape != "pair":
        return [] if rule.allows(value) else [f"{where} is {value!r} but must be {rule.describe()}"]
    if not isinstance(value, list) or len(value) != 2:
        return [f"{where} is {value!r} but must be a [low, high] pair"]
    bad = [v for v in value if not rule.allows(v)]
    if bad:
        return [f"{where} is {value!r} but each end must be {rule.describe()}{rule.because(*value)}"]
    if value[0] > value[1]:
        return [f"{where} is {value!r}: low > high (swapped?)"]
    return []
