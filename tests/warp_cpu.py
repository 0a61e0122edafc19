"""Whether warp's CPU device works on this machine: the tests that run mujoco-warp on the CPU skip where it does not."""

from __future__ import annotations

import warp as wp


def warp_cpu_available() -> bool:
    try:
        wp.init()
        return wp.get_device("cpu") is not None
    except (RuntimeError, ValueError):
        return False
