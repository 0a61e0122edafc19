"""``reset_pass="reduced"`` (issue 25, the env's default) against the full reset pass, on mujoco-warp's CPU device.

The reduced pass runs only the position and velocity stages over all worlds and copies the rest of a registered start
state from a table; everything the sim and the env return, and the trajectories after resets (worlds reset
mid-episode beside worlds that continue, a start state with foot contacts), must be bit-identical to the full pass.
"""

from __future__ import annotations

from pathlib import Path

import mujoco_warp as mjw
import pytest
import torch
import warp as wp
from tensordict import TensorDict
from warp_cpu import warp_cpu_available

from tocabi_torchrl import robot
from tocabi_torchrl.envs.config import EnvSimConfig
from tocabi_torchrl.sim import SimConfig, WarpSim

pytestmark = pytest.mark.skipif(not warp_cpu_available(), reason="warp's CPU device is unavailable")

N = 4
#: What the sim exposes (views) plus the solver's warm start, which decides the next steps.
SIM_KEYS = ("qpos", "qvel", "ctrl", "sensordata", "xpos", "xquat", "foot_force", "foot_torque", "contact_counts",
            "foot_contact", "forbidden_ground_contact", "self_collision", "obstacle_contact", "healthy", "overflow",
            "applied_actuator_force", "mass_matrix", "qfrc_bias", "time")


#: The solver's iteration-limit flags (not health flags): the full pass re-solves every untouched world from its warm
#: start, the reduced one does not, so a re-solve whose line search stops at its limit flags a world in the full pass
#: alone (seen on an AMD EPYC host: LS_ITERATIONS on one untouched world, every trajectory still bit-identical).
SOLVER_LIMIT_BITS = int(mjw.OverflowType.ITERATIONS | mjw.OverflowType.LS_ITERATIONS)


def _assert_sims_equal(a: WarpSim, b: WarpSim, when: str) -> None:
    for key in SIM_KEYS:
        x, y = getattr(a, key), getattr(b, key)
        if key == "overflow":
            x, y = x & ~SOLVER_LIMIT_BITS, y & ~SOLVER_LIMIT_BITS
        assert torch.equal(x, y), f"{when}: sim.{key} differs, max {(x.double() - y.double()).abs().max().item()}"
    x, y = wp.to_torch(a.wp_data.qacc_warmstart), wp.to_torch(b.wp_data.qacc_warmstart)
    assert torch.equal(x, y), f"{when}: qacc_warmstart differs"
    # Not d.qacc: the full pass re-solves the untouched worlds from their warm start (within the solver's tolerance,
    # up to ~0.007 here); the reduced one keeps the step's solution. Only the health flag reads it (finite or not),
    # and neither the warm start nor any trajectory differs.


def _assert_tds_equal(a: TensorDict, b: TensorDict, when: str) -> None:
    assert set(a.keys(True, True)) == set(b.keys(True, True)), when
    for key in a.keys(True, True):
        assert torch.equal(a[key], b[key]), f"{when}: {key} differs"


def _step_both(full, reduced, td_f, td_r, action: torch.Tensor, when: str):
    """One sync-free step of the full-pass and the reduced-pass env with the same action; asserts that what they
    return, and their simulators, are bit-identical. Returns (out_f, td_f, out_r, td_r)."""
    td_f["action"], td_r["action"] = action.clone(), action.clone()
    out_f, td_f = full.step_and_maybe_reset(td_f)
    out_r, td_r = reduced.step_and_maybe_reset(td_r)
    _assert_tds_equal(out_f, out_r, when)
    _assert_tds_equal(td_f, td_r, f"{when}, after the sync-free resets")
    _assert_sims_equal(full.base_env.sim, reduced.base_env.sim, when)
    return out_f, td_f, out_r, td_r


def _step_sims(a: WarpSim, b: WarpSim, pose: torch.Tensor, g: torch.Generator, k: int, when: str) -> None:
    """``k`` steps of both simulators with the same random controls (leg torques, upper-body targets around the
    start pose ``pose`` (nq,)), asserting after each that they are bit-identical."""
    n = a.num_worlds
    for t in range(k):
        u = torch.zeros(n, 33)
        u[:, robot.LEGS] = 60.0 * (2 * torch.rand(n, 12, generator=g) - 1)
        u[:, robot.UPPER_BODY] = pose[7:][robot.UPPER_BODY] + 0.1 * torch.randn(n, 21, generator=g)
        a.ctrl.copy_(u)
        b.ctrl.copy_(u)
        a.step()
        b.step()
        _assert_sims_equal(a, b, f"{when}, step {t}")


def _random_action(g: torch.Generator) -> torch.Tensor:
    a = 2 * torch.rand(N, 13, generator=g) - 1
    a[:, 12] = a[:, 12].abs()
    return a


# ------------------------------------------------------------------------------------------------ config and API
def test_config_values():
    SimConfig(reset_pass="reduced").validate()
    EnvSimConfig(reset_pass="reduced").validate()
    with pytest.raises(ValueError, match="reset_pass"):
        SimConfig(reset_pass="fast").validate()
    with pytest.raises(ValueError, match="env.sim.reset_pass"):
        EnvSimConfig(reset_pass="fast").validate()
    # The env registers its start states, so it can default to the reduced pass; a bare simulator cannot.
    assert SimConfig().reset_pass == "full" and EnvSimConfig().reset_pass == "reduced"


def test_a_saved_config_without_the_field_keeps_the_full_pass_it_trained_with():
    from tocabi_torchrl.config import RunConfig, config_from_dict
    from tocabi_torchrl.rl.checkpoint import config_from_checkpoint, read_checkpoint

    tree = RunConfig().to_dict()
    assert config_from_dict(tree).env.sim.reset_pass == "reduced"  # saved with the field: kept
    del tree["env"]["sim"]["reset_pass"]
    assert config_from_dict(tree).env.sim.reset_pass == "full"  # saved before the field existed
    shipped = Path(__file__).resolve().parents[1] / "assets/policies/tocabi_walk_ppo.pt"  # a flat config, older
    assert config_from_checkpoint(read_checkpoint(shipped), shipped).env.sim.reset_pass == "full"


@pytest.fixture(scope="module")
def start_states():
    """Three start states: standing at rest (feet 1.3 mm above the ground), lowered 3 mm into foot contact with random
    controls, and moving (joint velocities) with random controls."""
    g = torch.Generator().manual_seed(3)
    qpos = torch.as_tensor(robot.INIT_QPOS, dtype=torch.float32).repeat(3, 1)
    qpos[1, 2] -= 0.003
    qvel = torch.zeros(3, 39)
    qvel[2, 6:] = 0.5 * torch.randn(33, generator=g)
    ctrl = torch.zeros(3, 33)
    ctrl[1:, robot.LEGS] = 40.0 * (2 * torch.rand(2, 12, generator=g) - 1)  # leg torques [N·m]
    ctrl[:, robot.UPPER_BODY] = qpos[:, 7:][:, robot.UPPER_BODY] + 0.05 * torch.randn(3, 21, generator=g)
    return qpos, qvel, ctrl


@pytest.fixture(scope="module")
def sims(start_states):
    full = WarpSim(SimConfig(num_worlds=N, device="cpu"))
    reduced = WarpSim(SimConfig(num_worlds=N, device="cpu", reset_pass="reduced"))
    reduced.register_start_states(*start_states)
    return full, reduced


def test_api_errors(start_states, sims):
    full, reduced = sims
    with pytest.raises(ValueError, match="reset_pass='reduced'"):
        full.register_start_states(*start_states)
    with pytest.raises(ValueError, match="called already"):  # a captured graph may read the first table
        reduced.register_start_states(*start_states)
    fresh = WarpSim(SimConfig(num_worlds=1, device="cpu", reset_pass="reduced"))
    with pytest.raises(RuntimeError, match="register_start_states"):
        fresh.reset_to_start(torch.ones(1, dtype=torch.bool), torch.zeros(1, dtype=torch.int64))
    with pytest.raises(ValueError, match=r"\(K, 40\)"):
        fresh.register_start_states(start_states[0][:, :10], start_states[1], start_states[2])


def test_sim_reduced_matches_full(start_states, sims):
    """Resets of all worlds, then of some mid-trajectory, to each start state: every view, the warm start and the
    following steps are bit-identical to the full pass (and a start state has its feet in contact)."""
    full, reduced = sims
    qpos, qvel, ctrl = start_states
    g = torch.Generator().manual_seed(5)

    def reset(mask, index):
        full.reset(mask, qpos[index], qvel[index], ctrl[index])
        reduced.reset_to_start(mask, index)

    def steps(k, when):
        _step_sims(full, reduced, qpos[0], g, k, when)

    reset(torch.ones(N, dtype=torch.bool), torch.tensor([0, 1, 2, 1]))
    _assert_sims_equal(full, reduced, "reset of all worlds")
    assert bool(full.foot_contact[1].all()) and bool(full.foot_force[1].abs().sum() > 0)  # contacts at the start
    assert not bool(full.foot_contact[0].any())
    steps(3, "after the first reset")
    for mask, index in (([True, False, False, True], [1, 0, 0, 2]), ([False, True, True, False], [0, 2, 1, 0])):
        before = reduced.qpos.clone()
        reset(torch.tensor(mask), torch.tensor(index))
        _assert_sims_equal(full, reduced, f"partial reset {mask}")
        keep = ~torch.tensor(mask)
        assert torch.equal(reduced.qpos[keep], before[keep])
        steps(4, f"after partial reset {mask}")


def test_sim_per_world_obstacles(start_states):
    """The table is per world: a box under the feet in worlds 0 and 2 only (contact at the start there), the same
    start states everywhere; the reduced pass matches the full one in every world."""
    from tocabi_torchrl.envs.config import BoxObstacle
    from tocabi_torchrl.envs.obstacles import add_obstacles

    spec = robot.load_spec()
    (name,) = add_obstacles(spec, [BoxObstacle(size=(0.5, 0.6, 0.004), pos=(0.0, 0.0))])
    centres = torch.tensor([[0.0, 0.0, 0.002], [3.0, 0.0, 0.002]]).repeat(2, 1).numpy()  # worlds 0, 2: under the feet
    qpos, qvel, ctrl = start_states
    full = WarpSim(SimConfig(num_worlds=N, device="cpu"), model=spec, mocap_pos={name: centres})
    reduced = WarpSim(SimConfig(num_worlds=N, device="cpu", reset_pass="reduced"), model=spec,
                      mocap_pos={name: centres})
    reduced.register_start_states(qpos, qvel, ctrl)
    index = torch.tensor([0, 0, 2, 2])
    for mask in ([True] * N, [True, True, False, False], [False, True, True, True]):
        mask = torch.tensor(mask)
        full.reset(mask, qpos[index], qvel[index], ctrl[index])
        reduced.reset_to_start(mask, index)
        _assert_sims_equal(full, reduced, f"reset {mask.tolist()}")
        assert full.obstacle_contact[[0, 2]].any(-1).all() and not full.obstacle_contact[[1, 3]].any()
        for t in range(2):
            full.step()
            reduced.step()
            _assert_sims_equal(full, reduced, f"step {t} after reset {mask.tolist()}")


# ------------------------------------------------------------------------------------------------------ the env
@pytest.fixture(scope="module")
def envs():
    from tocabi_torchrl import make_env

    def build(reset_pass):
        # Torque mode and a 6-step truncation: the sync-free step resets worlds itself, out of phase after the
        # explicit partial reset below.
        return make_env(num_envs=N, device="cpu", seed=0, sync_free_resets=True, backend="warp",
                        control_mode="torque", max_episode_steps=6, reset_pass=reset_pass)

    return build("full"), build("reduced")


def test_env_reduced_matches_full(envs):
    """Observations, rewards and their terms, done flags and every signal of the transformed env, through resets
    of all worlds, an explicit partial reset mid-episode and the sync-free step's own resets, are bit-identical."""
    full, reduced = envs
    assert reduced.base_env.sim.config.reset_pass == "reduced" and full.base_env.sim.config.reset_pass == "full"
    td_f, td_r = full.reset(), reduced.reset()
    _assert_tds_equal(td_f, td_r, "reset")
    g = torch.Generator().manual_seed(7)
    partial_autoresets = 0
    for t in range(14):
        out_f, td_f, _, td_r = _step_both(full, reduced, td_f, td_r, _random_action(g), f"step {t}")
        done = out_f["next", "done"].squeeze(-1)
        partial_autoresets += int(bool(done.any()) and not bool(done.all()))
        if t == 2:  # worlds 0 and 2 restart mid-episode; 1 and 3 go on
            mask = torch.tensor([True, False, True, False]).unsqueeze(-1)
            td_f = full.reset(td_f.set("_reset", mask.clone()))
            td_r = reduced.reset(td_r.set("_reset", mask.clone()))
            _assert_tds_equal(td_f, td_r, "partial reset")
            _assert_sims_equal(full.base_env.sim, reduced.base_env.sim, "partial reset")
    assert partial_autoresets >= 2  # the step reset some worlds while others went on


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.filterwarnings("error:SyncFreeResetEnv")  # a failed capture or an eager fallback fails the test
def test_gpu_reduced_pass_is_captured_and_never_syncs():
    """On the GPU the reduced reset graph is recorded inside the env's captured step, replays like the eager step
    and reads nothing on the host; a 6-step truncation makes the step reset worlds itself."""
    from captured_vs_eager import assert_captured_equals_eager

    kwargs = {"num_envs": 64, "device": "cuda", "seed": 3, "control_mode": "torque", "max_episode_steps": 6,
              "reset_pass": "reduced"}
    assert_captured_equals_eager(kwargs, ("observation", "reward", "done"))


# -------------------------------------------------------------------------------------- a pool of drawn start states
def _pool_env(reset_pass, pool=3, seed=0, **kwargs):
    from tocabi_torchrl import make_env
    from tocabi_torchrl.randomize import TOCABI_LAB_DYNAMICS

    options = {"start_joint_vel_std": 0.5, "start_base_vel_std": 0.1, "dynamics": TOCABI_LAB_DYNAMICS, **kwargs}
    return make_env(num_envs=N, device="cpu", seed=seed, sync_free_resets=True, backend="warp",
                    control_mode="torque", max_episode_steps=5, reset_pass=reset_pass, start_pool=pool, **options)


def test_pool_reduced_matches_full():
    """With diverse starts and per-world dynamics drawn from a start pool, the reduced pass (each world's pooled
    states registered with their own masses, damping and armature) gives every observation, signal and sim view of
    the full pass bit for bit, through the sync-free step's own resets into other pooled states."""
    full, reduced = _pool_env("full"), _pool_env("reduced")
    assert full.base_env.sim.config.reset_pass == "full" and reduced.base_env.sim.config.reset_pass == "reduced"
    assert reduced.base_env._reduced_reset and not full.base_env._reduced_reset
    td_f, td_r = full.reset(), reduced.reset()
    _assert_tds_equal(td_f, td_r, "reset")
    _assert_sims_equal(full.base_env.sim, reduced.base_env.sim, "reset")
    g = torch.Generator().manual_seed(11)
    states, resets = set(), 0
    for t in range(16):
        out_f, td_f, _, td_r = _step_both(full, reduced, td_f, td_r, _random_action(g), f"step {t}")
        resets += int(out_f["next", "done"].sum())
        states.add(tuple(reduced.base_env.sim._start_states.index_t.tolist()))
        if t in (1, 8):  # worlds 1 and 2 restart mid-episode, into other pooled states; 0 and 3 go on
            mask = torch.tensor([False, True, True, False]).unsqueeze(-1)
            keep = reduced.base_env.sim.qpos[[0, 3]].clone()
            td_f = full.reset(td_f.set("_reset", mask.clone()))
            td_r = reduced.reset(td_r.set("_reset", mask.clone()))
            _assert_tds_equal(td_f, td_r, f"partial reset after step {t}")
            _assert_sims_equal(full.base_env.sim, reduced.base_env.sim, f"partial reset after step {t}")
            assert torch.equal(reduced.base_env.sim.qpos[[0, 3]], keep)
    assert resets >= N and len(states) > 1  # every world restarted, into more than one pooled state


def test_pool_draws():
    """Each world's pooled states differ from each other and from other worlds'; a reset's masses and start
    velocities are those of one of its world's pooled states; the pool is the same for the same seed."""
    from tocabi_torchrl.randomize import TOCABI_LAB_DYNAMICS

    env = _pool_env("reduced", pool=4)
    base = env.base_env
    qvel, dyn = base._pool_qvel, base._pool_dyn
    assert qvel.shape == (4, N, base.sim.nv) and dyn.shape == (4, N, base.dynamics.draws)
    assert torch.equal(qvel[..., 3:6], torch.zeros(4, N, 3))  # no angular start velocity
    assert (qvel[..., 6:].std() - 0.5).abs() < 0.1 and (dyn.flatten(0, 1)[:, None] != dyn.flatten(0, 1)).any(-1).sum() == 16 * 15
    for _ in range(3):
        td = env.reset()
        for w in range(N):
            match = [k for k in range(4) if torch.equal(td["joint_vel"][w], qvel[k, w, 6:])]
            assert len(match) == 1, f"world {w} started with velocities of none of its pooled states"
            lo, hi = TOCABI_LAB_DYNAMICS.mass_scale
            scale = base.dynamics.mass_scale[w, base.dynamics.bodies]
            assert torch.equal(scale, lo + (hi - lo) * dyn[match[0], w, :len(base.dynamics.bodies)])
    again = _pool_env("reduced", pool=4).base_env
    assert torch.equal(again._pool_qvel, qvel) and torch.equal(again._pool_dyn, dyn)  # same seed: same pool
    assert not torch.equal(_pool_env("reduced", pool=4, seed=1).base_env._pool_qvel, qvel)


def test_pool_config_and_errors():
    from tocabi_torchrl.envs.config import MAX_START_POOL

    for bad in (-1, MAX_START_POOL + 1, 1.5, True):
        with pytest.raises(ValueError, match="env.sim.start_pool"):
            EnvSimConfig(start_pool=bad).validate()
    env = _pool_env("reduced", pool=2)
    with pytest.raises(ValueError, match="start_pool=0"):
        env.base_env.set_randomized_worlds(torch.tensor([True, False, True, True]))
    env.base_env.set_randomized_worlds(torch.ones(N, dtype=torch.bool))  # all randomised: nothing changes
    # A pool of start velocities only holds no dynamics: ideal worlds are allowed there (their actuators, sensors).
    from tocabi_torchrl.sim.dynamics_config import DynamicsRandomization

    starts_only = _pool_env("reduced", pool=2, dynamics=DynamicsRandomization())
    assert starts_only.base_env._pool == 2 and starts_only.base_env._pool_dyn is None
    starts_only.base_env.set_randomized_worlds(torch.tensor([True, False, True, True]))
    starts_only.reset()
    # The pool is the build seed's: set_seed moves the per-episode draws, not the pooled states.
    assert env.base_env.pool_seed == 0
    before = env.base_env._pool_qvel.clone()
    env.set_seed(123)
    assert torch.equal(env.base_env._pool_qvel, before) and env.base_env.pool_seed == 0
    # Without diverse starts or dynamics the pool has nothing to draw: the env is the plain one.
    plain = _pool_env("reduced", pool=2, start_joint_vel_std=0.0, start_base_vel_std=0.0,
                      dynamics=DynamicsRandomization())
    assert plain.base_env._pool == 0 and plain.base_env._reduced_reset
    sim = WarpSim(SimConfig(num_worlds=2, device="cpu", reset_pass="reduced", per_world_fields=("body_mass",)))
    qpos = torch.as_tensor(robot.INIT_QPOS, dtype=torch.float32).repeat(1, 1)
    with pytest.raises(ValueError, match="set_fields"):
        sim.register_start_states(qpos, torch.zeros(1, 39), torch.zeros(1, 33))
    with pytest.raises(ValueError, match=r"\(K, 2, 39\)"):
        sim.register_start_states(qpos, torch.zeros(1, 3, 39), torch.zeros(1, 33), lambda k: None)


def test_robust_preset_training_env_pool_matches_full():
    """The robust preset's own training env (its start pool, every randomisation piece, kicks, the privileged
    critic's input), on mujoco-warp's CPU device: the reduced pass gives what the full pass gives, bit for bit."""
    from tocabi_torchrl.config import preset_tree
    from tocabi_torchrl.rl.trainer import build_env
    from tocabi_torchrl.tree import replace_paths

    cfg = preset_tree("robust")
    assert cfg.env.sim.start_pool > 0 and cfg.env.sim.reset_pass == "reduced"
    # Short episodes and an early kick, so that worlds restart and get kicked within the few steps run here.
    cfg = replace_paths(cfg, {"env.sim.backend": "warp", "env.task.max_episode_steps": 6,
                              "env.pushes.window": (0.0, 0.02)})
    envs = [build_env(replace_paths(cfg, {"env.sim.reset_pass": p}), torch.device("cpu"), num_envs=N,
                      for_training=True, sync_free_resets=True) for p in ("full", "reduced")]
    full, reduced = envs
    assert reduced.base_env._reduced_reset and not full.base_env._reduced_reset
    td_f, td_r = full.reset(), reduced.reset()
    _assert_tds_equal(td_f, td_r, "reset")
    g = torch.Generator().manual_seed(2)
    resets, kicked = 0, False
    for t in range(9):
        out_f, td_f, _, td_r = _step_both(full, reduced, td_f, td_r, _random_action(g), f"step {t}")
        resets += int(out_f["next", "done"].sum())
        kicked |= bool(full.base_env.sim.wp_data.xfrc_applied.numpy().any())
    assert resets >= N and kicked


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.filterwarnings("error:SyncFreeResetEnv")  # a failed capture or an eager fallback fails the test
def test_gpu_pool_reduced_pass_is_captured_and_never_syncs():
    """A start pool with diverse starts and per-world dynamics on the GPU: the reduced reset (each world's pooled
    state, its drawn masses written in place) is recorded inside the captured step, replays like the eager step and
    reads nothing on the host."""
    from captured_vs_eager import assert_captured_equals_eager

    from tocabi_torchrl.randomize import TOCABI_LAB_DYNAMICS

    kwargs = {"num_envs": 64, "device": "cuda", "seed": 3, "control_mode": "torque", "max_episode_steps": 6,
              "reset_pass": "reduced", "start_pool": 4, "start_joint_vel_std": 0.5, "start_base_vel_std": 0.1,
              "dynamics": TOCABI_LAB_DYNAMICS}
    assert_captured_equals_eager(kwargs, ("observation", "reward", "done"))


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.filterwarnings("error:SyncFreeResetEnv")
def test_gpu_robust_preset_training_env_reduced_matches_full():
    """The robust preset's own training env on the GPU, both reset passes: the first reset (each world's pooled state,
    the reduced pass's from the table the GPU computed at build) gives the full pass's observations and sensors
    (within float32 rounding: the GPU sums contact forces in atomics, so no two GPU runs are bit-identical); then
    captured steps through truncations, resets and kicks read nothing on the host."""
    from tocabi_torchrl.config import preset_tree
    from tocabi_torchrl.rl.trainer import build_env
    from tocabi_torchrl.tree import replace_paths

    cfg = replace_paths(preset_tree("robust"), {"env.task.max_episode_steps": 8, "env.pushes.window": (0.0, 0.03)})
    dev = torch.device("cuda")
    envs = [build_env(replace_paths(cfg, {"env.sim.reset_pass": p}), dev, num_envs=256, for_training=True,
                      sync_free_resets=True, cuda_graph=True) for p in ("full", "reduced")]
    full, reduced = envs
    assert reduced.base_env._reduced_reset and not full.base_env._reduced_reset
    td_f, td_r = full.reset(), reduced.reset()
    torch.testing.assert_close(td_r["observation"], td_f["observation"], atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(reduced.base_env.sim.sensordata, full.base_env.sim.sensordata, atol=1e-3, rtol=1e-4)
    g = torch.Generator(device="cpu").manual_seed(4)
    resets = 0
    try:
        for t in range(20):
            a = (2 * torch.rand(256, 13, generator=g) - 1).to(dev)
            td_f["action"], td_r["action"] = a.clone(), a.clone()
            if t == 3:
                torch.cuda.set_sync_debug_mode("error")  # after the captures: replays must not read the host
            _, td_f = full.step_and_maybe_reset(td_f)
            out_r, td_r = reduced.step_and_maybe_reset(td_r)
            torch.cuda.set_sync_debug_mode(0)
            resets += int(out_r["next", "done"].sum())
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert resets >= 256 and full.graph_captured and reduced.graph_captured
