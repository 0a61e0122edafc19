"""Both physics backends implement the one interface of sim/backend.py: members, tensor shapes, dtypes and devices,
and tensors that are updated in place (never rebound), as captured CUDA graphs need."""

from __future__ import annotations

import inspect

import pytest
import torch

from tocabi_torchrl import robot
from tocabi_torchrl.sim import SIM_TENSORS, MujocoSim, SimBackend, SimConfig, WarpSim, check_backend
from tocabi_torchrl.sim.views import SimViews

N = 2


@pytest.fixture(scope="module", params=["warp", "mujoco"])
def sim(request):
    # mujoco-warp on its CPU device (as tests/test_sim.py builds it) and C MuJoCo.
    cls = WarpSim if request.param == "warp" else MujocoSim
    return cls(SimConfig(num_worlds=N, device="cpu"))


def test_implements_the_interface(sim):
    assert isinstance(sim, SimBackend) and isinstance(sim, SimViews)
    check_backend(sim)
    assert sim.num_worlds == N and sim.device == torch.device("cpu")
    assert (sim.nq, sim.nv, sim.nu) == (7 + robot.NUM_JOINTS, 6 + robot.NUM_JOINTS, robot.NUM_JOINTS)
    assert sim.control_dt == pytest.approx(sim.physics_dt * sim.config.substeps)
    # The table's shapes, spelled out for the shipped model.
    assert sim.qpos.shape == (N, 40) and sim.ctrl.shape == (N, 33) and sim.foot_force.shape == (N, 2, 3)
    assert sim.healthy.dtype == torch.bool and sim.overflow.dtype == torch.int32
    assert sim.xquat.shape == (N, sim.mj_model.nbody, 4)


def test_tensors_are_updated_in_place(sim):
    buffers = {t.name: getattr(sim, t.name) for t in SIM_TENSORS}
    pointers = {name: value.data_ptr() for name, value in buffers.items()}
    before = sim.qpos.clone()
    qpos = torch.as_tensor(robot.INIT_QPOS, dtype=torch.float32)
    sim.reset(torch.ones(N, dtype=torch.bool), qpos, torch.zeros(sim.nv))
    sim.ctrl[:, robot.LEGS] = 50.0
    sim.step()
    sim.forward()
    assert not torch.equal(sim.qpos, before), "the step should have moved the robot"
    for t in SIM_TENSORS:
        value = getattr(sim, t.name)
        assert value is buffers[t.name] and value.data_ptr() == pointers[t.name], f"{t.name} was rebound"
    check_backend(sim)


def test_reset_takes_a_state_that_requires_grad_as_data(sim):
    # MujocoSim failed in numpy() ("Can't call numpy() on Tensor that requires grad"), and WarpSim's staging
    # buffers were left in the caller's autograd graph: a start state is data.
    qpos = torch.as_tensor(robot.INIT_QPOS, dtype=torch.float32).expand(N, -1).clone()
    qvel, ctrl = torch.zeros(N, sim.nv), torch.full((N, sim.nu), 0.5)
    mask = torch.ones(N, dtype=torch.bool)
    sim.reset(mask, qpos, qvel, ctrl)
    want = {t.name: getattr(sim, t.name).clone() for t in SIM_TENSORS}
    sim.reset(mask, *(x.clone().requires_grad_() for x in (qpos, qvel, ctrl)))
    for t in SIM_TENSORS:
        assert torch.equal(getattr(sim, t.name), want[t.name]), t.name
    held = [k for k, v in vars(sim).items() if isinstance(v, torch.Tensor) and v.requires_grad]
    assert not held and not any(getattr(sim, t.name).requires_grad for t in SIM_TENSORS), held


def test_methods_share_one_signature():
    for name in ("step", "forward", "reset", "check_overflow"):
        want = inspect.signature(getattr(SimBackend, name))
        for cls in (WarpSim, MujocoSim):
            got = inspect.signature(getattr(cls, name))
            assert list(got.parameters) == list(want.parameters), (cls.__name__, name)


def test_an_incomplete_backend_is_refused(sim):
    class NoStep(SimViews):  # the abstract methods make a backend that lacks one impossible to build
        def forward(self): ...
        def reset(self, mask, qpos, qvel, ctrl=None): ...
        def check_overflow(self): ...

    with pytest.raises(TypeError, match="step"):
        NoStep()

    class Partial:
        num_worlds = N

    assert not isinstance(Partial(), SimBackend)
    with pytest.raises(TypeError, match=r"Partial is not a physics backend: it lacks \['config'"):
        check_backend(Partial())


def test_a_wrong_tensor_is_named(sim, monkeypatch):
    monkeypatch.setattr(type(sim), "healthy", property(lambda self: torch.zeros(N, dtype=torch.int64)))
    with pytest.raises(ValueError, match=r"healthy is \(2,\) torch.int64 on cpu, the interface says \(2,\) torch.bool"):
        check_backend(sim)


def test_the_default_health_mask_is_mujoco_warps_overflow_bits():
    # sim.config writes the mask as a number, so that the config tree reads without mujoco-warp.
    from tocabi_torchrl.sim.config import DEFAULT_HEALTH_OVERFLOW_MASK
    from tocabi_torchrl.sim.health import HEALTH_OVERFLOW_MASK

    assert DEFAULT_HEALTH_OVERFLOW_MASK == int(HEALTH_OVERFLOW_MASK) == SimConfig().health_overflow_mask
