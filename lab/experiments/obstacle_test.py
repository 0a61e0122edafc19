"""Obstacle test (TocabiLab's experiment 3): a thin box on the path, no perception, command (0.5, 0) m/s for 8 s.

    python -m lab.experiments.obstacle_test                                   # shipped policies, 0/5/12/20 mm, then +10 mm
    python -m lab.experiments.obstacle_test --policy PD=runs/ppo_walk --policy torque=runs/torque --num_envs 1024
    python -m lab.experiments.obstacle_test --heights_mm 0,12 --step_mm 0 --device cpu --num_envs 16

Each controller (``--policy LABEL=PATH``; default: the shipped PD-residual, torque and model-based policies) walks
into a box ``--box_length`` x ``--box_width`` m, centred ``--distance`` m ahead of the left sole's start position, in
``--num_envs`` robots whose box is moved by a uniform ±``--jitter`` m (x and y) per robot. Heights: ``--heights_mm``,
then ``--step_mm`` higher each time until every controller's pass rate is below ``--fail_below``, at most
``--max_mm``. Height 0 is the plain ground (no box); its "obstacle" metrics use the box's footprint. Definitions of
pass, failure on the obstacle, reached/crossed, the first 3 steps on the obstacle and the torque metrics:
``lab/experiments/obstacle_eval.py`` (also in the table's notes). Written to ``--out`` (an existing, non-empty
folder is refused unless ``--overwrite`` or ``--resume``):

    table.md, table.json        one row per controller and height, rewritten (atomically) after every controller
                                and height, so a run stopped midway keeps what it measured
    pass_rate.png, lateral_deviation.png, peak_torque.png   those values against the height, one line per controller
    torques_<h>mm.png           hip-pitch, knee, ankle-pitch torques of one robot per controller over its first 3 steps
                                on the obstacle (t = 0: its first contact); trace_<label>_<h>mm.npz: that trace
    frames_<label>_<h>mm_pass.png, ..._fail.png   one robot that passed and one that failed, from the camera at
                                (2, 6, 2.5) m: start, first contact, +1 s, +2 s, end (or termination)

``--resume`` continues a run in ``--out`` (one cut short, or split over several calls: repeat the same command with
``--resume`` until it ends): the rows of its table.json stay, only the (controller, height) pairs missing there are
measured, and the escalation and the pass-rate, lateral-deviation and peak-torque plots use every row. It is refused
when that table was made with other settings (those that change a row: ``--num_envs``, ``--seconds``, ``--vx``,
``--vy``, ``--distance``, ``--box_length``, ``--box_width``, ``--jitter``, ``--steps_on_obstacle``, and each label's
checkpoint). Without a table.json in ``--out`` it starts from scratch there. ``--overwrite`` ignores an earlier table:
its rows are replaced by this run's.

Needs the env's obstacles (``env.scene.obstacles``, ``BoxObstacle``).
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import math
import sys

from tocabi_torchrl.cli import RecipeParser
from tocabi_torchrl.render_gl import NO_GL_FIX, choose_gl_backend_or_exit

#: (option, type, default, description): the command line, defaults shown once by build_parser.
OPTIONS = (
    ("--num_envs", int, 256, "robots per controller and height"),
    ("--device", str, "auto", "auto (CUDA if present, else cpu), cpu, cuda or cuda:N"),
    ("--seconds", float, 8.0, "episode length [s]; pass = no termination within it"),
    ("--vx", float, 0.5, "commanded forward speed [m/s]"),
    ("--vy", float, 0.0, "commanded lateral speed [m/s]"),
    ("--heights_mm", str, "0,5,12,20", "box heights [mm], comma-separated; 0 = no box"),
    ("--step_mm", float, 10.0, "then higher by this until every controller fails (0: only --heights_mm)"),
    ("--max_mm", float, 60.0, "cap of the heights tried"),
    ("--fail_below", float, 0.5, "a controller fails a height when its pass rate is below this"),
    ("--distance", float, 0.6, "box centre ahead of the left sole's start position [m]"),
    ("--box_length", float, 0.3, "box length along x [m]"),
    ("--box_width", float, 0.6, "box width along y [m] (0.6 spans both feet's tracks)"),
    ("--jitter", float, 0.05, "half-range of the per-robot uniform box offset in x and y [m]"),
    ("--steps_on_obstacle", int, 3, "footfalls from the first contact that the torque window covers"),
    ("--frame_width", int, 480, "frame width [px]"),
    ("--frame_height", int, 360, "frame height [px]"),
    ("--fovy", float, 25.0, "the camera's vertical field of view [deg] (MuJoCo's default: 45)"),
    ("--out", str, "runs/experiments/obstacle_test", "output folder"),
)
#: The options that change what a row measures: a run is resumed only with the values its table was made with.
SETTINGS = ("num_envs", "seconds", "vx", "vy", "distance", "box_length", "box_width", "jitter", "steps_on_obstacle")
EXPERIMENT = "obstacle test (TocabiLab experiment 3)"

COLUMNS = {"controller": "controller", "height_mm": "height [mm]", "num_envs": "robots", "pass_rate": "pass",
           "failed_on_obstacle_rate": "failed on obstacle", "failed_before_obstacle_rate": "failed before it",
           "stepped_on_rate": "stepped on", "reached_rate": "reached", "crossed_rate": "crossed",
           "lateral_deviation_after_m": "lateral deviation after [m]",
           "peak_torque_on_obstacle_Nm": "peak abs torque, 3 steps [N·m]",
           "torque_variation_on_obstacle_Nm_per_step": "torque variation, 3 steps [N·m/step]"}
NOTES = [
    "Shares of robots, or means over them. pass: no termination within the episode. failed on obstacle "
    "(TocabiLab's failure): terminated after its first contact with the box; failed before it: terminated without "
    "having touched it. stepped on: a foot touched the box.",
    "reached: a sole's front edge got past the box's near edge; crossed: both soles' rear edges got past its far "
    "edge (while the robot was up).",
    "lateral deviation after: |pelvis y at the last alive step - pelvis y when the pelvis passed the box centre|, "
    "over the robots whose pelvis passed it.",
    "3 steps: from the first foot contact with the box until the third footfall after it (a footfall: a foot "
    "touching down after >= 0.2 s in the air, the end of a swing). peak abs torque: max |tau| over that window "
    "and the hip-pitch, knee and ankle-pitch joints of both legs; torque variation: mean |tau_k - tau_(k-1)| per "
    "4 ms policy step there.",
    "tau: the applied actuator torque (PD modes: the position servos' actuator_force in the step's last physics "
    "substep; torque mode: the commanded torque).",
    "Contact with the box: the env's obstacle_contact signal; at height 0 (no box) the sole's footprint over the "
    "box's footprint within 1 cm of the ground.",
]


def build_parser() -> argparse.ArgumentParser:
    parser = RecipeParser(prog="python -m lab.experiments.obstacle_test", description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", action="append", metavar="[LABEL=]PATH",
                        help="a controller: checkpoint .pt or run folder, optionally labelled; repeat for each "
                             "(default: the three shipped policies: PD, torque, model_based)")
    for flag, kind, default, text in OPTIONS:
        parser.add_argument(flag, type=kind, default=default, help=f"{text} (default: {default})")
    parser.add_argument("--overwrite", action="store_true",
                        help="write into an existing --out folder, ignoring any earlier table there: its rows are "
                             "replaced by this run's, files of the same name are replaced, others stay")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in --out: keep its table.json's rows, measure only the (controller, "
                             "height) pairs missing there, redraw the plots from all rows (frames and torque traces "
                             "of earlier heights stay). Refused if that table was made with other "
                             f"--{', --'.join(SETTINGS)} or another checkpoint under a label; without a table.json "
                             "there it starts from scratch in that folder")
    return parser


if __name__ == "__main__":  # --help or a misspelt option answers before torch and mujoco load
    build_parser().parse_args(sys.argv[1:])

choose_gl_backend_or_exit()  # before mujoco is imported

import numpy as np  # noqa: E402
import torch  # noqa: E402

from tocabi_torchrl import robot  # noqa: E402
from tocabi_torchrl.rl.checkpoint import CheckpointError  # noqa: E402
from tocabi_torchrl.evaluation.plots import plot_joint_torques, plot_vs_height  # noqa: E402
from tocabi_torchrl.evaluation.video import CAMERA_POS, label_image, render_stills, rendering_unavailable, save_strip  # noqa: E402
from lab.experiments.common import (  # noqa: E402
    ExperimentOutputError,
    checkpoint_record,
    display_path,
    earlier_table,
    parse_controllers,
    prepare_out_dir,
    replace_atomically,
    slug,
    write_atomic,
    write_table,
)
from lab.experiments.gait_record import CRITICAL, CRITICAL_JOINTS, load_policy, record_rollout  # noqa: E402
from lab.experiments.obstacle_eval import analyse_obstacle, pick_example  # noqa: E402
from tocabi_torchrl.rl.trainer import resolve_device  # noqa: E402


def make_box(args, height_mm: float):
    """The box of ``height_mm`` (the env feature's ``BoxObstacle``), and whether it is only a footprint (0 mm)."""
    from tocabi_torchrl.envs.config import BoxObstacle

    virtual = height_mm <= 0
    box = BoxObstacle.ahead_of_left_foot(0.001 if virtual else height_mm / 1000.0, distance=args.distance,
                                         length=args.box_length, width=args.box_width,
                                         jitter=(args.jitter, args.jitter))
    return box, virtual


def with_box(box, virtual: bool):
    """The env-config edit that puts ``box`` into the scene (none for a virtual box)."""
    from tocabi_torchrl.envs.config import SceneConfig

    def edit(env_cfg):
        return env_cfg if virtual else dataclasses.replace(env_cfg, scene=SceneConfig(obstacles=(box,)))

    return edit


def box_centres(policy, box, virtual: bool) -> torch.Tensor:
    """(N, 3) the box centre of every robot: the env's own, or (no box) the jittered positions it would have."""
    base = policy.env.base_env
    if not virtual:
        return base.obstacle_pos[:, 0].cpu()
    from tocabi_torchrl.envs.obstacles import world_obstacle_centres

    return torch.as_tensor(world_obstacle_centres((box,), base.num_envs, base.scene_seed)[:, 0], dtype=torch.float32)


def run_one(controller, height_mm, args, device) -> dict:
    """One controller at one height: rollout, analysis, the example robots' frames and torque traces."""
    box, virtual = make_box(args, height_mm)
    policy = load_policy(controller.path, args.num_envs, device, command=(args.vx, args.vy),
                         edit_env=with_box(box, virtual), nominal=True)  # the robot, as the gait tests
    rec = record_rollout(policy.actor, policy.env, args.seconds, (args.vx, args.vy), snapshot_every=0.5,
                         desc=f"{controller.label}, {height_mm:g} mm").cpu()
    size = (box.size[0], box.size[1], 0.0 if virtual else box.size[2])
    centres = box_centres(policy, box, virtual)
    outcome = analyse_obstacle(rec, centres, size, virtual=virtual, steps=args.steps_on_obstacle)
    row = {"controller": controller.label, "checkpoint": display_path(controller.path),
           "control_mode": rec.control_mode,
           "height_mm": height_mm, "box_size_m": list(size), "box_nominal_pos_m": list(box.pos),
           **outcome.summary}
    row["peak_torque_on_obstacle_per_joint_Nm"] = dict(zip(CRITICAL_JOINTS,
                                                           row["peak_torque_on_obstacle_per_joint_Nm"]))
    print(f"   {controller.label}, {height_mm:g} mm: pass {row['pass_rate']:.2f}, failed on obstacle "
          f"{row['failed_on_obstacle_rate']:.2f}, crossed {row['crossed_rate']:.2f}, lateral deviation after "
          f"{row['lateral_deviation_after_m']:.3f} m", flush=True)
    # torque trace of one robot that touched the box: 0.5 s before its first contact to the end of its window
    trace = None
    touched = np.flatnonzero(outcome.first_contact.numpy() >= 0)
    if touched.size:
        env = int(touched[0])
        first = int(outcome.first_contact[env])
        s0 = max(0, first - int(round(0.5 / rec.dt)))
        end = int(np.flatnonzero(outcome.window[:, env].numpy())[-1]) + 1
        trace = {"torque": rec.leg_torque[s0:end, env][:, list(CRITICAL)].numpy(), "t0": (first - s0 + 1) * rec.dt,
                 "env": env}
    examples = {}
    mocap = getattr(policy.env.base_env.sim, "world_mocap_pos", None)  # (N, nmocap, 3) per-world boxes, or None
    for kind, want in (("pass", True), ("fail", False)):
        env = pick_example(outcome, want)
        if env is not None:
            examples[kind] = frame_states(rec, outcome, env)
            examples[kind]["mocap_pos"] = None if mocap is None else mocap[env]
    return {"row": row, "trace": trace, "examples": examples, "dt": rec.dt,
            "model": policy.env.base_env.sim.mj_model, "virtual": virtual}


def frame_states(rec, outcome, env: int) -> dict:
    """Joint states of ``env`` to draw: start, first contact, +1 s, +2 s, and the end or its termination."""
    times = np.asarray(rec.snapshot_times)
    first = int(outcome.first_contact[env])
    term = int(rec.termination_step[env])
    end_t = (term + 1) * rec.dt if term >= 0 else rec.seconds
    picks = [(0.0, "start")]
    if first >= 0:
        t_contact = (first + 1) * rec.dt
        for extra, name in ((0.0, "first contact"), (1.0, "contact + 1 s"), (2.0, "contact + 2 s")):
            t = t_contact + extra
            if t < end_t:
                picks.append((t, name))
    states, labels = [], []
    for t, name in picks:
        j = int(np.searchsorted(times, t - 1e-9))  # the first snapshot at or after t
        if j < len(times) and times[j] < end_t:
            states.append(rec.snapshots[j, env].numpy())
            labels.append(f"{name}, t = {times[j]:g} s")
    if term >= 0:
        states.append(rec.termination_qpos[env].numpy())
        labels.append(f"terminated, t = {end_t:.2f} s")
    else:
        states.append(rec.snapshots[-1, env].numpy())
        labels.append(f"end, t = {rec.snapshot_times[-1]:g} s")
    return {"qpos": np.stack(states), "labels": labels, "env": env}


def render_examples(result: dict, label: str, height_mm: float, args, out) -> list[str]:
    """Frame strips of the pass and fail examples of one controller at one height; returns the files written."""
    written = []
    model = result["model"]
    for kind, ex in result["examples"].items():
        def place(data, mocap_pos=ex["mocap_pos"]):  # this robot's box, where its world had it
            if mocap_pos is not None:
                data.mocap_pos[:] = mocap_pos

        stills = render_stills(model, ex["qpos"], CAMERA_POS, width=args.frame_width, height=args.frame_height,
                               setup=place, fovy=args.fovy)
        stills = [label_image(im, f"{label}, {height_mm:g} mm, robot {ex['env']} ({kind}): {text}")
                  for im, text in zip(stills, ex["labels"])]
        path = out / f"frames_{slug(label)}_{height_mm:g}mm_{kind}.png"
        # atomically: a run killed mid-write (or a full disk) leaves the earlier strip of a resumed run whole
        replace_atomically(path, lambda tmp, stills=stills: save_strip(stills, tmp))
        written.append(path.name)
    return written


def save_trace(trace: dict | None, dt: float, path) -> None:
    """The torque trace drawn into torques_<h>mm.png, kept as a file so that a resumed run can redraw that figure
    with the controllers it adds (none: no robot touched the box)."""
    if trace is None:
        path.unlink(missing_ok=True)
        return
    buffer = io.BytesIO()
    np.savez_compressed(buffer, torque=trace["torque"], t0=trace["t0"], env=trace["env"], dt=dt)
    write_atomic(path, buffer.getvalue())


def plot_torques(out, height_mm: float, controllers, args) -> None:
    """torques_<h>mm.png from the saved traces of every controller at this height, measured now or earlier."""
    traces, dt = {}, None
    for controller in controllers:
        path = out / f"trace_{slug(controller.label)}_{height_mm:g}mm.npz"
        if path.is_file():
            with np.load(path) as saved:
                traces[controller.label] = {"torque": saved["torque"], "t0": float(saved["t0"]),
                                            "env": int(saved["env"])}
                dt = float(saved["dt"])
    if not traces:
        return
    plot_joint_torques({label: tr["torque"] for label, tr in traces.items()}, dt, out / f"torques_{height_mm:g}mm.png",
                       CRITICAL_JOINTS, f"Torques over the first {args.steps_on_obstacle} steps on a {height_mm:g} mm "
                       f"box (robots {', '.join(str(tr['env']) for tr in traces.values())})",
                       t0={label: tr["t0"] for label, tr in traces.items()}, xlabel="time from the first contact [s]",
                       limits=robot.LEG_TORQUE_LIMITS[list(CRITICAL)], mark_zero=True)


def main(argv: list[str] | None = None) -> dict:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        heights = sorted({float(h) for h in args.heights_mm.split(",") if h.strip()})
    except ValueError:
        parser.error(f"--heights_mm takes comma-separated numbers, got {args.heights_mm!r}")
    if args.num_envs < 1 or args.seconds <= 0 or not heights or min(heights) < 0 or args.step_mm < 0:
        parser.error("--num_envs must be >= 1, --seconds > 0, --heights_mm non-empty and >= 0, --step_mm >= 0")
    if args.steps_on_obstacle < 1:
        parser.error(f"--steps_on_obstacle must be >= 1 (footfalls the torque window covers), got "
                     f"{args.steps_on_obstacle}")
    if not math.isfinite(args.step_mm) or 0 < args.step_mm < 1e-6:  # heights are rounded to 1e-6 mm
        parser.error(f"--step_mm must be 0 (only --heights_mm) or a finite step of at least 1e-6 mm, got "
                     f"{args.step_mm:g}")
    if not all(map(math.isfinite, heights)):
        parser.error(f"--heights_mm must be finite numbers, got {args.heights_mm!r}")
    if not math.isfinite(args.max_mm) or args.max_mm < 0:  # a NaN or inf cap never stops the search
        parser.error(f"--max_mm must be a finite height >= 0 (the cap of the heights tried), got {args.max_mm:g}")
    if math.isnan(args.fail_below):  # (0 means no height fails, above 1 that every one does: both have their uses)
        parser.error("--fail_below must be a number: a controller fails a height when its pass rate is below it")
    # The box checks its own sizes only when the first height is measured, after --out was made: checked here first.
    if not math.isfinite(args.distance):
        parser.error(f"--distance must be a finite distance [m] (box centre ahead of the left sole), got "
                     f"{args.distance:g}")
    for flag, value in (("--box_length", args.box_length), ("--box_width", args.box_width)):
        if not math.isfinite(value) or value <= 0:
            parser.error(f"{flag} must be a finite length > 0 [m], got {value:g}")
    if not math.isfinite(args.jitter) or args.jitter < 0:
        parser.error(f"--jitter must be a finite half-range >= 0 [m] (0: every robot's box at the same place), got "
                     f"{args.jitter:g}")
    if args.resume and args.overwrite:
        parser.error("--resume keeps the earlier table's rows, --overwrite replaces them: pass one of them")
    try:
        from tocabi_torchrl.envs.config import BoxObstacle, SceneConfig  # noqa: F401
    except ImportError:
        sys.exit("error: this recipe needs the env's obstacles (tocabi_torchrl.envs.config.BoxObstacle, "
                 "env.scene.obstacles), which this version of the package lacks")
    settings = {f"--{name}": getattr(args, name) for name in SETTINGS}
    try:
        controllers = parse_controllers(args.policy)
        device = resolve_device(args.device)
        checkpoints = {controller.label: checkpoint_record(controller) for controller in controllers}
        out = prepare_out_dir(args.out, args.overwrite, resume=args.resume)
        rows, earlier = earlier_table(out, EXPERIMENT, settings, checkpoints) if args.resume else ([], {})
    except (ValueError, RuntimeError, ExperimentOutputError) as err:
        sys.exit(f"error: {err}")
    for label, record in checkpoints.items():  # a checkpoint gone since: keep the earlier call's record of it
        if record["sha256"] is None and label in earlier.get("checkpoints", {}):
            checkpoints[label] = earlier["checkpoints"][label]
    order = {controller.label: i for i, controller in enumerate(controllers)}
    done = {(row["controller"], round(row["height_mm"], 6)) for row in rows}
    if rows:
        print(f"resuming {out}/table.json: {len(rows)} rows kept, at "
              f"{', '.join(f'{h:g}' for h in sorted({h for _, h in done}))} mm")
    frames = list(earlier.get("frames", []))
    this_call = {"argv": sys.argv[1:] if argv is None else list(argv), "device": str(device),
                 "torch": torch.__version__, "measured": []}
    no_frames = rendering_unavailable()  # why nothing is rendered (also after the first failure), or None
    if no_frames:
        print(f"frames skipped: {no_frames}")

    def save_table(stop: str | None) -> None:
        """table.md and table.json with every row so far; ``stop`` None: the run is still going."""
        rows.sort(key=lambda row: (row["height_mm"], order[row["controller"]]))
        calls = earlier.get("calls", []) + ([this_call] if this_call["measured"] else [])
        devices = ", ".join(dict.fromkeys(call["device"] for call in calls)) or str(device)
        meta = {"experiment": EXPERIMENT, "command_mps": [args.vx, args.vy], "seconds": args.seconds,
                "num_envs": args.num_envs, "heights_mm": sorted({row["height_mm"] for row in rows}),
                "complete": stop is not None, "stopped_after": stop or "in progress (continue it with --resume)",
                "box_length_m": args.box_length, "box_width_m": args.box_width,
                "distance_ahead_of_left_sole_m": args.distance, "jitter_m": args.jitter, "frames": frames,
                "settings": settings, "checkpoints": checkpoints, "calls": calls}
        write_table(rows, COLUMNS, out, notes=NOTES, meta=meta,
                    title=f"Obstacle test at ({args.vx:g}, {args.vy:g}) m/s, {args.seconds:g} s, {args.num_envs} "
                    f"robots per controller and height, {devices}")

    stop, i = "the heights listed in --heights_mm", 0
    while i < len(heights):
        height = heights[i]
        todo = [controller for controller in controllers if (controller.label, round(height, 6)) not in done]
        print(f"[height {height:g} mm] {len(todo)} of {len(controllers)} controllers to measure"
              + (f" x {args.num_envs} robots x {args.seconds:g} s on {device}" if todo else
                 " (all in the earlier table)"), flush=True)
        for controller in todo:
            try:
                result = run_one(controller, height, args, device)
            except (CheckpointError, ValueError) as err:
                sys.exit(f"error: {controller.label}: {err}")
            rows.append(result["row"])
            this_call["measured"].append([controller.label, height])
            save_trace(result["trace"], result["dt"], out / f"trace_{slug(controller.label)}_{height:g}mm.npz")
            if no_frames:
                frames.append(f"not rendered: {controller.label}, {height:g} mm: {no_frames}")
            else:
                try:
                    frames += render_examples(result, controller.label, height, args, out)
                except Exception as err:  # noqa: BLE001 - no OpenGL backend; MuJoCo is not asked again (it can abort)
                    no_frames = f"{type(err).__name__}: {err}"
                    frames.append(f"not rendered: {controller.label}, {height:g} mm: {no_frames}")
                    print(f"frames skipped from here on ({no_frames}); rendering is not tried again in this run. On "
                          f"a headless machine: {NO_GL_FIX}")
            save_table(None)
        # Redrawn at every height, measured now or not: a run killed after a row was saved but before this plot
        # would otherwise leave the figure without that controller.
        plot_torques(out, height, controllers, args)
        i += 1
        if i == len(heights) and args.step_mm > 0:
            at_height = [row for row in rows if round(row["height_mm"], 6) == round(height, 6)]
            nxt = round(height + args.step_mm, 6)
            if all(row["pass_rate"] < args.fail_below for row in at_height):
                stop = f"every controller's pass rate fell below {args.fail_below:g} at {height:g} mm"
            elif nxt > args.max_mm:
                stop = f"the cap --max_mm {args.max_mm:g} (not every controller failed)"
            else:
                heights.append(nxt)
    plot_vs_height(rows, "pass_rate", "pass rate", out / "pass_rate.png", "Pass rate (no termination in the episode)")
    plot_vs_height(rows, "lateral_deviation_after_m", "lateral deviation after the box [m]",
                   out / "lateral_deviation.png", "Lateral deviation after the obstacle")
    plot_vs_height(rows, "peak_torque_on_obstacle_Nm", "peak |torque| [N·m]", out / "peak_torque.png",
                   f"Peak torque over the first {args.steps_on_obstacle} steps on the obstacle")
    save_table(stop)
    print(f"wrote {out}/: table.md, table.json ({len(this_call['measured'])} of {len(rows)} rows measured now), "
          f"pass_rate.png, lateral_deviation.png, peak_torque.png, torques_<h>mm.png, "
          f"{len([f for f in frames if f.endswith('.png')])} frame strips; stopped after {stop}")
    print(json.dumps([{k: row[k] for k in COLUMNS} for row in rows], indent=2))
    return {"out": str(out), "rows": rows, "frames": frames, "heights_mm": heights, "stopped_after": stop,
            "measured": [tuple(pair) for pair in this_call["measured"]]}


if __name__ == "__main__":
    main(sys.argv[1:])
