"""Velocity command (vx, vy) per env: sampling at reset and the every-2000-steps schedule, batched and sync-free."""

from __future__ import annotations

import math

import torch

from .command_config import MAX_COMMAND_MPS, CommandConfig

__all__ = ["CommandConfig", "VelocityCommand"]


class VelocityCommand:
    """Command state of ``num_envs`` envs on one device.

    Tensors: ``value`` (num_envs, 2) m/s, and the ramp state ``start``/``final`` (num_envs, 2), ``ramp_len`` and
    ``ramp_pos`` (num_envs,) int64. Every update is a masked tensor op, so nothing reads device values on the host, and
    every update writes in place, so a captured CUDA graph of the env's step keeps updating these same tensors.
    """

    def __init__(self, cfg: CommandConfig, num_envs: int, device: torch.device, generator: torch.Generator):
        cfg.validate()
        self.cfg = cfg
        self.gen = generator
        zeros2 = torch.zeros(num_envs, 2, device=device)
        self.value = zeros2.clone()
        self.start = zeros2.clone()
        self.final = zeros2.clone()
        self.ramp_len = torch.ones(num_envs, dtype=torch.int64, device=device)
        self.ramp_pos = torch.ones(num_envs, dtype=torch.int64, device=device)
        lo = torch.tensor([cfg.vx_range[0], cfg.vy_range[0]], device=device)
        hi = torch.tensor([cfg.vx_range[1], cfg.vy_range[1]], device=device)
        lo0 = torch.tensor([cfg.vx_initial_range[0], cfg.vy_range[0]], device=device)
        hi0 = torch.tensor([cfg.vx_initial_range[1], cfg.vy_range[1]], device=device)
        # (num_envs, 2) low end and width of each env's ranges (one row per env, so pin() can fix some envs).
        rows = (num_envs, 2)
        self._range = (lo.expand(rows).clone(), (hi - lo).expand(rows).clone())
        self._initial_range = (lo0.expand(rows).clone(), (hi0 - lo0).expand(rows).clone())

    def restart(self) -> None:
        """Forget the schedule's state, as built (no ramp under way), in place: with ``ramp_survives_reset`` a ramp
        runs on across resets, so a re-seeded env must drop it to repeat its first episodes."""
        for t in (self.start, self.final):
            t.zero_()
        self.ramp_len.fill_(1)
        self.ramp_pos.fill_(1)

    def pin(self, envs: torch.Tensor, command: tuple[float, float]) -> None:
        """Hold ``command`` = (vx, vy) [m/s] in the envs flagged in ``envs`` (num_envs,) bool, from their next draw
        on (reset or resample): their ranges become that one value, so one env can hold fixed-command and
        re-drawn-command robots side by side (the robust gait test). In place."""
        n = self.value.shape[0]
        if not isinstance(envs, torch.Tensor) or envs.dtype != torch.bool or tuple(envs.shape) != (n,):
            # A (1,) mask broadcast to every env and pinned them all; a (num_envs, 1) one failed in a where.
            raise ValueError(f"VelocityCommand.pin takes a ({n},) bool tensor (one flag per env), got "
                             f"{getattr(envs, 'dtype', type(envs).__name__)} {tuple(getattr(envs, 'shape', ()))}")
        value = self._command_tensor("VelocityCommand.pin", *command)
        m = envs.to(self.value.device).unsqueeze(-1)
        for lo, span in (self._range, self._initial_range):
            torch.where(m, value, lo, out=lo)
            span.masked_fill_(m, 0.0)

    def _command_tensor(self, what: str, vx: float, vy: float) -> torch.Tensor:
        """(2,) float32 (vx, vy) [m/s] on the device, else a ``ValueError``: a NaN or inf reached the observation of
        every world it was given to, and a speed past the config's sanity bound is another unit (km/h, mm/s)."""
        value = (float(vx), float(vy))
        if not all(math.isfinite(v) and abs(v) <= MAX_COMMAND_MPS for v in value):
            raise ValueError(f"{what}: the command (vx, vy) must be finite speeds in m/s within "
                             f"±{MAX_COMMAND_MPS:g} (the default ranges end at 0.7 m/s), got {value}")
        return torch.tensor(value, device=self.value.device)

    def _sample(self, rng: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
        u = torch.rand(self.value.shape, device=self.value.device, generator=self.gen)
        return rng[0] + rng[1] * u

    def reset(self, mask: torch.Tensor, uniform: torch.Tensor | None = None) -> None:
        """Draw a fresh command for the envs flagged in ``mask`` (num_envs,) bool.

        ``uniform`` (num_envs, 2) in [0, 1) supplies the random numbers (the env passes per-episode ones); by default
        they come from the generator.
        """
        m = mask.unsqueeze(-1)
        lo, span = self._initial_range
        fresh = lo + span * uniform if uniform is not None else self._sample(self._initial_range)
        torch.where(m, fresh, self.value, out=self.value)
        if not self.cfg.ramp_survives_reset:
            torch.where(mask, self.ramp_len, self.ramp_pos, out=self.ramp_pos)

    def hold(self, vx: float, vy: float) -> None:
        """Command (vx, vy) [m/s] to every env from now on, resets and resampling included (a live viewer's sliders).

        Writes the value, the ramp's end points and both sampling ranges in place (a captured step keeps reading the
        same tensors): a resample then draws (vx, vy) again, and a ramp runs from it to itself."""
        v = self._command_tensor("VelocityCommand.hold", vx, vy)
        for t in (self.value, self.start, self.final):
            t.copy_(v.expand_as(t))
        for lo, span in (self._range, self._initial_range):
            lo.copy_(v)
            span.zero_()

    def update(self, episode_step: torch.Tensor) -> None:
        """Advance the schedule before the physics of a step; ``episode_step`` (num_envs,) is the pre-step count."""
        cfg = self.cfg
        due = (episode_step % cfg.resample_every) == (cfg.resample_every - 1)
        d = due.unsqueeze(-1)
        torch.where(d, self.value, self.start, out=self.start)
        torch.where(d, self._sample(self._range), self.final, out=self.final)
        if cfg.max_ramp_steps > 1:
            draw = torch.randint(1, cfg.max_ramp_steps, due.shape, device=due.device, generator=self.gen)
            torch.where(due, draw, self.ramp_len, out=self.ramp_len)
            self.ramp_pos.masked_fill_(due, 0)
            ramping = self.ramp_pos < self.ramp_len
            frac = (self.ramp_pos.float() / self.ramp_len.float()).unsqueeze(-1)
            ramped = self.start + (self.final - self.start) * frac
            torch.where(ramping.unsqueeze(-1), ramped, self.value, out=self.value)
            self.ramp_pos.add_(ramping.long())
        else:
            torch.where(d, self.final, self.value, out=self.value)
