"""Can the PPO update hide behind the physics? Raw mujoco-warp and an update stand-in, alone and on two CUDA streams.

    python -m lab.benchmarks.overlap_probe --num_envs 4096 16384      # GPU; writes docs/benchmarks/overlap_probe.{json,md}

Issue 25's plan (docs/benchmarks.md, "Where the 0.29 goes") runs the update of one rollout beside the collection of
the next. That pays only if the GPU executes both at once: mujoco-warp's kernels at 4,096 worlds may leave most of the
GPU idle, or may not. This measures it before anything is built, per env count, in seconds of one iteration:

- ``physics``: ``steps_per_env`` raw policy steps (``common.raw_policy_step``: PD hold + 8 x ``mujoco_warp.step``);
- ``update``: ``epochs`` x (frames / ``minibatch_size``) steps of a stand-in update on the preset's own actor and
  critic networks (forward, backward, gradient clipping, Adam) at the preset's mini-batch size, on random
  observations with a squared-error loss: the update's matrix products without its PPO arithmetic;
- ``both``: the two queued together, physics on one stream and the update on another.

``hidden`` = (physics + update - both) / update: the share of the update that ran concurrently (1: wholly hidden,
0: serial). The full update (GAE, PPO losses, KL) and the policy inside the collector are not in it.
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import time
from pathlib import Path

import torch

from tocabi_torchrl.envs.tocabi_walk import ACTION_DIM
from tocabi_torchrl.rl.actors import gaussian_head
from tocabi_torchrl.rl.trainer import build_agent

from . import common

NAME = "overlap_probe"
#: The policy's observation width (transforms/history.py: 5 x 37 + 4 x 13).
OBS_DIM = 237


def update_stand_in(preset: str, num_envs: int, device: str):
    """``(step, steps, params)``: one mini-batch step of the stand-in update, how many make one iteration's update,
    and the parameters it trains (the actor's mean network and the critic)."""
    cfg = common.preset_config(preset)
    ppo = cfg.ppo
    agent = build_agent(cfg, OBS_DIM, ACTION_DIM, torch.device(device))
    mean_net, value_net = gaussian_head(agent.actor).mean_net, agent.critic.module
    params = [*mean_net.parameters(), *value_net.parameters()]
    optimizer = torch.optim.Adam(params, lr=ppo.lr)
    frames = ppo.steps_per_env * num_envs
    batch = min(ppo.minibatch_size, frames)
    obs = torch.randn(batch, OBS_DIM, device=device)
    target = torch.randn(batch, ACTION_DIM + 1, device=device)

    def step() -> None:
        out = torch.cat([mean_net(obs), value_net(obs)], dim=-1)
        loss = (out - target).square().mean()
        optimizer.zero_grad(set_to_none=False)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, ppo.max_grad_norm, foreach=True)
        optimizer.step()

    return step, ppo.epochs * max(1, frames // batch), params


def timed(fn, device: str, repeats: int) -> float:
    """Median wall seconds of ``fn()`` over ``repeats`` runs, the device's queued work included."""
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    fn()
    sync()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def measure(n: int, preset: str, device: str, repeats: int) -> dict:
    cfg = common.preset_config(preset)
    physics_step = common.raw_policy_step(n, device)
    update_step, updates, _ = update_stand_in(preset, n, device)
    cuda = device.startswith("cuda")
    streams = (torch.cuda.Stream(), torch.cuda.Stream()) if cuda else (None, None)

    def on(stream):
        return torch.cuda.stream(stream) if stream is not None else contextlib.nullcontext()

    def physics() -> None:
        with on(streams[0]):
            for _ in range(cfg.ppo.steps_per_env):
                physics_step()

    def update() -> None:
        with on(streams[1]):
            for _ in range(updates):
                update_step()

    def both() -> None:
        physics()  # queues its graph launches and returns; the update's launches follow on the other stream
        update()

    t_phys, t_upd, t_both = (timed(f, device, repeats) for f in (physics, update, both))
    return {"num_envs": n, "policy_steps": cfg.ppo.steps_per_env, "update_steps": updates,
            "physics_s": t_phys, "update_s": t_upd, "both_s": t_both,
            "hidden": (t_phys + t_upd - t_both) / t_upd, "serial_s": t_phys + t_upd}


def render(data: dict, out: Path) -> str:
    rows = [[f"{r['num_envs']:,}", r["policy_steps"], r["update_steps"], common.fmt(1e3 * r["physics_s"], ".1f"),
             common.fmt(1e3 * r["update_s"], ".1f"), common.fmt(1e3 * r["both_s"], ".1f"),
             common.fmt(r["hidden"], ".2f")] for r in data["results"]]
    body = (common.table(["envs", "policy steps", "update steps", "physics [ms]", "update [ms]", "both [ms]",
                          "update hidden"], rows)
            + "\n\n`update hidden` = (physics + update - both) / update: 1 when the update ran wholly beside the "
              "physics, 0 when serial. The update is a stand-in (the preset's networks, mini-batch and step count, "
              "a squared-error loss; no GAE, PPO loss or KL). Module docstring: `lab/benchmarks/overlap_probe.py`.")
    return common.page("Update beside physics on two CUDA streams (issue 25 probe)", data, body)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--num_envs", type=int, nargs="+", default=[4096, 16384],
                        help="robot counts (worlds), one measurement each (default: 4096 16384)")
    parser.add_argument("--preset", default="default", help="training preset whose steps per env, networks, epochs "
                        "and mini-batch size are measured (default: default)")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per measurement (median reported)")
    parser.add_argument("--device", default="cuda", help="cuda, or cpu to check only that the probe runs")
    parser.add_argument("--name", default=NAME, help=f"the report's file name, <out>/<name>.json (default: {NAME})")
    parser.add_argument("--out", default=str(common.DOCS), help="folder of the report <name>.json and .md (default: "
                        "docs/benchmarks; a CPU measurement goes to runs/benchmarks_cpu instead)")
    args = parser.parse_args(argv)
    common.require_cuda(parser, args.device, "two CUDA streams are what is measured; --device cpu only checks "
                                             "that the probe runs")
    if min(args.num_envs) < 1 or args.repeats < 1:
        parser.error("--num_envs and --repeats must be positive")
    if args.preset not in common.presets:
        parser.error(f"--preset {args.preset!r}: no such preset; choose one of {', '.join(common.presets)}")
    results = []
    for n in args.num_envs:
        print(f"overlap probe: {n:,} envs ...", flush=True)
        results.append(measure(n, args.preset, args.device, args.repeats))
        r = results[-1]
        print(f"  physics {1e3 * r['physics_s']:.1f} ms, update {1e3 * r['update_s']:.1f} ms, both "
              f"{1e3 * r['both_s']:.1f} ms: {r['hidden']:.2f} of the update hidden", flush=True)
    data = {"meta": common.meta(NAME, argv, on=args.device, preset=args.preset), "results": results}
    common.publish(args.out, args.name, data, render, measured_on=args.device)
    return data


if __name__ == "__main__":
    main()
