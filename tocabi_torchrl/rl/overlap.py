"""The PPO update on a side CUDA stream while the next rollout is collected (``ppo.overlap_update``).

mujoco-warp steps a few thousand worlds in kernels that leave most of a GPU's multiprocessors idle (its solver iterates
every world in lockstep, one thread per world in many kernels), and the trainer's update, a few hundred matrix-product
kernels per mini-batch, can fill them. :class:`UpdateOverlap` runs iteration k's update on a stream of its own and lets
the host go on to collect rollout k+1 on the training stream (:meth:`UpdateOverlap.collecting`: a stream of high
priority), with a copy of the actor taken before update k: each rollout is collected with the policy of one update
before. Measured against that policy (the rollout's stored log-probabilities), every mini-batch's ratio, clip and
approximate KL would also hold the previous update's move, and the adaptive learning rate would fall for it (a pd-preset
run sat at its floor, docs/training/pd/h100_overlap_seed0). So the trainer makes the update decoupled PPO
(``GuardedClipPPOLoss.use_proximal``): before each update it stores each frame's log-probability under the policy the
update starts from, and the ratio, clip and KL are taken from that one.

Order, per iteration (host): :meth:`finish` waits for the previous update and hands back its losses; the trainer then
reads the learner (GAE's critic, the teacher, the symmetry's statistics), sets its schedules, :meth:`refresh` copies the
learner's actor into the collector's (on the training stream), and :meth:`launch` starts the update on the side stream
after everything queued on the training stream so far. What the update reads (the rollout's flattened copy: the
trainer's is the update step's own buffer, ``MinibatchStep.keep``) is not written again before :meth:`finish`, and
:meth:`launch`'s ``keep`` holds a reference until then, so the allocator cannot hand memory the side stream still reads
to the next rollout. The losses come back through pinned memory (:class:`~.deferred_read.DeferredRead`, copied on the
side stream): :meth:`finish` waits for that update alone, not for the rollout queued on the training stream since. On a
CPU there is no stream: :meth:`launch` runs the update at once, in the same order, so a CPU run trains exactly as a GPU
run would without the concurrency.

>>> import torch
>>> actor = torch.nn.Linear(2, 1)
>>> overlap = UpdateOverlap(torch.device("cpu"), actor)
>>> overlap.collect_actor is actor, overlap.finish()
(False, None)
>>> with torch.no_grad():
...     _ = actor.weight.add_(1.0)  # an update of the learner
>>> overlap.refresh()
>>> torch.equal(overlap.collect_actor.weight, actor.weight)
True
>>> overlap.launch(lambda: torch.tensor([0.5]), keep=None)
>>> overlap.annotate({"iteration": 1})
>>> overlap.finish()
([0.5], {'iteration': 1})
"""

from __future__ import annotations

import contextlib
import copy
import threading
from collections.abc import Callable, Iterator
from typing import Any

import torch

from .deferred_read import DeferredRead

__all__ = ["UpdateOverlap"]


class UpdateOverlap:
    """One update in flight at a time on a side stream (CUDA), or run inline (CPU, or ``side_stream=False``).

    Args:
        device: the training device.
        actor: the learner's actor; :attr:`collect_actor` is a copy of it (parameters and buffers, e.g. the scheduled
            action std) that the collector acts with, refreshed by :meth:`refresh`.
        side_stream: False: no overlap (``ppo.overlap_update`` off). :meth:`launch` queues the update on the training
            stream, the collector acts with the learner itself (:attr:`collect_actor` is ``actor``, :meth:`refresh`
            copies nothing), and only the read of its losses waits for the next rollout to be queued: the trainer
            then never waits for the GPU's queue between two rollouts, and trains exactly as it reads at once.
        collect_first: with a side stream, collect on a stream of CUDA's high priority (:meth:`collecting`), so that
            wherever the physics and the update both wait for a multiprocessor, the physics' blocks go first.
            False: both on streams of one priority (an ablation: the numbers computed are the same, only the GPU's
            order of blocks differs).
    """

    def __init__(self, device: torch.device, actor: torch.nn.Module, side_stream: bool = True,
                 collect_first: bool = True):
        self.device = device
        # CUDA's lowest priority (0, also the default stream's): below the collection's stream, if it has its own.
        self.stream = torch.cuda.Stream(device, priority=0) if device.type == "cuda" and side_stream else None
        #: The high-priority stream :meth:`collecting` runs the rollout on (None: the caller's stream).
        self.collect_stream = (torch.cuda.Stream(device, priority=-1) if self.stream is not None and collect_first
                               else None)
        self.collect_actor = copy.deepcopy(actor) if side_stream else actor
        if side_stream:
            self.collect_actor.requires_grad_(False)
        self._learner = actor
        self._pairs = _state_pairs(self.collect_actor, actor) if side_stream else []
        self._pending: tuple[Any, Any, Any] | None = None  # (its _Queuing or None, what it keeps, its context)
        self._losses = DeferredRead()
        #: Set to a list to record each update's (start, done) CUDA events on the side stream (a benchmark's timeline;
        #: None: nothing recorded).
        self.spans: list[tuple[torch.cuda.Event, torch.cuda.Event]] | None = None

    @contextlib.contextmanager
    def collecting(self) -> Iterator[None]:
        """Run the block (the training loop: the rollouts and what the host queues between them) on
        :attr:`collect_stream`, after the work queued on the current stream so far; the current stream waits for it
        on the way out. Without that stream, the block runs on the current stream.

        The physics of a step is a chain of short kernels of a few blocks each, which waits whenever the update's
        wide matrix products hold the multiprocessors; CUDA's block scheduler gives the next free one to a waiting
        block of the higher-priority stream first, so the update is meant to fill what the physics leaves idle."""
        if self.collect_stream is None:
            yield
            return
        outer = torch.cuda.current_stream(self.device)
        self.collect_stream.wait_stream(outer)
        try:
            with torch.cuda.stream(self.collect_stream):
                yield
        finally:
            outer.wait_stream(self.collect_stream)

    @property
    def in_flight(self) -> bool:
        """Whether an update has been launched and not yet :meth:`finish`-ed."""
        return self._pending is not None

    def refresh(self) -> None:
        """Copy the learner's actor into :attr:`collect_actor` on the current (training) stream. Call it after
        :meth:`finish`: the copy must not race an update."""
        if self._pending is not None:
            raise RuntimeError("UpdateOverlap.refresh() while an update is in flight: call finish() first")
        if not self._pairs:  # side_stream=False: the collector acts with the learner itself
            return
        with torch.no_grad():
            torch._foreach_copy_([dst for dst, _ in self._pairs], [src for _, src in self._pairs])

    def launch(self, update: Callable[[], torch.Tensor], keep: Any, *, threaded: bool = False) -> None:
        """Start ``update()`` (which returns a 1-D device tensor of the numbers to read back: its losses and what
        the caller reads with them) on the side stream (without one: at once, on the current stream), after the work
        already queued on the current stream; ``keep`` (what the update reads) stays referenced until
        :meth:`finish`, which also hands back the context :meth:`annotate` gave it (None without one).

        ``threaded``: queue it from a host thread of its own and return at once. Queuing a few thousand captured
        kernels per mini-batch can block the host in CUDA's launch queue until the GPU has run most of the update
        (at 16,384 envs on an H100: 241 ms, during which the next rollout was not queued and the GPU ran no
        physics); from a thread, the host queues the next rollout meanwhile. Only for an ``update`` that captures
        nothing, records no autograd graph, draws no random numbers and changes no process-wide setting (the thread
        would race the collector for them: tensordict's sampling mode, which a TensorDict module's ``get_dist`` or a
        TorchRL loss's ``forward`` sets and restores, left rollouts acting without exploration): replays of captured
        graphs, and plain torch under ``torch.no_grad`` on modules the collector does not run (the trainer's proximal
        log-probabilities); ignored without a side stream.
        """
        if self._pending is not None:
            raise RuntimeError("UpdateOverlap.launch() with an update in flight: call finish() first")
        if self.stream is None:
            self._losses.start(update())
            self._pending = (None, keep, None)
            return
        ready = torch.cuda.current_stream(self.device).record_event()
        queuing = _Queuing(self, update, ready)
        if threaded:
            queuing.thread = threading.Thread(target=queuing.run, name="ppo-update-launch", daemon=True)
            self._pending = (queuing, keep, None)  # first: a Ctrl-C right after the start still finds it to wait for
            queuing.thread.start()
        else:
            queuing.run()
            queuing.raise_error()
            self._pending = (queuing, keep, None)

    def _queue(self, update: Callable[[], torch.Tensor], ready: torch.cuda.Event) -> torch.cuda.Event:
        """Queue ``update()`` on the side stream after ``ready``, its losses' copy after it; the update's end event.
        Runs on the launching host thread (the current stream is a thread's own)."""
        with torch.cuda.device(self.device), torch.cuda.stream(self.stream):
            self.stream.wait_event(ready)
            start = self.stream.record_event(torch.cuda.Event(enable_timing=True)) if self.spans is not None else None
            try:
                # Read back through pinned memory on this stream: finish() then waits for the update alone, where a
                # .tolist() there would wait for the rollout queued on the training stream since.
                self._losses.start(update())
            except BaseException:
                # Kernels it queued may still read what the caller is about to free: let them end first.
                self.stream.synchronize()
                raise
            done = self.stream.record_event(torch.cuda.Event(enable_timing=self.spans is not None))
        if self.spans is not None:
            self.spans.append((start, done))
        return done

    def annotate(self, context: Any) -> None:
        """Give the in-flight update a ``context`` (what the host learnt after launching it) for :meth:`finish`."""
        if self._pending is None:
            raise RuntimeError("UpdateOverlap.annotate() with no update in flight")
        self._pending = (*self._pending[:2], context)

    def finish(self) -> tuple[list[float], Any] | None:
        """Wait (host) for the update in flight and return its numbers as floats and its ``context``; None when no
        update is in flight. Releases what :meth:`launch` kept. An error raised while the update was queued from its
        thread is raised here."""
        if self._pending is None:
            return None
        queuing, _keep, context = self._pending
        if queuing is not None:
            if queuing.thread is not None:
                if queuing.cancel_unless_begun():  # launch() was interrupted before the thread began: nothing queued
                    self._pending = None
                    return None
                queuing.thread.join()
            if queuing.error is not None:  # raised while queuing from the thread: this update is lost
                self._pending, self._losses = None, DeferredRead()
                raise queuing.error
            queuing.done.synchronize()  # the update's end (the copy's own event comes just before it)
        values = self._losses.values()
        self._pending = None
        return values, context


class _Queuing:
    """One update being queued on the side stream, inline or from a host thread (:meth:`UpdateOverlap.launch`)."""

    def __init__(self, overlap: UpdateOverlap, update: Callable[[], torch.Tensor], ready: torch.cuda.Event):
        self._overlap, self._update, self._ready = overlap, update, ready
        self.thread: threading.Thread | None = None
        self.done: torch.cuda.Event | None = None
        self.error: BaseException | None = None
        self._lock = threading.Lock()
        self._began = self._cancelled = False

    def cancel_unless_begun(self) -> bool:
        """Make a :meth:`run` that has not begun return at once; whether it had not (nothing was queued)."""
        with self._lock:
            self._cancelled = not self._began
            return self._cancelled

    def run(self) -> None:
        with self._lock:  # a thread interrupted as it started may run after finish() gave up on it
            if self._cancelled:
                return
            self._began = True
        try:
            self.done = self._overlap._queue(self._update, self._ready)
        except BaseException as err:  # noqa: BLE001 - raised by finish() (threaded) or raise_error() (inline)
            self.error = err
        self._update = None  # what the closure holds (the rollout's rows) is the caller's `keep` from here on

    def raise_error(self) -> None:
        if self.error is not None:
            raise self.error


def _state_pairs(copy_of: torch.nn.Module, original: torch.nn.Module) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """(copy, original) tensor pairs of two modules of one structure: parameters, then floating-point buffers."""
    pairs = [(a, b) for a, b in zip(copy_of.parameters(), original.parameters(), strict=True)]
    pairs += [(a, b) for a, b in zip(copy_of.buffers(), original.buffers(), strict=True)
              if a.is_floating_point()]
    return pairs
