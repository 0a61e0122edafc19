"""The physics backend: mujoco-warp worlds, zero-copy torch views, recorded graphs, masked reset, contact signals.

``WarpSim(SimConfig(num_worlds=4096, device="cuda"))`` builds the shipped TOCABI; see ``warp_backend`` for the tensors
it exposes, ``contacts`` for how contact signals come from MuJoCo contact sensors, ``config`` for the measured buffer
sizes and ``health`` for overflow handling.
"""

from .config import CONTACT_SENSOR_MAXMATCH, NCONMAX, NJMAX, SimConfig
from .contacts import ContactLayout, ContactSensorError, add_contact_sensors, contact_layout, has_contact_sensors
from .health import HEALTH_OVERFLOW_MASK, SimOverflowError
from .warp_backend import WarpSim

__all__ = [
    "WarpSim",
    "SimConfig",
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
