"""Which kick topples a robot in the robust gait test's pushed cases, from which direction, and how soon after.

Runs one pushed case of the robust test (``robust_1.0`` by default: the test's seed, diverse starts, the
``tocabi_lab`` randomisation, three one-step kicks at random times in 2-7 s) for each checkpoint on the CPU (C MuJoCo)
through :func:`tocabi_torchrl.evaluation.robust.run_case`: the case's settings in an env of its own
(:func:`~tocabi_torchrl.evaluation.robust.case_env`), so its robots are not the very ones of the test's batch env,
where the case holds other world indices. It reads each robot's kick schedule from the env
(``Pushes.start_step`` and ``Pushes.force``) and its fall time (``alive_seconds``), and attributes every fall to the
last kick before it. Directions are those of the kick's force in the world frame, in four 90° sectors (every robot
starts facing +x and the test's robots turn 0.03-0.6 rad, so "forward" is roughly the way the robot walks).

Reports per checkpoint: survival, falls by the condition that ended them (:func:`note_first_flags`:
``self_collision``, ``neck_tilt``, ...), how far apart the feet were before the self-collisions (:func:`foot_gaps`),
those before any kick with their times, falls by the kick that preceded
them, the hazard of each kick (falls after it over the robots it met alive), falls by direction against the kicks per
direction that met a standing robot, the hazard of a kick by the seconds since the robot's previous kick
(:func:`hazard_by_gap`), and the fall delay after the kick (null when nothing fell); with ``--values``, the critic's
mean value around the kicks robots fell after and around the others (:func:`value_around_kicks`).

Wrote docs/training/robust/h200_run3/kick_falls.json (about 80 s per checkpoint of 64 robots on 2 cores)::

    PYTHONPATH=. python lab/analysis/kick_falls.py --num_envs 64 --out docs/training/robust/h200_run3/kick_falls.json \\
        --checkpoint runs/time_to_walk/robust_v3/checkpoints/wall_01260s.pt \\
        runs/time_to_walk/robust_v2/checkpoints/wall_01080s.pt
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import torch

from tocabi_torchrl.evaluation import robust
from tocabi_torchrl.transforms.reward_terms import feet_apart_across_heading
from tocabi_torchrl.value_rules import PUSH_KINDS

from lab.analysis.reports import check_paths
from lab.new_files import write_new_files

SECTORS = ("forward (+x)", "left (+y)", "back (-x)", "right (-y)")
#: Upper edges [s] of the bins of the time since a robot's previous kick (the last bin is open): whether a kick is
#: deadlier when the robot has not recovered from the one before.
GAP_EDGES_S = (0.5, 1.0, 2.0)
#: Policy steps from a kick's step at which ``--values`` reads the critic: the step before it, then 0.05, 0.1 and
#: 0.2 s after it (4 ms steps).
VALUE_OFFSETS = (-1, 12, 25, 50)


def sector(angle: float) -> str:
    """The 90° sector of a world-frame direction ``angle`` [rad] (0 = +x), centred on the four axes."""
    return SECTORS[int(((math.degrees(angle) + 45.0) % 360.0) // 90.0)]


def kicks_met(row, end_s: float, dt: float = 1.0) -> list:
    """One robot's kicks that came while it stood, in time order: the items of ``row`` (kick times, in units of
    ``dt`` seconds) at or before its fall time ``end_s`` [s] (``inf``: it stood to the end)."""
    return sorted(k for k in row if k * dt <= end_s)


def hazard_by_gap(kick_s: torch.Tensor, t_end: torch.Tensor, edges=GAP_EDGES_S) -> dict:
    """The kicks after each robot's first, binned by the seconds since its previous kick.

    kick_s: (N, K) start time of each robot's kicks [s]; t_end: (N,) the robot's fall time [s] (``inf``: it stood to
    the end). Per bin ("<0.5 s", "0.5-1 s", ..., ">=2 s"): ``met``, the kicks that came while their robot stood;
    ``falls``, those that were the last kick before their robot fell; ``hazard``, falls / met (None when none met).

    >>> import torch
    >>> r = hazard_by_gap(torch.tensor([[2.0, 2.3, 5.0], [2.0, 2.7, 6.0]]), torch.tensor([3.0, float("inf")]))
    >>> r["<0.5 s"], r["0.5-1 s"], r[">=2 s"]["met"]
    ({'met': 1, 'falls': 1, 'hazard': 1.0}, {'met': 1, 'falls': 0, 'hazard': 0.0}, 1)
    """
    labels = [f"<{edges[0]:g} s", *(f"{a:g}-{b:g} s" for a, b in zip(edges[:-1], edges[1:])), f">={edges[-1]:g} s"]
    table = {label: {"met": 0, "falls": 0} for label in labels}
    for row, end in zip(kick_s.double().tolist(), t_end.tolist()):
        met = kicks_met(row, end)
        for j in range(1, len(met)):
            cell = table[labels[sum(met[j] - met[j - 1] >= e for e in edges)]]
            cell["met"] += 1
            cell["falls"] += int(math.isfinite(end) and j == len(met) - 1)
    for cell in table.values():
        cell["hazard"] = cell["falls"] / cell["met"] if cell["met"] else None
    return table


def value_around_kicks(values: torch.Tensor, kick_step: torch.Tensor, t_end: torch.Tensor, dt: float,
                       offsets=VALUE_OFFSETS) -> dict:
    """The critic's mean value around the kicks that met a standing robot, for the kicks its robot fell after (the
    last kick before its fall) and for the others.

    values: (N, T) the critic's value of each robot's state at each policy step; kick_step: (N, K) the policy step of
    each kick; t_end: (N,) the robot's fall time [s] (``inf``: it stood); dt: the policy step [s]. A kick is counted
    only where every offset (policy steps from the kick, ``offsets``) lies within the rollout. Returns ``{"falls
    after": {...}, "stands": {...}}``, each ``{"kicks": n, "value": {offset: mean or None}}``.

    >>> import torch
    >>> v = torch.arange(10.0).repeat(2, 1)            # value t at step t
    >>> r = value_around_kicks(v, torch.tensor([[3], [4]]), torch.tensor([0.05, float("inf")]), 0.01, offsets=(-1, 2))
    >>> r["falls after"], r["stands"]
    ({'kicks': 1, 'value': {-1: 2.0, 2: 5.0}}, {'kicks': 1, 'value': {-1: 3.0, 2: 6.0}})
    """
    groups = {"falls after": [], "stands": []}
    for i, (row, end) in enumerate(zip(kick_step.to(torch.int64).tolist(), t_end.tolist())):
        met = kicks_met(row, end, dt)
        for j, k in enumerate(met):
            if not all(0 <= k + o < values.shape[1] for o in offsets):
                continue
            fell_after = math.isfinite(end) and j == len(met) - 1
            groups["falls after" if fell_after else "stands"].append([float(values[i, k + o]) for o in offsets])
    return {name: {"kicks": len(rows), "value": {o: (sum(r[c] for r in rows) / len(rows) if rows else None)
                                                 for c, o in enumerate(offsets)}}
            for name, rows in groups.items()}


def foot_gaps(gap: torch.Tensor, t_end: torch.Tensor, dt: float, touched: list[int]) -> dict:
    """The feet's distance across the heading [m] (``FootGap``'s d) around the falls that ended with the feet
    touching: ``gap`` (N, T) per robot and policy step (the state each action was chosen in, the reset state first),
    ``t_end`` (N,) each robot's fall time [s] (its alive seconds, the terminating step not counted; inf: it stood),
    ``touched`` the robots whose fall was a self-collision. Reports d in the state each of those robots took its
    last action in (one policy step before the feet touched), each standing robot's smallest d, and the quantiles
    of d over every robot's states before its fall.

    >>> g = torch.tensor([[0.30, 0.25, 0.20, 0.19], [0.30, 0.28, 0.26, 0.27]])
    >>> r = foot_gaps(g, torch.tensor([0.03, math.inf]), 0.01, [0])  # robot 0's 4th step touched
    >>> r["before_self_collision"], r["standing_min"]["p50"]
    ([0.19], 0.26)
    """
    steps = gap.shape[1]
    # States each robot acted in while alive: a fall after k alive steps came from the (k + 1)-th state.
    seen = torch.where(torch.isinf(t_end), steps, (t_end / dt).round() + 1).long().clamp(1, steps)
    alive_steps = torch.arange(steps).unsqueeze(0) < seen.unsqueeze(1)
    before = [round(float(gap[i, int(seen[i]) - 1]), 3) for i in touched]
    standing = torch.isinf(t_end)
    smallest = gap.masked_fill(~alive_steps, math.inf).min(1).values[standing]
    walking = gap[alive_steps]

    def q(values: torch.Tensor, levels: dict) -> dict:
        return {k: (round(float(values.quantile(v)), 3) if values.numel() else None) for k, v in levels.items()}

    return {"before_self_collision": before, "standing_min": q(smallest, {"p5": 0.05, "p50": 0.5}),
            "alive_steps": q(walking, {"p1": 0.01, "p5": 0.05, "p50": 0.5})}


def note_first_flags(first: dict, flags: dict, step: int) -> None:
    """Note in ``first`` (robot index -> (step, condition)) each robot's first termination: the conditions of
    ``flags`` (name -> (N,) bool, as :func:`tocabi_torchrl.envs.termination.termination_flags` returns them, ``"any"``
    left out) true at ``step``, for robots not noted before (the first condition in ``flags``' order when several).

    >>> import torch
    >>> first = {}
    >>> yes, no = torch.tensor([True, True]), torch.tensor([False, False])
    >>> note_first_flags(first, {"pelvis_low": torch.tensor([False, True]), "self_collision": yes, "any": yes}, 5)
    >>> note_first_flags(first, {"pelvis_low": torch.tensor([True, False]), "self_collision": no, "any": yes}, 6)
    >>> first
    {1: (5, 'pelvis_low'), 0: (5, 'self_collision')}
    """
    for name, flag in flags.items():
        if name == "any":
            continue
        for i in flag.nonzero().flatten().tolist():
            first.setdefault(i, (step, name))


@contextlib.contextmanager
def noting_terminations(first: dict):
    """While open, every step of a walking env notes its robots' first termination in ``first``
    (:func:`note_first_flags`, steps counted from 1 per env step). The env keeps only whether a robot ended, so this
    wraps the one function that computes the conditions, in the env module's namespace, and restores it on exit."""
    from tocabi_torchrl.envs import tocabi_walk

    original, steps = tocabi_walk.termination_flags, [0]

    def noting(**kwargs):
        flags = original(**kwargs)
        steps[0] += 1
        note_first_flags(first, flags, steps[0])
        return flags

    tocabi_walk.termination_flags = noting
    try:
        yield first
    finally:
        tocabi_walk.termination_flags = original


def measure(path: Path, case: str, num_envs: int, push_kind: str = "velocity", as_trained: bool = False,
            push_window: tuple[float, float] = (2.0, 7.0), seconds: float = 8.0, values: bool = False) -> dict:
    test = robust.RobustTestConfig(num_envs=num_envs, push_kind=push_kind, push_window=tuple(push_window),
                                   seconds=seconds)
    state, cfg, env, agent = robust.checkpoint_case(path, case, "cpu", test, as_trained=as_trained)
    beta = env.base_env.assist_scale
    pushes, schedule, critic_values, gaps = env.base_env.pushes, {}, [], []

    def actor(td):
        if not schedule:  # the reset drew every robot's kicks; they stay fixed for the case (no robot is reset)
            schedule["start"], schedule["force"] = pushes.start_step.clone(), pushes.force.clone()
        gaps.append(feet_apart_across_heading(td["foot_pos"], td["base_rpy"][..., 2:3]).reshape(-1).clone())
        if values:  # the critic of the state the action is chosen in (a copy: the critic writes its output key)
            critic_values.append(agent.critic(td.clone())["state_value"].reshape(-1).clone())
        return agent.actor(td)

    with noting_terminations({}) as first_flag:
        per_env = robust.run_case(actor, env, test.seconds, desc=f"kick falls: {Path(path).name}")
    dt = float(env.base_env.dt)
    kick_s = schedule["start"].double() * dt  # (N, K) start time of each kick [s]
    # A kick due after the case's end (a --seconds shorter than the window) never came: NaN is met by no robot.
    kick_s = torch.where(kick_s < seconds, kick_s, torch.full_like(kick_s, math.nan))
    angle = torch.atan2(schedule["force"][..., 1], schedule["force"][..., 0])  # (N, K) world-frame direction [rad]
    alive = per_env["alive"]
    # (N,) each robot's fall time [s], inf for a robot that stood to the end
    t_end_all = torch.where(alive.bool(), torch.full_like(per_env["alive_seconds"].double(), math.inf),
                            per_env["alive_seconds"].double())
    count = kick_s.shape[1]
    met = [0] * count  # robots alive when kick j came
    after = [0] * count  # falls whose last kick before them was kick j
    by_dir = {s: 0 for s in SECTORS}
    met_dir = {s: 0 for s in SECTORS}  # kicks per direction that came while their robot stood
    delays, before_any_s, reasons, before_reasons, touched = [], [], Counter(), Counter(), []
    for i in range(num_envs):
        t_end = float(t_end_all[i])
        for j in range(count):
            standing = float(kick_s[i, j]) <= t_end
            met[j] += int(standing)
            met_dir[sector(float(angle[i, j]))] += int(standing)
        if bool(alive[i]):
            continue
        reason = first_flag.get(i, (0, "unknown"))[1]
        reasons[reason] += 1
        if reason == "self_collision":
            touched.append(i)
        prior = [j for j in range(count) if float(kick_s[i, j]) <= t_end]
        if not prior:
            before_any_s.append(round(t_end, 3))
            before_reasons[reason] += 1
            continue
        j = prior[-1]
        after[j] += 1
        by_dir[sector(float(angle[i, j]))] += 1
        delays.append(t_end - float(kick_s[i, j]))
    delays_t = torch.tensor(delays, dtype=torch.float64)
    extra = {"foot_gap_m": foot_gaps(torch.stack(gaps, 1), t_end_all, dt, touched)}
    if values:
        extra["critic_value_around_kicks"] = {
            "offsets_s": [o * dt for o in VALUE_OFFSETS], "gamma": float(cfg.ppo.gamma),
            **value_around_kicks(torch.stack(critic_values, 1), schedule["start"], t_end_all, dt)}
    return {
        "checkpoint": str(path), "case": case, "num_envs": num_envs, "seed": robust.EVAL_SEED,
        "push_kind": push_kind, "push_window_s": list(push_window), "seconds": seconds,
        "torque_assist": None if beta is None else float(beta),
        "env_steps": int(state.get("env_steps", 0)), "train_seconds": float(state.get("train_seconds", 0.0)),
        "survival": float(alive.float().mean()),
        "falls_by_reason": dict(reasons),
        "falls_before_any_kick": len(before_any_s),
        "falls_before_any_kick_s": sorted(before_any_s),
        "falls_before_any_kick_by_reason": dict(before_reasons),
        "falls_after_kick": after,
        "robots_alive_at_kick": met,
        "kick_hazard": [a / m if m else None for a, m in zip(after, met)],
        "falls_by_direction_of_last_kick": by_dir,
        "hazard_by_seconds_since_previous_kick": hazard_by_gap(kick_s, t_end_all),
        "kicks_met_standing_by_direction": met_dir,
        "fall_delay_after_kick_s": ({"mean": float(delays_t.mean()), "min": float(delays_t.min()),
                                     "max": float(delays_t.max())} if delays else None),
        **extra,
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", nargs="+", required=True, type=Path, help="checkpoints (.pt) to test")
    p.add_argument("--case", default="robust_1.0", help="a pushed case of the robust test (robust_0.5, robust_1.0)")
    p.add_argument("--num_envs", type=int, default=64, help="robots (the test asks 1,024 on a GPU)")
    p.add_argument("--push_kind", choices=PUSH_KINDS, default="velocity",
                   help="velocity: the test's kicks (default); force: the same momentum on the pelvis alone")
    p.add_argument("--as_trained", action="store_true",
                   help="a torque-assisted run's checkpoint acts with the assist at the β its training had reached")
    p.add_argument("--push_window", type=float, nargs=2, default=(2.0, 7.0), metavar=("START", "END"),
                   help="seconds the three kicks fall in, one per third (the test's: 2 7); a wider window spaces them")
    p.add_argument("--seconds", type=float, default=8.0, help="length of the case [s] (the test's: 8)")
    p.add_argument("--values", action="store_true",
                   help="also the critic's mean value before and 0.05-0.2 s after the kicks robots fell after, and "
                        "after the others: does the critic see a fall coming?")
    p.add_argument("--out", type=Path, default=None, help="JSON to write (default: print only)")
    args = p.parse_args(argv)
    check_paths(p, args.checkpoint, args.out)  # before the rollouts: a report is never written over
    if args.case not in robust.CASES or not robust.CASES[args.case].randomized:
        pushed = sorted(n for n, c in robust.CASES.items() if c.randomized)
        p.error(f"--case must be a pushed case of the robust test, one of {pushed}; got {args.case!r}")
    results = []
    for path in args.checkpoint:
        start = time.perf_counter()
        r = measure(path, args.case, args.num_envs, args.push_kind, args.as_trained, args.push_window, args.seconds,
                    args.values)
        delay = r["fall_delay_after_kick_s"]
        assisted = "" if r["torque_assist"] is None else f" (assist β {r['torque_assist']:.2f})"
        print(f"{path}{assisted}: survival {r['survival']:.3f}, falls by reason {r['falls_by_reason']}, "
              f"{r['falls_before_any_kick']} before any kick (at {r['falls_before_any_kick_s']} s), "
              f"falls after kicks {r['falls_after_kick']} of robots "
              f"{r['robots_alive_at_kick']} alive at them, by direction {r['falls_by_direction_of_last_kick']} of "
              f"{r['kicks_met_standing_by_direction']}, delay {'-' if delay is None else round(delay['mean'], 2)} s "
              f"({time.perf_counter() - start:.0f} s)", flush=True)
        if "critic_value_around_kicks" in r:
            v = r["critic_value_around_kicks"]
            print("  critic value at", [round(t, 3) for t in v["offsets_s"]], "s from the kick:", flush=True)
            for group in ("falls after", "stands"):
                means = [None if x is None else round(x, 1) for x in v[group]["value"].values()]
                print(f"    {group} ({v[group]['kicks']} kicks): {means}", flush=True)
        results.append(r)
    if args.out is not None:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], check=False, capture_output=True,
                                text=True).stdout.strip()
        meta = {"command": " ".join(["python", "lab/analysis/kick_falls.py", *(argv or sys.argv[1:])]),
                "date": time.strftime("%Y-%m-%d"), "code": commit, "hardware": "CPU (C MuJoCo)"}
        # Nor over a file that appeared there during the rollouts: the results then go beside it.
        write_new_files({args.out: json.dumps({"meta": meta, "results": results}, indent=1, allow_nan=False) + "\n"})
    return 0


if __name__ == "__main__":
    sys.exit(main())
