"""Physics backend (``WarpSim.step``) against raw mujoco-warp stepping of the same model, in one process.

    python -m benchmarks.sim_throughput --nworld 1024 4096 16384 --steps 200

Both sides: the shipped model with the backend's contact sensors and buffers, legs PD-held on the initial pose by
the same warp kernel. Raw: ``mujoco_warp.step`` x 8 (every sensor, every substep) in one graph; backend: the kernel
then ``WarpSim.step()``. Median of ``--repeats`` interleaved timings. Target: backend / raw >= 0.95 at 4096 and 16384.
"""

from __future__ import annotations

import argparse
import statistics

import torch

from . import common

NAME = "sim_throughput"


def measure(n: int, steps: int, repeats: int, device: str) -> dict:
    from tocabi_torchrl.sim import SimConfig, WarpSim
    from tocabi_torchrl.sim.graph import Recorded

    raw = common.raw_stepper(n, device)
    sim = WarpSim(SimConfig(num_worlds=n, device=device, substeps=common.SUBSTEPS), model=raw.model)
    data = raw.data
    # The backend starts from the raw side's initial state and reuses its PD kernel launch on the backend's arrays.
    sim.reset(torch.ones(n, dtype=torch.bool, device=sim.device), torch.as_tensor(data.qpos.numpy(), device=sim.device),
              torch.zeros(sim.nv, device=sim.device), torch.as_tensor(data.ctrl.numpy(), device=sim.device))
    common.sync(device)
    pd = Recorded(lambda: _launch_hold(raw, sim), sim.wp_device)

    def backend() -> None:
        pd()
        sim.step()

    common.per_second(raw, 20, device)
    common.per_second(backend, 20, device)
    t_raw = [1 / common.per_second(raw, steps, device) for _ in range(repeats)]
    t_backend = [1 / common.per_second(backend, steps, device) for _ in range(repeats)]
    raw_sps, backend_sps = n / statistics.median(t_raw), n / statistics.median(t_backend)
    return {"nworld": n, "steps": steps, "repeats": repeats, "raw_policy_steps_per_s": raw_sps,
            "backend_policy_steps_per_s": backend_sps, "ratio_backend_over_raw": backend_sps / raw_sps,
            "upright_raw": float((data.qpos.numpy()[:, 2] > 0.8).mean()),
            "upright_backend": float((sim.base_pos[:, 2] > 0.8).float().mean())}


def _launch_hold(raw, sim) -> None:
    """The raw side's PD kernel, pointed at the backend's arrays (the first launch of ``raw``'s recorded body)."""
    import warp as wp

    kernel, inputs = raw.hold_launch
    wp.launch(kernel, dim=(sim.num_worlds, len(inputs[0])), inputs=[sim.wp_data.qpos, sim.wp_data.qvel, *inputs],
              outputs=[sim.wp_data.ctrl])


def render(data: dict, out) -> str:
    rows = [(r["nworld"], f"{r['raw_policy_steps_per_s'] * common.SUBSTEPS:,.0f}",
             f"{r['backend_policy_steps_per_s'] * common.SUBSTEPS:,.0f}", f"{r['raw_policy_steps_per_s']:,.0f}",
             f"{r['backend_policy_steps_per_s']:,.0f}", f"{r['ratio_backend_over_raw']:.3f}",
             f"{r['upright_raw']:.0%} / {r['upright_backend']:.0%}") for r in data["results"]]
    body = common.table(("worlds", "raw physics steps/s", "backend physics steps/s", "raw policy steps/s",
                         "backend policy steps/s", "backend / raw", "upright raw / backend"), rows)
    return common.page("Physics backend throughput (WarpSim vs raw mujoco-warp)", data,
                       body + "\n\n" + data["meta"].get("note", ""))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--nworld", type=int, nargs="+", default=[1024, 4096, 16384])
    p.add_argument("--steps", type=int, default=200, help="policy steps per timing")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--device", default="cuda", help="cuda, or cpu for a (slow) smoke run on warp's CPU device")
    p.add_argument("--out", default=str(common.DOCS))
    args = p.parse_args(argv)
    results = [measure(n, args.steps, args.repeats, args.device) for n in args.nworld]
    print(common.publish(args.out, NAME, {"meta": common.meta(NAME, argv, args.device), "results": results},
                         render))


if __name__ == "__main__":
    main()
