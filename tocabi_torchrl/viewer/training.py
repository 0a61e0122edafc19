"""The live page of a training run (``recipes/ppo_walk.py --viewer``): a few training worlds, streamed by a
:class:`~.stream.PoseStream`, and the last logged iteration's metrics.

A daemon thread draws the newest completed host copy at most ``fps`` times a second; the training loop only ticks
the stream (through the collector's :class:`~.stream.TappedPolicy`) and hands over each logged iteration's metrics
(host floats it already has).
"""

from __future__ import annotations

import threading

from .. import robot
from .config import ViewerConfig
from .controls import WorldControls
from .geometry import body_meshes
from .overlays import MetricsPanel
from .scene import RobotScene, follow
from .server import page_url, start_server
from .stream import PoseStream, TappedPolicy

__all__ = ["TrainingView", "TRAINING_ROWS"]

#: The iteration's metrics shown on the page: key -> (label, unit, decimals) (others stay in the logs).
TRAINING_ROWS = {
    "iteration": ("iteration", "", 0),
    "env_steps": ("env steps", "", 0),
    "env_steps_per_s": ("env steps / s", "", 0),
    "episode_return": ("episode return", "", 3),
    "episode_length": ("episode length", "steps", 1),
    "terminated_frac": ("terminated per step", "", 4),
    "reward": ("reward per step", "", 4),
    "lr": ("learning rate", "", 6),
    "action_std": ("action std", "", 3),
    "kl": ("KL", "", 5),
    "push_scale": ("push scale", "", 2),
    "torque_assist": ("torque assist β", "", 3),
}


class TrainingView:
    """Serve a page of the first ``cfg.worlds`` worlds of ``sim`` while training.

    Use :meth:`wrap` on the collector's policy, :meth:`publish` after each logged iteration and :meth:`close` at the
    end. ``fps``: frames drawn per second at most.
    """

    def __init__(self, cfg: ViewerConfig, sim, fps: float = 30.0):
        cfg.validate()
        self.cfg = cfg
        self.stream = PoseStream(sim, min(cfg.worlds, sim.num_worlds), cfg.every)
        self.server = start_server(cfg.host, cfg.port, option="viewer.port")
        self.controls = WorldControls(self.server, self.stream.worlds)
        self.panel = MetricsPanel(self.server, "training: waiting for the first logged iteration…")
        self.scene = RobotScene(self.server, body_meshes(sim.mj_model), self.stream.worlds)
        self._pelvis = sim.mj_model.body(robot.BASE_BODY).id
        self.frames = 0
        self._stop = threading.Event()
        self._period = 1.0 / fps
        self._thread = threading.Thread(target=self._draw_loop, name="tocabi-viewer", daemon=True)
        self._thread.start()
        print(f"viewer: {self.stream.worlds} training worlds live at {page_url(cfg.host, self.server.get_port())}",
              flush=True)

    def wrap(self, policy) -> TappedPolicy:
        """The collector's policy: ``policy``, ticking the stream once per policy step."""
        return TappedPolicy(policy, self.stream)

    def publish(self, iteration: int, metrics: dict) -> None:
        """Show a logged iteration's metrics (host values)."""
        self.panel.show({"iteration": iteration, **metrics}, TRAINING_ROWS, title="training")

    def _draw_loop(self) -> None:
        while not self._stop.wait(self._period):
            try:
                self.draw()
            except Exception as err:  # noqa: BLE001 - the page must never stop the training
                print(f"viewer: drawing failed ({type(err).__name__}: {err}); the page stops updating", flush=True)
                return

    def draw(self) -> bool:
        """Draw the newest completed copy, if there is a new one; whether one was drawn."""
        frame = self.stream.latest()
        if frame is None:
            return False
        self.scene.update(frame.xpos, frame.xquat)
        sel = min(self.controls.selected, self.stream.worlds - 1)
        self.scene.select(sel)
        if self.controls.follow.value:
            follow(self.server, self.scene.shown_position(sel, frame.xpos[sel, self._pelvis]))
        self.frames += 1
        return True

    def close(self) -> None:
        """Stop drawing and serving."""
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.server.stop()
