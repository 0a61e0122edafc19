"""Gymnasium spaces from TorchRL specs: per-env (``single_*``) and batched (num_envs, ...) ``Box`` spaces."""

from __future__ import annotations

import numpy as np
from gymnasium import spaces
from torchrl.data import Bounded, TensorSpec, Unbounded

__all__ = ["box_from_spec"]


def box_from_spec(spec: TensorSpec, batched: bool) -> spaces.Box:
    """A float32 ``Box`` for a batched continuous TorchRL spec of shape (num_envs, dim).

    ``batched=False`` gives the per-env space (dim,), read from the first env's bounds (every env shares them);
    ``batched=True`` the (num_envs, dim) space. Unbounded specs map to ±inf bounds. Other spec kinds raise
    ``TypeError``: the walking task has only continuous vectors.
    """
    if isinstance(spec, Bounded):
        low, high = spec.space.low.cpu().numpy(), spec.space.high.cpu().numpy()
    elif isinstance(spec, Unbounded):
        low = np.full(tuple(spec.shape), -np.inf, dtype=np.float32)
        high = np.full(tuple(spec.shape), np.inf, dtype=np.float32)
    else:
        raise TypeError(f"cannot map a {type(spec).__name__} spec to a gymnasium Box (only Bounded/Unbounded)")
    if len(spec.shape) != 2:
        raise ValueError(f"expected a (num_envs, dim) spec, got shape {tuple(spec.shape)}")
    if not batched:
        low, high = low[0], high[0]
    return spaces.Box(low.astype(np.float32), high.astype(np.float32), dtype=np.float32)
