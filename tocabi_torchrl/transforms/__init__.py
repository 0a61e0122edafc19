"""TorchRL transforms that turn ``TocabiWalk``'s raw signals (docs/concepts/env-and-signals.md) into the policy input
and the reward.

One module per job:

* :mod:`.phase`: :class:`PhaseEncoding` (sin/cos harmonics of the gait phase)
* :mod:`.orientation`: :class:`BaseEulerAngles` (the quaternion math is :mod:`tocabi_torchrl.rotations`)
* :mod:`.observation`: :class:`ObservationAssembly` of the per-step vector (37 values in the reference order)
* :mod:`.sensor_noise`: :class:`SensorNoise` (sensor biases and noise on that vector), :class:`SensorNoiseConfig`
* :mod:`.normalize`: :class:`FixedNormalization` (reference statistics) and :class:`RunningNormalization`
* :mod:`.history`: :class:`ObsActionHistory` with a :class:`HistoryLayout` (reference: 237-value input)
* :mod:`.reward_terms`: one :class:`RewardTerm` per reference reward component; :mod:`.reward`: :class:`TaskReward`
  (with :class:`KickRelax`, terms relaxed while a kicked robot recovers)
* :mod:`.presets`: :class:`TransformConfig`, :data:`HISTORIES` and :func:`default_transforms`
* :mod:`.privileged`: :class:`PrivilegedState`, the asymmetric critic's true-state input (``ppo.critic_privileged``)
"""

from .._lazy import lazy_names

__all__ = [
    "PhaseEncoding",
    "BaseEulerAngles",
    "quat_to_rpy",
    "quat_rotation_angle",
    "ObsComponent",
    "REFERENCE_OBS_LAYOUT",
    "ObservationAssembly",
    "SensorNoise",
    "SensorNoiseConfig",
    "REFERENCE_OBS_MEAN",
    "REFERENCE_OBS_VAR",
    "FixedNormalization",
    "RunningNormalization",
    "HistoryLayout",
    "REFERENCE_HISTORY",
    "TOCABILAB_HISTORY",
    "ObsActionHistory",
    "RewardTerm",
    "CallableTerm",
    "NeckOrientation",
    "JointPosTracking",
    "JointVelRegulation",
    "BodyVelTracking",
    "ContactForce",
    "TorqueRegulation",
    "TorqueDiffRegulation",
    "JointAccRegulation",
    "FootContactPattern",
    "ContactForceDiff",
    "ForceReference",
    "ForceThresholdPenalty",
    "ForceDiffThresholdPenalty",
    "HeadingHold",
    "FootGap",
    "CycleVelTracking",
    "REFERENCE_TERMS",
    "reference_terms",
    "TaskReward",
    "KickRelax",
    "PrivilegedState",
    "TransformConfig",
    "TransformSettings",
    "RewardWeights",
    "HISTORIES",
    "BASE_VEL_OBS_LAYOUT",
    "OBS_LAYOUTS",
    "transform_config",
    "default_transforms",
]

# Each name loads its submodule when first read: importing any submodule (a config dataclass for the run config
# tree and --help) runs this file first, and must not load the torch, torchrl and mujoco-warp code of the others.
__getattr__, __dir__ = lazy_names(globals(), {
    "history": ("REFERENCE_HISTORY", "TOCABILAB_HISTORY", "HistoryLayout", "ObsActionHistory"),
    "normalize": ("REFERENCE_OBS_MEAN", "REFERENCE_OBS_VAR", "FixedNormalization", "RunningNormalization"),
    "observation": ("REFERENCE_OBS_LAYOUT", "ObservationAssembly", "ObsComponent"),
    "layouts": ("BASE_VEL_OBS_LAYOUT", "OBS_LAYOUTS"),
    "orientation": ("BaseEulerAngles", "quat_rotation_angle", "quat_to_rpy"),
    "phase": ("PhaseEncoding",),
    "presets": ("default_transforms",),
    "privileged": ("PRIVILEGED_DIM", "PRIVILEGED_MIRROR", "PrivilegedState"),
    "settings": ("HISTORIES", "RewardWeights", "TransformConfig", "TransformSettings", "transform_config"),
    "reward": ("TaskReward",),
    "kick_relax_config": ("KICK_RELAX_TERMS", "KickRelax"),
    "reward_terms": (
        "REFERENCE_TERMS", "BodyVelTracking", "CallableTerm", "ContactForce", "ContactForceDiff", "FootContactPattern",
        "ForceDiffThresholdPenalty", "ForceReference", "ForceThresholdPenalty", "FootGap", "CycleVelTracking",
        "HeadingHold", "JointAccRegulation", "JointPosTracking", "JointVelRegulation", "NeckOrientation", "RewardTerm",
        "TorqueDiffRegulation", "TorqueRegulation", "reference_terms"),
    "sensor_noise": ("SensorNoise",),
    "sensor_noise_config": ("SensorNoiseConfig",),
})
