"""Training throughput (collection + PPO update) against raw mujoco-warp stepping of the same model, same run.

    python benchmarks/train_throughput.py --num_envs 4096 16384 --iterations 20

For each env count: ``iterations`` PPO iterations of the default preset (after 3 warm-up iterations) give training
env-steps/s; the raw ceiling is ``mujoco_warp.step`` × substeps in one CUDA graph with the legs PD-held (see
``benchmarks/sim_throughput.py``). Peak GPU memory (torch allocator peak, plus device-wide use from
``cudaMemGetInfo``, which includes warp's allocations) is reported per env count.
Writes ``docs/benchmarks/train_throughput.{json,md}``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from report import run_meta, write_report  # noqa: E402
from sim_throughput import raw_policy_steps_per_second  # noqa: E402

from tocabi_torchrl.rl.config import preset_config  # noqa: E402
from tocabi_torchrl.rl.trainer import train  # noqa: E402


def _device_used_gib() -> float:
    free, total = torch.cuda.mem_get_info()
    return (total - free) / 2**30


def measure(num_envs: int, iterations: int, warmup: int, raw_steps: int) -> dict:
    torch.cuda.empty_cache()
    torch.cuda.reset_peak_memory_stats()
    base_used = _device_used_gib()
    steps = preset_config("default").steps_per_env
    cfg = preset_config("default", num_envs=num_envs, total_env_steps=(warmup + iterations) * num_envs * steps,
                        minibatch_size=min(49152, num_envs * steps // 4), run_dir="/tmp/bench_runs",
                        name=f"train_{num_envs}", checkpoint_every=10**6, progress_bar=False, eval_at_end=False,
                        log_every=1, device="cuda")
    result = train(cfg)
    import csv

    rows = list(csv.DictReader(open(result.run_dir / "metrics.csv")))
    # env_steps_per_s is cumulative from the start: use the last rows' wall-clock difference after warm-up.
    t0, t1 = float(rows[warmup - 1]["wall_s"]), float(rows[-1]["wall_s"])
    steps = int(rows[-1]["env_steps"]) - int(rows[warmup - 1]["env_steps"])
    train_sps = steps / (t1 - t0)
    peak_alloc = torch.cuda.max_memory_allocated() / 2**30
    used = _device_used_gib()
    raw = raw_policy_steps_per_second(num_envs, raw_steps)
    return {"num_envs": num_envs, "train_env_steps_per_s": train_sps, "raw_policy_steps_per_s": raw,
            "ratio_train_over_raw": train_sps / raw, "torch_peak_allocated_gib": peak_alloc,
            "device_used_gib": used, "device_used_before_gib": base_used,
            "update_s_last": float(rows[-1]["update_s"])}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--num_envs", type=int, nargs="+", default=[4096, 16384])
    parser.add_argument("--iterations", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--raw_steps", type=int, default=200)
    parser.add_argument("--out", default="docs/benchmarks")
    args = parser.parse_args(argv)
    if not torch.cuda.is_available():
        raise SystemExit("train_throughput needs a CUDA GPU")
    results = [measure(n, args.iterations, args.warmup, args.raw_steps) for n in args.num_envs]
    text = write_report(
        args.out, "train_throughput", "Training throughput", run_meta("train_throughput.py", argv), results,
        ["envs", "train env-steps/s", "raw mujoco-warp policy steps/s", "train / raw", "torch peak GiB",
         "device used GiB"],
        lambda r: [str(r["num_envs"]), f"{r['train_env_steps_per_s']:,.0f}", f"{r['raw_policy_steps_per_s']:,.0f}",
                   f"{r['ratio_train_over_raw']:.2f}", f"{r['torch_peak_allocated_gib']:.2f}",
                   f"{r['device_used_gib']:.2f}"],
    )
    print(text)

if __name__ == "__main__":
    main()
