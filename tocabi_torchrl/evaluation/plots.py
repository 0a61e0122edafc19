"""Figures of the evaluations: the gait test's knee trajectories against the reference (``knees.png``), the robust
gait test's distributions per case (``robust.png``), and the experiment recipes' knee comparison, joint torques and
obstacle-height curves (the experiments in ``lab/experiments/``).

Figures are drawn on their own ``matplotlib.figure.Figure`` with the Agg canvas, never through ``pyplot``: the
caller's matplotlib backend (a notebook's, a GUI's) stays as it was. Each file is written atomically
(:mod:`tocabi_torchrl.atomic`): an interrupted run leaves the earlier figure whole, never half a PNG."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_bytes

__all__ = ["MARKED_ROBOTS", "check_plotting", "ecdf", "new_figure", "plot_joint_torques", "plot_knee_comparison",
           "plot_knees", "plot_robust", "plot_vs_height", "robust_figure", "save_figure"]


def check_plotting(instead: str = "") -> None:
    """An ``ImportError`` naming the install command unless matplotlib, which draws the gait tests' ``knees.png`` and
    ``robust.png``, is installed; ``instead``: what the caller may do without it, appended. It is no core dependency
    (the ``viz`` extra's), and the gait test needs it only after its rollout: checked up front, a missing one costs no
    rollout (minutes on a CPU) and no recipe's training (hours)."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise ImportError('the gait test draws knees.png with matplotlib, which is not installed: pip install -e '
                          f'".[viz]" in the repository (or pip install matplotlib){instead}') from None


def new_figure(**kwargs):
    """A new figure on an Agg canvas of its own (no ``pyplot``, so no global backend switch and nothing to close)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(**kwargs)
    FigureCanvasAgg(fig)
    return fig


def figure_format(path: str | Path) -> str:
    """The image format :func:`save_figure` writes ``path`` in: its suffix, PNG without one.

    >>> figure_format("curves.PDF"), figure_format("out/curves")
    ('pdf', 'png')
    """
    return Path(path).suffix[1:].lower() or "png"


def save_figure(fig, path: str | Path, title: str, dpi: int = 120) -> Path:
    """Render ``fig`` (format from ``path``'s suffix, PNG by default: :func:`figure_format`) with ``title`` in its
    metadata and write it to ``path`` atomically."""
    path = Path(path)
    buffer = io.BytesIO()
    fig.savefig(buffer, format=figure_format(path), dpi=dpi, metadata={"Title": title})
    return atomic_write_bytes(path, buffer.getvalue())


def plot_knees(q: np.ndarray, ref: np.ndarray, dt: float, path: Path, command: tuple[float, float]) -> None:
    """Left and right knee angles (T, 2) [rad] of env 0 against the reference's over time, one panel each (TocabiLab
    figs 4.7-4.8), a red line where the episode ended (NaN rows); saved to ``path``."""
    t = (np.arange(len(q)) + 1) * dt  # row k is the state after the k-th policy step
    fig = new_figure(figsize=(8, 5))
    axes = fig.subplots(2, 1, sharex=True)
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
    save_figure(fig, path, title)


#: Robots per case up to which the robust figure's CDFs mark each robot: one robot's CDF is a single step, which a
#: line alone does not show, and a few robots' steps read better as points.
MARKED_ROBOTS = 32


def ecdf(values) -> tuple[np.ndarray, np.ndarray]:
    """The empirical CDF of ``values`` (N,) over its non-NaN entries, as points for ``step(where="post")``: x sorted
    with its first value repeated, y = 0, 1/n, ..., 1 (the fraction of robots at or below x), so that the curve
    rises from 0 at the smallest value (one robot: a vertical line from 0 to 1). Empty arrays when none is finite.

    >>> ecdf([2.0, float("nan"), 1.0])
    (array([1., 1., 2.]), array([0. , 0.5, 1. ]))
    """
    x = np.sort(np.asarray(values, dtype=float))
    x = x[~np.isnan(x)]
    if not x.size:
        return x, x
    return np.concatenate([x[:1], x]), np.arange(x.size + 1) / x.size


def _draw_ecdf(ax, values, **style) -> None:
    """One CDF of ``values`` on ``ax`` (:func:`ecdf`), each robot marked when there are at most
    :data:`MARKED_ROBOTS` (the marks sit on the line's points after the first, which is the rise from 0)."""
    x, y = ecdf(values)
    if not x.size:
        return
    marked = x.size - 1 <= MARKED_ROBOTS
    ax.step(x, y, where="post", marker="o" if marked else None, markevery=list(range(1, x.size)) if marked else None,
            markersize=4, clip_on=not marked, **style)  # unclipped: a mark at y = 1 shows whole


def robust_figure(per_case: dict, report: dict):
    """The robust gait test in one figure (see :func:`plot_robust`), returned unsaved: a
    ``matplotlib.figure.Figure`` whose axes are survival, then the CDFs of distance, drift and tracking error."""
    names = list(per_case)
    colors = {name: f"C{i}" for i, name in enumerate(names)}
    fig = new_figure(figsize=(11, 7.5))
    axes = fig.subplots(2, 2).ravel()
    ax = axes[0]
    survival = [float(np.asarray(per_case[n]["alive"], dtype=float).mean()) for n in names]
    ax.bar(range(len(names)), survival, color=[colors[n] for n in names])
    for i, name in enumerate(names):
        check = report["cases"][name].get("checks", {}).get("survival")
        if check is not None:
            limit = float(check["needs"].split()[1])
            ax.hlines(limit, i - 0.4, i + 0.4, color="k", ls=":", lw=1.2)
        ax.text(i, min(survival[i], 1.0) + 0.01, f"{survival[i]:.3f}", ha="center", va="bottom", fontsize=8)
    ax.set_xticks(range(len(names)), names)
    ax.set_ylim(0, 1.1)
    ax.set_ylabel("survival fraction (dotted: threshold)")
    ax.grid(alpha=0.3, axis="y")
    panels = (("forward_m", "forward distance [m]", "forward_distance_m", np.asarray),
              ("lateral_m", "lateral drift |y| [m]", "lateral_drift_m", np.abs),
              ("tracking_error_mps", ("speed tracking error, heading frame [m/s]\n"
                                      "solid: of the gait-cycle mean velocity; dashed: instantaneous"),
               "tracking_error_mps", np.asarray))
    for ax, (key, label, metric, fn) in zip(axes[1:], panels):
        for name in names:
            keys = [(key, "-")] + ([("instant_speed_error_mps", "--")] if key == "tracking_error_mps"
                                   and "instant_speed_error_mps" in per_case[name] else [])
            for series, style in keys:
                _draw_ecdf(ax, fn(np.asarray(per_case[name][series], dtype=float)), color=colors[name], ls=style,
                           label=name if style == "-" else None)
            for path_, check in report["cases"][name].get("checks", {}).items():
                if path_.split(".")[0] == metric:
                    ax.axvline(float(check["needs"].split()[1]), color=colors[name], ls=":", lw=1.2)
        ax.set_ylim(0, 1)  # a fraction: autoscaled, one robot's CDF at 1 showed 0.95-1.05
        ax.set_xlabel(label)
        ax.set_ylabel("fraction of robots")
        ax.grid(alpha=0.3)
    axes[1].legend(loc="lower right", fontsize=8)
    fig.suptitle(_robust_title(report))
    fig.tight_layout()
    return fig


def _robust_title(report: dict) -> str:
    """The robust figure's title, also its file's metadata title: the test's length, robots and verdict."""
    s = report["settings"]
    return (f"Robust gait test ({s['seconds']:g} s, {s['num_envs']} robots per case): "
            + ("passes" if report["passes"] else "fails"))


def plot_robust(per_case: dict, report: dict, path: Path) -> Path:
    """The robust gait test in one figure: survival per case (bars, its threshold marked), and the CDFs over the
    robots of forward distance [m], lateral drift |y| [m] and heading-frame speed tracking error [m/s] (of the
    gait-cycle mean velocity, solid; the instantaneous error, dashed, where ``per_case`` has it), one line per case
    (each robot marked when a case has few, :data:`MARKED_ROBOTS`), the thresholds of
    :data:`~tocabi_torchrl.evaluation.gait_test.ROBUST_CRITERIA` as dotted lines in the case's colour.
    ``per_case``: case -> per-robot (N,) tensors or arrays (``robust.run_case``); ``report``: the report whose
    ``cases`` hold the checks. Saved to ``path`` (:func:`robust_figure` draws it)."""
    return save_figure(robust_figure(per_case, report), path, _robust_title(report))


# ------------------------------------------------------------------------------------------------ experiment figures
def plot_knee_comparison(traces: dict[str, tuple[np.ndarray, np.ndarray]], dt: float, out_dir: Path,
                         command: tuple[float, float], stem: str = "knee") -> list[Path]:
    """One figure per knee (``<stem>_left.png``, ``<stem>_right.png``): every controller's knee angle [rad] of env 0
    and the reference, over time (TocabiLab figs 4.7-4.8, several controllers on one axis).

    ``traces``: label -> ((T, 2) knee angles, NaN after a termination; (T, 2) the reference of that rollout). Each
    rollout has its own reference (the phase action speeds its clock up), so the references are drawn once, in black,
    when they agree within 1 mrad, and else dashed in each controller's colour. A mark shows where an env 0
    terminated. Returns the two paths."""
    refs = [ref for _, ref in traces.values()]
    shared = all(r.shape == refs[0].shape and np.allclose(r, refs[0], atol=1e-3) for r in refs)
    paths = []
    for i, side in enumerate(("left", "right")):
        fig = new_figure(figsize=(9, 3.6))
        ax = fig.subplots()
        for j, (label, (q, ref)) in enumerate(traces.items()):
            color = f"C{j}"
            t = (np.arange(len(q)) + 1) * dt
            ax.plot(t, q[:, i], color=color, lw=1.5, label=label)
            if not shared:
                ax.plot(t, ref[:, i], color=color, ls="--", lw=1.0, label=f"{label}: reference")
            fell = np.flatnonzero(np.isnan(q[:, i]))
            if fell.size:
                ax.axvline(t[fell[0]], color=color, ls=":", lw=1.0, label=f"{label}: terminated")
        if shared and refs:
            t = (np.arange(len(refs[0])) + 1) * dt
            ax.plot(t, refs[0][:, i], "k--", lw=1.2, label="reference")
        ax.set_xlabel("time [s]")
        ax.set_ylabel(f"{side} knee [rad]")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
        title = f"{side.capitalize()} knee at command ({command[0]:g}, {command[1]:g}) m/s, env 0"
        ax.set_title(title)
        fig.tight_layout()
        paths.append(save_figure(fig, Path(out_dir) / f"{stem}_{side}.png", title))
    return paths


def plot_joint_torques(traces: dict[str, np.ndarray], dt: float, path: Path, joints: tuple[str, ...],
                       title: str, t0: dict[str, float] | None = None, xlabel: str = "time [s]",
                       limits: np.ndarray | None = None, mark_zero: bool = False) -> Path:
    """Joint torques [N·m] over time, one panel per joint (3 rows: hip pitch, knee, ankle pitch; columns: left,
    right, for the six sagittal ``joints`` the gait comparison plots), one line per controller.

    ``traces``: label -> (T, len(joints)) torques, step k at time (k + 1)·dt − ``t0[label]`` (default 0);
    ``limits``: (len(joints),) torque limits drawn as grey lines; ``mark_zero``: a black line at t = 0 (e.g. the
    first contact with an obstacle). Saved to ``path``."""
    cols = 2 if len(joints) % 2 == 0 else 1
    rows = len(joints) // cols
    fig = new_figure(figsize=(5.2 * cols, 2.2 * rows + 0.6))
    axes = fig.subplots(rows, cols, sharex=True, squeeze=False)
    for c in range(cols):
        for r in range(rows):
            ax = axes[r, c]
            j = c * rows + r
            for i, (label, tau) in enumerate(traces.items()):
                t = (np.arange(len(tau)) + 1) * dt - (t0 or {}).get(label, 0.0)
                ax.plot(t, tau[:, j], color=f"C{i}", lw=1.1, label=label)
            if mark_zero:
                ax.axvline(0.0, color="k", lw=0.8)
            if limits is not None:
                for sign in (-1, 1):
                    ax.axhline(sign * limits[j], color="0.6", lw=0.8, ls=":")
            ax.set_title(joints[j].replace("_Joint", ""), fontsize=9)
            ax.grid(alpha=0.3)
            if c == 0:
                ax.set_ylabel("torque [N·m]")
            if r == rows - 1:
                ax.set_xlabel(xlabel)
    axes[0, 0].legend(loc="upper right", fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return save_figure(fig, path, title)


def plot_vs_height(rows: list[dict], key: str, ylabel: str, path: Path, title: str) -> Path:
    """One line per controller of ``row[key]`` against ``row["height_mm"]`` (rows of the obstacle table)."""
    fig = new_figure(figsize=(6.4, 3.8))
    ax = fig.subplots()
    for i, label in enumerate(dict.fromkeys(row["controller"] for row in rows)):
        mine = sorted((row["height_mm"], row[key]) for row in rows if row["controller"] == label)
        x, y = zip(*mine)
        ax.plot(x, [np.nan if v is None else v for v in y], "o-", color=f"C{i}", label=label)
    ax.set_xlabel("obstacle height [mm]")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title)
    fig.tight_layout()
    return save_figure(fig, path, title)
