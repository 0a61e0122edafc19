"""Access to the reference data in ``../shared/reference`` (beside the repository), for parity tests only.

The project never copies these files; tests read them in place and skip when the folder is absent.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
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
    """Compile the reference robot in modern MuJoCo.

    Mesh geoms and assets are removed (visual only, and some meshes are missing upstream) and so are the two
    inertial ``quat`` attributes that modern MuJoCo rejects beside ``fullinertia`` (MuJoCo 2.1 ignored them).
    """
    import mujoco

    root = ET.parse(reference_file("dyros_tocabi.xml")).getroot()
    root.find("compiler").attrib.pop("meshdir", None)
    for parent in root.iter():
        for child in list(parent):
            if child.tag == "mesh" or (child.tag == "geom" and (child.get("class") == "viz" or "mesh" in child.attrib)):
                parent.remove(child)
            elif child.tag == "inertial" and "fullinertia" in child.attrib:
                child.attrib.pop("quat", None)
    return mujoco.MjModel.from_xml_string(ET.tostring(root, encoding="unicode"))
