"""The interface of a physics backend: what ``TocabiWalk`` (and anything else) may use of a simulator.

:class:`~tocabi_torchrl.sim.WarpSim` (mujoco-warp) and :class:`~tocabi_torchrl.sim.MujocoSim` (C MuJoCo) implement it
through their common base :class:`~tocabi_torchrl.sim.views.SimViews`. :class:`SimBackend` spells it out as a
``typing.Protocol`` (for type checkers and ``isinstance``), :data:`SIM_TENSORS` gives every tensor's shape, dtype and
unit, and :func:`check_backend` checks an object against both, with an error naming what is wrong.

The tensors are the simulator's own buffers, created once: a backend overwrites them in place on every
:meth:`~SimBackend.step` / :meth:`~SimBackend.reset` / :meth:`~SimBackend.forward` and never rebinds them, so a
captured CUDA graph that reads or writes them stays valid (``tests/test_sim_backend.py`` checks this).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import mujoco
import numpy as np
import torch

from .config import SimConfig
from .contacts import ContactLayout

__all__ = ["SimBackend", "SimTensor", "SIM_TENSORS", "check_backend"]


@dataclass(frozen=True)
class SimTensor:
    """One tensor of the interface: ``shape`` in named sizes (``"N"`` worlds, ``"nq"``, ``"nv"``, ``"nu"``,
    ``"nbody"``, ``"nsensordata"``, ``"ncontact"`` contact sensors, ``"nC"`` non-zeros of the inertia matrix) and
    ints."""

    name: str
    shape: tuple[str | int, ...]
    dtype: torch.dtype
    meaning: str


_F32, _BOOL = torch.float32, torch.bool

#: Every tensor a backend exposes, on its ``device``.
SIM_TENSORS: tuple[SimTensor, ...] = (
    SimTensor("qpos", ("N", "nq"), _F32, "base position [m], base quaternion (w, x, y, z), joints [rad]"),
    SimTensor("qvel", ("N", "nv"), _F32, "base linear (world) [m/s], angular (local) [rad/s], joints [rad/s]"),
    SimTensor("ctrl", ("N", "nu"), _F32, "actuator controls; writing them is how actions reach the physics"),
    SimTensor("sensordata", ("N", "nsensordata"), _F32, "every sensor of the model"),
    SimTensor("time", ("N",), _F32, "simulated time since the world's last reset [s]"),
    SimTensor("xpos", ("N", "nbody", 3), _F32, "body frame origins in the world [m]"),
    SimTensor("xquat", ("N", "nbody", 4), _F32, "body orientations in the world (w, x, y, z)"),
    SimTensor("base_pos", ("N", 3), _F32, "pelvis origin [m]"),
    SimTensor("base_quat", ("N", 4), _F32, "pelvis orientation (w, x, y, z)"),
    SimTensor("neck_pos", ("N", 3), _F32, "Neck_Link origin [m]"),
    SimTensor("neck_quat", ("N", 4), _F32, "Neck_Link orientation (w, x, y, z)"),
    SimTensor("foot_pos", ("N", 2, 3), _F32, "Foot_Link origins in the world [m], [left, right]"),
    SimTensor("foot_force", ("N", 2, 3), _F32, "foot F/T force, site frame [N], [left, right]"),
    SimTensor("foot_torque", ("N", 2, 3), _F32, "foot F/T torque, site frame [N·m], [left, right]"),
    SimTensor("contact_counts", ("N", "ncontact"), _F32, "contact-sensor counts (columns: contact_layout.names)"),
    SimTensor("foot_contact", ("N", 2), _BOOL, "a foot touches the ground or an obstacle, [left, right]"),
    SimTensor("forbidden_ground_contact", ("N",), _BOOL,
              "a robot.GROUND_FORBIDDEN_BODIES body touches the ground or a scene body (obstacle)"),
    SimTensor("self_collision", ("N",), _BOOL, "two robot.SELF_COLLISION_BODIES bodies touch"),
    SimTensor("obstacle_contact", ("N", 2), _BOOL,
              "a foot touches a scene body outside the robot other than the world body (an obstacle), [left, right]"),
    SimTensor("healthy", ("N",), _BOOL, "finite state and no buffer overflow or health warning"),
    SimTensor("overflow", ("N",), torch.int32, "backend overflow/warning bits (sticky until the world resets)"),
    SimTensor("applied_actuator_force", ("N", "nu"), _F32, "actuator forces applied in the last substep [N·m]"),
    SimTensor("mass_matrix", ("N", "nC"), _F32, "joint-space inertia M(q) of the current state (armature included) "
              "in MuJoCo's sparse layout: lower triangle, rows by mj_model.M_rowadr/M_rownnz, columns M_colind "
              "(sim.inertia.dense_block reads a dense block of it)"),
    SimTensor("xfrc_applied", ("N", "nbody", 6), _F32, "external force [N] and torque [N·m] on each body, in the world "
              "frame at the body's centre of mass; an input like ctrl (held until changed, zeroed at reset)"),
    SimTensor("qfrc_bias", ("N", "nv"), _F32, "bias force c(q, q̇) of the current state: gravity, Coriolis and "
              "centrifugal [N, N·m]: the free joint's first 3 entries are forces [N], the rest torques [N·m] "
              "(M·q̈ + c = applied + passive + constraint forces)"),
)

#: The plain attributes and the methods of the interface (the tensors are :data:`SIM_TENSORS`).
_ATTRIBUTES = ("config", "num_worlds", "device", "nq", "nv", "nu", "mj_model", "contact_layout", "physics_dt",
               "control_dt", "world_mocap_pos")
_METHODS = ("step", "forward", "reset", "check_overflow")


@runtime_checkable
class SimBackend(Protocol):
    """N worlds of one MuJoCo model, advanced together, with their state as torch tensors (see :data:`SIM_TENSORS`).

    ``isinstance(x, SimBackend)`` checks that the members exist; :func:`check_backend` also checks the tensors.
    """

    config: SimConfig
    num_worlds: int  #: N
    device: torch.device
    nq: int
    nv: int
    nu: int
    mj_model: mujoco.MjModel  #: the compiled model (contact sensors included)
    contact_layout: ContactLayout
    physics_dt: float  #: [s] one physics step
    control_dt: float  #: [s] one :meth:`step`, ``substeps`` physics steps
    #: (N, nmocap, 3) float64 mocap-body positions [m] each world starts and resets with (the constructor's
    #: ``mocap_pos``: the env's obstacles), or ``None`` where every world keeps the model's
    world_mocap_pos: np.ndarray | None

    qpos: torch.Tensor
    qvel: torch.Tensor
    ctrl: torch.Tensor
    sensordata: torch.Tensor
    time: torch.Tensor
    xpos: torch.Tensor
    xquat: torch.Tensor
    base_pos: torch.Tensor
    base_quat: torch.Tensor
    neck_pos: torch.Tensor
    neck_quat: torch.Tensor
    foot_pos: torch.Tensor
    foot_force: torch.Tensor
    foot_torque: torch.Tensor
    contact_counts: torch.Tensor
    foot_contact: torch.Tensor
    forbidden_ground_contact: torch.Tensor
    self_collision: torch.Tensor
    obstacle_contact: torch.Tensor
    healthy: torch.Tensor
    overflow: torch.Tensor
    applied_actuator_force: torch.Tensor
    mass_matrix: torch.Tensor
    qfrc_bias: torch.Tensor

    def step(self) -> None:
        """Advance every world by one control period with the current ``ctrl``; no host synchronisation on GPU."""
        ...

    def forward(self) -> None:
        """Recompute positions, sensors and flags from the current qpos/qvel/ctrl (after writing them directly)."""
        ...

    def reset(
        self, mask: torch.Tensor, qpos: torch.Tensor, qvel: torch.Tensor, ctrl: torch.Tensor | None = None
    ) -> None:
        """Put the worlds flagged in ``mask`` (N,) bool into state ``qpos`` (N, nq) or (nq,), ``qvel`` (N, nv) or
        (nv,), ``ctrl`` (N, nu) or (nu,) (zeros if ``None``); the other worlds stay bit-identical."""
        ...

    def check_overflow(self) -> None:
        """Raise :class:`~tocabi_torchrl.sim.health.SimOverflowError` if a world overflowed or warned (host sync)."""
        ...


def _sizes(sim) -> dict[str, int]:
    mj = sim.mj_model
    return {"N": sim.num_worlds, "nq": sim.nq, "nv": sim.nv, "nu": sim.nu, "nbody": mj.nbody,
            "nsensordata": mj.nsensordata, "ncontact": len(sim.contact_layout.adr), "nC": mj.nC}


def check_backend(sim: object) -> None:
    """Raise ``TypeError`` if ``sim`` lacks a member of :class:`SimBackend`, or ``ValueError`` if one of its tensors
    has the wrong type, shape, dtype or device (see :data:`SIM_TENSORS`)."""
    missing = [m for m in (*_ATTRIBUTES, *(t.name for t in SIM_TENSORS)) if not hasattr(sim, m)]
    missing += [m for m in _METHODS if not callable(getattr(sim, m, None))]
    if missing:
        raise TypeError(f"{type(sim).__name__} is not a physics backend: it lacks {missing} (see sim.backend)")
    sizes = _sizes(sim)
    wrong = []
    for t in SIM_TENSORS:
        value = getattr(sim, t.name)
        want = tuple(sizes[d] if isinstance(d, str) else d for d in t.shape)
        if not isinstance(value, torch.Tensor):
            wrong.append(f"{t.name} is a {type(value).__name__}, not a torch.Tensor")
        elif tuple(value.shape) != want or value.dtype != t.dtype or value.device != sim.device:
            wrong.append(f"{t.name} is {tuple(value.shape)} {value.dtype} on {value.device}, the interface says "
                         f"{want} {t.dtype} on {sim.device}")
    if wrong:
        raise ValueError(f"{type(sim).__name__} breaks the backend interface: " + "; ".join(wrong))
