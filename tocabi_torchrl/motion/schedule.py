"""Gait phase schedule of a two-step walking cycle: foot-force references and the reward's stance pattern.

Both are functions of the integer row index only, so the reference file, the project's generated cycle and any other
cycle with the same layout share them. The layout (spec §3.3) is a cycle of ``2·S`` rows (``S`` rows per step) that
starts in the middle of a double support with the weight moving onto the right foot::

    rows   0 .. H-1          second half of a double support, load moving L -> R
           H .. S-H          right single support (left foot swings)
         S-H .. S+H          double support, load moving R -> L   (its middle, row S, is the second start row)
         S+H .. 2S-H         left single support (right foot swings)
        2S-H .. 2S-1         first half of the next double support, load moving L -> R

with ``D`` double-support rows and ``H = D/2``. The reference walk has ``S = 1800``, ``D = 600`` at 2 kHz
(0.9 s steps, 0.3 s double support). The exact integer boundaries below reproduce the reference (``walk.m`` for the
forces, the reward code for the stance pattern, off-by-one quirks included); tests check them row by row against the
reference file when it is present.
"""

from __future__ import annotations

import numpy as np

from tocabi_torchrl.robot import GRAVITY, NOMINAL_MASS

__all__ = [
    "DOUBLE_SUPPORT",
    "RIGHT_STANCE",
    "LEFT_STANCE",
    "REFERENCE_WEIGHT_FORCE",
    "smoothstep",
    "cycle_layout",
    "force_schedule",
    "stance_schedule",
]

#: Stance codes of :func:`stance_schedule` (and of ``ReferenceMotion.stance``).
DOUBLE_SUPPORT, RIGHT_STANCE, LEFT_STANCE = 0, 1, 2

#: Full-weight vertical foot force [N]; the reference rounds m·g = 1025.02 N to 1025 N (spec §3.3).
REFERENCE_WEIGHT_FORCE: float = float(round(NOMINAL_MASS * GRAVITY))


def smoothstep(s: np.ndarray) -> np.ndarray:
    """Zero-velocity cubic ``3s² − 2s³`` of ``s`` clamped to [0, 1] (the reference's ``cubic`` helper, normalised)."""
    s = np.clip(s, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def cycle_layout(num_rows: int, dsp_rows: int) -> tuple[int, int]:
    """Rows per step ``S`` and half double-support rows ``H`` of a ``num_rows`` two-step cycle.

    Raises ``ValueError`` for layouts the schedule cannot describe (odd row count, double support longer than a step).
    """
    if num_rows < 2 or num_rows % 2:
        raise ValueError(f"a two-step cycle needs an even number of rows >= 2, got {num_rows}")
    step_rows = num_rows // 2
    # At least two rows: each double support has a half on either side of its middle row.
    if dsp_rows < 2 or dsp_rows > step_rows or dsp_rows % 2:
        raise ValueError(f"double support must be an even number of rows in [2, {step_rows}], got {dsp_rows}")
    return step_rows, dsp_rows // 2


def force_schedule(num_rows: int, dsp_rows: int, weight: float = REFERENCE_WEIGHT_FORCE) -> np.ndarray:
    """Reference vertical foot forces, shape ``(num_rows, 2)`` [left, right] in N, sensor sign (loaded < 0).

    Spec §3.3: the left load follows a zero-velocity cubic across each double support, the right load is the rest,
    ``Fz_R = −weight − Fz_L``. Boundaries are those of ``walk.m`` in 0-based rows (e.g. for the reference:
    ``−509.9`` N at row 0, exactly 0 from row 299 to 1499, ``−512.5`` N at rows 1799 and 3599).
    """
    step_rows, half = cycle_layout(num_rows, dsp_rows)
    f = -float(weight)
    k = np.arange(num_rows, dtype=np.float64)
    d = float(dsp_rows)
    left = np.empty(num_rows)
    # The loops of walk.m (1-based) shifted to 0-based rows; each row range is half-open here.
    a, b = half - 1, step_rows - half  # right single support: rows [H-1, S-H)
    c, e = step_rows + half - 1, 2 * step_rows - half  # left single support: rows [S+H-1, 2S-H)
    # Rows before the right single support continue the last double support of the previous cycle (k + 2S).
    left[:a] = f * (1.0 - smoothstep((k[:a] + half + 1) / d))
    left[a:b] = 0.0
    left[b:c] = f * smoothstep((k[b:c] - (step_rows - half - 1)) / d)
    left[c:e] = f
    left[e:] = f * (1.0 - smoothstep((k[e:] - (2 * step_rows - half - 1)) / d))
    return np.stack([left, f - left], axis=1)


def stance_schedule(num_rows: int, dsp_rows: int) -> np.ndarray:
    """Contact pattern the reward expects at each row, shape ``(num_rows,)`` int64.

    Spec §8: double support (0) if ``k < H`` or ``S−H < k < S+H`` or ``2S−H < k``; right stance (1) if
    ``H < k < S−H``; otherwise left stance (2). "Otherwise" includes the single rows ``H`` and ``S−H`` (300 and 1500
    for the reference): the reward's off-by-one quirk, kept on purpose so rewards match the reference.
    """
    step_rows, half = cycle_layout(num_rows, dsp_rows)
    k = np.arange(num_rows)
    s, h = step_rows, half
    dsp = (k < h) | ((k > s - h) & (k < s + h)) | (k > 2 * s - h)
    right = (k > h) & (k < s - h)
    return np.where(dsp, DOUBLE_SUPPORT, np.where(right, RIGHT_STANCE, LEFT_STANCE)).astype(np.int64)
