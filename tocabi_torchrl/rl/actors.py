"""Gaussian actors for PPO: a scheduled-std actor that mirrors the reference, and a learned-std actor.

Both return a TorchRL ``ProbabilisticActor`` reading ``observation`` (num_envs, obs_dim) and writing ``loc``,
``scale`` (num_envs, act_dim), ``action`` and ``action_log_prob``. The sampled action is *not* squashed or clipped:
the log-probability belongs to the unclipped sample and the environment clips what it applies (as the reference's
SB3 PPO does).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import IndependentNormal, ProbabilisticActor

from .networks import ACTION_OUT_GAIN, make_mlp

__all__ = ["GaussianHead", "gaussian_head", "gaussian_log_prob", "make_actor", "set_action_std", "action_std"]


class GaussianHead(nn.Module):
    """Mean network plus a state-independent std.

    ``learn_std=False``: the std is a buffer (no gradient), set from outside by a schedule (:func:`set_action_std`).
    ``learn_std=True``: the log-std is a parameter trained with the policy (rsl_rl's default).

    Input (num_envs, obs_dim); outputs ``loc`` and ``scale`` (num_envs, act_dim).
    """

    def __init__(self, mean_net: nn.Module, act_dim: int, init_std: float, learn_std: bool):
        super().__init__()
        self.mean_net = mean_net
        self.learn_std = learn_std
        log_std = torch.full((act_dim,), math.log(init_std))
        if learn_std:
            self.log_std = nn.Parameter(log_std)
        else:
            self.register_buffer("log_std", log_std)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        loc = self.mean_net(obs)
        return loc, self.log_std.exp().expand_as(loc)


def make_actor(
    obs_dim: int,
    act_dim: int,
    hidden: Sequence[int] = (256, 256),
    activation: str = "relu",
    init_std: float = 0.1,
    learn_std: bool = False,
    obs_key: str = "observation",
) -> ProbabilisticActor:
    """Gaussian policy over ``obs_key`` (see the module docstring)."""
    if not init_std > 0:
        raise ValueError(f"init_std must be > 0, got {init_std}")
    head = GaussianHead(make_mlp(obs_dim, hidden, act_dim, activation, out_gain=ACTION_OUT_GAIN), act_dim, init_std,
                        learn_std)
    module = TensorDictModule(head, in_keys=[obs_key], out_keys=["loc", "scale"])
    return ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        out_keys=["action"],
        distribution_class=IndependentNormal,
        return_log_prob=True,
        log_prob_key="action_log_prob",
    )


def gaussian_head(actor: ProbabilisticActor) -> GaussianHead:
    """The actor's :class:`GaussianHead` (mean network and std)."""
    for m in actor.modules():
        if isinstance(m, GaussianHead):
            return m
    raise TypeError("actor has no GaussianHead; build it with tocabi_torchrl.rl.make_actor")


def gaussian_log_prob(head: GaussianHead, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """(N,) log-probability [nats] of each ``action`` (N, act_dim) under ``head``'s Gaussian at ``obs`` (N, obs_dim),
    as the actor's ``IndependentNormal`` gives it, in plain torch: no TensorDict module runs, so the process-wide
    sampling mode that a TensorDict module's ``get_dist`` sets and restores is left alone (a thread may call it
    while another collects), and no argument check reads the device.

    >>> head = GaussianHead(torch.nn.Linear(3, 2), act_dim=2, init_std=0.5, learn_std=False)
    >>> obs, action = torch.randn(4, 3), torch.randn(4, 2)
    >>> loc, scale = head(obs)
    >>> reference = torch.distributions.Normal(loc, scale).log_prob(action).sum(-1)
    >>> torch.allclose(gaussian_log_prob(head, obs, action), reference)
    True
    """
    loc, scale = head(obs)
    # torch.distributions.Normal.log_prob's own expression, term for term: the same floats as the actor's.
    return (-((action - loc) ** 2) / (2 * scale**2) - scale.log() - math.log(math.sqrt(2 * math.pi))).sum(-1)


def set_action_std(actor: ProbabilisticActor, std: float) -> None:
    """Set the (scheduled) std of every action dimension."""
    head = gaussian_head(actor)
    with torch.no_grad():
        head.log_std.fill_(math.log(std))


def action_std(actor: ProbabilisticActor) -> torch.Tensor:
    """(act_dim,) current std."""
    return gaussian_head(actor).log_std.detach().exp()
