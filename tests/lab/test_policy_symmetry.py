"""lab/analysis/policy_symmetry.py: how asymmetric a policy is, and whether the augmentation's mirrored frames
still fall inside PPO's clip."""

from __future__ import annotations

import doctest
import json

import pytest
import torch

from lab.analysis import policy_symmetry


def test_docstring_examples_run():
    result = doctest.testmod(policy_symmetry)
    assert result.attempted >= 2 and result.failed == 0


def test_a_symmetric_policy_keeps_every_mirrored_frame_inside_the_clip_and_an_asymmetric_one_none():
    loc = torch.randn(64, 13)
    sigma = torch.full((12,), 0.05)
    same = policy_symmetry.mirrored_log_ratio(loc, loc, loc, sigma)
    assert torch.equal(same, torch.zeros(64)) and policy_symmetry.within_clip(same, 0.2) == 1.0
    # 0.07 off on every leg joint at σ 0.05: 12 · 0.98 nats below, far outside a 0.2 clip; a wider σ brings it back.
    off = policy_symmetry.mirrored_log_ratio(loc, loc + 0.07, loc, sigma)
    assert torch.allclose(off, torch.full((64,), -11.76)) and policy_symmetry.within_clip(off, 0.2) == 0.0
    wide = policy_symmetry.mirrored_log_ratio(loc, loc + 0.07, loc, torch.full((12,), 1.0))
    assert policy_symmetry.within_clip(wide, 0.2) == 1.0
    # The phase-rate action (13th) is not counted.
    assert torch.equal(policy_symmetry.mirrored_log_ratio(loc, loc + torch.eye(13)[12], loc, sigma), same)


def test_a_short_rollout_of_a_shipped_policy_writes_its_report(tmp_path):
    from lab.benchmarks.robust_policies import POLICIES

    out = tmp_path / "symmetry.json"
    args = ["--checkpoint", str(POLICIES / "tocabi_walk_torque.pt"), "--num_envs", "2", "--seconds", "0.1",
            "--out", str(out)]
    assert policy_symmetry.main(args) == 0
    report = json.loads(out.read_text())
    (r,) = report["results"]
    assert r["inputs"] == 2 * 25 and r["leg_asymmetry_abs"]["mean"] >= 0.0
    assert 0.0 <= r["mirrored_frames_within_clip"] <= 1.0 and r["clip_epsilon"] == 0.2
    assert report["command"].startswith("PYTHONPATH=. python lab/analysis/policy_symmetry.py --checkpoint")
    with pytest.raises(SystemExit):
        policy_symmetry.main(args)  # never overwrites
