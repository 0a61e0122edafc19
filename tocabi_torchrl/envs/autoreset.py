"""A ``TransformedEnv`` whose automatic resets in ``step_and_maybe_reset`` never read device values on the host."""

from __future__ import annotations

from tensordict import TensorDictBase
from torchrl.envs import TransformedEnv

__all__ = ["SyncFreeResetEnv"]


class SyncFreeResetEnv(TransformedEnv):
    """``TransformedEnv`` with a host-sync-free ``step_and_maybe_reset`` (what TorchRL collectors call every step).

    TorchRL's stock version asks ``done.any()`` on the host to decide whether to reset, then merges the reset rows
    after reading ``_reset.all()``: each read waits for the GPU to finish the step, so the host cannot queue the next
    step's kernels while the physics runs. Here every step runs the masked reset (the base env's ``_reset`` and every
    transform's ``_reset``, all of which only touch flagged rows with ``where``) and merges the flagged rows into the
    next-step data with ``where``: no host reads, so Python and kernel launches overlap the GPU work.

    Semantics equal the stock path: the ``"next"`` entries of a step keep the terminal/truncated data (GAE bootstraps
    from them), and the returned carry-over data hold the reset observation for done envs. The base env must build
    all-False done flags on reset rows (``TocabiWalk`` does).
    """

    def _step_and_maybe_reset(self, tensordict: TensorDictBase) -> tuple[TensorDictBase, TensorDictBase]:
        if tensordict.device != self.device:
            tensordict = tensordict.to(self.device)
        tensordict = self.step(tensordict)
        tensordict_ = self._step_mdp(tensordict)
        done = tensordict_.get("done")  # (num_envs, 1) bool
        request = tensordict_.clone(False).set("_reset", done)
        reset = self._reset(request)
        # Flagged rows take the reset data; the others keep the step's data (bit-identical). Only keys present on
        # both sides take part: `where(pad=...)` would build its pad value on the host (a sync per missing key).
        keys = [k for k in reset.keys(True, True) if k != "_reset"]
        merged = reset.select(*keys).where(done.reshape(self.batch_size), other=tensordict_.select(*keys))
        return tensordict, tensordict_.update(merged)
