"""Training throughput (collection + PPO update) against raw mujoco-warp stepping of the same model, same run.

    python benchmarks/train_throughput.py --num_envs 4096 16384 --iterations 10

Each env count runs in a fresh process (so memory figures are its own): ``iterations`` PPO iterations of the default
preset after ``warmup`` iterations give training env-steps/s; the raw ceiling is ``mujoco_warp.step`` × substeps in
one CUDA graph with the legs PD-held (``benchmarks/sim_throughput.py``), measured in the same process right after.
Memory: the torch allocator's peak (allocated and reserved) and the device-wide peak seen by ``cudaMemGetInfo``
(sampled every 50 ms while training; includes warp's simulator buffers and the CUDA context).
Writes ``docs/benchmarks/train_throughput.{json,md}``.
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from report import run_meta, write_report  # noqa: E402


class DevicePeak:
    """Largest device-wide memory use (``total - free`` from ``cudaMemGetInfo``) seen while the context is open."""

    def __init__(self, every_s: float = 0.05):
        self.every_s, self.peak_gib = every_s, 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _sample(self) -> None:
        free, total = torch.cuda.mem_get_info()
        self.peak_gib = max(self.peak_gib, (total - free) / 2**30)

    def _run(self) -> None:
        while not self._stop.wait(self.every_s):
            self._sample()

    def __enter__(self) -> DevicePeak:
        self._sample()
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self._sample()


def measure(num_envs: int, iterations: int, warmup: int, raw_steps: int, overrides: dict) -> dict:
    """One env count, in this process."""
    from sim_throughput import raw_policy_steps_per_second

    from tocabi_torchrl.rl.config import preset_config
    from tocabi_torchrl.rl.trainer import train

    torch.cuda.init()
    free, total = torch.cuda.mem_get_info()
    steps = preset_config("default").steps_per_env
    cfg = preset_config("default", num_envs=num_envs, total_env_steps=(warmup + iterations) * num_envs * steps,
                        minibatch_size=min(49152, num_envs * steps // 4), run_dir="/tmp/bench_runs",
                        name=f"train_{num_envs}", checkpoint_every=10**6, progress_bar=False, eval_at_end=False,
                        log_every=1, device="cuda", **overrides)
    shutil.rmtree(Path(cfg.run_dir) / cfg.name, ignore_errors=True)  # scratch: a re-measurement starts fresh
    with DevicePeak() as peak:
        result = train(cfg)
    with open(result.run_dir / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    # env_steps_per_s is cumulative from the start: use the wall-clock difference after the warm-up iterations.
    t0, t1 = float(rows[warmup - 1]["wall_s"]), float(rows[-1]["wall_s"])
    train_sps = (int(rows[-1]["env_steps"]) - int(rows[warmup - 1]["env_steps"])) / (t1 - t0)
    raw = raw_policy_steps_per_second(num_envs, raw_steps)
    return {"num_envs": num_envs, "train_env_steps_per_s": train_sps, "raw_policy_steps_per_s": raw,
            "ratio_train_over_raw": train_sps / raw,
            "torch_peak_allocated_gib": torch.cuda.max_memory_allocated() / 2**30,
            "torch_peak_reserved_gib": torch.cuda.max_memory_reserved() / 2**30,
            "device_peak_used_gib": peak.peak_gib, "device_used_at_start_gib": (total - free) / 2**30,
            "update_s_last": float(rows[-1]["update_s"]), "overrides": overrides}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--num_envs", type=int, nargs="+", default=[4096, 16384])
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--raw_steps", type=int, default=200)
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                        help="PPOConfig overrides for an ablation, e.g. cuda_graph=false store_env_signals=true")
    parser.add_argument("--out", default="docs/benchmarks")
    parser.add_argument("--name", default="train_throughput")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if not torch.cuda.is_available():
        raise SystemExit("train_throughput needs a CUDA GPU")
    from tocabi_torchrl.rl.config import PPOConfig, _parse_value

    defaults = PPOConfig()
    overrides = {}
    for item in args.set:
        field, _, value = item.partition("=")
        if not hasattr(defaults, field):
            raise SystemExit(f"--set {item}: PPOConfig has no field {field!r}")
        kind = type(getattr(defaults, field))
        overrides[field] = _parse_value(bool, value) if kind is bool else kind(value)
    if args.child:
        (n,) = args.num_envs
        print("RESULT " + json.dumps(measure(n, args.iterations, args.warmup, args.raw_steps, overrides)))
        return
    results = []
    for n in args.num_envs:
        cmd = [sys.executable, __file__, "--child", "--num_envs", str(n), "--iterations", str(args.iterations),
               "--warmup", str(args.warmup), "--raw_steps", str(args.raw_steps), "--set", *args.set]
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
        lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
        if proc.returncode != 0 or not lines:
            sys.stderr.write(proc.stdout[-4000:] + proc.stderr[-4000:])
            raise SystemExit(f"{n} envs failed (exit {proc.returncode})")
        results.append(json.loads(lines[-1][len("RESULT "):]))
        r = results[-1]
        print(f"{n} envs: {r['train_env_steps_per_s']:,.0f} env-steps/s, {r['ratio_train_over_raw']:.2f}x raw, "
              f"device peak {r['device_peak_used_gib']:.2f} GiB", flush=True)
    text = write_report(
        args.out, args.name, "Training throughput", run_meta("train_throughput.py", argv), results,
        ["envs", "train env-steps/s", "raw mujoco-warp policy steps/s", "train / raw", "torch peak alloc GiB",
         "torch peak reserved GiB", "device peak used GiB"],
        lambda r: [str(r["num_envs"]), f"{r['train_env_steps_per_s']:,.0f}", f"{r['raw_policy_steps_per_s']:,.0f}",
                   f"{r['ratio_train_over_raw']:.2f}", f"{r['torch_peak_allocated_gib']:.2f}",
                   f"{r['torch_peak_reserved_gib']:.2f}", f"{r['device_peak_used_gib']:.2f}"],
    )
    print(text)


if __name__ == "__main__":
    main()
