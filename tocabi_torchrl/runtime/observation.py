"""The policy input from raw robot signals, per the contract: Euler angles, the 37 (or 43) entries, normalisation,
history.

numpy only. Each function mirrors one TorchRL transform of ``tocabi_torchrl.transforms`` (named in its docstring);
``tests/test_runtime.py`` checks the result against the TorchRL env's ``observation`` on the same states.
"""

from __future__ import annotations

import numpy as np

from .contract import ContractError

__all__ = ["History", "ObservationBuilder", "quat_to_rpy"]


def quat_to_rpy(quat: np.ndarray) -> np.ndarray:
    """(N, 4) (w, x, y, z) -> (N, 3) fixed-XYZ roll, pitch, yaw [rad] (``transforms.orientation.quat_to_rpy``).

    Computed in float64 from the quaternion (need not be unit length); at the gimbal lock yaw = atan2(-R01, R11),
    roll = 0, as in the reference.
    """
    q = np.asarray(quat, dtype=np.float64)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    # |q|²·R entries; atan2 is scale-invariant
    r00, r01 = w * w + x * x - y * y - z * z, 2 * (x * y - w * z)
    r10, r11 = 2 * (x * y + w * z), w * w - x * x + y * y - z * z
    r20, r21, r22 = 2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z
    cy = np.hypot(r00, r10)
    roll, pitch, yaw = np.arctan2(r21, r22), np.arctan2(-r20, cy), np.arctan2(r10, r00)
    locked = cy <= 4.0 * np.finfo(np.float32).eps * (w * w + x * x + y * y + z * z)
    roll = np.where(locked, 0.0, roll)
    yaw = np.where(locked, np.arctan2(-r01, r11), yaw)
    return np.stack((roll, pitch, yaw), axis=-1).astype(np.float32)


class ObservationBuilder:
    """Assemble and normalise the per-step observation (``ObservationAssembly`` + ``FixedNormalization``).

    Reads the contract's ``observation`` section: entry ``i`` is element ``element`` of the flattened signal
    ``signal``; normalised = (raw - mean) / scale, clipped to ±clip when the contract gives one.
    """

    def __init__(self, observation: dict):
        self.entries = observation["entries"]
        self.signals = observation["signals"]
        self.harmonics = int(observation["phase_harmonics"])
        norm = observation["normalization"]
        self.mean = np.asarray(norm["mean"], dtype=np.float32)
        self.scale = np.asarray(norm["scale"], dtype=np.float32)
        self.clip = norm.get("clip")
        # One gather per signal: which output columns come from which flat elements.
        self._gathers = []
        for name in dict.fromkeys(e["signal"] for e in self.entries):
            cols = [i for i, e in enumerate(self.entries) if e["signal"] == name]
            elems = [self.entries[i]["element"] for i in cols]
            self._gathers.append((name, np.asarray(cols), np.asarray(elems)))
        self._freq = 2.0 * np.pi * np.arange(1, self.harmonics + 1, dtype=np.float32)

    def raw(self, signals: dict[str, np.ndarray]) -> np.ndarray:
        """(N, D) float32 raw observation from a dict of (N, *shape) signals named as in the contract."""
        n = next(iter(signals.values())).shape[0]
        out = np.empty((n, len(self.entries)), dtype=np.float32)
        for name, cols, elems in self._gathers:
            if name not in signals:
                raise ContractError(f"observation signal {name!r} missing: the contract's observation needs "
                                    f"{[g[0] for g in self._gathers]}; pass every one of them")
            flat = np.asarray(signals[name], dtype=np.float32).reshape(n, -1)
            out[:, cols] = flat[:, elems]
        return out

    def phase_features(self, phase: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N,) phase in [0, 1) -> (N, H) sines and cosines, float32 (``PhaseEncoding``)."""
        angle = phase.astype(np.float32)[:, None] * self._freq
        return np.sin(angle), np.cos(angle)

    def normalize(self, raw: np.ndarray) -> np.ndarray:
        """(N, D) raw observation (the contract's units) -> (N, D) float32 (raw - mean) / scale, clipped to ±clip when
        the contract gives one (``FixedNormalization``; ``scale`` already holds sqrt(var + eps))."""
        out = (raw - self.mean) / self.scale
        if self.clip is not None:
            out = np.clip(out, -self.clip, self.clip)
        return out.astype(np.float32)


class History:
    """Past normalised observations and applied actions at the contract's ages (``ObsActionHistory``).

    Slot ``k`` of each ring holds the entry from ``k`` policy steps ago; the policy input is the observations at
    ``obs_ages`` (oldest first), then the actions at ``action_ages`` (oldest first). A reset fills every slot with
    the first observation and the reset action (zeros).
    """

    def __init__(self, obs_ages: list[int], action_ages: list[int]):
        self.obs_ages = np.asarray(obs_ages, dtype=np.int64)
        self.action_ages = np.asarray(action_ages, dtype=np.int64)
        self._obs: np.ndarray | None = None
        self._act: np.ndarray | None = None

    def reset(self, obs: np.ndarray, action: np.ndarray) -> None:
        """Fill every slot with ``obs`` (N, D) float32, the normalised first observation, and ``action`` (N, A)
        float32, the reset action (zeros)."""
        self._obs = np.repeat(obs[:, None, :], int(self.obs_ages.max()) + 1, axis=1)
        length = int(self.action_ages.max()) + 1 if self.action_ages.size else 1
        self._act = np.repeat(action[:, None, :], length, axis=1)

    def push(self, obs: np.ndarray, action: np.ndarray) -> None:
        """Age every slot by one period and store ``obs`` (N, D), the normalised observation after the period, and
        ``action`` (N, A), the clipped action applied in it, at age 0."""
        if self._obs is None:
            raise RuntimeError("History.push before reset: call PolicyRuntime.reset first")
        self._obs = np.roll(self._obs, 1, axis=1)
        self._obs[:, 0] = obs
        self._act = np.roll(self._act, 1, axis=1)
        self._act[:, 0] = action

    def read(self) -> np.ndarray:
        """(N, K·D + M·A) float32 policy input."""
        if self._obs is None:
            raise RuntimeError("History.read before reset: call PolicyRuntime.reset first")
        n = self._obs.shape[0]
        parts = [self._obs[:, self.obs_ages].reshape(n, -1)]
        if self.action_ages.size:
            parts.append(self._act[:, self.action_ages].reshape(n, -1))
        return np.concatenate(parts, axis=1).astype(np.float32)
