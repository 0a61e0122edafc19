"""Solver iterations per physics substep when the leg actuators' delay spreads the torque changes over a control
period: C MuJoCo robots driven by an exported policy through the torch-free runtime (``recipes/sim2sim.py``'s
driver), the delay off, of one whole control period, the TOCABI lab's 4-20 substeps, those on a grid of one
period (4, 12 and 20 substeps: ``env.control.actuators.delay_stride``) and of two substeps (4, 6, ..., 20), and
the lab's 4-20 substeps averaged over each period (``env.control.actuators.delay_average``).

Each substep's Newton solve starts from the previous substep's acceleration, which a jump in the commanded torque
makes stale, so the substep a jump lands in takes more iterations. Without a delay every robot's torque jumps at
substep 0 of each period; with a delay of k substeps at substep k mod S, which differs from robot to robot.
mujoco-warp iterates all worlds of a substep until the slowest has converged, so a GPU pays, per substep, about the
most iterations any world needs: the ``lockstep`` count below (the maximum over robots, summed over a period's
substeps), beside each robot's ``own``. C MuJoCo stands in for mujoco-warp here (same solver and warm start; the
counts differ in detail).

The lockstep count also grows with how different the robots' states are: robots that start alike and draw the same
delay move alike and need their iterations in the same substeps. A training batch is thousands of worlds in every
phase of their episodes, so by default every robot starts with the robust gait test's random joint and pelvis
velocities (``ROBUST_START``), in every variant alike; ``--at_rest`` starts them at rest, as the first report did.

Wrote docs/benchmarks/randomization/substep_iterations.json (about 10 minutes on 2 cores) and, robots at rest,
substep_iterations_at_rest.json (about 5)::

    PYTHONPATH=. python lab/analysis/substep_iterations.py --num_robots 64 --seconds 4 \\
        --out docs/benchmarks/randomization/substep_iterations.json
    PYTHONPATH=. python lab/analysis/substep_iterations.py --num_robots 32 --seconds 4 --at_rest \\
        --out docs/benchmarks/randomization/substep_iterations_at_rest.json

With the solver capped (``env.sim.solver_iterations``), the slowest worlds' solves are cut short, in the substeps a
delayed torque jumps in as in the others; wrote substep_iterations_cap4.json, _cap3.json and _cap5.json (about 10
minutes each)::

    PYTHONPATH=. python lab/analysis/substep_iterations.py --num_robots 64 --seconds 4 --iterations 4 \\
        --out docs/benchmarks/randomization/substep_iterations_cap4.json
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable, Iterator
from pathlib import Path

import mujoco
import numpy as np

from tocabi_torchrl import robot
from tocabi_torchrl.runtime import load_contract
from tocabi_torchrl.runtime import randomization as rnd
from tocabi_torchrl.runtime.mujoco_driver import run_sim2sim

from lab.analysis.reports import sim2sim_args, sim2sim_meta, sim2sim_parser, write_report

CONTRACT = robot.asset_path("policies", "tocabi_walk_robust.json")


@contextlib.contextmanager
def counted_steps(before: Callable[[mujoco.MjModel], None] | None = None) -> Iterator[list[int]]:
    """Within the block, every ``mujoco.mj_step`` appends the solver iterations of its solve (``solver_niter[0]``)
    to the yielded list, after ``before(model)`` when given; ``mj_step`` is restored on leaving."""
    counts: list[int] = []
    step = mujoco.mj_step

    def counting(m, d):
        if before is not None:
            before(m)
        step(m, d)
        counts.append(int(d.solver_niter[0]))

    mujoco.mj_step = counting
    try:
        yield counts
    finally:
        mujoco.mj_step = step


def lockstep(counts: np.ndarray) -> dict:
    """Summary of iterations ``counts`` (periods, robots, substeps): per period, each robot's own sum (mean over
    robots and periods) and the lockstep sum (the maximum over robots per substep, summed), and per substep the
    mean and the lockstep maximum (means over periods).

    >>> c = np.array([[[3, 1], [1, 3]]])  # one period, two robots, two substeps: each jumps in another substep
    >>> s = lockstep(c)
    >>> s["own_per_period"], s["lockstep_per_period"], s["lockstep_per_substep"]
    (4.0, 6.0, [3.0, 3.0])
    """
    most = counts.max(axis=1)
    return {"own_per_period": round(float(counts.sum(axis=2).mean()), 3),
            "lockstep_per_period": round(float(most.sum(axis=1).mean()), 3),
            "mean_per_substep": counts.mean(axis=(0, 1)).round(3).tolist(),
            "lockstep_per_substep": most.mean(axis=0).round(3).tolist()}


def variants(substeps: int) -> dict[str, rnd.Randomization]:
    """The actuator layers compared: none, a delay of exactly one control period (every jump back at substep 0),
    the TOCABI lab's delay (``rnd.TOCABI_LAB``'s range, motor constant left at 1), and the same range on a grid of
    one control period (``ActuatorConfig.delay_stride`` = S: 4, 12, 20 substeps, every jump in the same substep),
    on a grid of two substeps (4, 6, ..., 20: 1 ms steps of 0.5 ms substeps, jumps in the even substeps alone),
    and the lab's range averaged over each period (``ActuatorConfig.delay_average``: every jump at substep 0)."""
    lab = rnd.TOCABI_LAB.actuators.delay_substeps
    return {"no delay": rnd.Randomization(),
            "delay of one period": rnd.Randomization(actuators=rnd.ActuatorSettings(delay_substeps=(substeps,) * 2)),
            "tocabi_lab delay": rnd.Randomization(actuators=rnd.ActuatorSettings(delay_substeps=lab)),
            "tocabi_lab delay, one-period grid": rnd.Randomization(
                actuators=rnd.ActuatorSettings(delay_substeps=lab, delay_stride=substeps)),
            "tocabi_lab delay, two-substep grid": rnd.Randomization(
                actuators=rnd.ActuatorSettings(delay_substeps=lab, delay_stride=2)),
            "tocabi_lab delay, averaged per period": rnd.Randomization(
                actuators=rnd.ActuatorSettings(delay_substeps=lab, delay_average=True))}


def measure(contract: Path, num_robots: int, seconds: float, seed: int, at_rest: bool = False,
            iterations: int | None = None) -> list[dict]:
    """One sim-to-sim run per :func:`variants` entry, the same robots, seed and start velocities (``ROBUST_START``,
    none when ``at_rest``): their iteration summaries. ``iterations``: the solver's iteration cap per substep
    (``env.sim.solver_iterations``; None: the model's)."""
    substeps = int(load_contract(contract)["timing"]["substeps"])
    start = None if at_rest else rnd.ROBUST_START
    capped = None if iterations is None else (lambda m: setattr(m.opt, "iterations", iterations))
    results = []
    for name, randomization in variants(substeps).items():
        with counted_steps(capped) as counts:
            run = run_sim2sim(contract, num_robots=num_robots, seconds=seconds, seed=seed, randomize=randomization,
                              start_velocity=start)
        summary = lockstep(np.asarray(counts).reshape(-1, num_robots, substeps))
        results.append({"variant": name, "delay_substeps": list(randomization.actuators.delay_substeps),
                        "delay_stride": randomization.actuators.delay_stride,
                        "delay_average": randomization.actuators.delay_average,
                        "survival": run.survival, **summary})
        print(f"{name}: own {summary['own_per_period']:.2f}, lockstep {summary['lockstep_per_period']:.2f} "
              "iterations per period", flush=True)
    return results


def main(argv: list[str] | None = None) -> None:
    parser = sim2sim_parser(__doc__, CONTRACT, "seed of the delays' draws (one per robot)")
    parser.add_argument("--at_rest", action="store_true",
                        help="start the robots at rest (default: the robust test's random start velocities)")
    parser.add_argument("--iterations", type=int, default=None,
                        help="cap the solver at this many iterations per substep, as env.sim.solver_iterations does "
                             "(default: the model's 20)")
    args = sim2sim_args(parser, argv)
    if args.iterations is not None and args.iterations < 1:
        parser.error(f"--iterations must be >= 1, got {args.iterations}")
    results = measure(args.contract, args.num_robots, args.seconds, args.seed, args.at_rest, args.iterations)
    if args.out is not None:
        meta = sim2sim_meta(args, start_velocity=None if args.at_rest else dataclasses.asdict(rnd.ROBUST_START),
                            solver_iterations=args.iterations)
        write_report(args.out, "lab/analysis/substep_iterations.py", argv, results, meta)


if __name__ == "__main__":
    main()
