"""``CommandConfig``: how the velocity command is drawn (``env.command``), in a module of its own so that the config
tree reads without torch (``VelocityCommand``, in ``envs.command``, runs it)."""

from __future__ import annotations

from dataclasses import dataclass

from ..tree import check_field_types

__all__ = ["CommandConfig"]


#: [m/s] the largest speed a command range may reach: far past any walk (the defaults end at 0.7 m/s).
MAX_COMMAND_MPS = 10.0


@dataclass
class CommandConfig:
    """How the commanded pelvis-frame velocity [m/s] is drawn.

    The defaults are the TocabiLab report's: vx ~ U(0, 0.7) with the first vx of an episode ~ U(0.2, 0.7),
    vy ~ U(-0.2, 0.2), re-sampled every ``resample_every`` steps and applied at once. ``CommandConfig.reference()``
    reproduces the reference code (spec §9.4): U(-0.2, 0.8) everywhere, and each re-sample ramps linearly over
    D ~ randint(1, 250) steps, stopping at (D-1)/D of the change, with the ramp state surviving resets.
    """

    vx_range: tuple[float, float] = (0.0, 0.7)
    """forward command range low,high [m/s]"""
    vx_initial_range: tuple[float, float] = (0.2, 0.7)
    """forward command range of an episode's first command [m/s]"""
    vy_range: tuple[float, float] = (-0.2, 0.2)
    """lateral command range low,high [m/s]"""
    resample_every: int = 2000
    """policy steps between command re-samples"""
    #: Ramp length D is drawn from randint(1, max_ramp_steps) (exclusive upper bound, like numpy); 1 = switch at once.
    max_ramp_steps: int = 1
    #: The reference never resets its ramp state, so a ramp in progress overwrites a new episode's first commands.
    ramp_survives_reset: bool = False

    @classmethod
    def reference(cls) -> "CommandConfig":
        return cls(vx_range=(-0.2, 0.8), vx_initial_range=(-0.2, 0.8), vy_range=(-0.2, 0.2),
                   max_ramp_steps=250, ramp_survives_reset=True)

    @classmethod
    def named(cls, name: str) -> "CommandConfig":
        """The schedule called ``name``: ``"tocabilab"`` (the default) or ``"reference"``."""
        schedules = {"tocabilab": cls, "reference": cls.reference}
        if name not in schedules:
            raise ValueError(f"unknown command schedule {name!r}; choose one of {sorted(schedules)}")
        return schedules[name]()

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad option (``env.command.NAME``) and the accepted values."""
        # Here as well as in TocabiWalkConfig.validate: VelocityCommand takes a CommandConfig on its own. An inf bound
        # would reach the observation, and a float step count would fail in randint or never match the schedule.
        check_field_types(self, "env.command.")
        for field in ("vx_range", "vx_initial_range", "vy_range"):
            lo, hi = getattr(self, field)
            if not lo <= hi:
                raise ValueError(f"env.command.{field} must be (low, high) with low <= high, got {(lo, hi)}")
            if max(abs(lo), abs(hi)) > MAX_COMMAND_MPS:  # a typo (1e9), not a walk: it would reach the observation
                raise ValueError(f"env.command.{field} {(lo, hi)} reaches past {MAX_COMMAND_MPS:g} m/s, far beyond "
                                 "a walk (the defaults go to 0.7 m/s): give the range in m/s")
        if self.resample_every < 1:
            raise ValueError(f"env.command.resample_every must be an int >= 1 (steps between re-samples), got "
                             f"{self.resample_every!r}")
        if self.max_ramp_steps < 1:
            raise ValueError(f"env.command.max_ramp_steps must be an int >= 1 (1 = switch at once), got "
                             f"{self.max_ramp_steps!r}")
