"""Supported version ranges of the RL libraries the adapters speak to, checked before an adapter is built.

Each library's interface changed across major versions (rsl_rl's ``VecEnv`` returns a ``TensorDict`` of observation
groups from 3.x on; skrl 2.x moved its wrappers and configs), so an adapter refuses a version outside the range it
was written and tested against instead of failing later with an obscure ``AttributeError``.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import re
from types import ModuleType

__all__ = ["SUPPORTED", "LibraryVersionError", "require", "version_in_range"]

#: import name -> (distribution name, lowest supported version (inclusive), first unsupported version, extra).
#: Tested with rsl-rl-lib 5.5.1, stable-baselines3 2.9.2 and skrl 2.1.1 (pyproject.toml
#: declares the same ranges, gymnasium's in the core dependencies: tests/test_adapters_common.py checks).
SUPPORTED: dict[str, tuple[str, str, str, str]] = {
    "rsl_rl": ("rsl-rl-lib", "5.0", "6.0", "rsl_rl"),
    "stable_baselines3": ("stable-baselines3", "2.3", "3.0", "sb3"),
    "skrl": ("skrl", "2.0", "3.0", "skrl"),
    "gymnasium": ("gymnasium", "1.1", "2.0", ""),
}


class LibraryVersionError(ImportError):
    """An RL library is installed in a version outside the range an adapter supports (or is missing)."""


def _parse(version: str) -> tuple[int, ...]:
    """Leading numeric release parts of a version string: ``"5.5.1rc1"`` -> ``(5, 5, 1)``."""
    parts = []
    for piece in version.split("."):
        match = re.match(r"\d+", piece)
        if match is None:
            break
        parts.append(int(match.group()))
        if match.end() != len(piece):  # "1rc1": a pre-release tag ends the release part
            break
    return tuple(parts)


def version_in_range(version: str, low: str, high: str) -> bool:
    """Whether ``low <= version < high`` by numeric release parts (pre-release tags are ignored)."""
    v, lo, hi = _parse(version), _parse(low), _parse(high)
    width = max(len(v), len(lo), len(hi))
    pad = lambda t: t + (0,) * (width - len(t))
    return pad(lo) <= pad(v) < pad(hi)


def require(module: str) -> ModuleType:
    """Import ``module`` (a key of :data:`SUPPORTED`) and check its installed version.

    Raises :class:`LibraryVersionError` naming the supported range and the install command when the library is
    missing or its version is outside the range.
    """
    dist, low, high, extra = SUPPORTED[module]
    install = (f'pip install -e ".[{extra}]" in the repository' if extra else f"pip install '{dist}>={low},<{high}'")
    try:
        version = importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        raise LibraryVersionError(f"{dist} is not installed; the {module} adapter needs {dist}>={low},<{high}: "
                                  f"{install}") from None
    if not version_in_range(version, low, high):
        raise LibraryVersionError(
            f"{dist} {version} is installed, but the tocabi_torchrl {module} adapter supports {dist}>={low},<{high} "
            f"(its interface differs across major versions); install a supported version: {install}")
    return importlib.import_module(module)
