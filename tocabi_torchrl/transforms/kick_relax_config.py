"""``KickRelax``: which reward terms a kick relaxes while the robot recovers, and for how long
(``transforms.kick_relax``), in a module without torch so that the config tree reads without it.
:class:`~tocabi_torchrl.transforms.TaskReward` applies it."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

__all__ = ["KickRelax", "KICK_RELAX_TERMS"]

#: The terms tied to the reference gait's clock or to smoothness: the joint positions, the contact pattern and the
#: foot loads of the reference at the phase clock's time, and the step-to-step changes of torque, joint velocity and
#: foot force. A kicked robot recovers by an early, wide or quick step that each of them pays less for.
KICK_RELAX_TERMS = ("qpos", "foot_contact", "force_ref", "torque_diff", "qacc", "contact_force_diff")


@dataclass(frozen=True)
class KickRelax:
    """After a kick, scale the named reward terms by ``1 − r``, ``r = clamp(1 − age / seconds, 0, 1) ·
    clamp(speed / full_speed, 0, 1)`` (``age`` [s] since the env's latest kick began, ``speed`` [m/s] the velocity
    change it gave, curriculum included: the env's ``kick_age`` and ``kick_speed`` signals). ``seconds = 0`` (the
    default) is off: no term changes.

    Attributes:
        seconds: how long a kick's relaxation lasts [s]; it falls linearly from the kick to 0 at this age.
        full_speed: a kick of at least this velocity change [m/s] relaxes the terms fully at first; a weaker one in
            proportion (so the kicks' curriculum, ramping their speed in, ramps the relaxation in with it).
        terms: the reward terms relaxed (names of terms in use).

    >>> KickRelax(seconds=1.5).enabled
    True
    >>> KickRelax().enabled
    False
    """

    seconds: float = 0.0
    full_speed: float = 1.0
    terms: tuple[str, ...] = KICK_RELAX_TERMS

    KEYS = ("kick_age", "kick_speed")

    def __post_init__(self):
        terms = self.terms
        # Before the tuple: one name ("qpos") became its letters ('q', 'p', 'o', 's'), and None failed as a raw
        # "'NoneType' object is not iterable".
        if isinstance(terms, (str, bytes)) or not isinstance(terms, Iterable):
            fix = f"; for one term give ({terms!r},)" if isinstance(terms, str) else f"; e.g. {KICK_RELAX_TERMS}"
            raise ValueError(f"transforms.kick_relax.terms must be a tuple of reward term names, got {terms!r}{fix}")
        object.__setattr__(self, "terms", tuple(terms))
        self.validate()

    @property
    def enabled(self) -> bool:
        return self.seconds > 0 and bool(self.terms)

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad field (``transforms.kick_relax.<name>``)."""
        for name, low in (("seconds", 0.0), ("full_speed", None)):
            value = getattr(self, name)
            ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
            if not ok or (value < 0 if low is not None else value <= 0):
                rule = ">= 0 (0: off)" if low is not None else "> 0"
                raise ValueError(f"transforms.kick_relax.{name} must be a finite number {rule}, got {value!r}")
        if not all(isinstance(t, str) and t for t in self.terms):
            raise ValueError(f"transforms.kick_relax.terms must be reward term names, got {self.terms!r}")
