"""NaN/inf stays in its world: the broken world terminates with finite outputs and resets; no normaliser statistic,
observation, reward, or PPO update of any other world sees it (both physics backends)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from tocabi_torchrl import make_env
from tocabi_torchrl.transforms import RunningNormalization

N = 4


def _running_norm(env) -> RunningNormalization:
    return next(t for t in env.transform if isinstance(t, RunningNormalization))


def _zero_step(env, td):
    return env.step_and_maybe_reset(td.set("action", torch.zeros(N, 13)))


@pytest.mark.parametrize("backend", ["warp", "mujoco"])
def test_a_nan_world_terminates_resets_and_poisons_no_other_world(backend):
    # The issue's repro: running normalisation, NaN into env 0's qvel, one step with zero actions.
    env = make_env(num_envs=N, device="cpu", backend=backend, normalization="running", seed=0, sync_free_resets=True)
    twin = make_env(num_envs=N, device="cpu", backend=backend, normalization="running", seed=0, sync_free_resets=True)
    td, td_twin = env.reset(), twin.reset()
    norm = _running_norm(env)
    count = float(norm.count)
    env.base_env.sim.qvel[0] = float("nan")
    out, td = _zero_step(env, td)
    out_twin, td_twin = _zero_step(twin, td_twin)
    nxt = out["next"]
    assert nxt["terminated"].flatten().tolist() == [True, False, False, False]
    assert not nxt["healthy"][0] and nxt["healthy"][1:].all()
    for key in ("observation", "obs_step", "reward", "episode_reward", "joint_pos", "base_pos", "foot_force"):
        assert torch.isfinite(nxt[key]).all(), f"{key} is not finite (NaN world's terminal step included)"
    assert nxt["reward"][0] == 0.0
    # The other worlds' physics and signals are those of a run without the NaN.
    torch.testing.assert_close(nxt["obs_step"][1:], out_twin["next", "obs_step"][1:], rtol=0, atol=0)
    # The normaliser learned from the three healthy rows only, and its statistics stay finite.
    assert float(norm.count) == count + N - 1
    assert torch.isfinite(norm.mean).all() and torch.isfinite(norm.var).all()
    # The broken world was reset in the same call; every world steps on with finite values.
    assert td["step_count"][0] == 0 and torch.isfinite(td["observation"]).all()
    out, td = _zero_step(env, td)
    assert torch.isfinite(out["next", "observation"]).all() and out["next", "healthy"].all()
    assert float(norm.count) == count + 2 * N - 1


def test_the_warp_health_flag_covers_qacc_and_sensors():
    import warp as wp

    from tocabi_torchrl.sim.kernels import derive_signals

    wp.init()
    qacc = np.zeros((3, 2), np.float32)
    qacc[1, 0] = np.inf
    sensors = np.zeros((3, 4), np.float32)
    sensors[2, 3] = np.nan
    healthy = wp.zeros(3, dtype=wp.bool, device="cpu")
    with wp.ScopedDevice("cpu"):
        wp.launch(derive_signals, dim=3, inputs=[
            wp.zeros((3, 2), dtype=float), wp.zeros((3, 2), dtype=float), wp.array(qacc, dtype=float),
            wp.array(sensors, dtype=float), wp.zeros(1, dtype=int), wp.zeros((1, 1), dtype=float),
            wp.zeros(3, dtype=int), wp.zeros(3, dtype=int), wp.zeros(1, dtype=int), wp.zeros(1, dtype=int), 10, 10, 0,
        ], outputs=[wp.zeros((3, 1), dtype=wp.bool), wp.zeros(3, dtype=int), healthy])
    assert healthy.numpy().tolist() == [True, False, False]


def test_the_mujoco_health_flag_covers_sensors():
    from tocabi_torchrl.sim import MujocoSim, SimConfig

    sim = MujocoSim(SimConfig(num_worlds=3, device="cpu", threads=1))
    sim._staged["sensordata"][1, 0] = math.inf
    sim._publish()
    assert sim.healthy.tolist() == [True, False, True]


def test_running_normalisation_skips_non_finite_and_unhealthy_rows():
    norm = RunningNormalization(dim=2, init_count=1.0)
    x = torch.tensor([[1.0, 2.0], [math.nan, 0.0], [3.0, math.inf], [5.0, 6.0]])
    healthy = torch.tensor([[True], [True], [True], [False]])
    norm.update(x, healthy)
    # Only row 0 is usable: mean moves from (0, 0) halfway to (1, 2) with count 1 + 1.
    torch.testing.assert_close(norm.mean, torch.tensor([0.5, 1.0], dtype=torch.float64))
    assert float(norm.count) == 2.0 and torch.isfinite(norm.var).all()


def test_a_broken_frame_cannot_poison_the_ppo_update():
    # A NaN action, a ±1e6 action written over the sampled one (a wrapped policy) and a NaN observation: those frames
    # are masked out, and the losses, statistics and parameters stay finite.
    from tocabi_torchrl.rl import preset_config
    from tocabi_torchrl.rl.rollout_guard import VALID_KEY, guard_rollout
    from tocabi_torchrl.rl.trainer import (NORM_MASK_KEY, _loss_keys, _update, build_agent, estimate_advantages,
                                           make_loss, make_optimizer, make_update_step)

    cfg = preset_config("cpu_smoke", device="cpu", **{"env.num_envs": 4, "ppo.steps_per_env": 8,
                        "ppo.minibatch_size": 32, "ppo.epochs": 2})
    cpu = torch.device("cpu")
    torch.manual_seed(0)
    agent = build_agent(cfg, 6, 13, cpu)
    obs = torch.randn(4, 9, 6)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):  # sampled as the collector does
        td = agent.actor(TensorDict({"observation": obs[:, :-1].clone()}, batch_size=[4, 8]))
    done = torch.zeros(4, 8, 1, dtype=torch.bool)
    td["next"] = TensorDict({"observation": obs[:, 1:].clone(), "reward": torch.randn(4, 8, 1), "done": done,
                             "terminated": done.clone(), "truncated": done.clone()}, batch_size=[4, 8])
    td.refine_names(None, "time")
    td["action"][0, 3, 2] = math.nan
    td["action"][1, 5] = 1e6
    td["observation"][2, 6, 0] = math.nan
    optimizer = make_optimizer(cfg, agent, cpu)
    loss_module, advantage = make_loss(cfg, agent)
    observations = (td["observation"], td["next", "observation"])
    valid = guard_rollout(td)
    assert (~valid).nonzero().tolist() == [[0, 3], [1, 5], [2, 6]]
    # Cleaned in place: a copy of the rollout's observations would stay alive into the next iteration (memory).
    assert td["observation"] is observations[0] and td["next", "observation"] is observations[1]
    for key in ("action", "action_log_prob", "observation"):
        assert torch.isfinite(td[key]).all(), key
    estimate_advantages(advantage, td)
    flat = td.select(*_loss_keys(loss_module, td)).reshape(-1)
    assert VALID_KEY in flat.keys() and torch.equal(flat[NORM_MASK_KEY], flat[VALID_KEY])
    # A masked frame's advantage moves neither the loss nor the advantage normalisation of the valid frames (it did:
    # TorchRL normalises with its own mask key, not the loss mask).
    masked = int((~flat[VALID_KEY].squeeze(-1)).nonzero()[0])
    with torch.no_grad():
        losses = []
        for value in (0.0, 50.0):
            batch = flat.clone()
            batch["advantage"][masked] = value
            losses.append(float(loss_module(batch)["loss_objective"]))
    assert losses[0] == pytest.approx(losses[1], rel=1e-6), losses
    stats = _update(cfg, flat, make_update_step(cfg, loss_module, optimizer, cpu))
    assert all(math.isfinite(v) for v in stats.values()), stats
    for name, p in [*agent.actor.named_parameters(), *agent.critic.named_parameters()]:
        assert torch.isfinite(p).all(), name


def test_a_masked_frame_moves_neither_the_kl_nor_the_clip_fraction():
    # The adaptive learning rate reads kl_approx; TorchRL averaged it (and clip_fraction) over every frame, the
    # masked ones included, whose log-ratio compares the stored mean with the policy at a sanitised observation: a
    # few NaN-observation frames at a small std read as a KL far above the target and held the rate at its floor.
    from tocabi_torchrl.rl import preset_config
    from tocabi_torchrl.rl.rollout_guard import VALID_KEY, guard_rollout
    from tocabi_torchrl.rl.symmetry import PolicyInputMirror, SignedPermutation, SymmetryAugmentLoss, action_mirror_map
    from tocabi_torchrl.rl.trainer import _loss_keys, build_agent, estimate_advantages, make_loss

    cfg = preset_config("cpu_smoke", device="cpu", **{"env.num_envs": 4, "ppo.steps_per_env": 8,
                        "ppo.minibatch_size": 32})
    torch.manual_seed(0)
    agent = build_agent(cfg, 237, 13, torch.device("cpu"))
    obs = torch.randn(4, 9, 237)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        td = agent.actor(TensorDict({"observation": obs[:, :-1].clone()}, batch_size=[4, 8]))
    done = torch.zeros(4, 8, 1, dtype=torch.bool)
    td["next"] = TensorDict({"observation": obs[:, 1:].clone(), "reward": torch.randn(4, 8, 1), "done": done,
                             "terminated": done.clone(), "truncated": done.clone()}, batch_size=[4, 8])
    td.refine_names(None, "time")
    td["observation"][2, 6, 0] = math.nan  # its stored mean, action and log-probability are NaN too
    td["loc"][2, 6] = td["action"][2, 6] = math.nan
    td["action_log_prob"][2, 6] = math.nan
    loss_module, advantage = make_loss(cfg, agent)
    guard_rollout(td)
    estimate_advantages(advantage, td)
    flat = td.select(*_loss_keys(loss_module, td)).reshape(-1)
    masked = int((~flat[VALID_KEY].squeeze(-1)).nonzero()[0])
    mirrored = SymmetryAugmentLoss(loss_module, PolicyInputMirror(), SignedPermutation(*action_mirror_map()))
    for loss in (loss_module, mirrored):
        seen = []
        with torch.no_grad():
            for value in (0.0, 30.0):  # the policy's mean at the masked frame moves far from the stored one
                batch = flat.clone()
                batch["observation"][masked] = value
                out = loss(batch)
                seen.append((float(out["kl_approx"]), float(out["clip_fraction"])))
        assert seen[0] == pytest.approx(seen[1], rel=1e-6, abs=1e-9), (type(loss).__name__, seen)


def test_a_reward_term_that_returns_nan_is_said_not_trained_on_silently(tmp_path, capsys):
    # Every frame was masked out of the update, the losses were 0 and the progress lines said nothing.
    from tocabi_torchrl.rl import preset_config
    from tocabi_torchrl.rl.metrics_files import read_metrics
    from tocabi_torchrl.rl.trainer import build_env, train
    from tocabi_torchrl.transforms import CallableTerm
    from tocabi_torchrl.transforms.settings import REFERENCE_TERM_NAMES

    cfg = preset_config("cpu_smoke", device="cpu", run_dir=str(tmp_path), name="nan", total_env_steps=8 * 16 * 2,
                        progress_bar=False, eval_at_end=False)
    # NaN in half the envs (as a diverging world's physics would give): trained on, masked, said.
    half = CallableTerm("half", lambda td, nxt: torch.where(torch.arange(len(nxt["base_pos"]))[:, None] % 2 == 0,
                                                            math.nan, nxt["base_pos"][:, :1] * 0), 0.1)
    train(cfg, env=build_env(cfg, torch.device("cpu"), for_training=True,
                             reward_terms=(*REFERENCE_TERM_NAMES, half)))
    out = capsys.readouterr().out
    assert out.count("warning: 50.0 % of iteration 1's frames were left out of the update") == 1  # once a run
    assert [float(row["masked_frac"]) for row in read_metrics(tmp_path / "nan")] == [0.5, 0.5]
    # NaN in every env is a broken term: said at the first step, by name.
    broken = CallableTerm("broken", lambda td, nxt: torch.full_like(nxt["base_pos"][:, :1], math.nan), 0.1)
    with pytest.raises(ValueError, match="reward term 'broken' returned NaN or inf in every env at the first step"):
        train(dataclasses.replace(cfg, name="nan2"), env=build_env(cfg, torch.device("cpu"), for_training=True,
                                                                   reward_terms=(*REFERENCE_TERM_NAMES, broken)))


def test_the_logged_action_noise_reads_whether_a_rollout_explored():
    # A rollout that acted with its mean action (no exploration) logs 0, Gaussian draws about sqrt(2/pi); a faulted
    # world's non-finite action counts for nothing.
    from tensordict import TensorDict

    from tocabi_torchrl.rl.trainer import _episode_values

    g = torch.Generator().manual_seed(0)
    n, t, a = 64, 8, 13
    loc, scale = torch.randn(n, t, a, generator=g), torch.full((n, t, a), 0.2)

    def noise(action):
        batch = TensorDict({"action": action, "loc": loc, "scale": scale,
                            ("next", "done"): torch.zeros(n, t, 1, dtype=torch.bool),
                            ("next", "terminated"): torch.zeros(n, t, 1, dtype=torch.bool),
                            ("next", "reward"): torch.zeros(n, t, 1)}, batch_size=[n, t])
        names, values = _episode_values(batch)
        return float(values[names.index("action_noise_z")])

    drawn = loc + scale * torch.randn(n, t, a, generator=g)
    assert abs(noise(drawn) - (2 / math.pi) ** 0.5) < 0.02
    assert noise(loc.clone()) == 0.0
    drawn[0, 0, 0] = float("nan")
    assert abs(noise(drawn) - (2 / math.pi) ** 0.5) < 0.02
