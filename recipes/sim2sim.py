"""Sim-to-sim: drive C MuJoCo TOCABI robots through an exported policy with the torch-free runtime.

    python recipes/sim2sim.py --contract assets/policies/tocabi_walk_ppo.json
    python recipes/sim2sim.py --contract assets/policies/tocabi_walk_torque.json --model reference --num_robots 8
    python recipes/sim2sim.py --contract assets/policies/tocabi_walk_ppo.json --viewer --seconds 60 --num_robots 16
    python recipes/sim2sim.py --contract assets/policies/tocabi_walk_torque.json --randomize tocabi_lab \
        --pushes 3 --push_speed 0.5 --start_noise --seed 1

``--model authored`` (default) is assets/tocabi/tocabi.xml; ``reference`` is ../shared/reference/dyros_tocabi.xml
(beside the repository) with its mesh geoms removed; any other value is an MJCF path. Prints the gait-test metrics
of evaluation/gait_test.py (survival, forward distance, lateral drift, speed tracking error, knee RMS) as JSON. Needs
numpy, mujoco, onnxruntime and tqdm only (`pip install -e ".[export]"`); torch is never imported.

``--randomize`` (default ``none``: the nominal robot, numbers exactly as without it) draws per robot at the reset:
``trained`` what the contract's ``trained_under`` section states, ``tocabi_lab`` the TOCABI lab's actuator delay and
motor constant (torque policies), link masses, damping, armature and sensor biases and noise. ``--pushes N`` kicks
every robot N times at random times in 2-7 s (so ``--seconds`` must last past 7 s), each a velocity change of
``--push_speed`` m/s in a random horizontal direction, within one control period (``--push_kind velocity``, the
robust gait test's: the whole robot's velocity changes; ``force``: an impulse of the same momentum on the pelvis
alone); ``--start_noise`` starts the robots with the robust gait test's N(0, 0.5 rad/s) joint and N(0, 0.1 m/s)
pelvis velocities; ``--sensor FIELD=VALUE ...`` replaces sensor fields of the chosen set (an estimator's error on the
pelvis velocity, say); ``--seed`` seeds every draw (docs/concepts/randomization.md, "Sim-to-sim with randomisation").
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
from pathlib import Path

from tocabi_torchrl.cli import RecipeParser, add_viewer_options
from tocabi_torchrl.value_rules import PUSH_KINDS

REFERENCE_MODEL = Path(__file__).resolve().parents[1].parent / "shared" / "reference" / "dyros_tocabi.xml"


def build_parser() -> argparse.ArgumentParser:
    parser = RecipeParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--contract", required=True, help="policy contract .json (the .onnx lies beside it)")
    parser.add_argument("--onnx", default=None,
                        help="the .onnx to run (default: the one beside the contract, of its name); it must be the "
                             "one exported with the contract (its sha256)")
    parser.add_argument("--model", default="authored", help="authored, reference, or an MJCF path (default: authored)")
    parser.add_argument("--seconds", type=float, default=8.0, help="simulated time [s] (default: 8)")
    parser.add_argument("--num_robots", type=int, default=4,
                        help="robots, started at the motion's start rows in turn (default: 4)")
    parser.add_argument("--vx", type=float, default=0.5, help="commanded forward speed [m/s] (default: 0.5)")
    parser.add_argument("--vy", type=float, default=0.0, help="commanded lateral speed [m/s] (default: 0)")
    parser.add_argument("--out", default=None, help="also write the metrics to this JSON file (never overwritten)")
    parser.add_argument("--randomize", default="none", choices=("none", "trained", "tocabi_lab"),
                        help="per-robot randomisation drawn at the reset: none (default), trained (what the contract "
                             "states the policy was trained under) or tocabi_lab")
    parser.add_argument("--pushes", type=int, default=0,
                        help="horizontal kicks per robot, at random times in 2-7 s (default: 0)")
    parser.add_argument("--push_speed", type=float, default=0.5,
                        help="velocity change of the whole robot per kick [m/s] (default: 0.5)")
    parser.add_argument("--push_kind", choices=PUSH_KINDS, default="velocity",
                        help="velocity: every body's velocity changes by --push_speed (the robust gait test's kicks, "
                             "default); force: the same momentum as a force on the pelvis alone")
    parser.add_argument("--sensor", nargs="+", action="extend", default=[], metavar="FIELD=VALUE",
                        help="sensor biases (half-widths of U(±b)) and noise (σ, clip or none) set on top of "
                             "--randomize's, by SensorSettings field (tocabi_torchrl/runtime/randomization.py; rad, "
                             "rad/s, N, N·m, m/s as the signal), e.g. base_lin_vel_noise_std=0.0144 "
                             "base_lin_vel_noise_clip=0.025: what a state estimator's error does to the policy "
                             "(default: none)")
    parser.add_argument("--start_noise", action="store_true",
                        help="start with N(0, 0.5 rad/s) joint and N(0, 0.1 m/s) pelvis velocities (robust gait test)")
    parser.add_argument("--seed", type=int, default=0, help="seed of every random draw (default: 0)")
    add_viewer_options(parser, "watch the robots live in a browser while they run, in real time (pip install -e "
                               "\".[viewer]\"; docs/viewer.md)")
    return parser


if __name__ == "__main__":  # --help or a misspelt option answers before mujoco and onnxruntime load
    build_parser().parse_args(sys.argv[1:])

from tocabi_torchrl.atomic import atomic_write_text  # noqa: E402
from tocabi_torchrl.evaluation.output import json_safe  # noqa: E402
from tocabi_torchrl.runtime import ContractError, PolicyRuntime  # noqa: E402
from tocabi_torchrl.runtime.mujoco_driver import resolve_randomization, run_sim2sim  # noqa: E402
from tocabi_torchrl.runtime.randomization import ROBUST_START, PushSettings, SensorSettings  # noqa: E402
from tocabi_torchrl.value_rules import MAX_SEED, PUSH_SPEED  # noqa: E402


def watch(args: argparse.Namespace, dt: float):
    """--viewer: a live page (numpy, mujoco and viser only) and the driver's per-period callback that draws on it
    (``dt``: the contract's control period [s])."""
    from tocabi_torchrl.viewer.exported import ExportedWatch
    from tocabi_torchrl.viewer.server import page_url, start_server

    server = start_server(args.viewer_host, args.viewer_port)
    print(f"viewer: {args.num_robots} robots of {args.contract} for {args.seconds} s, in real time; open "
          f"{page_url(args.viewer_host, server.get_port())}", flush=True)
    return server, ExportedWatch(server, dt)


def progress(args: argparse.Namespace, dt: float, draw=None):
    """A progress bar on stderr (stdout stays the JSON) and the driver's per-period callback that moves it (and
    calls ``draw``, the viewer's, when given): ``(bar, on_step)``; ``dt``: the contract's control period [s]."""
    try:
        from tqdm import tqdm
    except ImportError as err:
        raise ImportError("the progress bar needs tqdm: pip install tqdm (or pip install -e \".[export]\" in the "
                          "repository, which brings it with the package)") from err

    bar = tqdm(total=round(args.seconds / dt), unit="step", desc=f"sim2sim, {args.num_robots} robots",
               file=sys.stderr, mininterval=1.0, leave=False)

    def on_step(step, model, datas) -> None:
        bar.update(1)
        if draw is not None:
            draw(step, model, datas)

    return bar, on_step


def sensor_overrides(items: list[str]) -> dict[str, float | None]:
    """``--sensor`` items ``FIELD=VALUE`` as SensorSettings fields; ``ValueError`` naming a malformed item, an unknown
    or repeated field, a value that is not a number (a clip also takes ``none``) or one the training config would
    refuse (a negative or NaN bias or σ, a clip <= 0)."""
    known = [f.name for f in dataclasses.fields(SensorSettings)]
    out = {}
    for item in items:
        field, sep, text = item.partition("=")
        if not sep or not field:
            raise ValueError(f"--sensor {item!r}: give FIELD=VALUE, e.g. base_lin_vel_noise_std=0.0144")
        if field not in known:
            raise ValueError(f"--sensor {item!r}: no sensor field {field!r}; the fields are {', '.join(known)}")
        if field in out:  # the last would win unseen
            raise ValueError(f"--sensor {item!r}: {field} is given twice; give each field once")
        if field.endswith("_clip") and text.strip().lower() == "none":
            out[field] = None
            continue
        try:
            out[field] = float(text)
        except ValueError:
            raise ValueError(f"--sensor {item!r}: {text!r} is not a number"
                             + (" (or none: no clip)" if field.endswith("_clip") else "")) from None
    # Each field's rule stands alone, so the defaults with these fields show every bad value before a file is read.
    SensorSettings(**out).validate(prefix="--sensor ")
    return out


def with_sensors(randomize: str, runtime: PolicyRuntime, overrides: dict):
    """The randomisation ``randomize`` names for ``runtime``'s policy, its sensor settings replaced field by field by
    ``overrides`` (``randomize`` itself when there are none). ``ValueError``, before the run (and a viewer's page),
    for a bias or noise on a signal the policy does not observe and for a clip given for a signal left without
    noise: either would do nothing, yet be reported."""
    if not overrides:
        return randomize
    observed = runtime.observation.signals
    unread = [f for f, v in overrides.items() if not f.endswith("_clip") and v
              and f.removesuffix("_noise_std").removesuffix("_bias") not in observed]
    if unread:
        raise ValueError(f"--sensor {unread[0]}: this policy does not observe that signal (it observes "
                         f"{', '.join(sorted(observed))}); leave it out")
    chosen = resolve_randomization(randomize, runtime.contract)
    sensors = dataclasses.replace(chosen.sensors, **overrides)
    idle = [f for f in overrides if f.endswith("_noise_clip") and overrides[f] is not None
            and getattr(sensors, f.replace("_clip", "_std")) == 0]
    if idle:
        raise ValueError(f"--sensor {idle[0]} clips a noise that is off in --randomize {randomize} and not set: give "
                         f"{idle[0].replace('_clip', '_std')} too, or leave the clip out")
    return dataclasses.replace(chosen, sensors=sensors)


def main(argv: list[str] | None = None) -> dict:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.num_robots < 1:
        parser.error(f"--num_robots must be >= 1, got {args.num_robots}")
    if not 0 < args.seconds < math.inf:
        parser.error(f"--seconds must be a finite number of seconds > 0, got {args.seconds}")
    if not (math.isfinite(args.vx) and math.isfinite(args.vy)):
        parser.error(f"--vx and --vy must be finite speeds [m/s], got {args.vx} and {args.vy}")
    if not 0 <= args.pushes <= 64:
        parser.error(f"--pushes must be an int in [0, 64] (kicks per robot), got {args.pushes}")
    if not PUSH_SPEED.allows(args.push_speed):  # the kicks' own rule, said with the option's name
        parser.error(f"--push_speed must be a finite velocity change >= 0 and <= {PUSH_SPEED.high:g} [m/s], got "
                     f"{args.push_speed}{PUSH_SPEED.because(args.push_speed)}")
    parser.refuse_without(args, args.pushes > 0, "--pushes N", ("push_speed", "push_kind"))
    parser.refuse_without(args, args.viewer, "--viewer", ("viewer_host", "viewer_port"))
    try:
        sensors = sensor_overrides(args.sensor)
    except ValueError as err:
        parser.error(str(err))
    if not 0 <= args.seed <= MAX_SEED:
        parser.error(f"--seed must be an int in [0, 2**63 - 1], got {args.seed}")
    if args.out is not None and not args.out.strip():  # "--out $OUT" with OUT unset would write nothing
        parser.error("--out is empty; give a JSON file to write the metrics to (e.g. --out sim2sim.json), or leave "
                     "--out out")
    if args.out and (Path(args.out).is_dir() or args.out.endswith(("/", os.sep))):
        # A missing "runs/" would otherwise be written as a file named runs.
        parser.error(f"--out {args.out} is a folder; give a file name, e.g. --out "
                     f"{Path(args.out) / 'sim2sim.json'}")
    if args.out and Path(args.out).exists():
        parser.error(f"--out {args.out} exists; choose another file")
    if args.out and not Path(args.out).parent.is_dir():  # checked now, not after the whole run
        parser.error(f"--out {args.out}: folder {Path(args.out).parent} does not exist; create it or choose another "
                     "file")
    contract = Path(args.contract)
    if contract.suffix in (".onnx", ".pt"):  # the policy itself rather than its contract
        stem = contract.name.removesuffix(".pt").removesuffix(".ts") if contract.suffix == ".pt" else contract.stem
        beside = contract.with_name(f"{stem}.json")
        hint = f"; the contract beside it is {beside}" if beside.is_file() else (
            "; python -m tocabi_torchrl.export writes the .onnx and its .json" if contract.suffix == ".pt" else "")
        parser.error(f"--contract takes the policy's .json contract, not a {contract.suffix} file ({contract}){hint}")
    model, strip = args.model, False
    if model not in ("authored", "reference") and not Path(model).is_file():
        parser.error(f"--model {model}: no such file; give an MJCF path, or authored (default) or reference")
    if model == "authored":
        model = None
    elif model == "reference":
        if not REFERENCE_MODEL.is_file():
            parser.error(f"--model reference: the reference implementation's model is not at {REFERENCE_MODEL} (this "
                         "repository does not ship it); leave --model out for the authored model, or give an MJCF path")
        model, strip = REFERENCE_MODEL, True
    server = bar = None
    try:
        # The whole policy (contract, the .onnx that runs and its hash, onnxruntime, motion) is checked before a
        # page is served: a failure after the URL is printed would leave a page that never shows a robot.
        runtime = PolicyRuntime(args.contract, onnx=args.onnx)
        randomize = with_sensors(args.randomize, runtime, sensors)
        dt, draw = float(runtime.contract["timing"]["control_dt_s"]), None
        pushes = (PushSettings(count=args.pushes, speed=(args.push_speed, args.push_speed), kind=args.push_kind)
                  if args.pushes else None)
        if pushes and round(args.seconds / dt) <= round(pushes.window[1] / dt):
            # Kicks after the run's end never start: --seconds 1 ran with no kick at all and reported the survival
            # of an unpushed walk, with only "kicks_started": 0 in the metrics to tell.
            start, end = pushes.window  # the kicks' times [s]
            parser.error(f"--pushes {args.pushes} kicks each robot at random times in {start:g}-{end:g} s "
                         f"(kick j in the j-th share), but --seconds {args.seconds:g} ends the run before "
                         f"{'any' if args.seconds <= start else 'all'} of them: pass --seconds "
                         f"{end + 1:g} or more (the default is 8), or leave --pushes out")
        if args.viewer:  # the missing extra is an ImportError, said before the run
            server, draw = watch(args, dt)
        bar, on_step = progress(args, dt, draw)
        try:
            result = run_sim2sim(runtime, model, seconds=args.seconds, num_robots=args.num_robots,  # the one checked
                                 command=(args.vx, args.vy), remove_meshes=strip, seed=args.seed,
                                 randomize=randomize, pushes=pushes,
                                 start_velocity=ROBUST_START if args.start_noise else None,
                                 on_step=on_step).as_dict()
        except MemoryError:  # numpy's bare MemoryError named neither the option nor what to do
            sys.exit(f"error: not enough memory for {args.num_robots:,} robots over {args.seconds:g} s on this "
                     "machine: lower --num_robots (or --seconds)")
    except (ContractError, ValueError, ImportError) as err:  # bad contract or model, or onnxruntime missing
        sys.exit(f"error: {err}")
    except KeyboardInterrupt:  # 130, as for any Ctrl-C stop (sys.exit with a message would say 1)
        print("stopped (Ctrl-C)", file=sys.stderr)
        sys.exit(130)
    finally:
        if bar is not None:
            bar.close()
        if server is not None:
            server.stop()
    result["model"] = str(args.model)
    if sensors:  # the driver names a randomisation it was given as an object "custom": say which, and what changed
        result["perturbations"].update(randomize=args.randomize, sensor=sensors)
    # Standard JSON, as the export writes: a metric of no robot (every one fell in the first period) is null, not the
    # NaN that strict JSON readers refuse.
    text = json.dumps(json_safe(result), indent=2, allow_nan=False)
    print(text)
    if args.out:
        try:
            # Never a half-written file, nor one replacing a file created there during the run (--out was free).
            atomic_write_text(args.out, text + "\n", replace=False)
        except FileExistsError:
            sys.exit(f"error: --out {args.out} was created by something else during the run and is left as it is; "
                     "the metrics are printed above")
        except OSError as err:  # e.g. a full disk or no write permission: the metrics are printed above
            sys.exit(f"error: cannot write --out {args.out} ({err}); the metrics are printed above")
    return result


if __name__ == "__main__":
    main(sys.argv[1:])
