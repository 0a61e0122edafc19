"""lab/analysis/solver_tolerance.py: Newton iterations and parity per solver tolerance."""

from __future__ import annotations

import doctest
import json

import mujoco
import pytest

pytest.importorskip("onnxruntime")

from lab.analysis import solver_tolerance


def test_docstring_examples_run():
    result = doctest.testmod(solver_tolerance)
    assert result.attempted >= 1 and result.failed == 0


def test_solving_restores_mj_step_even_after_an_error():
    step = mujoco.mj_step
    with pytest.raises(RuntimeError, match="boom"), solver_tolerance.solved_with(1e-6):
        assert mujoco.mj_step is not step
        raise RuntimeError("boom")
    assert mujoco.mj_step is step


def test_a_looser_tolerance_never_needs_more_iterations_and_the_model_own_is_the_parity_origin(tmp_path):
    """Two robots, 0.2 s: the model's own setting deviates 0 from itself; looser tolerances need no more iterations
    on the same robots (the solve stops earlier on every path) and move the parity sequence by less than 1e-3 rad
    down to 1e-5. The report names its command and is never written over."""
    out = tmp_path / "tol.json"
    solver_tolerance.main(["--num_robots", "2", "--seconds", "0.2", "--out", str(out)])
    report = json.loads(out.read_text())
    assert report["command"].startswith("PYTHONPATH=. python lab/analysis/solver_tolerance.py --num_robots 2")
    by = {(r["tolerance"], r["iterations"]): r for r in report["results"] if r["case"] == "walking"}
    assert by[None, None]["parity_deviation_rad"] == 0.0 and report["meta"]["model_tolerance"] == 1e-8
    own = [by[t, None]["own_per_period"] for t in (None, 1e-7, 1e-6, 1e-5, 1e-4)]
    assert own == sorted(own, reverse=True) and own[-1] < own[0]
    assert all(by[t, None]["parity_within_test"] for t in (1e-7, 1e-6, 1e-5))
    # A cap of 3 iterations stops solves the model's 20 would continue: fewer iterations in all.
    assert by[None, 3]["own_per_period"] < by[None, None]["own_per_period"]
    with pytest.raises(SystemExit):
        solver_tolerance.main(["--num_robots", "2", "--seconds", "0.2", "--out", str(out)])


@pytest.mark.slow  # three 8 s robust_1.0 runs of one robot on C MuJoCo
def test_the_caps_also_meet_the_robust_test_kicks():
    rows = solver_tolerance.measure_kicked(solver_tolerance.ROBUST_CONTRACT, 1)
    assert [(r["case"], r["iterations"]) for r in rows] == [("robust_1.0", None), ("robust_1.0", 4),
                                                             ("robust_1.0", 3)]
    assert all(0.0 <= r["survival"] <= 1.0 for r in rows)
