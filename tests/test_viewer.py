"""The live web viewer (tocabi_torchrl.viewer, docs/viewer.md): a shipped policy served on the CPU backend and opened
in headless Chromium (the scene shows robots, the vx slider changes the env's command, push changes a robot's
velocity), the training stream's host copies, the geometry, the config section and the missing-extra message."""

from __future__ import annotations

import os
import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from test_runs import recipe

REPO = Path(__file__).resolve().parents[1]
SHIPPED_POLICY = REPO / "assets" / "policies" / "tocabi_walk_ppo.pt"
#: Debian's chromium (apt-get install chromium); playwright's own download is used when that is absent.
SYSTEM_CHROMIUM = "/usr/bin/chromium"


# ------------------------------------------------------------------------------------------------ the browser test
def _chromium_or_skip():
    """(playwright's sync API, executable path or None) or skip, saying what is missing."""
    pytest.importorskip("viser", reason="the viewer extra (viser) is not installed: pip install -e '.[viewer]'")
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (the test extra)")
    if Path(SYSTEM_CHROMIUM).is_file():
        return sync_api, SYSTEM_CHROMIUM
    try:  # playwright's own browser, if `playwright install chromium` fetched it
        with sync_api.sync_playwright() as p:
            if Path(p.chromium.executable_path).is_file():
                return sync_api, None
    except Exception:  # noqa: BLE001 - any failure to find a browser is a reason to skip
        pass
    pytest.skip(f"no Chromium: neither {SYSTEM_CHROMIUM} (apt-get install chromium) nor playwright's "
                "(playwright install chromium)")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait(condition, timeout: float, what: str) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def _robot_pixels(image: np.ndarray) -> int:
    """Pixels of the robots' saturated blue (left side) or red (right side); the ground, the grid and the sky are
    grey or white."""
    rgb = image[..., :3].astype(np.int32)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    blue = (b - r > 40) & (b - g > 20)
    red = (r - b > 40) & (r - g > 30)
    return int((blue | red).sum())


def _screenshot(page, path: Path) -> np.ndarray:
    from PIL import Image  # matplotlib's dependency, in the test extra

    page.screenshot(path=str(path))
    return np.asarray(Image.open(path).convert("RGB"))


@pytest.mark.slow
@pytest.mark.skipif(not SHIPPED_POLICY.is_file(), reason="shipped policy not present")
def test_the_page_shows_robots_and_its_slider_and_push_reach_the_env(tmp_path):
    sync_api, executable = _chromium_or_skip()
    from tocabi_torchrl.viewer.play import serve_policy

    port, stop, started = _free_port(), threading.Event(), []
    server = threading.Thread(target=serve_policy, daemon=True, kwargs=dict(
        path=SHIPPED_POLICY, num_envs=4, device="cpu", host="127.0.0.1", port=port, backend="mujoco", stop=stop,
        ready=started.append))
    server.start()
    try:
        _wait(lambda: started, 120, "the viewer to load the policy and serve its page")
        live = started[0]
        assert live.sim.__class__.__name__ == "MujocoSim", "the CPU backend (C MuJoCo) was asked for"
        # The live loop steps the policy as fast as it can up to real time: on a 2-core machine a whole core (it
        # does not reach real time). Paused while Chromium starts and draws its first frames in software WebGL,
        # the slowest part of the test, it leaves that core to the browser; it runs again for the slider below.
        live.controls.pause.value = True
        url = f"http://127.0.0.1:{live.server.get_port()}"
        shots = Path(os.environ.get("TOCABI_VIEWER_SHOTS", tmp_path))
        shots.mkdir(parents=True, exist_ok=True)
        with sync_api.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=executable, headless=True,
                                        args=["--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                                              "--no-sandbox"])
            try:
                page = browser.new_page(viewport={"width": 1280, "height": 800})
                page.goto(url)
                page.wait_for_selector("canvas", timeout=60_000)
                _wait(lambda: len(live.server.get_clients()) == 1, 30, "the page to connect")
                page.get_by_role("button", name="push", exact=True).wait_for(timeout=30_000)
                # The first frames: meshes uploaded, then software WebGL draws them, slowly on a loaded machine.
                # Wait for the robots to appear (or a minute and a half), not for a fixed time.
                deadline = time.monotonic() + 90.0
                while True:
                    for toast in page.locator(".mantine-Notification-closeButton").all():
                        toast.click()  # the "software WebGL" notice covers the scene's corner
                    shown = _screenshot(page, shots / "viewer_live.png")
                    scene_area = shown[160:760, :860]  # left of the control panel, below the notice
                    if _robot_pixels(scene_area) > 800 or time.monotonic() > deadline:
                        break
                    time.sleep(1.0)
                # The same view with the robots hidden: what the ground and the sky alone look like.
                for handle in live.scene.handles:
                    handle.visible = False
                time.sleep(1.5)
                empty = _screenshot(page, tmp_path / "viewer_no_robots.png")[160:760, :860]
                for handle in live.scene.handles:
                    handle.visible = True
                with_robots, without = _robot_pixels(scene_area), _robot_pixels(empty)
                assert with_robots > 800 and without < with_robots / 20, (
                    f"robot-coloured pixels: {with_robots} with the robots, {without} without them")
                assert len(live.scene.handles) == len(live.scene.meshes) > 10  # one batched mesh per body

                # The loop steps the policy again once unpaused (the page's checkbox follows the server's value).
                steps = live.total_steps
                live.controls.pause.value = False
                _wait(lambda: live.total_steps >= steps + 10, 30, "the live loop to step the policy")

                # The vx slider: keyboard on its thumb, as a user's arrows move it; the env's command follows.
                base = live.base
                before = base.command.value.clone()
                label = page.locator("label", has_text="vx [m/")
                thumb = page.locator(f"[id='{label.get_attribute('for')}'] [role=slider]")
                thumb.focus()
                for _ in range(4):
                    thumb.press("ArrowRight")  # 4 × 0.05 m/s
                assert torch.allclose(before, torch.tensor([0.5, 0.0]))  # --vx's default
                target = torch.tensor([0.7, 0.0]).expand(4, 2)
                _wait(lambda: torch.allclose(base.command.value, target, atol=1e-5), 20,
                      f"the env's command to become (0.7, 0) (it is {base.command.value.tolist()})")
                assert thumb.get_attribute("aria-valuenow") == "0.7"

                # Pause (so only the push moves anything), then push robot 0 along +y and take one step.
                page.locator("label", has_text="pause").click()
                _wait(lambda: live.controls.paused, 20, "the pause checkbox")
                time.sleep(0.3)
                vel_before = live.sim.qvel[:, :2].clone()
                steps = live.steps
                page.get_by_role("button", name="push", exact=True).click()
                _wait(lambda: (live.sim.qvel[0, 1] - vel_before[0, 1]).abs() > 0.4, 20,
                      "robot 0's lateral velocity to jump")
                kick = live.sim.qvel[:, :2] - vel_before
                assert torch.allclose(kick[0], torch.tensor([0.0, 0.5]), atol=1e-4), kick  # 0.5 m/s at 90 degrees
                assert kick[1:].abs().max() == 0, "only the selected robot is pushed"
                page.get_by_role("button", name="step", exact=True).click()
                _wait(lambda: live.steps == steps + 1, 20, "one single step")
                after = live.sim.qvel[:, 1] - vel_before[:, 1]
                assert after[0] > 0.3 and after[1:].abs().max() < 0.2, after  # the kick survives the step
                _screenshot(page, shots / "viewer_pushed.png")
            finally:
                browser.close()
    finally:
        stop.set()
        server.join(timeout=30)


# ------------------------------------------------------------------------------------------------ the stream
class _FakeSim:
    def __init__(self, n: int = 5, nbody: int = 3):
        self.xpos = torch.randn(n, nbody, 3)
        self.xquat = torch.nn.functional.normalize(torch.randn(n, nbody, 4), dim=-1)
        self.num_worlds = n


def test_the_stream_copies_the_first_worlds_every_k_ticks_on_the_cpu():
    from tocabi_torchrl.viewer.stream import PoseStream

    sim = _FakeSim()
    stream = PoseStream(sim, worlds=3, every=2)
    assert stream.latest() is None
    stream.tick()
    assert stream.latest() is None, "one tick of two: no copy yet"
    stream.tick()
    frame = stream.latest()
    assert frame is not None and frame.index == 1 and frame.tick == 2
    np.testing.assert_array_equal(frame.xpos, sim.xpos[:3].numpy())
    np.testing.assert_array_equal(frame.xquat, sim.xquat[:3].numpy())
    taken = sim.xpos[:3].numpy().copy()
    sim.xpos += 1.0  # the simulator moves on: the frame taken is the viewer's own
    np.testing.assert_array_equal(frame.xpos, taken)
    assert stream.latest() is None, "a frame is returned once"
    stream.tick(), stream.tick()
    np.testing.assert_array_equal(stream.latest().xpos, sim.xpos[:3].numpy())
    assert stream.copies == 2 and stream.skipped == 0


def test_the_stream_refuses_more_than_64_worlds_and_a_zero_period():
    from tocabi_torchrl.viewer.stream import PoseStream

    with pytest.raises(ValueError, match="1 to 64 worlds"):
        PoseStream(_FakeSim(70), worlds=65, every=1)
    with pytest.raises(ValueError, match="every must be >= 1"):
        PoseStream(_FakeSim(), worlds=2, every=0)
    assert PoseStream(_FakeSim(2), worlds=8, every=1).worlds == 2  # never more than the simulator has


def test_the_tapped_policy_ticks_once_per_call_and_acts_as_the_policy():
    from tensordict import TensorDict
    from tensordict.nn import TensorDictModule

    from tocabi_torchrl.viewer.stream import PoseStream, TappedPolicy

    policy = TensorDictModule(torch.nn.Linear(4, 2), in_keys=["observation"], out_keys=["action"])
    stream = PoseStream(_FakeSim(), worlds=2, every=3)
    tapped = TappedPolicy(policy, stream)
    td = TensorDict({"observation": torch.randn(5, 4)}, batch_size=[5])
    for _ in range(3):
        out = tapped(td.clone())
    assert stream.ticks == 3 and stream.copies == 1
    torch.testing.assert_close(out["action"], policy(td.clone())["action"])
    assert list(tapped.parameters()) == list(policy.parameters())


def _record_live_views(monkeypatch) -> list:
    """Make training runs start their live page through ``TrainingView`` as usual, keeping each view in the list
    returned, for the test to inspect."""
    from tocabi_torchrl.rl import trainer
    from tocabi_torchrl.viewer.training import TrainingView

    views = []

    def live_view(cfg, env):
        views.append(TrainingView(cfg.viewer, env.base_env.sim))
        return views[-1]

    monkeypatch.setattr(trainer, "_live_view", live_view)
    return views


@pytest.mark.slow
def test_a_training_run_with_the_viewer_streams_its_worlds_and_shows_its_metrics(tmp_path, monkeypatch):
    pytest.importorskip("viser", reason="the viewer extra (viser) is not installed")
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.rl import trainer

    views = _record_live_views(monkeypatch)
    cfg = preset_config("cpu_smoke", device="cpu", total_env_steps=8 * 16 * 2, eval_at_end=False, progress_bar=False,
                        run_dir=str(tmp_path), name="viewer_run")
    cfg.viewer.enabled, cfg.viewer.port, cfg.viewer.worlds, cfg.viewer.every = True, _free_port(), 4, 5
    result = trainer.train(cfg)
    (view,) = views
    assert result.iterations == 2 and view.stream.worlds == 4
    # one tick per collected policy step, and the collector's one call of the policy as it is built
    assert view.stream.ticks in (2 * 16, 2 * 16 + 1), view.stream.ticks
    assert view.stream.copies == view.stream.ticks // 5
    assert view.frames > 0 or view.stream.latest() is not None  # a copy reached the page's side
    assert "| iteration | 2 |" in view.panel.handle.content
    assert view._stop.is_set(), "closed with the run"


# ------------------------------------------------------------------------------------------------ pieces
def test_the_geometry_draws_the_silhouette_not_the_collision_shells():
    from tocabi_torchrl.robot import load_model
    from tocabi_torchrl.viewer.geometry import COLLISION_GROUP, body_meshes, drawn_geoms

    model = load_model()
    drawn = drawn_geoms(model)
    assert len(drawn) > 15 and not np.isin(model.geom_group[drawn], [COLLISION_GROUP]).any()
    assert (model.geom_rgba[drawn, 3] >= 0.5).all() and (model.geom_type[drawn] != 0).all()  # no plane
    meshes = body_meshes(model)
    assert len({m.body for m in meshes}) == len(meshes), "one mesh per body (TOCABI draws each body in one colour)"
    for m in meshes:
        assert m.vertices.dtype == np.float32 and m.faces.max() < len(m.vertices)
        assert np.abs(m.vertices).max() < 0.6, m.name  # in the body frame: a link is smaller than the robot


def test_world_offsets_spread_the_worlds_on_a_grid():
    from tocabi_torchrl.viewer.scene import world_offsets

    off = world_offsets(64)
    assert off.shape == (64, 3) and len({tuple(o) for o in off}) == 64
    assert np.allclose(off.mean(axis=0), 0) and (off[:, 2] == 0).all()


def test_command_hold_survives_resampling_and_resets():
    from tocabi_torchrl.envs.command import CommandConfig, VelocityCommand

    cmd = VelocityCommand(CommandConfig(), 6, torch.device("cpu"), torch.Generator().manual_seed(0))
    cmd.hold(0.3, -0.1)
    cmd.reset(torch.ones(6, dtype=torch.bool))
    for step in range(2 * cmd.cfg.resample_every):
        cmd.update(torch.full((6,), step))
    assert torch.allclose(cmd.value, torch.tensor([0.3, -0.1]).expand(6, 2))


def test_the_metrics_table_formats_numbers_and_leaves_nan_as_a_dash():
    from tocabi_torchrl.viewer.overlays import metrics_markdown

    text = metrics_markdown({"survival": 0.98765, "knee_rms_rad": float("nan"), "other": 1.0},
                            {"survival": ("survival", "", 3), "knee_rms_rad": ("knee RMS", "rad", 3)})
    assert "| survival | 0.988 |" in text and "| knee RMS | – |" in text and "other" not in text
    small = metrics_markdown({"lr": 3e-5, "seconds": 0.04}, {"lr": ("lr", "", 6), "seconds": ("time", "s", 1)})
    assert "| lr | 3.00e-05 |" in small and "| time | 0.0 s |" in small


def test_the_viewer_section_is_a_resume_safe_documented_part_of_the_run_config():
    from tocabi_torchrl.config import RunConfig, config_from_dict
    from tocabi_torchrl.rl.resume import RESUME_SAFE
    from tocabi_torchrl.viewer.config import ViewerConfig, expand_viewer_flag

    # (every leaf's help text on --help: tests/test_cli.py)
    leaves = {f"viewer.{name}" for name in ViewerConfig.__dataclass_fields__}
    assert leaves <= RESUME_SAFE
    cfg = RunConfig()
    cfg.viewer.worlds = 65
    with pytest.raises(ValueError, match="viewer.worlds"):
        cfg.validate()
    saved = RunConfig().to_dict()
    del saved["viewer"]  # a config written before the section: the viewer stays off
    assert config_from_dict(saved).viewer == ViewerConfig()
    assert expand_viewer_flag(["--viewer", "--viewer.port", "9000"]) == [
        "--viewer.enabled", "true", "--viewer.port", "9000"]


@pytest.mark.parametrize("name", ["play", "ppo_walk"])
def test_a_missing_viewer_extra_names_the_install_command(name, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "viser", None)  # import viser now raises ImportError
    argv = (["--policy", "ppo", "--viewer", "--device", "cpu"] if name == "play" else
            ["--viewer", "--device", "cpu", "--preset", "cpu_smoke"])
    with pytest.raises(SystemExit) as exc:
        recipe(name).main(argv)
    message = str(exc.value.code)
    assert message.startswith("error: the live viewer needs the 'viewer' extra (viser)"), message
    assert 'pip install -e ".[viewer]"' in message


@pytest.mark.parametrize("name", ["play", "ppo_walk"])
def test_a_viewer_address_it_cannot_serve_on_is_said_before_anything_is_loaded(name, monkeypatch):
    # Checked only when the server started: after the policy was loaded or the training env built (kernel
    # compilation on a GPU).
    pytest.importorskip("viser", reason="the viewer extra (viser) is not installed: pip install -e '.[viewer]'")
    from tocabi_torchrl.evaluation import record
    from tocabi_torchrl.rl import trainer

    def loaded(*args, **kwargs):
        raise AssertionError("loaded before the address was checked")

    monkeypatch.setattr(record, "load_policy", loaded)
    monkeypatch.setattr(trainer, "build_env", loaded)
    argv = (["--policy", "ppo", "--viewer", "--device", "cpu"] if name == "play" else
            ["--viewer", "--device", "cpu", "--preset", "cpu_smoke"])
    with pytest.raises(SystemExit) as exc:
        recipe(name).main([*argv, "--viewer.host" if name == "ppo_walk" else "--viewer_host", "10.9.9.9"])
    assert "the viewer cannot serve on host '10.9.9.9'" in str(exc.value.code), exc.value.code


def test_a_host_is_served_when_any_of_its_addresses_binds(monkeypatch):
    # The server binds every address a name resolves to and skips those it cannot; the check tried the first only
    # (localhost resolving to ::1 first on a machine without IPv6 was refused).
    from tocabi_torchrl.viewer import server

    foreign = (socket.AF_INET, socket.SOCK_STREAM, 6, "", ("10.9.9.9", 0))
    local = (socket.AF_INET, socket.SOCK_STREAM, 6, "", ("127.0.0.1", 0))
    monkeypatch.setattr(server.socket, "getaddrinfo", lambda *a, **k: [foreign, local])
    server.check_address("both.example", 8080)
    monkeypatch.setattr(server.socket, "getaddrinfo", lambda *a, **k: [foreign])
    with pytest.raises(ValueError, match="cannot serve on host 'both.example'"):
        server.check_address("both.example", 8080)


def test_the_page_url_brackets_an_ipv6_address(monkeypatch):
    # "http://::1:8080" reads as host "" and a bad port; a browser needs "http://[::1]:8080".
    import doctest

    from tocabi_torchrl.viewer import server

    runner = doctest.DocTestRunner()
    for test in doctest.DocTestFinder().find(server.page_url, globs={"page_url": server.page_url}):
        runner.run(test)
    assert runner.failures == 0 and runner.tries == 1
    assert server.page_url("fe80::1", 9) == "http://[fe80::1]:9"
    monkeypatch.setattr(server.socket, "gethostname", lambda: "robot-lab")
    assert server.page_url("::", 8080) == "http://robot-lab:8080"


def test_policy_names_a_shipped_policy_or_says_which_there_are(tmp_path):
    from tocabi_torchrl.viewer.policy_source import resolve_policy

    assert resolve_policy("ppo") == resolve_policy("tocabi_walk_ppo") == SHIPPED_POLICY
    assert resolve_policy("ppo.onnx").suffix == ".onnx"
    assert resolve_policy(tmp_path) == tmp_path  # a run folder as given
    with pytest.raises(ValueError, match="shipped ones are .*ppo"):
        resolve_policy("no_such_policy")


def test_a_bad_port_names_the_option_that_set_it_and_an_empty_policy_is_refused():
    # The port error said "viewer port" whichever of --viewer_port and the config's viewer.port set it; "" was
    # the current folder, looked up as a run ("checkpoint not found: ./latest.pt").
    from tocabi_torchrl.viewer.policy_source import resolve_policy
    from tocabi_torchrl.viewer.server import check_address

    with pytest.raises(ValueError, match=r"^--viewer_port must be an int in \[0, 65535\]"):
        check_address("127.0.0.1", 70000)
    with pytest.raises(ValueError, match=r"^viewer\.port must be an int in \[0, 65535\]"):
        check_address("127.0.0.1", -1, "viewer.port")
    for empty in ("", "  "):
        with pytest.raises(ValueError, match="--policy is empty: give a shipped policy"):
            resolve_policy(empty)


# ------------------------------------------------------------------------------------------------ exported policies
ONNX_POLICY = REPO / "assets" / "policies" / "tocabi_walk_ppo.onnx"


@pytest.mark.skipif(not ONNX_POLICY.is_file(), reason="shipped ONNX policy not present")
def test_the_exported_policy_driver_draws_every_control_period_on_the_page():
    pytest.importorskip("viser", reason="the viewer extra (viser) is not installed")
    pytest.importorskip("onnxruntime", reason="the export extra (onnxruntime) is not installed")
    from tocabi_torchrl.runtime.mujoco_driver import run_sim2sim
    from tocabi_torchrl.viewer.exported import ExportedWatch, contract_of
    from tocabi_torchrl.viewer.server import start_server

    server = start_server("127.0.0.1", _free_port())
    try:
        watch = ExportedWatch(server, dt=0.004, fps=1e6, real_time=False)  # draw every period, no pacing
        seen = []

        def on_step(step, model, datas):
            watch(step, model, datas)
            seen.append((step, np.stack([d.xpos for d in datas])))

        run_sim2sim(contract_of(ONNX_POLICY), seconds=0.02, num_robots=2, on_step=on_step)
        assert [s for s, _ in seen] == list(range(5)) and watch.frames == 5
        last = seen[-1][1]
        mesh = watch.scene.meshes[0]
        np.testing.assert_allclose(watch.scene.handles[0].batched_positions,
                                   last[:, mesh.body] + watch.scene.offsets, atol=1e-6)
    finally:
        server.stop()


@pytest.mark.skipif(not ONNX_POLICY.is_file(), reason="shipped ONNX policy not present")
def test_play_viewer_of_an_onnx_policy_runs_the_torch_free_driver(capsys):
    pytest.importorskip("viser", reason="the viewer extra (viser) is not installed")
    pytest.importorskip("onnxruntime", reason="the export extra (onnxruntime) is not installed")
    recipe("play").main(["--policy", "ppo.onnx", "--viewer", "--num_envs", "2", "--seconds", "0.02",
                         "--viewer_port", str(_free_port())])
    out = capsys.readouterr().out
    assert "viewer: 2 robots of" in out and '"survival"' in out  # the page was served, then sim2sim's metrics


@pytest.mark.skipif(not ONNX_POLICY.is_file(), reason="shipped ONNX policy not present")
def test_play_viewer_of_a_renamed_onnx_runs_that_file_and_checks_it_before_serving(tmp_path, monkeypatch, capsys):
    # A renamed pair's contract still records the old .onnx: the old file of that name ran instead of the one
    # named, and the page was served (its URL printed) before a missing or wrong .onnx was found.
    pytest.importorskip("onnxruntime", reason="the export extra (onnxruntime) is not installed")
    import shutil

    import tocabi_torchrl.viewer.server as server

    shutil.copy(ONNX_POLICY.with_suffix(".json"), tmp_path / "mine.json")
    shutil.copy(REPO / "assets" / "policies" / "tocabi_walk_torque.onnx", tmp_path / "mine.onnx")  # not ppo's
    shutil.copy(ONNX_POLICY, tmp_path / ONNX_POLICY.name)  # the recorded name, holding the contract's policy

    def refuse(*args, **kwargs):
        raise AssertionError("the page was served before the policy was checked")

    monkeypatch.setattr(server, "start_server", refuse)
    with pytest.raises(SystemExit) as info:
        recipe("play").main(["--checkpoint", str(tmp_path / "mine.onnx"), "--viewer", "--num_envs", "1",
                             "--seconds", "0.02", "--viewer_port", "0"])
    assert "mine.onnx does not match the sha256" in str(info.value.code)
    assert "viewer:" not in capsys.readouterr().out


class _Camera:
    """viser's camera handle as it behaves: setting the position moves look_at along with it."""

    def __init__(self):
        self._position, self._look_at = np.array([-3.0, -3.0, 2.0]), np.array([0.0, 0.0, 0.6])

    @property
    def position(self):
        return self._position

    @position.setter
    def position(self, value):
        value = np.asarray(value, np.float64)
        self._look_at = self._look_at + (value - self._position)
        self._position = value

    @property
    def look_at(self):
        return self._look_at

    @look_at.setter
    def look_at(self, value):
        self._look_at = np.asarray(value, np.float64)


def test_camera_follow_looks_at_the_robot_and_a_world_out_of_range_is_clamped():
    # follow() set look_at before the position, whose setter moved look_at again: the view flipped between two wrong
    # ones every frame. A world index past the robots (the page's number box sends any) ended the play viewer with
    # an IndexError; a --vx outside the slider's range was viser's error after the model had loaded.
    import contextlib
    from types import SimpleNamespace

    pytest.importorskip("viser", reason="the viewer extra (viser) is not installed: pip install -e '.[viewer]'")
    from tocabi_torchrl.viewer.controls import PlayControls
    from tocabi_torchrl.viewer.scene import follow
    from tocabi_torchrl.viewer.server import start_server

    client = SimpleNamespace(camera=_Camera(), atomic=contextlib.nullcontext)
    server = SimpleNamespace(get_clients=lambda: {0: client})
    target = np.array([1.5, -0.5, 0.9])
    for _ in range(3):
        follow(server, target)
        np.testing.assert_allclose(client.camera.look_at, target)
        np.testing.assert_allclose(client.camera.position - client.camera.look_at, [-3.0, -3.0, 1.4])
    page = start_server("127.0.0.1", 0)
    try:
        controls = PlayControls(page, 4, command=(2.0, 0.0))
        assert controls.vx.value == 2.0 and controls.vx.max == 2.0
        controls.world.value = 7
        assert controls.selected == 3
    finally:
        page.stop()


@pytest.mark.skipif(not SHIPPED_POLICY.is_file(), reason="shipped policy not present")
def test_selecting_another_robot_starts_its_own_knee_trace():
    # The trace went on with the new robot's knees after the old one's, one line through two robots.
    pytest.importorskip("viser", reason="the viewer extra (viser) is not installed: pip install -e '.[viewer]'")
    from tocabi_torchrl.evaluation.record import load_policy
    from tocabi_torchrl.viewer.play import LivePage
    from tocabi_torchrl.viewer.server import start_server

    policy = load_policy(SHIPPED_POLICY, 2, "cpu", command=(0.5, 0.0), backend="mujoco")  # a name works too
    server = start_server("127.0.0.1", 0)
    try:
        live = LivePage(policy.env, policy.actor, server)
        for _ in range(3):
            live.step()
        assert len(live.knee_trace.t) == 3
        live.controls.world.value = 1
        live.step()
        assert list(live.knee_trace.t) == [pytest.approx(4 * live.dt)]
        live.step()
        assert len(live.knee_trace.t) == 2
    finally:
        server.stop()


@pytest.mark.skipif(not SHIPPED_POLICY.is_file(), reason="shipped policy not present")
def test_the_viewer_banner_names_the_backend_it_runs(capsys):
    # It printed the config's "auto", not the simulator the env resolved it to.
    pytest.importorskip("viser", reason="the viewer extra (viser) is not installed: pip install -e '.[viewer]'")
    import threading

    from tocabi_torchrl.viewer.play import serve_policy

    stop = threading.Event()
    stop.set()  # serve the page, print the banner, stop at once
    serve_policy(SHIPPED_POLICY, num_envs=1, device="cpu", host="127.0.0.1", port=0, stop=stop)
    banner = capsys.readouterr().out
    assert "robots on cpu (mujoco backend)" in banner, banner


@pytest.mark.skipif(not SHIPPED_POLICY.is_file(), reason="shipped policy not present")
def test_serving_a_policy_closes_its_env_when_the_page_stops():
    # The CPU backend's worker threads stayed after serve_policy returned, a garbage collection included.
    pytest.importorskip("viser", reason="the viewer extra (viser) is not installed: pip install -e '.[viewer]'")
    from tocabi_torchrl.viewer.play import serve_policy

    before = set(threading.enumerate())
    pages = []
    stop = threading.Event()
    stop.set()
    serve_policy(SHIPPED_POLICY, num_envs=4, device="cpu", host="127.0.0.1", port=0, stop=stop, ready=pages.append)
    assert len(pages) == 1
    left = [t.name for t in set(threading.enumerate()) - before if t.is_alive()]
    assert not [name for name in left if name.startswith("MujocoSim")], left


def test_a_training_run_that_fails_to_start_stops_its_live_page(tmp_path, monkeypatch):
    # A failure between the page's start and the training loop (here the logger) left it served, its port bound and
    # its drawing thread running in the process.
    pytest.importorskip("viser", reason="the viewer extra (viser) is not installed")
    from tocabi_torchrl.config import preset_config
    from tocabi_torchrl.rl import trainer

    def no_logger(*args, **kwargs):
        raise OSError("cannot write the run's logs")

    views = _record_live_views(monkeypatch)
    monkeypatch.setattr(trainer, "RunLogger", no_logger)
    cfg = preset_config("cpu_smoke", device="cpu", total_env_steps=8 * 16 * 2, eval_at_end=False, progress_bar=False,
                        run_dir=str(tmp_path), name="viewer_fail")
    port = _free_port()
    cfg.viewer.enabled, cfg.viewer.port = True, port
    with pytest.raises(OSError, match="cannot write the run's logs"):
        trainer.train(cfg)
    (view,) = views
    assert view._stop.is_set() and not view._thread.is_alive()

    def port_free() -> bool:
        with socket.socket() as probe:
            try:
                probe.bind(("127.0.0.1", port))
            except OSError:
                return False
        return True

    _wait(port_free, 10.0, "the page's port to be free again")  # viser's server thread ends within its stop()'s 1 s


def test_a_port_with_every_port_after_it_taken_is_refused_not_waited_on():
    # viser moves up from a taken port; past 65535 it fails outside its retry and start_server waited for ever.
    pytest.importorskip("viser", reason="the viewer extra (viser) is not installed")
    from tocabi_torchrl.viewer.server import start_server

    held = []
    for port in (65534, 65535):
        sock = socket.socket()
        try:
            sock.bind(("127.0.0.1", port))
            sock.listen()
            held.append(sock)
        except OSError:  # taken already, as the test needs it
            sock.close()
    outcome = {}

    def start():
        try:
            outcome["server"] = start_server("127.0.0.1", 65534)
        except ValueError as err:
            outcome["error"] = str(err)

    try:
        worker = threading.Thread(target=start, daemon=True)
        worker.start()
        worker.join(timeout=30)
        assert not worker.is_alive(), "start_server waited for a port that cannot come"
        assert "viewer port 65534 is taken and so is every port after it" in outcome.get("error", ""), outcome
    finally:
        if "server" in outcome:
            outcome["server"].stop()
        for sock in held:
            sock.close()


@pytest.mark.parametrize("given", ["file", "folder"])
def test_a_library_recipes_policy_file_is_named_as_such_by_play(given, tmp_path, capsys):
    # train_sb3.py's <out>/policy.pt was "lacks ['iteration', ...] (not a tocabi-torchrl training checkpoint?)" and
    # its --out folder "checkpoint not found: <out>/latest.pt": neither said what the file is or where to look.
    pytest.importorskip("viser", reason="the viewer extra (viser) is not installed")
    from tocabi_torchrl.adapters.policy_file import save_policy

    policy = save_policy(tmp_path / "policy.pt", "sb3", {"mlp.weight": torch.zeros(2, 2)}, {"preset": "default"})
    target = policy if given == "file" else tmp_path
    with pytest.raises(SystemExit) as exc:
        recipe("play").main(["--checkpoint", str(target), "--viewer", "--device", "cpu", "--viewer_port", "0"])
    message = str(exc.value.code)
    assert f"{policy} is the policy file of recipes/train_sb3.py" in message, message
    assert "recipes/ppo_walk.py" in message and "<out>/eval/" in message
    assert "viewer:" not in capsys.readouterr().out  # refused before a page was served


@pytest.mark.skipif(not ONNX_POLICY.is_file(), reason="shipped ONNX policy not present")
def test_the_exported_policy_page_draws_at_most_the_first_max_shown_robots(monkeypatch):
    # A checkpoint's page draws the first 256 robots; an exported policy's drew every robot the driver ran.
    pytest.importorskip("viser", reason="the viewer extra (viser) is not installed")
    pytest.importorskip("onnxruntime", reason="the export extra (onnxruntime) is not installed")
    from tocabi_torchrl.runtime.mujoco_driver import run_sim2sim
    from tocabi_torchrl.viewer import exported
    from tocabi_torchrl.viewer.config import MAX_SHOWN
    from tocabi_torchrl.viewer.play import MAX_SHOWN as PLAY_MAX_SHOWN
    from tocabi_torchrl.viewer.server import start_server

    assert MAX_SHOWN == PLAY_MAX_SHOWN == 256
    monkeypatch.setattr(exported, "MAX_SHOWN", 2)  # 3 robots run, 2 drawn: the cap without simulating 257
    server = start_server("127.0.0.1", _free_port())
    try:
        watch = exported.ExportedWatch(server, dt=0.004, fps=1e6, real_time=False)
        last = []
        run_sim2sim(exported.contract_of(ONNX_POLICY), seconds=0.008, num_robots=3,
                    on_step=lambda step, model, datas: (watch(step, model, datas), last.append(datas)))
        assert watch.scene.num_worlds == 2 and watch.frames == 2
        mesh = watch.scene.meshes[0]
        drawn = np.stack([d.xpos for d in last[-1][:2]])[:, mesh.body] + watch.scene.offsets
        np.testing.assert_allclose(watch.scene.handles[0].batched_positions, drawn, atol=1e-6)
    finally:
        server.stop()
