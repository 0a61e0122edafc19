"""Where the robust gait test's lateral drift comes from: a turn, or walking sideways; when; from which start.

Runs one case of the robust test (``nominal`` by default: diverse starts, command (0.5, 0) m/s) for each checkpoint
on the CPU (C MuJoCo) through :func:`tocabi_torchrl.evaluation.robust.checkpoint_case`, stepping the deterministic
policy eagerly, and splits each robot's world-y displacement into two integrals over its alive steps
(:func:`lateral_parts`): the part from its heading, ``∫ v_x·sin ψ dt``, and the part from walking sideways in its
heading frame, ``∫ v_y·cos ψ dt`` (v the pelvis velocity in the heading frame, ψ the pelvis yaw). It reports the
displacement at fixed times (the start's transient against the rest of the walk) and grouped by the start phase
(every start row of the motion: a symmetric policy on a symmetric robot drifts by the same amount to opposite sides
from mirrored starts, so the mean over both is the policy's own bias).

After the first gait cycle it also reports the error of the velocity averaged over the last cycle, forward and
sideways (:func:`cycle_mean_error`): the slow sideways walk the drift accumulates from, which the ``cycle_vel`` reward
term pays for (``transforms.cycle_vel_weight``).

It also tallies where in the gait the robots fell (:func:`falls_by_phase`): the gait phase at each robot's last
alive step, in tenths of the cycle (a policy that falls as one foot takes over falls near phases 0 and 0.5).

``--model FILE`` runs another TOCABI MJCF, e.g. the exactly symmetric copy ``lab/analysis/symmetric_model.py``
writes: does a drift or a fall come from the authored robot's small asymmetries?

``--train_solver`` runs the physics with the solver iteration cap each checkpoint's run trained with
(``env.sim.solver_iterations``) instead of the model's solver the test runs: does a capped run's policy walk better
on the physics it trained on?

Wrote the drift sources of docs/training/robust/h200_run8/README.md (about 80 s per checkpoint and start of 64 robots
on 2 cores)::

    PYTHONPATH=. python lab/analysis/drift_sources.py --num_envs 64 --calm_start \\
        --out docs/training/robust/h200_run8/drift_sources.json \\
        --checkpoint docs/training/robust/h200_run8/checkpoints/wall_01080s.pt
"""

from __future__ import annotations

import time
from pathlib import Path

import torch
from tqdm.auto import tqdm
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from tocabi_torchrl.envs.cycle_velocity import gait_cycle_steps
from tocabi_torchrl.evaluation import robust
from tocabi_torchrl.evaluation.record import policy_steps
from tocabi_torchrl.rotations import quat_to_rpy
from tocabi_torchrl.transforms.normalize import freeze_running_statistics

from lab.analysis.reports import case_parser, check_paths, write_report

#: Times [s] at which the displacement is read (the test's case lasts 8 s).
MARKS_S = (0.5, 1.0, 2.0, 4.0, 8.0)


def lateral_parts(v_heading: torch.Tensor, yaw: torch.Tensor, dt: float) -> tuple[torch.Tensor, torch.Tensor]:
    """One step's world-y displacement [m] of each robot split in two: from the heading, ``v_x·sin ψ·dt``, and from
    walking sideways, ``v_y·cos ψ·dt``; ``v_heading`` (N, 2) [m/s] in the heading frame, ``yaw`` (N,) [rad].

    >>> turned, sideways = lateral_parts(torch.tensor([[0.5, 0.0], [0.5, 0.1]]), torch.tensor([0.1, 0.0]), 1.0)
    >>> [round(x, 4) for x in turned.tolist()], [round(x, 4) for x in sideways.tolist()]
    ([0.0499, 0.0], [0.0, 0.1])
    """
    return v_heading[:, 0] * torch.sin(yaw) * dt, v_heading[:, 1] * torch.cos(yaw) * dt


def spread(values: torch.Tensor) -> dict:
    """Mean, mean of the magnitude and its p95 [m] of per-robot displacements ``values`` (N,) (NaN-free).

    >>> spread(torch.tensor([0.1, -0.3]))
    {'mean': -0.1, 'abs_mean': 0.2, 'abs_p95': 0.29}
    """
    a = values.abs()
    return {"mean": round(float(values.mean()), 4), "abs_mean": round(float(a.mean()), 4),
            "abs_p95": round(float(a.quantile(0.95)), 4)}


def by_start(values: torch.Tensor, start_phase: torch.Tensor) -> dict:
    """:func:`spread` of ``values`` (N,) for each start phase in ``start_phase`` (N,), keyed by the phase (3
    decimals), with its robot count.

    >>> by_start(torch.tensor([0.2, 0.4, -0.1]), torch.tensor([0.0, 0.0, 0.5]))["0.000"]
    {'robots': 2, 'mean': 0.3, 'abs_mean': 0.3, 'abs_p95': 0.39}
    """
    return {f"{float(p):.3f}": {"robots": int((start_phase == p).sum()), **spread(values[start_phase == p])}
            for p in start_phase.unique()}


def falls_by_phase(phase: torch.Tensor, bins: int = 10) -> list[int]:
    """How many robots fell in each ``1/bins`` of the gait cycle: ``phase`` (N,) in [0, 1), the gait phase at each
    fallen robot's last alive step (NaN for a robot that did not fall, left out).

    >>> falls_by_phase(torch.tensor([0.02, 0.48, 0.51, float("nan"), 0.99]))
    [1, 0, 0, 0, 1, 1, 0, 0, 0, 1]
    """
    fell = phase[~torch.isnan(phase)]
    return torch.bincount((fell * bins).long().clamp(0, bins - 1), minlength=bins).tolist()


def measure(path: Path, case: str, num_envs: int, seconds: float, calm_start: bool = False,
            train_solver: bool = False, model: Path | None = None) -> dict:
    """The drift sources of one checkpoint in one case of the robust test (see the module docstring);
    ``calm_start``: the robots start without the test's random joint and pelvis velocities; ``train_solver``: the
    physics runs the solver iteration cap the run trained with, not the model's solver the test runs; ``model``:
    another TOCABI MJCF to run instead of the checkpoint's."""
    calm = {"start_joint_vel_std": 0.0, "start_base_vel_std": 0.0} if calm_start else {}
    test = robust.RobustTestConfig(num_envs=num_envs, seconds=seconds, **calm)
    _, cfg, env, agent = robust.checkpoint_case(path, case, "cpu", test, train_solver=train_solver, model_path=model)
    freeze_running_statistics(env)  # as the test does: the policy as trained
    dt = float(env.base_env.dt)
    steps = policy_steps(seconds, dt)
    marks = {round(s / dt): s for s in (*MARKS_S, seconds) if s <= seconds}  # and the case's end
    # The error of the velocity averaged over the last gait cycle, what the cycle_vel reward term pays for, at every
    # step after the first cycle where the robot is alive: (steps, N, 2) collected, then summarised.
    cycle = robust.CycleMeanTracking(num_envs, gait_cycle_steps(env.base_env.motion.period, dt))
    cycle_errors, cycle_alive = [], []
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.reset()
        start_y, start_phase = td["base_pos"][:, 1].clone(), td["phase"].reshape(-1).clone()
        alive = torch.ones(num_envs, dtype=torch.bool)
        # The phase at each robot's last alive step (the step's start: a fall's own step reports a reset's phase).
        phase, fall_phase = start_phase.clone(), torch.full((num_envs,), float("nan"))
        turned, sideways = torch.zeros(num_envs), torch.zeros(num_envs)
        y = start_y.clone()
        at = {}
        for k in tqdm(range(1, steps + 1), desc=f"drift sources: {path.name} {case}", unit="step", leave=False):
            td = env.step(agent.actor(td))
            nxt = td["next"]
            v = robust.heading_frame_velocity(nxt["base_quat"], nxt["base_lin_vel"])
            dt_turned, dt_sideways = lateral_parts(v, quat_to_rpy(nxt["base_quat"])[..., 2], dt)
            # A fallen robot's displacement stays where it fell, as in the test's metrics.
            turned += torch.where(alive, dt_turned, 0.0)
            sideways += torch.where(alive, dt_sideways, 0.0)
            y = torch.where(alive, nxt["base_pos"][:, 1], y)
            fell = alive & nxt["done"].reshape(-1)
            fall_phase = torch.where(fell, phase, fall_phase)
            alive &= ~fell
            phase = nxt["phase"].reshape(-1).clone()
            cycle.update(v, nxt["command"], alive)
            if k > cycle.window:
                cycle_errors.append((cycle.mean_velocity() - cycle.mean_command()).float())
                cycle_alive.append(alive.clone())
            if k in marks:
                at[f"{marks[k]:g} s"] = spread(y - start_y)
            td = step_mdp(td)
    lateral = y - start_y
    solver = cfg.env.sim.solver_iterations if train_solver else None
    return {"checkpoint": str(path), "case": case, "robots": num_envs, "seconds": seconds, "calm_start": calm_start,
            "solver_iterations": solver, "model": None if model is None else str(model),
            "survival": round(float(alive.float().mean()), 4), "lateral_m": spread(lateral),
            "lateral_m_at": at, "from_heading_m": spread(turned), "from_sideways_walk_m": spread(sideways),
            "lateral_m_by_start_phase": by_start(lateral, start_phase),
            "cycle_mean_error_mps": cycle_mean_error(cycle_errors, cycle_alive),
            "falls_by_phase_tenth": falls_by_phase(fall_phase)}


def cycle_mean_error(errors: list[torch.Tensor], alive: list[torch.Tensor]) -> dict | None:
    """Over every step after the first gait cycle where the robot is alive: the mean and p95 of the magnitude of the
    forward and sideways parts of the cycle-mean velocity error (each ``errors`` entry (N, 2) [m/s], each
    ``alive`` (N,) bool), and the mean of exp(−100·‖ē‖²), the ``cycle_vel`` term's kernel at its default scale;
    None when no such step exists (a case shorter than a cycle, or every robot fallen).

    >>> cycle_mean_error([torch.tensor([[0.1, 0.0], [0.0, -0.2]])], [torch.tensor([True, False])])
    {'forward': {'abs_mean': 0.1, 'abs_p95': 0.1}, 'sideways': {'abs_mean': 0.0, 'abs_p95': 0.0}, 'kernel_mean': 0.3679}
    """
    if not errors:
        return None
    e = torch.stack(errors)[torch.stack(alive)]  # (alive steps, 2)
    if not len(e):
        return None
    parts = {name: {"abs_mean": round(float(e[:, i].abs().mean()), 4),
                    "abs_p95": round(float(e[:, i].abs().quantile(0.95)), 4)}
             for i, name in enumerate(("forward", "sideways"))}
    return {**parts, "kernel_mean": round(float(torch.exp(-100.0 * e.square().sum(-1)).mean()), 4)}


def main(argv=None) -> int:
    p = case_parser(__doc__, num_envs=64, seconds=8.0, robots_help="robots (the test asks 1,024 on a GPU)",
                    seconds_help="length of the case [s] (the test's: 8)")
    p.add_argument("--calm_start", action="store_true",
                   help="also each checkpoint with the robots starting still (no random start velocities): how much "
                        "of the drift is the start's")
    p.add_argument("--train_solver", action="store_true",
                   help="run the physics with the solver iteration cap each run trained with "
                        "(env.sim.solver_iterations), not the model's solver the test runs: is the drift the cap's?")
    p.add_argument("--model", type=Path, default=None,
                   help="run on this TOCABI MJCF instead of each checkpoint's model (e.g. the exactly symmetric copy "
                        "of lab/analysis/symmetric_model.py: is the drift or a fall the authored robot's asymmetry?)")
    p.add_argument("--out", type=Path, default=None, help="JSON to write (default: print only)")
    args = p.parse_args(argv)
    check_paths(p, args.checkpoint, args.out)
    if args.model is not None and not args.model.is_file():
        p.error(f"--model {args.model}: no such file (write the symmetric copy with "
                "PYTHONPATH=. python lab/analysis/symmetric_model.py --out FILE.xml)")
    results = []
    for path, calm in [(c, calm) for c in args.checkpoint for calm in (False, True)[:1 + args.calm_start]]:
        start = time.perf_counter()
        r = measure(path, args.case, args.num_envs, args.seconds, calm, args.train_solver, args.model)
        solver = f" (solver capped at {r['solver_iterations']})" if r["solver_iterations"] else ""
        solver += f" (on {args.model})" if args.model is not None else ""
        print(f"{path}{' (calm start)' if calm else ''}{solver}: survival {r['survival']}, lateral {r['lateral_m']}, "
              f"from the heading {r['from_heading_m']}, from walking sideways {r['from_sideways_walk_m']}, "
              f"by start phase {r['lateral_m_by_start_phase']}, cycle-mean velocity error after the first cycle "
              f"{r['cycle_mean_error_mps']}, falls by tenth of the gait cycle {r['falls_by_phase_tenth']} "
              f"({time.perf_counter() - start:.0f} s)", flush=True)
        results.append(r)
    if args.out is not None:
        write_report(args.out, "lab/analysis/drift_sources.py", argv, results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
