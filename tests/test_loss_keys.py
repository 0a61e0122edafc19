"""What the PPO update gathers per mini-batch (``trainer._loss_keys``): the loss's inputs, without what only its value
estimator reads once GAE has run, and the update computes exactly what it computed on every listed input."""

from __future__ import annotations

import copy
from types import SimpleNamespace

import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from tocabi_torchrl.rl import preset_config
from tocabi_torchrl.rl.rollout_guard import VALID_KEY, guard_rollout
from tocabi_torchrl.rl.trainer import (_loss_keys, _update, build_agent, estimate_advantages, make_loss,
                                       make_optimizer, make_update_step)
from tocabi_torchrl.transforms.privileged import PRIVILEGED_DIM

NEXT_INPUTS = {("next", k) for k in ("observation", "privileged", "reward", "done", "terminated", "truncated")}


def _rollout(agent, envs: int = 4, steps: int = 8, obs: int = 6, privileged: int = PRIVILEGED_DIM) -> TensorDict:
    g = torch.Generator().manual_seed(1)
    o, p = torch.randn(envs, steps + 1, obs, generator=g), torch.randn(envs, steps + 1, privileged, generator=g)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        td = agent.actor(TensorDict({"observation": o[:, :-1].clone(), "privileged": p[:, :-1].clone()},
                                    batch_size=[envs, steps]))
    done = torch.rand(envs, steps, 1, generator=g) < 0.1
    td["next"] = TensorDict({"observation": o[:, 1:].clone(), "privileged": p[:, 1:].clone(),
                             "reward": torch.randn(envs, steps, 1, generator=g), "done": done,
                             "terminated": done.clone(), "truncated": torch.zeros_like(done)},
                            batch_size=[envs, steps])
    td.refine_names(None, "time")
    return td


def test_the_update_gathers_no_next_step_inputs_and_computes_the_same():
    cfg = preset_config("cpu_smoke", device="cpu", **{"env.num_envs": 4, "ppo.steps_per_env": 8,
                        "ppo.minibatch_size": 16, "ppo.epochs": 2, "ppo.critic_privileged": True})
    cpu = torch.device("cpu")
    torch.manual_seed(0)
    agent = build_agent(cfg, 6, 13, cpu)
    loss_module, advantage = make_loss(cfg, agent)
    listed = set(loss_module.in_keys)
    # What TorchRL lists for its value estimator (the next step's actor inputs and outcome).
    assert {("next", k) for k in ("observation", "reward", "done", "terminated")} <= listed
    td = _rollout(agent)
    guard_rollout(td)
    estimate_advantages(advantage, td)
    keys = set(_loss_keys(loss_module, td))
    assert not keys & NEXT_INPUTS, keys & NEXT_INPUTS
    assert {"observation", "privileged", "action", "advantage", "value_target", VALID_KEY} <= keys
    # The update on the smaller selection equals the update on every listed input, from the same start.
    everything = sorted((k for k in listed | keys if k in set(td.keys(True, True))), key=str)
    results = []
    for selection in (sorted(keys, key=str), everything):
        learner = copy.deepcopy(agent)
        loss, _ = make_loss(cfg, learner)
        torch.manual_seed(2)
        stats = _update(cfg, td.select(*selection).reshape(-1),
                        make_update_step(cfg, loss, make_optimizer(cfg, learner, cpu), cpu))
        results.append((stats, [p.detach().clone() for p in (*learner.actor.parameters(),
                                                               *learner.critic.parameters())]))
    (stats_small, params_small), (stats_all, params_all) = results
    assert stats_small == stats_all
    assert all(torch.equal(a, b) for a, b in zip(params_small, params_all, strict=True))


def test_next_step_keys_a_loss_reads_itself_stay_and_nothing_is_left_out_before_gae():
    loss = SimpleNamespace(in_keys=["observation", "action", ("next", "observation"), ("next", "reward"),
                                    ("next", "truncated"), ("next", "leg_assist")])
    batch = TensorDict({"observation": torch.zeros(2, 3), "action": torch.zeros(2, 1),
                        "next": {"observation": torch.zeros(2, 3), "reward": torch.zeros(2, 1),
                                 "truncated": torch.zeros(2, 1, dtype=torch.bool),
                                 "leg_assist": torch.zeros(2, 12)}}, batch_size=[2])
    assert set(_loss_keys(loss, batch)) == set(loss.in_keys)  # no advantage yet: the estimator may still run
    batch["advantage"], batch["value_target"] = torch.zeros(2, 1), torch.zeros(2, 1)
    assert set(_loss_keys(loss, batch)) == {"observation", "action", ("next", "leg_assist"), "advantage",
                                            "value_target"}
