"""The reference motion for the runtime: numpy lookups that reproduce ``motion.ReferenceMotion`` in float32.

Only numpy and the standard library: the runtime must run where torch is not installed. The arithmetic follows
``tocabi_torchrl/motion/reference.py`` step for step (time in row units, a zero-velocity cubic between rows), in
float32 as the env does, so targets and phase agree with the training env to float32 rounding.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np

from .contract import ContractError, folder_note

__all__ = ["RuntimeMotion", "file_sha256"]

_F32 = np.float32


def file_sha256(path: str | os.PathLike) -> str:
    """Hex sha256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _text_sample_rate(time: np.ndarray) -> float:
    """Rows per second of a text motion's time column [s], as training reads it (``motion.io._sample_rate_of``): over
    the whole column, snapped to a whole rate when within 1e-6 of one. Printed times carry rounding (0.0003333 for
    1/3000 s), so the first step alone gives another period than the one the policy was trained with."""
    rate = (time.size - 1) / float(time[-1] - time[0])
    return float(round(rate)) if abs(rate - round(rate)) < 1e-6 * rate else float(rate)


class RuntimeMotion:
    """A cyclic reference motion: (R, J) joint targets at ``row_dt`` spacing, and the rows an episode starts at.

    Args:
        joint_pos: (R, J) joint targets [rad] in the contract's joint order.
        row_dt: seconds between rows.
        init_rows: start rows allowed by the motion.
        source: the file it was read from, for messages ("" for arrays).
    """

    def __init__(self, joint_pos: np.ndarray, row_dt: float, init_rows: np.ndarray, source: str = ""):
        self.source = source
        self.joint_pos = np.asarray(joint_pos, dtype=_F32)
        self.row_dt = float(row_dt)
        self.init_rows = np.asarray(init_rows, dtype=np.int64).reshape(-1)
        self.cycle_rows = self.joint_pos.shape[0] - 1
        self.period = self.cycle_rows * self.row_dt

    @classmethod
    def from_file(cls, path: str | os.PathLike, joint_names: list[str], sha256: str | None = None) -> RuntimeMotion:
        """Load a ``.npz`` (project format) or ``.txt`` (reference format) motion; with ``sha256`` the file must
        have that hash (the contract's), else :class:`ContractError`. Only ``sha256=None``, the caller's explicit
        choice, skips the check (:class:`~.policy.PolicyRuntime` always passes the contract's, which
        ``check_contract`` requires to be a sha256)."""
        path = Path(path)
        if not path.is_file():
            raise ContractError(folder_note(path, "reference motion", ".npz") or f"reference motion not found: "
                                f"{path}; pass the file the contract names")
        if sha256 is not None and (not isinstance(sha256, str) or len(sha256) != 64):
            raise ContractError(f"reference motion hash {sha256!r} is not a sha256 (64 hex digits): pass the "
                                "contract's reference_motion.sha256, or None to skip the check")
        if sha256 is not None:
            found = file_sha256(path)
            if found != sha256:
                raise ContractError(f"reference motion {path} has sha256 {found[:16]}…, but the contract expects "
                                    f"{sha256[:16]}…: the policy was trained on another motion; pass that file")
        if path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as npz:
                names = [str(n) for n in np.atleast_1d(npz["joint_names"])]
                missing = [n for n in joint_names if n not in names]
                if missing:
                    raise ContractError(f"reference motion {path} lacks joints {missing}")
                cols = [names.index(n) for n in joint_names]
                # float64 on disk -> float32, as ReferenceMotion does
                joint_pos = np.asarray(npz["joint_pos"], dtype=np.float64)[:, cols]
                return cls(joint_pos, 1.0 / float(npz["sample_rate"]), npz["init_rows"], str(path))
        table = np.loadtxt(path)  # reference text format: time, 33 joints, 2 forces; start rows 0 and R/2
        rows = table.shape[0]
        return cls(table[:, 1 : 1 + len(joint_names)], 1.0 / _text_sample_rate(table[:, 0]), np.array([0, rows // 2]),
                   str(path))

    def _cycle_position(self, time: np.ndarray) -> np.ndarray:
        n = _F32(self.cycle_rows)
        u = np.remainder(time.astype(_F32) * _F32(1.0 / self.row_dt), n)
        return np.clip(u, _F32(0.0), np.nextafter(n, _F32(0.0)))

    def _row_and_fraction(self, time: np.ndarray, init_row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = self._cycle_position(time)
        whole = np.floor(u)
        step = np.clip(whole.astype(np.int64), 0, self.cycle_rows - 1)
        idx = np.remainder(init_row.astype(np.int64) + step, self.cycle_rows)
        return idx, np.clip(u - whole, _F32(0.0), _F32(1.0))

    def joint_targets(self, time: np.ndarray, init_row: np.ndarray) -> np.ndarray:
        """(N, J) float32 targets [rad] at clock ``time`` (N,) float32 [s] for start rows ``init_row`` (N,)."""
        idx, s = self._row_and_fraction(time, init_row)
        q0, q1 = self.joint_pos[idx], self.joint_pos[idx + 1]
        w = (s * s * (_F32(3.0) - _F32(2.0) * s))[:, None]
        return q0 + (q1 - q0) * w

    def phase(self, time: np.ndarray, init_row: np.ndarray) -> np.ndarray:
        """(N,) float32 observation phase in [0, 1)."""
        n = _F32(self.cycle_rows)
        p = np.remainder(init_row.astype(_F32) + self._cycle_position(time), n) * _F32(1.0 / self.cycle_rows)
        return np.clip(p, _F32(0.0), np.nextafter(_F32(1.0), _F32(0.0)))
