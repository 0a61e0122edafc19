"""The reduced reset pass over the reset worlds alone (``CompactResetPass``) against the pass over every world, on
mujoco-warp's CPU device: every view, the warm start and the trajectories after resets are bit-identical, with
resets that fit the small ``Data``, resets of more worlds than it holds (taken a chunk at a time) and of none."""

from __future__ import annotations

import mujoco
import pytest
import torch
import warp as wp
from test_reset_pass import N as POOL_WORLDS
from test_reset_pass import _assert_sims_equal, _assert_tds_equal, _pool_env, _random_action, _step_both, _step_sims
from test_reset_pass import start_states  # noqa: F401 - the fixture: standing, in foot contact, moving
from warp_cpu import warp_cpu_available

from tocabi_torchrl import robot
from tocabi_torchrl.sim import SimConfig, WarpSim
from tocabi_torchrl.sim import warp_backend
from tocabi_torchrl.sim.compact_reset import CompactResetPass, _RowTable, traced_stages
from tocabi_torchrl.sim.config import compact_reset_capacity

pytestmark = pytest.mark.skipif(not warp_cpu_available(), reason="warp's CPU device is unavailable")

N = 6


def _pair(start_states, capacity=2, **config):
    every = WarpSim(SimConfig(num_worlds=N, device="cpu", reset_pass="reduced", **config))
    every.register_start_states(*start_states, compact=0)
    compact = WarpSim(SimConfig(num_worlds=N, device="cpu", reset_pass="reduced", **config))
    compact.register_start_states(*start_states, compact=capacity)
    return every, compact


def test_the_compacted_pass_matches_the_pass_over_every_world(start_states):
    every, compact = _pair(start_states)
    assert every._compact is None and compact._compact.capacity == 2
    qpos = start_states[0]
    g = torch.Generator().manual_seed(5)

    def steps(k, when):
        _step_sims(every, compact, qpos[0], g, k, when)

    steps(3, "after registering")
    resets = (([1, 0, 0, 1, 0, 0], [1, 0, 0, 2, 0, 0]),  # two worlds, one of them world 0 (reset_data's count)
              ([0, 1, 1, 1, 0, 1], [0, 2, 1, 0, 1, 1]),  # four: more than the small Data holds
              ([0, 0, 1, 0, 0, 0], [1, 1, 1, 1, 1, 1]),  # one, into foot contact
              ([0, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0]))  # none
    chunks = []
    for mask, index in resets:
        mask, index = torch.tensor(mask, dtype=torch.bool), torch.tensor(index)
        before = compact.qpos.clone()
        every.reset_to_start(mask, index)
        compact.reset_to_start(mask, index)
        chunks.append(int(compact._compact._chunk.numpy()[0]))
        _assert_sims_equal(every, compact, f"reset {mask.tolist()}")
        assert torch.equal(compact.qpos[~mask], before[~mask])
        steps(4, f"after reset {mask.tolist()}")
    assert chunks == [1, 2, 1, 0]  # two worlds at a time; none resetting, no stage ran


def test_appended_contacts_that_do_not_fit_are_dropped_and_flag_their_world(start_states):
    """A contact buffer one row short of full (as if the untouched worlds filled it): a reset into foot contact
    appends one contact, drops the rest, flags its world (NARROWPHASE, a health flag), and the dropped contacts'
    constraint rows become rows of no contact and no force, so the next step reads no contact that is not there."""
    import mujoco_warp as mjw

    _, compact = _pair(start_states)
    d = compact.wp_data
    full = d.naconmax - 1  # rows of world 0, linked to no constraint row: nothing for the reset to refill
    wp.to_torch(d.nacon).fill_(full)
    wp.to_torch(d.contact.dim)[:full] = 3
    wp.to_torch(d.contact.worldid)[:full] = 0
    wp.to_torch(d.contact.efc_address)[:full] = -1
    mask = torch.tensor([False, True, False, False, False, False])
    compact.reset_to_start(mask, torch.ones(N, dtype=torch.int64))
    # The count goes past the buffer, as after mujoco-warp's collision when it overflows (every world reads so).
    assert int(d.nacon.numpy()[0]) > d.naconmax
    assert int(wp.to_torch(d.overflow)[1]) & int(mjw.OverflowType.NARROWPHASE) and not bool(compact.healthy[1])
    assert not wp.to_torch(d.overflow)[~mask].any()
    nefc = int(d.nefc.numpy()[1])
    ids, kinds, strength = d.efc.id.numpy()[1, :nefc], d.efc.type.numpy()[1, :nefc], d.efc.D.numpy()[1, :nefc]
    contact = kinds >= int(mujoco.mjtConstraint.mjCNSTR_CONTACT_FRICTIONLESS)
    assert (ids[contact] == d.naconmax - 1).all() and contact.sum() >= 1  # the one contact that fit
    inert = (kinds == int(mujoco.mjtConstraint.mjCNSTR_LIMIT_JOINT)) & (strength == 0)
    assert inert.sum() >= 3  # the dropped contacts' rows (an elliptic contact has three or more)
    compact.step()  # reads every remaining contact row's contact; nothing out of range
    # The step's first substep saw the count past the buffer and flagged every world, as mujoco-warp does.
    assert not bool(compact.healthy.any()) and bool(torch.isfinite(compact.qpos).all())
    # The next reset's world takes the same slot of the small Data, not its overflow bits.
    again = torch.tensor([False, False, True, False, False, False])
    compact.reset_to_start(again, torch.zeros(N, dtype=torch.int64))
    assert int(compact.overflow[2]) == 0 and bool(compact.healthy[2])


def test_per_world_model_fields_and_mocap_positions_are_those_of_each_reset_world(start_states):
    """Per-world masses (a heavier robot in each world) and per-world obstacle positions reach the small pass."""
    from tocabi_torchrl.envs.config import BoxObstacle
    from tocabi_torchrl.envs.obstacles import add_obstacles

    spec = robot.load_spec()
    (name,) = add_obstacles(spec, [BoxObstacle(size=(0.5, 0.6, 0.004), pos=(0.0, 0.0))])
    centres = torch.tensor([[0.0, 0.0, 0.002], [3.0, 0.0, 0.002]]).repeat(3, 1).numpy()  # under the feet: 0, 2, 4
    sims = []
    for capacity in (0, 2):
        sim = WarpSim(SimConfig(num_worlds=N, device="cpu", reset_pass="reduced", per_world_fields=("body_mass",)),
                      model=spec, mocap_pos={name: centres})
        masses = sim.model_fields["body_mass"]

        def set_fields(k, masses=masses):
            masses.copy_(masses[:1].expand_as(masses) * (1.0 + 0.05 * torch.arange(N).unsqueeze(-1) + 0.01 * k))

        sim.register_start_states(*start_states, set_fields=set_fields, compact=capacity)
        sims.append(sim)
    every, compact = sims
    index = torch.tensor([0, 1, 2, 0, 1, 2])
    for mask in ([0, 1, 1, 0, 0, 1], [1, 0, 0, 1, 1, 0]):  # three worlds: two chunks of the small Data
        mask = torch.tensor(mask, dtype=torch.bool)
        for sim in sims:  # each world keeps its own masses (of the last registered state): the same in both
            sim.reset_to_start(mask, index)
        _assert_sims_equal(every, compact, f"reset {mask.tolist()}")
        assert compact.obstacle_contact[[0, 2, 4]].any(-1).all() and not compact.obstacle_contact[[1, 3, 5]].any()
        for t in range(3):
            every.step()
            compact.step()
            _assert_sims_equal(every, compact, f"step {t} after reset {mask.tolist()}")


def test_resets_without_a_step_between_refill_the_rows_they_emptied(start_states):
    """The build resets every world and env.reset() does again: the new contacts take the rows reset_data emptied,
    so the contact count stays that of the first reset and nothing overflows; a world of one slot works too."""
    every, compact = _pair(start_states, capacity=1)
    index = torch.ones(N, dtype=torch.int64)  # into foot contact
    counts = []
    for mask in ([1, 1, 1, 1, 1, 1], [1, 1, 1, 1, 1, 1], [0, 1, 0, 1, 0, 0], [1, 1, 1, 1, 1, 1]):
        mask = torch.tensor(mask, dtype=torch.bool)
        every.reset_to_start(mask, index)
        compact.reset_to_start(mask, index)
        counts.append(int(compact.wp_data.nacon.numpy()[0]))
        _assert_sims_equal(every, compact, f"reset {mask.tolist()}")
    assert counts[0] > 0 and counts[1:] == counts[:1] * 3 and bool(compact.healthy.all())
    every.step()
    compact.step()
    _assert_sims_equal(every, compact, "the step after")


def test_the_training_env_with_a_start_pool_and_dynamics_is_unchanged(monkeypatch):
    """The env as the robust presets build it (a start pool, per-world dynamics), its sync-free step resetting
    worlds itself: with the small pass forced on, every output and sim view is that of the pass over every world."""
    every = _pool_env("reduced")
    monkeypatch.setattr(warp_backend, "compact_reset_capacity", lambda n: 2)
    compact = _pool_env("reduced")
    assert every.base_env.sim._compact is None and compact.base_env.sim._compact.capacity == 2
    td_e, td_c = every.reset(), compact.reset()
    _assert_tds_equal(td_e, td_c, "reset")
    g = torch.Generator().manual_seed(11)
    resets = 0
    for t in range(16):
        out, td_e, _, td_c = _step_both(every, compact, td_e, td_c, _random_action(g), f"step {t}")
        resets += int(out["next", "done"].sum())
    assert resets >= POOL_WORLDS


def test_the_traced_stages_read_the_state_and_write_kinematics_and_constraint_rows():
    import mujoco_warp as mjw

    from tocabi_torchrl.sim import add_contact_sensors

    mj = add_contact_sensors(robot.load_spec()).compile()
    with wp.ScopedDevice("cpu"):
        m = mjw.put_model(mj)
        d = mjw.make_data(mj, nworld=2, nconmax=8, njmax=64)
        reads, writes = traced_stages(m, d)
    assert {"qpos", "qvel"} <= set(reads) and not {"xpos", "qLD", "efc.J"} & set(reads)
    assert {"xpos", "xquat", "cinert", "crb", "M", "qLD", "efc.J", "efc.id", "nefc", "qfrc_bias", "cvel"} <= set(writes)
    assert not {"qpos", "qvel", "ctrl", "sensordata", "qacc_warmstart"} & set(writes)


def test_row_tables_copy_every_pair_in_one_launch_and_byte_rows_apart():
    """The fused copies: rows of several arrays of 32-bit words (float, int, a 3-vector) gathered into the slots and
    scattered back in one launch each, a pair of 3-byte rows apart, the unoccupied slots untouched."""
    rng = torch.Generator().manual_seed(0)
    n, cap = 7, 3
    with wp.ScopedDevice("cpu"):
        big = [wp.from_torch(torch.randn(n, 5, generator=rng)),
               wp.from_torch(torch.randint(-9, 9, (n,), generator=rng, dtype=torch.int32)),
               wp.from_torch(torch.randn(n, 2, 3, generator=rng), dtype=wp.vec3),
               wp.from_torch(torch.randint(0, 255, (n, 3), generator=rng, dtype=torch.uint8))]
        small = [wp.zeros((cap, *a.shape[1:]), dtype=a.dtype) for a in big]
        pairs = {str(k): pair for k, pair in enumerate(zip(big, small))}
        table = _RowTable(pairs, n, cap)
        assert (len(table.bytes), table.columns) == (1, 5 + 1 + 6)
        slots, count = wp.array([4, 0, 6], dtype=int), wp.array([2], dtype=int)  # the third slot unoccupied
        table.copy_slots(slots, count, to_big=False)
        for b, sm in zip(big, small):
            got, want = sm.numpy(), b.numpy()
            assert (got[:2] == want[[4, 0]]).all() and not got[2].any()
        for sm in small:  # the stages' results, scattered back to worlds 4 and 0 only
            sm.assign(sm.numpy() + 1)
        before = [b.numpy().copy() for b in big]
        table.copy_slots(slots, count, to_big=True)
        for b, old in zip(big, before):
            want = old.copy()
            want[[4, 0]] += 1
            assert (b.numpy() == want).all()
        with pytest.raises(ValueError, match="'3' rows of 3 bytes are not of 32-bit words"):
            _RowTable(pairs, n, cap, words_only=True)
        with pytest.raises(ValueError, match="'wide' holds 6 words .* and 5 in the small one"):
            _RowTable({"wide": (wp.zeros((n, 6), dtype=float), small[0])}, n, cap)


def test_capacity_rule_and_refusals(start_states, monkeypatch):
    assert [compact_reset_capacity(n) for n in (64, 4095, 4096, 16384)] == [0, 0, 64, 256]
    # The rule stands aside for sensors in every substep, which the small pass cannot serve; asked for, it refuses.
    monkeypatch.setattr(warp_backend, "compact_reset_capacity", lambda n: 2)
    auto = WarpSim(SimConfig(num_worlds=4, device="cpu", reset_pass="reduced", sensors_every_substep=True))
    auto.register_start_states(*start_states)
    assert auto._compact is None
    sim = WarpSim(SimConfig(num_worlds=4, device="cpu", reset_pass="reduced"))
    for bad in (-1, 4, 1.5, True):
        with pytest.raises(ValueError, match=r"compact must be an int in \[0, 4\)"):
            sim.register_start_states(*start_states, compact=bad)
    substeps = WarpSim(SimConfig(num_worlds=4, device="cpu", reset_pass="reduced", sensors_every_substep=True))
    with pytest.raises(ValueError, match="sensors_every_substep"):
        substeps.register_start_states(*start_states, compact=2)
    with pytest.raises(ValueError, match=r"capacity must be in \[1, 4\)"):
        CompactResetPass(sim.mj_model, sim.wp_model, sim.wp_data, 4, 8, 64, 0)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_gpu_compacted_pass_matches_the_pass_over_every_world_and_never_syncs(start_states):
    """On the GPU (recorded graphs, the chunks a loop on the device): resets that fit the small Data and one that
    does not, each followed by steps, read nothing on the host and agree with the pass over every world (contacts come
    in another order within a world there: float tolerance)."""
    cuda = [t.cuda() for t in start_states]
    sims = []
    for capacity in (0, 2):
        sim = WarpSim(SimConfig(num_worlds=N, device="cuda", reset_pass="reduced"))
        sim.register_start_states(*cuda, compact=capacity)
        sims.append(sim)
    every, compact = sims
    index = torch.tensor([1, 0, 2, 1, 0, 2], device="cuda")
    for mask in ([1, 0, 0, 1, 0, 0], [0, 1, 1, 1, 0, 1], [0, 0, 1, 0, 0, 0]):
        mask = torch.tensor(mask, dtype=torch.bool, device="cuda")
        torch.cuda.set_sync_debug_mode("error")
        try:
            for sim in sims:
                sim.reset_to_start(mask, index)
                for _ in range(3):
                    sim.step()
        finally:
            torch.cuda.set_sync_debug_mode(0)
        for key in ("qpos", "qvel", "sensordata", "foot_force", "healthy"):
            torch.testing.assert_close(getattr(compact, key), getattr(every, key), rtol=1e-3, atol=1e-3,
                                       msg=lambda m, key=key, mask=mask: f"{key} after reset {mask.tolist()}: {m}")
    assert int(compact._compact._chunk.numpy()[0]) == 1  # the last reset took the small Data once
    assert compact._start_reset_graph.graph is not None  # recorded: the loop's condition is never read on the host
