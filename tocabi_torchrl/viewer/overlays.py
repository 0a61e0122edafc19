"""Overlays of the page: a metrics table (gait metrics while playing, the iteration's metrics while training) and
the selected robot's knee angles against the reference motion (a uPlot chart)."""

from __future__ import annotations

import math
from collections import deque

import numpy as np

__all__ = ["metrics_markdown", "KneeTrace", "MetricsPanel"]

#: How the gait metrics of a live policy are shown: key -> (label, unit, decimals).
GAIT_ROWS = {
    "seconds": ("time", "s", 2),
    "survival": ("survival", "", 3),
    "forward_distance_m": ("forward distance", "m", 2),
    "lateral_drift_m": ("lateral drift", "m", 3),
    "mean_speed_mps": ("mean speed", "m/s", 3),
    "speed_tracking_error_mps": ("speed error", "m/s", 3),
    "knee_rms_rad": ("knee RMS vs reference", "rad", 3),
}


def _number(value, decimals: int) -> str:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return str(value)
    if not math.isfinite(value):
        return "–"
    if isinstance(value, int):
        return f"{value:,}"
    # learning rates and KLs: small numbers keep their digits; times and distances are shown rounded
    tiny = 0 < abs(value) < 1e-3 and decimals >= 4
    return f"{value:.2e}" if tiny else f"{value:.{decimals}f}"


def metrics_markdown(metrics: dict, rows: dict | None = None, title: str | None = None) -> str:
    """``metrics`` as a two-column markdown table: with ``rows`` (key -> (label, unit, decimals)) those keys in
    that order (missing ones left out), else every scalar entry with 4 decimals. NaN shows as a dash."""
    lines = [f"**{title}**", ""] if title else []
    lines += ["| metric | value |", "|---|---|"]
    if rows is None:
        rows = {k: (k, "", 4) for k, v in metrics.items() if isinstance(v, (int, float))}
    for key, (label, unit, decimals) in rows.items():
        if key in metrics:
            shown = _number(metrics[key], decimals)
            lines.append(f"| {label} | {shown}{' ' + unit if unit and shown != '–' else ''} |")
    return "\n".join(lines)


class KneeTrace:
    """The last ``seconds`` of one robot's left/right knee angles and their reference [rad], drawn as a uPlot chart.

    :meth:`append` is cheap (host floats into ring buffers); :meth:`draw` sends the chart (call it a few times a
    second, not every step).
    """

    LABELS = ("left knee", "right knee", "left reference", "right reference")
    COLORS = ("#4073d9", "#d94c40", "#9bb5ea", "#eaa39b")

    def __init__(self, server, dt: float, seconds: float = 4.0):
        import viser.uplot as uplot

        self.dt = float(dt)
        self.length = max(2, int(round(seconds / dt)))
        self.t = deque(maxlen=self.length)
        self.series = [deque(maxlen=self.length) for _ in self.LABELS]
        series = (uplot.Series(label="t [s]"),) + tuple(
            uplot.Series(label=label, stroke=color, width=2 if i < 2 else 1)
            for i, (label, color) in enumerate(zip(self.LABELS, self.COLORS)))
        # x is seconds since the metrics restarted, not a date (uPlot's default x scale is time of day)
        self.handle = server.gui.add_uplot(data=self._arrays(), series=series, title="knee angle [rad]", aspect=1.6,
                                           scales={"x": uplot.Scale(time=False)})

    def _arrays(self) -> tuple[np.ndarray, ...]:
        if len(self.t) < 2:  # uPlot needs points: two at t = 0 until the first steps arrive
            return (np.zeros(2),) + tuple(np.zeros(2) for _ in self.LABELS)
        return (np.asarray(self.t),) + tuple(np.asarray(s) for s in self.series)

    def append(self, t: float, knees: np.ndarray, reference: np.ndarray) -> None:
        """One step at time ``t`` [s]: ``knees`` and ``reference`` (2,) left/right [rad] (NaN: a fallen robot)."""
        self.t.append(float(t))
        for s, value in zip(self.series, (*knees, *reference)):
            s.append(float(value))

    def clear(self) -> None:
        """Forget the trace (after a reset or when another robot is selected)."""
        self.t.clear()
        for s in self.series:
            s.clear()

    def draw(self) -> None:
        """Send the trace to the page."""
        self.handle.data = self._arrays()


class MetricsPanel:
    """A markdown block of metrics on the page; :meth:`show` replaces its content."""

    def __init__(self, server, text: str = "waiting for the first numbers…"):
        self.handle = server.gui.add_markdown(text)

    def show(self, metrics: dict, rows: dict | None = None, title: str | None = None) -> None:
        self.handle.content = metrics_markdown(metrics, rows, title)
