"""Small warp kernels the backend launches inside its captured graphs (one thread per world).

They are warp kernels rather than torch ops because torch cannot record into a graph that warp captures (and on the
CPU, warp replays its own recording), so the derived signals are computed in the same graph as the physics.
"""

from __future__ import annotations

import warp as wp

from mujoco_warp import OverflowType

__all__ = ["derive_signals", "write_reset_state", "copy_rows_where", "copy_start_rows", "or_start_overflow",
           "contact_buffer_bits", "NARROWPHASE"]

_NEFC = int(OverflowType.NEFC)
_BROADPHASE = int(OverflowType.BROADPHASE)
#: mujoco-warp's flag of a contact that did not fit the contact buffer.
NARROWPHASE = int(OverflowType.NARROWPHASE)


@wp.func
def contact_buffer_bits(nacon: int, ncollision: int, naconmax: int) -> int:
    """The overflow bits of a contact buffer of ``naconmax`` rows shared by the worlds: BROADPHASE where more
    collision candidates than that were found, NARROWPHASE where more contacts (mujoco-warp leaves its counts past
    the buffer then)."""
    bits = int(0)
    if ncollision > naconmax:
        bits = bits | _BROADPHASE
    if nacon > naconmax:
        bits = bits | NARROWPHASE
    return bits


@wp.kernel(enable_backward=False)
def derive_signals(
    qpos: wp.array2d(dtype=float),
    qvel: wp.array2d(dtype=float),
    qacc: wp.array2d(dtype=float),
    sensordata: wp.array2d(dtype=float),
    found_adr: wp.array(dtype=int),
    weights: wp.array2d(dtype=float),
    overflow: wp.array(dtype=int),
    nefc: wp.array(dtype=int),
    nacon: wp.array(dtype=int),
    ncollision: wp.array(dtype=int),
    njmax: int,
    naconmax: int,
    health_mask: int,
    # outputs
    signals_out: wp.array2d(dtype=wp.bool),
    overflow_out: wp.array(dtype=int),
    healthy_out: wp.array(dtype=wp.bool),
):
    """Contact signals (signed sums of contact counts > 0.5), the overflow bits and the health flag of one world
(finite qpos, qvel, qacc and sensordata, and no overflow bit of ``health_mask``).

    ``overflow_out`` adds the buffer checks that mujoco-warp only records when it integrates, so an overflow in the
    final forward pass of a step is visible after that step rather than one step later.
    """
    w = wp.tid()
    for k in range(weights.shape[0]):
        s = float(0.0)
        for i in range(found_adr.shape[0]):
            s += weights[k, i] * sensordata[w, found_adr[i]]
        signals_out[w, k] = s > 0.5

    bits = int(overflow[w])
    if nefc[w] > njmax:
        bits = bits | _NEFC
    bits = bits | contact_buffer_bits(nacon[0], ncollision[0], naconmax)
    overflow_out[w] = bits

    # A NaN or inf anywhere in the state, its acceleration or a sensor makes the sum non-finite (C MuJoCo resets such a
    # world itself and warns; mujoco-warp keeps integrating it, so this flag is what stops it).
    total = float(0.0)
    for i in range(qpos.shape[1]):
        total += qpos[w, i] * 0.0
    for i in range(qvel.shape[1]):
        total += qvel[w, i] * 0.0 + qacc[w, i] * 0.0
    for i in range(sensordata.shape[1]):
        total += sensordata[w, i] * 0.0
    healthy_out[w] = wp.isfinite(total) and (bits & health_mask) == 0


@wp.kernel(enable_backward=False)
def write_reset_state(
    mask: wp.array(dtype=wp.bool),
    qpos_in: wp.array2d(dtype=float),
    qvel_in: wp.array2d(dtype=float),
    ctrl_in: wp.array2d(dtype=float),
    qpos: wp.array2d(dtype=float),
    qvel: wp.array2d(dtype=float),
    ctrl: wp.array2d(dtype=float),
):
    """Copy the requested initial state into the flagged worlds (after ``mujoco_warp.reset_data`` cleared them)."""
    w = wp.tid()
    if not mask[w]:
        return
    for i in range(qpos.shape[1]):
        qpos[w, i] = qpos_in[w, i]
    for i in range(qvel.shape[1]):
        qvel[w, i] = qvel_in[w, i]
    for i in range(ctrl.shape[1]):
        ctrl[w, i] = ctrl_in[w, i]


@wp.kernel(enable_backward=False)
def copy_rows_where(
    mask: wp.array(dtype=wp.bool),
    when: wp.bool,
    src: wp.array2d(dtype=float),
    dst: wp.array2d(dtype=float),
):
    """``dst[w] = src[w]`` for the worlds whose ``mask[w] == when``."""
    w = wp.tid()
    if mask[w] != when:
        return
    for i in range(src.shape[1]):
        dst[w, i] = src[w, i]


@wp.kernel(enable_backward=False)
def copy_start_rows(
    mask: wp.array(dtype=wp.bool),
    index: wp.array(dtype=wp.int32),
    table: wp.array3d(dtype=float),
    dst: wp.array2d(dtype=float),
):
    """``dst[w] = table[index[w], w]`` for the flagged worlds: a registered start state's precomputed values."""
    w = wp.tid()
    if not mask[w]:
        return
    r = index[w]
    for i in range(dst.shape[1]):
        dst[w, i] = table[r, w, i]


@wp.kernel(enable_backward=False)
def or_start_overflow(
    mask: wp.array(dtype=wp.bool),
    index: wp.array(dtype=wp.int32),
    table: wp.array2d(dtype=int),
    overflow: wp.array(dtype=int),
):
    """Add to the flagged worlds' overflow bits those the skipped stages set in their start state's full pass."""
    w = wp.tid()
    if mask[w]:
        overflow[w] = overflow[w] | table[index[w], w]


@wp.kernel(enable_backward=False)
def write_substep_ctrl(
    schedule: wp.array3d(dtype=float),
    substep: int,
    columns: wp.array(dtype=int),
    ctrl: wp.array2d(dtype=float),
):
    """``ctrl[w, columns[j]] = schedule[w, substep, j]``: the controls of one physics substep (an actuator delay)."""
    w, j = wp.tid()
    ctrl[w, columns[j]] = schedule[w, substep, j]
