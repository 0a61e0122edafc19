"""Time to walk: train a preset from scratch on the GPU, run the 8 s gait test on the checkpoints saved at fixed
training wall-clock points, and report the first training time (and env-step count) at which the gait test passes.

    python benchmarks/time_to_walk.py train --preset torque --minutes 9.5   # resumes; repeat until the budget is used
    python benchmarks/time_to_walk.py eval --preset torque                  # gait tests of every wall-clock checkpoint
    python benchmarks/time_to_walk.py report --runs docs/benchmarks/time_to_walk/torque ...

``train`` runs ``recipes/ppo_walk.py``'s trainer on ``runs/time_to_walk/<preset>`` with
``checkpoint_minutes=--every``, stopping when ``--budget_minutes`` of training wall-clock are used (summed over
resumed calls, without evaluation or warp's kernel compilation, with the first iteration's CUDA-graph captures); the
first call also measures raw mujoco-warp stepping of the same model at the same env count in the same process, for
the train/raw ratio. ``eval`` runs the gait test of
issue 19 on each ``wall_XXXXXs.pt``: 256 envs, 8 s, deterministic policy, standard resets, at (0.5, 0) m/s, and at
(0.2, 0) and (0.7, 0.1) for checkpoints that pass the first. ``train`` writes ``runs/time_to_walk/<preset>/train.json``
and ``eval`` writes ``evals.json`` beside it (separate files: the two may run at once).
``report`` writes ``time_to_walk.{json,md,png}`` (survival and forward distance against training minutes) and,
with ``--curves``, reward and imitation-reward curves of several runs against env steps.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
from pathlib import Path

#: The gait test's pass criteria (issue 19): at (0.5, 0) survival, forward distance, drift, knee RMS; survival only
#: at the other two commands.
MAIN_COMMAND = (0.5, 0.0)
OTHER_COMMANDS = ((0.2, 0.0), (0.7, 0.1))
CRITERIA = {"survival": 0.95, "forward_distance_m": 2.6, "lateral_drift_m": 0.3, "knee_rms_rad": 0.15}
RUNS = Path("runs/time_to_walk")


def passes_main(summary: dict) -> bool:
    """Whether a gait-test summary at (0.5, 0) meets every criterion of :data:`CRITERIA`."""
    return (summary["survival"] >= CRITERIA["survival"] and summary["forward_distance_m"] >= CRITERIA[
        "forward_distance_m"] and summary["lateral_drift_m"] <= CRITERIA["lateral_drift_m"]
            and summary["knee_rms_rad"] <= CRITERIA["knee_rms_rad"])


def walks(evaluation: dict) -> bool:
    """Whether one checkpoint's evaluation passes the whole gait test (all three commands)."""
    runs = evaluation["commands"]
    key = lambda c: f"{c[0]:.1f},{c[1]:.1f}"
    return (key(MAIN_COMMAND) in runs and passes_main(runs[key(MAIN_COMMAND)])
            and all(key(c) in runs and runs[key(c)]["survival"] >= CRITERIA["survival"] for c in OTHER_COMMANDS))


def _load(path: Path) -> dict:
    return json.loads(path.read_text()) if path.is_file() else {}


def _save(path: Path, record: dict) -> None:
    from tocabi_torchrl.rl.atomic import atomic_write_text

    atomic_write_text(path, json.dumps(record, indent=2))


def _command_line(argv) -> str:
    return " ".join(["python benchmarks/time_to_walk.py", *argv])


def steady_rate(rows: list[dict], skip: int = 3) -> float | None:
    """Env-steps/s of the longest resumed segment of ``metrics.csv`` rows, after its first ``skip`` iterations."""
    segments, current = [], []
    for row in rows:  # wall_s restarts at each resume
        if current and float(row["wall_s"]) < float(current[-1]["wall_s"]):
            segments.append(current)
            current = []
        current.append(row)
    segments.append(current)
    best = max(segments, key=len)
    if len(best) <= skip + 1:
        return None
    a, b = best[skip], best[-1]
    return (int(b["env_steps"]) - int(a["env_steps"])) / (float(b["wall_s"]) - float(a["wall_s"]))


def train_part(args, argv) -> None:
    import torch

    from tocabi_torchrl.rl.checkpoint import read_checkpoint
    from tocabi_torchrl.rl.config import preset_config
    from tocabi_torchrl.rl.trainer import train

    run_dir = RUNS / args.preset
    record_path = run_dir / "train.json"
    record = _load(record_path)
    latest = run_dir / "checkpoints" / "latest.pt"
    prior_s = float(read_checkpoint(latest).get("train_seconds", 0.0)) if latest.is_file() else 0.0
    left_min = args.budget_minutes - prior_s / 60.0
    if left_min <= 0:
        print(f"{args.preset}: the {args.budget_minutes}-minute training budget is used ({prior_s:.0f} s); "
              "run the eval part")
        return
    cfg = preset_config(args.preset, run_dir=str(RUNS), name=args.preset, device=args.device, eval_at_end=False,
                        progress_bar=False, log_every=args.log_every, checkpoint_minutes=args.every,
                        max_minutes=min(args.minutes, left_min), resume=str(latest) if latest.is_file() else "")
    print(f"{args.preset}: training {'from ' + str(latest) if cfg.resume else 'from scratch'}, "
          f"{prior_s / 60:.1f} of {args.budget_minutes} min used, this call up to {cfg.max_minutes:.1f} min",
          flush=True)
    result = train(cfg)
    record.setdefault("preset", args.preset)
    record.setdefault("config", cfg.to_dict())
    record.setdefault("commands", []).append(_command_line(argv))
    record["gpu"] = torch.cuda.get_device_name() if torch.cuda.is_available() else "cpu"
    record["env_steps"] = result.env_steps
    record["train_seconds"] = prior_s + result.wall_seconds
    with open(result.run_dir / "metrics.csv") as f:
        record["train_env_steps_per_s"] = steady_rate(list(csv.DictReader(f)))
    if "raw_policy_steps_per_s" not in record and args.raw_steps > 0 and args.device == "cuda":
        from sim_throughput import raw_policy_steps_per_second  # benchmarks/, this script's folder

        record["raw_policy_steps_per_s"] = raw_policy_steps_per_second(cfg.num_envs, args.raw_steps)
    if record.get("train_env_steps_per_s") and record.get("raw_policy_steps_per_s"):
        record["train_over_raw"] = record["train_env_steps_per_s"] / record["raw_policy_steps_per_s"]
    _save(record_path, record)
    print(json.dumps({k: record.get(k) for k in ("env_steps", "train_seconds", "train_env_steps_per_s",
                                                 "raw_policy_steps_per_s", "train_over_raw")}), flush=True)


def eval_part(args, argv) -> None:
    import torch

    run_dir = RUNS / args.preset
    record_path = run_dir / "evals.json"
    record = _load(record_path)
    evals = record.setdefault("evaluations", {})
    device = torch.device(args.device)
    envs, cfg = {}, None
    while True:
        # Checkpoints are written atomically (a dot-named temporary file, then a rename): a wall_*.pt is complete.
        pending = [p for p in sorted((run_dir / "checkpoints").glob("wall_*.pt")) if p.stem not in evals]
        for ckpt in pending:
            cfg = _evaluate_checkpoint(ckpt, evals, envs, cfg, args, device)
            _save(record_path, record)
        if args.follow_pid and _alive(args.follow_pid):
            time.sleep(10.0)
        elif args.follow_pid:
            args.follow_pid = 0  # the trainer has ended: one more pass for what it wrote last
        else:
            break
    record.setdefault("eval_commands", []).append(_command_line(argv))
    record["time_to_walk"] = first_walk(record)
    _save(record_path, record)
    print("time to walk:", json.dumps(record["time_to_walk"]))


def _alive(pid: int) -> bool:
    import os

    try:
        os.kill(pid, 0)
    except OSError:
        return False
    return True


def _evaluate_checkpoint(ckpt: Path, evals: dict, envs: dict, cfg, args, device):
    """Gait tests of one wall-clock checkpoint into ``evals[ckpt.stem]``; returns the run's config."""
    from tocabi_torchrl.rl.checkpoint import apply_checkpoint, config_from_checkpoint, read_checkpoint
    from tocabi_torchrl.rl.evaluate import _fixed_command, evaluate_policy
    from tocabi_torchrl.rl.trainer import build_agent, build_env

    state = read_checkpoint(ckpt)
    if cfg is None:
        cfg = config_from_checkpoint(state, ckpt)
    entry = {"train_seconds": state["train_seconds"], "env_steps": state["env_steps"],
             "iteration": state["iteration"], "commands": {}}
    for command in (MAIN_COMMAND, *OTHER_COMMANDS):
        if command != MAIN_COMMAND and not passes_main(entry["commands"][f"{MAIN_COMMAND[0]:.1f},0.0"]):
            break
        if command not in envs:
            envs[command] = build_env(cfg, device, num_envs=args.num_envs, command=_fixed_command(command))
        env = envs[command]
        agent = build_agent(cfg, env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1],
                            device)
        apply_checkpoint(state, agent, env=env, path=ckpt)
        out = ckpt.parent.parent / "eval" / ckpt.stem / f"{command[0]:.1f}_{command[1]:.1f}"
        summary = evaluate_policy(agent.actor, cfg, out, num_envs=args.num_envs, device=device,
                                  seconds=args.seconds, command=command, video_envs=0, env=env,
                                  progress=False)
        entry["commands"][f"{command[0]:.1f},{command[1]:.1f}"] = {k: v for k, v in summary.items()
                                                                    if isinstance(v, (int, float))}
    entry["walks"] = walks(entry)
    evals[ckpt.stem] = entry
    main = entry["commands"][f"{MAIN_COMMAND[0]:.1f},0.0"]
    print(f"{ckpt.stem}: {entry['train_seconds'] / 60:5.1f} min, {entry['env_steps'] / 1e6:6.1f} M steps: "
          f"survival {main['survival']:.3f}, forward {main['forward_distance_m']:.2f} m, drift "
          f"{main['lateral_drift_m']:.2f} m, knee RMS {main['knee_rms_rad']:.3f} rad -> "
          f"{'WALKS' if entry['walks'] else 'no'}", flush=True)
    return cfg


def first_walk(record: dict) -> dict | None:
    """The earliest checkpoint (by training time) that passes the gait test, or None."""
    passing = [e for e in record.get("evaluations", {}).values() if e.get("walks")]
    if not passing:
        return None
    first = min(passing, key=lambda e: e["train_seconds"])
    return {"train_minutes": first["train_seconds"] / 60.0, "env_steps": first["env_steps"],
            "iteration": first["iteration"]}


def read_run(folder: Path) -> dict:
    """A run's ``train.json`` and ``evals.json`` as one record (``time_to_walk`` recomputed from the evaluations)."""
    record = {**_load(folder / "train.json"), **_load(folder / "evals.json")}
    if not record:
        raise SystemExit(f"{folder}: no train.json or evals.json (run the train and eval parts first)")
    record["time_to_walk"] = first_walk(record)
    return record


def report_part(args, argv) -> None:
    records = [read_run(Path(p)) for p in args.runs]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "time_to_walk.json").write_text(json.dumps({"command": _command_line(argv), "records": records},
                                                      indent=2))
    lines = ["# Time to walk (issue 19)", "",
             "Training wall-clock (summed over resumed device calls; no evaluation, no kernel compilation) until a "
             "checkpoint first passes the 8 s gait test on 256 envs: at (0.5, 0) m/s survival >= 95 %, forward >= "
             "2.6 m, drift <= 0.3 m, knee RMS <= 0.15 rad; at (0.2, 0) and (0.7, 0.1) survival >= 95 %.", "",
             "| preset | GPU | time to walk [min] | env steps then | training env-steps/s | raw mujoco-warp policy "
             "steps/s (same run) | train / raw |", "|---|---|---:|---:|---:|---:|---:|"]
    for r in records:
        ttw = r.get("time_to_walk")
        lines.append("| {} | {} | {} | {} | {} | {} | {} |".format(
            r["preset"], r.get("gpu", "?"), f"{ttw['train_minutes']:.1f}" if ttw else "not within "
            f"{r.get('train_seconds', 0) / 60:.1f} min", f"{ttw['env_steps'] / 1e6:.1f} M" if ttw else "-",
            _num(r.get("train_env_steps_per_s")), _num(r.get("raw_policy_steps_per_s")),
            f"{r['train_over_raw']:.2f}" if r.get("train_over_raw") else "-"))
    for r in records:
        lines += ["", f"## {r['preset']}", "", "Commands:", ""] + [f"- `{c}`" for c in
                                                                   r.get("commands", []) + r.get("eval_commands", [])]
        lines += ["", ("| checkpoint | minutes | env steps | survival | forward [m] | drift [m] | knee RMS [rad] | "
                       "survival (0.2, 0) | survival (0.7, 0.1) | walks |"),
                  "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
        for name, e in sorted(r.get("evaluations", {}).items()):
            c = e["commands"]
            m = c.get("0.5,0.0", {})
            other = [f"{c[k]['survival']:.3f}" if k in c else "-" for k in ("0.2,0.0", "0.7,0.1")]
            lines.append(f"| {name} | {e['train_seconds'] / 60:.1f} | {e['env_steps'] / 1e6:.1f} M | "
                         f"{m.get('survival', math.nan):.3f} | {m.get('forward_distance_m', math.nan):.2f} | "
                         f"{m.get('lateral_drift_m', math.nan):.2f} | {m.get('knee_rms_rad', math.nan):.3f} | "
                         f"{other[0]} | {other[1]} | {'yes' if e.get('walks') else 'no'} |")
    (out / "time_to_walk.md").write_text("\n".join(lines) + "\n")
    _plot_progress(records, out / "time_to_walk.png")
    if args.curves:
        _plot_curves([Path(p) for p in args.curves], out / "time_to_walk_curves.png")
    print("\n".join(lines))


def _num(x) -> str:
    return f"{x:,.0f}" if x else "-"


def _plot_progress(records: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for r in records:
        points = sorted((e["train_seconds"] / 60, e["commands"]["0.5,0.0"]) for e in r.get("evaluations", {}).values())
        if not points:
            continue
        minutes = [p[0] for p in points]
        axes[0].plot(minutes, [100 * p[1]["survival"] for p in points], "o-", label=r["preset"])
        axes[1].plot(minutes, [p[1]["forward_distance_m"] for p in points], "o-", label=r["preset"])
        if r.get("time_to_walk"):
            for ax in axes:
                ax.axvline(r["time_to_walk"]["train_minutes"], ls=":", color=ax.lines[-1].get_color())
    axes[0].axhline(100 * CRITERIA["survival"], color="k", lw=0.8, ls="--", label="pass")
    axes[1].axhline(CRITERIA["forward_distance_m"], color="k", lw=0.8, ls="--", label="pass")
    axes[0].set_ylabel("survival over 8 s at (0.5, 0) m/s [%]")
    axes[1].set_ylabel("forward distance in 8 s [m]")
    for ax in axes:
        ax.set_xlabel("training wall-clock [min]")
        ax.grid(alpha=0.3)
        ax.legend()
    fig.suptitle("Gait test of checkpoints against training time (dotted: first pass)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_curves(metrics: list[Path], path: Path) -> None:
    """Reward per step and the imitation (qpos) reward against env steps, one line per run (TocabiLab figs 4.2-4.3)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for p in metrics:
        with open(p) as f:
            rows = list(csv.DictReader(f))
        steps = [int(r["env_steps"]) for r in rows]
        label = p.stem.replace("_metrics", "")
        axes[0].plot(steps, [float(r["reward"]) for r in rows], label=label)
        axes[1].plot(steps, [float(r["reward_terms/qpos"]) for r in rows], label=label)
    axes[0].set_ylabel("reward per step")
    axes[1].set_ylabel("imitation reward per step (qpos term, max 0.35)")
    for ax in axes:
        ax.set_xscale("log")
        ax.set_xlabel("env steps")
        ax.grid(alpha=0.3, which="both")
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="part", required=True)
    t = sub.add_parser("train", help="train (or resume) a preset on the GPU for up to --minutes")
    t.add_argument("--preset", default="torque")
    t.add_argument("--minutes", type=float, default=9.0, help="training minutes in this call")
    t.add_argument("--budget_minutes", type=float, default=30.0, help="training minutes in all (summed over calls)")
    t.add_argument("--every", type=float, default=2.0, help="minutes between evaluated checkpoints (0: none)")
    t.add_argument("--log_every", type=int, default=5)
    t.add_argument("--raw_steps", type=int, default=200, help="raw mujoco-warp steps timed (0: skip)")
    t.add_argument("--device", default="cuda", help="cuda (the benchmark) or cpu (a smoke test of the script)")
    e = sub.add_parser("eval", help="gait tests of every wall-clock checkpoint of a preset's run")
    e.add_argument("--preset", default="torque")
    e.add_argument("--num_envs", type=int, default=256)
    e.add_argument("--seconds", type=float, default=8.0)
    e.add_argument("--device", default="cuda")
    e.add_argument("--follow_pid", type=int, default=0,
                   help="keep evaluating new checkpoints while this process (the trainer) runs")
    r = sub.add_parser("report", help="tables and plots from the runs' train.json and evals.json")
    r.add_argument("--runs", nargs="+", required=True, help="run folders holding train.json / evals.json")
    r.add_argument("--curves", nargs="*", default=[], help="metrics.csv files to plot reward curves from")
    r.add_argument("--out", default="docs/benchmarks")
    args = parser.parse_args(argv)
    t0 = time.time()
    {"train": train_part, "eval": eval_part, "report": report_part}[args.part](args, argv)
    print(f"[{args.part} took {time.time() - t0:.0f} s]")


if __name__ == "__main__":
    main()
