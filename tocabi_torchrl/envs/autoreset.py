"""A ``TransformedEnv`` whose automatic resets in ``step_and_maybe_reset`` never read device values on the host,
and whose whole step can run as one captured CUDA graph."""

from __future__ import annotations

import warnings

from tensordict import TensorDictBase
from torchrl.envs import TransformedEnv

from ..cuda_graphs import CAPTURE_MODES, CUDA_GRAPHS, Capturer, WarmCapture
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
    calls and replayed from there on (:class:`~tocabi_torchrl.cuda_graphs.WarmCapture` over
    :class:`~tocabi_torchrl.envs.step_graph.StepGraph`, capture modes tried in the order of ``graph_modes``): the few
    hundred small launches of the signals, transforms and reset become one, so the host no longer limits the step
    rate. The graph
    freezes Python-side settings read during the step (config fields, ``RunningNormalization.frozen``): after
    changing one call :meth:`invalidate_graph` (:meth:`set_seed` does so by itself; reward weights set with
    ``TaskReward.set_weight`` live on the device and need nothing). If the capture fails, the env warns and stays
    eager. An input with other keys than the captured one runs eagerly (with a warning).

    Semantics equal the stock path: the ``"next"`` entries of a step keep the terminal/truncated data (GAE bootstraps
    from them), and the returned carry-over data hold the reset observation for done envs. The base env must build
    all-False done flags on reset rows (``TocabiWalk`` does) and update its state in place.
    """

    def __init__(self, *args, cuda_graph: bool = False, graph_warmup: int = 2, capturer: Capturer = CUDA_GRAPHS,
                 **kwargs):
        super().__init__(*args, **kwargs)
        self._warned_keys = False
        #: Capture modes tried in order (see StepGraph): one joined graph, else torch graphs cut around the physics.
        self.graph_modes: tuple[str, ...] = CAPTURE_MODES
        self._capture = WarmCapture("SyncFreeResetEnv", "the step", self._eager_step_and_maybe_reset,
                                    self._build_step_graph, warmup=graph_warmup, capturer=capturer,
                                    warmup_option="graph_warmup")
        self._cuda_graph = bool(cuda_graph)
        # The base env's count of Python-side settings the captured step reads (TocabiWalk.graph_settings).
        self._graph_settings = getattr(self.base_env, "graph_settings", 0)

    @property
    def cuda_graph(self) -> bool:
        """Whether ``step_and_maybe_reset`` is captured and replayed as a CUDA graph (CUDA envs only)."""
        return self._cuda_graph and not self._capture.gave_up and self._capture.capturer.supports(self.device)

    def set_cuda_graph(self, enabled: bool, capturer: Capturer | None = None) -> None:
        """Turn the captured step on or off (dropping any capture); ``capturer`` replaces how it is captured."""
        if capturer is not None:
            self._capture.capturer = capturer
        self._cuda_graph = bool(enabled)
        self.invalidate_graph()
        self._capture.gave_up = False

    @property
    def graph_captured(self) -> bool:
        """Whether a captured step graph is ready to replay."""
        return self._capture.captured

    @property
    def _step_graph(self) -> StepGraph | None:
        return self._capture.replayer

    def invalidate_graph(self) -> None:
        """Drop the captured step; the next calls run eagerly and capture again (after changing a Python setting)."""
        self._capture.reset()

    def set_seed(self, *args, **kwargs):
        # TocabiWalk keeps its seed on the device, which a graph follows; a base env that reads a Python seed
        # during the step would not, so a new seed always means a new capture.
        self.invalidate_graph()
        return super().set_seed(*args, **kwargs)

    def _step_and_maybe_reset(self, tensordict: TensorDictBase) -> tuple[TensorDictBase, TensorDictBase]:
        if tensordict.device != self.device:
            tensordict = tensordict.to(self.device)
        settings = getattr(self.base_env, "graph_settings", 0)  # a Python int: no device read
        if settings != self._graph_settings:  # a setting the capture froze has changed: capture again
            self._graph_settings = settings
            self.invalidate_graph()
        if not self.cuda_graph:
            return self._eager_step_and_maybe_reset(tensordict)
        graph = self._capture.replayer
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
        self._capture.modes = self.graph_modes
        return self._capture.run(self.device, tensordict)

    def _build_step_graph(self, args, stream, mode: str) -> StepGraph:
        base = self.base_env
        return StepGraph(self._eager_step_and_maybe_reset, args[0], getattr(base, "cuda_graph_generators", list)(),
                         stream=stream, mode=mode, recorded=getattr(base, "recorded_graphs", list)(),
                         capturer=self._capture.capturer)

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
