"""Engine parity: C MuJoCo (float64, MujocoSim) and mujoco-warp (float32, WarpSim on warp's CPU device) follow the
same trajectory: joints within 5e-3 rad and identical foot contact flags at every one of 25 policy steps.

Measured curves: ``docs/benchmarks/engine_parity.md`` (``python lab/benchmarks/engine_parity.py``).
"""

from __future__ import annotations

import pytest

from lab.sim_measure.parity import engine_parity

STEPS = 25


@pytest.mark.parametrize(
    "perturbation, drop",
    [(0.02, 0.0), (0.1, 0.0), (0.02, 0.01)],
    ids=["standing-2%", "standing-10%", "dropped-1cm-2%"],
)
def test_engines_agree_over_25_policy_steps(perturbation, drop):
    trace = engine_parity(STEPS, seed=0, perturbation=perturbation, drop=drop)
    assert trace.max_joint_diff.shape == (STEPS,)
    assert trace.max_joint_diff.max() < 5e-3, trace.max_joint_diff
    assert trace.contact_agreement.all(), (trace.foot_contact_mujoco, trace.foot_contact_warp)
    # The flags must change during the run (the feet touch down), or their agreement would prove little.
    assert not trace.foot_contact_mujoco[0].any() and trace.foot_contact_mujoco[-1].all()
    assert trace.base_pos_diff.max() < 1e-3
