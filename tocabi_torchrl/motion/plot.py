"""Figure of a cycle's leg joint trajectories, optionally over a second motion (e.g. the reference walk)."""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np

from tocabi_torchrl.robot import JOINT_NAMES

from ..atomic import atomic_write_bytes
from .io import MotionData
from .schedule import DOUBLE_SUPPORT

__all__ = ["plot_leg_joints"]


def _phase(data: MotionData) -> np.ndarray:
    return np.arange(data.num_rows) / (data.num_rows - 1)


def plot_leg_joints(
    motion: MotionData, reference: MotionData | None, path: str | os.PathLike, dpi: int = 110
) -> Path:
    """Write a 6 × 2 grid (joint × leg) of joint angle over cycle phase; double supports are shaded.

    Args:
        motion: the cycle to show (solid lines).
        reference: optional motion drawn dashed underneath (same phase axis: row / (R − 1)).
        path: output PNG.
    """
    # A Figure on its own Agg canvas, not pyplot: the caller's matplotlib backend (a notebook's) stays as it was.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 12))
    FigureCanvasAgg(fig)
    axes = fig.subplots(6, 2, sharex=True)
    phase = _phase(motion)
    dsp = motion.stance == DOUBLE_SUPPORT
    for j in range(12):
        ax = axes[j % 6, j // 6]
        ax.fill_between(phase, 0, 1, where=dsp, transform=ax.get_xaxis_transform(), color="0.92", lw=0)
        if reference is not None:
            ax.plot(_phase(reference), reference.joint_pos[:, j], "--", color="0.35", lw=1.4, label="reference")
        ax.plot(phase, motion.joint_pos[:, j], color="C0" if j < 6 else "C3", lw=1.6, label="generated")
        ax.set_title(JOINT_NAMES[j].removesuffix("_Joint"), fontsize=9)
        ax.tick_params(labelsize=8)
        ax.set_ylabel("rad", fontsize=8)
    for ax in axes[-1]:
        ax.set_xlabel("cycle phase (row / (R-1)); shaded: double support", fontsize=8)
    axes[0, 0].legend(fontsize=8, loc="best")
    fig.suptitle("TOCABI walking cycle: leg joint targets", fontsize=11)
    fig.tight_layout()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    # Rendered in memory, then written atomically: an interrupted run leaves the earlier figure (e.g. the docs' one,
    # regenerated with --overwrite) whole, never half a PNG.
    buffer = io.BytesIO()
    fig.savefig(buffer, format=out.suffix[1:].lower() or "png", dpi=dpi)
    return atomic_write_bytes(out, buffer.getvalue())
