"""ppo.kl_adapt_every="minibatch": the adaptive rule before every mini-batch step, on the device (rsl_rl's schedule).

The per-iteration rule lets an update that overshoots run to its end at the same rate; this one lowers the rate
within the update, from each mini-batch's KL to the rollout's policy, before that mini-batch's step.
"""
from __future__ import annotations

import pytest
import torch

from tocabi_torchrl.config import preset_config
from tocabi_torchrl.rl.metrics_files import read_metrics
from tocabi_torchrl.rl.update_step import MinibatchKLRule, MinibatchStep


class _FixedKLLoss(torch.nn.Module):
    """A loss whose gradient is 1 for every weight and whose KL is a set number."""

    def __init__(self, kl: float):
        super().__init__()
        self.weight = torch.nn.Parameter(torch.zeros(3))
        self.kl = kl

    def forward(self, mb):
        zero = torch.zeros(())
        return {"loss_objective": self.weight.sum(), "loss_critic": zero, "kl_approx": torch.tensor(self.kl),
                "clip_fraction": zero}


@pytest.mark.parametrize("kl, factor", [(0.05, 1 / 1.5), (0.001, 1.5), (0.01, 1.0)])
def test_each_step_runs_at_the_rate_its_own_kl_set(kl, factor):
    loss = _FixedKLLoss(kl)
    optimizer = torch.optim.Adam([{"params": [loss.weight], "lr": torch.tensor(1e-3)}], fused=True)
    rule = MinibatchKLRule(optimizer.param_groups, desired_kl=0.01, floor=None, device="cpu")
    step = MinibatchStep(loss, optimizer, [loss.weight], max_grad_norm=float("inf"), kl_rule=rule)
    step(None)
    # Adam's first step moves each weight by its rate: the rate after the rule, not before it.
    torch.testing.assert_close(loss.weight.detach(), torch.full((3,), -1e-3 * factor))
    step(None)
    assert float(optimizer.param_groups[0]["lr"]) == pytest.approx(1e-3 * factor ** 2)


def test_the_rule_keeps_the_floor_and_the_ceiling_and_leaves_fixed_groups_alone():
    low, high = {"lr": torch.tensor(1.2e-4)}, {"lr": torch.tensor(8e-3)}
    MinibatchKLRule([low], 0.01, floor=1e-4, device="cpu")(torch.tensor(1.0))
    MinibatchKLRule([high], 0.01, floor=None, device="cpu")(torch.tensor(1e-6))
    assert float(low["lr"]) == pytest.approx(1e-4) and float(high["lr"]) == pytest.approx(1e-2)
    with pytest.raises(ValueError, match="tensor"):
        MinibatchKLRule([{"lr": 1e-3}], 0.01, floor=None, device="cpu")


def test_an_updates_first_step_keeps_the_rate_and_a_kl_of_0_or_less_never_raises_it():
    # rsl_rl: the first mini-batch of an update reads a KL of exactly 0, and the rate rises only on a KL above 0.
    group = {"lr": torch.tensor(1e-3)}
    rule = MinibatchKLRule([group], desired_kl=0.01, floor=None, device="cpu")
    rule.start_update()
    rule(torch.tensor(1.0))  # the update's first step: kept, however large its KL
    assert float(group["lr"]) == pytest.approx(1e-3)
    rule(torch.tensor(1.0))  # the next one acts
    assert float(group["lr"]) == pytest.approx(1e-3 / 1.5)
    for kl in (0.0, -1e-4):  # an estimate at or below 0 (rounding noise about a KL of 0) does not raise it
        rule(torch.tensor(kl))
        assert float(group["lr"]) == pytest.approx(1e-3 / 1.5)
    rule(torch.tensor(1e-4))  # a small positive KL does
    assert float(group["lr"]) == pytest.approx(1e-3)


def _cfg(tmp_path, **paths):
    return preset_config("cpu_smoke", device="cpu", run_dir=str(tmp_path), name="kl", progress_bar=False,
                         eval_at_end=False, log_every=1, total_env_steps=2 * 8 * 16,
                         **{"ppo.lr": 1e-3, "ppo.desired_kl": 1e-12, "ppo.kl_adapt_every": "minibatch", **paths})


def test_a_run_lowers_the_rate_at_every_mini_batch_step_and_logs_it(tmp_path):
    # cpu_smoke: 8 envs x 16 steps, mini-batches of 64, 2 epochs: 4 steps per update. A KL target no step meets
    # lowers the rate before each of them but the first (the per-iteration rule: once per update).
    from tocabi_torchrl.rl.trainer import train

    result = train(_cfg(tmp_path))
    rates = [float(r["lr"]) for r in read_metrics(result.run_dir)]
    assert rates == pytest.approx([1e-3 / 1.5 ** 3, 1e-3 / 1.5 ** 6])  # each update's first step keeps the rate
    saved = torch.load(result.run_dir / "checkpoints" / "latest.pt", weights_only=True)["optimizer"]
    assert float(saved["param_groups"][0]["lr"]) == pytest.approx(rates[-1])  # a resume goes on from it


def test_the_minibatch_rule_refuses_a_data_parallel_run_and_needs_the_adaptive_schedule(tmp_path):
    from tocabi_torchrl.config import UnusedOptionError
    from tocabi_torchrl.rl.distributed import DistInfo
    from tocabi_torchrl.rl.trainer import train

    with pytest.raises(ValueError, match="ranks' rates would part; this run has 2 ranks"):
        train(_cfg(tmp_path), dist_info=DistInfo(rank=0, world_size=2, local_rank=0))
    with pytest.raises(UnusedOptionError, match="ppo.kl_adapt_every"):
        preset_config("cpu_smoke", **{"ppo.lr_schedule": "fixed", "ppo.kl_adapt_every": "minibatch"})
    with pytest.raises(ValueError, match=r"ppo.kl_adapt_every must be one of \('iteration', 'minibatch'\)"):
        preset_config("cpu_smoke", **{"ppo.kl_adapt_every": "epoch"})


def test_the_minibatch_rule_is_held_while_the_teacher_pulls(tmp_path):
    # As the per-iteration rule (tests/test_torque_assist.py): no change of rate while β fades and the pull decays.
    from tocabi_torchrl.rl.trainer import train

    n, steps = 4, 8
    frames = n * steps
    cfg = preset_config("torque_ideal", device="cpu", total_env_steps=7 * frames, run_dir=str(tmp_path), name="t",
                        eval_at_end=False, progress_bar=False, checkpoint_every=1000,
                        **{"env.num_envs": n, "ppo.steps_per_env": steps, "ppo.minibatch_size": 8,
                           "ppo.epochs": 1, "ppo.desired_kl": 1e-12, "ppo.kl_adapt_every": "minibatch",
                           "ppo.assist_fade_start": frames, "ppo.assist_fade_end": 2 * frames,
                           "ppo.assist_anchor_decay": 3 * frames, "ppo.assist_lr_hold": "pull",
                           "ppo.actor_hidden": (16,), "ppo.critic_hidden": (16,), "ppo.cuda_graph": "off"})
    rows = read_metrics(train(cfg).run_dir)
    lr, weight = [float(r["lr"]) for r in rows], [float(r["absorb_weight"]) for r in rows]
    assert weight[:5] == pytest.approx([0, 1, 2 / 3, 1 / 3, 0])
    # Four mini-batch steps: the first keeps the rate, each of the others lowers it or, on an estimate of 0 or less
    # (the policy barely moved), keeps it.
    assert 1e-3 / 1.5 ** 3 <= lr[0] * (1 + 1e-6) and lr[0] < 1e-3
    assert lr[1] == lr[2] == lr[3] == lr[0]  # held until the pull is gone
    # Then the rule acts again (an update whose two steps went down and up ends where it began: look further on).
    assert any(rate != lr[3] for rate in lr[4:])
