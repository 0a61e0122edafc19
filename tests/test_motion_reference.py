"""ReferenceMotion: batched, sync-free lookups against hand computations and the spec's float64 formulas."""

import numpy as np
import pytest
import torch
from reference_data import reference_file

from tocabi_torchrl import robot
from tocabi_torchrl.motion import (
    DOUBLE_SUPPORT,
    LEFT_STANCE,
    RIGHT_STANCE,
    MotionData,
    ReferenceMotion,
    force_schedule,
    stance_schedule,
)


def small_motion(rows: int = 10, sample_rate: float = 2.0, seed: int = 0) -> ReferenceMotion:
    """Random table on a coarse clock (dt = 0.5 s) so phases like 3.25 rows are exact in float32."""
    rng = np.random.default_rng(seed)
    joint_pos = rng.normal(size=(rows, 33))
    joint_pos[-1] = joint_pos[0]  # a cycle: its last row is its first again
    data = MotionData(
        joint_pos=joint_pos,
        foot_force=-1025 * rng.random((rows, 2)),
        stance=stance_schedule(rows, 2),
        sample_rate=sample_rate,
        init_rows=np.array([0, rows // 2]),
    )
    return ReferenceMotion.from_data(data)


@pytest.fixture(scope="module")
def walk() -> ReferenceMotion:
    return ReferenceMotion.default()


def spec_lookup(time: float, init: int, table: np.ndarray, n: int, dt: float):
    """Spec §3.2 in float64, literally: idx, lt', and the zero-velocity cubic between rows idx and idx+1."""
    period = n * dt
    lt = time % period
    idx = (init + int(np.floor(lt / dt))) % n
    ltp = (lt + init * dt) % period
    s = np.clip((ltp - idx * dt) / dt, 0.0, 1.0)
    q = table[idx] + (table[idx + 1] - table[idx]) * (3 * s**2 - 2 * s**3)
    phase = ((init + lt / dt) % n) / n
    return idx, q, phase


# ------------------------------------------------------------------------------------------------ hand computations
@pytest.mark.parametrize(
    "rows_in,init,expect_row,s",
    [
        (3.25, 0, 3, 0.25),
        (3.25, 5, 8, 0.25),  # 5 + 3 = 8 = N - 1, the last interpolated interval
        (3.25, 7, 1, 0.25),  # 7 + 3 = 10 -> wraps mod N = 9
        (9 + 3.25, 0, 3, 0.25),  # one full period later: the same
        (0.5, 4, 4, 0.5),
        (8.75, 0, 8, 0.75),
        (0.0, 5, 5, 0.0),
    ],
)
def test_joint_targets_equal_hand_computed_cubic(rows_in, init, expect_row, s):
    m = small_motion()
    time = torch.tensor([rows_in * 0.5])
    init_row = torch.tensor([init])
    q = m.joint_pos.numpy().astype(np.float64)
    w = 3 * s**2 - 2 * s**3
    expect = q[expect_row] + (q[expect_row + 1] - q[expect_row]) * w
    assert m.row_index(time, init_row).tolist() == [expect_row]
    np.testing.assert_allclose(m.joint_targets(time, init_row)[0].numpy(), expect, rtol=0, atol=1e-6)


def test_phase_hand_computed():
    m = small_motion()  # N = 9 rows per cycle
    time = torch.tensor([3.25 * 0.5, 3.25 * 0.5, 0.0, 9 * 0.5 * 3 + 1.0])
    init_row = torch.tensor([0, 7, 5, 0])
    expect = [3.25 / 9, (10.25 % 9) / 9, 5 / 9, 2.0 / 9]
    np.testing.assert_allclose(m.phase(time, init_row).numpy(), expect, atol=1e-6)


def test_cubic_has_zero_velocity_at_rows():
    """Between two rows the target eases in and out: a quarter of the way in time is 15.6 % of the way in value."""
    m = small_motion()
    t = torch.tensor([2.0, 2.0 + 0.125, 2.0 + 0.25, 2.0 + 0.375, 2.5])  # rows 4, 4.25, 4.5, 4.75, 5
    q = m.joint_targets(t, torch.zeros(5, dtype=torch.int64))[:, 0].numpy()
    frac = (q - q[0]) / (q[-1] - q[0])
    np.testing.assert_allclose(frac, [0.0, 0.15625, 0.5, 0.84375, 1.0], atol=1e-5)


# ----------------------------------------------------------------------------------- spec boundaries on the real cycle
@pytest.mark.parametrize(
    "row,stance",
    [(0, DOUBLE_SUPPORT), (299, DOUBLE_SUPPORT), (300, LEFT_STANCE), (301, RIGHT_STANCE), (1499, RIGHT_STANCE),
     (1500, LEFT_STANCE), (1501, DOUBLE_SUPPORT), (2099, DOUBLE_SUPPORT), (2100, LEFT_STANCE), (3300, LEFT_STANCE),
     (3301, DOUBLE_SUPPORT), (3598, DOUBLE_SUPPORT)],
)  # fmt: skip
def test_stance_and_force_at_boundary_rows(walk, row, stance):
    idx = torch.tensor([row])
    assert walk.stance_at(idx).tolist() == [stance]
    f = force_schedule(3600, 600)[row]
    np.testing.assert_allclose(walk.force_reference(idx)[0].numpy(), f, atol=1e-3)


def test_row_index_at_boundary_rows_from_time(walk):
    """A time in the middle of row k gives row k, and its force and stance are those of row k."""
    rows = torch.tensor([0, 298, 299, 300, 301, 1499, 1500, 1501, 2099, 2100, 3299, 3300, 3598])
    time = (rows.to(torch.float64) + 0.5) * 0.0005
    idx = walk.row_index(time.to(torch.float32), torch.zeros_like(rows))
    assert idx.tolist() == rows.tolist()
    assert walk.stance_at(idx).tolist() == stance_schedule(3600, 600)[rows.numpy()].tolist()


def test_default_motion_layout(walk):
    assert walk.num_rows == 3600 and walk.cycle_rows == 3599
    assert walk.row_dt == 0.0005
    assert walk.period == pytest.approx(1.7995)
    assert walk.init_rows.tolist() == [0, 1800]
    assert walk.joint_pos.dtype == torch.float32 and walk.joint_pos.shape == (3600, 33)
    assert walk.foot_force.shape == (3600, 2) and walk.stance.dtype == torch.int64
    assert walk.base_pos is not None and walk.base_pos.shape == (3600, 3)
    # The upper body holds the initial pose (spec §3.1).
    np.testing.assert_allclose(walk.joint_pos[:, 12:].numpy(), np.tile(robot.INIT_JOINT_POS[12:], (3600, 1)), atol=1e-7)


# --------------------------------------------------------------------------------------------- batching and precision
def test_batched_lookup_equals_loop_of_single_lookups(walk):
    gen = torch.Generator().manual_seed(0)
    n = 64
    time = torch.rand(n, generator=gen) * 40.0
    init_row = torch.randint(0, 3599, (n,), generator=gen)
    idx = walk.row_index(time, init_row)
    q = walk.joint_targets(time, init_row)
    ph = walk.phase(time, init_row)
    f, st = walk.force_reference(idx), walk.stance_at(idx)
    assert idx.shape == (n,) and q.shape == (n, 33) and ph.shape == (n,) and f.shape == (n, 2) and st.shape == (n,)
    for i in range(n):
        t1, r1 = time[i : i + 1], init_row[i : i + 1]
        i1 = walk.row_index(t1, r1)
        assert i1.item() == idx[i].item()
        assert torch.equal(walk.joint_targets(t1, r1)[0], q[i])
        assert torch.equal(walk.phase(t1, r1)[0], ph[i])
        assert torch.equal(walk.force_reference(i1)[0], f[i])
        assert walk.stance_at(i1).item() == st[i].item()


def test_float32_lookup_matches_spec_float64_away_from_row_boundaries(walk):
    rng = np.random.default_rng(1)
    table = walk.joint_pos.numpy().astype(np.float64)
    n = walk.cycle_rows
    # Times whose row fraction is safely inside (0.05, 0.95): float32 and float64 must pick the same row.
    rows = rng.integers(0, 30 * n, 200)
    frac = rng.uniform(0.05, 0.95, 200)
    time = ((rows + frac) * 0.0005).astype(np.float32)
    init = rng.choice([0, 1800], 200)
    idx = walk.row_index(torch.from_numpy(time), torch.from_numpy(init)).numpy()
    q = walk.joint_targets(torch.from_numpy(time), torch.from_numpy(init)).numpy()
    ph = walk.phase(torch.from_numpy(time), torch.from_numpy(init)).numpy()
    for i in range(200):
        e_idx, e_q, e_ph = spec_lookup(float(time[i]), int(init[i]), table, n, 0.0005)
        assert idx[i] == e_idx
        np.testing.assert_allclose(q[i], e_q, atol=2e-5)
        assert ph[i] == pytest.approx(e_ph, abs=1e-5)


def test_lookup_is_robust_at_period_multiples_and_row_boundaries(walk):
    """float32 time exactly at (or a hair off) row and period boundaries never indexes outside the table."""
    period32 = np.float32(walk.period)
    edges = [0.0, period32, 2 * period32, 17 * period32, np.nextafter(period32, 0), np.nextafter(period32, 10)]
    rows = np.arange(0, 3599, 7) * np.float32(0.0005)
    time = torch.tensor(np.concatenate([edges, rows, rows + 5 * period32]).astype(np.float32))
    for init in (0, 1800, 3598):
        init_row = torch.full_like(time, init, dtype=torch.int64)
        idx = walk.row_index(time, init_row)
        assert int(idx.min()) >= 0 and int(idx.max()) <= 3598
        ph = walk.phase(time, init_row)
        assert float(ph.min()) >= 0.0 and float(ph.max()) < 1.0
        q = walk.joint_targets(time, init_row)
        assert torch.isfinite(q).all()
    # At the exact row times the float32 row is the intended one or its predecessor, and the target is continuous.
    exact = torch.arange(1, 3599, 13)
    t = (exact.to(torch.float64) * 0.0005).to(torch.float32)
    idx = walk.row_index(t, torch.zeros_like(exact))
    assert bool(((idx == exact) | (idx == exact - 1)).all())
    q = walk.joint_targets(t, torch.zeros_like(exact))
    np.testing.assert_allclose(q.numpy(), walk.joint_pos[exact].numpy(), atol=1e-4)


def test_cycle_wraps_smoothly(walk):
    """Across the period the target moves as little as anywhere else: the shipped cycle is closed."""
    t = torch.arange(0, 2 * 3599 + 1, dtype=torch.float64) * 0.0005
    q = walk.joint_targets(t.to(torch.float32), torch.zeros(t.numel(), dtype=torch.int64))
    steps = (q[1:] - q[:-1]).abs().amax(dim=1)
    assert float(steps.max()) < 0.005


def test_sample_init_rows_draws_from_init_rows(walk):
    gen = torch.Generator().manual_seed(3)
    rows = walk.sample_init_rows(1000, generator=gen)
    assert rows.dtype == torch.int64 and rows.shape == (1000,)
    assert set(rows.tolist()) == {0, 1800}
    assert 400 < int((rows == 0).sum()) < 600


def test_to_moves_every_tensor(walk):
    moved = walk.to("meta")
    assert moved.joint_pos.is_meta and moved.foot_force.is_meta and moved.stance.is_meta
    assert moved.init_rows.is_meta and moved.base_pos.is_meta
    assert moved.row_dt == walk.row_dt and walk.joint_pos.device.type == "cpu"


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_lookups_do_not_synchronise_on_gpu(walk):
    gpu = walk.to("cuda")
    time = torch.rand(4096, device="cuda") * 30
    init_row = gpu.sample_init_rows(4096)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        idx = gpu.row_index(time, init_row)
        gpu.joint_targets(time, init_row), gpu.force_reference(idx), gpu.stance_at(idx), gpu.phase(time, init_row)
    finally:
        torch.cuda.set_sync_debug_mode("default")


def test_reference_file_loads_with_spec_layout():
    ref = ReferenceMotion.from_file(reference_file("processed_data_tocabi_walk.txt"))
    assert ref.num_rows == 3600 and ref.period == pytest.approx(1.7995)
    assert ref.row_dt == 0.0005 and ref.init_rows.tolist() == [0, 1800]
    # Spec §3.4 samples: row 1800 of the hip pitch columns, and the force columns at rows 0 and 1799.
    assert ref.joint_pos[1800, 2].item() == pytest.approx(-0.36998, abs=1e-5)
    assert ref.joint_pos[1800, 8].item() == pytest.approx(-0.16275, abs=1e-5)
    assert ref.force_reference(torch.tensor([1799]))[0].tolist() == pytest.approx([-512.5, -512.5], abs=1e-3)
