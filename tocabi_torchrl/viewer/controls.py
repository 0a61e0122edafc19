"""The page's controls. Callbacks run on viser's threads and only record requests; the loop that owns the env
applies them between steps (:meth:`PlayControls.take`), so nothing touches the simulator from two threads."""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field

__all__ = ["PlayControls", "Requests", "WorldControls"]


@dataclass
class Requests:
    """What the user asked for since the last :meth:`PlayControls.take`: ``steps`` single steps, ``reset``, and
    ``pushes`` as (world, vx, vy) velocity kicks [m/s]."""

    steps: int = 0
    reset: bool = False
    pushes: list[tuple[int, float, float]] = field(default_factory=list)


class WorldControls:
    """Pick a world (highlighted, followed by the camera, traced in the overlays) and camera follow."""

    def __init__(self, server, num_worlds: int):
        gui = server.gui
        self.num_worlds = num_worlds
        self.world = gui.add_slider("world", min=0, max=max(num_worlds - 1, 1), step=1, initial_value=0,
                                    disabled=num_worlds < 2, hint="the robot pushes act on, traced and followed")
        self.follow = gui.add_checkbox("camera follow", initial_value=False,
                                       hint="keep the camera on the selected robot")

    @property
    def selected(self) -> int:
        """The picked world, clamped to the worlds there are: the page's number box can send any value (7 of 4
        worlds once ended the play viewer with an IndexError)."""
        return min(max(int(self.world.value), 0), self.num_worlds - 1)


class PlayControls(WorldControls):
    """Command sliders, pause, single step, reset and push (a velocity kick of the selected robot's pelvis).

    Args:
        server: the ``viser.ViserServer``.
        num_worlds: robots on the page.
        command: the initial (vx, vy) [m/s].
        vx_range, vy_range: slider limits [m/s].
    """

    def __init__(self, server, num_worlds: int, command: tuple[float, float] = (0.5, 0.0),
                 vx_range: tuple[float, float] = (-0.5, 1.0), vy_range: tuple[float, float] = (-0.5, 0.5)):
        gui = server.gui
        self._lock = threading.Lock()
        self._requests = Requests()
        # A start command outside the default ranges widens them (--vx 2.0 was an error from viser after the load).
        vx_range = (min(vx_range[0], float(command[0])), max(vx_range[1], float(command[0])))
        vy_range = (min(vy_range[0], float(command[1])), max(vy_range[1], float(command[1])))
        with gui.add_folder("command"):
            self.vx = gui.add_slider("vx [m/s]", min=vx_range[0], max=vx_range[1], step=0.05,
                                     initial_value=float(command[0]))
            self.vy = gui.add_slider("vy [m/s]", min=vy_range[0], max=vy_range[1], step=0.05,
                                     initial_value=float(command[1]))
        with gui.add_folder("simulation"):
            self.pause = gui.add_checkbox("pause", initial_value=False)
            self.step_button = gui.add_button("step", hint="one policy step (while paused)")
            self.reset_button = gui.add_button("reset", hint="restart every robot (and the metrics)")
        with gui.add_folder("robot"):
            super().__init__(server, num_worlds)
            self.push_speed = gui.add_slider("push speed [m/s]", min=0.0, max=2.0, step=0.05, initial_value=0.5)
            self.push_angle = gui.add_slider("push direction [deg]", min=-180, max=180, step=15, initial_value=90,
                                             hint="world frame: 0 is +x (the walking direction at the start), 90 is +y")
            self.push_button = gui.add_button("push", hint="kick the selected robot's pelvis")
        self.step_button.on_click(lambda _: self._add(steps=1))
        self.reset_button.on_click(lambda _: self._add(reset=True))
        self.push_button.on_click(lambda _: self._add(push=True))

    def _add(self, steps: int = 0, reset: bool = False, push: bool = False) -> None:
        with self._lock:
            self._requests.steps += steps
            self._requests.reset |= reset
            if push:
                angle = math.radians(float(self.push_angle.value))
                speed = float(self.push_speed.value)
                self._requests.pushes.append((self.selected, speed * math.cos(angle), speed * math.sin(angle)))

    @property
    def command(self) -> tuple[float, float]:
        """The sliders' (vx, vy) [m/s]."""
        return float(self.vx.value), float(self.vy.value)

    @property
    def paused(self) -> bool:
        return bool(self.pause.value)

    def take(self) -> Requests:
        """The requests since the last call (and forget them)."""
        with self._lock:
            out, self._requests = self._requests, Requests()
        return out
