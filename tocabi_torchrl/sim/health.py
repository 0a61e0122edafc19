"""Numerical health of a world: which mujoco-warp overflow flags count, and the clear error when they fire."""

from __future__ import annotations

import numpy as np
from mujoco_warp import OverflowType

__all__ = ["HEALTH_OVERFLOW_MASK", "SimOverflowError", "describe_overflow", "overflow_error"]

#: Overflows after which a world's physics is silently wrong: contacts or constraint rows were dropped.
#: Not included: ITERATIONS / LS_ITERATIONS (the solver stopped at its iteration limit, a normal event with tight
#: tolerances), CONTACT_MATCH (``found`` counts stay exact past the slot limit), EPA_HORIZON and TACTILE.
HEALTH_OVERFLOW_MASK = (
    OverflowType.NEFC
    | OverflowType.NJMAX_NNZ
    | OverflowType.BROADPHASE
    | OverflowType.NARROWPHASE
    | OverflowType.CCD
    | OverflowType.HFIELD
    | OverflowType.NVMAX
)

_FIX = {
    OverflowType.NEFC: "more constraint rows than njmax: raise SimConfig.njmax",
    OverflowType.NJMAX_NNZ: "constraint Jacobian non-zeros overflowed: raise SimConfig.njmax",
    OverflowType.BROADPHASE: "more candidate collision pairs than nconmax*num_worlds: raise SimConfig.nconmax",
    OverflowType.NARROWPHASE: "more contacts than nconmax*num_worlds: raise SimConfig.nconmax",
    OverflowType.CCD: "more convex-collision pairs than nccdmax*num_worlds: raise SimConfig.nccdmax "
                      "(env.sim.nccdmax)",
    OverflowType.HFIELD: "height-field collision buffer overflowed: simplify the height field",
    OverflowType.NVMAX: "island dof buffer overflowed",
    OverflowType.CONTACT_MATCH: "contact sensor slots overflowed (counts stay exact): raise contact_sensor_maxmatch",
    OverflowType.EPA_HORIZON: "EPA horizon buffer overflowed in convex collision",
    OverflowType.ITERATIONS: "solver hit its iteration limit",
    OverflowType.LS_ITERATIONS: "line search hit its iteration limit",
    OverflowType.TACTILE: "tactile sensor buffer overflowed",
}


class SimOverflowError(RuntimeError):
    """A world overflowed a mujoco-warp buffer; the message says which buffer and which setting to raise."""


def describe_overflow(bits: int) -> list[str]:
    """Human-readable causes and fixes for an ``OverflowType`` bitmask."""
    return [f"{flag.name}: {text}" for flag, text in _FIX.items() if int(bits) & int(flag)]


def overflow_error(overflow: np.ndarray, mask: int, nconmax: int, njmax: int) -> SimOverflowError | None:
    """The error to raise for per-world overflow bits ``overflow`` (N,), or ``None`` if no bit in ``mask`` is set."""
    hit = (overflow.astype(np.int64) & int(mask)) != 0
    if not hit.any():
        return None
    worlds = np.flatnonzero(hit)
    bits = int(np.bitwise_or.reduce(overflow[worlds].astype(np.int64)))
    shown = ", ".join(map(str, worlds[:8])) + (" ..." if len(worlds) > 8 else "")
    causes = "; ".join(describe_overflow(bits & int(mask)))
    return SimOverflowError(
        f"{len(worlds)} world(s) overflowed mujoco-warp buffers (worlds {shown}; nconmax={nconmax}, njmax={njmax}): "
        f"{causes}. Their physics is wrong from that step on and healthy=False marks them; the TOCABI defaults "
        "(sim.config.NCONMAX/NJMAX) are measured for one robot on a plane, so a scene with more geometry needs more."
    )
