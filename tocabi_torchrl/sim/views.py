"""The tensor interface every physics backend exposes, and the checks of :meth:`reset`'s arguments.

A backend (:class:`~tocabi_torchrl.sim.WarpSim`, :class:`~tocabi_torchrl.sim.MujocoSim`) fills the primary buffers
(``_qpos``, ``_qvel``, ``_ctrl``, ``_sensordata``, ``_time``, ``_xpos``, ``_xquat``, the signal, health and applied
force tensors, ``_mass_matrix``, ``_qfrc_bias``) and calls :meth:`SimViews._make_derived_views`; this base class
turns them into the public properties (the table in ``WarpSim``'s docstring), so the environment reads every backend
the same way. The interface itself (members, tensor shapes and dtypes) is
:class:`~tocabi_torchrl.sim.backend.SimBackend`; the four methods every backend must write are abstract here, so a
backend that lacks one cannot be instantiated.
"""

from __future__ import annotations

import abc
from collections.abc import Mapping

import mujoco
import numpy as np
import torch

from .. import robot

__all__ = ["SimViews", "MocapPositions"]

#: Per-world positions of mocap bodies: ``{body name: (N, 3) positions [m]}`` (numpy or torch, any float dtype).
MocapPositions = Mapping[str, object]


def world_mocap_pos(mj: mujoco.MjModel, num_worlds: int, mocap_pos: MocapPositions | None) -> np.ndarray | None:
    """(N, nmocap, 3) float64 mocap positions of every world: the model's ``body_pos`` of each mocap body, replaced
    by ``mocap_pos[name]`` for the bodies it names; ``None`` when ``mocap_pos`` is empty or ``None`` (the worlds keep
    the model's positions). Raises ``ValueError`` for a name that is not a mocap body or a bad array."""
    if not mocap_pos:
        return None
    bodies = np.flatnonzero(mj.body_mocapid >= 0)
    by_mocap = np.empty(mj.nmocap, dtype=np.int64)
    by_mocap[mj.body_mocapid[bodies]] = bodies
    out = np.tile(mj.body_pos[by_mocap].astype(np.float64), (num_worlds, 1, 1))
    for name, value in mocap_pos.items():
        b = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_BODY, name)
        if b < 0 or mj.body_mocapid[b] < 0:
            raise ValueError(f"mocap_pos names {name!r}, which is not a mocap body of the model")
        if isinstance(value, torch.Tensor):
            value = value.detach().cpu().numpy()
        value = np.asarray(value, dtype=np.float64)
        if value.shape != (num_worlds, 3) or not np.isfinite(value).all():
            raise ValueError(f"mocap_pos[{name!r}] must be ({num_worlds}, 3) finite positions [m], one row per world, "
                             f"got shape {value.shape}")
        out[:, mj.body_mocapid[b]] = value
    return out


class SimViews(abc.ABC):
    """Public views shared by the backends; see :data:`~tocabi_torchrl.sim.backend.SIM_TENSORS` for shapes and
    units."""

    num_worlds: int
    device: torch.device
    nq: int
    nv: int
    nu: int

    def _make_derived_views(self, mj: mujoco.MjModel) -> None:
        """Body poses, foot F/T and contact counts as windows into the primary buffers (no copies)."""

        def body(name: str) -> int:
            return mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_BODY, name)

        self._base_pos, self._base_quat = self._xpos[:, body(robot.BASE_BODY)], self._xquat[:, body(robot.BASE_BODY)]
        self._neck_pos, self._neck_quat = self._xpos[:, body(robot.NECK_BODY)], self._xquat[:, body(robot.NECK_BODY)]
        left, right = (body(name) for name in robot.FOOT_BODIES)
        if right <= left:
            raise ValueError(f"bodies {robot.FOOT_BODIES} must appear left before right in the model to be viewed as "
                             "one tensor")
        self._foot_pos = self._xpos[:, left : right + 1 : right - left]  # (N, 2, 3), a strided window
        self._foot_force = self._sensor_pair(mj, robot.FOOT_FORCE_SENSORS)
        self._foot_torque = self._sensor_pair(mj, robot.FOOT_TORQUE_SENSORS)
        adr = self.contact_layout.adr
        contiguous = bool(np.all(np.diff(adr) == 1))
        self._contact_counts = self._sensordata[:, adr[0] : adr[-1] + 1] if contiguous else None

    def _signal_views(self, signals: torch.Tensor) -> None:
        """The flag views of the (N, rows) contact-signal tensor (rows: ``contact_layout.signal_names``)."""
        self._foot_contact, self._forbidden, self._self_collision = signals[:, 0:2], signals[:, 2], signals[:, 3]
        if signals.shape[1] > 4:
            self._obstacle_contact = signals[:, 4:6]
        else:  # no scene bodies besides the ground: never touched
            self._obstacle_contact = torch.zeros(self.num_worlds, 2, dtype=torch.bool, device=signals.device)

    def _sensor_pair(self, mj: mujoco.MjModel, names: tuple[str, str]) -> torch.Tensor:
        """A (N, 2, 3) view of two 3-D sensors, [left, right], without copying."""
        ids = [mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_SENSOR, s) for s in names]
        a, b = (int(mj.sensor_adr[i]) for i in ids)
        if b <= a:
            raise ValueError(f"sensors {names} must appear left before right in the model to be viewed as one tensor")
        sd = self._sensordata
        return sd.as_strided((self.num_worlds, 2, 3), (sd.stride(0), b - a, 1), sd.storage_offset() + a)

    # ------------------------------------------------------------------------------------------- backend methods
    @abc.abstractmethod
    def step(self) -> None:
        """Advance every world by one control period (``substeps`` physics steps) with the current ``ctrl``."""

    @abc.abstractmethod
    def forward(self) -> None:
        """Recompute positions, sensors and flags from the current qpos/qvel/ctrl."""

    @abc.abstractmethod
    def reset(
        self, mask: torch.Tensor, qpos: torch.Tensor, qvel: torch.Tensor, ctrl: torch.Tensor | None = None
    ) -> None:
        """Put the flagged worlds into the given state; the others stay bit-identical."""

    @abc.abstractmethod
    def check_overflow(self) -> None:
        """Raise :class:`~tocabi_torchrl.sim.health.SimOverflowError` if a world overflowed or warned."""

    def recorded_graphs(self) -> list:
        """The :class:`~tocabi_torchrl.sim.graph.Recorded` graphs that :meth:`step`, :meth:`forward` and :meth:`reset`
        launch: a torch CUDA graph capturing them must hold them (:func:`tocabi_torchrl.cuda_graphs.capture_graph`).
        Empty on a backend without such graphs."""
        return []

    # ------------------------------------------------------------------------------------------- reset arguments
    def _check_reset_args(self, mask, qpos, qvel, ctrl) -> None:
        """Raise a clear error for a wrong type, device, shape or dtype of :meth:`reset`'s arguments, and on the CPU
        for NaN or inf in a flagged world's state (on a GPU such a world is reported by ``healthy``)."""
        self._check_tensor("mask", mask, (self.num_worlds,), allow_row=False, dtype=torch.bool)
        self._check_tensor("qpos", qpos, (self.num_worlds, self.nq))
        self._check_tensor("qvel", qvel, (self.num_worlds, self.nv))
        if ctrl is not None:
            self._check_tensor("ctrl", ctrl, (self.num_worlds, self.nu))
        if self.device.type == "cpu":  # on a GPU this would read device values on the host: a sync in every reset
            self._check_finite_reset(mask, qpos, qvel, ctrl)

    def _check_finite_reset(self, mask, qpos, qvel, ctrl) -> None:
        """Refuse NaN or inf in a flagged world's reset state. It started diverged without a word: unhealthy, and on
        C MuJoCo put back to the model's default pose (qpos0) by its next step."""
        for name, value in (("qpos", qpos), ("qvel", qvel), ("ctrl", ctrl)):
            if value is None:
                continue
            bad = ~torch.isfinite(value).all(dim=-1)  # (N,) per world, or () for one row that every world takes
            bad = bad & mask if bad.dim() else mask & bad
            if bad.any():
                worlds = torch.nonzero(bad).flatten().tolist()
                shown = ", ".join(map(str, worlds[:8])) + (" ..." if len(worlds) > 8 else "")
                raise ValueError(f"reset: {name} holds NaN or inf for {len(worlds)} flagged world(s) ({shown}); a "
                                 "world cannot start from a non-finite state: pass finite values in the flagged rows")

    def _check_tensor(self, name, value, shape, allow_row: bool = True, dtype: torch.dtype | None = None) -> None:
        if not isinstance(value, torch.Tensor):
            raise TypeError(f"reset: {name} must be a torch.Tensor on {self.device}, got {type(value).__name__}")
        if value.device != self.device:
            raise ValueError(f"reset: {name} is on {value.device}, the simulator on {self.device}; move it there first")
        ok = tuple(value.shape) == shape or (allow_row and tuple(value.shape) == shape[1:])
        if not ok:
            want = f"{shape}" + (f" or {shape[1:]}" if allow_row else "")
            raise ValueError(f"reset: {name} must have shape {want}, got {tuple(value.shape)}")
        if dtype is not None and value.dtype != dtype:
            raise ValueError(f"reset: {name} must have dtype {dtype}, got {value.dtype}")
        if dtype is None and not value.is_floating_point():
            raise ValueError(f"reset: {name} must be a floating-point tensor, got {value.dtype}")

    # --------------------------------------------------------------------------------------------------- views
    qpos = property(lambda self: self._qpos, doc="(N, nq) generalized positions.")
    qvel = property(lambda self: self._qvel, doc="(N, nv) generalized velocities.")
    ctrl = property(lambda self: self._ctrl, doc="(N, nu) actuator controls (write actions here).")
    sensordata = property(lambda self: self._sensordata, doc="(N, nsensordata) all sensor values.")
    time = property(lambda self: self._time, doc="(N,) simulated time since the world's reset [s].")
    xpos = property(lambda self: self._xpos, doc="(N, nbody, 3) body origins in the world [m].")
    xquat = property(lambda self: self._xquat, doc="(N, nbody, 4) body orientations (w, x, y, z).")
    base_pos = property(lambda self: self._base_pos, doc="(N, 3) pelvis origin [m].")
    base_quat = property(lambda self: self._base_quat, doc="(N, 4) pelvis orientation (w, x, y, z).")
    neck_pos = property(lambda self: self._neck_pos, doc="(N, 3) Neck_Link origin [m].")
    neck_quat = property(lambda self: self._neck_quat, doc="(N, 4) Neck_Link orientation (w, x, y, z).")
    foot_pos = property(lambda self: self._foot_pos, doc="(N, 2, 3) Foot_Link origins in the world [m], [L, R].")
    foot_force = property(lambda self: self._foot_force, doc="(N, 2, 3) foot F/T force, site frame [N], [L, R].")
    foot_torque = property(lambda self: self._foot_torque, doc="(N, 2, 3) foot F/T torque, site frame [N·m].")
    foot_contact = property(lambda self: self._foot_contact,
                            doc="(N, 2) bool foot touches the ground or an obstacle, [L, R].")
    forbidden_ground_contact = property(lambda self: self._forbidden,
                                        doc="(N,) bool forbidden contact with the ground or a scene body.")
    self_collision = property(lambda self: self._self_collision, doc="(N,) bool self collision.")
    obstacle_contact = property(lambda self: self._obstacle_contact,
                                doc="(N, 2) bool foot touches a scene body other than the ground plane, [L, R].")
    healthy = property(lambda self: self._healthy_t, doc="(N,) bool finite state and no buffer overflow.")
    overflow = property(lambda self: self._overflow_t, doc="(N,) int32 backend overflow/warning bits.")
    applied_actuator_force = property(
        lambda self: self._applied_force_t, doc="(N, nu) actuator forces applied in the last substep [N·m]."
    )
    mass_matrix = property(
        lambda self: self._mass_matrix,
        doc="(N, nC) joint-space inertia M(q) of the current state, MuJoCo's sparse lower-triangle (CSR) layout.",
    )
    qfrc_bias = property(lambda self: self._qfrc_bias,
                         doc="(N, nv) bias force c(q, q̇): gravity, Coriolis and centrifugal [N, N·m] (the free "
                             "joint's first 3 entries are forces [N], the rest torques [N·m]).")
    xfrc_applied = property(
        lambda self: self._xfrc_t,
        doc="(N, nbody, 6) external force [N] and torque [N·m] per body (world frame, at the body's centre of mass): "
            "an input like ctrl, applied in every substep until changed, zeroed when the world resets.",
    )
    substep_ctrl = property(
        lambda self: self._substep_ctrl_t,
        doc="(N, substeps, k) controls of the ``SimConfig.substep_ctrl`` actuators in each physics substep of the "
            "next step (their ``ctrl`` entries are ignored by the step, which leaves the last substep's controls "
            "there for the post-step forward pass), or None when the config names none.",
    )

    def _substep_columns(self, mj: mujoco.MjModel) -> tuple[int, ...]:
        """``config.substep_ctrl`` checked against the model's actuators."""
        cols = tuple(self.config.substep_ctrl)
        if any(c >= mj.nu for c in cols):
            raise ValueError(f"SimConfig.substep_ctrl names actuators {cols}, but the model has nu={mj.nu}")
        return cols

    @property
    def contact_counts(self) -> torch.Tensor:
        """(N, k) contact-sensor counts, columns named by ``contact_layout.names``."""
        if self._contact_counts is None:
            raise ValueError("the contact sensors are not contiguous in sensordata; index sensordata[:, layout.adr]")
        return self._contact_counts
