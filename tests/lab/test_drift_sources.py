"""lab/analysis/drift_sources.py: the split of the lateral drift into a turn and a sideways walk."""

from __future__ import annotations

import doctest
import json
import math

import pytest
import torch

from lab.analysis import drift_sources


def test_docstring_examples_run():
    result = doctest.testmod(drift_sources, optionflags=doctest.ELLIPSIS)
    assert result.attempted >= 3 and result.failed == 0


def test_the_two_parts_add_up_to_the_world_lateral_displacement():
    """Walking at a constant heading-frame velocity v with a constant yaw ψ moves the pelvis by R(ψ)·v·t; its world
    y is the sum of the two parts."""
    v, yaw, dt = torch.tensor([[0.5, -0.05], [0.3, 0.2]]), torch.tensor([0.2, -0.4]), 0.004
    turned, sideways = drift_sources.lateral_parts(v, yaw, dt)
    world_y = (v[:, 0] * torch.sin(yaw) + v[:, 1] * torch.cos(yaw)) * dt
    torch.testing.assert_close(turned + sideways, world_y)
    assert turned[0] > 0 > turned[1]  # turned left walks to +y, turned right to -y


def test_falls_are_binned_by_the_phase_of_their_last_alive_step():
    """Phase 0.5 is the first bin of the second half; phase just under 1 the last bin; robots that stayed up (NaN)
    are not counted."""
    phases = torch.tensor([0.5, 0.999, float("nan"), 0.0, 0.1])
    assert drift_sources.falls_by_phase(phases) == [1, 1, 0, 0, 0, 1, 0, 0, 0, 1]
    assert drift_sources.falls_by_phase(phases, bins=2) == [2, 2]


def test_groups_by_start_phase_keep_each_robot_once():
    values = torch.tensor([0.1, -0.2, 0.3, 0.05])
    groups = drift_sources.by_start(values, torch.tensor([0.5, 0.0, 0.5, 0.0]))
    assert sorted(groups) == ["0.000", "0.500"]
    assert sum(g["robots"] for g in groups.values()) == 4
    assert math.isclose(groups["0.500"]["mean"], 0.2) and math.isclose(groups["0.000"]["mean"], -0.075)


def test_a_short_case_on_a_shipped_policy_writes_its_report(tmp_path):
    """Two robots, 0.2 s, with and without the start velocities: the report holds both and the parts add up to the
    displacement; a second run never overwrites it."""
    from lab.benchmarks.robust_policies import POLICIES

    out = tmp_path / "drift.json"
    args = ["--checkpoint", str(POLICIES / "tocabi_walk_torque.pt"), "--num_envs", "2", "--seconds", "0.2",
            "--calm_start", "--out", str(out)]
    assert drift_sources.main(args) == 0
    report = json.loads(out.read_text())
    assert "--calm_start" in report["command"]
    moving, calm = report["results"]
    assert moving["calm_start"] is False and calm["calm_start"] is True
    for r in (moving, calm):
        assert set(r["lateral_m_at"]) == {"0.2 s"} and r["lateral_m_at"]["0.2 s"] == r["lateral_m"]
        parts = r["from_heading_m"]["mean"] + r["from_sideways_walk_m"]["mean"]
        assert abs(parts - r["lateral_m"]["mean"]) < 2e-3
        assert r["solver_iterations"] is None  # the test's solver, the model's own
        assert r["cycle_mean_error_mps"] is None  # 0.2 s: no step after a whole gait cycle
        falls = r["falls_by_phase_tenth"]
        assert len(falls) == 10 and sum(falls) == round((1 - r["survival"]) * 2)
    with pytest.raises(SystemExit):
        drift_sources.main(args)


def test_train_solver_runs_the_cap_the_run_trained_with(tmp_path):
    """A checkpoint saved as if trained with the solver capped at 4 iterations: --train_solver runs its case on that
    cap and says so in the report; without the flag the report names none (the model's solver)."""
    from lab.benchmarks.robust_policies import POLICIES

    saved = torch.load(POLICIES / "tocabi_walk_torque.pt", map_location="cpu", weights_only=True)
    saved["config"]["env"]["sim"]["solver_iterations"] = 4
    capped = tmp_path / "capped.pt"
    torch.save(saved, capped)
    for flag, expected in ((["--train_solver"], 4), ([], None)):
        out = tmp_path / f"drift{len(flag)}.json"
        assert drift_sources.main(["--checkpoint", str(capped), "--num_envs", "2", "--seconds", "0.1", *flag,
                                   "--out", str(out)]) == 0
        assert json.loads(out.read_text())["results"][0]["solver_iterations"] == expected


def test_model_runs_the_case_on_another_mjcf(tmp_path):
    """--model runs the checkpoint on the given MJCF (the exactly symmetric copy) and names it in the report; the
    checkpoint's own model is named by none; a missing file is refused before any robot runs."""
    from lab.analysis.symmetric_model import main as write_symmetric
    from lab.benchmarks.robust_policies import POLICIES

    model = tmp_path / "sym.xml"
    assert write_symmetric(["--out", str(model)]) == 0
    ckpt = str(POLICIES / "tocabi_walk_torque.pt")
    reports = {}
    for name, flag in (("own", []), ("sym", ["--model", str(model)])):
        out = tmp_path / f"{name}.json"
        assert drift_sources.main(["--checkpoint", ckpt, "--num_envs", "2", "--seconds", "0.3", *flag,
                                   "--out", str(out)]) == 0
        reports[name] = json.loads(out.read_text())["results"][0]
    assert reports["own"].pop("model") is None and reports["sym"].pop("model") == str(model)
    # Other inertials, other motion: the same robots, started alike, walk otherwise.
    assert reports["own"] != reports["sym"]
    with pytest.raises(SystemExit, match="2"):
        drift_sources.main(["--checkpoint", ckpt, "--model", str(tmp_path / "none.xml")])
