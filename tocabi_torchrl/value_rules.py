"""The rules a config value must obey, each written once: the env config (``envs/config.py``), the run config
(``config.py``), the env's seed entry points and the policy contract reader (``runtime/contract.py``) all check with
these, so a value one of them refuses cannot reach the robot through another.

Standard library only: the torch-free runtime imports it to check a contract before loading anything else.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Any

__all__ = ["ENV_RULES", "FINITE", "MAX_SEED", "NON_NEGATIVE", "POSITIVE", "POSITIVE_INT", "Range", "check_env_value",
           "check_seed"]


@dataclass(frozen=True)
class Range:
    """A real number in ``[low, high]`` (an end excluded where ``low_open``/``high_open``), always finite, and an
    int where ``integer``. A bool is refused either way: ``True`` is not a gain."""

    low: float = -math.inf
    high: float = math.inf
    low_open: bool = False
    high_open: bool = False
    integer: bool = False

    def allows(self, value: Any) -> bool:
        """Whether ``value`` obeys the rule (text, NaN, inf and bools do not)."""
        if isinstance(value, bool) or not isinstance(value, numbers.Integral if self.integer else numbers.Real):
            return False
        try:
            if not math.isfinite(value):
                return False
        except OverflowError:  # an int too large for a float is beyond any range here
            return False
        above = value > self.low if self.low_open else value >= self.low
        below = value < self.high if self.high_open else value <= self.high
        return above and below

    def describe(self) -> str:
        """The allowed values in words, e.g. ``"a finite number >= 0"``, ``"a finite number in [0, 100)"``."""
        kind = "an int" if self.integer else "a finite number"
        low, high = _text(self.low), _text(self.high)
        if self.low == -math.inf and self.high == math.inf:
            return kind
        if self.high == math.inf:
            return f"{kind} {'>' if self.low_open else '>='} {low}"
        if self.low == -math.inf:
            return f"{kind} {'<' if self.high_open else '<='} {high}"
        return f"{kind} in {'(' if self.low_open else '['}{low}, {high}{')' if self.high_open else ']'}"

    def check(self, value: Any, where: str) -> None:
        """Raise ``ValueError`` naming ``where``, the allowed values and ``value`` unless the rule allows it."""
        if not self.allows(value):
            raise ValueError(f"{where} must be {self.describe()}, got {value!r}")


def _text(bound: float) -> str:
    return str(int(bound)) if float(bound).is_integer() else repr(bound)


FINITE = Range()
NON_NEGATIVE = Range(low=0.0)
POSITIVE = Range(low=0.0, low_open=True)
POSITIVE_INT = Range(low=1, integer=True)

#: The rule of each numeric env config value, by its path in the env tree (``TocabiWalkConfig``); a tuple value's
#: rule holds for every entry. ``runtime/contract.py`` checks the contract fields that carry these values with the
#: same rules (its ``ENV_FIELDS``).
ENV_RULES: dict[str, Range] = {
    "sim.substeps": POSITIVE_INT,
    "task.phase_rate_gain": Range(low=0.0, high=100.0, high_open=True),
    "task.min_pelvis_height": NON_NEGATIVE,
    "task.min_neck_height": NON_NEGATIVE,
    "task.max_neck_angle": NON_NEGATIVE,
    "control.pd_kp": NON_NEGATIVE,
    "control.pd_kv": NON_NEGATIVE,
    "control.pd_action_scale": NON_NEGATIVE,
    "control.pd_nominal": FINITE,
    "control.mb_omega": NON_NEGATIVE,
    "control.mb_zeta": NON_NEGATIVE,
    "control.mb_residual_gain": NON_NEGATIVE,
    "control.mb_ref_window": POSITIVE,
}


def check_env_value(path: str, value: Any, where: str | None = None) -> None:
    """Raise ``ValueError`` unless ``value`` (every entry of a tuple or list) obeys the rule of the env config value
    at ``path`` (:data:`ENV_RULES`); the message names ``where`` (default ``env.<path>``), entry ``[i]`` included."""
    rule = ENV_RULES[path]
    where = where or f"env.{path}"
    if isinstance(value, (tuple, list)):
        for i, v in enumerate(value):
            rule.check(v, f"{where}[{i}]")
    else:
        rule.check(value, where)


#: The largest seed: the env keeps its seed in an int64 tensor (``envs/tocabi_walk.py``).
MAX_SEED = 2**63 - 1


def check_seed(seed: Any, where: str = "seed") -> int:
    """``seed`` as a plain int, or a ``ValueError`` naming ``where``: a seed is an int in [0, 2**63 - 1] (numpy
    ints too; bools, floats and text are refused). The one rule of every place a seed enters: the env's constructor,
    ``set_seed``, ``reset(seed=...)``, ``make_env`` and the run config's ``seed``."""
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or not 0 <= seed <= MAX_SEED:
        raise ValueError(f"{where} must be an int in [0, 2**63 - 1] (the env keeps it as a 64-bit int; not a bool, "
                         f"a float or text), got {seed!r}; give e.g. {where}=0")
    return int(seed)
