"""The reduced reset pass's position and velocity stages over the worlds that reset alone.

The reduced reset pass (``SimConfig.reset_pass="reduced"``) runs ``mujoco_warp.fwd_position`` and ``fwd_velocity``
so that the reset worlds start their next step (``step2``, which reuses those stages) from a consistent state.
mujoco-warp's kernels run over every world of a ``Data``, so over all N worlds that costs 2.5 ms per step at 16,384
worlds on an H100, though a training step resets a few dozen (``docs/benchmarks/reset_pass_cost/``). Here the same
two stages run on a second ``Data`` of ``capacity`` worlds, one per reset world, and their results go back into the
big ``Data``:

=====================  ======================================================================================
step                   what moves
=====================  ======================================================================================
slots                  the next ``capacity`` reset world ids into slots (an atomic counter: no host read)
gather                 every per-world array the two stages read before writing it, big row -> slot row; the
                       per-world model fields (``SimConfig.per_world_fields``) into the small model's rows
stages                 ``fwd_position(factorize=True)`` and ``fwd_velocity`` on the small ``Data``
contacts               the new ones into the big buffer's rows that ``reset_data`` emptied of the reset worlds'
                       old contacts (dimension 0), then past its count; their world ids mapped back, the
                       constraint rows' contact ids remapped
scatter                every per-world array the stages write, slot row -> big row
=====================  ======================================================================================

Which arrays are read and written is found by running the stages once with warp's launches traced (their
``inputs``, ``outputs``, copies and fills, matched to the arrays whose memory they point into), so the lists follow
the installed mujoco-warp. Each of gather, contacts and scatter is one launch over all its arrays' rows side by side
(``_RowTable``: the arrays' addresses and widths in a table on the device), not one per array. When more worlds
reset than ``capacity`` (the first steps of training, when untrained robots fall together), the small ``Data``
takes them ``capacity`` at a time, in a loop on the device
(``wp.capture_while``: no host read once recorded into a graph); none resetting, it runs no stage at all. A loop body
may not allocate memory, and mujoco-warp's stages make scratch arrays as they run: the body keeps those of its first
run and hands them out again (``_AllocationPool``), sized for the small ``Data``.

The untouched worlds keep what the step's closing forward pass computed for their unchanged state, which is what the
pass over every world recomputes; constraint rows are per world, contacts are found from them, so each world's
physics is unchanged (bit-identical on the CPU), though the big buffer holds its contacts in another order and the
emptied rows it did not refill (inert: no world's constraint rows point at them) until the next step's collision.
Where the big buffer is full, a new contact is dropped, its world flagged ``NARROWPHASE`` (a health flag) and its
constraint rows made inert, and the buffer's count is left past its size, which flags every world (``derive`` and
the next step read it), as an overflowing collision over every world does. Where the small ``Data``'s own buffers
overflow, the reset worlds of that chunk are flagged (its unoccupied slots, holding earlier worlds' states, take room
there too, so that can flag a chunk whose own contacts would have fit: rare, and a flag rather than a wrong state).
"""

from __future__ import annotations

import contextlib
import dataclasses
import operator
import threading
from collections.abc import Callable

import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp

from .kernels import NARROWPHASE, contact_buffer_bits

__all__ = ["CompactResetPass", "traced_stages"]

#: Held while warp's module functions are replaced (``_tracing``, ``_AllocationPool.active``): the replacement is
#: process-wide, so two simulators building or resetting eagerly in two threads would otherwise restore each other's.
_PATCH_LOCK = threading.RLock()
#: Constraint row types whose ``efc.id`` is a contact's index in the contact buffer (MuJoCo's numbering, which
#: mujoco-warp's rows share).
_CONTACT_ROWS = tuple(int(getattr(mujoco.mjtConstraint, f"mjCNSTR_CONTACT_{k}")) for k in
                      ("FRICTIONLESS", "PYRAMIDAL", "ELLIPTIC"))
#: ``Data``'s counters of the contact buffer, one for all worlds (of shape (1,), like a per-world array of one world).
_GLOBAL_COUNTS = ("nacon", "ncollision")
#: What a dropped contact's rows become: a joint-limit row (no contact to read) with no force (``efc.D`` 0).
_INERT_ROW = int(mujoco.mjtConstraint.mjCNSTR_LIMIT_JOINT)


@wp.kernel(enable_backward=False)
def _rank_resets(mask: wp.array(dtype=wp.bool), count: wp.array(dtype=int), order: wp.array(dtype=int),
                 more: wp.array(dtype=wp.int32)):
    """List the flagged worlds in ``order[0:count]`` (in no particular order); ``more``: any at all."""
    w = wp.tid()
    if mask[w]:
        order[wp.atomic_add(count, 0, 1)] = w
        more[0] = 1


@wp.kernel(enable_backward=False)
def _next_chunk(order: wp.array(dtype=int), count: wp.array(dtype=int), chunk: wp.array(dtype=int),
                capacity: int, slot_world: wp.array(dtype=int), in_chunk: wp.array(dtype=int)):
    """The worlds of chunk ``chunk``: ``order[chunk * capacity:][:capacity]`` into the slots."""
    s = wp.tid()
    start = chunk[0] * capacity
    if s == 0:
        in_chunk[0] = wp.clamp(count[0] - start, 0, capacity)
    if start + s < count[0]:
        slot_world[s] = order[start + s]


@wp.kernel(enable_backward=False)
def _advance_chunk(count: wp.array(dtype=int), capacity: int, chunk: wp.array(dtype=int),
                   more: wp.array(dtype=wp.int32)):
    chunk[0] = chunk[0] + 1
    more[0] = wp.where(chunk[0] * capacity < count[0], 1, 0)


@wp.func
def _copy_word(big: wp.array(dtype=wp.uint64), small: wp.array(dtype=wp.uint64), width: wp.array(dtype=int),
               big_rows: int, small_rows: int, column_of: wp.array(dtype=wp.vec2i), j: int, big_row: int,
               small_row: int, to_big: bool):
    """Word ``j`` of all the table's rows side by side (``column_of[j]``: its array pair and column) between row
    ``big_row`` of the pair's big array and row ``small_row`` of its small one, in the direction ``to_big`` says."""
    k = column_of[j][0]
    c = column_of[j][1]
    big_array = wp.array(ptr=big[k], shape=(big_rows, width[k]), dtype=wp.int32)
    small_array = wp.array(ptr=small[k], shape=(small_rows, width[k]), dtype=wp.int32)
    if to_big:
        big_array[big_row, c] = small_array[small_row, c]
    else:
        small_array[small_row, c] = big_array[big_row, c]


@wp.kernel(enable_backward=False)
def _slot_rows(big: wp.array(dtype=wp.uint64), small: wp.array(dtype=wp.uint64), width: wp.array(dtype=int),
               big_rows: int, small_rows: int, column_of: wp.array(dtype=wp.vec2i), slot_world: wp.array(dtype=int),
               count: wp.array(dtype=int), to_big: bool):
    """Between row ``slot_world[s]`` of every big array and row ``s`` of its small one, for the occupied slots: into
    the slots (gather) or, ``to_big``, back to the worlds (scatter); one thread per slot and 32-bit word of all the
    arrays' rows together."""
    s, j = wp.tid()
    if s < count[0]:
        _copy_word(big, small, width, big_rows, small_rows, column_of, j, slot_world[s], s, to_big)


@wp.kernel(enable_backward=False)
def _append_rows(big: wp.array(dtype=wp.uint64), small: wp.array(dtype=wp.uint64), width: wp.array(dtype=int),
                 big_rows: int, small_rows: int, column_of: wp.array(dtype=wp.vec2i), nacon: wp.array(dtype=int),
                 remap: wp.array(dtype=int)):
    """Row ``i`` of every small contact field into row ``remap[i]`` of the big one, for the contacts given a row."""
    i, j = wp.tid()
    if i < nacon[0] and remap[i] >= 0:
        _copy_word(big, small, width, big_rows, small_rows, column_of, j, remap[i], i, True)


@wp.kernel(enable_backward=False)
def _slot_bytes(big: wp.array2d(dtype=wp.uint8), small: wp.array2d(dtype=wp.uint8), slot_world: wp.array(dtype=int),
                count: wp.array(dtype=int), to_big: bool):
    """:func:`_slot_rows` for one pair of byte rows."""
    s, j = wp.tid()
    if s < count[0]:
        if to_big:
            big[slot_world[s], j] = small[s, j]
        else:
            small[s, j] = big[slot_world[s], j]


@wp.kernel(enable_backward=False)
def _free_rows(nacon: wp.array(dtype=int), dim: wp.array(dtype=int), nfree: wp.array(dtype=int),
               free: wp.array(dtype=int)):
    """List the big buffer's rows ``reset_data`` emptied (a contact of dimension 0: it clears the reset worlds'
    contacts so), for the new contacts to take before any row past the count."""
    i = wp.tid()
    if i < nacon[0] and dim[i] == 0:
        free[wp.atomic_add(nfree, 0, 1)] = i


@wp.kernel(enable_backward=False)
def _number_contacts(worldid: wp.array(dtype=int), nacon: wp.array(dtype=int), count: wp.array(dtype=int),
                     slot_world: wp.array(dtype=int), free: wp.array(dtype=int), nfree: wp.array(dtype=int),
                     taken: wp.array(dtype=int), total: wp.array(dtype=int), remap: wp.array(dtype=int),
                     big_worldid: wp.array(dtype=int), overflow: wp.array(dtype=int)):
    """Give each contact of an occupied slot its row in the big buffer (``remap``, -1 for the others): an emptied
    row while any is left, else the next row past the count ``total``."""
    i = wp.tid()
    if i >= nacon[0]:
        return
    s = worldid[i]
    remap[i] = -1
    if s >= count[0]:  # a slot no reset world occupies this time: its contacts are stale
        return
    w = slot_world[s]
    k = wp.atomic_add(taken, 0, 1)
    row = int(0)
    if k < nfree[0]:
        row = free[k]
    else:
        row = wp.atomic_add(total, 0, 1)
    if row < big_worldid.shape[0]:
        remap[i] = row
        big_worldid[row] = w
    else:  # the big buffer is full: the contact is dropped, and its slot says so (scattered to its world after)
        wp.atomic_or(overflow, s, NARROWPHASE)


@wp.kernel(enable_backward=False)
def _remap_contact_ids(count: wp.array(dtype=int), nefc: wp.array(dtype=int), remap: wp.array(dtype=int),
                       kinds: wp.vec3i, inert: int, efc_type: wp.array2d(dtype=int), efc_id: wp.array2d(dtype=int),
                       efc_D: wp.array2d(dtype=float)):
    s, r = wp.tid()
    if s < count[0] and r < nefc[s]:
        t = efc_type[s, r]
        if t == kinds[0] or t == kinds[1] or t == kinds[2]:
            k = remap[efc_id[s, r]]
            if k >= 0:
                efc_id[s, r] = k
            else:
                # A dropped contact's rows would send the solver to a contact that is not there (its elliptic
                # line search reads the contact without a bound check): rows of no contact and no force instead.
                # The world is flagged (NARROWPHASE), so its episode ends.
                efc_type[s, r] = inert
                efc_id[s, r] = 0
                efc_D[s, r] = 0.0


@wp.kernel(enable_backward=False)
def _flag_small_overflow(nacon: wp.array(dtype=int), ncollision: wp.array(dtype=int), naconmax: int,
                         count: wp.array(dtype=int), overflow: wp.array(dtype=int)):
    """The small ``Data``'s contact buffers are shared by its slots: where a chunk overflowed them, contacts of its
    worlds are missing, and each occupied slot says so (as mujoco-warp's step flags every world)."""
    s = wp.tid()
    if s < count[0]:
        overflow[s] = overflow[s] | contact_buffer_bits(nacon[0], ncollision[0], naconmax)


def _rows(array: wp.array, rows: int) -> tuple[wp.array, bool]:
    """``array`` (contiguous, leading dimension ``rows``) as a 2-D view of its memory: 32-bit words per row, or
    bytes where a row's size is not a multiple of 4; the flag says which."""
    if not array.is_contiguous:
        raise ValueError(f"CompactResetPass copies whole rows of contiguous arrays; got strides {array.strides}")
    width = array.size // rows * wp.types.type_size_in_bytes(array.dtype)
    words = width % 4 == 0
    view = wp.array(ptr=array.ptr, dtype=wp.int32 if words else wp.uint8,
                    shape=(rows, width // 4 if words else width), device=array.device)
    view._owner = array  # the view does not own its memory: keep the owner alive with it
    return view, words


@contextlib.contextmanager
def _tracing(reads: list, writes: list):
    """Note, in launch order, the arrays each warp launch lists as ``inputs`` (``reads``) and ``outputs``
    (``writes``), and those that copies and fills write; restored on exit."""
    with _PATCH_LOCK:  # from before the originals are read
        originals = {"launch": wp.launch, "launch_tiled": wp.launch_tiled, "copy": wp.copy}
        fills = {"zero_": wp.array.zero_, "fill_": wp.array.fill_}

        def launch(inner):
            def traced(kernel, *args, inputs=(), outputs=(), **kwargs):
                reads.append([a for a in inputs if isinstance(a, wp.array)])
                writes.append([a for a in outputs if isinstance(a, wp.array)])
                return inner(kernel, *args, inputs=inputs, outputs=outputs, **kwargs)
            return traced

        def copy(dest, src, *args, **kwargs):
            reads.append([src])
            writes.append([dest])
            return originals["copy"](dest, src, *args, **kwargs)

        def fill(inner):
            def traced(self, *args, **kwargs):
                reads.append([])
                writes.append([self])
                return inner(self, *args, **kwargs)
            return traced

        wp.launch, wp.launch_tiled, wp.copy = launch(wp.launch), launch(wp.launch_tiled), copy
        wp.array.zero_, wp.array.fill_ = fill(fills["zero_"]), fill(fills["fill_"])
        try:
            yield
        finally:
            wp.launch, wp.launch_tiled, wp.copy = originals["launch"], originals["launch_tiled"], originals["copy"]
            wp.array.zero_, wp.array.fill_ = fills["zero_"], fills["fill_"]


class _AllocationPool:
    """The arrays the pass's loop body allocates (mujoco-warp's stages make scratch arrays with ``wp.empty`` and
    ``wp.zeros`` as they run), made on its first run and handed out again, in the same order, on every later run,
    zeroed where ``wp.zeros`` asked: a loop body on the device (a conditional node) may not allocate
    memory (CUDA refuses a body graph with allocation nodes). While :meth:`active` runs, warp's allocation functions
    are replaced for the whole process: other threads' calls pass through to warp's own, and ``_PATCH_LOCK`` keeps
    two replacements from overlapping."""

    _POOLED = ("empty", "zeros")
    _REFUSED = ("empty_like", "zeros_like", "ones", "full", "clone", "ones_like", "full_like")

    def __init__(self, name: str):
        self.name = name
        self.arrays: list[tuple[wp.array, tuple]] | None = None  # (array, what was asked for)

    @contextlib.contextmanager
    def active(self):
        with _PATCH_LOCK:  # from before the originals are read
            originals = {k: getattr(wp, k) for k in (*self._POOLED, *self._REFUSED)}
            made, used, here = [], [0], threading.get_ident()

            def pooled(kind):
                def alloc(shape=0, dtype=float, *args, **kwargs):
                    if threading.get_ident() != here:  # another thread's warp work is not the pass's
                        return originals[kind](shape, dtype, *args, **kwargs)
                    shape = (operator.index(shape),) if not isinstance(shape, (tuple, list)) else tuple(shape)
                    key = (shape, dtype, args, tuple(sorted(kwargs.items(), key=lambda item: item[0])))
                    if self.arrays is None:  # the first run: allocate, and keep
                        array = originals[kind](shape, dtype, *args, **kwargs)
                        made.append((array, key))
                        return array
                    k = used[0]
                    if k >= len(self.arrays) or self.arrays[k][1] != key:
                        raise RuntimeError(f"CompactResetPass ({self.name}): mujoco-warp's allocation {k} "
                                           f"({shape}, {dtype}) differs from its first run; the pass cannot reuse "
                                           "its scratch arrays")
                    used[0] += 1
                    array = self.arrays[k][0]
                    if kind == "zeros":
                        array.zero_()
                    return array
                return alloc

            def refused(kind):
                def alloc(*args, **kwargs):
                    if threading.get_ident() != here:
                        return originals[kind](*args, **kwargs)
                    raise RuntimeError(f"CompactResetPass ({self.name}): mujoco-warp allocated with wp.{kind} in "
                                       "the reset pass, which a loop on the device cannot hold; build the simulator "
                                       "with register_start_states(..., compact=0)")
                return alloc

            for kind in self._POOLED:
                setattr(wp, kind, pooled(kind))
            for kind in self._REFUSED:
                setattr(wp, kind, refused(kind))
            try:
                yield
            finally:
                for kind, fn in originals.items():
                    setattr(wp, kind, fn)
        if self.arrays is None:
            self.arrays = made
        elif used[0] != len(self.arrays):
            raise RuntimeError(f"CompactResetPass ({self.name}): mujoco-warp allocated {used[0]} arrays, its first run "
                               f"{len(self.arrays)}; the pass cannot reuse its scratch arrays")


def per_world_arrays(data: mjw.Data, rows: int) -> dict[str, wp.array]:
    """``{name: array}`` of the arrays of ``data`` and of its constraint rows (``efc.<name>``) with ``rows`` rows,
    one per world (the contact buffer and its counters, one for all worlds, are not among them)."""
    found = {}
    for name, value in vars(data).items():
        if name in _GLOBAL_COUNTS:
            continue
        if isinstance(value, wp.array) and value.ndim >= 1 and value.shape[0] == rows and value.size > 0:
            found[name] = value
    for name, value in vars(data.efc).items():
        if isinstance(value, wp.array) and value.ndim >= 1 and value.shape[0] == rows and value.size > 0:
            found[f"efc.{name}"] = value
    return found


def traced_stages(model: mjw.Model, data: mjw.Data) -> tuple[list[str], list[str]]:
    """Run ``fwd_position(factorize=True)`` and ``fwd_velocity`` on ``data`` once and return the names of its
    per-world arrays (:func:`per_world_arrays`) that they read before writing them, and those they write."""
    reads, writes = [], []
    with _tracing(reads, writes):
        _stages(model, data)
    spans = [(a.ptr, a.ptr + a.size * wp.types.type_size_in_bytes(a.dtype), name)
             for name, a in per_world_arrays(data, data.nworld).items()]

    def owner(a: wp.array) -> str | None:  # a per-world array, or a view into one (a slice of its rows' columns)
        return next((name for lo, hi, name in spans if a.ptr is not None and lo <= a.ptr < hi), None)

    read_first, written = [], []
    for ins, outs in zip(reads, writes):
        for name in map(owner, ins):
            if name is not None and name not in written and name not in read_first:
                read_first.append(name)
        for name in map(owner, outs):
            if name is not None and name not in written:
                written.append(name)
    return read_first, written


def _stages(model: mjw.Model, data: mjw.Data) -> None:
    mjw.fwd_position(model, data, factorize=True)
    mjw.fwd_velocity(model, data)


class _RowTable:
    """Whole rows of many array pairs, copied by one launch: each pair's two base addresses and row width in 32-bit
    words, and each word's (pair, column) over all the pairs' rows side by side. A round launches three of these
    (gather, contacts, scatter) instead of one copy per array (84 with mujoco-warp 4.0.0's TOCABI). Pairs whose rows
    are not whole words are kept apart in :attr:`bytes` ((big, small) 2-D byte views, one launch each).

    Args:
        pairs: name -> (big, small) arrays of one per-row layout: contiguous, ``big_rows`` and ``small_rows`` rows.
        words_only: refuse a pair of byte rows (ValueError) instead of keeping it apart.
    """

    def __init__(self, pairs: dict[str, tuple[wp.array, wp.array]], big_rows: int, small_rows: int,
                 words_only: bool = False):
        words, self.bytes = [], []
        for name, (big, small) in pairs.items():
            (b, in_words), (sm, _) = _rows(big, big_rows), _rows(small, small_rows)
            if b.shape[1] != sm.shape[1]:  # one width is read for both: a mismatch would copy past a row
                raise ValueError(f"CompactResetPass: {name!r} holds {b.shape[1]} words (or bytes) per row in the big "
                                 f"Data and {sm.shape[1]} in the small one")
            if not in_words and words_only:
                raise ValueError(f"CompactResetPass: {name!r} rows of {b.shape[1]} bytes are not of 32-bit words")
            (words if in_words else self.bytes).append((b, sm))
        self._views = words  # they keep the arrays alive while the table holds their addresses
        widths = np.array([b.shape[1] for b, _ in words], dtype=np.int32)
        self.columns = int(widths.sum())  # 32-bit words per row, all pairs together
        self.big_rows, self.small_rows = big_rows, small_rows
        device = next(iter(pairs.values()))[0].device if pairs else None
        self.big = wp.array([b.ptr for b, _ in words], dtype=wp.uint64, device=device)
        self.small = wp.array([sm.ptr for _, sm in words], dtype=wp.uint64, device=device)
        self.width = wp.array(widths, dtype=int, device=device)
        pair = np.repeat(np.arange(len(words), dtype=np.int32), widths)
        column = np.arange(self.columns, dtype=np.int32) - np.repeat(np.cumsum(widths) - widths, widths)
        self.column_of = wp.array(np.stack((pair, column), axis=-1), dtype=wp.vec2i, device=device)

    def launch(self, kernel, rows: int, *inputs) -> None:
        """``kernel`` (:func:`_slot_rows` or :func:`_append_rows`) over ``rows`` rows of every pair's words, with its
        trailing ``inputs``."""
        if self.columns:
            wp.launch(kernel, dim=(rows, self.columns), inputs=[self.big, self.small, self.width, self.big_rows,
                                                                self.small_rows, self.column_of, *inputs])

    def copy_slots(self, slot_world: wp.array, count: wp.array, to_big: bool) -> None:
        """Every pair's rows between world ``slot_world[s]`` and slot ``s``, for the ``count[0]`` occupied slots:
        into the slots, or back to the worlds with ``to_big``; the words in one launch, each byte pair in one."""
        self.launch(_slot_rows, self.small_rows, slot_world, count, to_big)
        for big, small in self.bytes:
            wp.launch(_slot_bytes, dim=small.shape, inputs=[big, small, slot_world, count, to_big])


class CompactResetPass:
    """The reset pass's position and velocity stages for the flagged worlds, on a second ``Data`` of ``capacity``
    worlds (the module's docstring says how). Build it before any graph records :meth:`run`; it runs the stages
    once eagerly on the small ``Data`` (compiling nothing new: the same kernels).

    Args:
        mj: the compiled MuJoCo model the big ``Data`` was made from.
        model: the big ``Data``'s mujoco-warp model (its per-world fields, ``(N, ...)`` rows, are gathered).
        data: the big ``Data``, N worlds.
        capacity: the most reset worlds the small ``Data`` holds; more go through it ``capacity`` at a time.
        nconmax, njmax, nccdmax: the big ``Data``'s per-world buffer sizes (``mujoco_warp.make_data``).
        per_world_fields: names of ``model``'s fields with one row per world.
    """

    def __init__(self, mj, model: mjw.Model, data: mjw.Data, capacity: int, nconmax: int, njmax: int,
                 nccdmax: int, per_world_fields: tuple[str, ...] = ()):
        n = data.nworld
        if not 0 < capacity < n:
            raise ValueError(f"CompactResetPass capacity must be in [1, {n}) for {n} worlds, got {capacity}")
        self.capacity, self.model, self.data = capacity, model, data
        self.small = mjw.make_data(mj, nworld=capacity, nconmax=nconmax, njmax=njmax, nccdmax=nccdmax)
        small_fields = {}
        for name in per_world_fields:
            big = getattr(model, name)
            small_fields[name] = wp.empty((capacity, *big.shape[1:]), dtype=big.dtype)
            wp.copy(small_fields[name], big, count=small_fields[name].size)
        self.small_model = dataclasses.replace(model, **small_fields)
        reads, writes = traced_stages(self.small_model, self.small)
        big_arrays, small_arrays = per_world_arrays(data, n), per_world_arrays(self.small, capacity)
        missing = sorted(set(reads + writes) - set(big_arrays))
        if missing:
            raise ValueError(f"CompactResetPass: the big Data lacks the per-world arrays {missing} of the small one "
                             "(another mujoco-warp layout?); use the pass over every world")
        # The overflow bits are or-ed into (an output read as well): each slot starts from its reset world's bits,
        # which reset_data cleared, not from those of the slot's last world; and they always go back.
        reads += [] if "overflow" in reads else ["overflow"]
        writes += [name for name in ("overflow", "efc.type", "efc.id", "efc.D") if name not in writes]
        #: names of the per-world arrays gathered before the stages and scattered after them
        self.reads, self.writes = tuple(reads), tuple(writes)
        fields = {f"model.{k}": (getattr(model, k), v) for k, v in small_fields.items()}
        self._gather = _RowTable(fields | {k: (big_arrays[k], small_arrays[k]) for k in reads}, n, capacity)
        self._scatter = _RowTable({k: (big_arrays[k], small_arrays[k]) for k in writes}, n, capacity)
        big_c, rows_small = data.contact, self.small.naconmax
        self._contacts = _RowTable({f"contact.{name}": (getattr(big_c, name), value)
                                    for name, value in vars(self.small.contact).items()
                                    if isinstance(value, wp.array) and value.shape[0] == rows_small and value.size > 0
                                    and name != "worldid"}, data.naconmax, rows_small, words_only=True)
        self._pool = _AllocationPool("reset worlds")
        self._order = wp.zeros(n, dtype=int)  # the reset worlds, chunk after chunk
        self._count = wp.zeros(1, dtype=int)  # how many reset
        self._chunk = wp.zeros(1, dtype=int)  # the chunk in the small Data; after the pass, how many there were
        self._more = wp.zeros(1, dtype=wp.int32)  # the loop's condition: a chunk is left
        self._slot_world = wp.zeros(capacity, dtype=int)  # the world in each slot of this chunk
        self._in_chunk = wp.zeros(1, dtype=int)  # how many slots this chunk fills
        self._total = wp.zeros(1, dtype=int)  # the big buffer's contact count before the reset, then as appended
        self._remap = wp.zeros(self.small.naconmax, dtype=int)  # each small contact's row in the big buffer
        self._free = wp.zeros(data.naconmax, dtype=int)  # the big buffer's emptied rows ...
        self._nfree = wp.zeros(1, dtype=int)  # ... how many ...
        self._taken = wp.zeros(1, dtype=int)  # ... and how many the new contacts took

    def run(self, mask: wp.array, write_reset_state: Callable[[], None]) -> None:
        """``write_reset_state()`` (which writes the reset worlds' state into the big ``Data``, e.g. with
        ``mujoco_warp.reset_data``), then the two stages for the worlds ``mask`` (N,) bool flags, ``capacity`` of
        them at a time on the small ``Data``. Warp launches only (recordable into a graph)."""
        n, d = self.data.nworld, self.data
        # reset_data zeroes the contact count when world 0 resets; the untouched worlds' contacts stay in their rows.
        wp.copy(self._total, d.nacon)
        write_reset_state()
        for counter in (self._count, self._chunk, self._more):
            counter.zero_()
        wp.launch(_rank_resets, dim=n, inputs=[mask, self._count, self._order, self._more])
        # Resets without a step between them (env.reset() after the build's) refill the rows they emptied, so the
        # count does not grow by every reset world's contacts each time.
        self._nfree.zero_()
        self._taken.zero_()
        wp.launch(_free_rows, dim=d.naconmax, inputs=[self._total, d.contact.dim, self._nfree], outputs=[self._free])
        wp.capture_while(self._more, self._chunk_pass)
        # Not clamped to the buffer: a count over it is mujoco-warp's sign of a full buffer, as after its collision.
        wp.copy(d.nacon, self._total)

    def _chunk_pass(self) -> None:
        d, s, cap = self.data, self.small, self.capacity
        slots, count = self._slot_world, self._in_chunk
        wp.launch(_next_chunk, dim=cap, inputs=[self._order, self._count, self._chunk, cap], outputs=[slots, count])
        self._gather.copy_slots(slots, count, to_big=False)
        with self._pool.active():
            _stages(self.small_model, s)
        wp.launch(_number_contacts, dim=s.naconmax,
                  inputs=[s.contact.worldid, s.nacon, count, slots, self._free, self._nfree],
                  outputs=[self._taken, self._total, self._remap, d.contact.worldid, s.overflow])
        self._contacts.launch(_append_rows, s.naconmax, s.nacon, self._remap)
        wp.launch(_flag_small_overflow, dim=cap, inputs=[s.nacon, s.ncollision, s.naconmax, count],
                  outputs=[s.overflow])
        wp.launch(_remap_contact_ids, dim=(cap, s.efc.id.shape[1]),
                  inputs=[count, s.nefc, self._remap, wp.vec3i(*_CONTACT_ROWS), _INERT_ROW],
                  outputs=[s.efc.type, s.efc.id, s.efc.D])
        self._scatter.copy_slots(slots, count, to_big=True)
        wp.launch(_advance_chunk, dim=1, inputs=[self._count, cap], outputs=[self._chunk, self._more])

