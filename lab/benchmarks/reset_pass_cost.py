"""What the reduced reset pass would cost over the worlds that reset only, against every world (issue 50).

    python -m lab.benchmarks.reset_pass_cost                     # GPU: docs/benchmarks/reset_pass_cost.{json,md}
    python -m lab.benchmarks.reset_pass_cost --device cpu --num_envs 8 --subsets 2 4 --steps 2   # warp's CPU device

The reduced reset pass (``SimConfig.reset_pass="reduced"``) runs mujoco-warp's ``fwd_position`` and
``fwd_velocity`` over every world at every step, so that the few worlds that reset start their next step from a
consistent state: 2.56 ms of an 83 ms training step at 16,384 envs on an H200. mujoco-warp's kernels run over every
world of a ``Data``; a second, small ``Data`` of R worlds could run the same stages for the reset worlds alone, at
the price of copying its per-world arrays into the big ``Data`` rows of those worlds. This times, on the same model
and standing robots (``common.raw_policy_step``'s model and state), each recorded as a graph and replayed:

- the pass over ``--num_envs`` worlds (what every step pays today);
- the pass over R worlds, for each R of ``--subsets``;
- the copy of every per-world array of a ``Data`` of R worlds (leading dimension ``nworld``, the constraint rows'
  included) into R rows of the big one, one ``index_copy_`` per array: an upper bound on the scatter a compacted
  pass needs (it needs the arrays the next step's ``step2`` reads, fewer than all). Contacts (one buffer for all
  worlds, not per world) are not in it.

It answers one question: would the compacted pass (small pass + scatter) be cheaper than the pass over every world,
and by how much per step.

With ``--resets K ...`` it also times the simulator's reduced reset as built (``WarpSim.reset_to_start``, one start
state, K worlds drawn at random flagged), once with the pass over every world (``compact=0``) and once with
:class:`~tocabi_torchrl.sim.compact_reset.CompactResetPass` of ``--capacity`` worlds (default: the simulator's rule
for the env count), so that resets of more worlds than it holds (its chunks one after another) are measured too:

    python -m lab.benchmarks.reset_pass_cost --num_envs 16384 --subsets 256 --resets 0 16 64 256 1024 16384
"""

from __future__ import annotations

import argparse

import torch

from tocabi_torchrl import robot
from tocabi_torchrl.sim.compact_reset import per_world_arrays

from . import common

NAME = "reset_pass_cost"


def _standing_data(mj, m, num_worlds: int, mjw):
    """A ``Data`` of ``num_worlds`` robots in the initial pose, a forward pass done (the feet touch the floor)."""
    from tocabi_torchrl.sim.buffers import NCONMAX, NJMAX

    d = mjw.make_data(mj, nworld=num_worlds, nconmax=NCONMAX, njmax=NJMAX)
    d.qpos.assign(torch.as_tensor(robot.INIT_QPOS, dtype=torch.float32).repeat(num_worlds, 1).numpy())
    mjw.forward(m, d)
    return d


def measure(num_envs: int, subsets: list[int], steps: int, device: str) -> dict:
    import mujoco_warp as mjw
    import warp as wp

    from tocabi_torchrl.sim import add_contact_sensors
    from tocabi_torchrl.sim.buffers import CONTACT_SENSOR_MAXMATCH
    from tocabi_torchrl.sim.graph import Recorded

    wdev = wp.get_device(device)
    mj = add_contact_sensors(robot.load_spec()).compile()
    result = {"num_envs": num_envs, "steps": steps, "subsets": {}}
    with wp.ScopedDevice(wdev):
        m = mjw.put_model(mj)
        m.opt.contact_sensor_maxmatch, m.opt.warn_overflow = CONTACT_SENSOR_MAXMATCH, 0

        def pass_ms(d) -> float:
            def body() -> None:
                mjw.fwd_position(m, d, factorize=True)
                mjw.fwd_velocity(m, d)

            body()
            wp.synchronize_device(wdev)
            graph = Recorded(body, wdev)
            return 1e3 / common.per_second(graph, steps, device, warmup=3)

        big = _standing_data(mj, m, num_envs, mjw)
        result["pass_all_ms"] = pass_ms(big)
        big_arrays = per_world_arrays(big, num_envs)
        for r in subsets:
            small = _standing_data(mj, m, r, mjw)
            small_arrays = per_world_arrays(small, r)
            names = sorted(set(small_arrays) & set(big_arrays))
            pairs = [(wp.to_torch(big_arrays[k]), wp.to_torch(small_arrays[k])) for k in names]
            index = torch.randperm(num_envs, device=device)[:r]  # scattered reset worlds

            def scatter() -> None:
                for dst, src in pairs:
                    dst.index_copy_(0, index, src)

            scatter()
            if wdev.is_cuda:
                torch.cuda.synchronize()
                graph = torch.cuda.CUDAGraph()
                with torch.cuda.graph(graph):
                    scatter()
                copy = graph.replay
            else:
                copy = scatter
            result["subsets"][r] = {
                "pass_ms": pass_ms(small),
                "scatter_all_ms": 1e3 / common.per_second(copy, steps, device, warmup=3),
                "arrays": len(pairs),
                "bytes_per_world": sum(src[0].numel() * src.element_size() for _, src in pairs),
            }
            del small
    return result


def measure_resets(num_envs: int, resets: list[int], capacity: int, steps: int, device: str) -> dict:
    """ms per ``WarpSim.reset_to_start`` of K random worlds, for each K of ``resets``: over every world and with the
    small pass of ``capacity`` worlds (one simulator at a time)."""
    import gc

    from tocabi_torchrl.sim import SimConfig, WarpSim

    dev = torch.device(device)
    g = torch.Generator().manual_seed(0)
    masks = {}
    for k in resets:
        mask = torch.zeros(num_envs, dtype=torch.bool)
        mask[torch.randperm(num_envs, generator=g)[:k]] = True
        masks[k] = mask.to(dev)
    index = torch.zeros(num_envs, dtype=torch.int64, device=dev)
    qpos = torch.as_tensor(robot.INIT_QPOS, dtype=torch.float32, device=dev).unsqueeze(0)
    ms = {}
    for held in (0, capacity):
        sim = WarpSim(SimConfig(num_worlds=num_envs, device=device, reset_pass="reduced"))
        sim.register_start_states(qpos, torch.zeros(1, sim.nv, device=dev), torch.zeros(1, sim.nu, device=dev),
                                  compact=held)
        ms[held] = {k: 1e3 / common.per_second(lambda k=k: sim.reset_to_start(masks[k], index), steps, device,
                                               warmup=3) for k in resets}
        del sim
        gc.collect()
    return {"capacity": capacity, "rows": [{"resets": k, "every_world_ms": ms[0][k], "small_pass_ms": ms[capacity][k]}
                                           for k in resets]}


def render(data: dict) -> str:
    r = data["result"]
    rows = [[f"{r['num_envs']:,} (every world)", f"{r['pass_all_ms']:.3f}", "", "", ""]]
    for size, s in r["subsets"].items():
        total = s["pass_ms"] + s["scatter_all_ms"]
        rows.append([f"{int(size):,}", f"{s['pass_ms']:.3f}", f"{s['scatter_all_ms']:.3f}", f"{total:.3f}",
                     f"{r['pass_all_ms'] - total:+.3f}"])
    s0 = next(iter(r["subsets"].values()))
    body = common.table(["worlds in the pass", "fwd_position + fwd_velocity [ms]",
                         f"copy of all {s0['arrays']} per-world arrays into the big Data [ms]",
                         "small pass + copy [ms]", "saved per step [ms]"], rows)
    body += (f"\n\nPer world the copied arrays hold {s0['bytes_per_world'] / 1024:,.0f} KiB. Each time is one "
             f"recorded graph replayed {r['steps']} times after 3 warm-up replays, standing robots.\n")
    sim = data.get("resets")
    if sim:
        rows = [[f"{row['resets']:,}", f"{row['every_world_ms']:.3f}", f"{row['small_pass_ms']:.3f}",
                 f"{row['every_world_ms'] - row['small_pass_ms']:+.3f}"] for row in sim["rows"]]
        body += ("\nThe simulator's reduced reset as built (`WarpSim.reset_to_start`, one start state, the flagged "
                 f"worlds drawn at random), ms per reset, {r['steps']} after 3 warm-up:\n\n"
                 + common.table(["worlds reset", "pass over every world [ms]",
                                 f"small pass, {sim['capacity']:,} worlds at a time [ms]", "saved [ms]"], rows) + "\n")
    return common.page("The reset pass over the worlds that reset only: its cost", data, body)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--num_envs", type=int, default=16384, help="worlds of the big Data (a training run's envs)")
    parser.add_argument("--subsets", type=int, nargs="+", default=[64, 256, 1024],
                        help="sizes of the small Data: how many worlds a compacted pass would hold")
    parser.add_argument("--steps", type=int, default=50, help="graph replays timed per measurement")
    parser.add_argument("--resets", type=int, nargs="*", default=[],
                        help="also time the simulator's reset of this many random worlds, each count, over every world "
                             "and with the small pass (none: skipped)")
    parser.add_argument("--capacity", type=int, default=None,
                        help="with --resets: the small pass's worlds (default: compact_reset_capacity of --num_envs)")
    parser.add_argument("--device", default="cuda", help="cuda, or cpu (warp's CPU device: no graphs, slow)")
    parser.add_argument("--out", default=None, help="report folder (default: docs/benchmarks, or runs/ on the CPU)")
    parser.add_argument("--name", default=NAME, help="report file name, without extension")
    args = parser.parse_args(argv)
    common.require_cuda(parser, args.device, "pass --device cpu")
    bad = [s for s in args.subsets if not 0 < s <= args.num_envs]
    if bad or args.num_envs < 1 or args.steps < 1:
        parser.error(f"--num_envs and --steps must be >= 1 and every --subsets size in [1, --num_envs]; got "
                     f"num_envs={args.num_envs}, steps={args.steps}, subsets={args.subsets}")
    from tocabi_torchrl.sim.config import compact_reset_capacity

    capacity = compact_reset_capacity(args.num_envs) if args.capacity is None else args.capacity
    if args.resets and (not 0 < capacity < args.num_envs or not all(0 <= k <= args.num_envs for k in args.resets)):
        parser.error(f"--resets counts must be in [0, --num_envs] and --capacity in [1, --num_envs) (the rule gives "
                     f"0 below 4,096 envs: pass --capacity); got resets={args.resets}, capacity={capacity}")
    data = {"meta": common.meta(NAME, argv, on=args.device),
            "result": measure(args.num_envs, args.subsets, args.steps, args.device)}
    if args.resets:
        data["resets"] = measure_resets(args.num_envs, args.resets, capacity, args.steps, args.device)
    print(common.publish(args.out or common.DOCS, args.name, data, lambda d, _path: render(d),
                         measured_on=args.device))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
