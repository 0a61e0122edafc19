"""The torch-free runtime: it never imports torch, reproduces the TorchRL env's policy input and leg commands on the
same states, walks every shipped policy like the TorchRL env (C MuJoCo backend), drives the reference robot model
when ``../shared/reference`` is there, and refuses malformed or mismatched contracts. CPU only."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("onnxruntime")

from model_files import (DEGREE_COMPILERS, shipped_model_in_degrees, shipped_model_mixing_units, shipped_model_read_as,
                         shipped_model_with_range)
from reference_data import REFERENCE_DIR

from tocabi_torchrl import robot
from tocabi_torchrl.runtime import ContractError, PolicyRuntime, RobotState, load_contract
from tocabi_torchrl.runtime.contract import content_sha256

POLICIES = ("ppo", "torque")
#: Robots per side in the walking comparison (each its own 1e-6 perturbation of a chaotic gait).
WALK_ROBOTS = 16


def _contract(name: str):
    return robot.asset_path("policies", f"tocabi_walk_{name}.json")


def _sim2sim_subprocess(contract, seconds: float, num_robots: int, init_rows=None, model=None,
                        remove_meshes=False, perturbation=0.0) -> subprocess.Popen:
    """Start run_sim2sim in a fresh interpreter that reports its metrics and whether torch/torchrl got imported."""
    code = textwrap.dedent(f"""
        import json, sys
        from tocabi_torchrl.runtime.mujoco_driver import run_sim2sim
        r = run_sim2sim({str(contract)!r}, {None if model is None else str(model)!r}, seconds={seconds},
                        num_robots={num_robots}, init_rows={init_rows!r}, remove_meshes={remove_meshes},
                        perturbation={perturbation})
        out = r.as_dict()
        out["imported"] = sorted(m for m in ("torch", "torchrl", "tensordict") if m in sys.modules)
        print(json.dumps(out))
    """)
    return subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _result(proc: subprocess.Popen, timeout: float = 300) -> dict:
    out, err = proc.communicate(timeout=timeout)
    assert proc.returncode == 0, err[-3000:]
    return json.loads(out.strip().splitlines()[-1])


def test_runtime_never_imports_torch():
    result = _result(_sim2sim_subprocess(_contract("ppo"), seconds=0.2, num_robots=1))
    assert result["imported"] == []
    assert result["survival"] == 1.0


def _state(td, velocities: bool = False) -> RobotState:
    extra = ({"base_lin_vel": td["base_lin_vel"].numpy(), "base_ang_vel": td["base_ang_vel"].numpy()}
             if velocities else {})
    return RobotState(base_quat=td["base_quat"].numpy(), joint_pos=td["joint_pos"].numpy(),
                      joint_vel=td["joint_vel"].numpy(), foot_force=td["foot_force"].numpy(),
                      foot_torque=td["foot_torque"].numpy(), **extra)


def _small_exported_policy(root: Path, name: str, **overrides) -> tuple[Path, Path]:
    """A ``cpu_smoke`` policy with ``overrides``, trained two iterations on the CPU and exported: (checkpoint,
    contract)."""
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.export.onnx_export import export_policy
    from tocabi_torchrl.rl.trainer import train

    cfg = preset_config("cpu_smoke", device="cpu", **{"env.num_envs": 4, "ppo.steps_per_env": 8,
                                                      "ppo.minibatch_size": 16, **overrides},
                        total_env_steps=64, run_dir=str(root), name=name, progress_bar=False, eval_at_end=False)
    train(cfg)
    checkpoint = root / name / "checkpoints" / "iter_000002.pt"
    export_policy(checkpoint, root / f"{name}.onnx")
    return checkpoint, root / f"{name}.json"


@pytest.fixture(scope="module")
def base_vel_policy(tmp_path_factory):
    """A torque policy of the pelvis-velocity observation (``transforms.observation`` base_vel, the ``torque``
    preset's): (checkpoint, contract)."""
    return _small_exported_policy(tmp_path_factory.mktemp("base_vel"), "bv", **{
        "transforms.observation": "base_vel", "env.control.mode": "torque"})


@pytest.fixture(scope="module")
def pd_held_policy(tmp_path_factory):
    """A policy of the ``pd_held`` mode (the PD runs at the control rate and sends torques): (checkpoint,
    contract)."""
    return _small_exported_policy(tmp_path_factory.mktemp("pd_held"), "ph", **{"env.control.mode": "pd_held"})


@pytest.mark.parametrize("name", [*POLICIES, "base_vel", "pd_held"])
def test_runtime_reproduces_torchrl_observation_and_commands(name, request):
    """On the states of a TorchRL rollout (C MuJoCo backend), the runtime's policy input equals the env's
    ``observation`` and its leg commands and upper-body targets equal what the env wrote into ``ctrl``; for a
    policy that observes the pelvis velocity too (``base_vel``), given in the state; for a ``pd_held`` policy, the
    PD's torques computed by the runtime from the state, and the history's leg actions their fraction of the
    limits (the policy input holds them)."""
    import torch
    from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

    from tocabi_torchrl.export import load_policy
    from tocabi_torchrl.evaluation.gait_test import _fixed_command

    velocities = name == "base_vel"
    checkpoint, contract = (request.getfixturevalue(f"{name}_policy") if name in ("base_vel", "pd_held") else
                            (robot.asset_path("policies", f"tocabi_walk_{name}.pt"), _contract(name)))
    policy = load_policy(checkpoint, num_envs=4, command=_fixed_command((0.5, 0.0)))
    env, base = policy.env, policy.env.base_env
    runtime = PolicyRuntime(contract)
    if velocities:  # the contract reads the two signals, as the env's layout does
        assert {"base_lin_vel", "base_ang_vel"} <= set(runtime.observation.signals)
    # Torque commands scale a ~1e-6 ONNX-vs-torch action difference by up to 333 N·m (the limits), pd_held's by
    # up to kp·scale N·m (2,500 N·m per action unit).
    gain = runtime.kp * runtime.action_scale if runtime.mode == "pd_held" else runtime.torque_limits
    leg_tol = 6e-6 * float(gain.max()) if runtime.leg_kind == "torque" else 1e-5
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.reset()
        cmd = runtime.reset(_state(td, velocities), (0.5, 0.0), init_row=base.init_row.numpy())
        for _ in range(60):
            np.testing.assert_allclose(runtime.policy_input(), td["observation"].numpy(), atol=1e-4, rtol=0)
            td = env.step(policy.agent.actor(td))
            ctrl = base.sim.ctrl.numpy()
            np.testing.assert_allclose(cmd.leg, ctrl[:, :12], atol=leg_tol, rtol=0)
            np.testing.assert_allclose(cmd.upper_targets, ctrl[:, 12:], atol=1e-5, rtol=0)
            np.testing.assert_allclose(cmd.reference, td["next", "ref_joint_pos"].numpy(), atol=1e-5, rtol=0)
            td = step_mdp(td)
            cmd = runtime.step(_state(td, velocities))


def test_a_pd_held_contract_sends_torques_and_its_robots_take_the_actuator_layer(pd_held_policy):
    """pd_held's contract commands torques with the robot's PD gains on the reference (no joint range: the target is
    not clipped), and the sim-to-sim driver keeps its leg motors as motors, so the actuator layer applies."""
    import mujoco

    from tocabi_torchrl.envs.config import ControlConfig
    from tocabi_torchrl.runtime import randomization as rnd
    from tocabi_torchrl.runtime.mujoco_driver import build_model, run_sim2sim

    _, contract = pd_held_policy
    loaded = load_contract(contract)
    leg = loaded["action"]["leg"]
    assert (leg["kind"], leg["center"]) == ("torque", "reference") and "joint_range" not in leg
    assert leg["kp"] == list(ControlConfig().pd_kp) and leg["kv"] == list(ControlConfig().pd_kv)
    runtime = PolicyRuntime(contract)
    assert runtime.leg_kind == "torque"
    model = build_model(loaded, robot.asset_path("tocabi", "tocabi.xml"))
    legs = [model.actuator(n.replace("_Joint", "_Motor")).id for n in loaded["robot"]["leg_joint_names"]]
    assert (model.actuator_biastype[legs] == mujoco.mjtBias.mjBIAS_NONE).all()  # motors, not position servos
    # The actuator layer acts: delayed, rescaled torques walk the robots elsewhere than the nominal ones.
    actuators_only = rnd.Randomization(actuators=rnd.TOCABI_LAB.actuators)
    lab = run_sim2sim(runtime, seconds=0.2, num_robots=2, randomize=actuators_only)
    assert lab.per_robot_forward_m != run_sim2sim(runtime, seconds=0.2, num_robots=2).per_robot_forward_m


def test_a_velocity_policy_refuses_a_state_without_the_velocities(base_vel_policy):
    _, contract = base_vel_policy
    runtime = PolicyRuntime(contract)
    state = RobotState(base_quat=np.tile([1.0, 0.0, 0.0, 0.0], (2, 1)), joint_pos=np.zeros((2, 33)),
                       joint_vel=np.zeros((2, 33)), foot_force=np.zeros((2, 2, 3)), foot_torque=np.zeros((2, 2, 3)),
                       base_ang_vel=np.zeros((2, 3)))
    with pytest.raises(ContractError, match=r"RobotState\.base_lin_vel is None, but this policy observes it"):
        runtime.reset(state, (0.5, 0.0))
    state.base_lin_vel = np.zeros((2, 2))
    with pytest.raises(ContractError, match=r"RobotState\.base_lin_vel has shape \(2, 2\), expected \(2, 3\)"):
        runtime.reset(state, (0.5, 0.0))
    state.base_lin_vel = np.full((2, 3), np.nan)
    with pytest.raises(ContractError, match=r"RobotState\.base_lin_vel is not finite"):
        runtime.reset(state, (0.5, 0.0))
    state.base_lin_vel = np.zeros((2, 3))
    assert runtime.reset(state, (0.5, 0.0)).action.shape == (2, 13)
    # A policy of the reference observation never reads them: None is fine there.
    state.base_lin_vel = state.base_ang_vel = None
    assert PolicyRuntime(_contract("ppo")).reset(state, (0.5, 0.0)).action.shape == (2, 13)


def test_the_sim_to_sim_driver_runs_a_velocity_policy(base_vel_policy):
    from tocabi_torchrl.runtime.mujoco_driver import run_sim2sim

    result = run_sim2sim(base_vel_policy[1], None, seconds=0.2, num_robots=2)
    assert result.num_robots == 2 and result.seconds == pytest.approx(0.2)


def test_the_driver_reads_the_pelvis_velocity_as_the_env_does():
    """The sim2sim driver's state: linear velocity rotated from the world frame into the pelvis's, angular velocity as
    MuJoCo's free joint gives it (the pelvis frame), the env's ``base_lin_vel``/``base_ang_vel`` definitions."""
    import mujoco
    import torch

    from tocabi_torchrl.rotations import quat_rotate_inverse
    from tocabi_torchrl.runtime.mujoco_driver import _state

    m = mujoco.MjModel.from_xml_path(str(robot.asset_path("tocabi", "tocabi.xml")))
    rng = np.random.default_rng(0)
    datas = [mujoco.MjData(m) for _ in range(3)]
    for d in datas:
        q = rng.normal(size=4)
        d.qpos[3:7] = q / np.linalg.norm(q)
        d.qvel[:6] = rng.normal(size=6)
    state = _state(m, datas, (np.arange(3), np.arange(3)))
    quat = torch.tensor(np.stack([d.qpos[3:7] for d in datas]))
    lin = quat_rotate_inverse(quat, torch.tensor(np.stack([d.qvel[:3] for d in datas]))).numpy()
    np.testing.assert_allclose(state.base_lin_vel, lin, atol=1e-6)
    np.testing.assert_allclose(state.base_ang_vel, np.stack([d.qvel[3:6] for d in datas]), atol=1e-6)
    assert np.abs(state.base_lin_vel - np.stack([d.qvel[:3] for d in datas])).max() > 0.1  # rotated, not copied


@pytest.mark.slow  # 16 robots x 2000 steps per side: ~40 s on 2 idle cores, 190-240 s on a loaded 2-core machine
@pytest.mark.parametrize("name", POLICIES)
def test_runtime_walks_like_the_torchrl_env(name, tmp_path, record_property):
    """8 s at (0.5, 0) on the authored model: the torch-free runtime (a subprocess) and the TorchRL env (C MuJoCo)
    give the same survival and mean forward distances within 5 % (WALK_ROBOTS robots each, same start rows).

    Walking is chaotic: the ~1e-6 difference between ONNX and torch arithmetic grows to centimetres within 2 s
    (docs/deploying.md), so single trajectories cannot be compared. Each robot on both sides gets its own 1e-6
    perturbation (initial joint angles in the runtime, a constant action offset in the env) and the means of the
    two ensembles are compared.
    """
    import torch
    from tensordict.nn import TensorDictModule

    from tocabi_torchrl.export import load_policy
    from tocabi_torchrl.export.onnx_export import DeterministicActor
    from tocabi_torchrl.evaluation.gait_test import _fixed_command, evaluate_policy

    torch.set_num_threads(1)  # the runtime's subprocess runs beside this one on the second core
    policy = load_policy(robot.asset_path("policies", f"tocabi_walk_{name}.pt"), num_envs=WALK_ROBOTS,
                         command=_fixed_command((0.5, 0.0)), sim_threads=1)
    base = policy.env.base_env
    policy.env.reset()
    rows = base.init_row.tolist()  # the env's start rows: a hash of (seed, env, episode)
    base.episode_count.zero_()  # so that the gait test's own reset starts these same episodes again
    proc = _sim2sim_subprocess(_contract(name), seconds=8.0, num_robots=WALK_ROBOTS, init_rows=rows,
                               perturbation=1e-6)
    mean = DeterministicActor(policy.agent.actor)
    offset = 1e-6 * torch.randn(WALK_ROBOTS, 13, generator=torch.Generator().manual_seed(1))
    actor = TensorDictModule(lambda obs: mean(obs) + offset, in_keys=["observation"], out_keys=["action"])
    env_metrics = evaluate_policy(actor, policy.config, tmp_path, num_envs=WALK_ROBOTS, device="cpu",
                                  env=policy.env, video_envs=0, progress=False)
    assert policy.env.base_env.init_row.tolist() == rows
    runtime = _result(proc, timeout=900)
    record_property("sim2sim", json.dumps({"runtime": runtime, "torchrl": env_metrics}))
    print(name, "runtime:", runtime, "torchrl:", env_metrics)
    assert runtime["imported"] == []
    assert runtime["survival"] == env_metrics["survival"] == 1.0
    assert runtime["forward_distance_m"] == pytest.approx(env_metrics["forward_distance_m"], rel=0.05)


@pytest.mark.parametrize("name", POLICIES)
def test_runtime_drives_the_reference_robot_model(name, record_property):
    """Cross-model transfer: the same runtime on the reference ``dyros_tocabi.xml`` (meshes removed). Records
    whether the policy walks there (docs/deploying.md reports it); asserts only that the run is sound."""
    model = REFERENCE_DIR / "dyros_tocabi.xml"
    if not model.is_file():
        pytest.skip(f"reference data not available ({model})")
    result = _result(_sim2sim_subprocess(_contract(name), seconds=8.0, num_robots=2, init_rows=[0, 1800],
                                         model=model, remove_meshes=True))
    walks = result["survival"] == 1.0 and result["forward_distance_m"] > 2.0
    record_property("reference_model", json.dumps({**result, "walks": walks}))
    print(f"{name} on the reference model: walks={walks}", result)
    assert result["imported"] == []
    assert 0.0 <= result["survival"] <= 1.0 and np.isfinite(result["forward_distance_m"])


# ------------------------------------------------------------------------------------------- bad contracts
@pytest.fixture
def contract_copy(tmp_path):
    """A writable copy of the shipped ppo contract and its ONNX file; returns (path, contract dict)."""
    for suffix in (".json", ".onnx"):
        shutil.copy(robot.asset_path("policies", f"tocabi_walk_ppo{suffix}"), tmp_path / f"p{suffix}")
    path = tmp_path / "p.json"
    contract = json.loads(path.read_text())
    contract["policy"]["onnx_file"] = "p.onnx"
    return path, contract


def _write(path, contract):
    """Write ``contract`` to ``path`` with its ``content_sha256`` recomputed, as if exported so: the checks behind
    the hash (which still guard a contract of version 1) see the edit. ``_write_edited`` keeps the exported hash."""
    if isinstance(contract, dict) and "content_sha256" in contract:
        contract = {**contract, "content_sha256": content_sha256(contract)}
    return _write_edited(path, contract)


def _write_edited(path, contract):
    path.write_text(json.dumps(contract))
    return path


def test_contract_wrong_version_fails_clearly(contract_copy):
    path, c = contract_copy
    c["contract_version"] = 99
    with pytest.raises(ContractError, match="contract_version 99 is not supported.*Re-export"):
        PolicyRuntime(_write(path, c))


def test_contract_missing_key_fails_clearly(contract_copy):
    path, c = contract_copy
    del c["observation"]["normalization"]
    with pytest.raises(ContractError, match=r"missing required key\(s\) \['observation.normalization'"):
        load_contract(_write(path, c))


def test_contract_joint_count_mismatch_fails_clearly(contract_copy):
    path, c = contract_copy
    c["robot"]["joint_names"] = c["robot"]["joint_names"][:-1]
    with pytest.raises(ContractError, match="leg_joint_names \\+ robot.upper_joint_names must equal"):
        load_contract(_write(path, c))
    c = json.loads(_contract("ppo").read_text())
    c["policy"]["onnx_file"] = "p.onnx"
    c["action"]["leg"]["kp"] = c["action"]["leg"]["kp"][:11]
    with pytest.raises(ContractError, match="action.leg.kp must be a list of 12 values, got 11"):
        load_contract(_write(path, c))


def test_contract_joint_order_other_than_the_trained_one_fails_clearly(contract_copy):
    # Legs swapped consistently in every joint list loaded without a word: the runtime reads joints by position, so
    # the policy saw the right leg's angles as the left's and its left-leg actions drove the right leg.
    path, c = contract_copy
    legs = c["robot"]["leg_joint_names"]
    c["robot"]["leg_joint_names"] = legs[6:] + legs[:6]
    c["robot"]["joint_names"] = c["robot"]["leg_joint_names"] + c["robot"]["upper_joint_names"]
    with pytest.raises(ContractError, match=r"entries\[3\] is 'leg_joint_pos\[L_HipYaw_Joint\]', element 0 of "
                                            r"joint_pos, but robot.joint_names\[0\] is 'R_HipYaw_Joint'.*Keep the "
                                            r"exported joint order"):
        load_contract(_write(path, c))


def test_robot_state_with_another_joint_count_fails_clearly():
    runtime = PolicyRuntime(_contract("ppo"))
    state = RobotState(base_quat=np.array([[1.0, 0, 0, 0]]), joint_pos=np.zeros((1, 32)),
                       joint_vel=np.zeros((1, 32)), foot_force=np.zeros((1, 2, 3)), foot_torque=np.zeros((1, 2, 3)))
    with pytest.raises(ContractError, match="joint_pos has shape \\(1, 32\\), expected \\(1, 33\\).*33 joints"):
        runtime.reset(state, (0.5, 0.0))


def test_non_finite_sensors_or_commands_and_bad_command_shapes_fail_clearly():
    # A failed sensor (NaN/inf) stops the controller with the field and the robot named, instead of being normalised
    # into an observation the policy walks on blind; a command must be (2,) or (N, 2) finite speeds.
    runtime = PolicyRuntime(_contract("ppo"))

    def state(n=2):
        return RobotState(base_quat=np.tile([1.0, 0, 0, 0], (n, 1)), joint_pos=np.zeros((n, 33)),
                          joint_vel=np.zeros((n, 33)), foot_force=np.zeros((n, 2, 3)), foot_torque=np.zeros((n, 2, 3)))

    runtime.reset(state(), (0.5, 0.0))
    bad = state()
    bad.joint_pos[1, 4] = np.nan
    with pytest.raises(ContractError, match=r"RobotState.joint_pos is not finite .* robot\(s\) \[1\]"):
        runtime.step(bad)
    bad = state()
    bad.foot_force[0, 1, 2] = np.inf
    with pytest.raises(ContractError, match=r"RobotState.foot_force is not finite .* robot\(s\) \[0\]"):
        runtime.reset(bad, (0.5, 0.0))
    with pytest.raises(ContractError, match=r"command has shape \(3,\), expected \(2,\) or \(2, 2\)"):
        runtime.reset(state(), (0.5, 0.0, 0.0))
    with pytest.raises(ContractError, match="command holds NaN or inf"):
        runtime.reset(state(), (float("nan"), 0.0))
    runtime.reset(state(), [[0.5, 0.0], [0.3, 0.1]])  # one row per robot
    assert runtime.step(state(), (0.2, 0.0)).leg.shape == (2, 12)


def test_the_sim_to_sim_driver_holds_a_diverged_robots_last_finite_state():
    # The runtime refuses NaN readings (above); in the sim-to-sim driver a robot whose physics diverged is one fallen
    # robot among many: its rows are held at its last finite state, it is marked dead, and the others go on.
    from tocabi_torchrl.runtime.mujoco_driver import _hold_finite

    def state(value, velocities=True):
        vel = {"base_lin_vel": np.full((3, 3), value), "base_ang_vel": np.full((3, 3), value)} if velocities else {}
        return RobotState(base_quat=np.full((3, 4), value), joint_pos=np.full((3, 33), value),
                          joint_vel=np.full((3, 33), value), foot_force=np.full((3, 2, 3), value),
                          foot_torque=np.full((3, 2, 3), value), **vel)

    held, new = state(1.0), state(2.0)
    new.joint_vel[1, 7] = np.nan
    new.base_lin_vel[2, 0] = np.inf  # the pelvis velocity counts too
    out, finite = _hold_finite(new, held)
    assert finite.tolist() == [True, False, False]
    for name in ("base_quat", "joint_pos", "joint_vel", "foot_force", "foot_torque", "base_lin_vel", "base_ang_vel"):
        rows = getattr(out, name)
        assert np.isfinite(rows).all() and (rows[0] == 2.0).all() and (rows[1:] == 1.0).all()
    same, finite = _hold_finite(held, state(0.0))
    assert same is held and finite.all()
    # A state without the velocities (a policy that does not read them) keeps them None, a diverged robot's too.
    new = state(2.0, velocities=False)
    new.foot_force[0, 0, 2] = np.nan
    out, finite = _hold_finite(new, state(1.0, velocities=False))
    assert finite.tolist() == [False, True, True] and out.base_lin_vel is None and out.base_ang_vel is None
    assert (out.foot_force[0] == 1.0).all() and (out.foot_force[1:] == 2.0).all()


def test_a_contract_resaved_with_a_byte_order_mark_or_as_utf16_is_named_so(tmp_path):
    # An editor or shell (Windows PowerShell's > writes UTF-16, its Out-File -Encoding utf8 a UTF-8 BOM) re-saved a
    # sound contract; it was called "damaged or edited (corrupt)", with Python's codec error as the only hint.
    text = robot.asset_path("policies", "tocabi_walk_torque.json").read_text(encoding="utf-8")
    path = tmp_path / "walk.json"
    for data, said in ((b"\xef\xbb\xbf" + text.encode(), "with a UTF-8 byte order mark"),
                       (text.encode("utf-16"), r"as UTF-16 \(little-endian\)"),
                       (text.encode("utf-16-be"), r"as UTF-16 \(it starts with a zero byte beside a character\)")):
        path.write_bytes(data)
        with pytest.raises(ContractError, match=rf"walk\.json: it is saved {said}, not as the UTF-8 without a byte "
                                                r"order mark .*save it as UTF-8 without BOM"):
            load_contract(path)
    path.write_bytes(bytes(64))  # zeros, as a write lost in a power cut leaves: no text, cut short
    with pytest.raises(ContractError, match=r"not valid JSON .*ends before its JSON object does \(truncated\)"):
        load_contract(path)
    path.write_text(text, encoding="utf-8")
    assert load_contract(path)["action"]["control_mode"] == "torque"


def test_contract_not_json_or_input_size_mismatch_or_foreign_files_fail_clearly(contract_copy, tmp_path):
    path, c = contract_copy
    path.write_text("{ not json }")
    with pytest.raises(ContractError, match=r"not valid JSON .*damaged or was edited \(corrupt\); copy the contract "
                                            r"again .*or re-export the policy"):
        load_contract(path)
    # A copy cut short used to say only where the parser stopped, which names no fix.
    text = json.dumps(c, indent=1)
    for cut, said in ((len(text) // 2, "ends before its JSON object does"), (0, "is empty")):
        path.write_text(text[:cut])
        with pytest.raises(ContractError, match=rf"p\.json: not valid JSON .*{said} \(truncated\); copy the "
                                                r"contract again .*or re-export the policy"):
            load_contract(path)
    bad = json.loads(json.dumps(c))
    bad["observation"]["history"]["obs_ages"] = [4, 2, 0]
    with pytest.raises(ContractError, match="policy.input_dim is 237 but the history holds"):
        load_contract(_write(path, bad))
    bad = json.loads(json.dumps(c))
    bad["policy"]["onnx_sha256"] = "0" * 64
    with pytest.raises(ContractError, match="does not match the sha256"):
        PolicyRuntime(_write(path, bad))
    bad = json.loads(json.dumps(c))
    bad["reference_motion"]["sha256"] = "0" * 64
    with pytest.raises(ContractError, match="trained on another motion"):
        PolicyRuntime(_write(path, bad))
    with pytest.raises(ContractError, match="not found"):
        load_contract(tmp_path / "absent.json")


def test_sim_to_sim_counts_a_robot_that_mujoco_reset_as_fallen(monkeypatch, tmp_path):
    # C MuJoCo resets a diverged robot to the default pose and only counts a warning (mjWARN_BADQVEL here): the
    # state is finite and standing again. The training env marks such a world unhealthy and ends its episode, so the
    # driver must stop counting the robot too instead of letting it jump back and walk on.
    import mujoco

    from tocabi_torchrl.runtime.mujoco_driver import run_sim2sim

    monkeypatch.chdir(tmp_path)  # MuJoCo logs the warning to ./MUJOCO_LOG.TXT
    step, seen, blown = mujoco.mj_step, [], []

    def diverging_step(m, d):
        if not any(d is s for s in seen):
            seen.append(d)
        if d is seen[-1] and len(seen) == 2 and d.time >= 0.1 and not blown:  # robot 1, once, 0.1 s in
            d.qvel[6] = 1e12
            blown.append(d.time)
        step(m, d)

    monkeypatch.setattr(mujoco, "mj_step", diverging_step)
    result = run_sim2sim(_contract("ppo"), seconds=0.2, num_robots=2)
    assert blown and seen[1].warning[mujoco.mjtWarning.mjWARN_BADQVEL].number == 1
    assert np.isfinite(seen[1].qpos).all()
    assert result.alive == [True, False] and result.survival == 0.5


def test_sim_to_sim_health_warnings_are_the_training_envs():
    # The driver lists the warnings again (importing tocabi_torchrl.sim would load torch); they must not drift apart.
    from tocabi_torchrl.runtime.mujoco_driver import HEALTH_WARNINGS
    from tocabi_torchrl.sim.mujoco_health import MUJOCO_HEALTH_WARNINGS

    assert sum(1 << int(w) for w in HEALTH_WARNINGS) == MUJOCO_HEALTH_WARNINGS


def test_sim_to_sim_names_what_a_foreign_model_lacks(tmp_path):
    from tocabi_torchrl.runtime.mujoco_driver import run_sim2sim

    model = tmp_path / "other.xml"
    model.write_text('<mujoco><worldbody><body><joint/><geom size="0.1"/></body></worldbody></mujoco>')
    with pytest.raises(ValueError, match=r"other.xml lacks 72 name\(s\) the policy contract needs \(joint "
                                         r"'L_HipYaw_Joint', .*: pass a TOCABI MJCF"):
        run_sim2sim(_contract("ppo"), model, seconds=0.02, num_robots=1)
    # One missing actuator is named as such (the check runs before the actuators are set up from the contract).
    text = robot.asset_path("tocabi", "tocabi.xml").read_text()
    assert text.count('name="L_Knee_Motor"') == 1
    model = tmp_path / "one.xml"  # the authored model is self-contained (no meshes or includes)
    model.write_text(text.replace('name="L_Knee_Motor"', 'name="L_Knee_Servo"'))
    with pytest.raises(ValueError, match=r"lacks 1 name\(s\) the policy contract needs \(actuator 'L_Knee_Motor'\)"):
        run_sim2sim(_contract("ppo"), model, seconds=0.02, num_robots=1)



@pytest.mark.parametrize("compiler", DEGREE_COMPILERS.values(), ids=DEGREE_COMPILERS.keys())
def test_sim_to_sim_refuses_a_model_read_in_degrees_naming_the_file(tmp_path, compiler):
    # The driver compiles the model itself, not through robot.load_model: such a file (every range 180/π too
    # narrow, ±3.14 to ±0.055 rad) ran without a word, robots walking backwards against their joint limits.
    from tocabi_torchrl.runtime.mujoco_driver import run_sim2sim

    model = shipped_model_read_as(tmp_path, compiler)
    message = (r"robot model .*in_degrees\.xml: it is compiled with <compiler angle=\"degree\"> .* but its joint "
               r"ranges are written in radians: L_HipPitch_Joint range=\"-3\.14 3\.14\" becomes \[-0\.055, 0\.055\] "
               r"rad, which leaves out the initial pose's -0\.240 rad \(the contract's robot\.initial_qpos\) .*Set "
               r"<compiler angle=\"radian\"> in .*in_degrees\.xml")
    for remove_meshes in (False, True):  # the reference model's path goes through strip_meshes
        with pytest.raises(ValueError, match=message):
            run_sim2sim(_contract("ppo"), model, seconds=0.02, num_robots=1, remove_meshes=remove_meshes)


def test_sim_to_sim_refuses_a_model_in_degrees_with_radian_ranges_mixed_in(tmp_path):
    # It gave up on the unit (a range beyond a full turn is in degrees) and said only that the knee's range left out
    # the start pose, to be checked "in radians, under <compiler angle=\"radian\">", which would break the others.
    from tocabi_torchrl.runtime.mujoco_driver import build_model

    message = (r"robot model .*mixed\.xml: .* mixes units in its joint ranges: Waist1_Joint range=\"-119\.977 "
               r"119\.977\" is in degrees, but L_HipPitch_Joint range=\"-3\.14 3\.14\" becomes .*the contract's "
               r"robot\.initial_qpos.*Write each such range in degrees too")
    with pytest.raises(ValueError, match=message):
        build_model(load_contract(_contract("ppo")), shipped_model_mixing_units(tmp_path))


def test_sim_to_sim_builds_a_model_in_degrees_throughout(tmp_path):
    from tocabi_torchrl.runtime.mujoco_driver import build_model

    model = shipped_model_in_degrees(tmp_path)
    contract = load_contract(_contract("ppo"))
    shipped = build_model(contract, robot.asset_path("tocabi", "tocabi.xml"))
    np.testing.assert_allclose(build_model(contract, model).jnt_range, shipped.jnt_range, atol=1e-7)


def test_sim_to_sim_refuses_a_model_range_that_leaves_out_the_start_pose(tmp_path):
    # A radians model with a knee limited to ±0.5 rad (the contract's start pose bends it 0.6 rad) ran without a word,
    # every robot held off its start pose by the limit, and reported the limit's gait as the policy's.
    from tocabi_torchrl.runtime.mujoco_driver import build_model, run_sim2sim

    model = shipped_model_with_range(tmp_path / "narrow.xml", "L_Knee_Joint", -0.5, 0.5)
    message = (r"robot model .*narrow\.xml: L_Knee_Joint's range \[-0\.500, 0\.500\] rad leaves out the initial pose's "
               r"0\.600 rad \(the contract's robot\.initial_qpos\): check L_Knee_Joint's range in the model file "
               r"\(radians, under <compiler angle=\"radian\">\); the robot could not start from that pose")
    with pytest.raises(ValueError, match=message):
        build_model(load_contract(_contract("ppo")), model)
    with pytest.raises(ValueError, match=message):
        run_sim2sim(_contract("ppo"), model, seconds=0.02, num_robots=1)


def test_sim_to_sim_refuses_a_motion_beyond_a_model_range_naming_both_files(tmp_path):
    # A range that holds the start pose but not the walk's knee bend: the joint limit would clip the motion's targets.
    from tocabi_torchrl.runtime.mujoco_driver import run_sim2sim

    model = shipped_model_with_range(tmp_path / "short.xml", "R_Knee_Joint", 0.0, 0.8)
    with pytest.raises(ValueError) as info:
        run_sim2sim(_contract("ppo"), model, seconds=0.02, num_robots=1)
    message = str(info.value)
    assert re.fullmatch(r"reference motion .*tocabi_walk\.npz: R_Knee_Joint is [\d.]+ rad at row \d+, outside the "
                        r"model's range \[0\.000, 0\.800\] in .*short\.xml, which holds the robot's initial pose "
                        r"\(0\.600 rad\): check the motion \(joint targets are radians, in the contract's "
                        r"robot\.joint_names order: a motion in degrees, or of another robot\?\), or, if it is right, "
                        r"R_Knee_Joint's range in the model file", message), message


def test_reset_refuses_init_rows_that_are_not_rows_of_the_motion():
    # Out-of-range rows used to wrap silently, fractional rows were truncated, and a wrong count, NaN or zero robots
    # surfaced as numpy errors.
    runtime = PolicyRuntime(_contract("ppo"))
    last = runtime.motion.cycle_rows - 1

    def state(n=2):
        return RobotState(base_quat=np.tile([1.0, 0, 0, 0], (n, 1)), joint_pos=np.zeros((n, 33)),
                          joint_vel=np.zeros((n, 33)), foot_force=np.zeros((n, 2, 3)), foot_torque=np.zeros((n, 2, 3)))

    allowed = rf"pass one integer or 2 \(one per robot\) in \[0, {last}\]"
    for rows, problem in (([0, 1800, 0], r"has shape \(3,\)"), ([last + 1, 0], rf"has rows \[{last + 1}\] outside"),
                          ([-5, 0], r"has rows \[-5\] outside"), ([0.7, 1800.0], "has dtype float64, not integers"),
                          ([np.nan, 0], "has dtype float64"), ([True, False], "has dtype bool")):
        with pytest.raises(ContractError, match=f"init_row {problem}.*{allowed}"):
            runtime.reset(state(), (0.5, 0.0), init_row=rows)
    with pytest.raises(ContractError, match=r"base_quat has shape \(0, 4\), expected \(N, 4\) with N >= 1"):
        runtime.reset(state(0), np.zeros((0, 2)))
    runtime.reset(state(), (0.5, 0.0), init_row=np.array([0, last], dtype=np.int32))  # numpy ints are rows
    assert runtime.init_row.tolist() == [0, last] and runtime.init_row.dtype == np.int64
    runtime.reset(state(), (0.5, 0.0), init_row=1800)  # one row for every robot
    # The sim-to-sim driver checks its start rows before they index the motion (a numpy broadcast error before).
    from tocabi_torchrl.runtime.mujoco_driver import run_sim2sim

    with pytest.raises(ContractError, match=r"init_row has shape \(3,\): pass one integer or 2"):
        run_sim2sim(_contract("ppo"), None, seconds=0.02, num_robots=2, init_rows=[0, 0, 0])
    assert runtime.init_row.tolist() == [1800, 1800]


def test_a_missing_onnxruntime_says_which_extra_installs_it(monkeypatch):
    pyproject = (Path(__file__).resolve().parents[1] / "pyproject.toml").read_text()
    assert re.search(r'^export = \[.*"onnxruntime', pyproject, re.MULTILINE), "the message names the wrong extra"
    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # makes `import onnxruntime` fail
    with pytest.raises(ImportError, match=r'needs onnxruntime, which is not installed: pip install -e "\.\[export\]"'):
        PolicyRuntime(_contract("ppo"))


# ------------------------------------------------------------------------------------------- audit fixes
def _robots(n=1, **fields) -> RobotState:
    """n robots standing still at zero joint angles; ``fields`` replace some of the signals."""
    state = {"base_quat": np.tile([1.0, 0, 0, 0], (n, 1)), "joint_pos": np.zeros((n, 33)),
             "joint_vel": np.zeros((n, 33)), "foot_force": np.zeros((n, 2, 3)), "foot_torque": np.zeros((n, 2, 3))}
    return RobotState(**{**state, **fields})


def _mutated(c: dict, change) -> dict:
    c = json.loads(json.dumps(c))
    change(c)
    return c


def _set(dotted: str, value):
    def change(c):
        *parents, last = dotted.split(".")
        node = c
        for part in parents:
            node = node[int(part)] if isinstance(node, list) else node[part]
        node[int(last) if isinstance(node, list) else last] = value

    return change


def test_contract_with_nan_or_infinity_is_refused_and_values_must_be_valid(contract_copy):
    # json.loads accepts the non-standard NaN/Infinity tokens and the checks used to look at lengths only: a NaN
    # mean, a zero scale or swapped action bounds ran silently.
    path, c = contract_copy
    _write(path, _mutated(c, _set("observation.normalization.mean.0", float("nan"))))
    with pytest.raises(ContractError, match="non-standard JSON value NaN.*re-export it from a sound checkpoint"):
        load_contract(path)
    from tocabi_torchrl.runtime import check_contract

    swap = _mutated(c, lambda d: d["action"].update(low=d["action"]["high"], high=d["action"]["low"]))
    for bad, message in (
        (_set("observation.normalization.scale.1", float("inf")), r"normalization.scale\[1\] is inf, not a finite"),
        (_set("observation.normalization.scale.0", 0.0), r"normalization.scale\[0\] is 0.0 but must be > 0"),
        (_set("observation.normalization.clip", -1.0), "normalization.clip is -1.0 but must be > 0"),
        (_set("action.leg.kp.2", float("nan")), r"action.leg.kp\[2\] is nan, not a finite \(float32\) number"),
        (_set("observation.normalization.mean.3", 1e39), r"mean\[3\] is 1e\+39, not a finite \(float32\)"),
        (_set("action.leg.torque_limits_nm.0", -1.0), r"torque_limits_nm\[0\] is -1.0 but must be > 0"),
        (_set("timing.control_dt_s", 0.0), "timing.control_dt_s is 0.0 but must be > 0"),
        (_set("timing.substeps", 4), "control_dt_s 0.004 is not physics_dt_s 0.0005 x substeps 4"),
        (_set("robot.initial_qpos.2", float("-inf")), r"initial_qpos \(base pose \+ joints\)\[2\] is -inf"),
        (lambda d: d.update(swap), r"action.low > action.high at indices \[0, 1, .*swapped"),
    ):
        with pytest.raises(ContractError, match=f"{message}.*re-export the policy"):
            check_contract(_mutated(c, bad))


def test_contract_leg_kind_and_center_must_match_the_control_mode(contract_copy):
    # A pd_reference contract labelled torque made a controller apply PD targets [rad] as torques [N·m].
    path, c = contract_copy
    with pytest.raises(ContractError, match="action.leg.kind is 'torque' but control_mode is 'pd_reference', whose "
                                            "leg commands are 'position': re-export"):
        load_contract(_write(path, _mutated(c, _set("action.leg.kind", "torque"))))
    with pytest.raises(ContractError, match="action.leg.center is 'nominal' but control_mode 'pd_reference' centres "
                                            "the targets on 'reference'"):
        load_contract(_write(path, _mutated(c, _set("action.leg.center", "nominal"))))
    torque = json.loads(_contract("torque").read_text())
    torque["policy"]["onnx_file"] = "p.onnx"
    with pytest.raises(ContractError, match="action.leg.kind is 'position' but control_mode is 'torque'"):
        load_contract(_write(path, _mutated(torque, _set("action.leg.kind", "position"))))


@pytest.mark.parametrize("key", ["policy.onnx_sha256", "reference_motion.sha256"])
def test_contract_hashes_cannot_be_left_out(key, contract_copy):
    # A missing or null hash used to switch the ONNX/motion check off without a word.
    path, c = contract_copy
    section, name = key.split(".")
    removed = _mutated(c, lambda d: d[section].pop(name))
    with pytest.raises(ContractError, match=rf"missing required key\(s\) \['{key}'\]"):
        PolicyRuntime(_write(path, removed))
    for value in (None, "ABC", "A" * 64):
        with pytest.raises(ContractError, match=rf"{key} is {re.escape(repr(value))}, not a sha256 \(64 lowercase hex"):
            PolicyRuntime(_write(path, _mutated(c, _set(key, value))))
    if key == "policy.onnx_sha256":  # only the explicit flag skips the ONNX check
        PolicyRuntime(_write(path, _mutated(c, _set(key, "0" * 64))), check_onnx_hash=False)


def test_sensor_values_beyond_float32_are_refused():
    # 1e39 is finite in float64 but inf once the observation casts it to float32.
    runtime = PolicyRuntime(_contract("torque"))
    runtime.reset(_robots(2), (0.5, 0.0))
    with pytest.raises(ContractError, match=r"RobotState.joint_vel is not finite in float32 .* robot\(s\) \[1\]"):
        runtime.step(_robots(2, joint_vel=np.array([[0.0] * 33, [1e39] * 33])))
    with pytest.raises(ContractError, match="command holds NaN or inf in float32"):
        runtime.step(_robots(2), (1e39, 0.0))


def test_a_quaternion_that_is_not_unit_length_is_refused():
    # quat_to_rpy is scale-invariant: a zero quaternion (IMU dropout) read as upright.
    runtime = PolicyRuntime(_contract("ppo"))
    for quat in (np.zeros(4), np.full(4, 1e-20), np.array([2.0, 0, 0, 0])):
        with pytest.raises(ContractError, match=r"base_quat is not a unit quaternion .* robot\(s\) \[1\]: check"):
            runtime.reset(_robots(2, base_quat=np.stack([[1.0, 0, 0, 0], quat])), (0.5, 0.0))
    runtime.reset(_robots(1, base_quat=np.array([[1.05, 0, 0, 0]])), (0.5, 0.0))  # drift within 0.1 is fine


@pytest.mark.parametrize("field,value,dtype", [("joint_pos", "0.1", "<U3"), ("joint_pos", None, "object"),
                                               ("joint_vel", 1j, "complex128"), ("foot_force", True, "bool")])
def test_robot_state_of_non_numbers_is_refused(field, value, dtype):
    runtime = PolicyRuntime(_contract("ppo"))
    shape = np.shape(getattr(_robots(1), field))
    with pytest.raises(ContractError, match=rf"RobotState.{field} has dtype {dtype}: pass real numbers"):
        runtime.reset(_robots(1, **{field: np.full(shape, value)}), (0.5, 0.0))
    with pytest.raises(ContractError, match="command has dtype <U2, not numbers"):
        runtime.reset(_robots(1), "ab")


def test_a_refused_reset_leaves_the_running_episode_as_it_was():
    runtime = PolicyRuntime(_contract("ppo"))
    runtime.reset(_robots(2), (0.5, 0.0), init_row=1800)
    for _ in range(5):
        runtime.step(_robots(2))
    clock, rows, command = runtime.time.copy(), runtime.init_row.copy(), runtime.command.copy()
    with pytest.raises(ContractError, match="command holds NaN"):
        runtime.reset(_robots(2), (float("nan"), 0.0), init_row=0)
    with pytest.raises(ContractError, match=r"command has shape \(3,\)"):
        runtime.reset(_robots(3), (0.5, 0.0, 0.0))
    assert runtime.num_robots == 2
    assert (runtime.time == clock).all() and (runtime.init_row == rows).all() and (runtime.command == command).all()
    runtime.step(_robots(2))


@pytest.mark.parametrize("change,message", [
    (_set("observation.entries.0.element", 999), r"entries\[0\].element is 999, not an element index in \[0, 3\)"),
    (_set("observation.entries.0.element", True), r"entries\[0\].element is True"),
    (lambda d: (d["observation"]["signals"].update(base_pos={"shape": [3]}),
                d["observation"]["entries"][0].update(signal="base_pos")),
     "reads signal 'base_pos', which this runtime cannot build"),
    (_set("observation.signals.joint_pos.shape", [12]), r"signals.joint_pos.shape is \[12\], but the runtime builds"),
    (_set("action.phase_rate.index", 40), "phase_rate.index is 40, but the 12 leg actions come first"),
    (lambda d: d["action"]["leg"].update(joint_range=[r[0] for r in d["action"]["leg"]["joint_range"]]),
     r"joint_range\[0\] \(\[lo, hi\] rad\) must be a list of 2 values"),
    (_set("action.leg.joint_range.3", [0.5, -0.5]), r"joint_range\[3\] is \[0.5, -0.5\]: it needs lo < hi"),
    (_set("observation.history.obs_ages", [-1, -1, -1, -1, -1]), r"obs_ages is .* integer ages in \[0, 1024\]"),
    (_set("observation.history.action_ages", [7.0, 5, 3, 1]), r"action_ages is .* integer ages in \[0, 1024\]"),
    (_set("contract_version", True), "contract_version True is not supported"),
    (_set("action.dim", 13.0), "action.dim is 13.0"),
    # Loaded without a word: unknown keys (a misspelt optional one is ignored), a rate that contradicts the period,
    # and a text dimension reported as if it were the right number.
    (_set("foo", 1), r"unknown key\(s\) \['foo'\]; the runtime would ignore them"),
    (_set("termination.self_colision", True), r"unknown key\(s\) \['termination.self_colision'\]"),
    (_set("action.leg.kp_scale", 1.0), r"unknown key\(s\) \['action.leg.kp_scale'\]"),
    (_set("timing.control_hz", 100), r"timing.control_hz 100.0 is not 1 / control_dt_s 0.004 \(250\)"),
    (_set("policy.input_dim", "237"), r"policy.input_dim is '237' but .* \(an integer\)"),
    (_set("policy.output_dim", "13"), r"policy.output_dim is '13' but must be action.dim, the integer 13"),
    # Loaded, then a torque ten times the limits, a clock run backwards, a raw TypeError or MemoryError, a group of
    # randomisation or a count a controller would read ignored.
    (_set("action.low.0", -100.0), r"action.low/high at indices \[0\] reach outside .*legs in \[-1, 1\]"),
    (_set("action.low.12", -50.0), r"indices \[12\] reach outside .* the phase rate in \[0, 1\]"),
    (_set("action.control_mode", ["pd"]), r"unknown action.control_mode \['pd'\]"),
    (_set("observation.entries.0.signal", ["base_rpy"]), r"entries\[0\] must name a signal"),
    (_set("robot.base_body", 5), "robot.base_body: 5 is not a name"),
    (_set("robot.foot_force_sensors.1", "LF_Force_sensor"),
     r"foot_force_sensors \(left, right\): a name appears twice"),
    (_set("observation.history.obs_ages", [10 ** 12, 6, 4, 2, 0]), r"obs_ages is .* ages in \[0, 1024\]"),
    (_set("observation.phase_harmonics", 10 ** 10),
     "phase_harmonics is 10000000000 but this runtime builds at most 64"),
    (_set("trained_under.terrain", {"roughness_m": [0, 0.05]}), r"states \['terrain'\], which this reader cannot"),
    (lambda d: d["trained_under"].update(actuators={**d["trained_under"]["actuators"],
                                                    "delay": {"substeps": [4, 10 ** 9], "ms": [2.0, 5e8]}}),
     r"delay.substeps is \[4, 1000000000\] but each end must be an int in \[0, 400\]"),
    (_set("observation.history.num_obs", 7), "history.num_obs is 7 but obs_ages holds 5"),
    (_set("observation.normalization.kind", "running"),
     r"normalization.kind is 'running' but must be one of \['fixed', 'running \(frozen at export\)', 'none'\]"),
    (_set("observation.normalization.eps", "x"), "normalization.eps is 'x', not a finite"),
    (_set("observation.entries.3.index", 5), r"entries\[3\].index is 5, not its position 3"),
    (_set("observation.entries.0.scale", 2.0), r"entries\[0\] has unknown key\(s\) \['scale'\]"),
    (_set("observation.signals.base_rpy.bias", 0.1), r"signals.base_rpy has unknown key\(s\) \['bias'\]"),
    (_set("action.leg.torque_limits_nm.0", 1e-46), r"torque_limits_nm\[0\] is 1e-46 but must be > 0 \(in float32"),
    # Optional fields a controller may read, loaded unchecked.
    (_set("robot.actuator_names", ["L_HipYaw_Motor"]), r"actuator_names \(one motor per joint\) must be a list of 33"),
    (_set("robot.actuator_names.1", "L_HipYaw_Motor"), r"actuator_names \(one motor per joint\): a name appears twice"),
    (_set("policy.opset", "18"), "policy.opset is '18' but must be an integer >= 1"),
    (_set("policy.opset", 0), "policy.opset is 0 but must be an integer >= 1"),
])
def test_structurally_wrong_contracts_are_refused_on_load(change, message, contract_copy):
    # Each of these passed load_contract and then failed with an IndexError/KeyError in reset, or ran wrongly.
    path, c = contract_copy
    with pytest.raises(ContractError, match=message):
        load_contract(_write(path, _mutated(c, change)))


def _nudged(dotted: str, factor: float = 1.0, offset: float = 0.0):
    """An edit of a contract number ``dotted`` to number * factor + offset: a value every other check accepts."""
    def change(c):
        *parents, last = dotted.split(".")
        node = c
        for part in parents:
            node = node[int(part)] if isinstance(node, list) else node[part]
        key = int(last) if isinstance(node, list) else last
        node[key] = node[key] * factor + offset

    return change


def _doubled_timing(c):
    c["timing"].update(physics_dt_s=0.001, control_dt_s=0.008, control_hz=125.0)


@pytest.mark.parametrize("name,change", [
    ("ppo", _nudged("observation.normalization.mean.0", offset=0.01)),
    ("ppo", _nudged("observation.normalization.mean.20", factor=1.5)),
    ("ppo", _nudged("observation.normalization.scale.5", factor=1.5)),
    ("ppo", _set("observation.normalization.clip", 5.0)),
    ("ppo", _set("observation.entries.0.element", 1)),
    ("ppo", _set("observation.history.obs_ages", [6, 8, 4, 2, 0])),
    ("ppo", _nudged("action.leg.action_scale", factor=1.5)),
    ("ppo", _nudged("action.leg.kp.3", factor=1.2)),
    ("ppo", _nudged("action.leg.kv.3", factor=1.2)),
    ("ppo", _nudged("action.leg.joint_range.3.0", offset=-0.01)),
    ("ppo", _set("action.high.0", 0.5)),
    ("ppo", _nudged("action.phase_rate.gain", factor=0.5)),
    ("ppo", _nudged("upper_body.kp.0", factor=1.1)),
    ("ppo", _nudged("robot.initial_qpos.2", offset=0.01)),
    ("ppo", _doubled_timing),
    ("ppo", _set("reference_motion.init_rows", [0, 1700])),
    ("ppo", lambda c: c["policy"].update(onnx_sha256=load_contract(_contract("torque"))["policy"]["onnx_sha256"])),
    ("torque", _nudged("action.leg.torque_limits_nm.0", factor=0.9)),
], ids=["mean", "mean_factor", "scale", "clip", "entry_element", "obs_ages", "action_scale", "kp", "kv", "joint_range",
        "action_high", "phase_gain", "upper_kp", "initial_qpos", "timing", "init_rows", "onnx_sha256", "torque_limit"])
def test_a_contract_value_edited_after_export_is_refused(name, change, tmp_path):
    # Each of these passes every other check and changes what the robot does (or, for onnx_sha256, pairs the
    # statistics with another network): an edited or corrupted contract used to load without a word.
    for suffix in (".json", ".onnx"):
        shutil.copy(_contract(name).with_suffix(suffix), tmp_path / f"p{suffix}")
    path = tmp_path / "p.json"
    c = json.loads(path.read_text())
    with pytest.raises(ContractError, match=r"p\.json: contract values changed after export: content_sha256 does not "
                                            r"match .*re-export the policy"):
        load_contract(_write_edited(path, _mutated(c, change)))
    # The hash is what refuses it: with a fresh one the edit passes load_contract.
    load_contract(_write(path, _mutated(c, change)))


@pytest.mark.parametrize("name", ["ppo", "torque", "robust"])
def test_an_untouched_contract_loads_whatever_its_layout_and_unhashed_fields(name, tmp_path):
    # Indentation, key order, the recorded ONNX name and the sections the driver alone reads are not what the policy
    # computes: they may differ from the export's file.
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the shipped contracts are of the current version: no warning
        shipped = load_contract(_contract(name))
    assert shipped["contract_version"] == 2 and shipped["content_sha256"] == content_sha256(shipped)
    shutil.copy(_contract(name).with_suffix(".onnx"), tmp_path / "p.onnx")
    c = json.loads(_contract(name).read_text())
    c["policy"]["onnx_file"] = "p.onnx"
    c["termination"]["min_neck_height"] = 0.9
    c.pop("trained_under")
    path = tmp_path / "p.json"
    path.write_text(json.dumps(dict(reversed(list(c.items()))), separators=(",", ":")))
    runtime = PolicyRuntime(path)
    assert runtime.contract["content_sha256"] == shipped["content_sha256"]


def test_a_version_1_contract_loads_with_a_warning_and_version_2_needs_its_hash(contract_copy):
    # Version 1 (exported before content_sha256) keeps loading, saying its values are unchecked; version 2 without
    # its hash, or with one that is no sha256, is refused.
    path, c = contract_copy
    older = {k: v for k, v in c.items() if k != "content_sha256"}
    older["contract_version"] = 1
    with pytest.warns(UserWarning, match=r"p\.json: contract_version 1 has no content_sha256, so an edit of its "
                                         r"values .* cannot be detected; re-export"):
        runtime = PolicyRuntime(_write_edited(path, older))
    current = PolicyRuntime(_contract("ppo"))
    state = _robots(2, joint_vel=np.full((2, 33), 0.1))
    assert np.array_equal(runtime.reset(state, (0.5, 0.0)).leg, current.reset(state, (0.5, 0.0)).leg)
    with pytest.raises(ContractError, match=r"missing required key\(s\) \['content_sha256'\]"):
        load_contract(_write_edited(path, {k: v for k, v in c.items() if k != "content_sha256"}))
    with pytest.raises(ContractError, match="contract_version 1 has no content_sha256 .*the version was edited"):
        load_contract(_write_edited(path, {**c, "contract_version": 1}))
    with pytest.raises(ContractError, match="content_sha256 is 'abc', not a sha256"):
        load_contract(_write_edited(path, {**c, "content_sha256": "abc"}))


def test_a_missing_observation_signal_is_a_contract_error():
    from tocabi_torchrl.runtime.observation import ObservationBuilder

    builder = ObservationBuilder(load_contract(_contract("ppo"))["observation"])
    with pytest.raises(ContractError, match="observation signal 'base_rpy' missing.*pass every one of them"):
        builder.raw({"joint_pos": np.zeros((1, 33))})


@pytest.mark.parametrize("name", ["../p.onnx", "/tmp/p.onnx", "sub/p.onnx", "sub\\p.onnx", ""])
def test_contract_onnx_file_must_be_a_file_beside_the_contract(name, contract_copy):
    path, c = contract_copy
    with pytest.raises(ContractError, match=rf"policy.onnx_file is {re.escape(repr(name))}; it must be a plain file"):
        load_contract(_write(path, _mutated(c, _set("policy.onnx_file", name))))


def _onnx_linear(path, inputs: int, outputs: int, output_name: str, double: bool = False,
                 extra_input: bool = False) -> None:
    """A (batch, inputs) -> (batch, outputs) zero matrix as an ONNX file (no torch needed); ``double``: float64 in
    and out; ``extra_input``: a second, unused graph input."""
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper, numpy_helper

    kind, dtype = (TensorProto.DOUBLE, np.float64) if double else (TensorProto.FLOAT, np.float32)
    weight = numpy_helper.from_array(np.zeros((inputs, outputs), dtype), "w")
    ins = [helper.make_tensor_value_info("observation", kind, ["batch", inputs])]
    if extra_input:
        ins.append(helper.make_tensor_value_info("hidden", kind, ["batch", 4]))
    graph = helper.make_graph(
        [helper.make_node("MatMul", ["observation", "w"], [output_name])], "g", ins,
        [helper.make_tensor_value_info(output_name, kind, ["batch", outputs])], [weight])
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)]), str(path))


@pytest.mark.parametrize("double,extra,shown", [(True, False, r"'observation' tensor\(double\)"),
                                                (False, True, r"'observation' tensor\(float\) .*, 'hidden'")])
def test_an_onnx_input_of_another_type_or_count_is_refused(double, extra, shown, contract_copy):
    # Both loaded; the first reset then failed inside onnxruntime (a raw InvalidArgument or "Required inputs").
    path, c = contract_copy
    _onnx_linear(path.with_name("p.onnx"), 237, 13, "action", double=double, extra_input=extra)
    with pytest.raises(ContractError, match=rf"input {shown}.* does not match the contract's one 'observation' of "
                                            r"\(batch, 237\) float32 values"):
        PolicyRuntime(_write(path, c), check_onnx_hash=False)


@pytest.mark.parametrize("outputs,output_name,shown", [(12, "action", r"'action' tensor\(float\) \['batch', 12\]"),
                                                       (13, "value", r"'value' tensor\(float\) \['batch', 13\]")])
def test_an_onnx_output_that_is_not_the_contracts_is_refused(outputs, output_name, shown, contract_copy):
    # Only the input used to be checked: a 12-wide output ran (the phase rate read past the end), another name too.
    path, c = contract_copy
    _onnx_linear(path.with_name("p.onnx"), 237, outputs, output_name)
    with pytest.raises(ContractError, match=rf"output {shown} does not match the contract's one 'action' of "
                                            r"\(batch, 13\)"):
        PolicyRuntime(_write(path, c), check_onnx_hash=False)


def test_a_text_motion_has_the_row_spacing_training_reads(tmp_path):
    # The runtime took the first time step of a .txt motion as its row spacing: with times printed to 7 decimals at
    # 3000 rows/s (0.0003333 s) its cycle lasted 1.19955 s where training's lasted 1.19967 s, and a policy trained on
    # the file was refused as if its contract had been edited.
    from tocabi_torchrl.motion.io import load_npz, load_txt
    from tocabi_torchrl.runtime.motion import RuntimeMotion

    data = load_npz(robot.asset_path("motions", "tocabi_walk.npz"))
    rows = data.joint_pos.shape[0]
    path = tmp_path / "walk_3000hz.txt"
    np.savetxt(path, np.column_stack([np.arange(rows) / 3000.0, data.joint_pos, data.foot_force]), fmt="%.7f")
    trained = load_txt(path)
    loaded = RuntimeMotion.from_file(path, list(robot.JOINT_NAMES))
    assert trained.sample_rate == 3000.0
    assert loaded.row_dt == 1.0 / trained.sample_rate
    assert loaded.period == pytest.approx((rows - 1) / trained.sample_rate, rel=1e-12)
    assert loaded.init_rows.tolist() == trained.init_rows.tolist()


def test_a_motion_of_ones_own_is_found_beside_the_contract(contract_copy):
    # Only the shipped motions were looked in: a policy trained on its own motion could not run, though the
    # contract's check says the motion is a file beside the contract.
    path, c = contract_copy
    own = path.with_name("my_walk.npz")
    shutil.copy(robot.asset_path("motions", "tocabi_walk.npz"), own)
    c["reference_motion"]["name"] = own.name
    runtime = PolicyRuntime(_write(path, c))
    assert runtime.motion is not None
    own.unlink()
    with pytest.raises(ContractError, match="reference motion my_walk.npz is neither beside the policy"):
        PolicyRuntime(_write(path, c))


def test_an_old_copy_of_a_shipped_motion_beside_the_contract_does_not_hide_the_shipped_one(contract_copy):
    # A file of the shipped motion's name beside the contract with another hash was taken first and then failed the
    # hash check, where the shipped file matched.
    path, c = contract_copy
    stale = path.with_name(c["reference_motion"]["name"])
    np.savez(stale, stale=np.zeros(3))
    assert stale.is_file()
    runtime = PolicyRuntime(_write(path, c))
    assert runtime.motion is not None
    c["reference_motion"]["sha256"] = "0" * 64  # neither matches: the error names the file beside the contract
    with pytest.raises(ContractError, match=f"reference motion {stale}"):
        PolicyRuntime(_write(path, c), check_onnx_hash=False)


def test_a_file_that_is_not_onnx_is_a_contract_error(contract_copy):
    # A file whose hash the contract matches but that onnxruntime cannot load (an empty or foreign file) ended in
    # onnxruntime's own InvalidProtobuf traceback.
    pytest.importorskip("onnxruntime")
    from tocabi_torchrl.runtime.motion import file_sha256

    path, c = contract_copy
    onnx = path.with_name("p.onnx")
    for data in (b"", b"not a model"):
        onnx.write_bytes(data)
        c["policy"]["onnx_sha256"] = file_sha256(onnx)
        # The contract names this file (its sha256 matches): an onnxruntime too old for the opset fails alike.
        with pytest.raises(ContractError, match=r"onnxruntime [0-9.]+ cannot load .*p.onnx .*too old for the graph's "
                                                r"opset 18 \(pip install -U onnxruntime\).*export it again"):
            PolicyRuntime(_write(path, c))
        with pytest.raises(ContractError, match=r"p.onnx is not an ONNX model onnxruntime can load .*export it again"):
            PolicyRuntime(_write(path, c), check_onnx_hash=False)


class _FixedOutputSession:
    """Stands in for the onnxruntime session: returns ``raw`` and records the output names asked for."""

    def __init__(self, raw):
        self.raw, self.asked = np.asarray(raw, np.float32), []

    def run(self, names, feeds):
        self.asked.append(names)
        return [self.raw]


def test_a_policy_output_with_no_finite_entry_stops_that_robot():
    # Single NaN entries count as 0 (the contract's rule); a whole NaN row used to become a zero action, i.e. zero
    # torque, silently.
    runtime = PolicyRuntime(_contract("torque"))
    raw = np.full((3, 13), 0.5, np.float32)
    raw[0, 2] = np.nan
    runtime.session = _FixedOutputSession(raw)
    cmd = runtime.reset(_robots(3), (0.5, 0.0))
    assert cmd.action[0, 2] == 0.0 and cmd.action[0, 3] == 0.5 and runtime.session.asked == [["action"]]
    raw[2] = np.nan
    raw[1] = [np.inf] * 6 + [np.nan] * 7
    with pytest.raises(ContractError, match=r"output is NaN or inf in every entry for robot\(s\) \[1, 2\].*re-export"):
        runtime.step(_robots(3))
    # The clock had moved on to a period with no command: a further step is refused, not run on the stale action.
    with pytest.raises(RuntimeError, match=r"step without a running episode.*reset\(state, command\)"):
        runtime.step(_robots(3))
    raw[1:] = 0.25
    assert runtime.reset(_robots(3), (0.5, 0.0)).action[1, 0] == 0.25  # a reset starts another episode
    runtime.step(_robots(3))


def test_policy_input_and_set_command_before_reset_say_to_reset_first():
    runtime = PolicyRuntime(_contract("ppo"))
    with pytest.raises(RuntimeError, match=r"policy_input without a running episode.*reset\(state, command\)"):
        runtime.policy_input()
    with pytest.raises(RuntimeError, match=r"set_command without a running episode.*reset\(state, command\)"):
        runtime.set_command((0.5, 0.0))


# ------------------------------------------------------------------------------------------- the env's value rules
@pytest.mark.parametrize("field, value, shown", [
    ("action.leg.action_scale", -0.5, r"action.leg.action_scale is -0.5 but must be a finite number >= 0"),
    ("action.leg.kp.4", -1.0, r"action.leg.kp\[4\] is -1.0 but must be a finite number >= 0"),
    ("action.leg.kv.0", -15.0, r"action.leg.kv\[0\] is -15.0 but must be a finite number >= 0"),
    ("action.phase_rate.gain", 100.0, r"action.phase_rate.gain is 100.0 but must be a finite number in \[0, 100\)"),
    ("action.phase_rate.gain", -1.0, r"action.phase_rate.gain is -1.0 but must be a finite number in \[0, 100\)"),
    ("timing.substeps", 0, r"timing.substeps is 0 but must be an int >= 1"),
    ("termination.min_pelvis_height", -0.6, r"termination.min_pelvis_height is -0.6 but must be a finite number >= 0"),
    ("termination.max_neck_angle", "1",
     r"termination.max_neck_angle is '1' but must be a finite number in \[0, 3\.14159\d*\]"),
    ("upper_body.kp.3", -400.0, r"upper_body.kp\[3\] is -400.0 but must be a finite number >= 0"),
    # A list where the env takes one number passed entry by entry: [8] substeps ended in a TypeError, [] as a height
    # in run_sim2sim's ValueError, [0.6] loaded as if it were 0.6.
    ("timing.substeps", [8], r"timing.substeps is \[8\] but must be one number, not a list \(an int >= 1,"),
    ("termination.min_pelvis_height", [], r"min_pelvis_height is \[\] but must be one number, not a list"),
    ("termination.min_pelvis_height", [0.6], r"min_pelvis_height is \[0.6\] but must be one number, not a list"),
    ("termination.max_neck_angle", [], r"max_neck_angle is \[\] but must be one number, not a list"),
])
def test_contract_values_obey_the_env_configs_rules(field, value, shown, contract_copy):
    # A contract with action.leg.action_scale = -0.5 loaded and every robot fell, while TocabiWalk(pd_action_scale=-1)
    # was refused: the contract's values now go through the env config's own rules (value_rules.ENV_RULES).
    path, c = contract_copy
    with pytest.raises(ContractError, match=f"{shown} .*re-export the policy"):
        load_contract(_write(path, _mutated(c, _set(field, value))))


def test_contract_termination_switches_must_be_true_or_false(contract_copy):
    path, c = contract_copy
    with pytest.raises(ContractError, match="termination.self_collision is 'false' but must be true or false"):
        load_contract(_write(path, _mutated(c, _set("termination.self_collision", "false"))))


def test_every_contract_field_with_an_env_rule_is_checked_with_that_rule():
    # One source of truth: each field the contract carries from the env config names a rule of ENV_RULES, and a
    # value that rule refuses is refused by the env config as well (so the two cannot drift apart).
    from tocabi_torchrl.envs import TocabiWalkConfig
    from tocabi_torchrl.runtime.contract import _ENV_LIST_FIELDS, ENV_FIELDS
    from tocabi_torchrl.tree import get_path, replace_paths
    from tocabi_torchrl.value_rules import ENV_RULES

    for field, env_path in ENV_FIELDS.items():
        assert env_path in ENV_RULES, field
        default = get_path(TocabiWalkConfig(), env_path)
        assert isinstance(default, tuple) == (field in _ENV_LIST_FIELDS), field  # a list exactly where the env's is
        bad = -1 if env_path != "control.pd_nominal" else float("nan")
        env_value = tuple([bad] * len(default)) if isinstance(default, tuple) else bad
        with pytest.raises(ValueError, match=re.escape(f"env.{env_path}")):
            replace_paths(TocabiWalkConfig(), {env_path: env_value}).validate()


@pytest.mark.parametrize("text,message", [
    ('{"a": 1e999}', "non-standard JSON value 1e999"),
    ('{"a": 1, "a": 2}', "key 'a' appears twice in one object"),
    ("[" * 100000 + "]" * 100000, "nested too deep to be a contract"),
])
def test_contract_json_that_python_reads_loosely_is_refused(text, message, tmp_path):
    # 1e999 read as inf, a repeated key as its last value (some C++ readers take the first), deep nesting as a
    # RecursionError traceback.
    path = tmp_path / "p.json"
    path.write_text(text)
    with pytest.raises(ContractError, match=message):
        load_contract(path)


@pytest.mark.parametrize("key,value", [("period_s", 5.0), ("rows", 7), ("init_rows", [0, 99999]),
                                       ("row_dt_s", 0.001)])
def test_contract_motion_values_must_be_the_motion_files(key, value, contract_copy):
    # The runtime reads the motion file (checked by hash) and ignored what the contract said of it, which a robot
    # controller running its clock from the contract would follow.
    path, c = contract_copy
    with pytest.raises(ContractError, match=rf"reference_motion.{key} is .* in the contract, but the motion .* has"):
        PolicyRuntime(_write(path, _mutated(c, _set(f"reference_motion.{key}", value))))


def test_editing_a_returned_command_does_not_change_the_runtimes_next_input():
    # Command.action was the runtime's own pending action: a caller zeroing it in place changed the phase clock and
    # the action history of the next step.
    edited, kept = PolicyRuntime(_contract("torque")), PolicyRuntime(_contract("torque"))
    edited.reset(_robots(2), (0.5, 0.0)).action[:] = 1.0
    kept.reset(_robots(2), (0.5, 0.0))
    edited.step(_robots(2)).action[:] = 0.0
    kept.step(_robots(2))
    assert (edited.time == kept.time).all()
    assert np.array_equal(edited.step(_robots(2)).action, kept.step(_robots(2)).action)
    assert np.array_equal(edited.policy_input(), kept.policy_input())


def test_a_reset_or_step_whose_sensors_fail_leaves_the_episode_as_it_was():
    # The clock and robot count were committed before the observation was built: a reset of 3 robots with sensor
    # biases drawn for 2 failed (with numpy's broadcast error) but left a 3-robot runtime, and a sensors fault in a
    # step still advanced the clock.
    from tocabi_torchrl.runtime import randomization as rnd

    sensors = rnd.SensorModel(rnd.SensorSettings(joint_pos_bias=0.03), 33, np.random.default_rng(0))
    sensors.reset(np.random.default_rng(1), 2)
    runtime = PolicyRuntime(_contract("ppo"), sensors=sensors)
    runtime.reset(_robots(2), (0.5, 0.0))
    runtime.step(_robots(2))
    clock, command, given = runtime.time.copy(), runtime.command.copy(), runtime.policy_input()
    with pytest.raises(ValueError, match=r"'joint_pos' has shape \(3, 33\), expected \(2, 33\).*call reset\(rng, n\)"):
        runtime.reset(_robots(3), (0.5, 0.0))
    assert runtime.num_robots == 2

    def fault(signals):
        raise OSError("IMU timeout")

    for broken, error, message in (
        (fault, OSError, "IMU timeout"),
        (lambda s: {**s, "joint_pos": np.zeros((2, 12))}, ContractError,
         r"returned \(2, 12\) for signal 'joint_pos', expected its input's shape \(2, 33\)"),
        (lambda s: None, ContractError, "returned NoneType, not a dict"),
    ):
        runtime.sensors = broken
        with pytest.raises(error, match=message):
            runtime.step(_robots(2), (0.2, 0.0))
        assert (runtime.time == clock).all() and (runtime.command == command).all()
        assert np.array_equal(runtime.policy_input(), given)
    runtime.sensors = sensors
    runtime.step(_robots(2))


def test_a_sensors_callable_returning_nan_is_refused_by_name_and_leaves_the_episode():
    # A NaN from the sensors callable (a bias or noise model's bug) reached the policy, whose all-NaN output was
    # then reported as a broken network to re-export, and ended the episode.
    runtime = PolicyRuntime(_contract("ppo"))
    runtime.reset(_robots(2), (0.5, 0.0))
    clock, given = runtime.time.copy(), runtime.policy_input()

    def nan_for_robot_1(signals):
        vel = signals["joint_vel"].astype(np.float64)
        vel[1, 0] = np.nan
        return {**signals, "joint_vel": vel}

    as_text = lambda s: {**s, "command": s["command"].astype(str)}  # noqa: E731
    for broken, message in (
        (nan_for_robot_1, r"returned NaN or inf \(in float32\) for signal 'joint_vel' of robot\(s\) \[1\].*fix the "
                          "sensors callable"),
        (as_text, r"returned dtype <U\d+ for signal 'command'"),
    ):
        runtime.sensors = broken
        with pytest.raises(ContractError, match=message):
            runtime.step(_robots(2))
        assert (runtime.time == clock).all() and np.array_equal(runtime.policy_input(), given)
    runtime.sensors = None
    runtime.step(_robots(2))


def test_sim_to_sim_arguments_are_checked_up_front_and_a_command_may_be_per_robot():
    # Zero robots, a negative count or perturbation and a per-robot command ended in numpy errors that named no
    # argument ('need at least one array to stack', 'scale < 0', a TypeError); 0.003 s ran one 4 ms step while the
    # message for shorter runs asked for at least 0.004.
    from tocabi_torchrl.runtime.mujoco_driver import run_sim2sim

    contract = _contract("ppo")
    for kw, message in (({"num_robots": 0}, "num_robots must be an int >= 1 .* got 0; pass e.g. num_robots=4"),
                        ({"num_robots": -1}, "num_robots must be an int >= 1 .* got -1"),
                        ({"num_robots": 2.0}, r"num_robots must be an int >= 1 .* got 2.0"),
                        ({"perturbation": -1}, r"perturbation must be a finite number >= 0 .* got -1; pass 0 for none"),
                        ({"perturbation": float("nan")}, "perturbation must be a finite number >= 0"),
                        ({"seed": -1}, r"seed must be an int in \[0, 2\*\*63 - 1\]"),
                        ({"seconds": 0.003}, r"seconds=0.003 is shorter than one control period \(4 ms\).*0.004"),
                        ({"command": [[0.5, 0.0]] * 3}, r"command has shape \(3, 2\), expected \(2,\) or \(2, 2\)")):
        with pytest.raises(ValueError, match=message):
            run_sim2sim(contract, **{"seconds": 0.008, "num_robots": 2, **kw})
    # The result's length is the simulated one: whole control periods.
    assert run_sim2sim(contract, seconds=0.005, num_robots=1).seconds == 0.004
    same = run_sim2sim(contract, seconds=0.02, num_robots=2, command=[[0.5, 0.0], [0.5, 0.0]]).as_dict()
    assert same == run_sim2sim(contract, seconds=0.02, num_robots=2, command=(0.5, 0.0)).as_dict()
    apart = run_sim2sim(contract, seconds=0.02, num_robots=2, command=np.array([[0.5, 0.0], [0.0, 0.0]]))
    # Robot 1 is told to stand: its speed error is measured against 0 m/s, robot 0's against 0.5 m/s.
    assert apart.speed_tracking_error_mps != same["speed_tracking_error_mps"]


def test_a_policy_file_given_to_load_contract_names_the_contract_beside_it(tmp_path):
    # An .onnx or .pt file read as "not valid JSON ('utf-8' codec can't decode byte ...)", which names no fix.
    shipped = _contract("ppo")
    for suffix, kind in ((".onnx", "an ONNX model"), (".pt", "a checkpoint")):
        with pytest.raises(ContractError, match=rf"{kind}, not a policy contract .*pass the contract beside it, "
                                                rf"{re.escape(str(shipped))}"):
            load_contract(shipped.with_suffix(suffix))
    lone = shutil.copy(shipped.with_suffix(".onnx"), tmp_path / "renamed.bin")  # known by its first bytes too
    with pytest.raises(ContractError, match=r"renamed.bin is an ONNX model, .*its contract .*renamed.json is missing"):
        load_contract(lone)
    checkpoint = shutil.copy(shipped.with_suffix(".pt"), tmp_path / "latest.pt")
    with pytest.raises(ContractError, match=r"latest.pt is a checkpoint, .*python -m tocabi_torchrl.export "
                                            r"--checkpoint .*latest.pt --out policy.onnx"):
        load_contract(checkpoint)
    module = tmp_path / "walk.ts.pt"
    module.write_bytes(b"PK\x03\x04 a TorchScript zip")
    with pytest.raises(ContractError, match=r"walk.ts.pt is a TorchScript module, .*walk.json is missing"):
        load_contract(module)


def test_a_renamed_pair_runs_the_onnx_of_its_name_not_the_recorded_one(tmp_path):
    # The contract records the .onnx it was exported with; after my.onnx + my.json were renamed from it, a file of
    # the old name beside them (another policy) ran instead of my.onnx, and a wrong my.onnx was never looked at.
    shipped = robot.asset_path("policies", "tocabi_walk_torque.json")
    shutil.copy(shipped, tmp_path / "my.json")
    shutil.copy(shipped.with_suffix(".onnx"), tmp_path / "my.onnx")
    old = shutil.copy(robot.asset_path("policies", "tocabi_walk_ppo.onnx"), tmp_path / "tocabi_walk_torque.onnx")
    assert load_contract(tmp_path / "my.json")["policy"]["onnx_file"] == "tocabi_walk_torque.onnx"
    assert PolicyRuntime(tmp_path / "my.json").onnx_path == tmp_path / "my.onnx"
    assert PolicyRuntime(tmp_path / "my.json", onnx=tmp_path / "my.onnx").onnx_path == tmp_path / "my.onnx"
    with pytest.raises(ContractError, match=r"tocabi_walk_torque\.onnx does not match the sha256"):
        PolicyRuntime(tmp_path / "my.json", onnx=old)
    # The named file is another policy while the recorded one is the contract's: refused, naming the named file.
    shutil.copy(old, tmp_path / "my.onnx")
    shutil.copy(shipped.with_suffix(".onnx"), old)
    with pytest.raises(ContractError, match=r"my\.onnx does not match the sha256 .*records tocabi_walk_torque\.onnx"):
        PolicyRuntime(tmp_path / "my.json")
    with pytest.raises(ContractError, match=r"ONNX file .*absent\.onnx not found"):
        PolicyRuntime(tmp_path / "my.json", onnx=tmp_path / "absent.onnx")


def test_a_folder_given_for_a_policy_file_is_named_a_folder_with_the_files_it_holds(tmp_path):
    # A folder passed as the contract, the .onnx or the motion was reported "not found", and the user went looking
    # for a file that was there; the message now says it is a folder and lists the files of the kind it holds.
    shipped = robot.asset_path("policies", "tocabi_walk_torque.json")
    shutil.copy(shipped, tmp_path / "walk.json")
    shutil.copy(shipped.with_suffix(".onnx"), tmp_path / "walk.onnx")
    with pytest.raises(ContractError, match=r"policy contract .* is a folder, not a file \(it holds walk\.json\): "
                                            r"pass the \.json file itself"):
        PolicyRuntime(tmp_path)
    (tmp_path / "empty").mkdir()
    with pytest.raises(ContractError, match=r"ONNX file .*empty is a folder, not a file \(it holds no \.onnx file\)"):
        PolicyRuntime(tmp_path / "walk.json", onnx=tmp_path / "empty")
    with pytest.raises(ContractError, match=r"ONNX file .* is a folder, not a file \(it holds walk\.onnx\)"):
        PolicyRuntime(tmp_path / "walk.json", onnx=tmp_path)
    with pytest.raises(ContractError, match=r"reference motion .*empty is a folder, not a file"):
        PolicyRuntime(tmp_path / "walk.json", motion=tmp_path / "empty")


def test_run_sim2sim_takes_a_built_runtime_and_gives_the_numbers_of_the_path_based_call():
    from tocabi_torchrl.runtime.mujoco_driver import run_sim2sim

    contract = _contract("torque")  # a torque policy: tocabi_lab randomises it
    kw = {"seconds": 0.04, "perturbation": 1e-6, "seed": 2}
    fresh = PolicyRuntime(contract)
    assert run_sim2sim(fresh, num_robots=2, **kw).as_dict() == run_sim2sim(contract, num_robots=2, **kw).as_dict()
    # Reused for another robot count, and after a run with sensor randomisation (the run's sensors do not stay).
    noisy = run_sim2sim(fresh, num_robots=3, randomize="tocabi_lab", **kw).as_dict()
    assert fresh.sensors is None and fresh.num_robots == 3
    assert noisy == run_sim2sim(contract, num_robots=3, randomize="tocabi_lab", **kw).as_dict()
    assert run_sim2sim(fresh, num_robots=1, **kw).as_dict() == run_sim2sim(contract, num_robots=1, **kw).as_dict()
    # The same file as onnx= is what runs anyway; another file or a motion contradicts the runtime.
    assert run_sim2sim(fresh, num_robots=1, onnx=fresh.onnx_path, **kw).num_robots == 1
    other = _contract("ppo").with_suffix(".onnx")
    with pytest.raises(ValueError, match="onnx=.* with a PolicyRuntime that runs"):
        run_sim2sim(fresh, num_robots=1, onnx=other, **kw)
    with pytest.raises(ValueError, match="motion=.* with a PolicyRuntime"):
        run_sim2sim(fresh, num_robots=1, motion=contract, **kw)
    with pytest.raises(ValueError, match="sensors of its own"):
        run_sim2sim(PolicyRuntime(contract, sensors=lambda state: state), num_robots=1, **kw)


def test_an_on_step_that_is_not_callable_is_refused_before_anything_is_built(tmp_path):
    # It failed with "TypeError: 'int' object is not callable" at the first control period, after the policy, the
    # model and every robot were built. Missing files show that the check comes first.
    from tocabi_torchrl.runtime.mujoco_driver import run_sim2sim

    for hook, shown in ((3, "int 3"), ("print", "str 'print'")):
        with pytest.raises(ValueError, match=rf"on_step must be None or a callable on_step\(step, model, datas\) "
                                             rf".* got {shown}; pass a function"):
            run_sim2sim(tmp_path / "missing.json", model_path=tmp_path / "missing.xml", on_step=hook)


def test_a_state_that_is_not_a_robot_state_is_refused_by_name():
    # A dict of the fields, or None (a failed read), gave "AttributeError: 'dict' object has no attribute
    # 'base_quat'" from reset and step, naming neither the argument nor RobotState.
    runtime = PolicyRuntime(_contract("ppo"))
    fields = vars(_robots(1))
    for call in (lambda state: runtime.reset(state, (0.5, 0.0)), lambda state: runtime.step(state)):
        with pytest.raises(ContractError, match=r"state must be a RobotState \(tocabi_torchrl.runtime.RobotState\("
                                                r"base_quat=.*\), got dict \(for a dict of its fields: "
                                                r"RobotState\(\*\*fields\)\) without base_quat, joint_pos"):
            call(dict(fields))
        with pytest.raises(ContractError, match=r"state must be a RobotState .* got NoneType without base_quat"):
            call(None)
        runtime.reset(RobotState(**fields), (0.5, 0.0))  # for step: a running episode
    # An object with the fields is read as a RobotState, as before.
    runtime.step(SimpleNamespace(**fields))


def test_onnx_threads_must_be_an_int_of_at_least_zero(tmp_path):
    # "2" failed with onnxruntime's own "incompatible function arguments" TypeError, and -1 was taken silently. A
    # missing contract shows that the check comes first.
    for threads, shown in (("2", "str '2'"), (-1, "int -1"), (1.5, "float 1.5"), (True, "bool True")):
        with pytest.raises(ValueError, match=rf"threads must be an int >= 0 \(onnxruntime's intra-op threads; 0: its "
                                             rf"own default\), got {re.escape(shown)}; pass e.g. threads=1"):
            PolicyRuntime(tmp_path / "missing.json", threads=threads)
    assert PolicyRuntime(_contract("ppo"), threads=np.int64(2)).session is not None  # numpy ints as before
