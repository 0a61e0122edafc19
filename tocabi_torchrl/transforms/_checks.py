"""Input checks shared by the transforms: each error names the problem and the fix."""

from __future__ import annotations

import math
from numbers import Real
from typing import TYPE_CHECKING

from tocabi_torchrl.value_rules import plain_number

if TYPE_CHECKING:  # annotations only: the config's checks (check_positive_int) need no torch
    from tensordict.utils import NestedKey
    from torchrl.data import Composite, TensorSpec

__all__ = ["require_spec", "check_positive_int", "check_finite", "check_positive"]

# Which transform produces which derived key, so a missing-key error can say what to add in front.
_PRODUCERS = {
    "base_rpy": "BaseEulerAngles",
    "phase_sin": "PhaseEncoding",
    "phase_cos": "PhaseEncoding",
    "obs_step": "ObservationAssembly",
    "obs_step_norm": "FixedNormalization or RunningNormalization",
}


def require_spec(
    observation_spec: Composite, key: NestedKey, owner: object, last_dim: int | None = None
) -> TensorSpec:
    """Return ``observation_spec[key]``; raise ``KeyError``/``ValueError`` naming the owner, the key and the fix."""
    name = type(owner).__name__
    if key not in observation_spec.keys(True, True):
        hint = _PRODUCERS.get(key if isinstance(key, str) else key[-1])
        fix = (
            f"put {hint} before {name} in the Compose"
            if hint
            else "check the key name against docs/concepts/env-and-signals.md or the transform that should produce it"
        )
        available = sorted(str(k) for k in observation_spec.keys(True, True))
        raise KeyError(f"{name} reads {key!r}, which the environment does not provide; {fix}. Available: {available}")
    spec = observation_spec[key]
    if last_dim is not None and (len(spec.shape) == 0 or spec.shape[-1] != last_dim):
        raise ValueError(
            f"{name} expects {key!r} with last dimension {last_dim}, but its spec has shape {tuple(spec.shape)}; "
            "fix the producing transform or pass the right key"
        )
    return spec


def check_positive_int(value: object, what: str, fix: str = "") -> int:
    """``value`` as a plain int >= 1; raises naming ``what``. A numpy integer or a 0-d array or tensor is taken as the
    int it holds (:func:`~tocabi_torchrl.value_rules.plain_number`), as the config tree takes it, and a bool is not
    a count. Callers store the returned value, so no numpy scalar is kept."""
    plain = plain_number(value)
    if isinstance(plain, bool) or not isinstance(plain, int) or plain < 1:
        raise ValueError(f"{what} must be an integer >= 1, got {value!r}" + (f"; {fix}" if fix else ""))
    return plain


def check_finite(value: object, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, Real) or not math.isfinite(float(value)):
        raise ValueError(f"{what} must be a finite real number, got {value!r}")
    return float(value)


def check_positive(value: object, what: str) -> float:
    v = check_finite(value, what)
    if v <= 0:
        raise ValueError(f"{what} must be > 0, got {value!r}")
    return v
