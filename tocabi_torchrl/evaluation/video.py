"""Rendering of recorded joint states, offscreen by MuJoCo: the gait test's video (a few robots side by side, a
camera tracking each) and the experiments' still frames and time-lapse images from a fixed camera position
(TocabiLab's camera at (2, 6, 2.5) m, looking at the pelvis).

MuJoCo is asked to render at most until its first OpenGL failure in a process (a renderer that cannot start or
render): after that every render function raises :class:`RenderingUnavailable` at once (a failed GLFW start, MuJoCo's
default without ``MUJOCO_GL``, can abort the whole process when tried again), and so it does when ``MUJOCO_GL`` turns
OpenGL off
(:func:`~tocabi_torchrl.render_gl.choose_gl_backend` on a machine without a display or EGL).
:func:`rendering_unavailable` says so before trying."""

from __future__ import annotations

import functools
import time
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from .. import robot
from ..atomic import atomic_write_bytes
from ..render_gl import offscreen_unavailable

__all__ = ["CAMERA_POS", "SHADOW_BUDGET_S", "RenderingUnavailable", "free_camera", "label_image", "render_stills",
           "render_timelapse", "render_video", "rendering_unavailable", "save_strip"]

#: TocabiLab's camera for the gait figures [m], world frame: to the robot's left, ahead of the start, above.
CAMERA_POS = (2.0, 6.0, 2.5)

#: Seconds a video tile may take with shadows before the video is rendered without them. On a machine without a GPU,
#: EGL renders with Mesa's software rasteriser (llvmpipe): ~0.13 s per 480x360 tile with MuJoCo's 4096x4096 shadow
#: map, ~0.02 s without (a smaller map saves little), so shadows took 5/6 of play.py's time on a CPU (8 s at 31 fps,
#: 4 robots: 1000 tiles, over two minutes). A GPU draws a tile in about a millisecond either way.
SHADOW_BUDGET_S = 0.04

#: The first OpenGL failure in this process ("<type>: <message>"); MuJoCo is not asked to render again after it.
_failure: str | None = None


class RenderingUnavailable(RuntimeError):
    """Nothing is rendered in this process: ``MUJOCO_GL`` turns OpenGL off, or an earlier render failed."""


def rendering_unavailable() -> str | None:
    """Why the render functions would refuse in this process (with the fix where known), or ``None``: they try."""
    if _failure is not None:
        return f"an earlier render in this process failed ({_failure}); MuJoCo is not asked again"
    return offscreen_unavailable()


def _guarded(render):
    """``render`` refusing at once when :func:`rendering_unavailable`."""

    @functools.wraps(render)
    def guarded(*args, **kwargs):
        reason = rendering_unavailable()
        if reason is not None:
            raise RenderingUnavailable(reason)
        return render(*args, **kwargs)

    return guarded


def _gl(call, *args, **kwargs):
    """``call(*args, **kwargs)`` on MuJoCo's OpenGL side (starting a renderer, or its ``render``), remembering its
    failure (let through). Failures elsewhere (a bad camera, a callback, the video writer) leave rendering on: they
    say nothing about OpenGL, and the next call with good arguments renders; so does MuJoCo's own refusal of bad
    arguments (a ``ValueError`` or ``TypeError``, e.g. an image larger than the model's offscreen buffer), raised
    before any OpenGL context exists."""
    global _failure
    try:
        return call(*args, **kwargs)
    except (ValueError, TypeError):
        raise
    except Exception as err:
        _failure = f"{type(err).__name__}: {err}"
        raise


@_guarded
def render_video(model, qpos: np.ndarray, fps: float, out: Path, width: int = 480, height: int = 360,
                  progress: bool = True, mocap_pos: np.ndarray | None = None, shadows: bool | None = None) -> Path:
    """Render (T, k, nq) joint states of k robots side by side (one camera each) into ``out/walk.mp4``, or
    ``out/walk.gif`` without an mp4 writer, at ``fps`` frames per second, and its middle frame into
    ``out/walk_frame.png``; each file is written atomically. Returns the video's path.

    ``mocap_pos``: (k, nmocap, 3) positions [m] of the model's mocap bodies in each robot's world (the obstacles of a
    jittered scene, ``sim.world_mocap_pos``); ``None`` shows them where the model puts them. ``shadows``: ``None``
    draws them when a tile takes at most :data:`SHADOW_BUDGET_S` with them (a GPU; not a software renderer)."""
    import imageio.v2 as imageio
    import mujoco

    data = mujoco.MjData(model)
    renderer = _gl(mujoco.Renderer, model, height=height, width=width)
    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_TRACKING
    camera.trackbodyid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, robot.BASE_BODY)
    camera.distance, camera.elevation, camera.azimuth = 3.0, -15.0, 120.0
    option = mujoco.MjvOption()
    option.geomgroup[2] = 0  # hide the translucent collision geoms: show the silhouette

    def tile(q, i):
        data.qpos[:] = q
        if mocap_pos is not None:
            data.mocap_pos[:] = mocap_pos[i]
        mujoco.mj_forward(model, data)
        renderer.update_scene(data, camera, scene_option=option)
        return _gl(renderer.render)

    frames = []
    try:
        if shadows is None:
            shadows = _shadows_in_budget(lambda: tile(qpos[0][0], 0))
        if not shadows:  # scene flags outlive update_scene: set once for every tile
            renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
        desc = "rendering video" + ("" if shadows else " (no shadows: software OpenGL)")
        for step in tqdm(qpos, desc=desc, unit="frame", disable=not progress, leave=False):
            frames.append(np.concatenate([tile(q, i) for i, q in enumerate(step)], axis=1))
    finally:  # its OpenGL context goes too when a frame fails: rendering may go on in this process
        renderer.close()
    # Encoded in memory and then written atomically: a run stopped while encoding (or a full disk) leaves the
    # earlier video whole, not half an mp4 under its name.
    try:
        path, data = out / "walk.mp4", imageio.mimwrite("<bytes>", frames, format=".mp4", fps=fps, macro_block_size=1)
    except Exception:  # no mp4 writer (imageio-ffmpeg, in the `viz` extra): fall back to a gif
        (out / "walk.mp4").unlink(missing_ok=True)  # an earlier test's video would pass for this one's
        path, data = out / "walk.gif", imageio.mimwrite("<bytes>", frames[::2], format=".gif",
                                                        duration=_gif_durations(len(frames[::2]), fps / 2.0))
    atomic_write_bytes(path, data)
    atomic_write_bytes(out / "walk_frame.png", imageio.imwrite("<bytes>", frames[len(frames) // 2], format=".png"))
    return path


def _gif_durations(count: int, fps: float) -> list[int]:
    """How long each of ``count`` GIF frames shows [ms] for them to play at ``fps`` frames per second.

    imageio's GIF writer (Pillow) takes milliseconds, not seconds: a duration of ``2 / fps`` s was read as 0.06 ms
    and stored as 0, which viewers play as fast as they can or at their own default speed. A GIF stores hundredths
    of a second, so each frame shows a multiple of 10 ms, chosen so that the running sum stays on the frames' times
    (15.625 fps: 60 and 70 ms in turn, 64 ms on average) and the video lasts as long as the rollout did.
    """
    ends = np.round(np.arange(1, count + 1) * (100.0 / fps)) * 10  # each frame's end time, in whole 10 ms [ms]
    return np.diff(ends, prepend=0.0).astype(int).tolist()


def _shadows_in_budget(render_tile) -> bool:
    """Whether ``render_tile()`` (one tile, shadows on) takes at most :data:`SHADOW_BUDGET_S`; timed on its second
    call, as the first also compiles the shaders."""
    render_tile()
    start = time.perf_counter()
    render_tile()
    return time.perf_counter() - start <= SHADOW_BUDGET_S


def free_camera(position, lookat):
    """A MuJoCo free camera at ``position`` (3,) [m] looking at ``lookat`` (3,) [m] (world frame)."""
    import mujoco

    position, lookat = np.asarray(position, dtype=float), np.asarray(lookat, dtype=float)
    view = lookat - position
    distance = float(np.linalg.norm(view))
    if distance < 1e-6:
        raise ValueError("the camera position and the point it looks at coincide")
    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_FREE
    camera.lookat[:] = lookat
    camera.distance = distance
    camera.azimuth = float(np.degrees(np.arctan2(view[1], view[0])))
    camera.elevation = float(np.degrees(np.arcsin(view[2] / distance)))
    return camera


def _silhouette_option():
    import mujoco

    option = mujoco.MjvOption()
    option.geomgroup[2] = 0  # hide the translucent collision geoms: show the silhouette
    return option


@_guarded
def render_stills(model, qpos: np.ndarray, camera_pos=CAMERA_POS, lookat=None, width: int = 480,
                  height: int = 360, setup=None, fovy: float | None = None) -> list[np.ndarray]:
    """One (height, width, 3) uint8 image per joint state of (k, nq) ``qpos``, from a free camera at
    ``camera_pos`` looking at ``lookat`` (default: each frame's pelvis). ``setup(data)``: called on the
    ``MjData`` before each frame (e.g. to place a per-world obstacle); ``fovy``: the vertical field of view [deg]
    (default: the model's, 45)."""
    import mujoco

    data = mujoco.MjData(model)
    renderer = _gl(mujoco.Renderer, model, height=height, width=width)
    option = _silhouette_option()
    images = []
    saved_fovy = float(model.vis.global_.fovy)
    try:
        if fovy is not None:
            model.vis.global_.fovy = fovy
        for q in np.atleast_2d(qpos):
            data.qpos[:] = q
            if setup is not None:
                setup(data)
            mujoco.mj_forward(model, data)
            camera = free_camera(camera_pos, q[:3] if lookat is None else lookat)
            renderer.update_scene(data, camera, scene_option=option)
            images.append(_gl(renderer.render).copy())
    finally:
        model.vis.global_.fovy = saved_fovy
        renderer.close()
    return images


@_guarded
def render_timelapse(model, qpos: np.ndarray, camera_pos=CAMERA_POS, lookat=None, width: int = 960,
                     height: int = 480, setup=None, fovy: float | None = None) -> np.ndarray:
    """One image with the robot drawn at every joint state of (k, nq) ``qpos`` (a time-lapse), from a free camera at
    ``camera_pos`` looking at ``lookat`` (default: the middle of the pelvis positions); ``setup``, ``fovy``: as
    :func:`render_stills`."""
    import mujoco

    qpos = np.atleast_2d(qpos)
    data = mujoco.MjData(model)
    renderer = _gl(mujoco.Renderer, model, height=height, width=width,
                   max_geom=max(10000, 2 * model.ngeom * len(qpos)))
    option = _silhouette_option()
    if lookat is None:
        lookat = 0.5 * (qpos[:, :3].min(0) + qpos[:, :3].max(0))
    camera = free_camera(camera_pos, lookat)
    saved_fovy = float(model.vis.global_.fovy)
    try:
        if fovy is not None:
            model.vis.global_.fovy = fovy
        data.qpos[:] = qpos[0]
        if setup is not None:
            setup(data)
        mujoco.mj_forward(model, data)
        renderer.update_scene(data, camera, scene_option=option)
        perturb = mujoco.MjvPerturb()
        for q in qpos[1:]:
            data.qpos[:] = q
            mujoco.mj_forward(model, data)
            # the robot's geoms only: the floor and any obstacle are already in the scene
            mujoco.mjv_addGeoms(model, data, option, perturb, mujoco.mjtCatBit.mjCAT_DYNAMIC, renderer.scene)
        image = _gl(renderer.render).copy()
    finally:
        model.vis.global_.fovy = saved_fovy
        renderer.close()
    return image


def label_image(image: np.ndarray, text: str) -> np.ndarray:
    """``image`` with ``text`` written in its top-left corner (black on a white box)."""
    from PIL import Image, ImageDraw

    picture = Image.fromarray(image)
    draw = ImageDraw.Draw(picture)
    box = draw.textbbox((6, 4), text)
    draw.rectangle((box[0] - 3, box[1] - 2, box[2] + 3, box[3] + 2), fill=(255, 255, 255))
    draw.text((6, 4), text, fill=(0, 0, 0))
    return np.asarray(picture)


def save_strip(images: list[np.ndarray], path: Path) -> Path:
    """Write images of one size side by side (one row) to ``path`` (atomically; format from its suffix, PNG without
    one); a list of rows (lists) stacks the rows, padding short rows with white."""
    import imageio.v2 as imageio

    rows = images if images and isinstance(images[0], list) else [images]
    width = max(len(row) for row in rows)
    blank = np.full_like(rows[0][0], 255)
    strip = np.concatenate([np.concatenate(row + [blank] * (width - len(row)), axis=1) for row in rows], axis=0)
    path = Path(path)
    return atomic_write_bytes(path, imageio.imwrite("<bytes>", strip, format=path.suffix or ".png"))

