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


def test_a_short_rollout_of_a_shipped_policy_writes_its_report(tmp_path):
    import json

    import pytest

    from lab.benchmarks.robust_policies import POLICIES

    out = tmp_path / "bounds.json"
    args = ["--checkpoint", str(POLICIES / "tocabi_walk_torque.pt"), "--num_envs", "2", "--seconds", "0.1",
            "--out", str(out)]
    assert action_bounds.main(args) == 0
    report = json.loads(out.read_text())
    (r,) = report["results"]
    assert len(r["entries"]) == 13 and r["entries"][-1] == r["phase_rate"]  # 12 legs, then the phase rate
    assert all(0.0 <= e["sampled_outside"] <= 1.0 and e["p5"] <= e["mean"] <= e["p95"] for e in r["entries"])
    assert report["command"].startswith("PYTHONPATH=. python lab/analysis/action_bounds.py --checkpoint")
    assert report["meta"]["hardware"].startswith("CPU")
    with pytest.raises(SystemExit):
        action_bounds.main(args)  # never overwrites
