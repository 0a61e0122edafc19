"""The physics backends: mujoco-warp worlds (GPU or CPU) or C MuJoCo on CPU threads, behind one tensor interface.

``WarpSim(SimConfig(num_worlds=4096, device="cuda"))`` builds the shipped TOCABI in mujoco-warp; see ``warp_backend``
for the tensors it exposes, ``contacts`` for how contact signals come from MuJoCo contact sensors, ``config`` for the
measured buffer sizes and ``health`` for overflow handling. ``MujocoSim(SimConfig(num_worlds=32, threads=16))`` steps
the same model with MuJoCo's C engine (``mujoco_backend``, health in ``mujoco_health``); ``views`` holds the interface
both share, and ``backend`` spells that interface out (``SimBackend``, ``check_backend``).
"""

from .._lazy import lazy_names

__all__ = [
    "WarpSim",
    "MujocoSim",
    "SimBackend",
    "SIM_TENSORS",
    "check_backend",
    "MUJOCO_HEALTH_WARNINGS",
    "SimConfig",
    "RESET_PASSES",
    "NCONMAX",
    "NJMAX",
    "CONTACT_SENSOR_MAXMATCH",
    "ContactLayout",
    "ContactSensorError",
    "add_contact_sensors",
    "contact_layout",
    "has_contact_sensors",
    "HEALTH_OVERFLOW_MASK",
    "SimOverflowError",
]

# Each name loads its submodule when first read: importing any submodule (a config dataclass for the run config
# tree and --help) runs this file first, and must not load the torch, torchrl and mujoco-warp code of the others.
__getattr__, __dir__ = lazy_names(globals(), {
    "backend": ("SIM_TENSORS", "SimBackend", "check_backend"),
    "config": ("CONTACT_SENSOR_MAXMATCH", "NCONMAX", "NJMAX", "RESET_PASSES", "SimConfig"),
    "contacts": ("ContactLayout", "ContactSensorError", "add_contact_sensors", "contact_layout", "has_contact_sensors"),
    "health": ("HEALTH_OVERFLOW_MASK", "SimOverflowError"),
    "mujoco_backend": ("MujocoSim",),
    "mujoco_health": ("MUJOCO_HEALTH_WARNINGS",),
    "warp_backend": ("WarpSim",),
})
