"""Number checks of the config trees (``tree.check_field_types``): a NaN gain, an inf command bound, a float step
count or a number given as text is refused by its path before an env is built; every default and preset passes."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from tocabi_torchrl.config import PRESETS, preset_config
from tocabi_torchrl import make_env
from tocabi_torchrl.envs import TocabiWalk, TocabiWalkConfig
from tocabi_torchrl.envs.command import CommandConfig
from tocabi_torchrl.envs.config import ControlConfig
from tocabi_torchrl.tree import check_field_types

NAN, INF = math.nan, math.inf

#: flat TocabiWalk option(s) -> the error (its path, what it got, what is accepted).
BAD = [
    ({"pd_kp": (100.0,) * 3 + (NAN,) * 9}, r"env.control.pd_kp\[3\] must be a finite number.*got nan"),
    ({"pd_kv": (INF,) * 12}, r"env.control.pd_kv\[0\] must be a finite number.*got inf"),
    ({"pd_nominal": (NAN,) * 12}, r"env.control.pd_nominal\[0\] must be a finite number"),
    ({"pd_kp": "100"}, r"env.control.pd_kp must be a tuple of finite numbers, got '100'"),
    ({"pd_action_scale": "0.5"}, r"env.control.pd_action_scale must be a finite number.*bool or text\), got '0.5'"),
    ({"min_pelvis_height": "0.6"}, r"env.task.min_pelvis_height must be a finite number.*got '0.6'"),
    ({"phase_rate_gain": "1"}, r"env.task.phase_rate_gain must be a finite number.*got '1'"),
    ({"phase_rate_gain": NAN}, r"env.task.phase_rate_gain must be a finite number.*got nan"),
    ({"phase_rate_gain": True}, r"env.task.phase_rate_gain must be a finite number.*got True"),
    # A tilt in degrees: the neck's angle never passed 60 rad, so the neck-tilt termination was off without a word.
    ({"max_neck_angle": 60.0}, r"env.task.max_neck_angle must be a finite number in \[0, 3.14.*got 60.0; the neck's "
                               r"rotation from upright \(yaw included\) is at most π rad.*give it in rad"),
    ({"max_episode_steps": 1000.0}, r"env.task.max_episode_steps must be an int \(not a float.*got 1000.0"),
    ({"command": CommandConfig(vx_range=(0.0, INF))}, r"env.command.vx_range\[1\] must be a finite number"),
    ({"command": CommandConfig(vx_range=(NAN, 0.7))}, r"env.command.vx_range\[0\] must be a finite number"),
    ({"command": CommandConfig(vx_range=(0.0, 1e9))}, r"env.command.vx_range \(0.0, 1000000000.0\) reaches past 10"),
    ({"command": CommandConfig(vy_range=(-20.0, 0.0))}, r"env.command.vy_range \(-20.0, 0.0\) reaches past 10 m/s"),
    ({"command": CommandConfig(vx_range=(0.0, 0.5, 0.7))}, r"env.command.vx_range must be a tuple of 2 finite"),
    ({"command": CommandConfig(resample_every=2.5)}, r"env.command.resample_every must be an int.*got 2.5"),
    ({"command": CommandConfig(resample_every="100")}, r"env.command.resample_every must be an int.*got '100'"),
    ({"command": CommandConfig(max_ramp_steps=2.5)}, r"env.command.max_ramp_steps must be an int.*got 2.5"),
    ({"command": CommandConfig(max_ramp_steps=0)}, r"env.command.max_ramp_steps must be an int >= 1"),
    ({"command": CommandConfig(resample_every=0)}, r"env.command.resample_every must be an int >= 1"),
]


@pytest.mark.parametrize("flat, message", BAD, ids=[str(k) for k, _ in BAD])
def test_bad_numbers_are_refused_by_their_path(flat, message):
    with pytest.raises(ValueError, match=message):
        TocabiWalkConfig().with_flat(**flat).validate()


def test_the_env_refuses_them_before_it_builds():
    # These used to build: a NaN gain ended every episode at its first step, an inf bound reached the command
    # observation, and a float ramp length failed as a raw TypeError in randint at the first re-sample.
    with pytest.raises(ValueError, match=r"env.control.pd_kp\[0\]"):
        TocabiWalk(num_envs=1, device="cpu", pd_kp=(NAN,) * 12)
    with pytest.raises(ValueError, match=r"env.command.vx_range\[1\]"):
        TocabiWalk(num_envs=1, device="cpu", command=CommandConfig(vx_range=(0.0, INF), resample_every=2))
    with pytest.raises(ValueError, match=r"env.command.max_ramp_steps must be an int"):
        CommandConfig(max_ramp_steps=2.5).validate()  # as VelocityCommand checks its config on its own


def test_a_misspelt_option_names_the_nearest():
    with pytest.raises(TypeError, match=r"\['num_env'\]; 'num_env': did you mean 'num_envs'\?; use a section "
                                        r"\(num_envs, sim, .*\) or one of \[.*'control_mode'"):
        TocabiWalk(num_env=3, device="cpu")
    with pytest.raises(TypeError, match=r"\['max_episode_step'\]; 'max_episode_step': did you mean "
                                        r"'max_episode_steps'"):
        TocabiWalkConfig().with_flat(max_episode_step=10)


def test_every_default_and_preset_passes_and_none_stays_allowed():
    TocabiWalkConfig().validate()
    TocabiWalkConfig.reference().validate()
    for name in PRESETS:
        cfg = preset_config(name)
        check_field_types(cfg)  # the whole run tree, as RunConfig.validate may call it
        cfg.env.validate()
    cfg = TocabiWalkConfig().with_flat(nconmax=None, njmax=None, sim_threads=None, motion=None)
    cfg.validate()
    assert cfg.sim.nconmax is None


def test_a_motion_given_as_a_path_object_is_a_path(tmp_path):
    """A pathlib.Path, as ReferenceMotion.from_file takes, was refused by the motion check ("must be a path ...,
    got PosixPath(...)"); an empty one is still refused."""
    from tocabi_torchrl import robot

    shipped = Path(robot.asset_path("motions", "tocabi_walk.npz"))
    TocabiWalkConfig().with_flat(motion=shipped).validate()
    env = TocabiWalk(num_envs=1, device="cpu", config=TocabiWalkConfig().with_flat(motion=shipped))
    assert env.motion.num_rows > 0
    with pytest.raises(ValueError, match="env.task.motion must be a path"):
        TocabiWalkConfig().with_flat(motion="  ").validate()


@pytest.mark.parametrize("model_path", [5, "", "  "])
def test_a_model_path_that_is_no_path_is_refused_by_name(model_path):
    # 5 ended in a raw TypeError when the env loaded the model, and "" in "robot model file not found: .".
    with pytest.raises(ValueError, match="env.task.model_path must be a path to a MuJoCo XML model"):
        TocabiWalkConfig().with_flat(model_path=model_path).validate()
    TocabiWalkConfig().with_flat(model_path=None).validate()


def test_numpy_scalars_are_taken_as_plain_numbers():
    cfg = TocabiWalkConfig().with_flat(pd_action_scale=np.float32(0.25), max_episode_steps=np.int64(100),
                                       pd_kp=tuple(np.float32(50.0) for _ in range(12)),
                                       command=CommandConfig(resample_every=np.int32(7)))
    cfg.validate()
    assert type(cfg.control.pd_action_scale) is float and cfg.control.pd_action_scale == 0.25
    assert type(cfg.task.max_episode_steps) is int and type(cfg.command.resample_every) is int
    assert all(type(v) is float for v in cfg.control.pd_kp)
    assert TocabiWalkConfig().with_flat(phase_rate_gain=1).validate() is None  # an int for a float
    # The env's own num_envs too (it once said "must be a positive int, got np.int64(2)"); a dict for the config
    # tree is named, not an AttributeError from inside.
    assert TocabiWalk(num_envs=np.int64(2), device="cpu").num_envs == 2
    for bad in (np.float64(2.0), 2.0, True, torch.tensor([1, 2])):
        with pytest.raises(ValueError, match="num_envs must be a positive int"):
            TocabiWalk(num_envs=bad, device="cpu")
    with pytest.raises(TypeError, match="config must be a TocabiWalkConfig, got dict; pass settings as keywords"):
        TocabiWalk(num_envs=2, device="cpu", config={"num_envs": 2})
    # .to() moved the specs alone and failed later, inside a step; the env's own device is still fine.
    env = TocabiWalk(num_envs=2, device="cpu")
    assert env.to("cpu") is env and env.to("cpu:0") is env and env.device == torch.device("cpu")
    with pytest.raises(RuntimeError, match="cannot move from cpu to cuda: .* build it there|torch sees no CUDA GPU"):
        env.to("cuda")
    with pytest.raises(ValueError, match="unsupported device meta"):
        env.to("meta")


def test_num_envs_is_read_as_the_config_reads_numbers():
    # TocabiWalk took torch.tensor(True) as 1 world and torch.tensor([2]) as 2 (operator.index), which the config
    # refuses; the config refused torch.tensor(4) and np.int64(4) as env.num_envs, which every other int field takes.
    for count in (torch.tensor(4), np.int64(4), np.array(4), torch.tensor(4, dtype=torch.uint8)):
        env = TocabiWalk(num_envs=count, device="cpu")
        assert type(env.num_envs) is int and env.num_envs == 4 and env.batch_size == torch.Size([4])
        cfg = TocabiWalkConfig().with_flat(num_envs=count)
        cfg.validate()
        assert type(cfg.num_envs) is int and cfg.num_envs == 4
    for bad in (torch.tensor(True), np.bool_(True), torch.tensor(4.5), 4.5, True, -1, 0, "4"):
        with pytest.raises(ValueError, match=r"num_envs must be a positive int \(a numpy integer or 0-d integer "
                                             r"tensor is taken too\), got "):
            TocabiWalk(num_envs=bad, device="cpu")
    for one in (torch.tensor([4]), np.array([4])):
        with pytest.raises(ValueError, match=r"an array or tensor of shape \(1,\): pass the count itself"):
            TocabiWalk(num_envs=one, device="cpu")
        with pytest.raises(ValueError, match="env.num_envs must be a positive int"):
            TocabiWalkConfig().with_flat(num_envs=one).validate()
    with pytest.raises(ValueError, match="env.num_envs must be a positive int, got tensor\\(True\\)"):
        TocabiWalkConfig().with_flat(num_envs=torch.tensor(True)).validate()


def test_build_env_reads_num_envs_as_the_env_does():
    # rl.trainer.build_env and the adapters' build_env took np.int64(2) but refused torch.tensor(2), which TocabiWalk
    # and its config take; now all read the count alike and refuse what they refuse.
    from tocabi_torchrl.adapters._build import build_env as adapter_env
    from tocabi_torchrl.rl.trainer import build_env as trainer_env

    cfg = preset_config("cpu_smoke", device="cpu")
    env, task = adapter_env(torch.tensor(2), "cpu")
    assert env.batch_size == torch.Size([2]) and type(task.env.num_envs) is int and task.env.num_envs == 2
    assert trainer_env(cfg, "cpu", num_envs=np.array(3)).batch_size == torch.Size([3])
    for bad in (torch.tensor(True), np.bool_(True), torch.tensor(2.0), 2.0, 0, -1, torch.tensor([2]), np.array([2])):
        with pytest.raises(ValueError, match=r"num_envs must be a positive int \(a numpy integer or 0-d integer "
                                             r"tensor is taken too\), got "):
            adapter_env(bad, "cpu")
        with pytest.raises(ValueError, match=r"num_envs must be a positive int .*; None for the run's env.num_envs"):
            trainer_env(cfg, "cpu", num_envs=bad)
    with pytest.raises(ValueError, match=r"shape \(1,\): pass the count itself"):
        adapter_env(torch.tensor([2]), "cpu")


@pytest.mark.parametrize("number, count", [(torch.tensor(0.5), torch.tensor(3)), (np.float32(0.5), np.int64(3))],
                         ids=["0-d tensors", "numpy scalars"])
def test_every_section_takes_0d_tensors_and_numpy_scalars_as_plain_numbers(number, count):
    # PushConfig, SimConfig and the config tree refused a 0-d tensor that DynamicsRandomization took (text too,
    # through float()) and kept as a tensor; SimConfig and EnvSimConfig refused a numpy int that the tree took. One
    # rule now: the number it holds, stored as a plain number, on every path.
    from tocabi_torchrl.config import RunConfig
    from tocabi_torchrl.envs.config import ControlConfig, EnvSimConfig, PushConfig, TaskConfig
    from tocabi_torchrl.sim import SimConfig
    from tocabi_torchrl.sim.dynamics_config import DynamicsRandomization

    pushes = PushConfig(count=count, speed=(number, 1.0), calm_fraction=number)
    pushes.validate()
    assert (pushes.count, pushes.speed, pushes.calm_fraction) == (3, (0.5, 1.0), 0.5)
    assert type(pushes.count) is int and type(pushes.speed[0]) is float and type(pushes.calm_fraction) is float
    dynamics = DynamicsRandomization(mass_scale=(number, 1.0))
    dynamics.validate()
    assert dynamics.mass_scale == (0.5, 1.0) and type(dynamics.mass_scale[0]) is float
    sim = SimConfig(num_worlds=count, threads=count, solver_tolerance=number)
    sim.validate()
    assert (sim.num_worlds, sim.threads, sim.solver_tolerance) == (3, 3, 0.5) and type(sim.num_worlds) is int
    env_sim = EnvSimConfig(substeps=count, threads=count)
    env_sim.validate()
    assert (env_sim.substeps, env_sim.threads) == (3, 3) and type(env_sim.threads) is int
    # The task and control sections alone kept the tensor (the whole tree converted it).
    task, control = TaskConfig(phase_rate_gain=number), ControlConfig(pd_action_scale=number)
    task.validate()
    control.validate()
    assert type(task.phase_rate_gain) is float and type(control.pd_action_scale) is float
    run = RunConfig()
    run.env.pushes, run.env.control.pd_action_scale = PushConfig(count=count, speed=(number, number)), number
    run.validate()
    assert run.env.pushes.speed == (0.5, 0.5) and type(run.env.control.pd_action_scale) is float
    # A bool, a NaN or a 1-element tensor is no number on any path.
    for bad in (torch.tensor(True), torch.tensor(math.nan), torch.tensor([0.5])):
        with pytest.raises(ValueError, match="env.pushes.speed"):
            PushConfig(count=1, speed=(bad, 1.0)).validate()
        with pytest.raises(ValueError, match=r"env.dynamics.mass_scale\[0\]"):
            DynamicsRandomization(mass_scale=(bad, 1.0)).validate()
        with pytest.raises(ValueError, match="SimConfig.solver_tolerance"):
            SimConfig(solver_tolerance=bad).validate()
    with pytest.raises(ValueError, match=r"env.dynamics.mass_scale\[0\] must be a finite number.*got '0.8'"):
        DynamicsRandomization(mass_scale=("0.8", 1.0)).validate()


@dataclass(frozen=True)
class _Item:
    gain: float = 1.0
    limit: float | None = None
    pair: tuple[float, float] = (0.0, 1.0)


@dataclass
class _Tree:
    steps: int = 3
    items: tuple[_Item, ...] = ()
    name: str = "x"


def test_check_field_types_reads_string_annotations_items_and_frozen_trees():
    tree = _Tree(steps=np.int16(4), items=(_Item(), _Item(gain=np.float64(2.0), limit=np.float32(0.5))))
    check_field_types(tree, "t.")  # this module's annotations are strings (from __future__ import annotations)
    assert type(tree.steps) is int and type(tree.items[1].gain) is float and type(tree.items[1].limit) is float
    with pytest.raises(ValueError, match=r"t.items\[1\].pair\[1\] must be a finite number.*got inf"):
        check_field_types(_Tree(items=(_Item(), _Item(pair=(0.0, INF)))), "t.")
    with pytest.raises(ValueError, match=r"t.items\[0\].limit must be a finite number.*got '1'"):
        check_field_types(_Tree(items=(_Item(limit="1"),)), "t.")
    with pytest.raises(ValueError, match=r"t.steps must be an int.*got True"):
        check_field_types(_Tree(steps=True), "t.")


def test_the_convex_collision_slots_reach_mujoco_warp_and_a_bad_count_is_named():
    from tocabi_torchrl.envs import TocabiWalk
    from tocabi_torchrl.envs.config import EnvSimConfig
    from tocabi_torchrl.sim.buffers import NCCDMAX

    with pytest.raises(ValueError, match=r"env.sim.nccdmax must be a positive int or None, got 0"):
        EnvSimConfig(nccdmax=0).validate()
    env = TocabiWalk(num_envs=2, device="cpu", config=TocabiWalkConfig(sim=EnvSimConfig(backend="warp", nccdmax=4)))
    assert env.sim.wp_data.naccdmax == 2 * 4
    default = TocabiWalk(num_envs=2, device="cpu", config=TocabiWalkConfig(sim=EnvSimConfig(backend="warp")))
    assert default.sim.wp_data.naccdmax == 2 * NCCDMAX


@pytest.mark.parametrize("sim, message", [
    (dict(nccdmax=100), r"env.sim.nccdmax must be <= the default env.sim.nconmax \(48\).*got 100; lower "
                        r"env.sim.nccdmax or raise env.sim.nconmax to at least 100"),
    (dict(nccdmax=40, nconmax=20, backend="mujoco"), r"env.sim.nccdmax must be <= env.sim.nconmax \(20\).*got 40"),
])
def test_more_convex_collision_slots_than_contacts_are_refused_by_the_env_path(sim, message):
    # Only the warp backend's SimConfig refused them, at the env's build and as "SimConfig.nccdmax"; the run config
    # and a config naming the mujoco backend took them.
    from tocabi_torchrl.config import RunConfig
    from tocabi_torchrl.tree import replace_paths

    with pytest.raises(ValueError, match=message):
        replace_paths(RunConfig(), {f"env.sim.{k}": v for k, v in sim.items()}).validate()
    replace_paths(RunConfig(), {"env.sim.nccdmax": 20, "env.sim.nconmax": 20}).validate()


@pytest.mark.parametrize("backend", ["mujoco", "warp"])
def test_the_solver_iteration_cap_reaches_both_backends_and_a_bad_cap_is_named(backend):
    from tocabi_torchrl.envs import TocabiWalk
    from tocabi_torchrl.envs.config import EnvSimConfig

    with pytest.raises(ValueError, match=r"env.sim.solver_iterations must be a positive int or None, got 0"):
        EnvSimConfig(solver_iterations=0).validate()
    env = TocabiWalk(num_envs=2, device="cpu",
                     config=TocabiWalkConfig(sim=EnvSimConfig(backend=backend, solver_iterations=3)))
    assert env.sim.mj_model.opt.iterations == 3
    if backend == "warp":  # what mujoco-warp's solver loop reads
        assert int(env.sim.wp_model.opt.iterations) == 3
    default = TocabiWalk(num_envs=2, device="cpu", config=TocabiWalkConfig(sim=EnvSimConfig(backend=backend)))
    assert default.sim.mj_model.opt.iterations == 20  # the model's own


@pytest.mark.gpu
def test_the_capped_solver_steps_on_the_gpu_without_a_torch_sync_and_bounds_every_substep(monkeypatch):
    # Random full-scale leg torques make robots stumble and fall, the states that need the most iterations.
    import torch
    import warp as wp

    from tocabi_torchrl import robot
    from tocabi_torchrl.envs.config import EnvSimConfig
    from tocabi_torchrl.sim import SimConfig, WarpSim

    from warp_substeps import after_each_substep

    if not torch.cuda.is_available():
        pytest.skip("needs CUDA")
    n = 256
    env = TocabiWalk(num_envs=n, device="cuda", seed=0, control_mode="torque",
                     config=TocabiWalkConfig(sim=EnvSimConfig(backend="warp", solver_iterations=4)))
    td = env.reset()
    gen = torch.Generator(device="cuda").manual_seed(0)
    actions = [torch.rand(n, 13, device="cuda", generator=gen) * 2 - 1 for _ in range(40)]
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:  # the env's captured step
        for action in actions:
            td = env.step(td.set("action", action))["next"]
    finally:
        torch.cuda.set_sync_debug_mode(0)
    assert bool(torch.isfinite(td["joint_pos"]).all())

    # Every substep's iterations, read right after mjw.step/step2 (the step's closing forward pass overwrites them),
    # on eager CUDA steps of the simulator, with and without the cap; the maximum stays on the device.
    def most_per_substep(cap):
        sim = WarpSim(SimConfig(num_worlds=n, device="cuda", use_graph=False, solver_iterations=cap))
        most = torch.zeros((), dtype=torch.int32, device="cuda")
        calls = []

        def record(d):
            calls.append(1)
            torch.maximum(most, wp.to_torch(d.solver_niter).max(), out=most)

        after_each_substep(monkeypatch, record)
        start = torch.as_tensor(robot.INIT_QPOS, dtype=torch.float32, device="cuda")
        sim.reset(torch.ones(n, dtype=torch.bool, device="cuda"), start, torch.zeros(sim.nv, device="cuda"),
                  torch.zeros(sim.nu, device="cuda"))
        limits = torch.as_tensor(robot.LEG_TORQUE_LIMITS, dtype=torch.float32, device="cuda")
        torques = [(torch.rand(n, 12, device="cuda", generator=gen) * 2 - 1) * limits for _ in range(20)]
        torch.cuda.synchronize()
        torch.cuda.set_sync_debug_mode("error")
        try:
            for tau in torques:
                sim.ctrl[:, :12].copy_(tau)
                sim.step()
        finally:
            torch.cuda.set_sync_debug_mode(0)
            monkeypatch.undo()
        assert len(calls) == 20 * sim.config.substeps
        return int(most)

    assert 1 <= most_per_substep(4) <= 4
    assert most_per_substep(None) > 4  # the same robots need more without the cap, so the bound could fail


@pytest.mark.parametrize("config,where,kind", [
    (lambda: TocabiWalkConfig(dynamics=None), "env.dynamics", "DynamicsRandomization"),
    (lambda: TocabiWalkConfig(pushes={"count": 1}), "env.pushes", "PushConfig"),
    (lambda: TocabiWalkConfig(pushes=0), "env.pushes", "PushConfig"),
    (lambda: TocabiWalkConfig(control=ControlConfig(actuators={"delay_substeps": (1, 2)})), "env.control.actuators",
     "ActuatorConfig"),
])
def test_a_section_given_as_none_or_a_dict_to_the_config_class_is_named(config, where, kind):
    # Each failed with "AttributeError: 'NoneType' (or 'dict') object has no attribute 'validate'".
    with pytest.raises(ValueError, match=rf"{where} must be a {kind}, got .*\({kind}\(\) for its defaults\)"):
        make_env(num_envs=2, device="cpu", config=config())
