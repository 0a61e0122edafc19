"""A few device numbers read on the host later, without making the host wait for the GPU's queue now.

``tensor.tolist()`` of a CUDA tensor copies it on the current stream and waits: the host idles until every kernel
queued before it on that stream has run, and the GPU then idles until the host queues more. Between two rollouts that
gap is the host's whole work of the iteration (GAE, the update's launch, the log): the stream drains, then waits.
:class:`DeferredRead` queues the copy into pinned host memory instead (``non_blocking``), with an event after it, and
:meth:`DeferredRead.values` waits for that event alone, where the numbers are needed (the next iteration's log, the
learning rate of the next update). On the CPU the numbers are read when asked for.

>>> import torch
>>> read = DeferredRead()
>>> read.start(torch.tensor([1.0, 2.5]))
>>> read.values()
[1.0, 2.5]
"""

from __future__ import annotations

import torch

__all__ = ["DeferredRead"]


class DeferredRead:
    """One pending host copy of a small 1-D tensor at a time: :meth:`start` queues it, :meth:`values` returns it as
    floats. The pinned buffer is kept across starts of one size (no allocation per iteration)."""

    def __init__(self):
        self._buffer: torch.Tensor | None = None
        self._event: torch.cuda.Event | None = None
        self._pending: torch.Tensor | None = None

    @property
    def pending(self) -> bool:
        """Whether a started read has not been taken by :meth:`values` yet."""
        return self._pending is not None

    def start(self, values: torch.Tensor) -> None:
        """Queue the copy of ``values`` ((K,) float) on the current stream of its device; returns at once.

        Raises:
            RuntimeError: a read is pending (its numbers would be overwritten before they were taken).
        """
        if self._pending is not None:
            raise RuntimeError("DeferredRead.start() with a read pending: take it with values() first")
        if values.device.type != "cuda":
            self._pending = values
            return
        if self._buffer is None or self._buffer.shape != values.shape or self._buffer.dtype != values.dtype:
            self._buffer = torch.empty(values.shape, dtype=values.dtype, pin_memory=True)
        self._buffer.copy_(values, non_blocking=True)
        self._event = torch.cuda.current_stream(values.device).record_event()
        self._pending = self._buffer

    def values(self) -> list[float]:
        """The started read's numbers, once its copy has run (a wait for that copy alone on CUDA).

        Raises:
            RuntimeError: nothing was started.
        """
        if self._pending is None:
            raise RuntimeError("DeferredRead.values() with no read started")
        if self._event is not None:
            self._event.synchronize()
            self._event = None
        out, self._pending = self._pending.tolist(), None
        return out
