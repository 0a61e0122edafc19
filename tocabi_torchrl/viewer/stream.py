"""Host copies of a few training worlds' body poses for the live viewer, taken off the training's critical path.

Every ``every`` policy steps :meth:`PoseStream.tick` (called by :class:`TappedPolicy` as the collector asks for an
action) copies the first W worlds' ``xpos``/``xquat`` (W <= 64) to the host. On CUDA it never waits for the GPU:

1. one device-to-device copy on the training stream into a staging buffer, ordered after the step that wrote the
   poses (and before the next step overwrites them);
2. a side stream waits for that (an event, not a host sync), copies the staging buffer into pinned host memory with
   ``non_blocking=True`` and records an event;
3. the viewer's thread takes the host copy only once that event has completed (``event.query()``, which never
   blocks). While a copy is still in flight the next tick is skipped, so no buffer is written while it is read.

Nothing here runs inside the env's captured CUDA graph: the tick runs in the collector's Python loop, beside the
policy call. On the CPU the copy is a plain host copy. Pinned double buffers and a lock let the viewer's thread read
a completed copy while the next one is in flight.
"""

from __future__ import annotations

import threading

import numpy as np
import torch
from tensordict.nn import TensorDictModuleBase

from .config import MAX_STREAM_WORLDS

__all__ = ["PoseStream", "PoseFrame", "TappedPolicy"]


class PoseFrame:
    """One completed host copy: ``xpos`` (W, nbody, 3) and ``xquat`` (W, nbody, 4) float32 numpy arrays (the
    viewer's own), ``index`` the copy's sequence number (1, 2, ...) and ``tick`` the policy step it was taken at."""

    __slots__ = ("xpos", "xquat", "index", "tick")

    def __init__(self, xpos: np.ndarray, xquat: np.ndarray, index: int, tick: int):
        self.xpos, self.xquat, self.index, self.tick = xpos, xquat, index, tick


class PoseStream:
    """Host copies of worlds [0, W) of ``sim.xpos``/``sim.xquat`` every ``every`` ticks (see the module doc).

    Args:
        sim: the simulator (``WarpSim`` or ``MujocoSim``; anything with ``xpos`` (N, nbody, 3) and ``xquat``
            (N, nbody, 4) tensors that it updates in place).
        worlds: W, how many worlds to copy (at most :data:`~.config.MAX_STREAM_WORLDS` and the sim's count).
        every: ticks (policy steps) between copies, >= 1.
    """

    def __init__(self, sim, worlds: int, every: int):
        if not 1 <= worlds <= MAX_STREAM_WORLDS:
            raise ValueError(f"the viewer streams 1 to {MAX_STREAM_WORLDS} worlds, got {worlds}")
        if every < 1:
            raise ValueError(f"every must be >= 1 policy step, got {every}")
        self.sim, self.every = sim, int(every)
        self.worlds = min(int(worlds), int(sim.xpos.shape[0]))
        self.device = sim.xpos.device
        self.cuda = self.device.type == "cuda"
        shape = (self.worlds, sim.xpos.shape[1], 7)  # xpos | xquat side by side: one copy per tick
        self._host = [torch.empty(shape, dtype=torch.float32, pin_memory=self.cuda) for _ in range(2)]
        self._lock = threading.Lock()
        self.ticks = self.copies = self.skipped = 0
        #: Whether ticks take copies (``False`` pauses the stream; the benchmark alternates it).
        self.active = True
        self._ready: tuple[int, int, int] | None = None  # (buffer, index, tick) of the newest completed copy
        self._taken = 0  # index of the newest copy :meth:`latest` returned
        if self.cuda:
            self._stage = torch.empty(shape, dtype=torch.float32, device=self.device)
            self._side = torch.cuda.Stream(self.device)
            self._event = torch.cuda.Event()
            self._flight: tuple[int, int, int] | None = None  # (buffer, index, tick) of the copy in flight
            self._slot = 0

    def tick(self) -> None:
        """Count one policy step; every ``every``-th takes a copy (:meth:`capture`)."""
        self.ticks += 1
        if self.active and self.ticks % self.every == 0:
            self.capture()

    def capture(self) -> bool:
        """Start a host copy of the current poses; ``False`` when it was skipped (the last one still in flight).
        Never synchronises with the GPU."""
        xpos, xquat, w = self.sim.xpos, self.sim.xquat, self.worlds
        if not self.cuda:
            slot = 0 if self._ready is None or self._ready[0] == 1 else 1
            with self._lock:  # the viewer may be reading the other buffer, never this one
                self._host[slot][..., :3].copy_(xpos[:w])
                self._host[slot][..., 3:].copy_(xquat[:w])
                self.copies += 1
                self._ready = (slot, self.copies, self.ticks)
            return True
        if self._flight is not None:
            if not self._event.query():  # still copying: skip this tick rather than wait
                self.skipped += 1
                return False
            self._publish()
        main = torch.cuda.current_stream(self.device)
        # On the training stream: ordered after the step that wrote the poses, before the next one overwrites them.
        self._stage[..., :3].copy_(xpos[:w])
        self._stage[..., 3:].copy_(xquat[:w])
        self._side.wait_stream(main)
        slot = self._free_slot()
        with torch.cuda.stream(self._side):
            self._host[slot].copy_(self._stage, non_blocking=True)
            self._event.record(self._side)
        # The staging buffer belongs to the training stream's allocator: keep it alive while the side stream reads.
        self._stage.record_stream(self._side)
        self.copies += 1
        self._flight = (slot, self.copies, self.ticks)
        return True

    def _free_slot(self) -> int:
        with self._lock:
            return 0 if self._ready is None or self._ready[0] == 1 else 1

    def _publish(self) -> None:
        """Make the completed copy in flight the newest (the viewer's thread may have done so already)."""
        with self._lock:
            if self._flight is not None:
                self._ready, self._flight = self._flight, None

    def latest(self) -> PoseFrame | None:
        """The newest completed copy not returned before, as the caller's own arrays; ``None`` when there is none
        (safe from another thread: a copy in flight is checked with ``event.query()``, which never blocks)."""
        if self.cuda and self._flight is not None and self._event.query():
            self._publish()
        with self._lock:
            if self._ready is None or self._ready[1] == self._taken:
                return None
            slot, index, tick = self._ready
            data = self._host[slot].numpy().copy()
            self._taken = index
        return PoseFrame(np.ascontiguousarray(data[..., :3]), np.ascontiguousarray(data[..., 3:]), index, tick)


class TappedPolicy(TensorDictModuleBase):
    """``policy`` that also ticks ``stream`` once per call (once per collected policy step): the training collector's
    policy while the live viewer streams. Parameters, keys and outputs are ``policy``'s own."""

    def __init__(self, policy: TensorDictModuleBase, stream: PoseStream):
        super().__init__()
        self.policy = policy
        self.stream = stream
        self.in_keys = list(policy.in_keys)
        self.out_keys = list(policy.out_keys)

    def forward(self, tensordict):
        self.stream.tick()
        return self.policy(tensordict)
