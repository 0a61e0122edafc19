"""The buffer measurement's count of convex-collision candidates (lab.sim_measure.measure_buffers, the number behind
``sim.buffers.NCCDMAX``) replicates mujoco-warp's broadphase: with the plane pairs counted the same way, it adds up to
the broadphase's own pair count in every substep, for robots standing and tangled."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lab.sim_measure.measure_buffers import ConvexCandidates, _scenario_state


def _plane_candidates(mj, pairs: np.ndarray, xpos: np.ndarray, xmat: np.ndarray) -> np.ndarray:
    """(N,) pairs with the ground plane that mujoco-warp's plane filter passes (the geom's bounding sphere reaches
    the plane, margins included)."""
    plane = mj.geom_rbound == 0.0
    rows = pairs[plane[pairs[:, 0]] | plane[pairs[:, 1]]]
    p, g = np.where(plane[rows[:, 0]], rows[:, 0], rows[:, 1]), np.where(plane[rows[:, 0]], rows[:, 1], rows[:, 0])
    margin = (mj.geom_margin + mj.geom_gap)[p] + (mj.geom_margin + mj.geom_gap)[g]
    dist = ((xpos[:, g] - xpos[:, p]) * xmat[:, p][..., :, 2]).sum(-1)  # the plane normal: its z axis
    return (dist <= mj.geom_rbound[g] + margin).sum(1)


@pytest.mark.parametrize("scenario", ["standing", "tangled"])
def test_convex_and_plane_candidates_add_up_to_the_broadphase_count(scenario):
    import mujoco_warp as mjw
    import warp as wp

    from tocabi_torchrl.sim import SimConfig, WarpSim

    n = 4
    sim = WarpSim(SimConfig(num_worlds=n, nconmax=160, njmax=400))
    qpos = torch.as_tensor(_scenario_state(scenario, n, np.random.default_rng(1)), dtype=torch.float32)
    sim.reset(torch.ones(n, dtype=torch.bool), qpos, torch.zeros(sim.nv))
    m, d, mj = sim.wp_model, sim.wp_data, sim.mj_model
    pairs = m.nxn_geom_pair_filtered.numpy()
    convex = ConvexCandidates(mj, pairs)
    # Every filtered pair is a plane pair or a convex one: the two counts cover the broadphase.
    plane = mj.geom_rbound == 0.0
    assert len(convex.pairs) + int((plane[pairs[:, 0]] | plane[pairs[:, 1]]).sum()) == len(pairs)
    seen = 0
    for _ in range(6):
        mjw.step(m, d)  # collision ran on these poses; the step then integrated qpos only
        wp.synchronize_device(sim.wp_device)
        xpos, xmat = d.geom_xpos.numpy(), d.geom_xmat.numpy().reshape(n, -1, 3, 3)
        counts = convex.count(xpos, xmat)
        total = int(counts.sum() + _plane_candidates(mj, pairs, xpos, xmat).sum())
        assert total == int(d.ncollision.numpy()[0])
        seen += int(counts.sum())
    assert (seen > 0) == (scenario == "tangled")  # standing robots send no pair to the convex narrowphase
