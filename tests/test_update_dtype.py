"""The PPO update's compute options: bfloat16 hidden layers (``ppo.update_dtype``) and the compiled loss
(``ppo.compile_loss``)."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torch import nn

from tocabi_torchrl.rl import preset_config
from tocabi_torchrl.rl.actors import gaussian_head, gaussian_log_prob
from tocabi_torchrl.rl.networks import OutputLinear, make_mlp
from tocabi_torchrl.rl.trainer import (
    PROXIMAL_KEY,
    _fill_proximal,
    _update,
    build_agent,
    decoupled_update,
    make_loss,
    make_optimizer,
    make_update_step,
)
from tocabi_torchrl.rl.update_step import update_autocast

OBS, ACT = 17, 5


def _setup(device: str = "cpu", **overrides):
    cfg = preset_config("default", **{"env.num_envs": 64, "ppo.steps_per_env": 8, "ppo.minibatch_size": 128,
                                      "ppo.epochs": 2, "ppo.actor_hidden": (32, 16), "ppo.critic_hidden": (32, 16),
                                      "ppo.update_graph": False, **overrides}, device=device)
    torch.manual_seed(0)
    agent = build_agent(cfg, OBS, ACT, torch.device(device))
    loss_module, _ = make_loss(cfg, agent)
    optimizer = make_optimizer(cfg, agent, torch.device(device))
    return cfg, agent, loss_module, make_update_step(cfg, loss_module, optimizer, torch.device(device))


def _rollout(n: int) -> TensorDict:
    g = torch.Generator().manual_seed(1)
    return TensorDict({
        "observation": torch.randn(n, OBS, generator=g),
        "action": torch.randn(n, ACT, generator=g) * 0.1,
        "action_log_prob": -torch.rand(n, generator=g) * 5,
        "advantage": torch.randn(n, 1, generator=g),
        "value_target": torch.randn(n, 1, generator=g),
        "state_value": torch.randn(n, 1, generator=g),
    }, batch_size=[n])


def _acted(agent, flat: TensorDict) -> TensorDict:
    """``flat`` as the agent's float32 rollout pass would have logged it: each action's log-probability under the
    agent, and the decoupled update's proximal entry (the behaviour's, until ``_fill_proximal`` overwrites it)."""
    with torch.no_grad():
        logp = gaussian_log_prob(gaussian_head(agent.actor), flat.get("observation"), flat.get("action"))
    flat.set("action_log_prob", logp.reshape(-1))
    flat.set(PROXIMAL_KEY, logp.reshape(-1).clone())
    return flat


def _params(agent) -> torch.Tensor:
    return torch.cat([p.detach().flatten() for p in list(agent.actor.parameters()) + list(agent.critic.parameters())])


def _linear_dtypes(agent) -> dict[str, set[torch.dtype]]:
    """Record the input and output dtypes every Linear of both networks sees, by kind (hidden or output)."""
    seen: dict[str, set[torch.dtype]] = {"hidden_out": set(), "output_in": set(), "output_out": set()}

    def output_hook(module, args, out) -> None:
        seen["output_in"].add(args[0].dtype)
        seen["output_out"].add(out.dtype)

    def hidden_hook(module, args, out) -> None:
        seen["hidden_out"].add(out.dtype)

    for net in (agent.actor, agent.critic):
        for module in net.modules():
            if isinstance(module, nn.Linear):
                module.register_forward_hook(output_hook if isinstance(module, OutputLinear) else hidden_hook)
    return seen


def test_a_bfloat16_update_runs_its_hidden_layers_in_bfloat16_and_keeps_float32_elsewhere():
    """With ppo.update_dtype bfloat16 the hidden layers compute in bfloat16 and the output layers in float32; the
    parameters and their gradients stay float32, the rollout's own pass stays float32, and one update moves the
    parameters as the float32 update does, up to bfloat16's rounding (not bit for bit)."""
    cfg, agent, loss_module, step = _setup(**{"ppo.update_dtype": "bfloat16"})
    _, ref_agent, _, ref_step = _setup()
    assert torch.equal(_params(agent), _params(ref_agent))
    before = _params(agent)
    flat = _acted(agent, _rollout(512))
    seen = _linear_dtypes(agent)
    torch.manual_seed(3)
    stats = _update(cfg, flat, step, proximal_loss=loss_module)
    torch.manual_seed(3)
    ref_stats = _update(cfg, flat, ref_step)
    assert seen == {"hidden_out": {torch.bfloat16}, "output_in": {torch.bfloat16}, "output_out": {torch.float32}}
    assert all(p.dtype == torch.float32 for p in agent.actor.parameters())
    assert all(p.grad is None or p.grad.dtype == torch.float32 for p in step.params)
    moved, ref_moved = _params(agent) - before, _params(ref_agent) - before
    assert not torch.equal(moved, ref_moved), "the bfloat16 update computed in float32"
    assert (moved - ref_moved).norm() < 0.05 * ref_moved.norm()
    assert stats["loss_value"] == pytest.approx(ref_stats["loss_value"], rel=0.02)
    # Outside the update (the rollout's pass) every layer computes in float32.
    for kind in seen.values():
        kind.clear()
    with torch.no_grad():
        agent.actor(TensorDict({"observation": torch.randn(4, OBS)}, batch_size=[4]))
    assert seen["hidden_out"] == {torch.float32} and seen["output_out"] == {torch.float32}


def test_a_bfloat16_update_is_decoupled_so_its_ratios_start_from_one():
    """The rollout acts in float32; bfloat16's rounding alone moves the log-probabilities, and PPO's ratio against the
    policy that acted would start away from 1 (past the 0.2 clip on 30-59 % of the shipped torque policy's frames).
    So a bfloat16 update is decoupled (decoupled_update), overlapped or not: its ratio and KL are taken against the
    learner as the update computes it, and start at exactly 1 and 0."""
    assert not decoupled_update(preset_config("default").ppo)
    cfg, agent, loss_module, step = _setup(**{"ppo.update_dtype": "bfloat16"})
    assert decoupled_update(cfg.ppo) and PROXIMAL_KEY in loss_module.in_keys
    coupled, _ = make_loss(preset_config("default", device="cpu"), agent)  # PPO's own ratio, as before
    assert PROXIMAL_KEY not in coupled.in_keys
    with torch.no_grad():
        # The actor's output layer scaled up to action means of ~0.7, as a trained policy's: its rounding then shows
        # (a quarter of the coupled loss's frames start clipped).
        gaussian_head(agent.actor).mean_net[-1].weight.mul_(100.0)
        flat = _acted(agent, _rollout(2048))
        _fill_proximal(loss_module, flat, step.autocast_dtype)
        with update_autocast(step.autocast_dtype, torch.device("cpu")):
            decoupled, plain = loss_module(flat), coupled(flat)
    assert decoupled["kl_approx"].item() == 0.0 and decoupled["clip_fraction"].item() == 0.0
    assert plain["kl_approx"].item() > 0.0 and plain["clip_fraction"].item() > 0.0


def test_the_proximal_log_probabilities_follow_the_update_dtype():
    """_fill_proximal computes the decoupled update's proximal log-probabilities in the update's dtype: equal to the
    same head's log-probabilities under that autocast, and not to the float32 ones."""
    _, agent, loss_module, step = _setup(**{"ppo.update_dtype": "bfloat16", "ppo.overlap_update": True})
    flat = _rollout(256)
    flat.set(PROXIMAL_KEY, flat.get("action_log_prob").clone())
    _fill_proximal(loss_module, flat, step.autocast_dtype)
    head = gaussian_head(agent.actor)
    obs, action = flat.get("observation"), flat.get("action")
    with torch.no_grad():
        float32 = gaussian_log_prob(head, obs, action)
        with update_autocast(torch.bfloat16, obs.device):
            bfloat16 = gaussian_log_prob(head, obs, action)
    torch.testing.assert_close(flat.get(PROXIMAL_KEY), bfloat16, rtol=0, atol=0)
    assert not torch.equal(bfloat16, float32)
    torch.testing.assert_close(bfloat16, float32, rtol=0, atol=0.5)


def test_the_output_layer_is_a_linear_with_the_same_state_dict():
    """make_mlp's output layer keeps nn.Linear's parameters and keys: networks saved before load into it."""
    net = make_mlp(6, (8, 4), 3)
    assert isinstance(net[-1], OutputLinear) and isinstance(net[-1], nn.Linear)
    plain = nn.Sequential(nn.Linear(6, 8), nn.ReLU(), nn.Linear(8, 4), nn.ReLU(), nn.Linear(4, 3))
    net.load_state_dict(plain.state_dict())
    x = torch.randn(5, 6)
    torch.testing.assert_close(net(x), plain(x), rtol=0, atol=0)


def test_bad_update_dtypes_are_refused_by_name(monkeypatch):
    with pytest.raises(ValueError, match="ppo.update_dtype must be one of"):
        preset_config("default", **{"ppo.update_dtype": "float16"}).validate()
    # A GPU without bfloat16 is named, with the fix, before anything is built on it.
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda: False)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device=None: "Tesla V100")
    cfg = preset_config("default", **{"ppo.update_dtype": "bfloat16"})
    with pytest.raises(ValueError, match="Tesla V100 does not support bfloat16.*set ppo.update_dtype=float32"):
        make_update_step(cfg, None, None, torch.device("cuda"))


def test_a_compiled_loss_trains_as_the_eager_one():
    """ppo.compile_loss puts the step's loss through torch.compile; its update matches the eager loss's (up to the
    fused kernels' float rounding)."""
    cfg, agent, _, step = _setup(**{"ppo.compile_loss": True, "ppo.epochs": 1})
    _, ref_agent, _, ref_step = _setup(**{"ppo.epochs": 1})
    assert isinstance(step.loss_module, torch._dynamo.eval_frame.OptimizedModule)
    flat = _rollout(256)
    torch.manual_seed(3)
    stats = _update(cfg, flat, step)
    torch.manual_seed(3)
    ref_stats = _update(cfg, flat, ref_step)
    torch.testing.assert_close(_params(agent), _params(ref_agent), rtol=1e-4, atol=1e-6)
    assert stats == pytest.approx(ref_stats, rel=1e-3, abs=1e-6)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("compile_loss", [False, True], ids=["eager_loss", "compiled_loss"])
def test_a_captured_bfloat16_update_matches_its_eager_steps_without_syncs(compile_loss):
    """On CUDA the bfloat16 update (its loss compiled or not) is captured as the float32 one is: the graph that
    gathers its mini-batch from the kept rollout computes what the eager bfloat16 step computes, and replays without
    a host synchronisation."""
    options = {"ppo.update_dtype": "bfloat16", "ppo.compile_loss": compile_loss}
    cfg, eager_agent, eager_loss, eager = _setup("cuda", **options)
    _, graph_agent, graph_loss, graphed = _setup("cuda", **options, **{"ppo.update_graph": True})
    flat = _acted(eager_agent, _rollout(512).to("cuda"))
    rows = graphed.keep(flat)
    for it in range(2):  # 8 steps: 3 eager warm-up steps, the capture, then replays
        torch.manual_seed(10 + it)
        stats_eager = _update(cfg, flat, eager, proximal_loss=eager_loss)
        torch.manual_seed(10 + it)
        stats_graph = _update(cfg, rows, graphed, proximal_loss=graph_loss)
        assert stats_graph == pytest.approx(stats_eager, rel=1e-3, abs=1e-5)
    assert graphed._rows_capture.captured
    idx = torch.randperm(flat.shape[0], device="cuda")[: cfg.ppo.minibatch_size]
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        graphed.on_rows(idx)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    eager(flat[idx])
    torch.testing.assert_close(_params(graph_agent), _params(eager_agent), rtol=1e-3, atol=1e-4)


def test_compile_loss_without_a_compiler_is_refused_before_the_run_starts(tmp_path, monkeypatch):
    # Without a C++ compiler torch.compile failed in the first mini-batch step, after the env was built and a
    # rollout collected, with inductor's own trace; the refusal now names the option and the fix up front.
    import shutil

    from tocabi_torchrl.rl import trainer

    monkeypatch.setenv("CXX", "no-such-c++")
    real_which = shutil.which
    monkeypatch.setattr(trainer.shutil, "which", lambda name: None if name == "no-such-c++" else real_which(name))
    cfg = preset_config("cpu_smoke", **{"ppo.compile_loss": True, "run_dir": str(tmp_path), "name": "r"},
                        device="cpu")
    with pytest.raises(ValueError, match=r"ppo.compile_loss on the CPU needs a C\+\+ compiler .*'no-such-c\+\+'.*"
                                         r"set ppo.compile_loss=false"):
        trainer.train(cfg)
    assert not (tmp_path / "r").exists()  # refused before the run folder was made
    with pytest.raises(ValueError, match="needs a C"):  # make_update_step refuses it for its own callers too
        _setup(**{"ppo.compile_loss": True})
    monkeypatch.setattr(trainer.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(ValueError, match="ppo.compile_loss needs Triton on a GPU.*pip install triton"):
        trainer.check_compile_toolchain(torch.device("cuda"))
    trainer.check_compile_toolchain(torch.device("meta"))  # nothing compiled for it, nothing to refuse


def test_the_rounding_analysis_finds_more_frames_past_the_clip_for_larger_action_means():
    # lab/analysis/bf16_rounding.py's measure, on a network whose output layer is scaled as in the test above: a larger
    # mean, more rounding, more frames a coupled update would start clipped; a smaller std, more too.
    from lab.analysis.bf16_rounding import rounding

    torch.manual_seed(0)
    net, obs = make_mlp(OBS, (64, 64), ACT, "elu"), torch.randn(4096, OBS)
    small = rounding(obs, net, [0.1, 0.05], 0.2, seed=0)
    with torch.no_grad():
        net[-1].weight.mul_(100.0)
    large = rounding(obs, net, [0.1, 0.05], 0.2, seed=0)
    assert small["frames"] == 4096 and small["action_dim"] == ACT
    assert 0 < small["mean_abs_diff"] < large["mean_abs_diff"]
    shares = [[s["share_past_clip"] for s in r["per_std"]] for r in (small, large)]
    assert shares[0][0] <= shares[1][0] < shares[1][1] and 0 < shares[1][1] <= 1, shares
    ess = [s["behaviour_ess"] for s in large["per_std"]]  # what the decoupled update's weights pay instead
    assert 0 < ess[1] < ess[0] < 1, ess
