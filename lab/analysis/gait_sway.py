"""How much of the robust test's instantaneous speed error is the gait's own sway (docs/evaluation.md).

Runs the robust test's ``nominal`` case (command (0.5, 0) m/s, diverse starts, the test's seed) of a policy on the
CPU (C MuJoCo) through :func:`tocabi_torchrl.evaluation.robust.run_case`, and records the heading-frame pelvis
velocity of every robot at every step. Reports, averaged over the robots alive at the end: the per-robot std of v_x
and v_y over the last ``--tail`` seconds, the error of their mean velocity over that time per axis, the
instantaneous error ``|v − command|`` over that time, the error of the mean velocity over the last gait cycle per
axis, and the test's two metrics over the whole case (``tracking_error_mps``: the error of the gait-cycle mean
velocity; ``instant_speed_error_mps``). The policy's phase action may run its clock faster than the reference's,
which shortens its own gait cycle: the script reports that rate over the tail, the cycle in policy steps it gives,
and the cycle-mean error over the recorded steps with that window beside the test's (one reference cycle).

Wrote docs/evaluation/gait_sway.json (about a minute on 2 cores)::

    PYTHONPATH=. python lab/analysis/gait_sway.py --out docs/evaluation/gait_sway.json
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import torch

from tocabi_torchrl.atomic import atomic_write_text
from tocabi_torchrl.evaluation import robust
from tocabi_torchrl.evaluation.gait_test import summary_json

SHIPPED = Path(__file__).resolve().parents[2] / "assets" / "policies" / "tocabi_walk_ppo.pt"


def measure(path: Path, num_envs: int, seconds: float, tail: float) -> dict:
    test = robust.RobustTestConfig(num_envs=num_envs, seconds=seconds)
    _, cfg, env, agent = robust.checkpoint_case(path, "nominal", "cpu", test)
    trace, phase = [], []

    def actor(td):
        # The actor sees the last step's outputs (step_mdp moved them to the root): the velocity after each step.
        trace.append((robust.heading_frame_velocity(td["base_quat"], td["base_lin_vel"]), td["command"].clone()))
        td = agent.actor(td)
        phase.append(td["action"][:, -1].clamp(0.0, 1.0))  # the phase-rate action, clipped as the env clips it
        return td

    per_env = robust.run_case(actor, env, seconds, desc="gait sway")
    base = env.base_env
    vel = torch.stack([v for v, _ in trace[1:]]).double()  # (T, N, 2): after steps 1 .. T (the reset's left out)
    cmd = torch.stack([c for _, c in trace[1:]]).double()
    last = vel[-round(tail / base.dt):]
    alive = per_env["alive"]
    std = last.std(0)[alive]
    mean_err = (last.mean(0) - cmd[-1])[alive].abs()
    window = robust.gait_cycle_steps(base.motion.period, base.dt)
    cycle_err = (vel[-window:].mean(0) - cmd[-window:].mean(0))[alive].abs()
    instant = (last - cmd[-1]).norm(dim=-1).mean(0)[alive]
    # The policy's phase action runs its clock at 1 + gain·a times the reference's: its own gait cycle is shorter.
    rate = 1.0 + cfg.env.task.phase_rate_gain * torch.stack(phase)[-len(last):].double().mean()
    own = round(window / float(rate))
    by_window = {}
    for steps in sorted({own, window}):  # the cycle-mean error over the recorded steps, robots alive at the end
        tracker = robust.CycleMeanTracking(num_envs, steps)
        for v, c in zip(vel, cmd):
            tracker.update(v, c, alive)
        by_window[str(steps)] = float(tracker.per_env()[alive].mean())
    return {"policy": path.name, "num_envs": num_envs, "seconds": seconds, "tail_s": tail, "seed": robust.EVAL_SEED,
            "window_steps": window, "phase_clock_rate": float(rate), "policy_cycle_steps": own,
            "survival": float(alive.float().mean()),
            "tail": {"std_vx_mps": float(std[:, 0].mean()), "std_vy_mps": float(std[:, 1].mean()),
                     "mean_velocity_error_vx_mps": float(mean_err[:, 0].mean()),
                     "mean_velocity_error_vy_mps": float(mean_err[:, 1].mean()),
                     "instant_speed_error_mps": float(instant.mean())},
            "last_cycle": {"mean_velocity_error_vx_mps": float(cycle_err[:, 0].mean()),
                           "mean_velocity_error_vy_mps": float(cycle_err[:, 1].mean())},
            "tracking_error_by_window_mps": by_window,
            "case": {k: float(per_env[k].nanmean()) for k in ("tracking_error_mps", "instant_speed_error_mps")}}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", type=Path, default=SHIPPED,
                        help="policy checkpoint (.pt) (default: the shipped assets/policies/tocabi_walk_ppo.pt)")
    parser.add_argument("--num_envs", type=int, default=24, help="robots in the case (default: 24)")
    parser.add_argument("--seconds", type=float, default=8.0, help="length of the case [s] (default: 8)")
    parser.add_argument("--tail", type=float, default=4.0, help="seconds at the end the sway is measured over")
    parser.add_argument("--out", type=Path, help="JSON to write, must not exist yet (default: print only)")
    args = parser.parse_args(argv)
    if args.out is not None and args.out.exists():
        raise SystemExit(f"error: {args.out} exists; give another --out (results are never overwritten)")
    t0 = time.perf_counter()
    result = measure(args.policy, args.num_envs, args.seconds, args.tail)
    used = sys.argv[1:] if argv is None else argv
    git = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False)
    data = {"command": "PYTHONPATH=. python lab/analysis/gait_sway.py " + " ".join(used), "commit": git.stdout.strip(),
            "device": "cpu", "took_s": round(time.perf_counter() - t0), **result}
    text = summary_json(data)  # strict JSON: a value that does not exist (a case shorter than a cycle) is null
    print(text)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.out, text + "\n")
    return data


if __name__ == "__main__":
    main()
