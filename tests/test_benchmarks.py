"""The benchmark harness on the CPU: every committed report regenerates from its JSON, and every benchmark runs end
to end at toy size (``--device cpu``); their GPU paths reuse the same helpers."""

from __future__ import annotations

import json

import pytest

from benchmarks import common, env_throughput, regenerate, scaling, sim_throughput, soak, train_throughput


@pytest.mark.parametrize("page", sorted(regenerate.REPORTS))
def test_committed_report_regenerates_from_its_json(page, tmp_path):
    pytest.importorskip("matplotlib")
    text = regenerate.regenerate(page, common.DOCS, tmp_path)
    assert text == (common.DOCS / page).read_text(), f"{page} differs from what its JSON renders"
    plotted = page not in ("train_throughput.md", "sim_throughput.md")  # the two pages without a figure
    assert bool(list(tmp_path.glob("*.png"))) == plotted


def test_window_rate_takes_the_longest_segment_after_warmup():
    rows = [{"wall_s": w, "env_steps": s} for w, s in ((1, 100), (2, 200), (4, 600), (1, 700), (3, 900))]
    assert common.window_rate(rows, skip=1) == pytest.approx(400 / 2)  # (600 - 200) / (4 - 2): the resume restarts
    assert common.window_rate(rows[:2], skip=1) is None


def test_unknown_override_is_named():
    with pytest.raises(SystemExit, match="no field 'cuda_grpah'"):
        common.parse_overrides(["cuda_grpah=on"])
    assert common.parse_overrides(["cuda_graph=on", "num_envs=8", "actor_hidden=16,8"]) == {
        "cuda_graph": "on", "num_envs": 8, "actor_hidden": (16, 8)}


def test_env_throughput_smoke(tmp_path):
    env_throughput.main(["--device", "cpu", "--num_envs", "2", "--steps", "3", "--raw_steps", "0", "--out",
                         str(tmp_path)])
    (r,) = json.loads((tmp_path / "env_throughput.json").read_text())["results"]
    assert r["env_steps_per_s"] > 0 and r["make_env_steps_per_s"] > 0 and r["raw_policy_steps_per_s"] is None
    assert "| 2 | - |" in (tmp_path / "env_throughput.md").read_text()


@pytest.mark.slow  # warp compiles mujoco-warp's kernels for its CPU device on first use
def test_sim_throughput_smoke(tmp_path):
    sim_throughput.main(["--device", "cpu", "--nworld", "2", "--steps", "2", "--repeats", "1", "--out",
                         str(tmp_path)])
    (r,) = json.loads((tmp_path / "sim_throughput.json").read_text())["results"]
    assert r["raw_policy_steps_per_s"] > 0 and r["backend_policy_steps_per_s"] > 0 and r["upright_backend"] == 1.0


def test_train_throughput_smoke_in_a_child_process(tmp_path):
    train_throughput.main(["--device", "cpu", "--num_envs", "8", "--iterations", "2", "--warmup", "1",
                           "--raw_steps", "0", "--set", "steps_per_env=8", "actor_hidden=8,8", "--out", str(tmp_path),
                           "--run_dir", str(tmp_path / "runs")])
    (r,) = json.loads((tmp_path / "train_throughput.json").read_text())["results"]
    assert r["num_envs"] == 8 and r["train_env_steps_per_s"] > 0 and r["overrides"]["actor_hidden"] == [8, 8]


@pytest.mark.slow
def test_scaling_partial_run_trains_on_and_reports(tmp_path):
    args = ["--kind", "time", "--backend", "cpu", "--num_envs", "8", "--hidden", "8", "--max_minutes", "0.02",
            "--results", str(tmp_path / "scaling"), "--run_dir", str(tmp_path / "runs")]
    scaling.main(args)
    first = json.loads((tmp_path / "scaling" / "time_cpu_0000008.json").read_text())
    assert first["status"] == "partial" and first["env_steps"] > 0 and not first["segments"]
    scaling.main(args)  # a partial result trains on from its checkpoint
    second = json.loads((tmp_path / "scaling" / "time_cpu_0000008.json").read_text())
    assert [s["env_steps"] for s in second["segments"]][0] == first["env_steps"] and len(second["segments"]) == 2
    assert second["env_steps"] == sum(s["env_steps"] for s in second["segments"]) > first["env_steps"]
    scaling.main(["--report", "--results", str(tmp_path / "scaling")])
    assert "| CPU (C MuJoCo) | 8 | 256 / 512 | - |" in (tmp_path / "scaling.md").read_text()


@pytest.mark.slow  # two training processes (one killed, one resumed) and a faulty training run
def test_tiny_soak_on_the_cpu(tmp_path):
    code = soak.main(["--num_envs", "8", "--minutes", "0.25", "--device", "cpu", "--fault_every", "40",
                      "--out", str(tmp_path), "--run_dir", str(tmp_path / "runs")])
    report = json.loads((tmp_path / "soak.json").read_text())
    assert code == 0 and not [c for c in report["results"] if not c["ok"]]
    faults, kill = report["meta"]["faults"], report["meta"]["kill_resume"]
    assert faults["fault_events"] >= 1 and faults["monitor"]["nan_worlds"] == faults["fault_events"]
    assert kill["killed"] and kill["metrics_iterations"][-1] == kill["last_checkpoint_iteration"] + 2
    assert [r["rollout"] for r in faults["memory_series"]] == list(range(1, len(faults["memory_series"]) + 1))
    assert (tmp_path / "soak_memory.png").stat().st_size > 1000
    # One mode per command: the other mode's results stay in soak.json.
    assert soak.main(["--mode", "kill_resume", "--device", "cuda", "--num_envs", "8", "--out", str(tmp_path),
                      "--run_dir", str(tmp_path / "runs")]) in (0, 1)
    again = json.loads((tmp_path / "soak.json").read_text())
    assert again["meta"]["faults"] == faults and {c["mode"] for c in again["results"]} == {"faults", "kill_resume"}
