"""Build the policy I/O contract from a loaded policy's env, transforms and config (``docs/deploying.md``).

Every number comes from the objects that trained the policy: the env's config, simulator model and motion, and the
transforms (layout, normalisation buffers, history layout), never from copies, so a change of observation or
history shows up in the contract by itself. :mod:`tocabi_torchrl.runtime.contract` checks what this writes.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import mujoco
import numpy as np

from .. import __version__, robot
from ..runtime.contract import (CONTRACT_FORMAT, CONTRACT_VERSION, NORMALIZATION_KINDS, check_contract,
                                content_sha256)
from ..runtime.motion import file_sha256

__all__ = ["SIGNAL_DOCS", "ExportError", "build_contract", "config_sha256", "sha256_bytes"]

_SIDES = ("left", "right")
_AXES = ("x", "y", "z")

#: Unit, frame and source of every signal the observation may read (docs/concepts/env-and-signals.md has the env's
#: side).
SIGNAL_DOCS: dict[str, dict[str, str]] = {
    "base_rpy": {"unit": "rad", "frame": "world; fixed-XYZ (roll, pitch, yaw) of the base body (pelvis) quaternion, "
                 "yaw = absolute heading", "source": "qpos[3:7] (w, x, y, z) -> Euler angles"},
    "joint_pos": {"unit": "rad", "frame": "joint", "source": "qpos[7 + j], robot.joint_names order"},
    "joint_vel": {"unit": "rad/s", "frame": "joint", "source": "qvel[6 + j], robot.joint_names order"},
    "phase_sin": {"unit": "1", "frame": "-", "source": "sin(2*pi*k*phase), phase from the runtime's clock"},
    "phase_cos": {"unit": "1", "frame": "-", "source": "cos(2*pi*k*phase), phase from the runtime's clock"},
    "command": {"unit": "m/s", "frame": "pelvis heading frame (vx forward, vy left)", "source": "velocity command"},
    "foot_force": {"unit": "N", "frame": "foot F/T sensor site frame; loaded foot: z < 0",
                   "source": "robot.foot_force_sensors [left, right] x (x, y, z)"},
    "foot_torque": {"unit": "N*m", "frame": "foot F/T sensor site frame",
                    "source": "robot.foot_torque_sensors [left, right] x (x, y, z)"},
    "base_lin_vel": {"unit": "m/s", "frame": "base body (pelvis) frame",
                     "source": "qvel[0:3] (world frame) rotated into the pelvis frame (a state estimator's)"},
    "base_ang_vel": {"unit": "rad/s", "frame": "base body (pelvis) frame", "source": "qvel[3:6] (the IMU's gyro)"},
}


class ExportError(ValueError):
    """A checkpoint that loads but cannot be exported as it is (non-finite weights or statistics, a non-finite
    output); the message names the problem and what to export instead."""


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def config_sha256(config: dict) -> str:
    """sha256 of the training config as canonical JSON (sorted keys, no spaces, no NaN/Infinity)."""
    return sha256_bytes(json.dumps(config, sort_keys=True, separators=(",", ":"), default=list,
                                   allow_nan=False).encode())


def _element_names(signal: str, shape: tuple[int, ...]) -> list[str]:
    size = int(np.prod(shape)) if shape else 1
    if signal in ("joint_pos", "joint_vel") and size == robot.NUM_JOINTS:
        return list(robot.JOINT_NAMES)
    if signal == "base_rpy":
        return ["roll", "pitch", "yaw"]
    if signal in ("phase_sin", "phase_cos"):
        return [f"harmonic {k + 1}" for k in range(size)]
    if signal == "command":
        return ["vx", "vy"]
    if signal in ("foot_force", "foot_torque") and shape == (2, 3):
        return [f"{s} {a}" for s in _SIDES for a in _AXES]
    if signal in ("base_lin_vel", "base_ang_vel") and shape == (3,):
        return list(_AXES)
    return [str(i) for i in range(size)]


def _find(transform, cls_name: str):
    for t in transform:
        if type(t).__name__ == cls_name:
            return t
    return None


def _observation(env) -> dict:
    transform = env.transform
    assembly = _find(transform, "ObservationAssembly")
    history = _find(transform, "ObsActionHistory")
    phase = _find(transform, "PhaseEncoding")
    if assembly is None or history is None or phase is None:
        raise ValueError("the env's transforms lack ObservationAssembly, PhaseEncoding or ObsActionHistory; only the "
                         "default transform chain (transforms.default_transforms) can be exported")
    spec = env.observation_spec
    entries, signals = [], {}
    for comp in assembly.layout:
        shape = tuple(spec[comp.key].shape[1:])  # without the batch dimension
        elements = np.arange(int(np.prod(shape)) if shape else 1).reshape(shape)[comp.index].ravel()
        names = _element_names(comp.key, shape)
        signals.setdefault(comp.key, {"shape": list(shape), **SIGNAL_DOCS.get(comp.key, {})})
        doc = SIGNAL_DOCS.get(comp.key, {})
        for e in elements.tolist():
            entries.append({"index": len(entries), "block": comp.name, "signal": comp.key, "element": int(e),
                            "name": f"{comp.name}[{names[e]}]", "unit": doc.get("unit", "?"),
                            "frame": doc.get("frame", "?")})
    norm = _find(transform, "FixedNormalization")
    if norm is not None:
        normalization = {"kind": NORMALIZATION_KINDS[0],
                         "rule": "(raw - mean) / scale, then clip to +-clip when clip is set",
                         "mean": norm.loc.tolist(), "scale": norm.scale.tolist(), "eps": norm.eps, "clip": norm.clip}
    elif _find(transform, "RunningNormalization") is not None:
        run = _find(transform, "RunningNormalization")
        loc, scale = run._loc_scale()  # frozen at export: the checkpoint's statistics
        normalization = {"kind": NORMALIZATION_KINDS[1], "rule": "(raw - mean) / scale, then clip",
                         "mean": loc.tolist(), "scale": scale.tolist(), "eps": run.eps, "clip": run.clip}
    else:
        normalization = {"kind": NORMALIZATION_KINDS[2], "rule": "identity", "mean": [0.0] * len(entries),
                         "scale": [1.0] * len(entries), "eps": 0.0, "clip": None}
    lay = history.layout
    return {
        "step_dim": len(entries),
        "entries": entries,
        "signals": signals,
        "phase_harmonics": int(phase.harmonics),
        "normalization": normalization,
        "history": {
            "num_obs": lay.num_obs, "stride": lay.stride, "num_actions": lay.num_actions,
            "obs_ages": list(lay.obs_ages), "action_ages": list(lay.action_ages), "blocks": lay.describe(),
            "order": "normalised observations at obs_ages (oldest first), then clipped applied actions at "
                     "action_ages (oldest first); age in control periods, 0 = the current observation / the action "
                     "just applied",
            "reset": "every slot holds the first observation of the episode and the zero action",
        },
    }


def _check_normalization(norm: dict, checkpoint: Path) -> None:
    # check_contract would refuse these too, but only the export can say where they came from and what to do.
    mean, scale = np.asarray(norm["mean"], dtype=np.float64), np.asarray(norm["scale"], dtype=np.float64)
    bad = np.flatnonzero(~np.isfinite(mean) | ~np.isfinite(scale) | ~(scale > 0))
    if bad.size:
        raise ExportError(f"{checkpoint}: the observation normalisation ({norm['kind']}) has a non-finite mean or a "
                          f"scale that is not finite and > 0 at entries {bad[:8].tolist()} (mean "
                          f"{mean[bad[:4]].tolist()}, scale {scale[bad[:4]].tolist()}): the policy input would be NaN "
                          "or inf. The run diverged or normalises a constant signal with eps = 0: export an earlier "
                          "checkpoint, or retrain with eps > 0")


def _trained_under(policy, cfg, model) -> dict:
    """The contract's ``trained_under`` section: the env config's actuator layer, dynamics, pushes and start
    velocities, the transform chain's sensor noise and the run config's push curriculum (``ppo.push_ramp``)."""
    from ..runtime import randomization as rnd

    noise = _find(policy.env.transform, "SensorNoise")  # in the chain exactly when the run's sensor noise is on
    dynamics = getattr(cfg, "dynamics", None)  # an env config without the section had no dynamics randomisation
    randomization = rnd.Randomization(
        actuators=rnd.settings_from(rnd.ActuatorSettings, cfg.control.actuators, "env.control.actuators"),
        dynamics=(rnd.settings_from(rnd.DynamicsSettings, dynamics, "env.dynamics") if dynamics is not None
                  else rnd.DynamicsSettings()),
        sensors=(rnd.settings_from(rnd.SensorSettings, noise.config, "transforms.sensor_noise") if noise is not None
                 else rnd.SensorSettings()))
    start = rnd.StartVelocity(float(getattr(cfg.task, "start_joint_vel_std", 0.0)),
                              float(getattr(cfg.task, "start_base_vel_std", 0.0)))
    # The kicks' impulse is speed × the robot's nominal mass, as the env computes it (envs/pushes.py).
    mass = float(model.body_subtreemass[model.body(robot.BASE_BODY).id])
    ramp = getattr(getattr(policy.config, "ppo", None), "push_ramp", (0, 0))
    return rnd.trained_under_section(randomization, rnd.settings_from(rnd.PushSettings, cfg.pushes, "env.pushes"),
                                     start, float(model.opt.timestep), mass, ramp,
                                     start_pool=int(getattr(cfg, "start_pool", 0)),
                                     solver_iterations=getattr(getattr(cfg, "sim", None), "solver_iterations", None))


def _upper_gains(model) -> dict[str, list[float]]:
    """``kp`` and ``kv`` of the upper body's position servos in ``model``, the compiled model the policy trained on:
    the env sends them the reference targets (``control.PDHold``) and their gains come from the model file
    (``env.task.model_path``), not from ``robot.UPPER_KP``/``UPPER_KV``, the shipped model's."""
    kp, kv = [], []
    for name in robot.ACTUATOR_NAMES[robot.NUM_LEG_JOINTS :]:
        act = model.actuator(name)
        gain, bias = act.gainprm, act.biasprm
        # A MuJoCo position servo: force = kp * ctrl - kp * q - kv * qdot.
        servo = (int(act.gaintype[0]) == mujoco.mjtGain.mjGAIN_FIXED and int(act.biastype[0]) ==
                 mujoco.mjtBias.mjBIAS_AFFINE and bias[0] == 0 and bias[1] == -gain[0] and gain[0] > 0
                 and bias[2] <= 0)
        if not servo:
            raise ValueError(f"the training model's actuator {name!r} is not a position servo (gain {gain[:3]}, bias "
                             f"{bias[:3]}), so the upper body it held has no gains the contract can state: export a "
                             "policy trained on a model whose upper-body actuators are <position> servos")
        kp.append(float(gain[0]))
        kv.append(float(-bias[2]))
    return {"kp": kp, "kv": kv}


def build_contract(policy, onnx_file: str, onnx_sha256: str, input_name: str, output_name: str, opset: int) -> dict:
    """The contract of a :class:`~tocabi_torchrl.export.onnx_export.LoadedPolicy` exported to ``onnx_file``, with its
    ``content_sha256`` (:func:`~tocabi_torchrl.runtime.contract.content_sha256`)."""
    env = policy.env
    base = env.base_env
    cfg = base.cfg
    model = base.sim.mj_model
    n_leg = robot.NUM_LEG_JOINTS
    leg_ids = [model.joint(n).id for n in robot.JOINT_NAMES[:n_leg]]
    limits = [float(v) for v in robot.LEG_TORQUE_LIMITS]
    if cfg.control.mode not in ("torque", "pd", "pd_reference", "pd_held"):
        # The runtime (numpy + onnxruntime, runtime/policy.py) has no computed-torque law yet: a contract would
        # describe an action the deployed controller cannot apply.
        raise ValueError(f"control mode {cfg.control.mode!r} cannot be exported yet: the contract and the torch-free "
                         "runtime describe only the torque, pd, pd_reference and pd_held modes")
    if cfg.control.mode == "torque":
        leg = {"kind": "torque", "torque_limits_nm": limits,
               "rule": "tau[j] = action[j] * torque_limits_nm[j], held for every physics substep"}
    elif cfg.control.mode == "pd_held":
        leg = {"kind": "torque", "kp": [float(v) for v in cfg.control.pd_kp],
               "kv": [float(v) for v in cfg.control.pd_kv],
               "action_scale": float(cfg.control.pd_action_scale), "torque_limits_nm": limits, "center": "reference",
               "rule": "tau[j] = clip(kp*(reference[j] + action_scale*action[j] - q[j]) - kv*qdot[j], "
                       "+-torque_limits_nm[j]) from the sensed q, qdot at the period's start, held for every physics "
                       "substep; the history's leg actions are tau[j] / torque_limits_nm[j]"}
    else:
        leg = {"kind": "position", "kp": [float(v) for v in cfg.control.pd_kp],
               "kv": [float(v) for v in cfg.control.pd_kv],
               "action_scale": float(cfg.control.pd_action_scale), "torque_limits_nm": limits,
               "joint_range": model.jnt_range[leg_ids].tolist(),
               "center": "nominal" if cfg.control.mode == "pd" else "reference",
               "rule": "target[j] = clip(center[j] + action_scale * action[j], joint_range[j]); tau = clip(kp*(target"
                       " - q) - kv*qdot, +-torque_limits_nm) in every physics substep (a MuJoCo position servo)"}
        if cfg.control.mode == "pd":
            leg["nominal"] = [float(v) for v in cfg.control.pd_nominal]
    act_spec = base.action_spec
    motion = base.motion
    motion_file = Path(motion.source)
    observation = _observation(env)
    _check_normalization(observation["normalization"], policy.checkpoint)
    contract = {
        "format": CONTRACT_FORMAT,
        "contract_version": CONTRACT_VERSION,
        "package_version": __version__,
        "training_config_sha256": config_sha256(policy.saved_config),
        "training_config": policy.config_dict,
        "checkpoint": {"file": policy.checkpoint.name, "iteration": policy.iteration, "env_steps": policy.env_steps},
        "policy": {"onnx_file": onnx_file, "onnx_sha256": onnx_sha256, "opset": opset, "input_name": input_name,
                   "output_name": output_name,
                   "input_dim": int(env.observation_spec["observation"].shape[-1]),
                   "output_dim": int(act_spec.shape[-1]),
                   "output": "Gaussian mean (deterministic action), unclipped: clip to action.low/high before use"},
        "robot": {
            "joint_names": list(robot.JOINT_NAMES),
            "leg_joint_names": list(robot.JOINT_NAMES[:n_leg]),
            "upper_joint_names": list(robot.JOINT_NAMES[n_leg:]),
            "actuator_names": list(robot.ACTUATOR_NAMES),
            "initial_qpos": [float(v) for v in robot.INIT_QPOS],
            "base_body": robot.BASE_BODY, "neck_body": robot.NECK_BODY,
            "foot_force_sensors": list(robot.FOOT_FORCE_SENSORS),
            "foot_torque_sensors": list(robot.FOOT_TORQUE_SENSORS),
        },
        "timing": {"physics_dt_s": float(model.opt.timestep), "substeps": int(cfg.sim.substeps),
                   "control_dt_s": float(base.dt), "control_hz": 1.0 / float(base.dt)},
        "action": {
            "dim": int(act_spec.shape[-1]),
            "low": act_spec.space.low[0].tolist(), "high": act_spec.space.high[0].tolist(),
            "nan": "NaN entries count as 0",
            "control_mode": cfg.control.mode,
            "leg": leg,
            "phase_rate": {"index": int(act_spec.shape[-1]) - 1, "gain": float(cfg.task.phase_rate_gain),
                           "rule": "after each control period: t = (t + control_dt_s * (1 + gain * action[index])) "
                                   "mod reference_motion.period_s"},
        },
        "upper_body": {"hold": "reference_motion joint targets at the period's start clock", **_upper_gains(model)},
        "observation": observation,
        "reference_motion": {
            "name": motion_file.name, "sha256": file_sha256(motion_file), "rows": motion.num_rows,
            "row_dt_s": float(motion.row_dt), "period_s": float(motion.period),
            "init_rows": motion.init_rows.tolist(),
            "interpolation": "zero-velocity cubic between rows: q = q[i] + (q[i+1] - q[i]) * (3s^2 - 2s^3)",
            "phase": "((init_row + (t mod period) / row_dt) mod (rows - 1)) / (rows - 1)",
        },
        "termination": {"min_pelvis_height": float(cfg.task.min_pelvis_height),
                        "min_neck_height": float(cfg.task.min_neck_height),
                        "max_neck_angle": float(cfg.task.max_neck_angle),
                        "forbidden_contact": bool(cfg.task.terminate_on_forbidden_contact),
                        "self_collision": bool(cfg.task.terminate_on_self_collision)},
        "trained_under": _trained_under(policy, cfg, model),
    }
    # Beside the version, where a reader looks first: the hash of every value that sets the policy's input or action.
    digest = content_sha256(contract)
    head = {k: contract.pop(k) for k in ("format", "contract_version")}
    contract = {**head, "content_sha256": digest, **contract}
    check_contract(contract, "exported contract")
    return contract
