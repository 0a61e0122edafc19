"""recipes/sim2sim.py reports a model without the contract's names, a file MuJoCo cannot read, a model that reads its
radian joint ranges as degrees, a missing model file, a policy file given as the contract, an --out folder that does
not exist, an --out that is empty or a folder, an --out file it cannot write and a missing onnxruntime in one
``error:`` line (or a usage error), not a traceback."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

pytest.importorskip("onnxruntime")

from recipe_runner import load_recipe

CONTRACT = Path(__file__).resolve().parents[1] / "assets" / "policies" / "tocabi_walk_ppo.json"
needs_contract = pytest.mark.skipif(not CONTRACT.is_file(), reason="shipped policy contract not present")


def _run(argv: list[str]) -> SystemExit:
    with pytest.raises(SystemExit) as info:
        load_recipe("sim2sim").main(["--contract", str(CONTRACT), "--seconds", "0.02", "--num_robots", "1", *argv])
    return info.value


@needs_contract
def test_a_model_without_the_contracts_names_is_one_error_line(tmp_path):
    # It used to crash with AttributeError: 'NoneType' object has no attribute 'set_to_position'.
    model = tmp_path / "other.xml"
    model.write_text('<mujoco><worldbody><body><joint/><geom size="0.1"/></body></worldbody></mujoco>')
    message = str(_run(["--model", str(model)]).code)
    assert message.startswith(f"error: {model} lacks 72 name(s) the policy contract needs (joint 'L_HipYaw_Joint'")
    assert "\n" not in message


@needs_contract
@pytest.mark.parametrize("name, text", [("model.txt", "not a model"),
                                        ("broken.xml", "<mujoco><worldbody><body></mujoco>")])
def test_a_file_mujoco_cannot_read_is_one_error_line_naming_it(tmp_path, name, text):
    """A file of another kind, or broken XML: MuJoCo's own message ("could not find decoder for resource", or an XML
    error over several lines) on one line, with the file and what to pass."""
    model = tmp_path / name
    model.write_text(text)
    message = str(_run(["--model", str(model)]).code)
    assert message.startswith(f"error: {model}: MuJoCo cannot read it as an MJCF model (")
    assert message.endswith("pass a TOCABI MJCF (.xml)") and "\n" not in message



@needs_contract
def test_a_model_read_in_degrees_is_one_error_line_naming_the_file_and_the_fix(tmp_path):
    # It ran and printed metrics of robots held by joint ranges 180/π too narrow (no <compiler angle="radian">).
    model = tmp_path / "no_angle.xml"
    shipped = Path(__file__).resolve().parents[1] / "assets" / "tocabi" / "tocabi.xml"
    model.write_text(shipped.read_text().replace(' angle="radian"', ""))
    message = str(_run(["--model", str(model)]).code)
    assert message.startswith(f"error: robot model {model}: it is compiled with <compiler angle=\"degree\">")
    assert f'Set <compiler angle="radian"> in {model}' in message and "\n" not in message

def test_an_out_file_in_a_missing_folder_is_refused_before_the_run(capsys, tmp_path):
    # The contract does not exist either: the --out check comes first, so nothing is run (it used to fail with
    # FileNotFoundError after the whole run).
    out = tmp_path / "nodir" / "m.json"
    with pytest.raises(SystemExit) as info:
        load_recipe("sim2sim").main(["--contract", str(tmp_path / "missing.json"), "--out", str(out)])
    assert info.value.code == 2
    assert f"--out {out}: folder {out.parent} does not exist" in capsys.readouterr().err


@pytest.mark.parametrize("kind", ["empty", "missing folder/", "existing folder"])
def test_an_out_that_is_empty_or_a_folder_is_refused_before_the_run(capsys, tmp_path, kind):
    # "--out ''" ran and wrote nothing; "--out runs/" (a folder not yet made) wrote the metrics to a file named runs.
    # The contract does not exist: the --out check comes first, so nothing is run.
    out = {"empty": "", "missing folder/": f"{tmp_path / 'runs'}/", "existing folder": str(tmp_path)}[kind]
    with pytest.raises(SystemExit) as info:
        load_recipe("sim2sim").main(["--contract", str(tmp_path / "missing.json"), "--out", out])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert ("--out is empty; give a JSON file" in err if kind == "empty"
            else f"--out {out} is a folder; give a file name, e.g. --out {Path(out) / 'sim2sim.json'}" in err)
    assert not (tmp_path / "runs").exists()


@needs_contract
def test_an_out_file_that_cannot_be_written_is_one_error_line_after_the_printed_metrics(monkeypatch, capsys,
                                                                                         tmp_path):
    import tocabi_torchrl.atomic

    def refuse(path, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(path))

    # A read-only folder does not stop root, so refuse the (atomic) write.
    monkeypatch.setattr(tocabi_torchrl.atomic, "atomic_write_bytes", refuse)
    out = tmp_path / "m.json"
    message = str(_run(["--out", str(out)]).code)
    assert message.startswith(f"error: cannot write --out {out} ([Errno 13] Permission denied")
    assert message.endswith("the metrics are printed above") and '"survival": 1.0' in capsys.readouterr().out


@needs_contract
def test_an_out_file_created_during_the_run_is_left_as_it_is(capsys, tmp_path):
    # --out is checked free before the run; the metrics used to replace a file created there meanwhile.
    out = tmp_path / "m.json"
    recipe = load_recipe("sim2sim")
    run = recipe.run_sim2sim

    def another_writer_meanwhile(*args, **kwargs):
        out.write_text("theirs")
        return run(*args, **kwargs)

    recipe.run_sim2sim = another_writer_meanwhile
    with pytest.raises(SystemExit) as info:
        recipe.main(["--contract", str(CONTRACT), "--seconds", "0.02", "--num_robots", "1", "--out", str(out)])
    assert str(info.value.code) == (f"error: --out {out} was created by something else during the run and is left "
                                    "as it is; the metrics are printed above")
    assert out.read_text() == "theirs" and '"survival": 1.0' in capsys.readouterr().out


@needs_contract
def test_a_missing_onnxruntime_is_one_error_line(monkeypatch):
    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # makes `import onnxruntime` fail
    message = str(_run([]).code)
    assert message.startswith("error: running an exported policy needs onnxruntime")
    assert 'pip install -e ".[export]"' in message


@needs_contract
def test_a_contract_whose_leg_kind_contradicts_its_control_mode_is_one_error_line(tmp_path):
    # The driver built position servos from leg.kind while the runtime computed commands from control_mode: a
    # pd_reference contract labelled torque sent PD targets [rad] to torque motors.
    import json
    import shutil

    contract = json.loads(CONTRACT.read_text())
    contract["action"]["leg"]["kind"] = "torque"
    shutil.copy(CONTRACT.with_suffix(".onnx"), tmp_path / contract["policy"]["onnx_file"])
    path = tmp_path / "c.json"
    path.write_text(json.dumps(contract))
    with pytest.raises(SystemExit) as info:
        load_recipe("sim2sim").main(["--contract", str(path), "--seconds", "0.02", "--num_robots", "1"])
    message = str(info.value.code)
    assert message.startswith("error: ") and "action.leg.kind is 'torque' but control_mode is 'pd_reference'" in message
    assert "\n" not in message


@needs_contract
def test_a_contract_with_a_negative_action_scale_is_one_error_line(capsys, tmp_path):
    # It used to run: every robot fell and the recipe exited 0 with the metrics of a fall.
    import json
    import shutil

    contract = json.loads(CONTRACT.read_text())
    contract["action"]["leg"]["action_scale"] = -0.5
    shutil.copy(CONTRACT.with_suffix(".onnx"), tmp_path / contract["policy"]["onnx_file"])
    path = tmp_path / "c.json"
    path.write_text(json.dumps(contract))
    with pytest.raises(SystemExit) as info:
        load_recipe("sim2sim").main(["--contract", str(path), "--seconds", "0.02", "--num_robots", "1"])
    message = str(info.value.code)
    assert info.value.code != 0 and "\n" not in message
    assert message.startswith(f"error: {path}: action.leg.action_scale is -0.5 but must be a finite number >= 0")
    assert capsys.readouterr().out == ""  # no metrics: nothing ran


@needs_contract
@pytest.mark.parametrize("suffix", [".onnx", ".pt", ".ts.pt"])
def test_a_policy_file_given_as_the_contract_names_the_contract_beside_it(capsys, suffix):
    # It used to say only "not valid JSON ('utf-8' codec can't decode byte ...)". A TorchScript twin (walk.ts.pt)
    # has its contract at walk.json too.
    policy = CONTRACT.with_suffix(suffix)
    suffix = policy.suffix
    with pytest.raises(SystemExit) as info:
        load_recipe("sim2sim").main(["--contract", str(policy)])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert f"--contract takes the policy's .json contract, not a {suffix} file" in err
    assert f"the contract beside it is {CONTRACT}" in err


def test_a_missing_model_file_names_the_option(capsys, tmp_path):
    # It used to pass MuJoCo's own "ParseXML: Error opening file" through, after loading the contract.
    with pytest.raises(SystemExit) as info:
        load_recipe("sim2sim").main(["--contract", str(CONTRACT), "--model", str(tmp_path / "nope.xml")])
    assert info.value.code == 2
    assert f"--model {tmp_path / 'nope.xml'}: no such file" in capsys.readouterr().err


@needs_contract
def test_a_viewer_address_it_cannot_serve_on_is_one_error_line_not_a_hang():
    # viser, given a host that is not this machine's or a port out of range, tried a thousand ports and then waited
    # for ever (the training, play and sim2sim viewers alike); checked before viser is loaded.
    assert str(_run(["--viewer", "--viewer_port", "99999"]).code) == (
        "error: --viewer_port must be an int in [0, 65535] (0: any free port), got 99999")
    assert str(_run(["--viewer", "--viewer_host", "10.9.9.9"]).code).startswith(
        "error: the viewer cannot serve on host '10.9.9.9'")


@needs_contract
def test_a_run_shows_progress_on_stderr_and_keeps_stdout_json_without_torch(tmp_path):
    # Sixty-four robots for 8 s ran about 80 s in silence.
    import json
    import os
    import subprocess

    out = tmp_path / "m.json"
    recipe = Path(__file__).resolve().parents[1] / "recipes" / "sim2sim.py"
    proc = subprocess.run([sys.executable, "-X", "importtime", str(recipe), "--contract", str(CONTRACT), "--seconds",
                           "0.2", "--num_robots", "1", "--out", str(out)], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "PYTHONWARNINGS": "ignore"})
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert json.loads(proc.stdout) == json.loads(out.read_text())  # stdout is the JSON alone; --out the same
    assert "sim2sim, 1 robots" in proc.stderr and "0/50 [" in proc.stderr  # 0.2 s of 4 ms periods
    modules = {line.rsplit("|", 1)[1].strip() for line in proc.stderr.splitlines() if line.startswith("import time:")}
    assert "tqdm" in modules and not {"torch", "torchrl", "tensordict"} & modules


@needs_contract
@pytest.mark.parametrize("argv,message", [
    (["--push_speed", "3"], "--push_speed applies with --pushes N only, which is not given"),
    (["--push_kind", "force"], "--push_kind applies with --pushes N only"),
    (["--viewer_port", "8081"], "--viewer_port applies with --viewer only"),
])
def test_an_option_its_switch_is_missing_for_is_refused_not_ignored(argv, message, capsys):
    # Each ran as if it were not given: no kicks at 3 m/s, no viewer, and "pushes": null in the metrics.
    assert _run(argv).code == 2 and message in capsys.readouterr().err


@needs_contract
@pytest.mark.parametrize("seconds, when", [("0.02", "any"), ("7", "all")])
def test_pushes_in_a_run_that_ends_before_them_are_refused(seconds, when, capsys):
    # --pushes 3 --seconds 1 ran with no kick (they fall in 2-7 s) and reported the unpushed walk's survival, exit 0.
    assert _run(["--pushes", "3", "--seconds", seconds]).code == 2
    assert (f"--pushes 3 kicks each robot at random times in 2-7 s (kick j in the j-th share), but --seconds "
            f"{seconds} ends the run before {when} of them: pass --seconds 8 or more" in capsys.readouterr().err)


@needs_contract
def test_metrics_of_no_surviving_robot_are_null_in_strict_json(capsys, tmp_path):
    # A robot that fell in the first period has no speed or knee error: printed as NaN, which strict JSON readers
    # (and the contract's own rule) refuse.
    import json
    import shutil

    for suffix in (".json", ".onnx"):
        shutil.copy(CONTRACT.with_suffix(suffix), tmp_path / f"p{suffix}")
    contract = json.loads((tmp_path / "p.json").read_text())
    contract["policy"]["onnx_file"] = "p.onnx"
    contract["termination"]["min_neck_height"] = 3.0  # above the standing robot's neck: every robot ends at once
    (tmp_path / "p.json").write_text(json.dumps(contract))
    result = load_recipe("sim2sim").main(["--contract", str(tmp_path / "p.json"), "--seconds", "0.02",
                                          "--num_robots", "1"])
    printed = json.loads(capsys.readouterr().out, parse_constant=lambda name: pytest.fail(f"non-standard {name}"))
    assert result["survival"] == 0.0 and printed["knee_rms_rad"] is None


@needs_contract
def test_the_recipe_loads_the_policy_once_and_runs_the_runtime_it_checked(monkeypatch, capsys):
    # The recipe built a PolicyRuntime to check the policy before serving a page, and run_sim2sim loaded it again.
    from tocabi_torchrl.runtime import PolicyRuntime
    from tocabi_torchrl.runtime.mujoco_driver import run_sim2sim

    built = []
    init = PolicyRuntime.__init__

    def counting_init(self, *args, **kwargs):
        built.append(self)
        init(self, *args, **kwargs)

    monkeypatch.setattr(PolicyRuntime, "__init__", counting_init)
    argv = ["--contract", str(CONTRACT), "--seconds", "0.04", "--num_robots", "2", "--seed", "3"]
    result = load_recipe("sim2sim").main(argv)
    assert len(built) == 1
    result.pop("model")
    assert result == run_sim2sim(CONTRACT, seconds=0.04, num_robots=2, seed=3).as_dict()


@needs_contract
def test_robots_that_do_not_fit_in_memory_are_one_error_line_naming_the_option(monkeypatch):
    # A huge --num_robots ended in numpy's bare MemoryError traceback.
    recipe = load_recipe("sim2sim")

    def out_of_memory(*args, **kwargs):
        raise MemoryError

    monkeypatch.setattr(recipe, "run_sim2sim", out_of_memory)
    with pytest.raises(SystemExit) as info:
        recipe.main(["--contract", str(CONTRACT), "--seconds", "0.02", "--num_robots", "1000000000"])
    assert str(info.value.code) == ("error: not enough memory for 1,000,000,000 robots over 0.02 s on this machine: "
                                    "lower --num_robots (or --seconds)")
