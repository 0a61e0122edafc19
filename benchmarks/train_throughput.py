"""Training throughput (collection + PPO update) against raw mujoco-warp stepping of the same model, same process.

    python -m benchmarks.train_throughput --num_envs 4096 16384 --iterations 10
    python -m benchmarks.train_throughput --num_envs 8 96 4096 --set cuda_graph=on --name graph_on_8_to_4096 \\
        --out docs/benchmarks/env_graph     # and the same with cuda_graph=off: the env-graph ablation
    python -m benchmarks.train_throughput --env_graph_report   # env_graph.{md,png} from the ablation's JSON pairs

Each env count runs in a fresh process: ``--iterations`` PPO iterations of the default preset after ``--warmup``
give training env-steps/s; the raw ceiling is measured right after in the same process. Memory: the torch
allocator's peaks and the device-wide peak in use (sampled every 50 ms: warp's buffers and the CUDA context too).
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

from . import common

NAME = "train_throughput"
ENV_GRAPH = common.DOCS / "env_graph"


def measure(n: int, iterations: int, warmup: int, raw_steps: int, device: str, run_dir: str, overrides: dict) -> dict:
    steps = overrides.get("steps_per_env", common.config("default").steps_per_env)
    cfg = common.config("default", **{"minibatch_size": min(49152, n * steps // 4), **overrides, "num_envs": n,
                                      "total_env_steps": (warmup + iterations) * n * steps, "run_dir": run_dir,
                                      "name": f"train_{n}", "checkpoint_every": 10**6, "progress_bar": False,
                                      "eval_at_end": False, "log_every": 1, "device": device})
    shutil.rmtree(Path(run_dir) / cfg.name, ignore_errors=True)  # the benchmark's own scratch run: start afresh
    start = common.device_used_gib(device)
    with common.MemoryPeak(device) as peak:
        _, rows = common.train(cfg)
    rate = common.window_rate(rows, skip=warmup - 1)  # env_steps_per_s is cumulative: time after the warm-up
    raw = common.raw_policy_steps_per_second(n, raw_steps, device) if raw_steps else None
    return {"num_envs": n, "train_env_steps_per_s": rate, "raw_policy_steps_per_s": raw,
            "ratio_train_over_raw": rate / raw if raw else None, **common.torch_peaks(),
            "device_peak_used_gib": peak.device_gib, "device_used_at_start_gib": start,
            "update_s_last": float(rows[-1]["update_s"]), "overrides": overrides}


def render(data: dict, out) -> str:
    rows = [(r["num_envs"], common.fmt(r["train_env_steps_per_s"]), common.fmt(r["raw_policy_steps_per_s"]),
             common.fmt(r["ratio_train_over_raw"], ".2f"), f"{r['torch_peak_allocated_gib']:.2f}",
             f"{r['torch_peak_reserved_gib']:.2f}", common.fmt(r["device_peak_used_gib"], ".2f"))
            for r in data["results"]]
    return common.page("Training throughput", data, common.table(
        ("envs", "train env-steps/s", "raw mujoco-warp policy steps/s", "train / raw", "torch peak alloc GiB",
         "torch peak reserved GiB", "device peak used GiB"), rows))


def env_graph_rows(folder: Path) -> list[dict]:
    """Rates with the env-step graph on and off per env count, from pairs ``graph_on_X.json``/``graph_off_X.json``
    (each pair measured in one device command, so both modes share a machine)."""
    rows = []
    for on_path in sorted(folder.glob("graph_on_*.json")):
        off_path = on_path.with_name(on_path.name.replace("graph_on_", "graph_off_"))
        if not off_path.is_file():
            raise FileNotFoundError(f"{on_path} has no eager counterpart {off_path.name}")
        on, off = (json.loads(p.read_text()) for p in (on_path, off_path))
        eager = {r["num_envs"]: r["train_env_steps_per_s"] for r in off["results"]}
        rows += [{"num_envs": r["num_envs"], "graph": r["train_env_steps_per_s"], "eager": eager[r["num_envs"]],
                  "raw": r["raw_policy_steps_per_s"], "date": on["meta"]["date"], "gpu": on["meta"]["gpu"],
                  "commands": (on["meta"]["command"], off["meta"]["command"])} for r in on["results"]]
    return sorted(rows, key=lambda r: r["num_envs"])


def render_env_graph(folder: Path, out: Path) -> str:
    """``env_graph.md`` and ``.png``: the evidence behind ``cuda_graph="auto"`` (captured up to 128 envs)."""
    from tocabi_torchrl.rl.config import ENV_GRAPH_AUTO_MAX_ENVS as auto

    rows = env_graph_rows(folder)
    if not rows:
        raise SystemExit(f"no graph_on_*.json results under {folder}")
    plt = common.pyplot()
    if plt is not None:
        fig, ax = plt.subplots(figsize=(6.4, 3.6))
        ax.plot([r["num_envs"] for r in rows], [r["graph"] / r["eager"] for r in rows], "o-", label="graph / eager")
        ax.axhline(1.0, color="grey", lw=0.8)
        ax.axvline(auto, color="tab:red", ls="--", lw=0.8, label=f"auto: graph up to {auto} envs")
        ax.set_xscale("log", base=2)
        ax.set(xlabel="envs", ylabel="training env-steps/s ratio", title="Env step as one CUDA graph vs eager")
        ax.legend()
        common.save(fig, out / "env_graph.png")
    body = common.table(("envs", "graph env-steps/s", "eager env-steps/s", "graph / eager",
                         "raw mujoco-warp policy steps/s", "date"),
                        [(f"{r['num_envs']:,}", f"{r['graph']:,.0f}", f"{r['eager']:,.0f}",
                          f"{r['graph'] / r['eager']:.2f}", f"{r['raw']:,.0f}", r["date"]) for r in rows])
    commands = "\n".join(f"    {c}" for c in dict.fromkeys(c for r in rows for c in r["commands"]))
    text = (f"# The env step as one CUDA graph: training env-steps/s with `cuda_graph` on and off ({rows[0]['gpu']})"
            f"\n\nDefault preset, 48 steps per env, each on/off pair from one device command. Small counts are "
            f"launch-bound and the graph removes the launches; from a few hundred envs the physics dominates. Hence "
            f"`cuda_graph=\"auto\"`: captured up to {auto:,} envs (`ENV_GRAPH_AUTO_MAX_ENVS`).\n\n{body}\n\n"
            f"![graph / eager vs env count](env_graph.png)\n\nCommands (older runs spelled the modes true/false and "
            f"ran the scripts by path):\n\n{commands}\n\nRegenerate: `python -m benchmarks.train_throughput "
            f"--env_graph_report`.\n")
    return text


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--num_envs", type=int, nargs="+", default=[4096, 16384])
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--raw_steps", type=int, default=200, help="raw mujoco-warp steps timed (0: skip)")
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                        help="training config overrides for an ablation, e.g. cuda_graph=off")
    parser.add_argument("--device", default="cuda", help="cuda, or cpu for a smoke run of the script")
    parser.add_argument("--run_dir", default="/tmp/tocabi_bench_runs", help="scratch folder of the training runs")
    parser.add_argument("--out", default=str(common.DOCS))
    parser.add_argument("--name", default=NAME)
    parser.add_argument("--env_graph_report", action="store_true", help="render env_graph.md from --out's pairs")
    parser.add_argument("--child", action="store_true", help="measure one env count in this process (internal)")
    args = parser.parse_args(argv)
    if args.env_graph_report:
        text = render_env_graph(ENV_GRAPH, common.DOCS)
        common.atomic_write_text(common.DOCS / "env_graph.md", text)
        print(text)
        return
    overrides = common.parse_overrides(args.set)
    if args.child:
        common.child_result(measure(args.num_envs[0], args.iterations, args.warmup, args.raw_steps, args.device,
                                    args.run_dir, overrides))
        return
    results = []
    for n in args.num_envs:
        results.append(common.run_child(NAME, [
            "--num_envs", str(n), "--iterations", str(args.iterations), "--warmup", str(args.warmup), "--raw_steps",
            str(args.raw_steps), "--device", args.device, "--run_dir", f"{args.run_dir}/{args.name}", "--set",
            *args.set]))
        print(f"{n} envs: {results[-1]['train_env_steps_per_s']:,.0f} env-steps/s", flush=True)
    print(common.publish(args.out, args.name, {"meta": common.meta(NAME, argv, args.device), "results": results},
                         render))


if __name__ == "__main__":
    main()
