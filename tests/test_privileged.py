"""The asymmetric critic (``ppo.critic_privileged``): the PrivilegedState transform, the critic that reads it, and a
training run that resumes with it. Its left-right mirror is checked against the physics in tests/test_symmetry.py."""

from __future__ import annotations

import pytest
import torch
from mock_env import MockTocabiWalk
from tensordict import TensorDict
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs

from tocabi_torchrl import robot
from tocabi_torchrl.config import preset_config
from tocabi_torchrl.rl.trainer import build_agent, build_env, train, training_keys
from tocabi_torchrl.transforms import default_transforms
from tocabi_torchrl.transforms.privileged import PRIVILEGED_DIM, PRIVILEGED_MIRROR, PrivilegedState


def test_the_privileged_vector_is_the_true_state_of_the_same_step():
    env = TransformedEnv(MockTocabiWalk(4), default_transforms("reference"))
    env.append_transform(PrivilegedState())
    check_env_specs(env)
    ro = env.rollout(3)
    for td in (ro, ro["next"]):  # the reset state (CallOnReset) and every step
        v = td["privileged"]
        assert v.shape == (4, 3, PRIVILEGED_DIM) and v.dtype == torch.float32
        torch.testing.assert_close(v[..., 0:3], td["base_lin_vel"])
        torch.testing.assert_close(v[..., 3:6], td["base_ang_vel"])
        torch.testing.assert_close(v[..., 6], td["base_pos"][..., 2])
        torch.testing.assert_close(v[..., 7:9], -td["foot_force"][..., 2] / (robot.NOMINAL_MASS * robot.GRAVITY))
        torch.testing.assert_close(v[..., 9:12], td["base_rpy"])
    # Its mirror is a signed permutation that undoes itself.
    perm, sign = (torch.tensor(x) for x in PRIVILEGED_MIRROR)
    x = torch.randn(5, PRIVILEGED_DIM)
    once = x[:, perm] * sign
    torch.testing.assert_close(once[:, perm] * sign, x)


def test_the_transform_names_what_the_env_lacks():
    env = TransformedEnv(MockTocabiWalk(2))  # no BaseEulerAngles: no base_rpy
    with pytest.raises(KeyError, match=r"PrivilegedState reads \['base_rpy'\].*append it after the default"):
        env.append_transform(PrivilegedState())
        env.observation_spec  # noqa: B018 - the spec is what checks


def test_the_critic_reads_the_policy_input_and_the_true_state():
    cfg = preset_config("cpu_smoke", device="cpu", **{"ppo.critic_privileged": True})
    agent = build_agent(cfg, 237, 13, torch.device("cpu"))
    assert agent.critic.in_keys == ["observation", "privileged"]
    assert agent.critic.module[0].in_features == 237 + PRIVILEGED_DIM
    td = TensorDict({"observation": torch.zeros(6, 237), "privileged": torch.zeros(6, PRIVILEGED_DIM)}, [6])
    assert agent.critic(td)["state_value"].shape == (6, 1)
    # The value head keeps its own learning rate (the reference's second optimizer) with the wider input too.
    from tocabi_torchrl.rl.trainer import _param_groups

    ref = preset_config("reference", device="cpu", **{"ppo.critic_privileged": True})
    groups = _param_groups(build_agent(ref, 237, 13, torch.device("cpu")), ref)
    assert [g["name"] for g in groups] == ["policy", "value_head"]
    # Off (the default): the critic reads the policy input only, as every shipped policy's does.
    plain = build_agent(preset_config("cpu_smoke", device="cpu"), 237, 13, torch.device("cpu"))
    assert plain.critic.in_keys == ["observation"] and plain.critic.module[0].in_features == 237


def test_a_run_with_the_privileged_critic_trains_mirrors_and_resumes(tmp_path):
    over = {"ppo.critic_privileged": True, "ppo.symmetry": "augment", "env.num_envs": 4, "ppo.steps_per_env": 8,
            "ppo.minibatch_size": 16}
    cfg = preset_config("cpu_smoke", device="cpu", **over, total_env_steps=64, run_dir=str(tmp_path), name="priv",
                        progress_bar=False, eval_at_end=False)
    env = build_env(cfg, torch.device("cpu"), for_training=True)
    assert "privileged" in training_keys(env)  # the rollout keeps it for GAE and the update
    first = train(cfg)
    assert first.iterations == 2 and torch.isfinite(torch.tensor(first.last_metrics["loss_value"]))
    resumed = train(preset_config("cpu_smoke", device="cpu", **over, total_env_steps=128, run_dir=str(tmp_path),
                                  name="priv2", progress_bar=False, eval_at_end=False,
                                  resume=str(tmp_path / "priv")))
    assert resumed.env_steps == 128
    # The resumed critic started from the saved one (same shapes: it loaded), and training moved it on.
    saved = torch.load(tmp_path / "priv" / "checkpoints" / "latest.pt", weights_only=True)["agent"]["critic"]
    now = resumed.agent.critic.state_dict()
    assert saved.keys() == now.keys() and any(not torch.equal(saved[k], now[k]) for k in saved)
