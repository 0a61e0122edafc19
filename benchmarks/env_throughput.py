"""Environment throughput against raw mujoco-warp stepping of the same model, measured in one run.

    python benchmarks/env_throughput.py --num_envs 1024 4096 16384 --steps 200

For each env count, three numbers of policy steps per second (8 physics substeps each):
  * raw: ``mujoco_warp.step`` × 8 in one CUDA graph with the legs PD-held
    (``sim_throughput.raw_policy_steps_per_second``)
  * env: ``TocabiWalk.step`` (torque mode), legs driven by the same PD hold of the initial pose computed in torch
  * make_env: the same through ``make_env``'s transforms (observation history, normalisation, 13 reward terms)
and the ratios env/raw (target >= 0.9 at 4096) and the transforms' share of the env step (target <= 10 %).
Also the collectors' call, ``step_and_maybe_reset`` of the sync-free env (masked reset every step), eager and with
the step captured as a CUDA graph (``cuda_graph=True``), as policy steps per second.
Writes ``docs/benchmarks/env_throughput.{json,md,png}``.
"""

from __future__ import annotations

import argparse
import gc
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from report import run_meta, write_report  # noqa: E402
from sim_throughput import raw_policy_steps_per_second  # noqa: E402

from tocabi_torchrl import make_env, robot  # noqa: E402
from tocabi_torchrl.envs import TocabiWalk  # noqa: E402


def _pd_hold_action(td, kp, kv, q0, limits):
    """Leg torques of a PD hold of the initial pose, as a fraction of the limits; phase rate 0."""
    q, qd = td["joint_pos"][:, :12], td["joint_vel"][:, :12]
    legs = ((kp * (q0 - q) - kv * qd) / limits).clamp(-1.0, 1.0)
    return torch.cat((legs, torch.zeros_like(legs[:, :1])), dim=-1)


def _timed_loop(env, step, steps: int, warmup: int) -> float:
    """Policy steps per second of ``td = step(td_with_action)`` over ``steps`` steps after ``warmup``; the action
    is a PD hold of the initial pose computed from the current ``td``."""
    dev = env.device
    kp, kv = (torch.as_tensor(x, dtype=torch.float32, device=dev) for x in (robot.LEG_KP, robot.LEG_KV))
    q0 = torch.as_tensor(robot.INIT_JOINT_POS[:12], dtype=torch.float32, device=dev)
    limits = torch.as_tensor(robot.LEG_TORQUE_LIMITS, dtype=torch.float32, device=dev)
    td = env.reset()
    for k in range(warmup + steps):
        if k == warmup:
            torch.cuda.synchronize()
            t0 = time.perf_counter()
        td = step(td.set("action", _pd_hold_action(td, kp, kv, q0, limits)))
    torch.cuda.synchronize()
    return steps * env.batch_size[0] / (time.perf_counter() - t0)


def time_env(env, steps: int, warmup: int = 10) -> float:
    """Policy steps per second of ``env.step`` (all envs)."""
    return _timed_loop(env, lambda td: env.step(td)["next"], steps, warmup)


def time_autoreset(env, steps: int, warmup: int = 10) -> float:
    """Policy steps per second of ``env.step_and_maybe_reset`` (what collectors call), same PD-hold actions."""
    return _timed_loop(env, lambda td: env.step_and_maybe_reset(td)[1], steps, warmup)


def _autoreset_rate(n: int, steps: int, cuda_graph: bool) -> float:
    env = make_env(num_envs=n, device="cuda", seed=0, max_episode_steps=10**6, cuda_graph=cuda_graph)
    rate = time_autoreset(env, steps)
    if cuda_graph and not env.graph_captured:
        raise RuntimeError("the step was not captured as a CUDA graph (see the warning above)")
    del env
    gc.collect()
    torch.cuda.empty_cache()
    return rate


def measure(n: int, steps: int) -> dict:
    raw = raw_policy_steps_per_second(n, steps)
    env = TocabiWalk(num_envs=n, device="cuda", seed=0, max_episode_steps=10**6)
    bare = time_env(env, steps)
    upright = float((env.sim.base_pos[:, 2] > 0.8).float().mean())
    del env
    gc.collect()
    torch.cuda.empty_cache()
    tenv = make_env(num_envs=n, device="cuda", seed=0, max_episode_steps=10**6)
    transformed = time_env(tenv, steps)
    del tenv
    gc.collect()
    torch.cuda.empty_cache()
    sync_free = _autoreset_rate(n, steps, cuda_graph=False)
    graphed = _autoreset_rate(n, steps, cuda_graph=True)
    return {
        "num_envs": n,
        "raw_policy_steps_per_s": raw,
        "autoreset_steps_per_s": sync_free,
        "autoreset_graph_steps_per_s": graphed,
        "autoreset_over_raw": sync_free / raw,
        "autoreset_graph_over_raw": graphed / raw,
        "env_steps_per_s": bare,
        "make_env_steps_per_s": transformed,
        "env_over_raw": bare / raw,
        "make_env_over_raw": transformed / raw,
        "transform_share_of_env_step": bare / transformed - 1.0,
        "upright_fraction_after_run": upright,
    }


def _plot(results: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    x = np.arange(len(results))
    fig, ax = plt.subplots(figsize=(7, 4))
    for i, (key, label) in enumerate((("raw_policy_steps_per_s", "raw mujoco-warp"), ("env_steps_per_s", "TocabiWalk"),
                                      ("make_env_steps_per_s", "make_env (transforms)"))):
        ax.bar(x + (i - 1) * 0.27, [r[key] / 1e3 for r in results], 0.27, label=label)
    ax.set_xticks(x, [str(r["num_envs"]) for r in results])
    ax.set_xlabel("parallel envs")
    ax.set_ylabel("policy steps/s (thousands)")
    ax.legend()
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--num_envs", type=int, nargs="+", default=[1024, 4096, 16384])
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--out", default="docs/benchmarks")
    args = parser.parse_args(argv)
    if not torch.cuda.is_available():
        raise SystemExit("env_throughput needs a CUDA GPU")
    results = [measure(n, args.steps) for n in args.num_envs]
    text = write_report(
        args.out, "env_throughput", "Environment throughput", run_meta("env_throughput.py", argv), results,
        ["envs", "raw policy steps/s", "TocabiWalk steps/s", "env / raw", "make_env steps/s", "make_env / raw",
         "transforms' share of env step", "step_and_maybe_reset / raw (eager)", "(CUDA graph)"],
        lambda r: [str(r["num_envs"]), f"{r['raw_policy_steps_per_s']:,.0f}", f"{r['env_steps_per_s']:,.0f}",
                   f"{r['env_over_raw']:.3f}", f"{r['make_env_steps_per_s']:,.0f}", f"{r['make_env_over_raw']:.3f}",
                   f"{100 * r['transform_share_of_env_step']:.1f} %", f"{r['autoreset_over_raw']:.3f}",
                   f"{r['autoreset_graph_over_raw']:.3f}"],
    )
    _plot(results, Path(args.out) / "env_throughput.png")
    print(text)


if __name__ == "__main__":
    main()
