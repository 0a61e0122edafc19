"""gymnasium adapter: registration, spaces from the TorchRL specs, gymnasium's own space and data checks, and the
SAME_STEP autoreset, truncation and termination on crafted episodes (CPU, 2 envs)."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_space_limit, data_equivalence
from gymnasium.vector import AutoresetMode
from host_reads import HostReads, counting_reads, crafted_step_result

import tocabi_torchrl.adapters  # noqa: F401  (registers TocabiWalk-v0)
from tocabi_torchrl.adapters import TocabiVectorEnv

N = 2


@pytest.fixture(scope="module")
def envs():
    env = gymnasium.make_vec("TocabiWalk-v0", num_envs=N, device="cpu", numpy=True, max_episode_steps=3)
    yield env
    env.close()


def _zero(envs):
    return np.zeros(envs.action_space.shape, dtype=np.float32)


def test_step_before_reset_and_calls_after_close_are_refused():
    # As gymnasium's own envs: no step before the first reset (there is no observation to act on yet), and nothing
    # after close (the simulator is released). Both used to step silently.
    env = TocabiVectorEnv(N, "cpu", numpy=True)
    zeros = np.zeros((N, 13), dtype=np.float32)
    try:
        for actions in (zeros, torch.zeros(N, 13), np.zeros((N, 12), dtype=np.float32)):  # the order comes first
            with pytest.raises(gymnasium.error.ResetNeeded,
                               match=r"TocabiVectorEnv.step\(\) called before reset\(\): call reset\(\) first"):
                env.step(actions)
        assert env.stepper.env_steps == 0  # nothing was stepped
        env.reset(seed=0)
        env.step(zeros)
    finally:
        env.close()
    for call, name in ((lambda: env.step(zeros), "step"), (lambda: env.reset(seed=0), "reset")):
        with pytest.raises(RuntimeError, match=rf"TocabiVectorEnv.{name}\(\) called after close\(\): the env is "
                                               r"closed .* build a new TocabiVectorEnv"):
            call()
    env.close()  # closing twice is allowed, as gymnasium's envs allow it


def test_make_vec_builds_the_adapter_with_same_step_autoreset(envs):
    assert isinstance(envs.unwrapped, TocabiVectorEnv)
    assert envs.num_envs == N
    assert envs.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP


def test_spaces_match_the_torchrl_specs(envs):
    env = envs.unwrapped.torchrl_env
    obs_spec, act_spec = env.observation_spec["observation"], env.action_spec
    assert envs.single_observation_space.shape == tuple(obs_spec.shape[1:]) == (237,)
    assert envs.observation_space.shape == tuple(obs_spec.shape)
    assert envs.single_action_space.shape == (13,)
    np.testing.assert_array_equal(envs.single_action_space.low, act_spec.space.low[0].numpy())
    np.testing.assert_array_equal(envs.single_action_space.high, act_spec.space.high[0].numpy())
    assert envs.single_action_space.low[-1] == 0.0 and envs.single_action_space.low[0] == -1.0  # phase rate >= 0
    for space, kind in ((envs.single_observation_space, "observation"), (envs.single_action_space, "action")):
        check_space_limit(space, kind)  # gymnasium's own check (warns on a badly scaled bounded space)


def test_reset_and_step_return_gymnasium_types_in_the_spaces(envs):
    obs, info = envs.reset(seed=3)
    assert isinstance(info, dict) and obs.dtype == np.float32 and envs.observation_space.contains(obs)
    action = envs.action_space.sample()
    obs, reward, terminated, truncated, infos = envs.step(action)
    assert envs.observation_space.contains(obs)
    assert reward.shape == (N,) and reward.dtype == np.float32
    assert terminated.dtype == bool and truncated.dtype == bool
    terms = infos["reward_terms"]
    assert len(terms) == 13
    np.testing.assert_allclose(sum(terms.values()), reward, rtol=1e-5, atol=1e-5)


def test_reset_with_a_seed_is_deterministic(envs):
    # gymnasium's env checker asks the same of single envs (check_reset_seed_determinism); data_equivalence is its.
    a, _ = envs.reset(seed=7)
    step_a = envs.step(_zero(envs))[0]
    b, _ = envs.reset(seed=7)
    step_b = envs.step(_zero(envs))[0]
    assert data_equivalence(a, b) and data_equivalence(step_a, step_b)
    # gymnasium's generator is seeded too (check_reset_seed_determinism asks it), and a bad seed is named by the
    # env's own check (int() once took 1.9, True and "1" as 1; [] raised an IndexError).
    from gymnasium.utils.env_checker import check_reset_seed_determinism

    envs.reset(seed=np.int64(3))
    assert envs.np_random_seed == 3
    check_reset_seed_determinism(envs)
    for bad in (1.9, True, "1", []):
        with pytest.raises(ValueError, match="seed"):
            envs.reset(seed=bad)


def test_truncation_at_the_time_limit_resets_in_the_same_step(envs):
    envs.reset(seed=0)
    for _ in range(2):
        obs, _, terminated, truncated, infos = envs.step(_zero(envs))
        assert not truncated.any() and not infos["_final_obs"].any() and not infos["_episode"].any()
        # 0 in rows whose episode goes on, as RecordEpisodeStatistics has it (the running return once sat there).
        assert not infos["episode"]["r"].any() and not infos["episode"]["l"].any()
    obs, _, terminated, truncated, infos = envs.step(_zero(envs))
    assert truncated.all() and not terminated.any()
    assert infos["_final_obs"].all() and infos["_episode"].all()
    np.testing.assert_array_equal(infos["episode"]["l"], [3, 3])
    assert not np.allclose(infos["final_obs"], obs)  # the returned obs is the reset one, not the terminal one
    # A fresh episode: the next step is its first, not a dummy transition.
    _, _, terminated, truncated, infos = envs.step(_zero(envs))
    assert not (terminated | truncated).any() and not infos["_episode"].any()


def test_termination_is_not_truncation_and_returns_the_episode():
    # A pelvis height limit above the robot makes every first step a fall; a 1-step limit makes it also the time
    # limit: termination wins, and truncation stays False.
    env = TocabiVectorEnv(N, "cpu", numpy=False, max_episode_steps=1, env_options={"min_pelvis_height": 5.0})
    try:
        env.reset(seed=1)
        obs, reward, terminated, truncated, infos = env.step(torch.zeros(N, 13))
        assert isinstance(obs, torch.Tensor) and obs.device == env.device
        assert terminated.all() and not truncated.any()
        assert infos["_episode"].all()
        assert torch.equal(infos["episode"]["l"], torch.ones(N, dtype=torch.int64))
        torch.testing.assert_close(infos["episode"]["r"], reward)
        assert not torch.equal(infos["final_obs"], obs)
    finally:
        env.close()


def test_bad_actions_and_options_are_refused(envs):
    envs.reset(seed=0)
    # A complex array stepped with its imaginary part dropped (numpy's ComplexWarning alone).
    for bad in (np.zeros((N, 13), complex), np.zeros((N, 13), bool), torch.zeros(N, 13, dtype=torch.complex64)):
        with pytest.raises(TypeError, match="actions must be real numbers"):
            envs.step(bad)
    with pytest.raises(ValueError, match="actions must have shape"):
        envs.step(np.zeros((N, 12), dtype=np.float32))
    with pytest.raises(ValueError, match="takes no options"):
        envs.reset(options={"x": 1})


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_numpy_mode_refuses_non_finite_actions_naming_the_rows(envs, bad):
    # The actions are on the host already, so the check is free; the env would act on NaN as 0 and clip inf.
    envs.reset(seed=0)
    actions = _zero(envs)
    actions[1, 4] = bad
    with pytest.raises(ValueError, match=r"actions must be finite, but env rows \[1\] hold NaN or inf"):
        envs.step(actions)
    with pytest.raises(ValueError, match=r"env rows \[1\] hold NaN or inf"):
        envs.step(torch.as_tensor(actions))  # a CPU tensor is on the host too
    envs.step(_zero(envs))  # nothing was stepped: the env goes on


@pytest.mark.parametrize("numpy_mode", [False, True], ids=["tensor_mode", "numpy_mode"])
def test_both_modes_check_host_actions_alike_whatever_their_type(numpy_mode):
    # Tensor mode took arrays and CPU tensors too but skipped the finite check numpy mode made: a NaN acted as 0 and
    # an inf as the bound. Shape, type and values are now checked alike in both modes, for every host action.
    env = TocabiVectorEnv(N, "cpu", numpy=numpy_mode)
    try:
        env.reset(seed=0)
        bad = np.zeros((N, 13), dtype=np.float32)
        bad[1, 4], bad[0, 0] = np.nan, -np.inf
        for actions in (bad, bad.astype(np.float64), bad.tolist(), torch.as_tensor(bad)):
            with pytest.raises(ValueError, match=r"actions must be finite, but env rows \[0, 1\] hold NaN or inf"):
                env.step(actions)
        too_large = np.full((N, 13), 1e39)  # finite as float64, inf once cast to the env's float32
        with pytest.raises(ValueError, match=r"env rows \[0, 1\] hold NaN or inf"):
            env.step(too_large)
        for actions in (np.zeros((N, 12), dtype=np.float32), [[0.0] * 13], torch.zeros(N, 12)):
            with pytest.raises(ValueError, match=r"actions must have shape \(2, 13\)"):
                env.step(actions)
        for actions in (np.zeros((N, 13), bool), np.full((N, 13), "0.5"), torch.zeros(N, 13, dtype=torch.bool)):
            with pytest.raises(TypeError, match="actions must be real numbers"):
                env.step(actions)
        assert env.stepper.env_steps == 0  # nothing was stepped
        for actions in (np.zeros((N, 13), dtype=np.float32), [[0] * 13] * N, torch.zeros(N, 13, dtype=torch.float64)):
            obs, *_ = env.step(actions)
            assert isinstance(obs, np.ndarray if numpy_mode else torch.Tensor)
        assert env.stepper.env_steps == 3 * N
    finally:
        env.close()


def test_an_action_that_requires_grad_steps_and_the_next_step_too():
    # The docs' own envs.step(policy(obs)): the action carries the policy's graph, which reached the env's control
    # buffer, and every later step failed, even with zeros and after a reset.
    env = TocabiVectorEnv(N, "cpu")
    policy = torch.nn.Linear(237, 13)
    seen = []
    step = env.stepper.env.step_and_maybe_reset

    def spy(td):
        seen.append(td.get("action").requires_grad)
        return step(td)

    env.stepper.env.step_and_maybe_reset = spy
    try:
        obs, _ = env.reset(seed=0)
        action = policy(obs)
        obs, reward, *_ = env.step(action)
        assert not obs.requires_grad and not reward.requires_grad
        env.step(policy(obs))
        env.step(torch.zeros(N, 13))
        assert seen == [False, False, False]  # detached where the adapters take it
        action.sum().backward()  # the caller's graph is intact
        assert policy.weight.grad is not None
    finally:
        env.close()


def test_gymnasiums_episode_statistics_wrapper_applies_with_the_option_off():
    # The env's own infos["episode"] collided with RecordEpisodeStatistics ("key already exists"); with
    # episode_statistics=False gymnasium's wrapper records them. num_envs may be any integer type, numpy's too.
    from gymnasium.wrappers.vector import RecordEpisodeStatistics

    env = RecordEpisodeStatistics(TocabiVectorEnv(np.int64(N), "cpu", numpy=True, episode_statistics=False,
                                                  max_episode_steps=2))
    try:
        assert env.num_envs == N and type(env.unwrapped.num_envs) is int
        env.reset(seed=0)
        zeros = np.zeros((N, 13), dtype=np.float32)
        _, _, _, _, infos = env.step(zeros)
        assert "episode" not in infos
        _, _, _, truncated, infos = env.step(zeros)
        assert truncated.all() and infos["_episode"].all()
        np.testing.assert_array_equal(infos["episode"]["l"], [2, 2])
        assert set(infos["episode"]) == {"r", "l", "t"} and len(env.return_queue) == N
    finally:
        env.close()
    with pytest.raises(ValueError, match="num_envs must be a positive int .*, got True"):
        TocabiVectorEnv(True, "cpu")


@pytest.mark.parametrize("kwargs, match", [
    ({"render_mode": "human"}, "does not render"),  # said, not silently dropped
    ({"numpy": "no"}, "numpy must be True or False"),  # bool("no") is True
    ({"episode_statistics": "no"}, "episode_statistics must be True or False"),
    ({"vectorization_mode": "sync"}, "is a batched env .* use gymnasium.make_vec"),
])
def test_make_vec_names_what_the_env_cannot_do(kwargs, match):
    with pytest.raises(ValueError, match=match):
        gymnasium.make_vec("TocabiWalk-v0", num_envs=1, device="cpu", **kwargs)
    with pytest.raises(ValueError, match="is a batched env"):
        gymnasium.make("TocabiWalk-v0")


def test_make_vec_imports_the_adapters_itself_with_the_module_prefix():
    env = gymnasium.make_vec("tocabi_torchrl.adapters:TocabiWalk-v0", num_envs=1, device="cpu")
    try:
        assert isinstance(env.unwrapped, TocabiVectorEnv) and env.num_envs == 1
    finally:
        env.close()


def _per_array_step(r, episode_statistics: bool):
    """What numpy mode's ``step`` returns from the step result ``r``, each array copied to the host on its own: the
    straightforward computation the packed copies must equal bit for bit."""
    done = r.done.cpu().numpy()
    infos = {"reward_terms": {k: v.cpu().numpy() for k, v in r.reward_terms.items()},
             "final_obs": r.final_obs.cpu().numpy(), "_final_obs": done}
    if episode_statistics:
        infos["episode"] = {"r": torch.where(r.done, r.episode_return, 0.0).cpu().numpy(),
                            "l": torch.where(r.done, r.episode_length, 0).cpu().numpy()}
        infos["_episode"] = done
    return r.obs.cpu().numpy(), r.reward.cpu().numpy(), r.terminated.cpu().numpy(), r.truncated.cpu().numpy(), infos


def _assert_bit_identical(got, want):
    """``got`` and ``want`` (``step``'s five results) hold arrays of equal dtypes, shapes and bytes under the same
    keys; the done flags are one array in both ``"_final_obs"`` and ``"_episode"``, as before."""
    def flat(x, at=()):
        if isinstance(x, dict):
            return {k: v for key in x for k, v in flat(x[key], (*at, key)).items()}
        if isinstance(x, (tuple, list)):
            return {k: v for i, item in enumerate(x) for k, v in flat(item, (*at, i)).items()}
        return {at: x}

    got, want = flat(got), flat(want)
    assert got.keys() == want.keys()
    for key, b in want.items():
        a = got[key]
        assert type(a) is np.ndarray and a.flags.c_contiguous, key
        assert (a.dtype, a.shape, a.tobytes()) == (b.dtype, b.shape, b.tobytes()), key
    if (4, "_episode") in got:
        assert got[4, "_episode"] is got[4, "_final_obs"]


@pytest.mark.parametrize("episode_statistics", [True, False], ids=["statistics", "no_statistics"])
@pytest.mark.parametrize("ending", ["truncation", "termination", "some_envs"])
def test_numpy_mode_returns_what_copying_each_array_returned_bit_for_bit(ending, episode_statistics, monkeypatch):
    # Numpy mode copies one packed buffer per step (and the ended envs' last observations in a second); it must
    # return the arrays that copying each of them on its own returned, in every row, ended or not.
    options = {"min_pelvis_height": 5.0} if ending == "termination" else None  # every first step is a fall
    env = TocabiVectorEnv(N, "cpu", numpy=True, max_episode_steps=2, env_options=options,
                          episode_statistics=episode_statistics)
    try:
        seen, step = [], env.stepper.step

        def spy(action):
            r = step(action)
            seen.append(_per_array_step(r, episode_statistics))
            return r

        monkeypatch.setattr(env.stepper, "step", spy)
        env.reset(seed=3)
        rng = np.random.default_rng(0)
        if ending == "some_envs":  # one step in, restart env 0 alone: from then on the envs end on different steps
            env.step(np.zeros((N, 13), dtype=np.float32))
            td = env.stepper._td.clone().set("_reset", torch.tensor([[True], [False]]))
            env.stepper._td = env.torchrl_env.reset(td)
        dones = []
        for _ in range(5):
            got = env.step(rng.uniform(-1.0, 1.0, (N, 13)).astype(np.float32))
            _assert_bit_identical(got, seen[-1])
            dones.append(got[4]["_final_obs"].tolist())
        want = {"truncation": [[False, False], [True, True]] * 3, "termination": [[True, True]] * 5,
                "some_envs": [[False, True], [True, False]] * 3}[ending]
        assert dones == want[:5]
    finally:
        env.close()


def test_numpy_mode_puts_each_ended_envs_last_observation_in_its_own_row_bit_for_bit(monkeypatch):
    # The ended envs' rows come from a second copy: each must land in its own row, with nothing cast on the way
    # (NaN payloads, -0.0, a subnormal reward, lengths past 2**24). The rows whose episode goes on are the
    # observation's, as TorchRL's partial reset leaves them.
    results = [crafted_step_result(N, 0, [False, True], [False, True], [3, 2 ** 40 + 3]),
               crafted_step_result(N, 1, [True, False], [False, False], [2 ** 24 + 1, 7]),
               crafted_step_result(N, 2, [True, True], [True, False], [5, 2 ** 53 - 1]),
               crafted_step_result(N, 3, [False, False], [False, False], [1, 1])]
    for r in results:
        r.final_obs = torch.where(r.done.unsqueeze(-1), r.final_obs, r.obs)
    env = TocabiVectorEnv(N, "cpu", numpy=True)
    try:
        queue = list(results)
        monkeypatch.setattr(env.stepper, "step", lambda action: queue.pop(0))
        env.reset(seed=0)
        for r in results:
            got = env.step(np.zeros((N, 13), dtype=np.float32))
            _assert_bit_identical(got, _per_array_step(r, episode_statistics=True))
            assert not np.shares_memory(got[4]["final_obs"], got[0])  # two arrays, as two copies made them
        assert not queue
    finally:
        env.close()


def test_numpy_mode_copies_a_step_to_the_host_once_and_again_only_where_an_episode_ended(envs, monkeypatch):
    # Numpy mode copied each array on its own: obs, reward, both flags, the 13 reward terms, the final observations,
    # the done flags and the episode statistics, some 20 synchronisations a step on a GPU.
    env = envs.unwrapped
    step = env.stepper.step
    monkeypatch.setattr(env.stepper, "step", lambda action: counting_reads(step(action)))
    monkeypatch.setattr(HostReads, "reads", [])
    env.reset(seed=0)  # max_episode_steps=3: every third step ends every episode
    reads = []
    for _ in range(6):
        HostReads.reads.clear()
        *_, infos = env.step(_zero(envs))
        reads.append((bool(infos["_final_obs"].any()), list(HostReads.reads)))
    assert reads == [(False, ["cpu"]), (False, ["cpu"]), (True, ["cpu", "cpu"])] * 2
