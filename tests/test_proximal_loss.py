"""The decoupled PPO objective of ``GuardedClipPPOLoss.use_proximal`` (rl/rollout_guard.py), which an update that
runs beside the next rollout (``ppo.overlap_update``) trains with: ratio, clip and KL from the proximal policy (the one
the update starts from), the surrogate weighted by the proximal over the behaviour policy."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.modules import IndependentNormal, ProbabilisticActor, ValueOperator

from tocabi_torchrl.rl.rollout_guard import BEHAVIOUR_ESS_KEY, PROXIMAL_KEY, GuardedClipPPOLoss, proximal_kl

B, OBS, ACT, CLIP = 64, 3, 2, 0.2


def _loss(seed=0):
    torch.manual_seed(seed)
    module = TensorDictModule(nn.Sequential(nn.Linear(OBS, 2 * ACT), NormalParamExtractor()),
                              in_keys=["observation"], out_keys=["loc", "scale"])
    actor = ProbabilisticActor(module, in_keys=["loc", "scale"], distribution_class=IndependentNormal,
                               return_log_prob=True, log_prob_key="action_log_prob")
    critic = ValueOperator(nn.Linear(OBS, 1), in_keys=["observation"])
    loss = GuardedClipPPOLoss(actor, critic, clip_epsilon=CLIP, normalize_advantage=False)
    loss.set_keys(sample_log_prob="action_log_prob")
    return loss, actor


def _batch(actor, seed=1):
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(B, OBS, generator=g)
    with torch.no_grad():
        dist = actor.get_dist(TensorDict(observation=obs, batch_size=[B]))
        action = dist.mean + dist.stddev * torch.randn(B, ACT, generator=g)
        log_prob = dist.log_prob(action)
    return TensorDict(observation=obs, action=action, advantage=torch.randn(B, 1, generator=g),
                      value_target=torch.randn(B, 1, generator=g), batch_size=[B]), log_prob


def _grads(loss, td):
    out = loss(td.clone())
    (out["loss_objective"] + out["loss_critic"]).backward()
    grads = [p.grad.clone() for p in loss.parameters() if p.grad is not None]
    loss.zero_grad()
    return out, grads


def test_a_proximal_policy_equal_to_the_behaviour_policy_is_ppo_itself():
    plain, actor = _loss()
    td, log_prob = _batch(actor)
    td.set("action_log_prob", log_prob + 0.3 * torch.randn(B))  # the policy that acted: not the learner
    decoupled, _ = _loss()
    decoupled.use_proximal()
    assert PROXIMAL_KEY in decoupled.in_keys and PROXIMAL_KEY not in plain.in_keys
    out_a, grads_a = _grads(plain, td)
    out_b, grads_b = _grads(decoupled, td.clone().set(PROXIMAL_KEY, td["action_log_prob"].clone()))
    for key in ("loss_objective", "loss_critic", "clip_fraction"):
        torch.testing.assert_close(out_b[key], out_a[key], rtol=0, atol=1e-7)
    assert BEHAVIOUR_ESS_KEY not in out_a.keys() and float(out_b[BEHAVIOUR_ESS_KEY]) == pytest.approx(1.0)
    for a, b in zip(grads_a, grads_b, strict=True):
        torch.testing.assert_close(b, a, rtol=0, atol=1e-7)
    # The KL estimate is another of the same mean: (r - 1) - log r where PPO's own reads -log r.
    log_r = (log_prob - td["action_log_prob"]).unsqueeze(-1)
    torch.testing.assert_close(out_a["kl_approx"], (-log_r).mean(), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(out_b["kl_approx"], (log_r.exp() - 1 - log_r).mean(), rtol=1e-5, atol=1e-6)


def test_ratio_clip_and_kl_come_from_the_proximal_policy_the_weight_from_the_behaviour_policy():
    loss, actor = _loss()
    loss.use_proximal()
    td, learner = _batch(actor)
    g = torch.Generator().manual_seed(7)
    proximal = learner + 0.1 * torch.randn(B, generator=g)  # the update's start, a little off the learner
    behaviour = proximal + 0.5 * torch.randn(B, generator=g)  # one update further back
    out = loss(td.clone().set("action_log_prob", behaviour).set(PROXIMAL_KEY, proximal))
    adv = td["advantage"].squeeze(-1)
    log_r = learner - proximal
    weight = (proximal - behaviour).exp()
    # TorchRL clamps log r at log(1 ± ε): ±0.182 and ±0.223 for ε = 0.2
    gain = torch.minimum(log_r.exp() * weight * adv,
                         log_r.clamp(torch.log1p(torch.tensor(-CLIP)), torch.log1p(torch.tensor(CLIP))).exp()
                         * weight * adv)
    torch.testing.assert_close(out["loss_objective"], -gain.mean(), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(out["kl_approx"], (weight * (log_r.exp() - 1 - log_r)).mean(), rtol=1e-5, atol=1e-6)
    outside = (log_r < torch.log1p(torch.tensor(-CLIP))) | (log_r > torch.log1p(torch.tensor(CLIP)))
    torch.testing.assert_close(out["clip_fraction"], outside.float().mean())
    torch.testing.assert_close(out[BEHAVIOUR_ESS_KEY], weight.mean() ** 2 / weight.square().mean())
    assert float(out[BEHAVIOUR_ESS_KEY]) < 0.99  # spread weights count as fewer frames


def test_stored_log_probabilities_that_require_grad_are_refused():
    loss, actor = _loss()
    loss.use_proximal()
    td, learner = _batch(actor)
    td.set("action_log_prob", learner.clone()).set(PROXIMAL_KEY, learner.clone().requires_grad_())
    with pytest.raises(RuntimeError, match="must not require grad"):
        loss(td)


def test_a_loss_with_its_own_proximal_policy_refuses_a_stored_one():
    torch.manual_seed(0)
    loss, actor = _loss()
    delayed = GuardedClipPPOLoss(actor, ValueOperator(nn.Linear(OBS, 1), in_keys=["observation"]), delay_actor=True)
    with pytest.raises(ValueError, match="delay_actor=True"):
        delayed.use_proximal()
    loss.use_proximal()
    loss.use_proximal(None)  # back to PPO's own: the entry is no input any more
    assert PROXIMAL_KEY not in loss.in_keys


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_the_kl_estimate_is_the_proximal_policys_kl_over_the_behaviour_policys_actions(sign):
    """Gaussians of one std whose means step by d_prev (behaviour -> proximal) and then d (proximal -> learner), in
    std units: KL(prox || learner) = |d|^2 / 2 per state. Over the behaviour policy's actions, log(π_prox / π_θ)
    averages |d|^2 / 2 + d·d_prev (7x the KL when the moves align, below zero when they oppose); the estimate
    must read the KL."""
    g = torch.Generator().manual_seed(3)
    n, dims = 400_000, 2
    d, d_prev = torch.full((dims,), 0.1), sign * torch.full((dims,), 0.3)
    z = torch.randn(n, dims, generator=g)  # behaviour's actions, mean 0, std 1
    normal = torch.distributions.Normal

    def log_prob(mean):
        return normal(mean, 1.0).log_prob(z).sum(-1, keepdim=True)

    behaviour, proximal, learner = log_prob(torch.zeros(dims)), log_prob(d_prev), log_prob(d_prev + d)
    kl = float(d.square().sum() / 2)
    plain = float((proximal - learner).mean())
    assert abs(plain - (kl + sign * float(d @ d_prev.abs()))) < 0.1 * kl  # the cross term, 6x the KL
    estimate = float(proximal_kl(learner - proximal, proximal - behaviour).mean())
    assert abs(estimate - kl) < 0.1 * kl
    assert bool((proximal_kl(learner - proximal, proximal - behaviour) >= 0).all())


def test_the_kl_estimate_of_a_far_frame_stays_finite():
    out = proximal_kl(torch.tensor([[500.0], [-500.0]]), torch.tensor([[300.0], [-300.0]]))
    assert bool(torch.isfinite(out).all())


def test_the_effective_sample_size_leaves_out_masked_frames():
    from tocabi_torchrl.rl.rollout_guard import VALID_KEY, behaviour_ess

    log_w = torch.tensor([[0.0], [0.0], [80.0], [0.0]])  # a masked frame of a huge weight
    td = TensorDict({VALID_KEY: torch.tensor([True, True, False, True])}, batch_size=[4])
    assert float(behaviour_ess(log_w, td, VALID_KEY)) == pytest.approx(1.0)
    assert float(behaviour_ess(log_w, td, None)) == pytest.approx(0.25)


def test_a_capped_weight_lowers_the_behaviour_factor_where_the_whole_ratio_passes_the_cap():
    cap = 1.3
    loss, actor = _loss()
    capped = GuardedClipPPOLoss(actor, loss.critic_network, clip_epsilon=CLIP, normalize_advantage=False,
                                max_importance_ratio=cap)
    capped.set_keys(sample_log_prob="action_log_prob")
    capped.use_proximal()
    td, learner = _batch(actor)
    g = torch.Generator().manual_seed(11)
    proximal = learner + 0.1 * torch.randn(B, generator=g)
    behaviour = proximal - 0.8 * torch.rand(B, generator=g)  # π_prox / π_behav in [1, 2.2]: many pass the cap
    out = capped(td.clone().set("action_log_prob", behaviour).set(PROXIMAL_KEY, proximal))
    adv = td["advantage"].squeeze(-1)
    log_r = learner - proximal
    log_w = torch.minimum(proximal - behaviour, torch.log(torch.tensor(cap)) - log_r)
    assert bool((log_w < proximal - behaviour).any())  # the cap bites somewhere
    low, high = torch.log1p(torch.tensor(-CLIP)), torch.log1p(torch.tensor(CLIP))
    gain = torch.minimum(log_r.exp() * log_w.exp() * adv, log_r.clamp(low, high).exp() * log_w.exp() * adv)
    torch.testing.assert_close(out["loss_objective"], -gain.mean(), rtol=1e-5, atol=1e-6)
    w = log_w.exp()
    torch.testing.assert_close(out[BEHAVIOUR_ESS_KEY], w.mean() ** 2 / w.square().mean())
    # The KL estimate keeps the uncapped weights (the cap would bias it).
    w_all = (proximal - behaviour).exp()
    torch.testing.assert_close(out["kl_approx"], (w_all * (log_r.exp() - 1 - log_r)).mean(), rtol=1e-5, atol=1e-6)

