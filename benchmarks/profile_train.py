"""Where a PPO iteration's time goes on the GPU: physics, env/transforms, TorchRL collection, GAE and the update.

    python benchmarks/profile_train.py --num_envs 4096

Prints, per stage, wall ms per policy step (or per iteration) and host CPU ms per step, so one can tell whether the
collection is GPU-bound (physics) or host-bound (Python and kernel launches, or the host waiting on ``done.any()``).
Collection is timed with TorchRL's stock automatic reset, the sync-free one, and (on CUDA) the sync-free step captured
as one CUDA graph. Also writes torch.profiler tables of one collection iteration of the last of these to ``--out``.
Last, the trainer's own path (``build_env(for_training=True)``, ``make_collector`` and the preset's mini-batch
sizes) in the states reached after three rollouts: collector, policy + env step and bare physics per step, GAE, and
the update run eagerly and as a CUDA graph per mini-batch step.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sim_throughput import raw_policy_steps_per_second  # noqa: E402

from tocabi_torchrl.rl.config import preset_config  # noqa: E402
from tocabi_torchrl.rl.trainer import (  # noqa: E402
    _update, build_agent, build_env, make_loss, make_optimizer, make_update_step,
)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def timed(fn, steps: int, device: torch.device, warmup: int = 3) -> tuple[float, float]:
    """(wall ms, host CPU ms) per call of ``fn`` over ``steps`` calls after ``warmup``."""
    for _ in range(warmup):
        fn()
    _sync(device)
    w0, c0 = time.perf_counter(), time.process_time()
    for _ in range(steps):
        fn()
    _sync(device)
    return (time.perf_counter() - w0) / steps * 1e3, (time.process_time() - c0) / steps * 1e3


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--num_envs", type=int, default=4096)
    parser.add_argument("--steps", type=int, default=48)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--control_mode", default=preset_config("default").control_mode)
    parser.add_argument("--out", default="")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    n = args.num_envs
    cfg = preset_config("default", num_envs=n, device=args.device, minibatch_size=min(32768, n * 24 // 4),
                        control_mode=args.control_mode, progress_bar=False, eval_at_end=False)
    rows = []

    def report(name, wall, cpu, per="step"):
        rows.append((name, wall, cpu, per))
        print(f"{name:38s} {wall:9.2f} ms/{per}  host CPU {cpu:9.2f} ms/{per}", flush=True)

    if device.type == "cuda":
        raw = raw_policy_steps_per_second(n, 100)
        report("raw mujoco-warp (ceiling)", n / raw * 1e3, float("nan"))
    env = build_env(cfg, device, sync_free_resets=False, cuda_graph=False)
    agent = build_agent(cfg, 237, 13, device)
    base = env.base_env
    td = env.reset()
    zero = torch.zeros(n, 13, device=device)
    report("sim.step", *timed(base.sim.step, args.steps, device))
    report("bare env _step", *timed(lambda: base._step(td.set("action", zero)), args.steps, device))
    report("transformed env.step", *timed(lambda: env.step(td.clone().set("action", zero)), args.steps, device))
    mask = torch.zeros(n, 1, dtype=torch.bool, device=device)
    mask[::97] = True
    report("bare env _reset (masked)", *timed(lambda: base._reset(td.clone().set("_reset", mask)), args.steps, device))
    report("TorchRL env.reset (masked)", *timed(lambda: env.reset(td.clone().set("_reset", mask)), args.steps, device))
    with torch.no_grad():
        report("policy forward", *timed(lambda: agent.actor(td.clone()), args.steps, device))
    del env, base
    from torchrl.collectors import Collector

    batch = None
    # Explicit modes: the preset's cuda_graph="auto" would capture the sync-free step at small counts.
    variants = [("stock", {"sync_free_resets": False, "cuda_graph": False}),
                ("sync-free", {"sync_free_resets": True, "cuda_graph": False})]
    if device.type == "cuda":
        variants.append(("graph", {"sync_free_resets": True, "cuda_graph": True}))
    for tag, env_kw in variants:
        env = build_env(cfg, device, **env_kw)
        state = {"td": env.reset()}

        def step_and_reset():
            with torch.no_grad():
                state["td"].update(agent.actor(state["td"]))
            _, state["td"] = env.step_and_maybe_reset(state["td"])

        report(f"policy + step_and_maybe_reset [{tag}]", *timed(step_and_reset, args.steps, device))
        collector = Collector(env, agent.actor, frames_per_batch=n * 24, total_frames=-1, device=device,
                              storing_device=device, auto_register_policy_transforms=False, track_traj_ids=False)
        it = iter(collector)
        batch = next(it)
        report(f"collector iteration, 24 steps [{tag}]", *timed(lambda: next(it), 3, device, warmup=1), per="iter")
        if args.out and tag == variants[-1][0]:  # the profiler tables of the fastest path
            from torch.profiler import ProfilerActivity, profile

            acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
            with profile(activities=acts) as prof:
                next(it)
                _sync(device)
            out = Path(args.out)
            out.mkdir(parents=True, exist_ok=True)
            table = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=40)
            (out / "profile_cpu.txt").write_text(table)
            if device.type == "cuda":
                (out / "profile_cuda.txt").write_text(
                    prof.key_averages().table(sort_by="self_cuda_time_total", row_limit=40))
        collector.shutdown()
        del env
    # The trainer's own path: its env (for_training), its collector and its update sizes, in states reached after a
    # few rollouts of the untrained policy (falling and resetting robots), where physics costs more than standing.
    from torchrl.objectives.value import GAE

    from tocabi_torchrl.rl.trainer import _loss_keys, make_collector

    steps = preset_config("default").steps_per_env
    tcfg = preset_config("default", num_envs=n, device=args.device, minibatch_size=min(49152, n * steps // 4),
                         control_mode=args.control_mode)
    env = build_env(tcfg, device, for_training=True)
    collector = make_collector(tcfg, env, agent.actor, device)
    it = iter(collector)
    for _ in range(3):
        next(it)
    wall, cpu = timed(lambda: next(it), 2, device, warmup=0)
    report(f"collector iteration [trainer], {steps} steps", wall / steps, cpu / steps)
    carrier = collector._carrier  # the env state the collector stopped at

    def step_and_reset_trainer():
        nonlocal carrier
        with torch.no_grad():
            carrier.update(agent.actor(carrier))
        _, carrier = env.step_and_maybe_reset(carrier)

    report("policy + step_and_maybe_reset [trainer env]", *timed(step_and_reset_trainer, steps, device, warmup=0))
    report("sim.step in these states", *timed(env.base_env.sim.step, steps, device, warmup=0))
    batch = next(it)
    gae = GAE(gamma=tcfg.gamma, lmbda=tcfg.gae_lambda, value_network=agent.critic, average_gae=False,
              value_chunk_size=65536 // steps)
    work = batch.clone(False)
    with torch.no_grad():
        report("GAE", *timed(lambda: gae(work), 3, device, warmup=1), per="iter")
    loss, _ = make_loss(tcfg, agent)  # the trainer's loss (no entropy bonus in the preset: capturable)
    flat = work.select(*_loss_keys(loss, work)).reshape(-1)
    for graph in (False, True):
        gcfg = preset_config("default", num_envs=n, minibatch_size=tcfg.minibatch_size, update_graph=graph)
        opt = make_optimizer(gcfg, agent, device)
        step = make_update_step(gcfg, loss, opt, device)
        wall, cpu = timed(lambda: _update(gcfg, flat, step), 2, device, warmup=1)
        report(f"PPO update ({tcfg.epochs} epochs x {flat.shape[0] // tcfg.minibatch_size} mini-batches, "
               f"{'CUDA graph' if step.captured else 'eager'})", wall, cpu, per="iter")
    collector.shutdown()

if __name__ == "__main__":
    main()
