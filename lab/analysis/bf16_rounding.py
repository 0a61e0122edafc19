"""How far bfloat16's rounding moves a trained policy's action mean and PPO ratio (``ppo.update_dtype``).

Rolls each checkpoint's policy out on the CPU in the env its checkpoint describes (``evaluation.record.load_policy``:
``--num_envs`` robots, ``--steps`` policy steps, a command of 0.5 m/s forward, actions drawn as in training), keeps the
observations its actor saw, and passes them through the actor's mean network twice: in float32, as a rollout acts, and
under ``torch.autocast`` to bfloat16, as a ``ppo.update_dtype`` "bfloat16" update computes
(``rl.update_step.update_autocast``: hidden layers in bfloat16, the output layer in float32). For each action std given,
actions drawn around the float32 mean give the log-ratio of the two policies' likelihoods, the PPO ratio's start where
the update compares against the policy that acted; the share of frames whose ratio starts past the checkpoint's clip
(``ppo.clip_epsilon``) is what a coupled update would clip before it learned anything: why a bfloat16 update is
decoupled (``rl.trainer.decoupled_update``). What the decoupled update pays instead: its surrogate's weights π_prox /
π_behav are those likelihood ratios, and their effective sample size (``rl.rollout_guard.behaviour_ess``, as the trainer
logs it) is given too.

Wrote docs/training/bf16_rounding.json (14 s on 2 cores)::

    PYTHONPATH=. python lab/analysis/bf16_rounding.py --checkpoint assets/policies/tocabi_walk_ppo.pt \\
        assets/policies/tocabi_walk_torque.pt assets/policies/tocabi_walk_robust.pt \\
        --out docs/training/bf16_rounding.json
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import torch
from tensordict import TensorDict
from tensordict.nn import InteractionType, set_interaction_type
from torchrl.envs.utils import step_mdp

from tocabi_torchrl.evaluation.record import load_policy
from tocabi_torchrl.rl.actors import gaussian_head
from tocabi_torchrl.rl.rollout_guard import behaviour_ess
from tocabi_torchrl.rl.update_step import update_autocast

from lab.analysis.reports import check_paths, write_report


def walk_observations(checkpoint: Path, num_envs: int, steps: int) -> tuple[torch.Tensor, torch.nn.Module, float]:
    """The observations (num_envs * steps, obs_dim) the checkpoint's actor saw in ``steps`` steps of its own walk,
    its mean network, and its clip range."""
    loaded = load_policy(checkpoint, num_envs, "cpu")
    env, actor = loaded.env, loaded.agent.actor
    seen = []
    td = env.reset()
    with torch.no_grad(), set_interaction_type(InteractionType.RANDOM):
        for _ in range(steps):
            td = actor(td)
            seen.append(td["observation"].clone())
            td = step_mdp(env.step(td))
    return torch.cat(seen), gaussian_head(actor).mean_net, float(loaded.cfg.ppo.clip_epsilon)


def rounding(obs: torch.Tensor, mean_net: torch.nn.Module, stds: list[float], clip: float, seed: int) -> dict:
    """The action means' bfloat16 - float32 difference [normalised action units] and, per std, the log-ratio of the
    two Gaussian policies at actions drawn around the float32 mean: its spread, the share of frames past ``clip`` and
    the effective sample size of its exponent."""
    with torch.no_grad():
        mean32 = mean_net(obs)
        with update_autocast(torch.bfloat16, obs.device):
            mean16 = mean_net(obs)
    diff = (mean16 - mean32).abs()
    out = {"frames": obs.shape[0], "action_dim": mean32.shape[-1], "clip_epsilon": clip,
           "mean_abs_action_mean": mean32.abs().mean().item(), "mean_abs_diff": diff.mean().item(),
           "p99_abs_diff": diff.flatten().quantile(0.99).item(), "max_abs_diff": diff.max().item(), "per_std": []}
    g, frames = torch.Generator().manual_seed(seed), TensorDict(batch_size=[obs.shape[0]])
    for std in stds:
        action = mean32 + std * torch.randn(mean32.shape, generator=g)
        log_ratio = ((action - mean32) ** 2 - (action - mean16) ** 2).sum(-1) / (2 * std ** 2)
        out["per_std"].append({"std": std, "log_ratio_sd": log_ratio.std().item(),
                               "share_past_clip": ((log_ratio.exp() - 1).abs() > clip).float().mean().item(),
                               "behaviour_ess": float(behaviour_ess(log_ratio.unsqueeze(-1), frames, None))})
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", nargs="+", required=True, type=Path, help="checkpoints (.pt) to measure")
    parser.add_argument("--num_envs", type=int, default=32, help="robots per checkpoint")
    parser.add_argument("--steps", type=int, default=150, help="policy steps per robot (0.02 s each)")
    parser.add_argument("--stds", type=float, nargs="+", default=[0.1, 0.05], help="action stds to draw with")
    parser.add_argument("--seed", type=int, default=0, help="seed of the rollouts and the draws")
    parser.add_argument("--out", type=Path, default=None, help="JSON to write (default: print only)")
    args = parser.parse_args(argv)
    check_paths(parser, args.checkpoint, args.out)
    if args.num_envs < 1 or args.steps < 1 or not all(s > 0 for s in args.stds):
        parser.error("--num_envs and --steps must be >= 1 and every --stds > 0")
    results = []
    for checkpoint in args.checkpoint:
        torch.manual_seed(args.seed)
        obs, mean_net, clip = walk_observations(checkpoint, args.num_envs, args.steps)
        row = {"checkpoint": str(checkpoint), **rounding(obs, mean_net, args.stds, clip, args.seed)}
        results.append(row)
        per_std = ", ".join(f"std {s['std']}: log-ratio sd {s['log_ratio_sd']:.3f}, past the clip "
                            f"{s['share_past_clip']:.1%}, ESS {s['behaviour_ess']:.3f}" for s in row["per_std"])
        print(f"{checkpoint}: |bf16 - f32| mean {row['mean_abs_diff']:.1e}, p99 {row['p99_abs_diff']:.1e}; {per_std}")
    if args.out is not None:
        meta = {"date": time.strftime("%Y-%m-%d"), "hardware": f"CPU, {platform.machine()}",
                "torch": torch.__version__, "num_envs": args.num_envs, "steps": args.steps}
        write_report(args.out, "lab/analysis/bf16_rounding.py", argv, results, meta)


if __name__ == "__main__":
    main()
