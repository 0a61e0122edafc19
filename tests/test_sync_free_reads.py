"""The reads between two rollouts that no longer make the host wait for the GPU's queue: TorchRL's GAE without its
NaN check (rl/gae.py) and the deferred host copies (rl/deferred_read.py), an iteration's only reads
(tests/test_training_step_host_reads.py counts them on the CPU)."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torch.overrides import TorchFunctionMode
from torchrl.objectives.value import GAE

from tocabi_torchrl.rl.deferred_read import DeferredRead
from tocabi_torchrl.rl.gae import SyncFreeGAE

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


def _rollout(n: int = 3, t: int = 5, nan: bool = False) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(n, t, 4, generator=g)
    nxt = torch.randn(n, t, 4, generator=g)
    if nan:  # a next observation a collector left out at a trajectory's end
        nxt[1, 2, :] = float("nan")
    done = torch.zeros(n, t, 1, dtype=torch.bool)
    done[1, 2] = True
    return TensorDict({"observation": obs, "next": {"observation": nxt, "reward": torch.randn(n, t, 1, generator=g),
                                                     "done": done, "terminated": done.clone()}}, batch_size=[n, t])


class _Reads(TorchFunctionMode):
    """The calls that bring a tensor's values to the host, by name."""

    def __init__(self):
        super().__init__()
        self.reads = []

    def __torch_function__(self, func, types, args=(), kwargs=None):
        if getattr(func, "__name__", "") in {"tolist", "item", "__bool__", "__float__", "__int__", "cpu", "numpy"}:
            self.reads.append(func.__name__)
        return func(*args, **(kwargs or {}))


@pytest.mark.parametrize("nan", [False, True], ids=["finite", "nan_next_observation"])
def test_sync_free_gae_gives_torchrls_advantages_without_a_host_read(nan):
    from torchrl.modules import ValueOperator

    torch.manual_seed(0)
    critic = ValueOperator(torch.nn.Linear(4, 1), in_keys=["observation"])
    ours, theirs = (cls(gamma=0.99, lmbda=0.95, value_network=critic, average_gae=False) for cls in (SyncFreeGAE, GAE))
    with torch.no_grad():
        expected = theirs(_rollout(nan=nan))
        with _Reads() as probe:
            got = ours(_rollout(nan=nan))
    assert probe.reads == [], probe.reads  # TorchRL's asks nan_mask.any() once per critic input
    for key in ("advantage", "value_target"):
        assert torch.equal(got[key], expected[key]), key
    assert torch.isfinite(got["advantage"]).all()


def test_sync_free_gae_replaces_in_place_where_it_can_and_in_a_copy_where_it_cannot():
    data = _rollout(nan=True)
    nxt = data["next", "observation"]
    out = SyncFreeGAE._sanitize_next_obs_nan(data, ["observation"])
    assert out is data and out["next", "observation"] is nxt  # the rollout's own tensor, its NaN row replaced
    assert torch.equal(nxt[1, 2], data["observation"][1, 2]) and torch.isfinite(nxt).all()
    # A next observation that shares memory across entries (expanded) cannot take the write: a copy, as TorchRL's.
    data = _rollout()
    row = torch.tensor([1.0, float("nan"), 2.0, 3.0])
    data["next"].set("observation", row.expand(3, 5, 4), inplace=False)
    out = SyncFreeGAE._sanitize_next_obs_nan(data, ["observation"])
    assert out is not data and torch.isnan(data["next", "observation"]).any()  # the caller's is left as it was
    assert torch.equal(out["next", "observation"][..., 1], data["observation"][..., 1])


def test_the_trainers_gae_keeps_gamma_and_lambda_on_the_critics_device():
    """Built without a device, TorchRL's GAE keeps gamma and lambda on the default device and copies them to the
    reward's on its first call: on CUDA a blocking host-to-device copy inside the first iteration. Built under another
    default device (meta here, standing for the CPU beside a CUDA critic), the trainer's still puts them by the
    critic."""
    from tocabi_torchrl.rl import preset_config
    from tocabi_torchrl.rl.trainer import build_agent, make_loss

    cfg = preset_config("cpu_smoke", device="cpu")
    agent = build_agent(cfg, 17, 5, torch.device("cpu"))
    with torch.device("meta"):
        _, advantage = make_loss(cfg, agent)
    critic_device = next(agent.critic.parameters()).device
    assert advantage.gamma.device == advantage.lmbda.device == critic_device != torch.device("meta")


def test_deferred_read_hands_back_one_read_at_a_time():
    read = DeferredRead()
    with pytest.raises(RuntimeError, match="no read started"):
        read.values()
    read.start(torch.tensor([1.0, 2.0]))
    assert read.pending
    with pytest.raises(RuntimeError, match="read pending"):  # its numbers would be overwritten untaken
        read.start(torch.tensor([3.0]))
    assert read.values() == [1.0, 2.0] and not read.pending
    read.start(torch.tensor([3.0]))
    assert read.values() == [3.0]


@pytest.mark.gpu
@CUDA
def test_deferred_read_on_cuda_copies_without_a_sync_and_keeps_its_pinned_buffer():
    read = DeferredRead()
    values = torch.arange(4, dtype=torch.float32, device="cuda")
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        read.start(values * 2)  # queued: a .tolist() here would raise under the debug mode
    finally:
        torch.cuda.set_sync_debug_mode(0)
    buffer = read._buffer
    assert buffer.is_pinned() and read.values() == [0.0, 2.0, 4.0, 6.0]
    read.start(values + 1)
    assert read._buffer is buffer and read.values() == [1.0, 2.0, 3.0, 4.0]  # no allocation per iteration


class _CudaReads(TorchFunctionMode):
    """The reads of a CUDA tensor's values into Python while :attr:`on`, by the innermost frame of the package or of
    TorchRL: each makes the host wait for everything queued before it."""

    READS = {"tolist", "item", "__bool__", "__float__", "__int__", "__index__", "cpu", "numpy"}

    def __init__(self):
        super().__init__()
        self.reads, self.on = [], False

    def __torch_function__(self, func, types, args=(), kwargs=None):
        if (self.on and getattr(func, "__name__", "") in self.READS and args and isinstance(args[0], torch.Tensor)
                and args[0].is_cuda):
            import traceback

            frames = [f.name for f in traceback.extract_stack()[:-1] if "torchrl" in f.filename]
            self.reads.append((frames[-1] if frames else "?", func.__name__))
        return func(*args, **(kwargs or {}))


OPTIONS = {"update_inline": {}, "overlap_update": {"ppo.overlap_update": True},
           "overlap_minibatch_kl_privileged": {"ppo.overlap_update": True, "ppo.kl_adapt_every": "minibatch",
                                               "ppo.critic_privileged": True}}


@pytest.mark.gpu
@CUDA
@pytest.mark.parametrize("option", list(OPTIONS))
def test_training_reads_no_cuda_value_between_rollouts(tmp_path, monkeypatch, option):
    """On CUDA, from the first rollout's end on, nothing of the training loop reads a CUDA tensor's values on the host
    or synchronises (``torch.cuda.set_sync_debug_mode("error")``; checkpoints aside, and the waits for the deferred
    copies' own events, which that mode does not count), with the update on the training stream or beside the next
    rollout: the losses and the episode metrics come back through pinned memory, GAE no longer asks whether a next
    observation holds NaN, and the env step and the update read nothing."""
    from tocabi_torchrl.rl import preset_config, trainer

    cfg = preset_config("cpu_smoke", device="cuda", run_dir=str(tmp_path), name="o", progress_bar=False,
                        eval_at_end=False, log_every=1, checkpoint_every=100, total_env_steps=4 * 8 * 16,
                        **OPTIONS[option])
    probe = _CudaReads()
    estimate, save = trainer.estimate_advantages, trainer.save_checkpoint

    def watching(on: bool) -> None:
        probe.on = on
        torch.cuda.set_sync_debug_mode("error" if on else 0)

    def from_the_first_advantages(*args, **kwargs):  # start-up reads come before it
        watching(True)
        return estimate(*args, **kwargs)

    def saving(*args, **kwargs):  # a checkpoint copies the state to the host by design
        watching(False)
        try:
            return save(*args, **kwargs)
        finally:
            watching(True)

    make_collector = trainer.make_collector

    def collector_off_at_shutdown(*args, **kwargs):  # the loop's end: what comes after it is no iteration's
        collector = make_collector(*args, **kwargs)
        shutdown = collector.shutdown

        def shutting_down(*a, **k):
            watching(False)
            return shutdown(*a, **k)

        collector.shutdown = shutting_down
        return collector

    monkeypatch.setattr(trainer, "estimate_advantages", from_the_first_advantages)
    monkeypatch.setattr(trainer, "save_checkpoint", saving)
    monkeypatch.setattr(trainer, "make_collector", collector_off_at_shutdown)
    try:
        with probe:
            result = trainer.train(cfg)
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert result.iterations == 4
    assert probe.reads == [], probe.reads


@pytest.mark.parametrize("overlap", [False, True], ids=["update_inline", "overlap_update"])
def test_an_error_in_the_next_rollout_still_logs_the_update_before_it(tmp_path, monkeypatch, overlap):
    """The update's row is written once the next rollout is queued; an error while that rollout is collected (a
    crash, a second Ctrl-C) still writes it, the row someone diagnosing the crash reads first."""
    from tocabi_torchrl.rl import preset_config, trainer
    from tocabi_torchrl.rl.metrics_files import read_metrics

    make_collector = trainer.make_collector

    class FailingSecondRollout:
        def __init__(self, collector):
            self._collector = collector

        def __getattr__(self, name):
            return getattr(self._collector, name)

        def __iter__(self):
            for k, batch in enumerate(self._collector):
                if k == 1:
                    raise RuntimeError("the env broke in the second rollout")
                yield batch

    monkeypatch.setattr(trainer, "make_collector", lambda *a, **k: FailingSecondRollout(make_collector(*a, **k)))
    cfg = preset_config("cpu_smoke", device="cpu", run_dir=str(tmp_path), name="e", progress_bar=False,
                        eval_at_end=False, log_every=1, checkpoint_every=100, total_env_steps=4 * 8 * 16,
                        **{"ppo.overlap_update": overlap})
    with pytest.raises(RuntimeError, match="second rollout"):
        trainer.train(cfg)
    rows = read_metrics(tmp_path / "e")
    assert [int(r["iteration"]) for r in rows] == [1] and float(rows[0]["kl"]) == float(rows[0]["kl"])
