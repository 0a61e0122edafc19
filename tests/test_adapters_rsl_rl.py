"""rsl_rl adapter (rsl-rl-lib 5.x): the VecEnv interface, zero-copy observation groups, time-outs on a crafted
episode, and 2 iterations of recipes/train_rsl_rl.py end to end with the gait test (CPU, tiny)."""

from __future__ import annotations

import json

import pytest
import torch

pytest.importorskip("rsl_rl")

from recipe_runner import TouchMarker, assert_preset_init, load_recipe
from rsl_rl.env import VecEnv
from tensordict import TensorDict

from tocabi_torchrl.adapters import TocabiRslRlEnv
from tocabi_torchrl.adapters.policy_file import load_policy

N = 2


@pytest.fixture(scope="module")
def env():
    e = TocabiRslRlEnv(N, "cpu", max_episode_steps=2)
    yield e
    e.close()


def test_vecenv_interface_and_zero_copy_groups(env):
    assert isinstance(env, VecEnv)
    assert env.num_envs == N and env.num_actions == 13 and env.max_episode_length == 2
    obs = env.get_observations()
    assert set(obs.keys()) == {"policy", "critic"} and obs["policy"].shape == (N, 237)
    # The groups are the TorchRL env's own observation tensor: no copy between the env and rsl_rl.
    ptr = env.stepper.observation.data_ptr()
    assert obs["policy"].data_ptr() == ptr and obs["critic"].data_ptr() == ptr
    obs, rewards, dones, extras = env.step(torch.zeros(N, 13))
    assert obs["policy"].data_ptr() == env.stepper.observation.data_ptr()
    assert rewards.shape == (N,) and dones.shape == (N,) and dones.dtype == torch.long
    assert set(extras["log"]) == {f"/reward/{k}" for k in env.stepper.term_names}


def test_time_outs_at_the_episode_limit(env):
    env.reset()
    _, _, dones, extras = env.step(torch.zeros(N, 13))
    assert not dones.any() and not extras["time_outs"].any()
    assert torch.equal(env.episode_length_buf, torch.ones(N, dtype=torch.int64))
    _, _, dones, extras = env.step(torch.zeros(N, 13))
    assert dones.all() and extras["time_outs"].all()  # rsl_rl bootstraps these
    assert torch.equal(env.episode_length_buf, torch.zeros(N, dtype=torch.int64))  # already reset
    with pytest.raises(NotImplementedError, match="init_at_random_ep_len=False"):
        env.episode_length_buf = torch.zeros(N, dtype=torch.int64)
    with pytest.raises(ValueError, match=r"actions must have shape \(2, 13\) \(num_envs, action_dim\), got \(2, 12\)"):
        env.step(torch.zeros(N, 12))


def test_ready_once_built_and_refused_after_close():
    # rsl_rl's VecEnv has no reset that its runner calls: a step first is allowed (it resets all envs, as
    # get_observations would). After close nothing runs: that used to step silently.
    env = TocabiRslRlEnv(N, "cpu")
    try:
        obs, rewards, dones, _ = env.step(torch.zeros(N, 13))
        assert obs["policy"].shape == (N, 237) and env.stepper.env_steps == N
    finally:
        env.close()
    for call, name in ((lambda: env.step(torch.zeros(N, 13)), "step"), (env.reset, "reset"),
                       (env.get_observations, "get_observations")):
        with pytest.raises(RuntimeError, match=rf"TocabiRslRlEnv.{name}\(\) called after close\(\).* build a new"):
            call()
    env.close()


def test_recipe_trains_two_iterations_and_gait_tests(tmp_path):
    recipe = load_recipe("train_rsl_rl")
    out = tmp_path / "run"
    result = recipe.main(["--out", str(out), "--device", "cpu", "--num_envs", "2", "--iterations", "2",
                          "--steps_per_env", "4", "--hidden", "16", "--eval_envs", "2", "--eval_seconds", "0.1"])
    assert result["train"]["env_steps"] == 2 * 2 * 4
    assert (out / "policy.pt").is_file() and (out / "rsl_rl").is_dir()
    summary = json.loads((out / "eval" / "summary.json").read_text())
    assert summary["num_envs"] == 2 and 0.0 <= summary["survival"] <= 1.0
    assert result["eval"]["passes"] is False  # 2 tiny iterations do not walk
    # The gait test ran the trained actor: the policy file holds rsl_rl's own final actor weights, and the rebuilt
    # actor gives rsl_rl's deterministic action.
    own = torch.load(out / "rsl_rl" / "model_1.pt", map_location="cpu", weights_only=True)["actor_state_dict"]
    meta, act = recipe.load_actor(out / "policy.pt")
    _, state = load_policy(out / "policy.pt", "rsl_rl")
    assert own.keys() == state.keys() and all(torch.equal(own[k], state[k]) for k in own)
    obs = torch.randn(3, 237)
    actor = recipe.make_actor(237, 13, meta["train_cfg"])
    actor.load_state_dict(own)
    torch.testing.assert_close(act(obs), actor(TensorDict({"policy": obs, "critic": obs}, batch_size=[3])))
    with pytest.raises(SystemExit, match="exists"):
        recipe.main(["--out", str(out), "--device", "cpu"])


def test_recipe_resumes_the_same_run(tmp_path):
    # One iteration, then a resumed call for one more: counters are cumulative and the second call starts from the
    # first call's weights and Adam state (rsl_rl's own load), not from a fresh initialisation.
    recipe = load_recipe("train_rsl_rl")
    out = tmp_path / "run"
    small = ["--out", str(out), "--device", "cpu", "--num_envs", "2", "--steps_per_env", "4", "--hidden", "16",
             "--eval_envs", "0"]
    first = recipe.main([*small, "--iterations", "1"])["train"]
    assert (first["iterations"], first["env_steps"], first["calls"]) == (1, 8, 1)
    state = torch.load(out / "resume" / "state_call1.pt", map_location="cpu", weights_only=True)
    _, policy1 = load_policy(out / "policy.pt", "rsl_rl")
    seen = {}
    from rsl_rl.runners import OnPolicyRunner

    real_load = OnPolicyRunner.load

    real_learn = OnPolicyRunner.learn

    def spy(self, path, *a, **k):
        infos = real_load(self, path, *a, **k)
        seen["adam_steps"] = [float(s["step"]) for s in self.alg.optimizer.state_dict()["state"].values()]
        return infos

    def spy_learn(self, *a, **k):  # the weights the second call trains from, after all of its set-up
        seen["actor"] = {k: v.clone() for k, v in self.alg.get_policy().state_dict().items()}
        return real_learn(self, *a, **k)

    OnPolicyRunner.load, OnPolicyRunner.learn = spy, spy_learn
    try:
        second = recipe.main([*small, "--iterations", "2", "--resume"])["train"]
    finally:
        OnPolicyRunner.load, OnPolicyRunner.learn = real_load, real_learn
    assert (second["iterations"], second["env_steps"], second["calls"]) == (2, 16, 2)
    assert second["train_seconds"] > first["train_seconds"]
    # nothing of the first call is overwritten: its result and policy are kept aside under the call's name
    assert json.loads((out / "result_call1.json").read_text())["train"]["calls"] == 1
    assert json.loads((out / "result.json").read_text())["train"]["calls"] == 2
    assert (out / "policy_call1.pt").is_file()
    assert all(torch.equal(seen["actor"][k], policy1[k]) for k in policy1)  # continued, not re-initialised
    saved_steps = [float(s["step"]) for s in state["optimizer_state_dict"]["state"].values()]
    assert seen["adam_steps"] == saved_steps and saved_steps[0] > 0  # Adam's state carried over
    _, policy2 = load_policy(out / "policy.pt", "rsl_rl")
    assert not all(torch.equal(policy2[k], policy1[k]) for k in policy1)  # trained on
    assert (out / "policy_call1.pt").is_file() and (out / "resume" / "state_call2.pt").is_file()
    assert torch.load(out / "resume" / "state_call2.pt", weights_only=True)["iter"] == 2 and state["iter"] == 1
    # Nothing left: a third call within the same --iterations trains nothing and keeps the counters.
    third = recipe.main([*small, "--iterations", "2", "--resume"])["train"]
    assert (third["iterations"], third["env_steps"]) == (2, 16)
    with pytest.raises(SystemExit, match="other settings"):
        recipe.main([*small[:-4], "--hidden", "8", "--eval_envs", "0", "--iterations", "3", "--resume"])


class _Stop(Exception):
    pass


@pytest.mark.parametrize("preset", ["default", "reference"])  # value heads of gain 1.0 and 0.01
def test_recipe_starts_from_the_presets_initialisation(tmp_path, monkeypatch, preset):
    # rsl_rl's own init (PyTorch's default) gives first action means far from 0; the recipe initialises the networks
    # as the preset's (spec §10.3) before learning: orthogonal, action mean 0.01, the preset's value_out_gain.
    from rsl_rl.runners import OnPolicyRunner

    from tocabi_torchrl.config import preset_config

    recipe = load_recipe("train_rsl_rl")
    seen = {}

    def spy(self, *a, **k):
        seen["actor"], seen["critic"] = self.alg.actor.mlp, self.alg.critic.mlp
        seen["clipped_value_loss"] = self.alg.use_clipped_value_loss
        obs = torch.randn(64, self.alg.actor.mlp[0].in_features)
        seen["mean"] = self.alg.actor(TensorDict({"policy": obs, "critic": obs}, batch_size=[64])).detach()
        raise _Stop  # before any update changes the weights

    monkeypatch.setattr(OnPolicyRunner, "learn", spy)
    with pytest.raises(_Stop):
        recipe.main(["--out", str(tmp_path / "run"), "--device", "cpu", "--num_envs", "2", "--steps_per_env", "4",
                     "--eval_envs", "0", "--iterations", "1", "--preset", preset])
    value_gain = preset_config(preset).ppo.value_out_gain
    assert_preset_init(seen["actor"], 0.01)
    assert_preset_init(seen["critic"], value_gain)
    assert seen["mean"].abs().max() < 0.1  # first actions ~0 (PyTorch's init gives ~0.2 on average here)
    # The preset's value loss is plain L2 (no clip_value); a clipped one lagged behind the returns on the GPU.
    assert preset_config(preset).ppo.value_loss == "l2" and seen["clipped_value_loss"] is False


def record_rollout_std(monkeypatch) -> list:
    """(std, requires_grad) of the actor as each rsl_rl update starts: the std its rollout was drawn with."""
    from rsl_rl.algorithms import PPO

    seen = []
    real_update = PPO.update

    def spy(self, *a, **k):
        param = self.actor.distribution.std_param
        seen.append((param.detach().clone(), param.requires_grad))
        return real_update(self, *a, **k)

    monkeypatch.setattr(PPO, "update", spy)
    return seen


@pytest.mark.parametrize("std", ["scheduled", "learned"])
def test_recipe_std_follows_the_presets_schedule_or_is_learned(tmp_path, monkeypatch, std):
    # cpu_smoke's budget is 384 env steps: two iterations of 2 envs x 48 steps reach half of it, where the preset's
    # schedule (0.2 -> 0.05 over the first half) ends. Each rollout's std is read as its update starts.
    recipe = load_recipe("train_rsl_rl")
    seen = record_rollout_std(monkeypatch)
    out = tmp_path / "run"
    recipe.main(["--out", str(out), "--device", "cpu", "--num_envs", "2", "--steps_per_env", "48", "--hidden", "16",
                 "--eval_envs", "0", "--iterations", "2", "--preset", "cpu_smoke", "--std", std])
    saved = torch.load(out / "resume" / "state_call1.pt", weights_only=True)
    final = saved["actor_state_dict"]["distribution.std_param"]
    (first, grad1), (second, grad2) = seen
    torch.testing.assert_close(first, torch.full((13,), 0.2))  # the schedule's start, both ways
    if std == "scheduled":
        assert not grad1 and not grad2
        torch.testing.assert_close(second, torch.full((13,), 0.125))  # a quarter through: halfway from 0.2 to 0.05
        torch.testing.assert_close(final, torch.full((13,), 0.05))
    else:
        assert grad1 and grad2
        assert not torch.equal(second, first) and not torch.equal(final, second)  # moved by the updates
        assert not torch.allclose(second, torch.full((13,), 0.125))


def test_recipe_fixed_learning_rate_stays(tmp_path):
    # rsl_rl's own "fixed" schedule, for comparing with its per-mini-batch adaptive rule: the rate after training is
    # the one given (the adaptive rule moves it on the same run: checked beside it).
    recipe = load_recipe("train_rsl_rl")
    small = ["--device", "cpu", "--num_envs", "2", "--steps_per_env", "8", "--hidden", "16", "--eval_envs", "0",
             "--iterations", "2", "--learning_rate", "5e-3"]
    lrs = {}
    for schedule in ("fixed", "adaptive"):
        out = tmp_path / schedule
        recipe.main(["--out", str(out), *small, "--lr_schedule", schedule])
        state = torch.load(out / "resume" / "state_call1.pt", weights_only=True)
        lrs[schedule] = {g["lr"] for g in state["optimizer_state_dict"]["param_groups"]}
    assert lrs["fixed"] == {5e-3}
    assert lrs["adaptive"] != {5e-3}  # a large first step: its KL rule lowers the rate


@pytest.mark.parametrize("start", [5e-3, 1e-5])  # a large first step (the rate falls) and a tiny one (it rises)
def test_recipe_per_iteration_rule_is_the_presets(tmp_path, monkeypatch, start):
    # The recipe's default (--lr_schedule per_iteration): rsl_rl's per-mini-batch rule is silenced and the preset's
    # rule acts once per iteration on the update's mean KL (5 epochs x 1 mini-batch here, each KL measured before
    # its step).
    recipe = load_recipe("train_rsl_rl")
    seen = []
    real_step = recipe.PerIterationLR.step

    def spy(self):
        kls = [float(k) for k in self.kls]
        before = self.alg.learning_rate
        real_step(self)
        seen.append((kls, before, self.alg.learning_rate, {g["lr"] for g in self.alg.optimizer.param_groups}))

    monkeypatch.setattr(recipe.PerIterationLR, "step", spy)
    recipe.main(["--out", str(tmp_path / "run"), "--device", "cpu", "--num_envs", "2", "--steps_per_env", "8",
                 "--hidden", "16", "--eval_envs", "0", "--iterations", "2", "--learning_rate", str(start)])
    assert len(seen) == 2
    assert seen[0][1] == start  # rsl_rl's own rule did not move it during the first update
    for kls, before, after, groups in seen:
        assert len(kls) == 5 and abs(kls[0]) < 1e-7 and max(kls[1:]) > 0  # the first is measured before any step
        kl = sum(kls) / len(kls)
        expected = max(before / 1.5, 1e-5) if kl > 0.02 else min(before * 1.5, 1e-2) if kl < 0.005 else before
        assert after == pytest.approx(expected) and groups == {after}
    # the rule acts on the real KL: a large start falls, a tiny one rises
    assert seen[0][2] < start if start > 1e-3 else seen[0][2] > start


def test_recipe_scheduled_std_continues_on_resume(tmp_path, monkeypatch):
    # One iteration (96 of cpu_smoke's 384 env steps), then a resumed call: its rollout's std is the schedule's at
    # 96 steps (0.125, set after the first update and restored with the actor), not the start (0.2).
    recipe = load_recipe("train_rsl_rl")
    seen = record_rollout_std(monkeypatch)
    small = ["--out", str(tmp_path / "run"), "--device", "cpu", "--num_envs", "2", "--steps_per_env", "48",
             "--hidden", "16", "--eval_envs", "0", "--preset", "cpu_smoke"]
    recipe.main([*small, "--iterations", "1"])
    recipe.main([*small, "--iterations", "2", "--resume"])
    assert len(seen) == 2
    torch.testing.assert_close(seen[0][0], torch.full((13,), 0.2))
    torch.testing.assert_close(seen[1][0], torch.full((13,), 0.125))


def _per_iteration_rank(rank: int, world: int, init: str, out) -> None:
    """One gloo rank of a PerIterationLR over a stand-in of rsl_rl's PPO: rank r measures the KLs r+1 and 3(r+1)."""
    from types import SimpleNamespace

    import torch.distributed as dist

    dist.init_process_group("gloo", rank=rank, world_size=world, init_method=f"file://{init}")
    try:
        recipe = load_recipe("train_rsl_rl")
        kl = 0.01 * (rank + 1)
        actor = SimpleNamespace(get_kl_divergence=lambda old, new: torch.full((4,), new))
        optimizer = torch.optim.Adam([torch.nn.Parameter(torch.zeros(1))], lr=1e-3)
        alg = SimpleNamespace(actor=actor, optimizer=optimizer, learning_rate=1e-3, desired_kl=0.01,
                              device=torch.device("cpu"), is_multi_gpu=True, gpu_world_size=world)
        rule = recipe.PerIterationLR(alg)
        silenced = [float(alg.actor.get_kl_divergence(None, k).sum()) for k in (kl, 3 * kl)]
        rule.step()
        out[rank] = (silenced, alg.learning_rate, [g["lr"] for g in optimizer.param_groups])
    finally:
        dist.destroy_process_group()


def test_per_iteration_rule_averages_the_kl_over_gpus(tmp_path):
    # Under torchrun every GPU must set the same rate: the rule reads the mean KL of all ranks' mini-batches.
    # Rank 0 alone (mean 0.02: rate held) and rank 1 alone (0.04 > 2 x 0.01: rate falls) would part; the mean
    # over both (0.03) lowers both rates alike.
    import torch.distributed as dist
    import torch.multiprocessing as mp

    if not dist.is_available() or not dist.is_gloo_available():
        pytest.skip("torch.distributed with gloo is needed")
    with mp.Manager() as manager:
        out = manager.dict()
        mp.spawn(_per_iteration_rank, args=(2, str(tmp_path / "init"), out), nprocs=2, join=True)
        results = dict(out)
    for rank in (0, 1):
        silenced, lr, groups = results[rank]
        assert silenced == [0.0, 0.0]  # rsl_rl's own rule sees no KL
        assert lr == pytest.approx(1e-3 / 1.5) and groups == [lr]


def test_a_sigterm_saves_the_call_and_resume_continues(tmp_path, monkeypatch, capsys):
    # SIGTERM (a job scheduler's stop) in the second rollout: the handler the recipe installs while training lets the
    # rollout stop at the next env step, the call saves its resume state and policy.pt, and --resume trains the rest.
    import os
    import signal

    from tocabi_torchrl.adapters.recipe import read_resume

    recipe = load_recipe("train_rsl_rl")
    real_clock, steps = recipe.TrainingClock, [0]

    class Terminated(real_clock):
        def __call__(self):
            steps[0] += 1
            if steps[0] == 6:  # 4 steps per rollout: the second one
                os.kill(os.getpid(), signal.SIGTERM)  # without the recipe's handler, this ends the test process
            super().__call__()

    handler = signal.getsignal(signal.SIGTERM)
    monkeypatch.setattr(recipe, "TrainingClock", Terminated)
    out = tmp_path / "run"
    small = ["--out", str(out), "--device", "cpu", "--num_envs", "2", "--steps_per_env", "4", "--hidden", "16",
             "--eval_envs", "0", "--iterations", "2", "--seed", str(2 ** 32 - 1)]
    first = recipe.main(small)
    assert first["interrupted"] == "SIGTERM" and recipe.exit_status(first) == 143
    assert (first["train"]["iterations"], first["train"]["env_steps"]) == (1, 12)
    assert read_resume(out, torch_state=True)["calls"] == 1 and (out / "policy.pt").is_file()
    assert "rsl_rl: interrupted (SIGTERM)" in capsys.readouterr().err
    assert signal.getsignal(signal.SIGTERM) is handler
    monkeypatch.setattr(recipe, "TrainingClock", real_clock)
    second = recipe.main([*small, "--resume"])["train"]  # seed 2**32 - 1 + 1 wraps to 0
    assert (second["iterations"], second["env_steps"], second["calls"]) == (2, 20, 2)


def test_resume_loads_the_state_it_checked_not_a_file_replaced_after(tmp_path, monkeypatch):
    # The state file was checked (tensors only) before the env was built and read again by rsl_rl's unpickling load
    # after: a file replaced in between ran its code. The library now loads the bytes that were checked.
    recipe = load_recipe("train_rsl_rl")
    out, marker = tmp_path / "run", tmp_path / "ran"
    small = ["--out", str(out), "--device", "cpu", "--num_envs", "2", "--steps_per_env", "4", "--hidden", "8",
             "--eval_envs", "0"]
    recipe.main([*small, "--iterations", "1"])
    read_resume = recipe.read_resume

    def checked_then_replaced(*a, **k):
        prior = read_resume(*a, **k)
        torch.save({"iter": 1, "payload": TouchMarker(marker)}, out / prior["state"])
        return prior

    monkeypatch.setattr(recipe, "read_resume", checked_then_replaced)
    second = recipe.main([*small, "--iterations", "2", "--resume"])["train"]
    assert not marker.exists() and second["iterations"] == 2
