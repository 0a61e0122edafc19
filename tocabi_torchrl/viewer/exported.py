"""The live page of an exported policy (ONNX + contract) driving C MuJoCo robots through the torch-free runtime
(``recipes/sim2sim.py --viewer``, ``recipes/play.py --policy ppo.onnx --viewer``). Imports numpy, mujoco and viser
only, like the runtime.

The runtime's sim-to-sim driver (:func:`~tocabi_torchrl.runtime.mujoco_driver.run_sim2sim`) calls
:class:`ExportedWatch` after every control period; it draws the robots at most ``fps`` times a second and holds the
loop to real time. The page has the world picker and camera follow; command and pushes are the driver's options
(``--vx``, ``--pushes``), fixed for the run.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from .. import robot
from .config import MAX_SHOWN
from .controls import WorldControls
from .geometry import body_meshes
from .overlays import MetricsPanel
from .scene import RobotScene, follow

__all__ = ["ExportedWatch", "contract_of"]


def contract_of(path: str | Path) -> Path:
    """The contract ``.json`` of an exported policy given as its ``.onnx`` (beside it, same stem) or as itself."""
    path = Path(path)
    contract = path.with_suffix(".json") if path.suffix == ".onnx" else path
    if not contract.is_file():
        raise ValueError(f"{path}: no policy contract {contract.name} beside it; an exported policy is the .onnx "
                         "with its .json contract (python -m tocabi_torchrl.export writes both)")
    return contract


class ExportedWatch:
    """``on_step`` of :func:`~tocabi_torchrl.runtime.mujoco_driver.run_sim2sim`: draws its robots (the first
    :data:`~.config.MAX_SHOWN`) on ``server``.

    Args:
        server: a running ``viser.ViserServer``.
        dt: the control period [s] (the contract's ``timing.control_dt_s``).
        fps: frames sent per second at most; real_time: never run faster than real time.
    """

    def __init__(self, server, dt: float, fps: float = 30.0, real_time: bool = True):
        self.server, self.dt, self.real_time = server, float(dt), real_time
        self.frame_s = 1.0 / fps
        self.scene: RobotScene | None = None
        self.controls: WorldControls | None = None
        self.panel = MetricsPanel(server, "exported policy (ONNX runtime, C MuJoCo)")
        self.frames = 0
        self._next_frame = 0.0
        self._clock: float | None = None

    def __call__(self, step: int, model, datas: list) -> None:
        if self.scene is None:  # the driver compiles the model: the scene is built from the first call's
            # The first MAX_SHOWN robots, as a checkpoint's page: every robot of a 1,000-robot run was sent each
            # frame and drawn by the browser, which the page's cap exists to spare.
            shown = min(len(datas), MAX_SHOWN)
            self.controls = WorldControls(self.server, shown)
            self.scene = RobotScene(self.server, body_meshes(model), shown)
            self._pelvis = model.body(robot.BASE_BODY).id
            self._clock = time.perf_counter()
        now = time.perf_counter()
        if now >= self._next_frame:
            datas = datas[:self.scene.num_worlds]
            xpos = np.stack([d.xpos for d in datas])
            self.scene.update(xpos, np.stack([d.xquat for d in datas]))
            sel = min(self.controls.selected, len(datas) - 1)
            self.scene.select(sel)
            if self.controls.follow.value:
                follow(self.server, self.scene.shown_position(sel, xpos[sel, self._pelvis]))
            self.panel.show({"time": (step + 1) * self.dt}, {"time": ("time", "s", 2)},
                            title="exported policy (ONNX runtime, C MuJoCo)")
            self.frames += 1
            self._next_frame = now + self.frame_s
        if self.real_time:
            self._clock += self.dt
            ahead = self._clock - time.perf_counter()
            if ahead > 0:
                time.sleep(ahead)
            else:
                self._clock = max(self._clock, time.perf_counter() - 0.1)  # a slow machine does not catch up later
