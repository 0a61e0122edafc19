"""The torque assist of the ``torque`` preset: a reference-tracking PD added to the policy's leg torques during
training, faded to zero, and the loss that moves each faded slice of it into the actor.

Why: a torque policy trained from scratch on thousands of envs settles on standing still (issue 19: 100 % survival,
2 cm forward). With the assist at full scale (β = 1) the torque env behaves like the residual PD preset, which learns
to walk in minutes. Fading β alone would ask PPO to rediscover, from the reward, the feedback the PD gave. Instead,
when β falls from β_k to β_(k+1) between two rollouts, the missing torque ``(β_k − β_(k+1)) · leg_assist(s)`` is known
for every state of the rollout, so the actor is pulled towards ``loc_k(s) + (β_k − β_(k+1)) · leg_assist(s)``: the
applied torque, and with it the gait, stays the same while the PD's share moves into the network. At β = 0 the
policy is a pure torque policy (the evaluation never uses the assist).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torch import nn

from .. import robot

__all__ = ["AssistSchedule", "AssistAbsorbLoss"]


@dataclass(frozen=True)
class AssistSchedule:
    """β of the torque assist against env steps: ``start`` until ``fade_start``, linear to 0 at ``fade_end``."""

    start: float
    fade_start: int
    fade_end: int

    def __post_init__(self):
        if not self.start >= 0:
            raise ValueError(f"AssistSchedule.start must be >= 0, got {self.start!r}")
        if not 0 <= self.fade_start < self.fade_end:
            raise ValueError(f"AssistSchedule needs 0 <= fade_start < fade_end, got {self.fade_start}, {self.fade_end}")

    def __call__(self, env_steps: int) -> float:
        frac = (env_steps - self.fade_start) / (self.fade_end - self.fade_start)
        return self.start * (1.0 - min(max(frac, 0.0), 1.0))


class AssistAbsorbLoss(nn.Module):
    """A PPO loss plus ``loss_absorb``, which moves the removed part of the assist into the actor's mean.

    ``loss_absorb = weight · mean_s Σ_j (μ_θ(s)_j − loc_j − delta · leg_assist_j)² / (2 σ_j²)`` over the 12 leg
    actions, i.e. the KL divergence from the Gaussian the actor should now be (the rollout's mean shifted by the
    faded assist, same σ) to the current one. ``loc`` and σ (``scale``) are the rollout's, ``leg_assist`` the env's
    signal of the step the action was taken in (``("next", "leg_assist")``). ``delta`` (β_k − β_(k+1)) and ``weight``
    are device scalars the trainer sets in place before each update (a captured update step reads them).

    Args:
        ppo_loss: the PPO loss (e.g. TorchRL's ``ClipPPOLoss``); its outputs are passed through.
        head: the actor's :class:`~tocabi_torchrl.rl.actors.GaussianHead` (shares its parameters with the actor).
    """

    def __init__(self, ppo_loss: nn.Module, head: nn.Module):
        super().__init__()
        self.ppo_loss = ppo_loss
        self.head = head
        device = next(head.parameters()).device
        self.register_buffer("delta", torch.zeros((), device=device))
        self.register_buffer("weight", torch.zeros((), device=device))

    @property
    def in_keys(self) -> list:
        return [*self.ppo_loss.in_keys, "loc", "scale", ("next", "leg_assist")]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        out = self.ppo_loss(td)
        legs = robot.NUM_LEG_JOINTS
        loc, _ = self.head(td["observation"])
        target = td["loc"][..., :legs] + self.delta * td["next", "leg_assist"]
        kl = 0.5 * ((loc[..., :legs] - target) / td["scale"][..., :legs]).pow(2).sum(-1)
        # Frames the rollout guard marked unusable (a faulted world) pull the actor nowhere, as in the PPO terms.
        mask_key = getattr(self.ppo_loss, "loss_mask_key", None)
        if mask_key is not None and mask_key in td.keys():
            valid = td[mask_key].reshape(kl.shape)
            kl = torch.where(valid, torch.nan_to_num(kl), 0.0).sum() / valid.sum().clamp_min(1)
        else:
            kl = kl.mean()
        out["loss_absorb"] = self.weight * kl
        return out
