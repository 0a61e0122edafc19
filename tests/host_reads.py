"""What the adapters' host copies are checked with: a tensor that counts each read of its values on the host, and a
crafted step result holding values a cast would change (for the tests of the numpy adapters, SB3's and gymnasium's
numpy mode). And what the training step's per-step paths are checked with on CPU: a dispatch mode recording each op
that would synchronise with the host on CUDA (:class:`HostSyncOps`), and a function mode recording where values are
read into Python (:class:`HostValueReads`)."""

from __future__ import annotations

import collections
import functools
import os
import traceback

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode

from tocabi_torchrl.adapters._core import StepResult

#: The StepResult fields that are tensors (``reward_terms`` is a dict of them).
STEP_TENSORS = ("obs", "final_obs", "reward", "terminated", "truncated", "done", "episode_return", "episode_length")


class HostReads(torch.Tensor):
    """A tensor counting each read of its values on the host (a copy to the CPU, or a value Python reads), on it
    and on every tensor computed from it: each is a copy, and a synchronisation on a GPU. The names of the reads
    collect in :attr:`reads` (a test resets it with ``monkeypatch.setattr(HostReads, "reads", [])``)."""

    reads: list = []
    _READS = {"cpu", "numpy", "tolist", "item", "__array__", "__bool__", "__float__", "__int__", "__index__",
              "nonzero", "argwhere", "masked_select"}

    @classmethod
    def __torch_function__(cls, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = getattr(func, "__name__", "")
        to_cpu = name == "to" and any(isinstance(a, (str, torch.device)) and torch.device(a).type == "cpu"
                                      for a in (*args[1:], kwargs.get("device", "meta")))
        mask = name == "__getitem__" and isinstance(args[1], torch.Tensor) and args[1].dtype == torch.bool
        if name in cls._READS or to_cpu or mask:
            cls.reads.append(name)
        out = super().__torch_function__(func, types, args, kwargs)
        # What was copied to the host is a plain tensor: reading it again costs nothing.
        return out.as_subclass(torch.Tensor) if name == "cpu" or to_cpu else out


class _Exempting:
    """:meth:`exempt` for the recording modes below: what a wrapped callable does is not recorded."""

    _paused = 0

    def exempt(self, fn):
        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            self._paused += 1
            try:
                return fn(*args, **kwargs)
            finally:
                self._paused -= 1
        return wrapper


class HostSyncOps(_Exempting, TorchDispatchMode):
    """Records the ops that synchronise with the host on CUDA, on any device (a CPU stand-in for
    ``torch.cuda.set_sync_debug_mode("error")``): a value read on the host (``item``, ``bool``, ``float``, ``if t``),
    data-dependent shapes (``nonzero``, boolean-mask indexing, ``masked_select``, ``unique``) and tensors made from
    host data (``torch.tensor(list)``: a blocking host-to-device copy on CUDA, refused inside a graph capture).
    :attr:`hits` holds ``"op at file:line"`` (the innermost frame of the package). :meth:`exempt` wraps a
    callable so that what it does is not recorded (e.g. the CPU physics backend, which is host code by design)."""

    OPS = {"_local_scalar_dense", "is_nonzero", "nonzero", "masked_select", "unique", "_unique2", "lift_fresh"}

    def __init__(self):
        super().__init__()
        self.hits: list[str] = []
        self._paused = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func.overloadpacket.__name__
        bool_index = name in ("index", "index_put", "index_put_") and any(
            isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in (args[1] if len(args) > 1 else ()))
        if not self._paused and (name in self.OPS or bool_index):
            frames = [f for f in traceback.extract_stack() if "tocabi_torchrl" in f.filename]
            self.hits.append(f"{name} at {frames[-1].filename.rsplit('tocabi_torchrl', 1)[-1]}:{frames[-1].lineno}"
                             if frames else name)
        return func(*args, **(kwargs or {}))


class HostValueReads(_Exempting, TorchFunctionMode):
    """Records each read of a tensor's values into Python (``tolist``, ``item``, ``cpu``, ``bool``, ``float``, ``int``,
    ``numpy``) while active, by the innermost frame of the package or of TorchRL: :attr:`sites` counts them by that
    frame's function name. Where :class:`HostSyncOps` sees ops at the dispatch level, this sees the calls that bring
    values to the host (a ``.cpu().tolist()`` of a CPU tensor dispatches nothing). :meth:`exempt` as there;
    :attr:`recording` off records nothing."""

    READS = {"tolist", "item", "cpu", "numpy", "__bool__", "__float__", "__int__", "__index__"}

    def __init__(self):
        super().__init__()
        self.sites: collections.Counter = collections.Counter()
        self.recording = True
        self._paused = 0

    def __torch_function__(self, func, types, args=(), kwargs=None):
        if self.recording and not self._paused and getattr(func, "__name__", "") in self.READS:
            frames = [f for f in traceback.extract_stack()[:-1]
                      if "tocabi_torchrl" in f.filename or f"torchrl{os.sep}" in f.filename]
            self.sites[frames[-1].name if frames else "?"] += 1
        return func(*args, **(kwargs or {}))


def counting_reads(r: StepResult) -> StepResult:
    """``r`` with every tensor (reward terms included) a :class:`HostReads`, in place; returns ``r``."""
    for name in STEP_TENSORS:
        setattr(r, name, getattr(r, name).as_subclass(HostReads))
    r.reward_terms = {k: v.as_subclass(HostReads) for k, v in r.reward_terms.items()}
    return r


def crafted_step_result(n: int, seed: int, done, truncated, length) -> StepResult:
    """A StepResult of ``n`` (1 or 2) envs with values a cast would change: NaNs with payloads, -0.0, a subnormal
    reward, lengths past 2**24. ``done``/``truncated``: (n,) bools; ``length``: (n,) ints [policy steps]."""
    g = torch.Generator().manual_seed(seed)
    obs, final_obs = torch.randn(n, 237, generator=g), torch.randn(n, 237, generator=g)
    obs.view(torch.int32)[0, :3] = torch.tensor([0x7FC00001, 0x7F800123, -0x7FFF_FFFF - 1])  # NaNs, -0.0
    final_obs.view(torch.int32)[-1, 5] = 0x7FC0BEEF
    done, truncated = torch.tensor(done), torch.tensor(truncated)
    terms = torch.randn(13, n, generator=g).t()  # strided rows, as the env's terms are
    return StepResult(obs=obs, final_obs=final_obs, reward=torch.tensor([-0.0, 1.5e-40])[:n],
                      terminated=done & ~truncated, truncated=truncated, done=done,
                      reward_terms={f"term{k}": terms[:, k] for k in range(13)},
                      episode_return=torch.randn(n, generator=g), episode_length=torch.tensor(length))
