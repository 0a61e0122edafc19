"""Fixtures shared across test modules."""

from __future__ import annotations

import pytest

from tocabi_torchrl import robot


@pytest.fixture(scope="session")
def model():
    """The shipped TOCABI model (compiled once per session)."""
    try:
        return robot.load_model()
    except robot.RobotAssetError as err:
        pytest.skip(f"robot model not available: {err}")
