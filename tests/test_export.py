"""ONNX export: the exported actor equals the torch actor, the contract holds the training objects' facts, every
control mode exports, and the command line never overwrites silently. CPU only (C MuJoCo backend)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import torch

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from tocabi_torchrl import robot
from tocabi_torchrl.export import load_policy
from tocabi_torchrl.export.__main__ import main as export_main
from tocabi_torchrl.export.contract import config_sha256
from tocabi_torchrl.export.onnx_export import DeterministicActor
from tocabi_torchrl.evaluation.gait_test import _fixed_command
from tocabi_torchrl.runtime import load_contract
from tocabi_torchrl.transforms import REFERENCE_HISTORY, REFERENCE_OBS_LAYOUT

POLICIES = ("ppo", "torque", "robust")


def _policy_file(name: str, suffix: str):
    return robot.asset_path("policies", f"tocabi_walk_{name}{suffix}")


def _recorded_observations(policy, steps: int) -> torch.Tensor:
    """(num_envs * steps, obs_dim) policy inputs of a deterministic rollout of the TorchRL env."""
    out = []
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        td = policy.env.reset()
        for _ in range(steps):
            out.append(td["observation"].clone())
            td = step_mdp(policy.env.step(policy.agent.actor(td)))
    return torch.cat(out)


@pytest.mark.parametrize("name", POLICIES)
def test_shipped_onnx_equals_torch_actor_on_random_and_recorded_observations(name):
    """The shipped .onnx reproduces the checkpoint's deterministic actor within 1e-5 on 10k random and 10k
    recorded observations, and its contract belongs to this checkpoint (config hash, ONNX hash)."""
    policy = load_policy(_policy_file(name, ".pt"), num_envs=50, command=_fixed_command((0.5, 0.0)))
    contract = load_contract(_policy_file(name, ".json"))
    assert contract["training_config_sha256"] == config_sha256(policy.saved_config)
    onnx_policy = ort.InferenceSession(str(_policy_file(name, ".onnx")), providers=["CPUExecutionProvider"])
    actor = DeterministicActor(policy.agent.actor).eval()
    obs_dim = contract["policy"]["input_dim"]
    gen = torch.Generator().manual_seed(0)
    random_obs = 3.0 * torch.randn(10_000, obs_dim, generator=gen)
    recorded = _recorded_observations(policy, steps=200)
    assert recorded.shape == (10_000, obs_dim)
    for obs in (random_obs, recorded):
        with torch.no_grad():
            expected = actor(obs).numpy()
        got = onnx_policy.run(None, {contract["policy"]["input_name"]: obs.numpy()})[0]
        assert got.shape == expected.shape == (10_000, contract["action"]["dim"])
        assert np.abs(got - expected).max() <= 1e-5


def test_an_export_leaves_an_output_file_that_appeared_while_it_ran(tmp_path, monkeypatch):
    # The outputs are checked free at the start; the atomic writes then replaced a file created there while the
    # policy was loaded and traced.
    from tocabi_torchrl.export import onnx_export

    out = tmp_path / "walk.onnx"
    trace = onnx_export.export_onnx

    def another_writer_meanwhile(*args, **kwargs):
        out.with_suffix(".json").write_text("theirs")
        return trace(*args, **kwargs)

    monkeypatch.setattr(onnx_export, "export_onnx", another_writer_meanwhile)
    with pytest.raises(SystemExit, match=r"walk.json appeared while the export ran and was left as it is .*export "
                                         r"again with --overwrite"):
        export_main(["--checkpoint", str(_policy_file("ppo", ".pt")), "--out", str(out)])
    assert out.with_suffix(".json").read_text() == "theirs" and not list(tmp_path.glob(".*.tmp"))
    export_main(["--checkpoint", str(_policy_file("ppo", ".pt")), "--out", str(out), "--overwrite"])
    load_contract(out.with_suffix(".json"))


def test_export_cli_writes_onnx_contract_torchscript_and_refuses_to_overwrite(tmp_path, capsys):
    out = tmp_path / "walk.onnx"
    export_main(["--checkpoint", str(_policy_file("ppo", ".pt")), "--out", str(out), "--torchscript"])
    onnx.checker.check_model(onnx.load(str(out)))
    contract = load_contract(out.with_suffix(".json"))
    scripted = torch.jit.load(str(out.with_suffix(".ts.pt")))
    obs = torch.randn(7, contract["policy"]["input_dim"])
    onnx_policy = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    np.testing.assert_allclose(scripted(obs).detach().numpy(), onnx_policy.run(None, {"observation": obs.numpy()})[0],
                               atol=1e-5)

    # The contract's facts are those of the objects that trained the policy.
    obs_section = contract["observation"]
    assert obs_section["step_dim"] == 37 and len(obs_section["entries"]) == 37
    knee = robot.JOINT_NAMES.index("L_Knee_Joint")
    assert obs_section["entries"][3 + knee]["name"] == "leg_joint_pos[L_Knee_Joint]"
    assert [e["block"] for e in obs_section["entries"]][::12][:2] == [REFERENCE_OBS_LAYOUT[0].name,
                                                                     REFERENCE_OBS_LAYOUT[1].name]
    assert obs_section["history"]["obs_ages"] == list(REFERENCE_HISTORY.obs_ages)
    assert obs_section["history"]["action_ages"] == list(REFERENCE_HISTORY.action_ages)
    assert contract["policy"]["input_dim"] == 237
    assert contract["action"]["control_mode"] == "pd_reference"
    assert contract["action"]["leg"]["kind"] == "position" and contract["action"]["leg"]["center"] == "reference"
    assert contract["action"]["leg"]["kp"] == pytest.approx(list(robot.LEG_KP))  # the run's pd_gains="robot"
    assert contract["timing"] == {"physics_dt_s": 0.0005, "substeps": 8, "control_dt_s": pytest.approx(0.004),
                                  "control_hz": pytest.approx(250.0)}
    motion = contract["reference_motion"]
    assert motion["name"] == "tocabi_walk.npz" and len(motion["sha256"]) == 64
    # Everything written is plain JSON that a C++ controller can read: no NaN/Infinity tokens.
    _strict_json(out.with_suffix(".json").read_text())
    json.dumps(contract, allow_nan=False)

    with pytest.raises(SystemExit, match=r"already exist\(s\); replace with --overwrite \(overwrite=True from "
                                         r"Python\) \(the \.ts\.pt is another export's"):
        export_main(["--checkpoint", str(_policy_file("ppo", ".pt")), "--out", str(out)])
    with pytest.raises(SystemExit) as refusal:  # with --torchscript the .ts.pt is replaced like the others
        export_main(["--checkpoint", str(_policy_file("ppo", ".pt")), "--out", str(out), "--torchscript"])
    assert "already exist(s)" in str(refusal.value.code) and "another export" not in str(refusal.value.code)
    capsys.readouterr()
    # Re-exported without --torchscript, the old .ts.pt (here the same checkpoint's, in general another one's) must
    # not be left beside the new ONNX file as if it were its TorchScript twin: it is removed, and the output says so.
    export_main(["--checkpoint", str(_policy_file("ppo", ".pt")), "--out", str(out), "--overwrite"])
    printed = capsys.readouterr().out
    assert "wrote" in printed and f"removed {out.with_suffix('.ts.pt')}" in printed
    assert not out.with_suffix(".ts.pt").exists()


def _strict_json(text: str):
    def refuse(name):
        raise ValueError(f"non-standard JSON constant {name}")

    return json.loads(text, parse_constant=refuse)


# ------------------------------------------------------------------------------------ broken checkpoints
@pytest.fixture(scope="module")
def tiny_checkpoints(tmp_path_factory):
    """Tiny untrained checkpoints (16-unit actor) as test_every_control_mode_exports builds them: ``torque`` (fixed
    normalisation), ``running_without_stats`` (running normalisation, saved without the env's transform state) and
    ``capped_solver`` (``torque`` trained with the Newton solver capped at 4 iterations)."""
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.rl.checkpoint import save_checkpoint
    from tocabi_torchrl.rl.trainer import build_agent, build_env

    root = tmp_path_factory.mktemp("tiny")
    out = {}
    for name, normalization, extra in (("torque", None, {}), ("running_without_stats", "running", {}),
                                       ("capped_solver", None, {"env.sim.solver_iterations": 4})):
        cfg = preset_config("default", **{"env.control.mode": "torque", "env.num_envs": 1, "ppo.minibatch_size": 48,
                            "ppo.actor_hidden": (16,),
                            "ppo.critic_hidden": (16,), **extra}, device="cpu")
        if normalization:
            cfg.transforms.normalization = normalization
        env = build_env(cfg, torch.device("cpu"), num_envs=1)
        agent = build_agent(cfg, 237, 13, torch.device("cpu"))
        out[name] = save_checkpoint(root / name, 0, 0, agent, None, None if normalization else env, cfg)
    return out


def _export_with(monkeypatch, tmp_path, checkpoint, breaks):
    """export_policy of ``checkpoint`` with ``breaks(policy)`` applied after loading: the damage reaches the export's
    own checks whatever the checkpoint reader lets through. Returns the output path."""
    from tocabi_torchrl.export import onnx_export

    load = onnx_export.load_policy

    def load_broken(ckpt):
        policy = load(ckpt)
        with torch.no_grad():
            breaks(policy)
        return policy

    monkeypatch.setattr(onnx_export, "load_policy", load_broken)
    return tmp_path / "p.onnx"


def _mean_net(policy):
    return DeterministicActor(policy.agent.actor).mean_net


def _normalizer(policy):
    return next(t for t in policy.env.transform if type(t).__name__ == "FixedNormalization")


@pytest.mark.parametrize("what", ["actor weight", "normalisation scale"])
def test_export_refuses_nan_or_inf_actor_weights_and_normalisation_statistics(what, tiny_checkpoints, tmp_path,
                                                                              monkeypatch):
    # A diverged run used to export cleanly: the runtime then turned the NaN actions into zeros and walked blind.
    from tocabi_torchrl.export import ExportError, export_policy

    def breaks(policy):
        if what == "actor weight":
            _mean_net(policy)[0].weight[3, 5] = float("nan")
        else:
            _normalizer(policy).scale[2] = float("inf")

    out = _export_with(monkeypatch, tmp_path, tiny_checkpoints["torque"], breaks)
    named = "actor.mean_net.0.weight" if what == "actor weight" else "env transform transforms.3.scale"
    with pytest.raises(ExportError, match=rf"NaN or inf in \['{re.escape(named)}'\].*Export an earlier checkpoint"):
        export_policy(tiny_checkpoints["torque"], out)
    assert not out.exists() and not out.with_suffix(".json").exists()


def test_export_refuses_a_policy_whose_onnx_output_is_not_finite(tiny_checkpoints, tmp_path, monkeypatch):
    # Finite weights large enough to overflow float32: only running the exported graph shows it.
    from tocabi_torchrl.export import ExportError, export_policy

    def breaks(policy):
        net = _mean_net(policy)
        net[0].weight.zero_()
        net[0].bias.fill_(1e30)
        net[2].weight.fill_(1e30)

    out = _export_with(monkeypatch, tmp_path, tiny_checkpoints["torque"], breaks)
    with pytest.raises(ExportError, match="action is NaN or inf on a representative input.*Export an earlier"):
        export_policy(tiny_checkpoints["torque"], out)
    assert not out.exists()


def test_export_refuses_a_zero_normalisation_scale(tiny_checkpoints, tmp_path, monkeypatch):
    # A constant signal normalised with eps = 0 has scale 0: finite, but the runtime would divide by it.
    from tocabi_torchrl.export import ExportError, export_policy

    out = _export_with(monkeypatch, tmp_path, tiny_checkpoints["torque"],
                       lambda policy: _normalizer(policy).scale.__setitem__(0, 0.0))
    with pytest.raises(ExportError, match=r"scale that is not finite and > 0 at entries \[0\].*retrain with eps > 0"):
        export_policy(tiny_checkpoints["torque"], out)
    assert not out.exists()


def test_export_writes_only_standard_json(tiny_checkpoints, tmp_path, monkeypatch):
    # json.dumps writes NaN/Infinity by default, which C++ readers refuse; the export refuses to write them.
    from tocabi_torchrl.export import ExportError, export_policy, onnx_export

    build = onnx_export.build_contract

    def with_nan(*args, **kwargs):
        contract = build(*args, **kwargs)
        contract["training_config"]["note"] = float("nan")  # a field check_contract does not read
        return contract

    monkeypatch.setattr(onnx_export, "build_contract", with_nan)
    out = tmp_path / "p.onnx"
    with pytest.raises(ExportError, match="would hold a NaN or infinite number"):
        export_policy(tiny_checkpoints["torque"], out)
    assert not out.exists() and not out.with_suffix(".json").exists()
    monkeypatch.setattr(onnx_export, "build_contract", build)
    export_policy(tiny_checkpoints["torque"], out)
    _strict_json(out.with_suffix(".json").read_text())


def test_export_refuses_a_running_normalisation_checkpoint_without_its_statistics(tiny_checkpoints, tmp_path):
    # Transform state is loaded leniently, so the export used to state the normaliser's initial statistics as the
    # trained ones, and play.py's gait test used to run with them.
    from tocabi_torchrl.evaluation.record import load_policy as load_for_play
    from tocabi_torchrl.rl.checkpoint import CheckpointError

    with pytest.raises(CheckpointError, match=r"lacks the running normalisation statistics .*would run with the "
                                              r"initial statistics"):
        load_for_play(tiny_checkpoints["running_without_stats"], num_envs=2, device=torch.device("cpu"))

    with pytest.raises(CheckpointError, match=r"lacks the running normalisation statistics \['transforms\.3\.mean', "
                                              r"'transforms\.3\.var', 'transforms\.3\.count'\].*Use a checkpoint "
                                              r"saved with its env"):
        load_policy(tiny_checkpoints["running_without_stats"])
    with pytest.raises(SystemExit, match="error: checkpoint .* lacks the running normalisation statistics"):
        export_main(["--checkpoint", str(tiny_checkpoints["running_without_stats"]), "--out",
                     str(tmp_path / "r.onnx")])


def test_every_control_mode_exports(tmp_path):
    """A pd (nominal-centred) run and a torque run export with the leg rule of their mode."""
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.rl.checkpoint import save_checkpoint
    from tocabi_torchrl.rl.trainer import build_agent, build_env

    cfg = preset_config("default", **{"env.control.mode": "pd", "env.num_envs": 1, "ppo.minibatch_size": 48,
                        "ppo.actor_hidden": (16,),
                        "ppo.critic_hidden": (16,)}, device="cpu")
    env = build_env(cfg, torch.device("cpu"), num_envs=1)
    agent = build_agent(cfg, 237, 13, torch.device("cpu"))
    ckpt = save_checkpoint(tmp_path / "run", 0, 0, agent, None, env, cfg)
    export_main(["--checkpoint", str(ckpt), "--out", str(tmp_path / "pd.onnx")])
    leg = load_contract(tmp_path / "pd.json")["action"]["leg"]
    assert leg["kind"] == "position" and leg["center"] == "nominal"
    assert leg["nominal"] == pytest.approx(list(env.base_env.cfg.control.pd_nominal))
    assert leg["kp"] == pytest.approx(list(env.base_env.cfg.control.pd_kp))

    torque = load_contract(_policy_file("torque", ".json"))["action"]["leg"]
    assert torque["kind"] == "torque" and torque["torque_limits_nm"] == pytest.approx(list(robot.LEG_TORQUE_LIMITS))


def test_export_warns_for_a_checkpoint_saved_while_the_torque_assist_was_on(tmp_path):
    # A checkpoint saved mid-fade exported without a word, though its policy trained with assist torque added to its
    # leg torques that the exported policy never gets.
    import warnings

    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.export.onnx_export import export_policy
    from tocabi_torchrl.rl.checkpoint import save_checkpoint
    from tocabi_torchrl.rl.trainer import assist_schedule, build_agent, build_env

    cfg = preset_config("default", **{"env.control.mode": "torque", "env.num_envs": 1, "ppo.minibatch_size": 48,
                        "ppo.actor_hidden": (16,), "ppo.critic_hidden": (16,), "ppo.torque_assist": 1.0,
                        "ppo.assist_fade_start": 1000, "ppo.assist_fade_end": 3000}, device="cpu")
    env = build_env(cfg, torch.device("cpu"), num_envs=1)
    agent = build_agent(cfg, 237, 13, torch.device("cpu"))
    beta = assist_schedule(cfg, env)(2000)
    assert 0 < beta < 1
    fading = save_checkpoint(tmp_path / "fading", 1, 2000, agent, None, env, cfg)
    said = (r"saved at 2,000 env steps, while the torque assist was still on: "
            rf"β = {beta:.3f} \(it fades from 1 at 1,000 to 0 at 3,000 env steps\).*export a checkpoint saved after "
            r"3,000 env steps")
    with pytest.warns(UserWarning, match=said) as recorded:
        result = export_policy(fading, tmp_path / "fading.onnx")
    assert [type(w.message).__name__ for w in recorded if "torque assist" in str(w.message)] == ["AssistFadeWarning"]
    assert result.assist == pytest.approx(beta)
    faded = save_checkpoint(tmp_path / "faded", 2, 3000, agent, None, env, cfg)
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*torque assist")
        assert export_policy(faded, tmp_path / "faded.onnx").assist == 0.0


def test_export_refuses_a_non_onnx_output_and_a_bad_checkpoint(tmp_path):
    with pytest.raises(SystemExit, match=r"\.onnx"):
        export_main(["--checkpoint", str(_policy_file("ppo", ".pt")), "--out", str(tmp_path / "x.bin")])
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(SystemExit, match="cannot read checkpoint"):
        export_main(["--checkpoint", str(bad), "--out", str(tmp_path / "x.onnx")])
    # An --out that cannot be written (here its folder is a file) is one error line, not a traceback.
    with pytest.raises(SystemExit, match=r"^error: .*bad\.pt"):
        export_main(["--checkpoint", str(_policy_file("ppo", ".pt")), "--out", str(bad / "x.onnx")])


def test_the_contract_says_when_training_capped_the_solver(tiny_checkpoints, tmp_path):
    from tocabi_torchrl.export import export_policy
    from tocabi_torchrl.runtime import load_contract

    sections = {}
    for name in ("torque", "capped_solver"):
        out = tmp_path / name / "p.onnx"
        out.parent.mkdir()
        export_policy(tiny_checkpoints[name], out)
        sections[name] = load_contract(out.with_suffix(".json"))["trained_under"]
    assert "solver" not in sections["torque"]
    assert sections["capped_solver"]["solver"].startswith("Newton iterations capped at 4 per physics substep")


def test_a_policy_of_its_own_motion_exports_with_it_and_sim2sim_runs_it(tmp_path, capsys):
    # The contract named my_walk.npz, which the export left behind: sim2sim then failed naming only the shipped
    # motions' folder, and had no way to be given the file.
    import shutil

    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.rl.checkpoint import save_checkpoint
    from tocabi_torchrl.rl.trainer import build_agent, build_env
    from tocabi_torchrl.robot import asset_path
    from tocabi_torchrl.runtime import ContractError, PolicyRuntime

    motion = tmp_path / "motions" / "my_walk.npz"
    motion.parent.mkdir()
    shutil.copy(asset_path("motions", "tocabi_walk.npz"), motion)
    cfg = preset_config("default", **{"env.num_envs": 1, "ppo.minibatch_size": 48, "ppo.actor_hidden": (16,),
                                      "ppo.critic_hidden": (16,), "env.task.motion": str(motion)}, device="cpu")
    env = build_env(cfg, torch.device("cpu"), num_envs=1)
    ckpt = save_checkpoint(tmp_path / "run", 0, 0, build_agent(cfg, 237, 13, torch.device("cpu")), None, env, cfg)
    out = tmp_path / "export" / "mine.onnx"
    out.parent.mkdir()
    (out.parent / "my_walk.npz").write_bytes(b"another motion")
    with pytest.raises(SystemExit, match="my_walk.npz already exists and is another motion than the policy's"):
        export_main(["--checkpoint", str(ckpt), "--out", str(out)])
    export_main(["--checkpoint", str(ckpt), "--out", str(out), "--overwrite"])
    assert f"copied the policy's reference motion to {out.parent / 'my_walk.npz'}" in capsys.readouterr().out
    assert (out.parent / "my_walk.npz").read_bytes() == motion.read_bytes()
    assert PolicyRuntime(out.with_suffix(".json")).motion.cycle_rows > 0  # the runtime finds it beside the .onnx
    export_main(["--checkpoint", str(ckpt), "--out", str(tmp_path / "export" / "again.onnx")])  # same file: kept
    assert "copied" not in capsys.readouterr().out
    (out.parent / "my_walk.npz").unlink()
    with pytest.raises(ContractError, match=r"my_walk.npz is neither beside the policy \(.*\) nor among the shipped"):
        PolicyRuntime(out.with_suffix(".json"))


def test_a_relative_motion_found_elsewhere_is_refused(tmp_path, monkeypatch):
    # A run trained with env.task.motion="my_walk.npz" (relative, as typed): exported from another folder holding
    # another my_walk.npz, the policy went out with that file's joint targets and hash, without a word.
    import numpy as np

    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.rl.checkpoint import read_checkpoint, save_checkpoint
    from tocabi_torchrl.rl.trainer import build_agent, build_env
    from tocabi_torchrl.robot import asset_path

    shipped = dict(np.load(asset_path("motions", "tocabi_walk.npz")))
    for folder, shift in (("a", 0.0), ("b", 0.01)):
        (tmp_path / folder).mkdir()
        np.savez(tmp_path / folder / "my_walk.npz", **{**shipped, "joint_pos": shipped["joint_pos"] + shift})
    monkeypatch.chdir(tmp_path / "a")
    cfg = preset_config("default", **{"env.num_envs": 1, "ppo.minibatch_size": 48, "ppo.actor_hidden": (16,),
                                      "ppo.critic_hidden": (16,), "env.task.motion": "my_walk.npz"}, device="cpu")
    env = build_env(cfg, torch.device("cpu"), num_envs=1)
    ckpt = save_checkpoint(tmp_path / "run", 0, 0, build_agent(cfg, 237, 13, torch.device("cpu")), None, env, cfg)
    assert len(read_checkpoint(ckpt)["motion_sha256"]) == 64
    export_main(["--checkpoint", str(ckpt), "--out", str(tmp_path / "a.onnx")])  # the same file: exported
    monkeypatch.chdir(tmp_path / "b")
    with pytest.raises(SystemExit, match=r"trained on a reference motion of sha256 .* but the env's motion "
                                         r".*b/my_walk.npz is another file .*run from the folder the training ran in"):
        export_main(["--checkpoint", str(ckpt), "--out", str(tmp_path / "b.onnx")])
    assert not (tmp_path / "b.onnx").exists()


def test_an_unwritable_out_is_said_before_the_policy_loads_and_ctrl_c_exits_130(tmp_path, monkeypatch, capsys):
    # The unwritable folder was found at the first write, after the policy had loaded and been traced; Ctrl-C gave
    # a KeyboardInterrupt traceback from deep inside the tracer.
    import tocabi_torchrl.export.onnx_export as onnx_export

    def never(*a, **k):
        raise AssertionError("the policy was loaded")

    blocked = tmp_path / "blocked"
    blocked.write_text("a file, not a folder")
    monkeypatch.setattr(onnx_export, "load_policy", never)
    with pytest.raises(SystemExit, match="error: .*a file, not a folder"):
        export_main(["--checkpoint", "assets/policies/tocabi_walk_ppo.pt", "--out", str(blocked / "p.onnx")])

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(onnx_export, "load_policy", interrupted)
    with pytest.raises(SystemExit) as info:
        export_main(["--checkpoint", "assets/policies/tocabi_walk_ppo.pt", "--out", str(tmp_path / "p.onnx")])
    assert info.value.code == 130 and "stopped (Ctrl-C); no file is left half-written" in capsys.readouterr().err


def test_a_policy_with_running_normalisation_exports_and_runs(tmp_path):
    # The contract check refused the export's own "running (frozen at export)" kind: no such policy could be exported.
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.export import export_policy
    from tocabi_torchrl.rl.checkpoint import save_checkpoint
    from tocabi_torchrl.rl.trainer import build_agent, build_env
    from tocabi_torchrl.runtime import PolicyRuntime

    cfg = preset_config("default", **{"env.num_envs": 1, "ppo.minibatch_size": 48, "ppo.actor_hidden": (16,),
                                      "ppo.critic_hidden": (16,), "transforms.normalization": "running"},
                        device="cpu")
    env = build_env(cfg, torch.device("cpu"), num_envs=1)
    ckpt = save_checkpoint(tmp_path / "run", 0, 0, build_agent(cfg, 237, 13, torch.device("cpu")), None, env, cfg)
    result = export_policy(ckpt, tmp_path / "p.onnx")
    runtime = PolicyRuntime(result.contract)
    assert runtime.contract["observation"]["normalization"]["kind"] == "running (frozen at export)"


def test_a_checkpoint_of_another_shipped_motion_says_so():
    # Another package version's shipped motion: the message must not send the user looking for a relative path.
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.rl.checkpoint import CheckpointError, apply_checkpoint, read_checkpoint
    from tocabi_torchrl.rl.trainer import build_agent, build_env

    state = read_checkpoint(robot.asset_path("policies", "tocabi_walk_ppo.pt"))
    cfg = preset_config("default", **{"env.num_envs": 1, "ppo.minibatch_size": 48}, device="cpu")
    env = build_env(cfg, torch.device("cpu"), num_envs=1)
    agent = build_agent(cfg, 237, 13, torch.device("cpu"))
    apply_checkpoint(state, agent, env=env)  # the shipped files predate the hash: nothing to compare
    with pytest.raises(CheckpointError, match=r"sha256 000000000000\.\.\., but the env's motion .*tocabi_walk.npz "
                                              r"is another file .*the shipped motion is not the one"):
        apply_checkpoint({**state, "motion_sha256": "0" * 64}, agent, env=env)


def test_the_contract_states_the_upper_body_gains_of_the_model_the_policy_trained_on(tmp_path):
    # The env holds the upper body with the training model's own position servos; the contract used to state the
    # shipped model's gains whatever env.task.model_path the run trained on, and sim2sim applied those.
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.export import export_policy
    from tocabi_torchrl.rl.checkpoint import save_checkpoint
    from tocabi_torchrl.rl.trainer import build_agent, build_env

    shipped = robot.asset_path("tocabi", "tocabi.xml").read_text()
    waist = '<position name="Waist1_Motor" joint="Waist1_Joint" kp="6000" kv="200"'
    assert waist in shipped
    model = tmp_path / "stiff_waist.xml"
    model.write_text(shipped.replace(waist, waist.replace('kp="6000" kv="200"', 'kp="7000" kv="250"')))
    cfg = preset_config("default", **{"env.control.mode": "torque", "env.num_envs": 1, "ppo.minibatch_size": 48,
                                      "ppo.actor_hidden": (16,), "ppo.critic_hidden": (16,),
                                      "env.task.model_path": str(model)}, device="cpu")
    env = build_env(cfg, torch.device("cpu"), num_envs=1)
    ckpt = save_checkpoint(tmp_path / "run", 0, 0, build_agent(cfg, 237, 13, torch.device("cpu")), None, env, cfg)
    upper = load_contract(export_policy(ckpt, tmp_path / "p.onnx").contract)["upper_body"]
    assert upper["kp"] == [7000.0, *robot.UPPER_KP[1:].tolist()]
    assert upper["kv"] == [250.0, *robot.UPPER_KV[1:].tolist()]

    # A model whose waist is a motor: the env sent it target angles as torques, which no contract can describe.
    model.write_text(shipped.replace(waist + ' forcerange="-303 303"/>',
                                     '<motor name="Waist1_Motor" joint="Waist1_Joint" ctrlrange="-303 303"/>'))
    cfg.env.task.model_path = str(model)
    env = build_env(cfg, torch.device("cpu"), num_envs=1)
    ckpt = save_checkpoint(tmp_path / "motor", 0, 0, build_agent(cfg, 237, 13, torch.device("cpu")), None, env, cfg)
    with pytest.raises(ValueError, match=r"actuator 'Waist1_Motor' is not a position servo"):
        export_policy(ckpt, tmp_path / "m.onnx")
    assert not (tmp_path / "m.onnx").exists()
