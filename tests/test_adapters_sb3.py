"""Stable-Baselines3 adapter: SB3's VecEnv interface and checks (spaces, NaN check wrapper, episode monitor),
terminal observation and truncation on a crafted episode, and 2 iterations of recipes/train_sb3.py end to end with
the gait test (CPU, tiny)."""

from __future__ import annotations

import errno
import math

import numpy as np
import pytest
import torch

pytest.importorskip("stable_baselines3")

from host_reads import HostReads, counting_reads, crafted_step_result
from recipe_runner import TouchMarker, load_recipe
from stable_baselines3.common.utils import check_for_correct_spaces
from stable_baselines3.common.vec_env import VecCheckNan, VecEnv, VecMonitor

from tocabi_torchrl.adapters import TocabiSB3VecEnv
from tocabi_torchrl.adapters.policy_file import load_policy
from tocabi_torchrl.adapters.recipe import read_resume

N = 2


@pytest.fixture(scope="module")
def env():
    e = TocabiSB3VecEnv(N, "cpu", max_episode_steps=2, reward_terms_in_infos=True)
    yield e
    e.close()


def test_vecenv_interface_passes_sb3_checks(env):
    assert isinstance(env, VecEnv)
    check_for_correct_spaces(env, env.observation_space, env.action_space)
    assert env.observation_space.shape == (237,) and env.action_space.shape == (13,)
    checked = VecMonitor(VecCheckNan(env, raise_exception=True))  # SB3's wrappers run on top of it
    obs = checked.reset()
    assert isinstance(obs, np.ndarray) and obs.shape == (N, 237) and obs.dtype == np.float32
    actions = np.stack([env.action_space.sample() for _ in range(N)])
    obs, rewards, dones, infos = checked.step(actions)
    assert rewards.shape == (N,) and dones.dtype == bool and len(infos) == N
    assert len(infos[0]["reward_terms"]) == 13
    assert math.isclose(sum(infos[0]["reward_terms"].values()), float(rewards[0]), rel_tol=1e-4, abs_tol=1e-5)
    assert env.get_attr("render_mode") == [None] * N and env.env_is_wrapped(VecMonitor) == [False] * N


def test_a_set_or_call_for_some_env_indices_is_refused(env):
    # They acted on every env: env_method("reset", indices=[0]) reset all of them.
    for call in (lambda: env.env_method("reset", indices=[0]), lambda: env.set_attr("x", 1, indices=[1])):
        with pytest.raises(ValueError, match=r"indices=\[\d\]: TocabiSB3VecEnv is one batched simulator"):
            call()
    assert not hasattr(env, "x")
    env.set_attr("x", 1, indices=list(range(N)))
    assert env.get_attr("x") == [1] * N
    del env.x


def test_truncation_gives_terminal_observation_and_episode(env):
    env.seed(5)
    env.reset()
    zeros = np.zeros((N, 13), dtype=np.float32)
    obs, _, dones, infos = env.step(zeros)
    assert not dones.any() and "terminal_observation" not in infos[0]
    obs, _, dones, infos = env.step(zeros)
    assert dones.all()
    for i, info in enumerate(infos):
        assert info["TimeLimit.truncated"] is True  # SB3's PPO bootstraps the value of truncated episodes
        assert info["terminal_observation"].shape == (237,)
        assert not np.allclose(info["terminal_observation"], obs[i])  # obs is the reset one
        assert info["episode"]["l"] == 2


def test_step_wait_without_actions_is_refused(env):
    env.reset()
    with pytest.raises(RuntimeError, match="step_async"):
        env.step_wait()
    with pytest.raises(ValueError, match="actions must have shape"):
        env.step_async(np.zeros((N, 3), dtype=np.float32))


def test_step_before_reset_and_calls_after_close_are_refused():
    # As SB3's DummyVecEnv over gymnasium envs: no step before the first reset (SB3's algorithms reset first), and
    # nothing after close. Both used to step silently.
    import gymnasium

    env = TocabiSB3VecEnv(N, "cpu")
    zeros = np.zeros((N, 13), dtype=np.float32)
    try:
        for call in (lambda: env.step_async(zeros), lambda: env.step(zeros),
                     lambda: env.step_async(np.zeros((N, 3), dtype=np.float32))):  # the order comes first
            with pytest.raises(gymnasium.error.ResetNeeded,
                               match=r"TocabiSB3VecEnv.step_async\(\) called before reset\(\): call reset\(\) first"):
                call()
        assert env.stepper.env_steps == 0
        env.reset()
        env.step(zeros)
        env.step_async(zeros)
    finally:
        env.close()
    for call, name in ((lambda: env.step(zeros), "step_async"), (env.step_wait, "step_wait"), (env.reset, "reset")):
        with pytest.raises(RuntimeError, match=rf"TocabiSB3VecEnv.{name}\(\) called after close\(\).* build a new"):
            call()
    env.close()


def test_non_finite_actions_are_refused_naming_the_rows(env):
    # SB3's actions are on the host: a NaN or inf is refused there, not acted on as 0 or as the bound.
    env.reset()
    actions = np.zeros((N, 13), dtype=np.float32)
    actions[0, 2], actions[1, 12] = np.nan, np.inf
    with pytest.raises(ValueError, match=r"actions must be finite, but env rows \[0, 1\] hold NaN or inf"):
        env.step_async(actions)
    env.step(np.zeros((N, 13), dtype=np.float32))


@pytest.mark.parametrize("bad", [np.ones((N, 13), bool), np.full((N, 13), 0.5 + 1j), np.full((N, 13), "0.5"),
                                 [[None] * 13] * N], ids=["bool", "complex", "text", "objects"])
def test_actions_that_are_not_real_numbers_are_refused_as_by_the_gymnasium_adapter(env, bad):
    # They were cast to float32 and stepped: True as a full-scale 1.0, a complex value without its imaginary part
    # (numpy's warning alone), text parsed as numbers; None ended in a misleading "must be finite".
    env.reset()
    steps = env.stepper.env_steps
    with pytest.raises(TypeError, match=r"actions must be real numbers \(float32\), got an array of"):
        env.step_async(bad)
    assert env.stepper.env_steps == steps
    with pytest.raises(RuntimeError, match="without step_async"):  # nothing was queued
        env.step_wait()
    env.step(np.zeros((N, 13), dtype=np.int64))  # integers are real numbers: stepped as float32


def test_reset_options_are_refused_as_by_the_gymnasium_adapter(env):
    # SB3's set_options hands them to the next reset, which used to drop them without a word.
    with pytest.raises(ValueError, match=r"TocabiSB3VecEnv.reset takes no options, got \{'x': 1\}"):
        env.set_options({"x": 1})
    with pytest.raises(ValueError, match="takes no options"):
        env.set_options([{}, {"x": 1}])
    env.set_options(None)
    env.set_options([{}, {}])
    assert env.reset().shape == (N, 237)


def _per_array_step(r, reward_terms: bool):
    """What ``step_wait`` returns from the step result ``r``, each array copied to the host on its own: the
    straightforward computation the packed copy must equal bit for bit."""
    obs, final_obs = r.obs.cpu().numpy(), r.final_obs.cpu().numpy()
    done, truncated = r.done.cpu().numpy(), r.truncated.cpu().numpy()
    infos = [{} for _ in range(len(done))]
    if reward_terms:
        terms = {k: v.cpu().numpy() for k, v in r.reward_terms.items()}
        for i, info in enumerate(infos):
            info["reward_terms"] = {k: float(v[i]) for k, v in terms.items()}
    ret, length = r.episode_return.cpu().numpy(), r.episode_length.cpu().numpy()
    for i in np.flatnonzero(done):
        infos[i]["terminal_observation"] = final_obs[i]
        infos[i]["TimeLimit.truncated"] = bool(truncated[i])
        infos[i]["episode"] = {"r": float(ret[i]), "l": int(length[i])}
    return obs, r.reward.cpu().numpy(), done, infos


def _assert_bit_identical(got, want):
    """``got`` (step_wait's four results) equals ``want`` (:func:`_per_array_step`'s) in dtypes, shapes and bytes;
    the episodes' wall-clock ``"t"`` is left out (the two are computed at different times)."""
    for a, b in zip(got[:3], want[:3]):
        assert (a.dtype, a.shape, a.tobytes()) == (b.dtype, b.shape, b.tobytes())
    assert len(got[3]) == len(want[3])
    for info, ref in zip(got[3], want[3]):
        assert info.keys() == ref.keys()
        if "terminal_observation" in ref:
            a, b = info["terminal_observation"], ref["terminal_observation"]
            assert (a.dtype, a.shape, a.tobytes()) == (b.dtype, b.shape, b.tobytes())
            assert type(info["TimeLimit.truncated"]) is bool
            assert info["TimeLimit.truncated"] is ref["TimeLimit.truncated"]
            episode = dict(info["episode"])
            assert type(episode.pop("t")) is float
            assert {k: (type(v), repr(v)) for k, v in episode.items()} == \
                   {k: (type(v), repr(v)) for k, v in ref["episode"].items()}
        if "reward_terms" in ref:
            assert {k: repr(v) for k, v in info["reward_terms"].items()} == \
                   {k: repr(v) for k, v in ref["reward_terms"].items()}


def _recording(env, monkeypatch) -> list:
    """Records each StepResult of ``env`` with its per-array reference, computed right after the step."""
    seen, step = [], env.stepper.step

    def spy(action):
        r = step(action)
        seen.append(_per_array_step(r, env.reward_terms_in_infos))
        return r

    monkeypatch.setattr(env.stepper, "step", spy)
    return seen


@pytest.mark.parametrize("ending", ["truncation", "termination"])
def test_a_step_returns_what_copying_each_array_returned_bit_for_bit(ending, monkeypatch):
    # A step now copies one packed buffer (and the ended envs' rows in a second); SB3 must see the same arrays and
    # infos as when every array was copied on its own.
    options = {"min_pelvis_height": 5.0} if ending == "termination" else None  # every first step is a fall
    env = TocabiSB3VecEnv(N, "cpu", max_episode_steps=2, reward_terms_in_infos=True, env_options=options)
    try:
        seen = _recording(env, monkeypatch)
        env.seed(3)
        env.reset()
        rng = np.random.default_rng(0)
        ended, truncated = [], []
        for _ in range(5):
            got = env.step(rng.uniform(-1.0, 1.0, (N, 13)).astype(np.float32))
            _assert_bit_identical(got, seen[-1])
            ended.append(bool(got[2].all()) if got[2].all() or not got[2].any() else None)
            truncated += [info["TimeLimit.truncated"] for info in got[3] if "terminal_observation" in info]
        # The time limit ends every second step's episodes; the fall every step's.
        assert ended == ([False, True] * 3)[:5] if ending == "truncation" else ended == [True] * 5
        assert all(t is (ending == "truncation") for t in truncated)
    finally:
        env.close()


def test_only_the_ended_envs_terminal_observations_are_fetched_and_they_are_bit_identical(env, monkeypatch):
    # The terminal observation, truncation flag, return and length come from a second copy of the ended rows only:
    # each must land in its own env's info, with nothing cast on the way.
    results = [crafted_step_result(N, 0, [False, True], [False, True], [3, 2 ** 40 + 3]),
               crafted_step_result(N, 1, [True, False], [False, False], [2 ** 24 + 1, 7]),
               crafted_step_result(N, 2, [True, True], [True, False], [5, 2 ** 53 - 1]),
               crafted_step_result(N, 3, [False, False], [False, False], [1, 1])]
    queue = list(results)
    monkeypatch.setattr(env.stepper, "step", lambda action: queue.pop(0))
    env.reset()
    for r in results:
        got = env.step(np.zeros((N, 13), dtype=np.float32))
        _assert_bit_identical(got, _per_array_step(r, reward_terms=True))
    assert not queue


def test_a_step_copies_to_the_host_once_and_again_only_where_an_episode_ended(env, monkeypatch):
    # The docs promise one synchronisation per step; the adapter copied obs, final_obs, done, truncated and reward on
    # their own (five), each of the 13 reward terms too, and the returns and lengths of every env on a done step.
    step = env.stepper.step

    monkeypatch.setattr(env.stepper, "step", lambda action: counting_reads(step(action)))
    monkeypatch.setattr(HostReads, "reads", [])
    env.seed(0)
    env.reset()  # max_episode_steps=2: the second step ends every episode
    zeros = np.zeros((N, 13), dtype=np.float32)
    reads = []
    for _ in range(4):
        HostReads.reads.clear()
        _, _, dones, infos = env.step(zeros)
        reads.append((bool(dones.any()), list(HostReads.reads)))
    assert reads == [(False, ["cpu"]), (True, ["cpu", "cpu"])] * 2
    assert all("terminal_observation" in info and "reward_terms" in info for info in infos)


def test_recipe_trains_two_iterations_with_the_reference_schedule(tmp_path):
    recipe = load_recipe("train_sb3")
    out = tmp_path / "run"
    result = recipe.main(["--out", str(out), "--device", "cpu", "--num_envs", "2", "--iterations", "2",
                          "--n_steps", "4", "--batch_size", "4", "--hidden", "16", "--eval_envs", "2",
                          "--eval_seconds", "0.1"])
    assert result["train"]["env_steps"] == 2 * 2 * 4
    assert (out / "sb3_model.zip").is_file() and result["eval"]["num_envs"] == 2
    _, state = load_policy(out / "policy.pt", "sb3")
    # The scheduled std: halfway through (2 of 2 rollouts done = progress 0) it sits at the end value 0.05.
    np.testing.assert_allclose(state["log_std"].numpy(), math.log(0.05), rtol=1e-6)
    assert recipe.LinearLR(1e-5, 2e-7)(0.5) == pytest.approx(5.1e-6)
    # The gait test ran SB3's own trained policy: the rebuilt network's mean action is that of SB3's saved model
    # (our own zip, written above; the schedules are replaced so that nothing of the recipe is unpickled).
    model = recipe.reference_ppo_class().load(out / "sb3_model.zip", device="cpu",
                     custom_objects={"learning_rate": 0.0, "lr_schedule": recipe.LinearLR(0.0, 0.0)})
    _, act = recipe.load_actor(out / "policy.pt")
    obs = torch.randn(3, 237)
    torch.testing.assert_close(act(obs), model.policy._predict(obs, deterministic=True))


def test_the_sb3_zip_is_written_atomically(tmp_path, monkeypatch):
    # A write that fails part way (a disk full here, a killed call alike) left a zip cut short under the name SB3's
    # tools load; written atomically, no sb3_model.zip appears and the resume point the call wrote first stays.
    import resource

    recipe = load_recipe("train_sb3")
    finish_call = recipe.finish_call

    def disk_full_for_the_zip(*args, also_save, **kwargs):
        def limited(tag):
            soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
            resource.setrlimit(resource.RLIMIT_FSIZE, (1000, hard))  # Python ignores SIGXFSZ: writes fail EFBIG
            try:
                also_save(tag)
            finally:
                resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))

        return finish_call(*args, also_save=limited, **kwargs)

    monkeypatch.setattr(recipe, "finish_call", disk_full_for_the_zip)
    out = tmp_path / "run"
    with pytest.raises(OSError) as info:
        recipe.main(["--out", str(out), "--device", "cpu", "--num_envs", "2", "--iterations", "1", "--n_steps", "4",
                     "--batch_size", "4", "--hidden", "8", "--eval_envs", "0"])
    assert info.value.errno == errno.EFBIG, info.value  # the zip's write hit the limit, not another error
    assert not (out / "sb3_model.zip").exists() and not list(out.glob("*.tmp"))
    assert read_resume(out)["calls"] == 1 and load_policy(out / "policy.pt", "sb3")


def test_recipe_resumes_the_same_run_and_its_schedules(tmp_path):
    # The first call's time is up after one of two iterations; a resumed call trains the second: counters are
    # cumulative, the second call starts from the first call's weights and Adam state, and the schedules' position
    # (progress remaining, which sets the LR and the std) is what one uninterrupted call would have had.
    from tocabi_torchrl.adapters.recipe import TimeUp

    recipe = load_recipe("train_sb3")
    out = tmp_path / "run"
    small = ["--out", str(out), "--device", "cpu", "--num_envs", "2", "--n_steps", "4", "--batch_size", "4",
             "--hidden", "16", "--eval_envs", "0", "--iterations", "2"]
    ref, seen = recipe.reference_ppo_class(), {"progress": [], "lr": [], "total": [], "calls": 0}

    class Spied(ref):
        @classmethod
        def load(cls, *a, **k):  # SB3's load unpickles: a resume builds the model anew instead
            raise AssertionError("a resume must never call PPO.load")

        def learn(self, *a, **k):
            seen["calls"] += 1
            seen["policy"] = {n: v.clone() for n, v in self.policy.state_dict().items()}
            seen["adam"] = [float(s["step"]) for s in self.policy.optimizer.state_dict()["state"].values()]
            return super().learn(*a, **k)

        def train(self):
            seen["progress"].append(self._current_progress_remaining)
            seen["total"].append(self._total_timesteps)
            super().train()
            seen["lr"].append([g["lr"] for g in self.policy.optimizer.param_groups])
            if seen["calls"] == 1:
                raise TimeUp("time is up after the first iteration")

    recipe.reference_ppo_class = lambda: Spied
    first = recipe.main(small)["train"]
    assert (first["iterations"], first["env_steps"], first["calls"]) == (1, 8, 1)
    _, policy1 = load_policy(out / "policy.pt", "sb3")
    # The resume state is tensors and plain values only, with the counters the schedules continue from.
    saved = torch.load(out / "resume" / "state_call1.pt", map_location="cpu", weights_only=True)
    assert (saved["num_timesteps"], saved["n_updates"]) == (8, 3)
    assert len(saved["optimizer"]["param_groups"]) == 2 and all(torch.equal(saved["policy"][k], policy1[k])
                                                                  for k in policy1)
    second = recipe.main([*small, "--resume"])["train"]
    assert (second["iterations"], second["env_steps"], second["calls"]) == (2, 16, 2)
    assert second["train_seconds"] > first["train_seconds"] and second["sb3_num_timesteps"] == 16
    assert seen["progress"] == [0.5, 0.0]  # as in one call of two iterations
    assert seen["total"] == [16, 16]  # learn(left, reset_num_timesteps=False) adds the saved num_timesteps
    lr = recipe.LinearLR(recipe.LR_START, recipe.LR_END)
    assert seen["lr"] == [[lr(0.5), recipe.VALUE_HEAD_LR], [lr(0.0), recipe.VALUE_HEAD_LR]]
    assert all(torch.equal(seen["policy"][k], policy1[k]) for k in policy1)  # continued, not re-initialised
    assert seen["adam"] and all(s == 3 * 2 for s in seen["adam"])  # the first call's 3 epochs x 2 mini-batches
    _, policy2 = load_policy(out / "policy.pt", "sb3")
    np.testing.assert_allclose(policy2["log_std"].numpy(), math.log(0.05), rtol=1e-6)
    assert not all(torch.equal(policy2[k], policy1[k]) for k in policy1)
    assert (out / "policy_call1.pt").is_file() and (out / "sb3_model_call1.zip").is_file()
    with pytest.raises(SystemExit, match="other settings"):
        recipe.main([*small[:-1], "3", "--resume"])


def test_an_interrupted_call_saves_its_resume_state_and_resumes(tmp_path, monkeypatch, capsys):
    # Ctrl-C (KeyboardInterrupt) in the second rollout: the call saves as at TimeUp, skips the gait test and says how
    # to resume; --resume then trains the rest. The top seed also checks that the resumed call's seed + 1 wraps.
    import signal

    recipe = load_recipe("train_sb3")
    real_clock, steps = recipe.TrainingClock, [0]

    class CtrlC(real_clock):
        def __call__(self):
            super().__call__()
            steps[0] += 1
            if steps[0] == 6:  # 4 steps per rollout: the second one
                raise KeyboardInterrupt

    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    monkeypatch.setattr(recipe, "TrainingClock", CtrlC)
    out = tmp_path / "run"
    small = ["--out", str(out), "--device", "cpu", "--num_envs", "2", "--n_steps", "4", "--batch_size", "4",
             "--hidden", "16", "--eval_envs", "2", "--eval_seconds", "0.1", "--iterations", "2",
             "--seed", str(2 ** 32 - 1)]
    first = recipe.main(small)
    assert first["interrupted"] == "KeyboardInterrupt" and "eval" not in first and recipe.exit_status(first) == 130
    assert (first["train"]["iterations"], first["train"]["env_steps"], first["train"]["calls"]) == (1, 12, 1)
    assert (out / "policy.pt").is_file() and read_resume(out)["iterations"] == 1 and not (out / "eval").exists()
    err = capsys.readouterr().err
    assert "sb3: interrupted (KeyboardInterrupt)" in err and "run the same command with --resume" in err
    assert {sig: signal.getsignal(sig) for sig in handlers} == handlers  # only replaced while training
    monkeypatch.setattr(recipe, "TrainingClock", real_clock)
    second = recipe.main([*small, "--resume"])
    assert (second["train"]["iterations"], second["train"]["calls"]) == (2, 2) and "eval" in second
    assert second["train"]["sb3_num_timesteps"] == 16 and "interrupted" not in second


def _sb3_zip_with_payload(zip_path, payload) -> bytes:
    # SB3's own zip with its "data" entry's ep_success_buffer replaced by a serialized object, as SB3 writes one
    # (base64 of a pickle), which SB3's load unpickles.
    import base64
    import io
    import json
    import pickle
    import zipfile

    buffer = io.BytesIO()
    with zipfile.ZipFile(zip_path) as src, zipfile.ZipFile(buffer, "w") as dst:
        for name in src.namelist():
            body = src.read(name)
            if name == "data":
                data = json.loads(body)
                data["ep_success_buffer"] = {":type:": "<class 'collections.deque'>",
                                             ":serialized:": base64.b64encode(pickle.dumps(payload)).decode()}
                body = json.dumps(data).encode()
            dst.writestr(name, body)
    return buffer.getvalue()


@pytest.mark.parametrize("kind", ["sb3_zip", "torch_pickle"])
def test_resume_refuses_a_crafted_state_file_without_running_it(tmp_path, kind):
    # A resume state that unpickles to code (os.system here) is refused before anything is loaded from it: a pickle
    # in SB3's zip layout (the recipe's old state file) and a torch file holding a pickled object alike.
    recipe = load_recipe("train_sb3")
    out, marker = tmp_path / "run", tmp_path / "MARKER"
    small = ["--out", str(out), "--device", "cpu", "--num_envs", "2", "--n_steps", "4", "--batch_size", "4",
             "--hidden", "16", "--eval_envs", "0", "--iterations", "1"]
    recipe.main(small)
    state = out / "resume" / "state_call1.pt"
    if kind == "sb3_zip":
        state.write_bytes(_sb3_zip_with_payload(out / "sb3_model.zip", TouchMarker(marker)))
        expected = r"is a Stable-Baselines3 zip.*start a new --out"
    else:
        torch.save({"num_timesteps": TouchMarker(marker), "policy": {}}, state)
        expected = r"does not load as tensors only.*start a new --out"
    with pytest.raises(SystemExit, match=expected) as refused:
        recipe.main([*small, "--resume"])
    message = str(refused.value)
    assert message.startswith("error: ") and str(state) in message and "\n" not in message
    assert not marker.exists()
    assert read_resume(out)["calls"] == 1 and not (out / "policy_call1.pt").exists()  # nothing ran or was written


def test_resume_loads_the_state_it_checked_not_a_file_replaced_after(tmp_path, monkeypatch):
    # read_resume checked the state file's bytes (an intact zip), then the recipe read the file again: a file
    # replaced in between was what got loaded. The recipe now loads the bytes that were checked.
    recipe = load_recipe("train_sb3")
    out, marker = tmp_path / "run", tmp_path / "ran"
    small = ["--out", str(out), "--device", "cpu", "--num_envs", "2", "--n_steps", "4", "--batch_size", "4",
             "--hidden", "8", "--eval_envs", "0"]
    recipe.main([*small, "--iterations", "1"])
    read_resume = recipe.read_resume

    def checked_then_replaced(*a, **k):
        prior = read_resume(*a, **k)
        torch.save({"num_timesteps": TouchMarker(marker), "policy": {}}, out / prior["state"])
        return prior

    monkeypatch.setattr(recipe, "read_resume", checked_then_replaced)
    second = recipe.main([*small, "--iterations", "1", "--resume"])["train"]
    assert not marker.exists() and second["calls"] == 2


def test_a_switch_that_is_not_a_bool_is_refused():
    # bool("no") is True: reward_terms_in_infos="no" switched the per-env dicts on.
    with pytest.raises(ValueError, match="reward_terms_in_infos must be True or False, got 'no'"):
        TocabiSB3VecEnv(2, "cpu", reward_terms_in_infos="no")


def test_recipe_runs_the_robust_gait_test_and_a_resume_may_test_otherwise(tmp_path, capsys):
    # --eval_test robust: a --preset robust run trained through a library got only the standard test's verdict (and
    # play.py refuses its policy.pt). The option is no training setting: a resume with another test is not refused,
    # and the earlier call's results are kept beside the new ones.
    import json

    recipe = load_recipe("train_sb3")
    out = tmp_path / "run"
    small = ["--out", str(out), "--device", "cpu", "--num_envs", "2", "--iterations", "1", "--n_steps", "4",
             "--batch_size", "4", "--hidden", "8", "--eval_envs", "2", "--eval_seconds", "0.1"]
    result = recipe.main([*small, "--eval_test", "robust"])
    report = json.loads((out / "eval" / "robust.json").read_text())
    assert result["eval"]["test"] == report["test"] == "robust" and not (out / "eval" / "summary.json").exists()
    assert report["checkpoint"] == str(out / "policy.pt") and report["settings"]["num_envs"] == 2
    assert json.loads((out / "result.json").read_text())["eval"]["passes"] == report["passes"]
    printed = capsys.readouterr().out
    assert "robust gait test (0.1 s, 2 robots per case)" in printed and "nominal     survival" in printed
    assert f"results: {out / 'eval' / 'robust.json'}" in printed
    assert "gait test: robust, does not walk yet (report above)" in printed  # 0.1 s walks no 2.6 m
    again = recipe.main([*small, "--resume"])  # the standard test, on the same policy
    assert again["train"]["calls"] == 2 and (out / "eval" / "summary.json").is_file()
    assert (out / "eval_call1" / "robust.json").is_file()  # the first call's, kept
