"""Timeline of the trainer's own PPO iterations on the GPU: where the wall time goes and whether the GPU idles.

    python benchmarks/trainer_timeline.py --num_envs 4096 --out $OUT/timeline

Builds exactly what ``train`` builds (``build_env(for_training=True)``, ``make_collector``, the preset's loss and
mini-batch sizes), runs ``--warmup`` iterations of the untrained policy, then times the phases of one iteration with
host clocks after a device synchronisation: the collector's rollout, GAE, the PPO update. Under ``torch.profiler``
it then records one more iteration and reports the busiest kernels and host ops and writes a Chrome trace
(``--out``). The trace does not show the kernels inside CUDA-graph conditional bodies (mujoco-warp's solver
iteration loops): they appear as gaps after ``set_conditional_if_handle_kernel``, whose lengths are the loops'
durations, so the printed "GPU busy" fraction undercounts the physics. Last, one iteration under
``torch.cuda.set_sync_debug_mode("warn")`` lists every place that synchronised with the host.
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
import traceback
import warnings
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tocabi_torchrl.rl.config import preset_config  # noqa: E402
from tocabi_torchrl.rl.trainer import (  # noqa: E402
    _loss_keys, _update, build_agent, build_env, make_collector, make_loss, make_optimizer, make_update_step,
)


def busy_fraction(events, t0_us: float, t1_us: float) -> float:
    """Fraction of [t0, t1] (µs) covered by at least one GPU kernel or memcpy/memset."""
    spans = sorted((e.time_range.start, e.time_range.end) for e in events
                   if e.device_type == torch.autograd.DeviceType.CUDA and e.time_range.end > e.time_range.start)
    covered, cur_s, cur_e = 0.0, None, None
    for s, e in spans:
        s, e = max(s, t0_us), min(e, t1_us)
        if e <= s:
            continue
        if cur_e is None or s > cur_e:
            if cur_e is not None:
                covered += cur_e - cur_s
            cur_s, cur_e = s, e
        else:
            cur_e = max(cur_e, e)
    if cur_e is not None:
        covered += cur_e - cur_s
    return covered / max(t1_us - t0_us, 1e-9)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--num_envs", type=int, default=4096)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE", help="PPOConfig overrides")
    parser.add_argument("--out", default="")
    args = parser.parse_args(argv)
    if not torch.cuda.is_available():
        raise SystemExit("trainer_timeline needs a CUDA GPU")
    from tocabi_torchrl.rl.config import PPOConfig, _parse_value

    overrides = {}
    for item in args.set:
        field, _, value = item.partition("=")
        kind = type(getattr(PPOConfig(), field))
        overrides[field] = _parse_value(bool, value) if kind is bool else kind(value)
    n = args.num_envs
    steps = preset_config("default").steps_per_env
    cfg = preset_config("default", num_envs=n, device="cuda", minibatch_size=min(49152, n * steps // 4),
                        progress_bar=False, eval_at_end=False, **overrides)
    device = torch.device("cuda")
    env = build_env(cfg, device, for_training=True)
    agent = build_agent(cfg, env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1], device)
    loss_module, advantage = make_loss(cfg, agent)
    optimizer = make_optimizer(cfg, agent, device)
    step = make_update_step(cfg, loss_module, optimizer, device)
    collector = make_collector(cfg, env, agent.actor, device)
    it = iter(collector)

    def iteration(phases: dict | None = None):
        t = [time.perf_counter()]
        batch = next(it)
        torch.cuda.synchronize()
        t.append(time.perf_counter())
        work = batch.clone(False)
        with torch.no_grad():
            advantage(work)
        flat = work.select(*_loss_keys(loss_module, work)).reshape(-1)
        torch.cuda.synchronize()
        t.append(time.perf_counter())
        _update(cfg, flat, step)
        torch.cuda.synchronize()
        t.append(time.perf_counter())
        if phases is not None:
            for name, a, b in (("collect", 0, 1), ("gae", 1, 2), ("update", 2, 3)):
                phases[name].append((t[b] - t[a]) * 1e3)

    for _ in range(args.warmup):
        iteration()
    phases = collections.defaultdict(list)
    for _ in range(3):
        iteration(phases)
    total = sum(min(v) for v in phases.values())
    print(f"{n} envs, {steps} steps per env; best of 3 iterations (ms):")
    for name, values in phases.items():
        best = min(values)
        print(f"  {name:8s} {best:9.1f} ms  ({best / steps:6.2f} ms per policy step, {100 * best / total:5.1f} %)")
    print(f"  total    {total:9.1f} ms -> {n * steps / total * 1e3:,.0f} env-steps/s "
          f"(update {'captured as a CUDA graph' if step.captured else 'eager'})")

    from torch.profiler import ProfilerActivity, profile

    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        iteration()
    events = prof.events()
    starts = [e.time_range.start for e in events if e.device_type == torch.autograd.DeviceType.CPU]
    ends = [e.time_range.end for e in events if e.device_type == torch.autograd.DeviceType.CPU]
    t0, t1 = min(starts), max(ends)
    print(f"profiled iteration: {(t1 - t0) / 1e3:.1f} ms, GPU busy {100 * busy_fraction(events, t0, t1):.1f} % "
          "(kernels in graph conditional bodies, the solver loops, are not recorded: an undercount)")
    print(prof.key_averages().table(sort_by="cpu_time_total", row_limit=30, max_name_column_width=60))
    print(prof.key_averages().table(sort_by="self_cuda_time_total", row_limit=25, max_name_column_width=60))
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        prof.export_chrome_trace(str(out / "trainer_iteration_trace.json"))

    sources = collections.Counter()

    def record(message, category, filename, lineno, file=None, line=None):
        if "synchroniz" in str(message):
            frames = [f for f in traceback.extract_stack()[:-2] if "warnings" not in f.filename]
            sources["\n    ".join(f"{f.filename.split('site-packages/')[-1]}:{f.lineno} {f.name}"
                                  for f in frames[-6:])] += 1

    torch.cuda.synchronize()
    old = warnings.showwarning
    warnings.showwarning = record
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            iteration()
        finally:
            torch.cuda.set_sync_debug_mode("default")
            warnings.showwarning = old
    print(f"host synchronisations in one iteration (collect + GAE + update): {sum(sources.values())}")
    for where, count in sources.most_common(12):
        print(f"  {count:5d} x\n    {where}")
    collector.shutdown()


if __name__ == "__main__":
    main()
