"""recipes/sim2sim.py --sensor FIELD=VALUE: sensor biases and noise on top of --randomize's set."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

pytest.importorskip("onnxruntime")

from recipe_runner import load_recipe

CONTRACT = Path(__file__).resolve().parents[1] / "assets" / "policies" / "tocabi_walk_ppo.json"
needs_contract = pytest.mark.skipif(not CONTRACT.is_file(), reason="shipped policy contract not present")


@pytest.mark.parametrize("item, message", [
    ("joint_pos_bias", "--sensor 'joint_pos_bias': give FIELD=VALUE"),
    ("=0.1", "--sensor '=0.1': give FIELD=VALUE"),
    ("pelvis_noise=0.1", "no sensor field 'pelvis_noise'; the fields are joint_pos_bias, "),
    ("joint_pos_bias=small", "'small' is not a number"),
    ("base_lin_vel_noise_clip=off", "'off' is not a number (or none: no clip)"),
    ("base_lin_vel_noise_std=nan", "--sensor base_lin_vel_noise_std must be a finite number >= 0 (0 = off), got nan"),
    ("joint_pos_bias=-0.1", "--sensor joint_pos_bias must be a finite number >= 0"),
    ("base_ang_vel_noise_clip=0", "--sensor base_ang_vel_noise_clip must be a finite number > 0"),
    ("joint_pos_bias=0.1 joint_pos_bias=0.2", "joint_pos_bias is given twice; give each field once"),
    ("joint_pos_bias=0.1 --seed 1 --sensor joint_pos_bias=0.2", "joint_pos_bias is given twice"),
])
def test_a_bad_sensor_item_is_refused_before_any_file_is_read(item, message, capsys, tmp_path):
    with pytest.raises(SystemExit) as info:
        load_recipe("sim2sim").main(["--contract", str(tmp_path / "missing.json"), "--sensor", *item.split()])
    assert info.value.code == 2 and message in capsys.readouterr().err


@needs_contract
def test_sensor_items_change_the_set_field_by_field_and_the_metrics_say_so(capsys):
    from tocabi_torchrl.runtime.mujoco_driver import run_sim2sim
    from tocabi_torchrl.runtime.randomization import Randomization, SensorSettings

    argv = ["--contract", str(CONTRACT), "--seconds", "0.2", "--num_robots", "2", "--seed", "5"]
    # Two --sensor options add up (the second does not replace the first).
    given = load_recipe("sim2sim").main([*argv, "--sensor", "joint_pos_noise_std=0.01", "--vx", "0.5", "--sensor",
                                         "joint_pos_noise_clip=none"])
    plain = load_recipe("sim2sim").main(argv)
    capsys.readouterr()
    # The run is the driver's with the nominal set's sensors so changed, and unlike the run without the option.
    sensors = dataclasses.replace(SensorSettings(), joint_pos_noise_std=0.01, joint_pos_noise_clip=None)
    expected = run_sim2sim(CONTRACT, seconds=0.2, num_robots=2, seed=5,
                           randomize=Randomization(sensors=sensors)).as_dict()
    assert given["per_robot_forward_m"] == expected["per_robot_forward_m"] != plain["per_robot_forward_m"]
    # The metrics name the set and the changed fields, where the driver alone would say "custom".
    assert expected["perturbations"]["randomize"] == "custom"
    assert given["perturbations"]["randomize"] == "none"
    assert given["perturbations"]["sensor"] == {"joint_pos_noise_std": 0.01, "joint_pos_noise_clip": None}
    assert "sensor" not in plain["perturbations"]


@needs_contract
@pytest.mark.parametrize("item, message", [
    # This policy does not read the pelvis velocity: noise on it would change nothing and look like a result.
    ("base_lin_vel_noise_std=0.01",
     "--sensor base_lin_vel_noise_std: this policy does not observe that signal (it observes base_rpy, "),
    # It would change nothing, yet the metrics would list it among the perturbations.
    ("joint_vel_noise_clip=0.1",
     "--sensor joint_vel_noise_clip clips a noise that is off in --randomize none and not set: give "
     "joint_vel_noise_std too"),
])
def test_a_sensor_item_that_would_change_nothing_is_one_error_line(item, message):
    with pytest.raises(SystemExit) as info:
        load_recipe("sim2sim").main(["--contract", str(CONTRACT), "--seconds", "0.02", "--num_robots", "1",
                                     "--sensor", item])
    assert message in str(info.value.code)
