"""Fixtures shared across test modules."""

from __future__ import annotations

import pytest

from tocabi_torchrl.render_gl import choose_gl_backend

# Offscreen rendering as the recipes set it up (EGL on a headless machine), chosen before any test imports mujoco.
choose_gl_backend()

from tocabi_torchrl import robot  # noqa: E402


@pytest.fixture(scope="session")
def model():
    """The shipped TOCABI model (compiled once per session)."""
    try:
        return robot.load_model()
    except robot.RobotAssetError as err:
        pytest.skip(f"robot model not available: {err}")
