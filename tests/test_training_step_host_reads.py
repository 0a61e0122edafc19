"""The per-step paths of a training iteration under the robust preset, and under the options a run adds to it, hold
no op that synchronises with the host on CUDA: the collector's step (the sync-free env step with its transforms, the
masked reset, through the emulated capture's replays, and the actor) and the PPO mini-batch step (loss, backward,
clipping). On CPU, with the dispatch-level stand-in for ``torch.cuda.set_sync_debug_mode("error")``
(``host_reads.HostSyncOps``); the GPU tests check the same at their own configurations.

What stays out of the check: the C MuJoCo backend (host code by design: the GPU runs mujoco-warp's recorded graphs)
and the optimiser's own step (on the CPU Adam counts its steps on the host; the captured update's Adam is the
capturable one, which keeps them on the device). Once per iteration, outside any capture, the trainer reads the
losses with the action std, and the episode metrics for its log: those are not per step. The last test checks
that a whole iteration reads only those on the host, and that docs/architecture.md lists each."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from graph_emulation import EmulatedCapture
from host_reads import HostSyncOps, HostValueReads
from torchrl.envs.utils import ExplorationType, set_exploration_type

from tocabi_torchrl.rl import preset_config
from tocabi_torchrl.rl.actors import gaussian_head
from tocabi_torchrl.rl.rollout_guard import guard_rollout
from tocabi_torchrl.rl.symmetry import SymmetryAugmentLoss
from tocabi_torchrl.rl.trainer import (_fill_proximal, _update_losses, _update_rows, build_agent, build_env,
                                       estimate_advantages, make_collector, make_loss, make_optimizer, make_update_step)
from tocabi_torchrl.rl.update_step import MinibatchStep

N, T = 4, 6
#: The robust preset at a tiny size, with the delay grid of runs 21-22; kicks at full strength from the first steps.
TINY = {"env.num_envs": N, "env.control.actuators.delay_stride": 2, "ppo.steps_per_env": T, "ppo.minibatch_size": 8,
        "ppo.epochs": 2, "ppo.actor_hidden": (16, 16), "ppo.critic_hidden": (16, 16), "ppo.push_ramp": (0, 1),
        "env.pushes.window": (0.004, 0.02), "env.task.max_episode_steps": 6}
OPTIONS = {
    "robust": {},
    "equivariant": {"ppo.symmetry": "equivariant"},
    "kick_relax-averaged_delay-running": {"transforms.kick_relax.seconds": 0.012,
                                          "env.control.actuators.delay_average": True,
                                          "transforms.normalization": "running"},
    # The adaptive rate set inside the captured step (rl/update_step.MinibatchKLRule).
    "kl_adapt_every_minibatch": {"ppo.kl_adapt_every": "minibatch"},
    # The decoupled update (the proximal log-probabilities filled before it), inside the symmetry's and the assist's
    # losses.
    "overlap_update": {"ppo.overlap_update": True},
}


def _update_inputs(agent, base, loss_module, advantage, batch):
    """The flat mini-batch source of the update between two rollouts, as the trainer makes it, with the teacher
    pulling at the fade's next step."""
    agent.teacher.anchor(gaussian_head(agent.actor).mean_net, base.assist_gain(0.5), 0.5)
    loss_module.set_step(base.assist_gain(0.5), base.assist_gain(0.4), 0.5, 0.4, 1.0)
    work = batch.clone(False)
    guard_rollout(work)
    estimate_advantages(advantage, work)
    return _update_rows(loss_module, work)


@pytest.mark.parametrize("option", list(OPTIONS))
def test_the_robust_training_step_reads_nothing_on_the_host(option):
    cfg = preset_config("robust", **TINY, **OPTIONS[option], device="cpu")
    device = torch.device("cpu")
    torch.manual_seed(0)
    probe = HostSyncOps()
    env = build_env(cfg, device, for_training=True, sync_free_resets=True)
    env.set_cuda_graph(True, capturer=EmulatedCapture())
    base = env.base_env
    for name in ("step", "reset", "forward"):  # the CPU physics backend: host code by design
        setattr(base.sim, name, probe.exempt(getattr(base.sim, name)))
    base.set_torque_assist(0.5)  # mid-fade: the assist's PD and the policy's torques both act
    base.set_push_scale(1.0)
    agent = build_agent(cfg, env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1], device)
    loss_module, advantage = make_loss(cfg, agent, env)
    optimizer = make_optimizer(cfg, agent, device)
    optimizer.step = probe.exempt(optimizer.step)
    params = [p for g in optimizer.param_groups for p in g["params"]]
    kl_rule = make_update_step(cfg, loss_module, optimizer, device).kl_rule  # the trainer's, if the option sets one
    step = MinibatchStep(loss_module, optimizer, params, cfg.ppo.max_grad_norm, use_graph=True,
                         capturer=EmulatedCapture(), kl_rule=kl_rule)
    assert (step.kl_rule is not None) == (option == "kl_adapt_every_minibatch")
    collector = make_collector(cfg, env, agent.actor, device, total_frames=3 * N * T)
    try:
        rollouts = iter(collector)
        batch = next(rollouts)  # the warm-up and the capture of the env step
        assert env.graph_captured
        with probe:
            batch = next(rollouts)  # replays only
        assert batch["next", "done"].any(), "the masked reset must have reset some worlds"
    finally:
        collector.shutdown()
    flat = _update_inputs(agent, base, loss_module, advantage, batch)
    if cfg.ppo.overlap_update:
        with probe:
            _fill_proximal(loss_module, flat)
    _update_losses(cfg, flat, step)  # three eager warm-up steps, the capture and a replay
    assert step.captured and "loss_absorb" in step.stat_keys
    augmented = any(isinstance(m, SymmetryAugmentLoss) for m in loss_module.modules())
    assert augmented == (cfg.ppo.symmetry == "augment")
    with probe:
        for k in range(2):
            step(flat[k * 8:(k + 1) * 8])
    assert probe.hits == [], sorted(set(probe.hits))


#: Where a training iteration reads values on the host, once per iteration (docs/architecture.md, "What the host reads
#: while training", lists them): the frame names :class:`host_reads.HostValueReads` records.
ITERATION_READS = {"values": "`rl.deferred_read.DeferredRead.values`"}


@pytest.mark.parametrize("overlap", [False, True], ids=["update_inline", "overlap_update"])
def test_a_training_iteration_reads_on_the_host_only_what_the_architecture_page_lists(tmp_path, monkeypatch, overlap):
    """Per iteration: the update's losses (with the action std and, on the device rule, the learning rate) and the
    logged episode metrics, both through :class:`DeferredRead`, which on CUDA waits for its own copy, not for the
    rollout queued since; TorchRL's GAE read whether a next observation held NaN (rl/gae.py: no longer)."""
    import tocabi_torchrl.rl.trainer as trainer

    iterations = 2
    cfg = preset_config("default", device="cpu", run_dir=str(tmp_path), progress_bar=False, eval_at_end=False,
                        **{"env.num_envs": N, "ppo.steps_per_env": T, "ppo.minibatch_size": 8, "ppo.epochs": 2,
                           "ppo.actor_hidden": (16, 16), "ppo.critic_hidden": (16, 16), "ppo.critic_privileged": True,
                           "total_env_steps": iterations * N * T, "ppo.overlap_update": overlap})
    probe = HostValueReads()
    env = build_env(cfg, torch.device("cpu"), for_training=True, sync_free_resets=True)  # the GPU's env step
    for name in ("step", "reset", "forward"):  # the CPU physics backend: host code by design
        setattr(env.base_env.sim, name, probe.exempt(getattr(env.base_env.sim, name)))
    make_optimizer = trainer.make_optimizer

    def optimizer_with_exempt_step(*args, **kwargs):  # on the CPU Adam counts its steps on the host
        optimizer = make_optimizer(*args, **kwargs)
        optimizer.step = probe.exempt(optimizer.step)
        return optimizer

    monkeypatch.setattr(trainer, "make_optimizer", optimizer_with_exempt_step)
    monkeypatch.setattr(trainer, "save_checkpoint", probe.exempt(trainer.save_checkpoint))  # its iterations only
    estimate = trainer.estimate_advantages

    def from_the_first_advantages(*args, **kwargs):  # the run's start-up reads are before it; rollouts 2.. after it
        probe.recording = True
        return estimate(*args, **kwargs)

    monkeypatch.setattr(trainer, "estimate_advantages", from_the_first_advantages)
    probe.recording = False
    with probe:
        result = trainer.train(cfg, env)
    assert result.iterations == iterations
    # The update's losses and the episode metrics (each iteration logs), both deferred, with or without the overlap.
    assert probe.sites == {"values": 2 * iterations}
    page = (Path(__file__).resolve().parents[1] / "docs" / "architecture.md").read_text()
    assert "## What the host reads while training" in page, "docs/architecture.md lost its section on host reads"
    section = page.split("## What the host reads while training", 1)[1].split("\n## ", 1)[0]
    assert all(name in section for name in ITERATION_READS.values())


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("option", list(OPTIONS))
def test_the_robust_training_step_never_syncs_on_cuda(option):
    """The CUDA twin of the CPU check above, under ``torch.cuda.set_sync_debug_mode("error")``: the captured env step
    with its masked resets and the actor (the collector's inner step, called directly so that a synchronisation of
    the collector's own bookkeeping is not counted), then replays of the captured PPO mini-batch step."""
    n = 64
    cfg = preset_config("robust", **{**TINY, "env.num_envs": n, "ppo.minibatch_size": 96}, **OPTIONS[option],
                        device="cuda")
    device = torch.device("cuda")
    torch.manual_seed(0)
    env = build_env(cfg, device, for_training=True, sync_free_resets=True)
    env.set_cuda_graph(True)
    base = env.base_env
    base.set_torque_assist(0.5)
    base.set_push_scale(1.0)
    agent = build_agent(cfg, env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1], device)
    loss_module, advantage = make_loss(cfg, agent, env)
    optimizer = make_optimizer(cfg, agent, device)
    params = [p for g in optimizer.param_groups for p in g["params"]]
    step = MinibatchStep(loss_module, optimizer, params, cfg.ppo.max_grad_norm, use_graph=True,
                         kl_rule=make_update_step(cfg, loss_module, optimizer, device).kl_rule)
    collector = make_collector(cfg, env, agent.actor, device, total_frames=2 * n * T)
    try:
        batch = next(iter(collector))  # the warm-up and the capture of the env step
    finally:
        collector.shutdown(close_env=False)
    assert env.graph_captured
    td = env.reset()
    steps = []
    # The collector's policy samples (Normal sample and log-prob): the same exploration mode here.
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        for _ in range(3):  # eager warm-up of the actor's first calls outside the check
            out, td = env.step_and_maybe_reset(agent.actor(td))
        torch.cuda.synchronize()
        torch.cuda.set_sync_debug_mode("error")
        try:
            for _ in range(2 * T):  # crosses the 6-step episodes: every world resets inside the captured step
                out, td = env.step_and_maybe_reset(agent.actor(td))
                steps.append(out["next", "done"])
        finally:
            torch.cuda.set_sync_debug_mode(0)
    assert bool(torch.stack(steps).any())
    flat = _update_inputs(agent, base, loss_module, advantage, batch)
    if cfg.ppo.overlap_update:
        _fill_proximal(loss_module, flat)  # its first call allocates; the checked one below must not sync
        torch.cuda.synchronize()
        torch.cuda.set_sync_debug_mode("error")
        try:
            _fill_proximal(loss_module, flat)
        finally:
            torch.cuda.set_sync_debug_mode(0)
    _update_losses(cfg, flat, step)  # eager warm-up steps, the capture and replays
    assert step.captured
    mbs = [flat[k * 96:(k + 1) * 96] for k in range(2)]
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for mb in mbs:
            step(mb)
    finally:
        torch.cuda.set_sync_debug_mode(0)
