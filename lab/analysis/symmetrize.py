"""Make a trained policy left-right symmetric after the fact, for analysis: how much of its drift and falls does its
asymmetry cause?

Writes a copy of a checkpoint whose actor's mean network is wrapped in
:class:`~tocabi_torchrl.rl.symmetry.EquivariantMean`, ``μ(o) = ½·(f(o) + A·f(M·o))`` with the trained network as
``f``, and whose config says ``ppo.symmetry "equivariant"``: the other analyses and the robust test then run it as
they run any checkpoint. The mirror takes the statistics of the checkpoint's own observation normaliser. The critic,
the env transforms' state and the rest of the config are the checkpoint's; the optimiser state and the torque
assist's teacher are left out (as in a shipped policy file). The result is not a policy of the committed preset: a
symmetric policy trained from scratch (``--set ppo.symmetry=equivariant``) is what a preset ships.

    PYTHONPATH=. python lab/analysis/symmetrize.py --checkpoint runs/x/checkpoints/wall_00960s.pt \\
        --out /tmp/wall_00960s_sym.pt
"""

from __future__ import annotations

import argparse
import dataclasses
import io
from pathlib import Path

import torch

from tocabi_torchrl.atomic import atomic_write_bytes
from tocabi_torchrl.rl.actors import gaussian_head
from tocabi_torchrl.rl.checkpoint import apply_checkpoint, config_from_checkpoint, read_checkpoint
from tocabi_torchrl.rl.symmetry import EquivariantMean, set_equivariant_statistics
from tocabi_torchrl.tree import to_dict


def symmetrize(checkpoint: Path, out: Path) -> Path:
    """Write the symmetric copy of ``checkpoint`` to ``out`` (refused if ``out`` exists); returns ``out``."""
    from tocabi_torchrl.rl.trainer import build_agent, build_env

    if out.exists():
        raise FileExistsError(f"{out} exists; pass another --out or remove it first")
    state = read_checkpoint(checkpoint)
    cfg = config_from_checkpoint(state, checkpoint)
    if cfg.ppo.symmetry == "equivariant":
        raise ValueError(f"{checkpoint}: its policy is symmetric already (ppo.symmetry 'equivariant')")
    saved = dataclasses.replace(cfg, ppo=dataclasses.replace(cfg.ppo, symmetry="equivariant"))
    # One CPU robot is enough to hold the normaliser's state; the copy keeps the run's own config otherwise.
    small = dataclasses.replace(saved, device="cpu", env=dataclasses.replace(saved.env, num_envs=1),
                                ppo=dataclasses.replace(saved.ppo, minibatch_size=1))
    cpu = torch.device("cpu")
    env = build_env(small, cpu, for_training=False)
    obs_dim, act_dim = env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1]
    trained = build_agent(dataclasses.replace(small, ppo=dataclasses.replace(small.ppo, symmetry="none")), obs_dim,
                          act_dim, cpu)
    apply_checkpoint(state, trained, env=env, path=checkpoint)  # the trained weights and the normaliser's state
    agent = build_agent(small, obs_dim, act_dim, cpu)
    head, trained_head = gaussian_head(agent.actor), gaussian_head(trained.actor)
    assert isinstance(head.mean_net, EquivariantMean)
    head.mean_net.net.load_state_dict(trained_head.mean_net.state_dict())
    head.log_std.data.copy_(trained_head.log_std.data)
    agent.critic.load_state_dict(trained.critic.state_dict())
    set_equivariant_statistics(agent.actor, env)
    policy = {**state, "optimizer": None, "config": to_dict(saved),
              "agent": {"actor": agent.actor.state_dict(), "critic": agent.critic.state_dict()}}
    buffer = io.BytesIO()
    torch.save(policy, buffer)
    return atomic_write_bytes(out, buffer.getvalue())


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", required=True, type=Path, help="the trained checkpoint (.pt)")
    p.add_argument("--out", required=True, type=Path, help="the symmetric copy to write (.pt; not overwritten)")
    args = p.parse_args(argv)
    if not args.checkpoint.is_file():
        p.error(f"no such checkpoint: {args.checkpoint}")
    print(f"wrote {symmetrize(args.checkpoint, args.out)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
