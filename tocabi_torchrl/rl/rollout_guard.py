"""Keep broken frames of a rollout out of the PPO update, so one bad world cannot poison every world's update.

The env keeps its outputs finite (a world whose physics fails terminates, its signals are zeroed, see
``TocabiWalk._observe``), but a frame can still be unusable: a non-finite observation or reward from a custom env or
transform, or an action that is not a sample of the stored action distribution (a NaN action, or ±1e6 from a wrapped
or broken policy). One such frame makes the loss of the whole mini-batch NaN (the advantage is normalised over the
batch; the log-probability ratio of ±1e6 loses all float32 precision), and the next optimiser step writes NaN into
every parameter.

:func:`guard_rollout` marks each frame valid or not in ``VALID_KEY`` and makes the invalid frames harmless: finite
observations and reward 0, the action replaced by the distribution's mean with its log-probability, so every loss
term stays finite; the loss leaves them out through TorchRL's loss mask (``loss_module.loss_mask_key = VALID_KEY``),
and each mini-batch's advantage normalisation through the same mask under the key it reads
(:func:`~tocabi_torchrl.rl.trainer.estimate_advantages`). The update's ``kl_approx`` and ``clip_fraction``, which the
KL-adaptive learning rate reads, are means over the usable frames too (:class:`GuardedClipPPOLoss`).
Masks and ``torch.where`` only: no host reads, no shapes that depend on the data.
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from torchrl.objectives import ClipPPOLoss

__all__ = ["VALID_KEY", "PROXIMAL_KEY", "MAX_SAMPLE_Z", "guard_rollout", "mean_over_valid", "ratio_statistics",
           "proximal_kl", "behaviour_ess", "BEHAVIOUR_ESS_KEY", "GuardedClipPPOLoss"]

#: Key of the (…, 1) bool mask of usable frames written by :func:`guard_rollout`.
VALID_KEY = "frame_valid"
#: Key of each frame's log-probability (B,) of its action under the policy an update starts from, which a decoupled
#: update (:meth:`GuardedClipPPOLoss.use_proximal`) measures its ratio, clip and KL from.
PROXIMAL_KEY = "proximal_log_prob"
#: A stored action further than this many standard deviations from the stored mean is no sample of the stored
#: Gaussian (probability far below 1e-500): it came from a fault, not from the policy's distribution.
MAX_SAMPLE_Z = 50.0


def mean_over_valid(values: torch.Tensor, td: TensorDictBase, mask_key: str | None) -> torch.Tensor:
    """The mean of the per-frame ``values`` (B,) over the frames of ``td`` (B,) its ``mask_key`` marks usable (the
    PPO loss's ``loss_mask_key``, :data:`VALID_KEY`), so that an extra loss term leaves out the frames the PPO terms
    leave out; the plain mean without a mask. ``values`` must already be finite (0 × NaN is NaN)."""
    if mask_key is None or mask_key not in td.keys():
        return values.mean()
    valid = td[mask_key].reshape(values.shape)
    return torch.where(valid, values, 0.0).sum() / valid.sum().clamp_min(1)


def ratio_statistics(log_weight: torch.Tensor, kl_approx: torch.Tensor, clip_bounds, td: TensorDictBase,
                     mask_key: str | None) -> tuple[torch.Tensor, torch.Tensor]:
    """``(kl_approx, clip_fraction)`` of a PPO loss's per-frame log-ratios ``log_weight`` and KL estimates
    ``kl_approx`` (B, 1), as means over the frames of ``td`` (B,) that ``mask_key`` marks usable (see
    :func:`mean_over_valid`), detached; ``clip_bounds`` the loss's ``(low, high)`` log-ratio clip."""
    log_weight = log_weight.detach().reshape(-1)
    low, high = clip_bounds
    clipped = (log_weight.clamp(low, high) != log_weight).to(log_weight.dtype)
    return (mean_over_valid(kl_approx.detach().reshape(-1), td, mask_key), mean_over_valid(clipped, td, mask_key))


#: The decoupled loss's output (and log name) of :func:`behaviour_ess`.
BEHAVIOUR_ESS_KEY = "behaviour_ess"

#: Bound on the log-ratios :func:`proximal_kl` exponentiates, so that a frame far off (a masked one) stays finite.
_KL_LOG_RATIO_BOUND = 20.0


def proximal_kl(log_weight: torch.Tensor, log_is_weight: torch.Tensor) -> torch.Tensor:
    """Per-frame estimates (B, 1) of KL(π_prox ‖ π_θ) from frames the behaviour policy acted in, detached:
    w·((r − 1) − log r), with r = π_θ / π_prox (``log_weight``) and w = π_prox / π_behav (``log_is_weight``).

    In nats; ``log_weight`` and ``log_is_weight`` (B, 1). Their mean is unbiased (for log-ratios within
    ±:data:`_KL_LOG_RATIO_BOUND`, where they are clamped), and each is >= 0. PPO's own estimate, log(π_prox / π_θ),
    is unbiased only over the proximal policy's own actions: over the behaviour policy's its mean gains a cross term
    between this update's move and the one before, linear in each (for Gaussian means μ_θ − μ_prox and
    μ_prox − μ_behav, in std units, it is their dot product, beside the KL's half squared norm), which early in an
    update is several times the KL itself and can be negative. Where π_prox = π_behav it is the ``k3`` estimator
    of J. Schulman's "Approximating KL divergence" (2020), as unbiased as PPO's own and of a smaller variance for
    nearby policies.

    >>> import torch
    >>> proximal_kl(torch.zeros(3, 1), torch.randn(3, 1))  # the update's start: no move yet
    tensor([[0.],
            [0.],
            [0.]])
    """
    log_r = log_weight.detach().clamp(-_KL_LOG_RATIO_BOUND, _KL_LOG_RATIO_BOUND)
    weight = log_is_weight.detach().clamp(max=_KL_LOG_RATIO_BOUND).exp()
    return weight * (torch.expm1(log_r) - log_r)


def behaviour_ess(log_is_weight: torch.Tensor, td: TensorDictBase, mask_key: str | None) -> torch.Tensor:
    """The effective sample size, as a fraction of the frames (a 0-d tensor), of the weights the decoupled surrogate
    applies, w = π_prox / π_behav (``log_is_weight`` (B, 1); where ``max_importance_ratio`` caps them, the capped
    ones): (mean w)² / mean w², over the frames of ``td`` (B,) that ``mask_key`` marks usable
    (:func:`mean_over_valid`), detached; 0 where none is. 1 where every frame weighs alike (the proximal policy is
    the one that acted); near 1/B where a few frames carry the mini-batch's gradient. TorchRL's own ``ESS`` output is
    of π_θ / π_behav, over every frame.

    >>> import torch
    >>> from tensordict import TensorDict
    >>> td = TensorDict(batch_size=[4])
    >>> float(behaviour_ess(torch.zeros(4, 1), td, None))
    1.0
    >>> float(behaviour_ess(torch.tensor([[0.0], [-50.0], [-50.0], [-50.0]]), td, None))  # one frame carries it
    0.25
    """
    log_w = log_is_weight.detach().reshape(-1)
    if mask_key is not None and mask_key in td.keys():
        top = torch.where(td[mask_key].reshape(log_w.shape), log_w, float("-inf")).amax()
    else:
        top = log_w.amax()
    w = (log_w - top).exp()  # scaled so that the largest usable weight is 1: no overflow, the ratio unchanged
    return mean_over_valid(w, td, mask_key).square() / mean_over_valid(w.square(), td, mask_key).clamp_min(1e-30)


class GuardedClipPPOLoss(ClipPPOLoss):
    """TorchRL's ``ClipPPOLoss`` whose logged ``kl_approx`` and ``clip_fraction`` leave out the frames its
    ``loss_mask_key`` masks, as its loss terms do. TorchRL (0.14) averages both over every frame: a masked frame's
    log-ratio compares its stored (sanitised) mean with the policy at a sanitised observation, so a few of them at a
    small std read as a KL far above ``desired_kl``, and the adaptive learning rate fell for frames the update never
    used. The per-frame values come from ``_log_weight`` (TorchRL 0.14's log-ratio), recorded as the loss runs. The
    mask is the entry ``loss_mask_key`` names (the trainer's :data:`VALID_KEY`); TorchRL's default ``"auto"``, which
    names no one entry, leaves both statistics plain means over every frame, as before.

    With :meth:`use_proximal` it is the decoupled objective of Hilton et al. (2021, "Batch size-invariance for policy
    optimization"), which TorchRL's loss computes from the log-ratios its ``_log_weight`` returns: the ratio
    r = π_θ / π_prox and its clip are taken against the proximal policy, the one the update starts from (each
    frame's log-probability under it in the batch entry :data:`PROXIMAL_KEY`), and the surrogate is weighted by
    π_prox / π_behav, the policy that update starts from over the one that acted (the stored ``sample_log_prob``).
    Where the two are the same it is PPO's own objective. The KL estimate is KL(π_prox ‖ π_θ), importance-weighted
    over the behaviour policy's actions (:func:`proximal_kl`): another estimator than PPO's own even where the two
    policies are one (the same mean, never negative). For an update that runs beside the next rollout
    (``ppo.overlap_update``), whose rollouts act with the policy of one update before: against the policy that acted,
    every mini-batch's KL held the previous update's move too, and the adaptive learning rate sat at its floor
    (docs/training/pd/h100_overlap_seed0)."""

    _frame_ratios: tuple | None = None
    #: The batch entry of the proximal log-probabilities, or None for PPO's objective (:meth:`use_proximal`).
    proximal_key: str | None = None

    def use_proximal(self, key: str | None = PROXIMAL_KEY) -> None:
        """Measure the ratio, clip and KL from the log-probabilities in the batch entry ``key`` (B,) (the decoupled
        objective, see the class), listed among :attr:`in_keys`; None: PPO's own, from the policy that acted."""
        if key is not None and self.delay_actor:
            raise ValueError("GuardedClipPPOLoss.use_proximal: this loss already has a proximal policy of its own "
                             "(delay_actor=True, target parameters); use one or the other")
        self.proximal_key = key
        self._in_keys = None  # listed again, with it

    def _set_in_keys(self):
        super()._set_in_keys()
        if self.proximal_key is not None and self.proximal_key not in self._in_keys:
            self._in_keys.append(self.proximal_key)

    def _log_weight(self, tensordict, adv_shape):
        if self.proximal_key is None:
            out = super()._log_weight(tensordict, adv_shape)
        else:
            out = self._decoupled_log_weight(tensordict, adv_shape)
        self._frame_ratios = out
        return out

    def _decoupled_log_weight(self, tensordict, adv_shape):
        """``(log_weight, dist, kl_approx, log_is_weight)`` in the places TorchRL 0.14's ``_log_weight`` returns
        them for a proximal policy (its ``delay_actor``), the proximal log-probabilities read from the batch instead
        of recomputed from target parameters: log(π_θ / π_prox), the distribution, the per-frame KL estimates of
        :func:`proximal_kl` (from the uncapped weights) where TorchRL returns log(π_prox / π_θ), and the
        gradient-free log(π_prox / π_behav), capped as TorchRL caps it where ``max_importance_ratio`` is set; each
        (B, 1)."""
        behaviour = tensordict.get(self.tensor_keys.sample_log_prob).reshape(adv_shape)
        proximal = tensordict.get(self.proximal_key).reshape(adv_shape)
        if behaviour.requires_grad or proximal.requires_grad:
            raise RuntimeError(f"the batch's stored log-probabilities ({self.tensor_keys.sample_log_prob!r}, "
                               f"{self.proximal_key!r}) must not require grad")
        log_prob, dist, is_composite = self._get_cur_log_prob(tensordict)
        if is_composite:
            raise NotImplementedError("GuardedClipPPOLoss.use_proximal: a composite action distribution is not "
                                      "supported; use one Gaussian over the action vector")
        log_weight = (log_prob.reshape(adv_shape) - proximal).unsqueeze(-1)
        log_is_weight = (proximal - behaviour).unsqueeze(-1)
        kl_approx = proximal_kl(log_weight, log_is_weight)
        if self.max_importance_ratio is not None:  # as TorchRL caps π_θ / π_behav
            log_is_weight = torch.minimum(log_is_weight, self.max_importance_ratio.log() - log_weight.detach())
        return log_weight, dist, kl_approx, log_is_weight

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        self._frame_ratios = None
        out = super().forward(tensordict)
        if self._frame_ratios is not None:
            log_weight, _, kl_approx, log_is_weight = self._frame_ratios
            self._frame_ratios = None  # the autograd graph it holds is not kept until the next step
            kl, clipped = ratio_statistics(log_weight, kl_approx, self._clip_bounds, tensordict, self.loss_mask_key)
            out.set("kl_approx", kl)
            out.set("clip_fraction", clipped)
            if self.proximal_key is not None:
                out.set(BEHAVIOUR_ESS_KEY, behaviour_ess(log_is_weight, tensordict, self.loss_mask_key))
        return out


def _finite_rows(x: torch.Tensor, event_dims: int) -> torch.Tensor:
    return torch.isfinite(x).flatten(-event_dims).all(-1) if event_dims else torch.isfinite(x)


def guard_rollout(batch: TensorDictBase, action_key: str = "action", log_prob_key: str = "action_log_prob",
                  loc_key: str = "loc", scale_key: str = "scale") -> torch.Tensor:
    """Mark and neutralise unusable frames of ``batch`` (shape (num_envs, T), modified in place); returns the
    (num_envs, T) bool mask of usable frames, also stored under :data:`VALID_KEY` as (num_envs, T, 1).

    The observation tensors themselves are overwritten (non-finite entries -> 0), not replaced by copies: a shallow
    clone of ``batch`` shares them with it. Action, log-probability and reward are replaced by new tensors (the
    trainer logs the raw rewards of the collector's batch)."""
    obs, next_obs = batch.get("observation"), batch.get(("next", "observation"))
    reward = batch.get(("next", "reward"))
    action, log_prob = batch.get(action_key), batch.get(log_prob_key)
    valid = (_finite_rows(obs, 1) & _finite_rows(next_obs, 1) & _finite_rows(reward, 1) & _finite_rows(action, 1)
             & torch.isfinite(log_prob))
    loc, scale = batch.get(loc_key, None), batch.get(scale_key, None)
    if loc is not None and scale is not None:
        # NaN compares False, so a NaN action, mean or std fails this too.
        valid = valid & ((action - loc).abs() <= MAX_SAMPLE_Z * scale).all(-1)
        safe_loc = torch.nan_to_num(loc, nan=0.0, posinf=0.0, neginf=0.0)
        log_prob_at_mean = (-torch.log(scale) - 0.5 * math.log(2.0 * math.pi)).sum(-1)
    else:  # not a Gaussian actor of this package: a zero action with log-probability 0 keeps the terms finite
        safe_loc, log_prob_at_mean = torch.zeros_like(action), torch.zeros_like(log_prob)
    batch.set(action_key, torch.where(valid.unsqueeze(-1), action, safe_loc))
    batch.set(log_prob_key, torch.where(valid, log_prob, torch.nan_to_num(log_prob_at_mean)))
    # The observations are sanitised in place: a copy of each would add 2 x obs_dim floats per frame (the size of the
    # rollout's observations, 1.4 GiB at 16,384 envs x 48 steps), alive until the next iteration's update replaces it.
    obs.nan_to_num_(nan=0.0, posinf=0.0, neginf=0.0)
    next_obs.nan_to_num_(nan=0.0, posinf=0.0, neginf=0.0)
    batch.set(("next", "reward"), torch.where(valid.unsqueeze(-1), reward, 0.0))
    batch.set(VALID_KEY, valid.unsqueeze(-1))
    return valid
