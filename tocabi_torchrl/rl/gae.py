"""TorchRL's GAE without its one host read per critic input.

Before it runs the critic on the next observations, TorchRL's value estimator replaces their NaN entries with the
observation of the same step (``ValueEstimatorBase._sanitize_next_obs_nan``, for collectors that leave NaN where a
trajectory ends). It asks ``nan_mask.any()`` first and skips the replacement when there is none: a host read of a
device value, which on CUDA makes the host wait until every queued step of the rollout has run before it can queue
the advantages, the update and the next rollout. :class:`SyncFreeGAE` always replaces, with the same
``torch.where``: where no entry is NaN the result is the next observation itself, bit for bit, so the advantages are
TorchRL's, and the host queues them without waiting. It replaces in place, in the rollout's own next observations (a
copy would add a rollout's worth of observations to the memory GAE needs; only NaN entries change).

>>> import torch
>>> from tensordict import TensorDict
>>> data = TensorDict({"observation": torch.ones(2, 3), "next": {"observation": torch.tensor(
...     [[2.0, float("nan"), 2.0], [2.0, 2.0, 2.0]])}}, batch_size=[2])
>>> SyncFreeGAE._sanitize_next_obs_nan(data, ["observation"])["next", "observation"]
tensor([[2., 1., 2.],
        [2., 2., 2.]])
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.objectives.value import GAE

__all__ = ["SyncFreeGAE"]


class SyncFreeGAE(GAE):
    """:class:`torchrl.objectives.value.GAE` whose NaN replacement in the next observations reads nothing on the
    host (module docstring); every argument as GAE's."""

    @staticmethod
    def _sanitize_next_obs_nan(data: TensorDictBase, in_keys: list) -> TensorDictBase:
        """``data`` with the NaN entries of ``("next", k)`` replaced by ``k``'s, in place, for each floating-point
        ``k`` of ``in_keys`` whose next value has its shape. A next value that cannot be written in place (it needs
        gradients, was made in inference mode, shares memory across entries or has another dtype than ``k``) is
        replaced as TorchRL does, in a shallow copy of ``data``."""
        copied = False
        for k in in_keys:
            root = data.get(k, default=None)
            if root is None or not root.is_floating_point():
                continue
            next_k = ("next", *k) if isinstance(k, tuple) else ("next", k)
            nxt = data.get(next_k, default=None)
            if nxt is None or nxt.shape != root.shape:
                continue
            nan = torch.isnan(nxt)
            if nxt.requires_grad or nxt.is_inference() or nxt.dtype != root.dtype or 0 in nxt.stride():
                if not copied:
                    data, copied = data.copy(), True
                data.set(next_k, torch.where(nan, root, nxt))
            else:
                data.set_(next_k, torch.where(nan, root, nxt, out=nxt))
        return data
