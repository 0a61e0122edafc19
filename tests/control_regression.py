"""Recorded rollouts of every control mode on the C MuJoCo backend, to show that a refactor of the control path
changes no number.

``python tests/control_regression.py OUT.pt`` records them (the file in ``tests/data/`` was recorded before the
control laws moved into ``tocabi_torchrl.control``); ``tests/test_control_regression.py`` replays the same actions
and compares bit for bit.
"""

from __future__ import annotations

import dataclasses
import sys

import torch

#: name -> (training preset whose env and transforms are used, env.control overrides, torque assist β or None)
CASES = {
    "default": ("default", {}, None),
    "pd": ("default", {"mode": "pd"}, None),
    "torque": ("reference", {}, None),
    "torque_assist": ("torque_ideal", {"torque_assist": True}, 0.4),
    "model_based": ("model_based_ideal", {}, None),
}
NUM_ENVS, STEPS, EPISODE_STEPS, SEED = 4, 24, 10, 3
#: What is recorded after every step (the transformed env's keys under "next").
KEYS = ("observation", "reward", "done", "joint_pos", "joint_vel", "applied_action", "leg_torque", "base_pos")


def rollout(case: str) -> dict[str, torch.Tensor]:
    """(STEPS, NUM_ENVS, ...) float32 stacks of :data:`KEYS` for one case, from fixed actions."""
    from tocabi_torchrl import make_env
    from tocabi_torchrl.config import preset_tree

    preset, control, beta = CASES[case]
    tree = preset_tree(preset)
    env_cfg = dataclasses.replace(tree.env, control=dataclasses.replace(tree.env.control, **control))
    env_cfg = dataclasses.replace(env_cfg, task=dataclasses.replace(env_cfg.task, max_episode_steps=EPISODE_STEPS))
    env = make_env(num_envs=NUM_ENVS, device="cpu", config=env_cfg, transforms=tree.transforms, seed=SEED)
    if beta is not None:
        env.base_env.set_torque_assist(beta)
    gen = torch.Generator().manual_seed(SEED)
    td = env.reset()
    out: dict[str, list[torch.Tensor]] = {k: [] for k in KEYS}
    for _ in range(STEPS):
        legs = (torch.rand(NUM_ENVS, 12, generator=gen) * 2 - 1) * 0.3
        rate = torch.rand(NUM_ENVS, 1, generator=gen)
        td["action"] = torch.cat((legs, rate), dim=-1)
        td, td_next = env.step_and_maybe_reset(td)
        nxt = td["next"]
        for k in KEYS:
            out[k].append(nxt[k].to(torch.float32).clone())
        td = td_next
    env.close()
    return {k: torch.stack(v) for k, v in out.items()}


if __name__ == "__main__":
    torch.save({case: rollout(case) for case in CASES}, sys.argv[1])
