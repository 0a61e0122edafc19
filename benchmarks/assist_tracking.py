"""Does a leg PD at the 250 Hz policy rate track the reference walk like the residual-PD preset's 2 kHz servo?

    python benchmarks/assist_tracking.py            # C MuJoCo on the CPU, ~1-2 minutes on 2 cores

The torque preset's assist at β = 1 is a PD on the legs computed once per policy step from the pre-step state and
held for the 8 physics substeps; ``pd_reference`` runs MuJoCo position servos inside every substep. Both use the
robot's gains. With a zero action (no balance feedback) each env tracks the reference walk until the robot falls;
this reports, per controller, the mean number of steps before termination and the mean leg tracking error while
alive. Writes ``docs/training/torque/assist_tracking.json``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
from tensordict import TensorDict

from tocabi_torchrl import robot
from tocabi_torchrl.envs import TocabiWalk

GAINS = {"pd_kp": tuple(robot.LEG_KP), "pd_kv": tuple(robot.LEG_KV)}
CONTROLLERS = {
    "pd_reference (servo inside every 0.5 ms substep)": {"control_mode": "pd_reference"},
    "torque + assist at beta = 1 (PD once per 4 ms policy step)": {"control_mode": "torque", "torque_assist": True},
}


def track(num_envs: int, steps: int, seed: int, **env_kw) -> dict:
    """Mean steps alive and mean |q − q_ref| over the legs while alive, zero action, C MuJoCo on the CPU."""
    env = TocabiWalk(num_envs=num_envs, device="cpu", backend="mujoco", seed=seed, **GAINS, **env_kw)
    env.reset()
    if env.cfg.torque_assist:
        env.set_torque_assist(1.0)
    td = TensorDict({"action": torch.zeros(num_envs, 13)}, batch_size=[num_envs])
    alive = torch.ones(num_envs, dtype=torch.bool)
    life, err_sum = torch.zeros(num_envs), torch.zeros(num_envs)
    for _ in range(steps):
        out = env.step(td)["next"]
        alive &= ~out["terminated"].squeeze(-1)
        life += alive.float()
        err_sum += alive.float() * (out["joint_pos"][:, :12] - out["ref_joint_pos"][:, :12]).abs().mean(-1)
        if not alive.any():
            break
    return {"mean_steps_alive": float(life.mean()), "mean_leg_error_rad": float(err_sum.sum() / life.sum())}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--num_envs", type=int, default=16)
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="docs/training/torque/assist_tracking.json")
    args = parser.parse_args(argv)
    t0 = time.time()
    results = {name: track(args.num_envs, args.steps, args.seed, **kw) for name, kw in CONTROLLERS.items()}
    record = {"command": "python benchmarks/assist_tracking.py", "date": time.strftime("%Y-%m-%d"),
              "num_envs": args.num_envs, "max_steps": args.steps, "results": results}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(record, indent=2))
    for name, r in results.items():
        print(f"{name}: {r['mean_steps_alive']:.0f} steps alive, leg error {r['mean_leg_error_rad']:.4f} rad")
    print(f"[{time.time() - t0:.0f} s] -> {args.out}")


if __name__ == "__main__":
    main()
