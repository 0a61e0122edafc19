"""One PPO mini-batch step (loss, backward, gradient clipping, optimiser step), optionally replayed as a CUDA graph.

The update of a 4,096-env rollout is 20 mini-batch steps of ~300 small kernels each; run eagerly, the host's Python
(TorchRL's loss, autograd, the optimiser) takes longer than the GPU work, so the GPU idles ~40 % of the update
(``lab/benchmarks/trainer_timeline.py``). Captured once as a CUDA graph, a step is one launch: the kernels are the same,
only their launching changes.

Warm-up, capture and fallback are :class:`tocabi_torchrl.cuda_graphs.WarmCapture`'s, as for the env step. What this
step adds: the graph reads its mini-batch from static buffers (each step copies the next mini-batch in); gradients
live in the graph's memory pool, so nothing outside may set them to ``None``; the optimiser is capturable with a
tensor learning rate (:func:`make_capturable_adam`), which the trainer changes in place (:func:`set_lr`).

A rollout kept by the step (:meth:`MinibatchStep.keep`) lets the graph gather each mini-batch itself
(:meth:`MinibatchStep.on_rows`): the host then queues one index copy and one replay per mini-batch instead of a
gather and a copy per rollout key. An update overlapped with the next rollout (``ppo.overlap_update``) uses it: at
4,096 envs on an H100 the host queued the update in 1.7 ms instead of 39
(docs/benchmarks/train_over_ceiling_overlap).
"""

from __future__ import annotations

import contextlib

import torch
from tensordict import TensorDictBase

from ..config import ADAPTIVE_LR_RANGE
from ..cuda_graphs import CUDA_GRAPHS, Capturer, WarmCapture
from .rollout_guard import BEHAVIOUR_ESS_KEY

__all__ = ["MinibatchStep", "MinibatchKLRule", "update_autocast", "AUTOCAST_DTYPES", "STAT_KEYS", "EXTRA_STAT_KEYS",
           "make_capturable_adam", "optimizer_mode", "restore_optimizer_mode", "set_lr", "get_lr", "adapt_lr"]

#: The loss outputs averaged into the update's log line, in this order.
STAT_KEYS = ("loss_objective", "loss_critic", "kl_approx", "clip_fraction")
#: Further loss outputs logged when the loss module returns them (after :data:`STAT_KEYS`): the assist's and the
#: symmetry's loss terms, and the decoupled update's effective sample size (``GuardedClipPPOLoss.use_proximal``).
EXTRA_STAT_KEYS = ("loss_absorb", "loss_symmetry", BEHAVIOUR_ESS_KEY)
#: ``ppo.update_dtype`` -> the dtype its network passes autocast to (None: no autocast, float32).
AUTOCAST_DTYPES = {"float32": None, "bfloat16": torch.bfloat16}


def update_autocast(dtype: torch.dtype | None, device: torch.device | None) -> contextlib.AbstractContextManager:
    """``torch.autocast`` to ``dtype`` on ``device``'s type for the update's network passes, or no context for None
    (float32, or no device known). The cast cache is off: a captured step must cast the weights inside its graph,
    as they change with every optimiser step (torch's CUDA-graph notes ask for it).

    >>> with update_autocast(torch.bfloat16, torch.device("cpu")):
    ...     (torch.ones(2, 3) @ torch.ones(3, 4)).dtype
    torch.bfloat16
    """
    if dtype is None or device is None:
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=dtype, cache_enabled=False)


def make_capturable_adam(param_groups: list[dict], eps: float, device: torch.device) -> torch.optim.Adam:
    """Fused Adam whose step can be captured in a CUDA graph: step counts and learning rates live on the device."""
    groups = [{**g, "lr": torch.tensor(float(g["lr"]), device=device)} for g in param_groups]
    return torch.optim.Adam(groups, eps=eps, fused=True, capturable=True)


def optimizer_mode(optimizer: torch.optim.Optimizer) -> list[dict]:
    """How each parameter group of ``optimizer`` runs (capturable, fused, foreach, tensor or float lr), to be
    restored by :func:`restore_optimizer_mode` after ``load_state_dict``."""
    keys = ("capturable", "fused", "foreach")
    return [{**{k: g.get(k) for k in keys}, "lr_tensor": isinstance(g["lr"], torch.Tensor)}
            for g in optimizer.param_groups]


def restore_optimizer_mode(optimizer: torch.optim.Optimizer, mode: list[dict]) -> None:
    """Undo what ``load_state_dict`` copied from a checkpoint of another mode: it restores every group setting as
    saved (a captured run's tensor lr and ``capturable=True``, or an eager run's float lr), so a checkpoint written
    on the GPU with ``update_graph`` would break an eager or CPU resume, and the reverse. The step counters move to
    where this mode keeps them (the parameters' device when capturable or fused, else the CPU)."""
    for group, m in zip(optimizer.param_groups, mode):
        group.update({k: v for k, v in m.items() if k != "lr_tensor"})
        lr = float(group["lr"].item()) if isinstance(group["lr"], torch.Tensor) else float(group["lr"])
        device = group["params"][0].device
        group["lr"] = torch.tensor(lr, device=device) if m["lr_tensor"] else lr
        on_device = bool(m.get("capturable") or m.get("fused"))
        for p in group["params"]:
            state = optimizer.state.get(p, {})
            if "step" in state:
                state["step"] = state["step"].to(dtype=torch.float32, device=p.device if on_device else "cpu")


def set_lr(group: dict, lr: float) -> None:
    """Set a parameter group's learning rate, in place when it is a device tensor (read by a captured step)."""
    if isinstance(group["lr"], torch.Tensor):
        group["lr"].fill_(lr)
    else:
        group["lr"] = lr


#: The adaptive rule's numbers (rsl_rl's): the rate is divided by LR_FACTOR when the KL is above KL_ABOVE times the
#: target, multiplied by it below KL_BELOW times the target. :func:`adapt_lr` (host) and :class:`MinibatchKLRule`
#: (device) both read them.
KL_ABOVE, KL_BELOW, LR_FACTOR = 2.0, 0.5, 1.5


def adapt_lr(lr: float, kl: float, desired_kl: float, floor: float | None = None) -> float:
    """The KL-adaptive learning-rate rule of the ``adaptive`` schedule, applied once per iteration: the rate divided
    by 1.5 when the update's KL is above twice ``desired_kl``, multiplied by 1.5 when below half of it, within
    :data:`~tocabi_torchrl.config.ADAPTIVE_LR_RANGE` ([1e-5, 1e-2]; ``PPOConfig.validate`` keeps ``lr`` inside it),
    and not below ``floor`` (``ppo.lr_min``) when given."""
    low, high = ADAPTIVE_LR_RANGE
    low = low if floor is None else max(low, floor)
    if kl > KL_ABOVE * desired_kl:
        return max(lr / LR_FACTOR, low)
    if kl < KL_BELOW * desired_kl:
        return min(lr * LR_FACTOR, high)
    return lr


class MinibatchKLRule:
    """The adaptive rule of :func:`adapt_lr` applied on the device before every mini-batch step
    (``ppo.kl_adapt_every="minibatch"``, rsl_rl's schedule): the step's KL to the rollout's policy (with
    ``ppo.overlap_update``, to the policy the update starts from: the decoupled loss's), the loss's
    estimate ``kl_approx`` before the step (rsl_rl computes the Gaussians' KL), divides the rate by 1.5 above twice
    ``desired_kl`` and multiplies it by 1.5 below half of it, within [``floor``, 1e-2], in the tensor learning rate
    of every scheduled parameter group. Tensor operations only (no host read), so a captured step replays it.

    ``enabled`` (a 0-d float tensor on the device, 1 or 0): the trainer sets it once per iteration from the host
    (:meth:`set_enabled`, a fill, no read), 0 while the torque assist's hold keeps the rate (``ppo.assist_lr_hold``).
    As in rsl_rl, where the first mini-batch of an update reads a KL of exactly 0 and the rate is raised only on a KL
    above 0, the first step after :meth:`start_update` keeps the rate (the estimate there is rounding noise about 0)
    and a KL estimate of 0 or less never raises it.

    >>> import torch
    >>> group = {"lr": torch.tensor(1e-3)}
    >>> rule = MinibatchKLRule([group], desired_kl=0.01, floor=1e-5, device="cpu")
    >>> rule(torch.tensor(0.05))  # KL above twice the target: the rate falls before this step
    >>> round(float(group["lr"]), 6)
    0.000667
    >>> rule.set_enabled(False); rule(torch.tensor(0.05)); round(float(group["lr"]), 6)  # held: unchanged
    0.000667
    """

    def __init__(self, groups: list[dict], desired_kl: float, floor: float | None, device) -> None:
        if not groups or not all(isinstance(g["lr"], torch.Tensor) for g in groups):
            raise ValueError("MinibatchKLRule needs parameter groups whose learning rate is a tensor "
                             "(make_capturable_adam, or torch.optim.Adam given tensor rates)")
        self.groups = groups
        self.desired_kl = float(desired_kl)
        low, self.high = ADAPTIVE_LR_RANGE
        self.low = low if floor is None else max(low, float(floor))
        self.enabled = torch.ones((), device=device)
        self.first = torch.zeros((), device=device)  # 1: the next step is an update's first (start_update)

    def set_enabled(self, on: bool) -> None:
        self.enabled.fill_(1.0 if on else 0.0)

    def start_update(self) -> None:
        """Mark the next step as its update's first, whose rate stays (a fill, no read)."""
        self.first.fill_(1.0)

    def __call__(self, kl: torch.Tensor) -> None:
        kl = kl.detach()
        acts = (self.enabled > 0) & (self.first == 0)
        self.first.zero_()
        down = (kl > KL_ABOVE * self.desired_kl) & acts
        up = (kl < KL_BELOW * self.desired_kl) & (kl > 0) & acts
        for group in self.groups:
            lr = group["lr"]
            new = torch.where(down, (lr / LR_FACTOR).clamp(min=self.low),
                              torch.where(up, (lr * LR_FACTOR).clamp(max=self.high), lr))
            lr.copy_(new)


def get_lr(group: dict) -> float:
    """A parameter group's learning rate as a float (a host read when it lives on the device)."""
    lr = group["lr"]
    return float(lr.item()) if isinstance(lr, torch.Tensor) else float(lr)


class MinibatchStep:
    """``step(mb)``: one optimiser step on the mini-batch ``mb``; returns the device tensor of the losses named by
    ``stat_keys`` (:data:`STAT_KEYS`, then those of :data:`EXTRA_STAT_KEYS` the loss returns) for that step, valid
    until the next call.

    Args:
        loss_module: a TorchRL PPO loss (its outputs must include :data:`STAT_KEYS`); the minimised total is the sum
            of its ``loss_*`` outputs. A loss with a ``graph_key`` attribute (the assist's
            :class:`~tocabi_torchrl.rl.assist.AssistAbsorbLoss`) runs other operations when that changes: the step
            then warms up and captures again. (A loss wrapped in ``DistributedDataParallel`` hides the attribute; such
            a step is never captured: ``ppo.grad_sync`` "ddp" needs ``ppo.update_graph`` false.)
        optimizer: the optimiser of ``params`` (capturable, see :func:`make_capturable_adam`, when ``use_graph``).
        params: the parameters whose gradient norm is clipped to ``max_grad_norm``.
        use_graph: capture the step as a CUDA graph after ``warmup`` eager steps (where ``capturer`` supports the
            mini-batch's device: CUDA). If the capture fails, the step warns and stays eager. TorchRL's entropy bonus
            checks its value on the host, so a loss with ``entropy_bonus=True`` (``entropy_coef > 0``) cannot be
            captured and runs eagerly.
        grad_sync: called with ``params`` between ``backward`` and clipping, e.g.
            :class:`~tocabi_torchrl.rl.distributed.GradientAllReduce` in a data-parallel run (captured with the step).
        kl_rule: a :class:`MinibatchKLRule` applied to the loss's ``kl_approx`` before the optimiser step (None: the
            trainer adapts the rate once per iteration, if at all).
        capturer: how to capture (:data:`~tocabi_torchrl.cuda_graphs.CUDA_GRAPHS`).
        autocast_dtype: the dtype the loss's forward pass autocasts to (:func:`update_autocast`; ``ppo.update_dtype``),
            None for float32. Backward, clipping and the optimiser step run outside it, on float32 parameters.
    """

    def __init__(self, loss_module, optimizer: torch.optim.Optimizer, params: list[torch.Tensor],
                 max_grad_norm: float, use_graph: bool = False, warmup: int = 3, grad_sync=None,
                 capturer: Capturer = CUDA_GRAPHS, kl_rule: MinibatchKLRule | None = None,
                 autocast_dtype: torch.dtype | None = None):
        self.loss_module, self.optimizer, self.params = loss_module, optimizer, params
        self.autocast_dtype = autocast_dtype
        self.kl_rule = kl_rule
        self.max_grad_norm = max_grad_norm
        self.use_graph = use_graph
        self.grad_sync = grad_sync
        self.stat_keys: tuple[str, ...] = STAT_KEYS
        self._capture = WarmCapture("MinibatchStep", "the PPO update", self._compute, self._build, warmup=warmup,
                                    capturer=capturer)
        #: The same step with the mini-batch gathered inside the graph from :attr:`rows` (:meth:`on_rows`).
        self._rows_capture = WarmCapture("MinibatchStep", "the PPO update", self._compute_rows, self._build_rows,
                                         warmup=warmup, capturer=capturer)
        #: The rollout :meth:`keep` copied in, ``(n,)`` rows; None until then.
        self.rows: TensorDictBase | None = None
        self._graph_key = None

    @property
    def captured(self) -> bool:
        """Whether the step now replays a captured CUDA graph (of :meth:`__call__` or of :meth:`on_rows`)."""
        return self._capture.captured or self._rows_capture.captured

    def _compute(self, mb: TensorDictBase) -> torch.Tensor:
        # Set to None, not zeroed: the first backward (the capture's, when captured) allocates them, in the graph's
        # pool; a replay overwrites its own, so inside a graph this is a no-op after the capture.
        self.optimizer.zero_grad(set_to_none=True)
        with update_autocast(self.autocast_dtype, _device_of(mb)):
            losses = self.loss_module(mb)
        # TorchRL's convention: the total is the sum of every "loss_*" output (objective, critic, entropy, extras).
        names = [k for k in losses.keys() if isinstance(k, str) and k.startswith("loss_")]
        total = sum(losses[k] for k in names)
        total.backward()
        if self.grad_sync is not None:
            self.grad_sync(self.params)
        torch.nn.utils.clip_grad_norm_(self.params, self.max_grad_norm)
        if self.kl_rule is not None:  # this step's rate, from the KL its mini-batch had before it
            self.kl_rule(losses["kl_approx"])
        self.optimizer.step()
        self.stat_keys = STAT_KEYS + tuple(k for k in EXTRA_STAT_KEYS if k in losses.keys())
        return torch.stack([losses[k].detach() for k in self.stat_keys])

    def replays(self, rows: bool = True) -> bool:
        """Whether the next mini-batch call (:meth:`on_rows` when ``rows``, else ``__call__``) replays a captured
        graph, nothing to warm up or capture first: the host then runs no autograd and captures nothing, so the
        update may be queued from a thread of its own (``UpdateOverlap.launch(threaded=True)``). That also needs the
        captured loss to draw no random numbers (a replay would move the CUDA generator from that thread): PPO's
        with an analytic entropy draws none."""
        self._follow_graph_key()
        return self.use_graph and (self._rows_capture if rows else self._capture).captured

    def __call__(self, mb: TensorDictBase) -> torch.Tensor:
        self._follow_graph_key()
        return self._run(self._capture, self._compute, _device_of(mb), mb)

    def keep(self, flat: TensorDictBase) -> TensorDictBase:
        """Copy the rollout ``flat`` (``(n,)`` rows: the loss's keys) into :attr:`rows`, the step's own buffer, and
        return it; the buffer is reused while the keys, shapes, dtypes and device stay (a captured :meth:`on_rows`
        reads it by address), and allocated anew, with a new capture, when they change. The copy runs on the current
        stream; the caller makes sure no update still reads the previous contents (the overlap's ``finish``)."""
        if self.rows is not None and _same_layout(self.rows, flat):
            self.rows.update_(flat)
        else:
            self.rows = flat.clone()
            self._rows_capture.reset()  # a graph captured on the old buffer would read memory given back
        return self.rows

    def on_rows(self, idx: torch.Tensor) -> torch.Tensor:
        """``self(self.rows[idx])``: one optimiser step on the rows ``idx`` (``(minibatch,)`` int64, on the rows'
        device) of the kept rollout (:meth:`keep`). Captured, the gather is part of the graph: the host copies
        ``idx`` in and launches the replay, nothing per rollout key."""
        if self.rows is None:
            raise RuntimeError("MinibatchStep.on_rows() before keep(): keep the rollout first")
        if idx.dim() != 1 or idx.dtype != torch.int64:
            raise ValueError(f"MinibatchStep.on_rows(idx): idx must be a 1-D int64 tensor of row indices, got "
                             f"{idx.dtype} of shape {tuple(idx.shape)}")
        self._follow_graph_key()
        return self._run(self._rows_capture, self._compute_rows, _device_of(self.rows), idx)

    def _run(self, capture: WarmCapture, compute, device, arg) -> torch.Tensor:
        """``compute(arg)`` eagerly where no graph is wanted or possible on ``device``, else through ``capture``."""
        if not self.use_graph or capture.gave_up or not capture.capturer.supports(device):
            return compute(arg)
        return capture.run(device, arg)

    def _follow_graph_key(self) -> None:
        key = getattr(self.loss_module, "graph_key", None)
        if key != self._graph_key:
            # The loss now runs other operations (the assist's absorb term switched on or off): a graph captured
            # before would replay the old ones, so the step warms up and captures again.
            self._graph_key = key
            self._capture.reset()
            self._rows_capture.reset()

    def _compute_rows(self, idx: torch.Tensor) -> torch.Tensor:
        return self._compute(self.rows[idx])

    def _build_rows(self, args, stream, mode: str):
        static_idx = args[0].clone()
        replay, stats = self._rows_capture.capturer.capture(lambda: self._compute_rows(static_idx),
                                                            device=_device_of(self.rows), stream=stream, mode=mode)

        def step(idx: torch.Tensor) -> torch.Tensor:
            if idx.shape != static_idx.shape:  # copy_ would broadcast one index, or fail on another length
                raise ValueError(f"MinibatchStep.on_rows(idx): the captured step takes {static_idx.shape[0]} rows, "
                                 f"got {idx.shape[0]}; keep every mini-batch the size of the first")
            static_idx.copy_(idx)
            replay()
            return stats

        return step

    def _build(self, args, stream, mode: str):
        static_mb = args[0].clone()
        replay, stats = self._capture.capturer.capture(lambda: self._compute(static_mb), device=_device_of(static_mb),
                                                       stream=stream, mode=mode)

        def step(mb: TensorDictBase) -> torch.Tensor:
            static_mb.update_(mb)
            replay()
            return stats

        return step


def _device_of(td: TensorDictBase) -> torch.device | None:
    """The tensordict's device, or, for one built without ``device=``, its first leaf's (None when it has none, or
    for what a stand-in loss takes instead of a tensordict)."""
    if not isinstance(td, TensorDictBase):
        return getattr(td, "device", None)
    if td.device is not None:
        return td.device
    leaf = next(iter(td.values(True, True)), None)
    return None if leaf is None else leaf.device


def _same_layout(a: TensorDictBase, b: TensorDictBase) -> bool:
    """Whether two tensordicts have the same keys, batch size, and leaf shapes, dtypes and devices (host metadata)."""
    if a.batch_size != b.batch_size:
        return False
    keys = list(a.keys(True, True))
    if set(keys) != set(b.keys(True, True)):
        return False
    for k in keys:
        x, y = a.get(k), b.get(k)
        if x.shape != y.shape or x.dtype != y.dtype or x.device != y.device:
            return False
    return True
