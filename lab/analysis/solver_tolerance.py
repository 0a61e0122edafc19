"""What a looser Newton tolerance or fewer iterations save the solver on a walking policy's states, and what they move.

mujoco-warp iterates every world of a substep until the slowest has converged to the model's tolerance (1e-8 in
``assets/tocabi/tocabi.xml``, at most 20 iterations), so a GPU pays about the most iterations any world needs: the
``lockstep`` count of ``lab/analysis/substep_iterations.py`` (the maximum over robots per substep, summed over a
control period). A looser tolerance ends the solve earlier, a lower iteration cap cuts the slowest worlds' solves
short; whether either may be used depends on what it moves. Per setting, this measures with C MuJoCo (the same
Newton solver and warm start; counts differ in detail from mujoco-warp's):

* the iterations, own and lockstep, of robots driven by a shipped policy through the torch-free runtime from the
  robust gait test's diverse starts (no randomisation, no kicks), and their survival and forward distance;
* the parity sequence of ``tests/test_model.py::test_parity_motion`` (0.25 s of one fixed leg-torque sequence from
  the initial pose): the largest joint-angle difference from the model's own tolerance, against that test's 1e-3 rad;
* for the iteration caps, the shipped robust policy under the robust gait test's ``robust_1.0`` case (the TOCABI
  lab's randomisation, three 1.0 m/s kicks, the test's seed): its survival, where hard impacts need the most
  iterations.

    PYTHONPATH=. python lab/analysis/solver_tolerance.py --num_robots 32 --seconds 4 --kicked \\
        --out docs/benchmarks/solver_tolerance.json
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import mujoco
import numpy as np

from tocabi_torchrl import robot
from tocabi_torchrl.runtime import load_contract
from tocabi_torchrl.runtime import randomization as rnd
from tocabi_torchrl.runtime.mujoco_driver import run_sim2sim

from lab.analysis.reports import sim2sim_args, sim2sim_meta, sim2sim_parser, write_report
from lab.analysis.substep_iterations import counted_steps, lockstep

CONTRACT = robot.asset_path("policies", "tocabi_walk_torque.json")
#: (tolerance, iteration cap) settings compared; None: the model's own.
SETTINGS = ((None, None), (1e-7, None), (1e-6, None), (1e-5, None), (1e-4, None), (None, 6), (None, 4), (None, 3))
#: The settings also run under the robust test's 1.0 m/s kicks, and the policy that meets them.
KICKED_SETTINGS = ((None, None), (None, 4), (None, 3))
ROBUST_CONTRACT = robot.asset_path("policies", "tocabi_walk_robust.json")
#: The parity sequence of tests/test_model.py::test_parity_motion and its bound [rad].
PARITY_STEPS, PARITY_ATOL = 62, 1e-3


@contextlib.contextmanager
def solved_with(tolerance: float | None, iterations: int | None = None) -> Iterator[list[int]]:
    """Within the block every ``mujoco.mj_step`` runs with ``opt.tolerance`` = ``tolerance`` and ``opt.iterations``
    = ``iterations`` (None: the model's) and appends its solver iterations to the yielded list; ``mj_step`` is
    restored on leaving.

    >>> m = robot.load_model()
    >>> d = mujoco.MjData(m)
    >>> with solved_with(1e-3, 5) as counts:
    ...     mujoco.mj_step(m, d)
    >>> len(counts), m.opt.tolerance, m.opt.iterations
    (1, 0.001, 5)
    >>> mujoco.mj_step.__name__
    'mj_step'
    """
    with counted_steps(lambda m: _set(m, tolerance, iterations)) as counts:
        yield counts


def _set(m: mujoco.MjModel, tolerance: float | None, iterations: int | None) -> None:
    if tolerance is not None:
        m.opt.tolerance = tolerance
    if iterations is not None:
        m.opt.iterations = iterations


def parity_deviation(tolerance: float | None, iterations: int | None = None) -> float:
    """The largest joint-angle difference [rad] after the parity sequence between the setting and the model's own
    (one robot, upper body held by its position actuators, the sequence's leg torques)."""
    rng = np.random.default_rng(1)
    amplitude = 0.15 * robot.LEG_TORQUE_LIMITS
    torques = amplitude * np.sin(2 * np.pi * (np.arange(PARITY_STEPS)[:, None] / 40 + rng.uniform(0, 1, 12)))
    finals = []
    for setting in ((None, None), (tolerance, iterations)):
        m = robot.load_model()
        _set(m, *setting)
        d = mujoco.MjData(m)
        d.qpos[:] = robot.INIT_QPOS
        d.ctrl[12:] = robot.INIT_JOINT_POS[12:]
        mujoco.mj_forward(m, d)
        for k in range(PARITY_STEPS):
            d.ctrl[:12] = torques[k]
            for _ in range(8):
                mujoco.mj_step(m, d)
        finals.append(d.qpos[7:].copy())
    return float(np.abs(finals[1] - finals[0]).max())


def measure(contract: Path, num_robots: int, seconds: float, seed: int) -> list[dict]:
    """One sim-to-sim run per setting, the same robots, seed and start velocities: iterations, outcomes, parity."""
    substeps = int(load_contract(contract)["timing"]["substeps"])
    results = []
    for tolerance, iterations in SETTINGS:
        with solved_with(tolerance, iterations) as counts:
            run = run_sim2sim(contract, num_robots=num_robots, seconds=seconds, seed=seed,
                              randomize=rnd.Randomization(), start_velocity=rnd.ROBUST_START)
        summary = lockstep(np.asarray(counts).reshape(-1, num_robots, substeps))
        parity = parity_deviation(tolerance, iterations)
        results.append({"case": "walking", "tolerance": tolerance, "iterations": iterations, "survival": run.survival,
                        "forward_distance_m": run.forward_distance_m, "parity_deviation_rad": parity,
                        "parity_within_test": parity <= PARITY_ATOL, **summary})
        print(f"tolerance {tolerance or 'model'}, iterations {iterations or 'model'}: own "
              f"{summary['own_per_period']:.2f}, lockstep {summary['lockstep_per_period']:.2f} iterations per period, "
              f"survival {run.survival:.3f}, parity {parity:.2e} rad", flush=True)
    return results


def measure_kicked(contract: Path, num_robots: int) -> list[dict]:
    """The robust test's ``robust_1.0`` case on C MuJoCo per :data:`KICKED_SETTINGS`: survival and distance."""
    from tocabi_torchrl.evaluation.robust import RobustTestConfig

    test = RobustTestConfig()
    kicks = rnd.PushSettings(count=test.push_count, window=test.push_window, speed=(1.0, 1.0), kind=test.push_kind)
    results = []
    for tolerance, iterations in KICKED_SETTINGS:
        with solved_with(tolerance, iterations):
            run = run_sim2sim(contract, num_robots=num_robots, seconds=test.seconds, seed=test.seed,
                              randomize="tocabi_lab", pushes=kicks, start_velocity=rnd.ROBUST_START)
        results.append({"case": "robust_1.0", "tolerance": tolerance, "iterations": iterations,
                        "survival": run.survival, "forward_distance_m": run.forward_distance_m})
        print(f"kicked, iterations {iterations or 'model'}: survival {run.survival:.3f}", flush=True)
    return results


def main(argv: list[str] | None = None) -> None:
    parser = sim2sim_parser(__doc__, CONTRACT, "seed of the start velocities")
    parser.add_argument("--kicked", action="store_true",
                        help="also run the caps under the robust test's 1.0 m/s kicks (the shipped robust policy)")
    args = sim2sim_args(parser, argv)
    results = measure(args.contract, args.num_robots, args.seconds, args.seed)
    if args.kicked:
        results += measure_kicked(ROBUST_CONTRACT, args.num_robots)
    if args.out is not None:
        model = robot.load_model()
        meta = sim2sim_meta(args, model_tolerance=float(model.opt.tolerance),
                            model_iterations=int(model.opt.iterations),
                            start_velocity={"joint_std": rnd.ROBUST_START.joint_std,
                                            "base_std": rnd.ROBUST_START.base_std})
        write_report(args.out, "lab/analysis/solver_tolerance.py", argv, results, meta)


if __name__ == "__main__":
    main()
