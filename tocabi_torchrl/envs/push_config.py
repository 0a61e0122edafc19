"""``PushConfig``: the kicks of the pelvis during an episode (``env.pushes``), in a module of its own so that the
config tree reads without torch (``Pushes``, in ``envs.pushes``, applies them)."""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["PushConfig"]


@dataclass
class PushConfig:
    """Velocity kicks of the pelvis during an episode (``TocabiWalkConfig.pushes``); ``count=0`` (default) is off.

    Attributes:
        count: kicks per episode.
        window: (start, end) [s] of episode time over which the kicks are spread (kick j in the j-th share).
        speed: (low, high) [m/s] the velocity change of the whole robot, drawn per kick (impulse = speed × mass).
        duration: (low, high) [s] how long each kick's force acts, drawn per kick (rounded to whole policy steps,
            at least one).
    """

    count: int = 0
    window: tuple[float, float] = (2.0, 7.0)
    speed: tuple[float, float] = (0.5, 0.5)
    duration: tuple[float, float] = (0.004, 0.004)

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad field (``env.pushes.<name>``) and what it takes."""
        if isinstance(self.count, bool) or not isinstance(self.count, int) or not 0 <= self.count <= 64:
            raise ValueError(f"env.pushes.count must be an int in [0, 64] (kicks per episode), got {self.count!r}")
        for name in ("window", "speed", "duration"):
            low, high = getattr(self, name)
            if not (math.isfinite(low) and math.isfinite(high)) or low < 0 or low > high:
                raise ValueError(f"env.pushes.{name} must be (low, high) with 0 <= low <= high, finite, got "
                                 f"{getattr(self, name)!r}")
