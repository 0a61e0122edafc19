"""Evaluate a trained walking policy: deterministic policy, command (0.5, 0) m/s for 8 s (TocabiLab's gait test).

    python recipes/play.py --checkpoint runs/ppo_walk                 # a run folder (uses checkpoints/latest.pt)
    python recipes/play.py --checkpoint runs/ppo_walk/checkpoints/iter_000500.pt --num_envs 64 --vx 0.3
    python recipes/play.py --checkpoint runs/ppo_walk --test robust   # the robust gait test (docs/evaluation.md)
    python recipes/play.py --policy ppo --viewer --num_envs 64        # watch it walk live in a browser

Writes summary.json (survival, forward distance, lateral drift, speed tracking error, knee RMS against the reference
motion; null for a metric without a value), knees.png (left/right knee over 6 s against the reference) and walk.mp4
(a few robots, rendered offscreen) to <run>/eval/, eval/ beside a checkpoint file, runs/eval/<name>/ for a policy
shipped with the package, or --out. Earlier results are never replaced silently: when the default folder already
holds some, the next free eval_2/, eval_3/, ... beside it is used; an --out that holds files is refused unless
--overwrite. The folder used is printed first. --test robust runs the robust gait test instead (diverse starts;
nominal, changing commands, randomised and pushed cases; --num_envs robots per case) and writes robust.json and
robust.png.
--viewer serves a live web page instead (the `viewer` extra, docs/viewer.md): every robot walking, command sliders,
pause/step, push, reset, world picker, camera follow, the gait metrics and a knee trace; --viewer_host/--viewer_port
say where (reach a remote machine with ssh -L 8080:localhost:8080). --policy names a shipped policy (ppo, torque,
model_based, robust) or a run folder or file, like --checkpoint.
On a headless machine the video uses EGL (MUJOCO_GL=egl, chosen automatically when libEGL is present); osmesa works
only with libOSMesa and PyOpenGL installed.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from tocabi_torchrl.cli import RecipeParser, add_viewer_options
from tocabi_torchrl.render_gl import choose_gl_backend_or_exit

#: (option, type, default, description): the command line, defaults shown once by build_parser.
OPTIONS = (
    ("--num_envs", int, None, ("robots simulated in the gait test, per case in the robust test (default: 256 in the "
                               "standard test, 1024 in the robust one)")),
    ("--device", str, "auto", "auto (CUDA if present, else cpu), cpu, cuda or cuda:N"),
    ("--seconds", float, 8.0, "duration of the gait test [s]; at least one policy step (0.004)"),
    ("--vx", float, 0.5, "commanded forward speed [m/s] (standard test)"),
    ("--vy", float, 0.0, "commanded lateral speed [m/s] (standard test)"),
    ("--out", str, None, ("output folder, refused if it holds files unless --overwrite (default: eval/ of the "
                          "run, eval/ beside a checkpoint file, or runs/eval/<name>/ for a shipped policy; eval_2/, "
                          "... once that holds results)")),
    ("--video_envs", int, 4, "robots shown side by side in the video (standard test); 0 = no video"),
)
#: The gait tests (docs/evaluation.md) and the robots each simulates when --num_envs is left out (per case: robust).
TESTS = {"standard": 256, "robust": 1024}


def build_parser() -> argparse.ArgumentParser:
    parser = RecipeParser(description=__doc__.split("\n\n")[0])
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--checkpoint", help="run folder or checkpoint .pt file (this or --policy is required)")
    source.add_argument("--policy", help="a shipped policy (ppo, torque, model_based, robust), a run folder or a file")
    for flag, kind, default, text in OPTIONS:
        shown = "" if default is None else f" (default: {default})"
        parser.add_argument(flag, type=kind, default=default, help=text + shown)
    parser.add_argument("--test", choices=tuple(TESTS), default="standard",
                        help="standard: the 8 s test at one command (256 robots, two distinct starts); robust: "
                             "diverse starts, the nominal, changing-command, randomised and pushed cases "
                             "(default: standard)")
    parser.add_argument("--overwrite", action="store_true",
                        help="write into an --out folder that holds files (files of the same name are replaced, "
                             "others stay) (default: refuse)")
    add_viewer_options(parser, "serve a live web page of the robots instead of the gait test (pip install -e "
                               "\".[viewer]\"; 64 robots unless --num_envs)")
    parser.add_argument("--backend", choices=("warp", "mujoco"), default=None,
                        help="--viewer: the physics backend, replacing the checkpoint's (mujoco: C MuJoCo on the CPU) "
                             "(default: the checkpoint's)")
    return parser


#: Robots simulated by --viewer when --num_envs is left out.
VIEWER_ENVS = 64


if __name__ == "__main__":  # --help or a misspelt option answers before torch and mujoco load
    build_parser().parse_args(sys.argv[1:])

choose_gl_backend_or_exit()  # before mujoco is imported

import torch  # noqa: E402

from tocabi_torchrl.device import check_device  # noqa: E402
from tocabi_torchrl.rl.checkpoint import verified_checkpoint_file  # noqa: E402
from tocabi_torchrl.rl.trainer import resolve_device  # noqa: E402
from tocabi_torchrl.evaluation.gait_test import eval_out_dir, evaluate_run, gait_report_text, policy_dt  # noqa: E402
from tocabi_torchrl.evaluation.output import remove_if_empty  # noqa: E402
from tocabi_torchrl.evaluation.plots import check_plotting  # noqa: E402
from tocabi_torchrl.evaluation.record import policy_steps  # noqa: E402


def sim2sim_options(args: argparse.Namespace) -> str:
    """The options of ``recipes/sim2sim.py`` that repeat this call's non-default ones, for an exported policy given
    as --checkpoint (sim2sim's own defaults are the same for --seconds, --vx and --vy)."""
    defaults = {flag: default for flag, _, default, _ in OPTIONS}
    options = [("--num_robots", args.num_envs)] if args.num_envs not in (None, TESTS["standard"]) else []
    options += [(flag, getattr(args, flag[2:])) for flag in ("--seconds", "--vx", "--vy")
                if getattr(args, flag[2:]) != defaults[flag]]
    return "".join(f" {flag} {value}" for flag, value in options)


def main(argv: list[str] | None = None) -> None:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.num_envs is not None and args.num_envs < 1 or args.video_envs < 0:
        parser.error("--num_envs must be >= 1 and --video_envs >= 0")
    if not 0 < args.seconds < math.inf:
        parser.error(f"--seconds must be a finite number of seconds > 0, got {args.seconds}")
    if not (math.isfinite(args.vx) and math.isfinite(args.vy)):
        parser.error(f"--vx and --vy must be finite speeds [m/s], got {args.vx} and {args.vy}")
    parser.refuse_without(args, args.viewer, "--viewer", ("viewer_host", "viewer_port"))
    if args.checkpoint is not None and not args.checkpoint.strip():  # Path("") would be the current folder
        parser.error("--checkpoint is empty: give a run folder or a checkpoint .pt file")
    if args.policy is not None:
        from tocabi_torchrl.viewer.policy_source import resolve_policy

        try:
            args.checkpoint = str(resolve_policy(args.policy))
        except ValueError as err:
            parser.error(str(err))
    if args.viewer:
        serve(args)
        return
    parser.refuse_without(args, args.out is not None, "--out", ("overwrite",))  # the fresh default folder needs none
    if args.backend is not None:  # the gait tests run on the checkpoint's own backend
        parser.error("--backend sets the physics of --viewer only; leave it out, or add --viewer")
    if args.test == "robust" and (args.vx, args.vy) != (0.5, 0.0):
        parser.error("--vx/--vy set the standard test's command; the robust test's commands are its cases' (leave "
                     "--vx/--vy out, or pass --test standard)")
    if args.test == "robust" and args.video_envs != 4:
        parser.error("--video_envs sets the standard test's video; the robust test records none (leave --video_envs "
                     "out, or pass --test standard)")
    if args.device != "auto" and args.device.startswith("cuda") and not torch.cuda.is_available():
        parser.error(f"--device {args.device}: torch sees no CUDA GPU on this machine; pass --device cpu (or leave "
                     "--device out: the GPU when there is one, else the CPU)")
    out, made = None, False
    try:
        # before the folder is named: a device torch does not know, a test shorter than one step, an exported
        # .onnx/.json (sim2sim runs those) or a damaged file goes no further
        check_device("cpu" if args.device == "auto" else args.device)
        policy_steps(args.seconds, policy_dt())
        verified_checkpoint_file(args.checkpoint, sim2sim_options(args))
        check_plotting()  # knees.png / robust.png: said before the test, not as a traceback after its rollout
        out = eval_out_dir(args.checkpoint, args.out, args.overwrite)
        made = not out.exists()  # a folder the test makes and leaves empty goes on Ctrl-C; one given stays
        print(f"results go to {out}/", flush=True)
        if args.test == "robust":
            from tocabi_torchrl.evaluation.robust import evaluate_robust_run, robust_report_text

            # Measured: about 1 step/s at 512 robots on 2 cores.
            if resolve_device(args.device).type == "cpu" and args.num_envs is None:
                print(f"note: {TESTS['robust']:,} robots per case for {args.seconds:g} s take hours on a CPU; "
                      "--num_envs 4 takes about a minute (a smaller sample of the same test)", flush=True)
            report = evaluate_robust_run(args.checkpoint, num_envs=args.num_envs or TESTS["robust"],
                                         device=args.device, seconds=args.seconds, out_dir=out,
                                         replace=args.overwrite)  # without it eval_out_dir refused earlier results
            print(robust_report_text(report, out))
            return
        args.num_envs = args.num_envs or TESTS["standard"]
        summary = evaluate_run(args.checkpoint, num_envs=args.num_envs, device=args.device, seconds=args.seconds,
                               command=(args.vx, args.vy), video_envs=min(args.video_envs, args.num_envs),
                               out_dir=out, replace=args.overwrite)  # without it eval_out_dir refused earlier results
    except (ValueError, RuntimeError, ImportError) as err:  # a bad or diverged checkpoint, --out with results, short
        # --seconds, the device, no matplotlib
        sys.exit(f"error: {err}")
    except OSError as err:  # an --out that is a file, or cannot be created or written
        sys.exit(f"error: cannot write the evaluation to {err.filename or args.out}: {err.strerror or err}; pass "
                 f"--out a folder that can be created")
    except KeyboardInterrupt:  # 130 as for any Ctrl-C stop; an output folder with nothing in it goes too
        kept = remove_if_empty(out, made)
        print(f"\nstopped (Ctrl-C) during the gait test{f'; {out}/ holds what was written' if kept else ''}",
              file=sys.stderr)
        sys.exit(130)
    print(gait_report_text(summary, args.seconds, args.num_envs, out))


def serve(args: argparse.Namespace) -> None:
    """--viewer: the live page of the policy (tocabi_torchrl.viewer), until Ctrl-C."""
    from tocabi_torchrl.viewer import ViewerUnavailable
    from tocabi_torchrl.viewer.play import serve_policy

    # The live page tests nothing and writes nothing: these would be ignored without a word.
    exported = Path(args.checkpoint).suffix in (".onnx", ".json")
    ignored = [flag for flag, given in (("--test", args.test != "standard"), ("--out", args.out is not None),
                                        ("--overwrite", args.overwrite), ("--video_envs", args.video_envs != 4))
               if given]
    if ignored:
        sys.exit(f"error: {', '.join(ignored)}: the live viewer tests nothing and writes no files, so it takes none "
                 "of them; leave them out (or drop --viewer for the gait test)")
    if args.seconds != 8.0 and not exported:
        sys.exit("error: --seconds: a checkpoint's live viewer runs until Ctrl-C, so it takes none; leave it out (an "
                 "exported policy's viewer, --checkpoint X.onnx, runs for --seconds)")
    if exported:  # an exported policy: the torch-free runtime drives it
        serve_exported(args)
        return
    try:
        verified_checkpoint_file(args.checkpoint)
        serve_policy(args.checkpoint, num_envs=args.num_envs or VIEWER_ENVS, device=args.device,
                     host=args.viewer_host, port=args.viewer_port, command=(args.vx, args.vy), backend=args.backend)
    except ViewerUnavailable as err:
        sys.exit(f"error: {err}")
    except (ValueError, RuntimeError) as err:
        sys.exit(f"error: {err}")
    except KeyboardInterrupt:  # while loading or serving: 130, as every Ctrl-C stop, not a traceback or 0
        print("viewer stopped (Ctrl-C)", file=sys.stderr)
        sys.exit(130)


def serve_exported(args: argparse.Namespace) -> None:
    """--viewer of an exported policy (.onnx and its .json contract): recipes/sim2sim.py's driver, drawn live for
    --seconds in real time."""
    from tocabi_torchrl.viewer.exported import contract_of

    # The torch-free driver runs C MuJoCo on the CPU and tests nothing: these would be ignored without a word.
    ignored = [flag for flag, given in (("--backend", args.backend is not None), ("--device", args.device != "auto"))
               if given]
    if ignored:
        sys.exit(f"error: {', '.join(ignored)}: an exported policy's viewer runs the torch-free C MuJoCo driver "
                 "(recipes/sim2sim.py), which takes none of them; leave them out")
    try:
        contract = contract_of(args.checkpoint)
    except ValueError as err:
        sys.exit(f"error: {err}")
    sim2sim = _recipe("sim2sim")
    # The .onnx named runs, not the file the contract records (a renamed pair keeps the old name there).
    named = ["--onnx", args.checkpoint] if Path(args.checkpoint).suffix == ".onnx" else []
    sim2sim.main(["--contract", str(contract), *named, "--num_robots", str(args.num_envs or VIEWER_ENVS),
                  "--seconds", str(args.seconds), "--vx", str(args.vx), "--vy", str(args.vy), "--viewer",
                  "--viewer_host", args.viewer_host, "--viewer_port", str(args.viewer_port)])


def _recipe(name: str):
    """recipes/<name>.py as a module (the recipes folder is not a package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(f"_recipe_{name}", Path(__file__).with_name(f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


if __name__ == "__main__":
    main(sys.argv[1:])
