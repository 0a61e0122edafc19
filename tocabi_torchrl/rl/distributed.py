"""Data-parallel PPO over ``torch.distributed`` (``torchrun --nproc_per_node K recipes/ppo_walk.py ...``).

Each rank owns its own worlds on its own device and collects its own rollouts; what must stay identical across ranks
is kept identical here:

- parameters: broadcast from rank 0 once (:func:`broadcast_module`), then every mini-batch step applies the same
  averaged gradient (:class:`GradientAllReduce`, run between ``backward`` and gradient clipping, so clipping and Adam
  see the gradient of the mean loss over all ranks' mini-batches);
- the logged losses and the KL that drives the adaptive learning rate: averaged (:func:`all_reduce_mean`); the
  episode statistics: summed over the ranks' finished episodes, then divided (:func:`all_reduce_sum`);
- running observation statistics: merged after each rollout (:class:`RunningStatsSync`);
- the std and LR schedules: functions of the iteration, which every rank counts alike.

No home-made transport: NCCL between GPUs, gloo on the CPU (tests). A single process (``WORLD_SIZE`` unset or 1)
runs with every helper here a no-op.
"""

from __future__ import annotations

import contextlib
import gc
import os
import sys
import traceback
from dataclasses import dataclass
from typing import Iterable, Mapping

import torch
import torch.distributed as dist

__all__ = ["DistInfo", "from_environment", "init_distributed", "shutdown", "ending", "rank_seed", "broadcast_module",
           "GradientAllReduce", "all_reduce_mean", "all_reduce_sum", "agree", "RunningStatsSync"]


@dataclass(frozen=True)
class DistInfo:
    """Where this process sits in a data-parallel run (one process per GPU)."""

    rank: int = 0
    world_size: int = 1
    #: Index of this process's GPU on its host (``cuda:<local_rank>``).
    local_rank: int = 0

    @property
    def enabled(self) -> bool:
        """More than one rank: gradients and statistics are exchanged."""
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        """Rank 0 logs, prints progress and writes checkpoints; the others only train."""
        return self.rank == 0


def _env_int(environ: Mapping[str, str], name: str, default: int) -> int:
    text = environ.get(name, "")
    if text == "":
        return default
    try:
        return int(text)
    except ValueError:
        raise ValueError(f"{name}={text!r} is not an integer; it is set by torchrun (launch with "
                         f"`torchrun --nproc_per_node K recipes/ppo_walk.py ...`, or unset it)") from None


def from_environment(environ: Mapping[str, str] | None = None) -> DistInfo:
    """The rank layout torchrun exports (``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``); one rank when they are unset."""
    environ = os.environ if environ is None else environ
    info = DistInfo(_env_int(environ, "RANK", 0), _env_int(environ, "WORLD_SIZE", 1),
                    _env_int(environ, "LOCAL_RANK", _env_int(environ, "RANK", 0)))
    if info.world_size < 1 or not 0 <= info.rank < info.world_size or info.local_rank < 0:
        raise ValueError(f"inconsistent torchrun layout: RANK={info.rank}, WORLD_SIZE={info.world_size}, "
                         f"LOCAL_RANK={info.local_rank} (need 0 <= RANK < WORLD_SIZE)")
    return info


def init_distributed(info: DistInfo, device: torch.device, init_method: str | None = None) -> torch.device:
    """Join the process group (NCCL on CUDA, gloo on the CPU) and return this rank's device.

    On CUDA every rank takes ``cuda:<local_rank>`` (a device index in ``device`` is ignored: torchrun decides).
    A single-rank run joins nothing and returns ``device`` unchanged.
    """
    if not info.enabled:
        return device
    if not dist.is_available():
        raise RuntimeError("torch.distributed is not available in this torch build; run with one process")
    if device.type == "cuda":
        if info.local_rank >= torch.cuda.device_count():
            raise RuntimeError(f"rank {info.rank} wants cuda:{info.local_rank} but this host has "
                               f"{torch.cuda.device_count()} GPU(s): use --nproc_per_node <= the GPU count")
        device = torch.device("cuda", info.local_rank)
        torch.cuda.set_device(device)
        backend = "nccl"
    elif device.type == "cpu":
        backend = "gloo"
    else:
        raise ValueError(f"data-parallel training runs on cuda (NCCL) or cpu (gloo), not {device}")
    if not dist.is_initialized():
        kwargs = {} if init_method is None else {"init_method": init_method}
        dist.init_process_group(backend, rank=info.rank, world_size=info.world_size, **kwargs)
    return device


def shutdown(info: DistInfo, code: int = 0) -> None:
    """End this rank's part after its last collective and its last output.

    gloo (the CPU): after a barrier (exit status 0 only: on an error the peer may never come), the process group is
    destroyed and the call returns. NCCL: ``destroy_process_group``, and the
    group's teardown at interpreter exit too, can wait for ever once CUDA graphs captured the group's collectives
    (pytorch/pytorch#115388); on an H100 pair it hung after the captured update's all-reduce. The trainer has closed
    its loggers and written its checkpoints atomically by then, so the process ends here, with exit status ``code``,
    without the teardown. A single-rank run is left as it is.
    """
    if not info.enabled or not dist.is_initialized():
        return
    if "nccl" not in str(dist.get_backend()):  # also a mixed "cpu:gloo,cuda:nccl" group
        if code == 0:
            # Both ranks past their last collective before either tears down: a gloo rank that exited while its
            # peer still had an operation open aborted at exit ("terminate called without an active exception") in
            # a loaded test run. On an error the peer may never get here, so no barrier then.
            dist.barrier()
        gc.collect()  # whatever still holds the group only through a reference cycle goes while the group works
        dist.destroy_process_group()
        return
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed or broken pipe must not bring back the hanging teardown
            pass
    os._exit(code)


@contextlib.contextmanager
def ending(info: DistInfo, expected: tuple[type[BaseException], ...] = ()):
    """Run a data-parallel rank's work, then :func:`shutdown`; on any exception, say it and end the rank with exit
    status 1 (an NCCL rank would otherwise wait for ever in the teardown, and its peers in their next collective,
    which no watchdog times out once it is captured in a graph). ``expected`` exceptions are said in one line
    (``error (rank R): ...``), others with their traceback; with gloo the exception then goes on. One rank: nothing
    is added."""
    try:
        yield
    except BaseException as err:
        if not info.enabled:
            raise
        if isinstance(err, expected):
            print(f"error (rank {info.rank}): {err}", file=sys.stderr)
        else:
            print(f"error (rank {info.rank}):", file=sys.stderr)
            traceback.print_exc()
        shutdown(info, code=1)
        raise  # gloo: shutdown returned
    shutdown(info)


def rank_seed(seed: int, info: DistInfo) -> int:
    """The seed of this rank's worlds, exploration noise and mini-batch shuffles: ``seed + rank``.

    Rank 0's worlds draw as a 1-rank run's with the same seed; its exploration noise and mini-batch order do not: a
    data-parallel run reseeds torch with this seed after the weights are built and broadcast, where a 1-rank run goes
    on with the stream its weight initialisation left."""
    return seed + info.rank


def broadcast_module(module: torch.nn.Module, info: DistInfo) -> None:
    """Copy rank 0's parameters and buffers into every rank's ``module`` (in place)."""
    if not info.enabled:
        return
    with torch.no_grad():
        for t in [*module.parameters(), *module.buffers()]:
            dist.broadcast(t.data, src=0)


class GradientAllReduce:
    """``sync(params)``: replace each gradient by its mean over the ranks, with one all-reduce of one flat buffer.

    The buffer is allocated at the first call and reused, so the exchange allocates nothing per step and can run
    inside the captured CUDA graph of :class:`~tocabi_torchrl.rl.update_step.MinibatchStep` (NCCL collectives can
    be captured). Parameters without a gradient are skipped alike on every rank (they are the same tensors).
    """

    def __init__(self, info: DistInfo):
        self.info = info
        self._flat: torch.Tensor | None = None

    def __call__(self, params: Iterable[torch.Tensor]) -> None:
        if not self.info.enabled:
            return
        grads = [p.grad for p in params if p.grad is not None]
        if not grads:
            return
        size = sum(g.numel() for g in grads)
        if self._flat is None or self._flat.numel() != size or self._flat.device != grads[0].device:
            self._flat = torch.empty(size, dtype=grads[0].dtype, device=grads[0].device)
        views = torch.split(self._flat, [g.numel() for g in grads])
        for view, g in zip(views, grads):
            view.copy_(g.reshape(-1))
        dist.all_reduce(self._flat, op=dist.ReduceOp.SUM)
        self._flat.div_(self.info.world_size)
        for view, g in zip(views, grads):
            g.copy_(view.view_as(g))


def all_reduce_mean(t: torch.Tensor, info: DistInfo) -> torch.Tensor:
    """``t`` averaged over the ranks, in place (returned for chaining); unchanged with one rank."""
    if info.enabled:
        dist.all_reduce(t, op=dist.ReduceOp.SUM)
        t.div_(info.world_size)
    return t


def all_reduce_sum(t: torch.Tensor, info: DistInfo) -> torch.Tensor:
    """``t`` summed over the ranks, in place (returned for chaining); unchanged with one rank."""
    if info.enabled:
        dist.all_reduce(t, op=dist.ReduceOp.SUM)
    return t


def agree(ok: bool, info: DistInfo, device: torch.device) -> bool:
    """Whether ``ok`` holds on every rank (one small all-reduce; no exchange with one rank).

    Used where ranks decide alone but must act together (stop on a time budget, give up on a bad run folder): a rank
    that left the loop early would leave the others waiting in their next collective.
    """
    if not info.enabled:
        return bool(ok)
    flag = torch.tensor([1 if ok else 0], dtype=torch.int32, device=device)
    dist.all_reduce(flag, op=dist.ReduceOp.MIN)
    return bool(flag.item())


class RunningStatsSync:
    """Keeps the running observation statistics (``RunningNormalization``: ``count``, ``mean``, ``var`` buffers)
    identical across ranks.

    During a rollout each rank folds only its own observations in. :meth:`sync` then merges what every rank added
    since the last sync into the shared statistics: counts, sums and sums of squares are additive, so the merge is
    exact (float64) and equals one normaliser fed every rank's rows. Call it after each rollout, before the update.
    """

    def __init__(self, normalizers: Iterable[torch.nn.Module], info: DistInfo):
        self.info = info
        self.normalizers = [n for n in normalizers if all(hasattr(n, b) for b in ("count", "mean", "var"))]
        # An unsized normaliser would size itself from its first observation, after the base below is taken; the
        # merge would then subtract a (1,) base from (2D + 1,) moments by broadcasting, every rank agreeing on the
        # wrong mean and variance.
        if any(n.mean.numel() == 0 for n in self.normalizers):
            raise ValueError("RunningStatsSync needs sized statistics: build RunningNormalization with dim= or "
                             "init_mean=, or create the sync after the env's observation_spec has been read (which "
                             "sizes a normaliser attached to it)")
        self._base = [self._moments(n) for n in self.normalizers]

    @staticmethod
    def _moments(n: torch.nn.Module) -> torch.Tensor:
        """(2D + 1,) float64: count, sum and sum of squares of every sample folded in so far."""
        count = n.count.to(torch.float64).reshape(1)
        mean, var = n.mean.to(torch.float64), n.var.to(torch.float64)
        return torch.cat([count, count * mean, count * (var + mean.square())])

    def sync(self) -> None:
        if not self.info.enabled:
            return
        for i, n in enumerate(self.normalizers):
            added = self._moments(n) - self._base[i]
            dist.all_reduce(added, op=dist.ReduceOp.SUM)
            total = self._base[i] + added
            d = n.mean.numel()
            count, s1, s2 = total[0], total[1:1 + d], total[1 + d:]
            mean = s1 / count
            with torch.no_grad():
                n.count.copy_(count.to(n.count.dtype))
                n.mean.copy_(mean.to(n.mean.dtype))
                n.var.copy_((s2 / count - mean.square()).clamp_min(0.0).to(n.var.dtype))
            self._base[i] = self._moments(n)
