"""ppo.overlap_update (rl/overlap.py): each rollout is collected with the actor as it was before the previous update,
the update's losses reach the adaptive learning rate and the log one rollout later, and a run checkpoints, logs and
resumes as without it. On the CPU the order is the GPU's, without the concurrency."""

from __future__ import annotations

import copy
import threading

import pytest
import torch

from tocabi_torchrl.rl import preset_config
from tocabi_torchrl.rl.metrics_files import read_metrics
from tocabi_torchrl.rl.rollout_guard import PROXIMAL_KEY


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

    def recording(cfg, flat, step, info=None, order=None):
        kept.append(flat is step.rows)  # with the overlap the update steps on the rollout its step keeps
        actor = agents[0].actor
        if snapshots:
            with torch.no_grad():
                logp = {name: a.get_dist(flat.clone()).log_prob(flat["action"])
                        for name, a in (("before_previous", snapshots[-1]), ("learner", actor))}
            checks.append({name: torch.allclose(v, flat["action_log_prob"], atol=1e-4) for name, v in logp.items()})
        snapshots.append(copy.deepcopy(actor))
        return losses(cfg, flat, step, info, order)

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
    # The spread of the surrogate's weights π_prox / π_behav, as an effective sample size (a fraction of the frames).
    ess = [float(r["behaviour_ess"]) for r in rows]
    assert all(0 < e <= 1 + 1e-6 for e in ess) and min(ess) < 0.99  # each update's policy moved from the one before
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


@pytest.mark.parametrize("device", ["cpu", GPU])
def test_an_update_queued_from_a_thread_returns_its_numbers_and_its_error(device):
    # launch(threaded=True) queues the update from a host thread of its own on a GPU (on the CPU, with no stream, it
    # runs at once): finish() hands back its numbers, or raises the error the thread met, after which a new update
    # can be launched.
    from tocabi_torchrl.rl.overlap import UpdateOverlap

    overlap = UpdateOverlap(torch.device(device), torch.nn.Linear(2, 1).to(device))
    threads = []

    def update():
        threads.append(threading.current_thread())
        return torch.arange(3.0, device=device) * 2

    overlap.launch(update, keep=None, threaded=True)
    overlap.annotate("ctx")
    assert overlap.finish() == ([0.0, 2.0, 4.0], "ctx")
    assert (threads[0] is threading.main_thread()) == (device == "cpu")

    def broken():
        raise ValueError("a mini-batch of the wrong size")

    if device == "cpu":  # the error comes at once
        with pytest.raises(ValueError, match="wrong size"):
            overlap.launch(broken, keep=None, threaded=True)
    else:  # the error comes with the wait
        overlap.launch(broken, keep=None, threaded=True)
        with pytest.raises(ValueError, match="wrong size"):
            overlap.finish()
    assert not overlap.in_flight
    overlap.launch(update, keep=None, threaded=True)
    assert overlap.finish() == ([0.0, 2.0, 4.0], None)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_a_run_whose_updates_are_queued_from_a_thread_trains_as_one_queued_inline(tmp_path, monkeypatch):
    # The thread changes when the host queues the update, not what runs on either stream nor in which order on each
    # (the mini-batch order is drawn on the trainer's thread, so the collector's random draws keep their order; the
    # CPU test below checks that a late update trains bit for bit alike). On a GPU the two runs' parameters differed
    # in the last digits after 4 updates (9.4e-6 at most on an H200; the GPU's physics may vary from run to run, its
    # contact order coming from atomics). The CPU test of a late update is the one that checks the order bit for bit.
    from tocabi_torchrl.rl import trainer
    from tocabi_torchrl.rl.overlap import UpdateOverlap

    launch, modes = UpdateOverlap.launch, []

    def run(name, threaded):
        def launching(self, update, keep, *, threaded=False):
            modes.append((name, threaded))
            return launch(self, update, keep, threaded=threaded and allow)

        allow = threaded
        monkeypatch.setattr(UpdateOverlap, "launch", launching)
        result = trainer.train(_cfg(tmp_path, name, True, "cuda", **{"ppo.update_graph": True}))
        return result.agent.actor.state_dict(), read_metrics(tmp_path / name)

    inline, inline_rows = run("inline", False)
    threaded, threaded_rows = run("threaded", True)
    # The first update warms up and captures its graph on the trainer's thread; later ones replay it from a thread.
    asked = [t for n, t in modes if n == "threaded"]
    assert len(asked) == 4 and not asked[0] and any(asked[1:])
    for key, value in inline.items():
        torch.testing.assert_close(threaded[key], value, rtol=0, atol=1e-4)
    assert len(inline_rows) == len(threaded_rows) == 4


@pytest.mark.parametrize("device", ["cpu", GPU])
def test_the_rollout_runs_on_a_stream_of_higher_priority_than_the_update(device):
    # On a GPU, collecting() moves the block onto the overlap's collection stream, of CUDA's high priority, after the
    # work queued before it; the update's stream has the low one. On the CPU (or asked not to) it changes nothing.
    from tocabi_torchrl.rl.overlap import UpdateOverlap

    overlap = UpdateOverlap(torch.device(device), torch.nn.Linear(2, 1).to(device))
    x = torch.zeros(1000, device=device)
    if device == "cpu":
        assert overlap.collect_stream is None
        with overlap.collecting():
            x += 1
    else:
        assert overlap.collect_stream.priority < overlap.stream.priority
        outer = torch.cuda.current_stream()
        x.add_(1.0)  # queued on the outer stream: ordered before the block
        with overlap.collecting():
            assert torch.cuda.current_stream() == overlap.collect_stream
            x.mul_(3.0)
        assert torch.cuda.current_stream() == outer
        same = UpdateOverlap(torch.device(device), torch.nn.Linear(2, 1).to(device), collect_first=False)
        assert same.collect_stream is None
    assert x.sum().item() == (1000.0 if device == "cpu" else 3000.0)


def test_an_update_queued_late_reads_what_it_was_launched_with(tmp_path, monkeypatch):
    # From a thread, the update may start after the trainer has gone on with the next rollout and let go of its own
    # names for the rollout and the mini-batch order: the update must hold them itself. An overlap that runs each
    # update only when it is waited for (a thread that starts as late as it can) trains exactly as the usual one.
    from tocabi_torchrl.rl import trainer
    from tocabi_torchrl.rl.overlap import UpdateOverlap

    class LateOverlap(UpdateOverlap):
        def launch(self, update, keep, *, threaded=False):
            self.late = update
            super().launch(lambda: torch.zeros(1), keep)  # in flight; run at finish()

        def finish(self):
            if not self.in_flight:
                return None
            _, context = super().finish()
            return self.late().tolist(), context

    usual = trainer.train(_cfg(tmp_path, "usual", True)).agent.actor.state_dict()
    monkeypatch.setattr(trainer, "UpdateOverlap", LateOverlap)
    late = trainer.train(_cfg(tmp_path, "late", True)).agent.actor.state_dict()
    for key, value in usual.items():
        torch.testing.assert_close(late[key], value, rtol=0, atol=0)


def test_a_launch_interrupted_before_its_thread_began_queues_nothing():
    # Ctrl-C inside Thread.start() can leave a thread that runs after finish() gave up on it: once cancelled, it
    # returns without queuing anything; one that has begun is waited for instead.
    from types import SimpleNamespace

    from tocabi_torchrl.rl.overlap import _Queuing

    queued = []
    overlap = SimpleNamespace(_queue=lambda update, ready: queued.append(update()) or "done")
    late = _Queuing(overlap, lambda: "update", ready=None)
    assert late.cancel_unless_begun()
    late.run()
    assert queued == [] and late.done is None and late.error is None
    begun = _Queuing(overlap, lambda: "update", ready=None)
    begun.run()
    assert not begun.cancel_unless_begun() and queued == ["update"] and begun.done == "done"


@pytest.mark.parametrize("device", ["cpu", GPU])
@pytest.mark.parametrize("overlap", [False, True])
def test_an_overlapped_update_measures_from_the_policy_it_starts_from(tmp_path, monkeypatch, overlap, device):
    # The decoupled objective (rollout_guard.GuardedClipPPOLoss.use_proximal): each frame's log-probability under the
    # learner as the update starts, its scheduled std already set, sits beside the behaviour policy's; without the
    # overlap the two are one policy and the batch holds no such entry. On a GPU the update (and the fill) run on
    # the side stream, queued from a thread once captured: read here, in the update, after the fill.
    from tocabi_torchrl.rl import trainer

    agents, checks = [], []
    build, losses = trainer.build_agent, trainer._update_losses

    def building(*args, **kwargs):
        agents.append(build(*args, **kwargs))
        return agents[-1]

    def recording(cfg, flat, step, info=None, order=None):
        if PROXIMAL_KEY not in flat.keys():
            checks.append(None)
        else:
            with torch.no_grad():
                learner = agents[0].actor.get_dist(flat.clone()).log_prob(flat["action"])
            checks.append((torch.allclose(flat[PROXIMAL_KEY], learner, atol=1e-5),
                           torch.allclose(flat[PROXIMAL_KEY], flat["action_log_prob"], atol=1e-4)))
        return losses(cfg, flat, step, info, order)

    monkeypatch.setattr(trainer, "build_agent", building)
    monkeypatch.setattr(trainer, "_update_losses", recording)
    result = trainer.train(_cfg(tmp_path, "proximal", overlap, device))  # the std schedule moves between updates
    assert result.iterations == 4
    # Every rollout explored: its actions are Gaussian draws around the mean (E|z| = 0.80), none the mean itself.
    noise = [float(r["action_noise_z"]) for r in read_metrics(tmp_path / "proximal")]
    assert len(noise) == 4 and all(0.7 < z < 0.9 for z in noise), noise
    # Never the policy that acted: the first rollout's std was the schedule's before its update, each later rollout
    # acted with the learner of one update before.
    assert checks == ([(True, False)] * 4 if overlap else [None] * 4)


def test_the_proximal_fill_leaves_the_process_wide_sampling_mode_alone(monkeypatch):
    # tensordict's sampling mode (interaction_type) is one setting for the whole process, which a TensorDict
    # module's get_dist sets and restores. The fill runs on the update's thread while the collector acts on the
    # trainer's: through get_dist it raced the rollout and left some rollouts acting with the mean action.
    from tensordict import TensorDict
    from tensordict.nn import probabilistic

    from tocabi_torchrl.rl.trainer import _fill_proximal, build_agent, make_loss

    cfg = preset_config("cpu_smoke", device="cpu", **{"ppo.overlap_update": True})
    agent = build_agent(cfg, 6, 13, torch.device("cpu"))
    loss, _ = make_loss(cfg, agent)
    n = 70_000  # more than one chunk
    flat = TensorDict({"observation": torch.randn(n, 6), "action": torch.randn(n, 13),
                       PROXIMAL_KEY: torch.zeros(n)}, batch_size=[n])
    set_modes = []
    manager = probabilistic._interaction_type
    monkeypatch.setattr(manager, "set_mode", lambda mode: set_modes.append(mode))
    _fill_proximal(loss, flat)
    assert set_modes == []
    with torch.no_grad():
        expected = agent.actor.get_dist(flat.clone()).log_prob(flat["action"])
    assert set_modes, "get_dist no longer sets the sampling mode: this test no longer guards anything"
    torch.testing.assert_close(flat[PROXIMAL_KEY], expected, rtol=1e-5, atol=1e-5)
