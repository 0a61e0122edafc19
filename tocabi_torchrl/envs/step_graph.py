"""``StepGraph``: one captured CUDA graph of an env's ``step_and_maybe_reset``, replayed with fresh outputs.

An env step of the walking task is a few hundred small torch launches around one physics graph; launched one by one
from Python, the host needs longer than the GPU needs to run them, so the GPU idles. Captured once and replayed, the
whole step (physics, signals, transforms, masked reset) is a single launch ("joined" mode), or five when the torch
graphs are cut around the simulator's own step and reset graphs ("segmented" mode).
"""

from __future__ import annotations

import gc
from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDict, TensorDictBase

from ..sim.graph import SegmentedCapture, no_gc

__all__ = ["StepGraph"]

StepFn = Callable[[TensorDictBase], "tuple[TensorDictBase, TensorDictBase]"]


def _sorted_keys(td: TensorDictBase) -> tuple:
    return tuple(sorted(td.keys(True, True), key=str))


class StepGraph:
    """A captured ``step_fn(td) -> (td_with_next, carry)`` with static input and output buffers.

    Replaying copies the caller's input leaves into the static inputs (one ``_foreach_copy_``), replays the graph, and
    copies the static outputs into freshly allocated tensors (one more), so every call returns tensors that later
    calls never overwrite, exactly as the eager function does. The outputs keep the eager function's aliasing: a
    carry-over entry that is the same tensor as a ``"next"`` entry stays one tensor. Nothing reads device values on
    the host.

    What the graph freezes: every Python value the step reads (config fields, seeds, flags such as
    ``RunningNormalization.frozen``) and every tensor's address. State must therefore be updated in place, and
    changing a Python-side setting needs a new capture (``SyncFreeResetEnv.invalidate_graph``).

    Args:
        step_fn: the eager step (``SyncFreeResetEnv._eager_step_and_maybe_reset``).
        example: an input of the shape and keys the graph will take (its values are only copied).
        generators: CUDA ``torch.Generator`` objects the step draws from besides the default one; their offsets
            advance on every replay as in eager mode.
        stream: the side stream to capture on (best the one the last eager warm-up call ran on); a new one if None.
        mode: ``"joined"``: one torch CUDA graph, the physics recorded into it through warp's external capture
            (:meth:`~tocabi_torchrl.sim.graph.Recorded._join_torch_capture`); ``"segmented"``: torch graphs cut
            around the physics, whose own warp graphs are launched between them
            (:class:`~tocabi_torchrl.sim.graph.SegmentedCapture`, a few launches per step, nothing nested).
        emulate: instead of capturing (CUDA only), call ``step_fn`` on the static inputs at every call and keep
            its outputs as the static outputs. Same bookkeeping and one step per call, no graph: this is how the
            wiring is tested without a GPU.
    """

    def __init__(self, step_fn: StepFn, example: TensorDictBase, generators: Sequence[torch.Generator] = (),
                 emulate: bool = False, stream: torch.cuda.Stream | None = None, mode: str = "joined"):
        device = example.device
        if not emulate and (device is None or device.type != "cuda"):
            raise ValueError(f"StepGraph captures CUDA work; the input tensordict is on {device}")
        if mode not in ("joined", "segmented"):
            raise ValueError(f"StepGraph mode must be 'joined' or 'segmented', got {mode!r}")
        self.mode = mode
        self.keys = _sorted_keys(example)
        self._static_in = example.select(*self.keys).clone()
        self._in_leaves = [self._static_in.get(k) for k in self.keys]
        self._step_fn, self._replay = step_fn, None
        if emulate:
            return  # the outputs' layout is taken from the first call
        stream = stream if stream is not None else torch.cuda.Stream(device)
        stream.wait_stream(torch.cuda.current_stream(device))
        # No garbage collection while capturing: freeing an unrelated warp array could call cudaFree, which a
        # "global" capture forbids (torch.cuda.graph collects once before it starts).
        gc.collect()
        with no_gc():
            if mode == "joined":
                graph = torch.cuda.CUDAGraph()
                for gen in generators:
                    graph.register_generator_state(gen)
                with torch.cuda.graph(graph, stream=stream):
                    out, carry = step_fn(self._static_in.copy())
                self._replay = graph.replay
            else:
                torch.cuda.synchronize(device)  # as torch.cuda.graph does before a capture
                with SegmentedCapture(stream, generators) as segmented:
                    out, carry = step_fn(self._static_in.copy())
                self._replay = segmented.replay
        torch.cuda.current_stream(device).wait_stream(stream)
        self._set_outputs(out, carry)

    def _set_outputs(self, out: TensorDictBase, carry: TensorDictBase) -> None:
        self._next = out.get("next")
        self._carry = carry
        self._next_keys = _sorted_keys(self._next)
        self._carry_keys = _sorted_keys(self._carry)
        self._next_leaves = [self._next.get(k) for k in self._next_keys]
        self._carry_leaves = [self._carry.get(k) for k in self._carry_keys]
        # Output buffers the carry shares with "next" (or with the input) are copied once.
        unique: dict[int, torch.Tensor] = {}
        for t in self._next_leaves + self._carry_leaves:
            unique.setdefault(id(t), t)
        self._unique = list(unique.values())
        self._slot = {key: i for i, key in enumerate(unique)}

    def accepts(self, td: TensorDictBase) -> bool:
        """Whether ``td`` has exactly the keys the graph was captured with (shapes are fixed by the env's specs)."""
        return _sorted_keys(td) == self.keys

    def __call__(self, td: TensorDictBase) -> tuple[TensorDictBase, TensorDictBase]:
        torch._foreach_copy_(self._in_leaves, [td.get(k) for k in self.keys])
        if self._replay is not None:
            self._replay()
        else:
            out, carry = self._step_fn(self._static_in.copy())
            self._set_outputs(out, carry)  # these fresh outputs act as the static ones
        fresh = [torch.empty_like(t) for t in self._unique]
        torch._foreach_copy_(fresh, self._unique)
        pick = lambda leaves: [fresh[self._slot[id(t)]] for t in leaves]  # noqa: E731
        nxt = self._build(self._next, self._next_keys, pick(self._next_leaves))
        carry = self._build(self._carry, self._carry_keys, pick(self._carry_leaves))
        td.set("next", nxt)
        return td, carry

    @staticmethod
    def _build(like: TensorDictBase, keys: tuple, leaves: list[torch.Tensor]) -> TensorDictBase:
        out = TensorDict(batch_size=like.batch_size, device=like.device)
        for key, value in zip(keys, leaves):
            out.set(key, value)
        return out
