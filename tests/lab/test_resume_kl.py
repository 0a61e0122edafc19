"""lab/analysis/resume_kl.py: the first PPO updates after a resume, as saved and in variants."""

from __future__ import annotations

import json

import pytest
import torch

from lab.analysis import resume_kl


def _state(num_envs=4096, minibatch=49152):
    return {"config": {"env": {"num_envs": num_envs, "task": {"start_joint_vel_std": 0.5, "start_base_vel_std": 0.1}},
                       "ppo": {"minibatch_size": minibatch, "assist_absorb": 1.0}}}


def test_the_copy_scales_the_robots_and_mini_batch_and_carries_the_variant_without_touching_the_source(tmp_path):
    state = _state()
    out = resume_kl.resumed_copy(state, 64, resume_kl.VARIANTS["still_starts"], tmp_path / "c.pt")
    config = torch.load(out, weights_only=True)["config"]
    assert config["env"]["num_envs"] == 64 and config["ppo"]["minibatch_size"] == 768  # 4 mini-batches, as saved
    assert config["env"]["task"] == {"start_joint_vel_std": 0.0, "start_base_vel_std": 0.0}
    assert state == _state()
    for envs, state_ in ((64, _state(minibatch=1000)), (100, state)):  # mini-batches not kept; not a divisor
        with pytest.raises(ValueError, match="is not a divisor of the run's"):
            resume_kl.resumed_copy(state_, envs, {}, tmp_path / "d.pt")
    for path in ("ppo.no_such", "no_such.part"):
        with pytest.raises(KeyError, match=path):
            resume_kl.resumed_copy(state, 64, {path: 1}, tmp_path / "e.pt")


def test_a_short_run_resumed_in_two_variants_writes_its_report(tmp_path):
    from tocabi_torchrl.rl import preset_config
    from tocabi_torchrl.rl.trainer import train

    cfg = preset_config("cpu_smoke", device="cpu", run_dir=str(tmp_path), name="src", progress_bar=False,
                        eval_at_end=False, total_env_steps=2 * 8 * 16)
    latest = train(cfg).run_dir / "checkpoints" / "latest.pt"
    before = latest.read_bytes()
    out = tmp_path / "resume_kl.json"
    args = ["--checkpoint", str(latest), "--num_envs", "4", "--iterations", "2", "--variants", "as_saved",
            "no_absorb", "--out", str(out)]
    assert resume_kl.main(args) == 0
    report = json.loads(out.read_text())
    assert [r["variant"] for r in report["results"]] == ["as_saved", "no_absorb"]
    for r in report["results"]:
        # The resumed run goes on after the saved two iterations with 4 robots, each of its two iterations logged.
        assert [row["iteration"] for row in r["iterations"]] == [3, 4] and r["num_envs"] == 4
        assert all(row["kl"] >= 0.0 for row in r["iterations"]) and r["resumed_at_env_steps"] == 2 * 8 * 16
    assert latest.read_bytes() == before
    assert report["command"].startswith("PYTHONPATH=. python lab/analysis/resume_kl.py --checkpoint")
    with pytest.raises(SystemExit):
        resume_kl.main(args)  # never overwrites


def test_a_policy_file_without_its_optimiser_is_refused(tmp_path, capsys):
    from lab.benchmarks.robust_policies import POLICIES

    with pytest.raises(SystemExit):
        resume_kl.main(["--checkpoint", str(POLICIES / "tocabi_walk_torque.pt")])
    assert "holds no optimiser state" in capsys.readouterr().err
