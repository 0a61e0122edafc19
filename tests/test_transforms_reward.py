"""Each reward term against a hand computation (spec §8), and the TaskReward sum/keys/options."""

from __future__ import annotations

import math

import pytest
import torch
from mock_env import MockTocabiWalk
from tensordict import TensorDict
from torchrl.envs import TransformedEnv

from tocabi_torchrl import robot
from tocabi_torchrl.transforms import (
    REFERENCE_TERMS,
    BodyVelTracking,
    CallableTerm,
    ContactForce,
    ContactForceDiff,
    FootContactPattern,
    ForceDiffThresholdPenalty,
    ForceReference,
    ForceThresholdPenalty,
    JointAccRegulation,
    JointPosTracking,
    JointVelRegulation,
    NeckOrientation,
    RewardTerm,
    TaskReward,
    TorqueDiffRegulation,
    TorqueRegulation,
    reference_terms,
)

N = 3


def _state() -> TensorDict:
    """Neutral signals (zeros, identity quaternions) with the contract's keys, shapes and dtypes."""
    td = MockTocabiWalk(N).full_observation_spec.zero()
    td["base_quat"][..., 0] = 1.0
    td["neck_quat"][..., 0] = 1.0
    td["terminated"] = torch.zeros(N, 1, dtype=torch.bool)
    return td


def _pair() -> tuple[TensorDict, TensorDict]:
    return _state(), _state()


def _close(value: torch.Tensor, expected: list[float]) -> None:
    assert value.shape == (N, 1)
    assert value.dtype == torch.float32
    torch.testing.assert_close(value.squeeze(-1), torch.tensor(expected, dtype=torch.float32), rtol=1e-5, atol=1e-7)


def test_reference_term_set_and_weights():
    assert list(REFERENCE_TERMS) == [
        "orientation", "qpos", "qvel", "body_vel", "contact_force", "torque", "torque_diff", "qacc",
        "foot_contact", "contact_force_diff", "force_ref", "force_threshold", "force_diff_threshold",
    ]  # fmt: skip
    weights = {t.name: t.weight for t in reference_terms()}
    assert weights == {
        "orientation": 0.3, "qpos": 0.35, "qvel": 0.05, "body_vel": 0.3, "contact_force": 0.1, "torque": 0.05,
        "torque_diff": 0.6, "qacc": 0.05, "foot_contact": 0.2, "contact_force_diff": 0.2, "force_ref": 0.2,
        "force_threshold": -0.08, "force_diff_threshold": -0.05,
    }  # fmt: skip
    # The positive terms' maxima add up to the reference's 2.4.
    assert sum(w for w in weights.values() if w > 0) == pytest.approx(2.4)


def test_orientation_uses_neck_rotation_angle():
    td, nxt = _pair()
    half = 0.05  # 0.1 rad about z (pure yaw still counts)
    nxt["neck_quat"][0] = torch.tensor([math.cos(half), 0.0, 0.0, math.sin(half)])
    # -q is the same rotation: pyquaternion's wrapped angle gives |θ| = 0.1 too.
    nxt["neck_quat"][1] = -torch.tensor([math.cos(half), 0.0, 0.0, math.sin(half)])
    # 0.6 rad about the axis (1, 2, 2)/3, quaternion not normalised (scaled by 2).
    s = math.sin(0.3) / 3
    nxt["neck_quat"][2] = 2.0 * torch.tensor([math.cos(0.3), s, 2 * s, 2 * s])
    expected = [0.3 * math.exp(-13.2 * 0.1), 0.3 * math.exp(-13.2 * 0.1), 0.3 * math.exp(-13.2 * 0.6)]
    _close(NeckOrientation()(td, nxt), expected)


def test_qpos_squared_error_over_all_33_joints():
    td, nxt = _pair()
    nxt["ref_joint_pos"][0, 0] = 0.1
    nxt["ref_joint_pos"][0, 32] = -0.1  # an upper-body joint counts too
    nxt["joint_pos"][1] = 0.05  # 33 joints off by 0.05
    _close(JointPosTracking()(td, nxt), [0.35 * math.exp(-4 * 0.02), 0.35 * math.exp(-4 * 33 * 0.0025), 0.35])


def test_qvel_squared_norm():
    td, nxt = _pair()
    nxt["joint_vel"][0, 3] = 3.0
    nxt["joint_vel"][0, 20] = 4.0
    _close(JointVelRegulation()(td, nxt), [0.05 * math.exp(-0.01 * 25), 0.05, 0.05])


def test_body_vel_compares_xy_with_command():
    td, nxt = _pair()
    nxt["base_lin_vel"][0] = torch.tensor([0.5, 0.1, 9.0])  # z is ignored
    nxt["command"][0] = torch.tensor([0.2, -0.3])
    nxt["command"][1] = torch.tensor([0.1, 0.0])
    _close(BodyVelTracking()(td, nxt), [0.3 * math.exp(-3 * 0.25), 0.3 * math.exp(-3 * 0.01), 0.3])


def test_contact_force_plain_3d_norms():
    td, nxt = _pair()
    nxt["foot_force"][0, 0] = torch.tensor([300.0, 400.0, 0.0])  # |F_L| = 500
    nxt["foot_force"][0, 1] = torch.tensor([0.0, 0.0, -1000.0])  # |F_R| = 1000
    _close(ContactForce()(td, nxt), [0.1 * math.exp(-0.0005 * 1500), 0.1, 0.1])


def test_torque_scales_every_leg_action_by_333_plain_norm():
    td, nxt = _pair()
    nxt["applied_action"][0, 0] = 0.3
    nxt["applied_action"][0, 11] = 0.4  # R_AnkleRoll (limit 166) is also scaled by 333
    nxt["applied_action"][0, 12] = 1.0  # the phase action is not a torque
    nxt["applied_action"][1, 12] = 1.0
    _close(TorqueRegulation()(td, nxt), [0.05 * math.exp(-0.01 * 333 * 0.5), 0.05, 0.05])


def test_torque_diff_uses_root_action_as_previous():
    td, nxt = _pair()
    td["applied_action"][0, 2] = 0.1
    nxt["applied_action"][0, 2] = 0.4
    td["applied_action"][1, 5] = 0.5  # same action at t and t+1: no change
    nxt["applied_action"][1, 5] = 0.5
    td["applied_action"][2, 12] = 0.0  # phase action change does not count
    nxt["applied_action"][2, 12] = 1.0
    _close(TorqueDiffRegulation()(td, nxt), [0.6 * math.exp(-0.01 * 333 * 0.3), 0.6, 0.6])


def test_qacc_velocity_change_per_step_not_divided_by_dt():
    td, nxt = _pair()
    td["joint_vel"][0, 0] = 1.0
    nxt["joint_vel"][0, 0] = 1.1
    nxt["joint_vel"][0, 30] = 0.2
    td["joint_vel"][1] = 2.0
    nxt["joint_vel"][1] = 2.0
    _close(JointAccRegulation()(td, nxt), [0.05 * math.exp(-20 * 0.05), 0.05, 0.05])


@pytest.mark.parametrize(
    "stance, left, right, paid",
    [
        (0, True, True, True), (0, True, False, False), (0, False, True, False), (0, False, False, False),
        (1, False, True, True), (1, True, True, False), (1, True, False, False), (1, False, False, False),
        (2, True, False, True), (2, True, True, False), (2, False, True, False), (2, False, False, False),
    ],
)  # fmt: skip
def test_foot_contact_stance_pattern(stance, left, right, paid):
    td, nxt = _pair()
    nxt["stance"][:] = stance
    nxt["foot_contact"][:] = torch.tensor([left, right])
    _close(FootContactPattern()(td, nxt), [0.2 if paid else 0.0] * N)


def test_contact_force_diff_plain_norms_of_jumps():
    td, nxt = _pair()
    td["foot_force"][0, 0] = torch.tensor([10.0, 0.0, -100.0])
    nxt["foot_force"][0, 0] = torch.tensor([40.0, 40.0, -100.0])  # |ΔF_L| = 50
    td["foot_force"][0, 1] = torch.tensor([0.0, 0.0, -500.0])
    nxt["foot_force"][0, 1] = torch.tensor([0.0, 0.0, -530.0])  # |ΔF_R| = 30
    _close(ContactForceDiff()(td, nxt), [0.2 * math.exp(-0.01 * 80), 0.2, 0.2])


def test_force_ref_two_feet_point_one_each():
    td, nxt = _pair()
    nxt["foot_force"][0, :, 2] = torch.tensor([-900.0, -10.0])
    nxt["ref_foot_force"][0] = torch.tensor([-1025.0, 0.0])
    nxt["ref_foot_force"][1] = torch.tensor([-1025.0, 0.0])
    expected0 = 0.1 * math.exp(-0.001 * 125) + 0.1 * math.exp(-0.001 * 10)
    expected1 = 0.1 * math.exp(-0.001 * 1025) + 0.1
    _close(ForceReference()(td, nxt), [expected0, expected1, 0.2])


def test_force_threshold_penalty_at_1_4_mg():
    threshold = 1.4 * robot.NOMINAL_MASS * robot.GRAVITY
    assert threshold == pytest.approx(1435.026, abs=1e-3)
    td, nxt = _pair()
    nxt["foot_force"][0, :, 2] = torch.tensor([-1435.0, -100.0])  # just below: no penalty
    nxt["foot_force"][1, :, 2] = torch.tensor([-100.0, -1435.1])  # right foot just above
    nxt["foot_force"][2, :, 2] = torch.tensor([1436.0, 0.0])  # |F_z| counts either sign
    _close(ForceThresholdPenalty()(td, nxt), [0.0, -0.08, -0.08])


def test_force_diff_threshold_penalty_at_0_2_mg():
    threshold = 0.2 * robot.NOMINAL_MASS * robot.GRAVITY
    assert threshold == pytest.approx(205.004, abs=1e-3)
    td, nxt = _pair()
    td["foot_force"][..., 2] = -500.0
    nxt["foot_force"][..., 2] = -500.0
    nxt["foot_force"][0, 0, 2] = -705.0  # jump 205.0: below
    nxt["foot_force"][1, 1, 2] = -705.1  # jump 205.1: above
    nxt["foot_force"][2, 0, 2] = -294.8  # unloading jump of 205.2 also counts
    nxt["foot_force"][2, 0, 0] = 1000.0  # x/y jumps do not count
    _close(ForceDiffThresholdPenalty()(td, nxt), [0.0, -0.05, -0.05])


# ------------------------------------------------------------------------------------------------ TaskReward
def _reward_env(**kwargs) -> TransformedEnv:
    terms = kwargs.pop("terms", reference_terms())
    return TransformedEnv(MockTocabiWalk(N, **kwargs), TaskReward(terms))


def test_task_reward_sums_terms_and_logs_each():
    env = _reward_env()
    ro = env.rollout(4)
    terms = ro["next", "reward_terms"]
    assert set(terms.keys()) == set(REFERENCE_TERMS)
    total = sum(terms[n] for n in REFERENCE_TERMS)
    torch.testing.assert_close(ro["next", "reward"], total)
    # Every term equals the term applied to (root, next) of the same step.
    for name, term in zip(REFERENCE_TERMS, reference_terms()):
        torch.testing.assert_close(terms[name], term(ro.exclude("next"), ro["next"]), msg=name)
    assert (ro["next", "reward"] <= 2.4 + 1e-6).all() and (ro["next", "reward"] >= -0.13 - 1e-6).all()
    # Reset writes zeros for every term.
    reset_td = env.reset()
    assert all((reset_td["reward_terms", n] == 0).all() for n in REFERENCE_TERMS)


def test_zero_reward_on_terminating_step_is_an_option():
    env = _reward_env(terminate_prob=0.5, seed=1)
    ro = env.rollout(6, break_when_any_done=False)
    term = ro["next", "terminated"]
    assert term.any() and (~term).any()
    assert (ro["next", "reward"][term] == 0).all()
    assert (ro["next", "reward"][~term] != 0).all()
    for n in REFERENCE_TERMS:
        assert (ro["next", "reward_terms", n][term] == 0).all()

    env_keep = TransformedEnv(
        MockTocabiWalk(N, terminate_prob=0.5, seed=1), TaskReward(reference_terms(), zero_on_terminated=False)
    )
    ro_keep = env_keep.rollout(6, break_when_any_done=False)
    torch.testing.assert_close(ro_keep["next", "terminated"], term)
    assert (ro_keep["next", "reward"][term] != 0).all()


def test_reweight_remove_and_add_terms():
    def alive(td, next_td):
        return torch.ones_like(next_td["reward"])

    terms = [JointPosTracking(), CallableTerm("alive", alive, weight=0.25), BodyVelTracking()]
    env = TransformedEnv(MockTocabiWalk(N), TaskReward(terms, weights={"qpos": 0.7}))
    ro = env.rollout(3)
    assert set(ro["next", "reward_terms"].keys()) == {"qpos", "alive", "body_vel"}
    torch.testing.assert_close(ro["next", "reward_terms", "alive"], torch.full((N, 3, 1), 0.25))
    torch.testing.assert_close(
        ro["next", "reward_terms", "qpos"], 2.0 * JointPosTracking()(ro.exclude("next"), ro["next"])
    )
    assert terms[0].weight == 0.35  # the caller's term is not modified
    # A plain named function is accepted as a weight-1 term.
    env2 = TransformedEnv(MockTocabiWalk(N), TaskReward([alive]))
    torch.testing.assert_close(env2.rollout(2)["next", "reward"], torch.ones(N, 2, 1))


def test_task_reward_errors_name_the_problem():
    with pytest.raises(KeyError, match="unknown term.*'qpoz'"):
        TaskReward(reference_terms(), weights={"qpoz": 1.0})
    with pytest.raises(ValueError, match="finite"):
        TaskReward(reference_terms(), weights={"qpos": float("nan")})
    with pytest.raises(ValueError, match="finite"):
        TaskReward(reference_terms(), weights={"qpos": "big"})
    with pytest.raises(ValueError, match="duplicate"):
        TaskReward([JointPosTracking(), JointPosTracking()])
    with pytest.raises(KeyError, match="known terms"):
        reference_terms(("qpos", "nope"))
    with pytest.raises(ValueError, match="CallableTerm"):
        TaskReward([lambda td, nxt: nxt["reward"]])
    with pytest.raises(ValueError, match="scale"):
        JointPosTracking(scale=-1.0)
    with pytest.raises(ValueError, match="torque_scale"):
        TorqueRegulation(torque_scale=(333.0,) * 5)
    bad = CallableTerm("wide", lambda td, nxt: torch.zeros(N, 2))
    env = TransformedEnv(MockTocabiWalk(N), TaskReward([bad]))
    with pytest.raises(ValueError, match="keepdim"):
        env.rollout(1)
    needs = CallableTerm("needs", lambda td, nxt: nxt["foot_slip"], next_keys=("foot_slip",))
    with pytest.raises(KeyError, match="foot_slip"):
        TransformedEnv(MockTocabiWalk(N), TaskReward([needs])).observation_spec


@pytest.mark.parametrize("key, error, message", [
    ("terminatd", KeyError, "zeroes the reward where 'terminatd' is True, and the step has no such key"),
    ("foot_contact", ValueError, rf"'foot_contact' must be \({N}, 1\) bool flags, got \({N}, 2\) torch.bool"),
    ("phase", ValueError, rf"'phase' must be \({N}, 1\) bool flags, got \({N}, 1\) torch.float32"),
])
def test_a_terminated_key_that_is_no_termination_flags_is_named_at_the_first_step(key, error, message):
    # A missing key failed inside torch.where with a bare TypeError; flags of another shape broadcast along the terms.
    env = TransformedEnv(MockTocabiWalk(N), TaskReward(reference_terms(), terminated_key=key))
    with pytest.raises(error, match=message):
        env.rollout(1)
    # Without zeroing nothing reads the key.
    env = TransformedEnv(MockTocabiWalk(N), TaskReward(reference_terms(), terminated_key=key, zero_on_terminated=False))
    assert env.rollout(1)["next", "reward"].shape == (N, 1, 1)


def test_per_joint_torque_scale_option():
    td, nxt = _pair()
    nxt["applied_action"][0, 0] = 1.0
    nxt["applied_action"][0, 5] = 1.0
    term = TorqueRegulation(torque_scale=tuple(float(x) for x in robot.LEG_TORQUE_LIMITS))
    _close(term(td, nxt), [0.05 * math.exp(-0.01 * math.hypot(333.0, 166.0)), 0.05, 0.05])


def test_wrong_signal_shape_is_reported_when_the_env_is_built():
    from torchrl.data import Unbounded

    class WrongForceShape(MockTocabiWalk):
        def _make_specs(self):
            super()._make_specs()
            spec = self.observation_spec.clone()
            spec["foot_force"] = Unbounded(shape=(N, 6))
            self.observation_spec = spec

    base = WrongForceShape(N)
    env = TransformedEnv(base, TaskReward(reference_terms()))
    with pytest.raises(ValueError, match=r"'foot_force' of shape \('num_envs', 2, 3\)"):
        env.observation_spec


def _mock_with_specs(**specs):
    """A mock env whose observation spec has these keys replaced or added: {key: per-env shape}."""
    from torchrl.data import Unbounded

    class Respecified(MockTocabiWalk):
        def _make_specs(self):
            super()._make_specs()
            spec = self.observation_spec.clone()
            for key, shape in specs.items():
                spec[key] = Unbounded(shape=(N, *shape))
            self.observation_spec = spec

    return Respecified(N)


@pytest.mark.parametrize("term, specs, message", [
    ("cycle_vel", {"cycle_vel_error": (1,)}, r"reward term 'cycle_vel' expects 'cycle_vel_error' of shape "
                                             r"\('num_envs', 2\).*spec has \(3, 1\)"),
    ("foot_gap", {"foot_pos": (6,)}, r"reward term 'foot_gap' expects 'foot_pos' of shape \('num_envs', 2, 3\)"),
    ("relax", {"kick_age": (), "kick_speed": ()}, r"kick_relax expects 'kick_age' of shape \('num_envs', 1\).*"
                                                  r"spec has \(3,\); fix the env signal$"),
])
def test_every_signal_a_term_reads_is_shape_checked_when_the_env_is_built(term, specs, message):
    # Only the signals the 13 reference terms read were checked: a (num_envs, 1) cycle_vel_error summed to a
    # plausible reward, and (num_envs,) kick signals broadcast along the terms.
    from torchrl.envs import Compose

    from tocabi_torchrl.transforms import BaseEulerAngles, CycleVelTracking, FootGap, KickRelax

    terms = {"cycle_vel": [CycleVelTracking(weight=1.0)], "foot_gap": [FootGap(weight=1.0)]}.get(
        term, reference_terms())
    relax = KickRelax(seconds=1.0, terms=("qpos",)) if term == "relax" else None
    env = TransformedEnv(_mock_with_specs(**specs), Compose(BaseEulerAngles(), TaskReward(terms, kick_relax=relax)))
    with pytest.raises(ValueError, match=message):
        env.observation_spec


def test_the_first_step_checks_the_shapes_of_the_signals_it_reads():
    # A step can write another shape than its spec says. With (num_envs,) kick signals and as many terms as envs,
    # the relaxation broadcast along the terms: no error, each env's terms scaled by the other envs' kicks.
    from tocabi_torchrl.transforms import KickRelax

    terms = reference_terms(("qpos", "body_vel", "orientation"))
    assert len(terms) == N
    reward = TaskReward(terms, kick_relax=KickRelax(seconds=2.0, terms=("qpos",)))
    td, nxt = _kicked_pair([0.0] * N, [1.0] * N)
    nxt["kick_age"] = nxt["kick_age"].squeeze(-1)
    with pytest.raises(ValueError, match=r"kick_relax expects 'kick_age' of shape \('num_envs', 1\).*but the "
                                         r"step's result holds \(3,\)"):
        reward._step(td, nxt)
    td, nxt = _pair()
    nxt["joint_pos"] = nxt["joint_pos"][:, :12]
    with pytest.raises(ValueError, match=r"reward term 'qpos' expects 'joint_pos' of shape \('num_envs', 33\)"):
        TaskReward(terms)._step(td, nxt)


def test_set_weight_changes_one_term_in_place():
    tr = TaskReward(reference_terms())
    env = TransformedEnv(MockTocabiWalk(N, seed=5), tr)
    tr.set_weight("qpos", 0.0)
    tr.set_weight("orientation", 0.6)
    ro = env.rollout(2)
    assert (ro["next", "reward_terms", "qpos"] == 0).all()
    torch.testing.assert_close(
        ro["next", "reward_terms", "orientation"], 2.0 * NeckOrientation()(ro.exclude("next"), ro["next"])
    )
    torch.testing.assert_close(ro["next", "reward"], sum(ro["next", "reward_terms", n] for n in REFERENCE_TERMS))
    with pytest.raises(KeyError, match="no term 'qpoz'"):
        tr.set_weight("qpoz", 1.0)



def test_a_clone_keeps_its_own_weights_and_kick_relaxation():
    # torchrl's clone is shallow: a clone shared the weights and relaxed-terms buffers, which set_weight and an env
    # without kicks change in place, so the original then computed the clone's weights under its own terms' names.
    from tocabi_torchrl.transforms import KickRelax

    relax = KickRelax(seconds=2.0, terms=("qpos",))
    original = TaskReward(reference_terms(), kick_relax=relax)
    copy = original.clone()
    copy.set_weight("qpos", 0.0)
    TransformedEnv(MockTocabiWalk(N), copy).rollout(1)  # no kicks: the copy's relaxation is off
    td, nxt = _kicked_pair([1.0] * N, [1.0] * N)
    got = original._weighted_terms(td, nxt)[:, original.names.index("qpos")]
    want = 0.5 * JointPosTracking()(td, nxt).squeeze(-1)  # half-way through a full kick's relaxation
    torch.testing.assert_close(got, want)
    assert copy.kick_relax is None and original.kick_relax is relax


def test_loaded_state_keeps_the_rewards_own_weights():
    # A checkpoint's weights were loaded over the env's: a resume with a term of one's own re-weighted, or the same
    # terms in another order, computed the saved weights while the terms and the repr named the new ones.
    saved = TaskReward([JointPosTracking(), BodyVelTracking()], weights={"qpos": 0.7}).state_dict()
    reward = TaskReward([BodyVelTracking(), JointPosTracking()], weights={"qpos": 0.0})
    env = TransformedEnv(MockTocabiWalk(N, seed=2), reward)
    reward.load_state_dict(saved)
    torch.testing.assert_close(reward._weights, torch.tensor([0.3, 0.0]))
    ro = env.rollout(2)
    assert (ro["next", "reward_terms", "qpos"] == 0).all()
    torch.testing.assert_close(ro["next", "reward_terms", "body_vel"],
                               BodyVelTracking()(ro.exclude("next"), ro["next"]))

@pytest.mark.slow
def test_compiled_reward_matches_eager():
    terms = [JointPosTracking(), FootContactPattern(), ForceDiffThresholdPenalty()]
    eager = TransformedEnv(MockTocabiWalk(N, seed=7, terminate_prob=0.3), TaskReward(terms))
    compiled = TransformedEnv(MockTocabiWalk(N, seed=7, terminate_prob=0.3), TaskReward(terms, compile=True))
    ro_e = eager.rollout(3, break_when_any_done=False)
    ro_c = compiled.rollout(3, break_when_any_done=False)
    assert compiled.transform._compiled is not None
    torch.testing.assert_close(ro_c["next", "reward"], ro_e["next", "reward"])
    torch.testing.assert_close(ro_c["next", "reward_terms"], ro_e["next", "reward_terms"])


# ------------------------------------------------------------------------------------------------ kick relaxation
def _kicked_pair(age: list[float], speed: list[float]) -> tuple[TensorDict, TensorDict]:
    td, nxt = _pair()
    nxt["kick_age"] = torch.tensor(age).unsqueeze(-1)
    nxt["kick_speed"] = torch.tensor(speed).unsqueeze(-1)
    return td, nxt


def test_a_kick_relaxes_the_named_terms_by_its_age_and_speed():
    from tocabi_torchrl.transforms import KickRelax

    relax = KickRelax(seconds=2.0, full_speed=1.0, terms=("qpos", "torque_diff"))
    plain, relaxed = TaskReward(reference_terms()), TaskReward(reference_terms(), kick_relax=relax)
    # Just kicked at full speed; half-way through at 1.4 m/s (clamped to 1); just kicked at 0.5 m/s; long ago.
    td, nxt = _kicked_pair([0.0, 1.0, 0.0, 5.0][:N], [1.0, 1.4, 0.5, 1.0][:N])
    want, got = plain._weighted_terms(td, nxt), relaxed._weighted_terms(td, nxt)
    factor = torch.tensor([0.0, 0.5, 0.5][:N]).unsqueeze(-1)
    names = plain.names
    for i, name in enumerate(names):
        expected = want[:, i:i + 1] * (factor if name in relax.terms else 1.0)
        torch.testing.assert_close(got[:, i:i + 1], expected, msg=name)
    # Past the relaxation (age >= seconds) every term is the plain one.
    td, nxt = _kicked_pair([2.0, 3.0, 9.0][:N], [1.0, 1.0, 1.0][:N])
    torch.testing.assert_close(relaxed._weighted_terms(td, nxt), plain._weighted_terms(td, nxt))


def test_kick_relaxation_is_off_without_kicks_and_refuses_bad_settings():
    from tocabi_torchrl.transforms import KickRelax

    # The mock env has no kicks (no kick_age / kick_speed): the relaxed reward is the plain one.
    relaxed = TransformedEnv(MockTocabiWalk(N, seed=3), TaskReward(reference_terms(), kick_relax=KickRelax(1.0)))
    plain = TransformedEnv(MockTocabiWalk(N, seed=3), TaskReward(reference_terms()))
    torch.manual_seed(0)  # the rollouts' random actions
    want = plain.rollout(3)["next", "reward"]
    torch.manual_seed(0)
    torch.testing.assert_close(relaxed.rollout(3)["next", "reward"], want)
    assert not KickRelax().enabled and TaskReward(reference_terms(), kick_relax=KickRelax()).kick_relax is None
    with pytest.raises(KeyError, match="qpoz.*not in use"):
        TaskReward(reference_terms(), kick_relax=KickRelax(1.0, terms=("qpoz",)))
    with pytest.raises(ValueError, match="kick_relax.seconds"):
        KickRelax(seconds=-1.0)
    with pytest.raises(ValueError, match="kick_relax.full_speed"):
        KickRelax(seconds=1.0, full_speed=0.0)
    with pytest.raises(TypeError, match="KickRelax"):
        TaskReward(reference_terms(), kick_relax={"seconds": 1.0})


@pytest.mark.parametrize("terms, message", [
    ("qpos", r"transforms.kick_relax.terms must be a tuple of reward term names, got 'qpos'; for one term give "
             r"\('qpos',\)"),
    (None, r"transforms.kick_relax.terms must be a tuple of reward term names, got None; e.g. \('qpos', "),
    (5, r"transforms.kick_relax.terms must be a tuple of reward term names, got 5"),
])
def test_kick_relax_terms_that_are_no_tuple_of_names_are_refused_by_name(terms, message):
    # One name was taken as its letters ('q', 'p', 'o', 's'), and None failed as a raw "not iterable" TypeError.
    from tocabi_torchrl.transforms import KickRelax

    with pytest.raises(ValueError, match=message):
        KickRelax(seconds=1.5, terms=terms)
    assert KickRelax(seconds=1.5, terms=["qpos", "qacc"]).terms == ("qpos", "qacc")


def test_a_reward_sum_in_front_of_the_reward_is_refused():
    # The bare env's reward is 0 by design: a RewardSum before TaskReward summed zeros into episode_reward, silently.
    from torchrl.envs import Compose, RewardSum

    from tocabi_torchrl.transforms import BaseEulerAngles, PhaseEncoding

    env = TransformedEnv(MockTocabiWalk(2), Compose(PhaseEncoding(), BaseEulerAngles(), RewardSum(),
                                                    TaskReward(reference_terms())))
    with pytest.raises(ValueError, match="RewardSum comes before TaskReward"):
        env.reset()
    env = TransformedEnv(MockTocabiWalk(2), Compose(PhaseEncoding(), BaseEulerAngles(), TaskReward(reference_terms()),
                                                    RewardSum()))
    assert env.rollout(3)["next", "episode_reward"].abs().sum() > 0



def test_a_second_task_reward_in_the_chain_is_refused():
    # Appended to a chain that has one, it replaced the reward with its own terms alone, without a word; the first's
    # terms were still logged as if they counted.
    from torchrl.envs import Compose, RewardSum

    alive = CallableTerm("alive", lambda td, nxt: torch.ones_like(nxt["reward"]), weight=0.05)
    for tail in ((TaskReward([alive]), RewardSum()), (RewardSum(), TaskReward([alive]))):
        env = TransformedEnv(MockTocabiWalk(2), Compose(TaskReward(reference_terms()), *tail))
        with pytest.raises(ValueError, match=r"a second TaskReward \(\['alive'\]\) comes after one of terms "
                                             r"\['orientation'.*give one TaskReward all the terms"):
            env.reset()
    # One with its own reward and terms keys is a second reward, not a replacement.
    other = TaskReward([alive], reward_key="alive_reward", terms_key="alive_terms")
    env = TransformedEnv(MockTocabiWalk(2), Compose(TaskReward(reference_terms()), other))
    assert env.rollout(2)["next", "reward"].abs().sum() > 0

def test_a_term_reading_an_undeclared_key_of_the_state_at_t_is_named():
    # It worked in env.rollout and failed in training, where the state at t holds only the declared keys, with a
    # KeyError from deep inside tensordict.
    term = CallableTerm("prev_height", lambda td, nxt: td["base_pos"][:, 2:3] * 0, weight=0.1)
    reward = TaskReward([term])
    td = TensorDict({"observation": torch.zeros(2, 3)}, batch_size=[2])
    nxt = TensorDict({"base_pos": torch.zeros(2, 3), "terminated": torch.zeros(2, 1, dtype=torch.bool)},
                     batch_size=[2])
    with pytest.raises(KeyError, match="reward term 'prev_height' reads a key its step does not hold.*root_keys"):
        reward._check_terms(td, nxt)


@pytest.mark.parametrize("fn,error,message", [
    # NaN made every reward NaN without a word; a float or a tensor of another device failed inside the sum
    # without the term's name; a complex tensor was silently cast to real.
    (lambda td, nxt: nxt["base_pos"][:, 2:3] / 0 * 0, ValueError, r"'bad' returned NaN or inf in every env at the"),
    (lambda td, nxt: 1.0, TypeError, r"'bad' returned a float; it must return a tensor of shape \(2, 1\)"),
    (lambda td, nxt: torch.zeros(2, 1, device="meta"), ValueError, r"'bad' returned a tensor on meta, the env"),
    (lambda td, nxt: torch.zeros(2, 1, dtype=torch.complex64), ValueError, r"'bad' returned torch.complex64"),
])
def test_a_term_returning_no_finite_real_tensor_of_the_envs_device_is_named(fn, error, message):
    reward = TaskReward([CallableTerm("bad", fn, weight=0.1)])
    td = TensorDict({}, batch_size=[2], device="cpu")
    nxt = TensorDict({"base_pos": torch.zeros(2, 3), "terminated": torch.zeros(2, 1, dtype=torch.bool)},
                     batch_size=[2], device="cpu")
    with pytest.raises(error, match=message):
        reward._check_terms(td, nxt)


class _PlainHeight(RewardTerm):
    """A term written as a plain subclass (class attributes, no dataclass): no ``__post_init__`` checks it."""

    name = "height"
    weight = 0.1
    next_keys = ("base_pos",)

    def kernel(self, td, next_td):
        return next_td["base_pos"][:, 2:3]


@pytest.mark.parametrize("make,error,message", [
    # The class itself is callable: it was taken for a function and failed at the first step, naming a TensorDict.
    (lambda: _PlainHeight, TypeError, r"got the class _PlainHeight as a term; pass an instance, e.g. _PlainHeight\(\)"),
    # A NaN weight made every reward NaN without a word; a missing name or kernel failed at the first step.
    (lambda: type("Nan", (_PlainHeight,), {"weight": float("nan")})(), ValueError, "'height' weight must be a finite"),
    (lambda: type("Text", (_PlainHeight,), {"weight": "0.1"})(), ValueError, "'height' weight must be a finite"),
    (lambda: type("Nameless", (_PlainHeight,), {"name": None})(), ValueError, "Nameless: name must be a non-empty"),
    (lambda: type("NoKernel", (RewardTerm,), {"name": "k", "weight": 1.0})(), TypeError, "does not implement kernel"),
    # A string of keys was read as its letters: "reads ['b', 'a', 's', 'e', ...]".
    (lambda: type("OneKey", (_PlainHeight,), {"next_keys": "base_pos"})(), TypeError, r"next_keys must be a tuple"),
    # The name is the metrics file's too: "a/b" wrote metrics/scalars/reward_terms/a/b.csv into a subfolder.
    (lambda: type("Slash", (_PlainHeight,), {"name": "a/b"})(), ValueError, r"names the term's metrics file too"),
])
def test_a_term_that_is_no_usable_instance_is_refused_when_the_reward_is_built(make, error, message):
    with pytest.raises(error, match=message):
        TaskReward([JointPosTracking(), make()])
    TaskReward([JointPosTracking(), _PlainHeight()])  # the plain subclass itself is a term
