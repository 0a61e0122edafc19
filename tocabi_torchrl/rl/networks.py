"""Policy and value networks: MLPs with the reference's orthogonal initialisation (spec §10.3)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn
from torch.nn import functional as F

__all__ = ["ACTION_OUT_GAIN", "ACTIVATIONS", "INIT_SETTING", "OutputLinear", "init_orthogonal", "make_mlp"]

ACTIVATIONS = {"relu": nn.ReLU, "elu": nn.ELU, "tanh": nn.Tanh, "silu": nn.SiLU}
#: Init gain of the action-mean output layer: first actions ~0, so the first rollouts replay the reference closely.
ACTION_OUT_GAIN = 0.01
#: :func:`init_orthogonal` with these gains, in words: the other libraries' recipes record it in their run settings, so
#: a run started with another initialisation is not resumed by them.
INIT_SETTING = "orthogonal, gain sqrt(2) hidden, 0.01 action mean, the preset's value_out_gain value head, biases 0"


def init_orthogonal(mlp: nn.Module, out_gain: float) -> nn.Module:
    """Initialise ``mlp``'s ``nn.Linear`` layers in place, in module order: orthogonal weights with gain √2, the last
    layer with ``out_gain``, all biases 0 (the reference's initialisation, spec §10.3). Returns ``mlp``.

    Also used on other libraries' networks (rsl_rl's and skrl's recipes) so that they start like this package's."""
    linears = [m for m in mlp.modules() if isinstance(m, nn.Linear)]
    if not linears:
        raise ValueError(f"init_orthogonal: {type(mlp).__name__} has no nn.Linear layer")
    for layer in linears:
        nn.init.orthogonal_(layer.weight, gain=out_gain if layer is linears[-1] else math.sqrt(2.0))
        if layer.bias is not None:
            nn.init.zeros_(layer.bias)
    return mlp


class OutputLinear(nn.Linear):
    """The output layer of :func:`make_mlp`: an ``nn.Linear`` (the same parameters, state-dict keys and float32 result
    outside autocast) that computes in float32 inside a ``torch.autocast`` region too, its input cast up. With
    ``ppo.update_dtype`` "bfloat16" the hidden layers run in bfloat16 and the action mean and value keep float32's
    precision: rounded to bfloat16's 8 significant bits, an action mean near 1 moves by up to 0.004, 0.08 of the
    0.05 std the schedule ends at, and the log-probability and the PPO ratio with it; a value near 300, by 1.

    >>> layer = OutputLinear(4, 2)
    >>> with torch.autocast("cpu", dtype=torch.bfloat16):
    ...     layer(torch.randn(3, 4, dtype=torch.bfloat16)).dtype
    torch.float32
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        kind = x.device.type  # "meta" (shapes only) has no autocast to ask about
        if torch.amp.is_autocast_available(kind) and torch.is_autocast_enabled(kind):
            with torch.autocast(kind, enabled=False):
                return F.linear(x.float(), self.weight, self.bias)
        return super().forward(x)


def make_mlp(in_dim: int, hidden: Sequence[int], out_dim: int, activation: str = "relu",
             out_gain: float = ACTION_OUT_GAIN) -> nn.Sequential:
    """``in_dim -> hidden... -> out_dim`` MLP; hidden layers orthogonal with gain √2, the output layer ``out_gain``.

    The reference initialises both the action mean and the value heads with gain 0.01 and all biases with 0.
    """
    if activation not in ACTIVATIONS:
        raise ValueError(f"unknown activation {activation!r}; choose one of {sorted(ACTIVATIONS)}")
    if not hidden or any(int(h) < 1 for h in hidden):
        raise ValueError(f"hidden layer sizes must be positive ints, got {tuple(hidden)}")
    layers: list[nn.Module] = []
    sizes = [in_dim, *[int(h) for h in hidden]]
    for a, b in zip(sizes[:-1], sizes[1:]):
        layers += [nn.Linear(a, b), ACTIVATIONS[activation]()]
    layers.append(OutputLinear(sizes[-1], out_dim))
    return init_orthogonal(nn.Sequential(*layers), out_gain)


class ConcatInputs(nn.Sequential):
    """An MLP (the layers of :func:`make_mlp`) over several inputs concatenated on the last dim: the asymmetric
    critic's ``(observation, privileged)`` -> value. A ``Sequential``, so its layers index and save as the plain
    critic's do.

    >>> net = ConcatInputs(*make_mlp(5, (8,), 1))
    >>> net(torch.zeros(3, 2), torch.zeros(3, 3)).shape
    torch.Size([3, 1])
    """

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return super().forward(torch.cat(inputs, dim=-1))
