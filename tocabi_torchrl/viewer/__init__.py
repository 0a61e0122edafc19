"""The live web viewer (optional extra ``viewer``: ``pip install -e ".[viewer]"``, on viser): many robots of a policy
or of a training run drawn in a browser, with controls (docs/viewer.md).

Modules, one job each:

- :mod:`.config`: ``ViewerConfig``, the run config's ``viewer`` section (standard library only).
- :mod:`.extra`: whether viser is installed, and the message that says how to install it.
- :mod:`.geometry`: the robot's (and obstacles') drawable meshes, built once from the compiled MuJoCo model.
- :mod:`.scene`: the viser scene: one batched mesh per body, all worlds updated in one call per body.
- :mod:`.controls`: the GUI (command sliders, pause, step, push, reset, world picker, camera follow).
- :mod:`.overlays`: gait-metric text and the knee-angle trace.
- :mod:`.play`: the live loop of a loaded policy (``recipes/play.py --viewer``).
- :mod:`.stream`: host copies of a few training worlds' body poses, off the training stream (torch only).
- :mod:`.training`: the page of a training run, fed by the stream (``recipes/ppo_walk.py --viewer``).

Nothing here imports viser at import time: :func:`.extra.require_viser` raises one clear error when it is missing.
"""

from .config import MAX_STREAM_WORLDS, ViewerConfig
from .extra import ViewerUnavailable, require_viser

__all__ = ["ViewerConfig", "MAX_STREAM_WORLDS", "ViewerUnavailable", "require_viser"]
