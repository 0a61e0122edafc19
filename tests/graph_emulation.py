"""A capturer for machines without CUDA: the bookkeeping of a captured graph (static inputs, outputs rewritten in
place, warm-up count, fallbacks) with a "replay" that calls the captured function again and copies its results into
the first call's tensors. Passed wherever the package takes a ``capturer`` (``tocabi_torchrl.cuda_graphs``).

A real capture records the work without running it, and its callers replay once right away on the same static inputs.
Here the capture has to run the function (to return its outputs), so that first replay is skipped: the work runs
once, as on the GPU."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase


def _leaves(result) -> list[torch.Tensor]:
    if isinstance(result, torch.Tensor):
        return [result]
    if isinstance(result, TensorDictBase):
        return [result.get(k) for k in sorted(result.keys(True, True), key=str)]
    if isinstance(result, (tuple, list)):
        return [leaf for item in result for leaf in _leaves(item)]
    raise TypeError(f"cannot emulate a graph returning {type(result).__name__}")


class EmulatedCapture:
    """Captures on any device; ``replay()`` reruns the function and writes its outputs into the captured ones."""

    def __init__(self):
        self.captures: list[str] = []  # the modes captured, in order

    def supports(self, device) -> bool:
        return True

    def side_stream(self, device):
        return None

    def capture(self, fn, *, device, stream, generators=(), mode="joined", recorded=()):
        self.captures.append(mode)
        result = fn()
        static = _leaves(result)
        ran = [True]  # the capture's call stands for the first replay

        def replay():
            if ran[0]:
                ran[0] = False
                return
            torch._foreach_copy_(static, _leaves(fn()))

        return replay, result


class FailingCapture(EmulatedCapture):
    """Fails in the given modes (to test the fallbacks)."""

    def __init__(self, failing=("joined",)):
        super().__init__()
        self.failing = tuple(failing)

    def capture(self, fn, *, mode="joined", **kwargs):
        if mode in self.failing:
            raise RuntimeError(f"no {mode} capture here")
        return super().capture(fn, mode=mode, **kwargs)
