"""Train TOCABI to walk with PPO on TorchRL.

    python recipes/ppo_walk.py                      # default preset: 4096 envs on the GPU
    python recipes/ppo_walk.py --preset torque --env.num_envs 8192   # a preset, then options that change it
    python recipes/ppo_walk.py --preset reference   # the reference's hyper-parameters (8 envs, 120 M steps)
    python recipes/ppo_walk.py --env.num_envs 8192 --ppo.lr 3e-4 --max_minutes 20 --name walk8k
    python recipes/ppo_walk.py --transforms.reward_weights.body_vel 0.6 --ppo.actor_hidden 256 256
    python recipes/ppo_walk.py --resume runs/ppo_walk   # continue from runs/ppo_walk/checkpoints/latest.pt
    python recipes/ppo_walk.py --viewer             # and watch 16 training worlds live in a browser (docs/viewer.md)
    python recipes/ppo_walk.py --preset torque --help   # every option (a dotted path of tocabi_torchrl/config.py),
                                                        # with the torque preset's values as defaults
    torchrun --nproc_per_node 2 recipes/ppo_walk.py --name walk2gpu   # data-parallel, one process per GPU

Without CUDA and with --device auto (the default) it says so and runs the small ``cpu_smoke`` configuration (seconds
on a laptop, learns nothing useful); an explicit --device cuda or GPU-sized --preset fails instead, and so does a
torchrun launch (pass --device cpu for a CPU data-parallel run). Writes
runs/<name>/: config.json, metrics/ (torchrl's CSV logger: one file per metric), checkpoints/, and (with
--eval_at_end) eval/ with a summary JSON, the knee-trajectory plot and a video. An existing run folder is never
overwritten: continue it with --resume, or give the new run another --name. --resume restores the saved run's
options; only budget, logging, checkpoint, eval and device options and how the same computation runs (CUDA graphs,
gradient sync, stored env signals, CPU threads, reset pass) may be given again with other values (--help lists them).
Ctrl-C or SIGTERM stops the run after the iteration in progress, saves a checkpoint of it, skips the final evaluation,
says how to --resume it and exits with status 130 (Ctrl-C) or 143 (SIGTERM); a second one stops at once. Ctrl-C
before training starts ends the recipe at once (status 130), no run written.
"""

from __future__ import annotations

import errno
import signal
import sys
import threading


#: What :func:`_stopped_before_training` says of the run folder: a new run's is not written before training, but a
#: resume's open_run tidies it (cuts the metrics back to the checkpoint), so main() sets the resume's line.
NEW_RUN_LEFT_BEHIND = "no run was written"
_LEFT_BEHIND = {"note": NEW_RUN_LEFT_BEHIND}
RESUME_LEFT_BEHIND = "no iteration ran; the same command resumes the run"


def _stopped_before_training(signum, frame) -> None:
    """Ctrl-C before training starts (imports, checks, the run folder's claim): no iteration has run, so the process
    ends at once with a line instead of a traceback. A claim taken goes with it (at exit)."""
    print(f"\nstopped (Ctrl-C) before training started; {_LEFT_BEHIND['note']}", file=sys.stderr, flush=True)
    sys.exit(130)  # 128 + SIGINT, as every Ctrl-C stop of a run


if __name__ == "__main__":  # first: the imports below take seconds (torch, mujoco), and a Ctrl-C then is a stop too
    signal.signal(signal.SIGINT, _stopped_before_training)

from tocabi_torchrl.render_gl import choose_gl_backend_or_exit  # noqa: E402

choose_gl_backend_or_exit()  # before mujoco is imported: headless video of the final evaluation

#: What --help says above the options: their defaults are the --preset's, which a machine without CUDA replaces.
HELP = (f"{__doc__.split(chr(10) * 2)[0]} The defaults below are the --preset's (default: 'default'). Without CUDA "
        "and without --preset or --device, the run uses the small 'cpu_smoke' preset instead (--preset cpu_smoke "
        "--help lists its values).")

if __name__ == "__main__":
    # --help, a misspelt option or a value of the wrong type answers before the trainer and the evaluation load.
    # The command line is tyro's, from the run config tree, whose modules import neither torch, torchrl nor
    # mujoco(-warp): it answers in a fraction of a second (tests/test_cli.py checks what it loads).
    from tocabi_torchrl.rl.config import check_command_line
    from tocabi_torchrl.viewer.config import expand_viewer_flag

    check_command_line(expand_viewer_flag(sys.argv[1:]), "ppo_walk.py", HELP)

import torch  # noqa: E402

from tocabi_torchrl.envs.model_based import check_settings  # noqa: E402
from tocabi_torchrl.motion import ReferenceMotion  # noqa: E402
from tocabi_torchrl.motion.io import MotionFormatError  # noqa: E402
from tocabi_torchrl.rl.checkpoint import CheckpointError, checkpoint_file  # noqa: E402
from tocabi_torchrl.rl.distributed import ending, from_environment, shutdown  # noqa: E402
from tocabi_torchrl.evaluation.gait_test import eval_out_dir, evaluate_run, gait_report_text  # noqa: E402
from tocabi_torchrl.evaluation.output import remove_if_empty  # noqa: E402
from tocabi_torchrl.evaluation.plots import check_plotting  # noqa: E402
from tocabi_torchrl.evaluation.record import policy_steps  # noqa: E402
from tocabi_torchrl.rl.config import repeated_options  # noqa: E402
from tocabi_torchrl.rl.interrupt import signal_exit_status  # noqa: E402
from tocabi_torchrl.rl.launch import banner, cpu_size_note, launch_config  # noqa: E402
from tocabi_torchrl.rl.logging import require_loggers  # noqa: E402
from tocabi_torchrl.rl.run_dir import holds_checkpoint, open_run  # noqa: E402
from tocabi_torchrl.rl.trainer import finished_result, raised_before_training, resolve_device, train  # noqa: E402
from tocabi_torchrl.robot import RobotAssetError, load_model  # noqa: E402
from tocabi_torchrl.viewer.config import expand_viewer_flag  # noqa: E402
from tocabi_torchrl.viewer.extra import require_viser  # noqa: E402
from tocabi_torchrl.viewer.server import check_address  # noqa: E402


def stopped(result) -> int:
    """Say that the run stopped on a signal, where its checkpoint is and how to continue; its exit status."""
    print(f"{result.interrupted}: stopped after iteration {result.iterations} ({result.env_steps:,} env steps); "
          f"checkpoint saved in {result.run_dir / 'checkpoints'}, final evaluation skipped. Continue the run with "
          f"--resume {result.run_dir}", file=sys.stderr, flush=True)
    return signal_exit_status(result.interrupted)


def stopped_at_once(run_dir) -> int:
    """Say that a second signal stopped the run without a save, and what it can be continued from; its exit status."""
    advice = (f"continue it from its last checkpoint with --resume {run_dir}" if holds_checkpoint(run_dir) else
              f"it saved no checkpoint: start it again under another --name, or remove {run_dir} to reuse the name")
    print(f"stopped at once (second signal), without saving the iteration in progress; {advice}", file=sys.stderr,
          flush=True)
    return signal_exit_status("SIGINT")


def done_text(result) -> str:
    """This call's env steps, seconds and rate, the run's total after a resume, and the run folder."""
    total = f" ({result.env_steps:,} in the run)" if result.start_env_steps else ""
    return (f"{result.env_steps - result.start_env_steps:,} env steps in {result.wall_seconds:.0f} s "
            f"({result.env_steps_per_second:,.0f} env-steps/s){total}; run folder {result.run_dir}")


def ranks_done_text(result, cfg, world_size: int) -> str:
    """The closing line of a data-parallel run: :func:`done_text`, and, when ``cfg.eval_at_end`` asks for the gait
    test, that torchrun leaves it out (it is one process's, docs/training.md) and the command that runs it."""
    test = ""
    if cfg.eval_at_end:  # the test the run asked for: its robots and seconds, which play.py's defaults are not
        size = f" --num_envs {cfg.eval_envs} --seconds {cfg.eval_seconds:g}"
        robust = " --test robust" if cfg.eval_test == "robust" else ""
        test = (f"; the gait test is not run under torchrun, run it with: python recipes/play.py --checkpoint "
                f"{result.run_dir}{size}{robust}")
    return f"done on {world_size} ranks: {done_text(result)}{test}"


def training_stops_on_ctrl_c() -> None:
    """From here on Ctrl-C is training's (it saves a checkpoint, rl/interrupt.py) and then the gait test's
    (``KeyboardInterrupt``): the early stop of :func:`_stopped_before_training` no longer applies."""
    if signal.getsignal(signal.SIGINT) is _stopped_before_training:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def main(argv: list[str] | None = None) -> None:
    # Everything that can stop the run before it starts is checked here and reported as one line (exit status 1):
    # bad values, a request this machine cannot honour, an existing run folder, an unreadable or changed --resume.
    try:
        dist_info = from_environment()  # torchrun's layout; one rank without it
        # --viewer is the shorthand of --viewer.enabled true (the live page of a few training worlds)
        argv = expand_viewer_flag(sys.argv[1:] if argv is None else argv)
        cfg, given, note = launch_config(argv, torch.cuda.is_available(), description=__doc__.split("\n\n")[0],
                                         data_parallel=dist_info.enabled, prog="ppo_walk.py")
        _LEFT_BEHIND["note"] = RESUME_LEFT_BEHIND if cfg.resume else NEW_RUN_LEFT_BEHIND  # this call's, not the last
        for line in repeated_options(argv) if dist_info.is_main else ():  # said once, not by every rank
            print(f"warning: {line}", file=sys.stderr, flush=True)
        if cfg.viewer.enabled:  # said now, not after the env is built
            require_viser()
            check_address(cfg.viewer.host, cfg.viewer.port, "viewer.port")
        unused = sorted(p for p in given if p.startswith("viewer.") and p != "viewer.enabled")
        if unused and not cfg.viewer.enabled:  # as play.py's and sim2sim.py's --viewer_port without --viewer
            raise ValueError(f"{', '.join('--' + p for p in unused)} set the live viewer, which is off: add --viewer, "
                             "or leave them out")
        model_based = cfg.env.control.mode == "model_based"
        if cfg.eval_at_end or model_based:
            control_dt = load_model(cfg.env.task.model_path).opt.timestep * cfg.env.sim.substeps
        if cfg.eval_at_end:  # the gait test's length, checked now rather than after the training it follows; the
            # config's own checks cannot: one step's length is the model file's timestep × the substeps
            policy_steps(cfg.eval_seconds, control_dt, option="--eval_seconds")
        if cfg.eval_at_end and not dist_info.enabled:  # its plots' library: said now, not after hours of training
            check_plotting("; or train without the test at the end: --eval_at_end false")
        if model_based:  # its gains against the control period, its window against the motion: before the banner
            motion = cfg.env.task.motion
            check_settings(cfg.env.control, ReferenceMotion.default() if motion is None
                           else ReferenceMotion.from_file(motion), control_dt)
        device = resolve_device(cfg.device)
        require_loggers(cfg.loggers)
    except (ValueError, RuntimeError, ImportError) as err:
        sys.exit(f"error: {err}")
    if dist_info.enabled:
        # Data-parallel: train() joins the process group, lets rank 0 alone check and write the run folder, and
        # makes every rank stop if it cannot start.
        expected = (ValueError, RuntimeError, ImportError)
        training_stops_on_ctrl_c()
        try:
            # Any failure ends every rank (an NCCL rank left waiting would never time out); on NCCL the process
            # ends inside ending(), after the last output.
            status = 0
            with ending(dist_info, expected):
                result = train(cfg, dist_info=dist_info)
                if result.interrupted is not None:
                    status = stopped(result) if dist_info.is_main else signal_exit_status(result.interrupted)
                    # NCCL: the rank ends here, with this status; gloo: the group is gone and ending() leaves it so.
                    shutdown(dist_info, code=status)
                elif dist_info.is_main:
                    print(ranks_done_text(result, cfg, dist_info.world_size))
        except expected:
            sys.exit(1)  # ending() has said why
        if status:
            sys.exit(status)  # outside ending(), which would report the SystemExit as a failure
        return
    try:
        run = open_run(cfg)
    except (ValueError, RuntimeError, ImportError) as err:
        sys.exit(f"error: {err}")
    # In env steps, as train() counts: a run saved by K data-parallel ranks counts K rollouts per iteration.
    if run.start_env_steps // cfg.frames_per_batch >= cfg.iterations:
        finished_result(run, cfg)  # says so; no training, no summary, no evaluation
        return
    if note:
        print(note, flush=True)
    print(banner(cfg, given, device), flush=True)
    if slow := cpu_size_note(cfg, device):  # asked for, so it runs; said, so that a still bar is not read as a hang
        print(slow, flush=True)
    training_stops_on_ctrl_c()
    try:
        result = train(cfg, run=run)
    except (MotionFormatError, RobotAssetError, CheckpointError) as err:  # a bad motion, model or resumed file
        sys.exit(f"error: {err}")
    except ValueError as err:
        if not raised_before_training(err):
            raise  # a failure while training is a bug to see whole, traceback included
        # A value the config's checks let through but the env or the networks refuse (a new run's folder is not written
        # yet).
        sys.exit(f"error: {err} (found while the run was being set up, before its first iteration)")
    except KeyboardInterrupt:
        sys.exit(stopped_at_once(run.path))
    except OSError as err:
        if err.errno not in WRITE_ERRNOS:
            raise
        # The disk filled or the folder became read-only mid-run: every file is written atomically, so the last
        # complete checkpoint stands.
        advice = (f"then continue from its last checkpoint with --resume {run.path}" if holds_checkpoint(run.path)
                  else f"it saved no checkpoint: start it again, under another --name or after removing {run.path}")
        sys.exit(f"error: the run could not write its files ({err}); free space or make {run.path} writable, "
                 f"{advice}")
    if result.interrupted is not None:
        sys.exit(stopped(result))
    print(f"done: {done_text(result)}")
    checkpoint = checkpoint_file(result.run_dir)
    # On a CPU the play recipe's default test (256 robots for 8 s) takes minutes: suggest this run's test size.
    small = ""
    if device.type == "cpu":
        small = f" --num_envs {cfg.eval_envs} --seconds {cfg.eval_seconds:g}" if cfg.eval_envs else ""
        small += " --test robust" if cfg.eval_test == "robust" else ""
    where = (f"checkpoint: {checkpoint}\nwatch or re-test it: python recipes/play.py --checkpoint "
             f"{result.run_dir}{small}")
    out, made = None, False
    main_thread = threading.current_thread() is threading.main_thread()  # where Python delivers signals
    previous = signal.signal(signal.SIGTERM, _terminate) if main_thread else None  # as Ctrl-C: said, not silent
    try:
        if cfg.eval_at_end:
            out = eval_out_dir(result.run_dir)
            made = not out.exists()  # a folder the test makes and leaves empty goes if it is stopped
        if cfg.eval_at_end and cfg.eval_test == "robust":  # the robust gait test (docs/evaluation.md) instead
            from tocabi_torchrl.evaluation.robust import evaluate_robust_run, robust_report_text

            report = evaluate_robust_run(result.run_dir, num_envs=cfg.eval_envs, device=cfg.device,
                                         seconds=cfg.eval_seconds, out_dir=out)
            print(robust_report_text(report, out))
        elif cfg.eval_at_end:
            summary = evaluate_run(result.run_dir, num_envs=cfg.eval_envs, device=cfg.device,
                                   seconds=cfg.eval_seconds, out_dir=out)
            print(gait_report_text(summary, cfg.eval_seconds, cfg.eval_envs, out))
    except (KeyboardInterrupt, _Terminated) as stop:  # training is done and saved: only the test stopped
        name = "SIGTERM" if isinstance(stop, _Terminated) else "SIGINT"
        remove_if_empty(out, made)
        print(f"\nstopped ({'SIGTERM' if name == 'SIGTERM' else 'Ctrl-C'}) during the gait test; training had "
              f"finished and is saved.\n{where}", file=sys.stderr)
        sys.exit(signal_exit_status(name))
    except OSError as err:
        if err.errno not in WRITE_ERRNOS:
            raise
        remove_if_empty(out, made)
        print(f"error: the gait test could not write its results ({err}); training had finished and is saved. "
              f"Free space or fix the folder's permissions and re-test it with play.py.\n{where}", file=sys.stderr)
        sys.exit(1)
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)
    print(where)


#: Errors of writing files (a full disk or quota, a read-only or forbidden folder, an I/O failure), which the run
#: reports in one line with what was saved; other OSErrors are bugs to see whole.
WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EIO})


class _Terminated(Exception):
    """SIGTERM during the gait test at the end (the signal handlers of training are gone by then)."""


def _terminate(signum, frame) -> None:
    raise _Terminated()


if __name__ == "__main__":
    main(sys.argv[1:])
