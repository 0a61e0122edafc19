"""Policy and value networks: MLPs with the reference's orthogonal initialisation (spec §10.3)."""

from __future__ import annotations

import math
from collections.abc import Sequence

from torch import nn

__all__ = ["ACTIVATIONS", "make_mlp"]

ACTIVATIONS = {"relu": nn.ReLU, "elu": nn.ELU, "tanh": nn.Tanh, "silu": nn.SiLU}


def make_mlp(in_dim: int, hidden: Sequence[int], out_dim: int, activation: str = "relu", out_gain: float = 0.01
             ) -> nn.Sequential:
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
    layers.append(nn.Linear(sizes[-1], out_dim))
    for layer in layers:
        if isinstance(layer, nn.Linear):
            gain = out_gain if layer is layers[-1] else math.sqrt(2.0)
            nn.init.orthogonal_(layer.weight, gain=gain)
            nn.init.zeros_(layer.bias)
    return nn.Sequential(*layers)
