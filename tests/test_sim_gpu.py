"""WarpSim on CUDA: recorded CUDA graphs, no host synchronisation in step/reset, standing sanity. Skipped without CUDA."""

from __future__ import annotations

import pytest
import torch
import warp as wp

from tocabi_torchrl import robot
from tocabi_torchrl.sim import SimConfig, WarpSim

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not (torch.cuda.is_available() and wp.is_cuda_available()), reason="needs CUDA"),
]

N = 64
LEGS = slice(0, robot.NUM_LEG_JOINTS)


@pytest.fixture(scope="module")
def sim() -> WarpSim:
    return WarpSim(SimConfig(num_worlds=N, device="cuda"))


def _inputs(sim: WarpSim):
    dev = sim.device
    qpos = torch.as_tensor(robot.INIT_QPOS, dtype=torch.float32, device=dev)
    ctrl = torch.zeros(robot.NUM_JOINTS, device=dev)
    ctrl[robot.NUM_LEG_JOINTS :] = torch.as_tensor(robot.INIT_JOINT_POS[robot.NUM_LEG_JOINTS :], device=dev)
    gains = [torch.as_tensor(x, dtype=torch.float32, device=dev) for x in (robot.LEG_KP, robot.LEG_KV)]
    q0 = torch.as_tensor(robot.INIT_JOINT_POS[LEGS], dtype=torch.float32, device=dev)
    return qpos, torch.zeros(sim.nv, device=dev), ctrl, gains, q0


def _pd_hold(sim: WarpSim, gains, q0) -> None:
    kp, kv = gains
    sim.ctrl[:, LEGS] = kp * (q0 - sim.qpos[:, 7:19]) - kv * sim.qvel[:, 6:18]


def test_step_and_reset_run_as_cuda_graphs_without_host_sync(sim):
    assert sim._step_graph.graph is not None and sim._reset_graph.graph is not None
    qpos, qvel, ctrl, gains, q0 = _inputs(sim)
    everyone = torch.ones(N, dtype=torch.bool, device=sim.device)
    some = torch.arange(N, device=sim.device) % 3 == 0
    sim.reset(everyone, qpos, qvel, ctrl)
    sim.step()  # first launches outside the check
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(5):
            _pd_hold(sim, gains, q0)
            sim.step()
            healthy_or_reset = some | ~sim.healthy  # device-side decisions only
            sim.reset(healthy_or_reset, qpos, qvel, ctrl)
        sim.forward()
    finally:
        torch.cuda.set_sync_debug_mode(0)
    torch.cuda.synchronize()
    assert sim.healthy.all()


def _stand(sim: WarpSim, steps: int):
    """Reset every world to the initial pose and PD-hold it for ``steps`` control steps; returns ``_inputs``."""
    qpos, qvel, ctrl, gains, q0 = inputs = _inputs(sim)
    sim.reset(torch.ones(N, dtype=torch.bool, device=sim.device), qpos, qvel, ctrl)
    for _ in range(steps):
        _pd_hold(sim, gains, q0)
        sim.step()
    return inputs


def test_standing_on_the_gpu(sim):
    _stand(sim, 250)
    assert sim.foot_contact.all() and sim.healthy.all()
    assert not sim.forbidden_ground_contact.any() and not sim.self_collision.any()
    m = sim.mj_model
    feet = [m.body(b).id for b in robot.FOOT_BODIES]
    weight_above = float((m.body_subtreemass[0] - m.body_subtreemass[feet].sum()) * -m.opt.gravity[2])
    fz = sim.foot_force[:, :, 2].sum(dim=1)
    assert torch.allclose(-fz, torch.full_like(fz, weight_above), rtol=0.05)


def test_masked_reset_keeps_other_worlds_bit_identical_on_the_gpu(sim):
    qpos, qvel, ctrl, _, _ = _stand(sim, 20)
    views = ("qpos", "qvel", "ctrl", "sensordata", "xpos", "xquat", "foot_contact", "healthy")
    before = {k: getattr(sim, k).clone() for k in views}
    mask = torch.arange(N, device=sim.device) % 2 == 1
    sim.reset(mask, qpos, qvel, ctrl)
    for k in views:
        assert torch.equal(getattr(sim, k)[~mask], before[k][~mask]), k
    assert torch.equal(sim.qpos[mask], qpos.expand(int(mask.sum()), -1))


def test_graph_follows_the_current_torch_stream(sim):
    """Work queued on a side stream is ordered with the graph launched on it."""
    qpos, qvel, ctrl, gains, q0 = _inputs(sim)
    side = torch.cuda.Stream(sim.device)
    side.wait_stream(torch.cuda.current_stream(sim.device))
    with torch.cuda.stream(side):
        high = qpos.clone()
        high[2] = 3.0
        sim.reset(torch.ones(N, dtype=torch.bool, device=sim.device), high, qvel, ctrl)
        z = sim.base_pos[:, 2].clone()
    torch.cuda.current_stream(sim.device).wait_stream(side)
    assert torch.allclose(z, torch.full_like(z, 3.0))


def test_capture_id_is_read_from_the_driver():
    """The joined capture's safety check reads CUDA's capture id through the driver API: 0 outside a capture, one
    non-zero id for the whole of a torch capture (the check would be skipped silently if the call failed)."""
    from tocabi_torchrl.sim.graph import _capture_id

    stream = wp.stream_from_torch(torch.cuda.current_stream())
    assert _capture_id(stream) == 0
    x = torch.zeros(4, device="cuda")
    graph = torch.cuda.CUDAGraph()
    side = torch.cuda.Stream()
    with torch.cuda.stream(side):
        inner = wp.stream_from_torch(side)
        with torch.cuda.graph(graph, stream=side):
            first = _capture_id(inner)
            x += 1
            second = _capture_id(inner)
    assert first is not None and first > 0 and first == second


def test_recorded_graph_refuses_a_capture_that_does_not_hold_it(sim):
    """Inside a torch capture the physics must be held by cuda_graphs.capture_graph (joined or segmented), never
    launched as a nested graph by accident. Last in this module: the refused capture leaves an empty graph."""
    graph = torch.cuda.CUDAGraph()
    with pytest.raises(RuntimeError, match="does not hold it"), torch.cuda.graph(graph):
        sim.step()
