"""Generate the project's own two-step walking cycle for TOCABI, and the CLI that writes the shipped default.

    python -m tocabi_torchrl.motion.gait --out my_walk.npz --step-length 0.15   # a cycle of one's own
    python -m tocabi_torchrl.motion.gait --overwrite     # regenerate assets/motions/tocabi_walk.npz
    python -m tocabi_torchrl.motion.gait --overwrite --plot docs/concepts/motion_leg_joints.png \
        --reference path/to/reference.txt

The cycle has the layout of the reference walk (spec §3.3, §3.6): 2 kHz rows, row 0 in the middle of a double
support with the weight moving onto the right (front) foot, right single support, a double support centred on the
middle row, left single support. It is built in four stages, all deterministic:

1. **Footsteps and swing feet.** Feet stay flat and face +x, ``step_width`` apart; each lands ``step_length`` ahead
   of the other. A swing foot follows a quintic in x (zero velocity and acceleration at lift-off and touchdown) and
   the bump ``16 s²(1 − s)² · swing_height`` in z (zero velocity at both ends).
2. **ZMP reference.** The load split of the force references of spec §3.3 weights the two feet, so the ZMP is the
   centre of pressure those forces would produce. Under each foot the centre of pressure rolls from heel to toe
   over the foot's stance (``zmp_travel``) around a point ``zmp_offset_x`` ahead of and ``zmp_offset_y`` outward
   of the ankle centre.
3. **CoM plan.** The periodic linear-inverted-pendulum CoM for that ZMP (:mod:`.lipm`), at the height of the
   model's CoM.
4. **Pelvis and legs.** The pelvis stays level at ``pelvis_height``; its horizontal position is iterated until the
   whole-body CoM of the project's MuJoCo model (legs from the analytic IK of :mod:`.kinematics`, upper body at the
   initial pose) lies on the planned CoM.

The continuous cycle lasts ``2·step_time`` and is sampled so that the table closes under the env's period of
``(R − 1)`` rows: row ``R − 1`` equals row 0, i.e. time runs 1/(R−1) (0.03 %) faster than the gait parameters say.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import math
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tocabi_torchrl import robot

from ..cli import RecipeParser
from .analysis import gait_metrics
from .io import MAX_PERIOD, MotionData, MotionFormatError, load_motion, save_npz
from .kinematics import SIDES, LegGeometry, leg_ik
from .lipm import periodic_lipm_com
from .schedule import REFERENCE_WEIGHT_FORCE, force_schedule, stance_schedule

__all__ = ["GaitConfig", "GaitPlan", "MAX_SAMPLE_RATE", "plan_gait", "generate_walk", "model_label", "main"]

#: How the metadata names the shipped model (its path in a source checkout).
SHIPPED_MODEL = "assets/tocabi/tocabi.xml"
#: The source checkout that holds this package (tocabi_torchrl/motion/gait.py -> the repository root).
_REPO = Path(__file__).resolve().parents[2]
#: The highest ``GaitConfig.sample_rate`` [rows/s]: five times the simulator's 2 kHz physics rate (the shipped model's
#: 0.5 ms timestep, which the shipped 2,000 rows/s tables match), so a model stepped at down to 0.1 ms still gets a
#: row per physics step. The env interpolates between rows, so finer rows give the physics nothing new, while the
#: table and the planning time grow with the rate (a typo such as 2e9 asked for billions of rows).
MAX_SAMPLE_RATE = 10_000.0


@dataclass(frozen=True)
class GaitConfig:
    """Gait parameters (defaults: spec §3.6, the reference walk). Lengths in m, times in s.

    Attributes:
        step_time: one step, single plus double support; at most 30 (the two-step cycle lasts at most 60 s,
            ``io.MAX_PERIOD``).
        dsp_time: double support per step.
        step_length: forward distance between the ankles in double support (stride = 2 × step_length per cycle).
        step_width: lateral distance between the ankle centres.
        swing_height: highest lift of the swing sole above the ground, reached mid-swing.
        pelvis_height: pelvis (``base_link`` origin) above the ground, constant.
        com_height: LIPM height; ``None`` takes the model's CoM height at the initial pose with this pelvis height.
        zmp_offset_x: mean centre of pressure ahead of the ankle centre over a foot's stance.
        zmp_offset_y: centre of pressure outward of the ankle centre (negative: inward, narrows the sway).
        zmp_travel: heel-to-toe roll of the centre of pressure over a foot's stance (touchdown to lift-off);
            it evens out the pelvis speed between single and double support.
        sample_rate: table rows per second, at most 10000 (``MAX_SAMPLE_RATE``, five times the simulator's 2 kHz
            physics rate; the shipped table has 2000).
        com_tolerance: stop the pelvis-CoM iteration when the pelvis moves less than this [m].

    The three centre-of-pressure numbers are not given by the spec; their defaults (−1 cm, −1.5 cm, 20 cm: the
    centre of pressure stays inside the sole, which spans −0.12 … +0.18 m around the ankle) reproduce the reference
    walk's measured pelvis motion: ±7.9 cm sway and 7.1 cm of pelvis travel per single support (spec §3.5).
    """

    step_time: float = 0.9
    dsp_time: float = 0.3
    step_length: float = 0.12
    step_width: float = 0.25
    swing_height: float = 0.054
    pelvis_height: float = 0.93
    com_height: float | None = None
    zmp_offset_x: float = -0.01
    zmp_offset_y: float = -0.015
    zmp_travel: float = 0.2
    sample_rate: float = 2000.0
    com_tolerance: float = 1e-7

    @property
    def step_rows(self) -> int:
        return int(round(self.step_time * self.sample_rate))

    @property
    def dsp_rows(self) -> int:
        return 2 * int(round(self.dsp_time * self.sample_rate / 2))

    @property
    def num_rows(self) -> int:
        """R, rows of the table: two steps of ``step_rows``; the last row repeats the first and closes the cycle."""
        return 2 * self.step_rows

    def validate(self) -> "GaitConfig":
        """Return ``self``, or raise ``ValueError`` naming the first parameter that makes no gait."""
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            # NaN passes every comparison below and infinity makes no table: both end here, named.
            if value is not None and not math.isfinite(value):
                raise ValueError(f"{f.name} must be a finite number, got {value}")
        for name in ("step_time", "step_width", "pelvis_height", "sample_rate", "com_tolerance"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        # The motion file's own check refuses a longer cycle, but only after the table was planned, which for a
        # step_time in ms (900) took hours.
        if 2.0 * self.step_time > MAX_PERIOD:
            raise ValueError(f"step_time must be at most {MAX_PERIOD / 2:g} s (the two-step cycle lasts at most "
                             f"{MAX_PERIOD:g} s; the reference's step is 0.9 s), got {self.step_time}")
        if self.sample_rate > MAX_SAMPLE_RATE:
            raise ValueError(f"sample_rate must lie in (0, {MAX_SAMPLE_RATE:g}] rows per second (five times the "
                             f"simulator's 2000 steps per second), got {self.sample_rate}")
        if self.com_height is not None and self.com_height <= 0:
            raise ValueError(f"com_height must be positive (or None for the model's), got {self.com_height}")
        if not 0.0 < self.dsp_time < self.step_time or self.dsp_rows < 2:
            raise ValueError(
                f"dsp_time {self.dsp_time} must lie in (0, step_time={self.step_time}) and span two or more rows "
                f"at sample_rate={self.sample_rate:g} rows per second"
            )
        if self.swing_height < 0:
            raise ValueError(f"swing_height must be >= 0, got {self.swing_height}")
        return self


@dataclass
class GaitPlan:
    """Task-space plan of one cycle at the table's M = R − 1 distinct samples (world frame of the cycle start).

    Attributes:
        time: (M,) cycle time of each sample [s].
        sole: (M, 2, 3) sole point under each ankle centre, [left, right] [m].
        zmp: (M, 2) ZMP reference [m].
        com: (M, 2) planned horizontal CoM [m].
        pelvis: (M, 3) pelvis position [m].
        joint_pos: (M, 33) joint targets [rad].
        com_height: LIPM height used [m].
        stride: forward advance per cycle [m].
    """

    time: np.ndarray
    sole: np.ndarray
    zmp: np.ndarray
    com: np.ndarray
    pelvis: np.ndarray
    joint_pos: np.ndarray
    com_height: float
    stride: float


def _quintic(s: np.ndarray) -> np.ndarray:
    """0 → 1 with zero velocity and acceleration at both ends."""
    s = np.clip(s, 0.0, 1.0)
    return s**3 * (10.0 - 15.0 * s + 6.0 * s**2)


def _bump(s: np.ndarray) -> np.ndarray:
    """0 → 1 → 0 with zero velocity at both ends and the peak at s = 1/2.

    A quartic rather than a flatter higher power: the reference lifts and lowers the swing foot promptly, which
    bends the swing knee early instead of stretching the trailing leg.
    """
    s = np.clip(s, 0.0, 1.0)
    return 16.0 * s**2 * (1.0 - s) ** 2


def _sole_trajectories(cfg: GaitConfig, t: np.ndarray) -> np.ndarray:
    """(M, 2, 3) sole points at cycle times ``t``: left stands at x = 0, right at x = step_length, at t = 0."""
    half_dsp, ssp = cfg.dsp_time / 2, cfg.step_time - cfg.dsp_time
    sole = np.zeros((t.size, 2, 3))
    # (start x, lift-off time) per foot: the left swings first (during the right single support).
    for i, (x0, lift) in enumerate(((0.0, half_dsp), (cfg.step_length, cfg.step_time + half_dsp))):
        s = (t - lift) / ssp if ssp > 0 else (t >= lift).astype(float)
        sole[:, i, 0] = x0 + 2.0 * cfg.step_length * _quintic(s)
        sole[:, i, 1] = (1.0 if SIDES[i] == "left" else -1.0) * cfg.step_width / 2
        sole[:, i, 2] = cfg.swing_height * _bump(s)
    return sole


def _centres_of_pressure(cfg: GaitConfig, t: np.ndarray, sole: np.ndarray) -> np.ndarray:
    """(M, 2, 2) horizontal centre of pressure under each foot: offset from the ankle, rolling heel to toe.

    A foot stands from its touchdown to its next lift-off (``step_time + dsp_time``); over that time its CoP moves
    forward by ``zmp_travel`` around ``ankle + zmp_offset_x``. Where a foot is in the air its load is zero, so its
    value there does not matter.
    """
    stand = cfg.step_time + cfg.dsp_time
    half_dsp = cfg.dsp_time / 2
    cop = sole[:, :, :2].copy()
    for i, touchdown in enumerate((cfg.step_time - half_dsp, half_dsp - cfg.dsp_time)):  # left, right
        progress = np.mod(t - touchdown, 2 * cfg.step_time) / stand
        cop[:, i, 0] += cfg.zmp_offset_x + cfg.zmp_travel * (np.clip(progress, 0.0, 1.0) - 0.5)
        cop[:, i, 1] += cfg.zmp_offset_y * (1.0 if SIDES[i] == "left" else -1.0)
    return cop


def _leg_joints(sole: np.ndarray, pelvis: np.ndarray, geometry: LegGeometry) -> np.ndarray:
    """(M, 33) joints: analytic leg IK for flat feet under a level pelvis, upper body at the initial pose.

    Raises ``ValueError`` naming the gait parameters to change when a foot is out of the leg's reach.
    """
    joints = np.tile(robot.INIT_JOINT_POS, (sole.shape[0], 1))
    level = np.broadcast_to(np.eye(3), (sole.shape[0], 3, 3))
    for i, side in enumerate(SIDES):
        ankle = sole[:, i] + np.array([0.0, 0.0, geometry.sole_depth]) - pelvis
        try:
            joints[:, 6 * i : 6 * i + 6] = leg_ik(ankle, level, side, geometry)
        except ValueError as err:  # leg_ik speaks of ankle targets; the caller chose gait parameters
            raise ValueError(
                f"pelvis_height, step_length, step_width or swing_height put the feet out of the legs' reach ({err}), "
                "or zmp_travel, zmp_offset_x or zmp_offset_y moved the pelvis (the CoM follows the centre of "
                "pressure) too far from them; lower the pelvis, shorten the steps or keep the pressure under the feet"
            ) from err
    return joints


def com_in_pelvis(model, joint_pos: np.ndarray) -> np.ndarray:
    """(M, 3) whole-body CoM of ``model`` in the pelvis frame (pelvis at the origin, level), per joint row [m]."""
    import mujoco

    data = mujoco.MjData(model)
    out = np.empty((joint_pos.shape[0], 3))
    for k, q in enumerate(joint_pos):
        data.qpos[:7] = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
        data.qpos[7:] = q
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        out[k] = data.subtree_com[0]
    return out


def geometry_problem(model, geometry: LegGeometry, tolerance: float = 1e-3) -> str | None:
    """What of ``geometry`` the compiled ``model`` does not have, measured at its zero pose (straight legs): each
    hip centre in the base body's frame, thigh (hip to knee axis) and shank (knee to ankle); None when all agree to
    ``tolerance`` [m]. The sole depth is not measured (the feet's collision shapes vary)."""
    import mujoco

    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    base = model.body(robot.BASE_BODY).id
    to_base = data.xmat[base].reshape(3, 3).T
    found = []
    for side in SIDES:
        prefix = side[0].upper()
        hip, knee, ankle = (data.xanchor[model.joint(f"{prefix}_{name}_Joint").id]
                            for name in ("HipPitch", "Knee", "AnklePitch"))
        measured = {"hip": to_base @ (hip - data.xpos[base]), "thigh": np.linalg.norm(knee - hip),
                    "shank": np.linalg.norm(ankle - knee)}
        planned = {"hip": geometry.hip_position(side), "thigh": geometry.thigh, "shank": geometry.shank}
        found += [f"{side} {name} {np.round(measured[name], 4).tolist()} m, planned "
                  f"{np.round(planned[name], 4).tolist()} m"
                  for name in measured if np.abs(measured[name] - planned[name]).max() > tolerance]
    return "; ".join(found) or None


def plan_gait(cfg: GaitConfig = GaitConfig(), model=None, geometry: LegGeometry = LegGeometry()) -> GaitPlan:
    """Plan one cycle (stages 1-4 of the module docstring) on ``model`` (default: ``robot.load_model()``)."""
    cfg.validate()
    model = robot.load_model() if model is None else model
    problem = geometry_problem(model, geometry)
    if problem:
        raise ValueError(f"the model's legs are not the ones the gait is planned for: {problem}; plan with the "
                         "model's own LegGeometry (generate_walk(geometry=...)), or on the shipped model")
    num_rows, dsp_rows = cfg.num_rows, cfg.dsp_rows
    m = num_rows - 1
    period = 2.0 * cfg.step_time
    t = np.arange(m) * (period / m)
    stride = 2.0 * cfg.step_length
    sole = _sole_trajectories(cfg, t)

    # Stage 2: the reference load split is the ZMP weighting (a foot without load has no say).
    load = force_schedule(num_rows, dsp_rows)[:m] / -REFERENCE_WEIGHT_FORCE
    zmp = np.einsum("mf,mfd->md", load, _centres_of_pressure(cfg, t, sole))

    # Stage 3: LIPM height from the model, unless given.
    nominal = com_in_pelvis(model, robot.INIT_JOINT_POS[None])[0]
    com_height = cfg.pelvis_height + nominal[2] if cfg.com_height is None else cfg.com_height
    com = periodic_lipm_com(zmp, period, com_height, drift=np.array([stride, 0.0]))

    # Stage 4: the CoM offset depends on the legs, the legs on the pelvis: a contraction, converging in a few steps.
    pelvis = np.zeros((m, 3))
    pelvis[:, 2] = cfg.pelvis_height
    pelvis[:, :2] = com - nominal[:2]
    for _ in range(50):
        joints = _leg_joints(sole, pelvis, geometry)
        target = com - com_in_pelvis(model, joints)[:, :2]
        change = np.abs(target - pelvis[:, :2]).max()
        pelvis[:, :2] = target
        if change < cfg.com_tolerance:
            break
    else:
        raise RuntimeError(f"pelvis/CoM iteration did not converge (last change {change:.2e} m)")
    joints = _leg_joints(sole, pelvis, geometry)
    return GaitPlan(t, sole, zmp, com, pelvis, joints, float(com_height), stride)


def generate_walk(
    cfg: GaitConfig = GaitConfig(),
    model=None,
    geometry: LegGeometry = LegGeometry(),
    *,
    model_path: str | os.PathLike | None = None,
) -> MotionData:
    """The walking cycle as :class:`~tocabi_torchrl.motion.io.MotionData` (R rows, last row = first row).

    Force references and stance pattern follow spec §3.3 and §8 on the row index; the start rows are the middles of
    the two double supports, 0 and R/2. ``model`` is a compiled MuJoCo model, or ``None`` to compile ``model_path``
    (default: the shipped model); ``meta["model"]`` records ``model_path`` (see :func:`model_label`), or ``None``
    when a compiled ``model`` comes without its path.
    """
    cfg.validate()  # before compiling a model: a bad parameter is reported at once
    if model is None:
        model = robot.load_model(model_path)
        model_path = SHIPPED_MODEL if model_path is None else model_path
    plan = plan_gait(cfg, model, geometry)
    num_rows = cfg.num_rows
    joint_pos = np.concatenate([plan.joint_pos, plan.joint_pos[:1]])
    base_pos = np.concatenate([plan.pelvis, plan.pelvis[:1] + np.array([plan.stride, 0.0, 0.0])])
    return MotionData(
        joint_pos=joint_pos,
        foot_force=force_schedule(num_rows, cfg.dsp_rows),
        stance=stance_schedule(num_rows, cfg.dsp_rows),
        sample_rate=cfg.sample_rate,
        init_rows=np.array([0, cfg.step_rows], dtype=np.int64),
        base_pos=base_pos,
        meta={
            "generator": "tocabi_torchrl.motion.gait",
            "config": dataclasses.asdict(cfg),
            "com_height": round(plan.com_height, 6),
            "model": None if model_path is None else model_label(model_path),
        },
    ).validate("generate_walk")


def model_label(path: str | os.PathLike) -> str:
    """How the metadata records an MJCF path: the shipped model as ``assets/tocabi/tocabi.xml``, a file inside the
    source checkout relative to it, any other as given (a record that does not depend on the machine that made it)."""
    resolved = Path(path).resolve()
    if resolved == robot.asset_path("tocabi", "tocabi.xml").resolve():
        return SHIPPED_MODEL
    # Only a source checkout (it has pyproject.toml) is a meaningful base; an installed package keeps paths as given.
    if (_REPO / "pyproject.toml").is_file() and resolved.is_relative_to(_REPO):
        return resolved.relative_to(_REPO).as_posix()
    return str(path)


def _options_named_in(message: str) -> list[str]:
    """The command-line options of the :class:`GaitConfig` fields a message names, e.g. ``--pelvis-height``."""
    names = [f.name for f in dataclasses.fields(GaitConfig) if re.search(rf"\b{f.name}\b", message)]
    return [f"--{name.replace('_', '-')}" for name in names]


def _field_help() -> dict[str, str]:
    """Per-field help from the ``Attributes:`` section of :class:`GaitConfig`'s docstring (one source of truth)."""
    helps: dict[str, str] = {}
    name = None
    section = (GaitConfig.__doc__ or "").split("Attributes:")[1].split("\n\n")[0]
    for line in section.splitlines():
        head, sep, text = line.strip().partition(": ")
        if sep and head.isidentifier() and line.startswith(" " * 8) and not line.startswith(" " * 12):
            name, helps[head] = head, text
        elif name:
            helps[name] += " " + line.strip()
    return helps


def _add_config_arguments(parser: argparse.ArgumentParser) -> None:
    helps = _field_help()
    group = parser.add_argument_group("gait parameters (GaitConfig; lengths in m, times in s)")
    for f in dataclasses.fields(GaitConfig):
        group.add_argument(
            f"--{f.name.replace('_', '-')}",
            type=float,
            default=f.default,
            metavar="X",
            help=f"{helps.get(f.name, '')} (default {f.default})",
        )


def main(argv: list[str] | None = None) -> int:
    """CLI: regenerate the default walking cycle (see the module docstring)."""
    parser = RecipeParser(
        prog="python -m tocabi_torchrl.motion.gait",
        description="Generate TOCABI's two-step reference walking cycle (project .npz format).",
    )
    parser.add_argument("--out", type=Path, default=None,
                        help="output .npz (default: the shipped assets/motions/tocabi_walk.npz, which the shipped "
                             "policies were trained on)")
    parser.add_argument("--model", type=Path, default=None, help="MJCF to plan on (default: the shipped model)")
    parser.add_argument("--plot", type=Path, default=None, help="also write a PNG of the leg joint trajectories")
    parser.add_argument("--reference", type=Path, default=None, help="motion file to overlay on the plot")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing --out or --plot file (the default --out always exists)")
    _add_config_arguments(parser)
    args = parser.parse_args(argv)

    if args.model is not None and not args.model.is_file():
        parser.error(f"--model {args.model} is not a file; pass an MJCF file, or leave --model out for the shipped "
                     "model")
    for option, path in (("--out", args.out), ("--plot", args.plot)):
        if path is not None and path.is_dir():
            parser.error(f"{option} {path} is a folder; give a file name")
    if args.plot is not None and args.plot.suffix.lower() != ".png":
        parser.error(f"--plot {args.plot}: give a .png file")
    if args.plot is not None and importlib.util.find_spec("matplotlib") is None:
        # Said before planning: the figure is drawn after --out is written, where a missing matplotlib ended in a
        # traceback, leaving a motion that a rerun then had to --overwrite.
        parser.error(f"--plot needs matplotlib, which is not installed: pip install -e \".[viz]\" in the repository "
                     "(or pip install matplotlib), or leave --plot out")
    out = Path(args.out or robot.asset_path("motions", "tocabi_walk.npz"))
    out = out if out.suffix == ".npz" else out.with_name(out.name + ".npz")  # what save_npz writes
    for option, path in (("--out", out), ("--plot", args.plot)):
        if path is not None and path.exists() and not args.overwrite:
            shipped = " (the shipped motion the shipped policies were trained on)" if args.out is None else ""
            parser.error(f"{option} {path} exists{shipped}; pass --overwrite to replace it, or give another "
                         f"{option}")
    # Read before anything is written: --reference may name the file --out replaces.
    try:
        reference = load_motion(args.reference) if args.reference is not None else None
    except (MotionFormatError, OSError) as err:  # a traceback once; the file is the user's to fix or replace
        parser.error(f"--reference: {err}")
    cfg = GaitConfig(**{f.name: getattr(args, f.name) for f in dataclasses.fields(GaitConfig)})
    try:
        data = generate_walk(cfg, model_path=args.model)
    except robot.RobotAssetError as err:  # the --model file does not compile or lacks TOCABI's names
        parser.error(f"--model: {err}")
    except ValueError as err:  # parameters that make no gait (validate) or put the feet out of reach (leg IK)
        options = _options_named_in(str(err))
        geometry = "legs are not the ones" in str(err)  # no gait parameter changes the model's legs
        hint = (f"change {', '.join(options)}" if options else "plan on a model of TOCABI's legs" if geometry
                else "change the gait parameters (see --help)")
        parser.error(f"cannot generate the walk: {err}; {hint}")
    except RuntimeError as err:  # the pelvis/CoM iteration did not reach --com-tolerance
        parser.error(f"cannot generate the walk: {err}; raise --com-tolerance (default {GaitConfig.com_tolerance})")
    out = save_npz(out, data)
    metrics = gait_metrics(data.joint_pos, data.init_rows)
    print(f"wrote {out} ({Path(out).stat().st_size / 1024:.0f} KiB, {data.num_rows} rows)")
    for key, value in metrics.summary().items():
        print(f"  {key:16s} {json.dumps(value)}")
    if args.plot is not None:
        from .plot import plot_leg_joints

        plot_leg_joints(data, reference, args.plot)
        print(f"wrote {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
