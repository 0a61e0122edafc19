"""Diagnostic (not the gait test): how much of a policy's 8 s drift is its own, and how much the start's rounding.

At a fixed command the gait test's 256 robots start from two rows of the reference motion, so they are two
trajectories, each chaotic in float32 rounding (docs/training.md). Here every robot gets its own small push
instead: for the first ``--kick_seconds`` its deterministic action gets Gaussian noise of ``--kick_std`` (in the
normalised action units), then the policy acts alone as in the gait test. The spread of the 256 drifts shows
whether a pass or fail at the 0.3 m limit is the policy's or the start's. On the CPU backend (C MuJoCo)::

    PYTHONPATH=. python lab/analysis/drift_spread.py --out docs/training/drift_spread.json CKPT [CKPT ...]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from tocabi_torchrl.atomic import atomic_write_text
from tocabi_torchrl.evaluation.record import GaitMetrics, load_policy, policy_steps

LIMIT_M = 0.3


def spread(path: str, num_envs: int, seconds: float, kick_seconds: float, kick_std: float, seed: int) -> dict:
    policy = load_policy(path, num_envs, torch.device("cpu"), nominal=True)  # as the gait tests: the nominal robot
    env, base = policy.env, policy.env.base_env
    steps, kick_steps = policy_steps(seconds, base.dt), round(kick_seconds / base.dt)
    noise = torch.Generator().manual_seed(seed)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.reset()
        metrics = GaitMetrics(td["base_pos"], (0.5, 0.0), base.dt)
        for k in range(steps):
            td = policy.actor(td)
            if k < kick_steps:
                td["action"] = td["action"] + kick_std * torch.randn(td["action"].shape, generator=noise)
            td = env.step(td)
            metrics.update(td["next"])
            td = step_mdp(td)  # as the gait test: fallen robots keep lying, no reset
    per = metrics.per_env()
    lateral = per["lateral_m"].abs()
    q = torch.quantile(lateral, torch.tensor([0.1, 0.5, 0.9])).tolist()
    return {"checkpoint": path, "num_envs": num_envs, "survival": float(per["alive"].float().mean()),
            "forward_m_mean": float(per["forward_m"].mean()), "drift_m_mean": float(lateral.mean()),
            "drift_m_p10_p50_p90": q, "share_within_limit": float((lateral <= LIMIT_M).float().mean())}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoints", nargs="+", help="policy checkpoints (.pt) to measure, one after another")
    parser.add_argument("--num_envs", type=int, default=256,
                        help="robots per checkpoint (default: 256, the gait test's)")
    parser.add_argument("--seconds", type=float, default=8.0, help="length of each walk [s] (default: 8)")
    parser.add_argument("--kick_seconds", type=float, default=0.1,
                        help="the first seconds of the walk, in which the action gets the noise [s] (default: 0.1)")
    parser.add_argument("--kick_std", type=float, default=0.01,
                        help="std of that Gaussian noise, in normalised action units (default: 0.01)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the noise's draws (default: 0)")
    parser.add_argument("--out", type=Path, required=True, help="JSON to write (must not exist yet)")
    args = parser.parse_args(argv)
    if args.out.exists():
        raise SystemExit(f"error: {args.out} exists; give another --out (results are never overwritten)")
    results = []
    for path in args.checkpoints:
        t0 = time.perf_counter()
        results.append(spread(path, args.num_envs, args.seconds, args.kick_seconds, args.kick_std, args.seed))
        print(json.dumps(results[-1]), f"({time.perf_counter() - t0:.0f} s)", flush=True)
    used = sys.argv[1:] if argv is None else argv
    data = {"command": "PYTHONPATH=. python lab/analysis/drift_spread.py " + " ".join(used),
            "settings": {k: v for k, v in vars(args).items() if k not in ("checkpoints", "out")}, "results": results}
    atomic_write_text(args.out, json.dumps(data, indent=2) + "\n")
    return data


if __name__ == "__main__":
    main()
