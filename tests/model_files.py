"""The shipped robot model rewritten with another ``<compiler>`` angle unit or a joint range, for the model-file
checks' tests."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from tocabi_torchrl import robot

#: The opening of the shipped model's compiler element, which states its unit.
RADIAN = '<compiler angle="radian" '
#: Compiler openings that read the shipped model's radian ranges as degrees: said outright, and MuJoCo's default.
DEGREE_COMPILERS = {"degree": '<compiler angle="degree" ', "mujoco-default": "<compiler "}


def shipped_text() -> str:
    """The shipped MJCF, checked to state its radian unit where :data:`RADIAN` replaces it."""
    text = robot.asset_path("tocabi", "tocabi.xml").read_text()
    assert RADIAN in text
    return text


def shipped_model_read_as(folder: Path, compiler: str, name: str = "in_degrees.xml") -> Path:
    """The shipped model with ``compiler`` in place of :data:`RADIAN`, written to ``folder / name``."""
    path = folder / name
    path.write_text(shipped_text().replace(RADIAN, compiler))
    return path


def shipped_model_in_degrees(folder: Path, name: str = "degrees.xml") -> Path:
    """The shipped model written in degrees throughout (its compiler and every joint range), to ``folder / name``:
    the same robot, which the angle-unit check must accept."""
    def in_degrees(match: re.Match) -> str:
        return ' range="{}"'.format(" ".join(f"{np.degrees(float(v)):.6f}" for v in match[1].split()))

    path = folder / name
    text = shipped_text().replace(RADIAN, DEGREE_COMPILERS["degree"])
    path.write_text(re.sub(r' range="([^"]+)"', in_degrees, text))
    return path


def shipped_model_mixing_units(folder: Path, name: str = "mixed.xml", narrow: str | None = None) -> Path:
    """The shipped model read in degrees with every joint range in degrees but the legs' (``-3.14 3.14``), left in
    radians, to ``folder / name``; with ``narrow``, instead every range in degrees and that joint's ±3 degrees."""
    def unit(match: re.Match) -> str:
        if narrow is None and match[1] == "-3.14 3.14":
            return match[0]
        return ' range="{}"'.format(" ".join(f"{np.degrees(float(v)):.6f}" for v in match[1].split()))

    path = folder / name
    text = re.sub(r' range="([^"]+)"', unit, shipped_text().replace(RADIAN, DEGREE_COMPILERS["degree"]))
    if narrow is not None:
        text, n = re.subn(rf'(<joint name="{narrow}"[^>]* range=")[^"]+"', r'\g<1>-3 3"', text)
        assert n == 1
    path.write_text(text)
    return path


def shipped_model_with_range(path: Path, joint: str, low: float, high: float) -> Path:
    """The shipped model, written to ``path`` with ``joint``'s range set to [low, high] rad."""
    text = shipped_text()
    old = f'<joint name="{joint}" axis="0 1 0" range="-3.14 3.14"'
    assert text.count(old) == 1
    path.write_text(text.replace(old, old.replace('"-3.14 3.14"', f'"{low:g} {high:g}"')))
    return path
