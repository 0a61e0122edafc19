"""Table and figure of the env-step CUDA graph ablation: training env-steps/s with ``cuda_graph`` on and off.

    python benchmarks/env_graph_report.py

Reads the ``train_throughput.py`` results under ``docs/benchmarks/env_graph/`` (pairs ``graph_on_<counts>.json`` and
``graph_off_<counts>.json``, each pair measured in one device command, so the two modes share a machine and a
lease) and writes ``docs/benchmarks/env_graph.md`` and ``env_graph.png``: the evidence behind
``PPOConfig.cuda_graph="auto"`` and ``ENV_GRAPH_AUTO_MAX_ENVS``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

DEFAULT_DIR = ROOT / "docs" / "benchmarks" / "env_graph"


def load_pairs(folder: Path) -> list[dict]:
    """One row per env count: rates with the graph on and off, and the command of each (from matching files)."""
    rows = []
    for on_path in sorted(folder.glob("graph_on_*.json")):
        off_path = on_path.with_name(on_path.name.replace("graph_on_", "graph_off_"))
        if not off_path.is_file():
            raise FileNotFoundError(f"{on_path} has no eager counterpart {off_path.name}")
        on, off = (json.loads(p.read_text()) for p in (on_path, off_path))
        off_rates = {r["num_envs"]: r for r in off["results"]}
        for r in on["results"]:
            eager = off_rates.get(r["num_envs"])
            if eager is None:
                raise ValueError(f"{off_path.name} lacks {r['num_envs']} envs, which {on_path.name} has")
            rows.append({"num_envs": r["num_envs"], "graph": r["train_env_steps_per_s"],
                         "eager": eager["train_env_steps_per_s"], "raw": r["raw_policy_steps_per_s"],
                         "date": on["meta"].get("date"), "gpu": on["meta"].get("gpu"),
                         "commands": (on["meta"]["command"], off["meta"]["command"])})
    return sorted(rows, key=lambda row: row["num_envs"])


def write(folder: Path, out: Path) -> str:
    from tocabi_torchrl.rl.config import ENV_GRAPH_AUTO_MAX_ENVS

    rows = load_pairs(folder)
    if not rows:
        raise SystemExit(f"no graph_on_*.json results under {folder}")
    lines = [
        f"# The env step as one CUDA graph: training throughput with `cuda_graph` on and off ({rows[0]['gpu']})",
        "",
        "Training env-steps/s of the default PPO preset (`benchmarks/train_throughput.py`: 8 iterations after 3 of "
        "warm-up, 48 steps per env) with the env step captured as one CUDA graph (`--set cuda_graph=on`) and "
        "launched op by op (`off`). Each pair of runs came from one device command. Small env counts are bound by "
        "kernel launches, which the graph removes; from a few hundred envs on, the physics dominates and the "
        "graph was a few per cent slower. Hence the default `cuda_graph=\"auto\"`: captured up to "
        f"{ENV_GRAPH_AUTO_MAX_ENVS:,} envs (`ENV_GRAPH_AUTO_MAX_ENVS`). These are short runs (48 steps per env). In "
        "the 983,040-step runs of [scaling.md](scaling.md), graph runs against earlier eager ones (other days and "
        "leases) gave 1.76× at 8 envs (the eager rate extrapolated from a partial run), 1.31× at 32 and 1.49× at 96.",
        "",
        "| envs | graph env-steps/s | eager env-steps/s | graph / eager | raw mujoco-warp policy steps/s | date |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for row in rows:
        lines.append(f"| {row['num_envs']:,} | {row['graph']:,.0f} | {row['eager']:,.0f} | "
                     f"{row['graph'] / row['eager']:.2f} | {row['raw']:,.0f} | {row['date']} |")
    lines += ["", "![graph / eager vs env count](env_graph.png)", "", "Commands (GPU machine, repository root; older "
              "runs spelled the modes true/false, which read as on/off):", ""]
    for command in dict.fromkeys(c for row in rows for c in row["commands"]):
        lines.append(f"    {command}")
    lines += ["", "Regenerate this page and its figure: `python benchmarks/env_graph_report.py`.", ""]
    text = "\n".join(lines)
    out.mkdir(parents=True, exist_ok=True)
    (out / "env_graph.md").write_text(text)
    _plot(rows, ENV_GRAPH_AUTO_MAX_ENVS, out / "env_graph.png")
    return text


def _plot(rows: list[dict], threshold: int, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = [row["num_envs"] for row in rows]
    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    ax.plot(n, [row["graph"] / row["eager"] for row in rows], "o-", label="graph / eager")
    ax.axhline(1.0, color="grey", lw=0.8)
    ax.axvline(threshold, color="tab:red", ls="--", lw=0.8, label=f"auto: graph up to {threshold} envs")
    ax.set_xscale("log", base=2)
    ax.set_xlabel("envs")
    ax.set_ylabel("training env-steps/s ratio")
    ax.set_title("Env step as one CUDA graph vs eager")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--results", default=str(DEFAULT_DIR))
    parser.add_argument("--out", default=str(DEFAULT_DIR.parent))
    args = parser.parse_args(argv)
    print(write(Path(args.results), Path(args.out)))


if __name__ == "__main__":
    main()
