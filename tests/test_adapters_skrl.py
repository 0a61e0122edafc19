"""skrl adapter (skrl 2.x): the wrapper interface on device tensors, autoreset with the terminal observation, and
2 iterations of recipes/train_skrl.py end to end with the gait test (CPU, tiny)."""

from __future__ import annotations

import json

import pytest
import torch

pytest.importorskip("skrl")

from recipe_runner import TouchMarker, assert_preset_init, load_recipe
from skrl.envs.wrappers.torch.base import Wrapper

from tocabi_torchrl.adapters import TocabiSkrlEnv

N = 2


def test_wrapper_interface_and_autoreset():
    env = TocabiSkrlEnv(N, "cpu", max_episode_steps=2)
    try:
        assert isinstance(env, Wrapper)
        assert env.num_envs == N and env.observation_space.shape == (237,) and env.action_space.shape == (13,)
        assert env.state_space is None and env.state() is None
        obs, _ = env.reset()
        assert obs.shape == (N, 237) and obs.device == env.device
        obs, reward, terminated, truncated, infos = env.step(torch.zeros(N, 13))
        assert reward.shape == terminated.shape == truncated.shape == (N, 1)
        assert not (terminated | truncated).any()
        assert set(infos["log"]) == {f"Reward / {k}" for k in env.stepper.term_names}
        obs, reward, terminated, truncated, infos = env.step(torch.zeros(N, 13))
        assert truncated.all() and not terminated.any() and infos["_final_obs"].all()
        assert not torch.equal(infos["final_obs"], obs)
        with pytest.raises(ValueError, match=r"actions must have shape \(2, 13\) \(num_envs, action_dim\), got \(3, 13\)"):
            env.step(torch.zeros(N + 1, 13))
    finally:
        env.close()


def test_step_before_reset_and_calls_after_close_are_refused():
    # skrl's trainers reset first: a step before that is refused as gymnasium refuses it, and nothing runs after
    # close. Both used to step silently.
    import gymnasium

    env = TocabiSkrlEnv(N, "cpu")
    try:
        with pytest.raises(gymnasium.error.ResetNeeded,
                           match=r"TocabiSkrlEnv.step\(\) called before reset\(\): call reset\(\) first"):
            env.step(torch.zeros(N, 13))
        assert env.stepper.env_steps == 0
        env.reset()
        env.step(torch.zeros(N, 13))
    finally:
        env.close()
    for call, name in ((lambda: env.step(torch.zeros(N, 13)), "step"), (env.reset, "reset")):
        with pytest.raises(RuntimeError, match=rf"TocabiSkrlEnv.{name}\(\) called after close\(\).* build a new"):
            call()
    env.close()


def test_recipe_trains_two_iterations_and_gait_tests(tmp_path):
    recipe = load_recipe("train_skrl")
    out = tmp_path / "run"
    result = recipe.main(["--out", str(out), "--device", "cpu", "--num_envs", "2", "--iterations", "2",
                          "--rollouts", "4", "--hidden", "16", "--eval_envs", "2", "--eval_seconds", "0.1"])
    assert result["train"]["env_steps"] == 2 * 2 * 4
    summary = json.loads((out / "eval" / "summary.json").read_text())
    assert summary["num_envs"] == 2 and "passes" in result["eval"]
    # The gait test's actor is the saved policy network: its action is the network's output (the Gaussian mean).
    from tocabi_torchrl.adapters.policy_file import load_policy

    _, state = load_policy(out / "policy.pt", "skrl")
    assert state["net.0.weight"].shape == (16, 237)
    _, act = recipe.load_actor(out / "policy.pt")
    obs = torch.randn(3, 237)
    hidden = torch.nn.functional.elu(obs @ state["net.0.weight"].T + state["net.0.bias"])
    torch.testing.assert_close(act(obs), hidden @ state["net.2.weight"].T + state["net.2.bias"])


def test_recipe_resumes_the_same_run(tmp_path):
    # One iteration, then a resumed call for one more: counters are cumulative and the second call starts from the
    # first call's weights and Adam state (skrl's agent.load), not from a fresh initialisation.
    from skrl.agents.torch.ppo import PPO

    from tocabi_torchrl.adapters.policy_file import load_policy

    recipe = load_recipe("train_skrl")
    out = tmp_path / "run"
    small = ["--out", str(out), "--device", "cpu", "--num_envs", "2", "--rollouts", "4", "--hidden", "16",
             "--eval_envs", "0"]
    first = recipe.main([*small, "--iterations", "1"])["train"]
    assert (first["iterations"], first["env_steps"], first["calls"]) == (1, 8, 1)
    _, policy1 = load_policy(out / "policy.pt", "skrl")
    saved = torch.load(out / "resume" / "state_call1.pt", map_location="cpu", weights_only=True)
    seen, real_load = {}, PPO.load

    def spy(self, path):
        real_load(self, path)
        seen["policy"] = {k: v.clone() for k, v in self.policy.state_dict().items()}
        seen["adam"] = [float(s["step"]) for s in self.optimizer.state_dict()["state"].values()]

    PPO.load = spy
    try:
        second = recipe.main([*small, "--iterations", "2", "--resume"])["train"]
    finally:
        PPO.load = real_load
    assert (second["iterations"], second["env_steps"], second["calls"]) == (2, 16, 2)
    assert second["train_seconds"] > first["train_seconds"]
    assert all(torch.equal(seen["policy"][k], policy1[k]) for k in policy1)  # continued, not re-initialised
    assert seen["adam"] == [float(s["step"]) for s in saved["optimizer"]["state"].values()] and seen["adam"][0] > 0
    _, policy2 = load_policy(out / "policy.pt", "skrl")
    assert not all(torch.equal(policy2[k], policy1[k]) for k in policy1)
    assert (out / "policy_call1.pt").is_file() and (out / "skrl" / "ppo_call2").is_dir()


class _Stop(Exception):
    pass


def test_models_start_from_the_presets_initialisation(tmp_path, monkeypatch):
    # As the preset's networks (spec §10.3): orthogonal, hidden gain √2, first action means ~0, the value head of the
    # preset's value_out_gain (the reference preset's 0.01 here, not the default 1.0), biases 0.
    from tocabi_torchrl.config import preset_config

    recipe = load_recipe("train_skrl")
    built = {}
    make_models = recipe.make_models

    def spy(*a, **k):
        built.update(make_models(*a, **k))
        raise _Stop  # the models as main() builds them, before any update

    monkeypatch.setattr(recipe, "make_models", spy)
    with pytest.raises(_Stop):
        recipe.main(["--out", str(tmp_path / "run"), "--device", "cpu", "--num_envs", "2", "--rollouts", "4",
                     "--eval_envs", "0", "--iterations", "1", "--preset", "reference"])
    value_gain = preset_config("reference").ppo.value_out_gain
    assert_preset_init(built["policy"].net, 0.01)
    assert_preset_init(built["value"].net, value_gain)
    obs = torch.randn(64, built["policy"].net[0].in_features)
    assert built["policy"].net(obs).abs().max() < 0.1


def test_resume_of_the_top_seed(tmp_path):
    # The resumed call reseeds with seed + 1, which used to leave NumPy's range at --seed 2**32 - 1.
    recipe = load_recipe("train_skrl")
    small = ["--out", str(tmp_path / "run"), "--device", "cpu", "--num_envs", "2", "--rollouts", "2", "--hidden", "8",
             "--eval_envs", "0", "--seed", str(2 ** 32 - 1)]
    recipe.main([*small, "--iterations", "1"])
    assert recipe.main([*small, "--iterations", "2", "--resume"])["train"]["iterations"] == 2


def test_recipe_bootstraps_a_time_out_from_the_ended_episodes_last_observation(tmp_path, monkeypatch):
    # skrl's time_limit_bootstrap adds discount * V(next_observations), which the autoresetting env returns as the
    # next episode's first observation; the recipe's agent takes V of infos["final_obs"], the state where time ran
    # out, and still acts on (and takes the rollout's last value from) next_observations.
    from skrl.trainers.torch.base import Trainer

    recipe = load_recipe("train_skrl")
    built = {}

    def spy(self):
        built["agent"], built["env"] = self.agents, self.env
        raise _Stop  # the agent as main() builds it, in training mode, before any step

    monkeypatch.setattr(Trainer, "train", spy)
    with pytest.raises(_Stop):
        recipe.main(["--out", str(tmp_path / "run"), "--device", "cpu", "--num_envs", "2", "--rollouts", "4",
                     "--hidden", "8", "--eval_envs", "0", "--iterations", "1"])
    agent, env = built["agent"], built["env"]
    try:
        obs, _ = env.reset()
        agent.act(obs, None, timestep=0, timesteps=4)
        generator = torch.Generator().manual_seed(0)
        next_obs, final_obs = (torch.randn(N, 237, generator=generator) for _ in range(2))
        truncated = torch.tensor([[True], [False]])
        agent.record_transition(observations=obs, states=None, actions=torch.zeros(N, 13), rewards=torch.ones(N, 1),
                                next_observations=next_obs, next_states=None, terminated=torch.zeros(N, 1, dtype=bool),
                                truncated=truncated, infos={"final_obs": final_obs, "_final_obs": truncated[:, 0]},
                                timestep=0, timesteps=4)
        with torch.no_grad():
            value = agent.value.act({"observations": final_obs, "states": None}, role="value")[0]
        stored = agent.memory.get_tensor_by_name("rewards")[0]
        torch.testing.assert_close(stored, torch.ones(N, 1) + 0.995 * value * truncated)
        assert agent._current_next_observations is next_obs
    finally:
        env.close()


def test_resume_loads_the_state_it_checked_not_a_file_replaced_after(tmp_path, monkeypatch):
    # The state file was checked (tensors only) before the env was built and read again by skrl's unpickling load
    # after: a file replaced in between ran its code. The agent now loads the bytes that were checked.
    recipe = load_recipe("train_skrl")
    out, marker = tmp_path / "run", tmp_path / "ran"
    small = ["--out", str(out), "--device", "cpu", "--num_envs", "2", "--rollouts", "2", "--hidden", "8",
             "--eval_envs", "0"]
    recipe.main([*small, "--iterations", "1"])
    read_resume = recipe.read_resume

    def checked_then_replaced(*a, **k):
        prior = read_resume(*a, **k)
        torch.save({"policy": TouchMarker(marker)}, out / prior["state"])
        return prior

    monkeypatch.setattr(recipe, "read_resume", checked_then_replaced)
    second = recipe.main([*small, "--iterations", "2", "--resume"])["train"]
    assert not marker.exists() and second["iterations"] == 2
