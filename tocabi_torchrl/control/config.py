"""``ActuatorConfig``: the actuator layer of the env's config tree (``env.control.actuators``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from ..value_rules import MAX_DELAY_SUBSTEPS, check_actuator_ranges

if TYPE_CHECKING:
    from .actuators import ActuatorChain

__all__ = ["ActuatorConfig", "MAX_DELAY_SUBSTEPS"]


@dataclass
class ActuatorConfig:
    """What happens to the legs' torque commands on their way to the joints (torque-kind controllers only; the PD
    modes' servos run inside the physics). Every range is drawn per world (and joint) at each reset; the defaults are
    the ideal actuator, which runs nothing.

    Attributes:
        delay_substeps: (low, high) the torque delay in physics substeps of 0.5 ms, k ~ U{low, low + stride, ...,
            high} per world; high at most :data:`MAX_DELAY_SUBSTEPS`.
        delay_stride: the step of the delay's grid [substeps]; ``high - low`` must be a multiple of it. 1: every
            whole substep. At the control period's substeps (8), every world's delayed torque changes in the same
            substep of the period; mujoco-warp's solver iterates all worlds of a substep until the slowest has
            converged, so the substep a torque change makes costly is then paid for once a period, not in each
            (lab/analysis/substep_iterations.py). The range's ends stay; the values between are fewer.
        delay_average: apply the delayed torque's mean over each policy step instead of the delayed torque itself
            substep by substep (``AveragedDelay``): each step's impulse and every delay of the range stay, only the
            torque's shape within the step goes, and every world's torque changes at the step's first substep, so
            the solver's lockstep pays no extra iterations for the delay (the grid's gain without the grid).
        motor_constant: (low, high) the motor-constant scale c ~ U(low, high) per world and joint (1 = nominal).
        coulomb: (low, high) Coulomb friction [N·m] per world and joint, against the joint's velocity.
        viscous: (low, high) viscous friction [N·m·s/rad] per world and joint.
        saturate: clip the torque at the joints' limits after the other stages (when any runs). The model's leg
            motors are control-limited to the same limits, so the physics never applies more; this decides whether
            the ``leg_torque`` signal reports the clipped torque (True) or the stages' unclipped output.
    """

    delay_substeps: tuple[int, int] = (0, 0)
    delay_stride: int = 1
    delay_average: bool = False
    motor_constant: tuple[float, float] = (1.0, 1.0)
    coulomb: tuple[float, float] = (0.0, 0.0)
    viscous: tuple[float, float] = (0.0, 0.0)
    saturate: bool = True

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad range (``env.control.actuators.<name>``) and what it takes."""
        check_actuator_ranges(self, "env.control.actuators.")

    @property
    def ideal(self) -> bool:
        """True when no stage would run."""
        return (tuple(self.delay_substeps) == (0, 0) and tuple(self.motor_constant) == (1.0, 1.0)
                and tuple(self.coulomb) == (0.0, 0.0) and tuple(self.viscous) == (0.0, 0.0))

    def build(self, substeps: int) -> ActuatorChain:
        """The chain these settings describe (empty when :attr:`ideal`): delay, motor constant, friction,
        saturation, each only where it changes something."""
        # Here, not at the top: the stages are torch code, and the config tree reads this module without torch.
        from .actuators import ActuatorChain, AveragedDelay, Delay, Friction, MotorConstant, Saturation

        stages = []
        if tuple(self.delay_substeps) != (0, 0):
            kind = AveragedDelay if self.delay_average else Delay
            stages.append(kind(int(self.delay_substeps[0]), int(self.delay_substeps[1]), substeps,
                               int(self.delay_stride)))
        if tuple(self.motor_constant) != (1.0, 1.0):
            stages.append(MotorConstant(*self.motor_constant))
        if tuple(self.coulomb) != (0.0, 0.0) or tuple(self.viscous) != (0.0, 0.0):
            stages.append(Friction(tuple(self.coulomb), tuple(self.viscous)))
        if stages and self.saturate:
            stages.append(Saturation())
        return ActuatorChain(stages)
