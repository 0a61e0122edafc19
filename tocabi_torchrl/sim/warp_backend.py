"""``WarpSim``: N TOCABI worlds in mujoco-warp, exposed as torch tensors that alias the warp arrays.

One :meth:`WarpSim.step` is one control period: ``substeps`` physics steps, then a forward pass so that positions,
sensors and contact signals describe the post-step state, then the derived flags (contacts, health). The whole sequence
is one recorded graph (a CUDA graph on GPU) that never reads device values on the host. :meth:`WarpSim.reset` writes
initial states into flagged worlds with a second recorded graph.

The step reuses work: the forward pass at the end of a step leaves the position- and velocity-dependent quantities of
the new state in ``Data``; only ``ctrl`` changes before the next step, so its first substep runs
``mujoco_warp.step2`` (actuation, constraint solve, integration) instead of a full ``step``. A step's final forward
pass, and every :meth:`forward`, leaves its constraint solution as the solver's warm start (``qacc_warmstart``); a
reset sets it in the reset worlds only, so the forward pass over the untouched ones converges at once and their
future stays bit-identical. The trajectory is bit-identical to calling ``mujoco_warp.step`` ``substeps`` times after
such a forward pass. Write ``qpos``/``qvel`` only through :meth:`reset`, or call :meth:`forward` after writing them
directly.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable, Mapping
from types import MappingProxyType

import mujoco
import mujoco_warp as mjw
import numpy as np
import torch
import warp as wp

from .buffers import NJMAX, permanent_constraint_rows
from .compact_reset import CompactResetPass
from .config import SimConfig, compact_reset_capacity
from .contacts import ContactLayout, contact_layout
from .graph import Recorded
from .health import overflow_error
from .kernel_cache import announce_compile_if_cold, quiet_warp_info
from .kernels import (copy_rows_where, copy_start_rows, derive_signals, or_start_overflow, write_reset_state,
                      write_substep_ctrl)
from .memory import check_fits, warp_world_bytes
from .model import ModelSource, compile_model
from .views import MocapPositions, SimViews, world_mocap_pos

__all__ = ["WarpSim"]

def _resolve_device(name) -> wp.Device:
    name = str(name)
    if name != "cpu" and name != "cuda" and not (name.startswith("cuda:") and name[5:].isdigit()):
        raise ValueError(f"unknown device {name!r}: use 'cpu', 'cuda' or 'cuda:N'")
    quiet_warp_info()
    wp.init()
    if name.startswith("cuda") and not wp.is_cuda_available():
        raise ValueError(f"device {name!r} requested but warp sees no CUDA device on this machine; use device='cpu'")
    try:
        return wp.get_device(name)
    except Exception as err:  # warp raises a bare RuntimeError/ValueError for an out-of-range ordinal
        raise ValueError(f"device {name!r} is not available ({err}); warp sees {wp.get_devices()}") from err


def _without_sensors(m: mjw.Model) -> mjw.Model:
    """A shallow copy of ``m`` whose steps skip sensor evaluation (same arrays, so the same physics)."""
    opt = dataclasses.replace(m.opt, disableflags=int(m.opt.disableflags) | int(mjw.DisableBit.SENSOR))
    return dataclasses.replace(m, opt=opt)


@dataclasses.dataclass
class _StartStates:
    """Registered start states (rows) and, per row and world, what the full reset pass computed for them."""

    qpos: torch.Tensor  # (K * N, nq): state k of world w in row k * N + w
    qvel: torch.Tensor  # (K * N, nv)
    ctrl: torch.Tensor  # (K * N, nu)
    num: int
    worlds: torch.Tensor  # (N,) int64 world ids, for the row of each world's state
    index: wp.array  # (N,) int32: the row each world resets to
    index_t: torch.Tensor  # its torch view, which the host side fills
    rows: torch.Tensor  # (N,) int64 scratch, refilled in place on every reset: clamped rows, then their flat rows
    sensordata: wp.array  # (K, N, nsensordata)
    qacc: wp.array  # (K, N, nv)
    actuator_force: wp.array  # (K, N, nu)
    overflow: wp.array  # (K, N) int32
    tables: dict  # the torch tensors the warp arrays above alias (kept alive with them)


class WarpSim(SimViews):
    """N worlds of one MuJoCo model stepped by mujoco-warp, with zero-copy torch views of the state.

    Args:
        config: :class:`SimConfig` (number of worlds, device, substeps, buffer sizes, solver overrides).
        model: the scene: ``None`` for the shipped TOCABI (``robot.load_spec()``), an MJCF path, a ``mujoco.MjSpec``
            (copied; the contact sensors are added to the copy) or a compiled ``mujoco.MjModel`` that already has
            them (built with :func:`~tocabi_torchrl.sim.contacts.add_contact_sensors`).
        mocap_pos: per-world positions of the model's mocap bodies, ``{body name: (N, 3) [m]}`` (e.g. the env's
            obstacles); each world starts with them and gets them back on every reset (mujoco-warp's ``reset_data``
            would put the model's ``body_pos`` back). Bodies not named, and every body when ``None``, keep the
            model's position. :attr:`world_mocap_pos` holds the result, (N, nmocap, 3) float64, or ``None``.

    Tensors (all on :attr:`device`, float32 unless stated, first dimension N = ``num_worlds``) are views of warp
    memory: reading them copies nothing, writing ``ctrl`` is how actions reach the physics. They hold the state after
    the last :meth:`step` / :meth:`reset` / :meth:`forward` and are overwritten by the next one, so clone what you keep.

    ========================== ================ ===============================================================
    name                       shape            meaning
    ========================== ================ ===============================================================
    qpos                       (N, nq=40)       base position [m], base quaternion (w, x, y, z), 33 joints [rad]
    qvel                       (N, nv=39)       base linear (world) [m/s], angular (local) [rad/s], joints [rad/s]
    ctrl                       (N, nu=33)       legs: torque [N·m]; upper body: position-actuator target [rad]
    xfrc_applied               (N, nbody, 6)    external force [N] / torque [N·m] per body, world frame at the COM:
                                                an input (held until changed, zeroed at reset)
    substep_ctrl               (N, S, k)        per-substep controls of the ``SimConfig.substep_ctrl`` actuators
                                                (S = substeps), or None
    sensordata                 (N, nsensordata) every sensor of the model
    xpos / xquat               (N, nbody, 3/4)  body frame origins [m] / orientations (w, x, y, z) in the world
    base_pos / base_quat       (N, 3) / (N, 4)  ``robot.BASE_BODY`` pose (views of xpos / xquat)
    neck_pos / neck_quat       (N, 3) / (N, 4)  ``robot.NECK_BODY`` pose
    foot_pos                   (N, 2, 3)        ``robot.FOOT_BODIES`` origins [m], world frame, [left, right]
    foot_force / foot_torque   (N, 2, 3)        foot F/T sensors [N] / [N·m], site frame, [left, right]
    contact_counts             (N, k)           the ``found`` counts of the contact sensors (see contact_layout)
    foot_contact               (N, 2) bool      a foot body touches the ground (a world-body geom) or an
                                                obstacle (a scene body outside the robot), [left, right]
    forbidden_ground_contact   (N,) bool        a ``robot.GROUND_FORBIDDEN_BODIES`` body touches the ground
                                                (or a scene body outside the robot: an obstacle)
    self_collision             (N,) bool        two ``robot.SELF_COLLISION_BODIES`` bodies touch
    obstacle_contact           (N, 2) bool      a foot body touches a scene body other than the world body
                                                (an obstacle), [left, right]; False without one
    healthy                    (N,) bool        finite qpos/qvel/qacc/sensors, no overflow (``health_overflow_mask``)
    overflow                   (N,) int32       mujoco-warp ``OverflowType`` bits (sticky until the world resets)
    applied_actuator_force     (N, nu)          actuator forces [N·m] applied in the last substep of the last step
                                                (``wp_data.actuator_force`` holds the post-step forward pass's values)
    mass_matrix                (N, nC=396)      joint-space inertia M(q) of the current state (``wp_data.M``: MuJoCo's
                                                sparse lower triangle, rows ``mj_model.M_rowadr``/``M_rownnz``,
                                                columns ``M_colind``)
    qfrc_bias                  (N, nv)          bias force c(q, q̇) of the current state: gravity, Coriolis and
                                                centrifugal [N, N·m] (the free joint's first 3 entries are forces
                                                [N], the rest torques [N·m]; ``wp_data.qfrc_bias``)
    time                       (N,)             simulated time since the world's last reset [s]
    model_fields[name]         (N, ...)         each world's row of model field ``name``, one per name of
                                                ``SimConfig.per_world_fields`` (e.g. ``body_mass`` (N, nbody) [kg],
                                                ``body_inertia`` (N, nbody, 3) [kg·m²], ``geom_friction``
                                                (N, ngeom, 3)): views of the model's own per-world arrays, an input
                                                read from the next step, reset or forward pass on (empty dict when
                                                the config names none: every world reads the one model)
    ========================== ================ ===============================================================
    """

    def __init__(self, config: SimConfig | None = None, model: ModelSource = None,
                 mocap_pos: MocapPositions | None = None):
        cfg = copy.deepcopy(config) if config is not None else SimConfig()
        cfg.validate()
        self.config = cfg
        self.wp_device = _resolve_device(cfg.device)
        self.device = torch.device(wp.device_to_torch(self.wp_device))
        self.num_worlds = n = cfg.num_worlds

        mj = compile_model(model, cfg)
        permanent = permanent_constraint_rows(mj)
        if cfg.njmax < permanent:
            # Else every world overflows from the first pass on, and healthy=False ends every episode at its first
            # step, with nothing said unless check_overflow is called.
            raise ValueError(
                f"SimConfig.njmax={cfg.njmax} cannot hold the {permanent} constraint rows every world of this model "
                f"has in every state (friction loss, equality constraints), before any contact or joint limit: raise "
                f"njmax (env.sim.njmax); the default {NJMAX} was measured for TOCABI (docs/benchmarks/sim_buffers.md)")
        check_fits(n, warp_world_bytes(mj, cfg.nconmax, cfg.njmax, cfg.ccd_per_world), self.device, "mujoco-warp")
        self.mj_model = mj
        self.contact_layout: ContactLayout = contact_layout(mj)
        self.world_mocap_pos = world_mocap_pos(mj, n, mocap_pos)
        self.nq, self.nv, self.nu = mj.nq, mj.nv, mj.nu
        self.physics_dt = float(mj.opt.timestep)
        self.control_dt = self.physics_dt * cfg.substeps

        announce_compile_if_cold(self.wp_device)
        with wp.ScopedDevice(self.wp_device):
            self.wp_model = mjw.put_model(mj)
            self.wp_model.opt.contact_sensor_maxmatch = cfg.contact_sensor_maxmatch
            self.wp_model.opt.warn_overflow = int(mjw.OverflowType.ALL) if cfg.kernel_overflow_prints else 0
            # Before _without_sensors' shallow copy and before any graph records the model's arrays.
            self._model_fields = self._per_world_fields(cfg.per_world_fields)
            self._substep_model = self.wp_model if cfg.sensors_every_substep else _without_sensors(self.wp_model)
            self.wp_data = mjw.make_data(mj, nworld=n, nconmax=cfg.nconmax, njmax=cfg.njmax,
                                         nccdmax=cfg.ccd_per_world)
            self._alloc_buffers(mj)
        self._make_views(mj)

        # Run everything once eagerly: it compiles the kernels (before any capture) and leaves a consistent state.
        with wp.ScopedDevice(self.wp_device):
            self._forward_fn()
            self._step_fn()
            self._reset_mask.fill_(True)
            self._reset_qpos.assign(np.tile(mj.qpos0, (n, 1)).astype(np.float32))
            self._reset_fn()
            wp.synchronize_device(self.wp_device)
        self._step_graph = Recorded(self._step_fn, self.wp_device, cfg.use_graph)
        self._reset_graph = Recorded(self._reset_fn, self.wp_device, cfg.use_graph)
        self._forward_graph = Recorded(self._forward_fn, self.wp_device, cfg.use_graph)
        self._start_states: _StartStates | None = None  # reset_pass="reduced": see register_start_states
        self._start_reset_graph: Recorded | None = None
        self._compact: CompactResetPass | None = None  # the reduced pass over the reset worlds alone

    # ----------------------------------------------------------------------------------------------- construction
    def _alloc_buffers(self, mj: mujoco.MjModel) -> None:
        n, lay = self.num_worlds, self.contact_layout
        self._found_adr = wp.array(lay.adr, dtype=int)
        self._weights = wp.array(lay.weights.astype(np.float32), dtype=float)
        self._signals = wp.zeros((n, lay.weights.shape[0]), dtype=wp.bool)
        self._overflow = wp.zeros(n, dtype=int)
        self._healthy = wp.zeros(n, dtype=wp.bool)
        self._reset_mask = wp.zeros(n, dtype=wp.bool)
        self._reset_qpos = wp.zeros((n, mj.nq), dtype=float)
        self._reset_qvel = wp.zeros((n, mj.nv), dtype=float)
        self._reset_ctrl = wp.zeros((n, mj.nu), dtype=float)
        self._sensor_snapshot = wp.zeros((n, mj.nsensordata), dtype=float)
        self._applied_force = wp.zeros((n, mj.nu), dtype=float)
        self._substep_cols = self._substep_columns(mj)
        self._substep_ctrl = self._substep_col_arr = None
        if self._substep_cols:
            self._substep_ctrl = wp.zeros((n, self.config.substeps, len(self._substep_cols)), dtype=float)
            self._substep_col_arr = wp.array(self._substep_cols, dtype=int)
        self._mocap_pos = None  # each world's mocap positions, put back after reset_data
        if self.world_mocap_pos is not None:
            self._mocap_pos = wp.array(self.world_mocap_pos.astype(np.float32), dtype=wp.vec3)
            wp.copy(self.wp_data.mocap_pos, self._mocap_pos)

    def _per_world_fields(self, names: tuple[str, ...]) -> dict[str, torch.Tensor]:
        """Replace each model field of ``names`` with an (N, ...) array, every row the model's value, and return its
        torch views.

        mujoco-warp declares these fields batched: a kernel reads row ``worldid % arr.shape[0]``, so a leading
        dimension of N instead of 1 gives each world its own value with the same kernels (no recompilation, nothing
        extra launched). Derived model quantities are not recomputed here: whoever writes ``body_mass`` keeps
        ``body_subtreemass`` consistent (``tocabi_torchrl.sim.dynamics`` does).
        """
        m, n, views = self.wp_model, self.num_worlds, {}
        for name in names:
            shared = getattr(m, name)
            if shared.shape[0] != 1:
                raise ValueError(f"mujoco-warp's Model.{name} has {shared.shape[0]} rows, expected the one of "
                                 "put_model: this mujoco-warp version lays the field out differently")
            rows = wp.empty((n, *shared.shape[1:]), dtype=shared.dtype)
            view = wp.to_torch(rows)
            view.copy_(wp.to_torch(shared).expand_as(view))
            setattr(m, name, rows)
            views[name] = view
        return views

    @property
    def model_fields(self) -> Mapping[str, torch.Tensor]:
        """``{name: (N, ...) float32}`` each world's row of the ``SimConfig.per_world_fields`` model fields, a
        read-only mapping of views of the model's arrays: write rows in place to change a world's physics from its
        next step, reset or forward pass (the recorded graphs read this memory). Empty when the config names none."""
        # Read-only: a rebound entry would reach no world's physics (the models read the first tensor).
        return MappingProxyType(self._model_fields)

    def _make_views(self, mj: mujoco.MjModel) -> None:
        d, t = self.wp_data, wp.to_torch
        self._qpos, self._qvel, self._ctrl = t(d.qpos), t(d.qvel), t(d.ctrl)
        self._sensordata, self._time = t(d.sensordata), t(d.time)
        self._xpos, self._xquat = t(d.xpos), t(d.xquat)
        self._signal_views(t(self._signals))
        self._healthy_t, self._overflow_t = t(self._healthy), t(self._overflow)
        self._reset_mask_t = t(self._reset_mask)
        self._reset_qpos_t, self._reset_qvel_t = t(self._reset_qpos), t(self._reset_qvel)
        self._reset_ctrl_t = t(self._reset_ctrl)
        self._applied_force_t = t(self._applied_force)
        self._substep_ctrl_t = None if self._substep_ctrl is None else t(self._substep_ctrl)
        self._xfrc_t = t(d.xfrc_applied)
        # The joint-space inertia and bias force of the last forward pass (mujoco-warp's Data.M is MuJoCo's sparse
        # CSR layout, (nworld, nC), whatever the model's opt.jacobian: dense factorisation blocks live in qLD).
        self._mass_matrix, self._qfrc_bias = t(d.M), t(d.qfrc_bias)

        self._make_derived_views(mj)

    # --------------------------------------------------------------------------------------------- graph bodies
    def _derive(self) -> None:
        d = self.wp_data
        wp.launch(
            derive_signals,
            dim=self.num_worlds,
            inputs=[
                d.qpos,
                d.qvel,
                d.qacc,
                d.sensordata,
                self._found_adr,
                self._weights,
                d.overflow,
                d.nefc,
                d.nacon,
                d.ncollision,
                d.njmax,
                d.naconmax,
                int(self.config.health_overflow_mask),
            ],
            outputs=[self._signals, self._overflow, self._healthy],
        )

    def _step_fn(self) -> None:
        m, d, ms = self.wp_model, self.wp_data, self._substep_model
        self._write_substep_ctrl(0)
        mjw.step2(ms, d)  # position/velocity stages of this state were computed by the previous forward pass
        for s in range(1, self.config.substeps):
            self._write_substep_ctrl(s)
            mjw.step(ms, d)
        wp.copy(self._applied_force, d.actuator_force)  # the forward pass below overwrites it with post-step values
        mjw.forward(m, d)
        wp.copy(d.qacc_warmstart, d.qacc)  # see _reset_fn: the solution of this state warm-starts what follows
        self._derive()

    def _write_substep_ctrl(self, substep: int) -> None:
        """The ``substep_ctrl`` actuators' controls for physics substep ``substep`` (nothing when there are none)."""
        if self._substep_cols:
            wp.launch(write_substep_ctrl, dim=(self.num_worlds, len(self._substep_cols)),
                      inputs=[self._substep_ctrl, substep, self._substep_col_arr], outputs=[self.wp_data.ctrl])

    def _write_reset_state(self) -> None:
        """Clear the flagged worlds as ``mujoco_warp.reset_data`` does and write their reset qpos, qvel and ctrl (both
        reset passes)."""
        m, d, mask = self.wp_model, self.wp_data, self._reset_mask
        mjw.reset_data(m, d, reset=mask)
        if self._mocap_pos is not None:  # reset_data put the model's positions back in the reset worlds
            wp.copy(d.mocap_pos, self._mocap_pos)
        wp.launch(
            write_reset_state,
            dim=self.num_worlds,
            inputs=[mask, self._reset_qpos, self._reset_qvel, self._reset_ctrl],
            outputs=[d.qpos, d.qvel, d.ctrl],
        )

    def _reset_fn(self) -> None:
        m, d, n, mask = self.wp_model, self.wp_data, self.num_worlds, self._reset_mask
        # The forward pass below recomputes every world; restoring the untouched worlds' sensors keeps them
        # bit-identical even where the GPU's contact order (atomics) would change the last bits of a force.
        wp.launch(copy_rows_where, dim=n, inputs=[mask, False, d.sensordata, self._sensor_snapshot])
        self._write_reset_state()
        # Warm start: mujoco-warp's Newton solver starts a world from qacc_warmstart and iterates until the slowest
        # world converges. The step leaves each world's warm start at the solution of its current state, so the
        # untouched worlds converge here in one iteration instead of re-solving from the last substep's
        # acceleration (about 5 iterations for all 4,096 worlds of a training step); reset_data zeroed the flagged
        # worlds' warm start, as MuJoCo does, which suits a reset state at rest.
        mjw.forward(m, d)
        wp.launch(copy_rows_where, dim=n, inputs=[mask, True, d.qacc, d.qacc_warmstart])
        wp.launch(copy_rows_where, dim=n, inputs=[mask, False, self._sensor_snapshot, d.sensordata])
        # Nothing was applied yet in a reset world: report what its actuators would apply in the reset state.
        wp.launch(copy_rows_where, dim=n, inputs=[mask, True, d.actuator_force, self._applied_force])
        self._derive()

    def _forward_fn(self) -> None:
        mjw.forward(self.wp_model, self.wp_data)
        wp.copy(self.wp_data.qacc_warmstart, self.wp_data.qacc)
        self._derive()

    def _reset_to_start_fn(self) -> None:
        """The ``reset_pass="reduced"`` reset (see :meth:`register_start_states`): no sensor, actuation, acceleration
        or solver stage over all worlds; the reset worlds get those results from the start-state table."""
        m, d, n, mask, s = self.wp_model, self.wp_data, self.num_worlds, self._reset_mask, self._start_states
        # What the next step's step2 reads besides its own stages: kinematics, com, inertia and its factorisation
        # (forward factorises in its acceleration stage, step2 does not), contacts, constraint rows, bias forces.
        # The untouched worlds keep their sensors, qacc, actuator forces and warm start from the step's forward pass.
        if self._compact is None:
            self._write_reset_state()
            mjw.fwd_position(m, d, factorize=True)
            mjw.fwd_velocity(m, d)
        else:  # the same stages over the reset worlds alone
            self._compact.run(mask, self._write_reset_state)
        idx = s.index
        wp.launch(copy_start_rows, dim=n, inputs=[mask, idx, s.sensordata, d.sensordata])
        wp.launch(copy_start_rows, dim=n, inputs=[mask, idx, s.qacc, d.qacc])
        wp.launch(copy_start_rows, dim=n, inputs=[mask, idx, s.qacc, d.qacc_warmstart])
        wp.launch(copy_start_rows, dim=n, inputs=[mask, idx, s.actuator_force, d.actuator_force])
        wp.launch(copy_start_rows, dim=n, inputs=[mask, idx, s.actuator_force, self._applied_force])
        wp.launch(or_start_overflow, dim=n, inputs=[mask, idx, s.overflow, d.overflow])
        self._derive()

    # ------------------------------------------------------------------------------------------------- public API
    def recorded_graphs(self) -> list[Recorded]:
        graphs = [self._step_graph, self._reset_graph, self._forward_graph]
        return graphs if self._start_reset_graph is None else [*graphs, self._start_reset_graph]

    def step(self) -> None:
        """Advance every world by one control period (``substeps`` physics steps) with the current ``ctrl``."""
        self._step_graph()

    def forward(self) -> None:
        """Recompute positions, sensors and flags from the current qpos/qvel/ctrl (after writing them directly).

        Its constraint solution becomes the solver's warm start, so an extra call on an unchanged state can move the
        following steps in the last float32 bits (re-solving from a converged solution need not return it exactly;
        measured: 2e-9 in qpos after 6 steps).
        """
        self._forward_graph()

    def reset(
        self,
        mask: torch.Tensor,
        qpos: torch.Tensor,
        qvel: torch.Tensor,
        ctrl: torch.Tensor | None = None,
    ) -> None:
        """Put the flagged worlds into the given state; the others stay bit-identical. Never syncs with the host.

        Args:
            mask: (N,) bool, True for the worlds to reset.
            qpos: (N, nq) or (nq,) initial positions (only flagged rows are read).
            qvel: (N, nv) or (nv,) initial velocities.
            ctrl: (N, nu) or (nu,) controls to start with; zeros if ``None``.

        On the CPU, NaN or inf in a flagged world's qpos, qvel or ctrl is refused (``ValueError``); on a GPU it is
        not read (that would sync) and the world reports ``healthy`` False.

        Everything else of a flagged world is cleared as by ``mujoco_warp.reset_data`` (time, activations, warm
        start, applied forces, overflow flags), then a forward pass fills positions, sensors and flags.
        """
        self._check_reset_args(mask, qpos, qvel, ctrl)
        # Detached: a copy from a tensor that requires grad would leave the staging buffers in its autograd graph.
        self._reset_mask_t.copy_(mask)
        self._reset_qpos_t.copy_(qpos.detach())
        self._reset_qvel_t.copy_(qvel.detach())
        if ctrl is None:
            self._reset_ctrl_t.zero_()
        else:
            self._reset_ctrl_t.copy_(ctrl.detach())
        self._reset_graph()

    def register_start_states(self, qpos: torch.Tensor, qvel: torch.Tensor, ctrl: torch.Tensor,
                              set_fields: Callable[[int], None] | None = None,
                              compact: int | None = None) -> None:
        """Register the K start states :meth:`reset_to_start` may reset to (``reset_pass="reduced"`` only).

        Args:
            qpos, qvel, ctrl: (K, nq), (K, nv), (K, nu) float32 tensors on :attr:`device`, start state k in row k;
                or (K, N, nq), (K, N, nv), (K, N, nu): each world's own start state k (a pool of drawn starts).
            set_fields: with ``SimConfig.per_world_fields``, required: ``set_fields(k)`` writes each world's
                model fields of its start state k (:attr:`model_fields`, e.g. drawn masses) before that state's
                full pass; a world reset to state k must then have those fields again (the caller writes them,
                as before the full pass). Without per-world fields, leave it None.
            compact: how many reset worlds the reduced pass runs its position and velocity stages over at a time on
                a second, small ``Data`` (:class:`~tocabi_torchrl.sim.compact_reset.CompactResetPass`; a reset of
                more worlds takes several rounds); 0 for the stages over every world; None (default) for
                :func:`~tocabi_torchrl.sim.config.compact_reset_capacity` of the world count (0 with
                ``SimConfig.sensors_every_substep``, which it cannot serve). Each world's physics is the same either
                way, but for a full contact buffer: both then flag every world (``NARROWPHASE``), the small pass
                after dropping the reset worlds' contacts that did not fit, the pass over every world after dropping
                any world's.

        Runs the full reset of :meth:`reset` once per start state over all worlds (each with its own mocap
        positions and, with ``set_fields``, model fields) and keeps, per state and world, what the reduced reset
        does not compute: the sensors, ``qacc`` (the warm start), the actuator forces and the overflow bits. Call it
        before the first :meth:`reset_to_start` and before capturing a graph that resets; it overwrites every world's
        state (leaving start state 0, with the model fields of state K - 1) and syncs with the host. The table holds
        for this simulator's model and mocap positions, which never change, and the fields ``set_fields`` wrote.
        Once only: a graph captured after it reads the table's memory, so replacing the table could free what the
        graph still reads.

        Right after a reduced reset, the reset worlds' constraint and acceleration by-products (``qfrc_actuator``,
        ``qfrc_smooth``, ``qacc_smooth``, ``qfrc_constraint``, ``cacc``, ``cfrc_int``/``cfrc_ext``, the ``efc``
        forces and states) are not those of the start state: nothing here reads them, and the next step recomputes
        them. The untouched worlds keep the step's ``qacc``, which the full pass re-solves from their warm start: the
        two agree within the solver's tolerance (up to ~0.007 in the CPU tests), feed nothing (the warm start and every
        trajectory are bit-identical), and only the health flag's finiteness check reads ``qacc``. That re-solve can
        also raise the solver's iteration-limit flags (``ITERATIONS``, ``LS_ITERATIONS``) in an untouched world's
        ``overflow`` where the reduced pass does not; neither is a health flag. Read only the views of
        :class:`WarpSim` after a reset.
        """
        if self.config.reset_pass != "reduced":
            raise ValueError(f"register_start_states needs SimConfig.reset_pass='reduced' (this simulator has "
                             f"{self.config.reset_pass!r}); with 'full', reset to any state with reset()")
        if self.config.per_world_fields and set_fields is None:
            raise ValueError(f"register_start_states: the table would hold sensors and accelerations of the model "
                             f"fields {self.config.per_world_fields} as they are now, but they change per world "
                             "(SimConfig.per_world_fields); pass set_fields (each state's fields, written before its "
                             "full pass), or reset with the full pass, reset_pass='full'")
        if set_fields is not None and not self.config.per_world_fields:
            raise ValueError("register_start_states: set_fields writes per-world model fields, but this simulator has "
                             "none (SimConfig.per_world_fields is empty); leave it None")
        if compact is None:  # the rule, where the small pass can stand in for the pass over every world
            compact = 0 if self.config.sensors_every_substep else compact_reset_capacity(self.num_worlds)
        if isinstance(compact, bool) or not isinstance(compact, int) or not 0 <= compact < self.num_worlds:
            raise ValueError(f"register_start_states: compact must be an int in [0, {self.num_worlds}) (reset worlds "
                             f"the small pass holds; 0: the pass over every world), got {compact!r}")
        if compact and self.config.sensors_every_substep:
            # step2 would evaluate contact sensors over the contact buffer, where rows emptied of the reset worlds'
            # old contacts still sit, and the small pass does not recompute the sensors.
            raise ValueError("register_start_states: compact > 0 needs SimConfig.sensors_every_substep=False; pass "
                             "compact=0")
        if self._start_states is not None:
            raise ValueError("register_start_states was called already: a graph captured since may read the table, "
                             "so it is not replaced; build another simulator for other start states")
        m = self.wp_model
        unsupported = int(m.opt.enableflags) & int(mjw.EnableBit.ENERGY | mjw.EnableBit.SLEEP)
        if unsupported or m.opt.integrator == mjw.IntegratorType.DISCRETE:
            raise ValueError("reset_pass='reduced' does not reproduce the energy, sleep or discrete-integrator "
                             "stages of the full pass; use reset_pass='full' with this model")
        n = self.num_worlds
        for name, value, width in (("qpos", qpos, self.nq), ("qvel", qvel, self.nv), ("ctrl", ctrl, self.nu)):
            ok = (isinstance(value, torch.Tensor) and value.dim() in (2, 3) and value.shape[0] >= 1
                  and value.shape[-1] == width and value.shape[0] == qpos.shape[0] and value.device == self.device
                  and (value.dim() == 2 or value.shape[1] == n))
            if not ok:
                raise ValueError(f"register_start_states: {name} must be a (K, {width}) or (K, {n}, {width}) tensor "
                                 f"on {self.device}, K >= 1 rows like qpos, got "
                                 f"{getattr(value, 'shape', type(value).__name__)}")
        k, d = qpos.shape[0], self.wp_data
        dev, f32 = self.device, torch.float32
        # Every world's own row of every state: (K, N, width), flattened to (K * N, width) for the reset's gather.
        qpos, qvel, ctrl = (v.to(f32).unsqueeze(1).expand(k, n, v.shape[-1]).clone() if v.dim() == 2
                            else v.to(f32).contiguous().clone() for v in (qpos, qvel, ctrl))
        table = {"sensordata": torch.zeros(k, n, self.mj_model.nsensordata, dtype=f32, device=dev),
                 "qacc": torch.zeros(k, n, self.nv, dtype=f32, device=dev),
                 "actuator_force": torch.zeros(k, n, self.nu, dtype=f32, device=dev),
                 "overflow": torch.zeros(k, n, dtype=torch.int32, device=dev)}
        t = wp.to_torch
        with wp.ScopedDevice(self.wp_device):
            for r in range(k):  # the full reset, eagerly, of every world into start state r
                if set_fields is not None:
                    set_fields(r)
                self._reset_mask_t.fill_(True)
                self._reset_qpos_t.copy_(qpos[r])
                self._reset_qvel_t.copy_(qvel[r])
                self._reset_ctrl_t.copy_(ctrl[r])
                wp.synchronize_device(self.wp_device)
                self._reset_fn()
                wp.synchronize_device(self.wp_device)
                for name in ("sensordata", "qacc", "actuator_force", "overflow"):
                    table[name][r].copy_(t(getattr(d, name)))
            index = wp.zeros(n, dtype=wp.int32)
            self._start_states = _StartStates(
                qpos=qpos.reshape(k * n, -1), qvel=qvel.reshape(k * n, -1), ctrl=ctrl.reshape(k * n, -1), num=k,
                worlds=torch.arange(n, dtype=torch.int64, device=dev), index=index, index_t=t(index),
                rows=torch.zeros(n, dtype=torch.int64, device=dev),
                **{name: wp.from_torch(v) for name, v in table.items()}, tables=table,
            )
            if compact:
                cfg = self.config
                self._compact = CompactResetPass(self.mj_model, m, d, compact, cfg.nconmax, cfg.njmax,
                                                 cfg.ccd_per_world, tuple(self._model_fields))
            # Compile and run the reduced reset once (all worlds into start state 0), then record it.
            self._fill_start_reset(torch.ones(n, dtype=torch.bool, device=dev), torch.zeros(n, dtype=torch.int64,
                                                                                            device=dev))
            wp.synchronize_device(self.wp_device)
            self._reset_to_start_fn()
            wp.synchronize_device(self.wp_device)
        self._start_reset_graph = Recorded(self._reset_to_start_fn, self.wp_device, self.config.use_graph)

    def _fill_start_reset(self, mask: torch.Tensor, index: torch.Tensor) -> None:
        # Every reset of the sync-free step comes here: into preallocated buffers only.
        s = self._start_states
        rows = torch.clamp(index, 0, s.num - 1, out=s.rows)  # an index out of range would read outside the table
        self._reset_mask_t.copy_(mask)
        s.index_t.copy_(rows)
        flat = rows.mul_(self.num_worlds).add_(s.worlds)  # state rows[w] of world w: row rows[w] * N + w
        torch.index_select(s.qpos, 0, flat, out=self._reset_qpos_t)
        torch.index_select(s.qvel, 0, flat, out=self._reset_qvel_t)
        torch.index_select(s.ctrl, 0, flat, out=self._reset_ctrl_t)

    def reset_to_start(self, mask: torch.Tensor, index: torch.Tensor) -> None:
        """Put each flagged world into registered start state ``index[w]`` with the reduced reset pass (see
        :meth:`register_start_states`); the others stay bit-identical. Never syncs with the host once recorded
        (``SimConfig.use_graph``; eagerly on a GPU, the small pass's loop reads its condition there each round).

        Args:
            mask: (N,) bool, True for the worlds to reset.
            index: (N,) int64 row of the registered states for each world (only flagged rows are read; values
                outside [0, K) are clamped).
        """
        if self._start_states is None:
            raise RuntimeError("reset_to_start needs register_start_states(...) first (SimConfig.reset_pass="
                               "'reduced'); reset() resets to any state with the full pass")
        self._check_tensor("mask", mask, (self.num_worlds,), allow_row=False, dtype=torch.bool)
        self._check_tensor("index", index, (self.num_worlds,), allow_row=False, dtype=torch.int64)
        self._fill_start_reset(mask, index)
        self._start_reset_graph()

    def check_overflow(self) -> None:
        """Raise :class:`~tocabi_torchrl.sim.health.SimOverflowError` if a world overflowed a buffer.

        Reads the flags on the host (a sync), so call it outside the hot loop, e.g. every few hundred steps.
        """
        error = self._overflow_error()
        if error is not None:
            raise error

    def _overflow_error(self):
        bits = self._overflow_t.cpu().numpy()  # ordered after the graphs: they run on torch's current stream
        return overflow_error(bits, self.config.health_overflow_mask, self.config.nconmax, self.config.njmax)

    def __repr__(self) -> str:
        return (
            f"WarpSim(num_worlds={self.num_worlds}, device={self.device}, substeps={self.config.substeps}, "
            f"nconmax={self.config.nconmax}, njmax={self.config.njmax}, dt={self.physics_dt}x{self.config.substeps})"
        )
