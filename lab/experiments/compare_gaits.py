"""Gait comparison (TocabiLab's experiment 2): controllers walk side by side at (0.5, 0) m/s for 8 s.

    python -m lab.experiments.compare_gaits                                    # the three shipped policies, 256 robots each
    python -m lab.experiments.compare_gaits --policy PD=runs/ppo_walk --policy torque=runs/torque/checkpoints/latest.pt
    python -m lab.experiments.compare_gaits --device cpu --num_envs 16 --out runs/experiments/compare_gaits_cpu16

Each controller (``--policy LABEL=PATH``, a .pt file or a run folder; default: the shipped PD-residual, torque
and model-based policies) runs its deterministic policy in ``--num_envs`` robots. The table averages over every
robot; the frames and trajectories are robot 0's. Written to ``--out`` (an existing, non-empty folder is refused unless
``--overwrite``):

    table.md, table.json    survival, forward distance, lateral drift, knee RMS against the reference, mean |tau|,
                            torque smoothness (defined in the table's notes)
    knee_left.png, knee_right.png   robot 0's knee over the first 6 s: every controller and the reference
    torques.png             robot 0's hip-pitch, knee and ankle-pitch torques over the first 2 s (applied torque:
                            the position servos' actuator force in the PD modes, the commanded torque in torque mode)
    frames_<label>.png      robot 0 every 2 s from a camera at (2, 6, 2.5) m looking at its pelvis; frames.png:
                            one row per controller
    timelapse_<label>.png   the same poses drawn into one image
    traces.npz              robot 0's knee, reference and critical-joint torque traces per controller

On a CPU this is slow (C MuJoCo on the cores; a few minutes per controller at 256 robots): lower --num_envs.
"""

from __future__ import annotations

import argparse
import io
import json
import math
import sys

from tocabi_torchrl.cli import RecipeParser
from tocabi_torchrl.render_gl import NO_GL_FIX, choose_gl_backend_or_exit

#: Most frames per controller (t = 0 and every --frame_every): each is a --frame_width image in one strip, so more
#: make a strip too wide to view (25 x 480 px is 12,000 px) and cost a render each.
MAX_FRAMES = 25

#: (option, type, default, description): the command line, defaults shown once by build_parser.
OPTIONS = (
    ("--num_envs", int, 256, "robots per controller for the table (frames and traces: robot 0)"),
    ("--device", str, "auto", "auto (CUDA if present, else cpu), cpu, cuda or cuda:N"),
    ("--seconds", float, 8.0, "duration of the walk [s]"),
    ("--vx", float, 0.5, "commanded forward speed [m/s]"),
    ("--vy", float, 0.0, "commanded lateral speed [m/s]"),
    ("--frame_every", float, 2.0, (f"seconds between frames; a whole number of policy steps (4 ms; others are "
                                   f"rounded to one), at most {MAX_FRAMES} frames over --seconds")),
    ("--knee_seconds", float, 6.0, "seconds of knee trajectory plotted; at least one policy step (0.004)"),
    ("--torque_seconds", float, 2.0, "seconds of joint torques plotted; at least one policy step (0.004)"),
    ("--frame_width", int, 480, "frame width [px]"),
    ("--frame_height", int, 360, "frame height [px]"),
    ("--fovy", float, 30.0, "the camera's vertical field of view [deg] (MuJoCo's default: 45)"),
    ("--out", str, "runs/experiments/compare_gaits", "output folder"),
)

COLUMNS = {"controller": "controller", "control_mode": "control", "num_envs": "robots", "survival": "survival",
           "forward_distance_m": "forward distance [m]", "lateral_drift_m": "lateral drift [m]",
           "knee_rms_rad": "knee RMS vs reference [rad]", "mean_abs_torque_Nm": "mean abs torque [N·m]",
           "torque_smoothness_Nm_per_step": "torque smoothness [N·m/step]"}
NOTES = [
    "Every value is a mean over the robots; a robot counts until its first termination (its alive steps).",
    "survival: share of robots not terminated within the walk. forward distance, lateral drift: pelvis x travelled, "
    "|pelvis y| travelled, at the last alive step.",
    "knee RMS vs reference: root mean square over the alive steps of (knee angle - reference knee angle), both knees.",
    "mean abs torque: mean of |tau| over the alive steps and the 12 leg joints; tau is the applied actuator torque "
    "(PD modes: the MuJoCo position servos' actuator_force in the last physics substep of the 4 ms policy step; "
    "torque mode: the commanded torque, applied unchanged in every substep).",
    "torque smoothness: mean of |tau_k - tau_(k-1)| over consecutive alive policy steps (4 ms) and the 12 leg "
    "joints, in N·m per step; lower is smoother. The first step's change from the reset is left out.",
]


def build_parser() -> argparse.ArgumentParser:
    parser = RecipeParser(prog="python -m lab.experiments.compare_gaits", description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", action="append", metavar="[LABEL=]PATH",
                        help="a controller: checkpoint .pt or run folder, optionally labelled; repeat for each "
                             "(default: the three shipped policies: PD, torque, model_based)")
    for flag, kind, default, text in OPTIONS:
        parser.add_argument(flag, type=kind, default=default, help=f"{text} (default: {default})")
    parser.add_argument("--overwrite", action="store_true",
                        help="write into an existing --out folder (files of the same name are replaced, others stay)")
    return parser


if __name__ == "__main__":  # --help or a misspelt option answers before torch and mujoco load
    build_parser().parse_args(sys.argv[1:])

choose_gl_backend_or_exit()  # before mujoco is imported

import numpy as np  # noqa: E402
import torch  # noqa: E402

from tocabi_torchrl import robot  # noqa: E402
from tocabi_torchrl.rl.checkpoint import (  # noqa: E402
    CheckpointError,
    checkpoint_file,
    config_from_checkpoint,
    read_checkpoint,
)
from tocabi_torchrl.evaluation.plots import plot_joint_torques, plot_knee_comparison  # noqa: E402
from tocabi_torchrl.evaluation.video import (  # noqa: E402
    CAMERA_POS,
    label_image,
    render_stills,
    render_timelapse,
    rendering_unavailable,
    save_strip,
)
from tocabi_torchrl.evaluation.gait_test import policy_dt  # noqa: E402
from lab.experiments.common import (  # noqa: E402
    ExperimentOutputError,
    display_path,
    parse_controllers,
    prepare_out_dir,
    replace_atomically,
    slug,
    write_atomic,
    write_table,
)
from lab.experiments.gait_record import CRITICAL, CRITICAL_JOINTS, load_policy, record_rollout, torque_stats  # noqa: E402
from tocabi_torchrl.rl.trainer import resolve_device  # noqa: E402


def read_controller(controller) -> dict:
    """Read and check a controller's checkpoint (file, contents, config); returns its state. ``main`` reads every
    controller's before any rollout: a bad path or file among the last must not end the run after the first have
    taken minutes. Raises ``CheckpointError`` naming the file."""
    file = checkpoint_file(controller.path)
    state = read_checkpoint(file)
    config_from_checkpoint(state, file)
    return state


def check_spans(args, parser, dt: float) -> None:
    """Refuse spans shorter than one policy step ``dt`` (an empty trace) and more than :data:`MAX_FRAMES` frames;
    round --frame_every to whole policy steps (frames are states after a step), saying so."""
    for flag in ("seconds", "frame_every", "knee_seconds", "torque_seconds"):
        if getattr(args, flag) < dt * (1 - 1e-9):
            parser.error(f"--{flag} must be at least one policy step ({dt * 1000:g} ms), got {getattr(args, flag):g}")
    snapped = round(args.frame_every / dt) * dt
    if abs(snapped - args.frame_every) > 1e-9:
        print(f"--frame_every {args.frame_every:g} s is not a whole number of policy steps ({dt * 1000:g} ms): frames "
              f"every {snapped:g} s instead", flush=True)
        args.frame_every = snapped
    frames = math.floor(args.seconds / args.frame_every + 1e-9) + 1
    if frames > MAX_FRAMES:
        parser.error(f"--frame_every {args.frame_every:g} s over --seconds {args.seconds:g} gives {frames} frames per "
                     f"controller, more than {MAX_FRAMES}; pass --frame_every "
                     f"{math.ceil(args.seconds / (MAX_FRAMES - 1) / dt) * dt:g} or more")


def run_controller(controller, args, device, index, total, state: dict | None = None) -> dict:
    """Roll one controller out (``state``: its checkpoint, already read); returns its table row, robot 0's traces
    and frames' joint states."""
    policy = load_policy(controller.path, args.num_envs, device, command=(args.vx, args.vy), state=state,
                         nominal=True)  # the robot, not a training's kicks or draws, as the gait tests
    print(f"[{index}/{total}] {controller.label}: {policy.control_mode} control, {args.num_envs} robots x "
          f"{args.seconds:g} s on {device} ({policy.env.base_env.backend})", flush=True)
    rec = record_rollout(policy.actor, policy.env, args.seconds, (args.vx, args.vy), snapshot_every=args.frame_every,
                         desc=controller.label).cpu()
    every, critical = torque_stats(rec), torque_stats(rec, joints=CRITICAL)
    row = {"controller": controller.label, "checkpoint": display_path(controller.path),
           "control_mode": rec.control_mode,
           **rec.metrics,
           "mean_abs_torque_Nm": float(every["mean_abs"].nanmean()),
           "torque_smoothness_Nm_per_step": float(every["smoothness"].nanmean()),
           "critical_mean_abs_torque_Nm": float(critical["mean_abs"].nanmean()),
           "critical_torque_smoothness_Nm_per_step": float(critical["smoothness"].nanmean()),
           "peak_abs_torque_Nm": dict(zip(CRITICAL_JOINTS, critical["peak"].nanmean(0).tolist()))}
    print("   " + ", ".join(f"{COLUMNS[k]} {row[k]:.3g}" for k in list(COLUMNS)[3:]), flush=True)
    knee_q, knee_ref = rec.knee_trace(0, args.knee_seconds)
    steps = min(rec.steps, int(round(args.torque_seconds / rec.dt)))
    return {"row": row, "knee": (knee_q, knee_ref), "torque": rec.leg_torque[:steps, 0][:, list(CRITICAL)].numpy(),
            "all_torque": rec.leg_torque[:, 0].numpy(), "snapshots": rec.snapshots[:, 0].numpy(),
            "times": rec.snapshot_times, "model": policy.env.base_env.sim.mj_model, "dt": rec.dt}


def _save_strip(images, path) -> None:
    """:func:`save_strip`, atomically: a run killed mid-write leaves the earlier image whole."""
    replace_atomically(path, lambda tmp: save_strip(images, tmp))


def render_frames(results: dict, args, out) -> str:
    """Frame strips, their composite and time-lapse images of robot 0; returns what was written (or why not). The
    first failure ends the rendering: MuJoCo is not asked again (a failed GLFW start can abort the process)."""
    reason = rendering_unavailable()  # MUJOCO_GL turns OpenGL off, or an earlier render in this process failed
    if reason:
        print(f"frames skipped: {reason}")
        return f"not rendered: {reason}"
    rows = []
    try:
        for label, res in results.items():
            stills = render_stills(res["model"], res["snapshots"], CAMERA_POS, width=args.frame_width,
                                   height=args.frame_height, fovy=args.fovy)
            stills = [label_image(im, f"{label}, t = {t:g} s") for im, t in zip(stills, res["times"])]
            _save_strip(stills, out / f"frames_{slug(label)}.png")
            lapse = render_timelapse(res["model"], res["snapshots"], CAMERA_POS, width=2 * args.frame_width,
                                     height=args.frame_height, fovy=args.fovy)
            _save_strip([label_image(lapse, f"{label}, t = {', '.join(f'{t:g}' for t in res['times'])} s")],
                        out / f"timelapse_{slug(label)}.png")
            rows.append(stills)
        _save_strip(rows, out / "frames.png")
    except Exception as err:  # noqa: BLE001 - rendering needs an OpenGL backend (MUJOCO_GL=egl on a headless machine)
        print(f"frames skipped ({type(err).__name__}: {err}); on a headless machine: {NO_GL_FIX}")
        return f"not rendered: {type(err).__name__}: {err}"
    return "frames.png, frames_<label>.png, timelapse_<label>.png"


def main(argv: list[str] | None = None) -> dict:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.num_envs < 1 or args.frame_width < 1 or args.frame_height < 1:
        parser.error("--num_envs, --frame_width and --frame_height must be >= 1")
    for flag in ("seconds", "frame_every", "knee_seconds", "torque_seconds", "fovy"):
        if not 0 < getattr(args, flag) < math.inf:  # a negative span would slice from the end: the wrong seconds
            parser.error(f"--{flag} must be a finite number > 0, got {getattr(args, flag)}")
    if not (math.isfinite(args.vx) and math.isfinite(args.vy)):
        parser.error(f"--vx and --vy must be finite speeds [m/s], got {args.vx} and {args.vy}")
    check_spans(args, parser, policy_dt())
    try:
        controllers = parse_controllers(args.policy)
    except ValueError as err:
        sys.exit(f"error: {err}")
    states = {}
    for controller in controllers:
        try:
            states[controller.label] = read_controller(controller)
        except CheckpointError as err:
            sys.exit(f"error: {controller.label}: {err}")
    try:
        device = resolve_device(args.device)
        out = prepare_out_dir(args.out, args.overwrite)
    except (ValueError, RuntimeError, ExperimentOutputError) as err:
        sys.exit(f"error: {err}")
    results = {}
    for i, controller in enumerate(controllers, 1):
        try:
            results[controller.label] = run_controller(controller, args, device, i, len(controllers),
                                                       state=states[controller.label])
        except (CheckpointError, ValueError) as err:
            sys.exit(f"error: {controller.label}: {err}")
        # One time axis for the plots, traces.npz and the per-step smoothness column: one control period.
        first, res = next(iter(results.items())), results[controller.label]
        if abs(res["dt"] - first[1]["dt"]) > 1e-12:
            sys.exit(f"error: {controller.label} steps every {res['dt'] * 1000:g} ms and {first[0]} every "
                     f"{first[1]['dt'] * 1000:g} ms (env.sim.substeps); compare controllers of one control period")
    rows = [res["row"] for res in results.values()]
    dt = next(iter(results.values()))["dt"]
    command = (args.vx, args.vy)
    plot_knee_comparison({label: res["knee"] for label, res in results.items()}, dt, out, command)
    plot_joint_torques({label: res["torque"] for label, res in results.items()}, dt, out / "torques.png",
                       CRITICAL_JOINTS, f"Applied joint torques, first {args.torque_seconds:g} s, robot 0, command "
                       f"({args.vx:g}, {args.vy:g}) m/s", limits=robot.LEG_TORQUE_LIMITS[list(CRITICAL)])
    traces = io.BytesIO()  # written whole or not at all: a file object, so numpy adds no suffix and no temp name
    np.savez_compressed(traces, dt=dt, critical_joints=np.array(CRITICAL_JOINTS),
                        **{f"{slug(label)}__{key}": value for label, res in results.items()
                           for key, value in (("knee", res["knee"][0]), ("knee_reference", res["knee"][1]),
                                              ("leg_torque", res["all_torque"]))})
    write_atomic(out / "traces.npz", traces.getvalue())
    frames = render_frames(results, args, out)
    meta = {"experiment": "gait comparison (TocabiLab experiment 2)", "command_mps": list(command),
            "seconds": args.seconds, "num_envs": args.num_envs, "device": str(device), "camera_pos_m": CAMERA_POS,
            "frame_every_s": args.frame_every, "frames": frames, "argv": sys.argv[1:] if argv is None else argv,
            "torch": torch.__version__}
    write_table(rows, COLUMNS, out, title=f"Gait comparison at ({args.vx:g}, {args.vy:g}) m/s, {args.seconds:g} s, "
                f"{args.num_envs} robots per controller, {device}", notes=NOTES, meta=meta)
    print(f"wrote {out}/: table.md, table.json, knee_left.png, knee_right.png, torques.png, traces.npz; {frames}")
    print(json.dumps(rows, indent=2))
    return {"out": str(out), "rows": rows, "frames": frames}


if __name__ == "__main__":
    main(sys.argv[1:])
