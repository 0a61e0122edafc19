"""Loads a recipe script (``recipes/<name>.py``) as a module, for the adapter tests that train through it, and checks
that a recipe's networks start as the preset's."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch

RECIPES = Path(__file__).resolve().parent.parent / "recipes"


def load_recipe(name: str):
    spec = importlib.util.spec_from_file_location(f"recipe_{name}", RECIPES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def assert_preset_init(net: torch.nn.Module, out_gain: float, num_layers: int = 4) -> None:
    """``net``'s ``num_layers`` linear layers are initialised as the preset's (spec §10.3): zero biases, orthogonal
    weights (the rows or columns, whichever are fewer, orthonormal times the gain), gain √2 but ``out_gain`` last."""
    layers = [m for m in net.modules() if isinstance(m, torch.nn.Linear)]
    assert len(layers) == num_layers and all(torch.count_nonzero(m.bias) == 0 for m in layers)
    for m in layers:
        gain = out_gain if m is layers[-1] else 2 ** 0.5
        w = m.weight.detach()
        gram = w @ w.T if w.shape[0] <= w.shape[1] else w.T @ w
        torch.testing.assert_close(gram, gain ** 2 * torch.eye(min(w.shape)), atol=1e-4 * max(gain ** 2, 1), rtol=0)
