"""The TOCABI lab's uncertainty model as one named set, ``tocabi_lab``, over the pieces that model it.

The lab's training code, which took torque policies to the real TOCABI, draws per env at every reset:

==================================== ======================================= ======================================
what                                 distribution                            where it lives here
==================================== ======================================= ======================================
motor constant, per leg joint        ×U(0.8, 1.2)                            ``env.control.actuators.motor_constant``
torque delay                         2-10 ms (4-20 physics substeps of 0.5 ms) ``env.control.actuators.delay_substeps``
link mass (and inertia)              ×U(0.8, 1.2)                            ``env.dynamics.mass_scale``
joint damping                        +U(0, 2.9) N·m·s/rad                     ``env.dynamics.joint_damping``
armature                             ×U(0.8, 1.2)                            ``env.dynamics.armature_scale``
joint-position bias                  U(±π/100) rad                           ``transforms.sensor_noise``
IMU orientation bias                 U(±π/150) rad per axis                  ``transforms.sensor_noise``
foot F/T force / moment bias         U(±100 N) / U(±10 N·m) per axis         ``transforms.sensor_noise``
encoder noise                        σ = 0.00016/3 rad, clipped ±0.00016 rad ``transforms.sensor_noise``
==================================== ======================================= ======================================

Pushes are separate (``env.pushes``, a training curriculum and the robust gait test's kicks). Every piece is off in
every preset but ``torque``, ``robust`` and ``model_based``, which train with the whole set; :func:`tocabi_lab`
switches all of them on in a run config or an env config (the sensor noise lives in the run config's transforms
section, so an env config alone gets the env's share).

>>> from tocabi_torchrl.config import preset_tree
>>> cfg = tocabi_lab(preset_tree("torque_ideal"))
>>> cfg.env.control.actuators.delay_substeps, cfg.env.dynamics.mass_scale
((4, 20), (0.8, 1.2))
"""

from __future__ import annotations

import dataclasses
import math
from typing import TypeVar

from .control.config import ActuatorConfig
from .sim.dynamics_config import DynamicsRandomization
from .transforms.sensor_noise_config import SensorNoiseConfig
from .tree import replace_paths

__all__ = ["tocabi_lab", "tocabi_lab_paths", "TOCABI_LAB_ACTUATORS", "TOCABI_LAB_DYNAMICS"]

#: The lab's actuator model: torque delay 2-10 ms (in 0.5 ms substeps) and motor constant ×U(0.8, 1.2).
TOCABI_LAB_ACTUATORS = ActuatorConfig(delay_substeps=(4, 20), motor_constant=(0.8, 1.2))
#: The lab's dynamics: link mass ×U(0.8, 1.2), joint damping +U(0, 2.9) N·m·s/rad, armature ×U(0.8, 1.2).
TOCABI_LAB_DYNAMICS = DynamicsRandomization(mass_scale=(0.8, 1.2), joint_damping=(0.0, 2.9),
                                            armature_scale=(0.8, 1.2))

Config = TypeVar("Config")


def tocabi_lab_paths(env_only: bool = False) -> dict[str, object]:
    """The set as dotted paths of the run config tree (what a preset adds); ``env_only``: without the transforms'
    sensor noise."""
    paths: dict[str, object] = {"env.control.actuators": TOCABI_LAB_ACTUATORS, "env.dynamics": TOCABI_LAB_DYNAMICS}
    if not env_only:
        paths["transforms.sensor_noise"] = SensorNoiseConfig.tocabi_lab()
    return paths


def tocabi_lab(cfg: Config) -> Config:
    """``cfg`` (a ``RunConfig``, or a ``TocabiWalkConfig``) with the TOCABI lab's uncertainty model switched on.

    The actuator stages act on torque commands only: the env config refuses them in the PD modes, so use it with a
    torque-level control mode (``torque``, ``model_based``, ``pd_held``)."""
    if dataclasses.is_dataclass(cfg) and hasattr(cfg, "env") and hasattr(cfg, "transforms"):
        return replace_paths(cfg, tocabi_lab_paths())
    return replace_paths(cfg, {path.removeprefix("env."): value
                               for path, value in tocabi_lab_paths(env_only=True).items()})


assert math.isclose(SensorNoiseConfig.tocabi_lab().joint_pos_bias, math.pi / 100)  # the table above
