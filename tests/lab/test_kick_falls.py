"""lab/analysis/kick_falls.py's breakdown of falls by the time since a robot's previous kick."""

from __future__ import annotations

import doctest
import math

import torch

from lab.analysis import kick_falls


def test_docstring_examples_run():
    result = doctest.testmod(kick_falls, optionflags=doctest.ELLIPSIS)
    assert result.attempted >= 3 and result.failed == 0


def test_each_kick_after_the_first_is_binned_once_and_only_the_last_before_a_fall_counts():
    inf = math.inf
    kick_s = torch.tensor([[2.0, 2.2, 6.5],    # falls at 3.0: the 0.2 s-gap kick is its last, the third never meets it
                           [5.9, 2.0, 4.4],    # unsorted: gaps 2.4 and 1.5; falls at 7.0 after the 1.5 s-gap kick
                           [2.0, 2.6, 4.0],    # stands: gaps 0.6 and 1.4
                           [3.0, 3.1, 3.2]])   # falls at 2.5, before any kick: nothing binned
    t_end = torch.tensor([3.0, 7.0, inf, 2.5])
    table = kick_falls.hazard_by_gap(kick_s, t_end)
    assert list(table) == ["<0.5 s", "0.5-1 s", "1-2 s", ">=2 s"]
    assert table["<0.5 s"] == {"met": 1, "falls": 1, "hazard": 1.0}
    assert table["0.5-1 s"] == {"met": 1, "falls": 0, "hazard": 0.0}
    assert table["1-2 s"] == {"met": 2, "falls": 1, "hazard": 0.5}
    assert table[">=2 s"] == {"met": 1, "falls": 0, "hazard": 0.0}
    assert sum(c["met"] for c in table.values()) == 5


def test_a_bin_no_kick_reaches_has_no_hazard():
    table = kick_falls.hazard_by_gap(torch.tensor([[2.0, 5.0]]), torch.tensor([math.inf]), edges=(1.0,))
    assert table == {"<1 s": {"met": 0, "falls": 0, "hazard": None}, ">=1 s": {"met": 1, "falls": 0, "hazard": 0.0}}
