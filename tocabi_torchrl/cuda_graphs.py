"""CUDA graphs in one place: when to capture (:func:`plan_graphs`, :func:`env_graph_blockers`), how to capture
(:func:`capture_graph`), and the warm-up / capture / fallback sequence (:class:`WarmCapture`) that the env step
(``envs.autoreset.SyncFreeResetEnv``) and the PPO update (``rl.update_step.MinibatchStep``) both use.

Why graphs: an env step is a few hundred small torch launches around one physics graph and a PPO mini-batch step
~300 more; launched one by one from Python the host is slower than the GPU, which idles. Captured once and
replayed, each is one launch (or a few).

Capture rules followed here (``torch.cuda.graphs``): warm-up calls run on the side stream the capture will use (lazy
per-stream set-up happens outside the capture); no garbage collection during the capture (a finaliser could record
a free); the captured function reads and writes only static buffers, which the callers refill in place.

How the capture is done is an object (:class:`CudaGraphCapture`), passed to the helpers: the package always uses
:data:`CUDA_GRAPHS`; a machine without CUDA can run the same bookkeeping with another implementation of the two
methods (the test suite's ``tests/graph_emulation.py`` replays by calling the function again).
"""

from __future__ import annotations

import gc
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import torch

from .sim.graph import JoinedCapture, Recorded, SegmentedCapture, no_gc

__all__ = ["ENV_GRAPH_AUTO_MAX_ENVS", "CAPTURE_MODES", "GraphPlan", "plan_graphs",
           "env_graph_blockers", "Capturer", "CudaGraphCapture", "CUDA_GRAPHS", "capture_graph", "WarmCapture"]

#: Largest env count for which ``ppo.cuda_graph="auto"`` captures the env step: the graph won at 96 envs and lost at
#: 256 on an H100 (128 only in short memory-sweep runs, see docs/benchmarks/env_graph.md): from 256 envs on the
#: collection is GPU-bound and the graph's copies cost more than the launches it saves.
ENV_GRAPH_AUTO_MAX_ENVS = 128
#: How a step that contains the simulator's recorded physics graphs is captured (see :func:`capture_graph`).
CAPTURE_MODES = ("joined", "segmented")


@dataclass(frozen=True)
class GraphPlan:
    """Which parts of a training run are captured as CUDA graphs."""

    env_step: bool
    update: bool


def env_graph_blockers(device: torch.device, sync_free_resets: bool = True, compile_reward: bool = False) -> list[str]:
    """Why an env step could not be captured (empty when it can), each reason with its fix."""
    blockers = []
    if device.type != "cuda":
        blockers.append(f"cuda_graph=True needs a CUDA device, got device={str(device)!r}; pass cuda_graph=False")
    if not sync_free_resets:
        blockers.append("cuda_graph=True needs sync_free_resets=True: a step that reads device values on the host "
                        "cannot be captured")
    if compile_reward:
        blockers.append("compile_reward=True and cuda_graph=True do not combine (a recompile inside the capture would "
                        "break it); the CUDA graph already removes the launches torch.compile saves")
    return blockers


def plan_graphs(cfg: Any, device: torch.device, num_envs: int | None = None, *, sync_free_resets: bool = True,
                compile_reward: bool = False) -> GraphPlan:
    """The one decision of what a run captures.

    Args:
        cfg: the run config (``cfg.ppo.cuda_graph``: "on", "off" or "auto"; ``cfg.ppo.update_graph``;
            ``cfg.env.num_envs`` and ``cfg.transforms.compile_reward``).
        device: where the run trains; nothing is captured off CUDA (the GPU options are ignored on the CPU).
        num_envs: the env count, if not ``cfg.env.num_envs``.
        sync_free_resets, compile_reward: how the env is built (``compile_reward`` or ``cfg.transforms``'s).

    The env step: "on" always (``make_env`` then says why it cannot, see :func:`env_graph_blockers`), "auto" up to
    :data:`ENV_GRAPH_AUTO_MAX_ENVS` envs when nothing blocks it. The update: ``ppo.update_graph``.
    """
    if device.type != "cuda":
        return GraphPlan(env_step=False, update=False)
    mode = cfg.ppo.cuda_graph  # checked by PPOConfig.validate
    blocked = env_graph_blockers(device, sync_free_resets, compile_reward or cfg.transforms.compile_reward)
    small = (num_envs or cfg.env.num_envs) <= ENV_GRAPH_AUTO_MAX_ENVS
    env_step = mode == "on" or (mode == "auto" and small and not blocked)
    return GraphPlan(env_step=env_step, update=bool(cfg.ppo.update_graph))


class Capturer(Protocol):
    """How a function is captured and replayed (:class:`CudaGraphCapture` on CUDA)."""

    def supports(self, device: torch.device) -> bool:
        """Whether functions on ``device`` can be captured."""

    def side_stream(self, device: torch.device) -> torch.cuda.Stream | None:
        """A stream for warm-up calls and the capture (None: run on the current one)."""

    def capture(self, fn: Callable[[], Any], *, device: torch.device, stream, generators: Sequence = (),
                mode: str = "joined", recorded: Sequence[Recorded] = ()) -> tuple[Callable[[], None], Any]:
        """Capture ``fn()``; return ``(replay, result)``: each ``replay()`` reruns it, rewriting ``result``'s tensors
        in place."""


class CudaGraphCapture:
    """Capture on CUDA (:func:`capture_graph`)."""

    def supports(self, device: torch.device) -> bool:
        return device is not None and device.type == "cuda"

    def side_stream(self, device: torch.device) -> torch.cuda.Stream:
        return torch.cuda.Stream(device)

    def capture(self, fn, *, device, stream, generators=(), mode="joined", recorded=()):
        return capture_graph(fn, device=device, stream=stream, generators=generators, mode=mode, recorded=recorded)


#: The capturer the package uses.
CUDA_GRAPHS = CudaGraphCapture()


def capture_graph(fn: Callable[[], Any], *, device: torch.device, stream: torch.cuda.Stream | None = None,
                  generators: Sequence[torch.Generator] = (), mode: str = "joined",
                  recorded: Sequence[Recorded] = ()) -> tuple[Callable[[], None], Any]:
    """Capture ``fn()`` (torch work, and the simulator's recorded warp graphs ``recorded`` it calls) as CUDA graphs.

    Returns ``(replay, result)``: ``result`` is what the capture's ``fn()`` returned (its tensors are the static
    outputs, rewritten by every ``replay()``); the capture itself does not run the work.

    Args:
        device: a CUDA device.
        stream: the side stream to capture on (best the one the warm-up ran on); a new one if None.
        generators: CUDA ``torch.Generator`` objects ``fn`` draws from besides the default one; their offsets advance
            on every replay as in eager mode.
        mode: ``"joined"``: one torch CUDA graph, the physics recorded into it through warp's external capture
            (:class:`~tocabi_torchrl.sim.graph.JoinedCapture`); ``"segmented"``: torch graphs cut around the physics,
            whose own warp graphs are launched between them (:class:`~tocabi_torchrl.sim.graph.SegmentedCapture`,
            a few launches per step, nothing nested).
        recorded: the :class:`~tocabi_torchrl.sim.graph.Recorded` graphs ``fn`` may call.
    """
    if device is None or device.type != "cuda":
        raise ValueError(f"a CUDA graph captures CUDA work; got device {device}")
    if mode not in CAPTURE_MODES:
        raise ValueError(f"capture mode must be one of {CAPTURE_MODES}, got {mode!r}")
    stream = stream if stream is not None else torch.cuda.Stream(device)
    stream.wait_stream(torch.cuda.current_stream(device))
    # No garbage collection while capturing: freeing an unrelated warp array could call cudaFree, which a "global"
    # capture forbids (torch.cuda.graph collects once before it starts).
    gc.collect()
    with no_gc():
        if mode == "joined":
            graph = torch.cuda.CUDAGraph()
            for gen in generators:
                graph.register_generator_state(gen)
            with JoinedCapture(recorded), torch.cuda.graph(graph, stream=stream):
                result = fn()
            replay = graph.replay
        else:
            torch.cuda.synchronize(device)  # as torch.cuda.graph does before a capture
            with SegmentedCapture(stream, generators, recorded) as segmented:
                result = fn()
            replay = segmented.replay
    torch.cuda.current_stream(device).wait_stream(stream)
    return replay, result


class WarmCapture:
    """Warm up, capture, replay; on failure warn and stay eager. Shared by the env step and the PPO update.

    ``run(*args)``: the first ``warmup`` calls run ``eager(*args)`` on the side stream the capture will use; the next
    call builds the replayer with ``build(args, stream, mode)`` for each mode of ``modes`` in turn until one succeeds
    (the builder captures through ``capturer``) and returns ``replayer(*args)``; from then on every call replays. If
    every mode fails, it warns once (naming each mode's error) and runs eagerly for good.

    Args:
        name: who captures, for the warnings (``"SyncFreeResetEnv"``, ``"MinibatchStep"``).
        what: what is captured, for the warnings ("the step", "the PPO update").
        eager: the uncaptured function.
        build: ``(args, stream, mode) -> replayer``, where ``replayer(*args)`` does what ``eager(*args)`` does.
        warmup: eager calls before the capture (>= 1).
        modes: capture modes to try, in order.
        capturer: how to capture (:data:`CUDA_GRAPHS`).
        warmup_option: the caller's name for ``warmup``, for the error on a bad value.
    """

    def __init__(self, name: str, what: str, eager: Callable, build: Callable, *, warmup: int,
                 modes: Sequence[str] = ("joined",), capturer: Capturer = CUDA_GRAPHS,
                 warmup_option: str = "warmup"):
        if isinstance(warmup, bool) or not isinstance(warmup, int) or warmup < 1:
            raise ValueError(f"{name}: {warmup_option} must be an int >= 1 (eager calls before the capture), "
                             f"got {warmup!r}")
        self.name, self.what, self.eager, self.build = name, what, eager, build
        self.warmup, self.modes, self.capturer = warmup, tuple(modes), capturer
        self.replayer: Callable | None = None
        #: The mode of the capture in use (None until captured).
        self.mode: str | None = None
        self.gave_up = False
        self._calls = 0
        self._stream = None

    @property
    def captured(self) -> bool:
        """Whether calls now replay a captured graph."""
        return self.replayer is not None

    def reset(self) -> None:
        """Drop the capture; the next calls warm up and capture again (after a Python-side setting changed). A
        capture that failed is not retried (clear ``gave_up`` for that)."""
        self.replayer, self.mode, self._calls = None, None, 0

    def run(self, device: torch.device, *args):
        if self.replayer is not None:
            return self.replayer(*args)
        if self.gave_up:
            return self.eager(*args)
        self._calls += 1
        if self._calls <= self.warmup:
            return self._on_side_stream(device, *args)
        failures = []
        for mode in self.modes:
            try:
                self.replayer = self.build(args, self._stream, mode)
                self.mode = mode
                break
            except Exception as err:  # noqa: BLE001 - any capture failure: try the next mode, say why
                failures.append(f"{mode}: {type(err).__name__}: {err}")
        if failures:
            outcome = f"using the {self.mode!r} capture" if self.replayer is not None else "running eagerly from now on"
            warnings.warn(f"{self.name}: capturing {self.what} as a CUDA graph failed ({'; '.join(failures)}); "
                          f"{outcome}", stacklevel=3)
        if self.replayer is None:
            self.gave_up = True
            return self.eager(*args)
        return self.replayer(*args)  # the capture recorded the work without running it; this replay runs it

    def _on_side_stream(self, device: torch.device, *args):
        if self._stream is None:
            self._stream = self.capturer.side_stream(device)
        if self._stream is None:
            return self.eager(*args)
        current = torch.cuda.current_stream(device)
        self._stream.wait_stream(current)
        with torch.cuda.stream(self._stream):
            out = self.eager(*args)
        current.wait_stream(self._stream)
        return out
