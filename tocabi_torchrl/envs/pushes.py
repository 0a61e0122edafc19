"""Pushes: horizontal kicks of the robot during an episode, as forces held for whole policy steps.

Each episode of each world draws ``count`` kicks at reset. Kick j starts at a random time in the j-th of ``count``
equal shares of ``window`` (two kicks overlap, their forces adding, only when one outlasts the gap to the next), in a
random horizontal direction, and changes the robot's velocity by ``speed``, over the kick's duration (a whole number
of policy steps, at least one). How (``PushConfig.kind``):

- ``"force"``: a force of impulse ``speed × mass`` (the whole robot's nominal mass) on the pelvis body
  (``sim.xfrc_applied``, world frame): the robot's momentum changes exactly as a velocity kick's, but the pelvis is
  jerked ahead of the limbs and upper body, which lag, so the joints are kicked as well. The TOCABI lab trains with
  such impulses, 50-250 N·s over 0.1-1 s.
- ``"velocity"``: every body gets its own mass × the kick's acceleration ``speed / duration`` (its world's drawn
  masses where ``env.dynamics`` randomises them): a uniform field, like a brief change of gravity, so every body's
  velocity changes by the same ``speed`` and no joint is kicked (contacts aside). This is a velocity kick of the whole
  robot, what MuJoCo Playground and Isaac Lab push with by writing the root velocity, here through forces so that it
  reaches both backends' physics alike and keeps the warp step's reuse of its last forward pass valid. The robust
  gait test's kicks: 0.5 and 1.0 m/s (≈ 52 and 104.5 N·s on the 104.5 kg robot) within one 4 ms policy step.

With ``PushConfig.calm_fraction`` f > 0, each episode is calm (no kicks at all) with probability f, drawn at reset
from one more uniform per world (:attr:`Pushes.calm_draws`): its kicks get no speed and a start time that never
comes, so a calm episode reads like one before its first kick (``latest``: the episode's time, speed 0).

Everything is device-side and sync-free: the schedule is (N, count) tensors drawn from the env's counter-based
per-episode uniforms and updated in place, the force is a masked sum over the kicks, and :attr:`Pushes.scale`
(a 0-d device tensor, e.g. a training curriculum) multiplies every kick without re-capturing a graph.
"""

from __future__ import annotations

import math

import torch

from ..value_rules import CALM_NEVER_S
from .push_config import PushConfig

__all__ = ["PushConfig", "Pushes"]


class Pushes:
    """The kicks of ``num_envs`` worlds (see the module docstring).

    Args:
        cfg: the :class:`PushConfig` (``count`` > 0).
        num_envs: N; device: the env's device.
        dt: the policy step [s].
        mass: the robot's mass [kg] (impulse = speed × mass).
    """

    def __init__(self, cfg: PushConfig, num_envs: int, device: torch.device, dt: float, mass: float):
        self.cfg, self.dt, self.mass = cfg, float(dt), float(mass)
        n, k, f32 = num_envs, cfg.count, torch.float32
        #: Uniforms per world that :meth:`reset` reads: time, direction, speed and duration of each kick.
        self.draws = 4 * k
        #: Uniforms per world that :meth:`reset` reads as ``calm``: 1 with ``calm_fraction`` > 0, else 0.
        self.calm_draws = 1 if cfg.calm_fraction > 0 else 0
        # Column 0 of these two pads is the episode's start (step 0, speed 0), the kicks' columns follow: the latest
        # kick is one gather at the number of kicks begun (:meth:`latest`), 0 meaning none yet.
        self._start_pad = torch.zeros(n, k + 1, dtype=torch.int64, device=device)
        self._speed_pad = torch.zeros(n, k + 1, dtype=f32, device=device)
        #: (N, count) int64 the policy step each kick starts at (a view of the pad), and how many steps it lasts.
        self.start_step = self._start_pad[:, 1:]
        self.steps = torch.ones(n, k, dtype=torch.int64, device=device)
        #: (N, count, 2) the force [N] of each kick while it acts, world x and y.
        self.force = torch.zeros(n, k, 2, dtype=f32, device=device)
        #: (N, count) the velocity change [m/s] of each kick as drawn (before :attr:`scale` and :attr:`world_scale`;
        #: 0 in a calm episode).
        self.speed = self._speed_pad[:, 1:]
        #: Multiplies every kick (a 0-d device tensor, 1 = the configured kicks; a curriculum sets it in place).
        self.scale = torch.ones((), dtype=f32, device=device)
        #: (N,) multiplies each world's kicks (1 = the configured kicks, 0 = none); set it in place, e.g. to give
        #: worlds different kick speeds in one env (the robust gait test).
        self.world_scale = torch.ones(n, dtype=f32, device=device)
        share = (cfg.window[1] - cfg.window[0]) / k
        self._share_start = cfg.window[0] + share * torch.arange(k, dtype=f32, device=device)
        self._share = share
        # A fixed duration (the velocity kicks': one 4 ms step) is the same whole number of steps for every kick:
        # made once, so a reset spends no ops on it (the values are those the draw would give).
        self._fixed_seconds = None
        if cfg.duration[0] == cfg.duration[1]:
            fixed = max(round(cfg.duration[0] / self.dt), 1)
            self.steps.fill_(fixed)
            # In seconds as the draw computes it (float32 steps times dt): the forces equal the drawn path's.
            self._fixed_seconds = torch.full((), float(fixed), dtype=f32, device=device) * self.dt

    def reset(self, mask: torch.Tensor, u: torch.Tensor, calm: torch.Tensor | None = None) -> None:
        """Draw the kicks of the worlds flagged in ``mask`` (N,) bool from ``u`` (N, :attr:`draws`) uniforms, and,
        with ``calm_fraction`` f > 0, whether the episode is calm from ``calm`` (N, 1) uniforms (calm below f)."""
        k, (s_lo, s_hi), (d_lo, d_hi) = self.cfg.count, self.cfg.speed, self.cfg.duration
        when = self._share_start + self._share * u[:, :k]
        angle = 2.0 * math.pi * u[:, k:2 * k]
        speed = s_lo + (s_hi - s_lo) * u[:, 2 * k:3 * k]
        if self.calm_draws:
            if calm is None or tuple(calm.shape) != (u.shape[0], 1):
                raise ValueError(f"Pushes.reset: calm_fraction {self.cfg.calm_fraction} needs `calm`, a "
                                 f"({u.shape[0]}, 1) float tensor of uniforms, got "
                                 f"{None if calm is None else tuple(calm.shape)}")
            still = calm < self.cfg.calm_fraction
            speed = speed.masked_fill(still, 0.0)  # no force
            when = when.masked_fill(still, CALM_NEVER_S)  # and no kick begun, as the time before a first kick reads
        if self._fixed_seconds is None:
            steps = torch.round((d_lo + (d_hi - d_lo) * u[:, 3 * k:]) / self.dt).long().clamp(min=1)
            magnitude = speed * self.mass / (steps * self.dt)
        else:
            magnitude = speed * self.mass / self._fixed_seconds
        force = magnitude.unsqueeze(-1) * torch.stack((torch.cos(angle), torch.sin(angle)), dim=-1)
        m = mask.unsqueeze(-1)
        torch.where(m, torch.round(when / self.dt).long(), self.start_step, out=self.start_step)
        if self._fixed_seconds is None:
            torch.where(m, steps, self.steps, out=self.steps)
        torch.where(m.unsqueeze(-1), force, self.force, out=self.force)
        torch.where(m, speed, self.speed, out=self.speed)

    def at(self, episode_step: torch.Tensor) -> torch.Tensor:
        """(N, 2) the horizontal force [N] of a ``"force"`` kick on the pelvis during policy step ``episode_step``
        (N,) int64 (0 = the episode's first step), world frame: the kick's impulse (speed × the robot's mass) over
        its duration."""
        step = episode_step.unsqueeze(-1)
        active = (step >= self.start_step) & (step < self.start_step + self.steps)
        return (self.force * active.unsqueeze(-1)).sum(dim=1) * (self.scale * self.world_scale).unsqueeze(-1)

    def latest(self, episode_step: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The episode's most recent kick as of ``episode_step`` (N,) int64 policy steps done: ``(age, speed)``, each
        (N, 1) float32: the seconds since it began [s] and the velocity change it gave [m/s], :attr:`scale` and
        :attr:`world_scale` included; (episode time, 0) before the first kick. The kicks' start steps rise with their
        index (one per share of the window), so the latest is the last one begun. A calm episode
        (``calm_fraction``) reads (episode time, 0) throughout."""
        step = episode_step.unsqueeze(-1)
        begun = (self.start_step < step).sum(dim=1, keepdim=True)  # (N, 1) kicks begun: the pads' column
        age = (step - self._start_pad.gather(1, begun)) * self.dt
        speed = self._speed_pad.gather(1, begun) * (self.scale * self.world_scale).unsqueeze(-1)
        return age, speed

    def body_forces(self, episode_step: torch.Tensor, body_mass: torch.Tensor) -> torch.Tensor:
        """(N, nbody, 2) the horizontal force [N] of a ``"velocity"`` kick on every body during policy step
        ``episode_step`` (N,) int64, world frame: each body's mass (``body_mass`` (N, nbody) or (nbody,) [kg]) times
        the kick's acceleration [m/s²] (the force of :meth:`at` over the robot's mass)."""
        acceleration = self.at(episode_step) / self.mass
        return acceleration.unsqueeze(1) * body_mass.unsqueeze(-1)
