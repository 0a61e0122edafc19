"""The ``model_based`` control mode's feed-forward law: joint-space computed torque on the legs from the simulator's
own dynamics, batched on the device and free of host synchronisation (it runs inside the captured step).

The law (per env, the 12 leg joints L, from the pre-step state)::

    τ_ff = M_LL(q) · (q̈_ref + Kp·(q_ref − q) + Kd·(q̇_ref − q̇)) + c_L(q, q̇)        Kp = ω², Kd = 2ζω
    τ    = clip(τ_ff + g · a[:12], ±limit)       (the policy's residual; g = ``control.mb_residual_gain``)

Where each term comes from:

- ``M_LL`` is the 12 × 12 leg block of the joint-space inertia M(q) (armature included) and ``c_L`` the leg entries
  of ``qfrc_bias`` (gravity, Coriolis and centrifugal forces), both from the forward pass that ends every
  :meth:`~tocabi_torchrl.sim.SimBackend.step` and :meth:`~tocabi_torchrl.sim.SimBackend.reset`: they describe the
  state the step starts from, so no extra forward pass is needed (the backends' ``mass_matrix`` and ``qfrc_bias``;
  the block is gathered from MuJoCo's sparse layout by :class:`~tocabi_torchrl.sim.inertia.DenseBlock`).
- ``q`` and ``q̇`` are the leg joints' ``qpos[7:19]`` and ``qvel[6:18]``.
- ``q_ref`` is the reference walk at the pre-step clock (``ReferenceMotion.joint_targets``, the targets every mode
  uses). ``q̇_ref`` and ``q̈_ref`` are per-row central differences of the reference over ±``mb_ref_window``
  (:meth:`ReferenceMotion.joint_derivatives`), read at the same clock with the same interpolation, times the step's
  phase rate ``r = 1 + phase_rate_gain·a[12]`` and ``r²``: the reference as the policy's clock runs through it.
- ``ω`` [rad/s] and ``ζ`` are ``control.mb_omega`` / ``mb_zeta`` per joint. Multiplying the feedback by M makes
  each joint's error obey ``ë + 2ζω·ė + ω²·e = 0`` whatever its inertia, so the gains are frequencies, not
  stiffnesses that would have to follow the configuration. The torque is held for the whole control period (a
  zero-order hold at 250 Hz), so the env checks when it is built that this sampled loop is stable for every joint
  (:func:`sampled_loop_radius`).

Why this law. The robot is torque controlled and the simulator knows its dynamics exactly, so the cheapest good
prior is the textbook computed-torque (inverse dynamics) controller: for a leg in the air it makes the reference
walk the solution of the closed loop, and it compensates the leg's own gravity and velocity forces, which a plain PD
(the ``torque_assist`` PD, the position servos of the PD modes) leaves as a tracking error. What it leaves out, on
purpose, goes to the residual ``g·a``, i.e. to the policy:

- **The floating-base coupling** ``M_LB·a_base`` (the legs' share of the pelvis's acceleration). The base
  acceleration is not measured before the step and depends on the contact forces of the same step; estimating it
  would need the full constrained dynamics (a QP or the solver's own solution), which is the next step's result.
- **Contact forces** ``J_Lᵀ·f``: in stance the leg carries the body's weight through the foot, which ``c_L`` (the
  gravity of the bodies below each leg joint only) does not include. How the load is shared between the feet is a
  choice of the gait, which the policy makes; the stiffness ``M_LL·ω²`` (the robot's Kp at the initial pose with
  the default ω) holds the stance leg near the reference until it does.
- Joint damping (2 N·m·s/rad) and friction loss (≤ 8.2 N·m), small next to the limits (166-333 N·m).

What it knows is privileged: under ``env.dynamics`` M and ``qfrc_bias`` are each world's drawn model (masses,
inertias, armature), and q, q̇ are the true joints, never the sensed ones (docs/concepts/controllers.md, "What the
model-based law knows").

All of it is tensor ops on preallocated buffers (the block gather, one batched 12 × 12 matrix-vector product, the
table lookups), masks instead of branches, so the mode keeps the env's step capturable as one CUDA graph.
"""

from __future__ import annotations

import mujoco
import numpy as np
import torch

from .. import robot
from ..motion import ReferenceMotion
from ..sim.inertia import DenseBlock
from .config import ControlConfig

__all__ = ["ComputedTorque", "check_settings", "sampled_loop_radius"]


def sampled_loop_radius(omega: np.ndarray, zeta: np.ndarray, dt: float) -> np.ndarray:
    """Spectral radius of the error dynamics of a unit inertia under ``ë = −ω²·e − 2ζω·ė`` sampled at the start of
    each period ``dt`` and held (zero-order hold): < 1 where the sampled loop is stable, per joint."""
    radius = []
    for w, z in zip(np.asarray(omega, float), np.asarray(zeta, float)):
        a = np.array([[1.0, dt], [0.0, 1.0]])
        b = np.array([[0.5 * dt * dt], [dt]])
        k = np.array([[w * w, 2.0 * z * w]])
        radius.append(float(np.abs(np.linalg.eigvals(a - b @ k)).max()))
    return np.array(radius)


def check_settings(control: ControlConfig, motion: ReferenceMotion, control_dt: float) -> int:
    """Check what :class:`ControlConfig.validate` cannot, the gains against the control period and the reference
    window against the motion's cycle, and return the window's half-width in rows.

    A joint with ω = 0 has no feedback (feed-forward and bias compensation only, the residual doing the rest): its
    sampled loop is a double integrator at radius exactly 1, which is allowed. Any ω > 0 must give a radius < 1.
    Raises ``ValueError`` naming the joints whose gains make the sampled loop unstable, or the longest usable window.
    """
    omega = np.asarray(control.mb_omega, dtype=np.float64)
    zeta = np.asarray(control.mb_zeta, dtype=np.float64)
    radius = sampled_loop_radius(omega, zeta, control_dt)
    unstable = [f"{robot.JOINT_NAMES[j]} (ω = {omega[j]:g} rad/s, ζ = {zeta[j]:g}: radius {radius[j]:.3f})"
                for j in range(len(omega)) if omega[j] > 0 and radius[j] >= 1.0]
    if unstable:
        raise ValueError(f"env.control.mb_omega/mb_zeta: the computed-torque loop, held for {control_dt * 1e3:g} ms "
                         f"per step, is unstable for {', '.join(unstable)}; lower ω (ω·dt well under 1), bring ζ "
                         "nearer 1, or set ω = 0 for no feedback on that joint")
    half_width = max(1, int(round(float(control.mb_ref_window) / motion.row_dt)))
    widest = motion.cycle_rows // 2 - 1
    if widest < 1:
        raise ValueError(f"the reference motion's cycle has {motion.cycle_rows} rows, too few for the model-based "
                         "law's reference window (it needs at least 4): use a motion of a whole walking cycle")
    if half_width > widest:
        raise ValueError(f"env.control.mb_ref_window {control.mb_ref_window:g} s is longer than half the reference "
                         f"cycle allows; use at most {widest * motion.row_dt:g} s (the default is 0.008 s)")
    return half_width


class ComputedTorque:
    """The feed-forward torque τ_ff of the ``model_based`` mode (see the module docstring), for ``num_envs`` worlds.

    Args:
        control: the env's :class:`ControlConfig` (``mb_omega``, ``mb_zeta``, ``mb_ref_window``).
        motion: the env's reference motion, on the env's device.
        mj_model: the simulator's compiled model (dof addresses and the inertia's sparse layout).
        num_envs: N.
        device: the env's device.
        control_dt: [s] one control period, over which the torque is held (for the stability check).

    Raises ``ValueError`` from :func:`check_settings` (unstable gains at ``control_dt``, too wide a window).
    """

    def __init__(self, control: ControlConfig, motion: ReferenceMotion, mj_model: mujoco.MjModel, num_envs: int,
                 device: torch.device, control_dt: float):
        half_width = check_settings(control, motion, control_dt)
        omega = np.asarray(control.mb_omega, dtype=np.float64)
        zeta = np.asarray(control.mb_zeta, dtype=np.float64)
        f32 = torch.float32
        self.kp = torch.as_tensor(omega**2, dtype=f32, device=device)
        self.kd = torch.as_tensor(2.0 * zeta * omega, dtype=f32, device=device)
        legs = robot.JOINT_NAMES[robot.LEGS]
        dofs = [int(mj_model.jnt_dofadr[mj_model.joint(name).id]) for name in legs]
        qadr = [int(mj_model.jnt_qposadr[mj_model.joint(name).id]) for name in legs]
        n_leg = robot.NUM_LEG_JOINTS
        if dofs != list(range(dofs[0], dofs[0] + n_leg)) or qadr != list(range(qadr[0], qadr[0] + n_leg)):
            raise ValueError("the leg joints' dofs must be contiguous in qpos and qvel (robot.JOINT_NAMES order)")
        self.dofs = slice(dofs[0], dofs[0] + n_leg)
        self.qpos = slice(qadr[0], qadr[0] + n_leg)
        self.block = DenseBlock(mj_model, dofs, num_worlds=num_envs, device=device)
        self.motion = motion
        vel, acc = motion.joint_derivatives(half_width)
        #: (R, 24) the legs' reference velocity [rad/s] then acceleration [rad/s²] per row: one table, so that one
        #: lookup (one row computation, two gathers) reads both every step.
        self.ref_vel_acc = torch.cat((vel[:, robot.LEGS], acc[:, robot.LEGS]), dim=1)
        self.half_width = half_width
        #: (N, 12) N·m, the feed-forward torque of the last call (overwritten in place).
        self.torque = torch.zeros(num_envs, n_leg, dtype=f32, device=device)

    def reference_derivatives(self, time: torch.Tensor, init_row: torch.Tensor,
                              rate: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, 12) q̇_ref [rad/s] and q̈_ref [rad/s²] at the pre-step clock, for phase rate ``rate`` (N,)."""
        r = rate.unsqueeze(-1)
        vel, acc = self.motion.interpolate(self.ref_vel_acc, time, init_row).split(robot.NUM_LEG_JOINTS, dim=1)
        return vel * r, acc * (r * r)

    def __call__(self, sim, q_ref: torch.Tensor, time: torch.Tensor, init_row: torch.Tensor,
                 rate: torch.Tensor) -> torch.Tensor:
        """τ_ff (N, 12) [N·m] from the simulator's current state (``sim``: a backend after a step/reset/forward).

        Args:
            q_ref: (N, 12) the reference leg angles at the pre-step clock [rad].
            time, init_row: (N,) the pre-step phase clock and start rows (as for ``ReferenceMotion``).
            rate: (N,) this step's phase rate ``1 + phase_rate_gain·a[12]``.

        Non-finite values (a world whose physics diverged; it terminates this step) give 0 feed-forward.
        """
        q, qd = sim.qpos[:, self.qpos], sim.qvel[:, self.dofs]
        vel, acc = self.reference_derivatives(time, init_row, rate)
        desired = acc + self.kp * (q_ref - q) + self.kd * (vel - qd)  # (N, 12) rad/s²
        inertia = self.block(sim.mass_matrix)  # (N, 12, 12)
        tau = torch.matmul(inertia, desired.unsqueeze(-1)).squeeze(-1) + sim.qfrc_bias[:, self.dofs]
        self.torque.copy_(torch.nan_to_num(tau, nan=0.0, posinf=0.0, neginf=0.0))
        return self.torque
