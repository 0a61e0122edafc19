"""The generated walking cycle: parameters honoured, kinematically sound on the model, structured like the reference."""

import numpy as np
import pytest
from model_files import DEGREE_COMPILERS, shipped_model_read_as
from reference_data import reference_file

from tocabi_torchrl import robot
from tocabi_torchrl.motion import ReferenceMotion, force_schedule, load_npz, load_txt, stance_schedule
from tocabi_torchrl.motion.analysis import gait_metrics, self_contacts, stance_foot_drift
from tocabi_torchrl.motion.gait import _REPO, SHIPPED_MODEL, GaitConfig, generate_walk, main, model_label, plan_gait
from tocabi_torchrl.motion.schedule import DOUBLE_SUPPORT

LEG = slice(0, 12)


@pytest.fixture(scope="module")
def walk(model):
    return generate_walk(GaitConfig(), model)


@pytest.fixture(scope="module")
def reference():
    return load_txt(reference_file("processed_data_tocabi_walk.txt"))


# ------------------------------------------------------------------------------------------------- the shipped file
def test_shipped_motion_is_the_generator_output(walk):
    """Regeneration reproduces assets/motions/tocabi_walk.npz; if the model changed, rerun the generator."""
    shipped = load_npz(robot.asset_path("motions", "tocabi_walk.npz"))
    hint = "stale assets/motions/tocabi_walk.npz: run `python -m tocabi_torchrl.motion.gait --overwrite`"
    np.testing.assert_allclose(shipped.joint_pos, walk.joint_pos, atol=2e-6, err_msg=hint)
    np.testing.assert_allclose(shipped.base_pos, walk.base_pos, atol=2e-6, err_msg=hint)
    np.testing.assert_array_equal(shipped.stance, walk.stance)
    assert shipped.init_rows.tolist() == walk.init_rows.tolist() == [0, 1800]


def test_generation_is_deterministic(model, walk):
    again = generate_walk(GaitConfig(), model)
    np.testing.assert_array_equal(again.joint_pos, walk.joint_pos)


# ---------------------------------------------------------------------------------------------- layout and schedule
def test_layout_force_and_stance_follow_the_spec(walk):
    assert walk.num_rows == 3600 and walk.sample_rate == 2000.0
    np.testing.assert_array_equal(walk.stance, stance_schedule(3600, 600))
    np.testing.assert_allclose(walk.foot_force, force_schedule(3600, 600))
    # Start rows sit in the middle of the two double supports: 300 double-support rows on either side.
    for row in walk.init_rows:
        window = (row + np.arange(-299, 300)) % 3600
        assert (walk.stance[window] == DOUBLE_SUPPORT).all()
    np.testing.assert_allclose(walk.joint_pos[-1], walk.joint_pos[0], atol=1e-12)  # closed under period R-1
    np.testing.assert_allclose(walk.joint_pos[:, 12:], np.tile(robot.INIT_JOINT_POS[12:], (3600, 1)))
    assert np.abs(np.diff(walk.joint_pos[:, LEG], axis=0)).max() < 0.004  # no row-to-row jumps (reference: 0.0039)


def test_gait_parameters_are_honoured(walk):
    m = gait_metrics(walk.joint_pos, walk.init_rows)
    np.testing.assert_allclose(m.clearance, 0.054, atol=2e-4)
    assert m.step_length == pytest.approx(0.12, abs=2e-4)
    assert m.step_width == pytest.approx(0.25, abs=1e-4)
    assert m.pelvis_height == pytest.approx(0.93, abs=1e-4)
    assert 0.07 < m.sway < 0.09  # "~±8 cm"
    # The swing apex is mid single support: rows 900 (left swings) and 2700 (right swings).
    np.testing.assert_allclose(m.clearance_row, [900, 2700], atol=5)
    np.testing.assert_allclose(walk.joint_pos[:, [0, 6]], 0.0, atol=1e-9)  # straight walk: no hip yaw


def test_changed_parameters_change_the_cycle(model):
    cfg = GaitConfig(step_length=0.08, swing_height=0.04, step_width=0.23)
    m = gait_metrics(generate_walk(cfg, model).joint_pos, [0, 1800])
    assert m.step_length == pytest.approx(0.08, abs=2e-4)
    np.testing.assert_allclose(m.clearance, 0.04, atol=2e-4)
    assert m.step_width == pytest.approx(0.23, abs=1e-4)


def test_com_follows_the_lipm_plan(model):
    """The pelvis is placed so that the model's whole-body CoM lies on the planned LIPM CoM."""
    import mujoco

    plan = plan_gait(GaitConfig(), model)
    data = mujoco.MjData(model)
    for k in range(0, plan.time.size, 97):
        data.qpos[:3] = plan.pelvis[k]
        data.qpos[3:7] = (1, 0, 0, 0)
        data.qpos[7:] = plan.joint_pos[k]
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        np.testing.assert_allclose(data.subtree_com[0][:2], plan.com[k], atol=1e-6)


@pytest.mark.parametrize(
    "field,value,message",
    [
        ("dsp_time", 0.9, "dsp_time 0.9 must lie in"),
        ("dsp_time", 0.0, "dsp_time 0.0 must lie in"),
        ("step_time", -1.0, "step_time must be positive"),
        ("swing_height", -0.01, "swing_height must be >= 0"),
        ("sample_rate", float("nan"), "sample_rate must be a finite number, got nan"),
        ("pelvis_height", float("inf"), "pelvis_height must be a finite number, got inf"),
        ("zmp_travel", float("nan"), "zmp_travel must be a finite number"),
        ("com_height", -0.5, "com_height must be positive"),
        ("com_tolerance", 0.0, "com_tolerance must be positive"),
        # A rate with no upper bound tried to build a table of billions of rows (tens of GB) before any check.
        ("sample_rate", 2e9, r"sample_rate must lie in \(0, 10000\] rows per second .*got 2000000000.0"),
        ("sample_rate", 10_000.5, r"sample_rate must lie in \(0, 10000\]"),
        ("sample_rate", 1.0, "span two or more rows at sample_rate=1 rows per second"),
        ("step_time", 900.0, r"step_time must be at most 30 s \(the two-step cycle lasts at most 60 s.*got 900.0"),
    ],
)
def test_config_validation(field, value, message):
    with pytest.raises(ValueError, match=message):
        GaitConfig(**{field: value}).validate()


# ------------------------------------------------------------------------------------------ kinematic soundness
def test_stance_foot_stays_put_over_single_support(model, walk):
    drift = stance_foot_drift(model, walk.joint_pos.astype(np.float32), walk.base_pos.astype(np.float32), walk.stance)
    for side in ("left", "right"):
        assert drift.slide[side] < 0.005, drift
        assert drift.lift[side] < 0.001, drift
        assert drift.tilt[side] < 0.02, drift


def test_stance_foot_check_catches_a_sliding_foot(model, walk):
    """The check is not vacuous: bending the right hip during right stance moves the planted foot."""
    joints = walk.joint_pos.copy()
    joints[:, 8] += 0.05 * np.sin(np.linspace(0, 2 * np.pi, joints.shape[0]))
    drift = stance_foot_drift(model, joints, walk.base_pos, walk.stance)
    assert drift.slide["right"] > 0.005 and drift.tilt["right"] > 0.02


def test_no_self_penetration_along_the_cycle(model, walk):
    assert self_contacts(model, walk.joint_pos, walk.base_pos) == []


def test_self_penetration_check_catches_crossed_legs(model, walk):
    joints = walk.joint_pos[::600].copy()
    joints[:, 1] -= 0.4  # left hip rolls in
    joints[:, 7] += 0.4  # right hip rolls in
    hits = self_contacts(model, joints, walk.base_pos[::600])
    assert any({"L_Thigh_Link", "R_Thigh_Link"} <= {b1, b2} for _, b1, b2, _ in hits)


# ---------------------------------------------------------------------------------------------- against the reference
def test_reference_structure_is_what_the_spec_measured(reference):
    m = gait_metrics(reference.joint_pos, reference.init_rows)
    np.testing.assert_allclose(m.clearance, 0.054, atol=1e-3)
    np.testing.assert_allclose(m.clearance_row, [888, 2689], atol=2)
    assert m.step_length == pytest.approx(0.119, abs=1e-3)
    assert m.sway == pytest.approx(0.079, abs=1e-3)


def test_generated_cycle_matches_the_reference_structure(walk, reference):
    gen = gait_metrics(walk.joint_pos, walk.init_rows)
    ref = gait_metrics(reference.joint_pos, reference.init_rows)
    np.testing.assert_array_equal(walk.stance, reference.stance)  # identical stance schedule
    np.testing.assert_allclose(walk.foot_force, reference.foot_force, atol=1e-6)
    assert ((gen.clearance > 0.04) & (gen.clearance < 0.07)).all()
    assert 0.10 < gen.step_length < 0.14
    assert np.abs(gen.leg_range - ref.leg_range).max() < 0.1, gen.leg_range - ref.leg_range
    # Stronger than the issue asks: each leg joint's extremes are within 0.06 rad of the reference's too.
    assert np.abs(gen.leg_min - ref.leg_min).max() < 0.06 and np.abs(gen.leg_max - ref.leg_max).max() < 0.06
    assert gen.sway == pytest.approx(ref.sway, abs=0.005)
    # Whole trajectories, not only their extremes, stay close: RMS difference per leg joint below 0.05 rad.
    rms = np.sqrt(((walk.joint_pos[:, LEG] - reference.joint_pos[:, LEG]) ** 2).mean(axis=0))
    assert rms.max() < 0.05, rms


def test_reference_motion_lookups_agree_between_reference_and_generated(walk, reference):
    """Same layout, so the env can swap them: the same rows, stance and forces for any time."""
    import torch

    a, b = ReferenceMotion.from_data(walk), ReferenceMotion.from_data(reference)
    time = torch.rand(256, generator=torch.Generator().manual_seed(0)) * 20
    init = torch.tensor([0, 1800]).repeat(128)
    assert torch.equal(a.row_index(time, init), b.row_index(time, init))
    idx = a.row_index(time, init)
    assert torch.equal(a.stance_at(idx), b.stance_at(idx))
    assert a.period == b.period


# --------------------------------------------------------------------------------------------------------- CLI
def test_cli_writes_motion_and_plot(tmp_path, capsys):
    out, png = tmp_path / "walk.npz", tmp_path / "legs.png"
    assert main(["--out", str(out), "--plot", str(png), "--swing-height", "0.05"]) == 0
    data = load_npz(out)
    assert data.meta["config"]["swing_height"] == 0.05
    assert data.meta["model"] == "assets/tocabi/tocabi.xml"
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"
    assert "clearance_m" in capsys.readouterr().out
    assert out.stat().st_size < 400_000


def test_highest_sample_rate_makes_a_cycle(model):
    # The bound admits what it documents: a table five times finer than the simulator's 2 kHz.
    data = generate_walk(GaitConfig(sample_rate=10_000.0), model)
    assert data.num_rows == 18_000 and data.sample_rate == 10_000.0


@pytest.mark.parametrize("argv,message", [
    (["--sample-rate", "2e9"], "sample_rate must lie in (0, 10000] rows per second (five times the simulator's 2000 "
                               "steps per second), got 2000000000.0; change --sample-rate"),
    (["--step-time", "900"], "step_time must be at most 30 s (the two-step cycle lasts at most 60 s; the reference's "
                             "step is 0.9 s), got 900.0; change --step-time"),
])
def test_cli_refuses_a_table_past_the_bounds_before_planning(tmp_path, capsys, monkeypatch, argv, message):
    """--sample-rate 2e9 went on to plan 3.6e9 rows (tens of GB, or a hang), a step_time in ms 3.6e6 rows (hours)
    before the motion's period check refused the result. Both are usage errors naming the option and the allowed
    range, raised before the model is even compiled."""

    def planned(*args, **kwargs):
        raise AssertionError("the generator went on to compile the model and plan the table")

    monkeypatch.setattr(robot, "load_model", planned)
    out = tmp_path / "walk.npz"
    with pytest.raises(SystemExit) as stop:
        main(["--out", str(out), *argv])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and f"cannot generate the walk: {message}" in err, err
    assert not out.exists()


def test_cli_help(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--help"])
    assert stop.value.code == 0
    text = capsys.readouterr().out
    assert "--step-length" in text and "--plot" in text and "heel-to-toe" in text


@pytest.mark.parametrize(
    "argv,options",
    [
        (["--pelvis-height", "1.2"], ["--pelvis-height", "--step-length", "--step-width", "--swing-height"]),
        (["--zmp-travel", "5"], ["--zmp-travel", "--zmp-offset-x"]),  # the hint once named the step options alone
        (["--sample-rate", "nan"], ["--sample-rate"]),
        (["--dsp-time", "2"], ["--dsp-time", "--step-time"]),
        (["--sample-rate", "1"], ["--sample-rate", "--dsp-time"]),
    ],
)
def test_cli_reports_parameters_that_make_no_gait(tmp_path, capsys, argv, options):
    """A parameter the generator cannot use is a one-line usage error naming the options to change; nothing is
    written."""
    out = tmp_path / "walk.npz"
    with pytest.raises(SystemExit) as stop:
        main(["--out", str(out), *argv])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "cannot generate the walk" in err
    assert all(option in err for option in options), err
    assert not out.exists()


@pytest.mark.parametrize("name,content", [("ref.npz", b"not a zip"), ("ref.txt", b"1 2 3\n")])
def test_cli_refuses_a_reference_that_is_no_motion_in_one_line(tmp_path, capsys, name, content):
    # A corrupt --reference ended in a MotionFormatError traceback.
    (tmp_path / name).write_bytes(content)
    with pytest.raises(SystemExit) as stop:
        main(["--out", str(tmp_path / "walk.npz"), "--reference", str(tmp_path / name)])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and "--reference: " in err and "Traceback" not in err
    assert not (tmp_path / "walk.npz").exists()


def test_cli_without_matplotlib_refuses_plot_before_writing_anything(tmp_path, capsys, monkeypatch):
    # The figure is drawn after --out is written: without matplotlib (the viz extra) --plot ended in a traceback
    # after the planning, leaving a motion that the rerun without --plot then had to --overwrite.
    import sys

    def planned(*args, **kwargs):
        raise AssertionError("the generator went on to compile the model and plan the table")

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # what an install without the viz extra imports
    monkeypatch.setattr(robot, "load_model", planned)
    out = tmp_path / "walk.npz"
    with pytest.raises(SystemExit) as stop:
        main(["--out", str(out), "--plot", str(tmp_path / "legs.png"), "--sample-rate", "200"])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and "--plot needs matplotlib" in err and "pip install" in err, err
    assert not out.exists()


def test_cli_refuses_a_missing_model(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--out", str(tmp_path / "walk.npz"), "--model", str(tmp_path / "none.xml")])
    assert stop.value.code == 2
    assert "--model" in capsys.readouterr().err


def test_cli_records_the_model_it_planned_on(tmp_path):
    """meta["model"] is the --model file, not the shipped one (a coarse table keeps the test short)."""
    other = tmp_path / "other.xml"
    other.write_text(robot.asset_path("tocabi", "tocabi.xml").read_text())
    out = tmp_path / "walk.npz"
    assert main(["--out", str(out), "--model", str(other), "--sample-rate", "200"]) == 0
    assert load_npz(out).meta["model"] == str(other)


def test_cli_replaces_no_file_unasked_and_reads_the_reference_first(tmp_path, capsys, monkeypatch):
    # It replaced the shipped motion when --out was left out (the shipped policies then ran against another cycle),
    # any --out or --plot, and read --reference after writing --out over it (the plot compared the walk with itself).
    import tocabi_torchrl.motion.plot as plot

    shipped = robot.asset_path("motions", "tocabi_walk.npz")
    before = shipped.read_bytes()
    with pytest.raises(SystemExit) as stop:
        main(["--sample-rate", "200"])
    assert stop.value.code == 2 and "(the shipped motion the shipped policies were trained on); pass --overwrite" \
        in capsys.readouterr().err
    assert shipped.read_bytes() == before
    out, png = tmp_path / "walk.npz", tmp_path / "legs.png"
    assert main(["--out", str(out), "--sample-rate", "200"]) == 0
    first = out.read_bytes()
    for argv, message in ((["--out", str(out)], f"--out {out} exists; pass --overwrite"),
                          (["--out", str(tmp_path / "w2"), "--plot", str(tmp_path / "legs.npz")], "give a .png file"),
                          (["--out", str(tmp_path)], f"--out {tmp_path} is a folder")):
        with pytest.raises(SystemExit) as stop:
            main([*argv, "--sample-rate", "200"])
        assert stop.value.code == 2 and message in capsys.readouterr().err
    assert out.read_bytes() == first and not (tmp_path / "w2.npz").exists()
    seen = {}
    monkeypatch.setattr(plot, "plot_leg_joints", lambda data, reference, path: seen.update(reference=reference))
    assert main(["--out", str(out), "--plot", str(png), "--reference", str(out), "--overwrite", "--sample-rate",
                 "200", "--swing-height", "0.05"]) == 0
    assert out.read_bytes() != first  # replaced, as asked; the plot's reference is the file as it was
    np.testing.assert_allclose(seen["reference"].joint_pos[:5], _first_rows(first))


def _first_rows(npz_bytes: bytes):
    import io

    with np.load(io.BytesIO(npz_bytes), allow_pickle=False) as data:
        return data["joint_pos"][:5]


def test_cli_refuses_a_model_read_in_degrees_naming_the_model(tmp_path, capsys):
    # The generator planned on it without a word (its ranges are not used here), and the env later refused the
    # motion it wrote as "a motion in degrees?".
    model = shipped_model_read_as(tmp_path, DEGREE_COMPILERS["degree"])
    out = tmp_path / "w.npz"
    with pytest.raises(SystemExit) as stop:
        main(["--out", str(out), "--model", str(model), "--sample-rate", "200"])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "--model: robot model" in err and "in_degrees.xml" in err, err
    assert 'Set <compiler angle="radian">' in err and not out.exists()


def test_cli_refuses_a_model_whose_legs_differ_from_the_planned_geometry(tmp_path, capsys):
    # It planned with TOCABI's leg lengths on a model of longer legs: replayed there, the feet were 13 cm in the
    # ground and the stance feet slid.
    longer = tmp_path / "long_legs.xml"
    longer.write_text(robot.asset_path("tocabi", "tocabi.xml").read_text().replace('pos="0 0 -0.35"',
                                                                                   'pos="0 0 -0.42"'))
    with pytest.raises(SystemExit) as stop:
        main(["--out", str(tmp_path / "w.npz"), "--model", str(longer), "--sample-rate", "200"])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and "the model's legs are not the ones the gait is planned for: left thigh 0.42" in err
    assert not (tmp_path / "w.npz").exists()


def test_model_label_is_repo_relative_inside_the_checkout(tmp_path):
    assert model_label(robot.asset_path("tocabi", "tocabi.xml")) == SHIPPED_MODEL == "assets/tocabi/tocabi.xml"
    if (_REPO / "pyproject.toml").is_file():  # a source checkout
        assert model_label(_REPO / "tests" / "data" / "m.xml") == "tests/data/m.xml"
    assert model_label(tmp_path / "m.xml") == str(tmp_path / "m.xml")


def test_generate_walk_records_the_model_path(model):
    cfg = GaitConfig(sample_rate=200.0)
    assert generate_walk(cfg).meta["model"] == "assets/tocabi/tocabi.xml"
    assert generate_walk(cfg, model).meta["model"] is None  # a compiled model without its path: not guessed


@pytest.mark.parametrize("every", [0, -1, 1.5, True])
def test_self_contacts_refuses_a_stride_that_is_not_a_positive_int(model, walk, every):
    # every=-1 returned [] (no row checked: "no contact"), every=0 a bare "range() arg 3 must not be zero".
    with pytest.raises(ValueError, match="every must be an int >= 1"):
        self_contacts(model, walk.joint_pos[:3], walk.base_pos[:3], every=every)


def test_an_interrupted_plot_leaves_the_earlier_figure_whole(tmp_path, monkeypatch):
    # The figure was drawn straight into its file: a run stopped while saving (regenerating the docs' figure with
    # --overwrite) left half a PNG under its name.
    from pathlib import Path

    from matplotlib.figure import Figure

    from tocabi_torchrl.motion.plot import plot_leg_joints

    walk = load_npz(robot.asset_path("motions", "tocabi_walk.npz"))
    png = tmp_path / "legs.png"
    plot_leg_joints(walk, None, png, dpi=20)
    earlier = png.read_bytes()
    assert earlier[:4] == b"\x89PNG"

    def stopped(self, fname, **kwargs):  # the first bytes are out, then Ctrl-C
        if hasattr(fname, "write"):
            fname.write(b"\x89PNG cut short")
        else:
            Path(fname).write_bytes(b"\x89PNG cut short")
        raise KeyboardInterrupt

    monkeypatch.setattr(Figure, "savefig", stopped)
    with pytest.raises(KeyboardInterrupt):
        plot_leg_joints(walk, None, png, dpi=20)
    assert png.read_bytes() == earlier, "the earlier figure was replaced by a cut-off one"


def test_plotting_leaves_the_callers_matplotlib_backend_alone(tmp_path, walk):
    import matplotlib

    from tocabi_torchrl.motion.plot import plot_leg_joints
    from tocabi_torchrl.evaluation.plots import plot_knees

    before = matplotlib.get_backend()
    try:
        matplotlib.use("svg")
        plot_leg_joints(walk, None, tmp_path / "legs.png")
        plot_knees(np.zeros((5, 2)), np.zeros((5, 2)), 0.004, tmp_path / "knees.png", (0.5, 0.0))
        assert matplotlib.get_backend() == "svg"
    finally:
        matplotlib.use(before)
    assert (tmp_path / "legs.png").read_bytes()[:4] == b"\x89PNG" and (tmp_path / "knees.png").stat().st_size > 0
