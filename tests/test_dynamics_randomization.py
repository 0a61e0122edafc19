"""Per-world dynamics randomisation (tocabi_torchrl.sim.dynamics): the draws, their isolation between worlds, their
effect on the physics, on both backends; off changes nothing (tests/test_control_regression.py replays the default
env bit for bit)."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import pytest
import torch
from tensordict import TensorDict

from tocabi_torchrl import make_env, robot
from tocabi_torchrl.envs import TocabiWalk, TocabiWalkConfig
from tocabi_torchrl.sim import MujocoSim, SimConfig
from tocabi_torchrl.sim.config import PER_WORLD_FIELDS
from tocabi_torchrl.sim.dynamics import DynamicsRandomization, WorldDynamics
from warp_cpu import warp_cpu_available

FULL = DynamicsRandomization(mass_scale=(0.8, 1.2), joint_damping=(0.0, 2.9), armature_scale=(0.8, 1.2),
                             friction_scale=(0.4, 1.0))
BACKENDS = ["mujoco", pytest.param("warp", marks=pytest.mark.skipif(not warp_cpu_available(),
                                                                   reason="warp's CPU device is unavailable"))]
TOP = 1.0 - 2.0**-24  # the largest uniform episode_uniform returns


@pytest.fixture(scope="module")
def mj():
    return robot.load_model()


def nominal_sim(mj, n):
    """A stand-in simulator for the draw alone: the model and its fields as (n, ...) float32 rows."""
    fields = {name: torch.as_tensor(getattr(mj, name), dtype=torch.float32).expand(n, *getattr(mj, name).shape)
              .clone() for name in PER_WORLD_FIELDS}
    return SimpleNamespace(mj_model=mj, num_worlds=n, device=torch.device("cpu"), model_fields=fields)


def drawn(sim, cfg, u):
    dyn = WorldDynamics(cfg)
    dyn.setup(sim)
    dyn.reset(torch.ones(sim.num_worlds, dtype=torch.bool), u(dyn.draws) if callable(u) else u)
    return dyn


def two_worlds(cfg):
    """A C MuJoCo simulator of 2 worlds: world 0 drew every range's low end, world 1 its high end."""
    sim = MujocoSim(SimConfig(num_worlds=2, threads=1, per_world_fields=cfg.sim_fields))
    drawn(sim, cfg, lambda k: torch.tensor([[0.0] * k, [TOP] * k]))
    return sim


def start_state(mj, qvel=None):
    """The initial pose at rest (or ``qvel``), legs unpowered, upper-body servos holding the pose."""
    q0 = torch.as_tensor(robot.INIT_QPOS, dtype=torch.float32)
    ctrl = torch.zeros(mj.nu)
    ctrl[robot.NUM_LEG_JOINTS:] = q0[7 + robot.NUM_LEG_JOINTS:]
    return q0, torch.zeros(mj.nv) if qvel is None else qvel, ctrl


def env_config(dynamics=FULL, **flat):
    return dataclasses.replace(TocabiWalkConfig(), dynamics=dynamics).with_flat(**flat)


def step(env, action):
    return env.step(TensorDict({"action": action}, batch_size=[env.num_envs]))["next"]


# ---------------------------------------------------------------------------------------------------------- config
def test_defaults_are_off_and_bad_ranges_name_their_path():
    off = DynamicsRandomization()
    assert not off.enabled and off.sim_fields == ()
    assert TocabiWalkConfig().dynamics == off
    assert FULL.sim_fields == PER_WORLD_FIELDS
    assert DynamicsRandomization(friction_scale=(0.4, 1.0)).sim_fields == ("geom_friction",)
    for bad in (dict(mass_scale=(0.0, 1.2)), dict(mass_scale=(1.2, 0.8)), dict(joint_damping=(-1.0, 1.0)),
                dict(armature_scale=(1.0, float("inf"))), dict(friction_scale=(0.5,))):
        name = next(iter(bad))
        with pytest.raises(ValueError, match=f"env.dynamics.{name}"):
            env_config(DynamicsRandomization(**bad)).validate()
    with pytest.raises(ValueError, match="per_world_fields"):
        SimConfig(per_world_fields=("body_pos",)).validate()


@pytest.mark.parametrize("name, bound", [("mass_scale", 5.0), ("joint_damping", 100.0), ("armature_scale", 5.0),
                                         ("friction_scale", 5.0)])
def test_a_range_past_its_sanity_bound_is_refused_alike_by_the_env_the_runtime_and_a_contract(mj, name, bound):
    # mass_scale=(0.8, 12), a typo for 1.2, ran on every path and simulated a robot 12x its weight. One rule
    # (value_rules.DYNAMICS_RANGES) for the training config, the torch-free runtime's settings and a contract's
    # trained_under section: the bound itself is taken by all three, above it refused by all three, by name.
    from tocabi_torchrl.runtime import randomization as rnd
    from tocabi_torchrl.value_rules import trained_under_problems

    section = rnd.trained_under_section(rnd.Randomization(), rnd.PushSettings(), rnd.StartVelocity(), 0.0005, 104.5)
    ok, bad = (0.5, bound), (0.5, bound * 2.4)
    DynamicsRandomization(**{name: ok}).validate()
    rnd.DynamicsSettings(**{name: ok}).validate()
    assert trained_under_problems({**section, "dynamics": {**section["dynamics"], name: {"range": list(ok)}}}) == []
    why = rf"above the bound {bound:g}; .*a typo\?"
    with pytest.raises(ValueError, match=rf"env.dynamics.{name} is \(0.5, {bad[1]}\), {why}"):
        DynamicsRandomization(**{name: bad}).validate()
    with pytest.raises(ValueError, match=rf"^dynamics.{name} is \(0.5, {bad[1]}\), {why}"):
        rnd.WorldDynamics(rnd.DynamicsSettings(**{name: bad}), mj)  # a given Randomization is checked too
    problems = trained_under_problems({**section, "dynamics": {**section["dynamics"], name: {"range": list(bad)}}})
    assert len(problems) == 1 and problems[0].startswith(f"trained_under.dynamics.{name}.range is [0.5, {bad[1]}] "
                                                         f"but each end must be a finite number ")
    assert problems[0].endswith("a typo?") and f"{bound:g}]" in problems[0]


def test_a_simulator_without_the_fields_is_refused(mj):
    sim = MujocoSim(SimConfig(num_worlds=1, threads=1))
    assert sim.model_fields == {}
    with pytest.raises(ValueError, match=r"per_world_fields=\('geom_friction',\)"):
        WorldDynamics(DynamicsRandomization(friction_scale=(0.5, 1.0))).setup(sim)


# ----------------------------------------------------------------------------------------------------- the draws
def test_each_field_follows_its_distribution_and_the_worlds_differ(mj):
    n = 4096
    sim = nominal_sim(mj, n)
    dyn = drawn(sim, FULL, lambda k: torch.rand(n, k, generator=torch.Generator().manual_seed(0)))
    f = sim.model_fields
    bodies, dofs = dyn.bodies, dyn.dofs
    assert len(bodies) == mj.nbody - 1 and len(dofs) == robot.NUM_JOINTS and dofs[0] == 6
    assert dyn.draws == len(bodies) + 2 * len(dofs) + 1

    def check_uniform(x, lo, hi):
        assert lo - 1e-6 <= float(x.min()) and float(x.max()) <= hi + 1e-6
        assert abs(float(x.mean()) - (lo + hi) / 2) < 0.01 * max(hi - lo, 1.0)
        assert abs(float(x.std()) - (hi - lo) / 12**0.5) < 0.02 * max(hi - lo, 1.0)

    # mass and inertia: the same factor per world and body; the world body keeps its (zero) mass
    mass0 = torch.as_tensor(mj.body_mass, dtype=torch.float32)
    scale = f["body_mass"][:, bodies] / mass0[bodies]
    check_uniform(scale, 0.8, 1.2)
    torch.testing.assert_close(scale, dyn.mass_scale[:, bodies])
    inertia0 = torch.as_tensor(mj.body_inertia, dtype=torch.float32)
    torch.testing.assert_close(f["body_inertia"][:, bodies], inertia0[bodies] * scale.unsqueeze(-1))
    assert float(f["body_mass"][:, 0].abs().max()) == 0.0
    # the subtree masses follow the drawn masses
    for b in (0, mj.body(robot.BASE_BODY).id, mj.body("L_Thigh_Link").id):
        sub = [j for j in range(mj.nbody) if b == 0 or b in _ancestors(mj, j)]
        torch.testing.assert_close(f["body_subtreemass"][:, b], f["body_mass"][:, sub].sum(1))
    # damping: added to the joint dofs only
    damping0 = torch.as_tensor(mj.dof_damping, dtype=torch.float32)
    check_uniform(f["dof_damping"][:, dofs] - damping0[dofs], 0.0, 2.9)
    assert torch.equal(f["dof_damping"][:, :6], damping0[:6].expand(n, 6))
    # armature: scaled on the joint dofs
    armature0 = torch.as_tensor(mj.dof_armature, dtype=torch.float32)
    check_uniform(f["dof_armature"][:, dofs] / armature0[dofs], 0.8, 1.2)
    # friction: one sliding-friction factor per world for every geom; torsional and rolling untouched
    friction0 = torch.as_tensor(mj.geom_friction, dtype=torch.float32)
    fs = f["geom_friction"][..., 0] / friction0[:, 0]
    check_uniform(fs[:, 0], 0.4, 1.0)
    assert torch.equal(fs, fs[:, :1].expand_as(fs)) and torch.equal(fs[:, 0], dyn.friction_scale)
    assert torch.equal(f["geom_friction"][..., 1:], friction0[:, 1:].expand(n, -1, -1))
    # the worlds differ: every draw is its own (a single float32 factor may repeat by chance among 4,096)
    for x in (scale, f["dof_damping"][:, dofs], f["dof_armature"][:, dofs], fs[:, 0]):
        assert len(torch.unique(x.reshape(n, -1), dim=0)) >= (n if x.dim() > 1 else 0.99 * n)


def _ancestors(mj, j):
    out = [j]
    while j:
        j = int(mj.body_parentid[j])
        out.append(j)
    return out


def test_a_range_that_is_off_writes_nothing_and_keeps_the_others_draws(mj):
    u = torch.rand(8, 200, generator=torch.Generator().manual_seed(1))
    only_damping = DynamicsRandomization(joint_damping=(0.0, 2.9))
    a, b = nominal_sim(mj, 8), nominal_sim(mj, 8)
    da = drawn(a, only_damping, lambda k: u[:, :k])
    drawn(b, FULL, lambda k: u[:, :k])
    assert set(WorldDynamics(only_damping).config.sim_fields) == {"dof_damping"}
    assert torch.equal(a.model_fields["body_mass"], nominal_sim(mj, 8).model_fields["body_mass"])
    assert torch.equal(a.model_fields["dof_damping"], b.model_fields["dof_damping"])  # the same lanes
    assert float(da.mass_scale.min()) == float(da.mass_scale.max()) == 1.0


def test_a_masked_draw_changes_only_the_flagged_worlds(mj):
    sim = nominal_sim(mj, 4)
    gen = torch.Generator().manual_seed(2)
    dyn = drawn(sim, FULL, lambda k: torch.rand(4, k, generator=gen))
    before = {k: v.clone() for k, v in sim.model_fields.items()}
    mask = torch.tensor([False, True, False, False])
    dyn.reset(mask, torch.rand(4, dyn.draws, generator=gen))
    for name, value in sim.model_fields.items():
        assert torch.equal(value[~mask], before[name][~mask]), name
        assert not torch.equal(value[1], before[name][1]), name


# --------------------------------------------------------------------------------------------------- the physics
@pytest.mark.parametrize("backend", BACKENDS)
def test_per_world_rows_at_nominal_step_exactly_like_the_shared_model(backend):
    # Giving the fields one row per world changes nothing by itself: the same numbers come out.
    from tocabi_torchrl.sim import WarpSim

    make = MujocoSim if backend == "mujoco" else WarpSim
    shared = make(SimConfig(num_worlds=2, threads=1))
    rows = make(SimConfig(num_worlds=2, threads=1, per_world_fields=PER_WORLD_FIELDS))
    assert rows.model_fields["body_inertia"].shape == (2, shared.mj_model.nbody, 3)
    for sim in (shared, rows):
        sim.reset(torch.ones(2, dtype=torch.bool), *start_state(sim.mj_model))
        for _ in range(5):
            sim.step()
    for name in ("qpos", "qvel", "sensordata", "mass_matrix"):
        assert torch.equal(getattr(rows, name), getattr(shared, name)), name


@pytest.mark.parametrize("backend", BACKENDS)
def test_model_fields_are_written_in_place_and_cannot_be_rebound(backend):
    # A rebound entry was taken without a word and reached no world: WarpSim's kernels and MujocoSim's worker threads
    # read the first tensor's memory (and MujocoSim then compared later writes against the new one).
    from tocabi_torchrl.sim import WarpSim

    make = MujocoSim if backend == "mujoco" else WarpSim
    sim = make(SimConfig(num_worlds=2, threads=1, per_world_fields=("dof_damping",)))
    rows = sim.model_fields["dof_damping"]
    with pytest.raises(TypeError, match="does not support item assignment"):
        sim.model_fields["dof_damping"] = rows + 5.0
    with pytest.raises(TypeError, match="does not support item deletion"):
        del sim.model_fields["dof_damping"]
    rows[1] += 5.0  # in place: world 1's physics from its next step on
    sim.step()
    if backend == "mujoco":
        assert torch.equal(torch.from_numpy(sim._world_models[1].dof_damping), rows[1])
        assert torch.equal(torch.from_numpy(sim._world_models[0].dof_damping), rows[0])


def test_a_heavier_world_presses_harder_on_its_feet():
    # Standing still (the "pd" mode holds the nominal pose), each world's feet carry its own weight.
    cfg = env_config(DynamicsRandomization(mass_scale=(0.8, 1.2)), backend="mujoco", control_mode="pd")
    env = TocabiWalk(num_envs=4, device="cpu", config=cfg, seed=0)
    env.reset()
    force = torch.zeros(4)
    for k in range(60):  # the mean vertical force of both foot F/T sensors over the last 50 steps [N]
        out = step(env, torch.zeros(4, 13))
        force -= out["foot_force"][:, :, 2].sum(1) * (k >= 10) / 50
    weight = env.sim.model_fields["body_subtreemass"][:, 0].float() * float(-env.sim.mj_model.opt.gravity[2])
    assert float(weight.max() / weight.min()) > 1.05  # the draws differ enough to tell
    ratio = force / weight  # the sensors (above the feet) carry the same share of each world's weight
    assert 0.9 < float(ratio.min()) and float(ratio.max() / ratio.min()) < 1.03, ratio
    heavy, light = int(weight.argmax()), int(weight.argmin())
    assert float(force[heavy] / force[light]) > 0.97 * float(weight[heavy] / weight[light])


def test_a_more_damped_joint_slows_down_more(mj):
    sim = two_worlds(DynamicsRandomization(joint_damping=(0.0, 2.9)))
    dof = int(mj.joint("L_Elbow_Joint").dofadr[0])
    assert float(sim.model_fields["dof_damping"][1, dof] - sim.model_fields["dof_damping"][0, dof]) == \
        pytest.approx(2.9, abs=1e-6)
    qvel = torch.zeros(mj.nv)
    qvel[dof] = 5.0
    sim.reset(torch.ones(2, dtype=torch.bool), *start_state(mj, qvel))
    sim.step()
    assert 0.0 < float(sim.qvel[1, dof]) < float(sim.qvel[0, dof]) - 0.1


def test_a_larger_armature_accelerates_less_and_is_in_the_inertia(mj):
    sim = two_worlds(DynamicsRandomization(armature_scale=(0.5, 2.0)))
    joint = mj.joint("L_Elbow_Joint")
    dof, adr = int(joint.dofadr[0]), int(joint.qposadr[0])
    act = next(a for a in range(mj.nu) if mj.actuator_trnid[a, 0] == joint.id)
    q0, qvel, ctrl = start_state(mj)
    ctrl[act] += 0.3  # the elbow servo's target 0.3 rad away
    sim.reset(torch.ones(2, dtype=torch.bool), q0, qvel, ctrl)
    # the inertia's diagonal entry of the dof holds each world's armature
    diag = sim.mass_matrix[:, int(mj.M_rowadr[dof] + mj.M_rownnz[dof] - 1)]
    extra = float(sim.model_fields["dof_armature"][1, dof] - sim.model_fields["dof_armature"][0, dof])
    assert float(diag[1] - diag[0]) == pytest.approx(extra, rel=1e-3)
    assert extra == pytest.approx(1.5 * mj.dof_armature[dof])
    sim.step()
    moved = sim.qpos[:, adr] - q0[adr]
    assert 0.0 < float(moved[1]) < 0.9 * float(moved[0])


def test_less_friction_lets_the_feet_slide_further(mj):
    sim = two_worlds(DynamicsRandomization(friction_scale=(0.1, 1.0)))
    qvel = torch.zeros(mj.nv)
    qvel[0] = 1.0  # the robot lands its feet moving forward at 1 m/s
    sim.reset(torch.ones(2, dtype=torch.bool), *start_state(mj, qvel))
    foot = mj.body("L_Foot_Link").id
    x0 = sim.xpos[:, foot, 0].clone()
    for _ in range(20):
        sim.step()
    slid = sim.xpos[:, foot, 0] - x0
    assert float(slid[0]) > 2.0 * float(slid[1]) > 0.0


# -------------------------------------------------------------------------------------------------------- the env
@pytest.mark.parametrize("backend", BACKENDS)
def test_the_env_draws_per_episode_and_one_worlds_reset_leaves_the_others_bit_identical(backend):
    # Two envs of the same seed step the same actions; one of them resets world 1 in between: the other worlds'
    # parameters and trajectories stay bit-identical, world 1 draws again.
    n, cfg = 3, env_config(backend=backend)
    a, b = (TocabiWalk(num_envs=n, device="cpu", config=cfg, seed=5) for _ in range(2))
    assert a.dynamics is not None and not a._reduced_reset and a.sim.config.reset_pass == "full"
    a.reset(), b.reset()
    assert torch.equal(a.dynamics.mass_scale, b.dynamics.mass_scale)  # (seed, env, episode) keys the draw
    action = (torch.rand(n, 13, generator=torch.Generator().manual_seed(0)) * 2 - 1) * 0.2
    for _ in range(3):
        step(a, action), step(b, action)
    fields = {k: v.clone() for k, v in a.sim.model_fields.items()}
    mask = torch.tensor([False, True, False])
    a.reset(a._observe().set("_reset", mask.unsqueeze(-1)))
    for name, value in a.sim.model_fields.items():
        assert torch.equal(value[~mask], fields[name][~mask]), name
        assert not torch.equal(value[1], fields[name][1]), name
    for _ in range(4):
        out_a, out_b = step(a, action), step(b, action)
    for key in ("joint_pos", "joint_vel", "base_pos", "foot_force"):
        assert torch.equal(out_a[key][~mask], out_b[key][~mask]), key
    assert not torch.equal(out_a["joint_pos"][1], out_b["joint_pos"][1])
    # the draw of env 1's second episode does not depend on which other worlds reset with it
    b.reset(b._observe().set("_reset", torch.ones(n, 1, dtype=torch.bool)))
    assert torch.equal(b.dynamics.mass_scale[1], a.dynamics.mass_scale[1])


@pytest.mark.skipif(not warp_cpu_available(), reason="warp's CPU device is unavailable")
def test_both_backends_draw_the_same_dynamics():
    envs = [TocabiWalk(num_envs=2, device="cpu", config=env_config(backend=b), seed=9) for b in ("mujoco", "warp")]
    for e in envs:
        e.reset()
    for name in ("mass_scale", "joint_damping", "armature_scale", "friction_scale"):
        assert torch.equal(getattr(envs[0].dynamics, name), getattr(envs[1].dynamics, name)), name
    for name, value in envs[0].sim.model_fields.items():
        torch.testing.assert_close(envs[1].sim.model_fields[name], value.float(), rtol=1e-6, atol=1e-6)


def test_off_builds_no_per_world_model():
    env = TocabiWalk(num_envs=2, device="cpu", seed=0, backend="mujoco")
    assert env.dynamics is None and env.sim.model_fields == {} and env.sim._world_models is None


@pytest.mark.skipif(not warp_cpu_available(), reason="warp's CPU device is unavailable")
def test_warp_refuses_a_start_state_table_with_per_world_fields():
    from tocabi_torchrl.sim import WarpSim

    sim = WarpSim(SimConfig(num_worlds=1, reset_pass="reduced", per_world_fields=("geom_friction",)))
    q, v, c = (x.unsqueeze(0) for x in start_state(sim.mj_model))
    with pytest.raises(ValueError, match="reset_pass='full'"):
        sim.register_start_states(q, v, c)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("cuda_graph", [False, True])
def test_gpu_dynamics_never_sync_and_follow_resets(cuda_graph):
    cfg = env_config(max_episode_steps=3)
    e = make_env(num_envs=128, device="cuda", seed=0, cuda_graph=cuda_graph, config=cfg)
    td = e.reset()
    action = (torch.rand(128, 13, device="cuda") * 2 - 1) * 0.3
    for _ in range(3):
        _, td = e.step_and_maybe_reset(td.set("action", action))
    assert e.graph_captured == cuda_graph
    dyn, fields = e.base_env.dynamics, e.base_env.sim.model_fields
    before = {k: v.clone() for k, v in fields.items()}
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(6):  # crosses the 3-step truncation: every world resets and redraws its dynamics
            step_td, td = e.step_and_maybe_reset(td.set("action", action))
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert bool(step_td["next", "truncated"].any())
    for name, value in fields.items():
        assert not torch.equal(value, before[name]), name  # redrawn in place, inside the (captured) step
    mass0 = torch.as_tensor(e.base_env.sim.mj_model.body_mass, dtype=torch.float32, device="cuda")
    scale = fields["body_mass"][:, dyn.bodies] / mass0[dyn.bodies]
    assert 0.8 - 1e-5 <= float(scale.min()) and float(scale.max()) <= 1.2 + 1e-5
    torch.testing.assert_close(scale, dyn.mass_scale[:, dyn.bodies])
    assert bool(torch.isfinite(step_td["next", "observation"]).all())
