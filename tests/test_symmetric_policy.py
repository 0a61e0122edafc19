"""ppo.symmetric_policy: a checkpoint's policy is the trained actor's mean made left-right symmetric in every loader
(gait tests, the robust test, play, export), exactly lab/analysis/symmetrize.py's copy, while training is unchanged."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from tocabi_torchrl.config import preset_config
from tocabi_torchrl.rl.actors import gaussian_head
from tocabi_torchrl.rl.symmetry import EquivariantMean

REPO = Path(__file__).resolve().parents[1]
ROBUST = REPO / "assets" / "policies" / "tocabi_walk_robust.pt"
needs_robust = pytest.mark.skipif(not ROBUST.is_file(), reason="the shipped robust policy is not present")


def _with_symmetric_policy(tmp_path: Path) -> Path:
    """The shipped robust policy with ppo.symmetric_policy switched on in its saved config."""
    state = torch.load(ROBUST, map_location="cpu", weights_only=True)
    state["config"]["ppo"]["symmetric_policy"] = True
    out = tmp_path / "robust_symmetric.pt"
    torch.save(state, out)
    return out


def _mean(actor, obs: torch.Tensor) -> torch.Tensor:
    return gaussian_head(actor).mean_net(obs)


@needs_robust
def test_every_loader_gives_the_symmetric_copy_that_symmetrize_writes(tmp_path):
    """The loaders' policy acts as lab/analysis/symmetrize.py's copy of the same checkpoint (the copy whose robust
    test is in docs/training/robust/symmetrized), and is symmetric: μ(M·o) = A·μ(o)."""
    from lab.analysis.symmetrize import symmetrize
    from tocabi_torchrl.evaluation import robust
    from tocabi_torchrl.evaluation.record import load_policy
    from tocabi_torchrl.export.onnx_export import load_policy as export_policy

    flagged = _with_symmetric_policy(tmp_path)
    copy = symmetrize(ROBUST, tmp_path / "copy.pt")
    cpu = torch.device("cpu")
    reference = load_policy(copy, 2, cpu, nominal=True).agent.actor
    obs = torch.randn(5, 237)
    want = _mean(reference, obs)
    loaded = {
        "load_policy": load_policy(flagged, 2, cpu, nominal=True).agent.actor,
        "checkpoint_case": robust.checkpoint_case(flagged, "nominal", "cpu", robust.RobustTestConfig(num_envs=2))[3]
        .actor,
        "export": export_policy(flagged).agent.actor,
    }
    for name, actor in loaded.items():
        mean = gaussian_head(actor).mean_net
        assert isinstance(mean, EquivariantMean), name
        torch.testing.assert_close(_mean(actor, obs), want, msg=name)
        torch.testing.assert_close(mean(mean.obs_mirror(obs)), mean.action_mirror(mean(obs)), atol=1e-5, rtol=1e-5)
    # Without the flag the same file's policy is the trained network itself.
    plain = gaussian_head(load_policy(ROBUST, 2, cpu, nominal=True).agent.actor).mean_net
    assert not isinstance(plain, EquivariantMean)


@needs_robust
def test_loading_again_into_a_symmetric_policy_takes_the_wrapper_off_for_the_weights(tmp_path):
    """A loader may load a checkpoint into the same agent again (evaluate_robust's prepare_env, once per env it is
    given): the wrapper comes off for the weights and back with that env's statistics (loading into the wrapped
    actor would fail on its keys), and the policy acts as after the first load; the robust test runs through it."""
    from tocabi_torchrl.evaluation.robust import RobustTestConfig, checkpoint_case, evaluate_robust_checkpoint
    from tocabi_torchrl.rl.checkpoint import read_checkpoint
    from tocabi_torchrl.rl.symmetry import apply_checkpoint_policy

    flagged = _with_symmetric_policy(tmp_path)
    state, cfg, env, agent = checkpoint_case(flagged, "nominal", "cpu", RobustTestConfig(num_envs=2))
    obs = torch.randn(4, 237)
    first = _mean(agent.actor, obs)
    apply_checkpoint_policy(state, agent, cfg, env, flagged)
    assert isinstance(gaussian_head(agent.actor).mean_net, EquivariantMean)
    assert isinstance(gaussian_head(agent.actor).mean_net.net, torch.nn.Sequential)  # not wrapped twice
    torch.testing.assert_close(_mean(agent.actor, obs), first)
    test = RobustTestConfig(num_envs=2, seconds=0.1, cases=("nominal", "robust_0.5"))
    report = evaluate_robust_checkpoint(read_checkpoint(flagged), flagged, tmp_path / "out", test=test, device="cpu",
                                        progress=False)
    assert set(report["cases"]) == {"nominal", "robust_0.5"}


def test_training_is_the_same_with_and_without_it(tmp_path):
    """The option changes what a checkpoint's policy is, not what the run computes: two CPU runs, one with it, end
    with the same weights bit for bit."""
    from tocabi_torchrl.rl.checkpoint import read_checkpoint
    from tocabi_torchrl.rl.trainer import train

    weights = {}
    for flag in (False, True):
        cfg = preset_config("cpu_smoke", device="cpu", **{"ppo.symmetry": "augment", "ppo.symmetric_policy": flag,
                                                          "env.num_envs": 4, "ppo.steps_per_env": 8,
                                                          "ppo.minibatch_size": 16},
                            total_env_steps=64, run_dir=str(tmp_path), name=f"run{int(flag)}", progress_bar=False,
                            eval_at_end=False)
        train(cfg)
        weights[flag] = read_checkpoint(tmp_path / f"run{int(flag)}")["agent"]["actor"]
    assert weights[True].keys() == weights[False].keys()
    for key in weights[False]:
        assert torch.equal(weights[True][key], weights[False][key]), key


def test_it_is_refused_beside_an_equivariant_actor_and_may_change_on_resume():
    from tocabi_torchrl.rl.resume import RESUME_SAFE

    with pytest.raises(ValueError, match="symmetric already: leave ppo.symmetric_policy false"):
        preset_config("cpu_smoke", **{"ppo.symmetry": "equivariant", "ppo.symmetric_policy": True})
    assert "ppo.symmetric_policy" in RESUME_SAFE  # it changes no computation of the run


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@needs_robust
def test_the_robust_test_runs_a_symmetric_policy_on_the_gpu(tmp_path):
    """On CUDA the robust test's batch env steps through a captured graph; the wrapped policy, its mirror buffers
    and the normaliser statistics must all live on the GPU, and the policy must act as on the CPU."""
    from tocabi_torchrl.evaluation.robust import RobustTestConfig, checkpoint_case, evaluate_robust_checkpoint
    from tocabi_torchrl.rl.checkpoint import read_checkpoint

    flagged = _with_symmetric_policy(tmp_path)
    test = RobustTestConfig(num_envs=8, seconds=0.2, cases=("nominal", "robust_1.0"))
    report = evaluate_robust_checkpoint(read_checkpoint(flagged), flagged, tmp_path / "out", test=test, device="cuda",
                                        progress=False)
    assert set(report["cases"]) == {"nominal", "robust_1.0"}
    obs = torch.randn(4, 237)
    cpu = checkpoint_case(flagged, "nominal", "cpu", RobustTestConfig(num_envs=2))[3].actor
    gpu = checkpoint_case(flagged, "nominal", "cuda", RobustTestConfig(num_envs=2))[3].actor
    assert all(b.device.type == "cuda" for b in gaussian_head(gpu).mean_net.buffers())
    torch.testing.assert_close(_mean(gpu, obs.cuda()).cpu(), _mean(cpu, obs), atol=1e-4, rtol=1e-4)
