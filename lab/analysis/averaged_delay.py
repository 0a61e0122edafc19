"""Does a policy meet the same robot when the torque delay is averaged over each control period? The shipped robust
policy (trained with the TOCABI lab's delay applied substep by substep) on C MuJoCo robots through the torch-free
runtime, under the robust gait test's pushed cases, once with the lab's delay per substep and once with its mean
over each period (``env.control.actuators.delay_average``), every other draw alike.

Both runs use the same seed, so each robot draws the same delay, motor constants, dynamics, sensor biases, start
velocities and kicks in both; only how the delayed torque reaches the joint differs. A policy that cannot tell the
two apart survives, walks and drifts alike, which is what training on the averaged delay relies on. A walking gait
is chaotic, so a robot near the edge of falling falls in one run and not in the other for any small difference: a
third run, the per-substep delay again with every robot's start joint angles offset by N(0, (1e-6 rad)²), shows
how many robots' outcomes change for a difference that means nothing.

Wrote docs/benchmarks/randomization/averaged_delay.json (about 13 minutes on 2 cores)::

    PYTHONPATH=. python lab/analysis/averaged_delay.py --num_robots 48 \\
        --out docs/benchmarks/randomization/averaged_delay.json
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import time
from pathlib import Path

import mujoco

from tocabi_torchrl import robot
from tocabi_torchrl.evaluation.robust import RobustTestConfig
from tocabi_torchrl.runtime import randomization as rnd
from tocabi_torchrl.runtime.mujoco_driver import run_sim2sim

from lab.analysis.reports import check_paths, write_report

CONTRACT = robot.asset_path("policies", "tocabi_walk_robust.json")


def variants() -> dict[str, rnd.Randomization]:
    """The TOCABI lab's set with its delay per substep (as the robust gait test applies it) and averaged."""
    lab = rnd.TOCABI_LAB
    averaged = dataclasses.replace(lab, actuators=dataclasses.replace(lab.actuators, delay_average=True))
    return {"delay per substep": lab, "delay averaged per period": averaged}


#: The chaos baseline's offset of the start joint angles [rad] (``run_sim2sim``'s ``perturbation``).
OFFSET_RAD = 1e-6


def runs() -> dict[str, tuple[rnd.Randomization, float]]:
    """Each run's randomisation and start-angle offset: :func:`variants`, then the chaos baseline."""
    out = {name: (randomization, 0.0) for name, randomization in variants().items()}
    out["delay per substep, start angles offset 1e-6 rad"] = (rnd.TOCABI_LAB, OFFSET_RAD)
    return out


def changed(a: list[bool], b: list[bool]) -> int:
    """How many robots survived in one run and not in the other.

    >>> changed([True, True, False, False], [True, False, True, False])
    2
    """
    return sum(x != y for x, y in zip(a, b))


def measure(contract: Path, num_robots: int, speeds: list[float], seed: int) -> list[dict]:
    """One sim-to-sim run per kick speed and :func:`runs` entry: the gait-test metrics of each, and how many
    robots' survival differs from the first run's of its speed."""
    test = RobustTestConfig()
    results = []
    for speed in speeds:
        pushes = rnd.PushSettings(count=test.push_count, window=test.push_window, speed=(speed, speed),
                                  kind=test.push_kind)
        first = None
        for name, (randomization, offset) in runs().items():
            run = run_sim2sim(contract, num_robots=num_robots, seconds=test.seconds, seed=seed,
                              randomize=randomization, pushes=pushes, start_velocity=rnd.ROBUST_START,
                              perturbation=offset)
            first = run if first is None else first
            differ = changed(first.alive, run.alive)
            results.append({"kick_speed_mps": speed, "variant": name, "survival": run.survival,
                            "outcomes_changed": differ,
                            "forward_distance_m": round(run.forward_distance_m, 3),
                            "lateral_drift_m": round(run.lateral_drift_m, 3),
                            "speed_tracking_error_mps": round(run.speed_tracking_error_mps, 4),
                            "alive": [bool(a) for a in run.alive]})
            print(f"kicks {speed} m/s, {name}: survival {run.survival:.3f}, forward {run.forward_distance_m:.2f} m, "
                  f"drift {run.lateral_drift_m:.2f} m, {differ} outcomes changed", flush=True)
    return results


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--contract", type=Path, default=CONTRACT, help="exported policy's contract (.json)")
    parser.add_argument("--num_robots", type=int, default=48, help="robots per run")
    parser.add_argument("--speeds", type=float, nargs="+", default=[0.5, 1.0], help="kick speeds [m/s], one run each")
    parser.add_argument("--seed", type=int, default=RobustTestConfig().seed,
                        help="seed of every draw (default: the robust gait test's)")
    parser.add_argument("--out", type=Path, default=None, help="JSON to write (default: print only)")
    args = parser.parse_args(argv)
    check_paths(parser, [args.contract], args.out)
    if args.num_robots < 1 or not all(s >= 0 for s in args.speeds):
        parser.error("--num_robots must be >= 1 and every --speeds value >= 0")
    results = measure(args.contract, args.num_robots, args.speeds, args.seed)
    if args.out is not None:
        meta = {"date": time.strftime("%Y-%m-%d"), "hardware": f"CPU (C MuJoCo {mujoco.__version__}), "
                f"{platform.machine()}", "num_robots": args.num_robots, "seconds": RobustTestConfig().seconds,
                "seed": args.seed}
        write_report(args.out, "lab/analysis/averaged_delay.py", argv, results, meta)


if __name__ == "__main__":
    main()
