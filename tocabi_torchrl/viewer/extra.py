"""Whether the ``viewer`` extra (viser) is installed, and the one error that says how to install it."""

from __future__ import annotations

import importlib

__all__ = ["ViewerUnavailable", "INSTALL_HINT", "require_viser"]

INSTALL_HINT = 'pip install -e ".[viewer]"'


class ViewerUnavailable(ImportError):
    """The live viewer needs viser, which is not installed (the message names the install command)."""


def require_viser():
    """The ``viser`` module; raises :class:`ViewerUnavailable` (an ``ImportError``) naming the install command when
    it is missing."""
    try:
        return importlib.import_module("viser")
    except ImportError as err:
        raise ViewerUnavailable(f"the live viewer needs the 'viewer' extra (viser), which is not installed "
                                f"({err}); install it with: {INSTALL_HINT}") from err
