"""The default Compose on the mock env: specs, the 237-value input end to end, options, and (GPU) no host syncs."""

from __future__ import annotations

import copy

import pytest
import torch
from mock_env import MockTocabiWalk
from torch.utils._python_dispatch import TorchDispatchMode
from torchrl.envs import Compose, RewardSum, TransformedEnv
from torchrl.envs.utils import check_env_specs, step_mdp

from tocabi_torchrl.transforms import (
    HISTORIES,
    REFERENCE_OBS_LAYOUT,
    REFERENCE_OBS_MEAN,
    REFERENCE_TERMS,
    CallableTerm,
    HistoryLayout,
    JointPosTracking,
    ObsComponent,
    default_transforms,
    transform_config,
)

N = 4


def _env(preset="reference", device="cpu", env_kwargs=None, **overrides) -> TransformedEnv:
    base = MockTocabiWalk(N, device=device, **(env_kwargs or {}))
    return TransformedEnv(base, default_transforms(preset, **overrides))


@pytest.mark.parametrize("preset", list(HISTORIES))
def test_check_env_specs(preset):
    env = _env(preset, env_kwargs={"terminate_prob": 0.3})
    check_env_specs(env, break_when_any_done="both")
    spec = env.observation_spec
    assert spec["observation"].shape == (N, 237)
    assert spec["obs_step"].shape == spec["obs_step_norm"].shape == (N, 37)
    assert set(spec["reward_terms"].keys()) == set(REFERENCE_TERMS)
    assert spec["episode_reward"].shape == spec["step_count"].shape == (N, 1)


@pytest.mark.parametrize("preset", list(HISTORIES))
def test_policy_input_is_the_history_of_normalised_observations_and_actions(preset):
    layout = HISTORIES[preset].history
    env = _env(preset, env_kwargs={"terminate_prob": 0.15, "seed": 3})
    ro = env.rollout(20, break_when_any_done=False)
    # Rebuild each input from the rollout's own per-step data: obs[t] is ("next", obs_step_norm) at t, obs[-1]
    # the reset one; after an env's reset its older entries are its first observation and zero actions.
    for i in range(N):
        obs_seq = [ro[i, 0]["obs_step_norm"]]
        act_seq = [ro[i, 0]["applied_action"]]
        for t in range(20):
            if t > 0 and bool(ro[i, t - 1]["next", "done"]):
                obs_seq, act_seq = [ro[i, t]["obs_step_norm"]], [ro[i, t]["applied_action"]]
            obs_seq.append(ro[i, t]["next", "obs_step_norm"])
            act_seq.append(ro[i, t]["next", "applied_action"])
            tau = len(obs_seq) - 1
            obs = [obs_seq[max(tau - a, 0)] for a in layout.obs_ages]
            act = [act_seq[max(tau - a, 0)] for a in layout.action_ages]
            torch.testing.assert_close(ro[i, t]["next", "observation"], torch.cat(obs + act), msg=f"env {i} t {t}")


def test_episode_return_and_step_counter():
    env = _env(max_episode_steps=3)
    ro = env.rollout(5, break_when_any_done=False)
    assert ro["next", "step_count"][0].squeeze(-1).tolist() == [1, 2, 3, 1, 2]
    assert ro["next", "truncated"][0].squeeze(-1).tolist() == [False, False, True, False, False]
    r = ro["next", "reward"][0].squeeze(-1)
    torch.testing.assert_close(
        ro["next", "episode_reward"][0].squeeze(-1), torch.stack((r[0], r[:2].sum(), r[:3].sum(), r[3], r[3:].sum()))
    )


def test_env_is_the_truncation_clock_unless_a_limit_is_given():
    # default_transforms used to truncate at 8000 steps whatever the env was configured for: an env of
    # 10,000-step episodes composed with it was cut at 8000. By default its StepCounter only counts, as make_env's.
    from tocabi_torchrl.transforms import TransformSettings

    env = _env("tocabilab", env_kwargs={"max_episode_steps": 10_000})
    counter = next(t for t in env.transform if type(t).__name__ == "StepCounter")
    assert counter.max_steps is None
    assert transform_config().max_episode_steps is TransformSettings().transform_config().max_episode_steps is None
    td = env.reset()
    td["step_count"].fill_(7999)  # the StepCounter's own count, as after 7999 steps
    td = env.rand_step(td)
    assert td["next", "step_count"].unique().tolist() == [8000]
    assert not td["next", "truncated"].any()
    # An explicit limit still truncates on top of the env's.
    env = _env(env_kwargs={"max_episode_steps": 10_000}, max_episode_steps=8000)
    td = env.reset()
    td["step_count"].fill_(7999)
    assert env.rand_step(td)["next", "truncated"].all()


def test_overrides_are_config_changes():
    def alive(td, next_td):
        return torch.ones_like(next_td["reward"])

    env = _env(
        reward_terms=("qpos", "body_vel", CallableTerm("alive", alive, weight=0.5)),
        reward_weights={"qpos": 1.0},
        history=HistoryLayout(num_obs=3, stride=1),
        phase_harmonics=2,
        obs_layout=REFERENCE_OBS_LAYOUT + (ObsComponent("base_ang_vel", "base_ang_vel"),),
        normalization="running",
        max_episode_steps=None,
        track_episode_return=False,
    )
    check_env_specs(env)
    spec = env.observation_spec
    assert spec["obs_step"].shape == (N, 37 + 2 + 3)
    assert spec["observation"].shape == (N, 3 * 42 + 2 * 13)
    assert set(spec["reward_terms"].keys()) == {"qpos", "body_vel", "alive"}
    assert "episode_reward" not in spec.keys()
    ro = env.rollout(3)
    terms = ro["next", "reward_terms"]
    torch.testing.assert_close(ro["next", "reward"], terms["qpos"] + terms["body_vel"] + terms["alive"])
    torch.testing.assert_close(terms["qpos"], JointPosTracking(weight=1.0)(ro.exclude("next"), ro["next"]))


def test_preset_errors():
    with pytest.raises(KeyError, match="unknown transforms history layout 'walk'"):
        default_transforms("walk")
    with pytest.raises(TypeError, match="unknown transform option.*'histroy'"):
        default_transforms(histroy=None)
    with pytest.raises(KeyError, match="unknown reward term 'qpoz'"):
        default_transforms(reward_terms=("qpoz",))
    with pytest.raises(ValueError, match="normalization must be one of"):
        transform_config(normalization="vecnorm")
    with pytest.raises(ValueError, match="max_episode_steps"):
        transform_config(max_episode_steps=0)
    with pytest.raises(ValueError, match="needs obs_mean/obs_var"):
        default_transforms(phase_harmonics=2)
    with pytest.raises(TypeError, match="HistoryLayout"):
        transform_config(history=(5, 2))
    with pytest.raises(ValueError, match="stride"):
        transform_config(history=HistoryLayout(num_obs=5, stride=0))
    assert transform_config("tocabilab").history.stride == 1
    assert transform_config("reference").zero_reward_on_terminated


def test_numbers_are_checked_by_name():
    import math

    import numpy as np

    with pytest.raises(ValueError, match=r"obs_clip must be a finite number.*got '5'"):
        transform_config(obs_clip="5")
    with pytest.raises(ValueError, match=r"obs_mean\[1\] must be a finite number.*got nan"):
        transform_config(obs_mean=(0.0, math.nan), obs_var=(1.0, 1.0))
    with pytest.raises(ValueError, match=r"max_episode_steps must be an int.*got 100.0"):
        transform_config(max_episode_steps=100.0)
    cfg = transform_config(obs_clip=np.float32(5.0), max_episode_steps=np.int64(100))  # frozen, converted
    assert type(cfg.obs_clip) is float and type(cfg.max_episode_steps) is int
    assert transform_config(obs_clip=None).obs_clip is None


def test_a_clip_without_a_normaliser_is_refused_by_name():
    # The normaliser clips its output: with normalization "none" there is none, and the clip was silently not
    # applied (the raw observation went on).
    from tocabi_torchrl.config import RunConfig
    from tocabi_torchrl.transforms import TransformSettings
    from tocabi_torchrl.tree import replace_paths

    with pytest.raises(ValueError, match=r"^obs_clip 5.0 clips the normalised observation, and normalization is "
                                         r"'none'.*use normalization 'fixed' or 'running', or obs_clip None"):
        transform_config(normalization="none", obs_clip=5.0)
    with pytest.raises(ValueError, match=r"^transforms.obs_clip 5.0 clips .*transforms.normalization is 'none'"):
        TransformSettings(normalization="none", obs_clip=5.0).validate()
    with pytest.raises(ValueError, match=r"^transforms.obs_clip 0.5 clips"):
        replace_paths(RunConfig(), {"transforms.normalization": "none", "transforms.obs_clip": 0.5}).validate()
    assert transform_config(normalization="none").obs_clip is None
    assert transform_config(normalization="running", obs_clip=5.0).obs_clip == 5.0


def test_a_clip_not_above_zero_is_refused_by_the_config_not_the_normaliser():
    # It passed the config and was refused only when the normaliser was built ("FixedNormalization clip must be
    # > 0"), naming no option.
    from tocabi_torchrl.transforms import TransformSettings

    for clip in (0.0, -1.0, 0):
        with pytest.raises(ValueError, match=r"^obs_clip must be a finite number > 0 .*or None for no clip"):
            transform_config(obs_clip=clip)
        with pytest.raises(ValueError, match=r"^obs_clip must be a finite number > 0"):
            transform_config(normalization="running", obs_clip=clip)
        with pytest.raises(ValueError, match=r"^obs_clip must be a finite number > 0"):
            TransformSettings().transform_config(obs_clip=clip)  # an override goes through the same check
        with pytest.raises(ValueError, match=r"^transforms.obs_clip must be a finite number > 0"):
            TransformSettings(obs_clip=clip).validate()
    assert transform_config(obs_clip=1e-3).obs_clip == 1e-3


def test_statistics_without_a_normaliser_are_refused_by_name():
    # With normalization "none" nothing reads obs_mean/obs_var: they were silently not applied. The running
    # normaliser starts from them, so there they stay allowed.
    from tocabi_torchrl.transforms.presets import _normalization

    stats = {"obs_mean": (0.0,) * 37, "obs_var": (1.0,) * 37}
    with pytest.raises(ValueError, match=r"^obs_mean/obs_var are the normaliser's statistics, and normalization is "
                                         r"'none'.*or leave obs_mean and obs_var None"):
        transform_config(normalization="none", **stats)
    running = transform_config(normalization="running", **stats)
    assert running.obs_mean == stats["obs_mean"]
    assert _normalization(running) is not None
    assert transform_config(normalization="fixed", **stats).obs_var == stats["obs_var"]
    assert _normalization(transform_config(normalization="none")) is None



@pytest.mark.parametrize("normalization", ["fixed", "running"])
def test_statistics_of_another_length_than_the_observation_are_refused_by_the_config(normalization):
    # A wrong length passed the config and failed only once the transforms met the env's spec, with a message naming
    # FixedNormalization (or RunningNormalization) rather than obs_mean/obs_var; mean and var of different lengths
    # were refused only by the normaliser's own check.
    with pytest.raises(ValueError, match=r"^obs_mean/obs_var have 36 values each but the per-step observation has 37 "
                                         r"\(the reference obs_layout: 35 values \+ sin and cos of phase_harmonics=1\)"
                                         r"; pass 37 of each, or leave both None"):
        transform_config(normalization=normalization, obs_mean=(0.0,) * 36, obs_var=(1.0,) * 36)
    with pytest.raises(ValueError, match=r"per-step observation has 39 .*phase_harmonics=2\); pass 39 of each"):
        transform_config(normalization=normalization, phase_harmonics=2, obs_mean=(0.0,) * 37, obs_var=(1.0,) * 37)
    with pytest.raises(ValueError, match=r"^obs_mean has 37 values but obs_var has 36; pass one mean and one "):
        transform_config(normalization=normalization, obs_mean=(0.0,) * 37, obs_var=(1.0,) * 36)
    # The size the config names is the one the env's observation has.
    cfg = transform_config(normalization=normalization, phase_harmonics=2, obs_mean=(0.0,) * 39, obs_var=(1.0,) * 39)
    assert cfg.step_obs_size() == 39
    assert _env(**{"normalization": normalization, "phase_harmonics": 2, "obs_mean": (0.0,) * 39,
                   "obs_var": (1.0,) * 39}).observation_spec["obs_step"].shape == (N, 39)


def test_the_statistics_length_error_says_what_leaving_them_none_gives():
    # The message said 'running' starts from mean 0 and variance 1, but with the reference layout and 1 harmonic it
    # starts from the reference statistics; with another harmonic count 'fixed' has none to fall back on.
    def message(normalization, harmonics, n):
        with pytest.raises(ValueError) as err:
            transform_config(normalization=normalization, phase_harmonics=harmonics, obs_mean=(0.0,) * n,
                             obs_var=(1.0,) * n)
        return str(err.value)

    assert message("running", 1, 36).endswith("pass 37 of each, or leave both None for the reference layout's "
                                              "statistics (normalization 'running' starts from them)")
    assert message("fixed", 1, 36).endswith("pass 37 of each, or leave both None for the reference layout's "
                                            "statistics")
    assert message("running", 2, 37).endswith("pass 39 of each, or leave both None (normalization 'running' then "
                                              "starts from mean 0 and variance 1)")
    assert "leave both None" not in message("fixed", 2, 37)
    # What the messages say is what leaving both None builds.
    from tocabi_torchrl.transforms.presets import _normalization

    reference = _normalization(transform_config(normalization="running"))
    torch.testing.assert_close(reference.mean, torch.as_tensor(REFERENCE_OBS_MEAN, dtype=reference.mean.dtype))
    with pytest.raises(ValueError, match="normalization='fixed' needs obs_mean/obs_var"):
        _normalization(transform_config(normalization="fixed", phase_harmonics=2))


@pytest.mark.parametrize("normalization", ["fixed", "running"])
def test_statistics_for_a_layout_of_another_size_are_refused_naming_them_when_the_env_is_known(normalization):
    # The config cannot size another obs_layout (the env's signals do), so the normaliser names the statistics'
    # option once it meets the env's observation spec.
    layout = REFERENCE_OBS_LAYOUT[:-1]  # 35 values: no foot_torque_y
    stats = {"obs_layout": layout, "obs_mean": (0.0,) * 37, "obs_var": (1.0,) * 37}
    cfg = transform_config(normalization=normalization, **stats)
    assert cfg.step_obs_size() is None
    with pytest.raises(ValueError, match=r"^obs_mean/obs_var have 37 values each but the per-step observation "
                                         r"'obs_step' has 35 \(shape \(4, 35\), set by obs_layout and "
                                         r"phase_harmonics\); pass 35 of each, or leave both None"):
        _env(normalization=normalization, **stats).observation_spec
    assert _env(normalization=normalization, obs_layout=layout, obs_mean=(0.0,) * 35,
                obs_var=(1.0,) * 35).observation_spec["obs_step_norm"].shape == (N, 35)


def test_reset_returns_policy_input_without_stepping():
    env = _env()
    td = env.reset()
    assert td["observation"].shape == (N, 237)
    # Right after reset the history is five copies of the first normalised observation and four zero actions.
    torch.testing.assert_close(td["observation"][:, :185], td["obs_step_norm"].repeat(1, 5))
    assert (td["observation"][:, 185:] == 0).all()
    td = env.step(step_mdp(env.rand_step(td)).set("action", env.action_spec.rand()))
    assert td["next", "observation"].shape == (N, 237)


def test_a_chain_nested_in_another_compose_is_named_and_a_flat_one_works():
    # torchrl's parent lookup fails there with a bare "IndexError: index -1 is out of range" at the first reset.
    from torchrl.envs import Compose

    from tocabi_torchrl.transforms import PrivilegedState

    nested = TransformedEnv(MockTocabiWalk(N), Compose(default_transforms(), PrivilegedState()))
    with pytest.raises(ValueError, match=r"PhaseEncoding sits in a Compose nested inside another Compose.*"
                                         r"Compose\(\*default_transforms\(\), MyTransform\(\)\)"):
        nested.reset()
    flat = TransformedEnv(MockTocabiWalk(N), Compose(*default_transforms(), PrivilegedState()))
    assert flat.reset()["observation"].shape == (N, 237)


@pytest.mark.parametrize("size", [N, N - 1])
def test_a_chain_given_to_a_second_env_is_refused_and_the_first_keeps_it(size):
    # torchrl moves the Compose to the second env without a word. With another batch size the first then failed in
    # StepCounter; with the same one, the second env's resets filled the first's history, silently.
    chain = default_transforms()
    first = TransformedEnv(MockTocabiWalk(N), chain)
    first.reset()
    with pytest.raises(RuntimeError, match=r"belongs to another env already.*default_transforms\(\) for each"):
        TransformedEnv(MockTocabiWalk(size), chain)
    assert first.transform is chain and chain.parent is not None
    assert first.reset()["observation"].shape == (N, 237)
    # A clone belongs to no env yet; a chain its env has let go of may go to another.
    assert TransformedEnv(MockTocabiWalk(size), chain.clone()).reset()["observation"].shape == (size, 237)
    first.transform = default_transforms()
    assert TransformedEnv(MockTocabiWalk(size), chain).reset()["observation"].shape == (size, 237)
    # A nested Compose: torchrl clears the containers all the way down, and they all come back.
    nested = TransformedEnv(MockTocabiWalk(N), Compose(*default_transforms(), Compose(RewardSum(in_keys=["reward"]))))
    with pytest.raises(RuntimeError, match="belongs to another env already"):
        TransformedEnv(MockTocabiWalk(size), nested.transform)
    assert nested.rollout(2)["next", "observation"].shape == (N, 2, 237)
    # A deep copy's chain belongs to the copy once it resets (a weak reference does not survive the copy).
    copied = copy.deepcopy(TransformedEnv(MockTocabiWalk(N), default_transforms()))
    copied.reset()
    with pytest.raises(RuntimeError, match="belongs to another env already"):
        TransformedEnv(MockTocabiWalk(size), copied.transform)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_transformed_step_has_no_host_sync():
    # TODO(make_env): switch the mock for TocabiWalk once it exists.
    env = _env(device="cuda", env_kwargs={"terminate_prob": 0.1})
    td = env.reset()
    action = env.action_spec.rand()
    for _ in range(3):  # warm up: lazy allocations and first-call caches may sync
        td = step_mdp(env.step(td.set("action", action)))
    torch.cuda.synchronize()
    try:
        torch.cuda.set_sync_debug_mode("error")
        for _ in range(5):
            td = step_mdp(env.step(td.set("action", action)))
    finally:
        torch.cuda.set_sync_debug_mode("default")
    torch.cuda.synchronize()
    assert td["observation"].shape == (N, 237)
    assert td["observation"].device.type == "cuda"


class _HostSyncOps(TorchDispatchMode):
    """Records ops that synchronise with the host on CUDA (a CPU stand-in for set_sync_debug_mode): reading a value
    (item/bool), data-dependent shapes (nonzero, boolean-mask indexing, masked_select, unique), and tensors made from
    host data (lift_fresh: torch.tensor(list) inside the loop is a blocking host-to-device copy on CUDA)."""

    OPS = {"_local_scalar_dense", "is_nonzero", "nonzero", "masked_select", "unique", "_unique2", "lift_fresh"}

    def __init__(self):
        super().__init__()
        self.hits: list[str] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func.overloadpacket.__name__
        bool_index = name in ("index", "index_put", "index_put_") and any(
            isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in (args[1] if len(args) > 1 else ())
        )
        if name in self.OPS or bool_index:
            self.hits.append(name)
        return func(*args, **(kwargs or {}))


def test_step_and_transform_reset_issue_no_host_sync_ops_cpu_proxy():
    x = torch.randn(8)
    with _HostSyncOps() as probe:  # the detector sees what would sync on CUDA
        x.sum().item()
        x[x > 0]
        torch.tensor([1.0, 2.0])
    assert {"_local_scalar_dense", "lift_fresh"} <= set(probe.hits)
    assert "nonzero" in probe.hits or "index" in probe.hits
    env = _env(env_kwargs={"terminate_prob": 0.2})
    td = env.reset()
    action = env.action_spec.rand()
    for _ in range(3):
        td = step_mdp(env.step(td.set("action", action)))
    with _HostSyncOps() as ops:
        for _ in range(3):
            td = step_mdp(env.step(td.set("action", action)))
    assert ops.hits == []
    # The transforms' own partial-reset path (TorchRL's reset bookkeeping around it is not ours).
    td_in = td.clone().set("_reset", torch.tensor([[True], [False], [True], [False]]))
    td_reset = env.base_env._reset(td_in)
    with _HostSyncOps() as ops:
        env.transform._reset(td_in, td_reset)
    assert ops.hits == []


def test_the_config_names_the_reference_terms_in_their_order():
    # transforms.settings holds the names so that the config checks a term without the terms' torch code.
    from tocabi_torchrl.transforms.settings import REFERENCE_TERM_NAMES

    assert REFERENCE_TERM_NAMES == tuple(REFERENCE_TERMS)


def test_reward_weights_have_one_field_per_term_whose_help_gives_its_reference_weight():
    # RewardWeights (transforms.reward_weights) is the command line's --transforms.reward_weights.<term>; the help
    # text of each field (its docstring) quotes the term's reference weight, which lives with the torch code.
    import dataclasses
    import inspect
    import re

    from tocabi_torchrl.transforms.reward_terms import reference_terms
    from tocabi_torchrl.transforms.settings import RewardWeights

    assert tuple(f.name for f in dataclasses.fields(RewardWeights)) == tuple(REFERENCE_TERMS)
    docs = dict(re.findall(r"\n    (\w+): float \| None = [^\n]+\n    \"\"\"([^\"]+)\"\"\"",
                inspect.getsource(RewardWeights)))
    for term in reference_terms():
        assert f"(reference {term.weight:g})" in docs[term.name], term.name
    assert RewardWeights().as_map() == {"body_vel": 0.9}  # the default preset's tripled velocity term
    with pytest.raises(ValueError, match=r"transforms.reward_weights.qpos must be a finite number"):
        RewardWeights(qpos=float("inf")).as_map()


def test_the_heading_hold_term_rewards_facing_the_start_heading_and_is_off_by_default():
    import math

    from tensordict import TensorDict

    from tocabi_torchrl.transforms.reward_terms import HeadingHold
    from tocabi_torchrl.transforms.settings import REFERENCE_TERM_NAMES, TransformSettings

    env = _env(reward_terms=(*REFERENCE_TERM_NAMES, HeadingHold(weight=0.3, scale=20.0)))
    nxt = env.rollout(3)["next"]
    yaw = nxt["base_rpy"][..., 2:3]
    assert yaw.abs().max() > 0.01  # the mock's pelvis turns, so the kernel is tested away from its peak
    torch.testing.assert_close(nxt["reward_terms", "heading"], 0.3 * torch.exp(-20.0 * yaw.square()))
    # Symmetric: a turn to either side costs the same.
    term = HeadingHold(weight=1.0, scale=20.0)
    rpy = torch.tensor([[0.0, 0.0, 0.1], [0.0, 0.0, -0.1], [0.0, 0.0, 0.0]])
    values = term(TensorDict({}, [3]), TensorDict({"base_rpy": rpy}, [3])).flatten()
    torch.testing.assert_close(values, torch.tensor([math.exp(-0.2), math.exp(-0.2), 1.0]))
    # The run config: 0 (the default) adds no term, a weight adds it after the reference's 13.
    assert all(not isinstance(t, HeadingHold) for t in TransformSettings().transform_config().reward_terms)
    terms = TransformSettings(heading_weight=0.3, heading_scale=10.0).transform_config().reward_terms
    assert terms[:13] == REFERENCE_TERM_NAMES and terms[13] == HeadingHold(weight=0.3, scale=10.0)
    for name, bad in (("heading_weight", -0.1), ("heading_weight", float("nan")), ("heading_scale", 0.0),
                      ("heading_scale", "20"), ("heading_weight", True)):
        with pytest.raises(ValueError, match=f"transforms.{name} must be a finite number"):
            TransformSettings(**{name: bad}).validate()


def test_the_foot_gap_term_pays_for_feet_apart_in_the_heading_frame_and_is_off_by_default():
    import doctest

    from tensordict import TensorDict

    from tocabi_torchrl.transforms import reward_terms
    from tocabi_torchrl.transforms.reward_terms import FootGap
    from tocabi_torchrl.transforms.settings import REFERENCE_TERM_NAMES, TransformSettings

    runner = doctest.DocTestRunner()
    for test in doctest.DocTestFinder().find(FootGap, "FootGap", globs={"FootGap": FootGap}):
        runner.run(test)
    assert runner.summarize(verbose=False).failed == 0 and runner.tries >= 3
    # In the env: the mock's feet sit 0.25 m apart (± noise) and its pelvis turns a little.
    env = _env(reward_terms=(*REFERENCE_TERM_NAMES, FootGap(weight=0.2, min_gap=0.3)))
    nxt = env.rollout(3)["next"]
    feet, yaw = nxt["foot_pos"], nxt["base_rpy"][..., 2:3]
    d = (feet[..., 0, 1:2] - feet[..., 1, 1:2]) * torch.cos(yaw) - (feet[..., 0, 0:1] - feet[..., 1, 0:1]) * torch.sin(
        yaw)
    expected = 0.2 * torch.exp(-((0.3 - d).clamp_min(0.0) / 0.05).square())
    torch.testing.assert_close(nxt["reward_terms", "foot_gap"], expected)
    assert (expected < 0.2).any()  # a min_gap above the mock's 0.25 m: the kernel is tested below its plateau
    # The gap is measured across the heading: the same feet turned with the pelvis keep their value; crossed feet
    # (the left one right of the right one) and feet side by side at the sole width get next to nothing.
    term = FootGap(weight=1.0, min_gap=0.2)
    psi = torch.tensor(0.7)
    turn = torch.tensor([[torch.cos(psi), -torch.sin(psi)], [torch.sin(psi), torch.cos(psi)]])
    left, right = torch.tensor([0.05, 0.09]), torch.tensor([-0.05, -0.09])  # 0.18 m apart, facing +x
    feet = torch.zeros(4, 2, 3)
    feet[0, :, :2] = torch.stack([left, right])
    feet[1, :, :2] = torch.stack([turn @ left, turn @ right])
    feet[2, :, :2] = torch.stack([right, left])  # crossed
    feet[3, :, 1] = torch.tensor([0.3, 0.0])  # 0.3 m apart: the full term
    rpy = torch.zeros(4, 3)
    rpy[1, 2] = psi
    values = term(None, TensorDict({"foot_pos": feet, "base_rpy": rpy}, [4])).flatten()
    torch.testing.assert_close(values[0], values[1])
    assert values[3] == 1.0 and values[2] < 1e-6 and 0.8 < values[0] < 0.9  # 0.18 m: exp(-0.16)
    # The run config: 0 (the default) adds no term; a weight adds it after the reference's 13 (and the heading term).
    assert all(not isinstance(t, FootGap) for t in TransformSettings().transform_config().reward_terms)
    settings = TransformSettings(heading_weight=0.3, foot_gap_weight=0.2, foot_gap_min=0.22)
    terms = settings.transform_config().reward_terms
    assert terms[:13] == REFERENCE_TERM_NAMES and terms[14] == FootGap(weight=0.2, min_gap=0.22)
    for name, bad in (("foot_gap_weight", -0.1), ("foot_gap_weight", float("inf")), ("foot_gap_min", 0.0),
                      ("foot_gap_min", "0.2"), ("foot_gap_weight", True)):
        with pytest.raises(ValueError, match=f"transforms.{name} must be a finite number"):
            TransformSettings(**{name: bad}).validate()
    with pytest.raises(ValueError, match="min_gap"):
        FootGap(weight=1.0, min_gap=-0.1)
    assert "FootGap" in reward_terms.__all__


def test_a_reward_scale_sharpens_its_term_and_bad_scales_are_named():
    from tocabi_torchrl.transforms.reward_terms import BodyVelTracking
    from tocabi_torchrl.transforms.settings import TransformSettings

    env = _env(reward_scales={"body_vel": 8.0})
    ro = env.rollout(3)
    nxt = ro["next"]
    err = (nxt["base_lin_vel"][..., :2] - nxt["command"]).square().sum(-1, keepdim=True)
    torch.testing.assert_close(nxt["reward_terms", "body_vel"], 0.3 * torch.exp(-8.0 * err))
    torch.testing.assert_close(nxt["reward_terms", "body_vel"],
                               BodyVelTracking(scale=8.0)(ro.exclude("next"), nxt))
    assert BodyVelTracking().scale == 3.0  # the default term is not changed by a config that sharpens a copy
    # The run config's field: None is the reference's kernel, a number sharpens it.
    assert TransformSettings().transform_config().reward_scales == {}
    assert TransformSettings(body_vel_scale=8.0).transform_config().reward_scales == {"body_vel": 8.0}
    for bad in (0.0, -1.0, float("inf"), "8", True):
        with pytest.raises(ValueError, match="transforms.body_vel_scale must be a finite number > 0"):
            TransformSettings(body_vel_scale=bad).validate()
    with pytest.raises(ValueError, match=r"reward_scales\['body_vel'\] must be a finite number > 0"):
        transform_config(reward_scales={"body_vel": float("nan")})
    with pytest.raises(KeyError, match=r"reward_scales given for term\(s\) \['qpoz'\] that are not in use"):
        default_transforms(reward_scales={"qpoz": 2.0})
    with pytest.raises(ValueError, match="has no kernel scale"):
        default_transforms(reward_terms=("qpos", CallableTerm("alive", lambda td, n: n["reward"])),
                           reward_scales={"alive": 2.0})
