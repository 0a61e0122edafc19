"""Exploration-noise schedules: the reference's scheduled (not learned) action standard deviation (spec §10.4)."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["StdSchedule"]


@dataclass(frozen=True)
class StdSchedule:
    """Action std as a function of training progress, interpolated in std space (not log-std).

    With ``P`` = progress remaining (1 at the start, 0 at the end) and ``b = max(0, (P - hold) / (1 - hold))``,
    ``std = start·b + end·(1 - b)``. The reference uses start 0.1, end 0.05, hold 0.5: the std falls linearly from
    0.1 to 0.05 over the first half of training, then stays at 0.05 (``b = 2P - 1`` for P > 0.5).
    """

    start: float = 0.1
    end: float = 0.05
    hold: float = 0.5

    def __post_init__(self):
        if not (self.start > 0 and self.end > 0):
            raise ValueError(f"StdSchedule start and end must be > 0, got {self.start}, {self.end}")
        if not 0.0 <= self.hold < 1.0:
            raise ValueError(f"StdSchedule.hold must be in [0, 1), got {self.hold}")

    def __call__(self, progress_remaining: float) -> float:
        p = min(max(float(progress_remaining), 0.0), 1.0)
        b = max(0.0, (p - self.hold) / (1.0 - self.hold))
        return self.start * b + self.end * (1.0 - b)
