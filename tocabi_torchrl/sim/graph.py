"""Record a sequence of warp launches once, replay it many times, on CPU and CUDA alike.

On CUDA the sequence becomes one CUDA graph. It is recorded on a private stream (capture cannot use the legacy default
stream) and replayed on PyTorch's *current* stream, so it is ordered with the torch ops around it without any host
synchronisation. On CPU, warp (>= 1.19) records the launches and replays them from C++, which removes the Python cost
of a few hundred launches per step; the recorded and the eager paths give bit-identical results.

A larger torch CUDA graph (the env's whole step, :mod:`tocabi_torchrl.cuda_graphs`) can contain these recordings in
one of two ways, chosen by the capture that registers them (:class:`JoinedCapture`, :class:`SegmentedCapture`): the
launches join torch's capture, or the torch capture is cut around the recorded graph, which is launched between the
torch graphs at replay. A :class:`Recorded` object only behaves differently while such a capture holds it.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import gc
from collections.abc import Callable, Sequence

import torch
import warp as wp

__all__ = ["Recorded", "JoinedCapture", "SegmentedCapture", "no_gc"]


def _capture_id(stream: wp.Stream) -> int | None:
    """CUDA's id of the capture in progress on ``stream`` (0 when none; None where it cannot be read).

    Neither warp nor torch has a public call for the id, so it is asked of the CUDA driver API itself
    (``cuStreamGetCaptureInfo``), which every CUDA machine has; the check that uses it is skipped where that fails.
    """
    fn = _driver_capture_info()
    if fn is None:
        return None
    status, capture = ctypes.c_int(0), ctypes.c_uint64(0)
    if fn(ctypes.c_void_p(stream.cuda_stream), ctypes.byref(status), ctypes.byref(capture)) != 0:
        return None
    return int(capture.value) if status.value == 1 else 0  # CU_STREAM_CAPTURE_STATUS_ACTIVE


@functools.cache
def _driver_capture_info() -> Callable | None:
    """``(stream, status*, id*) -> CUresult`` from libcuda (v3 on CUDA 13 drivers, v2 before), or None."""
    try:
        lib = ctypes.CDLL("libcuda.so.1")
    except OSError:
        return None
    null = ctypes.c_void_p(None)
    for name, extra in (("cuStreamGetCaptureInfo_v3", 4), ("cuStreamGetCaptureInfo_v2", 3)):
        fn = getattr(lib, name, None)
        if fn is not None:
            fn.restype = ctypes.c_int
            # The optional outputs (graph, dependencies, [edge data,] count) are not asked for: NULL pointers.
            return lambda s, st, cid, fn=fn, extra=extra: fn(s, st, cid, *([null] * extra))
    return None


@contextlib.contextmanager
def no_gc():
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
    calling runs ``fn`` eagerly instead. While a :class:`JoinedCapture` or :class:`SegmentedCapture` holds the object,
    a call is handed to that capture.
    """

    def __init__(self, fn: Callable[[], None], device: wp.Device, use_graph: bool = True):
        self.fn = fn
        self.device = device
        self.graph = None
        #: The capture this object is registered with (set only inside that capture's ``with`` block).
        self.held_by: JoinedCapture | SegmentedCapture | None = None
        self._joined: list = []  # warp Graphs of the captures this object joined (see _join_torch_capture)
        self._streams: dict[int, wp.Stream] = {}  # torch stream handle -> warp's wrapper of it
        if use_graph and device.is_cuda and not wp.is_mempool_enabled(device):
            print(
                f"[tocabi_torchrl.sim] warp memory pool disabled on {device}: running without CUDA graphs (slower); "
                "enable it with wp.set_mempool_enabled(device, True) before building the simulator",
                flush=True,
            )
            use_graph = False
        if use_graph:
            self._capture()

    def _torch_stream(self) -> wp.Stream:
        """Warp's view of PyTorch's current stream (cached: wrapping registers the handle with warp)."""
        ts = torch.cuda.current_stream(wp.device_to_torch(self.device))
        key = int(ts.cuda_stream)
        stream = self._streams.get(key)
        if stream is None:
            stream = self._streams[key] = wp.stream_from_torch(ts)
        return stream

    def _capture(self) -> None:
        with no_gc(), wp.ScopedDevice(self.device):
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
        if self.held_by is not None:
            self.held_by.launch(self)
            return
        if self.device.is_cuda and torch.cuda.is_current_stream_capturing():
            raise RuntimeError(
                "a recorded physics graph was called inside a torch CUDA graph capture that does not hold it; capture "
                "through tocabi_torchrl.cuda_graphs.capture_graph(..., recorded=...) so it joins or cuts the capture"
            )
        self.replay()

    def replay(self) -> None:
        """Run the recording (or ``fn`` eagerly without one) on PyTorch's current stream."""
        if self.graph is None:
            with wp.ScopedDevice(self.device), contextlib.ExitStack() as scope:
                if self.device.is_cuda:
                    scope.enter_context(wp.ScopedStream(self._torch_stream(), sync_enter=False))
                self.fn()
        elif self.device.is_cuda:
            wp.capture_launch(self.graph, stream=self._torch_stream())
        else:
            wp.capture_launch(self.graph)

    def _join_torch_capture(self) -> None:
        """Record ``fn``'s launches into the CUDA graph PyTorch is capturing on its current stream.

        A graph launch cannot be captured into another graph (and mujoco-warp's solver loop is a conditional node,
        which CUDA refuses inside a child graph), so the launches run live inside PyTorch's capture, registered
        with warp as an external capture so that warp's own conditional nodes and allocations join it.
        """
        stream = self._torch_stream()
        capture_id = _capture_id(stream)
        with no_gc(), wp.ScopedDevice(self.device), wp.ScopedStream(stream, sync_enter=False):
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


class _Holding:
    """Registers itself with the given :class:`Recorded` objects for the duration of its ``with`` block."""

    def __init__(self, recorded: Sequence[Recorded]):
        self.recorded = tuple(recorded)

    def _hold(self) -> None:
        if any(r.held_by is not None for r in self.recorded):
            raise RuntimeError("a recorded physics graph is already held by another capture")
        for r in self.recorded:
            r.held_by = self

    def _release(self) -> None:
        for r in self.recorded:
            if r.held_by is self:
                r.held_by = None

    def launch(self, recorded: Recorded) -> None:  # pragma: no cover - overridden
        raise NotImplementedError


class JoinedCapture(_Holding):
    """While torch captures a CUDA graph on its current stream (``torch.cuda.graph``), the held recordings' launches
    are recorded into that graph (:meth:`Recorded._join_torch_capture`): one graph, one launch per replay."""

    def __enter__(self) -> JoinedCapture:
        self._hold()
        return self

    def __exit__(self, *exc) -> None:
        self._release()

    def launch(self, recorded: Recorded) -> None:
        recorded._join_torch_capture()


class SegmentedCapture(_Holding):
    """Capture torch work and the held :class:`Recorded` warp graphs as alternating torch CUDA graphs and warp graph
    launches.

    Inside the ``with`` block, torch ops are captured into a torch CUDA graph on ``stream``; each call of a held
    :class:`Recorded` object ends that graph, is noted as a launch, and a new torch graph begins. :meth:`replay`
    runs the pieces in order on the current stream: a handful of launches per step, and no warp graph is ever nested
    in a torch one (the alternative to :class:`JoinedCapture`). The torch graphs share one memory pool and are always
    replayed in capture order, so tensors made in one piece and read in a later one stay valid.

    Args:
        stream: a side stream to capture on (capture cannot use the default stream).
        generators: custom CUDA generators the captured torch work draws from, registered with every piece.
        recorded: the recordings whose calls cut the capture.
    """

    def __init__(self, stream: torch.cuda.Stream, generators=(), recorded: Sequence[Recorded] = ()):
        super().__init__(recorded)
        self.stream = stream
        self.generators = tuple(generators)
        self.pool = torch.cuda.graph_pool_handle()
        self.pieces: list[Callable[[], None]] = []
        self._graph: torch.cuda.CUDAGraph | None = None
        self._stream_ctx = None

    def _begin(self) -> None:
        self._graph = torch.cuda.CUDAGraph()
        for gen in self.generators:
            self._graph.register_generator_state(gen)
        self._graph.capture_begin(pool=self.pool, capture_error_mode="global")

    def _end(self) -> None:
        graph, self._graph = self._graph, None
        graph.capture_end()
        self.pieces.append(graph.replay)

    def launch(self, recorded: Recorded) -> None:
        """Cut the torch capture here and replay ``recorded`` at this point."""
        self._end()
        self.pieces.append(recorded.replay)
        self._begin()

    def __enter__(self) -> SegmentedCapture:
        self._stream_ctx = torch.cuda.stream(self.stream)
        self._stream_ctx.__enter__()
        try:
            self._hold()
            self._begin()
        except BaseException as err:  # no __exit__ follows a failed __enter__: undo here, so eager calls still work
            self._release()
            self._stream_ctx.__exit__(type(err), err, err.__traceback__)
            raise
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if self._graph is not None:
                if exc_type is None:
                    self._end()
                else:
                    with contextlib.suppress(Exception):  # the capture failed already; leave capture mode
                        self._graph.capture_end()
                    self._graph = None
        finally:
            self._release()
            self._stream_ctx.__exit__(exc_type, exc, tb)

    def replay(self) -> None:
        for piece in self.pieces:
            piece()
