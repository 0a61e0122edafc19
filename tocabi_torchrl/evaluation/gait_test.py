"""Evaluation of a walking policy: TocabiLab's gait experiment (command (0.5, 0) m/s for 8 s, deterministic policy).

Writes ``summary.json`` (survival, forward distance, lateral drift, speed tracking error, knee RMS against the
reference motion), ``knees.png`` (left/right knee over 6 s against the reference, TocabiLab figs 4.7-4.8) and a
video of a few robots (``walk.mp4``, or ``walk.gif`` without an mp4 writer) rendered offscreen by MuJoCo. Both the
rollout and the rendering show a progress bar (rendering takes minutes on a CPU). This module runs the rollout and
computes the metrics (:class:`.record.GaitMetrics`, shared with the experiments' recorded rollouts); the figure
is :mod:`.plots`'s and the video :mod:`.video`'s.

``summary.json`` is strict JSON, written atomically: a metric that has no value (every robot fell in its first step:
no knee RMS, no speed error; no survivor: no survivors' distance) is ``null``. The summary :func:`evaluate_policy`
returns keeps those as NaN (``float``), for callers that format or compare the numbers.
"""

from __future__ import annotations

import contextlib
import ctypes.util
import json
import os
from pathlib import Path

import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp
from tqdm.auto import tqdm

from .. import robot
from ..atomic import atomic_write_text, check_writable, claim_path
from ..config import RunConfig
from ..render_gl import NO_GL_FIX
from ..transforms.normalize import freeze_running_statistics
from ..rl.checkpoint import checkpoint_file, read_checkpoint, run_folder_of
from ..rl.trainer import build_env, resolve_device
from .output import OutputExistsError, check_results_folder, json_safe, rounded_against
from .plots import plot_knees
from .record import (KNEES, GaitMetrics, first_action, fixed_command, load_policy, policy_steps,
                     require_trained_statistics)
from .video import render_video

__all__ = ["check_env_command", "evaluate_policy", "evaluate_run", "default_eval_dir", "fresh_eval_dir",
           "eval_out_dir", "policy_dt", "summary_json", "RESULT_FILES", "GAIT_CRITERIA", "ROBUST_CRITERIA",
           "gait_passes", "tested_on"]

#: Pass thresholds of the gait test at (0.5, 0) m/s (issue 19): a policy walks when its summary meets all of them
#: (and, in the time-to-walk benchmark, keeps ``survival`` at (0.2, 0) and (0.7, 0.1) too).
GAIT_CRITERIA = {"survival": 0.95, "forward_distance_m": 2.6, "lateral_drift_m": 0.3, "knee_rms_rad": 0.15}

#: Pass thresholds of the robust gait test (:mod:`.robust`, docs/evaluation.md), per case: metric path in the
#: case's report entry (``"forward_distance_m.mean"``: the mean over its robots) -> (">=" or "<=", limit). A policy
#: passes the robust test when every case meets all of its thresholds (``robust.robust_passes``).
ROBUST_CRITERIA = {
    "nominal": {"survival": (">=", 0.99), "forward_distance_m.mean": (">=", 2.6), "lateral_drift_m.p95": ("<=", 0.3)},
    "commands": {"survival": (">=", 0.99), "tracking_error_mps.mean": ("<=", 0.12)},
    "robust_0.5": {"survival": (">=", 0.97)},
    "robust_1.0": {"survival": (">=", 0.85)},
}


def gait_passes(summary: dict) -> bool:
    """Whether a gait-test summary (:func:`evaluate_policy`'s, or its ``summary.json`` read back) meets every
    :data:`GAIT_CRITERIA` threshold; a metric without a value (NaN, or ``null`` in the file) fails."""
    c = GAIT_CRITERIA
    values = {key: summary[key] for key in c}
    if any(v is None for v in values.values()):
        return False
    return (values["survival"] >= c["survival"] and values["forward_distance_m"] >= c["forward_distance_m"]
            and values["lateral_drift_m"] <= c["lateral_drift_m"] and values["knee_rms_rad"] <= c["knee_rms_rad"])


def summary_json(summary: dict) -> str:
    """``summary`` as strict JSON: NaN and inf as ``null`` (bare ``NaN`` tokens are not JSON)."""
    return json.dumps(json_safe(summary), indent=2, allow_nan=False)


def tested_on(device: str | torch.device) -> str:
    """Where a gait test on ``device`` runs, for its record: the GPU's name for "cuda", "cuda:1", ("auto" on a GPU
    machine), else "cpu". C MuJoCo and mujoco-warp agree closely, not step for step over 8 s, so a drift near its
    limit can differ."""
    dev = resolve_device(device) if device == "auto" else torch.device(device)
    return torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu"


def check_video_envs(video_envs) -> None:
    """``ValueError`` unless ``video_envs`` (robots in the gait test's video) is an int >= 0."""
    if isinstance(video_envs, bool) or not isinstance(video_envs, int) or video_envs < 0:
        raise ValueError(f"video_envs must be an int >= 0 (robots in the video; 0 for none), got {video_envs!r}")


def check_env_command(held: torch.Tensor, command: tuple[float, float]) -> None:
    """``ValueError`` unless every robot holds ``command`` = (vx, vy) [m/s]: ``held`` is the env's (N, 2)
    ``"command"`` [m/s] after its reset. The summary states ``command`` and measures the speed error against it, so
    an env built at another command (or with the training's command ranges) would be reported as a test it was
    not."""
    want = held.new_tensor([float(command[0]), float(command[1])])
    off = ~((held - want).abs() <= 1e-5).all(-1)  # a NaN command is off too
    if bool(off.any()):
        first = int(off.nonzero()[0, 0])
        vx, vy = (float(v) for v in held[first])
        raise ValueError(f"command={tuple(command)} m/s, but the env commands ({vx:g}, {vy:g}) m/s to robot {first} "
                         f"at its reset ({int(off.sum())} of {held.shape[0]} robots differ): the summary would report "
                         "a test at a command that did not run. Build the env at this command (load_policy(..., "
                         "command=command), or build_env(cfg, device, command=fixed_command(command))), or leave "
                         "env out")


def evaluate_policy(
    actor,
    cfg: RunConfig,
    out_dir: str | os.PathLike,
    num_envs: int = 256,
    device: str | torch.device = "auto",
    seconds: float = 8.0,
    command: tuple[float, float] = (0.5, 0.0),
    video_envs: int = 4,
    env=None,
    progress: bool = True,
    source: str | os.PathLike | None = None,
) -> dict:
    """Roll the deterministic policy out for ``seconds`` at a fixed command and write the summary, plot and video
    to ``out_dir`` (created if needed; files of the same name there are replaced: the caller chooses the folder,
    e.g. with :func:`eval_out_dir`). It tests ``env``, or the env ``cfg`` builds, as it is: the standard test's
    nominal robot is the env of ``load_policy(..., nominal=True)``, which :func:`evaluate_run` uses (or, for a
    policy without running normalisation, one built from ``nominal_config(cfg)``); a training config's kicks and
    randomisation stay on otherwise. An env whose running normaliser never saw a step (built from the config, not
    loaded with the checkpoint's statistics) raises ``ValueError`` (:func:`.record.require_trained_statistics`), and
    so does one whose robots are not commanded ``command`` [m/s] (:func:`check_env_command`).
    ``device``: "auto" (the GPU if torch sees one, else the CPU), "cuda", "cuda:K" or "cpu". ``seconds`` must cover
    at least one policy step; ``progress`` shows bars for the rollout and the rendering; ``source``, the checkpoint
    tested, is recorded in the summary as ``checkpoint``.
    Returns the summary, NaN where a metric has no value (``null`` in the file)."""
    device = resolve_device(device)  # "auto" too; a GPU asked for on a CPU-only machine says to pass "cpu"
    check_video_envs(video_envs)
    if env is None:
        env = build_env(cfg, device, num_envs=num_envs, command=fixed_command(command))
    require_trained_statistics(env)
    freeze_running_statistics(env)  # a test of the policy as trained, not of statistics drifting with its rollout
    base = env.base_env
    steps = policy_steps(seconds, base.dt)
    out = Path(out_dir)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.reset()
        check_env_command(td["command"], command)
        out.mkdir(parents=True, exist_ok=True)
        metrics = GaitMetrics(td["base_pos"], command, base.dt)
        trace_q, trace_ref, frames_qpos = [], [], []
        video_every = max(1, int(round(1.0 / (30.0 * base.dt))))
        for k in tqdm(range(steps), desc="gait test", unit="step", disable=not progress, leave=False):
            td = env.step(actor(td) if k else first_action(actor, td))
            nxt = td["next"]
            alive = metrics.update(nxt)
            if k * base.dt < 6.0:
                # After a fall the robot keeps lying there: blank its trace instead of plotting a fallen knee.
                trace_q.append(torch.where(alive[0], nxt["joint_pos"][0, KNEES], torch.nan))
                trace_ref.append(nxt["ref_joint_pos"][0, KNEES])
            if video_envs and k % video_every == 0:
                frames_qpos.append(base.sim.qpos[:video_envs].clone())
            # Fallen robots keep lying (no reset): `alive` already excludes them from every metric.
            td = step_mdp(td)
            # Once every robot has fallen no metric can change: stop (a host read every 50 steps only).
            if video_envs < 1 and k % 50 == 49 and not bool(alive.any()):
                break
    summary = metrics.summary(seconds)
    if source is not None:  # which policy these numbers are of, once several eval_N/ folders sit side by side
        summary["checkpoint"] = str(source)
    atomic_write_text(out / "summary.json", summary_json(summary))
    plot_knees(torch.stack(trace_q).cpu().numpy(), torch.stack(trace_ref).cpu().numpy(), base.dt, out / "knees.png",
                command)
    if video_envs < 1:
        summary["video"] = "not requested (video_envs=0)"
    else:
        try:
            mocap = base.sim.world_mocap_pos  # each world's obstacle positions, if the scene has any
            # One frame every `video_every` steps plays at the simulated speed: 31.25 fps at 4 ms steps, not 30.
            fps = 1.0 / (video_every * base.dt)
            summary["video"] = str(render_video(base.sim.mj_model, torch.stack(frames_qpos).cpu().numpy(), fps, out,
                                                 progress=progress,
                                                 mocap_pos=None if mocap is None else mocap[:video_envs]))
        except Exception as err:  # rendering needs an OpenGL backend (MUJOCO_GL=egl on a headless machine)
            summary["video"] = f"not rendered: {type(err).__name__}: {err}"
            if isinstance(err, ModuleNotFoundError) and err.name == "imageio":  # not a GL problem: the writer
                fix = '; install the video writer: pip install -e ".[viz]" (imageio with ffmpeg)'
            elif isinstance(err, OSError):  # the disk or the folder, not the renderer
                fix = f"; check that {out} has free space and can be written"
                for partial in (out / "walk.mp4", out / "walk.gif", out / "walk_frame.png"):  # half-written
                    with contextlib.suppress(OSError):
                        partial.unlink()
            elif not os.environ.get("MUJOCO_GL") and ctypes.util.find_library("EGL"):
                # EGL is here, but MuJoCo picked its backend when it was imported, before anything set it.
                fix = ("; on a headless machine set MUJOCO_GL=egl before Python imports mujoco (or call "
                       "tocabi_torchrl.render_gl.choose_gl_backend() first, as the recipes do)")
            else:
                fix = "" if NO_GL_FIX in str(err) else f"; on a headless machine: {NO_GL_FIX}"  # said once
            print(f"video skipped ({summary['video']}){fix}")
    atomic_write_text(out / "summary.json", summary_json(summary))
    return summary


#: The files a standard gait test writes into its folder (:func:`evaluate_policy`, :func:`.video.render_video`).
RESULT_FILES = ("summary.json", "knees.png", "walk.mp4", "walk.gif", "walk_frame.png")


def evaluate_run(run: str | os.PathLike, num_envs: int = 256, device: str = "auto",
                 out_dir: str | os.PathLike | None = None, replace: bool = False, **kwargs) -> dict:
    """Load ``run`` (a run folder or checkpoint file) and evaluate it; results go to ``out_dir`` as given, or by
    default to :func:`fresh_eval_dir` (``<run>/eval/``, or ``eval_2/``, ... when earlier results are there). An
    ``out_dir`` that already holds a test's results (:data:`RESULT_FILES`) raises
    :class:`~.output.OutputExistsError` unless ``replace`` (then files of the same name are replaced, others stay).
    Raises ``CheckpointError`` for a bad file and ``ValueError`` for ``seconds`` below one policy step,
    ``video_envs`` below 0 or an ``out_dir`` that is a file, before building anything."""
    check_results_folder(out_dir, RESULT_FILES, replace)
    if "video_envs" in kwargs:
        check_video_envs(kwargs["video_envs"])
    ckpt = checkpoint_file(run)
    state = read_checkpoint(ckpt)
    policy_steps(kwargs.get("seconds", 8.0), policy_dt())
    policy = load_policy(ckpt, num_envs, resolve_device(device), command=kwargs.get("command", (0.5, 0.0)),
                         state=state, nominal=True)
    if out_dir is None:
        out_dir = fresh_eval_dir(ckpt)
    return evaluate_policy(policy.actor, policy.cfg, out_dir, num_envs=num_envs, device=policy.env.device,
                           env=policy.env, source=ckpt, **kwargs)


def default_eval_dir(ckpt: Path) -> Path:
    """``<run folder>/eval/`` for a run's checkpoint, ``eval/`` beside any other file, and
    ``runs/eval/<checkpoint stem>/`` for a policy shipped in the package's assets (never into the source tree)."""
    ckpt = Path(ckpt)
    if ckpt.resolve().is_relative_to(robot.asset_path().resolve()):
        return Path(RunConfig().run_dir) / "eval" / ckpt.stem
    return run_folder_of(ckpt) / "eval"


def fresh_eval_dir(ckpt: Path) -> Path:
    """:func:`default_eval_dir`, or when that already holds files (an earlier evaluation) or another running
    evaluation has claimed it (:func:`~tocabi_torchrl.atomic.claim_path`), the first of ``eval_2``, ``eval_3``, ...
    beside it that is free: a repeated evaluation never replaces earlier results, and two at once never share a
    folder. The folder returned is claimed for this process until it ends."""
    base = default_eval_dir(ckpt)
    candidate, n = base, 1
    while True:
        free = not candidate.exists() or (candidate.is_dir() and not any(candidate.iterdir()))
        if free and claim_path(candidate)[0] is not None:
            return candidate
        n += 1
        candidate = base.with_name(f"{base.name}_{n}")


def eval_out_dir(checkpoint: str | os.PathLike, out_dir: str | os.PathLike | None = None,
                 overwrite: bool = False) -> Path:
    """The folder an evaluation of ``checkpoint`` writes to: ``out_dir``, refused
    (:class:`~.output.OutputExistsError`) when it already holds files unless ``overwrite`` (then files of the same
    name are replaced, others stay); without ``out_dir``, :func:`fresh_eval_dir` (which claims it). Creates no
    results folder; raises ``OSError`` for a folder that cannot be written (checked with a probe file before the test
    runs, not at its first write, minutes later) and ``CheckpointError`` for a missing checkpoint."""
    out = fresh_eval_dir(checkpoint_file(checkpoint)) if out_dir is None else Path(out_dir)
    if out_dir is not None and out.is_dir() and any(out.iterdir()) and not overwrite:
        held = sorted(p.name for p in out.iterdir())
        shown = ", ".join(held[:3]) + (f" and {len(held) - 3} more" if len(held) > 3 else "")
        raise OutputExistsError(f"{out} already holds results ({shown}); nothing there is overwritten. Choose another "
                                "--out, leave --out out to write to a fresh folder (eval/, eval_2/, ...), or pass "
                                "--overwrite to replace the files of the same name (the others stay)")
    check_writable(out)
    return out


def policy_dt() -> float:
    """Seconds per policy step of the walking task (physics timestep × substeps)."""
    from ..envs import TocabiWalkConfig

    return float(robot.load_model().opt.timestep) * TocabiWalkConfig().sim.substeps


#: Kept for the callers of before :mod:`.record` (tests, benchmarks).
_fixed_command = fixed_command
_policy_steps = policy_steps


#: Length [s] of the standard gait test, for which GAIT_CRITERIA's distance is set (the run config's default).
STANDARD_SECONDS = RunConfig.eval_seconds
#: The standard gait test's velocity command [m/s] (vx, vy), for which GAIT_CRITERIA's distance and drift are set.
STANDARD_COMMAND = (0.5, 0.0)


def length_note(seconds: float) -> str:
    """What a verdict's headline adds for a test of another length than the standard one: the distance threshold
    (and the robust test's kick window) assume the full length."""
    return "" if seconds == STANDARD_SECONDS else f" (the thresholds are set for the {STANDARD_SECONDS:g} s test)"


#: The gait test's metrics as people read them: (key, label, unit, decimals, "min"/"max" threshold).
GAIT_ROWS = (
    ("survival", "survival", "%", 1, "min"),
    ("forward_distance_m", "forward distance", "m", 2, "min"),
    ("lateral_drift_m", "lateral drift", "m", 2, "max"),
    ("knee_rms_rad", "knee RMS vs reference", "rad", 3, "max"),
)


def _shown(value, unit: str, decimals: int) -> str:
    """A metric for people: rounded, with its unit; a missing value (NaN or None) says so."""
    if value is None or value != value:
        return "no value"
    return f"{100 * value:.{decimals}f} %" if unit == "%" else f"{value:.{decimals}f} {unit}"


def gait_report_text(summary: dict, seconds: float, robots: int, out) -> str:
    """The gait test's verdict (walks / does not walk yet), each metric against its pass threshold, and the files
    written; the full-precision values stay in ``out/summary.json``. A command other than the standard (0.5, 0) m/s
    is said beside the verdict: the distance and drift thresholds assume it."""
    verdict = "walks" if gait_passes(summary) else "does not walk yet"
    command = tuple(summary.get("command_mps", STANDARD_COMMAND))
    note = length_note(seconds) + ("" if command == STANDARD_COMMAND else
                                   f" (the thresholds are set for the {STANDARD_COMMAND} m/s command, not {command})")
    lines = [f"gait test ({seconds:g} s, {robots} robots): {verdict}{note}"]
    for key, label, unit, decimals, kind in GAIT_ROWS:
        value, limit = summary.get(key), GAIT_CRITERIA[key]
        ok = value is not None and value == value and (value >= limit if kind == "min" else value <= limit)
        need = f"{'>=' if kind == 'min' else '<='} {_shown(limit, unit, decimals)}"
        shown = _shown(value, unit, decimals)
        if ok is False and value is not None and value == value:  # never a rounding that reads as a pass
            scale = 100.0 if unit == "%" else 1.0
            shown = f"{rounded_against(scale * value, scale * limit, ok, kind, decimals)} {unit}"
        lines.append(f"  {label:<22} {shown:>10}   needs {need:<13} {'pass' if ok else 'FAIL'}")
    files = [out / "summary.json", out / "knees.png"]
    video = str(summary.get("video", ""))
    lines.append("results: " + ", ".join(str(f) for f in files if f.exists())
                 + (f", {video}" if video.endswith(".mp4") else f" (video {video})" if video else ""))
    return "\n".join(lines)
