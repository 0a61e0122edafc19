"""Numerical health of a C MuJoCo world: which ``mjData.warning`` counters count, and the clear error when they fire.

C MuJoCo does not drop contacts or constraint rows silently as fixed mujoco-warp buffers do; it reports trouble through
warning counters and, for a non-finite or huge state, *resets the world to the model's default pose* (mj_checkPos /
mj_checkVel / mj_checkAcc). Such a world looks finite afterwards, so the warning counters, not the state, must mark it
unhealthy. The counters are cleared by ``mj_resetData``, so the bits stay set until the world is reset.
"""

from __future__ import annotations

import mujoco
import numpy as np

from .health import SimOverflowError

__all__ = ["MUJOCO_HEALTH_WARNINGS", "warning_bits", "warning_error"]

_W = mujoco.mjtWarning

_FIX = {
    _W.mjWARN_CONTACTFULL: "the contact buffer of the model's arena is full: raise <size memory=...> in the MJCF",
    _W.mjWARN_CNSTRFULL: "the constraint buffer of the model's arena is full: raise <size memory=...> in the MJCF",
    _W.mjWARN_BADQPOS: "non-finite or huge qpos: MuJoCo reset the world to the model's default pose",
    _W.mjWARN_BADQVEL: "non-finite or huge qvel: MuJoCo reset the world to the model's default pose",
    _W.mjWARN_BADQACC: "non-finite or huge qacc (simulation unstable): MuJoCo reset the world to its default pose",
}

#: ``1 << mjtWarning`` bits after which a world's trajectory is wrong (dropped contacts/constraints, or MuJoCo's own
#: reset of a diverged world). Not included: INERTIA (a model property) and BADCTRL (MuJoCo zeroes a non-finite
#: control; the env already treats NaN actions as 0).
MUJOCO_HEALTH_WARNINGS = sum(1 << int(w) for w in _FIX)


def warning_bits(numbers: np.ndarray) -> np.ndarray:
    """(N, mjNWARNING) warning counters -> (N,) int32 bitmask, bit ``k`` set when warning ``k`` fired."""
    weights = 1 << np.arange(numbers.shape[1], dtype=np.int64)
    return ((numbers > 0) @ weights).astype(np.int32)


def warning_error(bits: np.ndarray, mask: int = MUJOCO_HEALTH_WARNINGS) -> SimOverflowError | None:
    """The error to raise for per-world warning bits (N,), or ``None`` if no bit in ``mask`` is set."""
    hit = (bits.astype(np.int64) & int(mask)) != 0
    if not hit.any():
        return None
    worlds = np.flatnonzero(hit)
    union = int(np.bitwise_or.reduce(bits[worlds].astype(np.int64)))
    causes = "; ".join(f"{w.name}: {text}" for w, text in _FIX.items() if union & (1 << int(w)))
    shown = ", ".join(map(str, worlds[:8])) + (" ..." if len(worlds) > 8 else "")
    return SimOverflowError(
        f"{len(worlds)} world(s) raised MuJoCo warnings (worlds {shown}): {causes}. healthy=False marks them until "
        "they are reset."
    )
