"""Every reader of checkpoints checks the zip CRCs first: a checkpoint with flipped bits in a tensor's data is refused
by play, export and --resume (torch.load alone loads it as other weights), and so is a library recipe's policy.pt.
An exported policy (.onnx or its .json contract) given as a checkpoint points to recipes/sim2sim.py."""

from __future__ import annotations

import shlex
import shutil
import struct
import time
import zipfile
from pathlib import Path

import pytest
import torch
from recipe_runner import load_recipe as recipe

from tocabi_torchrl.integrity import zip_damage
from tocabi_torchrl.rl.checkpoint import CheckpointError, ExportedPolicyError, read_checkpoint

POLICIES = Path(__file__).resolve().parents[1] / "assets" / "policies"
SHIPPED = POLICIES / "tocabi_walk_ppo.pt"
pytestmark = pytest.mark.skipif(not SHIPPED.is_file(), reason="shipped policy not present")


def first_tensor_span(path: Path, length: int = 2048) -> tuple[int, int]:
    """Byte range of the start of the first tensor's data in the zip file ``path`` (member ``.../data/0``, the
    actor's first weight, stored uncompressed), read from the member's local header."""
    with zipfile.ZipFile(path) as z:
        info = next(i for i in z.infolist() if i.filename.endswith("/data/0"))
    raw = path.read_bytes()
    name_len, extra_len = struct.unpack("<HH", raw[info.header_offset + 26:info.header_offset + 30])
    start = info.header_offset + 30 + name_len + extra_len
    return start, start + min(length, info.file_size)


def flip_bits(source: Path, target: Path, span: tuple[int, int] | None = None) -> Path:
    """``source`` copied to ``target`` with bit 0 of every 4th byte of ``span`` (default: the first tensor's data,
    :func:`first_tensor_span`) flipped."""
    start, stop = span or first_tensor_span(source)
    data = bytearray(source.read_bytes())
    for offset in range(start, stop, 4):
        data[offset] ^= 1
    target.write_bytes(bytes(data))
    return target


@pytest.fixture
def flipped(tmp_path) -> Path:
    """The shipped policy with bits flipped inside a tensor's data (the first actor weight, stored uncompressed)."""
    return flip_bits(SHIPPED, tmp_path / "flipped.pt")


def test_flipped_bits_load_silently_in_torch_but_fail_the_zip_crc(flipped):
    # The premise: torch.load alone reads the damaged file as other weights.
    damaged = torch.load(flipped, weights_only=True)["agent"]["actor"]
    shipped = torch.load(SHIPPED, weights_only=True)["agent"]["actor"]
    assert any(not torch.equal(damaged[k], shipped[k]) for k in shipped)
    assert zipfile.ZipFile(flipped).testzip() is not None
    assert "fails its CRC-32 check" in zip_damage(flipped)


@pytest.mark.parametrize("path", sorted(POLICIES.glob("*.pt")), ids=lambda p: p.name)
def test_the_shipped_checkpoints_pass_the_check_in_milliseconds(path):
    zip_damage(path)  # the file into the page cache, as any reader finds it right after the first read
    start = time.perf_counter()
    assert zip_damage(path) is None
    assert time.perf_counter() - start < 0.25  # ~2 ms for 1.6 MB; generous for a busy machine


def test_read_checkpoint_refuses_flipped_bits_naming_the_file_and_the_fix(flipped):
    with pytest.raises(CheckpointError, match=rf"checkpoint {flipped} is damaged: entry '[^']+/data/\d+' fails its "
                                              r"CRC-32 check.*Copy it again .* or pick another checkpoint"):
        read_checkpoint(flipped)


def test_play_refuses_flipped_bits_before_naming_a_results_folder(flipped, capsys):
    with pytest.raises(SystemExit) as info:
        recipe("play").main(["--checkpoint", str(flipped), "--device", "cpu", "--num_envs", "8"])
    assert str(info.value.code).startswith(f"error: checkpoint {flipped} is damaged")
    assert "results go to" not in capsys.readouterr().out and not (flipped.parent / "eval").exists()


def test_export_refuses_flipped_bits(flipped):
    pytest.importorskip("onnx")
    from tocabi_torchrl.export.__main__ import main as export_main

    out = flipped.parent / "policy.onnx"
    with pytest.raises(SystemExit, match=rf"^error: checkpoint {flipped} is damaged"):
        export_main(["--checkpoint", str(flipped), "--out", str(out)])
    assert not out.exists() and not out.with_suffix(".json").exists()


def test_resume_refuses_flipped_bits_before_building_anything(flipped, tmp_path, monkeypatch):
    import tocabi_torchrl.rl.trainer as trainer

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(trainer, "build_env", lambda *a, **k: pytest.fail("an env was built"))
    with pytest.raises(SystemExit, match=rf"error: checkpoint {flipped} is damaged"):
        recipe("ppo_walk").main(["--resume", str(flipped), "--device", "cpu", "--run_dir", str(tmp_path / "runs")])
    assert not (tmp_path / "runs").exists()


def test_a_library_policy_file_with_flipped_bits_is_refused(tmp_path):
    from tocabi_torchrl.adapters.policy_file import PolicyFileError, load_policy, save_policy

    path = save_policy(tmp_path / "policy.pt", "sb3", {"w": torch.arange(4096, dtype=torch.float32)}, {"n": 1})
    entry = max(zipfile.ZipFile(path).infolist(), key=lambda info: info.file_size)  # the tensor's data
    damaged = flip_bits(path, tmp_path / "damaged.pt", (entry.header_offset + 200, entry.header_offset + 300))
    assert load_policy(path, "sb3")[1]["w"].equal(torch.arange(4096, dtype=torch.float32))
    with pytest.raises(PolicyFileError, match=rf"{damaged} is damaged: entry .* fails its CRC-32 check"):
        load_policy(damaged, "sb3")


# ----------------------------------------------------------------------------------------- exported policies
@pytest.mark.parametrize("suffix", [".onnx", ".json"])
def test_play_points_an_exported_policy_to_sim2sim_with_its_options(suffix, capsys):
    exported = POLICIES / f"tocabi_walk_ppo{suffix}"
    with pytest.raises(SystemExit) as info:
        recipe("play").main(["--checkpoint", str(exported), "--num_envs", "8", "--vx", "0.3"])
    message = str(info.value.code)
    assert message.startswith(f"error: {exported} is an exported policy") and "UnpicklingError" not in message
    command = message.split("run it with: ", 1)[1]
    contract = POLICIES / "tocabi_walk_ppo.json"
    assert command == f"python recipes/sim2sim.py --contract {contract} --num_robots 8 --vx 0.3"
    args = recipe("sim2sim").build_parser().parse_args(shlex.split(command)[2:])  # a command sim2sim accepts
    assert (args.contract, args.num_robots, args.vx) == (str(contract), 8, 0.3)
    assert "results go to" not in capsys.readouterr().out


def test_an_exported_policy_is_recognised_by_content_and_refused_by_every_reader(tmp_path):
    model = shutil.copy(POLICIES / "tocabi_walk_ppo.onnx", tmp_path / "policy.bin")
    with pytest.raises(ExportedPolicyError, match=r"an ONNX model.*needs its contract: .*policy\.json is missing"):
        read_checkpoint(model)
    contract = shutil.copy(POLICIES / "tocabi_walk_ppo.json", tmp_path / "contract.txt")
    with pytest.raises(ExportedPolicyError, match=rf"run it with: python recipes/sim2sim.py --contract {contract}$"):
        read_checkpoint(contract)


def test_an_exported_torchscript_module_or_a_runs_config_is_named_not_called_corrupt(tmp_path):
    # Both read as "not a complete torch checkpoint (truncated, corrupt or another kind of file)", the first after a
    # torch warning about TorchScript archives, the second as "UnpicklingError: Unsupported operand 123".
    import json
    import warnings

    module = tmp_path / "walk.ts.pt"
    module.write_bytes(b"PK\x03\x04 a TorchScript zip")
    with pytest.raises(ExportedPolicyError, match=r"a TorchScript module.*needs its contract: .*walk\.json is "):
        read_checkpoint(module)
    contract = shutil.copy(POLICIES / "tocabi_walk_ppo.json", tmp_path / "walk.json")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # torch's TorchScript warning no longer comes first
        with pytest.raises(ExportedPolicyError, match=rf"--contract {contract}$"):
            read_checkpoint(module)
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"env": {}, "ppo": {}, "seed": 0}))
    for read in (read_checkpoint, lambda p: recipe("play").main(["--checkpoint", str(p)])):
        with pytest.raises((CheckpointError, SystemExit),
                           match=rf"config.json is a run's config \(config.json\), not a checkpoint: pass the run "
                                 rf"folder {run} "):
            read(run / "config.json")
