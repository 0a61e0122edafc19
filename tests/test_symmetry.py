"""Left-right mirror symmetry (tocabi_torchrl/rl/symmetry.py): the joint signs from the MJCF, the maps being
involutions and normaliser-aware, the reference walk against itself half a cycle later, the physics against its
mirror image (C MuJoCo), and PPO's symmetry augmentation (the doubled mini-batch, a tiny training run)."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch
from graph_emulation import EmulatedCapture
from reference_data import reference_file
from tensordict import TensorDict

from lab.analysis.symmetric_model import MIRROR, partner, symmetric_spec
from tocabi_torchrl import make_env, robot
from tocabi_torchrl.config import PRESETS, field_choices, preset_config
from tocabi_torchrl.motion.reference import ReferenceMotion
from tocabi_torchrl.rl.resume import RESUME_SAFE
from tocabi_torchrl.rl.rollout_guard import VALID_KEY
from tocabi_torchrl.rl.symmetry import (
    PolicyInputMirror,
    SignedPermutation,
    SymmetryAugmentLoss,
    action_mirror_map,
    make_policy_input_mirror,
    mirror_qpos,
    mirror_qvel,
    obs_step_mirror_map,
)
from tocabi_torchrl.transforms.layouts import (OBS_LAYOUTS, REFERENCE_HISTORY, REFERENCE_OBS_LAYOUT, TOCABILAB_HISTORY,
                                               ObsComponent)
from tocabi_torchrl.transforms.normalize import REFERENCE_OBS_MEAN, REFERENCE_OBS_VAR
from tocabi_torchrl.transforms.privileged import PRIVILEGED_DIM, PRIVILEGED_MIRROR, PrivilegedState
from tocabi_torchrl.transforms.settings import TransformSettings, transform_config

# ------------------------------------------------------------------------------------------------------ the maps
def test_mirror_joints_and_signs_follow_the_mjcf_axes():
    """The reflection M turns a rotation by θ about the world axis a into one by −θ about M·a: a partner joint whose
    world axis is M·a takes −θ, one whose axis is −M·a takes +θ. Read from the compiled model at qpos0 (the Wrist2
    links' rotated body frames included), with each joint's anchor at the mirror image of its partner's."""
    model = robot.load_model()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    for j, name in enumerate(robot.JOINT_NAMES):
        assert robot.JOINT_NAMES[robot.MIRROR_JOINT[j]] == partner(name)
        a, p = model.joint(name).id, model.joint(partner(name)).id
        np.testing.assert_allclose(MIRROR @ data.xanchor[a], data.xanchor[p], atol=1e-9, err_msg=name)
        alignment = float((MIRROR @ data.xaxis[a]) @ data.xaxis[p])
        assert abs(abs(alignment) - 1.0) < 1e-9, name
        assert robot.MIRROR_SIGN[j] == -np.sign(alignment), name


def test_initial_pose_is_its_own_mirror_image():
    q = torch.as_tensor(robot.INIT_QPOS, dtype=torch.float64)[None]
    torch.testing.assert_close(mirror_qpos(q), q, rtol=0, atol=0)


@pytest.mark.parametrize("harmonics", [1, 2])
def test_maps_are_involutions(harmonics):
    g = torch.Generator().manual_seed(0)
    obs = SignedPermutation(*obs_step_mirror_map(REFERENCE_OBS_LAYOUT, harmonics))
    assert obs.dim == 35 + 2 * harmonics
    act = SignedPermutation(*action_mirror_map())
    for m in (obs, act):
        x = torch.randn(7, m.dim, generator=g)
        torch.testing.assert_close(m(m(x)), x, rtol=0, atol=0)
        assert not torch.allclose(m(x), x)
    # Non-symmetric statistics: the affine map of the normalised input is still its own inverse.
    loc, scale = torch.randn(37, generator=g), torch.rand(37, generator=g) + 0.5
    pin = PolicyInputMirror(TOCABILAB_HISTORY, loc=loc, scale=scale)
    x = torch.randn(5, 237, generator=g)
    torch.testing.assert_close(pin(pin(x)), x, rtol=1e-5, atol=1e-5)
    q = torch.randn(4, 40, generator=g, dtype=torch.float64)
    v = torch.randn(4, 39, generator=g, dtype=torch.float64)
    torch.testing.assert_close(mirror_qpos(mirror_qpos(q)), q, rtol=0, atol=0)
    torch.testing.assert_close(mirror_qvel(mirror_qvel(v)), v, rtol=0, atol=0)


def test_observation_and_action_maps_by_entry():
    perm, sign = obs_step_mirror_map()
    # roll, pitch, yaw; left hip yaw <- right hip yaw, flipped; left knee <- right knee; phase; vy; Fz; Mx; My.
    expect = {0: (0, -1), 1: (1, 1), 2: (2, -1), 3: (9, -1), 6: (12, 1), 21: (15, -1), 27: (27, -1), 28: (28, -1),
              29: (29, 1), 30: (30, -1), 31: (32, 1), 32: (31, 1), 33: (34, -1), 34: (33, -1), 35: (36, 1)}
    for i, (p, s) in expect.items():
        assert (perm[i], sign[i]) == (p, s), i
    perm, sign = action_mirror_map()
    assert perm[12] == 12 and sign[12] == 1.0 and perm[:6] == list(range(6, 12))


def test_policy_input_mirror_is_normalise_of_the_raw_mirror():
    """In normalised space the mirror is affine: equal to normalising the mirrored raw observations with the same
    (not exactly symmetric) reference statistics; the stored actions are raw."""
    g = torch.Generator().manual_seed(1)
    loc = torch.tensor(REFERENCE_OBS_MEAN)
    scale = torch.sqrt(torch.tensor(REFERENCE_OBS_VAR, dtype=torch.float64) + 1e-8).float()
    raw_obs = loc + scale * torch.randn(6, 5, 37, generator=g)
    actions = torch.rand(6, 4, 13, generator=g) * 2 - 1
    obs_m = SignedPermutation(*obs_step_mirror_map())
    act_m = SignedPermutation(*action_mirror_map())
    norm = lambda o: (o - loc) / scale
    policy_input = torch.cat((norm(raw_obs).flatten(1), actions.flatten(1)), dim=1)
    expected = torch.cat((norm(obs_m(raw_obs)).flatten(1), act_m(actions).flatten(1)), dim=1)
    mirror = PolicyInputMirror(REFERENCE_HISTORY, loc=loc, scale=scale)
    torch.testing.assert_close(mirror(policy_input), expected, rtol=1e-5, atol=2e-5)
    # The statistics matter (they are close to symmetric, not equal): without them the map is another one.
    assert not torch.allclose(PolicyInputMirror(REFERENCE_HISTORY)(policy_input), expected, atol=1e-3)


def test_running_statistics_reach_the_mirror():
    """With running normalisation the mirror follows the statistics the trainer refreshes before each update."""
    from tocabi_torchrl.rl.symmetry import find_normalization, refresh_statistics

    env = make_env(2, "cpu", seed=0, backend="mujoco", control_mode="torque", normalization="running")
    loss = SymmetryAugmentLoss(_Spy(), make_policy_input_mirror(env, transform_config("reference")),
                               SignedPermutation(*action_mirror_map()))
    td = env.reset()
    for _ in range(3):
        td["action"] = env.action_spec.zero()
        td = env.step(td)["next"]
    refresh_statistics(loss, env)
    loc, scale = find_normalization(env)._loc_scale()
    perm, sign = (torch.tensor(v) for v in obs_step_mirror_map())
    torch.testing.assert_close(loss.obs_mirror.gain[37:74], sign * scale[perm] / scale)
    torch.testing.assert_close(loss.obs_mirror.offset[:37], (sign * loc[perm] - loc) / scale)


def test_unknown_observation_block_is_refused():
    with pytest.raises(ValueError, match="no mirror rule for the observation block 'base_height'"):
        obs_step_mirror_map((*REFERENCE_OBS_LAYOUT, ObsComponent("base_height", "base_pos", (2,))))


def test_a_map_that_is_not_a_reflection_is_refused():
    with pytest.raises(ValueError, match="not an involution"):
        SignedPermutation([1, 0, 2], [1.0, -1.0, 1.0])


# ------------------------------------------------------------------------------------------ the reference motion
def _half_cycle_error(motion: ReferenceMotion) -> tuple[float, float]:
    """Max |mirror(q_ref(p)) − q_ref(p + 1/2)| [rad] over the legs and over the upper body, at 515 phases."""
    n = motion.cycle_rows
    t = torch.arange(0, n, 7, dtype=torch.float64) * motion.row_dt
    zero = torch.zeros(t.shape, dtype=torch.int64)
    q = motion.joint_targets(t.float(), zero).double()
    later = motion.joint_targets((t + 0.5 * n * motion.row_dt).float(), zero).double()
    sign = torch.tensor(robot.MIRROR_SIGN, dtype=torch.float64)
    err = (q[:, list(robot.MIRROR_JOINT)] * sign - later).abs()
    return float(err[:, robot.LEGS].max()), float(err[:, robot.UPPER_BODY].max())


def test_shipped_walk_is_its_own_mirror_image_half_a_cycle_later():
    """Measured 3.1 mrad on the legs (the cycle has an odd 3,599 rows, so half a cycle falls between rows), 0 on the
    upper body (the initial pose throughout)."""
    legs, upper = _half_cycle_error(ReferenceMotion.default())
    assert legs < 4e-3 and upper < 1e-6, (legs, upper)


def test_reference_walk_is_its_own_mirror_image_half_a_cycle_later():
    """The reference's text walk: measured 4.0 mrad on the legs (hip pitch), 0 on the upper body."""
    legs, upper = _half_cycle_error(ReferenceMotion.from_file(reference_file("processed_data_tocabi_walk.txt")))
    assert legs < 5e-3 and upper < 1e-6, (legs, upper)


# --------------------------------------------------------------------------------------------------- the physics


def _mirrored_pair_errors(model_path: str | None, mode: str, steps: int = 20,
                          backend: str = "mujoco", observation: str = "reference") -> dict[str, np.ndarray]:
    """Two worlds: world 0 walks 15 steps of random actions; world 1 is then put in its mirror image (qpos, qvel,
    controls, clock half a cycle on, command vy flipped, last action mirrored; both worlds' solvers cleared alike by
    the reset), and both step ``steps`` more times, world 1 with the mirrored actions. Returns per step the max error
    of world 1's observation against the mirror of world 0's: raw per-step observation by block, the policy input
    (from step 9 on, once the history holds only mirrored steps) and qpos. ``observation``: the per-step layout's
    name (``transforms.observation``)."""
    torch.manual_seed(0)
    env = make_env(2, "cpu", seed=3, backend=backend, control_mode=mode, model_path=model_path,
                   transforms=TransformSettings(observation=observation))
    base, sim = env.base_env, env.base_env.sim
    obs_m = SignedPermutation(*obs_step_mirror_map(OBS_LAYOUTS[observation]))
    act_m = SignedPermutation(*action_mirror_map())
    pin = make_policy_input_mirror(env, transform_config("reference", obs_layout=OBS_LAYOUTS[observation]))

    def action(n: int) -> torch.Tensor:
        a = torch.empty(n, 13)
        a[:, :12].uniform_(-0.3, 0.3)
        a[:, 12].uniform_(0.0, 1.0)
        return a

    td = env.reset()
    for _ in range(15):
        td["action"] = action(2)
        td = env.step(td)["next"]
    qpos, qvel, ctrl = sim.qpos.clone(), sim.qvel.clone(), sim.ctrl.clone()
    qpos[1], qvel[1] = mirror_qpos(qpos[:1])[0], mirror_qvel(qvel[:1])[0]
    ctrl[1] = ctrl[0, list(robot.MIRROR_JOINT)] * torch.tensor(robot.MIRROR_SIGN)
    sim.reset(torch.ones(2, dtype=torch.bool), qpos, qvel, ctrl)
    motion = base.motion
    base.init_row[1] = base.init_row[0]
    base.time[1] = torch.remainder(base.time[0] + 0.5 * motion.cycle_rows * motion.row_dt, motion.period)
    base.episode_step[1] = base.episode_step[0]
    base.command.value[1] = base.command.value[0] * torch.tensor([1.0, -1.0])
    base.applied_action[1] = act_m(base.applied_action[:1])[0]
    blocks = {"rpy": slice(0, 3), "joint_pos": slice(3, 15), "joint_vel": slice(15, 27), "phase": slice(27, 29),
              "command": slice(29, 31), "foot_force_z": slice(31, 33), "foot_moments": slice(33, 37)}
    if observation == "base_vel":
        blocks |= {"base_lin_vel": slice(37, 40), "base_ang_vel": slice(40, 43)}
    errors: dict[str, list[float]] = {k: [] for k in (*blocks, "policy_input", "qpos", "privileged")}
    priv_m, priv = SignedPermutation(*PRIVILEGED_MIRROR), PrivilegedState()
    for k in range(steps):
        a = action(1)
        td["action"] = torch.cat((a, act_m(a)))
        td = env.step(td)["next"]
        assert not td["done"].any(), "a world fell: the comparison needs both standing"
        o = td["obs_step"]
        err = (obs_m(o[:1]) - o[1:])[0].abs()
        for name, sl in blocks.items():
            errors[name].append(float(err[sl].max()))
        if k >= 9:
            p = td["observation"]
            errors["policy_input"].append(float((pin(p[:1]) - p[1:]).abs().max()))
        errors["qpos"].append(float((mirror_qpos(sim.qpos[:1]) - sim.qpos[1:]).abs().max()))
        v = priv._call(td.clone())["privileged"]  # the asymmetric critic's true-state input
        errors["privileged"].append(float((priv_m(v[:1]) - v[1:]).abs().max()))
    return {k: np.asarray(v) for k, v in errors.items()}


#: Bounds of the symmetric model's errors per backend. C MuJoCo (float64): measured 0 but for the phase's float32
#: clock (~1e-7). mujoco-warp on the CPU (float32): measured qpos 1.2e-7, joint velocity 1.6e-6 rad/s, foot Fz
#: 2.7e-3 N, policy input 3.7e-5 (2026-12-02).
_SYMMETRIC_BOUNDS = {
    "mujoco": {"rpy": 1e-6, "joint_pos": 1e-6, "joint_vel": 1e-6, "phase": 1e-6, "command": 0.0,
               "foot_force_z": 1e-6, "foot_moments": 1e-6, "qpos": 1e-6, "policy_input": 1e-5, "privileged": 1e-5},
    "warp": {"rpy": 1e-5, "joint_pos": 1e-5, "joint_vel": 1e-4, "phase": 1e-6, "command": 0.0,
             "foot_force_z": 0.05, "foot_moments": 0.05, "qpos": 1e-5, "policy_input": 1e-3, "privileged": 1e-3},
}


@pytest.mark.parametrize("backend", ["mujoco", "warp"])
def test_physics_is_mirror_equivariant_on_a_symmetric_model(tmp_path, backend):
    """What proves the signs: on an exactly symmetric copy of the model the mirrored world stays the mirror image
    over 20 policy steps with contacts: bit for bit in qpos, joint and foot readings on C MuJoCo, to float32 rounding
    on mujoco-warp (the training backend). A wrong sign anywhere (joint, base, command, foot moment) shows as an
    O(1) error (a flipped Mx sign: 124 N·m)."""
    if backend == "warp":
        from warp_cpu import warp_cpu_available

        if not warp_cpu_available():
            pytest.skip("warp's CPU device is not available")
    path = tmp_path / "tocabi_symmetric.xml"
    path.write_text(symmetric_spec().to_xml())
    errors = _mirrored_pair_errors(str(path), "torque", backend=backend)
    for name, bound in _SYMMETRIC_BOUNDS[backend].items():
        assert errors[name].max() <= bound, (name, errors[name])


def test_the_pelvis_velocity_observation_mirrors_with_the_physics(tmp_path):
    """The ``base_vel`` layout's mirror rules (linear velocity (x, -y, z), angular (-x, y, -z) in the pelvis frame)
    against the physics: on the exactly symmetric model the mirrored world's pelvis velocities are the mirror of the
    first world's to float64 rounding (C MuJoCo), and so is the whole 267-value policy input. A wrong sign is an
    error the size of the velocity (0.1-1 m/s, rad/s) after 20 steps of random actions."""
    path = tmp_path / "tocabi_symmetric.xml"
    path.write_text(symmetric_spec().to_xml())
    errors = _mirrored_pair_errors(str(path), "torque", observation="base_vel")
    for name in ("base_lin_vel", "base_ang_vel", "rpy", "joint_vel", "qpos", "policy_input"):
        assert errors[name].max() <= _SYMMETRIC_BOUNDS["mujoco"].get(name, 1e-6), (name, errors[name])


def test_physics_of_the_authored_model_is_nearly_mirror_equivariant():
    """The authored MJCF (the real robot's link inertials: e.g. Waist2's centre of mass 18 mm off the mid-plane, the
    knees' 4 mm the same side on both legs; R_Shoulder1's damping 5.0 against 3.0) is not exactly symmetric, so its
    mirrored world drifts. Measured over 20 steps (2026-12-02): qpos 2.3e-4, joint positions 2.3e-4 rad, joint
    velocities 7.2e-2 rad/s, foot Fz up to 94 N at a touch-down (a contact's timing), policy input 0.59 (normalised
    units, from the forces). Bounds at about twice that."""
    errors = _mirrored_pair_errors(None, "torque")
    assert errors["qpos"].max() < 5e-4, errors["qpos"]
    assert errors["joint_pos"].max() < 5e-4, errors["joint_pos"]
    assert errors["joint_vel"].max() < 0.15, errors["joint_vel"]
    assert errors["rpy"].max() < 5e-4, errors["rpy"]
    assert errors["foot_force_z"].max() < 200.0, errors["foot_force_z"]


# ------------------------------------------------------------------------------------------------ PPO augmentation
class _Spy(torch.nn.Module):
    """A loss that records the batch it sees and returns one trainable loss_* term."""

    in_keys = ("observation", "action", "action_log_prob")

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.ones(()))
        self.seen = None

    def forward(self, td):
        self.seen = td.clone()
        return TensorDict({"loss_objective": self.w * td["observation"].mean(), "loss_critic": self.w * 0,
                           "kl_approx": self.w.detach() * 0, "clip_fraction": self.w.detach() * 0}, [])


def _batch(n: int, g: torch.Generator, privileged: bool = False) -> TensorDict:
    extra = {"privileged": torch.randn(n, PRIVILEGED_DIM, generator=g)} if privileged else {}
    return TensorDict({
        **extra,
        "observation": torch.randn(n, 237, generator=g),
        "action": torch.rand(n, 13, generator=g) * 2 - 1,
        "action_log_prob": -torch.rand(n, generator=g),
        "advantage": torch.randn(n, 1, generator=g),
        "value_target": torch.randn(n, 1, generator=g),
        "state_value": torch.randn(n, 1, generator=g),
        VALID_KEY: torch.rand(n, 1, generator=g) > 0.1,
    }, [n])


def test_the_loss_sees_the_doubled_mirrored_batch():
    g = torch.Generator().manual_seed(2)
    pin = PolicyInputMirror(REFERENCE_HISTORY, loc=torch.tensor(REFERENCE_OBS_MEAN),
                            scale=torch.tensor(REFERENCE_OBS_VAR).sqrt())
    act = SignedPermutation(*action_mirror_map())
    spy = _Spy()
    loss = SymmetryAugmentLoss(spy, pin, act)
    assert loss.in_keys == list(spy.in_keys)
    td = _batch(16, g)
    loss(td)
    seen = spy.seen
    assert seen.batch_size == torch.Size([32])
    torch.testing.assert_close(seen[:16].to_dict(), td.to_dict(), rtol=0, atol=0)
    torch.testing.assert_close(seen["observation"][16:], pin(td["observation"]), rtol=0, atol=0)
    torch.testing.assert_close(seen["action"][16:], act(td["action"]), rtol=0, atol=0)
    assert not torch.allclose(seen["observation"][16:], td["observation"])
    for key in ("action_log_prob", "advantage", "value_target", "state_value", VALID_KEY):
        torch.testing.assert_close(seen[key][16:], td[key], rtol=0, atol=0)


def test_the_mirror_loss_measures_and_pulls_the_mean_action_towards_symmetry():
    from tocabi_torchrl.rl.actors import gaussian_head, make_actor

    g = torch.Generator().manual_seed(3)
    torch.manual_seed(3)
    pin = PolicyInputMirror(REFERENCE_HISTORY, loc=torch.tensor(REFERENCE_OBS_MEAN),
                            scale=torch.tensor(REFERENCE_OBS_VAR).sqrt())
    act = SignedPermutation(*action_mirror_map())
    head = gaussian_head(make_actor(237, 13, hidden=(16,)))
    td = _batch(32, g)
    spy = _Spy()
    spy.loss_mask_key = VALID_KEY
    assert "loss_symmetry" not in SymmetryAugmentLoss(spy, pin, act, head).forward(td).keys()
    loss = SymmetryAugmentLoss(spy, pin, act, head, mirror_loss=2.0)
    with torch.no_grad():
        gap = (head(pin(td["observation"]))[0] - act(head(td["observation"])[0])).square().mean(-1)
    valid = td[VALID_KEY].reshape(-1)
    assert not valid.all() and valid.any()
    expected = 2.0 * gap[valid].mean()  # frames the PPO loss masks out are left out here too
    first = loss(td)["loss_symmetry"]
    torch.testing.assert_close(first, expected)
    assert first > 0  # a random network is not symmetric
    # Its gradient makes the policy more symmetric (the mirrored side moves, the target is held fixed).
    opt = torch.optim.Adam(head.parameters(), lr=0.01)
    for _ in range(30):
        opt.zero_grad()
        loss(td)["loss_symmetry"].backward()
        opt.step()
    assert loss(td)["loss_symmetry"] < 0.5 * first
    with pytest.raises(ValueError, match="needs the actor's head"):
        SymmetryAugmentLoss(spy, pin, act, mirror_loss=1.0)
    with pytest.raises(ValueError, match="ppo.symmetry_loss > 0 works with ppo.symmetry='augment'"):
        preset_config("torque_ideal", **{"ppo.symmetry_loss": 0.5})
    for bad in (-1.0, float("inf"), True):
        with pytest.raises(ValueError, match="ppo.symmetry_loss must be"):
            preset_config("robust", **{"ppo.symmetry_loss": bad})
    assert preset_config("robust", **{"ppo.symmetry_loss": 0.5}).ppo.symmetry_loss == 0.5


def test_every_mirror_buffer_lives_on_the_mirrors_device():
    # Nothing moves the loss module to the env's device: each buffer it makes must start where the mirrors are (a
    # CPU-made privileged map broke the first CUDA update). The meta device stands in for CUDA on a CPU machine.
    act = SignedPermutation(*action_mirror_map()).to("meta")
    loss = SymmetryAugmentLoss(_Spy(), SignedPermutation(*obs_step_mirror_map()).to("meta"), act)
    assert {b.device.type for b in loss.buffers()} == {"meta"}
    out = loss.mirror_batch(TensorDict({"privileged": torch.empty(4, PRIVILEGED_DIM, device="meta")}, [4]))
    assert out["privileged"].device.type == "meta"


def test_the_logged_kl_and_clip_fraction_are_the_original_halfs():
    """The KL-adaptive learning rate reads kl_approx: it is the original frames' (as in rsl_rl), not the mirrored
    frames', whose ratio measures the policy's asymmetry. Old log-probs = the current policy's: their KL is 0, while
    the whole doubled batch's is not (an untrained policy is not symmetric)."""
    from torchrl.objectives import ClipPPOLoss

    from tocabi_torchrl.rl.trainer import build_agent

    torch.manual_seed(0)
    agent = build_agent(preset_config("cpu_smoke"), 237, 13, torch.device("cpu"))
    inner = ClipPPOLoss(agent.actor, agent.critic, clip_epsilon=0.2, normalize_advantage=True)
    inner.set_keys(sample_log_prob="action_log_prob")
    loss = SymmetryAugmentLoss(inner, PolicyInputMirror(), SignedPermutation(*action_mirror_map()))
    td = _batch(64, torch.Generator().manual_seed(6))
    with torch.no_grad():
        td["action_log_prob"] = agent.actor.get_dist(td.select("observation")).log_prob(td["action"])
        out = loss(td)
        doubled = torch.cat([td, loss.mirror_batch(td)], dim=0)
        whole = inner(doubled)
    assert abs(float(out["kl_approx"])) < 1e-5 and float(out["clip_fraction"]) == 0.0
    assert abs(float(whole["kl_approx"])) > 1e-3 and float(whole["clip_fraction"]) > 0.0
    torch.testing.assert_close(out["loss_objective"], whole["loss_objective"])


def test_a_key_without_a_mirror_rule_is_refused():
    g = torch.Generator().manual_seed(3)
    loss = SymmetryAugmentLoss(_Spy(), PolicyInputMirror(), SignedPermutation(*action_mirror_map()))
    td = _batch(4, g)
    td["joint_pos"] = torch.zeros(4, 33)
    with pytest.raises(KeyError, match="'joint_pos'"):
        loss(td)


def test_the_replayed_update_step_takes_the_doubled_batch():
    """The mini-batch step's static-buffer replay (CUDA graph wiring, emulated on the CPU) with the augmented loss
    gives the eager step's parameters: the doubled batch has a fixed size."""
    from tocabi_torchrl.rl.update_step import MinibatchStep

    g = torch.Generator().manual_seed(4)
    batches = [_batch(16, g) for _ in range(6)]
    params = []
    for capturer in (None, EmulatedCapture()):
        torch.manual_seed(0)
        spy = _Spy()
        loss = SymmetryAugmentLoss(spy, PolicyInputMirror(), SignedPermutation(*action_mirror_map()))
        opt = torch.optim.Adam(spy.parameters(), lr=0.1)
        step = (MinibatchStep(loss, opt, list(spy.parameters()), 1.0) if capturer is None else
                MinibatchStep(loss, opt, list(spy.parameters()), 1.0, use_graph=True, capturer=capturer))
        for mb in batches:
            step(mb)
        assert capturer is None or step.captured
        params.append(spy.w.detach().clone())
    torch.testing.assert_close(params[0], params[1], rtol=0, atol=0)


# ----------------------------------------------------------------------------------------------------- the config
def test_symmetry_is_off_in_every_preset_but_the_robust_recipe_and_not_resume_safe():
    assert field_choices()["ppo.symmetry"] == ("none", "augment", "equivariant")
    for name in PRESETS:  # the robust recipe mirrors its mini-batches for a gait without a sideways bias
        robust_recipe = name in ("robust", "torque", "model_based", "pd")
        assert preset_config(name).ppo.symmetry == ("augment" if robust_recipe else "none"), name
    assert "ppo.symmetry" not in RESUME_SAFE
    with pytest.raises(ValueError, match="ppo.symmetry must be one of"):
        preset_config("cpu_smoke", **{"ppo.symmetry": "mirror"})


def test_cpu_smoke_training_with_symmetry_augment(tmp_path, monkeypatch):
    from tocabi_torchrl.rl.trainer import train

    calls = []
    mirror_batch = SymmetryAugmentLoss.mirror_batch
    monkeypatch.setattr(SymmetryAugmentLoss, "mirror_batch",
                        lambda self, td: calls.append(td.batch_size) or mirror_batch(self, td))

    cfg = preset_config("cpu_smoke", device="cpu", **{"ppo.symmetry": "augment", "env.num_envs": 4,
                                                      "ppo.steps_per_env": 8, "ppo.minibatch_size": 16},
                        total_env_steps=64, run_dir=str(tmp_path), name="sym", progress_bar=False,
                        eval_at_end=False)
    result = train(cfg)
    assert result.iterations == 2 and np.isfinite(result.last_metrics["loss_policy"])
    assert (tmp_path / "sym" / "checkpoints" / "iter_000002.pt").is_file()
    # 2 iterations × 2 epochs × (32 frames / 16) mini-batches, each mirrored once.
    assert calls == [torch.Size([16])] * 8


def test_symmetry_sits_inside_the_torque_assist_loss():
    """With the torque assist the absorbing term wraps the augmented PPO loss; the trainer's mini-batch (the assist's
    loc, scale and leg_assist included) goes through both."""
    from tocabi_torchrl.rl.assist import AssistAbsorbLoss
    from tocabi_torchrl.rl.trainer import build_agent, build_env, make_loss

    cfg = preset_config("torque_ideal", device="cpu", **{"ppo.symmetry": "augment", "env.num_envs": 2,
                                                   "ppo.minibatch_size": 16, "ppo.steps_per_env": 8,
                                                   "ppo.actor_hidden": (16,), "ppo.critic_hidden": (16,),
                                                   "env.sim.backend": "mujoco"})
    env = build_env(cfg, torch.device("cpu"), for_training=True)
    agent = build_agent(cfg, 237, 13, torch.device("cpu"))
    loss, _ = make_loss(cfg, agent, env)
    assert isinstance(loss, AssistAbsorbLoss) and isinstance(loss.ppo_loss, SymmetryAugmentLoss)
    g = torch.Generator().manual_seed(5)
    td = _batch(8, g)
    td["loc"], td["scale"] = torch.randn(8, 13, generator=g), torch.rand(8, 13, generator=g) + 0.1
    td["next", "leg_assist"] = torch.randn(8, 12, generator=g)
    td["next", "observation"] = torch.randn(8, 237, generator=g)
    for key in (("next", "reward"), ("next", "done"), ("next", "terminated")):
        td[key] = torch.zeros(8, 1, dtype=torch.float32 if key[1] == "reward" else torch.bool)
    mirrored = loss.ppo_loss.mirror_batch(td)
    torch.testing.assert_close(mirrored["next", "leg_assist"][:, 0], -td["next", "leg_assist"][:, 6])
    torch.testing.assert_close(mirrored["scale"][:, :6], td["scale"][:, 6:12])
    base = env.base_env
    loss.set_step(base.assist_gain(1.0), base.assist_gain(0.9), 1.0, 0.9, 1.0)  # the fade: the term is computed
    out = loss(td)
    assert torch.isfinite(out["loss_objective"]) and torch.isfinite(out["loss_absorb"]) and out["loss_absorb"] > 0
    with pytest.raises(ValueError, match="pass the training env"):
        make_loss(cfg, agent)


def _augmented_update_steps(device: str, graphs: tuple[bool, ...], privileged: bool = False,
                            symmetry: str = "augment"):
    """The trainer's mini-batch step with ``ppo.symmetry`` ``symmetry`` on a 64-env default-preset env, one per entry
    of ``graphs`` (``ppo.update_graph``), each with its agent built from the same seed; ``privileged``: with the
    asymmetric critic (``ppo.critic_privileged``)."""
    from tocabi_torchrl.rl.symmetry import set_equivariant_statistics
    from tocabi_torchrl.rl.trainer import build_agent, build_env, make_loss, make_optimizer, make_update_step

    dev, made = torch.device(device), []
    for graph in graphs:
        cfg = preset_config("default", device=device, **{
            "ppo.symmetry": symmetry, "env.num_envs": 64, "ppo.minibatch_size": 128, "ppo.steps_per_env": 8,
            "ppo.actor_hidden": (32, 16), "ppo.critic_hidden": (32, 16), "ppo.update_graph": graph,
            "ppo.critic_privileged": privileged})
        env = build_env(cfg, dev, for_training=True)
        torch.manual_seed(0)
        agent = build_agent(cfg, env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1], dev)
        set_equivariant_statistics(agent.actor, env)
        loss, _ = make_loss(cfg, agent, env)
        made.append((make_update_step(cfg, loss, make_optimizer(cfg, agent, dev), dev), agent))
    return made


def _agent_params(agent) -> torch.Tensor:
    return torch.cat([p.detach().flatten() for p in (*agent.actor.parameters(), *agent.critic.parameters())])


@pytest.mark.parametrize("privileged", [False, True])
def test_the_trainers_augmented_update_step_runs_the_doubled_batch_on_the_cpu(privileged):
    # The same wiring as the GPU test below, eagerly: the trainer's loss, optimiser and step take the mini-batch.
    ((step, agent),) = _augmented_update_steps("cpu", (False,), privileged)
    before = _agent_params(agent).clone()
    step(_batch(128, torch.Generator().manual_seed(6), privileged))
    assert not torch.equal(_agent_params(agent), before)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("privileged", [False, True])
def test_the_captured_augmented_update_replays_without_host_syncs_and_matches_eager(privileged):
    """On CUDA the augmented update step is one captured graph after its warm-up: it replays without a host
    synchronisation (the mirror is a gather and a multiply-add on the device) and gives the eager step's parameters
    to float32 rounding; with the asymmetric critic too."""
    _replays_without_syncs_as_eager(_augmented_update_steps("cuda", (False, True), privileged), privileged)


def _replays_without_syncs_as_eager(steps, privileged: bool = False) -> None:
    """An eager and a graphed update step (``_augmented_update_steps`` on CUDA): warm-up, capture, then a replay
    under ``set_sync_debug_mode("error")``; both end with the same parameters to float32 rounding."""
    (eager, eager_agent), (graphed, graph_agent) = steps
    assert graphed.use_graph
    g = torch.Generator().manual_seed(6)
    batches = [_batch(128, g, privileged).to("cuda") for _ in range(6)]
    for mb in batches[:-1]:  # eager warm-up steps, the capture, then replays
        eager(mb)
        graphed(mb)
    assert graphed.captured
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        graphed(batches[-1])
    finally:
        torch.cuda.set_sync_debug_mode("default")
    eager(batches[-1])
    torch.testing.assert_close(_agent_params(graph_agent), _agent_params(eager_agent), rtol=1e-4, atol=1e-5)


def test_the_trainers_update_step_with_an_equivariant_actor_on_the_cpu():
    ((step, agent),) = _augmented_update_steps("cpu", (False,), symmetry="equivariant")
    before = _agent_params(agent).clone()
    step(_batch(128, torch.Generator().manual_seed(6)))
    assert not torch.equal(_agent_params(agent), before)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_the_captured_update_with_an_equivariant_actor_replays_without_host_syncs_and_matches_eager():
    """The equivariant actor's two passes (a stack, the mirror's gather and multiply-add, the clip) inside the
    captured update step: it replays without a host synchronisation and gives the eager step's parameters."""
    _replays_without_syncs_as_eager(_augmented_update_steps("cuda", (False, True), symmetry="equivariant"))


@pytest.mark.parametrize("normalization, refreshes", [("running", 2), ("fixed", 0)])
def test_the_trainer_refreshes_the_mirror_only_for_moving_statistics(tmp_path, monkeypatch, normalization, refreshes):
    # A running normaliser moves during each rollout: the mirror takes its statistics before each update. Fixed ones
    # never move, so the mirror keeps what make_loss gave it.
    from tocabi_torchrl.rl import trainer

    calls = []
    refresh = trainer.refresh_statistics
    monkeypatch.setattr(trainer, "refresh_statistics", lambda loss, env: calls.append(1) or refresh(loss, env))
    cfg = preset_config("cpu_smoke", device="cpu", **{"ppo.symmetry": "augment", "env.num_envs": 4,
                                                      "ppo.steps_per_env": 8, "ppo.minibatch_size": 16,
                                                      "transforms.normalization": normalization},
                        total_env_steps=64, run_dir=str(tmp_path), name="sym", progress_bar=False,
                        eval_at_end=False)
    assert trainer.train(cfg).iterations == 2
    assert len(calls) == refreshes
