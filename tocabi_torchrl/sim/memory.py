"""An up-front memory check: refuse a world count that cannot fit before allocating it.

Without it, ``num_envs=10**9`` on the CPU backend allocates ``MjData`` after ``MjData`` until the machine runs out of
memory. Each backend estimates its bytes per world from the compiled model (:func:`warp_world_bytes`,
:func:`mujoco_world_bytes`) and :func:`check_fits` compares ``num_worlds ×`` that with the memory available now
(``/proc/meminfo``'s MemAvailable, or ``os.sysconf``, for the host; ``torch.cuda.mem_get_info`` on a GPU). The
estimate covers the simulator alone (an env, transforms and a training rollout add more), so passing it does not
promise that training fits; failing it means the worlds alone cannot.
"""

from __future__ import annotations

import dataclasses
import os

import mujoco
import torch

__all__ = ["available_bytes", "check_fits", "epa_slot_bytes", "mujoco_world_bytes", "warp_world_bytes",
           "MUJOCO_OVERHEAD", "MODEL_OVERHEAD"]

#: Resident memory of a C MuJoCo world over the bytes its ``MjData`` uses (buffer, used arena and stack): the Python
#: binding's arrays and the allocator. Measured for TOCABI: 636 kB RSS per ``MjData`` against 235 kB used (2.7×).
MUJOCO_OVERHEAD = 3.0
#: Resident memory of a copied ``MjModel`` over its ``nbuffer``: the binding's array objects and the allocator.
#: Measured for TOCABI (MuJoCo 4.0.1): 1,061-1,077 KiB RSS per copy against 878 KiB of buffer (1.21×).
MODEL_OVERHEAD = 1.25


def available_bytes(device: torch.device) -> int | None:
    """Memory that can still be allocated on ``device`` (host memory for the CPU), or ``None`` if unknown."""
    if device.type == "cuda":
        free, _total = torch.cuda.mem_get_info(device)
        return int(free)
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _gib(n: float) -> str:
    return f"{n / 2**30:,.2f} GiB" if n >= 2**27 else f"{n / 2**20:,.1f} MiB"


def check_fits(num_worlds: int, bytes_per_world: int, device: torch.device, what: str) -> None:
    """Raise ``ValueError`` naming the estimate and the limit if ``num_worlds`` worlds cannot fit on ``device``."""
    available = available_bytes(device)
    need = num_worlds * bytes_per_world
    if available is not None and need > available:
        where = f"is free on {device}" if device.type == "cuda" else "of host memory is available"
        raise ValueError(
            f"{num_worlds:,} {what} worlds need about {_gib(need)} ({bytes_per_world / 1024:,.0f} KiB per world, "
            f"estimated from the model) but only {_gib(available)} {where}; lower num_envs to at most "
            f"{max(available // bytes_per_world, 0):,}")


def mujoco_world_bytes(mj: mujoco.MjModel, per_world_fields: tuple[str, ...] = ()) -> int:
    """Resident bytes of one C MuJoCo world of ``mj``: its ``MjData`` after a forward pass (buffer, used arena and
    stack) times :data:`MUJOCO_OVERHEAD`, plus the backend's float64 staging and float32 tensors. With
    ``per_world_fields`` (``SimConfig.per_world_fields``: dynamics randomisation) also the world's own model copy
    (``nbuffer`` times :data:`MODEL_OVERHEAD`) and its two float64 rows of those fields (the rows the user writes
    and the rows its model took)."""
    probe = mujoco.MjData(mj)
    mujoco.mj_forward(mj, probe)
    used = probe.nbuffer + probe.maxuse_arena + probe.maxuse_stack
    per_row = mj.nq + mj.nv + mj.nsensordata + 7 * mj.nbody + mj.nu + 1  # qpos, qvel, sensors, xpos+xquat, forces
    world = int(MUJOCO_OVERHEAD * used) + 12 * per_row + 4 * (mj.nq + mj.nv + mj.nu)
    if per_world_fields:
        rows = sum(getattr(mj, name).size for name in per_world_fields)
        world += int(MODEL_OVERHEAD * mj.nbuffer) + 2 * 8 * rows
    return world


def warp_world_bytes(mj: mujoco.MjModel, nconmax: int, njmax: int, nccdmax: int = 0) -> int:
    """Bytes of one mujoco-warp world of ``mj`` (every array of a one-world ``mujoco_warp.Data`` with these buffer
    sizes, on the CPU, which allocates nothing on the GPU), the backend's own per-world buffers and ``nccdmax``
    slots of the convex narrowphase's EPA scratch (:func:`epa_slot_bytes`, allocated when collision first runs)."""
    import mujoco_warp as mjw
    import warp as wp

    with wp.ScopedDevice("cpu"):
        data = mjw.make_data(mj, nworld=1, nconmax=nconmax, njmax=njmax)
    own = 4 * (2 * mj.nq + 2 * mj.nv + 3 * mj.nu + mj.nsensordata + 8)  # reset, snapshot and signal buffers
    return _array_bytes(data) + own + nccdmax * epa_slot_bytes(mj)


#: mujoco-warp 4.0's EPA polytope bounds: faces added per iteration and horizon edges (``MJ_MAX_EPAFACES``,
#: ``MJ_MAX_EPAHORIZON``).
_EPA_FACES_PER_ITERATION, _EPA_HORIZON = 5, 24


def epa_slot_bytes(mj: mujoco.MjModel) -> int:
    """Bytes of one slot of mujoco-warp's EPA scratch for ``mj``: the polytope's vertices (vec3 + index) and faces
    (three indices, the origin's projection and its squared norm) for ``opt.ccd_iterations`` iterations, and the
    horizon. TOCABI (35 iterations): about 5 KB."""
    it = int(mj.opt.ccd_iterations)
    vertices, faces = 10 + 2 * it, 6 + _EPA_FACES_PER_ITERATION * it
    return vertices * (12 + 4) + faces * (4 + 12 + 4) + _EPA_HORIZON * 4


def _array_bytes(obj) -> int:
    import warp as wp

    total = 0
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if isinstance(value, wp.array):
            total += value.capacity
        elif dataclasses.is_dataclass(value) and not isinstance(value, type):
            total += _array_bytes(value)
    return total
