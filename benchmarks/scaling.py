"""Efficiency and scalability of PPO training (issue 9: TocabiLab's chapter 5 on our system).

    python -m benchmarks.scaling --kind raw --num_envs 8 32 96 1024 4096 16384 65536
    python -m benchmarks.scaling --kind time --num_envs 4096 16384 65536 1024 96 32 8          # 983,040 env-steps
    python -m benchmarks.scaling --kind time --backend cpu --num_envs 96 32 8                  # C MuJoCo backend
    python -m benchmarks.scaling --kind memory --num_envs 8 16 32 64 128 256 512 2048 8192 ... # 3 iterations each
    python -m benchmarks.scaling --report                                                      # scaling.{md,png}

Every measurement runs in a fresh process (peak RSS and the allocator's peaks are its own) and writes
``<results>/<kind>_<backend>_<envs:07d>.json``; an existing result is skipped (``--redo`` measures it again), and a
memory sweep stops at the first env count that runs out of device memory. A training run stops at ``--max_minutes``
(status *partial*: its rate is measured, the time for 983,040 steps extrapolated); running the command again trains it
on from its checkpoint in ``--run_dir`` and adds the segments up. Same recipe for every env count: the default preset,
with a rollout of at least 2,048 transitions and mini-batches of a quarter of it (capped at the preset's).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import time
from pathlib import Path

from . import common

T0 = time.perf_counter()  # "total incl. set-up" counts from the process start
TARGET = 983_040  # TocabiLab's budget: 4,096 envs x 24 steps x 10 iterations
TOCABILAB_BEST = TARGET / 850  # env-steps/s of TocabiLab's best run (Isaac Lab + rsl_rl, 96 envs)
RESULTS = common.DOCS / "scaling"
OOM = ("out of memory", "outofmemory", "cudaerrormemoryallocation", "failed to allocate")


def training_config(kind: str, backend: str, n: int, run_dir: str, max_minutes: float, hidden=(), resume=""):
    base = common.config("default")
    steps = max(base.steps_per_env, math.ceil(2048 / n))
    total = 3 * n * steps if kind == "memory" else TARGET
    extra = {"actor_hidden": hidden, "critic_hidden": hidden} if hidden else {}
    return common.config("default", num_envs=n, steps_per_env=steps, minibatch_size=min(base.minibatch_size,
                         n * steps // 4), total_env_steps=total, device="cuda" if backend == "gpu" else "cpu",
                         run_dir=run_dir, name=f"{kind}_{backend}_{n:07d}", eval_at_end=False, progress_bar=False,
                         checkpoint_every=10**9, log_every=max(1, -(-total // (n * steps)) // 10),
                         max_minutes=max_minutes, resume=resume, **extra)


def measure(kind: str, backend: str, n: int, run_dir: str, max_minutes: float, hidden, previous: dict | None) -> dict:
    """One measurement in this process; ``previous`` is a partial time result to train on from its checkpoint."""
    import torch

    if kind == "raw":
        return {"raw_policy_steps_per_s": common.raw_policy_steps_per_second(n, 200), "status": "ok"}
    name = Path(run_dir) / f"{kind}_{backend}_{n:07d}"
    if not previous:
        shutil.rmtree(name, ignore_errors=True)  # this benchmark's own scratch run: a new measurement starts afresh
    resume = str(name / "checkpoints" / "latest.pt") if previous else ""
    cfg = training_config(kind, backend, n, run_dir, max_minutes, hidden, resume)
    cpu0, t_setup = os.times(), time.perf_counter() - T0
    with common.MemoryPeak(cfg.device, every_s=0.5) as peak:
        result, rows = common.train(cfg)
    cpu1 = os.times()
    segment = {"env_steps": result.env_steps - (previous or {}).get("env_steps", 0), "train_wall_s": result.wall_seconds,
               "setup_s": t_setup, "date": time.strftime("%Y-%m-%d %H:%M:%S")}
    segments = (previous or {}).get("segments") or ([previous] if previous else [])
    segments = [*segments, segment] if previous else []
    parts = segments or [segment]
    wall, steps = sum(s["train_wall_s"] for s in parts), sum(s["env_steps"] for s in parts)
    return {"status": "ok" if result.env_steps >= cfg.total_env_steps else "partial", "iterations": result.iterations,
            "env_steps": steps, "train_wall_s": wall, "setup_s": sum(s["setup_s"] for s in parts),
            "total_wall_s": wall + sum(s["setup_s"] for s in parts), "env_steps_per_s": steps / wall,
            "env_graph": result.env_graph, "segments": segments,
            "config": {"steps_per_env": cfg.steps_per_env, "minibatch_size": cfg.minibatch_size},
            "cpu": {"cores_used_mean": (cpu1.user + cpu1.system - cpu0.user - cpu0.system) / result.wall_seconds},
            "gpu": {**common.torch_peaks(), "device_used_peak_gib": peak.device_gib} if backend == "gpu" else None,
            "host": {"peak_rss_gib": common.peak_rss_gib()}, "steady_env_steps_per_s": common.window_rate(rows)}


def run(kind: str, backend: str, n: int, args) -> dict:
    """Measure in a fresh process and write the result; an out-of-memory failure is a result too (``oom``)."""
    path = Path(args.results) / f"{kind}_{backend}_{n:07d}.json"
    previous = json.loads(path.read_text()) if path.is_file() else None
    if previous and (previous["status"] != "partial" or kind != "time") and previous["status"] not in args.redo:
        return previous
    resume = previous if kind == "time" and previous and previous["status"] == "partial" and "partial" not in args.redo \
        else None
    head = {"kind": kind, "backend": backend, "num_envs": n, "command": common.meta("scaling", None)["command"]}
    try:
        record = common.run_child("scaling", [
            kind, backend, str(n), args.run_dir, str(args.max_minutes), ",".join(map(str, args.hidden)),
            json.dumps(resume)], env={"CUDA_VISIBLE_DEVICES": ""} if backend == "cpu" else None)
    except RuntimeError as err:
        record = {"status": "oom" if any(m in str(err).lower() for m in OOM) else "error", "error": str(err)[-3000:]}
    record = {**head, **record, "meta": common.meta("scaling", None, "cuda" if backend == "gpu" else "cpu")}
    common.write_json(path, record)
    print(f"{path.name}: {record['status']} {common.fmt(record.get('env_steps_per_s'))} env-steps/s", flush=True)
    return record


def _records(folder: Path) -> dict[tuple[str, str, int], dict]:
    return {(r["kind"], r["backend"], r["num_envs"]): r for r in map(json.loads, map(Path.read_text,
                                                                                  sorted(folder.glob("*_*_*.json"))))}


def render(folder: Path, out: Path) -> str:
    rec = _records(folder)
    get = lambda kind, backend: sorted((k[2], r) for k, r in rec.items() if k[:2] == (kind, backend))  # noqa: E731
    raw = dict((n, r["raw_policy_steps_per_s"]) for n, r in get("raw", "gpu"))
    time_rows = []
    for backend, label in (("gpu", "GPU (mujoco-warp)"), ("cpu", "CPU (C MuJoCo)")):
        for n, r in get("time", backend):
            sps, c = r["env_steps_per_s"], r["config"]
            time_rows.append((label, f"{n:,}", f"{c['steps_per_env']} / {c['minibatch_size']:,}",
                              ("graph" if r.get("env_graph") else "eager") if backend == "gpu" else "-",
                              f"{r['env_steps']:,}", f"{r['train_wall_s']:.1f}", f"{r['total_wall_s']:.1f}",
                              f"{sps:,.0f}", f"{TARGET / sps:,.1f}", f"{sps / TOCABILAB_BEST:.1f}×",
                              r["status"] + (f" ({len(r['segments'])} segments)" if r.get("segments") else "")))
    time_rows += [("TocabiLab: Isaac Lab + rsl_rl, RTX 4070 Ti Super (reported)", 96, "24 / -", "-", f"{TARGET:,}",
                   "850", "-", f"{TOCABILAB_BEST:,.0f}", "850", "1.0×", "reported"),
                  ("TocabiLab: CPU MuJoCo + SB3 (reported; failed at 96 envs)", 8, "-", "-", f"{TARGET:,}", "1,535",
                   "-", f"{TARGET / 1535:,.0f}", "1,535", f"{TARGET / 1535 / TOCABILAB_BEST:.2f}×", "reported")]
    trained = {n: r for n, r in get("time", "gpu")}
    # A count with a 983,040-step run takes its numbers from it (the short runs at those counts are older, eager ones).
    mem = {**{n: (r, "short run") for n, r in get("memory", "gpu")}, **{n: (r, "983k run") for n, r in trained.items()}}
    device = lambda r: (r.get("gpu") or {}).get("device_used_peak_gib", (r.get("gpu") or {}).get("device_used_end_gib"))  # noqa: E731
    mem_rows = [(f"{n:,}", src, r["status"], common.fmt(r.get("host", {}).get("peak_rss_gib"), ".2f"),
                 common.fmt((r.get("gpu") or {}).get("torch_peak_allocated_gib"), ".2f"),
                 common.fmt((r.get("gpu") or {}).get("torch_peak_reserved_gib"), ".2f"), common.fmt(device(r), ".2f"),
                 common.fmt(r.get("cpu", {}).get("cores_used_mean"), ".2f"),
                 common.fmt(r.get("env_steps_per_s") if r["status"] == "ok" else None, ",.0f", "not measured"))
                for n, (r, src) in sorted(mem.items())]
    fit = [(n, device(r)) for n, (r, _) in sorted(mem.items()) if n >= 1024 and r["status"] == "ok" and device(r)]
    slope = _slope(fit)
    cpu_best = max((r["env_steps_per_s"] for _, r in get("time", "cpu")), default=None)
    gpu4k = trained.get(4096, {}).get("env_steps_per_s")
    rss = {n: r["host"]["peak_rss_gib"] for n, (r, _) in mem.items() if r.get("host")}
    growth = 100 * (rss[16384] / rss[1024] - 1) if 1024 in rss and 16384 in rss else None
    fits = [n for n, (r, _) in mem.items() if r["status"] == "ok"]
    checks = [("GPU at 4,096 envs vs the CPU backend's best", 10, gpu4k and cpu_best and gpu4k / cpu_best),
              ("GPU at 4,096 envs vs TocabiLab's best", 100, gpu4k and gpu4k / TOCABILAB_BEST)]
    check_rows = [(name, f"≥ {target}×", common.fmt(v, ".1f") + "×", "**pass**" if v and v >= target else "fail")
                  for name, target, v in checks]
    check_rows.append(("Host RAM growth from 1,024 to 16,384 envs", "< 10 %", common.fmt(growth, ".1f") + " %",
                       "**pass**" if growth is not None and growth < 10 else "fail"))
    _plot(get, raw, mem, device, out)
    m = {**trained.get(4096, next(iter(rec.values())))["meta"], "date": max(r["meta"]["date"] for r in rec.values())}
    return (f"# Efficiency and scalability: TocabiLab's chapter 5 on our system ({m['gpu']})\n\n"
            f"From the result files in `scaling/` (one fresh process each, measured up to {m['date']}); regenerate with "
            f"`python -m benchmarks.scaling --report`. *Training time* runs from finished set-up to the end of the "
            f"last update (TocabiLab's timer); *total* adds the set-up; *s per 983,040* is 983,040 ÷ env-steps/s "
            f"(extrapolated for *partial* runs). TocabiLab's numbers are quoted, not re-measured.\n\n"
            + common.table(("check", "target", "measured", "result"), check_rows)
            + f"\n\nGPU memory per env: **{common.fmt(slope and slope * 1024, '.3f')} MiB** (least-squares slope over "
            f"{', '.join(str(n) for n, _ in fit)} envs); largest count that trained: {max(fits, default=0):,} envs."
            "\n\n## Training time for 983,040 env-steps\n\n" + common.table(
                ("system", "envs", "steps/env / mini-batch", "env step", "env-steps done", "training time [s]",
                 "total incl. set-up [s]", "env-steps/s", "s per 983,040", "vs TocabiLab best", "status"), time_rows)
            + "\n\n## Against the raw mujoco-warp ceiling (same machine)\n\n" + common.table(
                ("envs", "training env-steps/s", "raw policy steps/s", "train / raw"),
                [(f"{n:,}", f"{r['env_steps_per_s']:,.0f}", f"{raw[n]:,.0f}", f"{r['env_steps_per_s'] / raw[n]:.2f}")
                 for n, r in sorted(trained.items()) if n in raw])
            + "\n\n## Memory and CPU per env count (GPU)\n\n" + common.table(
                ("envs", "source", "status", "peak RSS [GiB]", "torch peak alloc. [GiB]", "torch peak reserved [GiB]",
                 "device in use [GiB]", "CPU cores busy", "env-steps/s"), mem_rows)
            + "\n\n![training time, rate and memory vs env count](scaling.png)\n")


def _slope(points: list[tuple[int, float]]) -> float | None:
    """Least-squares GiB per env of ``(envs, GiB)`` points."""
    if len(points) < 2:
        return None
    mx, my = (sum(p[i] for p in points) / len(points) for i in (0, 1))
    return sum((x - mx) * (y - my) for x, y in points) / sum((x - mx) ** 2 for x, _ in points)


def _plot(get, raw, mem, device, out: Path) -> None:
    plt = common.pyplot()
    if plt is None:
        return
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for backend in ("gpu", "cpu"):
        pts = get("time", backend)
        axes[0].plot([n for n, _ in pts], [TARGET / r["env_steps_per_s"] for _, r in pts], "o-", label=backend)
        axes[1].plot([n for n, _ in pts], [r["env_steps_per_s"] for _, r in pts], "o-", label=f"{backend} training")
    axes[0].axhline(850, color="k", ls="--", lw=0.8, label="TocabiLab best")
    axes[1].plot(sorted(raw), [raw[n] for n in sorted(raw)], "k--", label="raw mujoco-warp")
    ok = [(n, device(r)) for n, (r, _) in sorted(mem.items()) if r["status"] == "ok" and device(r)]
    axes[2].plot([n for n, _ in ok], [g for _, g in ok], "o-", label="device memory in use")
    for ax, ylabel in zip(axes, ("s per 983,040 env-steps", "env-steps/s", "GiB"), strict=True):
        ax.set(xscale="log", xlabel="envs", ylabel=ylabel)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    axes[0].set_yscale("log")
    axes[1].set_yscale("log")
    common.save(fig, out / "scaling.png")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kind", choices=("time", "memory", "raw"), default="time")
    parser.add_argument("--backend", choices=("gpu", "cpu"), default="gpu")
    parser.add_argument("--num_envs", type=int, nargs="+", default=[4096])
    parser.add_argument("--max_minutes", type=float, default=9.0, help="a training run's own time limit")
    parser.add_argument("--redo", nargs="*", default=[], help="measure results of these statuses again")
    parser.add_argument("--hidden", type=int, nargs="*", default=[], help="network sizes (default: the preset's)")
    parser.add_argument("--results", default=str(RESULTS))
    parser.add_argument("--run_dir", default="/tmp/tocabi_scaling_runs", help="scratch folder of the training runs")
    parser.add_argument("--report", action="store_true", help="render scaling.{md,png} beside --results")
    parser.add_argument("--child", nargs=7, help="one measurement in this process (internal)")
    args = parser.parse_args(argv)
    if args.child:
        kind, backend, n, run_dir, minutes, hidden, previous = args.child
        common.child_result(measure(kind, backend, int(n), run_dir, float(minutes),
                                    tuple(int(h) for h in hidden.split(",") if h), json.loads(previous)))
        return
    if args.report:
        out = Path(args.results).parent
        text = render(Path(args.results), out)
        common.atomic_write_text(out / "scaling.md", text)
        print(text)
        return
    for n in args.num_envs:
        if run(args.kind, args.backend, n, args)["status"] == "oom" and args.kind == "memory":
            break  # larger counts will not fit either


if __name__ == "__main__":
    main()
