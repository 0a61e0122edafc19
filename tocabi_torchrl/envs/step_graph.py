"""``StepGraph``: one captured CUDA graph of an env's ``step_and_maybe_reset``, replayed with fresh outputs.

An env step of the walking task is a few hundred small torch launches around one physics graph; launched one by one
from Python, the host needs longer than the GPU needs to run them, so the GPU idles. Captured once and replayed, the
whole step (physics, signals, transforms, masked reset) is a single launch ("joined" mode), or five when the torch
graphs are cut around the simulator's own step and reset graphs ("segmented" mode).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDict, TensorDictBase

from ..cuda_graphs import CUDA_GRAPHS, Capturer

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
        generators: CUDA ``torch.Generator`` objects the step draws from besides the default one.
        stream: the side stream to capture on (best the one the warm-up calls ran on); a new one if None.
        mode: a capture mode of :func:`~tocabi_torchrl.cuda_graphs.capture_graph` ("joined" or "segmented").
        recorded: the simulator's recorded physics graphs the step calls.
        capturer: how to capture (:data:`~tocabi_torchrl.cuda_graphs.CUDA_GRAPHS`).
    """

    def __init__(self, step_fn: StepFn, example: TensorDictBase, generators: Sequence[torch.Generator] = (),
                 stream: torch.cuda.Stream | None = None, mode: str = "joined", recorded: Sequence = (),
                 capturer: Capturer = CUDA_GRAPHS):
        self.mode = mode
        self.keys = _sorted_keys(example)
        self._static_in = example.select(*self.keys).clone()
        self._in_leaves = [self._static_in.get(k) for k in self.keys]
        self._replay, (out, carry) = capturer.capture(lambda: step_fn(self._static_in.copy()), device=example.device,
                                                      stream=stream, generators=generators, mode=mode,
                                                      recorded=recorded)
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
        self._replay()
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
