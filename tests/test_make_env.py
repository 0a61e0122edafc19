"""make_env: the default transformed walking env on the real simulator, both physics backends."""

from __future__ import annotations

import pytest
import torch
from graph_emulation import EmulatedCapture
from torchrl.envs.utils import check_env_specs

from tocabi_torchrl import make_env
from tocabi_torchrl.transforms import REFERENCE_TERMS, TransformSettings


@pytest.fixture(scope="module", params=["warp", "mujoco"])
def backend(request) -> str:
    return request.param


@pytest.fixture(scope="module")
def env(backend):
    return make_env(num_envs=3, device="cpu", seed=0, backend=backend)


def test_check_env_specs(env):
    check_env_specs(env, seed=0)


def test_policy_input_reward_and_terms(env):
    td = env.rollout(12, break_when_any_done=False)
    assert td["next", "observation"].shape == (3, 12, 237)
    assert td["next", "observation"].dtype == torch.float32
    terms = td["next", "reward_terms"]
    assert set(REFERENCE_TERMS) <= set(terms.keys())
    total = sum(terms[k] for k in terms.keys())
    alive = ~td["next", "terminated"]
    torch.testing.assert_close(td["next", "reward"] * alive, total * alive, rtol=1e-5, atol=1e-6)
    assert torch.all(td["next", "reward"] <= 2.4 + 1e-5)
    assert torch.all(td["next", "step_count"][:, -1] >= 1)
    assert ("next", "episode_reward") in td.keys(True)


def test_overrides_reach_env_and_transforms(backend):
    e = make_env(num_envs=2, device="cpu", control_mode="pd", max_episode_steps=7,
                 reward_weights={"qpos": 0.0}, backend=backend, sim_threads=1)
    assert e.base_env.cfg.control.mode == "pd" and e.base_env.cfg.task.max_episode_steps == 7
    assert e.base_env.backend == backend
    td = e.rollout(7, break_when_any_done=False)
    assert torch.all(td["next", "reward_terms", "qpos"] == 0)
    assert td["next", "truncated"][:, -1].all()
    with pytest.raises(TypeError, match="unknown option"):
        make_env(num_envs=2, device="cpu", history_length=3)


def test_reward_weights_reweight_on_top_of_the_defaults_and_switches_must_be_bools():
    from tocabi_torchrl.transforms import TaskReward, TransformConfig

    def weights(env):
        reward = next(t for t in env.transform if isinstance(t, TaskReward))
        return {t.name: t.weight for t in reward.terms}

    default = weights(make_env(num_envs=1, device="cpu", sim_threads=1))
    changed = weights(make_env(num_envs=1, device="cpu", sim_threads=1, reward_weights={"qpos": 0.5}))
    # The default preset's body_vel=0.9 stays: the map used to replace the settings' own (body_vel back to 0.3).
    assert default["body_vel"] == changed["body_vel"] == 0.9 and changed["qpos"] == 0.5
    assert {k: v for k, v in changed.items() if k != "qpos"} == {k: v for k, v in default.items() if k != "qpos"}
    # Terms without body_vel: the settings' own weight reaches only the terms in use (it once raised "weights given
    # for unknown term(s) ['body_vel']", a weight the caller never gave); a weight the caller names stays strict.
    assert weights(make_env(num_envs=1, device="cpu", reward_terms=("qpos", "orientation"))) == {
        "qpos": default["qpos"], "orientation": default["orientation"]}
    from tocabi_torchrl.transforms import CallableTerm

    mine = CallableTerm("body_vel", lambda td, nxt: nxt["base_pos"][:, :1] * 0, weight=2.0)  # one's own, built-in name
    assert weights(make_env(num_envs=1, device="cpu", reward_terms=("qpos", mine)))["body_vel"] == 2.0
    with pytest.raises(KeyError, match=r"unknown term\(s\) \['body_vel'\]"):
        make_env(num_envs=1, device="cpu", reward_terms=("qpos",), reward_weights={"body_vel": 1.0})
    # Scales go on top too: reward_scales={"qpos": 5.0} once dropped the robust preset's body_vel sharpness 8.0.
    reward = next(t for t in make_env(num_envs=1, device="cpu", preset="robust", reward_scales={"qpos": 5.0}).transform
                  if isinstance(t, TaskReward))
    assert {t.name: t.scale for t in reward.terms if t.name in ("qpos", "body_vel")} == {"qpos": 5.0, "body_vel": 8.0}
    for name in ("sync_free_resets", "cuda_graph"):
        with pytest.raises(TypeError, match=f"make_env {name} must be True or False, got 'no'"):
            make_env(num_envs=1, device="cpu", **{name: "no"})
    with pytest.raises(TypeError, match="transforms= takes a TransformSettings"):
        make_env(num_envs=1, device="cpu", transforms=TransformConfig())


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_gpu_transformed_step_never_syncs():
    e = make_env(num_envs=128, device="cuda", seed=0, control_mode="torque")
    td = e.reset()
    action = torch.zeros(128, 13, device="cuda")
    for _ in range(2):  # warm-up: lazy initialisations may sync once
        td = e.step(td.set("action", action))["next"]
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(3):
            td = e.step(td.set("action", action))["next"]
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert td["observation"].shape == (128, 237)



def test_sync_free_resets_match_torchrl_resets():
    """The sync-free reset path gives the same rollout as TorchRL's own (same seeds, falls and resets included)."""
    torch.manual_seed(0)
    actions = torch.rand(40, 3, 13) * 2 - 1
    rollouts, carries = [], []
    for sync_free in (False, True):
        e = make_env(num_envs=3, device="cpu", seed=5, sync_free_resets=sync_free, max_episode_steps=15)
        assert (type(e).__name__ == "SyncFreeResetEnv") == sync_free
        td = e.reset()
        steps, carry = [], []
        for a in actions:
            step, td = e.step_and_maybe_reset(td.set("action", a))
            steps.append(step)
            carry.append(td.exclude("action"))
        rollouts.append(torch.stack(steps, dim=1))
        carries.append(torch.stack(carry, dim=1))
    a, b = rollouts
    assert a["next", "truncated"].any() and a["next", "terminated"].any(), "the comparison must include both resets"
    for key in (("next", "observation"), ("next", "reward"), ("next", "done"), ("next", "step_count"),
                ("next", "episode_reward"), "observation", "episode_step", "step_count"):
        torch.testing.assert_close(a[key], b[key], msg=str(key))
    assert set(carries[0].keys(True, True)) == set(carries[1].keys(True, True))
    for key in carries[0].keys(True, True):
        torch.testing.assert_close(carries[0][key], carries[1][key], msg=str(key))


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("cuda_graph", [False, True])
def test_gpu_step_and_maybe_reset_never_syncs(cuda_graph):
    e = make_env(num_envs=128, device="cuda", seed=0, max_episode_steps=3, cuda_graph=cuda_graph,
                 control_mode="torque")
    td = e.reset()
    action = torch.rand(128, 13, device="cuda") * 2 - 1  # random torques: some robots fall
    for _ in range(3):  # warm-up: lazy initialisations (and the graph capture) may sync once
        _, td = e.step_and_maybe_reset(td.set("action", action))
    assert e.graph_captured == cuda_graph
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(6):  # crosses the 3-step truncation: automatic, masked resets included
            step, td = e.step_and_maybe_reset(td.set("action", action))
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert td["observation"].shape == (128, 237)
    assert bool(step["next", "truncated"].any() or step["next", "terminated"].any())


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.filterwarnings("error:SyncFreeResetEnv")  # a failed capture or an eager fallback fails the test
@pytest.mark.parametrize("preset, mode", [("reference", "joined"), ("tocabilab", "joined"), ("reference", "segmented")])
def test_gpu_cuda_graph_step_matches_eager(preset, mode):
    # The captured step must keep every piece of state moving (phase clock, command ramps, history, step counter,
    # episode draws): any state frozen at its capture value shows up as a difference within a few steps.
    # Short and gentle (24 steps of small residuals: nobody falls), so that GPU contact-order noise between the two
    # envs cannot grow into different episodes; the 7-step truncation still resets every env three times.
    n, steps = 64, 24
    kw = dict(num_envs=n, device="cuda", seed=3, max_episode_steps=7, control_mode="pd_reference",
              transforms=TransformSettings(history=preset))
    eager, graphed = make_env(cuda_graph=False, **kw), make_env(cuda_graph=True, **kw)
    graphed.graph_modes = (mode,)
    gen = torch.Generator(device="cuda").manual_seed(0)
    actions = [(torch.rand(n, 13, device="cuda", generator=gen) * 2 - 1) * 0.3 for _ in range(steps)]
    td_e, td_g = eager.reset(), graphed.reset()
    kept, n_done = [], 0
    for i, action in enumerate(actions):
        out_e, td_e = eager.step_and_maybe_reset(td_e.set("action", action))
        out_g, td_g = graphed.step_and_maybe_reset(td_g.set("action", action.clone()))
        for key in ("observation", "reward", "done", "step_count", "episode_reward", "base_pos", "command"):
            torch.testing.assert_close(out_g["next", key], out_e["next", key], rtol=1e-3, atol=1e-3,
                                       msg=lambda m, i=i, key=key: f"step {i}, next {key}: {m}")
            if key in td_e.keys():  # the carried state holds no reward or done flags of the step just taken
                torch.testing.assert_close(td_g[key], td_e[key], rtol=1e-3, atol=1e-3,
                                           msg=lambda m, i=i, key=key: f"step {i}, carry {key}: {m}")
        assert set(td_g.keys(True)) == set(td_e.keys(True))
        kept.append((out_g["next", "observation"], out_g["next", "observation"].clone()))
        n_done += int(out_e["next", "done"].sum())
    assert graphed.graph_captured and not eager.graph_captured and graphed._step_graph.mode == mode
    assert n_done >= n * (steps // 7), "the 7-step truncation must have reset every env three times"
    # Every step returned its own tensors: later replays did not overwrite earlier outputs.
    for returned, copy in kept:
        assert torch.equal(returned, copy)
    # A new seed drops the graph; after the warm-up it is captured again and the episodes follow the new seed.
    graphed.set_seed(5)
    eager.set_seed(5)
    assert not graphed.graph_captured
    for action in actions[:10]:
        out_e, td_e = eager.step_and_maybe_reset(td_e.set("action", action))
        out_g, td_g = graphed.step_and_maybe_reset(td_g.set("action", action.clone()))
        torch.testing.assert_close(td_g["command"], td_e["command"], rtol=1e-3, atol=1e-3)
        torch.testing.assert_close(td_g["observation"], td_e["observation"], rtol=1e-3, atol=1e-3)
    assert graphed.graph_captured


def test_cuda_graph_option_is_checked():
    with pytest.raises(ValueError, match="needs a CUDA device"):
        make_env(num_envs=2, device="cpu", cuda_graph=True)
    with pytest.raises(ValueError, match="do not combine"):
        make_env(num_envs=2, device="cpu", cuda_graph=True, compile_reward=True)
    env = make_env(num_envs=2, device="cpu", sync_free_resets=True)
    assert not env.cuda_graph and not env.graph_captured  # CPU: the eager sync-free step
    from tocabi_torchrl.envs.autoreset import SyncFreeResetEnv

    with pytest.raises(ValueError, match="graph_warmup"):
        SyncFreeResetEnv(env.base_env, cuda_graph=True, graph_warmup=0)


def test_a_captured_step_is_captured_again_when_a_world_turns_ideal():
    # The reset gives set_randomized_worlds' ideal worlds the nominal robot behind a Python branch, which a CUDA graph
    # freezes: a step captured while every world was randomised kept drawing dynamics for the new ideal worlds.
    from tocabi_torchrl.sim.dynamics_config import DynamicsRandomization

    env = make_env(num_envs=2, device="cpu", seed=0, sync_free_resets=True, max_episode_steps=4,
                   dynamics=DynamicsRandomization(mass_scale=(0.8, 1.2)))
    capturer = EmulatedCapture()
    env.set_cuda_graph(True, capturer=capturer)
    td, action = env.reset(), torch.zeros(2, 13)

    def steps(k):
        nonlocal td
        for _ in range(k):
            _, td = env.step_and_maybe_reset(td.set("action", action))

    steps(3)
    assert env.graph_captured and len(capturer.captures) == 1
    env.base_env.set_randomized_worlds(torch.tensor([True, False]))
    steps(1)
    assert not env.graph_captured  # dropped: the next capture takes the branch as it is now
    steps(3)
    assert env.graph_captured and len(capturer.captures) == 2
    assert float(env.base_env.dynamics.mass_scale[1].max()) == 1.0  # world 1 reset (step 4) as the ideal robot
    env.base_env.set_randomized_worlds(torch.tensor([True, False]))  # the same branch: the capture stays
    steps(1)
    assert env.graph_captured and len(capturer.captures) == 2


def test_graph_wiring_matches_eager_on_cpu():
    # The CUDA-graph path of SyncFreeResetEnv (warm-up count, key check, static input copy, fresh outputs, carry)
    # with an emulated capture: it must reproduce the eager sync-free path exactly, resets included.
    kw = dict(num_envs=3, device="cpu", seed=2, sync_free_resets=True, max_episode_steps=5)
    eager, wired = make_env(**kw), make_env(**kw)
    wired.set_cuda_graph(True, capturer=EmulatedCapture())
    gen = torch.Generator().manual_seed(0)
    td_e, td_w = eager.reset(), wired.reset()
    for i in range(14):
        action = torch.rand(3, 13, generator=gen) * 2 - 1
        out_e, td_e = eager.step_and_maybe_reset(td_e.set("action", action))
        out_w, td_w = wired.step_and_maybe_reset(td_w.set("action", action.clone()))
        assert wired.graph_captured == (i >= 2)  # two eager warm-up calls, then the graph path
        assert set(out_w["next"].keys(True, True)) == set(out_e["next"].keys(True, True))
        assert set(td_w.keys(True, True)) == set(td_e.keys(True, True))
        for key in out_e["next"].keys(True, True):
            torch.testing.assert_close(out_w["next", key], out_e["next", key], rtol=0, atol=0)
        for key in td_e.keys(True, True):
            torch.testing.assert_close(td_w[key], td_e[key], rtol=0, atol=0)
    # Another key layout than the captured one runs eagerly, with a warning, and still steps correctly.
    action = torch.rand(3, 13, generator=gen) * 2 - 1
    out_e, td_e = eager.step_and_maybe_reset(td_e.set("action", action))
    with pytest.warns(UserWarning, match="other keys"):
        out_w, td_w = wired.step_and_maybe_reset(td_w.set("action", action.clone()).set("extra", torch.zeros(3)))
    torch.testing.assert_close(out_w["next", "observation"], out_e["next", "observation"], rtol=0, atol=0)
    wired.set_seed(7)
    assert not wired.graph_captured


def test_preset_is_the_training_preset_as_everywhere_else():
    # make_env(preset="torque") failed with "unknown transforms.preset 'torque'": preset named the transforms' history
    # layout (now transforms.history) here and the training preset on the command line and in make_vec, and
    # "reference" meant both.
    from tocabi_torchrl.config import preset_tree
    from tocabi_torchrl.transforms import TaskReward, TransformSettings

    def weights(env):
        reward = next(t for t in env.transform if isinstance(t, TaskReward))
        return {t.name: t.weight for t in reward.terms}

    for name in ("torque_ideal", "reference"):
        tree = preset_tree(name)
        e = make_env(num_envs=1, device="cpu", seed=0, preset=name, backend="mujoco", max_episode_steps=9)
        cfg = e.base_env.cfg
        assert cfg.control == tree.env.control and cfg.command == tree.env.command and cfg.task.max_episode_steps == 9
        want = weights(make_env(num_envs=1, device="cpu", backend="mujoco", transforms=tree.transforms))
        assert weights(e) == want
    assert weights(e)["body_vel"] != 0.9  # the reference preset's reference weights, not the default's
    with pytest.raises(ValueError, match=r"unknown training preset 'banana'; choose one of \['cpu_smoke', 'default', "
                                         r"'model_based', 'model_based_ideal', 'pd', 'reference', 'robust', 'torque', "
                                         r"'torque_ideal'\]"):
        make_env(num_envs=1, device="cpu", preset="banana")
    with pytest.raises(ValueError, match=r"'tocabilab' is a transforms history layout: pass "
                                         r"transforms=TransformSettings\(history='tocabilab'\)"):
        make_env(num_envs=1, device="cpu", preset="tocabilab")
    with pytest.raises(TypeError, match="preset='torque' or the sections config=/transforms=, not both"):
        make_env(num_envs=1, device="cpu", preset="torque", transforms=TransformSettings())


def test_a_reward_terms_list_that_leaves_out_the_presets_extra_terms_is_refused_by_name():
    # A given list replaced every term, and the robust preset's heading and foot_gap terms were silently dropped.
    from tocabi_torchrl.config import preset_tree
    from tocabi_torchrl.transforms import CallableTerm, TaskReward
    from tocabi_torchrl.transforms.reward_terms import FootGap, HeadingHold
    from tocabi_torchrl.transforms.settings import REFERENCE_TERM_NAMES

    height = CallableTerm("height", lambda td, nxt: nxt["base_pos"][:, 2:3], weight=0.1)
    with pytest.raises(ValueError, match=r"leaves out \['heading', 'foot_gap'\].*transforms.heading_weight 0.3, "
                                         r"transforms.foot_gap_weight 0.3.*extra_reward_terms\(\).*weights to 0"):
        make_env(num_envs=1, device="cpu", preset="robust", reward_terms=(*REFERENCE_TERM_NAMES, height))
    settings = preset_tree("robust").transforms
    extra = settings.extra_reward_terms()
    assert [type(t) for t in extra] == [HeadingHold, FootGap]
    assert [(t.weight, t.name) for t in extra] == [(0.3, "heading"), (0.3, "foot_gap")]
    with pytest.raises(ValueError, match=r"leaves out \['foot_gap'\]"):  # one kept by a term of that name
        settings.transform_config(reward_terms=(*REFERENCE_TERM_NAMES, HeadingHold(weight=1.0)))
    # Kept: the settings' own objects, or the weights at 0 for none; without extra terms any list is taken.
    kept = settings.transform_config(reward_terms=(*REFERENCE_TERM_NAMES, height, *extra)).reward_terms
    assert kept[-3:] == (height, *extra)
    import dataclasses

    off = dataclasses.replace(settings, heading_weight=0.0, foot_gap_weight=0.0)
    assert off.extra_reward_terms() == ()
    assert off.transform_config(reward_terms=("qpos", height)).reward_terms == ("qpos", height)
    assert TransformSettings().transform_config(reward_terms=("qpos",)).reward_terms == ("qpos",)
    # Without reward_terms the settings' list is unchanged: the reference's terms and the extra ones.
    assert settings.transform_config().reward_terms == (*REFERENCE_TERM_NAMES, *extra)
    env = make_env(num_envs=1, device="cpu", preset="robust", reward_terms=(*REFERENCE_TERM_NAMES, height, *extra))
    reward = next(t for t in env.transform if isinstance(t, TaskReward))
    assert [t.name for t in reward.terms][-3:] == ["height", "heading", "foot_gap"]
