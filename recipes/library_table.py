"""The per-library table (issue 22): for each RL library, training env-steps/s on the walking task and the training
wall-clock at which its policy first passes the 8 s gait test (30-minute cap). Meant for one H100.

    python recipes/library_table.py --libraries torchrl,rsl_rl,skrl --num_envs 4096
    python recipes/library_table.py --libraries sb3 --num_envs 8,256,1024
    python recipes/library_table.py --report                 # rebuild the table from the saved rows only

Each library trains in its own process through its recipe (``recipes/ppo_walk.py`` for TorchRL,
``recipes/train_<library>.py`` otherwise) with ``--max_minutes`` (default 30) and a policy snapshot every
``--checkpoint_minutes`` of training wall-clock; then the snapshots are gait-tested in time order (256 robots, 8 s,
at (0.5, 0) m/s against the thresholds of ``adapters.evaluate.GAIT_CRITERIA``, and survival >= 95 % at (0.2, 0) and
(0.7, 0.1)) until one passes. Rows accumulate in ``--json`` (one per library, env count and preset; a rerun replaces
its row) and ``--md`` is rewritten from all of them. The env-steps/s are whole training (collection + update)
divided by training wall-clock; SB3's include its host copies (observations, rewards, done flags to the host and
the actions back every step).

This script lives in recipes/ while benchmarks/ is being rewritten; it belongs beside benchmarks/time_to_walk.py.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MAIN = (0.5, 0.0)
OTHERS = ((0.2, 0.0), (0.7, 0.1))
LIBRARIES = ("torchrl", "rsl_rl", "skrl", "sb3")


def train(library: str, num_envs: int, out: Path, args) -> dict:
    """Train one library in a subprocess; returns {env_steps, train_seconds, env_steps_per_s, snapshots}."""
    common = ["--max_minutes", str(args.max_minutes), "--checkpoint_minutes", str(args.checkpoint_minutes)]
    if library == "torchrl":
        cmd = [sys.executable, str(ROOT / "recipes/ppo_walk.py"), "--preset", args.preset, "--num_envs",
               str(num_envs), "--minibatch_size", str(min(49152, 48 * num_envs)), "--run_dir", str(out.parent), "--name", out.name, "--eval_at_end", "false",
               "--progress_bar", "false", "--device", args.device, *common]
    else:
        cmd = [sys.executable, str(ROOT / f"recipes/train_{library}.py"), "--out", str(out), "--num_envs",
               str(num_envs), "--preset", args.preset, "--device", args.device, "--eval_envs", "0",
               "--iterations", "1000000", *common]
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, cwd=ROOT)
    if library == "torchrl":
        from tocabi_torchrl.rl.curves import read_metrics

        last = read_metrics(out)[-1]
        snaps = sorted(str(p) for p in (out / "checkpoints").glob("wall_*.pt"))
        return {"env_steps": int(float(last["env_steps"])), "train_seconds": float(last["wall_s"]),
                "env_steps_per_s": float(last["env_steps_per_s"]), "snapshots": snaps}
    return json.loads((out / "result.json").read_text())["train"]


def gait(library: str, snapshot: str, out: Path, args, command) -> dict:
    """One gait test of one snapshot at ``command``."""
    if library == "torchrl":
        from tocabi_torchrl.rl.evaluate import evaluate_run

        return evaluate_run(snapshot, num_envs=args.eval_envs, device=args.device, out_dir=out, command=command,
                            video_envs=0, progress=False)
    import importlib.util

    spec = importlib.util.spec_from_file_location(f"train_{library}", ROOT / f"recipes/train_{library}.py")
    recipe = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(recipe)
    return recipe.evaluate(snapshot, out, num_envs=args.eval_envs, device=args.device, seconds=8.0, command=command)


def first_pass(library: str, snapshots: list[str], out: Path, args) -> dict | None:
    """The earliest snapshot passing the whole gait test, with its summaries; None if none passes."""
    from tocabi_torchrl.adapters.evaluate import GAIT_CRITERIA, gait_passes

    for snap in snapshots:
        name = Path(snap).stem
        main = gait(library, snap, out / "gait" / name / "0.5_0.0", args, MAIN)
        if not gait_passes(main):
            continue
        others = {f"{c[0]}_{c[1]}": gait(library, snap, out / "gait" / name / f"{c[0]}_{c[1]}", args, c)
                  for c in OTHERS}
        if all(s["survival"] >= GAIT_CRITERIA["survival"] for s in others.values()):
            return {"snapshot": snap, "minutes": int(name.split("_")[1].rstrip("s")) / 60.0, "main": main,
                    "others": {k: v["survival"] for k, v in others.items()}}
    return None


def report(rows: list[dict], path: Path) -> None:
    from tocabi_torchrl.rl.atomic import atomic_write_text

    intro = ("Training env-steps/s (collection + update over training wall-clock) and the training time at which the "
             "policy first passes the 8 s gait test (30-minute cap). Written by `recipes/library_table.py`.")
    lines = ["# Per-library table (issue 22)", "", intro, "",
             "| library | version | preset | envs | env-steps/s | walks at (min) | device | command |",
             "|---|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: (r["preset"], r["library"], r["num_envs"])):
        walks = f"{r['walks_minutes']:.1f}" if r.get("walks_minutes") is not None else f"no (≤ {r['cap_minutes']:g})"
        lines.append(f"| {r['library']} | {r.get('version', '')} | {r['preset']} | {r['num_envs']:,} | "
                     f"{r['env_steps_per_s']:,.0f} | {walks} | {r['device']} | `{r['command']}` |")
    atomic_write_text(path, "\n".join(lines) + "\n")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--libraries", default="torchrl,rsl_rl,skrl,sb3", help="comma-separated, of " +
                        ", ".join(LIBRARIES))
    parser.add_argument("--num_envs", default="4096", help="comma-separated env counts (default: 4096)")
    parser.add_argument("--preset", default="default", help="task preset (default; torque once it exists)")
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--max_minutes", type=float, default=30.0, help="training cap [min] (default: 30)")
    parser.add_argument("--checkpoint_minutes", type=float, default=1.0, help="snapshot period [min] (default: 1)")
    parser.add_argument("--eval_envs", type=int, default=256)
    parser.add_argument("--runs", default="runs/library_table", help="training runs go here (must be new per row)")
    parser.add_argument("--json", default="docs/adapters_table.json")
    parser.add_argument("--md", default="docs/adapters_table.md")
    parser.add_argument("--report", action="store_true", help="only rewrite --md from --json")
    args = parser.parse_args(argv)
    json_path, md_path = ROOT / args.json, ROOT / args.md
    rows = json.loads(json_path.read_text()) if json_path.is_file() else []
    if not args.report:
        from importlib import metadata

        from tocabi_torchrl.rl.atomic import atomic_write_text

        dists = {"torchrl": "torchrl", "rsl_rl": "rsl-rl-lib", "skrl": "skrl", "sb3": "stable-baselines3"}
        for library in args.libraries.split(","):
            if library not in LIBRARIES:
                parser.error(f"unknown library {library!r}; choose from {', '.join(LIBRARIES)}")
            for n in (int(x) for x in args.num_envs.split(",")):
                out = ROOT / args.runs / f"{library}_{args.preset}_{n}_{time.strftime('%Y%m%d_%H%M%S')}"
                trained = train(library, n, out, args)
                walked = first_pass(library, trained["snapshots"], out, args)
                import torch

                row = {"library": library, "version": metadata.version(dists[library]), "preset": args.preset,
                       "num_envs": n, "env_steps_per_s": trained["env_steps_per_s"],
                       "env_steps": trained["env_steps"], "train_seconds": trained["train_seconds"],
                       "walks_minutes": walked["minutes"] if walked else None, "walk": walked,
                       "cap_minutes": args.max_minutes, "run": str(out),
                       "device": torch.cuda.get_device_name() if torch.cuda.is_available() else "cpu",
                       "command": " ".join(["python recipes/library_table.py", *(argv or sys.argv[1:])])}
                rows = [r for r in rows if (r["library"], r["preset"], r["num_envs"]) != (library, args.preset, n)]
                rows.append(row)
                atomic_write_text(json_path, json.dumps(rows, indent=2))
                print(json.dumps({k: row[k] for k in ("library", "num_envs", "env_steps_per_s", "walks_minutes")}))
    report(rows, md_path)


if __name__ == "__main__":
    main()
