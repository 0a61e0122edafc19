"""Sensor biases and noise (transforms/sensor_noise.py): the draws' distributions, their keys (per world, episode and
step), where they land (the policy's observation, never the raw signals the rewards read), the config, and on a
GPU a captured step that stays sync-free across resets."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
import torch
from mock_env import MockTocabiWalk
from tensordict import TensorDict
from torchrl.envs import TransformedEnv

from tocabi_torchrl import make_env
from tocabi_torchrl.config import RunConfig, config_from_dict, to_dict
from tocabi_torchrl.transforms import (
    REFERENCE_OBS_LAYOUT,
    BaseEulerAngles,
    ObservationAssembly,
    SensorNoise,
    SensorNoiseConfig,
    TransformSettings,
    default_transforms,
)
from tocabi_torchrl.transforms.sensor_noise import SENSORS, sensor_biases, sensor_noise
from tocabi_torchrl.tree import replace_paths

LAB = SensorNoiseConfig.tocabi_lab()
N_DRAWS = 100_000


def _ids(n: int) -> torch.Tensor:
    return torch.arange(n, dtype=torch.int64)


# ---------------------------------------------------------------------------------------------------- config
def test_config_is_off_by_default_and_holds_the_lab_numbers():
    assert not SensorNoiseConfig().enabled and SensorNoiseConfig().perturbed() == ()
    assert not TransformSettings().sensor_noise.enabled
    assert LAB.joint_pos_bias == math.pi / 100 and LAB.base_rpy_bias == math.pi / 150
    assert (LAB.foot_force_bias, LAB.foot_torque_bias) == (100.0, 10.0)
    assert LAB.noise("joint_pos") == (0.00016 / 3, 0.00016) and LAB.noise("joint_vel") == (0.0, None)
    assert LAB.perturbed() == ("joint_pos", "base_rpy", "foot_force", "foot_torque")
    assert not SensorNoiseConfig(joint_pos_noise_clip=1.0).enabled  # a clip alone changes nothing


@pytest.mark.parametrize(("field", "value", "message"), [
    ("joint_pos_bias", -0.1, "joint_pos_bias must be a finite number >= 0"),
    ("foot_force_bias", float("nan"), "foot_force_bias must be a finite number >= 0"),
    ("joint_vel_noise_std", True, "joint_vel_noise_std must be a finite number >= 0"),
    ("joint_pos_noise_clip", 0.0, "joint_pos_noise_clip must be a finite number > 0, or None"),
    # Accepted, and then an observed angle of 3.65 rad: one 2π turn does not wrap a bias of 10 rad back.
    ("base_rpy_bias", 10.0, r"base_rpy_bias must be a finite number in \[0, 3.14159"),
])
def test_config_refuses_bad_values_by_path(field, value, message):
    with pytest.raises(ValueError, match=f"transforms.sensor_noise.{message}"):
        SensorNoiseConfig(**{field: value})
    with pytest.raises(ValueError, match=message):
        replace_paths(RunConfig(), {f"transforms.sensor_noise.{field}": value})


def test_config_round_trips_with_the_run_config():
    cfg = replace_paths(RunConfig(), {"transforms.sensor_noise": LAB})
    cfg.validate()
    data = json.loads(json.dumps(to_dict(cfg)))
    assert data["transforms"]["sensor_noise"]["joint_pos_noise_clip"] == 0.00016
    back = config_from_dict(data)
    assert back.transforms.sensor_noise == LAB and back == cfg
    # A file saved before the section existed reads back with the section off.
    del data["transforms"]["sensor_noise"]
    assert config_from_dict(data).transforms.sensor_noise == SensorNoiseConfig()
    assert cfg.transforms.transform_config().sensor_noise == LAB


def test_a_section_given_as_none_or_a_dict_is_named_or_built():
    # make_env(sensor_noise=None) and TransformSettings(sensor_noise=None).validate() ended in AttributeError.
    from tocabi_torchrl.transforms import KickRelax, TransformConfig, TransformSettings

    for make in (lambda: make_env(2, "cpu", sensor_noise=None), lambda: TransformConfig(sensor_noise=None),
                 lambda: TransformSettings(sensor_noise=None).validate()):
        with pytest.raises(ValueError, match=r"sensor_noise must be a SensorNoiseConfig.*got None; for none, give "
                                             r"SensorNoiseConfig\(\)"):
            make()
    with pytest.raises(ValueError, match="kick_relax must be a KickRelax or a dict of its options, got 3"):
        TransformConfig(kick_relax=3)
    # A dict of options, as an env section takes one: the section it names.
    assert TransformConfig(sensor_noise={"joint_pos_bias": 0.1}).sensor_noise == SensorNoiseConfig(joint_pos_bias=0.1)
    assert TransformConfig(kick_relax={"seconds": 1.5}).kick_relax == KickRelax(seconds=1.5)
    names = [type(t).__name__ for t in make_env(2, "cpu", sensor_noise={"joint_pos_bias": 0.1}).transform]
    assert "SensorNoise" in names


def test_off_adds_no_transform():
    for chain in (default_transforms(), default_transforms(sensor_noise=SensorNoiseConfig())):
        assert not any(isinstance(t, SensorNoise) for t in chain)
    chain = default_transforms(sensor_noise=LAB)
    names = [type(t).__name__ for t in chain]
    assert names.index("SensorNoise") == names.index("ObservationAssembly") + 1
    assert names.index("SensorNoise") + 1 == names.index("FixedNormalization")


def test_transform_refuses_what_it_cannot_do():
    with pytest.raises(ValueError, match="perturbs nothing"):
        SensorNoise(SensorNoiseConfig())
    with pytest.raises(ValueError, match=r"perturbs \['base_rpy'\], which the observation layout does not read"):
        SensorNoise(SensorNoiseConfig(base_rpy_bias=0.1), layout=REFERENCE_OBS_LAYOUT[1:])
    env = TransformedEnv(MockTocabiWalk(2), default_transforms(sensor_noise=LAB))
    with pytest.raises(TypeError, match="keys its random numbers on the env's counters"):
        env.reset()
    # After the normalisation the noise reached nothing the policy saw (its input equal to the noiseless one),
    # silently.
    from torchrl.envs import Compose

    from tocabi_torchrl.transforms import FixedNormalization, ObsActionHistory, PhaseEncoding

    late = Compose(PhaseEncoding(), BaseEulerAngles(), ObservationAssembly(), FixedNormalization(), SensorNoise(LAB),
                   ObsActionHistory())
    with pytest.raises(ValueError, match="SensorNoise comes after FixedNormalization, which builds the policy input"):
        TransformedEnv(make_env(num_envs=2, device="cpu").base_env, late).reset()
    # A transform that rewrites obs_step in place passes the noise on: that place is fine.
    from torchrl.envs import ClipTransform

    clipped = Compose(PhaseEncoding(), BaseEulerAngles(), ObservationAssembly(),
                      ClipTransform(in_keys=["obs_step"], out_keys=["obs_step"], low=-100.0, high=100.0),
                      SensorNoise(LAB), FixedNormalization(), ObsActionHistory())
    assert TransformedEnv(make_env(num_envs=2, device="cpu").base_env, clipped).reset()["observation"].shape == (2, 237)
    # A transform in front that only copies obs_step (a clean copy for a critic or a log) is fine too, while the
    # policy input is built behind the noise (it was refused as "comes after CatTensors").
    from torchrl.envs import CatTensors

    copied = Compose(PhaseEncoding(), BaseEulerAngles(), ObservationAssembly(),
                     CatTensors(in_keys=["obs_step"], out_key="obs_clean", del_keys=False), SensorNoise(LAB),
                     FixedNormalization(), ObsActionHistory())
    td = TransformedEnv(make_env(num_envs=2, device="cpu").base_env, copied).reset()
    assert td["observation"].shape == (2, 237) and not torch.equal(td["obs_clean"], td["obs_step"])
    # Behind the normalisation, a log copy reading obs_step behind the noise does not make the place right: the
    # policy input was built in front.
    logged = Compose(PhaseEncoding(), BaseEulerAngles(), ObservationAssembly(), FixedNormalization(), SensorNoise(LAB),
                     CatTensors(in_keys=["obs_step"], out_key="obs_log", del_keys=False), ObsActionHistory())
    with pytest.raises(ValueError, match="SensorNoise comes after FixedNormalization, which builds the policy input"):
        TransformedEnv(make_env(num_envs=2, device="cpu").base_env, logged).reset()
    # Behind a copy alone, with nothing behind reading obs_step, the noise reaches nothing either.
    alone = Compose(PhaseEncoding(), BaseEulerAngles(), ObservationAssembly(),
                    CatTensors(in_keys=["obs_step"], out_key="obs_copy", del_keys=False), SensorNoise(LAB))
    with pytest.raises(ValueError, match="after CatTensors, which reads 'obs_step' already, and nothing behind it"):
        TransformedEnv(make_env(num_envs=2, device="cpu").base_env, alone).reset()



def test_a_layout_other_than_the_assemblys_is_refused():
    # Joint velocities before positions (same width): the joint-position bias and noise landed on the velocity
    # columns, without a word.
    from torchrl.envs import Compose

    from tocabi_torchrl.transforms import ObsComponent, PhaseEncoding

    swapped = list(REFERENCE_OBS_LAYOUT)
    swapped[1], swapped[2] = swapped[2], swapped[1]
    chain = Compose(PhaseEncoding(), BaseEulerAngles(), ObservationAssembly(tuple(swapped)), SensorNoise(LAB))
    with pytest.raises(ValueError, match=r"SensorNoise was given a layout \(blocks \['base_rpy', 'leg_joint_pos'.*"
                                         r"other than that of the ObservationAssembly in front of it"):
        TransformedEnv(make_env(num_envs=2, device="cpu").base_env, chain).reset()
    # The assembly's layout passed on is fine, and so is the same one with other block names.
    renamed = tuple(ObsComponent(f"block{i}", c.key, c.index) for i, c in enumerate(swapped))
    for layout in (tuple(swapped), renamed):
        chain = Compose(PhaseEncoding(), BaseEulerAngles(), ObservationAssembly(tuple(swapped)),
                        SensorNoise(LAB, layout))
        assert TransformedEnv(make_env(num_envs=2, device="cpu").base_env, chain).reset()["obs_step"].shape == (2, 37)

# ------------------------------------------------------------------------------------------- distributions
@pytest.mark.parametrize("signal", ["joint_pos", "base_rpy", "foot_force", "foot_torque"])
def test_bias_is_uniform_in_its_range_and_differs_between_worlds(signal):
    half = LAB.bias(signal)
    ids = _ids(N_DRAWS)
    b = sensor_biases(LAB, 0, ids, torch.ones(N_DRAWS, dtype=torch.int64))[signal]
    assert b.shape == (N_DRAWS, *SENSORS[signal]) and b.dtype == torch.float32
    flat = b.flatten(1)
    assert float(flat.abs().max()) <= half
    assert float(flat.max()) > 0.999 * half and float(flat.min()) < -0.999 * half
    sd = half / math.sqrt(3.0)
    assert float(flat.mean(0).abs().max()) < 5 * sd / math.sqrt(N_DRAWS)  # each element centred
    torch.testing.assert_close(flat.std(0), torch.full((flat.shape[1],), sd), rtol=0.01, atol=0)
    # Worlds, elements, episodes and seeds all draw different numbers.
    assert torch.unique(flat[:, 0]).numel() > 0.99 * N_DRAWS
    assert abs(float(torch.corrcoef(flat[:, :2].T)[0, 1])) < 0.02
    other_episode = sensor_biases(LAB, 0, ids, torch.full((N_DRAWS,), 2))[signal]
    other_seed = sensor_biases(LAB, 1, ids, torch.ones(N_DRAWS, dtype=torch.int64))[signal]
    assert abs(float(torch.corrcoef(torch.stack((flat[:, 0], other_episode.flatten(1)[:, 0])))[0, 1])) < 0.02
    assert not torch.equal(other_seed, b)


def test_draws_of_a_world_do_not_depend_on_the_others():
    ids, episode, step = _ids(64), torch.arange(64) % 5, torch.arange(64) * 7
    full_b, full_n = sensor_biases(LAB, 3, ids, episode), sensor_noise(LAB, 3, ids, episode, step)
    pick = torch.tensor([5, 17, 40])
    part_b = sensor_biases(LAB, 3, ids[pick], episode[pick])
    part_n = sensor_noise(LAB, 3, ids[pick], episode[pick], step[pick])
    for name in part_b:
        assert torch.equal(part_b[name], full_b[name][pick])
    assert torch.equal(part_n["joint_pos"], full_n["joint_pos"][pick])
    # A signal's draws do not move when another signal is switched on or off (a stream per signal).
    alone = sensor_biases(SensorNoiseConfig(joint_pos_bias=LAB.joint_pos_bias), 3, ids, episode)
    assert torch.equal(alone["joint_pos"], full_b["joint_pos"])


def test_noise_is_normal_clipped_and_fresh_every_step():
    sigma, clip = LAB.noise("joint_pos")
    ids = _ids(N_DRAWS // 10)
    ep = torch.ones_like(ids)
    z = sensor_noise(SensorNoiseConfig(joint_pos_noise_std=sigma), 0, ids, ep, torch.full_like(ids, 4))["joint_pos"]
    flat = z.flatten() / sigma  # 330,000 standard normals
    assert abs(float(flat.mean())) < 5 / math.sqrt(flat.numel())
    assert abs(float(flat.std()) - 1.0) < 0.01
    assert abs(float((flat.abs() < 1).float().mean()) - 0.6827) < 0.005
    assert float(flat.abs().max()) > 4.0  # the unclipped tails are there
    clipped = sensor_noise(LAB, 0, ids, ep, torch.full_like(ids, 4))["joint_pos"]
    assert float(clipped.abs().max()) <= clip
    at_clip = float((clipped.abs() == clip).float().mean())
    assert 0.0015 < at_clip < 0.0040  # P(|Z| > 3) = 0.0027
    torch.testing.assert_close(clipped, z.clamp(-clip, clip), rtol=0, atol=0)  # the same draws, clipped
    # A step later, another episode: other numbers; the same key: the same numbers.
    later = sensor_noise(LAB, 0, ids, ep, torch.full_like(ids, 5))["joint_pos"]
    other_episode = sensor_noise(LAB, 0, ids, ep + 1, torch.full_like(ids, 4))["joint_pos"]
    assert abs(float(torch.corrcoef(torch.stack((clipped.flatten(), later.flatten())))[0, 1])) < 0.01
    assert abs(float(torch.corrcoef(torch.stack((clipped.flatten(), other_episode.flatten())))[0, 1])) < 0.01
    assert torch.equal(clipped, sensor_noise(LAB, 0, ids, ep, torch.full_like(ids, 4))["joint_pos"])
    vel = sensor_noise(SensorNoiseConfig(joint_vel_noise_std=0.5), 0, ids, ep, torch.full_like(ids, 4))
    assert set(vel) == {"joint_vel"} and abs(float(vel["joint_vel"].std()) - 0.5) < 0.01


# ------------------------------------------------------------------------------------------------ in the env
def _noise_stage(env) -> SensorNoise:
    return next(t for t in env.transform if isinstance(t, SensorNoise))


def _clean_obs_step(td) -> torch.Tensor:
    """The observation the true signals give: the default chain's first stages on a copy of ``td``."""
    t = td.select("base_quat", *(c.key for c in REFERENCE_OBS_LAYOUT if c.key != "base_rpy")).clone()
    BaseEulerAngles()._call(t)
    return ObservationAssembly(REFERENCE_OBS_LAYOUT)._call(t)["obs_step"]


def _check_observed_perturbation(env, td, atol=1e-6) -> None:
    """``td["obs_step"]`` = the true signals' observation + each world's bias + the noise of its current (episode,
    step), column by column (the Euler angles modulo 2π)."""
    base, stage = env.base_env, _noise_stage(env)
    cfg = stage.config
    want = torch.zeros_like(td["obs_step"])
    biases = sensor_biases(cfg, base._seed_t, base._env_ids, base.episode_count)
    noises = sensor_noise(cfg, base._seed_t, base._env_ids, base.episode_count, base.episode_step)
    for name, (cols, elems) in stage._index.items():
        for part in (biases, noises):
            if name in part:
                want[:, cols] += part[name].flatten(1)[:, elems]
    for name, bias in stage.biases.items():  # the stored biases are those of the current episodes
        assert torch.equal(bias, biases[name]), name
    delta = td["obs_step"] - _clean_obs_step(td)
    delta[:, :3] = torch.remainder(delta[:, :3] - want[:, :3] + math.pi, 2 * math.pi) - math.pi + want[:, :3]
    torch.testing.assert_close(delta[:, :31], want[:, :31], rtol=0, atol=atol)  # angles [rad], commands, phase
    torch.testing.assert_close(delta[:, 31:], want[:, 31:], rtol=0, atol=2e-3)  # forces [N], moments [N·m]


@pytest.fixture(scope="module")
def env_pair():
    kw = dict(num_envs=4, device="cpu", seed=7, max_episode_steps=4, control_mode="torque")
    return make_env(**kw), make_env(sensor_noise=LAB, **kw)


def test_policy_sees_the_perturbation_and_rewards_the_truth(env_pair):
    clean, noisy = env_pair
    assert not any(isinstance(t, SensorNoise) for t in clean.transform)
    gen = torch.Generator().manual_seed(0)
    td_c, td_n = clean.reset(), noisy.reset()
    _check_observed_perturbation(noisy, td_n)
    for _ in range(6):  # past the 4-step truncation: every world resets once
        action = (torch.rand(4, 13, generator=gen) * 2 - 1) * 0.2
        out_c = clean.step(td_c.set("action", action))
        out_n = noisy.step(td_n.set("action", action.clone()))
        nxt_c, nxt_n = out_c["next"], out_n["next"]
        # The physics and every raw signal, the reward and each reward term: bit for bit the noise-free env's.
        for key in ("joint_pos", "joint_vel", "base_quat", "foot_force", "foot_torque", "reward", "done"):
            assert torch.equal(nxt_n[key], nxt_c[key]), key
        for key in nxt_c["reward_terms"].keys():
            assert torch.equal(nxt_n["reward_terms", key], nxt_c["reward_terms", key]), key
        # The policy's input: the perturbed step observation, normalised, as the newest block of the history.
        _check_observed_perturbation(noisy, nxt_n)
        assert not torch.equal(nxt_n["observation"], nxt_c["observation"])
        assert torch.equal(nxt_n["observation"][:, 148:185], nxt_n["obs_step_norm"])
        td_c, td_n = clean.step_mdp(out_c), noisy.step_mdp(out_n)
        if bool(nxt_n["done"].any()):
            td_c, td_n = clean.reset(td_c.set("_reset", nxt_c["done"])), noisy.reset(td_n.set("_reset", nxt_n["done"]))
            _check_observed_perturbation(noisy, td_n)


def test_biases_hold_over_an_episode_and_are_redrawn_at_that_worlds_reset_only(env_pair):
    _, env = env_pair
    td = env.reset()
    stage = _noise_stage(env)
    zero = torch.zeros(4, 13)
    before = {k: v.clone() for k, v in stage.biases.items()}
    for _ in range(2):
        td = env.step(td.set("action", zero))["next"]
        for name, bias in stage.biases.items():
            assert torch.equal(bias, before[name]), name
    reset = torch.tensor([[False], [True], [False], [False]])
    td = env.reset(td.set("_reset", reset))
    for name, bias in stage.biases.items():
        assert torch.equal(bias[[0, 2, 3]], before[name][[0, 2, 3]]), name  # the others keep theirs
        assert not torch.equal(bias[1], before[name][1]), name
    _check_observed_perturbation(env, td)


@pytest.mark.parametrize("cfg", [LAB, dataclasses.replace(LAB, joint_vel_noise_std=0.02, joint_vel_noise_clip=0.03)],
                         ids=["lab", "with_joint_vel_noise"])
def test_sync_free_steps_follow_every_reset(cfg):
    # The collectors' path: a masked reset on every step (base env, then every transform), merged with where. The
    # reset draws the new biases and the first observation's noise in one hash pass, and the noisy signals share
    # one Box-Muller: each must still be what sensor_biases and sensor_noise give, signal by signal.
    env = make_env(num_envs=4, device="cpu", seed=1, max_episode_steps=3, sync_free_resets=True, sensor_noise=cfg)
    td = env.reset()
    stage = _noise_stage(env)
    hashes = []  # the step's own hash runs only where no reset drew its noise
    step_hash = stage._step_hash
    stage._step_hash = lambda *args: hashes.append(1) or step_hash(*args)
    episodes = env.base_env.episode_count.clone()
    for _ in range(7):
        before = {k: v.clone() for k, v in stage.biases.items()}
        step, td = env.step_and_maybe_reset(td.set("action", torch.zeros(4, 13)))
        redrawn = env.base_env.episode_count != episodes
        episodes = env.base_env.episode_count.clone()
        assert torch.equal(redrawn, step["next", "done"].reshape(-1))
        for name, bias in stage.biases.items():
            changed = (bias != before[name]).flatten(1).any(-1)
            assert torch.equal(changed, redrawn), name
        _check_observed_perturbation(env, td)
    assert int(episodes.min()) >= 3
    assert hashes == []  # every step read the noise the reset before it drew
    step = env.step(td.set("action", torch.zeros(4, 13)))["next"]  # a plain step after a step: no reset between
    step = env.step(step.set("action", torch.zeros(4, 13)))["next"]
    assert hashes == [1]
    _check_observed_perturbation(env, step)


def test_step_and_reset_are_capture_safe_cpu_proxy(env_pair):
    # What a captured step needs, checked on the CPU: no op that would read a device value on the host, and no
    # Python state that moves per step (every buffer updated in place, never rebound).
    from test_transforms_presets import _HostSyncOps

    _, env = env_pair
    td = env.reset()
    stage = _noise_stage(env)
    state = {k: id(v) for k, v in vars(stage).items() if isinstance(v, (torch.Tensor, dict, tuple))}
    buffers = [id(t) for t in (*stage.biases.values(), stage._bias_cols)]
    td_in = td.clone().set("_reset", torch.tensor([[True], [False], [True], [False]]))
    td_reset = env.base_env._reset(td_in)
    with _HostSyncOps() as ops:
        stage._call(td.clone())
        env.transform._reset(td_in, td_reset)  # the chain's reset: the assembly, then this stage
    assert ops.hits == []
    for _ in range(3):
        td = env.step(td.set("action", torch.zeros(4, 13)))["next"]
    assert state == {k: id(v) for k, v in vars(stage).items() if isinstance(v, (torch.Tensor, dict, tuple))}
    assert buffers == [id(t) for t in (*stage.biases.values(), stage._bias_cols)]


# ------------------------------------------------------------------------------------------------------ GPU
@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_gpu_captured_step_never_syncs_and_draws_fresh_noise_across_resets():
    e = make_env(num_envs=128, device="cuda", seed=0, cuda_graph=True, max_episode_steps=3, control_mode="torque",
                 sensor_noise=dataclasses.replace(LAB, joint_vel_noise_std=0.01))
    td = e.reset()
    action = (torch.rand(128, 13, device="cuda") * 2 - 1) * 0.3
    for _ in range(3):  # warm-up and capture
        _, td = e.step_and_maybe_reset(td.set("action", action))
    assert e.graph_captured
    stage = _noise_stage(e)
    before = {k: v.clone() for k, v in stage.biases.items()}
    seen = []
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(6):  # crosses the 3-step truncation: every world resets and redraws its biases
            step, td = e.step_and_maybe_reset(td.set("action", action))
            seen.append(td.select("obs_step", "base_quat", *(c.key for c in REFERENCE_OBS_LAYOUT
                                                             if c.key != "base_rpy")).clone())
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert bool(step["next", "truncated"].any())
    for name, bias in stage.biases.items():  # redrawn in place, inside the captured step
        assert not torch.equal(bias, before[name]), name
        assert float(bias.abs().max()) <= LAB.bias(name)
    _check_observed_perturbation(e, seen[-1])
    # The noise moved on every replay: the joint columns' perturbation differs from step to step.
    deltas = [s["obs_step"][:, 3:15] - _clean_obs_step(s)[:, 3:15] for s in seen]
    assert all(not torch.equal(a, b) for a, b in zip(deltas, deltas[1:]))


def test_biased_euler_angles_are_wrapped_back_into_minus_pi_pi():
    env = make_env(num_envs=64, device="cpu", seed=3, sensor_noise=SensorNoiseConfig(base_rpy_bias=0.5))
    env.reset()
    stage = _noise_stage(env)
    cols = stage._index["base_rpy"][0]
    exact = torch.full((64, stage._width), 0.25)
    near = torch.tensor([math.pi - 0.01, -math.pi + 0.01, math.pi, 0.0])
    exact[:, cols] = near.repeat(64)[: 64 * 3].reshape(64, 3)
    out = stage._perturbed(exact)
    angles, want = out[:, cols], (exact + stage._bias_cols)[:, cols]
    assert bool((angles > -math.pi).all() and (angles <= math.pi).all())
    assert bool(((angles - want).abs() > 1.0).any())  # some biased angles crossed ±pi and were wrapped
    torch.testing.assert_close(torch.remainder(angles - want + math.pi, 2 * math.pi) - math.pi,
                               torch.zeros_like(angles), rtol=0, atol=1e-6)
    rest = torch.ones(stage._width, dtype=torch.bool)
    rest[cols] = False
    assert torch.equal(out[:, rest], exact[:, rest])  # the other columns: no bias, no noise, no wrap


def test_a_reset_without_mask_redraws_every_world():
    # A reset without "_reset" redraws every world (the base env resets them all).
    env = make_env(num_envs=2, device="cpu", seed=5, sensor_noise=SensorNoiseConfig(foot_force_bias=50.0))
    env.reset()
    first = _noise_stage(env).biases["foot_force"].clone()
    env.reset(TensorDict({}, batch_size=[2]))
    assert not (first == _noise_stage(env).biases["foot_force"]).flatten(1).all(-1).any()


def test_a_clone_of_a_used_chain_draws_for_its_own_env():
    # torchrl's clone is shallow: a clone of a SensorNoise that had run kept the first env's counters and shared its
    # bias buffer, so the second env's resets redrew the first env's biases in place.
    from tocabi_torchrl.envs import TocabiWalk

    first = make_env(num_envs=2, device="cpu", seed=5, sensor_noise=LAB)
    first.reset()
    stage = _noise_stage(first)
    before = stage.biases["joint_pos"].clone()
    second = TransformedEnv(TocabiWalk(2, device="cpu", seed=6), first.transform.clone())
    td = second.reset()
    assert torch.equal(stage.biases["joint_pos"], before)
    copy = _noise_stage(second)
    assert not torch.equal(copy.biases["joint_pos"], before)  # its own seed's draw
    _check_observed_perturbation(second, td)
