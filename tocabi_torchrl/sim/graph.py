"""Record a sequence of warp launches once, replay it many times, on CPU and CUDA alike.

On CUDA the sequence becomes one CUDA graph. It is recorded on a private stream (capture cannot use the legacy default
stream) and replayed on PyTorch's *current* stream, so it is ordered with the torch ops around it without any host
synchronisation. On CPU, warp (>= 1.19) records the launches and replays them from C++, which removes the Python cost
of a few hundred launches per step; the recorded and the eager paths give bit-identical results.

Called while PyTorch captures a CUDA graph on its current stream (``torch.cuda.graph``), the launches join that
capture instead, so a larger graph (the env's whole step, see ``envs.autoreset``) can contain the physics.
"""

from __future__ import annotations

import contextlib
import gc
from typing import Callable

import torch
import warp as wp

__all__ = ["Recorded", "torch_stream_scope"]

_STREAMS: dict[tuple[str, int], wp.Stream] = {}


def _current_warp_stream(device: wp.Device) -> wp.Stream:
    """Warp's view of PyTorch's current stream on ``device`` (cached: wrapping registers the handle with warp)."""
    ts = torch.cuda.current_stream(wp.device_to_torch(device))
    key = (str(device), int(ts.cuda_stream))
    stream = _STREAMS.get(key)
    if stream is None:
        stream = _STREAMS[key] = wp.stream_from_torch(ts)
    return stream


def _capture_id(stream: wp.Stream) -> int | None:
    """CUDA's id of the capture in progress on ``stream`` (0 when none; None where warp does not expose it: warp has
    no public call for it, so this reads warp's runtime binding and skips the check if that ever moves)."""
    try:
        from warp._src.context import runtime

        return int(runtime.core.wp_cuda_stream_get_capture_id(stream.cuda_stream))
    except (ImportError, AttributeError):
        return None


def torch_stream_scope(device: wp.Device):
    """Context in which warp launches go to PyTorch's current stream (no-op on CPU)."""
    if not device.is_cuda:
        return contextlib.nullcontext()
    return wp.ScopedStream(_current_warp_stream(device), sync_enter=False)


@contextlib.contextmanager
def _no_gc():
    # A garbage collection during capture could finalise an unrelated warp object and record its free into the graph.
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


class Recorded:
    """``fn`` (a sequence of warp launches on ``device``) recorded as a graph; calling the object replays it.

    ``fn`` must not branch on device values; whatever it reads is read at replay time from the same arrays.
    With ``use_graph=False`` (or a CUDA device without warp's memory pool, which graph-captured allocations need)
    calling runs ``fn`` eagerly instead.
    """

    def __init__(self, fn: Callable[[], None], device: wp.Device, use_graph: bool = True):
        self.fn = fn
        self.device = device
        self.graph = None
        self._joined: list = []  # warp Graphs of the captures this object joined (see _join_torch_capture)
        if use_graph and device.is_cuda and not wp.is_mempool_enabled(device):
            print(
                f"[tocabi_torchrl.sim] warp memory pool disabled on {device}: running without CUDA graphs (slower); "
                "enable it with wp.set_mempool_enabled(device, True) before building the simulator",
                flush=True,
            )
            use_graph = False
        if use_graph:
            self._capture()

    def _capture(self) -> None:
        with _no_gc(), wp.ScopedDevice(self.device):
            if self.device.is_cuda:
                capture_stream = wp.Stream(self.device)
                with wp.ScopedStream(capture_stream, sync_enter=False), wp.ScopedCapture(stream=capture_stream) as cap:
                    self.fn()
                self._capture_stream = capture_stream  # the graph's memory-pool nodes belong to it; keep it alive
            else:
                with wp.ScopedCapture() as cap:
                    self.fn()
        self.graph = cap.graph

    def __call__(self) -> None:
        if self.device.is_cuda and torch.cuda.is_current_stream_capturing():
            self._join_torch_capture()
        elif self.graph is None:
            with wp.ScopedDevice(self.device), torch_stream_scope(self.device):
                self.fn()
        elif self.device.is_cuda:
            wp.capture_launch(self.graph, stream=_current_warp_stream(self.device))
        else:
            wp.capture_launch(self.graph)

    def _join_torch_capture(self) -> None:
        """Record ``fn``'s launches into the CUDA graph PyTorch is capturing on its current stream.

        A graph launch cannot be captured into another graph (and mujoco-warp's solver loop is a conditional node,
        which CUDA refuses inside a child graph), so the launches run live inside PyTorch's capture, registered
        with warp as an external capture so that warp's own conditional nodes and allocations join it.
        """
        stream = _current_warp_stream(self.device)
        capture_id = _capture_id(stream)
        with _no_gc(), wp.ScopedDevice(self.device), wp.ScopedStream(stream, sync_enter=False):
            # GLOBAL: warp pauses and resumes the capture around its conditional nodes; resume it in torch's mode.
            wp.capture_begin(stream=stream, force_module_load=False, external=True,
                             capture_mode=wp.CaptureMode.GLOBAL)
            try:
                self.fn()
            finally:
                graph = wp.capture_end(stream=stream)
        # The warp Graph holds the kernel modules the launches use: keep them loaded while the torch graph lives.
        self._joined.append(graph)
        if capture_id is not None and _capture_id(stream) != capture_id:
            # torch routes the capture's allocations to the graph's private pool by this id: after a change, the
            # torch ops recorded next would allocate outside it.
            raise RuntimeError(
                "warp's conditional nodes restarted PyTorch's CUDA graph capture under a new capture id; this "
                "warp/torch combination cannot join the physics into a torch graph (use cuda_graph=False)"
            )
