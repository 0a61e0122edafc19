"""Controllers and actuators: how the policy's actions become joint torques.

A :class:`Controller` is one control law for one group of joints (``τ_cmd = F_con(π_θ)``); an
:class:`ActuatorChain` is what happens to a torque command between the controller and the joint (delay, motor
constant, friction, saturation). ``TocabiWalk`` builds them from its config (``env.control``), or takes a
user-defined leg controller: ``TocabiWalk(..., leg_controller=MyLaw())``. docs/concepts/controllers.md has the guide.
"""

from .._lazy import lazy_names

__all__ = ["Actuator", "ActuatorChain", "ActuatorConfig", "AssistedTorque", "ComputedTorqueResidual",
           "ControlContext", "ControlInput", "Controller", "Delay", "DirectTorque", "Friction", "HeldPD",
           "JointPD", "MotorConstant", "PDHold", "Saturation", "clip_torque"]

# Each name loads its submodule when first read: importing any submodule (a config dataclass for the run config
# tree and --help) runs this file first, and must not load the torch, torchrl and mujoco-warp code of the others.
__getattr__, __dir__ = lazy_names(globals(), {
    "actuators": ("Actuator", "ActuatorChain", "Delay", "Friction", "MotorConstant", "Saturation"),
    "base": ("ControlContext", "ControlInput", "Controller"),
    "computed_torque": ("ComputedTorqueResidual",),
    "config": ("ActuatorConfig",),
    "joint_pd": ("JointPD", "PDHold"),
    "torque": ("AssistedTorque", "DirectTorque", "HeldPD", "clip_torque"),
})
