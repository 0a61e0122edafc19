"""ppo.overlap_update (rl/overlap.py): each rollout is collected with the actor as it was before the previous update,
the update's losses reach the adaptive learning rate and the log one rollout later, and a run checkpoints, logs and
resumes as without it. On the CPU the order is the GPU's, without the concurrency."""

from __future__ import annotations

import copy

import pytest
import torch

from tocabi_torchrl.rl import preset_config
from tocabi_torchrl.rl.metrics_files import read_metrics


def _cfg(tmp_path, name, overlap, device="cpu", **extra):
    return preset_config("cpu_smoke", device=device, run_dir=str(tmp_path), name=name, progress_bar=False,
                         eval_at_end=False, log_every=1, checkpoint_every=100, total_env_steps=4 * 8 * 16,
                         **{"ppo.overlap_update": overlap, **extra})


GPU = pytest.param("cuda", marks=[pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(),
                                                                      reason="needs CUDA")])


@pytest.mark.parametrize("device", ["cpu", GPU])
@pytest.mark.parametrize("overlap", [False, True])
def test_each_rollout_acts_with_the_actor_of_the_update_before_or_its_own(tmp_path, monkeypatch, overlap, device):
    # On a GPU the update runs on its side stream: the same values, read after it is done.
    # The rollout's stored log-probabilities are those of the actor that acted: with overlap_update the learner as
    # it was before the previous update (snapshots[k - 1] for rollout k + 1), without it the learner itself.
    from tocabi_torchrl.rl import trainer

    agents, snapshots, checks, kept = [], [], [], []
    build, losses = trainer.build_agent, trainer._update_losses

    def building(*args, **kwargs):
        agents.append(build(*args, **kwargs))
        return agents[-1]

    def recording(cfg, flat, step, info=None):
        kept.append(flat is step.rows)  # with the overlap the update steps on the rollout its step keeps
        actor = agents[0].actor
        if snapshots:
            with torch.no_grad():
                logp = {name: a.get_dist(flat.clone()).log_prob(flat["action"])
                        for name, a in (("before_previous", snapshots[-1]), ("learner", actor))}
            checks.append({name: torch.allclose(v, flat["action_log_prob"], atol=1e-4) for name, v in logp.items()})
        snapshots.append(copy.deepcopy(actor))
        return losses(cfg, flat, step, info)

    monkeypatch.setattr(trainer, "build_agent", building)
    monkeypatch.setattr(trainer, "_update_losses", recording)
    # A constant std: the schedule changes the learner's between a rollout and its update.
    result = trainer.train(_cfg(tmp_path, "lag", overlap, device, **{"ppo.std_start": 0.1, "ppo.std_end": 0.1}))
    assert result.iterations == 4 and len(checks) == 3
    expected = {"before_previous": True, "learner": False} if overlap else {"before_previous": False, "learner": True}
    assert checks == [expected] * 3
    assert kept == [overlap] * 4


def test_an_overlapped_run_logs_every_update_checkpoints_the_learner_and_resumes(tmp_path):
    from tocabi_torchrl.rl.trainer import train

    cfg = _cfg(tmp_path, "run", True, **{"ppo.lr": 2e-4, "ppo.lr_min": 1e-4, "ppo.desired_kl": 1e-12})
    result = train(cfg)
    rows = read_metrics(tmp_path / "run")
    assert [int(float(r["env_steps"])) for r in rows] == [128 * k for k in (1, 2, 3, 4)]
    assert all(float(r["kl"]) >= 0 for r in rows)
    # The adaptive rate read each update's KL (a target no update meets): down one step per update to the floor.
    rates = [float(r["lr"]) for r in rows]
    assert rates[0] == pytest.approx(2e-4 / 1.5) and rates[1:] == pytest.approx([1e-4] * 3)
    # The checkpoint holds the learner after the last update, not the collector's copy.
    saved = torch.load(tmp_path / "run" / "checkpoints" / "latest.pt", weights_only=True)["agent"]["actor"]
    for key, value in result.agent.actor.state_dict().items():
        torch.testing.assert_close(saved[key], value)
    resumed = preset_config("cpu_smoke", **{**cfg.to_dict(), "total_env_steps": 4 * 8 * 16 + 128,
                                            "resume": str(tmp_path / "run")})
    assert train(resumed).iterations == 5


def test_overlap_update_refuses_a_data_parallel_run(tmp_path):
    from tocabi_torchrl.rl.distributed import DistInfo
    from tocabi_torchrl.rl.trainer import train

    with pytest.raises(ValueError, match="ppo.overlap_update runs on one rank; this run has 2"):
        train(_cfg(tmp_path, "ddp", True), dist_info=DistInfo(rank=0, world_size=2, local_rank=0))


def test_update_overlap_refuses_to_race_an_update_in_flight():
    from tocabi_torchrl.rl.overlap import UpdateOverlap

    overlap = UpdateOverlap(torch.device("cpu"), torch.nn.Linear(2, 1))
    overlap.launch(lambda: torch.zeros(1), keep=None)
    with pytest.raises(RuntimeError, match="call finish"):
        overlap.refresh()
    with pytest.raises(RuntimeError, match="call finish"):
        overlap.launch(lambda: torch.zeros(1), keep=None)
    assert overlap.finish() == ([0.0], None) and not overlap.in_flight
