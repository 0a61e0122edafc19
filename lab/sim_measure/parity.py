"""Engine parity: the same TOCABI trajectory in C MuJoCo (float64) and mujoco-warp (float32), step by step.

Both backends get the same compiled model (with the contact sensors), the same initial state (``robot.INIT_QPOS`` at
rest) and the same controls rule: legs PD-held on the initial pose with the robot's gains (``robot.LEG_KP``/``LEG_KV``,
computed once per policy step from each engine's own state, as a policy would) plus small random torques drawn once
from a fixed seed, upper body on its position servos. The divergence after each policy step is what float32 vs
float64 and the two engines' solver implementations add up to. Used by ``tests/lab/test_engine_parity.py``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from tocabi_torchrl import robot
from tocabi_torchrl.sim.config import SimConfig
from tocabi_torchrl.sim.mujoco_backend import MujocoSim
from tocabi_torchrl.sim.views import SimViews

__all__ = ["ParityTrace", "engine_parity"]

@dataclass
class ParityTrace:
    """Per policy step k = 1..steps (arrays of length ``steps``).

    Attributes:
        max_joint_diff: max over the 33 joints of |q_warp - q_mujoco| [rad].
        base_pos_diff: |base position difference| [m].
        foot_contact_mujoco, foot_contact_warp: (steps, 2) bool, [left, right].
        foot_force_z_mujoco, foot_force_z_warp: (steps, 2) foot F/T z force [N].
    """

    max_joint_diff: np.ndarray
    base_pos_diff: np.ndarray
    foot_contact_mujoco: np.ndarray
    foot_contact_warp: np.ndarray
    foot_force_z_mujoco: np.ndarray
    foot_force_z_warp: np.ndarray

    @property
    def contact_agreement(self) -> np.ndarray:
        """(steps,) bool: both feet's contact flags agree."""
        return (self.foot_contact_mujoco == self.foot_contact_warp).all(axis=1)


def _pd_legs(sim: SimViews, perturbation: torch.Tensor) -> torch.Tensor:
    kp = torch.as_tensor(robot.LEG_KP, dtype=torch.float32)
    kv = torch.as_tensor(robot.LEG_KV, dtype=torch.float32)
    q0 = torch.as_tensor(robot.INIT_JOINT_POS[robot.LEGS], dtype=torch.float32)
    return kp * (q0 - sim.qpos[:, 7:][:, robot.LEGS]) - kv * sim.qvel[:, 6:][:, robot.LEGS] + perturbation


def engine_parity(
    steps: int = 25, seed: int = 0, perturbation: float = 0.02, drop: float = 0.0, warp_device: str = "cpu"
) -> ParityTrace:
    """Run both engines ``steps`` policy steps (8 substeps each) side by side and record their divergence.

    Args:
        steps: policy steps.
        seed: seed of the random leg torques.
        perturbation: their half-range as a fraction of each joint's torque limit (uniform).
        drop: start the robot this much higher [m] (the feet then touch down during the run, so the contact flags
            change at a time both engines must agree on).
        warp_device: where mujoco-warp runs (``"cpu"``: warp's CPU device, compiles its kernels once).
    """
    from tocabi_torchrl.sim.warp_backend import WarpSim  # imported here: the C side alone needs no warp

    sims = (MujocoSim(SimConfig(num_worlds=1, threads=1)), WarpSim(SimConfig(num_worlds=1, device=warp_device)))
    rng = np.random.default_rng(seed)
    limits = np.asarray(robot.LEG_TORQUE_LIMITS)
    draws = rng.uniform(-1, 1, (steps, robot.NUM_LEG_JOINTS))
    noise = torch.as_tensor(draws * perturbation * limits, dtype=torch.float32)
    ctrl0 = torch.zeros(1, robot.NUM_JOINTS)
    ctrl0[:, robot.UPPER_BODY] = torch.as_tensor(robot.INIT_JOINT_POS[robot.UPPER_BODY])
    qpos0 = torch.as_tensor(robot.INIT_QPOS, dtype=torch.float32)
    qpos0[2] += drop
    rows: list[list] = [[] for _ in range(6)]
    for s in sims:
        s.reset(torch.ones(1, dtype=torch.bool), qpos0.to(s.device), torch.zeros(s.nv, device=s.device),
                ctrl0.to(s.device))
    for k in range(steps):
        for s in sims:
            legs = _pd_legs(_Host(s), noise[k : k + 1])
            s.ctrl[:, robot.LEGS] = legs.to(s.device)
            s.step()
        c, w = (_Host(s) for s in sims)
        rows[0].append(float((w.qpos[0, 7:] - c.qpos[0, 7:]).abs().max()))
        rows[1].append(float((w.qpos[0, :3] - c.qpos[0, :3]).norm()))
        rows[2].append(c.foot_contact[0].numpy())
        rows[3].append(w.foot_contact[0].numpy())
        rows[4].append(c.foot_force[0, :, 2].numpy())
        rows[5].append(w.foot_force[0, :, 2].numpy())
    return ParityTrace(*(np.array(r) for r in rows))


class _Host:
    """The few tensors parity reads, on the host (mujoco-warp may run on CUDA)."""

    def __init__(self, sim: SimViews):
        # Copies (``.cpu()`` of a CPU tensor is the tensor itself): the simulator overwrites its buffers every step.
        self.qpos, self.qvel = sim.qpos.cpu().clone(), sim.qvel.cpu().clone()
        self.foot_contact, self.foot_force = sim.foot_contact.cpu().clone(), sim.foot_force.cpu().clone()
