"""The robust gait test: does a policy walk from many different starts, under changing commands, with the TOCABI
lab's model uncertainty and under pushes? (docs/evaluation.md)

The standard gait test (:func:`.gait_test.evaluate_policy`: 256 robots at (0.5, 0) m/s for 8 s) starts every robot
at rest on one of two rows of the reference motion, so its deterministic rollouts are two trajectories and its
survival and drift are two samples. This test makes the starts diverse (joint velocities ~ N(0, 0.5 rad/s), pelvis
linear velocity ~ N(0, 0.1 m/s) per axis, drawn per robot at the reset) and runs four cases of
:data:`CASES` robots each (1,024 by default), deterministic policy, 8 s:

* ``nominal``: command (0.5, 0) m/s;
* ``commands``: the training command range (``CommandConfig()``'s) re-drawn every 2 s (500 policy steps);
* ``robust_0.5`` and ``robust_1.0``: command (0.5, 0) m/s, the ``tocabi_lab`` randomisation (dynamics, actuators,
  sensor noise; :func:`robust_case_config`; a PD-mode policy's servos get no actuator model) drawn from
  :data:`EVAL_SEED`, and three horizontal velocity kicks of 0.5 or 1.0 m/s at random times in 2-7 s, each within
  one 4 ms policy step: every body of the robot gets the same velocity change (``PushConfig(kind="velocity")``).

Per case it reports distributions over the robots: survival fraction, forward distance (mean, p5, p50, p95),
lateral drift (mean, p50, p95 of |y|), speed tracking error (mean, p95), instantaneous speed error (mean, p95) and
knee RMS against the reference (mean, p95), and a verdict against :data:`.gait_test.ROBUST_CRITERIA`. Both speed
errors are of the pelvis's horizontal velocity in the heading (pelvis-yaw) frame against the command. The tracking
error, which the verdict reads, is of the velocity averaged over one gait cycle of the reference motion (450 policy
steps; :class:`CycleMeanTracking`): a walking pelvis sways sideways with each cycle and surges with each step, by
about 0.1 m/s (std) at (0.5, 0) m/s, which the instantaneous error (reported, not checked) includes. The policy
passes the test when every case passes. :func:`evaluate_robust` writes ``robust.json`` (strict JSON, ``null`` for a
value that does not exist) and ``robust.png`` (survival per case, distance, drift and speed error CDFs), both
atomically.

Every random draw (start velocities, commands, randomisation, pushes) is keyed on :data:`EVAL_SEED`, the robot and
its episode, so the same policy gets the same numbers from the same robot count on the same device.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp
from tqdm.auto import tqdm

from ..atomic import atomic_write_text
from ..config import RunConfig
from ..envs.cycle_velocity import gait_cycle_steps, heading_velocity
from ..rl.trainer import resolve_device  # gait_test, imported below, imports the trainer already
from ..rotations import quat_rotate_inverse, quat_to_rpy
from ..transforms.normalize import freeze_running_statistics
from ..value_rules import NON_NEGATIVE, PUSH_KINDS, Range, check_seed
from .env_reuse import build_sections, remember_built_state, restore_built_state
from .gait_test import ROBUST_CRITERIA, fresh_eval_dir, length_note, summary_json, tested_on
from .record import (GaitMetrics, first_action, fixed_command, nominal_config, policy_steps,
                     require_trained_statistics)
from .output import check_results_folder, rounded_against

__all__ = ["CASES", "EVAL_SEED", "ROBUST_FILES", "ROBUST_JSON", "ROBUST_PNG", "CycleMeanTracking", "RobustCase",
           "RobustTestConfig", "batch_config", "batch_env", "batch_key", "case_checks", "case_config", "case_env",
           "case_summary", "case_worlds", "checkpoint_case", "evaluate_robust", "evaluate_robust_checkpoint",
           "evaluate_robust_run", "gait_cycle_steps", "heading_frame_velocity", "kicks_text", "randomization_applied",
           "report_settings", "robust_case_config", "robust_passes", "robust_report_text", "run_case", "settings_note"]

#: The seed of every random draw of the robust test (starts, commands, randomisation, pushes). Below 2**32, where the
#: per-episode draws' key is the seed itself (envs.episode_random.hash_seed), and far from the small seeds the presets
#: and tests train with (0, 1, 2, ...), so the test's randomised models are not ones a policy was trained on.
EVAL_SEED = 2_971_215_073
#: Kicks per robot in a pushed case (the env's kicks hold at most 64).
_KICKS = Range(low=1, high=64, integer=True)
#: File names of the report and its figure in the evaluation folder.
ROBUST_JSON, ROBUST_PNG = "robust.json", "robust.png"
#: The files the robust test writes into its folder (:func:`evaluate_robust`).
ROBUST_FILES = (ROBUST_JSON, ROBUST_PNG)
#: Percentiles the report gives of each distribution.
PERCENTILES = (5, 50, 95)


@dataclass(frozen=True)
class RobustCase:
    """One case of the robust test.

    Attributes:
        name: its key in the report and in :data:`.gait_test.ROBUST_CRITERIA`.
        command: the fixed (vx, vy) command [m/s], or None for the training range (``CommandConfig()``) re-drawn
            every ``resample_every`` policy steps.
        resample_every: policy steps (4 ms) between command draws when ``command`` is None (500 = 2 s).
        push_speed: velocity change [m/s] of each horizontal kick; 0 = no kicks and no randomisation. Above 0 the
            case also switches the ``tocabi_lab`` randomisation on (:func:`robust_case_config`).

    Its one line for the report is :meth:`describe`, made from the test settings it ran under.
    """

    name: str
    command: tuple[float, float] | None = (0.5, 0.0)
    resample_every: int = 500
    push_speed: float = 0.0

    @property
    def randomized(self) -> bool:
        return self.push_speed > 0

    def describe(self, test: RobustTestConfig, dt: float) -> str:
        """One line for the report: the command, and for a pushed case the randomisation and ``test``'s kicks
        (``dt``: the policy step [s], which turns ``resample_every`` into seconds). Made from the settings run, not
        written beside them, so a report never describes other kicks than it had.

        >>> CASES["robust_1.0"].describe(RobustTestConfig(), 0.004)
        'command (0.5, 0) m/s, tocabi_lab randomisation, 3 kicks of 1.0 m/s in 2-7 s'
        """
        if self.command is None:
            return f"training command range re-drawn every {self.resample_every * dt:g} s"
        text = f"command ({self.command[0]:g}, {self.command[1]:g}) m/s"
        if not self.randomized:
            return text
        kicks = kicks_text(test.push_count, test.push_window, test.push_kind, self.push_speed)
        return f"{text}, tocabi_lab randomisation, {kicks}"


def kicks_text(count: int, window: Sequence[float], kind: str, speed: float | None = None,
               name_kind: bool = False) -> str:
    """Kicks in words: ``count`` kicks (of ``speed`` [m/s] when given) in ``window`` (start, end) [s].

    The kind is named when it is not the test's (``RobustTestConfig.push_kind``), or always with ``name_kind``: the
    test's own kicks read as plain "kicks" in its case lines, as the committed reports have them.

    >>> kicks_text(1, (0.2, 0.8), "force", 0.5)
    '1 force kick of 0.5 m/s in 0.2-0.8 s'
    """
    kind_word = f"{kind} " if name_kind or kind != RobustTestConfig.push_kind else ""
    # repr keeps the test's "1.0 m/s" (":g" would print "1") and every other speed in full.
    of = f" of {float(speed)!r} m/s" if speed is not None else ""
    return f"{count} {kind_word}kick{'' if count == 1 else 's'}{of} in {window[0]:g}-{window[1]:g} s"


#: The cases, in report order.
CASES: dict[str, RobustCase] = {c.name: c for c in (
    RobustCase("nominal"),
    RobustCase("commands", command=None, resample_every=500),
    RobustCase("robust_0.5", push_speed=0.5),
    RobustCase("robust_1.0", push_speed=1.0),
)}


@dataclass(frozen=True)
class RobustTestConfig:
    """The robust test's settings (the defaults are the test; smaller values are for quick checks).

    Attributes:
        num_envs: robots per case (the test asks for at least 1,024).
        seconds: length of each case [s].
        start_joint_vel_std: std of the Gaussian joint velocities each robot starts with [rad/s].
        start_base_vel_std: std of the Gaussian pelvis linear velocity (each axis) each robot starts with [m/s].
        push_count: kicks per robot in the pushed cases.
        push_window: (start, end) [s] of episode time the kicks fall in (kick j at a random time in the j-th third).
        push_kind: how a kick acts (``PushConfig.kind``): "velocity" (the test: the whole robot's velocity changes
            by the kick's speed) or "force" (an impulse of speed × mass on the pelvis alone, which also kicks the
            joints: a harder push of the same momentum, for comparison).
        seed: the seed of every draw (:data:`EVAL_SEED`).
        cases: which of :data:`CASES` to run, in order.
    """

    num_envs: int = 1024
    seconds: float = 8.0
    start_joint_vel_std: float = 0.5
    start_base_vel_std: float = 0.1
    push_count: int = 3
    push_window: tuple[float, float] = (2.0, 7.0)
    push_kind: str = "velocity"
    seed: int = EVAL_SEED
    cases: tuple[str, ...] = tuple(CASES)

    def validate(self, dt: float) -> None:
        """Raise ``ValueError`` naming a bad setting and the fix (``dt``: the policy step [s])."""
        if isinstance(self.num_envs, bool) or not isinstance(self.num_envs, int) or self.num_envs < 1:
            raise ValueError(f"num_envs must be an int >= 1 (robots per case; the test's default is 1024), got "
                             f"{self.num_envs!r}")
        policy_steps(self.seconds, dt)
        check_seed(self.seed, "seed")  # a float was truncated by int() while the report kept it
        for name in ("start_joint_vel_std", "start_base_vel_std"):
            if not NON_NEGATIVE.allows(getattr(self, name)):
                raise ValueError(f"{name} must be {NON_NEGATIVE.describe()} (the Gaussian's std; the test's is "
                                 f"{getattr(RobustTestConfig, name)}), got {getattr(self, name)!r}")
        if not _KICKS.allows(self.push_count):
            raise ValueError(f"push_count must be {_KICKS.describe()} (kicks per robot in the pushed cases; the "
                             f"test's is 3), got {self.push_count!r}")
        window = tuple(self.push_window) if isinstance(self.push_window, (tuple, list)) else ()
        if len(window) != 2 or not all(NON_NEGATIVE.allows(t) for t in window) or not window[0] < window[1]:
            # An end past `seconds` is taken: a shorter quick check keeps the test's window (the report says so).
            raise ValueError(f"push_window must be (start, end) [s] with 0 <= start < end, finite (the test's is "
                             f"(2.0, 7.0)), got {self.push_window!r}")
        if self.push_kind not in PUSH_KINDS:
            raise ValueError(f"push_kind must be one of {PUSH_KINDS} (the test's is velocity), got {self.push_kind!r}")
        if isinstance(self.cases, str):  # iterated, one name would be read as its letters
            raise ValueError(f"cases must be a tuple of case names, e.g. ({self.cases!r},), got the string "
                             f"{self.cases!r}")
        unknown = [c for c in self.cases if c not in CASES]
        if unknown or not self.cases:
            raise ValueError(f"unknown robust-test case(s) {unknown or '(none given)'}; choose from {list(CASES)}")
        if len(set(self.cases)) != len(self.cases) or list(self.cases) != [c for c in CASES if c in self.cases]:
            # Each case's robots are a block of world indices, whose draws are hashed by index: in the test's order
            # and once each, a case has the full test's start states and randomisation when every case before it
            # runs too (nominal, commands: the diverse test). The commands case's re-drawn commands come from one
            # generator over all worlds, so they differ with the number of cases run.
            raise ValueError(f"robust-test cases {list(self.cases)} must be distinct and in the test's order "
                             f"{list(CASES)}")


# ------------------------------------------------------------------------------------------------ the cases' envs
def robust_case_config(cfg: RunConfig, push_speed: float, test: RobustTestConfig = RobustTestConfig(),
                       trained: RunConfig | None = None) -> RunConfig:
    """``cfg`` with the TOCABI lab's uncertainty model switched on (:func:`tocabi_torchrl.randomize.tocabi_lab`:
    dynamics and the actuator delay and motor constant in the env section, sensor noise in the transform section)
    and ``test.push_count`` horizontal kicks of ``push_speed`` [m/s] (one 4 ms policy step each, of
    ``test.push_kind``) at random times in ``test.push_window``. The pelvis velocity's sensor noise, which the lab's
    set does not have, is that of ``trained`` (the policy's own run config; default ``cfg``): a policy that observes
    the velocity is not tested on a cleaner one than it trained with. The one place the robust cases' randomisation
    is made.

    The lab's actuator model acts on torque commands; in the PD modes the legs are MuJoCo servos inside the physics,
    where it has no place (the env refuses it), so a PD-mode policy gets the rest of the set
    (:func:`randomization_applied` says which)."""
    from ..envs.config import TORQUE_MODES
    from ..envs.pushes import PushConfig
    from ..randomize import tocabi_lab
    from ..transforms.sensor_noise_config import SensorNoiseConfig

    lab = tocabi_lab(cfg)
    trained_noise = (cfg if trained is None else trained).transforms.sensor_noise
    own = {f.name: getattr(trained_noise, f.name) for f in dataclasses.fields(SensorNoiseConfig)
           if f.name.startswith(("base_lin_vel_", "base_ang_vel_"))}
    lab = dataclasses.replace(lab, transforms=dataclasses.replace(
        lab.transforms, sensor_noise=dataclasses.replace(lab.transforms.sensor_noise, **own)))
    env = lab.env
    if env.control.mode not in TORQUE_MODES:
        env = dataclasses.replace(env, control=dataclasses.replace(env.control, actuators=cfg.env.control.actuators))
    pushes = PushConfig(count=test.push_count, window=tuple(test.push_window), speed=(push_speed, push_speed),
                        duration=(0.004, 0.004), kind=test.push_kind)
    return dataclasses.replace(lab, env=dataclasses.replace(env, pushes=pushes))


def randomization_applied(cfg: RunConfig) -> str:
    """What of the ``tocabi_lab`` set :func:`robust_case_config` applies to a policy of run config ``cfg``."""
    from ..envs.config import TORQUE_MODES

    mode = cfg.env.control.mode
    noise = cfg.transforms.sensor_noise
    kept = any(getattr(noise, f"{s}_bias") > 0 or getattr(noise, f"{s}_noise_std") > 0
               for s in ("base_lin_vel", "base_ang_vel"))
    own = "; the pelvis velocity's sensor noise of the policy's training" if kept else ""
    if mode in TORQUE_MODES:
        return f"tocabi_lab: dynamics, actuator delay and motor constant, sensor noise{own}"
    return (f"tocabi_lab without its actuator model (the {mode} mode's servos act inside the physics): dynamics, "
            f"sensor noise{own}")


def case_config(cfg: RunConfig, case: str | RobustCase, test: RobustTestConfig = RobustTestConfig()) -> RunConfig:
    """The run config a case's env is built from: ``cfg`` (a policy's own config) with diverse starts, the case's
    command schedule, :attr:`RobustTestConfig.seed` and, for a pushed case, :func:`robust_case_config`."""
    from ..envs import CommandConfig

    spec = CASES[case] if isinstance(case, str) else case
    # Every case starts from the ideal robot, whatever the policy trained under (record.nominal_config: no kicks,
    # noise or draws of the training, fresh draws at every reset rather than a start pool, and the model's own solver,
    # never a training's iteration cap): the randomised cases then add the test's own set.
    nominal = nominal_config(cfg)
    env = nominal.env
    task = dataclasses.replace(env.task, start_joint_vel_std=float(test.start_joint_vel_std),
                               start_base_vel_std=float(test.start_base_vel_std))
    command = (fixed_command(spec.command) if spec.command is not None
               else dataclasses.replace(CommandConfig(), resample_every=int(spec.resample_every)))
    # No truncation inside the case: a robot is followed for the whole case, reset or not (see run_case).
    from .gait_test import policy_dt

    # The kicks keep the test's window even in a shorter quick check, so the episode covers the window too.
    steps = max(policy_steps(test.seconds, policy_dt()), policy_steps(float(test.push_window[1]), policy_dt()))
    task = dataclasses.replace(task, max_episode_steps=max(int(task.max_episode_steps), steps + 1))
    env = dataclasses.replace(env, task=task, command=command)
    out = dataclasses.replace(nominal, seed=int(test.seed), env=env)
    # The nominal config has no sensor noise: the policy's own velocity noise comes from cfg.
    return robust_case_config(out, spec.push_speed, test, trained=cfg) if spec.randomized else out


def case_env(cfg: RunConfig, case: str | RobustCase, device: torch.device, num_envs: int,
             test: RobustTestConfig = RobustTestConfig(), torque_assist: bool = False, train_solver: bool = False):
    """The env of one case (``num_envs`` robots on ``device``), built as the trainer builds envs
    (:func:`~tocabi_torchrl.rl.trainer.build_env`) from :func:`case_config`. On CUDA its step is one captured CUDA
    graph (:class:`~tocabi_torchrl.envs.autoreset.SyncFreeResetEnv`), which :func:`run_case` replays.
    ``torque_assist``: the torque preset's training aid in the env (an analysis of a checkpoint as it acted in
    training, :func:`checkpoint_case`; the test itself never has it). ``train_solver``: ``cfg``'s own solver
    iteration cap instead of the model's (an analysis, :func:`checkpoint_case`; never the test's)."""
    from ..rl.trainer import build_env

    device = torch.device(device)
    graph = {"sync_free_resets": True, "cuda_graph": True} if device.type == "cuda" else {}
    out = case_config(cfg, case, test)
    if torque_assist:
        out = dataclasses.replace(out, env=dataclasses.replace(out.env, control=dataclasses.replace(
            out.env.control, torque_assist=True)))
    if train_solver:
        out = dataclasses.replace(out, env=dataclasses.replace(out.env, sim=dataclasses.replace(
            out.env.sim, solver_iterations=cfg.env.sim.solver_iterations)))
    return build_env(out, device, num_envs=num_envs, **graph)


def checkpoint_case(path: str | os.PathLike, case: str | RobustCase, device: torch.device | str,
                    test: RobustTestConfig = RobustTestConfig(), as_trained: bool = False,
                    train_solver: bool = False, model_path: str | os.PathLike | None = None):
    """A checkpoint's policy in one case's env, ready for :func:`run_case`: ``(state, cfg, env, agent)``, the
    checkpoint as read, its run config, the env of ``test.num_envs`` robots (:func:`case_env`) seeded with
    ``test.seed`` and holding the checkpoint's normaliser statistics, and the agent with its weights
    (``agent.actor`` is the policy to roll out). ``as_trained``: a checkpoint of a run with the torque assist
    (``ppo.torque_assist``) acts with the assist at the β its training had reached (an analysis: is a weakness the
    fade's?); without it, as in every test, its legs are pure torque. ``train_solver``: the case's physics runs the
    Newton solver the run trained with (``env.sim.solver_iterations``; an analysis: is a weakness the cap's?);
    without it, as in every test, the model's own. ``model_path``: the case runs on another TOCABI MJCF (an
    analysis: is a weakness the authored robot's asymmetry? ``lab/analysis/symmetric_model.py``); without it, the
    checkpoint's own model, as in every test."""
    from ..rl.checkpoint import config_from_checkpoint, read_checkpoint
    from ..rl.trainer import assist_schedule, checkpoint_agent

    state = read_checkpoint(path)
    cfg = config_from_checkpoint(state, path)
    if model_path is not None:
        cfg = dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, task=dataclasses.replace(
            cfg.env.task, model_path=str(model_path))))
    assisted = as_trained and cfg.ppo.torque_assist > 0
    env = case_env(cfg, case, torch.device(device), test.num_envs, test, torque_assist=assisted,
                   train_solver=train_solver)
    agent = checkpoint_agent(state, cfg, env, path)
    if assisted:
        env.base_env.set_torque_assist(assist_schedule(cfg, env)(int(state["env_steps"])))
    env.set_seed(int(test.seed))
    return state, cfg, env, agent


def batch_config(cfg: RunConfig, test: RobustTestConfig = RobustTestConfig()) -> RunConfig:
    """The run config of the one env that holds every case of ``test.cases`` side by side (:func:`batch_env`):
    :func:`case_config` of the commands case (diverse starts, the training command range re-drawn) and, when a case
    is pushed, :func:`robust_case_config` at the fastest case's kick speed. :func:`batch_env` then pins the
    fixed-command worlds, scales each world's kicks to its case and leaves the unrandomised cases' worlds ideal."""
    specs = [CASES[name] for name in test.cases]
    redrawn = {c.resample_every for c in specs if c.command is None}
    if len(redrawn) > 1:
        raise ValueError(f"the robust test's cases re-draw their commands at different intervals {sorted(redrawn)}; "
                         "one batch needs one interval")
    base = RobustCase("batch", command=None, resample_every=redrawn.pop() if redrawn else 500)
    out = case_config(cfg, base, test)
    fastest = max(c.push_speed for c in specs)
    return robust_case_config(out, fastest, test, trained=cfg) if fastest > 0 else out


def batch_key(test: RobustTestConfig, cfg: RunConfig, device: torch.device | str) -> tuple:
    """The key :func:`evaluate_robust` keeps a test's :func:`batch_env` under in its ``envs`` cache: the test's
    size and cases, the env and transform sections of the policy's :func:`batch_config`, so that a policy of
    another control mode, observation or normalisation never meets an env built for another (a PD policy run in a
    torque env once fell in every case), and the ``device`` the env is built on, so that a cache shared across
    devices never hands back an env on another device than the one asked for."""
    sections = build_sections(batch_config(cfg, test))
    place = torch.device(device)
    if place.type == "cuda" and place.index is None:  # "cuda" is the current GPU: one env, not one per spelling
        place = torch.device("cuda", torch.cuda.current_device())
    return ("batch", str(place), tuple(test.cases), test.num_envs, test.push_kind, sections)


def case_worlds(test: RobustTestConfig, device: torch.device | str = "cpu") -> dict[str, slice]:
    """Which worlds of :func:`batch_env` each case holds: ``test.num_envs`` consecutive worlds per case, in
    ``test.cases`` order."""
    n = test.num_envs
    return {name: slice(i * n, (i + 1) * n) for i, name in enumerate(test.cases)}


def batch_env(cfg: RunConfig, device: torch.device | str, test: RobustTestConfig = RobustTestConfig()):
    """One env of ``len(test.cases) × test.num_envs`` robots that runs every case at once (:func:`case_worlds`
    says whose worlds are whose): one batch keeps the GPU busier than a case at a time (at 1,024 robots the
    physics, not the host, limits a case's step rate). Built from :func:`batch_config`, then per world: a
    fixed-command case's worlds hold its command (``VelocityCommand.pin``), each world's kicks are scaled to its
    case's speed (``Pushes.world_scale``; 0 = none), and the worlds of an unrandomised case are the ideal robot
    (``TocabiWalk.set_randomized_worlds``). On CUDA the step is one captured graph (:func:`run_case`)."""
    from ..rl.trainer import build_env

    device = torch.device(device)
    worlds = case_worlds(test)
    graph = {"sync_free_resets": True, "cuda_graph": True} if device.type == "cuda" else {}
    env = build_env(batch_config(cfg, test), device, num_envs=test.num_envs * len(worlds), **graph)
    base = env.base_env
    n = base.num_envs
    fastest = max(CASES[name].push_speed for name in worlds)
    randomized = torch.zeros(n, dtype=torch.bool)
    kick = torch.zeros(n)
    for name, rows in worlds.items():
        case = CASES[name]
        randomized[rows] = case.randomized
        kick[rows] = case.push_speed / fastest if fastest > 0 else 0.0
        if case.command is not None:
            pinned = torch.zeros(n, dtype=torch.bool)
            pinned[rows] = True
            base.command.pin(pinned.to(base.device), case.command)
    base.set_randomized_worlds(randomized.to(base.device))
    if base.pushes is not None:
        base.pushes.world_scale.copy_(kick.to(base.device))
    remember_built_state(env)  # put back before each policy tested in it (evaluate_robust)
    return env


# ------------------------------------------------------------------------------------------------ one case
def heading_frame_velocity(base_quat: torch.Tensor, base_lin_vel: torch.Tensor) -> torch.Tensor:
    """(N, 2) horizontal pelvis velocity [m/s] in the heading frame (the world rotated by the pelvis yaw), from
    ``base_quat`` (N, 4) (w, x, y, z) and ``base_lin_vel`` (N, 3) in the pelvis frame. The command is meant in this
    frame: the pelvis frame itself tilts with the gait's roll and pitch."""
    conjugate = base_quat * base_quat.new_tensor([1.0, -1.0, -1.0, -1.0])
    world = quat_rotate_inverse(conjugate, base_lin_vel)  # R(q)·v: the inverse rotation of the conjugate
    return heading_velocity(base_quat, world)


class CycleMeanTracking:
    """Per-robot speed-tracking error of the velocity averaged over one gait cycle, one :meth:`update` per step.

    A walking pelvis sways sideways with each gait cycle and surges forward with each step, so the instantaneous
    ``|v − command|`` is large even for a gait whose average velocity is the command. This keeps, per robot, the
    sums over the last ``window`` steps (one gait cycle) of the heading-frame velocity and of the command, rolling:
    each step adds the new values and subtracts the ones leaving the ring buffers (``(window, N, 2)`` each, in the
    inputs' dtype; the sums are float64, so the leaving value cancels what it once added up to float64 rounding, not
    float32's). At every step where a robot has been alive for each of the last ``window`` steps it accumulates
    ``|mean_window(v) − mean_window(command)|`` [m/s]; :meth:`per_env` is that sum over the number of such steps.

    No value is read on the host: the step count is a Python int and the rest stays on the inputs' device.

    >>> t = CycleMeanTracking(num_envs=1, window=4)
    >>> for k in range(8):  # 0.5 m/s forward, a ±0.2 m/s surge alternating each step; command (0.4, 0)
    ...     _ = t.update(torch.tensor([[0.5 + 0.2 * (-1) ** k, 0.0]]), torch.tensor([[0.4, 0.0]]),
    ...                  torch.tensor([True]))
    >>> round(float(t.per_env()[0]), 6), int(t.steps[0])  # the surge averages out in each window: steps 4-8
    (0.1, 5)
    """

    def __init__(self, num_envs: int, window: int, device: torch.device | str = "cpu",
                 dtype: torch.dtype = torch.float32):
        if window < 1:
            raise ValueError(f"window must be >= 1 policy step, got {window}")
        self.window, self.num_envs, self.step_count = int(window), int(num_envs), 0
        self.vel_ring = torch.zeros(self.window, num_envs, 2, device=device, dtype=dtype)
        self.cmd_ring = torch.zeros_like(self.vel_ring)
        self.vel_sum = torch.zeros(num_envs, 2, device=device, dtype=torch.float64)
        self.cmd_sum = torch.zeros_like(self.vel_sum)
        #: (N,) consecutive alive steps up to the last update (int64).
        self.alive_run = torch.zeros(num_envs, device=device, dtype=torch.int64)
        #: (N,) float64 sum of the window-mean error over the counted steps [m/s], and their number.
        self.error_sum = torch.zeros(num_envs, device=device, dtype=torch.float64)
        self.steps = torch.zeros(num_envs, device=device, dtype=torch.int64)
        self._diff = torch.zeros_like(self.vel_sum)
        self._err = torch.zeros_like(self.error_sum)

    def update(self, velocity: torch.Tensor, command: torch.Tensor, alive: torch.Tensor) -> torch.Tensor:
        """Account one policy step: ``velocity`` and ``command`` (N, 2) [m/s] (heading frame), ``alive`` (N,) bool
        (whether the robot is alive after this step). Returns the (N,) float64 window-mean error of this step
        [m/s] (meaningful only where the robot has been alive for the whole window; a buffer the next update
        overwrites)."""
        slot = self.step_count % self.window
        for ring, total, new in ((self.vel_ring, self.vel_sum, velocity), (self.cmd_ring, self.cmd_sum, command)):
            total.sub_(ring[slot].double()).add_(new.double())  # the value leaving the window, then the new one
            ring[slot].copy_(new)
        self.step_count += 1
        self.alive_run.add_(1).mul_(alive)
        torch.sub(self.vel_sum, self.cmd_sum, out=self._diff)
        torch.linalg.vector_norm(self._diff, dim=-1, out=self._err)
        self._err.div_(self.window)
        if self.step_count >= self.window:  # a Python int: no robot has a full window before
            full = self.alive_run >= self.window
            self.error_sum.add_(self._err * full)
            self.steps.add_(full)
        return self._err

    def mean_velocity(self) -> torch.Tensor:
        """(N, 2) float64 mean heading-frame velocity over the last ``window`` steps (or the steps so far) [m/s]."""
        return self.vel_sum / min(self.step_count, self.window) if self.step_count else self.vel_sum.clone()

    def mean_command(self) -> torch.Tensor:
        """(N, 2) float64 mean command over the last ``window`` steps (or the steps so far) [m/s]."""
        return self.cmd_sum / min(self.step_count, self.window) if self.step_count else self.cmd_sum.clone()

    def per_env(self) -> torch.Tensor:
        """(N,) float32 mean over the counted steps of ``|mean_window(v) − mean_window(command)|`` [m/s]; NaN for a
        robot with none (it fell, or the rollout ended, within its first ``window`` steps)."""
        return torch.where(self.steps > 0, self.error_sum / self.steps.clamp_min(1), float("nan")).float()


def run_case(actor, env, seconds: float, desc: str = "robust test", progress: bool = True,
             autoreset: bool | None = None) -> dict[str, torch.Tensor]:
    """Roll the deterministic ``actor`` out in a case's ``env`` for ``seconds`` from a reset; fallen robots are not
    reset (they lie where they fell and every metric uses their alive steps only, as in the standard test).

    Returns (N,) CPU tensors per robot: ``alive`` (bool), ``forward_m`` and ``lateral_m`` (pelvis displacement in
    the world's x and y up to its last alive step [m]), ``tracking_error_mps`` (the error of the velocity averaged
    over one gait cycle, :class:`CycleMeanTracking`: the mean, over the steps where the robot has been alive for
    the whole last cycle, of ``|mean_cycle(v_heading) − mean_cycle(command)|`` [m/s], v_heading the horizontal
    pelvis velocity in the heading frame; NaN for a robot that fell, or a case that ended, within its first
    cycle), ``instant_speed_error_mps`` (the mean over alive steps of the instantaneous ``|v_heading − command|``
    [m/s], which includes the gait's sway within each cycle), ``knee_rms_rad`` (against the reference [rad]),
    ``heading_change_rad`` (|pelvis yaw| at the last alive step [rad]: every robot starts facing +x, so this is how
    far it turned, the usual cause of drift) and ``alive_seconds``; NaN for a robot with no alive step. The cycle is
    the reference motion's period in policy steps (:func:`gait_cycle_steps`: 450 steps of 4 ms).

    An env whose step is a captured CUDA graph (``env.cuda_graph``, as :func:`case_env` builds on CUDA) is stepped
    through that graph, ``step_and_maybe_reset``: a fallen robot is then reset and walks on, but the metrics stop
    at its first fall either way (:class:`GaitMetrics`), so both paths give the same numbers (``autoreset`` forces
    one: True needs a sync-free env, False is the eager ``env.step``)."""
    base = env.base_env
    dt = float(base.dt)
    steps = policy_steps(seconds, dt)
    freeze_running_statistics(env)  # a test of the policy as trained, not of statistics drifting with its rollout
    if autoreset is None:
        autoreset = bool(getattr(env, "cuda_graph", False))
    if autoreset and hasattr(env, "invalidate_graph"):
        env.invalidate_graph()  # the graph reads the normaliser's frozen flag as captured: capture it frozen
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.reset()
        metrics = GaitMetrics(td["base_pos"], (0.5, 0.0), dt)  # its own speed error is unused: the command varies
        instant = torch.zeros(env.num_envs, device=td["base_pos"].device)
        cycle = CycleMeanTracking(env.num_envs, gait_cycle_steps(base.motion.period, dt), td["base_pos"].device)
        heading = torch.zeros(env.num_envs, device=td["base_pos"].device)  # pelvis yaw at the last alive step
        for k in tqdm(range(steps), desc=desc, unit="step", disable=not progress, leave=False):
            action = actor(td) if k else first_action(actor, td)
            if autoreset:
                td, carry = env.step_and_maybe_reset(action)
            else:
                td = env.step(action)
            nxt = td["next"]
            alive = metrics.update(nxt)
            velocity = heading_frame_velocity(nxt["base_quat"], nxt["base_lin_vel"])
            instant += alive.float() * (velocity - nxt["command"]).norm(dim=-1)
            cycle.update(velocity, nxt["command"], alive)
            heading = torch.where(alive, quat_to_rpy(nxt["base_quat"])[..., 2], heading)
            td = carry if autoreset else step_mdp(td)
            if k % 50 == 49 and not bool(alive.any()):  # no metric can change once all have fallen (a read per 50)
                break
    per_env = metrics.per_env()
    per_env["tracking_error_mps"] = cycle.per_env()
    per_env["instant_speed_error_mps"] = metrics._per_alive_step(instant)
    per_env["heading_change_rad"] = torch.where(metrics.alive_steps > 0, heading.abs(), float("nan"))
    return {k: v.detach().cpu() for k, v in per_env.items()}


def _distribution(values: torch.Tensor, stats: Sequence[str]) -> dict[str, float]:
    """``stats`` ("mean", "p5", "p50", "p95", ...) of ``values`` (N,) over its non-NaN entries; NaN when none."""
    finite = values[~torch.isnan(values)].double()
    out = {}
    for stat in stats:
        if finite.numel() == 0:
            out[stat] = math.nan
        elif stat == "mean":
            out[stat] = float(finite.mean())
        else:
            out[stat] = float(torch.quantile(finite, float(stat[1:]) / 100.0))
    return out


def case_summary(case: RobustCase, per_env: dict[str, torch.Tensor], test: RobustTestConfig, dt: float) -> dict:
    """A case's report entry (without its verdict) from :func:`run_case`'s per-robot values, of a case run under
    ``test``'s settings (``dt``: the policy step [s])."""
    return {
        "description": case.describe(test, dt),
        "num_envs": int(per_env["alive"].numel()),
        "seconds": float(test.seconds),
        "command_mps": (list(case.command) if case.command is not None
                        else f"training range (CommandConfig()) re-drawn every {case.resample_every} steps"),
        "randomized": case.randomized,
        "push_speed_mps": float(case.push_speed),
        "survival": float(per_env["alive"].float().mean()),
        "forward_distance_m": _distribution(per_env["forward_m"], ("mean", "p5", "p50", "p95")),
        "lateral_drift_m": _distribution(per_env["lateral_m"].abs(), ("mean", "p50", "p95")),
        "tracking_error_mps": _distribution(per_env["tracking_error_mps"], ("mean", "p95")),
        "instant_speed_error_mps": _distribution(per_env["instant_speed_error_mps"], ("mean", "p95")),
        "knee_rms_rad": _distribution(per_env["knee_rms_rad"], ("mean", "p95")),
        "heading_change_rad": _distribution(per_env["heading_change_rad"], ("mean", "p95")),
    }


# ------------------------------------------------------------------------------------------------ verdicts
def _metric(summary: dict, path: str):
    """The value at ``path`` ("survival", "lateral_drift_m.p95") of a case summary; None if missing."""
    value = summary
    for part in path.split("."):
        if not isinstance(value, dict) or part not in value:
            return None
        value = value[part]
    return value


def case_checks(name: str, summary: dict) -> dict[str, dict]:
    """Each threshold of case ``name`` (:data:`.gait_test.ROBUST_CRITERIA`) against ``summary`` (a case entry of the
    report, or of ``robust.json`` read back): metric path -> {"value", "needs" (e.g. ">= 0.99"), "pass"}. A value
    that is missing, NaN or null fails."""
    checks = {}
    for path, (op, limit) in ROBUST_CRITERIA[name].items():
        value = _metric(summary, path)
        ok = (isinstance(value, (int, float)) and math.isfinite(value)
              and (value >= limit if op == ">=" else value <= limit))
        checks[path] = {"value": value, "needs": f"{op} {limit:g}", "pass": bool(ok)}
    return checks


def robust_passes(report: dict, cases: tuple[str, ...] | None = None) -> bool:
    """Whether a robust-test report (:func:`evaluate_robust`'s, or ``robust.json`` read back) passes: every case of
    ``cases`` (default: all of :data:`.gait_test.ROBUST_CRITERIA`) is in it and meets all its thresholds
    (re-checked from the values, not read from the stored verdicts)."""
    if cases is not None and not cases:
        raise ValueError("robust_passes: no cases to judge; give None (the whole test) or the cases' names")
    found = report.get("cases", {})
    return all(name in found and all(c["pass"] for c in case_checks(name, found[name]).values())
               for name in (tuple(ROBUST_CRITERIA) if cases is None else cases))


# ------------------------------------------------------------------------------------------------ the test
def report_settings(test: RobustTestConfig) -> dict:
    """``test``'s settings as the report records them (``robust.json``'s "settings"; units in the keys)."""
    return {"num_envs": test.num_envs, "seconds": test.seconds, "start_joint_vel_std_radps": test.start_joint_vel_std,
            "start_base_vel_std_mps": test.start_base_vel_std, "push_count": test.push_count,
            "push_window_s": list(test.push_window), "push_kind": test.push_kind}


def settings_note(settings: dict, pushed: bool) -> str:
    """What a verdict's headline adds for a report whose kicks (when ``pushed``: a pushed case ran) or start
    velocities are not the test's (:class:`RobustTestConfig`'s defaults); "" when they are. Robots per case and
    the length have notes of their own. A weaker test could otherwise print "walks" as if it were the test.

    A report made before the test recorded ``push_kind`` had force kicks (docs/evaluation.md)."""
    test = report_settings(RobustTestConfig())
    notes = []
    kicks = ("push_count", "push_window_s", "push_kind")
    ran = {**{k: settings.get(k, test[k]) for k in kicks}, "push_kind": settings.get("push_kind", "force")}
    if pushed and any(ran[k] != test[k] for k in kicks):
        ran_words, test_words = (kicks_text(*(s[k] for k in kicks), name_kind=True) for s in (ran, test))
        notes.append(f"{ran_words} (the test: {test_words})")
    starts = ("start_joint_vel_std_radps", "start_base_vel_std_mps")
    if any(settings.get(k, test[k]) != test[k] for k in starts):
        joint, base = (settings.get(k, test[k]) for k in starts)
        notes.append(f"start velocity std {joint:g} rad/s (joints) and {base:g} m/s (pelvis) (the test: "
                     f"{test[starts[0]]:g} and {test[starts[1]]:g})")
    return f"; not the test's settings: {'; '.join(notes)}" if notes else ""


def evaluate_robust(actor, cfg: RunConfig, out_dir: str | os.PathLike, test: RobustTestConfig = RobustTestConfig(),
                    device: str | torch.device = "auto", envs: dict | None = None,
                    prepare_env: Callable | None = None, progress: bool = True,
                    source: str | os.PathLike | None = None) -> dict:
    """Run the robust test's cases (``test.cases``) of the deterministic ``actor`` (trained with run config
    ``cfg``) and write ``robust.json`` and ``robust.png`` to ``out_dir`` (created if needed; files of the same name
    replaced). Returns the report: {"test": "robust", "passes", "seed", "settings", "tested_on", "criteria",
    "cases": {name: case summary with "checks" and "passes"}}, NaN where a value does not exist (``null`` in the
    file).

    Every case runs at once in one env (:func:`batch_env`). ``envs``: a dict to keep that env in for reuse (e.g.
    across checkpoints; built and stored under :func:`batch_key` when missing; its transform state is put back to
    the state it was built with before each policy, so no policy meets what one before it loaded).
    ``prepare_env(env)``: called on the env before the rollout, e.g. to load a checkpoint's normaliser statistics
    into it (without it, an env whose running normaliser never saw a step raises ``ValueError``). ``device``:
    "auto" (the GPU if torch sees one, else the CPU), "cuda", "cuda:K" or "cpu". ``progress``: a bar. ``source``:
    the checkpoint tested, recorded in the report as ``checkpoint``."""
    from .gait_test import policy_dt
    from .plots import plot_robust

    dt = policy_dt()
    test.validate(dt)
    device = resolve_device(device)  # before the folder is made: "cuda" on a CPU-only machine says to pass "cpu"
    envs = {} if envs is None else envs
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    report = {"test": "robust", "passes": False, "seed": test.seed, "tested_on": tested_on(device),
              "settings": report_settings(test),
              "criteria": {name: {p: f"{op} {v:g}" for p, (op, v) in c.items()} for name, c in ROBUST_CRITERIA.items()},
              "cases": {}}
    if source is not None:
        report["checkpoint"] = str(source)
    per_case = {}
    key = batch_key(test, cfg, device)
    if key not in envs:
        envs[key] = batch_env(cfg, device, test)
    env = envs[key]
    restore_built_state(env)  # nothing a policy tested before in this env loaded stays for this one
    if prepare_env is not None:
        prepare_env(env)
    require_trained_statistics(env)  # without prepare_env, a running normaliser has no checkpoint's statistics
    # The same robots for every policy tested in this env: episode draws restart from the test's seed.
    env.set_seed(int(test.seed))
    every = run_case(actor, env, test.seconds, progress=progress,
                     desc=f"robust test: {len(test.cases)} cases x {test.num_envs} robots")
    for name, rows in case_worlds(test).items():
        case = CASES[name]
        per_env = {k: v[rows] for k, v in every.items()}
        summary = case_summary(case, per_env, test, dt)
        if case.randomized:
            summary["randomization"] = randomization_applied(cfg)
        summary["checks"] = case_checks(name, summary) if name in ROBUST_CRITERIA else {}
        summary["passes"] = all(c["pass"] for c in summary["checks"].values())
        report["cases"][name] = summary
        per_case[name] = per_env
    report["passes"] = robust_passes(report)
    atomic_write_text(out / ROBUST_JSON, summary_json(report))
    plot_robust(per_case, report, out / ROBUST_PNG)
    return report


def evaluate_robust_checkpoint(state: dict, path: str | os.PathLike, out_dir: str | os.PathLike,
                               test: RobustTestConfig = RobustTestConfig(), device: str | torch.device = "auto",
                               envs: dict | None = None, progress: bool = True) -> dict:
    """:func:`evaluate_robust` of a checkpoint already read (``state``, from ``read_checkpoint(path)``): its actor,
    and its normaliser statistics loaded into every case's env. ``envs`` as there: a benchmark reuses the case envs
    of one run's checkpoints (building them costs more than the test)."""
    from ..rl.checkpoint import config_from_checkpoint
    from ..rl.symmetry import apply_checkpoint_policy
    from ..rl.trainer import checkpoint_agent
    from .gait_test import policy_dt

    device = resolve_device(device)
    cfg = config_from_checkpoint(state, path)
    test.validate(policy_dt())
    envs = {} if envs is None else envs
    key = batch_key(test, cfg, device)
    if key not in envs:  # the agent's sizes come from the env
        envs[key] = batch_env(cfg, device, test)
    env = envs[key]
    agent = checkpoint_agent(state, cfg, env, path)  # each case's env then gets the checkpoint's state again
    return evaluate_robust(agent.actor, cfg, out_dir, test=test, device=device, envs=envs,
                           prepare_env=lambda case_env_: apply_checkpoint_policy(state, agent, cfg, case_env_, path),
                           progress=progress, source=path)


def evaluate_robust_run(run: str | os.PathLike, num_envs: int = 1024, device: str = "auto",
                        out_dir: str | os.PathLike | None = None, seconds: float = 8.0,
                        cases: Sequence[str] | None = None, progress: bool = True, replace: bool = False,
                        envs: dict | None = None) -> dict:
    """Load ``run`` (a run folder or checkpoint file) and run the robust test (``num_envs`` robots per case,
    ``seconds`` each, ``cases`` of :data:`CASES`, default all). Results go to ``out_dir`` as given, or by default to
    :func:`.gait_test.fresh_eval_dir`. An ``out_dir`` that already holds a test's results (:data:`ROBUST_FILES`)
    raises :class:`~.output.OutputExistsError` unless ``replace`` (then files of the same name are replaced, others
    stay). ``envs``: as :func:`evaluate_robust`'s, a dict that keeps the test's env for the next policy tested with
    it (the same robots and draws; the build is saved, while on CUDA each policy's step is captured again, with its
    normaliser frozen). Raises ``CheckpointError`` for a bad file and ``ValueError`` for a bad setting, before
    building anything."""
    from ..rl.checkpoint import checkpoint_file, read_checkpoint
    from .gait_test import policy_dt

    # In the test's order, each once (RobustTestConfig.validate): a case has the full test's start states and draws
    # when the cases before it run too (not the commands case's re-drawn commands: RobustTestConfig.validate).
    if not isinstance(cases, str):  # a string goes to the test's own check whole (dict.fromkeys splits it)
        order = list(CASES)
        named = dict.fromkeys(CASES if cases is None else cases)  # [] stays empty: the check below names it
        cases = tuple(sorted(named, key=lambda c: order.index(c) if c in order else len(order)))
    test = RobustTestConfig(num_envs=num_envs, seconds=seconds, cases=cases)
    test.validate(policy_dt())
    check_results_folder(out_dir, ROBUST_FILES, replace)
    ckpt = checkpoint_file(run)
    state = read_checkpoint(ckpt)
    return evaluate_robust_checkpoint(state, ckpt, fresh_eval_dir(ckpt) if out_dir is None else out_dir, test=test,
                                      device=device, envs=envs, progress=progress)


def robust_report_text(report: dict, out: str | os.PathLike | None = None) -> str:
    """The report for people: the verdict, one line per case (survival, distance p5/p50/p95, drift p95, tracking
    error of the gait-cycle mean velocity and the instantaneous speed error, knee RMS), each threshold with
    pass/FAIL, and the files written. Full precision stays in the JSON."""

    def num(value, spec):
        return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else format(value, spec)

    s = report["settings"]
    lines = [f"robust gait test ({s['seconds']:g} s, {s['num_envs']} robots per case): "
             + ("walks" if report["passes"] else "does not walk yet") + length_note(s["seconds"])]
    window = s.get("push_window_s")
    if window and s["seconds"] < window[1] and any(n.startswith("robust") for n in report["cases"]):
        # The kicks come at random times in the window: a shorter test gives some robots fewer of them, or none.
        lines[0] += (f"; no kick falls within {s['seconds']:g} s (they come at {window[0]:g}-{window[1]:g} s)"
                     if s["seconds"] <= window[0] else
                     f"; the kicks come at {window[0]:g}-{window[1]:g} s, so some robots met fewer than "
                     f"{s.get('push_count', 3)} in {s['seconds']:g} s")
    lines[0] += settings_note(s, any(CASES[n].randomized for n in report["cases"] if n in CASES))
    if s["num_envs"] < RobustTestConfig().num_envs:
        lines[0] += f"; {s['num_envs']} robots per case, the test asks for {RobustTestConfig().num_envs:,}"
    left_out = [name for name in ROBUST_CRITERIA if name not in report["cases"]]
    if left_out:  # every case it ran may pass: the verdict needs all of them
        lines[0] += f"; not run: {', '.join(left_out)} (the verdict needs every case)"
    for name, c in report["cases"].items():
        d, drift = c["forward_distance_m"], c["lateral_drift_m"]
        lines.append(f"  {name:<11} survival {num(c['survival'], '.3f')}, forward p5/p50/p95 {num(d['p5'], '.2f')}/"
                     f"{num(d['p50'], '.2f')}/{num(d['p95'], '.2f')} m, drift p95 {num(drift['p95'], '.2f')} m, "
                     f"tracking (cycle mean / instantaneous) {num(c['tracking_error_mps']['mean'], '.3f')} / "
                     f"{num(c.get('instant_speed_error_mps', {}).get('mean'), '.3f')} m/s, knee RMS "
                     f"{num(c['knee_rms_rad']['mean'], '.3f')} rad, turned p95 "
                     f"{num(c.get('heading_change_rad', {}).get('p95'), '.2f')} rad")
        for path, check in c.get("checks", {}).items():
            value, (op, limit) = check["value"], check["needs"].split()
            shown = num(value, ".3f")
            if shown != "-":  # never a rounding that reads as the other verdict (0.9697 as 0.970, needs >= 0.97)
                shown = rounded_against(value, float(limit), check["pass"], "min" if op == ">=" else "max", 3)
            lines.append(f"      {path:<24} {shown:>8}  needs {check['needs']:<8} "
                         f"{'pass' if check['pass'] else 'FAIL'}")
    if out is not None:
        lines.append(f"results: {Path(out) / ROBUST_JSON}, {Path(out) / ROBUST_PNG}")
    return "\n".join(lines)
