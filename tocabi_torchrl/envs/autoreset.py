"""A ``TransformedEnv`` whose automatic resets in ``step_and_maybe_reset`` never read device values on the host,
and whose whole step can run as one captured CUDA graph."""

from __future__ import annotations

import warnings

import torch
from tensordict import TensorDictBase
from torchrl.envs import TransformedEnv

from .step_graph import StepGraph

__all__ = ["SyncFreeResetEnv"]


class SyncFreeResetEnv(TransformedEnv):
    """``TransformedEnv`` with a host-sync-free ``step_and_maybe_reset`` (what TorchRL collectors call every step).

    TorchRL's stock version asks ``done.any()`` on the host to decide whether to reset, then merges the reset rows
    after reading ``_reset.all()``: each read waits for the GPU to finish the step, so the host cannot queue the next
    step's kernels while the physics runs. Here every step runs the masked reset (the base env's ``_reset`` and every
    transform's ``_reset``, all of which only touch flagged rows with ``where``) and merges the flagged rows into the
    next-step data with ``where``: no host reads, so Python and kernel launches overlap the GPU work.

    With ``cuda_graph=True`` (on a CUDA env) the step is then captured as one CUDA graph after ``graph_warmup`` eager
    calls and replayed from there on (see :class:`~tocabi_torchrl.envs.step_graph.StepGraph`): the few hundred small
    launches of the signals, transforms and reset become one, so the host no longer limits the step rate. The graph
    freezes Python-side settings read during the step (config fields, ``RunningNormalization.frozen``): after
    changing one call :meth:`invalidate_graph` (:meth:`set_seed` does so by itself; reward weights set with
    ``TaskReward.set_weight`` live on the device and need nothing). If the capture fails, the env warns and stays
    eager. An input with other keys than the captured one runs eagerly (with a warning).

    Semantics equal the stock path: the ``"next"`` entries of a step keep the terminal/truncated data (GAE bootstraps
    from them), and the returned carry-over data hold the reset observation for done envs. The base env must build
    all-False done flags on reset rows (``TocabiWalk`` does) and update its state in place.
    """

    def __init__(self, *args, cuda_graph: bool = False, graph_warmup: int = 2, **kwargs):
        super().__init__(*args, **kwargs)
        if isinstance(graph_warmup, bool) or not isinstance(graph_warmup, int) or graph_warmup < 1:
            raise ValueError(f"graph_warmup must be an int >= 1 (eager calls before the capture), got {graph_warmup!r}")
        self._cuda_graph = bool(cuda_graph)
        self._graph_warmup = graph_warmup
        self._step_graph: StepGraph | None = None
        self._eager_calls = 0
        self._warned_keys = False
        # Tests without a GPU run the same wiring with StepGraph's emulated (uncaptured) replay.
        self._graph_emulate = False
        self._capture_stream = None
        #: Capture modes tried in order (see StepGraph): one joined graph, else torch graphs cut around the physics.
        self.graph_modes: tuple[str, ...] = ("joined", "segmented")

    @property
    def cuda_graph(self) -> bool:
        """Whether ``step_and_maybe_reset`` is captured and replayed as a CUDA graph (CUDA envs only)."""
        on_cuda = self.device is not None and self.device.type == "cuda"
        return self._cuda_graph and (on_cuda or self._graph_emulate)

    @property
    def graph_captured(self) -> bool:
        """Whether a captured step graph is ready to replay."""
        return self._step_graph is not None

    def invalidate_graph(self) -> None:
        """Drop the captured step; the next calls run eagerly and capture again (after changing a Python setting)."""
        self._step_graph = None
        self._eager_calls = 0

    def set_seed(self, *args, **kwargs):
        # TocabiWalk keeps its seed on the device, which a graph follows; a base env that reads a Python seed
        # during the step would not, so a new seed always means a new capture.
        self.invalidate_graph()
        return super().set_seed(*args, **kwargs)

    def _step_and_maybe_reset(self, tensordict: TensorDictBase) -> tuple[TensorDictBase, TensorDictBase]:
        if tensordict.device != self.device:
            tensordict = tensordict.to(self.device)
        if not self.cuda_graph:
            return self._eager_step_and_maybe_reset(tensordict)
        graph = self._step_graph
        if graph is not None:
            if graph.accepts(tensordict):
                check = getattr(self.base_env, "_check_action", None)
                if check is not None:  # metadata only; the replay would fail with a less helpful message
                    check(tensordict.get(self.action_key))
                return graph(tensordict)
            if not self._warned_keys:
                self._warned_keys = True
                warnings.warn(
                    "SyncFreeResetEnv: step_and_maybe_reset got other keys than its CUDA graph was captured with; "
                    "running this call eagerly (call invalidate_graph() to capture the new layout)",
                    stacklevel=2,
                )
            return self._eager_step_and_maybe_reset(tensordict)
        self._eager_calls += 1
        if self._eager_calls < self._graph_warmup:
            return self._eager_step_and_maybe_reset(tensordict)
        if self._eager_calls == self._graph_warmup:
            return self._warmup_on_capture_stream(tensordict)
        generators = getattr(self.base_env, "cuda_graph_generators", list)()
        failures = []
        for mode in self.graph_modes:
            try:
                self._step_graph = StepGraph(self._eager_step_and_maybe_reset, tensordict, generators,
                                             emulate=self._graph_emulate, stream=self._capture_stream, mode=mode)
                break
            except Exception as err:  # noqa: BLE001 - any capture failure: try the next mode, say why
                failures.append(f"{mode}: {type(err).__name__}: {err}")
        if failures:
            outcome = (f"using the {self._step_graph.mode!r} capture" if self._step_graph is not None
                       else "running eagerly from now on")
            warnings.warn(f"SyncFreeResetEnv: capturing the step as a CUDA graph failed ({'; '.join(failures)}); "
                          f"{outcome}", stacklevel=2)
        if self._step_graph is None:
            self._cuda_graph = False
            return self._eager_step_and_maybe_reset(tensordict)
        return self._step_graph(tensordict)  # the capture recorded the step; this replay runs it

    def _warmup_on_capture_stream(self, tensordict: TensorDictBase) -> tuple[TensorDictBase, TensorDictBase]:
        """The last warm-up call runs on the stream the capture will use (lazy per-stream set-up happens outside
        the capture, as torch recommends)."""
        if self._graph_emulate:  # no CUDA: the emulated replay needs no stream
            return self._eager_step_and_maybe_reset(tensordict)
        current = torch.cuda.current_stream(self.device)
        self._capture_stream = stream = torch.cuda.Stream(self.device)
        stream.wait_stream(current)
        with torch.cuda.stream(stream):
            out = self._eager_step_and_maybe_reset(tensordict)
        current.wait_stream(stream)
        return out

    def _eager_step_and_maybe_reset(self, tensordict: TensorDictBase) -> tuple[TensorDictBase, TensorDictBase]:
        tensordict = self.step(tensordict)
        tensordict_ = self._step_mdp(tensordict)
        done = tensordict_.get("done")  # (num_envs, 1) bool
        request = tensordict_.clone(False).set("_reset", done)
        reset = self._reset(request)
        # Flagged rows take the reset data; the others keep the step's data (bit-identical). Only keys present on
        # both sides take part: `where(pad=...)` would build its pad value on the host (a sync per missing key).
        keys = [k for k in reset.keys(True, True) if k != "_reset"]
        merged = reset.select(*keys).where(done.reshape(self.batch_size), other=tensordict_.select(*keys))
        return tensordict, tensordict_.update(merged)
