"""Where a policy's actions lie against the env's action bounds: how often training's sampled actions are clipped.

Rolls the policy out in one case of the robust test (``nominal`` by default) on the CPU (C MuJoCo), sampling its
actions as training does (the Gaussian's draw, ``ExplorationType.RANDOM``, seeded), and reports per action entry
(the 12 leg actions in [-1, 1], then the phase rate in [0, 1]) the Gaussian's mean μ (its mean and 5th and 95th
percentiles over every step and robot) and the share of sampled actions outside the bounds, which the env clips.
Every draw beyond a bound reaches the robot as the bound itself: the farther the mean lies beyond one, the fewer of
its draws act differently, and the weaker the signal that could bring it back.

Wrote docs/training/pd/h100_decoupled_kl_seed0/action_bounds.json (about 7 s per checkpoint of 16 robots on
2 cores)::

    PYTHONPATH=. python lab/analysis/action_bounds.py --num_envs 16 \\
        --out docs/training/pd/h100_decoupled_kl_seed0/action_bounds.json \\
        --checkpoint runs/time_to_walk/pd_decoupled_kl/checkpoints/wall_00240s.pt \\
        runs/time_to_walk/pd_decoupled_kl/checkpoints/wall_00360s.pt \\
        runs/time_to_walk/pd_decoupled/checkpoints/wall_00360s.pt \\
        assets/policies/tocabi_walk_ppo.pt assets/policies/tocabi_walk_robust.pt
"""

from __future__ import annotations

import platform
import time
from pathlib import Path

import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from tocabi_torchrl.evaluation import robust
from tocabi_torchrl.evaluation.record import policy_steps
from tocabi_torchrl.transforms.normalize import freeze_running_statistics

from lab.analysis.reports import case_parser, check_paths, write_report


def bound_statistics(loc: torch.Tensor, action: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> list[dict]:
    """Per action entry: the mean μ's mean and 5th/95th percentiles, the share of μ outside ``[low, high]`` and the
    share of sampled ``action`` outside it; ``loc`` and ``action`` (N, A) over every step and robot, ``low`` and
    ``high`` (A,).

    >>> s = bound_statistics(torch.tensor([[-0.5], [-0.1]]), torch.tensor([[-0.6], [0.2]]), torch.zeros(1),
    ...                      torch.ones(1))
    >>> s[0]["mean_outside"], s[0]["sampled_outside"]
    (1.0, 0.5)
    """
    outside_mean = ((loc < low) | (loc > high)).float().mean(0)
    outside_sample = ((action < low) | (action > high)).float().mean(0)
    q = torch.quantile(loc, torch.tensor([0.05, 0.95], dtype=loc.dtype), dim=0)
    return [{"mean": round(float(loc[:, j].mean()), 4), "p5": round(float(q[0, j]), 4),
             "p95": round(float(q[1, j]), 4), "mean_outside": round(float(outside_mean[j]), 4),
             "sampled_outside": round(float(outside_sample[j]), 4)} for j in range(loc.shape[1])]


def measure(path: Path, case: str, num_envs: int, seconds: float, seed: int) -> dict:
    """The action statistics of one checkpoint's policy over one case of the robust test, ``num_envs`` robots for
    ``seconds`` [s], each robot's frames until it fell: the checkpoint, the case and its settings, the control mode,
    ``phase_rate`` (the last entry's :func:`bound_statistics`), the most of any leg entry's ``sampled_outside``
    and ``mean_outside``, and ``entries`` (every entry's, legs first)."""
    test = robust.RobustTestConfig(num_envs=num_envs, seconds=seconds)
    _, cfg, env, agent = robust.checkpoint_case(path, case, "cpu", test)
    freeze_running_statistics(env)
    spec = env.action_spec
    low, high = spec.space.low[0], spec.space.high[0]
    torch.manual_seed(seed)
    locs, actions = [], []
    alive = torch.ones(num_envs, dtype=torch.bool)  # a robot's frames after it fell are not the policy walking
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        td = env.reset()
        for _ in range(policy_steps(seconds, float(env.base_env.dt))):
            td = agent.actor(td)
            locs.append(td["loc"][alive].clone())
            actions.append(td["action"][alive].clone())
            td = env.step(td)
            alive &= ~td["next", "done"].reshape(-1)
            td = step_mdp(td)
    stats = bound_statistics(torch.cat(locs), torch.cat(actions), low, high)
    legs = stats[:-1]
    return {"checkpoint": str(path), "case": case, "robots": num_envs, "seconds": seconds, "seed": seed,
            "control_mode": cfg.env.control.mode, "phase_rate": stats[-1],
            "legs_sampled_outside_max": max(s["sampled_outside"] for s in legs),
            "legs_mean_outside_max": max(s["mean_outside"] for s in legs), "entries": stats}


def main(argv=None) -> int:
    p = case_parser(__doc__, num_envs=16, seconds=2.0)
    p.add_argument("--seed", type=int, default=0, help="seed of the sampled actions")
    p.add_argument("--out", type=Path, default=None, help="JSON to write (default: print only)")
    args = p.parse_args(argv)
    check_paths(p, args.checkpoint, args.out)
    if args.num_envs < 1 or not args.seconds > 0:
        p.error("--num_envs must be >= 1 and --seconds > 0")
    results = []
    for path in args.checkpoint:
        start = time.perf_counter()
        r = measure(path, args.case, args.num_envs, args.seconds, args.seed)
        ph = r["phase_rate"]
        print(f"{path}: phase rate μ {ph['mean']:+.3f} (p5 {ph['p5']:+.3f}, p95 {ph['p95']:+.3f}), sampled outside "
              f"its bounds {ph['sampled_outside']:.2f}; legs: sampled outside at most "
              f"{r['legs_sampled_outside_max']:.2f} ({time.perf_counter() - start:.0f} s)", flush=True)
        results.append(r)
    if args.out is not None:
        import mujoco

        meta = {"date": time.strftime("%Y-%m-%d"), "hardware": f"CPU (C MuJoCo {mujoco.__version__}), "
                f"{platform.machine()}"}
        write_report(args.out, "lab/analysis/action_bounds.py", argv, results, meta)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
