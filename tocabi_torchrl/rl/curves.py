"""Training curves from a run's metrics: return and episode length, and every reward term (TocabiLab's figs 4.2-4.3
show the total and the imitation rewards), and, where the run logged them, the PPO update's learning rate, KL,
clip fraction and the decoupled update's ``behaviour_ess``.

    python -m tocabi_torchrl.rl.curves runs/ppo_walk curves.png
    python -m tocabi_torchrl.rl.curves docs/training/walk_metrics.csv docs/training/walk_curves.png --overwrite

An existing figure is replaced only with ``--overwrite``.

The metrics are read by :func:`~tocabi_torchrl.rl.metrics_files.read_metrics` (re-exported here): a run folder, its
``metrics/`` folder (torchrl's ``CSVLogger``) or an older run's wide ``metrics.csv``.
"""

from __future__ import annotations

import math
from pathlib import Path

from ..cli import RecipeParser

from ..evaluation.plots import figure_format
from .metrics_files import read_metrics

__all__ = ["metric_columns", "plot_curves", "read_metrics", "steady_rate"]

IMITATION_TERMS = ("qpos", "orientation", "foot_contact", "force_ref")
#: The update's logged numbers the last panel draws on its right axis, where a run logged them (the learning rate,
#: on its own logarithmic axis, is drawn beside them).
UPDATE_TERMS = ("kl", "clip_fraction", "behaviour_ess")


def metric_columns(path: str | Path) -> dict[str, list[float]]:
    """``read_metrics`` as one float column per metric (empty cells are NaN); a clear error when nothing is logged."""
    rows = read_metrics(path)
    if not rows:
        raise ValueError(f"{path} holds no metric rows (is it a run folder or a metrics file, and has an iteration "
                         f"finished?)")
    names = dict.fromkeys(k for r in rows for k in r)  # every metric, in first-seen order
    return {k: [float(r[k]) if r.get(k) not in (None, "") else float("nan") for r in rows] for k in names}


def _number(row: dict[str, str], key: str) -> float | None:
    """``row[key]`` as a finite float, or None where the cell is empty, missing or not a finite number."""
    try:
        value = float(row.get(key, ""))
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) else None


def steady_rate(rows: list[dict[str, str]], skip: int = 1) -> float | None:
    """Env-steps/s from the ``skip``-th of ``read_metrics`` rows to the last, within the longest process segment
    (``wall_s`` restarts when a run resumes), leaving out warm-up iterations; None with too few rows, or when the
    two rows' ``wall_s`` are equal (no time measured between them). Rows without a number in ``wall_s`` or
    ``env_steps`` (an empty cell) are left out, as if not logged."""
    timed = [(wall, steps) for row in rows
             if (wall := _number(row, "wall_s")) is not None and (steps := _number(row, "env_steps")) is not None]
    segments: list[list[tuple[float, float]]] = [[]]
    for wall, steps in timed:
        if segments[-1] and wall < segments[-1][-1][0]:
            segments.append([])
        segments[-1].append((wall, steps))
    timed = max(segments, key=len)
    if len(timed) <= skip + 1:
        return None
    (wall_a, steps_a), (wall_b, steps_b) = timed[skip], timed[-1]
    return (steps_b - steps_a) / (wall_b - wall_a) if wall_b > wall_a else None


def _plot(ax, x: list[float], y: list[float], **kwargs) -> None:
    """``ax.plot(x, y)`` with a dot on each value that has no finite neighbour: a line draws nothing through a lone
    point, so a run of one logged row (or a value between NaNs) would leave its panel empty."""
    finite = [math.isfinite(a) and math.isfinite(b) for a, b in zip(x, y)]
    lone = [i for i, f in enumerate(finite)
            if f and not (i > 0 and finite[i - 1]) and not (i + 1 < len(finite) and finite[i + 1])]
    ax.plot(x, y, **({"marker": "o", "markersize": 3, "markevery": lone} if lone else {}), **kwargs)


def plot_curves(metrics: str | Path, out_png: str | Path) -> Path:
    """Plot episode return/length, the per-term rewards and (where logged) the update's learning rate, KL, clip
    fraction and ``behaviour_ess`` against env steps (millions); ``metrics``: what :func:`read_metrics` reads (a run
    folder or a metrics file)."""
    from ..evaluation.plots import new_figure, save_figure  # its own canvas: the caller's matplotlib backend stays

    data = metric_columns(metrics)
    steps = [s / 1e6 for s in data["env_steps"]]
    # Return and length are means over the episodes that ended in the logged iteration: none ended -> no point
    # (long episodes often outlast an iteration; older logs wrote 0 there).
    finished = data.get("episodes_finished", [1.0] * len(steps))
    ep = [(x, r, n) for x, r, n, f in zip(steps, data["episode_return"], data["episode_length"], finished) if f > 0]
    ep_steps, ep_return, ep_length = (list(c) for c in zip(*ep)) if ep else ([], [], [])
    update = [k for k in UPDATE_TERMS if k in data]
    panels = 4 if update or "lr" in data else 3
    fig = new_figure(figsize=(5 * panels, 4))
    axes = fig.subplots(1, panels)
    _plot(axes[0], ep_steps, ep_return, label="episode return")
    axes[0].set_ylabel("episode return")
    twin = axes[0].twinx()
    _plot(twin, ep_steps, ep_length, color="tab:orange", alpha=0.7, label="episode length")
    twin.set_ylabel("episode length [steps]")
    axes[0].set_title("Total reward (sum over an episode)")
    _plot(axes[1], steps, data["reward"], color="k", label="reward per step")
    for term in IMITATION_TERMS:
        key = f"reward_terms/{term}"
        if key in data:
            _plot(axes[1], steps, data[key], label=term)
    axes[1].set_title("Reward per step: total and imitation terms")
    axes[1].legend(fontsize=8)
    for key in data:
        if key.startswith("reward_terms/") and key[13:] not in IMITATION_TERMS:
            _plot(axes[2], steps, data[key], label=key[13:])
    axes[2].set_title("Reward per step: other terms")
    if axes[2].get_lines():  # an empty legend only warns
        axes[2].legend(fontsize=7, ncol=2)
    if panels == 4:
        _plot_update(axes[3], steps, data, update)
    for ax in axes:
        ax.set_xlabel("env steps [millions]")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    return save_figure(fig, out, "Training curves", dpi=110)


def _plot_update(ax, steps: list[float], data: dict[str, list[float]], update: list[str]) -> None:
    """The update's panel: the learning rate on a logarithmic left axis, ``update`` (KL [nats], clip fraction,
    effective sample size: all near [0, 1]) on the right."""
    top = ax
    if "lr" in data:
        _plot(ax, steps, data["lr"], color="k", label="learning rate")
        if any(v > 0 for v in data["lr"] if math.isfinite(v)):
            ax.set_yscale("log", nonpositive="mask")  # a rate of 0 leaves a gap, not a drop to the axis
        ax.set_ylabel("learning rate")
    if update:
        top = ax.twinx()
        for key, color in zip(update, ("tab:red", "tab:blue", "tab:green"), strict=False):
            _plot(top, steps, data[key], color=color, alpha=0.8, label=key)
        top.set_ylabel("KL [nats], fractions")
    lines = ax.get_lines() + (top.get_lines() if top is not ax else [])
    top.legend(lines, [line.get_label() for line in lines], fontsize=7)  # on the axis drawn last: above its lines
    ax.set_title("PPO update")


def main(argv=None) -> None:
    parser = RecipeParser(description="Plot a run's training curves")
    parser.add_argument("metrics", help="a run folder, its metrics/ folder, or a wide metrics.csv")
    parser.add_argument("out_png", help="the figure to write (.png, or another format matplotlib writes: .pdf, "
                                        ".svg); an existing file is replaced only with --overwrite")
    parser.add_argument("--overwrite", action="store_true", help="replace out_png if it exists (default: refuse)")
    args = parser.parse_args(argv)
    if not Path(args.metrics).exists():
        parser.error(f"{args.metrics} does not exist: pass a run folder (runs/<name>), its metrics/ folder or a "
                     "metrics.csv")
    out = Path(args.out_png)
    suffix = figure_format(out)
    import matplotlib.figure  # the formats matplotlib can write (no backend needed)

    if suffix not in matplotlib.figure.Figure().canvas.get_supported_filetypes():
        parser.error(f"out_png {out}: matplotlib cannot write .{suffix} files; name a .png (or .pdf, .svg)")
    if out.is_dir() or (out.exists() and not args.overwrite):
        parser.error(f"out_png {out} exists; it is not replaced: pass --overwrite, or name another file"
                     if not out.is_dir() else f"out_png {out} is a folder: name the figure file, e.g. {out}/curves.png")
    try:
        print(plot_curves(args.metrics, args.out_png))
    except (ValueError, KeyError) as err:  # no rows, or a CSV without a plotted column
        parser.error(f"{args.metrics}: {err if isinstance(err, ValueError) else f'no column {err} to plot'}")


if __name__ == "__main__":
    main()
