"""lab.benchmarks.update_profile on the CPU at toy size: the third update's profile, its report, its refusals."""

from __future__ import annotations

import json

import pytest

from lab.benchmarks import update_profile


def test_the_profile_of_one_update_lists_its_heaviest_ops_and_their_total(tmp_path):
    update_profile.main(["--device", "cpu", "--num_envs", "8", "--rows", "5", "--out", str(tmp_path),
                         "--run_dir", str(tmp_path / "runs"), "--name", "up"])
    r = json.loads((tmp_path / "up.json").read_text())["results"]
    # 8 envs x 48 steps, mini-batches of a quarter of the rollout (the throughput benchmarks' rule), 5 epochs.
    assert (r["minibatch_size"], r["minibatch_steps"], r["clock"]) == (96, 20, "host")
    own = [e["own_ms"] for e in r["top"]]
    assert len(own) == 5 and own == sorted(own, reverse=True) and 0 < sum(own) <= r["update_ms"]
    # Twenty mini-batch steps: each runs the actor's and the critic's products, so the heaviest ops are called often.
    assert max(e["calls"] for e in r["top"]) >= 20
    page = (tmp_path / "up.md").read_text()
    assert f"**{r['update_ms']:.1f} ms** of host time" in page and "the loss eager" in page


def test_the_profile_refuses_an_overlapped_update_and_bad_counts(tmp_path, capsys):
    with pytest.raises(SystemExit, match="leave ppo.overlap_update off"):
        update_profile.profile_update(8, "cpu", {"ppo.overlap_update": True}, str(tmp_path))
    with pytest.raises(SystemExit):
        update_profile.main(["--device", "cpu", "--rows", "0"])
    assert "--num_envs and --rows take counts >= 1" in capsys.readouterr().err
