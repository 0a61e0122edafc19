"""Access to the reference data in ``../shared/reference`` (beside the repository), for parity tests only.

The project never copies these files; tests read them in place and skip when the folder is absent.
"""

from __future__ import annotations

from pathlib import Path

import pytest

REFERENCE_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "reference"


def reference_file(name: str) -> Path:
    """Path of a reference file, or skip the calling test when it is not there."""
    path = REFERENCE_DIR / name
    if not path.is_file():
        pytest.skip(f"reference data not available ({path})")
    return path


def load_reference_model():
    """Compile the reference robot in modern MuJoCo, as the sim-to-sim runtime does (``runtime.strip_meshes``).

    Mesh geoms and assets are removed (visual only, and some meshes are missing upstream) and so are the two
    inertial ``quat`` attributes that modern MuJoCo rejects beside ``fullinertia`` (MuJoCo 2.1 ignored them).
    """
    import mujoco

    from tocabi_torchrl.runtime.mujoco_driver import strip_meshes

    return mujoco.MjModel.from_xml_string(strip_meshes(reference_file("dyros_tocabi.xml")))
