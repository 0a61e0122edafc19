"""Watch mujoco-warp's substeps from a test: ``WarpSim`` runs a control period as ``mjw.step2`` then ``mjw.step``
per further substep, and closes it with a forward pass that overwrites per-solve fields such as ``solver_niter``."""

from __future__ import annotations

from typing import Callable

import mujoco_warp as mjw


def after_each_substep(monkeypatch, record: Callable[[object], None]) -> None:
    """Until ``monkeypatch.undo()``, every ``mjw.step``/``mjw.step2`` call (one per physics substep of an eager
    ``WarpSim`` step: ``use_graph=False``) is followed by ``record(data)``, before anything else reads the data."""
    for name in ("step", "step2"):
        def recorded(m, d, _real=getattr(mjw, name)):
            _real(m, d)
            record(d)

        monkeypatch.setattr(mjw, name, recorded)
