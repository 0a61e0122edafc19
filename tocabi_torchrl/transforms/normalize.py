"""Observation normalisation: the reference's fixed statistics (default) or running statistics (option).

Both compute ``(x - mean) / sqrt(var + eps)`` per element, optionally clipped. The fixed statistics are those of the
reference observation (spec §7.1 table), written here to 7 significant digits; at that precision they reproduce the
reference's normalised observation to ~1e-6 relative.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from types import MappingProxyType

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Composite, Unbounded

from tocabi_torchrl.transforms._base import CallOnReset
from tocabi_torchrl.transforms._checks import check_positive, check_positive_int, require_spec

__all__ = ["REFERENCE_OBS_MEAN", "REFERENCE_OBS_VAR", "BASE_VEL_OBS_MEAN", "BASE_VEL_OBS_VAR", "FIXED_STATISTICS",
           "FixedNormalization", "RunningNormalization",
           "freeze_running_statistics", "running_normalizers", "untrained_running_normalizers"]

_LEG_NAMES = ("HipYaw", "HipRoll", "HipPitch", "Knee", "AnklePitch", "AnkleRoll")

#: Mean of the 37 reference observation entries (spec §7.1 order).
REFERENCE_OBS_MEAN: tuple[float, ...] = (
    # roll, pitch, yaw
    5.713685e-05, 2.918405e-03, -1.289361e-04,
    # q, left leg then right leg
    3.085928e-04, 3.329158e-02, -2.840124e-01, 6.248943e-01, -3.402914e-01, -3.875068e-02,
    8.130309e-03, -3.335870e-02, -2.943861e-01, 6.364560e-01, -3.412546e-01, 4.137892e-02,
    # dq, left leg then right leg
    5.741393e-04, -6.541084e-04, -1.414430e-02, 2.425730e-02, -1.653029e-02, -6.558039e-05,
    6.991749e-05, -2.916816e-03, -1.556312e-02, 2.675701e-02, -1.815802e-02, 4.793702e-03,
    # sin, cos of the phase
    -1.007162e-02, -7.108355e-03,
    # command vx, vy
    1.484956e-01, 0.0,
    # Fz_L, Fz_R, Mx_L, Mx_R, My_L, My_R
    -500.0, -500.0, 0.0, 0.0, 0.0, 0.0,
)  # fmt: skip

#: Variance of the 37 reference observation entries (spec §7.1 order).
REFERENCE_OBS_VAR: tuple[float, ...] = (
    0.01, 0.01, 0.01,
    0.01, 0.01, 1.144567e-02, 1.619902e-02, 1.029234e-02, 0.01,
    0.01, 0.01, 1.319631e-02, 1.898347e-02, 1.017625e-02, 0.01,
    1.819640e-02, 7.414944e-02, 3.447816e-01, 9.961943e-01, 4.273807e-01, 1.587944e-01,
    1.890155e-02, 7.478288e-02, 4.259392e-01, 1.280129e+00, 4.722263e-01, 2.308447e-01,
    4.315630e-01, 5.682851e-01,
    3.710724e-02, 0.01,
    25000.0, 25000.0, 900.0, 900.0, 900.0, 900.0,
)  # fmt: skip

# The pelvis velocity that the ``base_vel`` layout adds (linear x, y, z [m/s], angular x, y, z [rad/s], pelvis frame):
# the variances of the shipped robust policy's walk (40 robots at commands 0-0.5 m/s forward and ±0.15 m/s sideways,
# 2.6 s each after 0.4 s, C MuJoCo: lab/analysis/velocity_statistics.py), rounded, and a mean of 0 but for the
# forward speed (0.3 m/s there), so that the mirror keeps the normalised sideways and turning values' signs.
_BASE_VEL_MEAN = (0.3, 0.0, 0.0, 0.0, 0.0, 0.0)
_BASE_VEL_VAR = (0.025, 0.0125, 0.015, 0.16, 0.08, 0.24)
#: Mean and variance of the 43 entries of the ``base_vel`` layout (the reference's 37, then the pelvis velocity).
BASE_VEL_OBS_MEAN: tuple[float, ...] = REFERENCE_OBS_MEAN + _BASE_VEL_MEAN
BASE_VEL_OBS_VAR: tuple[float, ...] = REFERENCE_OBS_VAR + _BASE_VEL_VAR
#: The fixed statistics of each named layout (``layouts.OBS_LAYOUTS``) with one phase harmonic.
FIXED_STATISTICS: Mapping[str, tuple[tuple[float, ...], tuple[float, ...]]] = MappingProxyType({
    "reference": (REFERENCE_OBS_MEAN, REFERENCE_OBS_VAR), "base_vel": (BASE_VEL_OBS_MEAN, BASE_VEL_OBS_VAR)})


def _check_stats(mean: Sequence[float], var: Sequence[float], owner: str) -> tuple[torch.Tensor, torch.Tensor]:
    mean_t = torch.as_tensor(mean, dtype=torch.float64).flatten()
    var_t = torch.as_tensor(var, dtype=torch.float64).flatten()
    if mean_t.numel() != var_t.numel():
        raise ValueError(f"{owner}: mean has {mean_t.numel()} values but var has {var_t.numel()}; pass equal lengths")
    if not bool(torch.isfinite(mean_t).all()) or not bool(torch.isfinite(var_t).all()) or bool((var_t < 0).any()):
        raise ValueError(f"{owner}: mean must be finite and var finite and >= 0")
    return mean_t, var_t


class _Normalization(CallOnReset):
    """Shared spec handling: ``out_key`` has the shape of ``in_key``, float32."""

    def __init__(self, in_key: NestedKey, out_key: NestedKey, eps: float, clip: float | None):
        super().__init__(in_keys=[in_key], out_keys=[out_key])
        self.eps = check_positive(eps, f"{type(self).__name__} eps")
        self.clip = None if clip is None else check_positive(clip, f"{type(self).__name__} clip")
        # The option the statistics came from (e.g. "obs_mean/obs_var"), named when their length does not fit.
        self.stats_source: str | None = None

    def _num_stats(self) -> int:
        raise NotImplementedError

    def _normalize(self, x: torch.Tensor, loc: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
        out = (x.to(torch.float32) - loc) / scale
        if self.clip is not None:
            out = out.clamp(-self.clip, self.clip)
        return out

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        spec = require_spec(observation_spec, self.in_keys[0], self)
        dim = spec.shape[-1] if len(spec.shape) else 0
        if dim != self._num_stats() and self.stats_source is not None:
            raise ValueError(
                f"{self.stats_source} have {self._num_stats()} values each but the per-step observation "
                f"{self.in_keys[0]!r} has {dim} (shape {tuple(spec.shape)}, set by obs_layout and phase_harmonics); "
                f"pass {dim} of each, or leave both None"
            )
        if dim != self._num_stats():
            raise ValueError(
                f"{type(self).__name__} holds {self._num_stats()} statistics but {self.in_keys[0]!r} has {dim} values "
                f"(shape {tuple(spec.shape)}); pass mean/var of length {dim} (e.g. after changing the observation "
                "layout or the phase harmonics), or use normalization='running'"
            )
        observation_spec[self.out_keys[0]] = Unbounded(
            shape=tuple(spec.shape), dtype=torch.float32, device=observation_spec.device
        )
        return observation_spec


class FixedNormalization(_Normalization):
    """``(x - mean) / sqrt(var + eps)`` with constant statistics; the reference's observation scaling by default.

    Reads ``in_key`` (num_envs, D); writes ``out_key`` (num_envs, D) float32. No clipping unless ``clip`` is given
    (the reference does not clip).

    Args:
        in_key, out_key: raw and normalised observation keys.
        mean, var: D statistics each (default: :data:`REFERENCE_OBS_MEAN`, :data:`REFERENCE_OBS_VAR`).
        eps: added to var before the square root (reference: 1e-8).
        clip: optional symmetric clip of the output.
    """

    def __init__(
        self,
        in_key: NestedKey = "obs_step",
        out_key: NestedKey = "obs_step_norm",
        mean: Sequence[float] = REFERENCE_OBS_MEAN,
        var: Sequence[float] = REFERENCE_OBS_VAR,
        eps: float = 1e-8,
        clip: float | None = None,
    ):
        super().__init__(in_key, out_key, eps, clip)
        mean_t, var_t = _check_stats(mean, var, "FixedNormalization")
        self.register_buffer("loc", mean_t.to(torch.float32))
        # The std is formed in float64 from the given variance, then stored as float32.
        self.register_buffer("scale", torch.sqrt(var_t + self.eps).to(torch.float32))

    def _num_stats(self) -> int:
        return self.loc.numel()

    def _apply_transform(self, x: torch.Tensor) -> torch.Tensor:
        return self._normalize(x, self.loc, self.scale)


class RunningNormalization(_Normalization):
    """``(x - mean) / sqrt(var + eps)`` with statistics accumulated over every env step (an option).

    Each ``env.step`` folds the batch of new observations (all num_envs rows, or those selected by ``mask_key``) into
    the running mean and variance with the parallel (Chan) update, using device tensor ops only; resets read the
    statistics but do not update them. Rows with a NaN/inf value, and rows of worlds whose ``health_key`` is False
    (numerically broken physics, which terminates), are always left out, so one broken world cannot poison the
    statistics every world is normalised with.
    Statistics are kept in float64 because they accumulate over 1e8+ samples, where float32 increments vanish.
    Call :meth:`freeze` for evaluation. The statistics are buffers, saved in ``state_dict``.

    Reads ``in_key`` (num_envs, D); writes ``out_key`` (num_envs, D) float32.

    Args:
        in_key, out_key: raw and normalised observation keys.
        dim: D. Inferred from ``init_mean`` when given, else from the observation spec once attached to an env.
        init_mean, init_var: starting statistics (e.g. the reference's); default 0 and 1.
        init_count: weight of the starting statistics in samples (> 0).
        eps, clip: as in :class:`FixedNormalization`.
        frozen: start without updating.
        mask_key: optional (num_envs, 1) bool key of the step output selecting the rows to learn from, e.g.
            ``"terminated"`` with ``mask_invert=True`` to skip states of falling robots.
        mask_invert: learn from the rows where ``mask_key`` is False instead.
        health_key: (num_envs, 1) bool key of the step output, True where the world's physics is sound
            (``TocabiWalk``'s ``healthy``); rows where it is False are left out. Ignored when the key is absent.
    """

    def __init__(
        self,
        in_key: NestedKey = "obs_step",
        out_key: NestedKey = "obs_step_norm",
        dim: int | None = None,
        init_mean: Sequence[float] | None = None,
        init_var: Sequence[float] | None = None,
        init_count: float = 1.0,
        eps: float = 1e-8,
        clip: float | None = None,
        frozen: bool = False,
        mask_key: NestedKey | None = None,
        mask_invert: bool = False,
        health_key: NestedKey | None = "healthy",
    ):
        super().__init__(in_key, out_key, eps, clip)
        if dim is not None:
            # A float dim failed as a bare "can't multiply sequence by non-int", and a dim other than init_mean's
            # length was named as a mean and var of unequal lengths, a var the caller never gave.
            dim = check_positive_int(dim, "RunningNormalization dim (D, the observation's values)",
                                     "or None to size the statistics from the observation")
            for name, given in (("init_mean", init_mean), ("init_var", init_var)):
                count = None if given is None else torch.as_tensor(given).numel()
                if count is not None and count != dim:
                    raise ValueError(f"RunningNormalization: dim={dim} but {name} has {count} values; pass {dim} "
                                     "values, or leave dim None to take init_mean's length")
        if init_mean is not None and dim is None:
            dim = len(init_mean)
        if dim is not None:
            mean = [0.0] * dim if init_mean is None else init_mean
            var = [1.0] * dim if init_var is None else init_var
            mean_t, var_t = _check_stats(mean, var, "RunningNormalization")
            if mean_t.numel() != dim:
                raise ValueError(
                    f"RunningNormalization: dim={dim} but the initial statistics have {mean_t.numel()} values"
                )
        else:
            if init_var is not None:
                raise ValueError("RunningNormalization: init_var given without init_mean; pass both")
            # Sized from the observation spec when the transform is attached to an env.
            mean_t, var_t = torch.zeros(0, dtype=torch.float64), torch.ones(0, dtype=torch.float64)
        self.register_buffer("mean", mean_t)
        self.register_buffer("var", var_t)
        # float64 like mean and var: a float32 count rounds increments away past 2**24 samples (~4,100 steps of
        # 4,096 envs), skewing the update's weights n / total. An older state_dict's float32 count still loads
        # (load_state_dict copies into this buffer, converting).
        count = check_positive(init_count, "RunningNormalization init_count")
        self.register_buffer("count", torch.tensor(count, dtype=torch.float64))
        self.init_count = count  # a count still at this value: statistics that never saw a step (untrained)
        self.frozen = bool(frozen)
        self.mask_key, self.mask_invert = mask_key, bool(mask_invert)
        self.health_key = health_key

    def freeze(self) -> RunningNormalization:
        """Stop updating the statistics (evaluation, export); returns ``self``."""
        self.frozen = True
        return self

    def unfreeze(self) -> RunningNormalization:
        """Update the statistics from every step again; returns ``self``."""
        self.frozen = False
        return self

    def _num_stats(self) -> int:
        return self.mean.numel()

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        spec = require_spec(observation_spec, self.in_keys[0], self)
        if len(spec.shape):
            self._size_stats(spec.shape[-1])
        return super().transform_observation_spec(observation_spec)

    def _size_stats(self, dim: int) -> None:
        """Give unsized statistics (no ``dim`` or initial values) ``dim`` entries: mean 0, variance 1. A reset or
        step can come before anything reads the env's observation spec, so the first observation sizes them too."""
        if self.mean.numel() == 0:
            self.mean = torch.zeros(dim, dtype=torch.float64, device=self.mean.device)
            self.var = torch.ones(dim, dtype=torch.float64, device=self.var.device)

    @torch.no_grad()
    def update(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> None:
        """Fold a batch (..., D) into the statistics, only the finite rows where ``mask`` (..., 1) is True if given.

        The number of rows used stays a device tensor, so a masked update needs no host sync; an all-False mask
        leaves the statistics unchanged.
        """
        self._size_stats(x.shape[-1])
        batch = x.detach().reshape(-1, x.shape[-1]).to(torch.float64)
        keep = torch.isfinite(batch).all(-1, keepdim=True)
        if mask is not None:
            keep = keep & mask.detach().reshape(-1, 1).to(torch.bool)
        # Left-out rows are zeroed, not only weighted 0: NaN · 0 is still NaN.
        batch = torch.where(keep, batch, 0.0)
        w = keep.to(torch.float64)
        n = w.sum()
        b_mean = (batch * w).sum(0) / n.clamp_min(1.0)
        b_var = ((batch - b_mean).square() * w).sum(0) / n.clamp_min(1.0)
        total = self.count + n
        delta = b_mean - self.mean
        self.mean.add_(delta * (n / total))
        m2 = self.var * self.count + b_var * n + delta.square() * (self.count * n / total)
        self.var.copy_(m2 / total)
        self.count.copy_(total)

    def _loc_scale(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self.mean.to(torch.float32), torch.sqrt(self.var + self.eps).to(torch.float32)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        x = next_tensordict.get(self.in_keys[0])
        self._size_stats(x.shape[-1])
        loc, scale = self._loc_scale()
        next_tensordict.set(self.out_keys[0], self._normalize(x, loc, scale))
        return next_tensordict

    def _step_mask(self, next_tensordict: TensorDictBase) -> torch.Tensor:
        """``mask_key``'s (num_envs, 1) bool rows to learn from, checked on metadata only (no device read)."""
        mask = next_tensordict.get(self.mask_key, None)
        want = (*next_tensordict.batch_size, 1)
        if mask is None:
            # tensordict's get gives None for a missing key: a misspelt mask_key learnt from every row without a
            # word (and with mask_invert failed on ~None).
            raise KeyError(f"RunningNormalization mask_key {self.mask_key!r} is not in the step's output; pass a key "
                           f"of the step's (num_envs, 1) bool flags, e.g. 'terminated', or mask_key=None. Available: "
                           f"{sorted(str(k) for k in next_tensordict.keys(True, True))}")
        if mask.dtype != torch.bool or tuple(mask.shape) != want:
            raise ValueError(f"RunningNormalization mask_key {self.mask_key!r} must be {want} bool flags, got "
                             f"{tuple(mask.shape)} {mask.dtype}; pass a key of the step's done-like flags")
        return ~mask if self.mask_invert else mask

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        if not self.frozen:
            mask = None
            if self.mask_key is not None:
                mask = self._step_mask(next_tensordict)
            healthy = next_tensordict.get(self.health_key, None) if self.health_key is not None else None
            if healthy is not None:
                mask = healthy if mask is None else mask & healthy
            self.update(next_tensordict.get(self.in_keys[0]), mask)
        return self._call(next_tensordict)

    def _apply_transform(self, x: torch.Tensor) -> torch.Tensor:  # used by forward() on stored data
        self._size_stats(x.shape[-1])
        loc, scale = self._loc_scale()
        return self._normalize(x, loc, scale)



def running_normalizers(env) -> list[RunningNormalization]:
    """Every :class:`RunningNormalization` among ``env``'s transforms, each once: inside a nested ``Compose`` and
    in the transforms of a ``TransformedEnv`` wrapped by another too."""
    norms, seen, layer = {}, set(), env
    while layer is not None and id(layer) not in seen:
        seen.add(id(layer))
        transform = getattr(layer, "transform", None) or ()
        stages = [transform] if isinstance(transform, torch.nn.Module) else list(transform)  # a Compose, or a list
        norms.update((id(m), m) for stage in stages if isinstance(stage, torch.nn.Module) for m in stage.modules()
                     if isinstance(m, RunningNormalization))
        layer = getattr(layer, "base_env", None)
    return list(norms.values())


def untrained_running_normalizers(env) -> list[RunningNormalization]:
    """The :class:`RunningNormalization` of ``env`` (:func:`running_normalizers`) that never folded in a step: their
    statistics are still the starting ones, as in an env freshly built from a config, not a trained policy's
    (loaded from its checkpoint). Reads each count on the host: for set-up checks, not for the step."""
    return [n for n in running_normalizers(env) if float(n.count) == n.init_count]


def freeze_running_statistics(env) -> int:
    """Freeze every :class:`RunningNormalization` among ``env``'s transforms; returns how many.

    For an env that evaluates or exports a trained policy: it must normalise with the statistics the policy was
    trained with (those its checkpoint holds, and its export's contract states), not with ones that drift towards
    the evaluation's own rollouts. An env with a captured step graph (``SyncFreeResetEnv``) drops it when a
    normaliser changes: the graph replays the updates it was captured with.

    Every normaliser counts, wherever it sits: inside a nested ``Compose`` and in the transforms of a
    ``TransformedEnv`` wrapped by another (one left unfrozen would go on learning from the evaluation)."""
    norms = running_normalizers(env)
    changed = [t.freeze() for t in norms if not t.frozen]
    if changed and hasattr(env, "invalidate_graph"):
        env.invalidate_graph()
    return len(norms)
