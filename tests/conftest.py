"""Fixtures shared across test modules."""

from __future__ import annotations

import os

import pytest

# Under pytest-xdist each worker gets its share of the cores for torch's and OpenMP's thread pools (its subprocesses
# inherit it): with every worker running one thread per core, the workers fight over the cores.
if "PYTEST_XDIST_WORKER_COUNT" in os.environ:
    _share = str(max(1, (os.cpu_count() or 1) // int(os.environ["PYTEST_XDIST_WORKER_COUNT"])))
    os.environ.setdefault("OMP_NUM_THREADS", _share)
    os.environ.setdefault("MKL_NUM_THREADS", _share)

from tocabi_torchrl.render_gl import choose_gl_backend  # noqa: E402

# Offscreen rendering as the recipes set it up (EGL on a headless machine), chosen before any test imports mujoco.
choose_gl_backend()

from tocabi_torchrl import robot  # noqa: E402


@pytest.fixture(scope="session")
def model():
    """The shipped TOCABI model (compiled once per test run)."""
    try:
        return robot.load_model()
    except robot.RobotAssetError as err:
        pytest.skip(f"robot model not available: {err}")
