"""Force references (spec §3.3) and the reward's stance pattern (spec §8) at the boundary rows."""

import numpy as np
import pytest
from reference_data import reference_file

from tocabi_torchrl.motion import DOUBLE_SUPPORT, LEFT_STANCE, RIGHT_STANCE, force_schedule, stance_schedule
from tocabi_torchrl.motion.io import load_txt
from tocabi_torchrl.motion.schedule import REFERENCE_WEIGHT_FORCE, cycle_layout

F = -1025.0


def smooth(s):
    return 3 * s**2 - 2 * s**3


# (row, Fz_L) by hand from the walk.m loops of spec §3.3 (0-based rows).
FORCE_ROWS = [
    (0, F * (1 - smooth(301 / 600))),  # −509.9
    (298, F * (1 - smooth(599 / 600))),  # −0.0085
    (299, 0.0),
    (300, 0.0),
    (1499, 0.0),
    (1500, F * smooth(1 / 600)),
    (1799, F * smooth(300 / 600)),  # −512.5
    (1800, F * smooth(301 / 600)),
    (2098, F * smooth(599 / 600)),
    (2099, F),
    (3299, F),
    (3300, F * (1 - smooth(1 / 600))),
    (3599, F * (1 - smooth(300 / 600))),  # −512.5
]

# (row, stance) from the reward's rule of spec §8, including the quirk at rows 300 and 1500.
STANCE_ROWS = [
    (0, DOUBLE_SUPPORT),
    (299, DOUBLE_SUPPORT),
    (300, LEFT_STANCE),  # quirk: neither "< 300" nor "300 <"
    (301, RIGHT_STANCE),
    (1499, RIGHT_STANCE),
    (1500, LEFT_STANCE),  # quirk
    (1501, DOUBLE_SUPPORT),
    (1800, DOUBLE_SUPPORT),
    (2099, DOUBLE_SUPPORT),
    (2100, LEFT_STANCE),
    (3300, LEFT_STANCE),
    (3301, DOUBLE_SUPPORT),
    (3599, DOUBLE_SUPPORT),
]


def test_weight_force_is_the_reference_rounding_of_mg():
    assert REFERENCE_WEIGHT_FORCE == 1025.0


@pytest.mark.parametrize("row,left", FORCE_ROWS)
def test_force_schedule_boundary_rows(row, left):
    forces = force_schedule(3600, 600)
    assert forces.shape == (3600, 2)
    assert forces[row, 0] == pytest.approx(left, abs=1e-9)
    assert forces[row, 1] == pytest.approx(F - left, abs=1e-9)


def test_force_schedule_spec_numbers_and_shape():
    forces = force_schedule(3600, 600)
    assert forces[0, 0] == pytest.approx(-509.9, abs=0.05)
    assert forces[298, 0] == pytest.approx(-0.0085, abs=1e-4)
    assert forces[1799] == pytest.approx([-512.5, -512.5])
    assert forces[3599] == pytest.approx([-512.5, -512.5])
    np.testing.assert_allclose(forces.sum(axis=1), F)
    assert forces.min() == F and forces.max() == 0.0
    # Single supports hold the whole weight on one foot for 1201 rows each.
    assert np.sum(forces[:, 0] == 0.0) == 1201 and np.sum(forces[:, 1] == 0.0) == 1201
    # Row to row, the load never jumps: at most the cubic's steepest slope, 1.5 F / 600 per row.
    assert np.abs(np.diff(forces[:, 0])).max() <= 1.5 * 1025 / 600 + 1e-9


@pytest.mark.parametrize("row,code", STANCE_ROWS)
def test_stance_schedule_boundary_rows(row, code):
    assert stance_schedule(3600, 600)[row] == code


def test_stance_schedule_counts():
    stance = stance_schedule(3600, 600)
    assert stance.dtype == np.int64
    # DSP rows: 0..299, 1501..2099, 3301..3599; right 301..1499; left 2100..3300 plus 300 and 1500.
    assert np.sum(stance == DOUBLE_SUPPORT) == 300 + 599 + 299
    assert np.sum(stance == RIGHT_STANCE) == 1199
    assert np.sum(stance == LEFT_STANCE) == 1201 + 2


@pytest.mark.parametrize("rows,dsp", [(3601, 600), (3600, 601), (3600, 2000), (3600, 0), (0, 0)])
def test_cycle_layout_rejects_impossible_layouts(rows, dsp):
    with pytest.raises(ValueError, match="rows"):
        cycle_layout(rows, dsp)


def test_schedule_matches_reference_file():
    ref = load_txt(reference_file("processed_data_tocabi_walk.txt"))
    np.testing.assert_allclose(ref.foot_force, force_schedule(3600, 600), atol=1e-6)
    np.testing.assert_array_equal(ref.stance, stance_schedule(3600, 600))
