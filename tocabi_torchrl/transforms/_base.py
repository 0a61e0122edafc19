"""The base class of the transforms whose reset output is computed like a step's."""

from __future__ import annotations

from tensordict import TensorDictBase
from torchrl.envs.transforms import Transform

__all__ = ["CallOnReset"]


class CallOnReset(Transform):
    """A :class:`~torchrl.envs.transforms.Transform` that writes its outputs into the reset tensordict too.

    TorchRL's default ``_reset`` leaves the reset tensordict alone, so the first observation of an episode would lack
    the keys the transform adds. A subclass of this one applies its ``_call`` there as well: the reset state gets the
    same keys, computed the same way, as every step.
    """

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)
