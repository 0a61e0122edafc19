"""The env's control laws from its config: ``env.control.mode`` names the legs' controller, the upper body is held
by :class:`~tocabi_torchrl.control.PDHold`, and ``env.control.actuators`` is the legs' actuator layer."""

from __future__ import annotations

from ..control import (ActuatorChain, AssistedTorque, ComputedTorqueResidual, Controller, DirectTorque, HeldPD,
                       JointPD, PDHold)
from .config import ControlConfig
from .model_based import ComputedTorque

__all__ = ["leg_law", "upper_body_law", "leg_actuator_chain"]


def leg_law(control: ControlConfig) -> Controller:
    """The legs' law for ``control.mode`` (and ``control.torque_assist``), with the config's numbers."""
    if control.torque_assist:
        return AssistedTorque(control.pd_kp, control.pd_kv, control.pd_action_scale)
    if control.mode == "torque":
        return DirectTorque()
    if control.mode == "pd_held":
        return HeldPD(control.pd_kp, control.pd_kv, control.pd_action_scale)
    if control.mode == "model_based":
        def make_law(ctx):
            return ComputedTorque(control, ctx.motion, ctx.sim.mj_model, ctx.num_envs, ctx.device, ctx.dt)

        return ComputedTorqueResidual(control.mb_residual_gain, make_law)
    centre = "nominal" if control.mode == "pd" else "reference"
    return JointPD(control.pd_kp, control.pd_kv, control.pd_action_scale, control.pd_nominal, centre=centre)


def upper_body_law(control: ControlConfig) -> Controller:
    """The upper body's law for ``control.upper_body``: ``"pd_hold"``, the reference pose held by the model's own
    position servos (the only one today)."""
    return {"pd_hold": PDHold}[control.upper_body]()


def leg_actuator_chain(control: ControlConfig, substeps: int) -> ActuatorChain:
    """The legs' actuator layer (empty, i.e. ideal, by default)."""
    return control.actuators.build(substeps)
