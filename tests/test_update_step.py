"""The PPO mini-batch step: eager, the static-buffer replay wiring (emulated on CPU), and on a GPU the captured CUDA
graph against the eager step, without host synchronisation."""

from __future__ import annotations

import pytest
import torch
from graph_emulation import EmulatedCapture
from tensordict import TensorDict

from tocabi_torchrl.rl import preset_config
from tocabi_torchrl.rl.rollout_guard import VALID_KEY
from tocabi_torchrl.rl.trainer import NORM_MASK_KEY, _update, build_agent, make_loss, make_optimizer, make_update_step
from tocabi_torchrl.rl.update_step import MinibatchStep, get_lr, optimizer_mode, restore_optimizer_mode, set_lr

OBS, ACT = 17, 5


def _setup(device: str, update_graph: bool, seed: int = 0):
    cfg = preset_config("default", **{"env.num_envs": 64, "ppo.steps_per_env": 8, "ppo.minibatch_size": 128,
                                      "ppo.epochs": 2, "ppo.actor_hidden": (32, 16), "ppo.critic_hidden": (32, 16),
                                      "ppo.update_graph": update_graph}, device=device)
    torch.manual_seed(seed)
    agent = build_agent(cfg, OBS, ACT, torch.device(device))
    loss_module, _ = make_loss(cfg, agent)
    optimizer = make_optimizer(cfg, agent, torch.device(device))
    return cfg, agent, make_update_step(cfg, loss_module, optimizer, torch.device(device))


def _rollout(n: int, device: str, masked: bool = False) -> TensorDict:
    """A flat rollout; ``masked`` adds the rollout guard's masks (about 10% of frames invalid) under both keys the
    trainer's mini-batches carry: the loss mask and the advantage normalisation mask."""
    g = torch.Generator().manual_seed(1)
    td = TensorDict({
        "observation": torch.randn(n, OBS, generator=g),
        "action": torch.randn(n, ACT, generator=g),
        "action_log_prob": -torch.rand(n, generator=g) * 5,
        "advantage": torch.randn(n, 1, generator=g),
        "value_target": torch.randn(n, 1, generator=g),
        "state_value": torch.randn(n, 1, generator=g),
    }, batch_size=[n])
    if masked:  # drawn after the rest, so the unmasked values are the same
        valid = torch.rand(n, 1, generator=g) >= 0.1
        td.set(VALID_KEY, valid)
        td.set(NORM_MASK_KEY, valid.clone())
    return td.to(device)


def _params(agent) -> torch.Tensor:
    return torch.cat([p.detach().flatten() for p in list(agent.actor.parameters()) + list(agent.critic.parameters())])


@pytest.mark.parametrize("masked", [False, True], ids=["unmasked", "masked"])
def test_emulated_replay_wiring_matches_the_eager_step(masked):
    """Static buffers refilled in place give the same parameters as fresh mini-batches, step for step; the masked
    variant carries the rollout guard's masks, as the trainer's mini-batches do."""
    cfg, eager_agent, eager = _setup("cpu", update_graph=False)
    _, emu_agent, plain = _setup("cpu", update_graph=False)
    emu = MinibatchStep(plain.loss_module, plain.optimizer, plain.params, plain.max_grad_norm, use_graph=True,
                        capturer=EmulatedCapture())
    flat = _rollout(512, "cpu", masked=masked)
    torch.manual_seed(3)
    stats_eager = _update(cfg, flat, eager)
    torch.manual_seed(3)
    stats_emu = _update(cfg, flat, emu)
    assert emu.captured and emu._capture.capturer.captures == ["joined"]
    assert stats_eager == pytest.approx(stats_emu, rel=1e-6)
    torch.testing.assert_close(_params(eager_agent), _params(emu_agent), rtol=0, atol=0)
    assert not torch.equal(_params(eager_agent), _params(_setup("cpu", update_graph=False)[1])), "nothing trained"


def _emulated(setup):
    _, agent, plain = setup
    return agent, MinibatchStep(plain.loss_module, plain.optimizer, plain.params, plain.max_grad_norm, use_graph=True,
                                capturer=EmulatedCapture())


@pytest.mark.parametrize("masked", [False, True], ids=["unmasked", "masked"])
def test_kept_rows_step_as_fresh_mini_batches_do_and_refill_in_place(masked):
    """keep() + on_rows(idx) (the gather inside the replay) trains exactly as step(flat[idx]): over two rollouts, the
    second copied into the same buffer, which the replays then read."""
    cfg, eager_agent, eager = _setup("cpu", update_graph=False)
    emu_agent, emu = _emulated(_setup("cpu", update_graph=False))
    first, second = _rollout(512, "cpu", masked=masked), _rollout(512, "cpu", masked=masked).apply(lambda x: x.flip(0))
    for it, flat in enumerate((first, second)):
        rows = emu.keep(flat)
        assert rows is emu.rows and not any(rows.get(k) is flat.get(k) for k in flat.keys(True, True))  # a copy
        ptrs = [rows.get(k).data_ptr() for k in sorted(rows.keys(True, True), key=str)]
        if it:  # a captured graph reads the buffer by address: the same layout is copied into the same memory
            assert rows is kept and ptrs == kept_ptrs
        kept, kept_ptrs = rows, ptrs
        torch.manual_seed(3 + it)
        stats_eager = _update(cfg, flat, eager)
        torch.manual_seed(3 + it)
        stats_emu = _update(cfg, rows, emu)
        assert stats_eager == pytest.approx(stats_emu, rel=1e-6)
        torch.testing.assert_close(_params(eager_agent), _params(emu_agent), rtol=0, atol=0)
    # Only the rows path ran and was captured once: 8 steps, 3 of them the warm-up.
    assert emu._rows_capture.captured and emu._rows_capture.capturer.captures == ["joined"]
    assert not emu._capture.captured


def test_kept_rows_of_another_layout_get_a_new_buffer_and_capture():
    _, _, step = _setup("cpu", update_graph=False)
    _, emu = _emulated(_setup("cpu", update_graph=False))
    idx = torch.arange(128)
    rows = emu.keep(_rollout(512, "cpu"))
    for _ in range(4):  # warm-up and capture
        emu.on_rows(idx)
    assert emu._rows_capture.captured
    double = _rollout(1024, "cpu", masked=True).apply(lambda x: x.double() if x.is_floating_point() else x)
    for other in (_rollout(1024, "cpu"), _rollout(1024, "cpu", masked=True), double):  # rows, keys, dtype
        new = emu.keep(other)
        assert new is not rows and not emu._rows_capture.captured, "a capture of the old buffer would read freed memory"
        torch.testing.assert_close(new.to_dict(), other.to_dict(), rtol=0, atol=0)
        rows = new
        if other is not double:  # (float32 networks)
            for _ in range(4):  # captured again, on the new buffer
                emu.on_rows(idx)
            assert emu._rows_capture.captured
    with pytest.raises(RuntimeError, match=r"on_rows\(\) before keep\(\)"):
        step.on_rows(idx)


def test_a_loss_that_changes_its_operations_recaptures_the_rows_step():
    """A loss whose graph_key changes (the assist's absorb term switching) runs other operations: the rows step warms
    up and captures again, as the mini-batch step does."""
    _, _, plain = _setup("cpu", update_graph=False)
    step = MinibatchStep(plain.loss_module, plain.optimizer, plain.params, plain.max_grad_norm, use_graph=True,
                         capturer=EmulatedCapture())
    step.keep(_rollout(512, "cpu"))
    idx = torch.arange(128)
    for _ in range(4):
        assert not step.replays()  # warm-up and capture: not to be queued from another thread
        step.on_rows(idx)
    assert step._rows_capture.captured and step.replays() and not step.replays(rows=False)
    plain.loss_module.graph_key = "another"  # what AssistAbsorbLoss.graph_key reports after a switch
    try:
        assert not step.replays()  # the next call warms up again
        step.on_rows(idx)
        assert not step._rows_capture.captured
        for _ in range(3):
            step.on_rows(idx)
        assert step._rows_capture.captured and step._rows_capture.capturer.captures == ["joined", "joined"]
    finally:
        del plain.loss_module.graph_key


def test_a_replayed_rows_step_queues_one_copy_per_mini_batch():
    """What the host launches per captured mini-batch on rows it keeps: the index copy, then the replay; no gather
    or copy per rollout key (which kept an overlapped update's host launching for as long as the update ran)."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class Count(TorchDispatchMode):
        def __init__(self):
            super().__init__()
            self.ops = []

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            self.ops.append(str(func.overloadpacket.__name__))
            return func(*args, **(kwargs or {}))

    class Replays(EmulatedCapture):  # a replay that launches nothing, counted
        def capture(self, fn, **kwargs):
            replay, result = super().capture(fn, **kwargs)
            self.replays = 0

            def counted():
                self.replays += 1

            return counted, result

    _, _, plain = _setup("cpu", update_graph=False)
    step = MinibatchStep(plain.loss_module, plain.optimizer, plain.params, plain.max_grad_norm, use_graph=True,
                         capturer=Replays())
    step.keep(_rollout(512, "cpu", masked=True))
    idx = torch.randperm(512)[:128]
    for _ in range(4):
        step.on_rows(idx)
    other, capturer = idx.flip(0), step._rows_capture.capturer
    capturer.replays = 0  # the capturing call replayed once
    with Count() as count:
        step.on_rows(idx)
        step.on_rows(other)
    assert count.ops == ["copy_", "copy_"] and capturer.replays == 2


def test_a_mini_batch_built_without_a_device_is_captured_on_its_tensors_device():
    """A TensorDict built without ``device=`` reports None; the step captures on its tensors' device all the same
    (it used to run eagerly for good, silently)."""

    class DeviceCapture(EmulatedCapture):  # captures where the real one would: on one device type only
        def supports(self, device) -> bool:
            return device is not None and device.type == "cpu"

    _, _, plain = _setup("cpu", update_graph=False)
    step = MinibatchStep(plain.loss_module, plain.optimizer, plain.params, plain.max_grad_norm, use_graph=True,
                         capturer=DeviceCapture())
    flat = _rollout(512, "cpu")
    mb = TensorDict(flat[:128].to_dict(), batch_size=[128])
    assert mb.device is None
    for _ in range(4):
        step(mb)
    assert step.captured and step._capture.capturer.captures == ["joined"]
    rows = TensorDict(flat.to_dict(), batch_size=[512])
    assert step.keep(rows).device is None
    for _ in range(4):
        step.on_rows(torch.arange(128))
    assert step._rows_capture.captured
    with pytest.raises(ValueError, match="the captured step takes 128 rows, got 64"):
        step.on_rows(torch.arange(64))
    with pytest.raises(ValueError, match="1-D int64"):
        step.on_rows(torch.arange(128, dtype=torch.int32))


def test_the_masks_reach_the_loss():
    """The same rollout with some frames marked invalid updates differently: the masks are read, not dropped."""
    results = []
    for masked in (False, True):
        cfg, agent, step = _setup("cpu", update_graph=False)
        flat = _rollout(512, "cpu", masked=masked)
        assert (VALID_KEY in flat) == masked and (NORM_MASK_KEY in flat) == masked
        torch.manual_seed(3)
        results.append((_update(cfg, flat, step), _params(agent)))
    (stats_plain, params_plain), (stats_masked, params_masked) = results
    valid = _rollout(512, "cpu", masked=True).get(VALID_KEY)
    assert valid.dtype == torch.bool and valid.shape == (512, 1) and 0.8 < valid.float().mean().item() < 0.97
    assert stats_plain.keys() == stats_masked.keys()
    assert any(stats_plain[k] != pytest.approx(stats_masked[k], rel=1e-6) for k in stats_plain)
    assert not torch.equal(params_plain, params_masked)


def test_update_graph_is_only_used_on_cuda():
    _, _, step = _setup("cpu", update_graph=True)
    assert not step.use_graph and not step.captured and not step.replays()
    assert all(not isinstance(g["lr"], torch.Tensor) for g in step.optimizer.param_groups)


def test_learning_rate_helpers():
    w = torch.nn.Parameter(torch.zeros(3))
    opt = torch.optim.Adam([{"params": [w], "lr": 1e-3}])
    set_lr(opt.param_groups[0], 5e-4)
    assert opt.param_groups[0]["lr"] == 5e-4 and get_lr(opt.param_groups[0]) == pytest.approx(5e-4)
    tensor_opt = torch.optim.Adam([{"params": [w], "lr": torch.tensor(1e-3)}])
    lr = tensor_opt.param_groups[0]["lr"]
    set_lr(tensor_opt.param_groups[0], 2e-4)
    assert tensor_opt.param_groups[0]["lr"] is lr, "a captured step reads this tensor: it must not be rebound"
    assert lr.item() == pytest.approx(2e-4) and get_lr(tensor_opt.param_groups[0]) == pytest.approx(2e-4)


def _stepped_adam(**groups_kw) -> torch.optim.Adam:
    w = torch.nn.Parameter(torch.ones(3))
    opt = torch.optim.Adam([{"params": [w], **groups_kw}])
    w.grad = torch.ones(3)
    opt.step()
    return opt


def test_resume_across_update_modes_keeps_this_runs_mode():
    """load_state_dict restores the saved groups' settings; a checkpoint of a captured GPU run (tensor lr,
    capturable) must still resume eagerly on the CPU, and an eager checkpoint into a tensor-lr optimiser."""
    captured_like = _stepped_adam(lr=1e-3).state_dict()
    for g in captured_like["param_groups"]:
        g.update(capturable=True, lr=torch.tensor(3e-4))
    eager = _stepped_adam(lr=1e-3)
    mode = optimizer_mode(eager)
    eager.load_state_dict(captured_like)
    with pytest.raises(AssertionError, match="capturable=True"):  # what a resume did without restoring the mode
        eager.step()
    restore_optimizer_mode(eager, mode)
    group = eager.param_groups[0]
    assert not group["capturable"] and group["lr"] == pytest.approx(3e-4) and not isinstance(group["lr"], torch.Tensor)
    eager.step()

    tensor_lr = _stepped_adam(lr=torch.tensor(1e-3))
    mode = optimizer_mode(tensor_lr)
    tensor_lr.load_state_dict(_stepped_adam(lr=5e-4).state_dict())
    restore_optimizer_mode(tensor_lr, mode)
    lr = tensor_lr.param_groups[0]["lr"]
    assert isinstance(lr, torch.Tensor) and lr.item() == pytest.approx(5e-4)
    tensor_lr.step()


def test_bad_warmup_is_refused():
    with pytest.raises(ValueError, match="warmup"):
        MinibatchStep(None, None, [], 1.0, warmup=0)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("masked", [False, True], ids=["unmasked", "masked"])
def test_captured_update_matches_eager_without_syncs(masked):
    """The CUDA-graph step computes what the eager step computes (capturable Adam keeps its bias corrections in
    float32 on the device, so equal to float32 rounding), and replays without a host synchronisation; the masked
    variant carries the rollout guard's masks, as the trainer's mini-batches do."""
    cfg, eager_agent, eager = _setup("cuda", update_graph=False)
    _, graph_agent, graphed = _setup("cuda", update_graph=True)
    assert graphed.use_graph and isinstance(graphed.optimizer.param_groups[0]["lr"], torch.Tensor)
    flat = _rollout(512, "cuda", masked=masked)
    for it in range(2):  # 16 steps: 3 eager warm-up steps, the capture, then replays
        torch.manual_seed(10 + it)
        stats_eager = _update(cfg, flat, eager)
        torch.manual_seed(10 + it)
        stats_graph = _update(cfg, flat, graphed)
        assert stats_graph == pytest.approx(stats_eager, rel=1e-4, abs=1e-6)
    mb = flat[torch.randperm(flat.shape[0], device="cuda")[: cfg.ppo.minibatch_size]]
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        graphed(mb)  # a replay: copies the mini-batch in and launches one graph, no host synchronisation
    finally:
        torch.cuda.set_sync_debug_mode("default")
    eager(mb)
    assert graphed.captured
    torch.testing.assert_close(_params(graph_agent), _params(eager_agent), rtol=1e-4, atol=1e-5)
    for group in graphed.optimizer.param_groups:
        set_lr(group, 0.0)  # a captured step reads the learning rate from the device: lr 0 must freeze it
    before = _params(graph_agent).clone()
    graphed(flat[: cfg.ppo.minibatch_size])
    torch.testing.assert_close(_params(graph_agent), before, rtol=0, atol=0)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_captured_rows_update_matches_eager_without_syncs():
    """The graph that gathers its mini-batch from the kept rollout computes what the eager step computes on the
    gathered rows, reads a second rollout copied into the same buffer, and replays without a host synchronisation."""
    cfg, eager_agent, eager = _setup("cuda", update_graph=False)
    _, graph_agent, graphed = _setup("cuda", update_graph=True)
    for it in range(2):  # 16 steps: 3 eager warm-up steps, the capture, then replays; the second on new rows
        flat = _rollout(512, "cuda", masked=True)
        flat = flat.apply(lambda x: x.flip(0)) if it else flat
        rows = graphed.keep(flat)
        torch.manual_seed(10 + it)
        stats_eager = _update(cfg, flat, eager)
        torch.manual_seed(10 + it)
        stats_graph = _update(cfg, rows, graphed)
        assert stats_graph == pytest.approx(stats_eager, rel=1e-4, abs=1e-6)
    assert graphed._rows_capture.captured and not graphed._capture.captured
    idx = torch.randperm(flat.shape[0], device="cuda")[: cfg.ppo.minibatch_size]
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        graphed.on_rows(idx)  # copies the index in and launches one graph
    finally:
        torch.cuda.set_sync_debug_mode("default")
    eager(flat[idx])
    torch.testing.assert_close(_params(graph_agent), _params(eager_agent), rtol=1e-4, atol=1e-5)


def test_the_run_trains_at_its_matmul_precision_and_puts_the_setting_back(monkeypatch):
    """ppo.matmul_precision is torch's process-wide setting inside train() only; bad values are refused by name."""
    from tocabi_torchrl.rl import trainer

    seen = []
    monkeypatch.setattr(trainer, "_train", lambda *args: seen.append(torch.get_float32_matmul_precision()) or "done")
    before = torch.get_float32_matmul_precision()
    cfg = preset_config("cpu_smoke")
    cfg.ppo.matmul_precision = "high"
    assert trainer.train(cfg) == "done" and seen == ["high"]
    assert torch.get_float32_matmul_precision() == before
    monkeypatch.setattr(trainer, "_train", lambda *args: (_ for _ in ()).throw(RuntimeError("boom")))
    with pytest.raises(RuntimeError, match="boom"):
        trainer.train(cfg)
    assert torch.get_float32_matmul_precision() == before  # also after a failed run
    cfg.ppo.matmul_precision = "medium"
    with pytest.raises(ValueError, match="ppo.matmul_precision must be one of"):
        trainer.train(cfg)
