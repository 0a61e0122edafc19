"""``PushConfig``: the kicks of the robot during an episode (``env.pushes``), in a module of its own so that the
config tree reads without torch (``Pushes``, in ``envs.pushes``, applies them)."""

from __future__ import annotations

from dataclasses import dataclass

from ..tree import check_field_types
from ..value_rules import PUSH_KINDS, check_push_settings

__all__ = ["PushConfig", "PUSH_KINDS"]


@dataclass
class PushConfig:
    """Kicks during an episode (``TocabiWalkConfig.pushes``): a force on the pelvis (``kind="force"``, the default)
    or a velocity kick of the whole robot (``"velocity"``); ``count=0`` (default) is off.

    Attributes:
        count: kicks per episode.
        window: (start, end) [s] of episode time over which the kicks are spread (kick j in the j-th share); the env
            refuses an end past its episode (``env.task.max_episode_steps``), whose last kicks would never come.
        speed: (low, high) [m/s] the velocity change of the whole robot, drawn per kick (impulse = speed × mass);
            at most 10 m/s, a sanity bound (``value_rules.PUSH_SPEED``).
        duration: (low, high) [s] how long each kick's force acts, drawn per kick (rounded to whole policy steps,
            at least one).
        kind: how the kick acts. ``"force"``: a force on the pelvis alone (the TOCABI lab's pushes): the robot's
            momentum changes by speed × mass, but the pelvis is jerked and the limbs and upper body lag behind it,
            so the joints are kicked too. ``"velocity"``: a velocity kick of the whole robot: every body gets the
            force of its own mass × the same acceleration (a uniform field, like a brief change of gravity), so
            every body's velocity changes by the same ``speed`` and no joint is kicked; what MuJoCo Playground's
            and Isaac Lab's velocity pushes do, and the robust gait test's kicks.
        calm_fraction: the probability, drawn per episode at reset, that an episode has no kicks at all, in [0, 1)
            (0: every episode has ``count``; moot when ``count`` is 0). The ``robust`` preset's kicks come at most
            3.75 s apart, so its robots never walk the 8 undisturbed seconds of the robust gait test's ``nominal``
            case; calm episodes are meant to train that walk beside the kicked ones.
    """

    count: int = 0
    window: tuple[float, float] = (2.0, 7.0)
    speed: tuple[float, float] = (0.5, 0.5)
    duration: tuple[float, float] = (0.004, 0.004)
    kind: str = "force"
    calm_fraction: float = 0.0

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad field (``env.pushes.<name>``) and what it takes."""
        check_push_settings(self, "env.pushes.")
        # Stored as plain numbers: a numpy scalar or a 0-d tensor passed the rules above as the number it holds, as it
        # does in the whole config tree, and the kicks' draws and the policy contract take plain numbers.
        check_field_types(self, "env.pushes.")
