"""PPO on TorchRL: a collector on the env's device, GAE, ``ClipPPOLoss``, mini-batch epochs, LR and std schedules,
logging and checkpoints. ``recipes/ppo_walk.py`` is a thin command line over :func:`train`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import importlib.util
import inspect
import math
import os
import shutil
import signal
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.distributed as dist
from tensordict import TensorDictBase
from torch.nn.parallel import DistributedDataParallel
from torchrl.collectors import Collector
from torchrl.envs import EnvBase, SelectTransform
from torchrl.modules import ProbabilisticActor, ValueOperator
from torchrl.objectives import ClipPPOLoss

from .. import robot
from ..cuda_graphs import plan_graphs
from ..device import check_device
from .actors import action_std, gaussian_head, gaussian_log_prob, make_actor, set_action_std
from .assist import AssistAbsorbLoss, AssistSchedule, AssistTeacher
from .checkpoint import apply_checkpoint, config_from_checkpoint, save_checkpoint
from .deferred_read import DeferredRead
from .gae import SyncFreeGAE
from ..config import MAX_SEED, PPOConfig, RunConfig, schedule_warning, wall_tag
from ..envs.config import TocabiWalkConfig
from ..tree import get_path, leaf_paths
from ..value_rules import positive_count
from .distributed import (DistInfo, GradientAllReduce, RunningStatsSync, agree, all_reduce_mean, all_reduce_sum,
                          broadcast_module, from_environment, init_distributed, rank_seed)
from .interrupt import StopFlag, stop_on_signals
from .logging import RunLogger, print_line, require_loggers
from .overlap import UpdateOverlap
from .networks import ConcatInputs, make_mlp
from .rollout_guard import PROXIMAL_KEY, VALID_KEY, GuardedClipPPOLoss, guard_rollout
from .run_dir import RunFolder, open_run
from .std_schedule import StdSchedule
from ..transforms.normalize import RunningNormalization
from ..transforms.privileged import PRIVILEGED_DIM, PrivilegedState
from .symmetry import (SymmetryAugmentLoss, apply_checkpoint_policy, find_normalization, make_equivariant_mean,
                       make_symmetry_loss, refresh_statistics, set_equivariant_statistics)
from .update_step import (AUTOCAST_DTYPES, MinibatchKLRule, MinibatchStep, adapt_lr, get_lr, make_capturable_adam,
                          optimizer_mode, restore_optimizer_mode, set_lr, update_autocast)

__all__ = ["Agent", "build_agent", "build_env", "env_config", "make_collector", "make_loss", "make_optimizer",
           "make_update_step", "check_update_device", "check_compile_toolchain", "decoupled_update", "training_keys",
           "train", "resolve_device", "float32_matmul_precision", "TrainResult", "raised_before_training"]

#: The mask ClipPPOLoss's advantage normalisation reads (TorchRL 0.14: ``_standardize_advantage``).
NORM_MASK_KEY = "shifted_valid"


def resolve_device(name: str) -> torch.device:
    """``"auto"`` -> the first CUDA GPU if torch sees one, else the CPU."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return check_device(name)


@dataclass
class Agent:
    """The trainable parts of a PPO run."""

    actor: ProbabilisticActor
    critic: ValueOperator
    std_schedule: StdSchedule | None
    #: The torque assist's frozen teacher (``assist_target="teacher"``), saved with the run; not trained.
    teacher: AssistTeacher | None = None

    def state_dict(self) -> dict:
        """``{"actor", "critic"[, "teacher"]}`` module state dicts, tensors only (what checkpoints hold)."""
        state = {"actor": self.actor.state_dict(), "critic": self.critic.state_dict()}
        if self.teacher is not None:
            state["teacher"] = self.teacher.state_dict()
        return state

    def load_state_dict(self, state: dict) -> None:
        """Load :meth:`state_dict`'s output; the teacher only where both this agent and ``state`` have one."""
        self.actor.load_state_dict(state["actor"])
        self.critic.load_state_dict(state["critic"])
        if self.teacher is not None and "teacher" in state:
            self.teacher.load_state_dict(state["teacher"])


def env_config(cfg: RunConfig, for_training: bool = False) -> TocabiWalkConfig:
    """The env section the run's envs are built from: ``cfg.env``, with the torque assist switched on for a
    training env when ``cfg.ppo.torque_assist`` > 0 (a training aid: evaluations run the pure torque policy)."""
    env = cfg.env
    if for_training and cfg.ppo.torque_assist > 0 and not env.control.torque_assist:
        env = dataclasses.replace(env, control=dataclasses.replace(env.control, torque_assist=True))
    return env


def check_given_env(cfg: RunConfig, env: EnvBase) -> None:
    """``ValueError`` unless an env given to :func:`train` is the one ``cfg`` describes: the run saves ``cfg``, and
    every evaluation, play, export and resume rebuilds the env from it, so an env built with other settings would
    train a policy its files describe wrongly (a torque policy saved as a PD one, running statistics dropped)."""
    if "observation" not in env.observation_spec.keys():
        raise ValueError("the env given to train() has no 'observation' (the policy input); build it with "
                         "build_env(cfg, device, for_training=True), or make_env with the default transforms")
    if env.batch_size.numel() != cfg.env.num_envs:
        raise ValueError(f"the env given to train() has {env.batch_size.numel()} worlds, cfg.env.num_envs "
                         f"{cfg.env.num_envs}: set env.num_envs in cfg, or build the env with build_env(cfg, ...)")
    base = getattr(env, "base_env", env)
    want = env_config(cfg, for_training=True)
    if isinstance(getattr(base, "cfg", None), TocabiWalkConfig):
        differ = [f"env.{path}: {get_path(base.cfg, path)!r} in the env, {get_path(want, path)!r} in cfg"
                  for path in leaf_paths(want)
                  if path != "num_envs" and get_path(base.cfg, path) != get_path(want, path)]
        if differ:
            raise ValueError(f"the env given to train() was built with other settings than cfg ({'; '.join(differ[:3])}"
                             f"{'; ...' if len(differ) > 3 else ''}): the run saves cfg, so its files would describe "
                             "another env; put the settings into cfg and build the env with build_env(cfg, device, "
                             "for_training=True)")
        # What build_env sets from cfg besides the env section: the seed and the assist PD's sensed joints.
        if base._seed != cfg.seed:
            raise ValueError(f"the env given to train() was seeded with {base._seed}, cfg.seed is {cfg.seed}: the run "
                             "saves cfg, so a resume or a repeat would draw other episodes; set seed in cfg, or build "
                             "the env with build_env(cfg, device, for_training=True)")
        control = base.cfg.control
        sensed = bool(cfg.ppo.assist_pd_sensed and control.torque_assist) or control.pd_senses_joints
        if base.assist_reads_sensed != sensed:
            why = (f"env.control.mode is {control.mode}, whose PD reads the sensed positions"
                   if control.pd_senses_joints else f"cfg.ppo.assist_pd_sensed is {cfg.ppo.assist_pd_sensed}")
            raise ValueError(f"the env given to train() has its assist PD read the {'true' if sensed else 'sensed'} "
                             f"joint positions, {why}: build the env with build_env(cfg, device, for_training=True), "
                             "which sets it")
    privileged = "privileged" in env.observation_spec.keys()
    if privileged != cfg.ppo.critic_privileged:
        raise ValueError(f"the env given to train() {'gives' if privileged else 'has no'} 'privileged' (the "
                         f"asymmetric critic's input), cfg.ppo.critic_privileged is {cfg.ppo.critic_privileged}: build "
                         "the env with build_env(cfg, device, for_training=True), which adds it")
    running = isinstance(find_normalization(env), RunningNormalization)
    if running != (cfg.transforms.normalization == "running"):
        raise ValueError(f"the env given to train() normalises with {'running' if running else 'fixed or no'} "
                         f"statistics, cfg.transforms.normalization is {cfg.transforms.normalization!r}: set it in cfg "
                         "and build the env with build_env(cfg, device, for_training=True)")
    # The policy input's other settings: a history layout, sensor noise or clip of another kind can give an input
    # of the same width, which every later evaluation, export and resume would build otherwise. (The reward terms
    # may be one's own: a task of its own passes them to build_env, docs/extending.md.)
    from ..transforms.presets import default_transforms

    given = _input_settings(getattr(env, "transform", None))
    if given is not None:
        want = _input_settings(default_transforms(cfg.transforms.transform_config()))
        differ = [f"{name}: {_short(given[name])} in the env, {_short(want[name])} in cfg" for name in want
                  if given[name] != want[name]]
        if differ:
            raise ValueError(f"the env given to train() builds its policy input otherwise than cfg "
                             f"({'; '.join(differ[:2])}{'; ...' if len(differ) > 2 else ''}): the run saves cfg, so "
                             "every evaluation, export and resume would build another input; put the settings into "
                             "cfg.transforms and build the env with build_env(cfg, device, for_training=True)")


def _short(value) -> str:
    """``value`` for an error line: its repr, or its type's name when that is long (a whole config)."""
    text = "none" if value is None else repr(value)
    return text if len(text) <= 64 else f"a {type(value).__name__} of its own"


def _input_settings(chain) -> dict | None:
    """What of a transform chain builds the policy input, for comparing two chains: the phase harmonics, the
    per-step layout, the sensor noise, the normalisation's kind and clip and the history layout; None without a
    chain (an env without transforms)."""
    if chain is None:
        return None
    from ..transforms._base import flatten_chain

    found = {"phase harmonics": None, "observation layout": None, "sensor noise": None, "normalization": None,
             "observation clip": None, "history": None}
    for t in flatten_chain([chain]):
        kind = type(t).__name__
        if kind == "PhaseEncoding":
            found["phase harmonics"] = t.harmonics
        elif kind == "ObservationAssembly":
            found["observation layout"] = tuple(c.name for c in t.layout)
        elif kind == "SensorNoise":
            found["sensor noise"] = t.config
        elif kind in ("FixedNormalization", "RunningNormalization"):
            found["normalization"], found["observation clip"] = kind, t.clip
        elif kind == "ObsActionHistory":
            found["history"] = t.layout
    return found


def build_env(cfg: RunConfig, device: torch.device | str, num_envs: int | None = None, for_training: bool = False,
              **env_overrides) -> EnvBase:
    """``make_env`` with the run's env and transform sections (:func:`env_config`) and seed.

    ``num_envs`` replaces ``cfg.env.num_envs``; ``env_overrides`` are ``make_env`` keywords (e.g.
    ``sync_free_resets``, ``cuda_graph``, ``command=...``). ``for_training``: unless ``cfg.ppo.store_env_signals``,
    the env's outputs are cut to what PPO, the logs and the transforms' next step read (:func:`training_keys`), so
    the collector stores ~40 % less per frame.
    """
    from .. import make_env

    # 0 once meant 4,096; a count read as the config reads it (a 0-d integer tensor as well as a numpy integer)
    num_envs = cfg.env.num_envs if num_envs is None else positive_count(
        num_envs, f"; None for the run's env.num_envs ({cfg.env.num_envs})")
    num_envs, device = int(num_envs), torch.device(device)  # a name ("cuda") works as well as a torch.device
    if device.type == "cuda":
        plan = plan_graphs(cfg, device, num_envs, sync_free_resets=env_overrides.get("sync_free_resets") is not False,
                           compile_reward=bool(env_overrides.get("compile_reward")))
        env_overrides.setdefault("cuda_graph", plan.env_step)
    env = make_env(num_envs, device, seed=cfg.seed, config=env_config(cfg, for_training),
                   transforms=cfg.transforms, **env_overrides)
    if cfg.ppo.assist_pd_sensed and env.base_env.cfg.control.torque_assist:
        env.base_env.sense_assist_joints()
    if cfg.ppo.critic_privileged:
        env.append_transform(PrivilegedState())
    if for_training and not cfg.ppo.store_env_signals:
        env.append_transform(SelectTransform(*training_keys(env)))
    return env


def training_keys(env: EnvBase) -> list:
    """Env outputs a training rollout needs: the policy input, the episode counters and per-term rewards that are
    logged, the torque assist (read by :class:`~tocabi_torchrl.rl.assist.AssistAbsorbLoss`) when the env has it,
    and the signals a transform reads from the previous step (the reward terms' ``root_keys``).
    Reward and done flags are always kept."""
    leaves = list(env.observation_spec.keys(True, True))
    keys = ["observation", "privileged", "step_count", "episode_reward", "leg_assist"]
    keys += [k for k in leaves if isinstance(k, tuple) and k[0] == "reward_terms"]
    for t in getattr(env, "transform", []):
        for term in getattr(t, "terms", ()):
            keys += [k for k in term.root_keys if k not in keys]
    return [k for k in keys if k in leaves]


def build_agent(cfg: RunConfig, obs_dim: int, act_dim: int, device: torch.device) -> Agent:
    """Actor, critic, std schedule and (torque assist with a teacher) the frozen teacher, as ``cfg.ppo`` says."""
    ppo = cfg.ppo
    actor = make_actor(obs_dim, act_dim, ppo.actor_hidden, ppo.activation, init_std=ppo.std_start,
                       learn_std=ppo.std_mode == "learned").to(device)
    if ppo.symmetry == "equivariant":  # before the teacher copies the mean network
        head = gaussian_head(actor)
        head.mean_net = make_equivariant_mean(head.mean_net, cfg.transforms.transform_config(), obs_dim, act_dim)
    # Asymmetric (ppo.critic_privileged): the critic reads the true state beside the policy input.
    width = obs_dim + (PRIVILEGED_DIM if ppo.critic_privileged else 0)
    value_net = make_mlp(width, ppo.critic_hidden, 1, ppo.activation, out_gain=ppo.value_out_gain)
    if ppo.critic_privileged:
        critic = ValueOperator(ConcatInputs(*value_net), in_keys=["observation", "privileged"]).to(device)
    else:
        critic = ValueOperator(value_net, in_keys=["observation"]).to(device)
    schedule = StdSchedule(ppo.std_start, ppo.std_end, ppo.std_hold) if ppo.std_mode == "scheduled" else None
    teacher = None
    if ppo.torque_assist > 0 and ppo.assist_target == "teacher":
        teacher = AssistTeacher(gaussian_head(actor).mean_net, robot.LEG_TORQUE_LIMITS)
    return Agent(actor, critic, schedule, teacher)


def checkpoint_agent(state: dict, cfg: RunConfig, env: EnvBase, path) -> Agent:
    """The agent of checkpoint ``state`` (read from ``path``, config ``cfg``) for ``env``: built at the env's
    observation and action widths on its device, with the trained weights and ``env``'s normaliser state applied by
    :func:`~.symmetry.apply_checkpoint_policy` (so, with ``cfg.ppo.symmetric_policy``, the symmetric policy). What
    every reader of a checkpoint's policy uses: the gait tests, play, the viewer, the export."""
    agent = build_agent(cfg, env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1], env.device)
    apply_checkpoint_policy(state, agent, cfg, env, path)
    return agent


def _param_groups(agent: Agent, cfg: RunConfig) -> list[dict]:
    """One group for everything, or (reference) a second, constant-LR group for the value head alone."""
    params = [p for p in list(agent.actor.parameters()) + list(agent.critic.parameters()) if p.requires_grad]
    lr, head_lr = cfg.ppo.lr, cfg.ppo.value_head_lr
    if head_lr <= 0:
        return [{"params": params, "lr": lr, "name": "all"}]
    head = list(agent.critic.module[-1].parameters())
    head_ids = {id(p) for p in head}
    rest = [p for p in params if id(p) not in head_ids]
    return [{"params": rest, "lr": lr, "name": "policy"},
            {"params": head, "lr": head_lr, "name": "value_head", "fixed": True}]


@dataclass
class TrainResult:
    run_dir: Path
    iterations: int
    env_steps: int
    wall_seconds: float
    env_steps_per_second: float
    last_metrics: dict
    #: Whether the env step ran as a captured CUDA graph by the end (``cfg.ppo.cuda_graph``;
    #: :func:`~tocabi_torchrl.cuda_graphs.plan_graphs`).
    env_graph: bool = False
    #: The resumed run had already reached its budget: nothing was trained (see :func:`finished_result`).
    already_finished: bool = False
    #: The trained actor and critic (None when nothing was trained).
    agent: Agent | None = None
    #: The signal (``"SIGINT"``, ``"SIGTERM"``) that stopped the run early, after a checkpoint of its last iteration
    #: was saved; ``None`` when it ran to its budget (or ``max_minutes``).
    interrupted: str | None = None
    #: The run's env steps before this call (its resumed checkpoint's; 0 for a new run): ``env_steps`` minus this is
    #: what ``wall_seconds`` and ``env_steps_per_second`` measure.
    start_env_steps: int = 0


def budget_iterations(total_env_steps: int, frames_per_iteration: int) -> int:
    """PPO iterations of a budget of ``total_env_steps`` (the last one may run past it), at least one."""
    return max(1, -(-total_env_steps // frames_per_iteration))


def linear_lr(ppo, progress_remaining: float) -> float:
    """``ppo.lr_schedule == "linear"``'s rate: ``ppo.lr`` at the start (progress remaining 1), ``ppo.lr_end`` at 0."""
    return ppo.lr_end + (ppo.lr - ppo.lr_end) * progress_remaining


def schedule_change_note(state: dict, cfg: RunConfig, start_iter: int, frames_per_iteration: int) -> str | None:
    """What a resumed run's changed ``total_env_steps`` does to its schedules, or None: the scheduled action std and
    the linear learning rate follow the progress made through the budget, so a larger budget puts them back toward
    their start (a smaller one forward) at the next iteration."""
    saved = config_from_checkpoint(state)
    if saved.total_env_steps == cfg.total_env_steps:
        return None
    ppo, moves = cfg.ppo, []
    before, after = (1.0 - (start_iter + 1) / budget_iterations(total, frames_per_iteration)
                     for total in (saved.total_env_steps, cfg.total_env_steps))
    if ppo.std_mode == "scheduled":
        schedule = StdSchedule(ppo.std_start, ppo.std_end, ppo.std_hold)
        moves.append(("action std", schedule(before), schedule(after)))
    if ppo.lr_schedule == "linear":
        moves.append(("learning rate", *(linear_lr(ppo, min(max(p, 0.0), 1.0)) for p in (before, after))))
    moves = [f"{name} {a:.4g} -> {b:.4g}" for name, a, b in moves if not math.isclose(a, b, rel_tol=1e-6)]
    if not moves:
        return None
    return (f"note: total_env_steps {cfg.total_env_steps:,} (the run's was {saved.total_env_steps:,}) moves the "
            f"schedules, which follow the progress through the budget: at the next iteration {', '.join(moves)}")


def finished_result(run: RunFolder, cfg: RunConfig) -> TrainResult:
    """Say that the resumed run is already done, and return its result without training."""
    print(f"{run.resume_file}: the run is already finished (iteration {run.start_iteration}, "
          f"{run.start_env_steps:,} of {cfg.total_env_steps:,} env steps); nothing to train. Raise --total_env_steps "
          f"to train it further.", flush=True)
    return TrainResult(run.path, run.start_iteration, run.start_env_steps, 0.0, 0.0, {}, already_finished=True,
                       start_env_steps=run.start_env_steps)


#: The share of a rollout's frames left out of the update (rollout_guard) above which training warns: a fault that
#: breaks a frame now and then is absorbed; a reward term or controller that returns NaN breaks them all.
MASKED_WARNING = 0.01


def _episode_metrics(batch: TensorDictBase, dist_info: DistInfo | None = None,
                     masked_frac: torch.Tensor | None = None) -> dict[str, float]:
    """:func:`_episode_values` read on the host (one read), by name."""
    names, values = _episode_values(batch, dist_info, masked_frac)
    return dict(zip(names, values.cpu().tolist()))


def _episode_values(batch: TensorDictBase, dist_info: DistInfo | None = None,
                    masked_frac: torch.Tensor | None = None) -> tuple[list[str], torch.Tensor]:
    """Mean return and length of the episodes that ended in this batch, their count, and per-step means: their names
    and one (K,) float32 device tensor, for one host read per iteration. In a data-parallel run the episode values
    are over every rank's finished episodes (sums merged, then divided: a rank that finished more episodes weighs
    more) and ``episodes_finished`` is their total; the per-step means are averaged over the ranks (equal batch
    sizes, so that is exact). ``masked_frac``: the share of the rollout's frames
    :func:`~tocabi_torchrl.rl.rollout_guard.guard_rollout` left out of the update, a 0-d device tensor read with
    the rest. ``action_noise_z``: the mean of |action − loc| / scale over the rollout's finite action entries,
    √(2/π) ≈ 0.80 for the Gaussian's draws and 0 for a rollout that acted with its mean: the trace of a rollout that
    did not explore (a thread that changed tensordict's process-wide sampling mode mid-rollout did that)."""
    done = batch["next", "done"].squeeze(-1)
    sums = {"episodes_finished": done.sum()}
    if ("next", "episode_reward") in batch.keys(True):
        sums["episode_return"] = (batch["next", "episode_reward"].squeeze(-1) * done).sum()
    if ("next", "step_count") in batch.keys(True):
        sums["episode_length"] = (batch["next", "step_count"].squeeze(-1).float() * done).sum()
    means = {"terminated_frac": batch["next", "terminated"].float().mean(), "reward": batch["next", "reward"].mean()}
    if masked_frac is not None:
        means["masked_frac"] = masked_frac
    if {"action", "loc", "scale"} <= set(batch.keys()):
        z = ((batch["action"] - batch["loc"]) / batch["scale"]).abs()
        finite = torch.isfinite(z)
        means["action_noise_z"] = torch.where(finite, z, 0.0).sum() / finite.sum().clamp_min(1)
    if ("next", "reward_terms") in batch.keys(True):
        for key, value in batch["next", "reward_terms"].items():
            means[f"reward_terms/{key}"] = value.mean()
    as_f32 = lambda values: torch.stack([v.to(torch.float32) for v in values])  # noqa: E731
    summed, averaged = as_f32(sums.values()), as_f32(means.values())
    if dist_info is not None:
        all_reduce_sum(summed, dist_info)
        all_reduce_mean(averaged, dist_info)
    count = summed[0]
    # NaN when no episode ended (long episodes outlast an iteration), so plots skip the point.
    per_episode = torch.where(count > 0, summed[1:] / count.clamp_min(1), torch.nan)
    return [*sums, *means], torch.cat([count.unsqueeze(0), per_episode, averaged])


def make_collector(cfg: RunConfig, env: EnvBase, actor: torch.nn.Module, device: torch.device,
                   total_frames: int = -1) -> Collector:
    """The TorchRL collector of :func:`train`: ``cfg.frames_per_batch`` frames per batch, all on ``device``.

    The batch it yields is its own buffer, overwritten by the next rollout: consume it (or clone it) first.
    """
    return Collector(
        env,
        actor,
        frames_per_batch=cfg.frames_per_batch,
        total_frames=total_frames,
        device=device,
        storing_device=device,
        auto_register_policy_transforms=False,  # the env already has every transform the policy reads
        track_traj_ids=False,  # trajectory ids are unused here and cost a host read (done.any()) per step
        # Each batch is consumed before the next rollout starts: no defensive copy of the whole rollout.
        return_same_td=True,
        # Env, policy and storage share one device, so there is nothing to synchronise; this also keeps the collector
        # from moving the rollout (and, as its context outlives each yield, the update) to a side stream.
        no_cuda_sync=True,
    )


def make_optimizer(cfg: RunConfig, agent: Agent, device: torch.device) -> torch.optim.Adam:
    """Adam over the actor and critic (with the reference's separate value-head group when configured)."""
    if plan_graphs(cfg, device).update:
        return make_capturable_adam(_param_groups(agent, cfg), cfg.ppo.adam_eps, device)
    groups = _param_groups(agent, cfg)
    if _minibatch_kl(cfg):  # the rule sets the rate on the device: a tensor the fused step reads
        groups = [{**g, "lr": torch.tensor(float(g["lr"]), device=device)} for g in groups]
        return torch.optim.Adam(groups, eps=cfg.ppo.adam_eps, fused=True)
    # Fused Adam: one kernel per step for all parameters instead of a handful per tensor (the update is launch-bound).
    return torch.optim.Adam(groups, eps=cfg.ppo.adam_eps, fused=device.type == "cuda")


def _minibatch_kl(cfg: RunConfig) -> bool:
    """Whether the adaptive rule runs before every mini-batch step (``ppo.kl_adapt_every``)."""
    return cfg.ppo.lr_schedule == "adaptive" and cfg.ppo.kl_adapt_every == "minibatch"


def check_compile_toolchain(device: torch.device) -> None:
    """Refuse ``ppo.compile_loss`` where torch.compile cannot build the loss's kernels, before any env step: on a CPU
    it compiles C++ with the compiler inductor looks for (``$CXX``, else g++; clang++ on macOS), on a GPU it writes
    Triton kernels. Without them the first mini-batch step would fail minutes into the run with torch's own long
    trace. Windows (MSVC, found differently) is left to torch.

    >>> check_compile_toolchain(torch.device("meta"))  # neither a CPU nor a GPU: nothing is compiled for it
    """
    if device.type == "cuda":
        if importlib.util.find_spec("triton") is None:
            raise ValueError("ppo.compile_loss needs Triton on a GPU (torch.compile writes its kernels in it), and "
                             "it is not installed: pip install triton, or set ppo.compile_loss=false")
    elif device.type == "cpu" and sys.platform != "win32":
        compiler = os.environ.get("CXX") or ("clang++" if sys.platform == "darwin" else "g++")
        if shutil.which(compiler) is None:
            raise ValueError(f"ppo.compile_loss on the CPU needs a C++ compiler (torch.compile builds the loss's "
                             f"kernels with {compiler!r}, from $CXX or the default), and none was found on PATH: "
                             "install one (e.g. apt install g++) or set CXX to it, or set ppo.compile_loss=false")


def check_update_device(cfg: RunConfig, device: torch.device) -> None:
    """Refuse the update's compute options that ``device`` cannot run, naming the fix: ``ppo.update_dtype``
    bfloat16 on a GPU without bfloat16, ``ppo.compile_loss`` without its compiler (:func:`check_compile_toolchain`).
    :func:`train` checks before it opens the run folder, :func:`make_update_step` for its own callers."""
    if cfg.ppo.update_dtype == "bfloat16" and device.type == "cuda" and not torch.cuda.is_bf16_supported():
        raise ValueError(f"ppo.update_dtype bfloat16: {torch.cuda.get_device_name(device)} does not support bfloat16 "
                         "(it needs compute capability 8.0 or newer); set ppo.update_dtype=float32")
    if cfg.ppo.compile_loss:
        check_compile_toolchain(device)


def make_update_step(cfg: RunConfig, loss_module: ClipPPOLoss, optimizer: torch.optim.Optimizer,
                     device: torch.device, dist_info: DistInfo | None = None) -> MinibatchStep:
    """The mini-batch step of :func:`train` (a CUDA graph after a few eager steps when
    :func:`~tocabi_torchrl.cuda_graphs.plan_graphs` says so);
    in a data-parallel run its gradients are averaged over the ranks before clipping (``cfg.ppo.grad_sync``: one
    all-reduce inside the step, or DDP around the loss)."""
    check_update_device(cfg, device)
    params = [p for g in optimizer.param_groups for p in g["params"]]
    sync, step_loss = None, loss_module
    if dist_info is not None and dist_info.enabled:
        if cfg.ppo.grad_sync == "ddp":
            # The ranks' parameters are equal already (broadcast from rank 0). No buffer broadcast: the loss's buffers
            # (the assist's schedule and teacher) are set alike on every rank from the global step count and equal
            # weights, and the running observation statistics live in the env's transforms, synced on their own.
            ids = [device.index] if device.type == "cuda" else None
            # torch 2.13 renamed the option (and warns on the old name); older releases only know the old one.
            no_sync = ("forward_sync_buffers" if "forward_sync_buffers" in
                       inspect.signature(DistributedDataParallel).parameters else "broadcast_buffers")
            step_loss = DistributedDataParallel(loss_module, device_ids=ids, **{no_sync: False})
        else:
            sync = GradientAllReduce(dist_info)
    kl_rule = None
    if _minibatch_kl(cfg):
        kl_rule = MinibatchKLRule([g for g in optimizer.param_groups if not g.get("fixed")], cfg.ppo.desired_kl,
                                  cfg.ppo.lr_min, device)
    if cfg.ppo.compile_loss:
        # Static shapes: every mini-batch has the same size. The eager steps before the capture compile it; a
        # captured step replays the compiled kernels like any others.
        step_loss = torch.compile(step_loss, dynamic=False)
    return MinibatchStep(step_loss, optimizer, params, cfg.ppo.max_grad_norm,
                         use_graph=plan_graphs(cfg, device).update, grad_sync=sync, kl_rule=kl_rule,
                         autocast_dtype=AUTOCAST_DTYPES[cfg.ppo.update_dtype])


def decoupled_update(ppo: PPOConfig) -> bool:
    """Whether the PPO update is decoupled (``GuardedClipPPOLoss.use_proximal``): its ratio, clip and KL taken against
    the learner as each update starts, computed as the update computes it, and its surrogate weighted by that policy
    over the one that acted. So it is when the rollout acted with another policy (``ppo.overlap_update``: the one of
    the update before) or computed its policy in another dtype (``ppo.update_dtype`` bfloat16: the rollout's pass is
    float32, and bfloat16's rounding alone moved the PPO ratio of the shipped torque policy past the 0.2 clip on 30 %
    of its own walk's frames at std 0.1, 59 % at 0.05: ``docs/training/bf16_rounding.json``).

    >>> from tocabi_torchrl.config import PPOConfig
    >>> decoupled_update(PPOConfig()), decoupled_update(PPOConfig(update_dtype="bfloat16"))
    (False, True)
    """
    return ppo.overlap_update or ppo.update_dtype != "float32"


def make_loss(cfg: RunConfig, agent: Agent, env: EnvBase | None = None,
              ) -> tuple[ClipPPOLoss | SymmetryAugmentLoss | AssistAbsorbLoss, SyncFreeGAE]:
    """The clipped PPO loss (in :class:`~tocabi_torchrl.rl.symmetry.SymmetryAugmentLoss` with ``cfg.ppo.symmetry``
    "augment", which needs the training ``env`` for its layout and normaliser; then in :class:`AssistAbsorbLoss` when
    ``cfg.ppo.torque_assist`` > 0) and the GAE value estimator of :func:`train`."""
    # The critic runs over the rollout in chunks of ~64k frames (along the env dim): unchunked, TorchRL stacks
    # observations and next observations and keeps (2 · frames, 400) activations, ~6 GB at 16384 envs.
    # gamma and lambda are made on the critic's device, where train() collects the rollout: GAE would otherwise copy
    # them to the rewards' device on its first call, a blocking host-to-device copy inside the first iteration.
    ppo = cfg.ppo
    advantage = SyncFreeGAE(gamma=ppo.gamma, lmbda=ppo.gae_lambda, value_network=agent.critic, average_gae=False,
                            value_chunk_size=_VALUE_CHUNK_FRAMES // ppo.steps_per_env or 1,
                            device=next(iter(agent.critic.parameters()), torch.empty(0)).device)
    loss_module = GuardedClipPPOLoss(
        agent.actor,
        agent.critic,
        clip_epsilon=ppo.clip_epsilon,
        entropy_bonus=ppo.entropy_coef > 0,
        entropy_coeff=ppo.entropy_coef if ppo.entropy_coef > 0 else None,
        critic_coeff=ppo.value_coef,
        loss_critic_type=ppo.value_loss,
        normalize_advantage=True,
    )
    loss_module.set_keys(sample_log_prob="action_log_prob")
    loss_module.loss_mask_key = VALID_KEY  # see rollout_guard: broken frames add nothing to the losses
    if decoupled_update(ppo):
        # Its rollouts act with the policy of one update before, or the update computes it in another dtype: ratio,
        # clip and KL from the policy each update starts from, as the update computes it, the surrogate weighted by
        # that policy over the one that acted (rollout_guard).
        loss_module.use_proximal(PROXIMAL_KEY)
    if ppo.symmetry == "augment":
        if env is None:
            raise ValueError("ppo.symmetry='augment' mirrors the policy input by the env's layout and normaliser: "
                             "pass the training env to make_loss")
        # Inside the assist's loss: its absorbing term copies the teacher on the rollout's own frames only.
        loss_module = make_symmetry_loss(loss_module, env, cfg.transforms.transform_config(),
                                         gaussian_head(agent.actor), ppo.symmetry_loss)
    if cfg.ppo.torque_assist > 0:
        loss_module = AssistAbsorbLoss(loss_module, gaussian_head(agent.actor), robot.LEG_TORQUE_LIMITS,
                                       teacher=agent.teacher)
    return loss_module, advantage


@contextlib.contextmanager
def float32_matmul_precision(precision: str):
    """torch's float32 matrix-product precision set to ``precision`` inside the block and restored after it (the
    setting is process-wide; a captured CUDA graph keeps the kernels chosen when it was captured)."""
    before = torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision(precision)
    try:
        yield
    finally:
        torch.set_float32_matmul_precision(before)


class _Progress(StopFlag):
    """The stop flag :func:`train` hands to the signal handlers, and whether the run folder has been written yet."""

    def __init__(self) -> None:
        super().__init__()
        self.started = False
        #: The run folder :func:`_train` opened (its claim is let go when :func:`train` returns).
        self.run: RunFolder | None = None
        #: The env :func:`_train` built itself (None when the caller gave one): closed when :func:`train` returns.
        self.built_env: EnvBase | None = None


#: A repeated signal within this many seconds of the first is the same request (:func:`~.interrupt.stop_on_signals`):
#: torchrun forwards the Ctrl-C that its workers also get from the terminal.
_REPEAT_GRACE_S = 1.0


def _repeat_grace_s(info: DistInfo) -> float:
    """The grace of :data:`_REPEAT_GRACE_S` for a data-parallel rank, none for one process: without torchrun no copy
    of a Ctrl-C comes, and a second one is the user's, who was told it stops at once."""
    return _REPEAT_GRACE_S if info.enabled else 0.0


def raised_before_training(err: BaseException) -> bool:
    """Whether :func:`train` raised ``err`` while it set the run up, before it wrote the run folder (a value the
    config's checks let through but the env or the networks refuse): the recipe reports it as one ``error:`` line."""
    return bool(getattr(err, "raised_before_training", False))


def train(cfg: RunConfig, env: EnvBase | None = None, run: RunFolder | None = None,
          dist_info: DistInfo | None = None) -> TrainResult:
    """Run PPO as configured; returns where the run was written and its throughput. ``run``: the run folder
    :func:`~tocabi_torchrl.rl.run_dir.open_run` already opened for ``cfg`` (the recipe checks it before it starts),
    so a resumed checkpoint is not read twice.

    Data-parallel (``torchrun --nproc_per_node K``, read from the environment unless ``dist_info`` is given): every
    rank trains ``cfg.env.num_envs`` worlds of its own (seed ``cfg.seed + rank``) on its own device, gradients, losses
    and running observation statistics are averaged over the ranks (:mod:`~tocabi_torchrl.rl.distributed`), an
    iteration is K rollouts (``cfg.total_env_steps`` counts all ranks' steps), and rank 0 alone logs and writes
    checkpoints. A run resumes on any K: its progress (schedules, budget) is derived from the env steps done,
    and its files and metrics rows go on numbering from the checkpoint's iteration.

    Ctrl-C (SIGINT) or SIGTERM (:mod:`~tocabi_torchrl.rl.interrupt`; handlers installed for the call and restored
    after it, main thread only): the iteration in progress finishes its update, a checkpoint of it is saved (with the
    usual retention), and the result's ``interrupted`` names the signal; a second signal raises ``KeyboardInterrupt``
    at once. Data-parallel ranks agree at each iteration's end whether any of them was asked to stop (one small
    all-reduce per iteration), so they all stop at the same iteration.
    """
    cfg.validate(allow_unused=bool(cfg.resume))  # a resumed run's saved options are checked against the checkpoint's
    info = dist_info if dist_info is not None else from_environment()
    progress = _Progress()
    try:
        with float32_matmul_precision(cfg.ppo.matmul_precision), \
                stop_on_signals(progress, "stopping after this iteration's update to save a checkpoint",
                                repeat_grace_s=_repeat_grace_s(info)):
            return _train(cfg, env, run, info, progress)
    except ValueError as err:
        if not progress.started:
            err.raised_before_training = True
        raise
    finally:  # the run has ended: another may write into its folder (it refuses a run that is there)
        for folder in (run, progress.run):
            if folder is not None:
                folder.release()
        if progress.built_env is not None:
            # Nothing returned holds it; on the CPU backend its worker threads would outlive the call otherwise (a
            # notebook training twice kept both envs' threads), failed starts included.
            progress.built_env.close(raise_if_closed=False)


def _train(cfg: RunConfig, env: EnvBase | None, run: RunFolder | None, info: DistInfo,
           progress: _Progress) -> TrainResult:
    if info.enabled and cfg.seed + info.world_size - 1 > MAX_SEED:
        raise ValueError(f"seed {cfg.seed}: rank r of a data-parallel run seeds its worlds with seed + r, which must "
                         f"stay <= {MAX_SEED} (2**63 - 1) on all {info.world_size} ranks; give a seed of at most "
                         f"{MAX_SEED - info.world_size + 1}")
    if _minibatch_kl(cfg) and info.enabled:
        raise ValueError(f"ppo.kl_adapt_every='minibatch' sets each rank's rate from its own mini-batch's KL, so the "
                         f"ranks' rates would part; this run has {info.world_size} ranks: train it on one GPU, or "
                         "set ppo.kl_adapt_every=iteration")
    if cfg.ppo.overlap_update and info.enabled:
        raise ValueError(f"ppo.overlap_update runs on one rank; this run has {info.world_size}: set "
                         "ppo.overlap_update=false for a data-parallel run")
    device = init_distributed(info, resolve_device(cfg.device))
    check_update_device(cfg, device)  # before the run folder exists
    if run is None:
        # Rank 0 checks the loggers and the folder (refusing to overwrite an earlier run); the others write nothing and
        # only read the resumed checkpoint. Every rank learns whether rank 0 may go on, so none waits in a collective.
        error = None
        try:
            if info.is_main:
                require_loggers(cfg.loggers)
            run = progress.run = open_run(cfg, writer=info.is_main)
        except Exception as err:  # noqa: BLE001 - re-raised below, after the ranks agreed to stop
            error = err
        if not agree(error is None, info, device):
            raise error if error is not None else RuntimeError("another rank could not open the run; see its error")
    frames_per_iteration = cfg.frames_per_batch * info.world_size
    iterations = budget_iterations(cfg.total_env_steps, frames_per_iteration)
    if run.start_env_steps // frames_per_iteration >= iterations:
        return finished_result(run, cfg)
    if info.is_main and (warning := schedule_warning(cfg)):
        # Not refused: a run trained in segments raises total_env_steps as it resumes (config.schedule_past_budget).
        warnings.warn(warning, UserWarning, stacklevel=3)
    torch.manual_seed(cfg.seed)
    if info.enabled:  # each rank its own worlds; rank 0 keeps the 1-rank run's seed (and so its worlds)
        cfg = dataclasses.replace(cfg, seed=rank_seed(cfg.seed, info))
    if env is not None:
        check_given_env(cfg, env)
    if env is None:
        env = progress.built_env = build_env(cfg, device, for_training=True)
    obs_dim = env.observation_spec["observation"].shape[-1]
    act_dim = env.action_spec.shape[-1]
    agent = build_agent(cfg, obs_dim, act_dim, device)
    optimizer = make_optimizer(cfg, agent, device)
    run_dir = run.path
    # Progress (schedules, budget) counts iterations of this rank count: the env steps done, as iterations of it.
    start_iter, env_steps, prior_train_s = run.start_env_steps // frames_per_iteration, run.start_env_steps, 0.0
    # Files and metrics go on numbering from the checkpoint's own iteration: on another rank count the same env steps
    # are another number of iterations, and numbering from those would overwrite the run's earlier iteration files
    # and repeat its metrics rows. ``it + shift`` is the iteration a file or row is written under.
    shift = (int(run.resume_state["iteration"]) if run.resume_state is not None else 0) - start_iter
    if run.resume_state is not None:
        mode = optimizer_mode(optimizer)  # the checkpoint may come from another update mode or device
        apply_checkpoint(run.resume_state, agent, optimizer, env, run.resume_file)
        restore_optimizer_mode(optimizer, mode)
        prior_train_s = float(run.resume_state.get("train_seconds", 0.0))
        if info.is_main:
            print(f"resumed from {run.resume_file} at iteration {start_iter + shift} ({env_steps:,} env steps)")
            note = schedule_change_note(run.resume_state, cfg, start_iter, frames_per_iteration)
            if note:
                print(note, flush=True)
    stats_sync = None
    if info.enabled:
        broadcast_module(agent.actor, info)
        broadcast_module(agent.critic, info)
        stats_sync = RunningStatsSync(getattr(env, "transform", []), info)
        torch.manual_seed(cfg.seed)  # this rank's seed (set above): its own exploration noise and mini-batch order

    ppo = cfg.ppo
    loss_module, advantage = make_loss(cfg, agent, env)
    # The symmetry loss whose mirror follows a running normaliser's statistics (fixed ones never move: make_loss set
    # them); None without symmetry or with fixed statistics.
    running_mirror = next((m for m in loss_module.modules() if isinstance(m, SymmetryAugmentLoss)), None)
    # An equivariant actor's mirror takes the normaliser's statistics now (a resumed run's, loaded above) and, with a
    # running normaliser, before each update; the teacher copies them with its weights when it is taken.
    equivariant = set_equivariant_statistics(agent.actor, env)
    running = isinstance(find_normalization(env), RunningNormalization)
    if not running:
        running_mirror = None
    update_step = make_update_step(cfg, loss_module, optimizer, device, info)
    assist = assist_schedule(cfg, env)
    if assist is not None:
        env.base_env.set_torque_assist(assist(env_steps))
    pushes = getattr(env.base_env, "pushes", None) is not None
    if pushes:
        env.base_env.set_push_scale(push_scale(ppo.push_ramp, env_steps))
    # One host read at start-up; from then on the trainer knows when it takes the teacher.
    teacher_taken = agent.teacher is not None and bool(agent.teacher.anchored)

    # Each update's losses are read once the next rollout is queued, so that no read between two rollouts waits for
    # the GPU's queue. With ppo.overlap_update the update itself runs beside that rollout, on a side stream, and the
    # collector acts with a copy of the actor taken before each update (rl/overlap.py).
    overlap = UpdateOverlap(device, agent.actor, side_stream=ppo.overlap_update)
    policy = overlap.collect_actor
    # The live viewer (rank 0): a policy that also ticks its pose stream, a host copy off the training stream.
    live = _live_view(cfg, env) if cfg.viewer.enabled and info.is_main else None
    collector = None
    try:
        collector = make_collector(cfg, env, policy if live is None else live.wrap(policy), device,
                                   (iterations - start_iter) * cfg.frames_per_batch)
        progress.started = True  # the logger writes config.json: from here on the run folder holds the run
        logger = (RunLogger(run_dir, cfg, total_iterations=iterations + shift, start_iteration=start_iter + shift)
                  if info.is_main else None)
    except BaseException:
        # The loop's finally below is not reached yet: without this a failed start (a logger that cannot open,
        # Ctrl-C while the collector is built) left the page served and its drawing thread running.
        if collector is not None:
            collector.shutdown()
        if live is not None:
            live.close()
        raise
    lr = get_lr(optimizer.param_groups[0])
    t_start = time.perf_counter()
    metrics: dict = {}
    it = start_iter
    mark_s = 60.0 * cfg.checkpoint_minutes
    next_mark = (int(prior_train_s // mark_s) + 1) * mark_s if mark_s else float("inf")
    warned_masked = False
    episodes = DeferredRead()  # the logged episode metrics, one iteration's at a time

    def settle(stats: dict[str, float], ctx: dict) -> None:
        """What needs an update's losses (``stats``, by log name): the adaptive learning rate for the next update,
        and the iteration's log row. Once the next rollout has been queued (or before a checkpoint, a stop or the
        end); ``ctx``: what the iteration knew without them."""
        nonlocal lr, metrics, warned_masked
        stats = {**stats, **ctx["extra"]}
        std = stats.pop("action_std")  # read with the losses (_update_stats)
        # While the assist fades, the KL also measures the intended move to the next β's actions; the adaptive
        # rule would read it as too large a step and starve the absorption (the LR fell to 1e-5 on the H100 and
        # the gait broke), so the learning rate is held there (and, with assist_lr_hold "pull", while the
        # teacher's pull decays after the fade: the same reading of an intended move).
        if update_step.kl_rule is not None:  # the rule ran before each mini-batch step, on the device
            lr = stats.pop("lr")
        elif ppo.lr_schedule == "adaptive" and not ctx["fading"]:
            lr = adapt_lr(lr, stats["kl"], ppo.desired_kl, ppo.lr_min)
            _set_scheduled_lr(optimizer, lr)
        if ctx["episode"] is None:
            return
        # Copied to the host when the rollout ended, read here, an iteration later.
        episode = dict(zip(ctx["episode"], episodes.values(), strict=True))
        if episode["masked_frac"] > MASKED_WARNING and info.is_main and not warned_masked:  # a broken term stays broken
            warned_masked = True
            print_line(f"warning: {100 * episode['masked_frac']:.1f} % of iteration {ctx['row']}'s frames were left "
                       "out of the update: a NaN or inf observation, reward or action (a reward term, controller or "
                       "env of your own?); metrics column masked_frac follows it")
        metrics = {**episode, **stats}
        metrics.update(lr=lr, action_std=std, **ctx["progress"])
        if logger is not None:
            logger.log(ctx["row"], metrics)
        if live is not None:
            live.publish(ctx["row"], metrics)

    streams = contextlib.ExitStack()  # the rollouts on the overlap's high-priority stream, if it has one
    streams.enter_context(overlap.collecting())
    try:
        for it, batch in enumerate(collector, start=start_iter + 1):
            t_collect = time.perf_counter()
            if overlap.in_flight:  # the previous update, queued before this rollout (or run beside it)
                settle(*_finished(overlap, update_step))
            env_steps += batch.numel() * info.world_size
            progress_remaining = 1.0 - it / iterations
            if stats_sync is not None:
                stats_sync.sync()  # before the update: every rank's next rollout normalises alike
            if running_mirror is not None:  # the mirror of a normalised input uses the rollout's last statistics
                refresh_statistics(running_mirror, env)
            if equivariant and running:
                set_equivariant_statistics(agent.actor, env)
            # The collector reuses `batch` as its buffer (return_same_td): GAE's outputs go to a shallow copy.
            work = batch.clone(False)
            masked = (~guard_rollout(work)).float().mean()  # frames with NaN/inf or impossible actions: out of the loss
            estimate_advantages(advantage, work)
            # Only what the loss reads: the rollout also holds every env signal, which each mini-batch would gather.
            flat = _update_rows(loss_module, work)
            if ppo.overlap_update:
                # The update reads it on the side stream while the collector refills `batch`: its own memory, the
                # step's, from which a captured step gathers each mini-batch inside its graph (MinibatchStep.keep).
                flat = update_step.keep(flat)
            extra: dict[str, float] = {}
            if assist is not None:
                # This rollout ran with β(steps before it); the next runs with β(now): the update absorbs the gap.
                beta, beta_next = assist(env_steps - batch.numel() * info.world_size), assist(env_steps)
                base = env.base_env
                if agent.teacher is None:
                    weight = ppo.assist_absorb if beta_next < beta else 0.0
                else:
                    if beta_next < beta and not teacher_taken:
                        # The policy that walks with the full assist, as it is when the fade begins.
                        agent.teacher.anchor(gaussian_head(agent.actor).mean_net, base.assist_gain(beta), beta)
                        teacher_taken = True
                    weight = ppo.assist_absorb * assist.teacher_weight(env_steps) if teacher_taken else 0.0
                loss_module.set_step(base.assist_gain(beta), base.assist_gain(beta_next), beta, beta_next, weight)
            # The reference (spec §10.2, §10.4) sets the linear learning rate and the scheduled std from the progress
            # made after each rollout and before its update, so the update runs with them, and so does the next
            # rollout. The adaptive rate, which reads this update's KL, is set after it (settle).
            if ppo.lr_schedule == "linear":
                lr = linear_lr(ppo, progress_remaining)
                _set_scheduled_lr(optimizer, lr)
            if agent.std_schedule is not None:
                set_action_std(agent.actor, agent.std_schedule(progress_remaining))
            fading = False
            if assist is not None:
                extra["torque_assist"] = beta  # the β this iteration's rollout (and its logged rewards) ran with
                extra["absorb_weight"] = weight
                fading = beta_next < beta or (ppo.assist_lr_hold == "pull" and weight > 0)
                if fading and ppo.lr_schedule == "adaptive" and 0 < ppo.assist_lr_max < lr:
                    # Held from here on, so bounded before this update (ppo.assist_lr_max).
                    lr = ppo.assist_lr_max
                    _set_scheduled_lr(optimizer, lr)
            if update_step.kl_rule is not None:  # held while β fades (and the pull decays), as the host rule is
                update_step.kl_rule.set_enabled(not fading)
                update_step.kl_rule.start_update()
            if ppo.overlap_update:
                overlap.refresh()  # the next rollout acts with the learner as it is before this update
            # Drawn here, on this thread, whether or not the update is queued from a thread of its own: the
            # collector's draws (the exploration noise) then come in one order, run after run.
            order = _minibatch_order(cfg, flat)
            # On its side stream the update reads `flat` and `order` while the next rollout is collected: kept until
            # it is done. On the training stream the stream's order protects them: nothing is kept.
            # Bound now (a lambda would look `flat` up when the thread runs it, after the `del` below).
            # A decoupled update first stores the proximal log-probabilities (with the overlap, on its own stream).
            overlap.launch(functools.partial(_update_stats, cfg, flat, update_step, agent.actor, info, order,
                                             loss_module if decoupled_update(ppo) else None),
                           keep=(flat, order) if ppo.overlap_update else None,
                           threaded=ppo.overlap_update and update_step.replays(rows=True) and not _env_capturing(env))
            del work, flat, order
            if assist is not None:
                env.base_env.set_torque_assist(beta_next)
            if pushes:
                extra["push_scale"] = push_scale(ppo.push_ramp, env_steps - batch.numel() * info.world_size)
                env.base_env.set_push_scale(push_scale(ppo.push_ramp, env_steps))
            if not ppo.overlap_update:
                collector.update_policy_weights_()
            elapsed = time.perf_counter() - t_start
            train_s = prior_train_s + elapsed
            logged = (it + shift) % cfg.log_every == 0 or it == iterations
            names = None
            if logged:  # computed now (the collector overwrites `batch` with the next rollout), read in settle
                names, values = _episode_values(batch, info, masked)
                episodes.start(values)
            context = {"extra": extra, "fading": fading, "row": it + shift, "episode": names,
                       "progress": dict(env_steps=env_steps,
                                        env_steps_per_s=(env_steps - run.start_env_steps) / elapsed,
                                        update_s=time.perf_counter() - t_collect, wall_s=elapsed, train_s=train_s)}
            mark_due = train_s >= next_mark
            saved = (it + shift) % cfg.checkpoint_every == 0 or it == iterations
            overlap.annotate(context)
            if mark_due or saved:  # a checkpoint holds the learner after this update, and the rate after it
                settle(*_finished(overlap, update_step))
            # Checkpoints hold rank 0's state, which every rank shares (parameters, optimiser, statistics).
            if mark_due:
                if info.is_main:
                    save_checkpoint(run_dir, it + shift, env_steps, agent, optimizer, env, cfg, train_s,
                                    tag=wall_tag(next_mark))
                next_mark = (int(train_s // mark_s) + 1) * mark_s
            if saved and info.is_main:
                save_checkpoint(run_dir, it + shift, env_steps, agent, optimizer, env, cfg, train_s)
            # Ranks' clocks differ and a signal may reach one rank only: stop when any rank's time is up or any was
            # asked to stop, all at the same iteration (a rank that left early would hang the others' collectives).
            time_up, stop_signal = _stop_requests(bool(cfg.max_minutes) and elapsed > 60.0 * cfg.max_minutes,
                                                  progress.stop_signal, info, device)
            if time_up or stop_signal is not None:
                if overlap.in_flight:  # the checkpoint below holds the learner after it
                    settle(*_finished(overlap, update_step))
                progress.stop_signal = progress.stop_signal or stop_signal
                if info.is_main:
                    if stop_signal is None:  # a signal was said when it came, and the caller says what it left
                        print_line(f"stopping after {cfg.max_minutes} min (max_minutes)")
                    if not saved:
                        save_checkpoint(run_dir, it + shift, env_steps, agent, optimizer, env, cfg, train_s)
                break
        if overlap.in_flight:  # the collector ran out: the last update's row
            settle(*_finished(overlap, update_step))
    finally:
        # Last, whatever fails before it: what follows on the caller's stream (an evaluation, a save) waits for the
        # last rollout, and the caller's thread is back on its own stream.
        with streams:
            env_graph = bool(getattr(env, "graph_captured", False))
            if overlap.in_flight:  # an error: let the update end before anything is freed, and log its row
                with contextlib.suppress(Exception):  # the error that got here is the one to report
                    settle(*_finished(overlap, update_step))
                if overlap.in_flight:  # the row could not be written: the wait alone
                    with contextlib.suppress(Exception):
                        overlap.finish()
            collector.shutdown()
            if logger is not None:
                logger.close()
            if live is not None:
                live.close()
    wall = time.perf_counter() - t_start
    done_steps = env_steps - run.start_env_steps
    return TrainResult(run_dir, it + shift, env_steps, wall, done_steps / max(wall, 1e-9), metrics, env_graph,
                       agent=agent, interrupted=progress.stop_signal, start_env_steps=run.start_env_steps)


def _live_view(cfg: RunConfig, env: EnvBase):
    """The training's live page (``cfg.viewer``; needs the ``viewer`` extra, whose absence the recipe reports before
    the run starts)."""
    from ..viewer.training import TrainingView

    return TrainingView(cfg.viewer, env.base_env.sim)


def _stop_requests(time_up: bool, stop_signal: str | None, info: DistInfo,
                   device: torch.device) -> tuple[bool, str | None]:
    """Whether any rank's ``max_minutes`` are up, and the stop signal any rank got (the highest-numbered one), from
    this rank's own: one all-reduce of two ints in a data-parallel run, at the iteration's end (its read waits for
    the work queued before it, the update included: a data-parallel iteration's one wait); nothing is exchanged with
    one rank."""
    signum = int(signal.Signals[stop_signal]) if stop_signal is not None else 0
    if info.enabled:
        flags = torch.tensor([int(time_up), signum], dtype=torch.int32, device=device)
        dist.all_reduce(flags, op=dist.ReduceOp.MAX)
        up, signum = flags.tolist()
        time_up = bool(up)
    return time_up, (signal.Signals(signum).name if signum else None)


#: Frames per network call over a whole rollout (bounds its activation memory): the critic in GAE, the actor in
#: _fill_proximal.
_VALUE_CHUNK_FRAMES = 65536


def assist_schedule(cfg: RunConfig, env: EnvBase) -> AssistSchedule | None:
    """β of the torque assist against env steps (geometric in the env's action gain), or None without an assist."""
    ppo = cfg.ppo
    if ppo.torque_assist <= 0:
        return None
    base = env.base_env
    # One host read at start-up: the geometric mean over the legs of c(1)/c(0).
    ratio = float((base.assist_gain(1.0) / base.assist_gain(0.0)).log().mean().exp())
    return AssistSchedule(ppo.torque_assist, ppo.assist_fade_start, ppo.assist_fade_end, max(ratio, 1.0),
                          anchor_decay=ppo.assist_anchor_decay)


def push_scale(ramp: tuple[int, int], env_steps: int) -> float:
    """The pushes' strength in [0, 1] after ``env_steps``: 0 before ``ramp[0]``, linear to 1 at ``ramp[1]``."""
    start, full = ramp
    if env_steps >= full:
        return 1.0
    if full <= start:  # a step at ``start`` rather than a ramp
        return 0.0
    return max(0.0, (env_steps - start) / (full - start))


def _set_scheduled_lr(optimizer: torch.optim.Optimizer, lr: float) -> None:
    """Set ``lr`` on every parameter group but the ``fixed`` ones (the reference's constant value-head rate)."""
    for group in optimizer.param_groups:
        if not group.get("fixed"):
            set_lr(group, lr)


def estimate_advantages(estimator: SyncFreeGAE, batch: TensorDictBase) -> None:
    """GAE's ``advantage`` and ``value_target`` into a guarded rollout ``batch`` (no gradients), and the guard's
    mask where ClipPPOLoss's advantage normalisation reads it (:data:`NORM_MASK_KEY`), not from the loss mask: without
    it a masked frame's advantage still moved each mini-batch's mean and std. Set after GAE, which reads that key as
    its own (shifted estimation) mask."""
    with torch.no_grad():
        estimator(batch)
    batch.set(NORM_MASK_KEY, batch.get(VALID_KEY))


#: The next step's outcome, which a PPO loss lists among its inputs for its value estimator alone.
_ESTIMATOR_OUTCOME = ("reward", "done", "terminated", "truncated")


def _loss_keys(loss_module: ClipPPOLoss | AssistAbsorbLoss, batch: TensorDictBase) -> list:
    """The keys of ``batch`` the update reads: the loss's inputs, the return estimates and the masks. With GAE's
    advantage and value target in the batch, TorchRL's PPO loss never runs its value estimator, so what it lists for
    that alone is left out: the next step's outcome and the next step's network inputs (``("next", "observation")``
    is as wide as the observation, and every mini-batch step would gather it). The rule goes by name: a ``"next"``
    key is left out when it is the next version of an input the batch keeps (``("next", "observation")``) or the
    next step's outcome (reward, done, terminated, truncated); others stay (the torque assist's
    ``("next", "leg_assist")``), so a loss term that reads the next observation itself needs its own key."""
    present = set(batch.keys(True, True))
    wanted = {*loss_module.in_keys, "advantage", "value_target", "state_value", VALID_KEY, NORM_MASK_KEY}
    if {"advantage", "value_target"} <= present:
        inputs = {k for k in wanted if not (isinstance(k, tuple) and k[0] == "next")}
        wanted = {k for k in wanted if not (isinstance(k, tuple) and len(k) == 2 and k[0] == "next"
                                            and (k[1] in inputs or k[1] in _ESTIMATOR_OUTCOME))}
    return [k for k in wanted if k in present]


def _update_rows(loss_module: torch.nn.Module, work: TensorDictBase) -> TensorDictBase:
    """The rollout ``work`` (num_envs, T), its advantages estimated, as the update reads it: the loss's keys
    (:func:`_loss_keys`) as (num_envs * T,) rows, and for a decoupled loss (``use_proximal``) its
    :data:`PROXIMAL_KEY` entry, the behaviour log-probabilities until :func:`_fill_proximal` overwrites them."""
    if PROXIMAL_KEY in loss_module.in_keys:
        work.set(PROXIMAL_KEY, work.get("action_log_prob").clone())
    return work.select(*_loss_keys(loss_module, work)).reshape(-1)


def _fill_proximal(loss_module: torch.nn.Module, flat: TensorDictBase, autocast_dtype: torch.dtype | None = None,
                   ) -> None:
    """Write each frame's log-probability (n,) of its action under the learner as this update starts (its std
    schedule set) into ``flat``'s :data:`PROXIMAL_KEY`, in place, without gradients, :data:`_VALUE_CHUNK_FRAMES`
    frames at a time: the proximal policy of the decoupled update (``GuardedClipPPOLoss.use_proximal``). No random
    draw, no autograd, no host read, and no TensorDict module: it may be queued from the update's own host thread
    (``UpdateOverlap.launch``) while the collector acts on this one. The actor's own ``get_dist`` would set and
    restore tensordict's sampling mode, one setting for the whole process: from that thread it raced the rollout, and
    left some rollouts acting with the mean action, without exploration (two pd-preset runs, whose logged
    torque-change reward jumped between two levels from one logged iteration to the next). The learner's
    :class:`~.actors.GaussianHead` computes it directly (:func:`~.actors.gaussian_log_prob`), with the parameters
    the loss trains, autocast to ``autocast_dtype`` as the update's passes are (``ppo.update_dtype``), so that the
    update's ratios start from 1 and not from bfloat16's rounding."""
    ppo = next((m for m in loss_module.modules() if isinstance(m, GuardedClipPPOLoss)), None)
    if ppo is None or ppo.proximal_key != PROXIMAL_KEY:
        raise ValueError("_fill_proximal needs a loss whose GuardedClipPPOLoss reads the proximal log-probabilities "
                         "(use_proximal, set by make_loss for a decoupled_update)")
    head = gaussian_head(ppo.actor_network)
    (obs_key,) = ppo.actor_network.in_keys  # make_actor's actor reads one entry
    obs, action, out = flat.get(obs_key), flat.get(ppo.tensor_keys.action), flat.get(PROXIMAL_KEY)
    with torch.no_grad(), update_autocast(autocast_dtype, obs.device):
        for start in range(0, flat.shape[0], _VALUE_CHUNK_FRAMES):
            rows = slice(start, start + _VALUE_CHUNK_FRAMES)
            out[rows].copy_(gaussian_log_prob(head, obs[rows], action[rows]).reshape(-1))


def _env_capturing(env) -> bool:
    """Whether the env step is still to be captured as a CUDA graph (its warm-up and capture, on this thread, must not
    meet an update queued from another). Checked at each launch: a setting that drops the capture later
    (``invalidate_graph``: a seed, randomised worlds, the assist's sensed joints) must not change while an update is
    in flight, as none does inside the training loop."""
    return bool(getattr(env, "cuda_graph", False)) and not bool(getattr(env, "graph_captured", False))


def _finished(overlap: UpdateOverlap, step: MinibatchStep) -> tuple[dict[str, float], dict]:
    """The in-flight update's :func:`_update_stats` by log name and its context, once it is done (a host wait for
    that update alone)."""
    values, context = overlap.finish()
    return dict(zip(_stat_names(step, with_actor=True), values, strict=True)), context


def _update(cfg: RunConfig, flat: TensorDictBase, step: MinibatchStep, dist_info: DistInfo | None = None,
            actor: ProbabilisticActor | None = None, proximal_loss: torch.nn.Module | None = None,
            ) -> dict[str, float]:
    """:func:`_update_stats` read on the host at once, by log name: one update as a single call (the trainer itself
    reads an update's numbers once the next rollout is queued, through :class:`UpdateOverlap`). A decoupled update
    (:func:`decoupled_update`) takes its loss module as ``proximal_loss``, and ``flat`` its :data:`PROXIMAL_KEY`."""
    # First: the step's losses name themselves.
    values = _update_stats(cfg, flat, step, actor, dist_info, proximal_loss=proximal_loss).tolist()
    return dict(zip(_stat_names(step, with_actor=actor is not None), values, strict=True))


def _update_stats(cfg: RunConfig, flat: TensorDictBase, step: MinibatchStep, actor: ProbabilisticActor | None = None,
                  dist_info: DistInfo | None = None, order: list[torch.Tensor] | None = None,
                  proximal_loss: torch.nn.Module | None = None) -> torch.Tensor:
    """The update (:func:`_update_losses`) and, given the ``actor``, what the trainer reads with its losses, as one
    float64 device tensor named by :func:`_stat_names`: the actor's mean std after it (the logged ``action_std``) and,
    with ``ppo.kl_adapt_every`` "minibatch", the learning rate the device-side rule left. One host read takes them
    all; float64 keeps each value as a read of its own would give it. Given the loss module as ``proximal_loss``
    (a decoupled update, ``ppo.overlap_update``), it first fills ``flat``'s proximal log-probabilities
    (:func:`_fill_proximal`), wherever the update runs: beside the next rollout, on the update's stream."""
    if proximal_loss is not None:
        _fill_proximal(proximal_loss, flat, step.autocast_dtype)
    losses = _update_losses(cfg, flat, step, dist_info, order).to(torch.float64)
    if actor is None:
        return losses
    after = [action_std(actor).mean()]
    if step.kl_rule is not None:
        after.append(torch.as_tensor(step.kl_rule.groups[0]["lr"], device=losses.device))
    return torch.cat([losses, torch.stack([v.to(torch.float64) for v in after])])


def _stat_names(step: MinibatchStep, with_actor: bool) -> list[str]:
    """The log names of :func:`_update_stats`' values (the step's losses are known once it has run)."""
    extra = ("action_std", *(("lr",) if step.kl_rule is not None else ())) if with_actor else ()
    return [*(_STAT_NAMES.get(k, k) for k in step.stat_keys), *extra]


def _minibatch_order(cfg: RunConfig, flat: TensorDictBase) -> list[torch.Tensor]:
    """The update's row order: one random permutation of the rollout's ``n`` rows per epoch, ``(n,)`` int64 each,
    on the rollout's device (queued on the current stream)."""
    return [torch.randperm(flat.shape[0], device=flat.device) for _ in range(cfg.ppo.epochs)]


def _update_losses(cfg: RunConfig, flat: TensorDictBase, step: MinibatchStep, dist_info: DistInfo | None = None,
                   order: list[torch.Tensor] | None = None) -> torch.Tensor:
    """``epochs`` passes of shuffled mini-batches over the rollout, each in its permutation of ``order`` (drawn here
    when None: :func:`_minibatch_order`). Returns the mean losses and KL (``step.stat_keys``) as a device tensor (no
    host read), averaged over the ranks in a data-parallel run, so that every rank adapts its learning rate alike."""
    n, mb, epochs = flat.shape[0], cfg.ppo.minibatch_size, cfg.ppo.epochs
    num_mb = max(1, n // mb)
    kept = flat is step.rows  # the step gathers its mini-batches itself (MinibatchStep.keep)
    sums = None
    for perm in _minibatch_order(cfg, flat) if order is None else order:
        for k in range(num_mb):
            idx = perm[k * mb : (k + 1) * mb]
            stats = step.on_rows(idx) if kept else step(flat[idx])
            sums = stats.clone() if sums is None else sums.add_(stats)
    mean = sums / (epochs * num_mb)
    if dist_info is not None:
        all_reduce_mean(mean, dist_info)
    return mean


#: Log names of the update's loss outputs.
_STAT_NAMES = {"loss_objective": "loss_policy", "loss_critic": "loss_value", "kl_approx": "kl"}
