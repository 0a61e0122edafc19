"""``python -m lab.benchmarks.update_profile``: where one PPO update's GPU time goes, kernel by kernel.

Trains a preset as the throughput benchmarks do (:func:`common.run_config`: ``--num_envs`` envs, the update inline,
not overlapped) for four iterations and profiles the third update with ``torch.profiler``: by then the mini-batch
step is captured (``ppo.update_graph``), so the profile holds what a training update replays, with each
mini-batch gathered outside the graph, as an update that is not overlapped gathers it. The report lists the
update's total GPU time (its kernels' and copies' own times, summed, as the profiler's table sums them) and the
kernels that take most of it.
``--compile_loss`` wraps the loss in ``torch.compile`` first (``ppo.compile_loss``)::

    python -m lab.benchmarks.update_profile --num_envs 16384 --set ppo.matmul_precision=high --name update_16k
    python -m lab.benchmarks.update_profile --num_envs 16384 --set ppo.matmul_precision=high --compile_loss \\
        --name update_16k_compiled_loss

On a CPU (``--device cpu``, a smoke run) the times are the host's.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from . import common
from .train_throughput import compile_override

NAME = "update_profile"
#: The update profiled: the first captures the mini-batch step, the second is the first replayed in full.
PROFILED = 3


def profile_update(n: int, device: str, overrides: dict, run_dir: str, compile_loss: bool = False,
                   rows: int = 25) -> dict:
    """Train ``PROFILED + 1`` iterations at ``n`` envs and profile update number ``PROFILED``: its total GPU time
    (ms: its kernels and copies; on a CPU the host's ops), the number of mini-batch steps and the ``rows`` kernels
    (ops on a CPU) with the most own time."""
    from torch.profiler import ProfilerActivity, profile

    cfg = common.run_config(n, PROFILED + 1, {**overrides, **compile_override(compile_loss)}, run_dir,
                            f"profile_{n}", device)
    if cfg.ppo.overlap_update:
        raise SystemExit(f"{NAME} profiles the update alone: leave ppo.overlap_update off")
    cuda = torch.device(device).type == "cuda"
    sync = (lambda: torch.cuda.synchronize(device)) if cuda else (lambda: None)  # noqa: E731
    update_stats, seen = common.trainer._update_stats, {"calls": 0}

    def profiled(*args, **kwargs):
        seen["calls"] += 1
        if seen["calls"] != PROFILED:
            return update_stats(*args, **kwargs)
        sync()
        with profile(activities=[ProfilerActivity.CPU, *([ProfilerActivity.CUDA] if cuda else [])]) as prof:
            out = update_stats(*args, **kwargs)
            sync()
        seen["table"] = prof.key_averages()
        return out

    patches = {"_update_stats": profiled}
    with common.trainer_patched(patches, []):
        common.train(cfg)
    if "table" not in seen:
        raise RuntimeError(f"{NAME}: the run ended after {seen['calls']} updates, before update {PROFILED}")
    entries = own_times(seen["table"], cuda)
    total_us = sum(us for _, us in entries)
    per_epoch = max(1, n * cfg.ppo.steps_per_env // cfg.ppo.minibatch_size)
    return {"num_envs": n, "overrides": overrides, "compile_loss": compile_loss, "clock": "GPU" if cuda else "host",
            "update_ms": total_us / 1e3, "minibatch_steps": cfg.ppo.epochs * per_epoch,
            "minibatch_size": cfg.ppo.minibatch_size,
            "top": [{"name": e.key, "calls": e.count, "own_ms": us / 1e3} for e, us in entries[:rows]]}


def own_times(table, cuda: bool) -> list[tuple]:
    """``(entry, own time in µs)`` of a profile's ``key_averages()``, most first. On a GPU the kernels and copies
    alone, as the profiler's own table sums them: an op's own GPU time repeats that of the kernels it launched
    (``aten::index`` and its index kernel), and a user annotation's spans the kernels inside it. On a CPU every op
    with its own host time."""
    if cuda:
        from torch.autograd import DeviceType

        pairs = [(e, e.self_device_time_total) for e in table
                 if e.device_type == DeviceType.CUDA and not getattr(e, "is_user_annotation", False)]
    else:
        pairs = [(e, e.self_cpu_time_total) for e in table]
    return sorted(pairs, key=lambda p: p[1], reverse=True)


def render(data: dict, out: Path) -> str:
    r, m = data["results"], data["meta"]
    lines = [f"# One PPO update, kernel by kernel ({m['gpu']}, {m['date']})", "", f"Command: `{m['command']}`", "",
             f"{r['num_envs']:,} envs, {r['minibatch_steps']} mini-batch steps of {r['minibatch_size']:,} rows, the "
             f"loss {'compiled' if r['compile_loss'] else 'eager'}: **{r['update_ms']:.1f} ms** of {r['clock']} time "
             f"in all ({r['update_ms'] / r['minibatch_steps']:.2f} ms per mini-batch step).", "",
             "| kernel or op | calls | own time [ms] | share |", "|---|---:|---:|---:|"]
    for e in r["top"]:
        name = e["name"].replace("|", "\\|")
        name = name if len(name) <= 90 else name[:87] + "..."
        lines.append(f"| `{name}` | {e['calls']} | {e['own_ms']:.2f} | {e['own_ms'] / r['update_ms']:.1%} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--num_envs", type=int, default=16384, help="robots of the training run profiled")
    parser.add_argument("--set", nargs="*", default=[], metavar="PATH=VALUE",
                        help="config overrides (dotted paths), e.g. ppo.matmul_precision=high; preset=NAME")
    parser.add_argument("--compile_loss", action="store_true", help="the PPO loss wrapped in torch.compile")
    parser.add_argument("--rows", type=int, default=25, help="kernels and ops listed, those with most own time")
    parser.add_argument("--device", default="cuda", help="cuda, or cpu for a smoke run of the script")
    parser.add_argument("--run_dir", default="/tmp/tocabi_bench_runs", help="scratch folder of the training run")
    parser.add_argument("--out", default=str(common.DOCS), help="folder of the report <name>.json and .md")
    parser.add_argument("--name", default=NAME, help="the report's file name, <out>/<name>.json")
    args = parser.parse_args(argv)
    if args.num_envs < 1 or args.rows < 1:
        parser.error(f"--num_envs and --rows take counts >= 1, not {args.num_envs} and {args.rows}")
    common.require_cuda(parser, args.device, "pass --device cpu for a smoke run of the script")
    result = profile_update(args.num_envs, args.device, common.parse_overrides(args.set), args.run_dir,
                            args.compile_loss, args.rows)
    print(common.publish(args.out, args.name, {"meta": common.meta(NAME, argv, args.device), "results": result},
                         render, measured_on=args.device))


if __name__ == "__main__":
    main()
