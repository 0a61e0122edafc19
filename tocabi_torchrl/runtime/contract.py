"""The policy I/O contract: the JSON file written beside an exported ONNX policy, read and checked here.

The contract says everything a controller needs to run the policy without the training stack: joint order, what each
action means per control mode, timing, the observation entries (37; 43 with the pelvis velocity) and how they are
normalised and stacked, the reference motion and the versions. ``docs/deploying.md`` describes it field by field. This
module imports only the standard library and :mod:`tocabi_torchrl.value_rules` (itself standard library only), so a
deployment can check a contract before loading anything else.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import struct
import warnings
from pathlib import Path

from ..value_rules import (DELAY_APPLIED, ENV_RULES, NON_NEGATIVE, PUSH_KINDS, delay_grid_problem,
                           trained_under_problems)

__all__ = ["CONTRACT_FORMAT", "CONTRACT_VERSION", "ENV_FIELDS", "NORMALIZATION_KINDS", "READABLE_VERSIONS",
           "REQUIRED_KEYS", "RUNTIME_SIGNALS", "UNHASHED_KEYS", "ContractError", "check_contract", "content_sha256",
           "contract_beside", "exported_policy_kind", "folder_note", "load_contract"]

#: ``format`` field of every contract.
CONTRACT_FORMAT = "tocabi_torchrl.policy_contract"
#: Layout version of the contract. Bump it when a field changes meaning; readers refuse versions they do not know. An
#: added optional section (``trained_under``) changes no field's meaning: older contracts without it still load.
#: Version 2 added ``content_sha256``, required from then on.
CONTRACT_VERSION = 2
#: Versions this reader loads: a version 1 contract (exported before ``content_sha256`` existed) loads with a warning
#: that its values are not covered by a hash.
READABLE_VERSIONS = (1, 2)
#: What ``content_sha256`` leaves out (dotted paths): the hash itself; ``policy.onnx_file``, a name only (the file's
#: bytes are bound by ``policy.onnx_sha256``, which is covered, and a pair may be renamed); and the sections that set
#: what the sim-to-sim driver measures and randomises, not the policy's action (``termination``, ``trained_under``).
#: Everything else is covered: every value the runtime or a controller applies to compute or apply the action.
UNHASHED_KEYS: tuple[str, ...] = ("content_sha256", "policy.onnx_file", "termination", "trained_under")

#: Top-level keys and the nested keys the runtime relies on (``"a.b"`` = key ``b`` of section ``a``).
REQUIRED_KEYS: tuple[str, ...] = (
    "format", "contract_version", "package_version", "training_config_sha256",
    "policy", "policy.onnx_file", "policy.onnx_sha256", "policy.input_name", "policy.output_name",
    "policy.input_dim", "policy.output_dim",
    "robot", "robot.joint_names", "robot.leg_joint_names", "robot.upper_joint_names", "robot.initial_qpos",
    "robot.base_body", "robot.neck_body", "robot.foot_force_sensors", "robot.foot_torque_sensors",
    "timing", "timing.physics_dt_s", "timing.substeps", "timing.control_dt_s",
    "action", "action.dim", "action.low", "action.high", "action.control_mode", "action.leg", "action.phase_rate",
    "action.phase_rate.index", "action.phase_rate.gain", "upper_body", "upper_body.kp", "upper_body.kv",
    "observation", "observation.step_dim", "observation.entries", "observation.signals", "observation.normalization",
    "observation.normalization.mean", "observation.normalization.scale", "observation.history",
    "observation.history.obs_ages", "observation.history.action_ages", "observation.phase_harmonics",
    "reference_motion", "reference_motion.name", "reference_motion.sha256", "termination",
    "termination.min_pelvis_height", "termination.min_neck_height", "termination.max_neck_angle",
)  # fmt: skip

#: Keys an export writes besides :data:`REQUIRED_KEYS`: descriptions and values a robot controller may use that the
#: runtime does not read. ``checkpoint``, ``training_config`` and ``trained_under`` are whole sections (the last
#: checked by ``value_rules.trained_under_problems``); ``action.leg`` holds its mode's keys.
OPTIONAL_KEYS: tuple[str, ...] = (
    "checkpoint", "training_config", "trained_under", "policy.opset", "policy.output", "robot.actuator_names",
    "timing.control_hz", "action.nan", "action.phase_rate.rule", "upper_body.hold", "observation.normalization.clip",
    "observation.normalization.eps", "observation.normalization.kind", "observation.normalization.rule",
    "observation.history.blocks", "observation.history.num_actions", "observation.history.num_obs",
    "observation.history.order", "observation.history.reset", "observation.history.stride",
    "reference_motion.init_rows", "reference_motion.interpolation", "reference_motion.period_s",
    "reference_motion.phase", "reference_motion.row_dt_s", "reference_motion.rows",
    "termination.forbidden_contact", "termination.self_collision",
)  # fmt: skip

#: Contract fields that carry a value of the env config the policy was trained with -> that value's path in the env
#: config (``value_rules.ENV_RULES``). Each is checked with the env's own rule, so a value the env refuses (a negative
#: action scale, which made every robot fall) is refused here too. Fields absent in a control mode are skipped.
ENV_FIELDS: dict[str, str] = {
    "timing.substeps": "sim.substeps",
    "action.phase_rate.gain": "task.phase_rate_gain",
    "action.leg.kp": "control.pd_kp",
    "action.leg.kv": "control.pd_kv",
    "action.leg.action_scale": "control.pd_action_scale",
    "action.leg.nominal": "control.pd_nominal",
    "termination.min_pelvis_height": "task.min_pelvis_height",
    "termination.min_neck_height": "task.min_neck_height",
    "termination.max_neck_angle": "task.max_neck_angle",
}

#: The :data:`ENV_FIELDS` whose env value is a tuple (one entry per leg joint); every other one is a single number.
_ENV_LIST_FIELDS = frozenset({"action.leg.kp", "action.leg.kv", "action.leg.nominal"})

_LEG_KEYS = {
    "torque": ("kind", "torque_limits_nm"),
    "pd": ("kind", "kp", "kv", "action_scale", "center", "nominal", "joint_range", "torque_limits_nm"),
    "pd_reference": ("kind", "kp", "kv", "action_scale", "center", "joint_range", "torque_limits_nm"),
    "pd_held": ("kind", "kp", "kv", "action_scale", "center", "torque_limits_nm"),
}
#: ``action.leg.kind`` and ``action.leg.center`` each control mode implies (what the runtime computes from the mode).
_LEG_KIND = {"torque": "torque", "pd": "position", "pd_reference": "position", "pd_held": "torque"}
#: ``observation.normalization.kind`` as the export writes it: statistics fixed by the config, a run's running
#: statistics as they were at export (the runtime never updates them), or none.
NORMALIZATION_KINDS = ("fixed", "running (frozen at export)", "none")
#: The keys an export writes into each ``observation.entries[i]`` and ``observation.signals.<name>``.
_ENTRY_KEYS = {"index", "block", "signal", "element", "name", "unit", "frame"}
_SIGNAL_KEYS = {"shape", "unit", "frame", "source"}
_LEG_CENTER = {"pd": "nominal", "pd_reference": "reference", "pd_held": "reference"}

#: The observation signals :class:`~tocabi_torchrl.runtime.policy.PolicyRuntime` builds; the contract's
#: ``observation.signals`` may use only these.
RUNTIME_SIGNALS: tuple[str, ...] = ("base_rpy", "joint_pos", "joint_vel", "phase_sin", "phase_cos", "command",
                                    "foot_force", "foot_torque", "base_lin_vel", "base_ang_vel")

_FLOAT32_MAX = 3.4028234663852886e38
_F32_ROUND = struct.Struct("<f")
#: Bounds on sizes the runtime allocates per robot: a history of at most this many control periods, at most this many
#: phase harmonics (the shipped policies: 8 periods, 1 harmonic).
MAX_HISTORY_AGE = 1024
MAX_PHASE_HARMONICS = 64
_SHA256 = re.compile(r"[0-9a-f]{64}")
#: ``ModelProto`` field tags an ONNX file's second field can have (producer name, version, domain, model version, doc,
#: graph, opsets), after its first: ``ir_version`` (tag 0x08).
_ONNX_SECOND_TAGS = frozenset(b"\x12\x1a\x22\x28\x32\x3a\x42")
#: The first bytes of a zip file: torch saves checkpoints (``.pt``) as zips.
_ZIP_MAGIC = b"PK\x03\x04"
_FIX = "re-export the policy with `python -m tocabi_torchrl.export` (the file was edited or written by another tool?)"


class ContractError(ValueError):
    """A policy contract is malformed, from another version, or does not fit the policy or robot it is used with."""


def folder_note(path: Path, what: str, suffix: str) -> str | None:
    """For a ``path`` that is a folder, not the ``what`` file it should be: the error, naming the ``suffix`` files it
    holds; None otherwise. Reported as "not found", a folder has the user look for a file that is there."""
    if not path.is_dir():
        return None
    held = sorted(p.name for p in path.glob(f"*{suffix}") if p.is_file())
    inside = (f"it holds {', '.join(held[:6])}{', ...' if len(held) > 6 else ''}" if held
              else f"it holds no {suffix} file")
    return f"{what} {path} is a folder, not a file ({inside}): pass the {suffix} file itself"


def load_contract(path: str | os.PathLike) -> dict:
    """Read and check the contract JSON at ``path``; raises :class:`ContractError` naming the file and the problem.

    The file must be standard JSON: ``NaN``/``Infinity`` (which Python's json module would accept) are refused. A
    contract of version 1 (no ``content_sha256``) loads with a ``UserWarning``: its values are not covered by a hash."""
    path = Path(path)
    if not path.is_file():
        raise ContractError(folder_note(path, "policy contract", ".json") or f"policy contract not found: {path} "
                            "(export one with `python -m tocabi_torchrl.export`)")
    wrong = _policy_file_note(path)
    if wrong is not None:  # its bytes would read as "not valid JSON ('utf-8' codec ...)", which names no fix
        raise ContractError(wrong)
    encoding = _encoding_note(path)
    if encoding is not None:  # it would read as "not valid JSON" and "damaged or edited": its values may be sound
        raise ContractError(f"cannot read policy contract {path}: it is saved {encoding}, not as the UTF-8 without a "
                            "byte order mark that an export writes and JSON readers expect (an editor or shell saved "
                            "it so, e.g. Windows PowerShell's > or Out-File): save it as UTF-8 without BOM, or copy "
                            "the contract again from where it was exported")
    try:
        # JSON is UTF-8 by definition: the platform's default encoding (cp1252 on Windows) would misread it.
        contract = json.loads(path.read_text(encoding="utf-8"), parse_constant=_refuse_constant,
                              parse_float=_finite_float, object_pairs_hook=_unique_keys)
    except _DuplicateKey as err:
        raise ContractError(f"cannot read policy contract {path}: key {err} appears twice in one object (JSON readers "
                            "disagree on which one counts: Python takes the last, some C++ readers the first); keep "
                            "one, or re-export the policy") from err
    except RecursionError as err:
        raise ContractError(f"cannot read policy contract {path}: nested too deep to be a contract; re-export the "
                            "policy") from err
    except _NonStandardJSON as err:
        raise ContractError(f"cannot read policy contract {path}: it holds the non-standard JSON value {err} (a NaN "
                            "or infinite number, which C++ JSON readers refuse and which would poison the policy "
                            "input); the exported policy is broken: re-export it from a sound checkpoint") from err
    except OSError as err:
        raise ContractError(f"cannot read policy contract {path}: {err}") from err
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        # An interrupted copy or download leaves a file that is empty or ends mid-object (a whole contract, one JSON
        # object, ends with "}"): say so, and how to get a whole one.
        text = err.doc.rstrip() if isinstance(err, json.JSONDecodeError) else "}"
        what = ("it is empty (truncated" if not text else "it ends before its JSON object does (truncated"
                if not text.endswith("}") else "the file is damaged or was edited (corrupt")
        raise ContractError(f"cannot read policy contract {path}: not valid JSON ({err}): {what}); copy the "
                            "contract again from where it was exported, or re-export the policy with `python -m "
                            "tocabi_torchrl.export` (it writes the .onnx and its .json together)") from err
    check_contract(contract, str(path))
    if contract["contract_version"] == 1:
        warnings.warn(f"{path}: contract_version 1 has no content_sha256, so an edit of its values (normalisation "
                      "statistics, gains, action scale, ...) cannot be detected; re-export the policy with `python -m "
                      "tocabi_torchrl.export` to get a contract whose values are checked", UserWarning, stacklevel=2)
    return contract


def contract_beside(path: str | os.PathLike) -> Path:
    """The JSON contract an export writes beside its ``.onnx`` (or ``.ts.pt``) file ``path``; for a shipped policy's
    checkpoint (``.pt``), the contract of the same name."""
    path = Path(path)
    stem = path.name[: -len(".ts.pt")] if path.name.endswith(".ts.pt") else path.stem
    return path.with_name(f"{stem}.json")


def exported_policy_kind(path: str | os.PathLike, head: bytes) -> str | None:
    """``"an ONNX model"`` or ``"a TorchScript module"`` when ``path`` (whose first bytes are ``head``, 3 or more) is
    an exported policy file, by its suffix or its first bytes; else None."""
    path = Path(path)
    if path.name.endswith(".ts.pt"):
        return "a TorchScript module"
    onnx = len(head) > 2 and head[0] == 0x08 and head[1] < 0x80 and head[2] in _ONNX_SECOND_TAGS
    return "an ONNX model" if path.suffix == ".onnx" or onnx else None


def _policy_file_note(path: Path) -> str | None:
    """The error for ``path`` when it is a policy file (an exported one or a training checkpoint) rather than its
    contract, naming the contract beside it or how to write one; None otherwise."""
    try:
        with open(path, "rb") as file:
            head = file.read(16)
    except OSError:
        return None  # reading it again below says what is wrong
    kind = exported_policy_kind(path, head)
    checkpoint = kind is None and (path.suffix == ".pt" or head.startswith(_ZIP_MAGIC))
    if checkpoint:
        kind = "a checkpoint" if path.suffix == ".pt" else "a zip file (a checkpoint?)"
    if kind is None:
        return None
    beside = contract_beside(path)
    if beside.is_file():
        fix = f"pass the contract beside it, {beside}"
    elif checkpoint:
        fix = (f"export it with `python -m tocabi_torchrl.export --checkpoint {path} --out policy.onnx`, which writes "
               "policy.json beside the .onnx")
    else:
        fix = (f"its contract {beside} is missing: export the policy again with `python -m tocabi_torchrl.export`, "
               "which writes both")
    return f"{path} is {kind}, not a policy contract (the .json an export writes beside the .onnx): {fix}"


#: Byte order marks an editor or shell may put at the start of a re-saved file -> the encoding they mean.
_BOMS = ((b"\xef\xbb\xbf", "with a UTF-8 byte order mark"), (b"\xff\xfe", "as UTF-16 (little-endian)"),
         (b"\xfe\xff", "as UTF-16 (big-endian)"))


def _encoding_note(path: Path) -> str | None:
    """How ``path`` is encoded when it starts with a byte order mark or as UTF-16 (``"as UTF-16 (little-endian)"``),
    else None (UTF-8, or not text at all: the JSON reader says what is wrong)."""
    try:
        with open(path, "rb") as file:
            head = file.read(3)
    except OSError:
        return None  # reading it again below says what is wrong
    # UTF-16 text without a mark: a zero byte beside a character ("{" is 00 7b or 7b 00). A file of zeros (a write
    # lost in a power cut) is no text: the JSON reader calls it truncated.
    if len(head) >= 2 and (head[0] == 0) != (head[1] == 0):
        return "as UTF-16 (it starts with a zero byte beside a character)"
    return next((said for bom, said in _BOMS if head.startswith(bom)), None)


class _NonStandardJSON(ValueError):
    pass


class _DuplicateKey(ValueError):
    pass


def _refuse_constant(name: str):
    raise _NonStandardJSON(name)


def _finite_float(text: str) -> float:
    # "1e999" is standard JSON that Python reads as inf: as poisonous as the Infinity literal.
    value = float(text)
    if not math.isfinite(value):
        raise _NonStandardJSON(text)
    return value


def _unique_keys(pairs: list) -> dict:
    seen = {}
    for key, value in pairs:
        if key in seen:
            raise _DuplicateKey(repr(key))
        seen[key] = value
    return seen


def _get(contract: dict, dotted: str):
    node = contract
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            raise KeyError(dotted)
        node = node[part]
    return node


def _covered(node: dict, left_out: tuple[str, ...]) -> dict:
    """``node`` without the dotted paths ``left_out`` (relative to it)."""
    out = {}
    for key, value in node.items():
        if key in left_out:
            continue
        inner = tuple(p[len(key) + 1 :] for p in left_out if p.startswith(f"{key}."))
        out[key] = _covered(value, inner) if inner and isinstance(value, dict) else value
    return out


def content_sha256(contract: dict) -> str:
    """sha256 of the contract's values that set the policy's input and action: every field but
    :data:`UNHASHED_KEYS`, as canonical JSON (sorted keys, no spaces, ASCII, each number as Python's ``json``
    writes it: the shortest text that reads back as the same double). A contract read back from its file gives the
    hash it was written with, whatever its indentation or key order."""
    # NaN is allowed here only so that the export reaches its own refusal of a non-finite value (a contract file
    # never holds one: load_contract refuses it first).
    text = json.dumps(_covered(contract, UNHASHED_KEYS), sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(text.encode("ascii")).hexdigest()


def check_contract(contract, source: str = "contract") -> None:
    """Check a contract's format, version, keys and internal consistency; raises :class:`ContractError` saying what
    is wrong and how to fix it.

    Consistency: the lengths of every per-joint and per-entry list; every number finite; ``scale`` > 0,
    ``low`` <= ``high``, ``clip`` null or > 0, positive timing; ``action.leg`` of the kind and center its control
    mode implies; observation entries that name a signal the runtime builds, with that signal's shape, and an
    element inside it, a joint entry's name naming the joint at its element in ``robot.joint_names``; non-negative
    integer history ages; the phase-rate action after the leg actions; both sha256
    hashes 64 lowercase hex digits; ``policy.onnx_file`` and ``reference_motion.name`` plain file names; every value
    the env config also constrains (:data:`ENV_FIELDS`: gains, action scale, nominal pose, substeps, phase-rate gain,
    termination limits) by the env's own rule, each one number or a list as the env takes it, and the upper-body
    gains >= 0; the optional ``robot.actuator_names`` (one distinct name per joint) and ``policy.opset`` (an
    integer >= 1) when given. The optional ``trained_under`` section (what the policy was trained under; a contract
    without it states nothing and loads as before) by ``value_rules.trained_under_problems``, its delay in ms
    against its substeps, and no actuator stages for servo legs. Last, ``content_sha256`` (version 2 on) against
    the values it covers (:func:`content_sha256`): a value edited after export is refused, whatever it is."""
    if not isinstance(contract, dict):
        raise ContractError(f"{source}: a policy contract is a JSON object, got {type(contract).__name__}")
    if contract.get("format") != CONTRACT_FORMAT:
        raise ContractError(f"{source}: format is {contract.get('format')!r}, expected {CONTRACT_FORMAT!r} (not a "
                            "tocabi-torchrl policy contract?)")
    version = contract.get("contract_version")
    if isinstance(version, bool) or version not in READABLE_VERSIONS:  # True == 1 in Python
        readable = ", ".join(map(str, READABLE_VERSIONS))
        raise ContractError(f"{source}: contract_version {version!r} is not supported; this runtime reads versions "
                            f"{readable}. Re-export the policy with this package version, or use the tocabi-torchrl "
                            "version that wrote it")
    if version == 1 and "content_sha256" in contract:
        raise ContractError(f"{source}: contract_version 1 has no content_sha256 (version 2 added it): the version "
                            f"was edited; {_FIX}")
    missing = []
    for key in (*REQUIRED_KEYS, *(("content_sha256",) if version >= 2 else ())):
        try:
            _get(contract, key)
        except KeyError:
            missing.append(key)
    if missing:
        raise ContractError(f"{source}: missing required key(s) {missing}; re-export the policy")
    _check_unknown_keys(contract, source)
    _check_consistency(contract, source)
    if version >= 2:
        _check_content_hash(contract, source)


def _check_content_hash(contract: dict, source: str) -> None:
    """Refuse a contract whose ``content_sha256`` is not that of its values: every other check passes a plausible
    edit (a normalisation mean, a gain, an action scale), which would silently change what the robot does."""
    _sha256(contract["content_sha256"], "content_sha256", source)
    if contract["content_sha256"] != content_sha256(contract):
        raise ContractError(f"{source}: contract values changed after export: content_sha256 does not match the "
                            "values it covers (everything that sets the policy's input or action: normalisation "
                            "statistics, action bounds, scale and gains, joint order, history, timing, motion; all but "
                            f"{', '.join(UNHASHED_KEYS[1:])}). The file was edited or corrupted: copy the contract "
                            "again from where it was exported, or re-export the policy with `python -m "
                            "tocabi_torchrl.export` (it writes the .onnx and its .json together)")


def _check_unknown_keys(contract: dict, source: str) -> None:
    """Refuse a key no export writes in a section the runtime reads: a misspelt optional key (``self_colision``)
    would be ignored without a word."""
    known = {*REQUIRED_KEYS, *OPTIONAL_KEYS, "content_sha256"}
    sections = {""} | {key.rsplit(".", 1)[0] for key in known if "." in key} - {"action.leg"}
    for section in sorted(sections):
        node = contract if not section else _get(contract, section)
        if isinstance(node, dict):
            prefix = f"{section}." if section else ""
            unknown = sorted(k for k in node if f"{prefix}{k}" not in known)
            if unknown:
                raise ContractError(f"{source}: unknown key(s) {[prefix + k for k in unknown]}; the runtime would "
                                    f"ignore them (a misspelt key?); {_FIX}")
    leg = contract["action"]["leg"]
    unknown = sorted(k for k in (leg if isinstance(leg, dict) else ()) if k not in {*_LEG_KEYS["pd"], "rule"})
    if unknown:
        raise ContractError(f"{source}: unknown key(s) {['action.leg.' + k for k in unknown]}; the runtime would "
                            f"ignore them (a misspelt key?); {_FIX}")


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _need_len(value, n: int, what: str, source: str) -> None:
    if not isinstance(value, list) or len(value) != n:
        got = len(value) if isinstance(value, list) else type(value).__name__
        raise ContractError(f"{source}: {what} must be a list of {n} values, got {got}; {_FIX}")


def _number(value, what: str, source: str, positive: bool = False) -> float:
    # The runtime computes in float32: a value beyond its range is inf there.
    if (isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value)
            or abs(value) > _FLOAT32_MAX):
        raise ContractError(f"{source}: {what} is {value!r}, not a finite (float32) number; {_FIX}")
    if positive and not _F32_ROUND.unpack(_F32_ROUND.pack(value))[0] > 0:  # 1e-46 > 0, but 0 in float32
        raise ContractError(f"{source}: {what} is {value!r} but must be > 0 (in float32, which the runtime computes "
                            f"in); {_FIX}")
    return float(value)


def _numbers(value, n: int, what: str, source: str, positive: bool = False) -> list[float]:
    _need_len(value, n, what, source)
    return [_number(v, f"{what}[{i}]", source, positive) for i, v in enumerate(value)]


def _count(value, what: str, source: str, minimum: int) -> int:
    if not _is_int(value) or value < minimum:
        raise ContractError(f"{source}: {what} is {value!r} but must be an integer >= {minimum}; {_FIX}")
    return value


def _names(value, n: int | None, what: str, source: str) -> None:
    """A model name (``n`` None) or a list of ``n`` distinct ones: non-empty strings, which the driver looks up in
    the MJCF model."""
    values = [value] if n is None else value
    if n is not None:
        _need_len(value, n, what, source)
    bad = [v for v in values if not isinstance(v, str) or not v]
    if bad or len(set(values)) != len(values):
        problem = f"{bad[0]!r} is not a name" if bad else "a name appears twice"
        raise ContractError(f"{source}: {what}: {problem}; each must be a distinct non-empty string naming an "
                            f"element of the robot model; {_FIX}")


def _file_name(value, what: str, source: str) -> None:
    # The runtime opens this name beside the contract (or in the shipped motions): a path could reach any file.
    if not isinstance(value, str) or not value or "/" in value or "\\" in value or ".." in value:
        raise ContractError(f"{source}: {what} is {value!r}; it must be a plain file name (no folder, no '..') of a "
                            "file beside the contract: put the file there and name it alone")


def _sha256(value, what: str, source: str) -> None:
    if not isinstance(value, str) or not _SHA256.fullmatch(value):
        raise ContractError(f"{source}: {what} is {value!r}, not a sha256 (64 lowercase hex digits): the runtime "
                            f"checks the file against it, so it cannot be left out; {_FIX}")


def _check_consistency(c: dict, source: str) -> None:
    rob, act, obs, pol = c["robot"], c["action"], c["observation"], c["policy"]
    joints = rob["joint_names"]
    if not isinstance(joints, list) or not joints:
        raise ContractError(f"{source}: robot.joint_names must be a non-empty list")
    legs, upper = rob["leg_joint_names"], rob["upper_joint_names"]
    if not isinstance(legs, list) or not isinstance(upper, list) or legs + upper != joints:
        raise ContractError(f"{source}: robot.leg_joint_names + robot.upper_joint_names must equal robot.joint_names "
                            f"({len(legs) if isinstance(legs, list) else '?'} + "
                            f"{len(upper) if isinstance(upper, list) else '?'} vs {len(joints)} joints)")
    _names(joints, len(joints), "robot.joint_names", source)
    for key in ("base_body", "neck_body"):
        _names(rob[key], None, f"robot.{key}", source)
    for key in ("foot_force_sensors", "foot_torque_sensors"):
        _names(rob[key], 2, f"robot.{key} (left, right)", source)
    _numbers(rob["initial_qpos"], 7 + len(joints), "robot.initial_qpos (base pose + joints)", source)
    if "actuator_names" in rob:  # optional, but a controller may drive its motors by these names
        _names(rob["actuator_names"], len(joints), "robot.actuator_names (one motor per joint)", source)
    if "opset" in pol:  # optional; the runtime names it when onnxruntime cannot load the graph
        _count(pol["opset"], "policy.opset", source, 1)
    _file_name(pol["onnx_file"], "policy.onnx_file", source)
    _sha256(pol["onnx_sha256"], "policy.onnx_sha256", source)
    _sha256(c["reference_motion"]["sha256"], "reference_motion.sha256", source)
    _file_name(c["reference_motion"]["name"], "reference_motion.name", source)
    _check_timing(c, source)
    n_leg = len(legs)
    if not _is_int(act["dim"]) or act["dim"] != n_leg + 1:
        raise ContractError(f"{source}: action.dim is {act['dim']!r} but there are {n_leg} leg joints (+1 phase rate)")
    low = _numbers(act["low"], act["dim"], "action.low", source)
    high = _numbers(act["high"], act["dim"], "action.high", source)
    swapped = [i for i in range(act["dim"]) if low[i] > high[i]]
    if swapped:
        raise ContractError(f"{source}: action.low > action.high at indices {swapped} (swapped?): every action entry "
                            f"needs low <= high; {_FIX}")
    # The env's bounds: leg actions in [-1, 1] (a torque policy's fraction of each joint's limit), the phase rate in
    # [0, 1]. Wider ones would let a controller command torques beyond the limits, or run the clock backwards.
    outside = [i for i in range(act["dim"]) if low[i] < (-1.0 if i < n_leg else 0.0) or high[i] > 1.0]
    if outside:
        raise ContractError(f"{source}: action.low/high at indices {outside} reach outside the policy's action bounds "
                            f"(legs in [-1, 1], the phase rate in [0, 1]); {_FIX}")
    rate = act["phase_rate"]
    if not _is_int(rate["index"]) or rate["index"] != n_leg:
        # The first n_leg entries are the leg actions: any other index would read one of them as the phase rate.
        raise ContractError(f"{source}: action.phase_rate.index is {rate['index']!r}, but the {n_leg} leg actions "
                            f"come first and the phase rate is entry {n_leg}, the last; {_FIX}")
    _number(rate["gain"], "action.phase_rate.gain", source)
    _check_leg(act, n_leg, source)
    for key in ("kp", "kv"):
        gains = _numbers(c["upper_body"][key], len(upper), f"upper_body.{key}", source)
        _obey(gains, NON_NEGATIVE, f"upper_body.{key}", source,
              "a servo gain, as the legs' env.control.pd_kp/pd_kv: a negative one pushes the joint off its target")
    _check_observation(obs, len(joints), source)
    _check_joint_entry_names(obs["entries"], joints, source)
    hist = obs["history"]
    step_dim = obs["step_dim"]
    expected = len(hist["obs_ages"]) * step_dim + len(hist["action_ages"]) * act["dim"]
    if pol["input_dim"] != expected or not _is_int(pol["input_dim"]):
        raise ContractError(f"{source}: policy.input_dim is {pol['input_dim']!r} but the history holds "
                            f"{len(hist['obs_ages'])} x {step_dim} + {len(hist['action_ages'])} x {act['dim']} = "
                            f"{expected} values (an integer)")
    if pol["output_dim"] != act["dim"] or not _is_int(pol["output_dim"]):
        raise ContractError(f"{source}: policy.output_dim is {pol['output_dim']!r} but must be action.dim, the "
                            f"integer {act['dim']}")
    for key, count in (("obs_ages", "num_obs"), ("action_ages", "num_actions")):
        if count in hist and hist[count] != len(hist[key]):  # a controller may size its history by the count
            raise ContractError(f"{source}: observation.history.{count} is {hist[count]!r} but {key} holds "
                                f"{len(hist[key])}; {_FIX}")
    for key in ("input_name", "output_name"):
        if not isinstance(pol[key], str) or not pol[key]:
            raise ContractError(f"{source}: policy.{key} is {pol[key]!r}, not the name of an ONNX graph input/output; "
                                f"{_FIX}")
    _check_env_values(c, source)
    _check_termination_switches(c["termination"], source)
    _check_trained_under(c, source)


def _obey(value, rule, what: str, source: str, whose: str) -> None:
    """Raise :class:`ContractError` unless ``value`` (each entry of a list) obeys ``rule`` (a
    :class:`~tocabi_torchrl.value_rules.Range`); the message names the field, the allowed values and ``whose`` rule
    it is."""
    entries = enumerate(value) if isinstance(value, list) else [(None, value)]
    for i, v in entries:
        if not rule.allows(v):
            name = what if i is None else f"{what}[{i}]"
            raise ContractError(f"{source}: {name} is {v!r} but must be {rule.describe()} ({whose}); {_FIX}")


def _check_env_field(c: dict, field: str, source: str) -> None:
    """One field of :data:`ENV_FIELDS`, if the contract holds it, by the env config's rule for its value."""
    try:
        value = _get(c, field)
    except KeyError:
        return  # a field of another control mode; the required ones are checked by check_contract
    env_path = ENV_FIELDS[field]
    rule = ENV_RULES[env_path]
    # _obey checks each entry of a list: a list where the env takes one number ([8] substeps, [] or [0.6] as a
    # height) would pass it, then fail as a TypeError in the runtime or be read as some other value.
    if isinstance(value, list) != (field in _ENV_LIST_FIELDS):
        shape = "a list of numbers, one per leg joint" if field in _ENV_LIST_FIELDS else "one number, not a list"
        raise ContractError(f"{source}: {field} is {value!r} but must be {shape} ({rule.describe()}, as the env "
                            f"requires of env.{env_path}, the option it carries); {_FIX}")
    _obey(value, rule, field, source, f"as the env requires of env.{env_path}, the option it carries")


def _check_env_values(c: dict, source: str) -> None:
    for field in ENV_FIELDS:
        _check_env_field(c, field, source)


def _check_termination_switches(termination: dict, source: str) -> None:
    # The driver reads them as truths: text such as "false" would switch the check on.
    for key in ("forbidden_contact", "self_collision"):
        if key in termination and not isinstance(termination[key], bool):
            raise ContractError(f"{source}: termination.{key} is {termination[key]!r} but must be true or false; "
                                f"{_FIX}")


def _check_timing(c: dict, source: str) -> None:
    timing = c["timing"]
    physics = _number(timing["physics_dt_s"], "timing.physics_dt_s", source, positive=True)
    _check_env_field(c, "timing.substeps", source)  # before it is used below
    substeps = timing["substeps"]
    control = _number(timing["control_dt_s"], "timing.control_dt_s", source, positive=True)
    # control_dt_s is written from the env's float32 dt: allow float32 rounding, nothing more.
    if abs(physics * substeps - control) > 1e-6 * control:
        raise ContractError(f"{source}: timing.control_dt_s {control} is not physics_dt_s {physics} x substeps "
                            f"{substeps}; {_FIX}")
    if "control_hz" in timing:  # not read here, but a robot controller may take its rate from it
        hz = _number(timing["control_hz"], "timing.control_hz", source, positive=True)
        if abs(hz * control - 1.0) > 1e-4:
            raise ContractError(f"{source}: timing.control_hz {hz} is not 1 / control_dt_s {control} "
                                f"({1.0 / control:g}); {_FIX}")


def _check_leg(act: dict, n_leg: int, source: str) -> None:
    mode = act["control_mode"]
    if not isinstance(mode, str) or mode not in _LEG_KEYS:
        raise ContractError(f"{source}: unknown action.control_mode {mode!r}; expected one of {list(_LEG_KEYS)}")
    leg = act["leg"]
    if not isinstance(leg, dict):
        raise ContractError(f"{source}: action.leg must be an object, got {type(leg).__name__}; {_FIX}")
    lacking = [k for k in _LEG_KEYS[mode] if k not in leg]
    if lacking:
        raise ContractError(f"{source}: action.leg lacks {lacking} for control mode {mode!r}")
    # A controller applies action.leg by its kind, the runtime computes it from the mode: they must agree, or PD
    # targets in radians would be sent as torques (or the reverse).
    if leg["kind"] != _LEG_KIND[mode]:
        raise ContractError(f"{source}: action.leg.kind is {leg['kind']!r} but control_mode is {mode!r}, whose leg "
                            f"commands are {_LEG_KIND[mode]!r}: {_FIX}")
    if mode in _LEG_CENTER and leg["center"] != _LEG_CENTER[mode]:
        raise ContractError(f"{source}: action.leg.center is {leg['center']!r} but control_mode {mode!r} centres the "
                            f"targets on {_LEG_CENTER[mode]!r}: {_FIX}")
    _numbers(leg["torque_limits_nm"], n_leg, "action.leg.torque_limits_nm", source, positive=True)
    for k in ("kp", "kv", "nominal"):
        if k in leg:
            _numbers(leg[k], n_leg, f"action.leg.{k}", source)
    if "action_scale" in leg:
        _number(leg["action_scale"], "action.leg.action_scale", source)
    if "joint_range" in leg:
        ranges = leg["joint_range"]
        _need_len(ranges, n_leg, "action.leg.joint_range", source)
        for i, pair in enumerate(ranges):
            lo, hi = _numbers(pair, 2, f"action.leg.joint_range[{i}] ([lo, hi] rad)", source)
            if not lo < hi:
                raise ContractError(f"{source}: action.leg.joint_range[{i}] is {pair}: it needs lo < hi; {_FIX}")


def _signal_shapes(num_joints: int, harmonics: int) -> dict[str, list[int]]:
    """The (per-robot) shape of each signal as the runtime builds it."""
    return {"base_rpy": [3], "joint_pos": [num_joints], "joint_vel": [num_joints], "phase_sin": [harmonics],
            "phase_cos": [harmonics], "command": [2], "foot_force": [2, 3], "foot_torque": [2, 3],
            "base_lin_vel": [3], "base_ang_vel": [3]}


def _check_observation(obs: dict, num_joints: int, source: str) -> None:
    step_dim = _count(obs["step_dim"], "observation.step_dim", source, 1)
    harmonics = _count(obs["phase_harmonics"], "observation.phase_harmonics", source, 1)
    if harmonics > MAX_PHASE_HARMONICS:
        raise ContractError(f"{source}: observation.phase_harmonics is {harmonics} but this runtime builds at most "
                            f"{MAX_PHASE_HARMONICS}; {_FIX}")
    _need_len(obs["entries"], step_dim, "observation.entries", source)
    shapes = _signal_shapes(num_joints, harmonics)
    signals = obs["signals"]
    if not isinstance(signals, dict):
        raise ContractError(f"{source}: observation.signals must be an object, got {type(signals).__name__}; {_FIX}")
    for i, entry in enumerate(obs["entries"]):
        if (not isinstance(entry, dict) or not isinstance(entry.get("signal"), str) or entry["signal"] not in signals
                or "element" not in entry):
            raise ContractError(f"{source}: observation.entries[{i}] must name a signal of observation.signals and "
                                f"an element index, got {entry!r}")
        unknown = sorted(set(entry) - _ENTRY_KEYS)
        if unknown:
            raise ContractError(f"{source}: observation.entries[{i}] has unknown key(s) {unknown} (it takes "
                                f"{sorted(_ENTRY_KEYS)}); {_FIX}")
        if "index" in entry and entry["index"] != i:  # the runtime reads entries by position
            raise ContractError(f"{source}: observation.entries[{i}].index is {entry['index']!r}, not its position "
                                f"{i}; {_FIX}")
        name, element = entry["signal"], entry["element"]
        if name not in shapes:
            raise ContractError(f"{source}: observation.entries[{i}] reads signal {name!r}, which this runtime cannot "
                                f"build (it builds {list(RUNTIME_SIGNALS)}): the policy needs a runtime that knows "
                                "that signal")
        spec = signals[name]
        unknown = sorted(set(spec) - _SIGNAL_KEYS) if isinstance(spec, dict) else []
        if unknown:
            raise ContractError(f"{source}: observation.signals.{name} has unknown key(s) {unknown} (it takes "
                                f"{sorted(_SIGNAL_KEYS)}); {_FIX}")
        if not isinstance(spec, dict) or spec.get("shape") != shapes[name]:
            got = spec.get("shape") if isinstance(spec, dict) else spec
            raise ContractError(f"{source}: observation.signals.{name}.shape is {got!r}, but the runtime builds "
                                f"{name} with shape {shapes[name]}; {_FIX}")
        size = math.prod(shapes[name])
        if not _is_int(element) or not 0 <= element < size:
            raise ContractError(f"{source}: observation.entries[{i}].element is {element!r}, not an element index in "
                                f"[0, {size}) of signal {name!r}; {_FIX}")
    norm = obs["normalization"]
    _numbers(norm["mean"], step_dim, "observation.normalization.mean", source)
    # A zero scale (a constant signal normalised with eps = 0) divides by zero: inf, then NaN, in every step.
    _numbers(norm["scale"], step_dim, "observation.normalization.scale", source, positive=True)
    if norm.get("clip") is not None:
        _number(norm["clip"], "observation.normalization.clip", source, positive=True)
    if "eps" in norm and _number(norm["eps"], "observation.normalization.eps", source) < 0:
        raise ContractError(f"{source}: observation.normalization.eps is {norm['eps']!r} but must be >= 0; {_FIX}")
    if "kind" in norm and norm["kind"] not in NORMALIZATION_KINDS:
        raise ContractError(f"{source}: observation.normalization.kind is {norm['kind']!r} but must be one of "
                            f"{list(NORMALIZATION_KINDS)}; {_FIX}")
    hist = obs["history"]
    for key in ("obs_ages", "action_ages"):
        ages = hist[key]
        if (not isinstance(ages, list) or not all(_is_int(a) and 0 <= a <= MAX_HISTORY_AGE for a in ages)
                or (key == "obs_ages" and not ages)):
            raise ContractError(f"{source}: observation.history.{key} is {ages!r}; it must be a list of integer ages "
                                f"in [0, {MAX_HISTORY_AGE}] control periods"
                                f"{' (at least one)' if key == 'obs_ages' else ''}; {_FIX}")


def _check_joint_entry_names(entries: list, joints: list, source: str) -> None:
    """Refuse a joint entry whose name (``leg_joint_pos[L_Knee_Joint]``, as the export writes it) names another joint
    than ``robot.joint_names[element]``: the runtime reads joint signals by position in ``robot.joint_names``, so a
    reordered list (edited to match a robot's own joint order) would feed the policy other joints' angles, and drive
    other joints with its leg actions, without a word."""
    known = set(joints)
    for i, entry in enumerate(entries):
        name = entry.get("name")
        if entry["signal"] not in ("joint_pos", "joint_vel") or not isinstance(name, str) or not name.endswith("]"):
            continue
        joint = name[name.rfind("[") + 1 : -1]
        if joint in known and joint != joints[entry["element"]]:
            raise ContractError(f"{source}: observation.entries[{i}] is {name!r}, element {entry['element']} of "
                                f"{entry['signal']}, but robot.joint_names[{entry['element']}] is "
                                f"{joints[entry['element']]!r}: robot.joint_names is not in the order the policy was "
                                "trained with. Keep the exported joint order (leg_joint_names, upper_joint_names) and "
                                "pass the robot's readings in it; re-export the policy if the contract was edited")


def _check_trained_under(contract: dict, source: str) -> None:
    """Raise :class:`ContractError` for a ``trained_under`` section (when the contract has one) that breaks
    ``value_rules.trained_under_problems``, whose delay in ms is not its substeps × ``timing.physics_dt_s`` or whose
    delay stride does not divide its range (``value_rules.delay_grid_problem``), whose delay is applied in a way this
    reader does not know (``value_rules.DELAY_APPLIED``), or that states actuator stages for
    servo legs (``action.leg.kind`` position: the training env refuses them there)."""
    if "trained_under" not in contract:
        return
    section = contract["trained_under"]
    problems = trained_under_problems(section)
    fix = _FIX
    if problems:
        raise ContractError(f"{source}: {problems[0]}; {fix}")
    delay = section["actuators"]["delay"]
    if delay != "off":
        dt_ms = float(contract["timing"]["physics_dt_s"]) * 1000.0
        expected = [k * dt_ms for k in delay["substeps"]]
        if any(abs(a - b) > 1e-6 * max(1.0, b) for a, b in zip(delay["ms"], expected)):
            raise ContractError(f"{source}: trained_under.actuators.delay.ms is {delay['ms']} but substeps "
                                f"{delay['substeps']} x timing.physics_dt_s is {expected} ms; {fix}")
        problem = delay_grid_problem(*delay["substeps"], delay.get("stride_substeps", 1))
        if problem:
            raise ContractError(f"{source}: trained_under.actuators.delay.stride_substeps: {problem}; {fix}")
        applied = delay.get("applied", DELAY_APPLIED[0])
        if applied not in DELAY_APPLIED:
            raise ContractError(f"{source}: trained_under.actuators.delay.applied is {applied!r} but must be one of "
                                f"{list(DELAY_APPLIED)}; {fix}")
    kind = section["pushes"].get("kind", "force") if isinstance(section["pushes"], dict) else "force"
    if kind not in PUSH_KINDS:
        raise ContractError(f"{source}: trained_under.pushes.kind is {kind!r} but must be one of {list(PUSH_KINDS)}; "
                            f"{fix}")
    mode = contract["action"]["control_mode"]
    on = [k for k in ("delay", "motor_constant", "friction") if section["actuators"][k] != "off"]
    if on and contract["action"]["leg"]["kind"] != "torque":
        raise ContractError(f"{source}: trained_under.actuators states {on} for control mode {mode!r}, whose servos "
                            f"take no actuator stages (the training env refuses them); {fix}")
