"""The gait test's figure: knee trajectories against the reference (``knees.png``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["plot_knees"]


def plot_knees(q: np.ndarray, ref: np.ndarray, dt: float, path: Path, command: tuple[float, float]) -> None:
    """Left and right knee angles (T, 2) [rad] of env 0 against the reference's over time, one panel each (TocabiLab
    figs 4.7-4.8), a red line where the episode ended (NaN rows); saved to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.arange(len(q)) * dt
    fig, axes = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    fell = np.flatnonzero(np.isnan(q[:, 0]))
    for i, (ax, side) in enumerate(zip(axes, ("left", "right"))):
        ax.plot(t, ref[:, i], "k--", lw=1.2, label="reference")
        ax.plot(t, q[:, i], lw=1.5, label="policy")
        if fell.size:
            ax.axvline(t[fell[0]], color="r", lw=1.0, label="episode terminated")
        ax.set_ylabel(f"{side} knee [rad]")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right")
    axes[-1].set_xlabel("time [s]")
    title = f"Knee trajectories at command ({command[0]:g}, {command[1]:g}) m/s, env 0"
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120, metadata={"Title": title})
    plt.close(fig)
