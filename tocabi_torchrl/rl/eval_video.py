"""The gait test's video: a few robots' recorded joint states rendered offscreen by MuJoCo, side by side."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from .. import robot

__all__ = ["render_video"]


def render_video(model, qpos: np.ndarray, fps: int, out: Path, width: int = 480, height: int = 360,
                  progress: bool = True, mocap_pos: np.ndarray | None = None) -> Path:
    """Render (T, k, nq) joint states of k robots side by side (one camera each) into an mp4 or a gif.

    ``mocap_pos``: (k, nmocap, 3) positions [m] of the model's mocap bodies in each robot's world (the obstacles of a
    jittered scene, ``sim.world_mocap_pos``); ``None`` shows them where the model puts them."""
    import imageio.v2 as imageio
    import mujoco

    data = mujoco.MjData(model)
    renderer = mujoco.Renderer(model, height=height, width=width)
    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_TRACKING
    camera.trackbodyid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, robot.BASE_BODY)
    camera.distance, camera.elevation, camera.azimuth = 3.0, -15.0, 120.0
    option = mujoco.MjvOption()
    option.geomgroup[2] = 0  # hide the translucent collision geoms: show the silhouette
    frames = []
    for step in tqdm(qpos, desc="rendering video", unit="frame", disable=not progress, leave=False):
        tiles = []
        for i, q in enumerate(step):
            data.qpos[:] = q
            if mocap_pos is not None:
                data.mocap_pos[:] = mocap_pos[i]
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, camera, scene_option=option)
            tiles.append(renderer.render())
        frames.append(np.concatenate(tiles, axis=1))
    renderer.close()
    try:
        path = out / "walk.mp4"
        imageio.mimwrite(path, frames, fps=fps, macro_block_size=1)
    except Exception:  # no mp4 writer (imageio-ffmpeg, in the `viz` extra): fall back to a gif
        path.unlink(missing_ok=True)
        path = out / "walk.gif"
        imageio.mimwrite(path, frames[::2], duration=2.0 / fps)
    imageio.imwrite(out / "walk_frame.png", frames[len(frames) // 2])
    return path
