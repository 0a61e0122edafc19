"""MuJoCo's OpenGL backend for offscreen video, chosen before ``mujoco`` is imported (it reads ``MUJOCO_GL`` once).

* unset, no display, EGL present: ``egl`` (headless GPU machines, and Mesa's EGL on CPU-only ones);
* ``osmesa``: only usable with the OSMesa library and PyOpenGL; without them ``import mujoco`` itself crashes with an
  ``AttributeError`` deep in PyOpenGL, so :func:`choose_gl_backend` raises :class:`GLBackendError` saying what to
  install or set instead;
* anything else (``egl``, ``glfw``, unset with a display) is left to MuJoCo.

This module imports neither mujoco nor torch, so the recipes can call it first.
"""

from __future__ import annotations

import ctypes.util
import importlib.util
import os
from collections.abc import MutableMapping

__all__ = ["GLBackendError", "choose_gl_backend"]


class GLBackendError(RuntimeError):
    """The requested ``MUJOCO_GL`` backend cannot work on this machine."""


def choose_gl_backend(environ: MutableMapping[str, str] | None = None) -> str | None:
    """Set ``MUJOCO_GL=egl`` on a headless machine with EGL, check an explicit ``osmesa``; returns the backend that
    MuJoCo will use (``None``: its default). Raises :class:`GLBackendError` for an ``osmesa`` that cannot load."""
    environ = os.environ if environ is None else environ
    chosen = environ.get("MUJOCO_GL")
    if not chosen:
        if not environ.get("DISPLAY") and ctypes.util.find_library("EGL"):
            environ["MUJOCO_GL"] = "egl"
            return "egl"
        return None
    if chosen.lower() == "osmesa":
        missing = [name for name, found in (("the OSMesa library (e.g. apt install libosmesa6)",
                                             ctypes.util.find_library("OSMesa")),
                                            ("PyOpenGL (pip install PyOpenGL)", importlib.util.find_spec("OpenGL")))
                   if not found]
        if missing:
            raise GLBackendError(
                f"MUJOCO_GL=osmesa needs {' and '.join(missing)}, which this machine lacks, so MuJoCo cannot start. "
                "Use MUJOCO_GL=egl on a headless machine (GPU or Mesa's EGL), leave MUJOCO_GL unset on a desktop, or "
                "install the missing piece")
    return chosen
