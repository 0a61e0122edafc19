"""Reference motions: loading, phase schedule, batched lookup on the device, and the project's own gait generator.

* :mod:`.reference` - :class:`ReferenceMotion`, the table on a device with sync-free per-env lookups (spec §3.2).
* :mod:`.io`        - the reference ``.txt`` and the project ``.npz`` formats, validation (:class:`MotionFormatError`).
* :mod:`.schedule`  - foot-force references (spec §3.3) and the reward's stance pattern (spec §8) per row.
* :mod:`.gait`      - generates the shipped cycle ``assets/motions/tocabi_walk.npz`` (``python -m ...motion.gait``).
* :mod:`.kinematics`, :mod:`.lipm`, :mod:`.analysis`, :mod:`.plot` - leg IK/FK, CoM plan, structure checks, figure.
"""

from .io import MotionData, MotionFormatError, load_motion, load_npz, load_txt, save_npz
from .reference import ReferenceMotion
from .schedule import DOUBLE_SUPPORT, LEFT_STANCE, RIGHT_STANCE, force_schedule, stance_schedule

__all__ = [
    "ReferenceMotion",
    "MotionData",
    "MotionFormatError",
    "load_motion",
    "load_npz",
    "load_txt",
    "save_npz",
    "force_schedule",
    "stance_schedule",
    "DOUBLE_SUPPORT",
    "RIGHT_STANCE",
    "LEFT_STANCE",
]
