"""MuJoCo's OpenGL backend for offscreen video, chosen before ``mujoco`` is imported (it reads ``MUJOCO_GL`` once).

* unset, no display, EGL present: ``egl`` (headless GPU machines, and Mesa's EGL on CPU-only ones);
* unset, no display, no EGL (Linux): ``disable``. MuJoCo's default there would be GLFW, which cannot open a context
  without a display; its first render raises and a second attempt in the same process can abort it (a C++ static
  initialisation guard: ``__cxa_guard_acquire detected recursive initialization``). With ``MUJOCO_GL=disable`` MuJoCo
  loads no OpenGL at all, and :func:`offscreen_unavailable` says why nothing is rendered and what to install;
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
import platform
from collections.abc import Mapping, MutableMapping

__all__ = ["GL_OFF", "NO_GL_FIX", "GLBackendError", "choose_gl_backend", "choose_gl_backend_or_exit",
           "offscreen_unavailable"]

#: ``MUJOCO_GL`` values with which MuJoCo loads no OpenGL (it then cannot render).
GL_OFF = ("disable", "disabled", "off", "false", "0")
#: What to do on a headless Linux machine that cannot render offscreen.
NO_GL_FIX = ("install the EGL loader (e.g. apt install libegl1, libglvnd's libEGL.so.1; with the GPU driver or "
             "Mesa behind it) and leave MUJOCO_GL unset, or set MUJOCO_GL=osmesa (needs libosmesa6 and PyOpenGL)")


class GLBackendError(RuntimeError):
    """The requested ``MUJOCO_GL`` backend cannot work on this machine."""


def _has_display(environ: Mapping[str, str]) -> bool:
    return bool(environ.get("DISPLAY") or environ.get("WAYLAND_DISPLAY"))


def choose_gl_backend(environ: MutableMapping[str, str] | None = None) -> str | None:
    """Set ``MUJOCO_GL=egl`` on a headless machine with EGL, ``MUJOCO_GL=disable`` on a headless Linux machine
    without it, check an explicit ``osmesa``; returns the backend that MuJoCo will use (``None``: its default;
    ``"disable"``: none, frames and videos are to be skipped, :func:`offscreen_unavailable` says why). Raises
    :class:`GLBackendError` for an ``osmesa`` that cannot load."""
    environ = os.environ if environ is None else environ
    chosen = environ.get("MUJOCO_GL")
    if not chosen:
        if not environ.get("DISPLAY") and ctypes.util.find_library("EGL"):
            environ["MUJOCO_GL"] = "egl"
            return "egl"
        if _has_display(environ):
            return None
        if platform.system() == "Linux":  # no display, no EGL: MuJoCo would pick GLFW (macOS: CGL, fine)
            environ["MUJOCO_GL"] = "disable"
            return "disable"
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


def offscreen_unavailable(environ: Mapping[str, str] | None = None) -> str | None:
    """Why MuJoCo cannot render in this process, judged from ``MUJOCO_GL`` (after :func:`choose_gl_backend`), with
    the fix; ``None`` when it may (whether it does is known only by trying)."""
    environ = os.environ if environ is None else environ
    value = environ.get("MUJOCO_GL", "").strip().lower()
    if value not in GL_OFF:
        return None
    if not _has_display(environ) and not ctypes.util.find_library("EGL"):
        return (f"no OpenGL for offscreen rendering (MUJOCO_GL={value}): this machine has no display and no EGL "
                f"library (libEGL.so.1); to render, {NO_GL_FIX}")
    return f"MUJOCO_GL={value} turns MuJoCo's OpenGL off; unset it (or set MUJOCO_GL=egl) to render"


def choose_gl_backend_or_exit() -> str | None:
    """:func:`choose_gl_backend` for a recipe, before mujoco is imported: a backend that cannot work ends the program
    with its one ``error:`` line (exit status 1) instead of a traceback."""
    try:
        return choose_gl_backend()
    except GLBackendError as err:
        raise SystemExit(f"error: {err}") from None
