"""The gait test's per-robot accounting and how a checkpoint is loaded for it (:mod:`.gait_test`, :mod:`.robust`).

:class:`GaitMetrics` is the gait test's per-env accounting (survival, distance, drift, speed error, knee RMS), one
update per policy step: :func:`~tocabi_torchrl.evaluation.gait_test.evaluate_policy` and the experiments' recorded
rollouts (``lab/experiments/gait_record.py``) both use it, so the two report the same numbers for the same rollout.
:func:`load_policy` reads a checkpoint and builds its env at a fixed command (:func:`fixed_command`) with its agent.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from .. import robot
from ..config import RunConfig
from ..transforms.normalize import freeze_running_statistics, untrained_running_normalizers

__all__ = ["GaitMetrics", "LoadedPolicy", "load_policy", "fixed_command", "first_action", "policy_steps",
           "require_trained_statistics", "LEG_JOINTS", "KNEES"]

#: The 12 leg joints, in action order.
LEG_JOINTS: tuple[str, ...] = tuple(robot.JOINT_NAMES[robot.LEGS])
#: Left and right knee, indices into the leg (and full) joint order.
KNEES = (LEG_JOINTS.index("L_Knee_Joint"), LEG_JOINTS.index("R_Knee_Joint"))


# ------------------------------------------------------------------------------------------------ gait test metrics
class GaitMetrics:
    """The gait test's per-env accounting, one :meth:`update` per policy step; :meth:`summary` gives the metrics.

    A robot counts as alive until its first termination; every metric uses its alive steps only and its pelvis
    position at its last alive step. A robot with no alive step (it fell in the first) has no knee RMS or speed
    error: NaN per env, left out of the summary's means (NaN there too when no robot has one). With no survivor the
    survivors' forward distance is NaN too (not 0: no robot stood still). The JSON writers turn NaN into ``null``.
    """

    def __init__(self, start_pos: torch.Tensor, command: tuple[float, float], dt: float):
        n, device = start_pos.shape[0], start_pos.device
        self.command, self.dt = (float(command[0]), float(command[1])), float(dt)
        self.start = start_pos.clone()
        self.last_pos = start_pos.clone()
        self.alive = torch.ones(n, dtype=torch.bool, device=device)
        self.knee_sq = torch.zeros(n, device=device)
        self.vel_err = torch.zeros(n, device=device)
        self.alive_steps = torch.zeros(n, device=device)

    def update(self, nxt) -> torch.Tensor:
        """Account the step whose outputs are ``nxt`` (the ``"next"`` of an env step); returns ``alive`` (N,)."""
        self.alive = self.alive & ~nxt["terminated"].squeeze(-1)
        a = self.alive.float()
        self.last_pos = torch.where(self.alive.unsqueeze(-1), nxt["base_pos"], self.last_pos)
        knee_err = nxt["joint_pos"][:, KNEES] - nxt["ref_joint_pos"][:, KNEES]
        self.knee_sq += a * knee_err.pow(2).mean(-1)
        self.vel_err += a * (nxt["base_lin_vel"][:, 0] - self.command[0]).abs()
        self.alive_steps += a
        return self.alive

    def per_env(self) -> dict[str, torch.Tensor]:
        """(N,) per-env values: distance travelled (x, y) and knee RMS over the alive steps."""
        dist = self.last_pos - self.start
        return {"forward_m": dist[:, 0], "lateral_m": dist[:, 1],
                "knee_rms_rad": self._per_alive_step(self.knee_sq).sqrt(), "alive": self.alive,
                "alive_seconds": self.alive_steps * self.dt}

    def _per_alive_step(self, total: torch.Tensor) -> torch.Tensor:
        """(N,) ``total`` over each robot's alive steps; NaN for a robot with none (0/0 once read as a perfect 0)."""
        return torch.where(self.alive_steps > 0, total / self.alive_steps.clamp_min(1), float("nan"))

    def summary(self, seconds: float) -> dict:
        """The gait test's ``summary.json`` values (without the video entry). ``speed_tracking_error_mps`` is the mean
        of ``|base vx - command vx|`` [m/s] over the alive steps: the forward speed alone, gait sway included (a
        report figure, not one of the test's thresholds)."""
        vx, vy = self.command
        alive, dt = self.alive, self.dt
        dist = self.last_pos - self.start
        return {
            "command_mps": [vx, vy],
            "seconds": seconds,
            "num_envs": int(alive.shape[0]),
            "survival": float(alive.float().mean()),
            "forward_distance_m": float(dist[:, 0].mean()),
            "forward_distance_survivors_m": float(dist[alive, 0].mean()) if alive.any() else math.nan,
            "lateral_drift_m": float(dist[:, 1].abs().mean()),
            "mean_speed_mps": float((dist[:, 0] / (self.alive_steps * dt).clamp_min(dt)).mean()),
            "speed_tracking_error_mps": float(self._per_alive_step(self.vel_err).nanmean()),
            "knee_rms_rad": float(self._per_alive_step(self.knee_sq).sqrt().nanmean()),
        }


# ------------------------------------------------------------------------------------------------ loading
@dataclass
class LoadedPolicy:
    """A checkpoint's config, its evaluation env (fixed command) and its agent, weights applied."""

    path: Path
    cfg: RunConfig
    env: object
    agent: object

    @property
    def actor(self):
        return self.agent.actor

    @property
    def control_mode(self) -> str:
        return self.cfg.env.control.mode


def fixed_command(command: tuple[float, float]):
    """A command schedule that holds ``command`` = (vx, vy) [m/s] for the whole episode."""
    from ..envs import CommandConfig

    vx, vy = command
    return CommandConfig(vx_range=(vx, vx), vx_initial_range=(vx, vx), vy_range=(vy, vy))


def policy_steps(seconds: float, dt: float, option: str = "seconds") -> int:
    """Policy steps in ``seconds``; ``ValueError`` if ``seconds`` is not finite or is less than one step. ``option``:
    the name the error gives the length, the caller's own (play.py's ``seconds``, ppo_walk's ``--eval_seconds``)."""
    if not math.isfinite(seconds):
        raise ValueError(f"{option}={seconds!r}: the test's length must be a finite number of seconds (e.g. 8)")
    steps = int(round(seconds / dt))
    if steps < 1 or seconds < dt * (1.0 - 1e-9):  # 0.003 s would round up to one 4 ms step: refused, as said
        raise ValueError(f"{option}={seconds:g} is shorter than one policy step ({dt * 1000:g} ms); pass at least "
                         f"{dt:g}")
    return steps


def first_action(actor, td):
    """``actor(td)`` for a rollout's first step, with a policy that does not fit the env's ``"observation"`` (N, D)
    said at the call: ``ValueError`` naming D and the fix instead of torch's shape error from inside the network (a
    policy trained with another observation layout than the config the env was built from). A wrong action size is
    the env's to refuse, at its step."""
    try:
        return actor(td)
    except RuntimeError as err:
        observation = td.get("observation", None)
        # torch's words for tensors that do not fit ("mat1 and mat2 shapes cannot be multiplied", "The size of
        # tensor a (10) must match ..."); anything else (out of memory, a bug in the policy) is passed on as it is.
        if observation is None or not re.search(r"shape|size of tensor|size mismatch|input of size", str(err)):
            raise
        raise ValueError(f"the policy cannot act on this env's observation of {observation.shape[-1]} values per robot "
                         f"({err}): it was trained with another observation layout than the config the env was built "
                         "from. Build the env from the policy's own config (load_policy, or config_from_checkpoint "
                         "of its checkpoint)") from err


def require_trained_statistics(env) -> None:
    """``ValueError`` if ``env`` normalises observations with running statistics that never saw a step: an env built
    from a run's config (e.g. ``build_env(nominal_config(cfg), ...)``) starts with the normaliser's initial
    statistics, not those of the checkpoint, so a policy trained with ``transforms.normalization running`` would be
    tested on inputs scaled unlike those it learned from, and its numbers would be wrong without a word."""
    if untrained_running_normalizers(env):
        raise ValueError("the env's running observation normaliser holds its starting statistics, not the "
                         "checkpoint's (an env built from the run's config): the policy would see inputs scaled "
                         "unlike those it trained on. Pass env=load_policy(checkpoint, ..., nominal=True).env, or "
                         "test the checkpoint with evaluate_run / evaluate_robust_run")


#: The task's fall rules (``TaskConfig`` fields), which the gait tests keep at their defaults.
FALL_RULES = ("min_pelvis_height", "min_neck_height", "max_neck_angle", "terminate_on_forbidden_contact",
              "terminate_on_self_collision")


def nominal_config(cfg: RunConfig) -> RunConfig:
    """``cfg`` without the perturbations a training may add: ideal actuators, no kicks, no dynamics randomisation, no
    sensor noise, starts at rest, no start pool, and the model's own solver (no training iteration cap). The gait
    tests run on it (the robust test's cases then add their own draws): a policy is tested on the robot, not on its
    training's draws. What counts as a fall is the task's default (:data:`FALL_RULES`), whatever the training used:
    a policy trained with looser terminations is judged by the same falls as every other."""
    from ..control.config import ActuatorConfig
    from ..envs.config import TaskConfig
    from ..envs.push_config import PushConfig
    from ..sim.dynamics_config import DynamicsRandomization
    from ..transforms.sensor_noise_config import SensorNoiseConfig

    env = cfg.env
    falls = {name: getattr(TaskConfig, name) for name in FALL_RULES}
    env = dataclasses.replace(
        env, task=dataclasses.replace(env.task, start_joint_vel_std=0.0, start_base_vel_std=0.0, **falls),
        control=dataclasses.replace(env.control, actuators=ActuatorConfig()), pushes=PushConfig(),
        dynamics=DynamicsRandomization(), sim=dataclasses.replace(env.sim, start_pool=0, solver_iterations=None))
    return dataclasses.replace(cfg, env=env, transforms=dataclasses.replace(cfg.transforms,
                                                                            sensor_noise=SensorNoiseConfig()))


def load_policy(path: str | os.PathLike, num_envs: int, device: torch.device | str,
                command: tuple[float, float] = (0.5, 0.0),
                edit_env: Callable | None = None, backend: str | None = None,
                state: dict | None = None, nominal: bool = False) -> LoadedPolicy:
    """Read ``path`` (a ``.pt`` file or a run folder) with the safe reader, build its env at a fixed ``command``
    with ``num_envs`` worlds on ``device`` (a ``torch.device`` or its name, ``"cpu"``, ``"cuda"``) and its agent, and
    apply the weights and transform state.

    ``edit_env``: a function from the checkpoint's env config (``TocabiWalkConfig``) to the one to build (e.g. a
    scene with an obstacle); ``backend``: replaces ``env.sim.backend``; ``state``: the file's contents if already
    read with ``read_checkpoint``; ``nominal``: the env of :func:`nominal_config` (the gait tests'), not the one the
    policy trained in. Raises ``CheckpointError`` for a bad file.
    """
    from ..rl.checkpoint import checkpoint_file, config_from_checkpoint, read_checkpoint
    from ..rl.trainer import build_env, checkpoint_agent

    device = torch.device(device)
    ckpt = checkpoint_file(path)
    state = read_checkpoint(ckpt) if state is None else state
    cfg = config_from_checkpoint(state, ckpt)
    if nominal:
        cfg = nominal_config(cfg)
    env_cfg = cfg.env
    if backend is not None:
        env_cfg = dataclasses.replace(env_cfg, sim=dataclasses.replace(env_cfg.sim, backend=backend))
    if edit_env is not None:
        env_cfg = edit_env(env_cfg)
    cfg = dataclasses.replace(cfg, env=env_cfg)
    env = build_env(cfg, device, num_envs=num_envs, command=fixed_command(command))
    agent = checkpoint_agent(state, cfg, env, ckpt)
    freeze_running_statistics(env)
    return LoadedPolicy(ckpt, cfg, env, agent)
