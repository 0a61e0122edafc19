"""Torque laws: commands in N·m held for the policy step."""

from __future__ import annotations

import torch

from .base import ControlContext, ControlInput, Controller
from .joint_pd import _finite, _vector

__all__ = ["DirectTorque", "AssistedTorque", "HeldPD", "clip_torque"]


def clip_torque(tau: torch.Tensor, limits: torch.Tensor) -> torch.Tensor:
    """``tau`` clipped to ``±limits`` (the same arithmetic everywhere a law saturates)."""
    return torch.maximum(torch.minimum(tau, limits), -limits)


class DirectTorque(Controller):
    """Torque = action × the joint's torque limit (the reference's action space)."""

    def __init__(self, action_dim: int = 12):
        self.action_dim = action_dim

    def setup(self, ctx: ControlContext) -> None:
        super().setup(ctx)
        self._limits = ctx.torque_limits

    def compute(self, inp: ControlInput) -> torch.Tensor:
        return inp.action * self._limits


class _SensedPD:
    """A PD at the policy rate, on the reference plus ``scale`` × the action, that may read the joint positions the
    robot senses (``q + q_offset``); its torque over the limits is the ``applied_action``. The gains' and scale's
    checks name the law's class."""

    def __init__(self, kp, kv, scale: float, action_dim: int = 12):
        self.kp, self.kv = kp, kv
        self.scale = _finite(scale, f"{type(self).__name__} scale [rad per action unit]")
        self.action_dim = action_dim

    def _setup_pd(self, ctx: ControlContext) -> None:
        """The limits and gains on the device, and a zero offset (call from ``setup``)."""
        j, dev, name = len(ctx.joint_ids), ctx.device, type(self).__name__
        self._limits = ctx.torque_limits
        self._kp = _vector(self.kp, j, dev, f"{name} kp [N·m/rad]", minimum=0.0)
        self._kv = _vector(self.kv, j, dev, f"{name} kv [N·m·s/rad]", minimum=0.0)
        #: (N, J) rad added to the measured joint positions the PD reads (the sensed encoder bias; 0 = true).
        self.q_offset = torch.zeros(ctx.num_envs, j, dtype=torch.float32, device=dev)

    def applied_action(self, inp: ControlInput, command: torch.Tensor) -> torch.Tensor:
        return command / self._limits

    def set_q_offset(self, mask: torch.Tensor, offset: torch.Tensor) -> None:
        """Worlds ``mask`` (N,) bool read their joint positions as ``q + offset`` ((N, J) rad) from now on (in place,
        so a captured step follows it)."""
        torch.where(mask.unsqueeze(-1), offset.to(self.q_offset.dtype), self.q_offset, out=self.q_offset)


class AssistedTorque(_SensedPD, Controller):
    """The torque preset's morph from PD residuals to torques (``env.control.torque_assist``):
    ``clip((1 − β)·a·limit + β·(kp·(q_ref + scale·a − q − b) − kv·q̇), ±limit)`` from the pre-step state.

    β is the device scalar :attr:`assist_scale` (:meth:`set_beta`), changed in place so a captured step follows it.
    ``b`` (:attr:`q_offset`, (N, J) rad, 0 unless set) is each world's encoder bias when the PD reads the joint
    positions the policy senses (:meth:`set_q_offset`, written by the SensorNoise transform when the env's
    ``sense_assist_joints`` is on, ``ppo.assist_pd_sensed``): a PD on the true positions is
    feedback the policy, whose encoders are biased, cannot copy when the assist fades.
    Records the action-independent part of the PD over the limits as the ``leg_assist`` signal, and reports the
    applied torque over the limits as ``applied_action`` (the action itself at β = 0).

    Args:
        kp, kv: (J,) PD gains [N·m/rad], [N·m·s/rad]; scale: the residual range per unit action [rad].
    """

    def setup(self, ctx: ControlContext) -> None:
        super().setup(ctx)
        self._setup_pd(ctx)
        n, j, dev = ctx.num_envs, len(ctx.joint_ids), ctx.device
        #: β, a 0-d float32 device scalar.
        self.assist_scale = torch.zeros((), dtype=torch.float32, device=dev)
        self._gain = self.gain(0.0).clone()  # (J,) N·m per unit action at assist_scale
        #: (N, J) the action-independent PD over the limits, from the last step's pre-step state.
        self.leg_assist = torch.zeros(n, j, dtype=torch.float32, device=dev)

    def gain(self, beta: float | torch.Tensor) -> torch.Tensor:
        """(J,) N·m per unit action at β: ``(1 − β)·limit + β·scale·kp``."""
        return (1.0 - beta) * self._limits + beta * self.scale * self._kp

    def set_beta(self, beta: float) -> None:
        self.assist_scale.fill_(float(beta))
        self._gain.copy_(self.gain(float(beta)))

    def compute(self, inp: ControlInput) -> torch.Tensor:
        self.leg_assist.copy_((self._kp * (inp.q_ref - inp.q - self.q_offset) - self._kv * inp.qd) / self._limits)
        total = self._gain * inp.action + self.assist_scale * self.leg_assist * self._limits
        return clip_torque(total, self._limits)

    def reset(self, mask: torch.Tensor) -> None:
        self.leg_assist.masked_fill_(mask.unsqueeze(-1), 0.0)

    def signals(self) -> dict[str, torch.Tensor]:
        return {"leg_assist": self.leg_assist}


class HeldPD(_SensedPD, Controller):
    """PD residuals on the reference walk, computed as torques at the policy rate (``env.control.mode``
    ``"pd_held"``): ``clip(kp·(q_ref + scale·a − q − b) − kv·q̇, ±limit)`` from the pre-step state, held for the
    step's substeps like a torque action, so the actuator layer (delay, motor constant, friction) acts on it.

    The torque assist's law at β = 1 (:class:`AssistedTorque`), the action space the torque preset learns in before
    its fade, as a law of its own that never fades: a ``pd_reference`` servo tracks the same target (clipped to the
    joint range there, not here) inside every 0.5 ms substep. ``b`` (:attr:`q_offset`, (N, J) rad) is each world's
    leg encoder bias: on by default, the law reads the joint positions the robot senses
    (``TocabiWalk.sense_assist_joints``; the SensorNoise transform writes it), as it would on the robot. The
    ``applied_action`` signal (observation history, torque rewards) is the applied torque over the limits.

    Args:
        kp, kv: (J,) PD gains [N·m/rad], [N·m·s/rad]; scale: the residual range per unit action [rad].

    >>> import torch
    >>> from tocabi_torchrl.control import ControlContext, ControlInput, HeldPD
    >>> law = HeldPD([100.0], [1.0], 0.5, action_dim=1)
    >>> law.setup(ControlContext(num_envs=2, device=torch.device("cpu"), joint_ids=[0],
    ...                          joint_range=torch.tensor([[-1.0, 1.0]]), torque_limits=torch.tensor([30.0])))
    >>> q = torch.zeros(2, 1)
    >>> law.compute(ControlInput(action=torch.tensor([[0.1], [1.0]]), q=q, qd=q, q_ref=q)).tolist()  # 5 N·m; clipped
    [[5.0], [30.0]]
    """

    def setup(self, ctx: ControlContext) -> None:
        super().setup(ctx)
        self._setup_pd(ctx)

    def compute(self, inp: ControlInput) -> torch.Tensor:
        target = inp.q_ref + self.scale * inp.action
        return clip_torque(self._kp * (target - inp.q - self.q_offset) - self._kv * inp.qd, self._limits)
