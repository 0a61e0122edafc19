"""Phase encoding, Euler angles, the 37-value observation in spec order, and its normalisation."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from mock_env import MockTocabiWalk
from torchrl.envs import Compose, TransformedEnv

from tocabi_torchrl.transforms import (
    REFERENCE_OBS_LAYOUT,
    REFERENCE_OBS_MEAN,
    REFERENCE_OBS_VAR,
    BaseEulerAngles,
    FixedNormalization,
    ObservationAssembly,
    ObsComponent,
    PhaseEncoding,
    RunningNormalization,
    quat_rotation_angle,
    quat_to_rpy,
)

REFERENCE_DIR = Path(__file__).resolve().parents[2] / "shared" / "reference"


def _qmul(a, b):
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def _quat_from_rpy(roll, pitch, yaw):
    """q = qz(yaw)·qy(pitch)·qx(roll), i.e. R = Rz·Ry·Rx (fixed X-Y-Z)."""
    qx = (math.cos(roll / 2), math.sin(roll / 2), 0.0, 0.0)
    qy = (math.cos(pitch / 2), 0.0, math.sin(pitch / 2), 0.0)
    qz = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
    return _qmul(qz, _qmul(qy, qx))


# ----------------------------------------------------------------------------------------------- phase, euler
def test_phase_encoding_harmonics():
    td = MockTocabiWalk(3).full_observation_spec.zero()
    td["phase"] = torch.tensor([[0.0], [0.125], [0.75]])
    out = PhaseEncoding(harmonics=3)(td)
    s = math.sqrt(0.5)
    sin = torch.tensor([[0.0, 0.0, 0.0], [s, 1.0, s], [-1.0, 0.0, 1.0]])
    cos = torch.tensor([[1.0, 1.0, 1.0], [s, 0.0, -s], [0.0, -1.0, 0.0]])
    torch.testing.assert_close(out["phase_sin"], sin, atol=1e-6, rtol=0)
    torch.testing.assert_close(out["phase_cos"], cos, atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="harmonics"):
        PhaseEncoding(harmonics=0)


@pytest.mark.parametrize("out_keys", ["sc", "phase_sin", ("phase_sin",), None])
def test_phase_encoding_refuses_out_keys_not_a_pair(out_keys):
    # "sc" has length 2: it was taken as the keys 's' and 'c'.
    with pytest.raises(ValueError, match="two out_keys"):
        PhaseEncoding(out_keys=out_keys)


@pytest.mark.parametrize("rpy", [(0.1, -0.2, 0.3), (-2.5, 1.2, -3.0), (0.0, 0.0, 2.0), (3.0, -0.5, 0.0)])
def test_quat_to_rpy_fixed_xyz(rpy):
    q = torch.tensor([_quat_from_rpy(*rpy)], dtype=torch.float64)
    torch.testing.assert_close(quat_to_rpy(q)[0], torch.tensor(rpy, dtype=torch.float64))
    torch.testing.assert_close(quat_to_rpy(-q)[0], torch.tensor(rpy, dtype=torch.float64))  # same rotation


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_quat_to_rpy_gimbal_fallback(dtype):
    # R = Ry(π/2)·Rx(0.3): at the lock the reference reports roll 0, yaw = atan2(-R01, R11) = -0.3.
    pitch90 = (math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0)
    roll03 = (math.cos(0.15), math.sin(0.15), 0.0, 0.0)
    q = torch.tensor([_qmul(pitch90, roll03)], dtype=dtype)
    rpy = quat_to_rpy(q)[0]
    torch.testing.assert_close(rpy, torch.tensor([0.0, math.pi / 2, -0.3], dtype=dtype), atol=1e-3, rtol=0)


def test_quat_rotation_angle():
    c, s = math.cos(0.5), math.sin(0.5)
    q = torch.tensor([[1.0, 0, 0, 0], [c, s, 0, 0], [-c, 0, -s, 0], [0.0, 0, 0, 1]])
    torch.testing.assert_close(quat_rotation_angle(q).squeeze(-1), torch.tensor([0.0, 1.0, 1.0, math.pi]))


# ------------------------------------------------------------------------------------------------ assembly
def _constructed_state():
    td = MockTocabiWalk(2).full_observation_spec.zero()
    td["base_quat"][:] = torch.tensor(_quat_from_rpy(0.1, -0.2, 0.3), dtype=torch.float32)
    td["joint_pos"][:] = 0.01 * torch.arange(33)
    td["joint_vel"][:] = -0.1 * torch.arange(33)
    td["phase"][:] = 0.125
    td["command"][:] = torch.tensor([0.5, -0.1])
    td["foot_force"][:] = torch.tensor([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    td["foot_torque"][:] = torch.tensor([[7.0, 8.0, 9.0], [10.0, 11.0, 12.0]])
    return td


def test_assembled_observation_matches_spec_order():
    td = Compose(PhaseEncoding(), BaseEulerAngles(), ObservationAssembly())(_constructed_state())
    obs = td["obs_step"]
    assert obs.shape == (2, 37) and obs.dtype == torch.float32
    s = math.sqrt(0.5)
    expected = (
        [0.1, -0.2, 0.3]  # 0-2 roll, pitch, yaw
        + [0.01 * j for j in range(12)]  # 3-14 leg q
        + [-0.1 * j for j in range(12)]  # 15-26 leg dq
        + [s, s]  # 27-28 sin, cos
        + [0.5, -0.1]  # 29-30 command
        + [3.0, 6.0]  # 31-32 Fz_L, Fz_R
        + [7.0, 10.0]  # 33-34 Mx_L, Mx_R
        + [8.0, 11.0]  # 35-36 My_L, My_R
    )
    torch.testing.assert_close(obs, torch.tensor([expected, expected]), atol=2e-6, rtol=1e-5)


def test_assembly_slices_and_custom_layout():
    env = TransformedEnv(MockTocabiWalk(2), Compose(PhaseEncoding(), BaseEulerAngles(), ObservationAssembly()))
    assert env.observation_spec["obs_step"].shape == (2, 37)
    sl = env.transform[-1].slices
    assert [sl[c.name] for c in REFERENCE_OBS_LAYOUT] == [
        slice(0, 3), slice(3, 15), slice(15, 27), slice(27, 28), slice(28, 29), slice(29, 31), slice(31, 33),
        slice(33, 35), slice(35, 37),
    ]  # fmt: skip
    layout = REFERENCE_OBS_LAYOUT + (ObsComponent("base_ang_vel", "base_ang_vel"),)
    env = TransformedEnv(MockTocabiWalk(2), Compose(PhaseEncoding(), BaseEulerAngles(), ObservationAssembly(layout)))
    td = env.reset()
    assert td["obs_step"].shape == (2, 40)
    torch.testing.assert_close(td["obs_step"][:, 37:], td["base_ang_vel"])


def test_assembly_errors():
    with pytest.raises(TypeError, match="ints, slices"):
        ObsComponent("bad", "joint_pos", ([0, 3],))
    env = TransformedEnv(MockTocabiWalk(2), ObservationAssembly())
    with pytest.raises(KeyError, match="BaseEulerAngles before ObservationAssembly"):
        env.observation_spec
    env = TransformedEnv(MockTocabiWalk(2), ObservationAssembly((ObsComponent("x", "command", (slice(None), 0)),)))
    with pytest.raises(ValueError, match="does not fit"):
        env.observation_spec
    # A slice past the end added 0 columns without a word.
    env = TransformedEnv(MockTocabiWalk(2), ObservationAssembly((ObsComponent("arms", "joint_pos", (slice(33, 40),)),)))
    with pytest.raises(ValueError, match=r"block 'arms': index \(slice\(33, 40, None\),\) selects no element"):
        env.observation_spec



@pytest.mark.parametrize("index, fix", [
    (slice(0, 12), r"pass \(slice\(0, 12, None\),\)"),
    (2, r"pass \(2,\)"),
    ([slice(0, 12)], r"pass a tuple, e.g. \(slice\(0, 12\),\)"),
])
def test_an_observation_block_index_that_is_no_tuple_is_named_with_the_tuple_to_pass(index, fix):
    # A lone slice failed as a bare "'slice' object is not iterable"; a list was accepted and failed only once an env
    # was attached ("can only concatenate tuple (not "list") to tuple").
    with pytest.raises(TypeError, match=r"ObsComponent 'legs': index must be a tuple of ints, slices or Ellipsis.*"
                                        + fix):
        ObsComponent("legs", "joint_pos", index)


def test_a_hand_built_chain_names_its_mistake_at_the_first_reset():
    # Specs are computed lazily: a chain whose specs nobody read once failed at its first reset on the missing key
    # ("'NoneType' object is not subscriptable"), not with the spec check's message naming the fix.
    from tocabi_torchrl.transforms import ObsActionHistory

    cases = [(Compose(ObservationAssembly(), PhaseEncoding(), BaseEulerAngles()), KeyError,
              "put BaseEulerAngles before ObservationAssembly"),
             (Compose(PhaseEncoding(in_key="phas")), KeyError, "PhaseEncoding reads 'phas'"),
             (Compose(PhaseEncoding(), BaseEulerAngles(), ObservationAssembly(), FixedNormalization(),
                      ObsActionHistory(action_key="action")), KeyError, "ObsActionHistory reads 'action'"),
             (Compose(PhaseEncoding(harmonics=2), BaseEulerAngles(), ObservationAssembly(), FixedNormalization()),
              ValueError, "holds 37 statistics but 'obs_step' has 39 values")]
    for chain, error, message in cases:
        with pytest.raises(error, match=message):
            TransformedEnv(MockTocabiWalk(2), chain).reset()
    env = TransformedEnv(MockTocabiWalk(2), Compose(PhaseEncoding(), BaseEulerAngles(), ObservationAssembly()))
    assert env.reset()["obs_step"].shape == (2, 37)  # a right chain resets as before

# ----------------------------------------------------------------------------------------- normalisation
def test_fixed_normalization_reference_statistics():
    mean = torch.tensor(REFERENCE_OBS_MEAN)
    std = torch.sqrt(torch.tensor(REFERENCE_OBS_VAR, dtype=torch.float64) + 1e-8).float()
    # A few std values of the spec §7.1 table.
    assert std[6].item() == pytest.approx(0.127275, abs=1e-6)
    assert std[24].item() == pytest.approx(1.13143, abs=1e-5)
    assert std[31].item() == pytest.approx(158.114, abs=1e-3)
    assert std[33].item() == pytest.approx(30.0, abs=1e-6)
    norm = FixedNormalization()
    td = MockTocabiWalk(2).full_observation_spec.zero()
    td["obs_step"] = torch.stack((mean, mean + 2 * std))
    out = norm(td)["obs_step_norm"]
    torch.testing.assert_close(out, torch.stack((torch.zeros(37), torch.full((37,), 2.0))))
    clipped = FixedNormalization(clip=1.5)(td)["obs_step_norm"]
    assert clipped.max().item() == 1.5


@pytest.mark.skipif(not (REFERENCE_DIR / "obs_mean_fixed.txt").exists(), reason="reference files not present")
def test_fixed_statistics_match_reference_files_to_7_digits():
    def read(name):
        return torch.tensor([float(x) for x in (REFERENCE_DIR / name).read_text().split()], dtype=torch.float64)

    ref_mean, ref_var = read("obs_mean_fixed.txt"), read("obs_variance_fixed.txt")
    ours_mean = torch.tensor(REFERENCE_OBS_MEAN, dtype=torch.float64)
    ours_var = torch.tensor(REFERENCE_OBS_VAR, dtype=torch.float64)
    torch.testing.assert_close(ours_mean, ref_mean, rtol=6e-7, atol=1e-12)
    torch.testing.assert_close(ours_var, ref_var, rtol=6e-7, atol=1e-12)
    # The normalised observation differs by < 1e-5 std for a typical observation.
    x = ref_mean + torch.sqrt(ref_var)
    ref_out = (x - ref_mean) / torch.sqrt(ref_var + 1e-8)
    our_out = (x - ours_mean) / torch.sqrt(ours_var + 1e-8)
    assert (ref_out - our_out).abs().max().item() < 1e-5


def test_fixed_normalization_errors():
    with pytest.raises(ValueError, match="equal lengths"):
        FixedNormalization(mean=[0.0] * 3, var=[1.0] * 4)
    env = TransformedEnv(MockTocabiWalk(2), FixedNormalization(in_key="command"))
    with pytest.raises(ValueError, match="37 statistics but 'command' has 2"):
        env.observation_spec


def test_running_normalization_tracks_batch_statistics():
    torch.manual_seed(0)
    norm = RunningNormalization(dim=3, init_count=1e-6)
    batches = [torch.randn(64, 3) * torch.tensor([1.0, 5.0, 0.1]) + torch.tensor([3.0, -2.0, 0.5]) for _ in range(5)]
    for b in batches:
        norm.update(b)
    allx = torch.cat(batches).double()
    torch.testing.assert_close(norm.mean, allx.mean(0), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(norm.var, allx.var(0, unbiased=False), rtol=1e-5, atol=1e-6)
    assert norm.count.item() == pytest.approx(320, rel=1e-6)


@pytest.mark.parametrize("kwargs, error, message", [
    (dict(dim=2.5), ValueError, r"RunningNormalization dim \(D, the observation's values\) must be an integer >= 1, "
                                r"got 2.5; or None to size the statistics from the observation"),
    (dict(dim=0), ValueError, "dim .* must be an integer >= 1, got 0"),
    (dict(dim=3, init_mean=[0.0] * 2), ValueError, "dim=3 but init_mean has 2 values; pass 3 values"),
    (dict(dim=3, init_var=[1.0] * 2), ValueError, "dim=3 but init_var has 2 values; pass 3 values"),
])
def test_running_normalization_names_a_dim_that_does_not_fit(kwargs, error, message):
    # A float dim failed as a bare "can't multiply sequence by non-int"; a dim other than init_mean's length was
    # named as a mean and a var of unequal lengths, a var the caller never gave; dim=0 was taken for "unsized".
    with pytest.raises(error, match=message):
        RunningNormalization(**kwargs)
    assert RunningNormalization(dim=2, init_mean=[[1.0, 2.0]]).mean.tolist() == [1.0, 2.0]  # flattened, as before

def test_running_normalization_count_is_float64_and_exact_past_2_24_samples():
    # A float32 count rounded each 3-sample update away once it passed 2**24 samples (16,777,216 -> 16,778,216
    # after 1000 updates, instead of 16,780,216), skewing the update's weights.
    norm = RunningNormalization(dim=1)
    assert norm.count.dtype == norm.mean.dtype == norm.var.dtype == torch.float64
    norm.count.fill_(2**24)
    for _ in range(1000):
        norm.update(torch.ones(3, 1))
    assert norm.count.item() == 2**24 + 3000
    # A state_dict of before, with a float32 count, still loads, into the float64 buffer.
    old = {k: v.clone() for k, v in norm.state_dict().items()}
    old["count"] = torch.tensor(1234.0, dtype=torch.float32)
    fresh = RunningNormalization(dim=1)
    fresh.load_state_dict(old)
    assert fresh.count.dtype == torch.float64 and fresh.count.item() == 1234.0
    fresh.update(torch.ones(2, 1))
    assert fresh.count.item() == 1236.0


def test_running_normalization_in_env_updates_on_step_only_and_freezes():
    env = TransformedEnv(
        MockTocabiWalk(4),
        Compose(PhaseEncoding(), BaseEulerAngles(), ObservationAssembly(), RunningNormalization()),
    )
    norm = env.transform[-1]
    assert norm.mean.shape == (0,)
    env.observation_spec  # sizes the statistics from the spec
    assert norm.mean.shape == (37,)
    env.reset()
    assert norm.count.item() == 1.0  # reset reads, does not update
    td = env.rand_step(env.reset())
    assert norm.count.item() == 5.0
    torch.testing.assert_close(
        td["next", "obs_step_norm"],
        ((td["next", "obs_step"].double() - norm.mean) / torch.sqrt(norm.var + 1e-8)).float(),
    )
    norm.freeze()
    env.rand_step(env.reset())
    assert norm.count.item() == 5.0


def test_running_normalization_sizes_itself_from_the_first_observation():
    # An env whose observation spec nobody read before the first reset (e.g. a changed layout, for which there are
    # no reference statistics to start from) must still normalize: the first observation sizes the statistics.
    env = TransformedEnv(
        MockTocabiWalk(4),
        Compose(PhaseEncoding(harmonics=2), BaseEulerAngles(), ObservationAssembly(), RunningNormalization()),
    )
    norm = env.transform[-1]
    td = env.rand_step(env.reset())
    dim = td["next", "obs_step"].shape[-1]
    assert norm.mean.shape == (dim,) and norm.var.shape == (dim,) and norm.count.item() == 5.0
    assert torch.isfinite(td["next", "obs_step_norm"]).all()
    assert env.observation_spec["obs_step_norm"].shape[-1] == dim  # reading the spec later keeps the statistics
    assert norm.count.item() == 5.0 and norm.mean.shape == (dim,)


def test_running_normalization_masked_update():
    torch.manual_seed(1)
    norm = RunningNormalization(dim=2, init_count=1e-6)
    x1, x2 = torch.randn(16, 2) * 3 + 1, torch.randn(16, 2) - 2
    m1, m2 = torch.rand(16, 1) < 0.5, torch.rand(16, 1) < 0.5
    norm.update(x1, m1)
    norm.update(x2, m2)
    sel = torch.cat((x1[m1.squeeze(-1)], x2[m2.squeeze(-1)])).double()
    torch.testing.assert_close(norm.mean, sel.mean(0), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(norm.var, sel.var(0, unbiased=False), rtol=1e-5, atol=1e-6)
    before = (norm.mean.clone(), norm.var.clone(), norm.count.clone())
    norm.update(torch.randn(16, 2) * 100, torch.zeros(16, 1, dtype=torch.bool))  # nothing selected: no change
    for a, b in zip(before, (norm.mean, norm.var, norm.count)):
        torch.testing.assert_close(a, b)


def _running_env(**norm_kwargs) -> TransformedEnv:
    return TransformedEnv(MockTocabiWalk(4, terminate_prob=0.5), Compose(
        PhaseEncoding(), BaseEulerAngles(), ObservationAssembly(), RunningNormalization(**norm_kwargs)))


def test_running_normalization_learns_from_the_mask_keys_rows_and_names_a_bad_mask_key():
    env = _running_env(mask_key="terminated", mask_invert=True, init_count=1e-6)
    norm = env.transform[-1]
    td = env.rand_step(env.reset())
    kept = ~td["next", "terminated"].squeeze(-1)
    assert norm.count.item() == pytest.approx(int(kept.sum()), abs=1e-5)
    # A misspelt key was read as no mask: every row went into the statistics without a word (and with
    # mask_invert=True the step failed on ~None).
    for invert in (False, True):
        env = _running_env(mask_key="terminatd", mask_invert=invert)
        with pytest.raises(KeyError, match="mask_key 'terminatd' is not in the step's output"):
            env.rand_step(env.reset())
        assert env.transform[-1].count.item() == 1.0  # nothing learnt
    env = _running_env(mask_key="base_pos")  # (num_envs, 3) float: no flags
    with pytest.raises(ValueError, match=r"mask_key 'base_pos' must be \(4, 1\) bool flags, got \(4, 3\)"):
        env.rand_step(env.reset())


def test_quat_to_rpy_matches_the_reference_formulas_on_random_quaternions():
    import numpy as np

    rng = np.random.default_rng(0)
    q = rng.normal(size=(500, 4)) * rng.uniform(0.5, 2.0, size=(500, 1))  # not unit length

    def reference(qi):  # gym quat2mat, then spec §7.2
        w, x, y, z = qi
        s = 2.0 / (qi @ qi)
        m = np.array(
            [
                [1 - s * (y * y + z * z), s * (x * y - w * z), s * (x * z + w * y)],
                [s * (x * y + w * z), 1 - s * (x * x + z * z), s * (y * z - w * x)],
                [s * (x * z - w * y), s * (y * z + w * x), 1 - s * (x * x + y * y)],
            ]
        )
        cy = math.hypot(m[0, 0], m[1, 0])
        return [math.atan2(m[2, 1], m[2, 2]), math.atan2(-m[2, 0], cy), math.atan2(m[1, 0], m[0, 0])]

    expected = torch.tensor([reference(qi) for qi in q], dtype=torch.float64)
    torch.testing.assert_close(quat_to_rpy(torch.tensor(q)), expected, rtol=0, atol=1e-9)
    torch.testing.assert_close(quat_to_rpy(torch.tensor(q, dtype=torch.float32)), expected.float(), rtol=0, atol=2e-5)


def test_freezing_running_statistics_drops_a_captured_step_graph_only_when_one_changed():
    # A captured step replays the updates it was captured with, whatever `frozen` says afterwards
    # (SyncFreeResetEnv's docstring): freezing must make the env capture again.
    from tocabi_torchrl.transforms.normalize import freeze_running_statistics

    class Env:  # the two things freeze_running_statistics reads of an env
        def __init__(self, transforms):
            self.transform, self.dropped = transforms, 0

        def invalidate_graph(self):
            self.dropped += 1

    norm = RunningNormalization(dim=3)
    env = Env([norm])
    assert freeze_running_statistics(env) == 1 and norm.frozen and env.dropped == 1
    assert freeze_running_statistics(env) == 1 and env.dropped == 1  # already frozen: the graph stays
    assert freeze_running_statistics(Env([])) == 0


def test_freezing_finds_running_statistics_in_a_nested_compose_and_a_wrapped_env():
    # A normaliser inside a Compose inside the env's Compose was missed, and kept learning from the evaluation.
    from torchrl.envs.transforms import Compose, StepCounter

    from tocabi_torchrl.transforms.normalize import freeze_running_statistics

    class Env:
        def __init__(self, transform, base_env=None):
            self.transform = transform
            self.base_env = self if base_env is None else base_env  # a base env is its own base_env

    inner, outer = RunningNormalization(dim=3), RunningNormalization(dim=3)
    env = Env(Compose(Compose(inner, StepCounter()), StepCounter()))
    assert freeze_running_statistics(env) == 1 and inner.frozen
    wrapped = Env(Compose(StepCounter()), base_env=Env(Compose(outer)))  # TransformedEnv(TransformedEnv(...))
    assert freeze_running_statistics(wrapped) == 1 and outer.frozen
