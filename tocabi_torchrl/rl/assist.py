"""The torque assist of the ``torque`` preset: the action space morphs from PD residuals (which learn to walk) to
torques during training, and a loss moves each step of the morph into the actor.

Why: a torque policy trained from scratch on thousands of envs settles on standing still (issue 19: 100 % survival,
2 cm forward). The assisted torque env (``TocabiWalkConfig.torque_assist``) applies
``τ = c(β)·a + β·limit·leg_assist(s)`` with ``c(β) = (1 − β)·limit + β·pd_action_scale·pd_kp``: at β = 1 the leg
actions are position residuals around the reference walk (the residual-PD preset, which learns to walk in minutes),
at β = 0 the reference's normalised torques. When β falls from β_k to β_(k+1) between two rollouts, the action that
applies the same torque in every state of the rollout is known in closed form:
``a' = (c(β_k)·a + (β_k − β_(k+1))·limit·leg_assist(s)) / c(β_(k+1))`` (with the env's action and torque clipping),
and the actor is pulled towards it: the gait stays while the action space changes under it. At β = 0 the policy
is a pure torque policy (the evaluation never uses the assist).

Two targets (``PPOConfig.assist_target``):
- ``"rollout"``: the torque the rollout's own mean applied. It keeps what the actor does, so it only moves the
  fade's small step of PD into the actor; on the H100 the gait held to β ≈ 0.1 and broke after
  (docs/training.md, runs 2 and 4).
- ``"teacher"``: the torque a frozen copy of the actor taken as the fade starts (:class:`AssistTeacher`, the β = 1
  policy plus its PD) applies in the same state: DAgger on the fading policy's own states, so the actor is taught
  the PD's whole feedback where its own copy of it fails, not only the fade's last step of it.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torch import nn

from .. import robot
from .rollout_guard import mean_over_valid

# What the absorbing loss copies into the actor (see the module docstring): a config value, defined with the config
# tree (which reads without torch) and named here too.
from ..config import ASSIST_TARGETS

__all__ = ["AssistSchedule", "AssistAbsorbLoss", "AssistTeacher", "ASSIST_TARGETS", "applied_leg_torque"]


@dataclass(frozen=True)
class AssistSchedule:
    """β of the torque assist against env steps: ``start`` until ``fade_start``, then down to 0 at ``fade_end``.

    With ``gain_ratio`` r = c(1)/c(0) > 1 (the action gain at β = 1 over that at β = 0, ``TocabiWalk.assist_gain``;
    the trainer passes the legs' geometric mean, 6.9 with the robot's gains) the fade is geometric in the gain:
    ``β(u) = start·(r^(1−u) − 1)/(r − 1)`` at fade fraction u, so (for start = 1) a leg with that ratio sees c fall by
    the same factor in every step. β falls fast while the PD still carries the gait and slowly near 0, where each step
    of β is a large relative change of c. (A linear fade broke the gait in its last sixth on the H100:
    docs/training.md.)
    ``gain_ratio`` 1 fades β linearly.
    """

    start: float
    fade_start: int
    fade_end: int
    gain_ratio: float = 1.0
    #: Env steps after ``fade_end`` over which the teacher's pull (:meth:`teacher_weight`) falls linearly to 0.
    anchor_decay: int = 0

    def __post_init__(self):
        if not self.start >= 0:
            raise ValueError(f"AssistSchedule.start must be >= 0, got {self.start!r}")
        if not 0 <= self.fade_start < self.fade_end:
            raise ValueError(f"AssistSchedule needs 0 <= fade_start < fade_end, got {self.fade_start}, {self.fade_end}")
        if not self.gain_ratio >= 1.0:
            raise ValueError(f"AssistSchedule.gain_ratio must be >= 1, got {self.gain_ratio!r}")
        if not self.anchor_decay >= 0:
            raise ValueError(f"AssistSchedule.anchor_decay must be >= 0, got {self.anchor_decay!r}")

    def __call__(self, env_steps: int) -> float:
        u = min(max((env_steps - self.fade_start) / (self.fade_end - self.fade_start), 0.0), 1.0)
        r = self.gain_ratio
        frac = 1.0 - u if r == 1.0 else (r ** (1.0 - u) - 1.0) / (r - 1.0)
        return self.start * frac

    def teacher_weight(self, env_steps: int) -> float:
        """Share (0-1) of the absorbing weight for the ``"teacher"`` target after ``env_steps``: 1 from the fade's
        start to its end, then linearly to 0 over ``anchor_decay`` steps (0 before the fade: no teacher yet)."""
        if env_steps <= self.fade_start:
            return 0.0
        if env_steps <= self.fade_end:
            return 1.0
        if self.anchor_decay <= 0:
            return 0.0
        return max(0.0, 1.0 - (env_steps - self.fade_end) / self.anchor_decay)


def applied_leg_torque(loc: torch.Tensor, leg_assist: torch.Tensor, gain: torch.Tensor, beta: torch.Tensor,
                       limits: torch.Tensor) -> torch.Tensor:
    """(…, 12) N·m, the leg torque the assisted env applies for leg actions ``loc`` (…, 12) at assist scale
    ``beta`` with action gain ``gain`` (12,) N·m: actions clipped to [-1, 1], torques to ±``limits`` (12,) N·m."""
    torque = gain * loc.clamp(-1.0, 1.0) + beta * limits * leg_assist
    return torch.maximum(torch.minimum(torque, limits), -limits)


class AssistTeacher(nn.Module):
    """A frozen copy of the actor's mean network, taken when the fade starts (:meth:`anchor`), with the β and action
    gain it acted at; :meth:`torque` is the leg torque it (with its PD) would apply in a state.

    Its state (weights, β, gain and whether it was taken) travels in checkpoints, so a resumed run keeps its teacher.
    The weights are copied in place, so a captured update step that reads them sees the copy.
    """

    def __init__(self, mean_net: nn.Module, limits: torch.Tensor):
        super().__init__()
        self.mean_net = copy.deepcopy(mean_net).requires_grad_(False)
        device = next(self.mean_net.parameters()).device
        limits = torch.as_tensor(limits, dtype=torch.float32, device=device)
        self.register_buffer("gain", limits.clone())
        self.register_buffer("beta", torch.zeros((), device=device))
        self.register_buffer("anchored", torch.zeros((), dtype=torch.bool, device=device))

    @torch.no_grad()
    def anchor(self, mean_net: nn.Module, gain: torch.Tensor, beta: float) -> None:
        """Copy ``mean_net``'s weights (the actor as it acts at assist scale ``beta``, gain ``gain`` (12,) N·m)."""
        for mine, theirs in zip(self.mean_net.parameters(), mean_net.parameters(), strict=True):
            mine.copy_(theirs)
        for mine, theirs in zip(self.mean_net.buffers(), mean_net.buffers(), strict=True):
            mine.copy_(theirs)
        self.gain.copy_(gain)
        self.beta.fill_(beta)
        self.anchored.fill_(True)

    def torque(self, observation: torch.Tensor, leg_assist: torch.Tensor, limits: torch.Tensor) -> torch.Tensor:
        """(…, 12) N·m the teacher's mean action applies in states ``observation`` (…, obs_dim) whose PD part is
        ``leg_assist`` (…, 12)."""
        with torch.no_grad():
            loc = self.mean_net(observation)[..., : limits.shape[-1]]
        return applied_leg_torque(loc, leg_assist, self.gain, self.beta, limits)


class AssistAbsorbLoss(nn.Module):
    """A PPO loss plus ``loss_absorb``, which moves one step of the assist's fade into the actor's mean.

    For each frame, the torque the rollout's mean applied at β is known: ``T = clip(c(β)·clip(loc) + β·limit·
    leg_assist, ±limit)`` (actions are clipped to [-1, 1], torques to the limits, as the env does); the target a' is
    the action nearest to ``loc`` that applies ``T`` at the next β' (:meth:`target`). ``loss_absorb = weight ·
    mean_s Σ_j (μ_θ(s)_j − a'_j)² / (2 σ_j²)`` over the 12 leg actions: the KL divergence from the Gaussian at a' (same
    σ) to the current one. ``loc`` and σ (``scale``) are the rollout's, ``leg_assist`` the env's signal of the step the
    action was taken in (``("next", "leg_assist")``). The gains, β, β' and ``weight`` are device buffers the trainer
    sets in place before each update (:meth:`set_step`; a captured update step reads them). Frames the PPO loss masks
    out (its ``loss_mask_key``) are left out here too. While ``weight`` is 0 (before the fade, and once the teacher's
    pull has decayed) the term is not computed: ``loss_absorb`` is 0 and the gradients are those the zeroed term would
    give, without the actor's second forward and the teacher's (set it through :meth:`set_step`, which also switches
    :attr:`graph_key`).

    With a ``teacher``, ``T`` is instead the torque the teacher applies in the frame's state
    (:meth:`AssistTeacher.torque`): the actor is pulled towards the action that applies it at β'.

    Args:
        ppo_loss: the PPO loss (e.g. TorchRL's ``ClipPPOLoss``); its outputs are passed through.
        head: the actor's :class:`~tocabi_torchrl.rl.actors.GaussianHead` (shares its parameters with the actor).
        limits: (12,) N·m, the leg torque limits (``TocabiWalk.leg_torque_limits``).
        teacher: the ``"teacher"`` target's :class:`AssistTeacher`, or None for the ``"rollout"`` target.
    """

    def __init__(self, ppo_loss: nn.Module, head: nn.Module, limits: torch.Tensor,
                 teacher: AssistTeacher | None = None):
        super().__init__()
        self.ppo_loss = ppo_loss
        self.head = head
        self.teacher = teacher
        device = next(head.parameters()).device
        self.register_buffer("limits", torch.as_tensor(limits, dtype=torch.float32, device=device).clone())
        self.register_buffer("gain_now", self.limits.clone())
        self.register_buffer("gain_next", self.limits.clone())
        self.register_buffer("beta_now", torch.zeros((), device=device))
        self.register_buffer("beta_next", torch.zeros((), device=device))
        self.register_buffer("weight", torch.zeros((), device=device))
        self._active = False  # weight > 0: see graph_key

    @property
    def graph_key(self) -> bool:
        """Whether the term is computed (its weight > 0, :meth:`set_step`): the two cases run different operations,
        so a captured update step (:class:`~tocabi_torchrl.rl.update_step.MinibatchStep`) captures again when this
        changes."""
        return self._active

    def set_step(self, gain_now: torch.Tensor, gain_next: torch.Tensor, beta_now: float, beta_next: float,
                 weight: float) -> None:
        """Targets for an update between a rollout at β = ``beta_now`` (action gain ``gain_now``, (12,) N·m per
        unit action, ``TocabiWalk.assist_gain``) and the next at ``beta_next`` (``gain_next``); ``weight`` 0 switches
        the term off."""
        self.gain_now.copy_(gain_now)
        self.gain_next.copy_(gain_next)
        self.beta_now.fill_(beta_now)
        self.beta_next.fill_(beta_next)
        self.weight.fill_(weight)
        self._active = float(weight) > 0.0

    def target(self, loc: torch.Tensor, leg_assist: torch.Tensor, torque: torch.Tensor | None = None) -> torch.Tensor:
        """(…, 12) the action at β' nearest to the rollout's mean ``loc`` (…, 12) that applies ``torque`` (…, 12)
        N·m, by default the torque ``loc`` applied at β.

        The env clips actions to [-1, 1] and torques to the limits, so a whole interval of actions may apply the same
        torque: the target is ``loc`` projected onto that interval. A frame whose torque stays saturated at β' (or
        whose action stays beyond the box) is not pulled at all; pulling it to the edge of saturation moved every
        saturated frame at once and broke the gait as the fade began on the H100 (KL 0.87 in the first fading
        update). Where no action applies the torque at β', the target is the box edge on its side."""
        limits = self.limits
        assist = limits * leg_assist
        if torque is None:
            torque = applied_leg_torque(loc, leg_assist, self.gain_now, self.beta_now, limits)
        exact = (torque - self.beta_next * assist) / self.gain_next
        # Every action below (above) the interval applies the same torque when the torque sits at its lower (upper)
        # limit or when even the box edge does not reach it.
        open_low = (torque <= -limits) | (exact <= -1.0)
        open_high = (torque >= limits) | (exact >= 1.0)
        low = torch.where(open_low, -torch.inf, exact.clamp(max=1.0))
        high = torch.where(open_high, torch.inf, exact.clamp(min=-1.0))
        return torch.minimum(torch.maximum(loc, low), high)

    @property
    def in_keys(self) -> list:
        return [*self.ppo_loss.in_keys, "loc", "scale", ("next", "leg_assist")]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        out = self.ppo_loss(td)
        if not self._active:
            # At weight 0 the term is 0 and adds exact zeros to every gradient (its distances are finite): the actor's
            # second forward and the teacher's (about a quarter of the robust preset's update) are skipped, the update
            # unchanged.
            out["loss_absorb"] = torch.zeros_like(self.weight)
            return out
        legs = robot.NUM_LEG_JOINTS
        loc, _ = self.head(td["observation"])
        # Finite before squaring: a broken frame is masked below, but 0 × NaN would still reach the gradients, and so
        # would 0 × inf from an infinite rollout mean (as the float32 maximum, its squared distance overflows).
        leg_assist = td["next", "leg_assist"]
        torque = None if self.teacher is None else self.teacher.torque(td["observation"], leg_assist, self.limits)
        target = torch.nan_to_num(self.target(td["loc"][..., :legs], leg_assist, torque), nan=0.0, posinf=0.0,
                                  neginf=0.0)
        scale = torch.nan_to_num(td["scale"][..., :legs], nan=1.0).clamp_min(1e-6)
        kl = 0.5 * ((loc[..., :legs] - target) / scale).pow(2).sum(-1)
        # Frames the rollout guard marked unusable (a faulted world) pull the actor nowhere, as in the PPO terms.
        out["loss_absorb"] = self.weight * mean_over_valid(kl, td, getattr(self.ppo_loss, "loss_mask_key", None))
        return out
