"""The PPO update on a side CUDA stream while the next rollout is collected (``ppo.overlap_update``).

mujoco-warp steps a few thousand worlds in kernels that leave most of a GPU's multiprocessors idle (its solver
iterates every world in lockstep, one thread per world in many kernels), and the trainer's update, a few hundred
matrix-product kernels per mini-batch, can fill them. :class:`UpdateOverlap` runs iteration k's update on a stream of
its own and lets the host go on to collect rollout k+1 on the training stream, with a copy of the actor taken before
update k: each rollout is collected with the policy of one update before. PPO takes its ratio against the policy that
acted (the rollout stores its log-probabilities), so every mini-batch's ratio, clip and approximate KL are measured
from one update back: the clip's trust region sits there, and the KL the adaptive learning rate reads also holds
the previous update's move (roughly twice an update's own), so that rule lowers the rate more often than without
the overlap. Whether that costs time to walk is for a from-scratch run to show.

Order, per iteration (host): :meth:`finish` waits for the previous update and hands back its losses; the trainer
then reads the learner (GAE's critic, the teacher, the symmetry's statistics), sets its schedules, :meth:`refresh`
copies the learner's actor into the collector's (on the training stream), and :meth:`launch` starts the update on
the side stream after everything queued on the training stream so far. What the update reads (the rollout's
flattened copy: the trainer's is the update step's own buffer, ``MinibatchStep.keep``) is not written again before
:meth:`finish`, and :meth:`launch`'s ``keep`` holds a reference until then, so the allocator cannot hand memory the
side stream still reads to the next rollout. The losses come back through pinned memory
(:class:`~.deferred_read.DeferredRead`, copied on the side stream): :meth:`finish` waits for that update alone, not for the rollout queued on the training
stream since. On a CPU there is no stream: :meth:`launch` runs the update at once, in the same
order, so a CPU run trains exactly as a GPU run would without the concurrency.

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

import copy
from collections.abc import Callable
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
    """

    def __init__(self, device: torch.device, actor: torch.nn.Module, side_stream: bool = True):
        self.device = device
        self.stream = torch.cuda.Stream(device) if device.type == "cuda" and side_stream else None
        self.collect_actor = copy.deepcopy(actor) if side_stream else actor
        if side_stream:
            self.collect_actor.requires_grad_(False)
        self._learner = actor
        self._pairs = _state_pairs(self.collect_actor, actor) if side_stream else []
        self._pending: tuple[Any, Any, Any] | None = None  # (done event or None, what it keeps, its context)
        self._losses = DeferredRead()
        #: Set to a list to record each update's (start, done) CUDA events on the side stream (a benchmark's timeline;
        #: None: nothing recorded).
        self.spans: list[tuple[torch.cuda.Event, torch.cuda.Event]] | None = None

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

    def launch(self, update: Callable[[], torch.Tensor], keep: Any) -> None:
        """Start ``update()`` (which returns a 1-D device tensor of the numbers to read back: its losses and what
        the caller reads with them) on the side stream (without one: at once, on the current stream), after the work
        already queued on the current stream; ``keep`` (what the update reads) stays referenced until
        :meth:`finish`, which also hands back the context :meth:`annotate` gave it (None without one)."""
        if self._pending is not None:
            raise RuntimeError("UpdateOverlap.launch() with an update in flight: call finish() first")
        if self.stream is None:
            self._losses.start(update())
            self._pending = (None, keep, None)
            return
        ready = torch.cuda.current_stream(self.device).record_event()
        with torch.cuda.stream(self.stream):
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
        self._pending = (done, keep, None)

    def annotate(self, context: Any) -> None:
        """Give the in-flight update a ``context`` (what the host learnt after launching it) for :meth:`finish`."""
        if self._pending is None:
            raise RuntimeError("UpdateOverlap.annotate() with no update in flight")
        self._pending = (*self._pending[:2], context)

    def finish(self) -> tuple[list[float], Any] | None:
        """Wait (host) for the update in flight and return its numbers as floats and its ``context``; None when no
        update is in flight. Releases what :meth:`launch` kept."""
        if self._pending is None:
            return None
        done, _keep, context = self._pending
        if done is not None:  # the update's end (the copy's own event comes just before it)
            done.synchronize()
        values = self._losses.values()
        self._pending = None
        return values, context


def _state_pairs(copy_of: torch.nn.Module, original: torch.nn.Module) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """(copy, original) tensor pairs of two modules of one structure: parameters, then floating-point buffers."""
    pairs = [(a, b) for a, b in zip(copy_of.parameters(), original.parameters(), strict=True)]
    pairs += [(a, b) for a, b in zip(copy_of.buffers(), original.buffers(), strict=True)
              if a.is_floating_point()]
    return pairs
