"""``DynamicsRandomization``: the ranges of the per-world dynamics drawn at every reset (``env.dynamics``), in a
module that imports neither torch nor MuJoCo so that the config tree reads without them. ``sim.dynamics`` has the
table of what each range draws and ``WorldDynamics``, which draws them."""

from __future__ import annotations

from dataclasses import dataclass

from ..tree import check_field_types
from ..value_rules import DYNAMICS_OFF, check_dynamics_ranges

__all__ = ["DynamicsRandomization"]

_RANGES = ("mass_scale", "joint_damping", "armature_scale", "friction_scale")
#: The identity of each range: the value that changes nothing.
_OFF = DYNAMICS_OFF
#: The simulator's per-world model fields each range writes.
_FIELDS = {"mass_scale": ("body_mass", "body_inertia", "body_subtreemass"), "joint_damping": ("dof_damping",),
           "armature_scale": ("dof_armature",), "friction_scale": ("geom_friction",)}


@dataclass
class DynamicsRandomization:
    """Ranges of the per-world dynamics drawn at every reset (``TocabiWalkConfig.dynamics``; see the module's table).
    Each is ``(low, high)`` of a uniform draw; the defaults change nothing.

    Attributes:
        mass_scale: scale of each body's mass and inertia tensor (> 0, <= 5).
        joint_damping: damping [N·m·s/rad] added to each joint dof's (>= 0, <= 100).
        armature_scale: scale of each joint dof's armature (>= 0, <= 5).
        friction_scale: scale of every geom's sliding friction, one per world (>= 0, <= 5).

    The upper bounds are sanity bounds (``value_rules.DYNAMICS_RANGES``, which says what lies beyond each).
    """

    mass_scale: tuple[float, float] = (1.0, 1.0)
    joint_damping: tuple[float, float] = (0.0, 0.0)
    armature_scale: tuple[float, float] = (1.0, 1.0)
    friction_scale: tuple[float, float] = (1.0, 1.0)

    def validate(self, prefix: str = "env.dynamics.") -> None:
        """Raise ``ValueError`` naming the first bad range (``<prefix><name>``) and what it takes."""
        # Two numbers each, as in the whole config tree: float() took text ("0.8") and bools here, and a numpy scalar
        # or a 0-d tensor stayed one; they are stored as plain numbers.
        check_field_types(self, prefix)
        # The rules the torch-free runtime and a policy contract's trained_under section check with too.
        check_dynamics_ranges(self, prefix)

    def on(self, name: str) -> bool:
        """Whether range ``name`` changes anything (it differs from its identity)."""
        return tuple(float(v) for v in getattr(self, name)) != _OFF[name]

    @property
    def enabled(self) -> bool:
        """True when any range changes something (else nothing is drawn or written)."""
        return any(self.on(name) for name in _RANGES)

    @property
    def sim_fields(self) -> tuple[str, ...]:
        """The model fields the simulator must give one row per world (``SimConfig.per_world_fields``)."""
        return tuple(f for name in _RANGES if self.on(name) for f in _FIELDS[name])
