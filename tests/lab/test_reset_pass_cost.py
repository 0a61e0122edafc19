"""lab.benchmarks.reset_pass_cost on warp's CPU device at toy size: what it copies, its report, its refusals."""

from __future__ import annotations

import json

import pytest

from lab.benchmarks import reset_pass_cost


def test_the_report_times_the_pass_over_every_world_and_over_each_subset(tmp_path):
    reset_pass_cost.main(["--device", "cpu", "--num_envs", "4", "--subsets", "1", "2", "--steps", "1",
                          "--out", str(tmp_path), "--name", "rp"])
    r = json.loads((tmp_path / "rp.json").read_text())["result"]
    assert r["num_envs"] == 4 and r["pass_all_ms"] > 0
    assert sorted(r["subsets"]) == ["1", "2"]
    for s in r["subsets"].values():
        assert s["pass_ms"] > 0 and s["scatter_all_ms"] > 0
        # qpos, qvel, the kinematics, the mass matrix and the constraint rows at least; the same set for every size.
        assert s["arrays"] == r["subsets"]["1"]["arrays"] > 50 and s["bytes_per_world"] > 10_000
    page = (tmp_path / "rp.md").read_text()
    assert "4 (every world)" in page and f"copy of all {r['subsets']['1']['arrays']} per-world arrays" in page


def test_the_copied_arrays_are_the_per_world_ones_the_constraint_rows_included():
    import mujoco_warp as mjw
    import warp as wp

    from tocabi_torchrl import robot
    from tocabi_torchrl.sim import add_contact_sensors

    mj = add_contact_sensors(robot.load_spec()).compile()
    with wp.ScopedDevice("cpu"):
        d = mjw.make_data(mj, nworld=3, nconmax=8, njmax=64)
    found = reset_pass_cost.per_world_arrays(d, 3)
    assert {"qpos", "qvel", "xpos", "qM" if "qM" in found else "M", "efc.J", "efc.id", "nefc"} <= set(found)
    assert all(a.shape[0] == 3 for a in found.values())
    assert not any(name.startswith("contact.") for name in found)  # one buffer for all worlds: not per world


@pytest.mark.parametrize("args", [["--subsets", "9"], ["--subsets", "0"], ["--steps", "0"]])
def test_bad_sizes_are_refused_in_one_line(args, capsys):
    with pytest.raises(SystemExit) as err:
        reset_pass_cost.main(["--device", "cpu", "--num_envs", "8", *args])
    assert err.value.code == 2 and "--subsets size in [1, --num_envs]" in capsys.readouterr().err


def test_resets_time_the_simulators_reset_both_ways_and_refuse_bad_counts(tmp_path, capsys):
    reset_pass_cost.main(["--device", "cpu", "--num_envs", "6", "--subsets", "2", "--steps", "1", "--resets", "0",
                          "6", "--capacity", "2", "--out", str(tmp_path), "--name", "rs"])
    data = json.loads((tmp_path / "rs.json").read_text())
    rows = data["resets"]["rows"]
    assert data["resets"]["capacity"] == 2 and [r["resets"] for r in rows] == [0, 6]
    assert all(r["every_world_ms"] > 0 and r["small_pass_ms"] > 0 for r in rows)
    assert "small pass, 2 worlds at a time [ms]" in (tmp_path / "rs.md").read_text()
    for bad in (["--resets", "7", "--capacity", "2"], ["--resets", "1"]):  # more than the envs; no rule below 4,096
        with pytest.raises(SystemExit):
            reset_pass_cost.main(["--device", "cpu", "--num_envs", "6", "--subsets", "2", *bad])
        assert "--resets counts must be in [0, --num_envs]" in capsys.readouterr().err
