"""The mjlab peer benchmark (issue 25). Its run needs mjlab's pinned environment (mujoco 3.11): it is tested where
mjlab imports, in this python or the one ``MJLAB_PYTHON`` names (docs/benchmarks.md, "Peer: mjlab"), else skipped as
in CI. The stand-ins and the merge with our report run here."""

from __future__ import annotations

import ast
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from lab.benchmarks import mjlab_peer

MJLAB_PYTHON = os.environ.get("MJLAB_PYTHON") or (sys.executable if importlib.util.find_spec("mjlab") else None)
PEER = {"meta": {"gpu": "H100", "date": "2026-12-01", "task": mjlab_peer.TASK, "stand_ins": ["wandb"],
                 "versions": {"mjlab": "1.6.0", "mujoco-warp": "3.11.0"}, "command": "python3 mjlab_peer.py"},
        "results": [{"num_envs": 4096, "decimation": 4, "physics_dt": 0.005, "train_env_steps_per_s": 200_000.0,
                     "raw_policy_steps_per_s": 400_000.0, "ratio_train_over_raw": 0.5}]}


def _ours(gpu="H100", num_envs=4096) -> dict:
    row = {"num_envs": num_envs, "gpus": 1, "overrides": {}, "train_env_steps_per_s": 129_276.0,
           "raw_policy_steps_per_s": 181_347.0, "ratio_train_over_raw": 0.7129}
    return {"meta": {"gpu": gpu, "date": "2026-12-01", "command": "python -m lab.benchmarks.train_throughput"},
            "results": [row]}


def test_merge_writes_the_page_of_both_sides_and_re_merges(tmp_path):
    peer, ours = tmp_path / "mjlab_peer.json", tmp_path / "ours.json"
    peer.write_text(json.dumps(PEER))
    ours.write_text(json.dumps(_ours()))
    data = mjlab_peer.main(["--out", str(peer), "--ours", str(ours)])
    assert json.loads(peer.read_text()) == data and data["ours"]["result"]["substeps"] == 8
    text = (tmp_path / "mjlab_peer.md").read_text()
    assert text == mjlab_peer.render(data)
    assert "| TOCABI walk, default preset | 4096 | 8 x 0.5 ms | 129,276 | 181,347 | 0.71 | H100 |" in text
    assert f"| mjlab 1.6.0 | {mjlab_peer.TASK} | 4096 | 4 x 5 ms | 200,000 | 400,000 | 0.50 | H100 |" in text
    assert "Both sides ran on H100 on 2026-12-01." in text
    ours.write_text(json.dumps(_ours(gpu="H200")))  # merging again replaces our side
    mjlab_peer.main(["--out", str(peer), "--ours", str(ours)])
    assert "**Not one run**" in (tmp_path / "mjlab_peer.md").read_text()
    ours.write_text(json.dumps(_ours(num_envs=16384)))
    with pytest.raises(SystemExit, match="no default 1-GPU row of 4096 envs"):
        mjlab_peer.main(["--out", str(peer), "--ours", str(ours)])


def test_stand_ins_replace_only_missing_modules(monkeypatch):
    for name in mjlab_peer.STAND_INS:
        monkeypatch.delitem(sys.modules, name, raising=False)
    missing = {name for name in mjlab_peer.STAND_INS if importlib.util.find_spec(name) is None}
    try:
        assert set(mjlab_peer.install_stand_ins()) == missing
        if "wandb" in missing:
            assert sys.modules["wandb"].run is None  # what the G1 runner's save() reads
    finally:  # a stand-in left in sys.modules (no __spec__) breaks find_spec for the tests after this one
        for name in missing:
            sys.modules.pop(name, None)


def test_nothing_at_module_level_imports_mjlab_or_our_package():
    tree = ast.parse(Path(mjlab_peer.__file__).read_text())
    names = [n.module if isinstance(n, ast.ImportFrom) else a.name for n in tree.body
             if isinstance(n, (ast.Import, ast.ImportFrom)) for a in n.names]
    assert not [n for n in names if n is None or n.split(".")[0] in ("mjlab", "tocabi_torchrl", "lab", "benchmarks")]


@pytest.mark.skipif(MJLAB_PYTHON is None, reason="no mjlab here: set MJLAB_PYTHON to a python with mjlab's pins")
def test_a_toy_run_on_the_cpu(tmp_path):
    out = tmp_path / "peer.json"
    cmd = [MJLAB_PYTHON, mjlab_peer.__file__, "--device", "cpu", "--num_envs", "4", "--iterations", "1", "--warmup",
           "1", "--raw_steps", "2", "--out", str(out), "--run_dir", str(tmp_path / "runs")]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False, timeout=1800,
                          env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"})
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    data = json.loads(out.read_text())
    (r,), meta = data["results"], data["meta"]
    assert (r["num_envs"], r["decimation"], r["steps_per_env"], r["runner"]) == (4, 4, 24, "VelocityOnPolicyRunner")
    assert r["train_env_steps_per_s"] > 0 and r["raw_policy_steps_per_s"] > 0 and r["ratio_train_over_raw"] > 0
    assert meta["versions"]["mujoco-warp"].startswith("3.11") and meta["task"] == mjlab_peer.TASK


def _stand_in_mjlab(monkeypatch) -> None:
    """Just the mjlab that main() calls (a runner whose learn() only logs), so that its CPU path runs here."""
    import types
    from dataclasses import dataclass

    @dataclass
    class RlCfg:
        seed: int = 0
        clip_actions: float | None = None
        logger: str = "wandb"
        num_steps_per_env: int = 24

    class Runner:
        def __init__(self, env, cfg, log_dir, device):
            self.current_learning_iteration, self.logger = 0, types.SimpleNamespace(log=lambda *a, it, **k: None)

        def learn(self, num_learning_iterations, init_at_random_ep_len=False):
            for it in range(num_learning_iterations):
                self.logger.log(it=it)

    def env(cfg, device):
        return types.SimpleNamespace(cfg=cfg, device=device, num_envs=cfg.scene.num_envs, physics_dt=0.005,
                                     sim=types.SimpleNamespace(use_cuda_graph=False))

    registry = types.SimpleNamespace(
        list_tasks=lambda: [mjlab_peer.TASK], load_rl_cfg=lambda task: RlCfg(), load_runner_cls=lambda task: None,
        load_env_cfg=lambda task: types.SimpleNamespace(scene=types.SimpleNamespace(num_envs=1), seed=None,
                                                        decimation=4))
    attributes = {"mjlab": {}, "mjlab.tasks": {"registry": registry}, "mjlab.envs": {"ManagerBasedRlEnv": env},
                  "mjlab.rl": {"MjlabOnPolicyRunner": Runner,
                               "RslRlVecEnvWrapper": lambda env, clip_actions: types.SimpleNamespace(unwrapped=env)},
                  "mjlab.utils": {}, "mjlab.utils.torch": {"configure_torch_backends": lambda: None}}
    for name, values in attributes.items():
        module = types.ModuleType(name)
        module.__dict__.update(values)
        monkeypatch.setitem(sys.modules, name, module)
    for parent in ("mjlab", "mjlab.utils"):  # `import mjlab.tasks` binds the submodules as attributes
        for name in attributes:
            if name.rpartition(".")[0] == parent:
                monkeypatch.setattr(sys.modules[parent], name.rpartition(".")[2], sys.modules[name], raising=False)


def test_a_smoke_run_off_cuda_does_not_replace_the_published_gpu_report(tmp_path, monkeypatch, capsys):
    # The documented `--device cpu` smoke run, without --out, once replaced the committed GPU report (whose page then
    # failed to regenerate); it goes where lab.benchmarks.common.report_dir sends any CPU measurement instead.
    published, cpu = tmp_path / "docs" / "mjlab_peer.json", tmp_path / "runs" / "mjlab_peer.json"
    published.parent.mkdir()
    published.write_text("the published GPU report")
    monkeypatch.setattr(mjlab_peer, "OUT", published)
    monkeypatch.setattr(mjlab_peer, "CPU_OUT", cpu)
    for name in ("MUJOCO_GL", "GIT_PYTHON_REFRESH"):  # main() sets them for mjlab
        monkeypatch.setenv(name, os.environ.get(name, ""))
    _stand_in_mjlab(monkeypatch)
    monkeypatch.setattr(mjlab_peer, "install_stand_ins", list)  # tested above; its modules would outlive this test
    data = mjlab_peer.main(["--device", "cpu", "--num_envs", "2", "--iterations", "1", "--warmup", "1", "--raw_steps",
                            "0", "--run_dir", str(tmp_path / "mjruns")])
    assert published.read_text() == "the published GPU report" and json.loads(cpu.read_text()) == data
    assert f"writing to {cpu}, not {published}" in capsys.readouterr().out
    out = tmp_path / "asked.json"  # a path asked for is honoured
    mjlab_peer.main(["--device", "cpu", "--num_envs", "2", "--iterations", "1", "--warmup", "1", "--raw_steps", "0",
                     "--run_dir", str(tmp_path / "mjruns"), "--out", str(out)])
    assert out.is_file()
