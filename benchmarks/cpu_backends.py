"""CPU env throughput of the two physics backends: C MuJoCo on threads (``backend="mujoco"``) vs mujoco-warp's CPU
device (``backend="warp"``), bare ``TocabiWalk``, legs PD-held as in ``env_throughput.py``.

    python benchmarks/cpu_backends.py --num_envs 8 16 32 96 --label 2core

Env-steps per second = policy steps (8 physics substeps each) × envs / wall time, after a warm-up. The mujoco
backend uses ``--threads`` threads (default: every available core). Writes
``docs/benchmarks/cpu_backends_<label>.{json,md}`` (label default: the host name). Other processes on the machine
share its cores: the load average before the run is recorded in the metadata.
"""

from __future__ import annotations

import argparse
import gc
import os
import socket
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from env_throughput import _pd_hold_action  # noqa: E402
from report import run_meta, write_report  # noqa: E402

from tocabi_torchrl import robot  # noqa: E402
from tocabi_torchrl.envs import TocabiWalk  # noqa: E402
from tocabi_torchrl.sim.config import available_cores  # noqa: E402


def env_steps_per_second(env: TocabiWalk, steps: int, warmup: int) -> float:
    """Env-steps/s of ``env.step`` over ``steps`` policy steps after ``warmup`` (CPU: no device sync needed)."""
    kp, kv = (torch.as_tensor(x, dtype=torch.float32) for x in (robot.LEG_KP, robot.LEG_KV))
    q0 = torch.as_tensor(robot.INIT_JOINT_POS[:12], dtype=torch.float32)
    limits = torch.as_tensor(robot.LEG_TORQUE_LIMITS, dtype=torch.float32)
    td = env.reset()
    for k in range(warmup + steps):
        if k == warmup:
            t0 = time.perf_counter()
        td = env.step(td.set("action", _pd_hold_action(td, kp, kv, q0, limits)))["next"]
    return steps * env.num_envs / (time.perf_counter() - t0)


def measure(backend: str, n: int, steps: int, threads: int | None) -> dict:
    t_build = time.perf_counter()
    env = TocabiWalk(num_envs=n, device="cpu", seed=0, max_episode_steps=10**6, backend=backend, sim_threads=threads)
    build_s = time.perf_counter() - t_build
    rate = env_steps_per_second(env, steps, warmup=max(2, steps // 10))
    upright = float((env.sim.base_pos[:, 2] > 0.8).float().mean())
    del env
    gc.collect()
    return {"backend": backend, "num_envs": n, "env_steps_per_s": rate, "steps": steps, "build_s": build_s,
            "threads": threads if backend == "mujoco" else None, "upright_fraction_after_run": upright}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--num_envs", type=int, nargs="+", default=[8, 16, 32, 96])
    parser.add_argument("--mujoco_steps", type=int, default=100, help="policy steps timed on the mujoco backend")
    parser.add_argument("--warp_steps", type=int, default=20, help="policy steps timed on warp's CPU device")
    parser.add_argument("--threads", type=int, default=None, help="mujoco backend threads (default: all cores)")
    parser.add_argument("--label", default=socket.gethostname())
    parser.add_argument("--out", default="docs/benchmarks")
    args = parser.parse_args(argv)
    import warp as wp

    wp.config.quiet = True
    meta = run_meta("cpu_backends.py", argv)
    threads = args.threads or available_cores()
    meta.update({"cores": available_cores(), "mujoco_threads": threads, "label": args.label,
                 "load_average_before": os.getloadavg()[0]})
    results = []
    for n in args.num_envs:
        mj = measure("mujoco", n, args.mujoco_steps, threads)
        wa = measure("warp", n, args.warp_steps, None)
        results.append({"num_envs": n, "mujoco": mj, "warp_cpu": wa,
                        "mujoco_over_warp": mj["env_steps_per_s"] / wa["env_steps_per_s"]})
        print(f"{n:4d} envs: mujoco {mj['env_steps_per_s']:8.0f} env-steps/s, warp cpu {wa['env_steps_per_s']:8.0f}")
    meta["load_average_after"] = os.getloadavg()[0]

    def row(r: dict) -> list[str]:
        return [str(r["num_envs"]), f"{r['mujoco']['env_steps_per_s']:.0f}", f"{r['warp_cpu']['env_steps_per_s']:.0f}",
                f"{r['mujoco_over_warp']:.1f}×", f"{r['mujoco']['build_s']:.2f}", f"{r['warp_cpu']['build_s']:.1f}"]

    header = ["envs", f"mujoco ({threads} threads) env-steps/s", "warp CPU env-steps/s", "mujoco / warp",
              "mujoco build [s]", "warp build [s]"]
    title = f"CPU backends, {meta['cores']} cores ({args.label})"
    text = write_report(args.out, f"cpu_backends_{args.label}", title, meta, results, header, row)
    print(text)


if __name__ == "__main__":
    main()
