"""A residual torque on a feed-forward law: the ``model_based`` mode's ``clip(τ_ff + g·a, ±limit)``."""

from __future__ import annotations

from typing import Callable

import torch

from .base import ControlContext, ControlInput, Controller
from .joint_pd import _vector
from .torque import clip_torque

__all__ = ["ComputedTorqueResidual"]


class ComputedTorqueResidual(Controller):
    """Torque ``clip(τ_ff + g·a, ±limit)``: a feed-forward law τ_ff (N, J) [N·m] from the pre-step state plus the
    policy's residual, ``g`` [N·m per action unit] per joint.

    Args:
        gain: (J,) the residual gain g.
        make_law: builds the feed-forward law from the :class:`ControlContext`, once; the law is called as
            ``law(sim, q_ref, time, init_row, rate)`` and returns τ_ff (the env's is
            :class:`tocabi_torchrl.envs.model_based.ComputedTorque`, the computed-torque law of the reference walk).

    Records τ_ff as the ``leg_feedforward`` signal and reports the applied torque over the limits as
    ``applied_action``, as torque mode would see it.
    """

    def __init__(self, gain, make_law: Callable[[ControlContext], Callable[..., torch.Tensor]], action_dim: int = 12):
        self.gain, self.make_law, self.action_dim = gain, make_law, action_dim

    def setup(self, ctx: ControlContext) -> None:
        super().setup(ctx)
        self.law = self.make_law(ctx)
        self._gain = _vector(self.gain, len(ctx.joint_ids), ctx.device,
                             "ComputedTorqueResidual gain [N·m per action unit]", minimum=0.0)
        self._limits = ctx.torque_limits
        #: (N, J) τ_ff of the last step [N·m].
        self.leg_feedforward = torch.zeros(ctx.num_envs, len(ctx.joint_ids), dtype=torch.float32, device=ctx.device)

    def compute(self, inp: ControlInput) -> torch.Tensor:
        tau_ff = self.law(self.ctx.sim, inp.q_ref, inp.time, inp.init_row, inp.rate)
        self.leg_feedforward.copy_(tau_ff)
        return clip_torque(tau_ff + self._gain * inp.action, self._limits)

    def applied_action(self, inp: ControlInput, command: torch.Tensor) -> torch.Tensor:
        return command / self._limits

    def reset(self, mask: torch.Tensor) -> None:
        self.leg_feedforward.masked_fill_(mask.unsqueeze(-1), 0.0)

    def signals(self) -> dict[str, torch.Tensor]:
        return {"leg_feedforward": self.leg_feedforward}
