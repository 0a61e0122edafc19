"""The policy I/O contract: the JSON file written beside an exported ONNX policy, read and checked here.

The contract says everything a controller needs to run the policy without the training stack: joint order, what each
action means per control mode, timing, the 37 observation entries and how they are normalised and stacked, the
reference motion and the versions. ``docs/export.md`` describes it field by field. This module imports only the
standard library, so a deployment can check a contract before loading anything else.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

__all__ = ["CONTRACT_FORMAT", "CONTRACT_VERSION", "REQUIRED_KEYS", "ContractError", "check_contract", "load_contract"]

#: ``format`` field of every contract.
CONTRACT_FORMAT = "tocabi_torchrl.policy_contract"
#: Layout version of the contract. Bump it when a field changes meaning; readers refuse other versions.
CONTRACT_VERSION = 1

#: Top-level keys and the nested keys the runtime relies on (``"a.b"`` = key ``b`` of section ``a``).
REQUIRED_KEYS: tuple[str, ...] = (
    "format", "contract_version", "package_version", "training_config_sha256",
    "policy", "policy.onnx_file", "policy.input_name", "policy.output_name", "policy.input_dim", "policy.output_dim",
    "robot", "robot.joint_names", "robot.leg_joint_names", "robot.upper_joint_names", "robot.initial_qpos",
    "robot.base_body", "robot.neck_body", "robot.foot_force_sensors", "robot.foot_torque_sensors",
    "timing", "timing.physics_dt_s", "timing.substeps", "timing.control_dt_s",
    "action", "action.dim", "action.low", "action.high", "action.control_mode", "action.leg", "action.phase_rate",
    "action.phase_rate.index", "action.phase_rate.gain", "upper_body", "upper_body.kp", "upper_body.kv",
    "observation", "observation.step_dim", "observation.entries", "observation.signals", "observation.normalization",
    "observation.normalization.mean", "observation.normalization.scale", "observation.history",
    "observation.history.obs_ages", "observation.history.action_ages", "observation.phase_harmonics",
    "reference_motion", "reference_motion.name", "reference_motion.sha256", "termination",
)  # fmt: skip

_LEG_KEYS = {
    "torque": ("kind", "torque_limits_nm"),
    "pd": ("kind", "kp", "kv", "action_scale", "center", "nominal", "joint_range", "torque_limits_nm"),
    "pd_reference": ("kind", "kp", "kv", "action_scale", "center", "joint_range", "torque_limits_nm"),
}


class ContractError(ValueError):
    """A policy contract is malformed, from another version, or does not fit the policy or robot it is used with."""


def load_contract(path: str | os.PathLike) -> dict:
    """Read and check the contract JSON at ``path``; raises :class:`ContractError` naming the file and the problem."""
    path = Path(path)
    if not path.is_file():
        raise ContractError(f"policy contract not found: {path} (export one with `python -m tocabi_torchrl.export`)")
    try:
        contract = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ContractError(f"cannot read policy contract {path}: not valid JSON ({err})") from err
    check_contract(contract, str(path))
    return contract


def _get(contract: dict, dotted: str):
    node = contract
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            raise KeyError(dotted)
        node = node[part]
    return node


def check_contract(contract, source: str = "contract") -> None:
    """Check a contract's format, version, keys and internal consistency (lengths of every per-joint and
    per-entry list); raises :class:`ContractError` saying what is wrong and how to fix it."""
    if not isinstance(contract, dict):
        raise ContractError(f"{source}: a policy contract is a JSON object, got {type(contract).__name__}")
    if contract.get("format") != CONTRACT_FORMAT:
        raise ContractError(f"{source}: format is {contract.get('format')!r}, expected {CONTRACT_FORMAT!r} (not a "
                            "tocabi-torchrl policy contract?)")
    version = contract.get("contract_version")
    if version != CONTRACT_VERSION:
        raise ContractError(f"{source}: contract_version {version!r} is not supported; this runtime reads version "
                            f"{CONTRACT_VERSION}. Re-export the policy with this package version, or use the "
                            "tocabi-torchrl version that wrote it")
    missing = []
    for key in REQUIRED_KEYS:
        try:
            _get(contract, key)
        except KeyError:
            missing.append(key)
    if missing:
        raise ContractError(f"{source}: missing required key(s) {missing}; re-export the policy")
    _check_consistency(contract, source)


def _need_len(value, n: int, what: str, source: str) -> None:
    if not isinstance(value, list) or len(value) != n:
        got = len(value) if isinstance(value, list) else type(value).__name__
        raise ContractError(f"{source}: {what} must be a list of {n} values, got {got}")


def _check_consistency(c: dict, source: str) -> None:
    rob, act, obs = c["robot"], c["action"], c["observation"]
    joints = rob["joint_names"]
    if not isinstance(joints, list) or not joints:
        raise ContractError(f"{source}: robot.joint_names must be a non-empty list")
    legs, upper = rob["leg_joint_names"], rob["upper_joint_names"]
    if not isinstance(legs, list) or not isinstance(upper, list) or legs + upper != joints:
        raise ContractError(f"{source}: robot.leg_joint_names + robot.upper_joint_names must equal robot.joint_names "
                            f"({len(legs) if isinstance(legs, list) else '?'} + "
                            f"{len(upper) if isinstance(upper, list) else '?'} vs {len(joints)} joints)")
    _need_len(rob["initial_qpos"], 7 + len(joints), "robot.initial_qpos (base pose + joints)", source)
    n_leg = len(legs)
    if act["dim"] != n_leg + 1:
        raise ContractError(f"{source}: action.dim is {act['dim']} but there are {n_leg} leg joints (+1 phase rate)")
    _need_len(act["low"], act["dim"], "action.low", source)
    _need_len(act["high"], act["dim"], "action.high", source)
    mode = act["control_mode"]
    if mode not in _LEG_KEYS:
        raise ContractError(f"{source}: unknown action.control_mode {mode!r}; expected one of {list(_LEG_KEYS)}")
    leg = act["leg"]
    lacking = [k for k in _LEG_KEYS[mode] if k not in leg]
    if lacking:
        raise ContractError(f"{source}: action.leg lacks {lacking} for control mode {mode!r}")
    for k in ("torque_limits_nm", "kp", "kv", "nominal", "joint_range"):
        if k in leg:
            _need_len(leg[k], n_leg, f"action.leg.{k}", source)
    _need_len(c["upper_body"]["kp"], len(upper), "upper_body.kp", source)
    _need_len(c["upper_body"]["kv"], len(upper), "upper_body.kv", source)
    step_dim = obs["step_dim"]
    _need_len(obs["entries"], step_dim, "observation.entries", source)
    _need_len(obs["normalization"]["mean"], step_dim, "observation.normalization.mean", source)
    _need_len(obs["normalization"]["scale"], step_dim, "observation.normalization.scale", source)
    for i, entry in enumerate(obs["entries"]):
        if not isinstance(entry, dict) or entry.get("signal") not in obs["signals"] or "element" not in entry:
            raise ContractError(f"{source}: observation.entries[{i}] must name a signal of observation.signals and "
                                f"an element index, got {entry!r}")
    hist = obs["history"]
    expected = len(hist["obs_ages"]) * step_dim + len(hist["action_ages"]) * act["dim"]
    if c["policy"]["input_dim"] != expected:
        raise ContractError(f"{source}: policy.input_dim is {c['policy']['input_dim']} but the history holds "
                            f"{len(hist['obs_ages'])} x {step_dim} + {len(hist['action_ages'])} x {act['dim']} = "
                            f"{expected} values")
    if c["policy"]["output_dim"] != act["dim"]:
        raise ContractError(f"{source}: policy.output_dim {c['policy']['output_dim']} != action.dim {act['dim']}")
