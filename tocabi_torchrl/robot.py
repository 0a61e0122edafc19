"""TOCABI facts in one place: joint order, groups, limits, initial pose, gains and names.

Everything else in the package (simulator, environment, motion, transforms) reads its robot numbers from here, so a
change of robot touches one file. Numbers follow the task specification (robot §1, reset §4, PD §6); angles are in
radians, torques in N·m, masses in kg, lengths in m.

Joint index ``j`` (0..32) maps to ``qpos[7 + j]`` and ``qvel[6 + j]``; the free base occupies ``qpos[0:7]``
(position, then quaternion w, x, y, z) and ``qvel[0:6]`` (world linear velocity, then local angular velocity).
"""

from __future__ import annotations

import functools
import hashlib
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = [
    "JOINT_NAMES",
    "ACTUATOR_NAMES",
    "NUM_JOINTS",
    "NUM_LEG_JOINTS",
    "LEG_JOINT_IDS",
    "UPPER_JOINT_IDS",
    "LEGS",
    "UPPER_BODY",
    "MIRROR_JOINT",
    "MIRROR_SIGN",
    "TORQUE_LIMITS",
    "LEG_TORQUE_LIMITS",
    "INIT_JOINT_POS",
    "INIT_BASE_POS",
    "INIT_QPOS",
    "UPPER_KP",
    "UPPER_KV",
    "LEG_KP",
    "LEG_KV",
    "NOMINAL_MASS",
    "GRAVITY",
    "FOOT_BODIES",
    "FOOT_SITES",
    "FOOT_FORCE_SENSORS",
    "FOOT_TORQUE_SENSORS",
    "BASE_BODY",
    "NECK_BODY",
    "PELVIS_IMU_SITE",
    "GROUND_GEOM",
    "GROUND_FORBIDDEN_BODIES",
    "SELF_COLLISION_BODIES",
    "RobotAssetError",
    "angle_unit_problem",
    "initial_pose_range_problem",
    "motion_range_problem",
    "asset_path",
    "load_model",
    "load_spec",
    "missing_names",
    "validate_model",
    "initial_sole_centre",
]

NUM_JOINTS = 33
NUM_LEG_JOINTS = 12

#: Hinge joints in qpos order (spec §1.3).
JOINT_NAMES: tuple[str, ...] = (
    "L_HipYaw_Joint", "L_HipRoll_Joint", "L_HipPitch_Joint", "L_Knee_Joint", "L_AnklePitch_Joint", "L_AnkleRoll_Joint",
    "R_HipYaw_Joint", "R_HipRoll_Joint", "R_HipPitch_Joint", "R_Knee_Joint", "R_AnklePitch_Joint", "R_AnkleRoll_Joint",
    "Waist1_Joint", "Waist2_Joint", "Upperbody_Joint",
    "L_Shoulder1_Joint", "L_Shoulder2_Joint", "L_Shoulder3_Joint", "L_Armlink_Joint",
    "L_Elbow_Joint", "L_Forearm_Joint", "L_Wrist1_Joint", "L_Wrist2_Joint",
    "Neck_Joint", "Head_Joint",
    "R_Shoulder1_Joint", "R_Shoulder2_Joint", "R_Shoulder3_Joint", "R_Armlink_Joint",
    "R_Elbow_Joint", "R_Forearm_Joint", "R_Wrist1_Joint", "R_Wrist2_Joint",
)  # fmt: skip

#: One actuator per joint, same order; named after the joint with ``_Motor``.
ACTUATOR_NAMES: tuple[str, ...] = tuple(n.replace("_Joint", "_Motor") for n in JOINT_NAMES)

LEG_JOINT_IDS: tuple[int, ...] = tuple(range(NUM_LEG_JOINTS))
UPPER_JOINT_IDS: tuple[int, ...] = tuple(range(NUM_LEG_JOINTS, NUM_JOINTS))
#: The leg joints / the upper-body joints as one slice of a joint-ordered dimension (basic indexing: a view, and no
#: index tensor to copy to the device).
LEGS = slice(0, NUM_LEG_JOINTS)
UPPER_BODY = slice(NUM_LEG_JOINTS, NUM_JOINTS)

_SIDE = tuple(range(6)), tuple(range(15, 23))  # a leg's 6 joints, an arm's 8: left at i, right at i + 6 / i + 10
#: Left-right mirror image of a joint configuration (reflection y -> -y about the pelvis's x-z plane): joint ``j`` of
#: the mirrored robot takes ``MIRROR_SIGN[j] * q[MIRROR_JOINT[j]]``. Left and right joints swap; the waist and the neck
#: map to themselves. The signs follow from the MJCF's joint axes: the reflection ``M = diag(1, -1, 1)`` turns a
#: rotation by θ about the world axis ``a`` into one by −θ about ``M·a``, so a partner joint whose axis is ``M·a`` takes
#: −θ and one whose axis is ``−M·a`` takes +θ. Hence the roll- and yaw-type joints (axis along x or z) flip, the legs'
#: pitch joints (y axes on both sides) keep their sign, and every arm joint flips (the right arm's y axes point the
#: other way). ``tests/test_symmetry.py`` derives these from the compiled model's world axes at ``qpos0``.
MIRROR_JOINT: tuple[int, ...] = (
    tuple(i + 6 for i in _SIDE[0]) + _SIDE[0] + (12, 13, 14) + tuple(i + 10 for i in _SIDE[1]) + (23, 24) + _SIDE[1]
)
#: See :data:`MIRROR_JOINT`; leg order hip yaw, hip roll, hip pitch, knee, ankle pitch, ankle roll.
MIRROR_SIGN: tuple[float, ...] = (
    (-1.0, -1.0, 1.0, 1.0, 1.0, -1.0) * 2 + (-1.0, 1.0, -1.0) + (-1.0,) * 8 + (-1.0, 1.0) + (-1.0,) * 8
)

_ARM_LIMITS = (64.0, 64.0, 64.0, 64.0, 23.0, 23.0, 10.0, 10.0)
#: Actuator torque limits [N·m] (spec §1.4), joint order.
TORQUE_LIMITS: np.ndarray = np.array(
    (333.0, 232.0, 263.0, 289.0, 222.0, 166.0) * 2 + (303.0,) * 3 + _ARM_LIMITS + (10.0, 10.0) + _ARM_LIMITS
)
LEG_TORQUE_LIMITS: np.ndarray = TORQUE_LIMITS[:NUM_LEG_JOINTS].copy()

_LEG_INIT = (0.0, 0.0, -0.24, 0.6, -0.36, 0.0)
#: Initial joint positions [rad] (spec §4): the nominal crouch, arms down, head straight.
INIT_JOINT_POS: np.ndarray = np.array(
    _LEG_INIT * 2
    + (0.0, 0.0, 0.0)
    + (0.3, 0.3, 1.5, -1.27, -1.0, 0.0, -1.0, 0.0)
    + (0.0, 0.0)
    + (-0.3, -0.3, -1.5, 1.27, 1.0, 0.0, 1.0, 0.0)
)
#: Initial base position [m]; the soles start ~1.3 mm above the ground.
INIT_BASE_POS: np.ndarray = np.array((0.0, 0.0, 0.92983))
#: Full initial qpos (40): base position, identity quaternion (w, x, y, z), joints.
INIT_QPOS: np.ndarray = np.concatenate((INIT_BASE_POS, (1.0, 0.0, 0.0, 0.0), INIT_JOINT_POS))

_ARM_KP = (400.0, 1000.0, 400.0, 400.0, 400.0, 400.0, 100.0, 100.0)
_ARM_KV = (10.0, 28.0, 10.0, 10.0, 10.0, 10.0, 3.0, 3.0)
#: Upper-body PD gains (21 joints, indices 12..32): Kp [N·m/rad], Kv [N·m·s/rad] (spec §6).
UPPER_KP: np.ndarray = np.array((6000.0, 10000.0, 10000.0) + _ARM_KP + (100.0, 100.0) + _ARM_KP)
UPPER_KV: np.ndarray = np.array((200.0, 100.0, 100.0) + _ARM_KV + (2.0, 2.0) + _ARM_KV)
#: Leg PD gains of the reference robot controller (12 joints). The torque task does not use them; the PD control
#: mode and the standing tests do.
LEG_KP: np.ndarray = np.array((2000.0, 5000.0, 4000.0, 3700.0, 3200.0, 3200.0) * 2)
LEG_KV: np.ndarray = np.array((15.0, 50.0, 20.0, 25.0, 24.0, 24.0) * 2)

#: Total mass [kg] of the nominal robot (sum of body masses) and gravity [m/s²].
NOMINAL_MASS = 104.48712
GRAVITY = 9.81

BASE_BODY = "base_link"
NECK_BODY = "Neck_Link"
PELVIS_IMU_SITE = "Pelvis_IMU"
GROUND_GEOM = "ground"
#: (left, right) in every pair below.
FOOT_BODIES = ("L_Foot_Link", "R_Foot_Link")
FOOT_SITES = ("LF_FT", "RF_FT")
FOOT_FORCE_SENSORS = ("LF_Force_sensor", "RF_Force_sensor")
FOOT_TORQUE_SENSORS = ("LF_Torque_sensor", "RF_Torque_sensor")

_SIDE_LEG_UPPER = ("HipRoll", "HipCenter", "Thigh", "Knee")
_SIDE_ARM = ("Shoulder1", "Shoulder2", "Shoulder3", "Armlink", "Elbow", "Forearm", "Wrist1", "Wrist2")
#: Bodies whose contact with the ground ends an episode (spec §9.1.1). Feet, ankles, neck and head are allowed.
GROUND_FORBIDDEN_BODIES: tuple[str, ...] = (
    (BASE_BODY,)
    + tuple(f"{s}_{b}_Link" for s in "LR" for b in _SIDE_LEG_UPPER)
    + ("Waist1_Link", "Waist2_Link", "Upperbody_Link")
    + tuple(f"{s}_{b}_Link" for s in "LR" for b in _SIDE_ARM)
)
#: Bodies whose mutual contact is a self collision (spec §9.1.2): the list above plus ankles and feet.
SELF_COLLISION_BODIES: tuple[str, ...] = GROUND_FORBIDDEN_BODIES + tuple(
    f"{s}_{b}_Link" for s in "LR" for b in ("AnkleCenter", "AnkleRoll", "Foot")
)

_ASSET_ENV = "TOCABI_TORCHRL_ASSETS"


class RobotAssetError(RuntimeError):
    """The robot model file is missing, malformed or lacks names the package relies on."""


def _assets_root() -> Path:
    """Folder holding ``tocabi/`` and ``motions/``.

    Works from a source checkout (``<repo>/assets``) and from an installed wheel, where the assets are packaged as
    ``tocabi_torchrl/_assets`` (see ``pyproject.toml``). ``$TOCABI_TORCHRL_ASSETS`` overrides both.
    """
    if os.environ.get(_ASSET_ENV):
        root = Path(os.environ[_ASSET_ENV])
        # Said here, naming the variable: a mistyped folder surfaced as "robot model file not found ... (pass an
        # existing MJCF path, or None for the default)" to a caller who had passed None.
        if not (root / "tocabi").is_dir():
            raise RobotAssetError(f"${_ASSET_ENV} is {str(root)!r}, which holds no tocabi/ folder; point it at the "
                                  "folder that holds tocabi/tocabi.xml (and motions/), or unset it for the shipped "
                                  "assets")
        return root
    here = Path(__file__).resolve().parent
    for candidate in (here / "_assets", here.parent / "assets"):
        if (candidate / "tocabi").is_dir():
            return candidate
    raise RobotAssetError(
        f"cannot find the TOCABI assets next to {here} (looked for _assets/ and ../assets/); reinstall the package "
        f"or set ${_ASSET_ENV} to the folder that contains tocabi/tocabi.xml"
    )


def asset_path(*parts: str) -> Path:
    """Path of a shipped asset, e.g. ``asset_path("tocabi", "tocabi.xml")`` or ``asset_path("motions", ...)``."""
    return _assets_root().joinpath(*parts)


def _resolve_model_path(path: str | os.PathLike | None) -> Path:
    p = Path(path) if path is not None else asset_path("tocabi", "tocabi.xml")
    if not p.is_file():
        raise RobotAssetError(f"robot model file not found: {p} (pass an existing MJCF path, or None for the default)")
    return p


def load_spec(path: str | os.PathLike | None = None) -> "mujoco.MjSpec":  # noqa: F821
    """Parse the MJCF into a ``mujoco.MjSpec`` for scene edits (obstacles, extra sensors) before compiling.

    Raises :class:`RobotAssetError` for a file MuJoCo cannot parse, or one that compiles its radian joint ranges
    as degrees (see :func:`load_model`)."""
    import mujoco

    p = _resolve_model_path(path)
    try:
        spec = mujoco.MjSpec.from_file(str(p))
    except Exception as err:  # mujoco raises ValueError with the parser message
        raise RobotAssetError(f"cannot parse robot model {p}: {err}") from err
    _check_angle_unit(spec, str(p))
    return spec


def load_model(path: str | os.PathLike | None = None, validate: bool = True) -> "mujoco.MjModel":  # noqa: F821
    """Compile the robot model (default: the shipped ``assets/tocabi/tocabi.xml``) and check its names.

    With ``validate``, also refuse a file that reads its joint ranges as degrees (``<compiler angle="degree">``,
    MuJoCo's default when ``<compiler>`` sets no angle) while they are written in radians: every range would shrink
    by 180/π and leave out the robot's initial pose."""
    import mujoco

    p = _resolve_model_path(path)
    try:
        model = mujoco.MjModel.from_xml_path(str(p))
    except Exception as err:
        raise RobotAssetError(f"cannot compile robot model {p}: {err}") from err
    if validate:
        if _initial_pose_outside_ranges(model):
            # Only then is the file parsed again: the compiled model no longer says which unit it was read in.
            _check_angle_unit(mujoco.MjSpec.from_file(str(p)), str(p))
        validate_model(model, source=str(p))
    return model


#: |range| [rad] up to which a file's joint range numbers read as radians: a full turn (and rounding).
_RADIAN_LIKE = 2.0 * np.pi + 0.01


def _initial_pose_outside_ranges(model: "mujoco.MjModel") -> bool:  # noqa: F821
    """Whether a limited TOCABI joint of the compiled ``model`` has its ``INIT_JOINT_POS`` entry outside its range."""
    import mujoco

    for q, name in zip(INIT_JOINT_POS, JOINT_NAMES):
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid >= 0 and model.jnt_limited[jid] and not model.jnt_range[jid, 0] <= q <= model.jnt_range[jid, 1]:
            return True
    return False


def _check_angle_unit(spec: "mujoco.MjSpec", source: str) -> None:  # noqa: F821
    """:class:`RobotAssetError` with :func:`angle_unit_problem`'s message, if it finds one."""
    problem = angle_unit_problem(spec, source)
    if problem is not None:
        raise RobotAssetError(problem)


def angle_unit_problem(spec: "mujoco.MjSpec", source: str, joint_names: Sequence[str] = JOINT_NAMES,  # noqa: F821
                       initial=INIT_JOINT_POS, initial_name: str = "robot.INIT_JOINT_POS") -> str | None:
    """What is wrong with a model file that MuJoCo reads in degrees while its joint ranges are written in radians, or
    None when nothing is.

    Such a file (``<compiler angle="degree">``, or no angle: MuJoCo's default) compiles each range 180/π times too
    narrow (the shipped ±3.14 becomes ±0.055 rad), leaving out the initial pose. Not caught, it surfaced later as a
    reference motion or a PD nominal pose "outside the model's range", blaming the motion or the pose. A file in
    degrees with its ranges in degrees passes; one that mixes the units (ranges beyond a full turn, so in degrees,
    beside ranges that hold the initial pose only when read as radians) is named as such, with the joint to rewrite.
    Reads the uncompiled ``spec`` only (the compiled model no longer says which unit it was read in); imports mujoco
    and numpy only, so the torch-free runtime uses it too.

    Args:
        spec: the parsed, uncompiled model file.
        source: the model file, as the message names it.
        joint_names: (J,) the joints to look at; names the file lacks are skipped.
        initial: (J,) the initial pose [rad] of those joints, which every compiled range must hold.
        initial_name: where ``initial`` comes from, as the message names it.
    """
    import mujoco

    if not spec.compiler.degree:
        return None
    ranged = []  # (name, initial position [rad], range as written)
    for q, name in zip(initial, joint_names):
        joint = spec.joint(name)
        if joint is not None and joint.limited != mujoco.mjtLimited.mjLIMITED_FALSE and joint.range[0] < joint.range[1]:
            ranged.append((name, float(q), (float(joint.range[0]), float(joint.range[1]))))
    # A range with a number beyond a full turn is in degrees: only degrees make sense of it.
    in_degrees = [(name, r) for name, _, r in ranged if max(abs(v) for v in r) > _RADIAN_LIKE]
    # A joint is blamed only where its range, read in degrees, leaves out the initial pose that its numbers read as
    # radians hold: such a model is refused either way (the pose is outside its compiled range), so no usable file
    # is; the check just names the unit rather than the range. A file in degrees throughout passes, tiny ranges
    # that hold the pose included.
    radian_like = [(name, q, (lo, hi)) for name, q, (lo, hi) in ranged if max(abs(lo), abs(hi)) <= _RADIAN_LIKE
                   and not np.radians(lo) <= q <= np.radians(hi) and lo <= q <= hi]
    if not radian_like:
        return None
    name, q, (lo, hi) = radian_like[0]
    lo_rad, hi_rad = np.radians(lo), np.radians(hi)
    becomes = (f"{name} range=\"{lo:g} {hi:g}\" becomes [{lo_rad:.3f}, {hi_rad:.3f}] rad, which leaves out the "
               f"initial pose's {q:.3f} rad ({initial_name}) and any walking motion")
    head = (f"robot model {source}: it is compiled with <compiler angle=\"degree\"> (MuJoCo's default when <compiler> "
            "sets no angle)")
    if not in_degrees:
        return (f"{head} but its joint ranges are written in radians: {becomes}. Set <compiler angle=\"radian\"> in "
                f"{source} (as the shipped assets/tocabi/tocabi.xml does), or write every angle of the file in degrees")
    # Mixed: switching the compiler to radians would break the ranges in degrees, so the fix is per joint.
    other, (dlo, dhi) = in_degrees[0]
    more = [n for n, _, _ in radian_like[1:]]
    also = (f" {len(more)} more joints' ranges look the same ({', '.join(more[:5])}{', ...' if len(more) > 5 else ''})."
            if more else "")
    return (f"{head} and mixes units in its joint ranges: {other} range=\"{dlo:g} {dhi:g}\" is in degrees, but "
            f"{becomes}: written in radians?{also} Write {'each such range' if more else 'it'} in degrees too "
            f"({name}: range=\"{np.degrees(lo):.6g} {np.degrees(hi):.6g}\"), as every angle of a file in degrees; or, "
            f"for radians, set <compiler angle=\"radian\"> and write every angle of {source} in radians")


def _ranges(model: "mujoco.MjModel", joint_names: Sequence[str]):  # noqa: F821
    """(low, high, limited) of the named joints of the compiled ``model``, each (J,) in ``joint_names`` order."""
    ids = [model.joint(name).id for name in joint_names]
    return model.jnt_range[ids, 0], model.jnt_range[ids, 1], model.jnt_limited[ids].astype(bool)


def initial_pose_range_problem(model: "mujoco.MjModel", model_file: str,  # noqa: F821
                               joint_names: Sequence[str] = JOINT_NAMES, initial=INIT_JOINT_POS,
                               initial_name: str = "robot.INIT_JOINT_POS") -> str | None:
    """What is wrong with a compiled ``model`` (of ``model_file``) whose joint ranges leave out the initial pose
    (beyond 1e-6 rad), or None when every limited joint holds it. Such a model holds the robot away from its start
    pose from the first step, and every metric after that measures the joint limit, not the policy.

    Args:
        model: the compiled model, with every name of ``joint_names``.
        model_file: the model file, as the message names it.
        joint_names: (J,) the joints to look at.
        initial: (J,) the initial pose [rad] of those joints.
        initial_name: where ``initial`` comes from, as the message names it.
    """
    low, high, limited = _ranges(model, joint_names)
    q = np.asarray(initial, dtype=np.float64)
    beyond = np.maximum(q - high, low - q) * limited  # (J,) [rad] past the range, <= 0 inside
    if not (beyond > 1e-6).any():
        return None
    j = int(np.argmax(beyond))
    others = f" ({int((beyond > 1e-6).sum())} joints leave out theirs)" if (beyond > 1e-6).sum() > 1 else ""
    return (f"robot model {model_file}: {joint_names[j]}'s range [{low[j]:.3f}, {high[j]:.3f}] rad leaves out the "
            f"initial pose's {q[j]:.3f} rad ({initial_name}){others}: check {joint_names[j]}'s range in the model file "
            "(radians, under <compiler angle=\"radian\">); the robot could not start from that pose")


def motion_range_problem(model: "mujoco.MjModel", model_file: str, joint_pos, motion_source: str,  # noqa: F821
                         joint_names: Sequence[str] = JOINT_NAMES, initial=INIT_JOINT_POS,
                         initial_name: str = "robot.INIT_JOINT_POS",
                         order_name: str = "robot.JOINT_NAMES") -> str | None:
    """What is wrong with a reference motion whose joint targets [rad] leave a limited joint's range in ``model``
    (the compiled ``model_file``) by more than 0.01 rad, or None when none does. Names the joint, its value and row,
    the range and both files.

    Either file may be at fault: a motion in degrees or of another robot (which the servos and the imitation reward
    would chase), or a model whose range is too narrow. A range that leaves out the robot's initial pose as well is
    the model's fault whatever the motion holds, so such a joint is named first and the message sends the user to the
    model file; otherwise it names both checks. Imports numpy only, so the torch-free runtime uses it too.

    Args:
        model: the compiled model, with every name of ``joint_names``.
        model_file: the model file, as the message names it.
        joint_pos: (R, J) the motion's joint targets [rad] in ``joint_names`` order.
        motion_source: the motion file, as the message names it.
        joint_names: (J,) the motion's joints.
        initial: (J,) the initial pose [rad] of those joints.
        initial_name: where ``initial`` comes from, as the message names it.
        order_name: where ``joint_names`` comes from, as the message names it.
    """
    low, high, limited = _ranges(model, joint_names)
    q = np.asarray(joint_pos)
    beyond = np.maximum(q - high, low - q) * limited  # (rows, J) [rad] past the range, <= 0 inside
    left = beyond.max(0) > 0.01  # (J,) the joints the motion leaves
    if not left.any():
        return None
    init = np.asarray(initial, dtype=np.float64)
    narrow = left & limited & ((init < low) | (init > high))  # ranges that leave out the start pose too
    j = int(np.argmax(np.where(narrow if narrow.any() else left, beyond.max(0), -np.inf)))
    row, name = int(np.argmax(beyond[:, j])), joint_names[j]
    others = f" ({int(left.sum())} joints leave their ranges)" if left.sum() > 1 else ""
    head = (f"reference motion {motion_source}: {name} is {q[row, j]:.3f} rad at row {row}{others}, "
            f"outside the model's range [{low[j]:.3f}, {high[j]:.3f}] in {model_file}")
    if narrow[j]:
        return (f"{head}, which leaves out the robot's initial pose ({init[j]:.3f} rad, {initial_name}) too: check "
                f"{name}'s range in the model file (radians, under <compiler angle=\"radian\">) before the motion")
    return (f"{head}, which holds the robot's initial pose ({init[j]:.3f} rad): check the motion (joint targets are "
            f"radians, in {order_name} order: a motion in degrees, or of another robot?), or, if it is "
            f"right, {name}'s range in the model file")


@dataclass(frozen=True)
class _Required:
    kind: str  # a mujoco.mjtObj name suffix: "JOINT", "ACTUATOR", "SENSOR", "BODY", "SITE", "GEOM"
    names: tuple[str, ...]


def _required_names() -> tuple[_Required, ...]:
    return (
        _Required("JOINT", JOINT_NAMES),
        _Required("ACTUATOR", ACTUATOR_NAMES),
        _Required("SENSOR", FOOT_FORCE_SENSORS + FOOT_TORQUE_SENSORS),
        _Required("BODY", (BASE_BODY, NECK_BODY) + FOOT_BODIES + SELF_COLLISION_BODIES),
        _Required("SITE", FOOT_SITES),
        _Required("GEOM", (GROUND_GEOM,)),
    )


def missing_names(model: mujoco.MjModel | mujoco.MjSpec) -> list[str]:  # noqa: F821
    """The expected TOCABI names a compiled model or an uncompiled spec lacks, as ``"joint 'L_Knee_Joint'"`` etc.

    The order is joints, actuators, sensors, bodies, sites, geoms (each in ``robot`` order); empty for a TOCABI
    model. On a spec this checks names only (nothing is compiled), so it is cheap to run before editing the spec.
    """
    import mujoco

    missing: list[str] = []
    for req in _required_names():
        if isinstance(model, mujoco.MjSpec):
            find = getattr(model, req.kind.lower())  # spec.joint(name), spec.actuator(name), ...: None if absent
            absent = [n for n in req.names if find(n) is None]
        else:
            obj = getattr(mujoco.mjtObj, f"mjOBJ_{req.kind}")
            absent = [n for n in req.names if mujoco.mj_name2id(model, obj, n) < 0]
        missing += [f"{req.kind.lower()} {n!r}" for n in absent]
    return missing


def validate_model(model: "mujoco.MjModel", source: str = "model") -> None:  # noqa: F821
    """Raise :class:`RobotAssetError` listing every expected name the model lacks, and check the joint order."""
    import mujoco

    missing = missing_names(model)
    if missing:
        raise RobotAssetError(f"{source} lacks {len(missing)} expected name(s): " + ", ".join(missing))
    _check_no_extras(model, source)
    for j, name in enumerate(JOINT_NAMES):
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if model.jnt_qposadr[jid] != 7 + j or model.jnt_dofadr[jid] != 6 + j:
            raise RobotAssetError(
                f"{source}: joint {name!r} sits at qpos {model.jnt_qposadr[jid]}, expected {7 + j} "
                "(joints must follow robot.JOINT_NAMES after the free base)"
            )
        aid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, ACTUATOR_NAMES[j])
        if aid != j:
            raise RobotAssetError(f"{source}: actuator {ACTUATOR_NAMES[j]!r} has index {aid}, expected {j}")
    _check_foot_sensors(model, source)


def _check_no_extras(model: "mujoco.MjModel", source: str) -> None:  # noqa: F821
    """Refuse joints and actuators beyond TOCABI's (its 33 and the base's free joint). Everything downstream writes
    whole rows of TOCABI's sizes (``INIT_QPOS``, one control per joint), so a free-floating prop or a second motor
    failed later as a numpy broadcast or a reset shape error that named neither the file nor the extra element."""
    import mujoco

    if (model.nq, model.nv, model.nu) == (7 + NUM_JOINTS, 6 + NUM_JOINTS, NUM_JOINTS):
        return
    base = model.body(BASE_BODY).id
    # The base's free joint may be unnamed: it is told by its body and type, not by a name.
    robot_joint = [model.joint(j).name in JOINT_NAMES
                   or (model.jnt_bodyid[j] == base and model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE)
                   for j in range(model.njnt)]
    joints = [model.joint(j).name or f"#{j}" for j in range(model.njnt) if not robot_joint[j]]
    motors = [model.actuator(a).name or f"#{a}" for a in range(model.nu)
              if model.actuator(a).name not in ACTUATOR_NAMES]
    extras = "; ".join(f"extra {kind} {names}" for kind, names in (("joints", joints), ("actuators", motors)) if names)
    raise RobotAssetError(
        f"{source} has {model.nq} qpos, {model.nv} dofs and {model.nu} actuators where TOCABI has {7 + NUM_JOINTS}, "
        f"{6 + NUM_JOINTS} and {NUM_JOINTS} ({extras or 'joints of other sizes'}): remove them; a static prop needs "
        "no joint (boxes: env.scene.obstacles)")


def _check_foot_sensors(model: "mujoco.MjModel", source: str) -> None:  # noqa: F821
    """Each foot's F/T pair is a 3-axis force and a 3-axis torque sensor on that foot's site: a sensor of another
    kind (a touch sensor under the force sensor's name) or on the other foot reads other values under the right
    name."""
    import mujoco

    kinds = ((FOOT_FORCE_SENSORS, mujoco.mjtSensor.mjSENS_FORCE, "force"),
             (FOOT_TORQUE_SENSORS, mujoco.mjtSensor.mjSENS_TORQUE, "torque"))
    for names, kind, word in kinds:
        for name, site in zip(names, FOOT_SITES):
            sid = model.sensor(name).id
            site_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, site)
            if model.sensor_type[sid] != kind or model.sensor_dim[sid] != 3:
                raise RobotAssetError(f"{source}: sensor {name!r} must be a 3-axis <{word}> sensor, got a "
                                      f"{mujoco.mjtSensor(model.sensor_type[sid]).name} of {model.sensor_dim[sid]} "
                                      "values")
            if model.sensor_objtype[sid] != mujoco.mjtObj.mjOBJ_SITE or model.sensor_objid[sid] != site_id:
                raise RobotAssetError(f"{source}: sensor {name!r} must sit on site {site!r} (its foot's F/T site)")


# ------------------------------------------------------------------------------------------------ initial pose
def _initial_pose(model_path: str | os.PathLike | None):
    """``(model, data)`` of the robot model at ``INIT_QPOS``, its kinematics computed (body and geom poses)."""
    import mujoco

    model = load_model(model_path)
    data = mujoco.MjData(model)
    data.qpos[:] = INIT_QPOS
    mujoco.mj_kinematics(model, data)
    return model, data


def _model_file_key(model_path: str | os.PathLike | None) -> tuple[str, str]:
    """What the initial-pose caches are keyed by: the model file's resolved path and a digest of its bytes.

    A path alone returned a stale result after the file at that path was regenerated or replaced while the process
    ran, and ``None`` kept the shipped model even after ``$TOCABI_TORCHRL_ASSETS`` pointed elsewhere. The digest,
    not the modification time: a rewrite within one tick of the file system's clock (a few ms, or 1-2 s on some file
    systems) keeps the time and often the size. Files the MJCF includes or loads (meshes) are not part of the key.
    """
    p = _resolve_model_path(model_path).resolve()
    try:
        digest = hashlib.blake2b(p.read_bytes(), digest_size=16).hexdigest()
    except OSError as err:
        raise RobotAssetError(f"cannot read robot model file {p}: {err}") from err
    return str(p), digest


def _soles(model_path: str | os.PathLike | None) -> tuple[np.ndarray, np.ndarray]:
    """(2, 3) centres and (2, 3) half extents of the world-axis box around each sole, in ``INIT_QPOS`` [m]."""
    return _soles_of_file(_model_file_key(model_path))


@functools.lru_cache(maxsize=8)
def _soles_of_file(key: tuple[str, str]) -> tuple[np.ndarray, np.ndarray]:
    import mujoco

    model, data = _initial_pose(key[0])
    centres, extents = [], []
    for foot in FOOT_BODIES:
        b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, foot)
        soles = [g for g in range(model.ngeom) if model.geom_bodyid[g] == b and model.geom_contype[g]
                 and model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX]
        if not soles:
            raise RobotAssetError(f"{foot} has no collision box (its sole) in the robot model")
        sole = max(soles, key=lambda g: float(np.prod(model.geom_size[g])))
        centres.append(data.geom_xpos[sole].copy())
        extents.append(np.abs(data.geom_xmat[sole].reshape(3, 3)) @ model.geom_size[sole])
    return np.array(centres), np.array(extents)


def initial_heights(model_path: str | os.PathLike | None = None) -> dict[str, float]:
    """The pelvis and neck heights [m] and the neck's angle from upright [rad] of the robot's initial pose
    (``INIT_QPOS``): what the early terminations compare with their thresholds. ``model_path`` None = the shipped
    model; the result is cached per file content, so an edited model file is read again."""
    return dict(_initial_heights_of_file(_model_file_key(model_path)))  # a copy: the cached dict stays as computed


@functools.lru_cache(maxsize=8)
def _initial_heights_of_file(key: tuple[str, str]) -> dict[str, float]:
    import mujoco

    model, data = _initial_pose(key[0])
    base, neck = (mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, b) for b in (BASE_BODY, NECK_BODY))
    w = min(1.0, abs(float(data.xquat[neck][0])))
    return {"pelvis_height": float(data.xpos[base][2]), "neck_height": float(data.xpos[neck][2]),
            "neck_angle": 2.0 * float(np.arccos(w))}


def initial_sole_extents(foot: int = 0, model_path: str | os.PathLike | None = None) -> np.ndarray:
    """(3,) half extents [m] along the world axes of a sole's box in the robot's initial pose (``INIT_QPOS``), around
    :func:`initial_sole_centre`; ``foot`` 0 = left, 1 = right."""
    return _soles(model_path)[1][foot].copy()


def initial_sole_centre(foot: int = 0, model_path: str | os.PathLike | None = None) -> np.ndarray:
    """(3,) world position [m] of a sole's centre (the foot's largest collision box) in the robot's initial pose
    (``INIT_QPOS``); ``foot`` 0 = left, 1 = right; ``model_path`` None = the shipped model. The left sole's
    centre of the shipped model is (0.0999, 0.1025, 0.0148)."""
    return _soles(model_path)[0][foot].copy()
