"""The live loop of a loaded policy on a web page (``recipes/play.py --viewer``).

The policy acts deterministically on every world (the gait test's setting: fallen robots lie where they fell until
**reset**), the page shows up to :data:`MAX_SHOWN` of them, and the GUI changes the command, pauses, single-steps,
pushes the selected robot (a velocity kick written into its pelvis's velocity, the same change of momentum as the
env's pushes) and resets. The gait metrics since the last reset (or command change) and the selected robot's knee
trace are drawn beside the scene. The loop runs the simulation as fast as it can up to real time, and sends at most
``fps`` frames a second, so a slow machine shows a slower walk, not a stuttering one.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from .. import robot
from .config import MAX_SHOWN
from .controls import PlayControls
from .geometry import body_meshes
from .overlays import GAIT_ROWS, KneeTrace, MetricsPanel
from .scene import RobotScene, follow

__all__ = ["LivePage", "MAX_SHOWN"]


class LivePage:
    """A policy, its env and the page that shows them.

    Args:
        env: the policy's env (e.g. :func:`~tocabi_torchrl.evaluation.record.load_policy`'s, running statistics
            frozen); its base env's ``command``, ``sim`` and ``dt`` are used.
        actor: the policy (a TensorDict module reading the env's observation).
        server: a running ``viser.ViserServer`` (:func:`~.server.start_server`).
        command: the first (vx, vy) [m/s].
        fps: frames sent per second at most.
        real_time: never run the simulation faster than real time.
    """

    def __init__(self, env, actor, server, command: tuple[float, float] = (0.5, 0.0), fps: float = 30.0,
                 real_time: bool = True):
        from ..evaluation.record import KNEES, GaitMetrics

        self.env, self.actor, self.server = env, actor, server
        self.base = env.base_env
        self.sim = self.base.sim
        self.dt, self.fps, self.real_time = float(self.base.dt), float(fps), real_time
        self.shown = min(int(self.sim.num_worlds), MAX_SHOWN)
        self._knees, self._metrics_cls = list(KNEES), GaitMetrics
        self._pelvis = self.sim.mj_model.body(robot.BASE_BODY).id
        self.controls = PlayControls(server, self.shown, command)
        self.metrics_panel = MetricsPanel(server)
        self.knee_trace = KneeTrace(server, self.dt)
        self._traced = 0  # the world the knee trace holds
        self.scene = RobotScene(server, body_meshes(self.sim.mj_model), self.shown)
        self.scene.select(0)
        self.steps = 0  # policy steps since the last reset
        self.total_steps = self.frames = 0  # policy steps and frames sent since the start
        self._command = None
        self._lock = threading.Lock()  # held while the env steps, so readers (tests, tools) see whole steps
        self._reset()

    # -------------------------------------------------------------------------------------------- env side
    def _reset(self) -> None:
        self.base.command.hold(*self.controls.command)
        self._command = self.controls.command
        with torch.no_grad():
            self.td = self.env.reset()
        self._restart_metrics()

    def _restart_metrics(self) -> None:
        self.metrics = self._metrics_cls(self.td["base_pos"], self._command, self.dt)
        self.metrics_t0 = self.steps
        self.knee_trace.clear()

    def _apply(self) -> int:
        """Apply the page's requests; returns how many single steps it asked for."""
        req = self.controls.take()
        if req.reset:
            self.steps = 0
            self._reset()
        if self.controls.command != self._command:
            self._command = self.controls.command
            self.base.command.hold(*self._command)
            self._restart_metrics()  # the metrics measure tracking of one command
        for world, vx, vy in req.pushes:
            # The pelvis's free joint: qvel[:, 0:3] is its linear velocity in the world frame. Writing it is a kick
            # of the whole robot's momentum on the next step (both backends take written state).
            self.sim.qvel[world, 0] += vx
            self.sim.qvel[world, 1] += vy
        return req.steps

    def step(self) -> None:
        """One policy step of every world, accounted in the gait metrics and the selected robot's knee trace."""
        with self._lock, torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            td = self.env.step(self.actor(self.td))
            nxt = td["next"]
            alive = self.metrics.update(nxt)
            w = self.controls.selected
            knees = torch.where(alive[w], nxt["joint_pos"][w, self._knees], torch.nan)
            ref = nxt["ref_joint_pos"][w, self._knees]
            self.td = step_mdp(td)
            self.steps += 1
            self.total_steps += 1
        if w != self._traced:  # one robot's trace: another robot's knees would continue its line
            self.knee_trace.clear()
            self._traced = w
        self.knee_trace.append((self.steps - self.metrics_t0) * self.dt, knees.cpu().numpy(), ref.cpu().numpy())

    # -------------------------------------------------------------------------------------------- page side
    def draw(self) -> None:
        """Send the shown worlds' poses (and the selection, and the camera when following)."""
        w = self.shown
        xpos = self.sim.xpos[:w].detach().cpu().numpy()
        xquat = self.sim.xquat[:w].detach().cpu().numpy()
        self.scene.update(xpos, xquat)
        self.frames += 1
        sel = self.controls.selected
        self.scene.select(sel)
        if self.controls.follow.value:
            follow(self.server, self.scene.shown_position(sel, xpos[sel, self._pelvis]))

    def show_metrics(self) -> None:
        """Refresh the gait metrics and the knee chart."""
        summary = self.metrics.summary((self.steps - self.metrics_t0) * self.dt)
        summary["command"] = f"({self._command[0]:+.2f}, {self._command[1]:+.2f}) m/s"
        rows = {"command": ("command", "", 2), **GAIT_ROWS}
        self.metrics_panel.show(summary, rows, title=f"gait test, {self.sim.num_worlds} robots")
        self.knee_trace.draw()

    def run(self, stop: threading.Event | None = None, metrics_every_s: float = 0.5) -> None:
        """Step and draw until ``stop`` is set (or forever; Ctrl-C ends it)."""
        stop = stop or threading.Event()
        frame_s = 1.0 / self.fps
        next_frame = next_metrics = time.perf_counter()
        sim_clock = time.perf_counter()
        while not stop.is_set():
            single = self._apply()
            if not self.controls.paused or single:
                for _ in range(single or 1):
                    self.step()
                sim_clock += self.dt
            now = time.perf_counter()
            if now >= next_frame:
                self.draw()
                # A fixed cadence: "now + frame_s" would add each loop's overshoot to every frame (27 fps, not 30).
                next_frame += frame_s
                if next_frame < now - frame_s:  # more than a frame behind (a slow machine): skip, never burst
                    next_frame = now + frame_s
            if now >= next_metrics:
                self.show_metrics()
                next_metrics = now + metrics_every_s
            if self.controls.paused and not single:
                time.sleep(0.01)
                sim_clock = time.perf_counter()
            elif self.real_time:
                ahead = sim_clock - time.perf_counter()
                if ahead > 0:
                    time.sleep(ahead)
                else:
                    sim_clock = max(sim_clock, time.perf_counter() - 0.1)  # a slow machine does not catch up later

    def body_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """(W, nbody, 3) and (W, nbody, 4) of the shown worlds (what :meth:`draw` sends)."""
        with self._lock:
            return self.sim.xpos[:self.shown].cpu().numpy(), self.sim.xquat[:self.shown].cpu().numpy()


def serve_policy(path, num_envs: int = 64, device: str = "auto", host: str = "127.0.0.1", port: int = 8080,
                 command: tuple[float, float] = (0.5, 0.0), backend: str | None = None,
                 stop: threading.Event | None = None, ready=None) -> None:
    """Load the checkpoint or run folder ``path`` with ``num_envs`` worlds and serve its live page on ``host``:
    ``port`` until Ctrl-C (or ``stop``). Prints the URL. ``backend`` replaces the checkpoint's ``env.sim.backend``
    (``"mujoco"``: C MuJoCo on the CPU). ``ready``: called with the :class:`LivePage` once the page is up. Ctrl-C
    stops the page and raises ``KeyboardInterrupt`` on to the caller (a command line exits 130 on it). However it
    ends, the page stops and the env is closed (the CPU backend's worker threads go with it)."""
    from ..evaluation.record import load_policy
    from ..rl.trainer import resolve_device
    from .extra import require_viser
    from .server import check_address, page_url, start_server

    require_viser()  # before minutes of loading: the missing extra and a bad address are said at once
    check_address(host, port)
    policy = load_policy(path, num_envs, resolve_device(device), command=command, backend=backend)
    try:
        server = start_server(host, port)
        try:
            live = LivePage(policy.env, policy.actor, server, command=command)
            print(f"viewer: {policy.path} with {num_envs} robots on {policy.env.device} "
                  f"({live.base.backend} backend); open {page_url(host, server.get_port())} "
                  "(Ctrl-C stops)", flush=True)
            if ready is not None:
                ready(live)
            live.run(stop)
        finally:
            server.stop()
    finally:
        # The simulator's worker threads outlive the env's last reference (they held on after a gc.collect()), so a
        # caller that serves again, or goes on with other work, would keep one idle pool per page served.
        policy.env.close(raise_if_closed=False)
