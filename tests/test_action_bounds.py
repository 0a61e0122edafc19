"""lab/analysis/action_bounds.py: the share of a policy's means and sampled actions outside the action bounds."""
import doctest

import torch

from lab.analysis import action_bounds


def test_its_examples_run():
    assert doctest.testmod(action_bounds).failed == 0


def test_each_entry_counts_its_own_bounds():
    loc = torch.tensor([[0.5, -0.2], [1.5, 0.3], [0.0, -0.1], [-1.2, 0.6]])  # leg-like in [-1, 1], rate-like in [0, 1]
    action = loc + torch.tensor([[0.6, 0.0], [0.0, 0.0], [0.0, 0.2], [0.0, 0.5]])
    stats = action_bounds.bound_statistics(loc, action, torch.tensor([-1.0, 0.0]), torch.tensor([1.0, 1.0]))
    assert [s["mean_outside"] for s in stats] == [0.5, 0.5]  # 1.5 and -1.2; -0.2 and -0.1
    assert [s["sampled_outside"] for s in stats] == [0.75, 0.5]  # 1.1, 1.5, -1.2; -0.2 and 1.1
    assert stats[1]["mean"] == round(0.15, 4) and stats[0]["p5"] < stats[0]["p95"]
