"""What every evaluation's output shares: the refusal to overwrite earlier results and JSON without NaN."""

from __future__ import annotations

import math
from pathlib import Path

__all__ = ["OutputExistsError", "check_results_folder", "json_safe", "remove_if_empty", "rounded_against"]


class OutputExistsError(RuntimeError):
    """The output folder holds earlier results that this run would overwrite."""


def check_results_folder(out_dir, names, replace: bool) -> None:
    """Before an evaluation builds anything: ``ValueError`` if ``out_dir`` is a file, :class:`OutputExistsError` if it
    holds one of the evaluation's result files ``names`` and not ``replace``. ``out_dir`` None (a fresh folder)
    passes."""
    if out_dir is None:
        return
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ValueError(f"out_dir {out_dir} is a file, not a folder: give a folder for the results")
    held = [] if replace else [out_dir / name for name in names if (out_dir / name).exists()]
    if held:
        raise OutputExistsError(f"{held[0]} holds an earlier evaluation's results; nothing was overwritten. Pass "
                                "replace=True to replace the files of the same name, another out_dir, or none (a "
                                "fresh eval/, eval_2/, ... folder)")


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


def remove_if_empty(out, made: bool) -> bool:
    """After a stopped evaluation: remove the results folder ``out`` if this evaluation ``made`` it and it is still
    empty (a folder given stays). Returns whether ``out`` holds files (what was written before the stop)."""
    kept = out is not None and out.is_dir() and any(out.iterdir())
    if made and out is not None and out.is_dir() and not kept:
        out.rmdir()
    return kept


def rounded_against(value: float, limit: float, passed: bool, kind: str, decimals: int) -> str:
    """``value`` with ``decimals`` decimals, or as many more as it takes for the rounded number to read as the
    verdict ``passed`` of ``value >= limit`` (``kind`` "min") or ``value <= limit`` ("max"): 0.9697 shown as 0.970
    beside "needs >= 0.97 FAIL" reads as a wrong verdict, 0.9697 does not."""
    for places in range(decimals, decimals + 7):
        text = f"{value:.{places}f}"
        if (float(text) >= limit if kind == "min" else float(text) <= limit) == passed:
            return text
    return repr(value)
