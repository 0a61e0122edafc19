"""Contact and constraint buffer sizes for TOCABI, and the measurement that chose them.

mujoco-warp allocates fixed buffers: a contact pool shared by all worlds (``naconmax = nconmax * num_worlds``, which
also bounds the broadphase candidate pairs) and ``njmax`` constraint rows per world. Too small and contacts or
constraints are silently dropped (the backend flags the world unhealthy, see ``health``); too large costs memory and
solver time. The defaults below come from ``python -m lab.sim_measure.measure_buffers``, which steps TOCABI through
standing, falling, thrashing and tangled scenarios and records the per-substep peaks
(results: ``docs/benchmarks/sim_buffers.md``).
"""

from __future__ import annotations

__all__ = ["NCONMAX", "NCCDMAX", "NJMAX", "CONTACT_SENSOR_MAXMATCH", "permanent_constraint_rows"]

#: Contacts per world, pooled over worlds (``naconmax = nconmax * num_worlds``). Measured in mujoco-warp, per substep:
#: 8 per standing robot (4 per sole); one world peaks at 28 lying on its back, 41 after a hard fall on its front and
#: 48 with tangled legs; the pool averaged at most 19 per world in any scenario and the broadphase at most 23 pairs.
#: 48 holds even the worst single world in every world at once (2.5x the worst pooled average).
NCONMAX = 48
#: Convex-collision (GJK/EPA) candidate pairs per world, pooled over worlds (``naccdmax = nccdmax * num_worlds``,
#: counted per pair of geom types). TOCABI's box and cylinder geoms collide with each other through mujoco-warp's
#: convex narrowphase (the ground plane's pairs are primitive), and its EPA scratch holds ~5 KB per slot
#: (``ccd_iterations`` 35): at mujoco-warp's default of nconmax slots per world that is 31 GB at 131,072 worlds.
#: Measured after the broadphase's sphere and OBB filters (lab.sim_measure.measure_buffers, whose count adds up to
#: mujoco-warp's own broadphase count): no pair for standing robots; pooled over 16 worlds at most 4.0 per world for
#: collapsed robots, 5.4 dropped on their side, 7.1 with tangled limbs, and 21 in the worst single world. 16 holds
#: 2.3x the worst pooled average, a third of mujoco-warp's default of nconmax slots.
NCCDMAX = 16
#: Constraint rows per world, a hard per-world limit: 33 friction-loss rows always, 3 per contact (elliptic cone,
#: condim 3) and joint-limit rows. Measured peaks: 57 standing, 117 lying on the back, 156 after a hard fall on the
#: front, 177 with tangled legs. 224 (a multiple of the solver's 16-row tile) leaves 1.27x over the worst case; the
#: solver loops stop at the actual row count, so the margin costs memory (~0.7 GB at 16384 worlds), not time.
NJMAX = 224
#: Slots per contact sensor in mujoco-warp's matching pass. The ``found`` counts used here stay exact beyond it (only
#: the CONTACT_MATCH flag is raised); 64 covers every contact of a fallen robot (at most 48 measured).
CONTACT_SENSOR_MAXMATCH = 64


def permanent_constraint_rows(mj) -> int:
    """Constraint rows every world of ``mj`` holds in every state: one per dof and tendon with friction loss and the
    rows of the active equality constraints (connect 3, weld 6, joint and tendon 1; flex ones not counted, so this
    is a lower bound). An ``njmax`` below it overflows in every world from the first step, before any contact."""
    import mujoco  # here, not at the top: the config tree reads this module without MuJoCo

    off = int(mj.opt.disableflags)
    dsbl = mujoco.mjtDisableBit
    if off & int(dsbl.mjDSBL_CONSTRAINT):
        return 0
    rows = 0
    if not off & int(dsbl.mjDSBL_FRICTIONLOSS):
        rows += int((mj.dof_frictionloss > 0).sum()) + int((mj.tendon_frictionloss > 0).sum())
    if not off & int(dsbl.mjDSBL_EQUALITY):
        eq = mujoco.mjtEq
        size = {int(eq.mjEQ_CONNECT): 3, int(eq.mjEQ_WELD): 6, int(eq.mjEQ_JOINT): 1, int(eq.mjEQ_TENDON): 1}
        rows += sum(size.get(int(t), 0) for t, on in zip(mj.eq_type, mj.eq_active0) if on)
    return rows
