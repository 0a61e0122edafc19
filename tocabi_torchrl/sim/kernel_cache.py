"""Tell the user, in one line, when warp is about to compile mujoco-warp's kernels (minutes on a new machine)."""

from __future__ import annotations

import os

import warp as wp

__all__ = ["announce_compile_if_cold", "quiet_warp_info"]

# A full step/forward/reset of this robot loads ~40 warp modules; far fewer compiled ones means a cold cache.
_WARM_MODULES = 30


def _compiled_modules(cache_dir: str, device: wp.Device) -> int:
    try:
        entries = list(os.scandir(cache_dir))
    except OSError:
        return 0
    count = 0
    for entry in entries:
        if not entry.is_dir() or not entry.name.startswith("wp_"):
            continue
        try:
            files = os.listdir(entry.path)
        except OSError:
            continue
        # CPU modules compile to .o; CUDA ones to .sm<arch>.cubin, or .ptx for a lower target arch.
        count += any(f.endswith(".o" if device.is_cpu else (".cubin", ".ptx")) for f in files)
    return count


def announce_compile_if_cold(device: wp.Device) -> bool:
    """Print one line if the kernel cache holds few compiled modules for ``device``; return whether it printed."""
    cache_dir = str(wp.config.kernel_cache_dir)
    if _compiled_modules(cache_dir, device) >= _WARM_MODULES:
        return False
    where = "GPU: ~3-4 min" if device.is_cuda else "CPU: ~1 min"
    print(
        f"[tocabi_torchrl.sim] compiling mujoco-warp kernels for {device} ({where}, once per machine and version); "
        f"cached in {cache_dir}",
        flush=True,
    )
    return True


def quiet_warp_info() -> None:
    """Lower warp's log level from its default (info) to warnings, before warp initialises.

    At the info level warp prints a banner and one line per module it loads, about fifty lines for every simulator
    built, which bury a run's own output; :func:`announce_compile_if_cold` says what a user needs to know about the
    compile. A level the user set (anything but the default) is kept; after a simulator is built,
    ``wp.config.log_level = wp.LOG_INFO`` brings the lines back. Warp versions before ``log_level`` have only the
    switch ``quiet``, which is set (``wp.config.quiet = False`` afterwards brings the lines back there).
    """
    if hasattr(wp.config, "log_level"):
        if wp.config.log_level == wp.LOG_INFO:
            wp.config.log_level = wp.LOG_WARNING
    elif hasattr(wp.config, "quiet"):
        wp.config.quiet = True
