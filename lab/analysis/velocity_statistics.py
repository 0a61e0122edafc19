"""Mean and variance of the pelvis velocity a walking policy meets: where the ``base_vel`` observation's fixed
statistics come from (``tocabi_torchrl/transforms/normalize.py``, ``_BASE_VEL_MEAN``/``_BASE_VEL_VAR``).

The policy walks on C MuJoCo, on the gait tests' nominal robot, at each of a few fixed commands; the first
``--skip`` policy steps of each command (the start) are left out. Printed: the mean and variance over every robot
and kept step of ``base_lin_vel`` (x, y, z [m/s]) and ``base_ang_vel`` (x, y, z [rad/s]), pelvis frame. The committed
statistics are those of the shipped robust policy, rounded (2026-12-06, 2 cores of an Intel Xeon, about 30 s)::

    PYTHONPATH=. python lab/analysis/velocity_statistics.py --policy assets/policies/tocabi_walk_robust.pt
"""

from __future__ import annotations

import argparse

#: The commands walked [m/s] (vx, vy): standing, slow and full forward, and forward with each sideways sign.
COMMANDS = ((0.0, 0.0), (0.25, 0.0), (0.5, 0.0), (0.4, 0.15), (0.4, -0.15))


def velocity_statistics(policy: str, num_envs: int = 8, steps: int = 750, skip: int = 100,
                        commands=COMMANDS) -> tuple[list[float], list[float]]:
    """(mean, variance), six values each (linear x, y, z, angular x, y, z), of the pelvis velocity over
    ``num_envs`` robots x (``steps`` - ``skip`` - 1) policy steps per command."""
    import torch
    from torchrl.envs.utils import step_mdp

    from tocabi_torchrl.evaluation.record import load_policy

    values = []
    for command in commands:
        loaded = load_policy(policy, num_envs=num_envs, device="cpu", command=command, backend="mujoco",
                             nominal=True)
        td = loaded.env.reset()
        with torch.no_grad():
            for i in range(steps):
                td = loaded.env.step(loaded.agent.actor(td))
                if i > skip:
                    values.append(torch.cat([td["next", "base_lin_vel"], td["next", "base_ang_vel"]], -1))
                td = step_mdp(td)
    v = torch.cat(values)
    return v.mean(0).tolist(), v.var(0).tolist()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", required=True, help="a checkpoint or policy .pt file")
    parser.add_argument("--num_envs", type=int, default=8, help="robots per command")
    parser.add_argument("--steps", type=int, default=750, help="policy steps per command (4 ms each)")
    parser.add_argument("--skip", type=int, default=100, help="first policy steps of each command left out")
    args = parser.parse_args(argv)
    mean, var = velocity_statistics(args.policy, args.num_envs, args.steps, args.skip)
    print("mean", [round(x, 4) for x in mean])
    print("var", [round(x, 5) for x in var])


if __name__ == "__main__":
    main()
