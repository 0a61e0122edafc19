"""What every evaluation's output shares: the refusal to overwrite earlier results and JSON without NaN."""

from __future__ import annotations

import math

__all__ = ["OutputExistsError", "json_safe"]


class OutputExistsError(RuntimeError):
    """The output folder holds earlier results that this run would overwrite."""


def json_safe(value):
    """``value`` with every non-finite float (NaN, ±inf) as ``None``, recursively through dicts, lists and tuples
    (tuples become lists): strict JSON (``allow_nan=False``) accepts the result."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value
