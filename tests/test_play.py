"""recipes/play.py and evaluation: wrapped errors for bad files and too-short runs, outputs of a shipped policy outside
the source tree, the plot titled with the command, progress while rolling out and rendering, a usable --help, a
clear message for an unusable MUJOCO_GL=osmesa, earlier results never overwritten silently, and strict JSON (null for
a metric without a value)."""

from __future__ import annotations

import ctypes.util
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from test_runs import recipe

REPO = Path(__file__).resolve().parents[1]
SHIPPED_POLICY = REPO / "assets" / "policies" / "tocabi_walk_ppo.pt"
needs_policy = pytest.mark.skipif(not SHIPPED_POLICY.is_file(), reason="shipped policy not present")


@pytest.mark.parametrize("kind", ["random", "truncated"])
def test_play_reports_an_unreadable_checkpoint_in_one_line(tmp_path, kind):
    bad = tmp_path / f"{kind}.pt"
    if kind == "random":
        bad.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    else:
        bad.write_bytes(SHIPPED_POLICY.read_bytes()[:5000] if SHIPPED_POLICY.is_file() else b"PK\x03\x04")
    with pytest.raises(SystemExit) as info:
        recipe("play").main(["--checkpoint", str(bad), "--num_envs", "1", "--device", "cpu"])
    assert f"cannot read checkpoint {bad}" in str(info.value.code)


@needs_policy
def test_play_reports_an_out_it_cannot_write_in_one_line(tmp_path, monkeypatch):
    afile = tmp_path / "afile"
    afile.write_text("not a folder")
    with pytest.raises(SystemExit) as info:
        recipe("play").main(["--checkpoint", str(SHIPPED_POLICY), "--num_envs", "1", "--seconds", "0.01",
                             "--video_envs", "0", "--device", "cpu", "--out", str(afile)])
    assert f"error: cannot write the evaluation to {afile}" in str(info.value.code)
    assert afile.read_text() == "not a folder"
    # A folder that cannot be written was found by the first write, after the whole test had run (minutes on a
    # CPU). The probe is made to fail here: these tests may run as root, whom permissions do not stop.
    import tempfile

    from tocabi_torchrl.evaluation import gait_test

    ran = []
    monkeypatch.setattr(gait_test, "evaluate_policy", lambda *a, **k: ran.append(1))

    def refused(*args, dir=None, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(tempfile, "TemporaryFile", refused)
    locked = tmp_path / "locked"
    locked.mkdir()
    with pytest.raises(SystemExit) as info:
        recipe("play").main(["--checkpoint", str(SHIPPED_POLICY), "--num_envs", "1", "--seconds", "0.01",
                             "--video_envs", "0", "--device", "cpu", "--out", str(locked / "eval")])
    assert str(info.value.code).startswith(f"error: cannot write the evaluation to {locked}: Permission denied")
    assert not ran


@needs_policy
def test_play_refuses_seconds_below_one_policy_step(capsys):
    with pytest.raises(SystemExit) as info:
        recipe("play").main(["--checkpoint", str(SHIPPED_POLICY), "--seconds", "0.001", "--device", "cpu"])
    assert "seconds=0.001 is shorter than one policy step (4 ms)" in str(info.value.code)
    # These were said after "results go to ...", a folder that was then never made; the device in Python's words.
    assert "results go to" not in capsys.readouterr().out
    with pytest.raises(SystemExit) as info:
        recipe("play").main(["--checkpoint", str(SHIPPED_POLICY), "--device", "gpu"])
    assert str(info.value.code).startswith("error: unknown device 'gpu'")
    assert "results go to" not in capsys.readouterr().out
    if not torch.cuda.is_available():
        with pytest.raises(SystemExit) as info:
            recipe("play").main(["--checkpoint", str(SHIPPED_POLICY), "--device", "cuda"])
        captured = capsys.readouterr()
        assert info.value.code == 2 and "torch sees no CUDA GPU on this machine; pass --device cpu" in captured.err
        assert "results go to" not in captured.out
    # --backend without --viewer was ignored without a word.
    with pytest.raises(SystemExit) as info:
        recipe("play").main(["--checkpoint", str(SHIPPED_POLICY), "--backend", "warp", "--device", "cpu"])
    assert info.value.code == 2 and "--backend sets the physics of --viewer only" in capsys.readouterr().err
    # The viewer of an exported policy ignored them without a word (it runs the torch-free C MuJoCo driver).
    with pytest.raises(SystemExit) as info:
        recipe("play").main(["--checkpoint", str(SHIPPED_POLICY.with_suffix(".onnx")), "--viewer", "--backend", "warp",
                             "--device", "cpu"])
    assert str(info.value.code).startswith("error: --backend, --device: an exported policy's viewer runs the "
                                           "torch-free")
    # Any live viewer ignored the test's options without a word (--video_envs and --overwrite among them).
    for policy in (SHIPPED_POLICY, SHIPPED_POLICY.with_suffix(".onnx")):
        with pytest.raises(SystemExit) as info:
            recipe("play").main(["--checkpoint", str(policy), "--viewer", "--test", "robust", "--video_envs", "2",
                                 "--overwrite"])
        assert str(info.value.code).startswith("error: --test, --overwrite, --video_envs: the live viewer tests "
                                               "nothing"), info.value.code
    # A checkpoint's viewer ran on after --seconds 2; the robust test wrote no video for --video_envs 2.
    with pytest.raises(SystemExit) as info:
        recipe("play").main(["--checkpoint", str(SHIPPED_POLICY), "--viewer", "--seconds", "2"])
    assert str(info.value.code).startswith("error: --seconds: a checkpoint's live viewer runs until Ctrl-C")
    with pytest.raises(SystemExit) as info:
        recipe("play").main(["--checkpoint", str(SHIPPED_POLICY), "--test", "robust", "--video_envs", "2"])
    assert info.value.code == 2 and "--video_envs sets the standard test's video" in capsys.readouterr().err
    # sim2sim ran no step and reported survival 1.0 with NaN metrics (not JSON) into its --out.
    with pytest.raises(SystemExit) as info:
        recipe("sim2sim").main(["--contract", str(SHIPPED_POLICY.with_suffix(".json")), "--seconds", "0.001"])
    assert "seconds=0.001 is shorter than one control period (4 ms)" in str(info.value.code)


@pytest.mark.parametrize("name", ["play", "sim2sim"])
@pytest.mark.parametrize("flags, message", [
    (["--seconds", "nan"], "--seconds must be a finite number"),
    (["--seconds", "inf"], "--seconds must be a finite number"),
    (["--vx", "nan"], "--vx and --vy must be finite speeds"),
    (["--vy=-inf"], "--vx and --vy must be finite speeds"),
])
def test_play_and_sim2sim_refuse_non_finite_lengths_and_speeds_by_flag(name, flags, message, capsys):
    # Checked before any file is read: NaN seconds used to surface as "cannot convert float NaN to integer", inf as
    # an OverflowError traceback, and a NaN speed as a NaN tracking error in (invalid) JSON.
    source = ["--checkpoint", "missing.pt"] if name == "play" else ["--contract", "missing.json"]
    with pytest.raises(SystemExit) as info:
        recipe(name).main([*source, *flags])
    assert info.value.code == 2 and message in capsys.readouterr().err


def test_policy_steps_names_a_non_finite_length():
    from tocabi_torchrl.evaluation.record import policy_steps

    assert policy_steps(8.0, 0.004) == 2000
    for bad in (float("nan"), float("inf")):
        with pytest.raises(ValueError, match="must be a finite number of seconds"):
            policy_steps(bad, 0.004)


@needs_policy
def test_a_shipped_policy_writes_outside_the_source_tree_and_titles_the_plot_with_the_command(
        tmp_path, monkeypatch, capsys):
    from PIL import Image

    from tocabi_torchrl.evaluation.gait_test import evaluate_run

    monkeypatch.chdir(tmp_path)
    before = set(SHIPPED_POLICY.parent.iterdir())
    evaluate_run(SHIPPED_POLICY, num_envs=1, device="cpu", seconds=0.1, command=(0.3, 0.1), video_envs=0)
    out = tmp_path / "runs" / "eval" / "tocabi_walk_ppo"
    assert (out / "summary.json").is_file() and (out / "knees.png").is_file()
    assert json.loads((out / "summary.json").read_text())["checkpoint"] == str(SHIPPED_POLICY)
    assert set(SHIPPED_POLICY.parent.iterdir()) == before, "evaluation wrote into the package's assets"
    assert Image.open(out / "knees.png").text["Title"] == "Knee trajectories at command (0.3, 0.1) m/s, env 0"
    assert "gait test" in capsys.readouterr().err  # the rollout's progress bar


def test_rendering_shows_progress(tmp_path, capsys, model):
    from tocabi_torchrl.evaluation import video as eval_video

    reason = eval_video.rendering_unavailable()
    if reason is not None:
        pytest.skip(f"no offscreen rendering here: {reason}")
    qpos = np.tile(model.qpos0, (3, 1, 1))
    try:
        eval_video.render_video(model, qpos, 30, tmp_path, width=64, height=48)
    except Exception as err:  # noqa: BLE001 - skip on OpenGL's failure only (the module remembers those)
        if eval_video._failure is None:
            raise  # not OpenGL: a bug in the video code, which a skip would hide
        pytest.skip(f"no offscreen rendering here: {err}")
    assert "rendering video" in capsys.readouterr().err


@pytest.mark.parametrize("budget, shadows", [(float("inf"), True), (-1.0, False)])
def test_the_video_drops_shadows_only_where_a_tile_is_slow(tmp_path, capsys, monkeypatch, model, budget, shadows):
    # Mesa's software OpenGL (a machine without a GPU) spent ~0.1 s per tile on the shadow map alone: 5/6 of play.py.
    import mujoco

    from tocabi_torchrl.evaluation import video as eval_video

    monkeypatch.setattr(eval_video, "_failure", None)
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    drawn = []

    class Renderer:  # records whether each tile is drawn with shadows
        def __init__(self, model, height, width, **kwargs):
            self.shape, self.scene = (height, width, 3), SimpleNamespace(flags=np.ones(32, bool))

        def update_scene(self, *args, **kwargs):
            pass

        def render(self):
            drawn.append(bool(self.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW]))
            return np.zeros(self.shape, np.uint8)

        def close(self):
            pass

    monkeypatch.setattr(mujoco, "Renderer", Renderer)
    monkeypatch.setattr(eval_video, "SHADOW_BUDGET_S", budget)
    eval_video.render_video(model, np.tile(model.qpos0, (3, 2, 1)), 30, tmp_path, width=64, height=48)
    assert drawn == [True, True] + [shadows] * 6  # two timed tiles with shadows, then 3 frames of 2 robots
    assert ("rendering video (no shadows: software OpenGL)" in capsys.readouterr().err) is not shadows


def test_a_video_stopped_while_encoding_leaves_the_earlier_one_whole(tmp_path, monkeypatch, model):
    # imageio wrote walk.mp4 in place: a run stopped while encoding (--overwrite of an earlier test) left half a video
    # under the earlier one's name.
    import imageio.v2 as imageio
    import mujoco

    from tocabi_torchrl.evaluation import video as eval_video

    class Renderer:  # no OpenGL needed: one grey tile per robot
        def __init__(self, model, height, width, **kwargs):
            self.shape, self.scene = (height, width, 3), SimpleNamespace(flags=np.ones(32, bool))

        def update_scene(self, *args, **kwargs):
            pass

        def render(self):
            return np.full(self.shape, 128, np.uint8)

        def close(self):
            pass

    monkeypatch.setattr(eval_video, "_failure", None)
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    monkeypatch.setattr(mujoco, "Renderer", Renderer)
    qpos = np.tile(model.qpos0, (4, 2, 1))
    path = eval_video.render_video(model, qpos, 30, tmp_path, width=64, height=48, progress=False, shadows=False)
    assert path == tmp_path / "walk.mp4" and len(imageio.mimread(path)) == 4
    assert imageio.imread(tmp_path / "walk_frame.png").shape == (48, 128, 3)
    earlier = path.read_bytes()
    write = imageio.mimwrite

    def stopped(uri, frames, **kwargs):  # the encoder gets one frame out, then Ctrl-C
        write(uri, frames[:1], **kwargs)
        raise KeyboardInterrupt

    monkeypatch.setattr(imageio, "mimwrite", stopped)
    with pytest.raises(KeyboardInterrupt):
        eval_video.render_video(model, qpos, 30, tmp_path, width=64, height=48, progress=False, shadows=False)
    assert path.read_bytes() == earlier, "the earlier video was replaced by a cut-off one"
    assert not list(tmp_path.glob(".*.tmp"))


def test_the_gif_without_an_mp4_writer_plays_at_the_rollouts_speed(tmp_path, monkeypatch, model):
    # The fallback passed its frame time in seconds (2/fps) where imageio's GIF writer takes milliseconds: every frame
    # was stored with 0 ms, so viewers played the walk at their own speed, not the simulated one.
    import imageio.v2 as imageio
    import mujoco
    from PIL import Image

    from tocabi_torchrl.evaluation import video as eval_video

    class Renderer:  # no OpenGL needed: a tile of another grey each frame (the GIF writer merges equal frames)
        def __init__(self, model, height, width, **kwargs):
            self.shape, self.scene = (height, width, 3), SimpleNamespace(flags=np.ones(32, bool))
            self.drawn = 0

        def update_scene(self, *args, **kwargs):
            pass

        def render(self):
            self.drawn += 1
            return np.full(self.shape, 3 * self.drawn, np.uint8)

        def close(self):
            pass

    write = imageio.mimwrite

    def no_mp4(uri, frames, format=None, **kwargs):  # an install without imageio-ffmpeg
        if format == ".mp4":
            raise ValueError("no ffmpeg")
        return write(uri, frames, format=format, **kwargs)

    monkeypatch.setattr(eval_video, "_failure", None)
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    monkeypatch.setattr(mujoco, "Renderer", Renderer)
    monkeypatch.setattr(imageio, "mimwrite", no_mp4)
    fps, frames = 31.25, 40  # the gait test's frame rate at 4 ms steps; 1.28 s of rollout
    path = eval_video.render_video(model, np.tile(model.qpos0, (frames, 1, 1)), fps, tmp_path, width=32, height=24,
                                   progress=False, shadows=False)
    assert path == tmp_path / "walk.gif"
    gif = Image.open(path)
    shown = []
    for k in range(gif.n_frames):
        gif.seek(k)
        shown.append(gif.info.get("duration", 0))  # no entry: 0 ms
    assert len(shown) == frames // 2 and min(shown) > 0
    assert abs(sum(shown) - 1000.0 * frames / fps) <= 10.0, shown  # it lasts as long as the rollout

def test_play_help_shows_every_default():
    parser = recipe("play").build_parser()
    for action in parser._actions:
        if action.dest not in ("help", "checkpoint", "policy"):  # one of the two is required: no default
            assert action.help.count("(default:") == 1, action.dest


def test_play_help_names_every_shipped_policy():
    from tocabi_torchrl.viewer.policy_source import shipped_policies

    parser = recipe("play").build_parser()
    (policy,) = [a for a in parser._actions if a.dest == "policy"]
    doc = " ".join(recipe("play").__doc__.split())
    for text in (policy.help, doc.split("--policy names a shipped policy", 1)[1]):
        names = text.split("(", 1)[1].split(")", 1)[0].split(", ")
        assert sorted(names) == sorted(shipped_policies()), f"{text!r} lists other names than the shipped policies"


def test_osmesa_is_checked_before_mujoco_loads():
    from tocabi_torchrl.render_gl import GLBackendError, choose_gl_backend

    environ = {"MUJOCO_GL": "osmesa"}
    if ctypes.util.find_library("OSMesa") and importlib.util.find_spec("OpenGL"):
        assert choose_gl_backend(environ) == "osmesa"
        return
    with pytest.raises(GLBackendError, match="MUJOCO_GL=osmesa needs .*MUJOCO_GL=egl"):
        choose_gl_backend(environ)
    assert choose_gl_backend({}) in ("egl", "disable", None) and choose_gl_backend({"MUJOCO_GL": "egl"}) == "egl"
    env = {**os.environ, "MUJOCO_GL": "osmesa", "PYTHONPATH": str(REPO)}
    # --help answers whatever the GL setting; a run checks it before mujoco loads.
    proc = subprocess.run([sys.executable, str(REPO / "recipes" / "play.py"), "--checkpoint", "missing.pt"], env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1 and "MUJOCO_GL=osmesa needs" in proc.stderr and "Traceback" not in proc.stderr
    help_proc = subprocess.run([sys.executable, str(REPO / "recipes" / "play.py"), "--help"], env=env,
                               capture_output=True, text=True, timeout=120)
    assert help_proc.returncode == 0 and "--checkpoint" in help_proc.stdout


@needs_policy
def test_ctrl_c_in_the_gait_test_exits_130_and_leaves_no_empty_folder(tmp_path, monkeypatch, capsys):
    # It ended in a KeyboardInterrupt traceback and left the empty results folder; sim2sim said 1.
    play = recipe("play")

    def interrupted(*args, **kwargs):
        kwargs["out_dir"].mkdir(parents=True, exist_ok=True)  # as the test makes its folder before its first step
        raise KeyboardInterrupt

    monkeypatch.setattr(play, "evaluate_run", interrupted)
    out = tmp_path / "eval"
    with pytest.raises(SystemExit) as info:
        play.main(["--checkpoint", str(SHIPPED_POLICY), "--device", "cpu", "--out", str(out)])
    assert info.value.code == 130 and "stopped (Ctrl-C) during the gait test" in capsys.readouterr().err
    assert not out.exists()
    given = tmp_path / "given"
    given.mkdir()  # a folder the user made stays
    with pytest.raises(SystemExit) as info:
        play.main(["--checkpoint", str(SHIPPED_POLICY), "--device", "cpu", "--out", str(given)])
    assert info.value.code == 130 and given.is_dir()
    sim2sim = recipe("sim2sim")
    monkeypatch.setattr(sim2sim, "run_sim2sim", lambda *a, **k: (_ for _ in ()).throw(KeyboardInterrupt))
    with pytest.raises(SystemExit) as info:
        sim2sim.main(["--contract", str(SHIPPED_POLICY.with_name("tocabi_walk_torque.json")), "--seconds", "0.1"])
    assert info.value.code == 130 and "stopped (Ctrl-C)" in capsys.readouterr().err


def test_play_refuses_an_out_holding_results_unless_overwrite(tmp_path, capsys):
    # Checked before anything is built: an earlier evaluation's files are not replaced silently.
    out = tmp_path / "earlier"
    out.mkdir()
    (out / "summary.json").write_text('{"earlier": true}')
    with pytest.raises(SystemExit) as info:
        recipe("play").main(["--checkpoint", str(SHIPPED_POLICY), "--num_envs", "1", "--seconds", "0.02",
                             "--video_envs", "0", "--device", "cpu", "--out", str(out)])
    # It names what the folder holds (it used to guess "an earlier evaluation's summary.json" whatever was there).
    assert f"{out} already holds results (summary.json)" in str(info.value.code)
    assert "--overwrite" in str(info.value.code)
    assert (out / "summary.json").read_text() == '{"earlier": true}'
    recipe("play").main(["--checkpoint", str(SHIPPED_POLICY), "--num_envs", "1", "--seconds", "0.02",
                         "--video_envs", "0", "--device", "cpu", "--out", str(out), "--overwrite"])
    assert json.loads((out / "summary.json").read_text())["num_envs"] == 1
    assert f"results go to {out}/" in capsys.readouterr().out


def test_the_default_eval_folder_is_never_reused_once_it_holds_results(tmp_path):
    from tocabi_torchrl.evaluation.gait_test import eval_out_dir, fresh_eval_dir

    ckpt = tmp_path / "run" / "checkpoints" / "latest.pt"
    ckpt.parent.mkdir(parents=True)
    ckpt.write_bytes(b"")  # only its place matters here
    assert fresh_eval_dir(ckpt) == tmp_path / "run" / "eval"
    (tmp_path / "run" / "eval").mkdir()
    assert eval_out_dir(tmp_path / "run") == tmp_path / "run" / "eval"  # an empty folder holds nothing to lose
    (tmp_path / "run" / "eval" / "summary.json").write_text("{}")
    assert eval_out_dir(tmp_path / "run") == tmp_path / "run" / "eval_2"
    (tmp_path / "run" / "eval_2").mkdir()
    (tmp_path / "run" / "eval_2" / "knees.png").write_bytes(b"png")
    (tmp_path / "run" / "eval_3").write_text("a file, not a folder")
    assert eval_out_dir(tmp_path / "run") == tmp_path / "run" / "eval_4"
    assert eval_out_dir(tmp_path / "run", tmp_path / "run" / "eval", overwrite=True) == tmp_path / "run" / "eval"
    # Two evaluations started together both chose the same fresh folder and wrote into it: a folder another live
    # process has claimed is passed over.
    from test_runs import hold_claim

    other_run = tmp_path / "other" / "checkpoints" / "latest.pt"
    other_run.parent.mkdir(parents=True)
    other_run.write_bytes(b"")
    other = hold_claim(tmp_path / "other" / "eval")
    try:
        assert eval_out_dir(tmp_path / "other") == tmp_path / "other" / "eval_2"
    finally:
        other.kill()
        other.wait()


@needs_policy
def test_a_gait_test_where_every_robot_falls_at_once_writes_strict_json(tmp_path, monkeypatch, capsys):
    from tocabi_torchrl.evaluation import gait_test as evaluate
    from tocabi_torchrl.evaluation.record import GaitMetrics

    class FallAtOnce(GaitMetrics):
        def update(self, nxt):
            nxt = nxt.clone()
            nxt["terminated"] = torch.ones_like(nxt["terminated"])
            return super().update(nxt)

    monkeypatch.setattr(evaluate, "GaitMetrics", FallAtOnce)
    out = tmp_path / "fell"
    recipe("play").main(["--checkpoint", str(SHIPPED_POLICY), "--num_envs", "2", "--seconds", "0.02",
                         "--video_envs", "0", "--device", "cpu", "--out", str(out)])

    def refuse(token):
        raise ValueError(f"not JSON: {token}")

    saved = json.loads((out / "summary.json").read_text(), parse_constant=refuse)
    assert saved["survival"] == 0.0
    for key in ("knee_rms_rad", "speed_tracking_error_mps", "forward_distance_survivors_m"):
        assert saved[key] is None, key
    # What play prints is the verdict for people, a metric without a value said so; the JSON holds the numbers.
    printed = capsys.readouterr().out
    assert "does not walk yet" in printed and "knee RMS vs reference    no value" in printed
    assert str(out / "summary.json") in printed and "nan" not in printed.lower()
    assert not evaluate.gait_passes(saved)
    assert not [p for p in out.iterdir() if p.name.endswith(".tmp")]


def test_a_missing_video_writer_names_the_viz_extra_not_egl(tmp_path, monkeypatch, capsys):
    from tocabi_torchrl.evaluation import gait_test as evaluate

    def no_imageio(*args, **kwargs):
        raise ModuleNotFoundError("No module named 'imageio'", name="imageio")

    monkeypatch.setattr(evaluate, "render_video", no_imageio)
    summary = evaluate.evaluate_run(SHIPPED_POLICY, num_envs=1, device="cpu", seconds=0.1, video_envs=1,
                                    out_dir=tmp_path / "ev")
    said = capsys.readouterr().out
    assert summary["video"].startswith("not rendered: ModuleNotFoundError")
    assert '.[viz]' in said and "libegl1" not in said


@needs_policy
def test_a_gait_test_of_an_env_at_another_command_is_refused_not_reported_at_this_one(tmp_path):
    # An env built at (0.5, 0) m/s tested with command=(0.2, 0) wrote a summary of a 0.2 m/s test, its speed error
    # measured against a command no robot had.
    from tocabi_torchrl.evaluation.gait_test import evaluate_policy
    from tocabi_torchrl.evaluation.record import load_policy

    policy = load_policy(SHIPPED_POLICY, 2, "cpu", nominal=True)  # the standard test's (0.5, 0) m/s
    with pytest.raises(ValueError, match=r"command=\(0\.2, 0\.0\) m/s, but the env commands \(0\.5, 0\) m/s to "
                                         r"robot 0 at its reset \(2 of 2 robots differ\).*load_policy"):
        evaluate_policy(policy.actor, policy.cfg, tmp_path / "e", env=policy.env, command=(0.2, 0.0), seconds=0.02,
                        video_envs=0, progress=False)
    assert not (tmp_path / "e").exists()
    summary = evaluate_policy(policy.actor, policy.cfg, tmp_path / "e", env=policy.env, command=(0.5, 0.0),
                              seconds=0.02, video_envs=0, progress=False)
    assert summary["command_mps"] == [0.5, 0.0]

@needs_policy
def test_a_policy_of_another_observation_size_is_refused_at_the_call(tmp_path):
    # Both gait tests let torch's "mat1 and mat2 shapes cannot be multiplied" out of the network's first layer.
    from tensordict.nn import TensorDictModule

    from tocabi_torchrl.evaluation.gait_test import evaluate_policy
    from tocabi_torchrl.evaluation.record import load_policy
    from tocabi_torchrl.evaluation.robust import run_case

    policy = load_policy(SHIPPED_POLICY, 2, "cpu", nominal=True)
    other = TensorDictModule(torch.nn.Linear(10, 13), in_keys=["observation"], out_keys=["action"])
    said = r"cannot act on this env's observation of 237 values per robot \(mat1 and mat2.*policy's own config"
    with pytest.raises(ValueError, match=said):
        evaluate_policy(other, policy.cfg, tmp_path / "e", env=policy.env, seconds=0.02, video_envs=0, progress=False)
    with pytest.raises(ValueError, match=said):
        run_case(other, policy.env, 0.02, progress=False)

    def broken(td):  # a policy's own failure is not taken for a size mismatch
        raise RuntimeError("a bug in the policy")

    with pytest.raises(RuntimeError, match="a bug in the policy"):
        run_case(broken, policy.env, 0.02, progress=False)

def test_no_robots_is_refused_not_the_runs_4096(tmp_path):
    # evaluate_run(num_envs=0) built the run's 4,096 worlds: half an hour and more on a CPU, without a word.
    from tocabi_torchrl.evaluation.gait_test import evaluate_run
    from tocabi_torchrl.robot import asset_path

    with pytest.raises(ValueError, match=r"num_envs must be a positive int .*, got 0; None for"):
        evaluate_run(asset_path("policies", "tocabi_walk_ppo.pt"), num_envs=0, device="cpu", seconds=0.2,
                     video_envs=0, out_dir=tmp_path / "e")
    assert not (tmp_path / "e").exists()


def test_the_standard_report_says_its_command_and_never_rounds_a_fail_into_a_pass():
    # --vx 0.3 (play.py's own example) could never pass the 2.6 m of the 0.5 m/s test, and the report did not say
    # so; 2.597 m was shown as "2.60 m needs >= 2.60 m FAIL".
    from tocabi_torchrl.evaluation.gait_test import gait_report_text

    summary = {"command_mps": [0.3, 0.0], "survival": 1.0, "forward_distance_m": 2.597, "lateral_drift_m": 0.1,
               "knee_rms_rad": 0.1}
    text = gait_report_text(summary, 8.0, 4, Path("/nonexistent"))
    assert text.splitlines()[0] == ("gait test (8 s, 4 robots): does not walk yet (the thresholds are set for the "
                                    "(0.5, 0.0) m/s command, not (0.3, 0.0))")
    assert "forward distance          2.597 m   needs >= 2.60 m     FAIL" in text
    assert "not (" not in gait_report_text({**summary, "command_mps": [0.5, 0.0]}, 8.0, 4, Path("/nonexistent"))


def test_overwrite_without_out_is_refused_and_a_cpu_robust_test_of_full_size_is_said(capsys, monkeypatch):
    # --overwrite without --out wrote to a fresh folder anyway; the robust test's default 1,024 robots per case on
    # a CPU sat for hours at "0/2000" without a word.
    with pytest.raises(SystemExit) as info:
        recipe("play").main(["--policy", "ppo", "--overwrite", "--device", "cpu"])
    assert info.value.code == 2 and "--overwrite applies with --out only" in capsys.readouterr().err
    import tocabi_torchrl.evaluation.robust as robust

    def stop(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(robust, "evaluate_robust_run", stop)
    with pytest.raises(SystemExit):
        recipe("play").main(["--policy", "robust", "--test", "robust", "--device", "cpu"])
    assert "note: 1,024 robots per case for 8 s take hours on a CPU; --num_envs 4 takes about a minute" in \
        capsys.readouterr().out


@pytest.mark.parametrize("cause", ["gl_unset_with_egl", "disk_full"])
def test_a_video_that_fails_names_its_own_cause(tmp_path, monkeypatch, capsys, cause):
    # With EGL installed and MUJOCO_GL unset (the Python API imports mujoco first), and for a full disk, the advice
    # was to install EGL and leave MUJOCO_GL unset, which held already; a failed write left half a walk.mp4.
    import ctypes.util
    import errno

    from tocabi_torchrl.evaluation import gait_test as evaluate

    def fails(model, qpos, fps, out, **kwargs):
        if cause == "disk_full":
            (out / "walk.mp4").write_bytes(b"half")
            raise OSError(errno.ENOSPC, "No space left on device")
        raise RuntimeError("an OpenGL platform library has not been loaded into this process")

    monkeypatch.setattr(evaluate, "render_video", fails)
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: "libEGL.so.1" if name == "EGL" else None)
    evaluate.evaluate_run(SHIPPED_POLICY, num_envs=1, device="cpu", seconds=0.1, video_envs=1, out_dir=tmp_path / "e")
    said = capsys.readouterr().out
    if cause == "disk_full":
        assert f"check that {tmp_path / 'e'} has free space and can be written" in said
        assert not (tmp_path / "e" / "walk.mp4").exists() and "libegl1" not in said
    else:
        assert "set MUJOCO_GL=egl before Python imports mujoco" in said and "leave MUJOCO_GL unset" not in said


def test_a_negative_video_size_and_a_file_as_results_folder_are_refused_before_anything_runs(tmp_path):
    # video_envs=-1 recorded "not requested (video_envs=0)"; out_dir naming a file was a raw FileExistsError after
    # the env was built.
    from tocabi_torchrl.evaluation.gait_test import evaluate_run
    from tocabi_torchrl.evaluation.robust import evaluate_robust_run

    with pytest.raises(ValueError, match=r"video_envs must be an int >= 0 \(robots in the video; 0 for none\), got -1"):
        evaluate_run(SHIPPED_POLICY, num_envs=1, device="cpu", seconds=0.1, video_envs=-1, out_dir=tmp_path / "e")
    afile = tmp_path / "afile"
    afile.write_text("")
    with pytest.raises(ValueError, match="out_dir .*afile is a file, not a folder"):
        evaluate_robust_run(SHIPPED_POLICY, num_envs=1, device="cpu", seconds=0.1, out_dir=afile)


def test_evaluate_run_replaces_an_earlier_summary_only_when_asked(tmp_path):
    # evaluate_run(out_dir=...) replaced a folder's earlier summary.json without a word.
    from tocabi_torchrl.evaluation.gait_test import evaluate_run
    from tocabi_torchrl.evaluation.output import OutputExistsError

    out = tmp_path / "e"
    out.mkdir()
    (out / "summary.json").write_text('{"earlier": true}')
    with pytest.raises(OutputExistsError, match=r"e/summary.json holds an earlier evaluation's results; nothing was "
                                                r"overwritten. Pass replace=True"):
        evaluate_run(SHIPPED_POLICY, num_envs=1, device="cpu", seconds=0.02, video_envs=0, out_dir=out,
                     progress=False)
    assert (out / "summary.json").read_text() == '{"earlier": true}'
    summary = evaluate_run(SHIPPED_POLICY, num_envs=1, device="cpu", seconds=0.02, video_envs=0, out_dir=out,
                           progress=False, replace=True)
    assert json.loads((out / "summary.json").read_text())["num_envs"] == summary["num_envs"] == 1


@needs_policy
def test_evaluate_robust_run_replaces_an_earlier_report_only_when_asked(tmp_path, capsys):
    # evaluate_robust_run(out_dir=...) replaced a folder's earlier robust.json and robust.png without a word.
    from tocabi_torchrl.evaluation.output import OutputExistsError
    from tocabi_torchrl.evaluation.robust import evaluate_robust_run

    out = tmp_path / "e"
    out.mkdir()
    (out / "robust.png").write_text("earlier")
    with pytest.raises(OutputExistsError, match=r"e/robust.png holds an earlier evaluation's results; nothing was "
                                                r"overwritten. Pass replace=True"):
        evaluate_robust_run(SHIPPED_POLICY, num_envs=1, device="cpu", seconds=0.02, out_dir=out, cases=["nominal"],
                            progress=False)
    assert (out / "robust.png").read_text() == "earlier" and not (out / "robust.json").exists()
    report = evaluate_robust_run(SHIPPED_POLICY, num_envs=1, device="cpu", seconds=0.02, out_dir=out,
                                 cases=["nominal"], progress=False, replace=True)
    assert json.loads((out / "robust.json").read_text())["settings"]["num_envs"] == report["settings"]["num_envs"]
    # play.py's --overwrite, which eval_out_dir asks for, reaches the robust test too
    recipe("play").main(["--checkpoint", str(SHIPPED_POLICY), "--test", "robust", "--num_envs", "1", "--seconds",
                         "0.02", "--device", "cpu", "--out", str(out), "--overwrite"])
    assert f"results: {out / 'robust.json'}" in capsys.readouterr().out


def test_ctrl_c_in_a_checkpoint_viewer_exits_130_while_loading_or_serving(monkeypatch, capsys):
    # Serving, Ctrl-C printed "viewer stopped" and exited 0; while loading it was a 67-line traceback.
    import tocabi_torchrl.viewer.play as viewer_play

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(viewer_play, "serve_policy", interrupted)
    with pytest.raises(SystemExit) as info:
        recipe("play").main(["--policy", "ppo", "--viewer", "--device", "cpu"])
    assert info.value.code == 130 and "viewer stopped (Ctrl-C)" in capsys.readouterr().err


@pytest.mark.parametrize("option", ["--policy", "--checkpoint"])
def test_play_refuses_an_empty_policy_or_checkpoint_path(option, capsys):
    # "" is the current folder as a path: it was looked up as a run and reported "checkpoint not found: ./latest.pt".
    with pytest.raises(SystemExit) as info:
        recipe("play").main([option, ""])
    assert info.value.code == 2
    assert f"{option} is empty" in capsys.readouterr().err


@needs_policy
def test_play_without_matplotlib_says_the_install_before_the_test(tmp_path, monkeypatch):
    # knees.png is drawn after the rollout: without the viz extra, play ran the whole test (minutes on a CPU) and then
    # stopped with a ModuleNotFoundError traceback, leaving a folder with summary.json alone.
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # what an install without the viz extra imports
    out = tmp_path / "eval"
    with pytest.raises(SystemExit) as info:
        recipe("play").main(["--policy", "ppo", "--num_envs", "1", "--seconds", "0.1", "--video_envs", "0",
                             "--device", "cpu", "--out", str(out)])
    assert str(info.value.code).startswith("error: the gait test draws knees.png with matplotlib, which is not "
                                           'installed: pip install -e ".[viz]"'), info.value.code
    assert not out.exists()
