"""Box obstacles (``TocabiWalkConfig.scene.obstacles``, issue 23): their geometry in the compiled model and in every
world on both backends (per-world jitter included), contacts with them counted like the ground's (feet allowed,
anything else terminates), the config round trips (dicts, JSON, checkpoints, command line) and the errors.

The warp backend runs on warp's CPU device (module-scoped simulators of 3 worlds, as tests/test_sim.py); the env-level
termination runs on C MuJoCo, whose flags come from the same contact sensors and sums.
"""

from __future__ import annotations

import json
import re

import mujoco
import numpy as np
import pytest
import torch

from tocabi_torchrl import robot
from tocabi_torchrl.config import config_from_dict, preset_config
from tocabi_torchrl.envs import TocabiWalk, TocabiWalkConfig
from tocabi_torchrl.envs.config import BoxObstacle, ControlConfig, SceneConfig
from tocabi_torchrl.envs.obstacles import add_obstacles, initial_sole_centre, obstacle_names, world_obstacle_centres
from tocabi_torchrl.envs.tocabi_walk import _servo_spec
from tocabi_torchrl.rl.config import parse_args
from tocabi_torchrl.sim import MujocoSim, SimConfig, WarpSim
from tocabi_torchrl.sim.model import compile_model

N = 3
SEED = 11
JITTERED = BoxObstacle(size=(0.3, 0.6, 0.012), pos=(0.7, 0.1025), jitter=(0.05, 0.03))
FIXED = BoxObstacle(size=(0.2, 0.1, 0.02), pos=(1.5, -0.3))
FAR = (5.0, 5.0)  # a box position no part of the standing robot reaches


def _body(m: mujoco.MjModel, name: str) -> int:
    return mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name)


def _geom(m: mujoco.MjModel, name: str) -> int:
    return mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, name)


# ------------------------------------------------------------------------------------------------------ config
@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"size": (0.3, 0.0, 0.01)}, r"size .* must be > 0"),
        ({"size": (0.3, 0.6, -0.01)}, r"size .* must be > 0"),
        ({"size": (0.3, 0.6)}, r"size .* must be 3 numbers, got 2"),
        ({"size": (0.3, float("nan"), 0.01)}, r"size .* must be finite"),
        ({"pos": (float("inf"), 0.0)}, r"pos .* must be finite"),
        ({"pos": (0.5,)}, r"pos .* must be 2 numbers"),
        ({"pos": "ab"}, r"pos .* must be 2 numbers"),
        ({"jitter": (0.05, -0.01)}, r"jitter .* must be >= 0"),
    ],
)
def test_bad_boxes_are_refused_with_the_field_and_its_unit(kwargs, match):
    with pytest.raises(ValueError, match=match):
        BoxObstacle(**kwargs)


def test_scene_is_validated_with_the_env():
    with pytest.raises(ValueError, match=r"env.scene.obstacles\[1\] must be a BoxObstacle, got dict"):
        TocabiWalkConfig(scene=SceneConfig(obstacles=(JITTERED, {"size": (1, 1, 1)}))).validate()
    with pytest.raises(ValueError, match=r"env.scene.obstacles must be a tuple"):
        TocabiWalkConfig(scene=SceneConfig(obstacles=[JITTERED])).validate()
    with pytest.raises(ValueError, match=r"size .* must be > 0"):
        preset_config("cpu_smoke", **{"env.scene.obstacles": [{"size": [0.3, 0.6, 0.0]}]})
    TocabiWalkConfig(scene=SceneConfig(obstacles=(JITTERED, FIXED))).validate()


def test_box_values_are_normalised_to_float_tuples():
    box = BoxObstacle(size=[1, 2, 3], pos=np.array([0.5, 0.25]), jitter=[0, 0.1])
    assert box == BoxObstacle(size=(1.0, 2.0, 3.0), pos=(0.5, 0.25), jitter=(0.0, 0.1))
    assert box.half_size == (0.5, 1.0, 1.5) and hash(box) == hash(BoxObstacle((1, 2, 3), (0.5, 0.25), (0, 0.1)))


def test_ahead_of_left_foot_is_measured_from_the_initial_left_sole():
    sole = initial_sole_centre(0)
    assert sole == pytest.approx((0.0999, 0.1025, 0.0148), abs=1e-4)
    assert initial_sole_centre(1)[1] == pytest.approx(-0.1025)
    box = BoxObstacle.ahead_of_left_foot(0.005, jitter=(0.05, 0.05))
    assert box.size == (0.3, 0.6, 0.005) and box.jitter == (0.05, 0.05)
    assert box.pos == pytest.approx((sole[0] + 0.6, sole[1]), abs=5e-5) and box.pos == (0.6999, 0.1025)
    side = BoxObstacle.ahead_of_left_foot(0.02, distance=0.5, length=0.2, width=0.15, lateral=0.01)
    assert side.size == (0.2, 0.15, 0.02) and side.pos == pytest.approx((sole[0] + 0.5, sole[1] + 0.01), abs=5e-5)
    assert BoxObstacle().pos == pytest.approx(BoxObstacle.ahead_of_left_foot(0.012).pos, abs=1e-3)


def test_config_round_trips_through_dicts_json_checkpoints_and_the_command_line(tmp_path):
    from tocabi_torchrl.rl.checkpoint import config_from_checkpoint, read_checkpoint

    boxes = (BoxObstacle.ahead_of_left_foot(0.012, jitter=(0.05, 0.05)), FIXED)
    cfg = preset_config("cpu_smoke", **{"env.scene.obstacles": boxes})
    data = cfg.to_dict()
    assert data["env"]["scene"]["obstacles"][1] == {"size": [0.2, 0.1, 0.02], "pos": [1.5, -0.3], "jitter": [0.0, 0.0]}
    assert config_from_dict(data) == cfg
    assert config_from_dict(json.loads(json.dumps(data))) == cfg
    path = tmp_path / "ckpt.pt"
    torch.save({"schema_version": 2, "iteration": 0, "env_steps": 0, "agent": {"actor": {}, "critic": {}},
                "config": data}, path)
    assert config_from_checkpoint(read_checkpoint(path), path) == cfg
    text = json.dumps(data["env"]["scene"]["obstacles"])
    assert parse_args(["--preset", "cpu_smoke", "--env.scene.obstacles", text])[0] == cfg
    one, _ = parse_args(["--preset", "cpu_smoke", "--env.scene.obstacles", '{"size": [0.3, 0.6, 0.005]}'])
    assert one.env.scene.obstacles == (BoxObstacle(size=(0.3, 0.6, 0.005)),)
    assert parse_args(["--preset", "cpu_smoke", "--env.scene.obstacles", "none"])[0].env.scene.obstacles == ()
    # The flat keyword and a whole section reach the same tree.
    assert TocabiWalkConfig().with_flat(obstacles=boxes) == TocabiWalkConfig(scene=SceneConfig(obstacles=boxes))


@pytest.mark.parametrize(
    "text, match",
    [("[{\"size\": [0.3, -1, 0.005]}]", "must be > 0"), ("[{\"hight\": 1}]", r"unknown config option.*hight"),
     ("[[0.3, 0.6, 0.01]]", "BoxObstacle"), ("0.3,0.6,0.01", "expected JSON")],
)
def test_command_line_names_a_bad_box(text, match, capsys):
    with pytest.raises(SystemExit):
        parse_args(["--preset", "cpu_smoke", "--env.scene.obstacles", text])
    err = " ".join(capsys.readouterr().err.replace("│", " ").split())  # tyro's box, as one line
    assert "Error parsing --env.scene.obstacles" in err and re.search(match, err), err


def test_jitter_is_uniform_per_world_within_bounds_and_deterministic_from_the_seed():
    boxes = (JITTERED, FIXED)
    a = world_obstacle_centres(boxes, 64, SEED)
    assert a.shape == (64, 2, 3)
    np.testing.assert_array_equal(a, world_obstacle_centres(boxes, 64, SEED))
    assert not np.allclose(a, world_obstacle_centres(boxes, 64, SEED + 1))
    offset = a[:, 0, :2] - JITTERED.pos
    assert (np.abs(offset) <= np.array(JITTERED.jitter) + 1e-12).all()
    assert (offset.max(axis=0) > 0.6 * np.array(JITTERED.jitter)).all()  # spread over the range, both signs
    assert (offset.min(axis=0) < -0.6 * np.array(JITTERED.jitter)).all()
    assert len(np.unique(a[:, 0, 0])) == 64  # every world its own
    np.testing.assert_array_equal(a[:, 1], np.tile((*FIXED.pos, 0.01), (64, 1)))  # no jitter: the nominal centre
    np.testing.assert_array_equal(a[:, :, 2], np.tile((0.006, 0.01), (64, 1)))  # resting on the ground
    assert world_obstacle_centres((), 4, SEED).shape == (4, 0, 3)


# ---------------------------------------------------------------------------------------------- env geometry
@pytest.fixture(scope="module", params=["mujoco", "warp"])
def env(request) -> TocabiWalk:
    env = TocabiWalk(num_envs=N, device="cpu", seed=SEED, backend=request.param, obstacles=(JITTERED, FIXED))
    env.reset()
    return env


def _world_box_centres(env: TocabiWalk, name: str) -> np.ndarray:
    """(N, 3) centre of geom ``name`` in every world, read from the backend's own state after its forward pass."""
    g = _geom(env.sim.mj_model, name)
    if isinstance(env.sim, WarpSim):
        return env.sim.wp_data.geom_xpos.numpy()[:, g].astype(np.float64)
    return np.array([d.geom_xpos[g] for d in env.sim.mj_data])


def test_boxes_are_static_collidable_box_geoms_of_the_compiled_model(env):
    m = env.sim.mj_model
    for name, box in zip(obstacle_names(2), (JITTERED, FIXED)):
        b, g = _body(m, name), _geom(m, name)
        assert b > 0 and g >= 0 and m.body_parentid[b] == 0 and m.body_mocapid[b] >= 0 and m.body_dofnum[b] == 0
        assert m.geom_bodyid[g] == b and m.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX
        np.testing.assert_allclose(m.geom_size[g], np.array(box.size) / 2)
        np.testing.assert_allclose(m.body_pos[b], (*box.pos, box.size[2] / 2))  # nominal; the bottom at z = 0
        assert m.geom_contype[g] == 1 and m.geom_conaffinity[g] == 1


def test_every_world_has_its_jittered_boxes_in_the_physics(env):
    expected = world_obstacle_centres((JITTERED, FIXED), N, SEED)
    torch.testing.assert_close(env.obstacle_pos, torch.as_tensor(expected, dtype=torch.float32))
    for k, name in enumerate(obstacle_names(2)):
        got = _world_box_centres(env, name)
        np.testing.assert_allclose(got, expected[:, k], atol=1e-6)
        # The body pose the env's tensors show agrees.
        np.testing.assert_allclose(env.sim.xpos[:, _body(env.sim.mj_model, name)].numpy(), expected[:, k], atol=1e-6)
    first = _world_box_centres(env, "obstacle_0")
    assert len({tuple(np.round(p, 6)) for p in first}) == N  # the worlds differ
    assert (np.abs(first[:, :2] - JITTERED.pos) <= np.array(JITTERED.jitter) + 1e-6).all()
    assert first[:, 2] - JITTERED.size[2] / 2 == pytest.approx(np.zeros(N), abs=1e-7)  # bottom face on the ground


def test_boxes_stay_put_through_steps_and_partial_resets(env):
    before = {name: _world_box_centres(env, name) for name in obstacle_names(2)}
    td = env.reset()
    for _ in range(3):
        td = env.step(td.set("action", torch.zeros(N, 13)))["next"]
    env.reset(td.set("_reset", torch.tensor([[True], [False], [True]])))
    for name, where in before.items():
        np.testing.assert_allclose(_world_box_centres(env, name), where, atol=1e-6)


def test_an_env_without_obstacles_compiles_the_model_it_compiled_before():
    env = TocabiWalk(num_envs=1, device="cpu", seed=0, backend="mujoco")
    before = compile_model(_servo_spec(robot.load_spec(), robot.LEG_JOINT_IDS, (ControlConfig().pd_kp, ControlConfig().pd_kv)), SimConfig())
    after = env.sim.mj_model
    fields = [k for k in dir(before) if not k.startswith("_") and isinstance(getattr(before, k), np.ndarray)]
    assert len(fields) > 100
    for k in fields:
        np.testing.assert_array_equal(getattr(after, k), getattr(before, k), err_msg=k)
    assert (after.nbody, after.ngeom, after.nsensor, after.nmocap) == (before.nbody, before.ngeom, before.nsensor, 0)
    assert env.sim.world_mocap_pos is None and env.obstacle_pos.shape == (1, 0, 3)
    assert "obstacle_contact" not in set(env.observation_spec.keys())
    assert env.sim.contact_layout.weights.shape[0] == 4


def test_obstacle_contact_is_a_signal_only_with_obstacles(env):
    assert env.signal_flags()["obstacles"] is True
    assert list(env.observation_spec.keys())[-1] == "obstacle_contact"
    td = env.reset()
    assert td["obstacle_contact"].shape == (N, 2) and td["obstacle_contact"].dtype == torch.bool


# --------------------------------------------------------------------------------------------------- contacts
def _hand_box() -> BoxObstacle:
    """A narrow pillar under the left hand of the initial pose, its top 3 mm into the wrist's collision box."""
    spec = robot.load_spec()
    m = spec.compile()
    d = mujoco.MjData(m)
    d.qpos[:] = robot.INIT_QPOS
    mujoco.mj_forward(m, d)
    wrist = next(g for g in range(m.ngeom) if m.geom_bodyid[g] == _body(m, "L_Wrist2_Link") and m.geom_contype[g])
    low = mujoco.mj_geomDistance(m, d, _geom(m, robot.GROUND_GEOM), wrist, 2.0, np.zeros(6))  # its lowest point
    return BoxObstacle(size=(0.06, 0.06, low + 0.003), pos=tuple(d.geom_xpos[wrist][:2]))


#: A 3 mm plate under both feet (the soles start 1.3 mm above the ground, so they rest 1.7 mm into it).
FEET_BOX = BoxObstacle(size=(0.4, 0.6, 0.003), pos=(0.1, 0.0))


@pytest.fixture(scope="module", params=["mujoco", "warp"])
def contact_sim(request):
    """Three worlds of the PD-leg robot with the feet plate and the hand pillar: world 0 has the plate under the
    feet, world 1 the pillar under the hand, world 2 neither (both boxes far away)."""
    hand = _hand_box()
    spec = _servo_spec(robot.load_spec(), robot.LEG_JOINT_IDS, (ControlConfig().pd_kp, ControlConfig().pd_kv))
    names = add_obstacles(spec, (FEET_BOX, hand))

    def far(box):
        return (*FAR, box.size[2] / 2)

    mocap = {names[0]: np.array([(*FEET_BOX.pos, 0.0015), far(FEET_BOX), far(FEET_BOX)]),
             names[1]: np.array([far(hand), (*hand.pos, hand.size[2] / 2), far(hand)])}
    cls = WarpSim if request.param == "warp" else MujocoSim
    sim = cls(SimConfig(num_worlds=N, device="cpu"), model=spec, mocap_pos=mocap)
    ctrl = torch.as_tensor(robot.INIT_JOINT_POS, dtype=torch.float32)  # PD legs and servo arms hold the pose
    sim.reset(torch.ones(N, dtype=torch.bool), torch.as_tensor(robot.INIT_QPOS, dtype=torch.float32),
              torch.zeros(sim.nv), ctrl)
    return sim


def _counts(sim, name: str) -> torch.Tensor:
    return sim.contact_counts[:, list(sim.contact_layout.names).index("tocabi_contact/" + name)]


def test_feet_on_a_box_are_foot_contact_and_a_hand_on_one_is_forbidden_contact(contact_sim):
    sim = contact_sim
    assert sim.foot_contact.tolist() == [[True, True], [False, False], [False, False]]
    assert sim.obstacle_contact.tolist() == [[True, True], [False, False], [False, False]]
    assert sim.forbidden_ground_contact.tolist() == [False, True, False]
    assert not sim.self_collision.any() and sim.healthy.all()
    # None of it is ground contact: the feet stand on the plate, the hand rests on the pillar.
    assert _counts(sim, "ground/all").tolist() == [0, 0, 0]
    assert (_counts(sim, "scene:obstacle_0/foot_left")[0] > 0) and (_counts(sim, "scene:obstacle_1/all")[1] > 0)
    assert _counts(sim, "scene:obstacle_1/all")[[0, 2]].tolist() == [0, 0]


def test_standing_on_the_box_keeps_the_contacts(contact_sim):
    sim = contact_sim
    for _ in range(10):
        sim.step()
    assert sim.obstacle_contact[0].all() and sim.foot_contact[0].all() and not sim.forbidden_ground_contact[0]
    assert sim.forbidden_ground_contact[1] and not sim.obstacle_contact[1:].any()
    assert _counts(sim, "ground/all")[0] == 0 and sim.healthy.all()
    assert sim.base_pos[0, 2] > 0.9  # still upright on the plate


@pytest.mark.parametrize("box, terminates", [(FEET_BOX, False), ("hand", True)], ids=["feet_on_box", "hand_on_box"])
def test_the_env_terminates_on_a_forbidden_obstacle_contact_only(box, terminates):
    box = _hand_box() if box == "hand" else box
    env = TocabiWalk(num_envs=1, device="cpu", seed=0, backend="mujoco", obstacles=(box,))
    td = env.reset()
    assert td["obstacle_contact"].any().item() != terminates
    done = []
    for _ in range(5):
        out = env.step(td.set("action", torch.zeros(1, 13)))
        done.append(bool(out["next", "terminated"]))
        td = out["next"]
    if terminates:
        assert done[0]
    else:
        assert not any(done) and td["obstacle_contact"].all() and td["foot_contact"].all()
    # The same pillar with forbidden-contact termination off: no termination.
    if terminates:
        calm = TocabiWalk(num_envs=1, device="cpu", seed=0, backend="mujoco", obstacles=(box,),
                          terminate_on_forbidden_contact=False)
        td = calm.reset()
        assert not calm.step(td.set("action", torch.zeros(1, 13)))["next", "terminated"].any()


def test_mocap_positions_are_checked():
    spec = robot.load_spec()
    add_obstacles(spec, (FIXED,))
    with pytest.raises(ValueError, match=r"'base_link', which is not a mocap body"):
        MujocoSim(SimConfig(num_worlds=2, device="cpu"), model=spec, mocap_pos={"base_link": np.zeros((2, 3))})
    with pytest.raises(ValueError, match=r"mocap_pos\['obstacle_0'\] must be \(2, 3\) finite positions"):
        MujocoSim(SimConfig(num_worlds=2, device="cpu"), model=spec, mocap_pos={"obstacle_0": np.zeros((3, 3))})
    with pytest.raises(ValueError, match="obstacle names are reserved"):
        add_obstacles(spec, (FIXED,))


@pytest.mark.parametrize("box, problem", [
    (BoxObstacle(size=(0.3, 0.6, 0.012), pos=(0.3, 0.1)), "overlaps the left sole"),
    (BoxObstacle(size=(0.2, 0.2, 0.05), pos=(0.1, -0.3), jitter=(0.0, 0.2)), "overlaps the right sole"),
])
def test_a_box_the_robot_would_start_inside_is_refused(box, problem):
    from tocabi_torchrl.envs.obstacles import check_clear_of_start

    with pytest.raises(ValueError, match=rf"env.scene.obstacles\[1\] .*{problem} where the robot starts"):
        check_clear_of_start((FIXED, box))
    # Clear of both soles: ahead of them, beside them once its jitter cannot reach, or a plate a few mm high.
    check_clear_of_start((BoxObstacle.ahead_of_left_foot(0.012), BoxObstacle((0.2, 0.2, 0.05), (0.1, -0.3)),
                          FEET_BOX))
    with pytest.raises(ValueError, match="overlaps the left sole"):
        TocabiWalk(num_envs=1, device="cpu", backend="mujoco", obstacles=(BoxObstacle((0.4, 0.6, 0.012), (0.1, 0.0)),))
