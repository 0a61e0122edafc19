"""lab/analysis/substep_iterations.py: solver iterations per substep with and without the actuators' delay."""

from __future__ import annotations

import doctest
import json

import mujoco
import pytest

pytest.importorskip("onnxruntime")

from lab.analysis import substep_iterations


def test_docstring_examples_run():
    result = doctest.testmod(substep_iterations)
    assert result.attempted >= 2 and result.failed == 0


def test_counting_restores_mj_step_even_after_an_error():
    step = mujoco.mj_step
    with pytest.raises(RuntimeError, match="boom"), substep_iterations.counted_steps():
        assert mujoco.mj_step is not step
        raise RuntimeError("boom")
    assert mujoco.mj_step is step


def test_a_delay_moves_the_costly_substep_and_a_whole_period_keeps_it(tmp_path):
    """Two robots, 0.2 s: without a delay the torque jump makes substep 0 the costliest; a delay of one period
    brings the jump back there; the TOCABI lab's delay moves it off substep 0 (its warm start there is the solution
    of the same torque), on a one-period grid onto one substep for every robot, on a two-substep grid onto the even
    substeps, and averaged per period back onto
    substep 0. The report names its command and is never written over."""
    out = tmp_path / "it.json"
    substep_iterations.main(["--num_robots", "2", "--seconds", "0.2", "--out", str(out)])
    report = json.loads(out.read_text())
    assert report["command"].startswith("PYTHONPATH=. python lab/analysis/substep_iterations.py --num_robots 2")
    by = {r["variant"]: r for r in report["results"]}
    none, period, lab = by["no delay"], by["delay of one period"], by["tocabi_lab delay"]
    grid = by["tocabi_lab delay, one-period grid"]
    for r in (none, period):
        assert r["mean_per_substep"][0] == max(r["mean_per_substep"]) and len(r["mean_per_substep"]) == 8
    assert lab["mean_per_substep"][0] < min(none["mean_per_substep"])
    # On the grid (4, 12, 20 substeps) every robot's jump lands in substep 4.
    assert grid["delay_stride"] == 8 and grid["mean_per_substep"][4] == max(grid["mean_per_substep"])
    # On the two-substep grid (4, 6, ..., 20) the jumps land in even substeps only: the costliest substep is even.
    two = by["tocabi_lab delay, two-substep grid"]
    assert two["delay_stride"] == 2 and two["mean_per_substep"].index(max(two["mean_per_substep"])) % 2 == 0
    # Averaged over each period, the torque changes only at the period's start: substep 0 is the costliest again.
    mean = by["tocabi_lab delay, averaged per period"]
    assert mean["delay_average"] and mean["mean_per_substep"][0] == max(mean["mean_per_substep"])
    for r in report["results"]:
        assert r["lockstep_per_period"] >= r["own_per_period"] > 0 and r["survival"] == 1.0
    with pytest.raises(SystemExit):
        substep_iterations.main(["--num_robots", "2", "--seconds", "0.2", "--out", str(out)])


def test_an_iteration_cap_bounds_every_substep_and_is_recorded(tmp_path, capsys):
    """--iterations caps the solver as env.sim.solver_iterations does: no substep of any robot takes more, the
    lockstep sum of a period is at most cap x substeps, and the report's meta names the cap; a cap below 1 is
    refused before anything runs."""
    out = tmp_path / "cap.json"
    substep_iterations.main(["--num_robots", "2", "--seconds", "0.2", "--iterations", "2", "--out", str(out)])
    report = json.loads(out.read_text())
    assert report["meta"]["solver_iterations"] == 2 and "--iterations 2" in report["command"]
    for r in report["results"]:
        assert max(r["lockstep_per_substep"]) <= 2 and r["lockstep_per_period"] <= 2 * 8
    capsys.readouterr()
    with pytest.raises(SystemExit):
        substep_iterations.main(["--num_robots", "2", "--seconds", "0.2", "--iterations", "0"])
    assert "--iterations must be >= 1, got 0" in capsys.readouterr().err
