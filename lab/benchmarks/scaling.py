"""Efficiency and scalability of PPO training (issue 9: TocabiLab's chapter 5 on our system).

    python -m lab.benchmarks.scaling --kind raw --num_envs 8 32 96 1024 4096 16384 65536   # raw mujoco-warp ceiling
    python -m lab.benchmarks.scaling --kind time --num_envs 4096 1024 96 32 8              # 983,040 env-steps each
    python -m lab.benchmarks.scaling --kind time --backend cpu --num_envs 96 32 8          # C MuJoCo CPU backend
    python -m lab.benchmarks.scaling --kind memory --num_envs 8 16 32 ... 65536 98304      # 3 iterations each
    python -m lab.benchmarks.scaling --report                                              # scaling.{md,png}

Each measurement runs in a fresh ``train_throughput`` process and writes ``<results>/<kind>_<backend>_<envs:07d>.json``
(kept unless its status is in ``--redo``); a memory sweep stops at the first count that runs out of device memory.
Same recipe everywhere: the default preset, rollouts of at least 2,048 transitions, mini-batches of a quarter of one
(capped at the preset's). See docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
from pathlib import Path

from . import common

TARGET = 983_040  # TocabiLab's budget: 4,096 envs x 24 steps x 10 iterations
TOCABILAB_BEST = TARGET / 850  # env-steps/s of TocabiLab's best run (Isaac Lab + rsl_rl, 96 envs)
OOM = ("out of memory", "outofmemory", "cudaerrormemoryallocation", "failed to allocate")
STATUSES = ("ok", "partial", "oom", "error")  # a record's; oom and error records have no rates


def _read(path: Path) -> dict:
    """One measurement's result file; where it is no JSON, one ``error:`` line naming it (it was a traceback)."""
    try:
        return common.read_json(path, "remove it and run that measurement again (without --report), which writes it "
                                      "anew")
    except ValueError as err:
        raise SystemExit(f"error: {err}") from None


def run(kind: str, backend: str, n: int, args) -> dict:
    """Measure in a fresh ``train_throughput`` process and write the result (skipped where one exists and its status
    is not in ``--redo``); running out of device memory is a result too (``oom``)."""
    path = Path(args.results) / f"{kind}_{backend}_{n:07d}.json"
    if path.is_file() and (record := _read(path))["status"] not in args.redo:
        print(f"kept {path.name} (status {record['status']}; --redo {record['status']} measures it again)", flush=True)
        return record
    base = common.config("default")
    steps = max(base.ppo.steps_per_env, math.ceil(2048 / n))  # small counts: rollouts of at least 2,048 transitions
    batch = min(base.ppo.minibatch_size, n * steps // 4)
    rounds = 0 if kind == "raw" else 3 if kind == "memory" else math.ceil(TARGET / (n * steps))
    sizes = args.hidden.replace(",", " ")  # --set takes a tuple space-separated, as ppo_walk.py does
    hidden = [f"ppo.actor_hidden={sizes}", f"ppo.critic_hidden={sizes}"] if args.hidden else []
    meta, r = common.meta("scaling", None, "cpu"), {}  # no CUDA context in this driving process: the child names it
    try:
        r = common.run_child("train_throughput", [
            "--num_envs", str(n), "--iterations", str(max(rounds - 1, 0)), "--warmup", str(min(rounds, 1)),
            "--raw_steps", str(200 if kind == "raw" else 0), "--device", "cuda" if backend == "gpu" else "cpu",
            "--run_dir", args.run_dir, "--set", f"ppo.steps_per_env={steps}", f"ppo.minibatch_size={batch}",
            f"max_minutes={args.max_minutes}", *hidden], env={"CUDA_VISIBLE_DEVICES": ""} if backend == "cpu" else None)
        record = {"status": "ok", "raw_policy_steps_per_s": r["raw_policy_steps_per_s"]} if kind == "raw" else {
            **{k: r[k] for k in ("status", "iterations", "env_steps", "train_wall_s", "setup_s", "env_graph")},
            "total_wall_s": r["train_wall_s"] + r["setup_s"], "env_steps_per_s": r["env_steps"] / r["train_wall_s"],
            "steady_env_steps_per_s": r["train_env_steps_per_s"], "config": {"steps_per_env": steps,
                                                                             "minibatch_size": batch},
            "cpu": {"cores_used_mean": r["cores_used_mean"]}, "host": {"peak_rss_gib": r["peak_rss_gib"]},
            "gpu": {k: r[k] for k in ("torch_peak_allocated_gib", "torch_peak_reserved_gib", "device_peak_used_gib")}
            if backend == "gpu" else None}
    except RuntimeError as err:
        record = {"status": "oom" if any(m in str(err).lower() for m in OOM) else "error", "error": str(err)[-3000:]}
        if record["status"] == "error":  # its cause, where the report keeps only the status
            last = str(err).strip().rpartition("\n")[2]
            print(f"{path.name}: the measurement failed: {last}", flush=True)
    meta["gpu"] = r.get("device_name", "?")
    record = {"kind": kind, "backend": backend, "num_envs": n, **record, "meta": meta}
    common.write_json(path, record)
    print(f"{path.name}: {record['status']} {common.fmt(record.get('env_steps_per_s'))} env-steps/s", flush=True)
    return record


def render(folder: Path, out: Path) -> str:
    rec = {(r["kind"], r["backend"], r["num_envs"]): r for r in map(_read, folder.iterdir())}
    get = lambda kind, backend: sorted((k[2], r) for k, r in rec.items() if k[:2] == (kind, backend))
    # The rates come from measured records only; a time run that ran out of memory or failed is a status-only row.
    measured = lambda kind, backend: [(n, r) for n, r in get(kind, backend) if r["status"] in ("ok", "partial")]
    raw = {n: r["raw_policy_steps_per_s"] for n, r in measured("raw", "gpu")}
    time_rows = []
    for backend, label in (("gpu", "GPU (mujoco-warp)"), ("cpu", "CPU (C MuJoCo)")):
        for n, r in get("time", backend):
            if r["status"] not in ("ok", "partial"):
                time_rows.append((label, f"{n:,}", *["-"] * 8, r["status"]))
                continue
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
    trained = dict(measured("time", "gpu"))
    # A count with a 983,040-step run takes its numbers from it (the short runs at those counts are older, eager ones).
    mem = {**{n: (r, "short run") for n, r in get("memory", "gpu")}, **{n: (r, "983k run") for n, r in trained.items()}}
    gpu = lambda r, k: (r.get("gpu") or {}).get(k)
    device = lambda r: (r.get("gpu") or {}).get("device_peak_used_gib", gpu(r, "device_used_end_gib"))  # or older
    mem_rows = [(f"{n:,}", src, r["status"], *(common.fmt(x, ".2f") for x in (
                    r.get("host", {}).get("peak_rss_gib"), gpu(r, "torch_peak_allocated_gib"),
                    gpu(r, "torch_peak_reserved_gib"), device(r), r.get("cpu", {}).get("cores_used_mean"))),
                 common.fmt(r.get("env_steps_per_s") if r["status"] == "ok" else None, ",.0f", "not measured"))
                for n, (r, src) in sorted(mem.items())]
    used = [(n, device(r)) for n, (r, _) in sorted(mem.items()) if r["status"] == "ok" and device(r)]
    fit = [(n, gib) for n, gib in used if n >= 1024]
    slope = statistics.linear_regression(*zip(*fit, strict=True)).slope if len(fit) > 1 else None  # GiB per env
    cpu_best = max((r["env_steps_per_s"] for _, r in measured("time", "cpu")), default=None)
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
    _plot(measured, raw, used, out)
    m = {**trained.get(4096, next(iter(rec.values())))["meta"], "date": max(r["meta"]["date"] for r in rec.values())}
    return (f"# Efficiency and scalability: TocabiLab's chapter 5 on our system ({m['gpu']})\n\n"
            f"From the result files in `scaling/` (one fresh process each, measured up to {m['date']}); regenerate "
            f"with `python -m lab.benchmarks.scaling --report`. *Training time* runs from finished set-up to the end of "
            f"the last update (TocabiLab's timer); *total* adds the set-up; *s per 983,040* is 983,040 ÷ env-steps/s "
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


def _plot(measured, raw, fit, out: Path) -> None:
    time_ = {b: ([n for n, _ in measured("time", b)], [r["env_steps_per_s"] for _, r in measured("time", b)])
             for b in ("gpu", "cpu")}
    common.plot(out / "scaling.png", [
        {"lines": {b: (n, [TARGET / x for x in y]) for b, (n, y) in time_.items()}, "hlines": [(850, "TocabiLab best")],
         "ylabel": "s per 983,040 env-steps", "xscale": "log", "yscale": "log", "xlabel": "envs"},
        {"lines": {**{f"{b} training": v for b, v in time_.items()}, "raw mujoco-warp": (sorted(raw), [
            raw[n] for n in sorted(raw)])}, "ylabel": "env-steps/s", "xscale": "log", "yscale": "log"},
        {"lines": {"device memory in use": tuple(zip(*fit, strict=True)) or ([], [])}, "ylabel": "GiB", "xscale": "log",
         "xlabel": "envs"}])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kind", choices=("time", "memory", "raw"), default="time",
                        help="time: train 983,040 env-steps; memory: 3 iterations, memory peaks; raw: the raw "
                             "mujoco-warp ceiling alone (default: time)")
    parser.add_argument("--backend", choices=("gpu", "cpu"), default="gpu",
                        help="gpu (mujoco-warp) or cpu (C MuJoCo, no GPU visible) (default: gpu)")
    parser.add_argument("--num_envs", type=int, nargs="+", default=[4096],
                        help="robot counts, each measured in a fresh process, in the order given (default: 4096)")
    parser.add_argument("--max_minutes", type=float, default=9.0, help="a training run's own time limit")
    parser.add_argument("--redo", nargs="*", default=[], choices=STATUSES,
                        help="measure results of these statuses again")
    parser.add_argument("--hidden", default="", help="actor and critic sizes, e.g. 64,64 (default: the preset's)")
    parser.add_argument("--results", default=str(common.DOCS / "scaling"),
                        help="folder of the per-measurement <kind>_<backend>_<envs>.json; --report writes "
                             "scaling.{md,png} into its parent (default: docs/benchmarks/scaling)")
    parser.add_argument("--run_dir", default="/tmp/tocabi_scaling_runs", help="scratch folder of the training runs")
    parser.add_argument("--report", action="store_true", help="render scaling.{md,png} beside --results")
    args = parser.parse_args(argv)
    if min(args.num_envs) < 1 or not 0 < args.max_minutes < math.inf:  # max_minutes 0 would mean no time limit
        parser.error(f"--num_envs must be >= 1 and --max_minutes a positive number, got {args.num_envs} and "
                     f"{args.max_minutes}")
    if args.report:
        out = Path(args.results).parent
        text = render(Path(args.results), out)
        common.atomic_write_text(out / "scaling.md", text)
        print(text)
        return
    failed = []
    for n in args.num_envs:
        status = run(args.kind, args.backend, n, args)["status"]
        failed += [n] if status == "error" else []
        if status == "oom" and args.kind == "memory":
            break  # larger counts will not fit either
    if failed:
        sys.exit(f"error: the {args.kind} measurement failed at {', '.join(map(str, failed))} envs (the error is in "
                 f"its result file under {args.results}); --redo error measures it again")


if __name__ == "__main__":
    main()
