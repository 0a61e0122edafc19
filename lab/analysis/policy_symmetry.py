"""How far from left-right symmetric a policy is, and whether ``ppo.symmetry "augment"`` can still pull it back.

Rolls the deterministic policy out in one case of the robust test (``nominal`` by default) on the CPU (C MuJoCo)
and, over every policy input o it saw, compares its mean action on the mirror image of the input, μ(M·o), with the
mirror image of its mean action, A·μ(o) (``rl.symmetry``'s maps). A symmetric policy has them equal.

The augmentation (:class:`~tocabi_torchrl.rl.symmetry.SymmetryAugmentLoss`) adds each mini-batch's mirror image with
the original frame's old log-probability, so a mirrored frame's PPO ratio is π(A·a | M·o) / π_old(a | o). For the
mean action a = μ(o) and the policy's own σ that log-ratio is ``-Σ_j (μ(M·o)_j − (A·μ(o))_j)² / (2 σ_j²)``
(:func:`mirrored_log_ratio`, the 12 leg actions): once it lies outside PPO's clip, the mirrored frame adds no
gradient, and the augmentation no longer acts on the asymmetry (:func:`within_clip`).

Wrote docs/training/robust/h200_run8/policy_symmetry.json (about 40 s per checkpoint of 16 robots on 2 cores)::

    PYTHONPATH=. python lab/analysis/policy_symmetry.py --num_envs 16 \\
        --out docs/training/robust/h200_run8/policy_symmetry.json \\
        --checkpoint docs/training/robust/h200_run8/checkpoints/wall_01080s.pt
"""

from __future__ import annotations

import time
from pathlib import Path

import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from tocabi_torchrl import robot
from tocabi_torchrl.evaluation import robust
from tocabi_torchrl.evaluation.record import policy_steps
from tocabi_torchrl.rl.actors import gaussian_head
from tocabi_torchrl.rl.symmetry import SignedPermutation, action_mirror_map, make_policy_input_mirror
from tocabi_torchrl.transforms.normalize import freeze_running_statistics

from lab.analysis.reports import case_parser, check_paths, write_report

LEGS = robot.NUM_LEG_JOINTS


def mirrored_log_ratio(loc: torch.Tensor, loc_of_mirror: torch.Tensor, mirrored_loc: torch.Tensor,
                       sigma: torch.Tensor) -> torch.Tensor:
    """(B,) the augmentation's log-ratio of a mirrored frame for the mean action: ``-Σ_j (μ(M·o)_j −
    (A·μ(o))_j)² / (2 σ_j²)`` over the 12 leg actions; ``loc`` (B, ≥12) μ(o) (only its shape is used),
    ``loc_of_mirror`` (B, ≥12) μ(M·o), ``mirrored_loc`` (B, ≥12) A·μ(o), ``sigma`` (12,) or (B, 12) the policy's
    action σ.

    >>> mu = torch.tensor([[0.1] * 12])
    >>> round(float(mirrored_log_ratio(mu, mu + 0.05, mu, torch.full((12,), 0.05))), 4)  # 0.05 off per joint, σ 0.05
    -6.0
    """
    assert loc.shape[-1] >= LEGS
    gap = (loc_of_mirror[..., :LEGS] - mirrored_loc[..., :LEGS]) / sigma
    return -0.5 * gap.square().sum(-1)


def within_clip(log_ratio: torch.Tensor, clip_epsilon: float) -> float:
    """Share of frames whose ratio ``exp(log_ratio)`` lies inside PPO's clip ``[1 − ε, 1 + ε]``.

    >>> within_clip(torch.tensor([0.0, -0.1, -3.0, 0.5]), 0.2)
    0.5
    """
    ratio = log_ratio.exp()
    return float(((ratio >= 1.0 - clip_epsilon) & (ratio <= 1.0 + clip_epsilon)).float().mean())


def measure(path: Path, case: str, num_envs: int, seconds: float) -> dict:
    """The symmetry of one checkpoint's policy over the inputs of one case of the robust test."""
    test = robust.RobustTestConfig(num_envs=num_envs, seconds=seconds)
    _, cfg, env, agent = robust.checkpoint_case(path, case, "cpu", test)
    freeze_running_statistics(env)
    mirror = make_policy_input_mirror(env, cfg.transforms.transform_config())
    action_mirror = SignedPermutation(*action_mirror_map())
    head = gaussian_head(agent.actor)
    inputs = []
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.reset()
        for _ in range(policy_steps(seconds, float(env.base_env.dt))):
            inputs.append(td["observation"].clone())
            td = step_mdp(env.step(agent.actor(td)))
        obs = torch.cat(inputs)
        loc, scale = head(obs)
        loc_of_mirror, _ = head(mirror(obs))
        mirrored_loc = action_mirror(loc)
    gap = (loc_of_mirror[:, :LEGS] - mirrored_loc[:, :LEGS]).abs()
    log_ratio = mirrored_log_ratio(loc, loc_of_mirror, mirrored_loc, scale[:, :LEGS])
    return {"checkpoint": str(path), "case": case, "robots": num_envs, "seconds": seconds, "inputs": obs.shape[0],
            "action_sigma_legs": round(float(scale[:, :LEGS].mean()), 4),
            "leg_action_mean_abs": round(float(loc[:, :LEGS].abs().mean()), 4),
            "leg_asymmetry_abs": {"mean": round(float(gap.mean()), 4), "p95": round(float(gap.quantile(0.95)), 4)},
            "mirrored_log_ratio": {k: round(float(log_ratio.quantile(q)), 2) for k, q in
                                   (("p5", 0.05), ("p50", 0.5), ("p95", 0.95))},
            "mirrored_frames_within_clip": within_clip(log_ratio, float(cfg.ppo.clip_epsilon)),
            "clip_epsilon": float(cfg.ppo.clip_epsilon)}


def main(argv=None) -> int:
    p = case_parser(__doc__, num_envs=16, seconds=2.0)
    p.add_argument("--out", type=Path, default=None, help="JSON to write (default: print only)")
    args = p.parse_args(argv)
    check_paths(p, args.checkpoint, args.out)
    results = []
    for path in args.checkpoint:
        start = time.perf_counter()
        r = measure(path, args.case, args.num_envs, args.seconds)
        print(f"{path}: leg asymmetry {r['leg_asymmetry_abs']} (mean |action| {r['leg_action_mean_abs']}, σ "
              f"{r['action_sigma_legs']}); mirrored log-ratio {r['mirrored_log_ratio']}, within the clip "
              f"{r['mirrored_frames_within_clip']:.3f} ({time.perf_counter() - start:.0f} s)", flush=True)
        results.append(r)
    if args.out is not None:
        write_report(args.out, "lab/analysis/policy_symmetry.py", argv, results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
