"""Motion file formats: loading, joint remapping, and validation errors that say what is wrong."""

import json
import re

import numpy as np
import pytest
from model_files import shipped_model_with_range
from reference_data import reference_file

from tocabi_torchrl.robot import INIT_JOINT_POS, JOINT_NAMES, asset_path
from tocabi_torchrl.motion import (
    MotionData,
    MotionFormatError,
    ReferenceMotion,
    force_schedule,
    load_motion,
    load_npz,
    load_txt,
    save_npz,
    stance_schedule,
)
from tocabi_torchrl.motion.io import NPZ_FORMAT

ROWS = 12


def table(rows: int = ROWS, rate: float = 2000.0, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.arange(rows) / rate
    joints = rng.normal(scale=0.3, size=(rows, 33))
    joints[-1] = joints[0]  # a cycle: its last row is its first again
    return np.column_stack([t, joints, -1025 * rng.random((rows, 2))])


def write_txt(path, tab: np.ndarray, fmt: str = "%.16e") -> str:
    np.savetxt(path, tab, fmt=fmt, delimiter="\t")
    return str(path)


def motion_data(rows: int = ROWS) -> MotionData:
    tab = table(rows)
    return MotionData(
        joint_pos=tab[:, 1:34],
        foot_force=force_schedule(rows, 4),
        stance=stance_schedule(rows, 4),
        sample_rate=2000.0,
        init_rows=np.array([0, rows // 2]),
        base_pos=np.zeros((rows, 3)),
        meta={"generator": "test"},
    )


def npz_fields(**override):
    d = motion_data()
    fields = {
        "format": np.array(NPZ_FORMAT),
        "joint_names": np.array(JOINT_NAMES),
        "joint_pos": d.joint_pos.astype(np.float32),
        "foot_force": d.foot_force.astype(np.float32),
        "stance": d.stance.astype(np.int8),
        "sample_rate": np.array(2000.0),
        "init_rows": d.init_rows,
    }
    fields.update(override)
    return {k: v for k, v in fields.items() if v is not None}


def write_npz(path, **override) -> str:
    np.savez(path, **npz_fields(**override))
    return str(path)


# ------------------------------------------------------------------------------------------------------ text format
def test_txt_loads_columns_and_layout(tmp_path):
    tab = table()
    data = load_txt(write_txt(tmp_path / "m.txt", tab))
    np.testing.assert_array_equal(data.joint_pos, tab[:, 1:34])
    np.testing.assert_array_equal(data.foot_force, tab[:, 34:])
    assert data.sample_rate == 2000.0
    assert data.init_rows.tolist() == [0, ROWS // 2]
    # 12 rows = two 6-row steps, a third of each in double support: 2 rows.
    np.testing.assert_array_equal(data.stance, stance_schedule(ROWS, 2))


def test_txt_wrong_column_count(tmp_path):
    path = tmp_path / "m.txt"
    lines = write_txt(path, table()) and path.read_text().splitlines()
    lines[1] = "\t".join(lines[1].split("\t")[:-1])  # line 2 loses its right foot force
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(MotionFormatError, match=r"line 2 has 35 columns, expected 36 \(time, 33 joint positions"):
        load_txt(path)


def test_txt_non_numeric(tmp_path):
    path = tmp_path / "m.txt"
    write_txt(path, table())
    path.write_text(path.read_text().replace("e-01", "e-O1", 1))
    with pytest.raises(MotionFormatError, match="line 1 is not numeric"):
        load_txt(path)


def test_txt_non_monotonic_time(tmp_path):
    tab = table()
    tab[5, 0] = tab[3, 0]
    with pytest.raises(MotionFormatError, match=r"time is not strictly increasing at row 5"):
        load_txt(write_txt(tmp_path / "m.txt", tab))


def test_txt_non_uniform_time(tmp_path):
    tab = table()
    tab[7:, 0] += 0.0001  # a 0.6 ms step among 0.5 ms steps
    with pytest.raises(MotionFormatError, match=r"time steps are not uniform: row 7 is 0.0006 s after row 6"):
        load_txt(write_txt(tmp_path / "m.txt", tab))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_txt_non_finite(tmp_path, bad):
    tab = table()
    tab[4, 5] = bad  # column 5 = joint 4
    with pytest.raises(MotionFormatError, match=rf"non-finite value {bad} at row 4, column 5 \(L_AnklePitch_Joint\)"):
        load_txt(write_txt(tmp_path / "m.txt", tab))


@pytest.mark.parametrize("rows", [0, 1])
def test_txt_fewer_than_two_rows(tmp_path, rows):
    path = tmp_path / "m.txt"
    write_txt(path, table(2)[:rows])
    with pytest.raises(MotionFormatError, match=f"at least two rows .* got {rows}"):
        load_txt(path)


def test_txt_odd_rows_are_not_a_two_step_cycle(tmp_path):
    with pytest.raises(MotionFormatError, match="11 rows do not form a two-step cycle"):
        load_txt(write_txt(tmp_path / "m.txt", table(11)))


def test_txt_printed_time_rounding_is_tolerated(tmp_path):
    data = load_txt(write_txt(tmp_path / "m.txt", table(), fmt="%.7g"))
    assert data.sample_rate == 2000.0


# ----------------------------------------------------------------------------------------------------- npz format
def test_npz_round_trip_is_float32_exact_and_byte_reproducible(tmp_path):
    data = motion_data()
    a, b = save_npz(tmp_path / "a.npz", data), save_npz(tmp_path / "b.npz", data)
    assert a.read_bytes() == b.read_bytes()
    back = load_npz(a)
    np.testing.assert_array_equal(back.joint_pos, data.joint_pos.astype(np.float32))
    np.testing.assert_array_equal(back.foot_force, data.foot_force.astype(np.float32))
    np.testing.assert_array_equal(back.stance, data.stance)
    assert back.sample_rate == 2000.0 and back.init_rows.tolist() == data.init_rows.tolist()
    assert back.base_pos.shape == (ROWS, 3) and back.meta == {"generator": "test"}
    with np.load(a) as raw:
        assert raw["joint_pos"].dtype == np.float32 and str(raw["format"]) == NPZ_FORMAT


def test_npz_other_joint_order_is_remapped(tmp_path):
    perm = np.random.default_rng(1).permutation(33)
    d = motion_data()
    path = write_npz(tmp_path / "m.npz", joint_names=np.array(JOINT_NAMES)[perm], joint_pos=d.joint_pos[:, perm])
    np.testing.assert_allclose(load_npz(path).joint_pos, d.joint_pos, atol=1e-6)


def test_npz_foreign_joint_names_are_rejected(tmp_path):
    names = list(JOINT_NAMES)
    names[24] = "Jaw_Joint"
    with pytest.raises(
        MotionFormatError,
        match=r"joint names do not match the robot: unknown \['Jaw_Joint'\], missing \['Head_Joint'\]",
    ):
        load_npz(write_npz(tmp_path / "m.npz", joint_names=np.array(names)))


def test_npz_duplicated_joint_names_are_rejected(tmp_path):
    names = list(JOINT_NAMES)
    names[1] = names[0]
    with pytest.raises(MotionFormatError, match=r"duplicated \['L_HipYaw_Joint'\]"):
        load_npz(write_npz(tmp_path / "m.npz", joint_names=np.array(names)))


def test_npz_column_count_must_match_names(tmp_path):
    d = motion_data()
    with pytest.raises(MotionFormatError, match="joint_pos has 32 columns but joint_names lists 33 joints"):
        load_npz(write_npz(tmp_path / "m.npz", joint_pos=d.joint_pos[:, :32]))


@pytest.mark.parametrize(
    "override,message",
    [
        ({"stance": None}, r"missing field\(s\) \['stance'\]"),
        ({"format": np.array("other/9")}, "format 'other/9' is not supported"),
        ({"joint_pos": np.zeros((1, 33), np.float32)}, "at least two rows"),
        ({"foot_force": np.zeros((ROWS, 3), np.float32)}, r"foot_force has shape \(12, 3\), expected \(12, 2\)"),
        ({"stance": np.full(ROWS, 5, np.int8)}, r"stance code 5 at row 0"),
        ({"init_rows": np.array([0, 11])}, r"init_rows \[0, 11\] must be a non-empty list in \[0, 10\]"),
        ({"sample_rate": np.array(-1.0)}, "sample_rate must be a positive"),
    ],
)
def test_npz_validation_errors(tmp_path, override, message):
    with pytest.raises(MotionFormatError, match=message):
        load_npz(write_npz(tmp_path / "m.npz", **override))


def test_npz_non_finite(tmp_path):
    d = motion_data()
    jp = d.joint_pos.astype(np.float32)
    jp[3, 30] = np.nan
    message = r"joint_pos: non-finite value nan at row 3, column 30 \(R_Forearm_Joint\)"
    with pytest.raises(MotionFormatError, match=message):
        load_npz(write_npz(tmp_path / "m.npz", joint_pos=jp))


def test_unknown_suffix_and_missing_file(tmp_path):
    with pytest.raises(MotionFormatError, match=r"unknown motion format '.csv'"):
        load_motion(tmp_path / "m.csv")
    with pytest.raises(MotionFormatError, match="motion file not found"):
        load_motion(tmp_path / "absent.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(MotionFormatError, match="not an .npz archive"):
        load_npz(tmp_path / "junk.npz")
    shipped = asset_path("motions", "tocabi_walk.npz")
    (tmp_path / "UPPER.NPZ").write_bytes(open(shipped, "rb").read())  # the suffix's case once refused it
    assert load_motion(tmp_path / "UPPER.NPZ").joint_pos.shape == load_motion(shipped).joint_pos.shape


def test_from_file_dispatches_on_suffix(tmp_path):
    tab = table()
    txt = ReferenceMotion.from_file(write_txt(tmp_path / "m.txt", tab))
    npz = ReferenceMotion.from_file(save_npz(tmp_path / "m.npz", load_txt(tmp_path / "m.txt")))
    for m in (txt, npz):
        assert m.num_rows == ROWS and m.row_dt == 0.0005
        np.testing.assert_allclose(m.joint_pos.numpy(), tab[:, 1:34], atol=1e-6)
    assert txt.source.endswith("m.txt") and npz.source.endswith("m.npz")


def test_shipped_motion_documents_its_generator():
    data = load_npz(asset_path("motions", "tocabi_walk.npz"))
    assert data.meta["generator"] == "tocabi_torchrl.motion.gait"
    assert json.loads(json.dumps(data.meta["config"]))["step_time"] == 0.9
    np.testing.assert_allclose(data.joint_pos[:, 12:], np.tile(INIT_JOINT_POS[12:], (data.num_rows, 1)), atol=1e-7)


def test_reference_txt_loads():
    data = load_txt(reference_file("processed_data_tocabi_walk.txt"))
    assert data.joint_pos.shape == (3600, 33) and data.sample_rate == 2000.0
    np.testing.assert_allclose(data.joint_pos[:, 12:], np.tile(INIT_JOINT_POS[12:], (3600, 1)), atol=1e-12)


# --------------------------------------------------------------------------- corrupt fields of the shipped .npz
def shipped_with(tmp_path, name: str, value) -> str:
    """The shipped motion with one field replaced, written with plain numpy."""
    with np.load(asset_path("motions", "tocabi_walk.npz")) as npz:
        fields = {k: npz[k] for k in npz.files}
    fields[name] = value
    path = tmp_path / f"bad_{name}.npz"
    np.savez(path, **fields)
    return str(path)


@pytest.mark.parametrize(
    "name,value,message",
    [
        ("meta", np.array("{not json"), "meta must be one string holding a JSON object; it is not valid JSON"),
        ("meta", np.array("[1, 2]"), "meta must be one string holding a JSON object, got JSON list"),
        ("sample_rate", np.array([1.0, 2.0]), r"sample_rate must be a single positive number .* got shape \(2,\)"),
        ("sample_rate", np.array("2000"), r"sample_rate must be a single positive number .* got dtype <U4"),
        ("stance", np.full(3600, "1"), r"stance must be a \(rows,\) array of stance codes .* got dtype <U1"),
        ("stance", np.full(3600, 1.5), "stance must be .*; value 1.5 at index 0 is not a whole number"),
        ("joint_pos", np.zeros((2, 3600, 33)), r"joint_pos must be a 2-D \(rows, joints\) .* \(2, 3600, 33\)"),
        ("joint_names", np.array([JOINT_NAMES]), r"joint_names must be a 1-D array of joint names .* shape \(1, 33\)"),
        ("foot_force", np.full((3600, 2), "x"), r"foot_force must be a \(rows, 2\) array .* got dtype <U1"),
        ("base_pos", np.zeros((3600, 3), bool), r"base_pos must be a \(rows, 3\) array .* got dtype bool"),
        ("init_rows", np.array([1.5, 2.7]), r"init_rows must be a 1-D array of integer .*; value 1.5 at index 0"),
        ("init_rows", np.array([0.0, np.nan]), "init_rows must be .*; value nan at index 1 is not a whole number"),
        ("init_rows", np.array([[0, 1800]]), r"init_rows must be a 1-D array of integer .*, got shape \(1, 2\)"),
    ],
)
def test_npz_corrupt_field_names_the_file_and_the_field(tmp_path, name, value, message):
    path = shipped_with(tmp_path, name, value)
    with pytest.raises(MotionFormatError, match=message) as info:
        load_npz(path)
    assert str(info.value).startswith(f"{path}: {name} must be")


def test_npz_whole_number_floats_are_accepted_as_integers(tmp_path):
    data = load_npz(shipped_with(tmp_path, "init_rows", np.array([0.0, 1800.0])))
    assert data.init_rows.dtype == np.int64 and data.init_rows.tolist() == [0, 1800]


def test_env_reports_a_corrupt_motion_by_file(tmp_path):
    from tocabi_torchrl import make_env

    path = shipped_with(tmp_path, "meta", np.array("{not json"))
    with pytest.raises(MotionFormatError, match=re.escape(f"{path}: meta must be one string holding a JSON object")):
        make_env(1, "cpu", motion=path)


def test_save_npz_writes_a_name_load_motion_reads_and_replaces_files_whole(tmp_path, monkeypatch):
    # A name without .npz was written as is, and load_motion then refused it for its suffix.
    import os

    from tocabi_torchrl.motion import io as motion_io

    data = motion_data()
    written = save_npz(tmp_path / "mymotion", data)
    assert written == tmp_path / "mymotion.npz" and not (tmp_path / "mymotion").exists()
    np.testing.assert_array_equal(load_motion(written).stance, data.stance)
    # A crash mid-write leaves the earlier file whole, and no temporary file.
    before = written.read_bytes()

    def crash(*args):
        raise OSError("disk full")

    monkeypatch.setattr(motion_io.os, "replace", crash)
    with pytest.raises(OSError, match="disk full"):
        save_npz(written, motion_data(rows=ROWS + 2))
    assert written.read_bytes() == before and sorted(os.listdir(tmp_path)) == ["mymotion.npz"]


def _cycle(**change) -> MotionData:
    """A 12-row closed cycle at 2 kHz, with ``change``'s fields replaced."""
    t = table()
    fields = dict(joint_pos=t[:, 1:34], foot_force=t[:, 34:], stance=stance_schedule(ROWS, 2), sample_rate=2000.0,
                  init_rows=np.array([0, 6]))
    return MotionData(**{**fields, **change})


@pytest.mark.parametrize("change,message", [
    # Each was accepted: truncated, cast, or loaded to run in other units.
    (dict(init_rows=np.array([0, 5.6])), r"init_rows must be row indices; value 5.6 at index 1 is not a whole"),
    (dict(stance=np.full(ROWS, 0.5)), r"stance must be 0, 1 or 2; value 0.5 at index 0 is not a whole number"),
    (dict(stance=np.full(ROWS, np.nan)), r"stance must be 0, 1 or 2; value nan"),
    (dict(sample_rate="2000"), "sample_rate must be a positive number of rows per second, got '2000'"),
    (dict(sample_rate=0.1), r"the cycle lasts 110 s .* more than 60 s: a time column in ms"),
    (dict(foot_force=np.full((ROWS, 2), 300.0)), r"foot_force\[0, 0\] is 300.0 N; .* <= 0 \(loaded < 0\)"),
    (dict(foot_force=np.full((ROWS, 2), -1e9)), r"foot_force\[0, 0\] is -1000000000.0 N; .* at least -10000 N"),
    (dict(joint_pos=table(seed=0)[:, 1:34] + np.linspace(0, 0.5, ROWS)[:, None]),
     r"the cycle does not close: L_HipYaw_Joint is .* in the first row and .* in the last"),
])
def test_motion_data_refuses_what_the_npz_reader_refuses_and_other_units(change, message):
    with pytest.raises(MotionFormatError, match=message):
        _cycle(**change).validate("m")


def test_a_motion_in_degrees_is_refused_by_the_env(tmp_path):
    # A .txt in degrees loaded, and the env then chased a knee target of 33 rad against a range of about ±3.
    from tocabi_torchrl import make_env
    from tocabi_torchrl.robot import asset_path

    walk = load_motion(asset_path("motions", "tocabi_walk.npz"))
    save_npz(tmp_path / "deg.npz", MotionData(joint_pos=np.degrees(walk.joint_pos), foot_force=walk.foot_force,
                                              stance=walk.stance, sample_rate=walk.sample_rate,
                                              init_rows=walk.init_rows))
    with pytest.raises(ValueError, match=r"deg.npz: .* rad at row .*, outside the model's range .*in degrees"):
        make_env(num_envs=1, device="cpu", motion=str(tmp_path / "deg.npz"))


def test_a_model_range_that_leaves_out_the_start_pose_is_blamed_before_the_motion(tmp_path):
    # A knee range of ±0.5 rad (the start pose bends the knee 0.6 rad) refused the shipped walk as "joint targets are
    # radians (a motion in degrees?)", naming neither the model file nor its range as a cause.
    from tocabi_torchrl import make_env

    model = shipped_model_with_range(tmp_path / "narrow.xml", "L_Knee_Joint", -0.5, 0.5)
    with pytest.raises(ValueError) as info:
        make_env(num_envs=1, device="cpu", model_path=str(model))
    message = str(info.value)
    assert re.fullmatch(r"reference motion .*tocabi_walk\.npz: L_Knee_Joint is [\d.]+ rad at row \d+, outside the "
                        r"model's range \[-0\.500, 0\.500\] in .*narrow\.xml, which leaves out the robot's initial "
                        r"pose \(0\.600 rad, robot\.INIT_JOINT_POS\) too: check L_Knee_Joint's range in the model "
                        r"file \(radians, under <compiler angle=\"radian\">\) before the motion", message), message
    # With a motion in degrees too, the model's range comes first although the shoulders leave theirs farther.
    walk = load_motion(asset_path("motions", "tocabi_walk.npz"))
    save_npz(tmp_path / "deg.npz", MotionData(joint_pos=np.degrees(walk.joint_pos), foot_force=walk.foot_force,
                                              stance=walk.stance, sample_rate=walk.sample_rate,
                                              init_rows=walk.init_rows))
    with pytest.raises(ValueError, match=r"deg\.npz: L_Knee_Joint is .* \(22 joints leave their ranges\), "
                                         r".*narrow\.xml, which leaves out the robot's initial pose"):
        make_env(num_envs=1, device="cpu", model_path=str(model), motion=str(tmp_path / "deg.npz"))


def test_a_motion_beyond_a_model_range_that_holds_the_start_pose_names_both_files_and_both_checks(tmp_path):
    from tocabi_torchrl import make_env

    model = shipped_model_with_range(tmp_path / "short.xml", "R_Knee_Joint", 0.0, 0.8)
    with pytest.raises(ValueError) as info:
        make_env(num_envs=1, device="cpu", model_path=str(model))
    message = str(info.value)
    assert re.fullmatch(r"reference motion .*tocabi_walk\.npz: R_Knee_Joint is [\d.]+ rad at row \d+, outside the "
                        r"model's range \[0\.000, 0\.800\] in .*short\.xml, which holds the robot's initial pose "
                        r"\(0\.600 rad\): check the motion \(joint targets are radians, in robot\.JOINT_NAMES order: "
                        r"a motion in degrees, or of another robot\?\), or, if it is right, R_Knee_Joint's range in "
                        r"the model file", message), message


def test_a_binary_file_named_txt_is_a_format_error(tmp_path):
    # A renamed .npz raised a raw UnicodeDecodeError.
    path = tmp_path / "walk.txt"
    path.write_bytes(asset_path("motions", "tocabi_walk.npz").read_bytes())
    with pytest.raises(MotionFormatError, match=r"walk.txt: not a text file .*a project motion ends in .npz"):
        load_motion(path)


def test_a_motion_shorter_than_two_policy_steps_is_refused_by_the_env(tmp_path):
    # A sample_rate in another unit (1e7 for 2000) was built and stepped: the 0.36 ms cycle is sampled once per 4 ms
    # step, so phase, targets and stance jumped to unrelated rows at every step.
    from tocabi_torchrl import make_env

    path = shipped_with(tmp_path, "sample_rate", np.array(1e7))
    with pytest.raises(ValueError, match=r"bad_sample_rate.npz: its cycle of 3600 rows at 1e\+07 rows/s lasts "
                                         r"0.0003599 s, shorter than two policy steps .*set it to at most 449875"):
        make_env(1, "cpu", motion=path)
    slow = shipped_with(tmp_path, "sample_rate", np.array(250.0))  # a slower walk of the same rows is fine
    assert make_env(1, "cpu", motion=slow).base_env.motion.period == pytest.approx(3599 / 250.0)


@pytest.mark.parametrize("content", ["text", "pickle", "npy", "truncated", "empty"])
def test_a_file_that_is_not_an_npz_archive_is_refused_without_unsafe_advice(tmp_path, content):
    # np.load falls back to unpickling for a non-zip file; refused, its message advised loading the file unsafely
    # (allow_pickle or the pickle module), for a motion file from outside.
    import io
    import pickle

    shipped = asset_path("motions", "tocabi_walk.npz").read_bytes()
    npy = io.BytesIO()
    np.save(npy, np.zeros(3))
    data = {"text": b"time q0 q1", "pickle": pickle.dumps({"joint_pos": [0.0]}), "npy": npy.getvalue(),
            "truncated": shipped[: len(shipped) // 2], "empty": b""}[content]
    path = tmp_path / "walk.npz"
    path.write_bytes(data)
    with pytest.raises(MotionFormatError, match=r"walk.npz: not an .npz archive .*motion.save_npz") as info:
        load_npz(path)
    assert "allow_pickle" not in str(info.value) and "pickle.load" not in str(info.value)


def test_an_object_array_in_a_motion_is_refused_by_field(tmp_path):
    path = shipped_with(tmp_path, "meta", np.array([{"generator": "mine"}], dtype=object))
    with pytest.raises(MotionFormatError, match=r"bad_meta.npz: field 'meta' is an object \(pickled\) array"):
        load_npz(path)


def test_save_npz_writes_numpy_and_path_provenance_and_refuses_meta_it_cannot_read_back(tmp_path):
    # numpy scalars and paths in meta raised a bare "Object of type float32 is not JSON serializable", and a meta of
    # None was written as JSON null, which load_npz then refused.
    from pathlib import Path

    data = motion_data()
    data.meta = {"scale": np.float32(0.5), "rows": np.int64(12), "offsets": np.arange(2), "source": Path("/a/b.txt")}
    written = save_npz(tmp_path / "m.npz", data)
    assert load_npz(written).meta == {"scale": 0.5, "rows": 12, "offsets": [0, 1], "source": "/a/b.txt"}
    for meta, message in ((None, "meta must be a dict .* got NoneType"),
                          ({"tool": object()}, r"meta cannot be written as JSON \(object value"),
                          ({1: "a", "b": 2}, "meta cannot be written as JSON .* str keys")):
        data.meta = meta
        with pytest.raises(MotionFormatError, match=f"save_npz: {message}"):
            save_npz(tmp_path / "other.npz", data)
    assert not (tmp_path / "other.npz").exists()


def test_text_fields_stored_as_bytes_are_read_as_text(tmp_path):
    # joint_names and meta were decoded from bytes but format was not: a file with every string stored as bytes was
    # refused as "format \"np.bytes_(b'tocabi_torchrl.motion/1')\" is not supported", and bytes that are not UTF-8
    # raised a bare UnicodeDecodeError naming no file or field.
    as_bytes = {"format": np.array(NPZ_FORMAT.encode()), "joint_names": np.array([n.encode() for n in JOINT_NAMES]),
                "meta": np.array(b'{"generator": "mine"}')}
    data = load_npz(write_npz(tmp_path / "bytes.npz", **as_bytes))
    assert data.meta == {"generator": "mine"} and data.num_rows == ROWS
    names = [n.encode() for n in JOINT_NAMES]
    names[3] = b"\xff\xfeKnee"
    with pytest.raises(MotionFormatError, match=r"bad.npz: joint_names holds bytes that are not UTF-8 text"):
        load_npz(write_npz(tmp_path / "bad.npz", joint_names=np.array(names)))
    with pytest.raises(MotionFormatError, match=r"list.npz: format must be one string, 'tocabi_torchrl.motion/1'"):
        load_npz(write_npz(tmp_path / "list.npz", format=np.array([NPZ_FORMAT])))


def test_a_model_read_in_degrees_is_blamed_not_the_motion(tmp_path):
    # A model file without <compiler angle="radian"> (MuJoCo reads angles in degrees by default) shrank every joint
    # range by 180/π, and the env refused the shipped walk as "a motion in degrees?": the user went to fix a good
    # motion file. The message names the model file, the unit and the fix.
    from tocabi_torchrl import make_env
    from tocabi_torchrl.robot import RobotAssetError

    model = tmp_path / "no_angle.xml"
    model.write_text(asset_path("tocabi", "tocabi.xml").read_text().replace(' angle="radian"', ""))
    with pytest.raises(RobotAssetError, match=r"no_angle\.xml: it is compiled with <compiler angle=\"degree\">.*"
                                              r"written in radians.*Set <compiler angle=\"radian\">") as info:
        make_env(num_envs=1, device="cpu", model_path=str(model), motion=str(asset_path("motions", "tocabi_walk.npz")))
    assert "reference motion" not in str(info.value) and "tocabi_walk.npz" not in str(info.value)
