"""``MujocoSim``: N TOCABI worlds stepped by MuJoCo's C engine on CPU threads, behind ``WarpSim``'s interface.

The CPU baseline (TocabiLab's comparison system ran C MuJoCo, one environment per core) and the reference the GPU
engine is checked against (``tests/test_engine_parity.py``). Each world is one ``mujoco.MjData`` of the same compiled
model (float64); a persistent thread pool steps contiguous chunks of worlds, and ``mujoco.mj_step`` releases the GIL,
so the chunks run in parallel on ``SimConfig.threads`` cores.

Precision and copies. The physics state stays float64 inside each ``MjData`` for the whole episode. The tensors the
environment sees (same names, shapes and float32 dtype as ``WarpSim``'s, see its docstring) are float32 torch
buffers: after every step / reset / forward the new state is gathered row by row into float64 staging arrays and
cast into them in one vectorised copy per buffer; before every step ``ctrl`` is copied from its float32 tensor into
each ``MjData``. Writing ``qpos``/``qvel`` directly (tests and debugging, as with ``WarpSim``) is supported: a world
whose float32 state differs from what was last published gets it pushed back into its ``MjData`` (so that world, and
only that world, is rounded to float32 once) and takes a full ``mj_step`` first, which re-checks the state.

Step semantics match ``WarpSim``: one :meth:`step` is ``substeps`` physics steps (sensors off inside them, unless
``SimConfig.sensors_every_substep``), the actuator forces of the last substep are kept, then ``mj_forward`` so that
positions, sensors and contact signals describe the post-step state, and its constraint solution becomes the solver's
warm start. Since that forward pass already computed the position and velocity stages of the new state, the next
step's first substep is ``mj_step2``; the trajectory is bit-identical to ``mj_step`` × ``substeps`` after such a
forward pass (``tests/test_sim_mujoco.py``).

Per-world model fields (``SimConfig.per_world_fields``): each world then steps its own copy of the model (one copy: its
substeps switch the copy's sensor flag off and back, as only that world's thread uses it), and
:attr:`MujocoSim.model_fields` holds every world's row of those fields as float64 tensors. A world whose rows changed
since they were last taken gets them copied into its models before its next step, reset or forward pass (only that
world's; the comparison is one vectorised check per field). Without the option every world reads the one compiled model,
as before.

Contact signals come from the same contact sensors and :class:`~tocabi_torchrl.sim.contacts.ContactLayout` sums as
the warp backend. Health: finite qpos/qvel/sensordata and none of
:data:`~tocabi_torchrl.sim.mujoco_health.MUJOCO_HEALTH_WARNINGS` since the world's last reset (C MuJoCo resets a
diverged world, a non-finite qacc included, itself and says so only through its warnings).
"""

from __future__ import annotations

import copy
import weakref
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from types import MappingProxyType
from typing import Callable

import mujoco
import numpy as np
import torch

from .config import SimConfig
from .contacts import ContactLayout, contact_layout
from .memory import check_fits, mujoco_world_bytes
from .model import ModelSource, compile_model
from .mujoco_health import MUJOCO_HEALTH_WARNINGS, warning_bits, warning_error
from .views import MocapPositions, SimViews, world_mocap_pos

__all__ = ["MujocoSim"]


def _check_cpu(device) -> torch.device:
    name = str(device)
    if name == "cuda" or name.startswith("cuda:"):
        raise ValueError(
            f"MujocoSim runs MuJoCo's C engine on the CPU; got device {name!r}. Use device='cpu', or WarpSim "
            "(backend='warp') for CUDA"
        )
    if name != "cpu":
        raise ValueError(f"unknown device {name!r}: MujocoSim runs on 'cpu'")
    return torch.device("cpu")


class MujocoSim(SimViews):
    """N worlds of one MuJoCo model stepped by C MuJoCo on CPU threads, with float32 torch tensors of the state.

    Args:
        config: :class:`SimConfig`; ``num_worlds``, ``substeps``, the solver overrides, ``sensors_every_substep`` and
            ``threads`` apply (the mujoco-warp buffer settings do not, see :class:`SimConfig`). ``device`` must be
            ``"cpu"``.
        model, mocap_pos: as for :class:`~tocabi_torchrl.sim.WarpSim` (the per-world mocap positions live in each
            world's ``MjData``, so every world shares the one compiled model unless ``per_world_fields`` is set).

    Tensors: the same names, shapes and dtypes as ``WarpSim`` (see its docstring), on the CPU. They are the
    simulator's own buffers: writing ``ctrl`` is how actions reach the physics, and they are overwritten by the next
    :meth:`step` / :meth:`reset` / :meth:`forward`, so clone what you keep. ``overflow`` holds ``1 << mjtWarning``
    bits (``mujoco_health.warning_bits``) instead of mujoco-warp's ``OverflowType`` bits.
    """

    def __init__(self, config: SimConfig | None = None, model: ModelSource = None,
                 mocap_pos: MocapPositions | None = None):
        cfg = copy.deepcopy(config) if config is not None else SimConfig()
        cfg.validate()
        self.config = cfg
        self.device = _check_cpu(cfg.device)
        self.num_worlds = n = cfg.num_worlds
        self.threads = min(cfg.resolved_threads(), n)

        mj = compile_model(model, cfg)
        check_fits(n, mujoco_world_bytes(mj, tuple(cfg.per_world_fields)), self.device, "C MuJoCo")
        self.mj_model = mj
        self.contact_layout: ContactLayout = contact_layout(mj)
        #: (N, nmocap, 3) float64 mocap positions each world starts and resets with, or None (the model's).
        self.world_mocap_pos = world_mocap_pos(mj, n, mocap_pos)
        self.nq, self.nv, self.nu = mj.nq, mj.nv, mj.nu
        self.physics_dt = float(mj.opt.timestep)
        self.control_dt = self.physics_dt * cfg.substeps
        # Substeps skip sensors (only the post-step forward pass's values are ever visible): same physics, less work.
        self._substep_model = mj
        if not cfg.sensors_every_substep:
            self._substep_model = copy.deepcopy(mj)
            self._substep_model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_SENSOR)
        self._per_world_models(mj)
        self._data = [mujoco.MjData(mj) for _ in range(n)]
        #: The ``MjData`` of each world (float64), for inspection; change state through reset/ctrl, not here.
        self.mj_data: tuple[mujoco.MjData, ...] = tuple(self._data)
        self._chunks = [c for c in np.array_split(np.arange(n), self.threads) if len(c)]
        self._pool = None
        if self.threads > 1:
            self._pool = ThreadPoolExecutor(max_workers=self.threads, thread_name_prefix="MujocoSim")
            weakref.finalize(self, self._pool.shutdown, wait=False)
        self._alloc_buffers(mj)
        self._make_derived_views(mj)
        self.reset(torch.ones(n, dtype=torch.bool), torch.as_tensor(mj.qpos0, dtype=torch.float32),
                   torch.zeros(self.nv))

    # ----------------------------------------------------------------------------------------------- construction
    def _per_world_models(self, mj: mujoco.MjModel) -> None:
        """``SimConfig.per_world_fields``: a model per world and the (N, ...) float64 rows of those fields; nothing
        without them."""
        names, n = tuple(self.config.per_world_fields), self.num_worlds
        self._world_models = None
        self._model_fields: dict[str, torch.Tensor] = {}
        self._fields_taken: dict[str, torch.Tensor] = {}  # the rows each world's models hold
        if not names:
            return
        self._world_models = [copy.deepcopy(mj) for _ in range(n)]
        for name in names:
            nominal = np.asarray(getattr(mj, name), dtype=np.float64)
            self._model_fields[name] = torch.from_numpy(np.broadcast_to(nominal, (n, *nominal.shape)).copy())
            self._fields_taken[name] = self._model_fields[name].clone()
        self._field_rows = {name: t.numpy() for name, t in self._model_fields.items()}  # read by the worker threads

    @property
    def model_fields(self) -> Mapping[str, torch.Tensor]:
        """``{name: (N, ...) float64}`` each world's row of the ``SimConfig.per_world_fields`` model fields (as
        ``WarpSim.model_fields``, in the C engine's float64), a read-only mapping: write rows in place to change a
        world's physics from its next step, reset or forward pass. Empty when the config names none."""
        # Read-only: a rebound entry would reach no world's physics (the models read the first tensor).
        return MappingProxyType(self._model_fields)

    def _changed_fields(self) -> np.ndarray | None:
        """(N,) bool: worlds whose ``model_fields`` rows differ from what their models hold (None without any)."""
        if not self._model_fields:
            return None
        changed = torch.zeros(self.num_worlds, dtype=torch.bool)
        for name, rows in self._model_fields.items():
            changed |= (rows != self._fields_taken[name]).flatten(1).any(dim=1)
        return changed.numpy()

    def _fields_were_taken(self, rows: np.ndarray | None) -> None:
        """Record that the worlds of ``rows`` (all if None) took their ``model_fields`` rows."""
        for name, taken in self._fields_taken.items():
            if rows is None:
                taken.copy_(self._model_fields[name])
            else:
                idx = torch.from_numpy(rows)
                taken[idx] = self._model_fields[name][idx]

    def _model(self, w: int, changed: np.ndarray | None) -> mujoco.MjModel:
        """World ``w``'s model: the shared one, or (per-world fields) its own after taking its changed rows."""
        if self._world_models is None:
            return self.mj_model
        m = self._world_models[w]
        if changed[w]:
            for name, rows in self._field_rows.items():
                getattr(m, name)[:] = rows[w]
        return m

    def _alloc_buffers(self, mj: mujoco.MjModel) -> None:
        n, f32 = self.num_worlds, torch.float32
        # float64 staging rows, filled by the worker threads (each writes only its own worlds' rows).
        self._staged = {
            "qpos": np.zeros((n, mj.nq)),
            "qvel": np.zeros((n, mj.nv)),
            "sensordata": np.zeros((n, mj.nsensordata)),
            "xpos": np.zeros((n, mj.nbody, 3)),
            "xquat": np.zeros((n, mj.nbody, 4)),
            "time": np.zeros(n),
            "applied_force": np.zeros((n, mj.nu)),
            "mass_matrix": np.zeros((n, mj.nC)),
            "qfrc_bias": np.zeros((n, mj.nv)),
        }
        self._warnings = np.zeros((n, int(mujoco.mjtWarning.mjNWARNING)), dtype=np.int32)
        # The float32 tensors the env sees, one per staging array.
        self._qpos, self._qvel = torch.zeros(n, mj.nq, dtype=f32), torch.zeros(n, mj.nv, dtype=f32)
        self._ctrl = torch.zeros(n, mj.nu, dtype=f32)
        self._xfrc_t = torch.zeros(n, mj.nbody, 6, dtype=f32)
        self._xfrc_np = self._xfrc_t.numpy()  # the same memory, read by the worker threads
        self._substep_cols = list(self._substep_columns(mj))
        self._substep_ctrl_t = (torch.zeros(n, self.config.substeps, len(self._substep_cols), dtype=f32)
                                if self._substep_cols else None)
        self._sensordata = torch.zeros(n, mj.nsensordata, dtype=f32)
        self._xpos, self._xquat = torch.zeros(n, mj.nbody, 3, dtype=f32), torch.zeros(n, mj.nbody, 4, dtype=f32)
        self._time = torch.zeros(n, dtype=f32)
        self._applied_force_t = torch.zeros(n, mj.nu, dtype=f32)
        self._mass_matrix, self._qfrc_bias = torch.zeros(n, mj.nC, dtype=f32), torch.zeros(n, mj.nv, dtype=f32)
        self._published = {
            "qpos": self._qpos,
            "qvel": self._qvel,
            "sensordata": self._sensordata,
            "xpos": self._xpos,
            "xquat": self._xquat,
            "time": self._time,
            "applied_force": self._applied_force_t,
            "mass_matrix": self._mass_matrix,
            "qfrc_bias": self._qfrc_bias,
        }
        # What was last published, to find worlds whose qpos/qvel were written directly.
        self._shown_qpos, self._shown_qvel = self._qpos.clone(), self._qvel.clone()
        signals = torch.zeros(n, len(self.contact_layout.weights), dtype=torch.bool)
        self._signal_views(signals)
        self._signals = signals
        self._healthy_t = torch.zeros(n, dtype=torch.bool)
        self._overflow_t = torch.zeros(n, dtype=torch.int32)

    # ------------------------------------------------------------------------------------------- per-world work
    def _gather(self, w: int, d: mujoco.MjData) -> None:
        """Copy world ``w``'s post-step state into the float64 staging rows."""
        s = self._staged
        s["qpos"][w] = d.qpos
        s["qvel"][w] = d.qvel
        s["sensordata"][w] = d.sensordata
        s["xpos"][w] = d.xpos
        s["xquat"][w] = d.xquat
        s["time"][w] = d.time
        s["mass_matrix"][w] = d.M  # MjData.M: mj_forward's sparse (CSR) inertia, the layout of mujoco-warp's Data.M
        s["qfrc_bias"][w] = d.qfrc_bias
        self._warnings[w] = d.warning.number

    def _step_world(self, w: int, ctrl: np.ndarray, dirty: np.ndarray, qpos: np.ndarray, qvel: np.ndarray,
                    changed: np.ndarray | None) -> None:
        model, d, cols = self._model(w, changed), self._data[w], self._substep_cols
        m = self._substep_model  # the shared model's sensor-free copy
        if model is not self.mj_model:  # the world's own model, with the substep copy's flags during the substeps
            m = model
            m.opt.disableflags = self._substep_model.opt.disableflags
        schedule = self._substep_ctrl_t[w].numpy() if cols else None
        d.ctrl[:] = ctrl[w]
        d.xfrc_applied[:] = self._xfrc_np[w]
        if cols:
            d.ctrl[cols] = schedule[0]
        if dirty[w]:
            # qpos/qvel were written directly: take them, and run a full step (it checks them and recomputes).
            d.qpos[:], d.qvel[:] = qpos[w], qvel[w]
            mujoco.mj_step(m, d)
        else:
            mujoco.mj_step2(m, d)  # the position/velocity stages were computed by the previous forward pass
        for s in range(1, self.config.substeps):
            if cols:
                d.ctrl[cols] = schedule[s]
            mujoco.mj_step(m, d)
        self._staged["applied_force"][w] = d.actuator_force  # the forward pass below overwrites it
        if m is model:  # the world's own model: its sensors back on for the forward pass
            model.opt.disableflags = self.mj_model.opt.disableflags
        self._forward_and_warm_start(model, d)
        self._gather(w, d)

    def _forward_and_warm_start(self, m: mujoco.MjModel, d: mujoco.MjData) -> None:
        """``mj_forward``, then its constraint solution warm-starts the next solve (as in ``WarpSim``)."""
        mujoco.mj_forward(m, d)
        d.qacc_warmstart[:] = d.qacc

    def _reset_world(self, w: int, qpos: np.ndarray, qvel: np.ndarray, ctrl: np.ndarray,
                     changed: np.ndarray | None) -> None:
        m, d = self._model(w, changed), self._data[w]
        mujoco.mj_resetData(m, d)  # clears time, activations, warm start and warning counters
        if self.world_mocap_pos is not None:  # mj_resetData put the model's mocap positions back
            d.mocap_pos[:] = self.world_mocap_pos[w]
        d.qpos[:], d.qvel[:], d.ctrl[:] = qpos[w], qvel[w], ctrl[w]
        self._forward_and_warm_start(m, d)
        # Nothing was applied yet: report what the actuators would apply in the reset state (as WarpSim does).
        self._staged["applied_force"][w] = d.actuator_force
        self._gather(w, d)

    def _forward_world(self, w: int, ctrl: np.ndarray, dirty: np.ndarray, qpos: np.ndarray, qvel: np.ndarray,
                       changed: np.ndarray | None) -> None:
        m, d = self._model(w, changed), self._data[w]
        d.ctrl[:] = ctrl[w]
        d.xfrc_applied[:] = self._xfrc_np[w]
        if dirty[w]:
            d.qpos[:], d.qvel[:] = qpos[w], qvel[w]
        self._forward_and_warm_start(m, d)
        self._gather(w, d)

    def _run(self, fn: Callable[..., None], worlds: np.ndarray | None, *args) -> None:
        """``fn(w, *args)`` for every world in ``worlds`` (all if ``None``), chunks of worlds in parallel threads."""
        chunks = self._chunks if worlds is None else [c for c in np.array_split(worlds, self.threads) if len(c)]

        def run_chunk(chunk: np.ndarray) -> None:
            for w in chunk.tolist():
                fn(w, *args)

        if self._pool is None or len(chunks) < 2:
            for c in chunks:
                run_chunk(c)
            return
        for future in [self._pool.submit(run_chunk, c) for c in chunks]:
            future.result()  # re-raises a worker's exception here

    # ------------------------------------------------------------------------------------------ host <-> torch
    def _dirty(self) -> np.ndarray:
        """(N,) bool: worlds whose qpos/qvel tensors differ from what the simulator last published."""
        changed = (self._qpos != self._shown_qpos).any(dim=1) | (self._qvel != self._shown_qvel).any(dim=1)
        return changed.numpy()

    def _publish(self, rows: np.ndarray | None = None) -> None:
        """Cast the staged float64 rows (all, or ``rows``) into the float32 tensors, then derive flags."""
        idx = None if rows is None else torch.from_numpy(rows)
        for name, tensor in self._published.items():
            staged = torch.from_numpy(self._staged[name])
            if idx is None:
                tensor.copy_(staged)
            else:
                tensor[idx] = staged[idx].to(tensor.dtype)
        if idx is None:
            self._shown_qpos.copy_(self._qpos)
            self._shown_qvel.copy_(self._qvel)
        else:  # other worlds keep any direct write pending, to be pushed by the next step or forward
            self._shown_qpos[idx] = self._qpos[idx]
            self._shown_qvel[idx] = self._qvel[idx]
        self._signals.copy_(self.contact_layout.signals(self._sensordata))
        self._overflow_t.copy_(torch.from_numpy(warning_bits(self._warnings)))
        # A non-finite qacc makes MuJoCo reset the world and warn (mjWARN_BADQACC), which the warning bits catch.
        finite = (torch.isfinite(self._qpos).all(dim=1) & torch.isfinite(self._qvel).all(dim=1)
                  & torch.isfinite(self._sensordata).all(dim=1))
        self._healthy_t.copy_(finite & ((self._overflow_t & MUJOCO_HEALTH_WARNINGS) == 0))

    def _host_inputs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        return self._ctrl.numpy(), self._dirty(), self._qpos.numpy(), self._qvel.numpy(), self._changed_fields()

    # ------------------------------------------------------------------------------------------------- public API
    def step(self) -> None:
        """Advance every world by one control period (``substeps`` physics steps) with the current ``ctrl``."""
        self._run(self._step_world, None, *self._host_inputs())
        self._fields_were_taken(None)
        if self._substep_cols:
            # As in WarpSim, whose substeps write these columns of the ctrl the physics reads: they hold the last
            # substep's controls, which the post-step forward pass used, so a later forward() uses them too.
            self._ctrl[:, self._substep_cols] = self._substep_ctrl_t[:, -1]
        self._publish()

    def forward(self) -> None:
        """Recompute positions, sensors and flags from the current qpos/qvel/ctrl (after writing them directly)."""
        self._run(self._forward_world, None, *self._host_inputs())
        self._fields_were_taken(None)
        self._publish()

    def reset(
        self,
        mask: torch.Tensor,
        qpos: torch.Tensor,
        qvel: torch.Tensor,
        ctrl: torch.Tensor | None = None,
    ) -> None:
        """Put the flagged worlds into the given state; the others stay bit-identical (same contract as
        :meth:`WarpSim.reset <tocabi_torchrl.sim.WarpSim.reset>`: (N,) bool mask, (N, nq)/(nq,) qpos, (N, nv)/(nv,)
        qvel, optional (N, nu)/(nu,) ctrl, zeros if ``None``; NaN or inf in a flagged world's rows is refused).

        A flagged world is cleared by ``mj_resetData`` (time, activations, warm start, warning counters), takes the
        given state, and a forward pass fills positions, sensors and flags.
        """
        self._check_reset_args(mask, qpos, qvel, ctrl)
        n = self.num_worlds
        rows = np.flatnonzero(mask.numpy())
        # A start state is data, not graph: one that requires grad failed in numpy(), and would have put ctrl's
        # buffer into the caller's autograd graph, where WarpSim takes it as a plain copy.
        ctrl = torch.zeros(self.nu) if ctrl is None else ctrl.detach()
        qpos, qvel = qpos.detach(), qvel.detach()
        qpos, qvel, ctrl = (x.to(torch.float32).expand(n, -1) for x in (qpos, qvel, ctrl))
        idx = torch.from_numpy(rows)
        self._ctrl[idx] = ctrl[idx]
        self._xfrc_t[idx] = 0.0  # as mj_resetData clears the world's applied forces
        self._run(self._reset_world, rows, qpos.numpy(), qvel.numpy(), ctrl.numpy(), self._changed_fields())
        self._fields_were_taken(rows)
        self._publish(rows)

    def check_overflow(self) -> None:
        """Raise :class:`~tocabi_torchrl.sim.health.SimOverflowError` if a world raised a health warning."""
        error = warning_error(self._overflow_t.numpy())
        if error is not None:
            raise error

    def __getstate__(self) -> dict:
        if self._pool is not None:  # else pickle's own "cannot pickle '_queue.SimpleQueue' object"
            raise TypeError(f"MujocoSim with {self.threads} worker threads cannot be copied or pickled (its thread "
                            "pool cannot): build one env per process or copy, e.g. pass an env factory "
                            "(lambda: TocabiWalk(...)) to ParallelEnv, or build it with sim_threads=1")
        return self.__dict__

    def close(self) -> None:
        """Stop the worker threads (also done when the simulator is garbage collected)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def __repr__(self) -> str:
        return (
            f"MujocoSim(num_worlds={self.num_worlds}, threads={self.threads}, substeps={self.config.substeps}, "
            f"dt={self.physics_dt}x{self.config.substeps})"
        )
