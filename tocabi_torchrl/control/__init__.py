"""Controllers and actuators: how the policy's actions become joint torques.

A :class:`Controller` is one control law for one group of joints (``τ_cmd = F_con(π_θ)``); an
:class:`ActuatorChain` is what happens to a torque command between the controller and the joint (delay, motor
constant, friction, saturation). ``TocabiWalk`` builds them from its config (``env.control``), or takes a
user-defined leg controller: ``TocabiWalk(..., leg_controller=MyLaw())``. docs/controllers.md has the guide.
"""

from .actuators import Actuator, ActuatorChain, Delay, Friction, MotorConstant, Saturation
from .base import ControlContext, ControlInput, Controller
from .computed_torque import ComputedTorqueResidual
from .config import ActuatorConfig
from .joint_pd import JointPD, PDHold
from .torque import AssistedTorque, DirectTorque, clip_torque

__all__ = ["Actuator", "ActuatorChain", "ActuatorConfig", "AssistedTorque", "ComputedTorqueResidual",
           "ControlContext", "ControlInput", "Controller", "Delay", "DirectTorque", "Friction", "JointPD",
           "MotorConstant", "PDHold", "Saturation", "clip_torque"]
