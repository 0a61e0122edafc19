"""The left-right equivariant actor (``ppo.symmetry="equivariant"``, rl/symmetry.py ``EquivariantMean``): symmetric
for any weights and normaliser statistics, built by ``build_agent``, kept through training, checkpoints and the
ONNX export."""

from __future__ import annotations

import pytest
import torch

from tocabi_torchrl.config import preset_config
from tocabi_torchrl.rl.actors import gaussian_head
from tocabi_torchrl.rl.networks import make_mlp
from tocabi_torchrl.rl.symmetry import (
    ACTION_DIM,
    EquivariantMean,
    PolicyInputMirror,
    SignedPermutation,
    action_mirror_map,
    find_normalization,
    normalization_statistics,
)

CPU = torch.device("cpu")


def _mean(seed: int = 0, clip: float | None = None) -> EquivariantMean:
    torch.manual_seed(seed)
    mean = EquivariantMean(make_mlp(237, (32, 16), ACTION_DIM, "elu"), PolicyInputMirror(),
                           SignedPermutation(*action_mirror_map()))
    d = mean.obs_mirror.obs_dim
    mean.set_statistics(torch.randn(d) * 0.3, torch.rand(d) + 0.5, clip)
    return mean


def test_the_mean_action_of_a_mirrored_input_is_the_mirrored_mean_action():
    """μ(M·o) = A·μ(o) for random weights and asymmetric statistics (an untrained MLP is far from symmetric: the
    wrapped network alone misses it by orders of magnitude more)."""
    mean = _mean()
    o = torch.randn(64, 237)
    with torch.no_grad():
        gap = (mean(mean.obs_mirror(o)) - mean.action_mirror(mean(o))).abs().max()
        raw = (mean.net(mean.obs_mirror(o)) - mean.action_mirror(mean.net(o))).abs().max()
    assert gap < 1e-5 and raw > 1e-2
    # Any batch shape the network takes: one frame, and (T, N) frames of a rollout.
    with torch.no_grad():
        assert mean(o[:1]).shape == (1, ACTION_DIM) and mean(o.reshape(4, 16, 237)).shape == (4, 16, ACTION_DIM)


def test_the_clip_is_applied_again_after_the_mirror_and_kept_as_a_buffer():
    """Inside the normaliser's clip the mirror is exact; the clip is a buffer, so a checkpoint keeps it."""
    mean = _mean(clip=5.0)
    assert float(mean.clip) == 5.0 and "clip" in dict(mean.named_buffers())
    o = torch.randn(8, 237).clamp(-1.0, 1.0)
    with torch.no_grad():
        mirrored = mean.obs_mirror(o)
        assert mirrored.abs().max() < 5.0  # o and M·o inside the clip: the mirror is exact there
        entries = mean.obs_mirror.obs_entries
        assert entries < 237 and mirrored[:, :entries].abs().max() > 0  # observation entries, the actions after them
        torch.testing.assert_close(mean(mirrored), mean.action_mirror(mean(o)), atol=1e-5, rtol=0)
    mean.set_statistics(None, None, None)  # raw observations, no clip
    assert float(mean.clip) == torch.finfo(torch.float32).max
    assert torch.equal(mean.obs_mirror.gain, mean.obs_mirror.sign)


def test_every_buffer_lives_on_the_networks_device():
    """Built around a network on another device (here "meta", which needs no GPU), the wrapper's buffers go there
    too: a CPU buffer beside CUDA weights would fail the first CUDA update."""
    from types import SimpleNamespace

    from tocabi_torchrl.rl.symmetry import make_equivariant_mean
    from tocabi_torchrl.transforms.layouts import REFERENCE_HISTORY, REFERENCE_OBS_LAYOUT

    layout = SimpleNamespace(history=REFERENCE_HISTORY, obs_layout=REFERENCE_OBS_LAYOUT, phase_harmonics=1)
    mean = make_equivariant_mean(make_mlp(237, (8,), ACTION_DIM).to("meta"), layout, 237, ACTION_DIM)
    assert {t.device.type for t in (*mean.buffers(), *mean.parameters())} == {"meta"}


def test_the_agent_built_on_another_device_acts_there_with_its_teacher():
    """build_agent on the meta device (shapes only, no GPU needed): every parameter and buffer of the actor and the
    teacher is there, and both act on inputs there, as they must on CUDA."""
    from tensordict import TensorDict

    from tocabi_torchrl import robot
    from tocabi_torchrl.rl.trainer import build_agent

    meta = torch.device("meta")
    cfg = preset_config("robust", device="cpu", **{"ppo.symmetry": "equivariant", "env.num_envs": 4,
                                                   "ppo.minibatch_size": 48})
    agent = build_agent(cfg, 237, 13, meta)
    tensors = (*agent.actor.parameters(), *agent.actor.buffers(), *agent.teacher.buffers())
    assert {t.device.type for t in tensors} == {"meta"}
    out = agent.actor(TensorDict({"observation": torch.zeros(8, 237, device=meta)}, [8], device=meta))
    assert out["action"].shape == (8, 13) and out["action"].device == meta
    limits = torch.as_tensor(robot.LEG_TORQUE_LIMITS, dtype=torch.float32, device=meta)
    assert agent.teacher.torque(torch.zeros(8, 237, device=meta), torch.zeros(8, 12, device=meta), limits).shape == (
        8, 12)


def test_bad_inputs_are_refused_by_name():
    mean = _mean()
    with pytest.raises(ValueError, match="policy input of 237 values, got shape"):
        mean(torch.zeros(2, 36))
    with pytest.raises(ValueError, match="applies the normaliser's clip itself"):
        EquivariantMean(torch.nn.Linear(237, 13), PolicyInputMirror(clip=3.0), SignedPermutation(*action_mirror_map()))


def test_build_agent_wraps_the_mean_network_and_the_teacher_copies_it():
    from tocabi_torchrl.rl.trainer import build_agent

    cfg = preset_config("robust", device="cpu", **{"ppo.symmetry": "equivariant", "env.num_envs": 4,
                                                   "ppo.minibatch_size": 48})
    agent = build_agent(cfg, 237, 13, CPU)
    assert isinstance(gaussian_head(agent.actor).mean_net, EquivariantMean)
    assert isinstance(agent.teacher.mean_net, EquivariantMean)  # the frozen teacher is symmetric too
    with pytest.raises(ValueError, match="mirrors a policy input of 237 values"):
        build_agent(cfg, 200, 13, CPU)
    plain = build_agent(preset_config("robust", device="cpu", **{"env.num_envs": 4, "ppo.minibatch_size": 48}),
                        237, 13, CPU)
    assert not isinstance(gaussian_head(plain.actor).mean_net, EquivariantMean)


def test_an_equivariant_checkpoint_does_not_load_into_another_mode_and_says_why():
    from tocabi_torchrl.rl.checkpoint import CheckpointError, apply_checkpoint
    from tocabi_torchrl.rl.trainer import build_agent

    small = {"ppo.actor_hidden": (16,), "ppo.critic_hidden": (16,), "env.num_envs": 4, "ppo.minibatch_size": 64}
    equivariant = build_agent(preset_config("cpu_smoke", **small, **{"ppo.symmetry": "equivariant"}), 237, 13, CPU)
    plain = build_agent(preset_config("cpu_smoke", **small), 237, 13, CPU)
    with pytest.raises(CheckpointError, match="symmetry differ"):
        apply_checkpoint({"agent": equivariant.state_dict()}, plain)


def test_the_teacher_taken_from_an_equivariant_actor_keeps_its_mirror_and_symmetry():
    """The torque assist's teacher copies the actor's weights and buffers when the fade starts: the mirror's
    statistics come with them, so the teacher's leg torques mirror with the state."""
    from tocabi_torchrl import robot
    from tocabi_torchrl.rl.trainer import build_agent

    cfg = preset_config("robust", device="cpu", **{"ppo.symmetry": "equivariant", "env.num_envs": 4,
                                                   "ppo.minibatch_size": 48})
    agent = build_agent(cfg, 237, 13, CPU)
    actor_mean = gaussian_head(agent.actor).mean_net
    d = actor_mean.obs_mirror.obs_dim
    actor_mean.set_statistics(torch.randn(d) * 0.2, torch.rand(d) + 0.5, 5.0)
    limits = torch.as_tensor(robot.LEG_TORQUE_LIMITS, dtype=torch.float32)
    agent.teacher.anchor(actor_mean, limits, 0.5)
    teacher_mirror = agent.teacher.mean_net.obs_mirror
    assert torch.equal(teacher_mirror.offset, actor_mean.obs_mirror.offset) and float(agent.teacher.mean_net.clip) == 5
    o = torch.randn(8, 237) * 0.3  # o and M·o inside the clip: the mirror is exact there
    assert actor_mean.obs_mirror(o).abs().max() < 5.0
    assist = torch.randn(8, 12) * 0.1
    leg_perm, leg_sign = actor_mean.action_mirror.perm[:12], actor_mean.action_mirror.sign[:12]
    torque = agent.teacher.torque(o, assist, limits)
    mirrored = agent.teacher.torque(teacher_mirror(o), assist[:, leg_perm] * leg_sign, limits)
    torch.testing.assert_close(mirrored, torque[:, leg_perm] * leg_sign, atol=1e-4, rtol=1e-5)


@pytest.mark.parametrize("normalization", ["fixed", "running"])
def test_cpu_training_keeps_the_policy_symmetric_through_checkpoint_and_export(tmp_path, normalization):
    """A tiny CPU run: the trainer gives the mirror the env's normaliser statistics (a running normaliser's again
    before each update), the trained policy is symmetric under them, a checkpoint restores them, and the ONNX export
    computes the same actions at any batch size."""
    from tocabi_torchrl.rl.checkpoint import config_from_checkpoint, load_checkpoint, read_checkpoint
    from tocabi_torchrl.rl.trainer import build_agent, build_env, train

    cfg = preset_config("cpu_smoke", device="cpu", **{"ppo.symmetry": "equivariant", "env.num_envs": 4,
                                                      "ppo.steps_per_env": 8, "ppo.minibatch_size": 16,
                                                      "transforms.normalization": normalization},
                        total_env_steps=64, run_dir=str(tmp_path), name="eq", progress_bar=False, eval_at_end=False)
    result = train(cfg)
    assert result.iterations == 2
    path = tmp_path / "eq" / "checkpoints" / "iter_000002.pt"
    state = read_checkpoint(path)
    agent = build_agent(config_from_checkpoint(state, path), 237, 13, CPU)
    env = build_env(cfg, CPU, for_training=True)
    load_checkpoint(path, agent, env=env)
    mean = gaussian_head(agent.actor).mean_net
    # The statistics the last update ran with are the normaliser's as saved: no rollout came after that update.
    loc, scale = normalization_statistics(find_normalization(env))
    assert loc is not None
    expected = PolicyInputMirror(loc=loc, scale=scale)
    torch.testing.assert_close(mean.obs_mirror.offset, expected.offset)
    torch.testing.assert_close(mean.obs_mirror.gain, expected.gain)
    assert mean.obs_mirror.offset.abs().max() > 0  # not the identity it was built with
    o = torch.randn(16, 237)
    with torch.no_grad():
        action = mean(o)
        torch.testing.assert_close(mean(mean.obs_mirror(o)), mean.action_mirror(action), atol=1e-5, rtol=0)
    ort = pytest.importorskip("onnxruntime")
    from tocabi_torchrl.export.onnx_export import export_policy

    exported = export_policy(path, tmp_path / "eq.onnx")
    onnx_policy = ort.InferenceSession(str(exported.onnx))
    for n in (1, 5):
        out = onnx_policy.run(None, {"observation": o[:n].numpy()})[0]
        torch.testing.assert_close(torch.from_numpy(out), action[:n], atol=1e-5, rtol=0)
