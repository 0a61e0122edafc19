"""Loads a recipe script (``recipes/<name>.py``, or one of the lab's tools in :data:`LAB_SCRIPTS`) as a fresh module,
for the tests that run it, checks that a recipe's networks start as the preset's, and gives the tests of its resume a
pickled object that runs code (:class:`TouchMarker`)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
RECIPES = ROOT / "recipes"
#: The lab's command-line tools the tests load like recipes (``python -m lab...`` runs them).
LAB_SCRIPTS = {"compare_gaits": ROOT / "lab/experiments/compare_gaits.py",
               "obstacle_test": ROOT / "lab/experiments/obstacle_test.py",
               "library_table": ROOT / "lab/library_table/table.py"}


def load_recipe(name: str):
    """A fresh module of ``recipes/<name>.py`` (or of the lab tool ``name``), not run as ``__main__``."""
    spec = importlib.util.spec_from_file_location(f"recipe_{name}", LAB_SCRIPTS.get(name, RECIPES / f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class TouchMarker:
    """Unpickled, runs ``touch <marker>``: what a crafted state file would do if a resume unpickled it."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        import os
        import shlex

        return os.system, (f"touch {shlex.quote(self.marker)}",)


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
