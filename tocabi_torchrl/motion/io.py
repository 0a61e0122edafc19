"""Reading, checking and writing reference motions as host (numpy) arrays.

Two formats are read; :func:`load_motion` picks one by the file suffix.

**Reference text format** (``.txt``, spec §3.1): whitespace-separated, one row per sample at a uniform rate (2 kHz
in the reference), 36 columns: time [s], the 33 joint positions [rad] in ``robot.JOINT_NAMES`` order, then the
vertical foot-force references ``Fz_L, Fz_R`` [N] (sensor sign, loaded < 0). The file carries no stance pattern
or start rows, so they follow the reference layout (:mod:`.schedule`): the stance pattern of spec §8 for a cycle of
``R`` rows with ``dsp_fraction`` of each step in double support, and start rows ``0`` and ``R/2``.

**Project format** (``.npz``, format ``tocabi_torchrl.motion/1``), written by :func:`save_npz`:

=============== =========== ======= ===========================================================================
field           shape       dtype   meaning
=============== =========== ======= ===========================================================================
``format``      ()          str     ``"tocabi_torchrl.motion/1"``
``joint_names`` (J,)        str     joint of each ``joint_pos`` column; any order of ``robot.JOINT_NAMES``
                                    (columns are remapped to the robot order on load; other names are rejected)
``joint_pos``   (R, J)      float32 joint position targets [rad]; row ``r`` is at time ``r / sample_rate``
``foot_force``  (R, 2)      float32 vertical foot-force references [N], [left, right], loaded < 0
``stance``      (R,)        int8    expected contact: 0 double support, 1 right stance, 2 left stance
``sample_rate`` ()          float64 rows per second [Hz] (2000 for the shipped cycle)
``init_rows``   (K,)        int64   rows an episode may start at, each in [0, R−2]
``base_pos``    (R, 3)      float32 optional: planned pelvis (``base_link``) position [m], world frame of the
                                    cycle's first row; the pelvis is level and faces +x throughout
``meta``        ()          str     optional: JSON with the generator and its parameters (informational)
=============== =========== ======= ===========================================================================

As in the reference, the cycle period is ``(R − 1) / sample_rate``: the last row is only the interpolation end
point of row ``R − 2``, so a closed cycle has row ``R − 1`` equal to row 0. Every loader returns a validated
:class:`MotionData` in robot joint order, or raises :class:`MotionFormatError` saying what is wrong and where.
"""

from __future__ import annotations

import io
import json
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tocabi_torchrl.robot import JOINT_NAMES, NUM_JOINTS

from ..atomic import atomic_write_bytes
from .schedule import DOUBLE_SUPPORT, LEFT_STANCE, cycle_layout, stance_schedule

__all__ = [
    "NPZ_FORMAT",
    "TXT_COLUMNS",
    "MotionFormatError",
    "MotionData",
    "load_motion",
    "load_txt",
    "load_npz",
    "save_npz",
]

NPZ_FORMAT = "tocabi_torchrl.motion/1"
#: Columns of the reference text format: time, 33 joints, 2 foot forces.
TXT_COLUMNS = 1 + NUM_JOINTS + 2
_TXT_LAYOUT = "time, 33 joint positions, 2 foot forces"
_REQUIRED_NPZ = ("format", "joint_names", "joint_pos", "foot_force", "stance", "sample_rate", "init_rows")
# Relative spread of time steps tolerated as "uniform": text files print time with finite precision.
_TIME_STEP_RTOL = 1e-3
#: The largest load a reference may put on one foot [N]: about ten times TOCABI's weight (1,025 N); the reference's
#: peak is the whole weight. More is a unit mistake (kN read as N, a scale).
MAX_FOOT_FORCE = 10_000.0
#: How far the last row's joint targets may be from the first's [rad]: the cycle's end point is its start again (the
#: reference walk's seam is 0.00225 rad; a larger jump kicks every joint at every loop).
SEAM_TOLERANCE = 0.01
#: The longest cycle [s] a motion may last: the reference's is 1.8 s; hours are a time column in ms.
MAX_PERIOD = 60.0


class MotionFormatError(ValueError):
    """A motion file or array set is malformed; the message names the file, the field and the offending row."""


@dataclass
class MotionData:
    """A reference motion as host arrays, joints in ``robot.JOINT_NAMES`` order (R rows).

    Attributes:
        joint_pos: (R, 33) joint position targets [rad].
        foot_force: (R, 2) vertical foot-force references [N], [left, right], loaded < 0.
        stance: (R,) int64 expected contact, 0 double support / 1 right stance / 2 left stance.
        sample_rate: rows per second [Hz].
        init_rows: (K,) int64 rows an episode may start at.
        base_pos: optional (R, 3) planned pelvis position [m].
        meta: free-form provenance (generator name and parameters, source file).
    """

    joint_pos: np.ndarray
    foot_force: np.ndarray
    stance: np.ndarray
    sample_rate: float
    init_rows: np.ndarray
    base_pos: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    @property
    def num_rows(self) -> int:
        return int(self.joint_pos.shape[0])

    def validate(self, source: str = "motion") -> "MotionData":
        """Check shapes, finiteness, stance codes and start rows (whole numbers, never truncated), the foot forces'
        sign and size (loaded < 0, at most :data:`MAX_FOOT_FORCE` N), that the cycle closes (the last row is the
        first, to :data:`SEAM_TOLERANCE` rad) and a period of at most :data:`MAX_PERIOD` s; return ``self``, else
        raise MotionFormatError."""
        rate = self.sample_rate
        if isinstance(rate, (bool, str, bytes)) or not isinstance(rate, (int, float, np.number)):
            raise MotionFormatError(f"{source}: sample_rate must be a positive number of rows per second, got "
                                    f"{self.sample_rate!r}")
        st = _whole_numbers(source, "stance", self.stance, "0, 1 or 2")
        _whole_numbers(source, "init_rows", self.init_rows, "row indices")
        jp, ff = np.asarray(self.joint_pos), np.asarray(self.foot_force)
        if jp.ndim != 2 or jp.shape[1] != NUM_JOINTS:
            raise MotionFormatError(f"{source}: joint_pos has shape {jp.shape}, expected (rows, {NUM_JOINTS})")
        rows = jp.shape[0]
        if rows < 2:
            raise MotionFormatError(f"{source}: a motion needs at least two rows (one interval), got {rows}")
        if ff.shape != (rows, 2):
            raise MotionFormatError(f"{source}: foot_force has shape {ff.shape}, expected ({rows}, 2)")
        if st.shape != (rows,):
            raise MotionFormatError(f"{source}: stance has shape {st.shape}, expected ({rows},)")
        for name, arr, cols in (("joint_pos", jp, JOINT_NAMES), ("foot_force", ff, ("left", "right"))):
            _check_finite(arr, f"{source}: {name}", cols)
        if self.base_pos is not None:
            bp = np.asarray(self.base_pos)
            if bp.shape != (rows, 3):
                raise MotionFormatError(f"{source}: base_pos has shape {bp.shape}, expected ({rows}, 3)")
            _check_finite(bp, f"{source}: base_pos", ("x", "y", "z"))
        bad = (st < DOUBLE_SUPPORT) | (st > LEFT_STANCE)
        if bad.any():
            r = int(np.argmax(bad))
            raise MotionFormatError(
                f"{source}: stance code {st[r]} at row {r}; allowed 0 (double), 1 (right), 2 (left)"
            )
        if not (np.isfinite(self.sample_rate) and self.sample_rate > 0):
            raise MotionFormatError(f"{source}: sample_rate must be a positive number of rows per second")
        period = (rows - 1) / float(self.sample_rate)
        if period > MAX_PERIOD:
            raise MotionFormatError(f"{source}: the cycle lasts {period:g} s ({rows} rows at {self.sample_rate:g} "
                                    f"rows/s), more than {MAX_PERIOD:g} s: a time column in ms, or the sample rate "
                                    "of another unit?")
        if (ff > 0).any() or (ff < -MAX_FOOT_FORCE).any():
            r, c = (int(i) for i in np.argwhere((ff > 0) | (ff < -MAX_FOOT_FORCE))[0])
            raise MotionFormatError(f"{source}: foot_force[{r}, {c}] is {float(ff[r, c])!r} N; the reference forces "
                                    f"are the load on each foot, <= 0 (loaded < 0) and at least -{MAX_FOOT_FORCE:g} N")
        seam = np.abs(jp[-1] - jp[0])
        if seam.max() > SEAM_TOLERANCE:
            j = int(np.argmax(seam))
            raise MotionFormatError(f"{source}: the cycle does not close: {JOINT_NAMES[j]} is {float(jp[0, j]):.4f} "
                                    f"rad in the first row and {float(jp[-1, j]):.4f} in the last; the last row is the "
                                    "cycle's end point (the first row again), or the targets jump at every loop")
        init = np.asarray(self.init_rows)
        if init.ndim != 1 or init.size == 0 or (init < 0).any() or (init > rows - 2).any():
            raise MotionFormatError(f"{source}: init_rows {init.tolist()} must be a non-empty list in [0, {rows - 2}]")
        return self


def _check_finite(arr: np.ndarray, what: str, columns) -> None:
    bad = ~np.isfinite(arr)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise MotionFormatError(f"{what}: non-finite value {arr[r, c]} at row {r}, column {c} ({columns[c]})")


def load_motion(path: str | os.PathLike) -> MotionData:
    """Load a ``.txt`` (reference format) or ``.npz`` (project format) motion."""
    p = Path(path)
    if p.suffix.lower() == ".npz":  # MOTION.NPZ too: the format is the file's, not its name's case
        return load_npz(p)
    if p.suffix.lower() == ".txt":
        return load_txt(p)
    raise MotionFormatError(f"{p}: unknown motion format {p.suffix!r}; expected .txt (reference) or .npz (project)")


def load_txt(path: str | os.PathLike, dsp_fraction: float = 1.0 / 3.0) -> MotionData:
    """Read the reference text format (see the module docstring).

    Args:
        path: the text file.
        dsp_fraction: share of each step spent in double support (1/3 in the reference: 0.3 s of 0.9 s); sets the
            stance pattern, which the text format does not store.
    """
    p = Path(path)
    if not p.is_file():
        raise MotionFormatError(f"motion file not found: {p}")
    rows: list[list[float]] = []
    try:
        with p.open(encoding="utf-8") as fh:
            for line_no, line in enumerate(fh, start=1):
                fields = line.split()
                if not fields:
                    continue
                if len(fields) != TXT_COLUMNS:
                    raise MotionFormatError(
                        f"{p}: line {line_no} has {len(fields)} columns, expected {TXT_COLUMNS} ({_TXT_LAYOUT})"
                    )
                try:
                    rows.append([float(x) for x in fields])
                except ValueError as err:
                    raise MotionFormatError(f"{p}: line {line_no} is not numeric ({err})") from err
    except UnicodeDecodeError as err:  # a binary file (a renamed .npz?) read as text
        raise MotionFormatError(f"{p}: not a text file ({err.reason} at byte {err.start}); the .txt format is "
                                f"{TXT_COLUMNS} numbers a line ({_TXT_LAYOUT}); a project motion ends in .npz") from err
    table = np.asarray(rows, dtype=np.float64).reshape(-1, TXT_COLUMNS)
    if table.shape[0] < 2:
        raise MotionFormatError(f"{p}: a motion needs at least two rows (one interval), got {table.shape[0]}")
    _check_finite(table, str(p), ("time",) + JOINT_NAMES + ("Fz_left", "Fz_right"))
    sample_rate = _sample_rate_of(table[:, 0], str(p))
    num_rows = table.shape[0]
    try:
        dsp_rows = 2 * int(round(dsp_fraction * num_rows / 4))
        stance = stance_schedule(num_rows, dsp_rows)
        step_rows, _ = cycle_layout(num_rows, dsp_rows)
    except ValueError as err:
        raise MotionFormatError(f"{p}: {num_rows} rows do not form a two-step cycle: {err}") from err
    return MotionData(
        joint_pos=table[:, 1 : 1 + NUM_JOINTS],
        foot_force=table[:, 1 + NUM_JOINTS :],
        stance=stance,
        sample_rate=sample_rate,
        init_rows=np.array([0, step_rows], dtype=np.int64),
        meta={"source": str(p), "format": "reference-txt"},
    ).validate(str(p))


def _sample_rate_of(time: np.ndarray, source: str) -> float:
    """Rows per second of a strictly increasing, uniform time column; raise naming the first bad row otherwise."""
    steps = np.diff(time)
    if (steps <= 0).any():
        r = int(np.argmax(steps <= 0)) + 1
        raise MotionFormatError(
            f"{source}: time is not strictly increasing at row {r} (t={float(time[r])!r} after "
            f"t={float(time[r - 1])!r})"
        )
    typical = float(np.median(steps))  # the median names the odd step, where the mean would blame row 1
    off = np.abs(steps - typical) > _TIME_STEP_RTOL * typical
    if off.any():
        r = int(np.argmax(off)) + 1
        raise MotionFormatError(
            f"{source}: time steps are not uniform: row {r} is {steps[r - 1]:.6g} s after row {r - 1}, "
            f"expected {typical:.6g} s"
        )
    rate = (time.size - 1) / (time[-1] - time[0])
    # Printed times carry rounding (1.7995/3599 is not exactly 0.0005); snap to a whole rate when that is the intent.
    return float(round(rate)) if abs(rate - round(rate)) < 1e-6 * rate else float(rate)


def load_npz(path: str | os.PathLike) -> MotionData:
    """Read the project format (see the module docstring), remapping columns to ``robot.JOINT_NAMES`` order."""
    p = Path(path)
    if not p.is_file():
        raise MotionFormatError(f"motion file not found: {p}")
    fields = _read_npz(p)
    missing = [k for k in _REQUIRED_NPZ if k not in fields]
    if missing:
        raise MotionFormatError(f"{p}: missing field(s) {missing}; a {NPZ_FORMAT} file has {list(_REQUIRED_NPZ)}")
    fmt = _format_field(p, fields["format"])
    if fmt != NPZ_FORMAT:
        raise MotionFormatError(f"{p}: format {fmt!r} is not supported; expected {NPZ_FORMAT!r}")
    names = _joint_names(p, fields["joint_names"])
    joint_pos = _floats(p, "joint_pos", fields["joint_pos"], "a 2-D (rows, joints) array of joint positions [rad]")
    if joint_pos.ndim != 2:
        raise MotionFormatError(
            f"{p}: joint_pos must be a 2-D (rows, joints) array of joint positions [rad], got shape {joint_pos.shape}"
        )
    if joint_pos.shape[1] != len(names):
        raise MotionFormatError(
            f"{p}: joint_pos has {joint_pos.shape[1]} columns but joint_names lists {len(names)} joints"
        )
    joint_pos = joint_pos[:, _robot_order(names, str(p))]
    base_pos = fields.get("base_pos")
    return MotionData(
        joint_pos=joint_pos,
        foot_force=_floats(p, "foot_force", fields["foot_force"], "a (rows, 2) array of foot forces [N]"),
        stance=_whole_numbers(
            p, "stance", fields["stance"], "a (rows,) array of stance codes 0 (double), 1 (right), 2 (left)"
        ),
        sample_rate=_sample_rate_field(p, fields["sample_rate"]),
        init_rows=_init_rows_field(p, fields["init_rows"]),
        base_pos=None if base_pos is None else _floats(p, "base_pos", base_pos, "a (rows, 3) array of positions [m]"),
        meta=_meta_field(p, fields["meta"]) if "meta" in fields else {},
    ).validate(str(p))


def _read_npz(p: Path) -> dict[str, np.ndarray]:
    """Every array of the archive ``p``, never unpickling anything (no code from a file runs).

    A file that is not a zip at all (text, a pickle, a bare .npy, empty or cut short) is refused before numpy sees
    it: np.load falls back to pickle for such files, and its refusal then advised loading the file unsafely.
    """
    if not zipfile.is_zipfile(p):
        raise MotionFormatError(f"{p}: not an .npz archive (a zip of .npy arrays): the file is empty, cut short or of "
                                "another format; write motions with tocabi_torchrl.motion.save_npz (or numpy.savez)")
    fields: dict[str, np.ndarray] = {}
    try:
        with np.load(p, allow_pickle=False) as npz:
            for name in npz.files:
                fields[name] = _read_field(p, npz, name)
    except MotionFormatError:
        raise
    except Exception as err:  # a damaged archive (bad CRC, broken header): numpy's own words
        raise MotionFormatError(f"{p}: cannot read as .npz ({err})") from err
    return fields


def _read_field(p: Path, npz, name: str) -> np.ndarray:
    """One array of an open archive. numpy refuses an object array with a ValueError about allow_pickle, its only
    mark (the dtype is unknown until the member is read), so that refusal is told apart by its words."""
    try:
        return npz[name]
    except ValueError as err:
        if "allow_pickle" not in str(err):
            raise
        raise MotionFormatError(f"{p}: field {name!r} is an object (pickled) array, which a motion file may not hold "
                                "(reading it would run code from the file); store numbers and strings as numeric and "
                                "str arrays") from err


# Converters of the .npz fields: each returns the field in its MotionData type, or raises MotionFormatError naming
# the file, the field and what it must be (numpy's own errors name neither, and its casts truncate silently).
def _describe(arr: np.ndarray) -> str:
    return f"dtype {arr.dtype}, shape {arr.shape}"


def _text(p: Path, name: str, value: str | bytes) -> str:
    """One string of a str or bytes field. Other tools (h5py conversions, ``np.array(b"...")``) store text as bytes,
    which str() would turn into "b'...'" and a bare decode fails on with a UnicodeDecodeError naming no field."""
    if not isinstance(value, bytes):
        return str(value)
    try:
        return value.decode("utf-8")
    except UnicodeDecodeError as err:
        raise MotionFormatError(f"{p}: {name} holds bytes that are not UTF-8 text ({err.reason} at byte {err.start}): "
                                f"{value[:40]!r}; store it as str") from err


def _format_field(p: Path, value: np.ndarray) -> str:
    arr = np.asarray(value)
    if arr.ndim != 0 or arr.dtype.kind not in "US":
        raise MotionFormatError(f"{p}: format must be one string, {NPZ_FORMAT!r}, got {_describe(arr)}")
    return _text(p, "format", arr.item())


def _joint_names(p: Path, value: np.ndarray) -> list[str]:
    arr = np.asarray(value)
    if arr.ndim != 1 or arr.dtype.kind not in "US":
        raise MotionFormatError(f"{p}: joint_names must be a 1-D array of joint names (strings), got {_describe(arr)}")
    return [_text(p, "joint_names", n) for n in arr.tolist()]


def _floats(p: Path, name: str, value: np.ndarray, must: str) -> np.ndarray:
    """A numeric field as float64 (integer or float dtypes; not strings, booleans, complex or objects)."""
    arr = np.asarray(value)
    if arr.dtype.kind not in "iuf":
        raise MotionFormatError(f"{p}: {name} must be {must} (an integer or float dtype), got {_describe(arr)}")
    return arr.astype(np.float64)


def _whole_numbers(p: Path | str, name: str, value: np.ndarray, must: str) -> np.ndarray:
    """An integer field as int64: an integer dtype, or floats that are all whole numbers (never truncated)."""
    arr = np.asarray(value)
    if arr.dtype.kind in "iu":
        return arr.astype(np.int64)
    if arr.dtype.kind != "f":
        raise MotionFormatError(f"{p}: {name} must be {must} (an integer dtype), got {_describe(arr)}")
    with np.errstate(invalid="ignore"):
        bad = ~(np.isfinite(arr) & (np.abs(arr) <= 2.0**53)) | (arr != np.round(arr))
    if bad.any():
        at = tuple(int(i) for i in np.argwhere(bad)[0]) if arr.ndim else ()
        where = f" at index {at[0] if len(at) == 1 else at}" if at else ""
        raise MotionFormatError(
            f"{p}: {name} must be {must}; value {float(arr[at])!r}{where} is not a whole number"
        )
    return arr.astype(np.int64)


def _sample_rate_field(p: Path, value: np.ndarray) -> float:
    arr = _floats(p, "sample_rate", value, "a single positive number of rows per second [Hz]")
    if arr.size != 1:
        raise MotionFormatError(
            f"{p}: sample_rate must be a single positive number of rows per second [Hz], got shape {arr.shape}"
        )
    return float(arr.reshape(()))


def _init_rows_field(p: Path, value: np.ndarray) -> np.ndarray:
    must = "a 1-D array of integer start rows"
    rows = _whole_numbers(p, "init_rows", value, must)
    if rows.ndim > 1:
        raise MotionFormatError(f"{p}: init_rows must be {must}, got shape {rows.shape}")
    return rows.reshape(-1)


def _meta_field(p: Path, value: np.ndarray) -> dict:
    arr = np.asarray(value)
    if arr.ndim != 0 or arr.dtype.kind not in "US":
        raise MotionFormatError(f"{p}: meta must be one string holding a JSON object, got {_describe(arr)}")
    text = _text(p, "meta", arr.item())
    try:
        meta = json.loads(text)
    except ValueError as err:  # JSONDecodeError is a ValueError
        raise MotionFormatError(
            f"{p}: meta must be one string holding a JSON object; it is not valid JSON ({err})"
        ) from err
    if not isinstance(meta, dict):
        raise MotionFormatError(
            f"{p}: meta must be one string holding a JSON object, got JSON {type(meta).__name__}"
        )
    return meta


def _robot_order(names: list[str], source: str) -> np.ndarray:
    """Column permutation taking a file's joint order to ``robot.JOINT_NAMES``; reject any other joint set."""
    unknown = [n for n in names if n not in JOINT_NAMES]
    missing = [n for n in JOINT_NAMES if n not in names]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if unknown or missing or dupes:
        raise MotionFormatError(
            f"{source}: joint names do not match the robot: unknown {unknown}, missing {missing}, duplicated {dupes}"
        )
    return np.array([names.index(n) for n in JOINT_NAMES])


def save_npz(path: str | os.PathLike, data: MotionData) -> Path:
    """Write ``data`` in the project format (float32, compressed) and return the path written: ``path``, with
    ``.npz`` appended when it has another ending (as ``np.savez`` does), since :func:`load_motion` picks the format
    by the suffix. The file is written atomically (a temporary file beside it, renamed over it): a crash never
    leaves half a motion where the env would load it."""
    data.validate("save_npz")
    p = Path(path)
    if p.suffix != ".npz":
        p = p.with_name(p.name + ".npz")
    p.parent.mkdir(parents=True, exist_ok=True)
    fields = {
        "format": np.array(NPZ_FORMAT),
        "joint_names": np.array(JOINT_NAMES),
        "joint_pos": np.asarray(data.joint_pos, dtype=np.float32),
        "foot_force": np.asarray(data.foot_force, dtype=np.float32),
        "stance": np.asarray(data.stance, dtype=np.int8),
        "sample_rate": np.array(float(data.sample_rate)),
        "init_rows": np.asarray(data.init_rows, dtype=np.int64),
        "meta": np.array(_meta_json(data.meta)),
    }
    if data.base_pos is not None:
        fields["base_pos"] = np.asarray(data.base_pos, dtype=np.float32)
    _write_npz(p, fields)
    return p


def _meta_json(meta) -> str:
    """``meta`` as the JSON object :func:`load_npz` reads back. Provenance often holds numpy scalars or arrays and
    paths (a parameter taken from an array, the source file), which json refused with a bare TypeError; they are
    written as plain numbers, lists and strings. A meta that is not a dict was written as JSON the loader refuses."""
    if not isinstance(meta, dict):
        raise MotionFormatError(f"save_npz: meta must be a dict (JSON object) of provenance, got "
                                f"{type(meta).__name__}; use {{}} for none")

    def plain(value):
        if isinstance(value, (np.generic, np.ndarray)):
            return value.tolist()
        if isinstance(value, os.PathLike):
            return os.fspath(value)
        raise TypeError(f"{type(value).__name__} value {value!r:.60}")

    try:
        return json.dumps(meta, sort_keys=True, default=plain)
    except (TypeError, ValueError) as err:  # an unknown type, or keys of mixed types that cannot be sorted
        raise MotionFormatError(f"save_npz: meta cannot be written as JSON ({err}); give it str keys and plain "
                                "strings, numbers, lists and dicts as values") from err


def _write_npz(path: Path, fields: dict[str, np.ndarray]) -> None:
    """``np.savez_compressed`` with a fixed timestamp per member, so regenerating a motion gives identical bytes;
    written atomically."""
    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, arr in fields.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(arr), allow_pickle=False)
            zf.writestr(info, buf.getvalue())
    atomic_write_bytes(path, archive.getvalue())

