"""Configuration of the physics backends (:class:`~tocabi_torchrl.sim.WarpSim`,
:class:`~tocabi_torchrl.sim.MujocoSim`)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import TYPE_CHECKING

from ..tree import check_field_types
from ..value_rules import NON_NEGATIVE, plain_number
from .buffers import CONTACT_SENSOR_MAXMATCH, NCCDMAX, NCONMAX, NJMAX

if TYPE_CHECKING:
    import torch

__all__ = ["SimConfig", "NCONMAX", "NCCDMAX", "NJMAX", "CONTACT_SENSOR_MAXMATCH", "RESET_PASSES", "PER_WORLD_FIELDS",
           "DEFAULT_HEALTH_OVERFLOW_MASK", "available_cores"]

#: ``SimConfig.health_overflow_mask``'s default: the ``mujoco_warp.OverflowType`` bits of
#: ``sim.health.HEALTH_OVERFLOW_MASK`` (NEFC 1 | NJMAX_NNZ 2 | BROADPHASE 4 | NARROWPHASE 8 | CCD 16 | HFIELD 32 |
#: NVMAX 128), written as a number so that this module (and the config tree) reads without importing mujoco-warp;
#: tests/test_sim_backend.py checks that the two agree.
DEFAULT_HEALTH_OVERFLOW_MASK = 0b1011_1111

#: ``SimConfig.reset_pass`` values: the full forward pass, or the reduced one for registered start states.
RESET_PASSES = ("full", "reduced")
#: ``SimConfig.per_world_fields`` values: the model fields a backend can give one row per world (all of them are
#: per-world ("batched") fields of mujoco-warp's ``Model``; ``tocabi_torchrl.sim.dynamics`` draws them).
PER_WORLD_FIELDS = ("body_mass", "body_inertia", "body_subtreemass", "dof_damping", "dof_armature", "geom_friction")


def compact_reset_capacity(num_worlds: int) -> int:
    """How many reset worlds the reduced reset pass holds in its second, small ``Data``
    (:class:`~tocabi_torchrl.sim.compact_reset.CompactResetPass`): one in 64 from 4,096 worlds on (64 there, 256 at
    16,384), where it took about 0.3 and 1.8 ms off each training step on an H100; 0, the pass over every world,
    below, where that pass costs about what the small one does. A step that resets more worlds takes them that many
    at a time (docs/benchmarks/reset_pass_cost/)."""
    return num_worlds // 64 if num_worlds >= 4096 else 0


def available_cores() -> int:
    """CPU cores this process may run on (its affinity mask, which container limits shrink; else the machine's)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


@dataclass
class SimConfig:
    """What to simulate and how.

    Attributes:
        num_worlds: number of parallel worlds N (>= 1).
        device: ``"cpu"``, ``"cuda"`` or ``"cuda:N"`` (or the equivalent ``torch.device``).
        substeps: physics steps per :meth:`WarpSim.step` (8: 2 kHz physics, 250 Hz control for a 0.5 ms timestep).
        nconmax: contacts per world (pooled over worlds), see :data:`NCONMAX`.
        njmax: constraint rows per world, see :data:`NJMAX`.
        nccdmax: convex-collision (GJK/EPA) candidate pairs per world, pooled over worlds, at most ``nconmax``;
            ``None``: :data:`NCCDMAX` (or ``nconmax`` if that is smaller). It sizes the EPA scratch (~5 KB a slot).
        contact_sensor_maxmatch: mujoco-warp contact-sensor slots, see :data:`CONTACT_SENSOR_MAXMATCH`.
        solver_iterations, solver_ls_iterations, solver_tolerance: explicit overrides of the model's solver options;
            ``None`` keeps what the model file says (the backend never changes physics on its own).
        use_graph: capture step/reset/forward as warp graphs (CUDA graphs on GPU, warp's recorded replay on CPU);
            ``False`` runs the same functions eagerly, for debugging.
        sensors_every_substep: evaluate sensors in every substep as ``mujoco_warp.step`` does. Off by default:
            only the values after the final forward pass are ever visible, so intermediate sensor work is wasted.
        health_overflow_mask: ``mujoco_warp.OverflowType`` bits that make a world unhealthy (default: the buffer
            overflows that silently drop contacts or constraints).
        kernel_overflow_prints: let mujoco-warp kernels print their own overflow warnings (one line per world and
            substep on the GPU, so off by default; use :meth:`WarpSim.check_overflow` instead).
        reset_pass: what :class:`WarpSim`'s reset computes over all worlds (issue 25). ``"full"`` (default): a full
            ``mujoco_warp.forward``, whatever the reset states. ``"reduced"``: for states registered in advance with
            :meth:`WarpSim.register_start_states` and reset with :meth:`WarpSim.reset_to_start`, only the position
            and velocity stages (``fwd_position``, ``fwd_velocity``: kinematics, inertia and its factorisation,
            collision, constraints, bias forces) run over all worlds; the reset worlds get the sensors, ``qacc``
            (also their warm start), actuator forces and solver overflow bits of their start state from a table
            that a full pass filled at registration (per world and start state, so per-world obstacles are
            included). Nothing else that a step reads comes from the skipped stages, so the trajectories match the
            full pass. :meth:`WarpSim.reset` with arbitrary states always runs the full pass.
        substep_ctrl: actuator indices whose control changes inside a step (an actuator delay of k physics
            substeps, ``tocabi_torchrl.control.Delay``): before physics substep s, actuator ``substep_ctrl[j]`` takes
            the value ``sim.substep_ctrl[:, s, j]`` instead of ``ctrl``. Empty (default): ``ctrl`` holds for the whole
            step and nothing is copied.
        per_world_fields: model fields (names of :data:`PER_WORLD_FIELDS`) that get one row per world, exposed as
            the simulator's ``model_fields[name]`` (N, ...) tensors; writing a row changes that world's physics from
            its next step, reset or forward pass (``tocabi_torchrl.sim.dynamics`` draws them at every reset). Empty
            (default): every world reads the one compiled model, as before the field existed.
        threads: CPU threads that step the worlds of :class:`MujocoSim` (``None``: every available core, see
            :func:`available_cores`). Ignored by ``WarpSim``, as are ``MujocoSim``'s own limits: ``nconmax``,
            ``njmax``, ``contact_sensor_maxmatch``, ``use_graph``, ``health_overflow_mask``,
            ``kernel_overflow_prints`` and ``reset_pass`` are mujoco-warp settings (C MuJoCo grows its buffers in the
            model's arena).
    """

    num_worlds: int = 1
    device: str | torch.device = "cpu"
    substeps: int = 8
    nconmax: int = NCONMAX
    njmax: int = NJMAX
    nccdmax: int | None = None
    contact_sensor_maxmatch: int = CONTACT_SENSOR_MAXMATCH
    solver_iterations: int | None = None
    solver_ls_iterations: int | None = None
    solver_tolerance: float | None = None
    use_graph: bool = True
    sensors_every_substep: bool = False
    health_overflow_mask: int = DEFAULT_HEALTH_OVERFLOW_MASK
    kernel_overflow_prints: bool = False
    threads: int | None = None
    reset_pass: str = "full"
    substep_ctrl: tuple[int, ...] = ()
    per_world_fields: tuple[str, ...] = ()

    @property
    def ccd_per_world(self) -> int:
        """The convex-collision slots per world this config allocates (``nccdmax``, or its default)."""
        return self.nccdmax if self.nccdmax is not None else min(NCCDMAX, self.nconmax)

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad field and what it should be."""

        def positive_int(name: str) -> None:
            # A numpy int or a 0-d tensor counts as the int it holds, as in the env's config tree, and is kept as one.
            v = plain_number(getattr(self, name))
            if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
                raise ValueError(f"SimConfig.{name} must be a positive int, got {getattr(self, name)!r}")
            setattr(self, name, v)

        for name in ("num_worlds", "substeps", "nconmax", "njmax", "contact_sensor_maxmatch"):
            positive_int(name)
        for name in ("solver_iterations", "solver_ls_iterations", "threads", "nccdmax"):
            if getattr(self, name) is not None:
                positive_int(name)
        # The switches and the overflow mask: "no" is truthy (sensors_every_substep="no" evaluated the sensors in
        # every substep) and 1.5 was cut to 1 when the mask reached the health kernel.
        check_field_types(self, "SimConfig.")
        tol = self.solver_tolerance
        if tol is not None and not NON_NEGATIVE.allows(tol):
            # inf stopped MuJoCo's solver after one iteration and True set 1.0, both without a word; text failed as
            # a raw comparison error.
            raise ValueError(f"SimConfig.solver_tolerance must be {NON_NEGATIVE.describe()} (the solver's "
                             f"tolerance; None keeps the model file's), got {tol!r}")
        self.solver_tolerance = plain_number(tol)
        if self.reset_pass not in RESET_PASSES:
            raise ValueError(f"SimConfig.reset_pass must be one of {RESET_PASSES}, got {self.reset_pass!r}")
        cols = self.substep_ctrl
        if (not isinstance(cols, (tuple, list)) or len(set(cols)) != len(cols)
                or any(isinstance(c, bool) or not isinstance(c, int) or c < 0 for c in cols)):
            raise ValueError(f"SimConfig.substep_ctrl must be distinct actuator indices >= 0, got {cols!r}")
        fields = self.per_world_fields
        if (not isinstance(fields, (tuple, list)) or len(set(fields)) != len(fields)
                or any(f not in PER_WORLD_FIELDS for f in fields)):
            raise ValueError(f"SimConfig.per_world_fields must be distinct names of {PER_WORLD_FIELDS}, got {fields!r}")
        if self.nccdmax is not None and self.nccdmax > self.nconmax:
            raise ValueError(f"SimConfig.nccdmax ({self.nccdmax}) must be <= nconmax ({self.nconmax}): mujoco-warp "
                             "takes convex-collision pairs from the contact pool")
        import torch  # here, not at the top: the config tree reads this module without torch

        if not isinstance(self.device, (str, torch.device)):
            raise ValueError(f"SimConfig.device must be a string like 'cpu' or 'cuda:0', got {self.device!r}")

    def resolved_threads(self) -> int:
        """``threads``, or every available core when it is ``None``."""
        return self.threads if self.threads is not None else available_cores()
