"""Plot rsl_rl's table rows against the TorchRL preset's time-to-walk run, per PPO iteration (issue 22):
episode length, the imitation reward ``qpos`` and the value loss, the three signals that told the rows apart.

    python docs/adapters/rsl_rl_rows.py     # writes docs/adapters/rsl_rl_rows.png

Reads committed CSVs only: rsl_rl's per-iteration values (parsed from its console log on the GPU machine) and the
preset's metrics. Iterations are counted from 1 in all three.
"""

from __future__ import annotations

import csv
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROWS = {  # label -> (csv, iteration, episode length, qpos, value loss columns)
    "rsl_rl, preset's LR rule + scheduled std (walks at 10 min)":
        (HERE / "table_2026-11-27c/rsl_rl_per_iteration_iterations.csv",
         "iteration", "episode_length", "qpos", "value_loss"),
    "rsl_rl, its own per-mini-batch LR rule + learned std (no walk in 22 min)":
        (HERE / "table_2026-11-27b/rsl_rl_learned_std_iterations.csv",
         "iteration", "episode_length", "qpos", "value_loss"),
    "TorchRL preset (time-to-walk run, H100)":
        (HERE.parent / "training/default_ttw/default_metrics.csv",
         "iteration", "episode_length", "reward_terms/qpos", "loss_value"),
}
PANELS = ("episode length [steps]", "qpos reward per step", "value loss")


def read(path: Path, columns: tuple[str, ...]) -> list[list[float]]:
    """The columns as floats, one list each; rows with an empty cell (no episode ended in that iteration) dropped."""
    with path.open() as fh:
        rows = [r for r in csv.DictReader(fh) if all(r.get(c) not in (None, "") for c in columns)]
    if not rows:
        raise SystemExit(f"error: {path} has no rows with all of {columns}")
    return [[float(r[c]) for r in rows] for c in columns]


def main(out: Path = HERE / "rsl_rl_rows.png") -> Path:
    """Draw the three panels for every row of :data:`ROWS` into ``out``; returns ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.2))
    for label, (path, *columns) in ROWS.items():
        it, *series = read(path, tuple(columns))
        for ax, ys in zip(axes, series):
            ax.plot(it, ys, label=label, lw=1)
    for ax, title in zip(axes, PANELS):
        ax.set_title(title)
        ax.set_xlabel("PPO iteration (196,608 env steps each)")
        ax.set_xlim(0, 400)
        ax.grid(alpha=0.3)
    axes[2].set_yscale("log")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out


if __name__ == "__main__":
    print(main())
