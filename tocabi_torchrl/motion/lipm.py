"""Centre-of-mass plan of a cyclic gait with the linear inverted pendulum (LIPM).

The LIPM at constant height ``z_c`` links the horizontal CoM ``c`` to the ZMP ``p`` by ``c'' = ω² (c − p)`` with
``ω² = g / z_c``. For a *cyclic* gait we want the one periodic CoM whose ZMP is a given periodic reference: that is
what ZMP preview control converges to with an infinite preview horizon, obtained here exactly (no preview gains, no
start-up transient) by solving the ODE in the Fourier domain, ``ĉ_k = p̂_k · ω² / (ω² + (2π k / T)²)``.
A walk moves forward, so its ZMP is periodic only up to a drift per cycle (the stride); the drift is a constant
velocity, which the LIPM tracks exactly (``c = p`` for a ramp), so it is removed before the solve and added back.
"""

from __future__ import annotations

import numpy as np

from tocabi_torchrl.robot import GRAVITY

__all__ = ["periodic_lipm_com", "lipm_zmp"]


def periodic_lipm_com(
    zmp: np.ndarray,
    period: float,
    com_height: float,
    drift: np.ndarray | None = None,
    gravity: float = GRAVITY,
) -> np.ndarray:
    """Periodic LIPM CoM that realises a ZMP reference.

    Args:
        zmp: (n, d) ZMP reference [m] at times ``k·period/n``, k = 0..n−1 (one cycle, endpoint excluded).
        period: cycle duration [s].
        com_height: LIPM height z_c [m].
        drift: (d,) ZMP (and CoM) advance per cycle [m], e.g. (stride, 0); ``None`` for none.
    Returns:
        (n, d) CoM positions [m] at the same times.
    """
    zmp = np.asarray(zmp, dtype=np.float64)
    n = zmp.shape[0]
    drift = np.zeros(zmp.shape[1:]) if drift is None else np.asarray(drift, dtype=np.float64)
    ramp = np.arange(n)[:, None] / n * drift
    omega2 = gravity / com_height
    freq = np.fft.rfftfreq(n, d=period / n)
    gain = omega2 / (omega2 + (2.0 * np.pi * freq) ** 2)
    periodic = np.fft.irfft(np.fft.rfft(zmp - ramp, axis=0) * gain[:, None], n=n, axis=0)
    return periodic + ramp


def lipm_zmp(com: np.ndarray, period: float, com_height: float, drift=None, gravity: float = GRAVITY) -> np.ndarray:
    """ZMP of a periodic CoM trajectory, ``p = c − c''/ω²`` (the inverse of :func:`periodic_lipm_com`)."""
    com = np.asarray(com, dtype=np.float64)
    n = com.shape[0]
    drift = np.zeros(com.shape[1:]) if drift is None else np.asarray(drift, dtype=np.float64)
    ramp = np.arange(n)[:, None] / n * drift
    freq = np.fft.rfftfreq(n, d=period / n)
    accel = np.fft.irfft(np.fft.rfft(com - ramp, axis=0) * -((2.0 * np.pi * freq) ** 2)[:, None], n=n, axis=0)
    return com - accel * com_height / gravity
