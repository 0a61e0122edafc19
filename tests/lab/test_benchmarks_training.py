"""The training benchmarks that measure in child processes and under torchrun, on the CPU at toy size:
train_throughput (one child, two gloo ranks), scaling (a child per measurement, kept or redone by its status) and
the soak (a faulty training run)."""

from __future__ import annotations

import json
import shutil
import time
from types import SimpleNamespace

import pytest

from lab.benchmarks import common, scaling, soak, train_throughput


def test_train_throughput_smoke_in_a_child_process_and_on_two_ranks(tmp_path):
    train_throughput.main(["--device", "cpu", "--num_envs", "8", "--iterations", "2", "--warmup", "1", "--nproc", "1",
                           "2", "--raw_steps", "0", "--set", "ppo.steps_per_env=8", "ppo.actor_hidden=8 8", "--out",
                           str(tmp_path), "--run_dir", str(tmp_path / "runs")])
    one, two = json.loads((tmp_path / "train_throughput.json").read_text())["results"]
    for r, k in ((one, 1), (two, 2)):
        assert r["num_envs"] == 8 and r["train_env_steps_per_s"] > 0 and r["overrides"]["ppo.actor_hidden"] == [8, 8]
        # 3 iterations of K x 8 envs x 8 steps: torchrun's K gloo ranks, counted together by rank 0
        assert r["gpus"] == k and r["iterations"] == 3 and r["env_steps"] == 3 * k * 64
    speedup = two["train_env_steps_per_s"] / one["train_env_steps_per_s"]
    assert f"| 2 | {speedup:.2f} | 8 |" in (tmp_path / "train_throughput.md").read_text()


@pytest.mark.slow
def test_scaling_measures_in_a_child_process_and_reports(tmp_path):
    args = ["--kind", "time", "--backend", "cpu", "--num_envs", "8", "--hidden", "8", "--max_minutes", "0.02",
            "--results", str(tmp_path / "scaling"), "--run_dir", str(tmp_path / "runs")]
    scaling.main(args)
    first = json.loads((tmp_path / "scaling" / "time_cpu_0000008.json").read_text())
    assert first["status"] == "partial" and 0 < first["env_steps"] < scaling.TARGET and first["host"]["peak_rss_gib"]
    scaling.main(args)  # an existing result is kept unless its status is redone
    assert json.loads((tmp_path / "scaling" / "time_cpu_0000008.json").read_text()) == first
    scaling.main(["--report", "--results", str(tmp_path / "scaling")])
    assert "| CPU (C MuJoCo) | 8 | 256 / 512 | - |" in (tmp_path / "scaling.md").read_text()


def test_scaling_keeps_a_failed_measurement_as_a_status_says_so_and_still_reports(tmp_path, monkeypatch, capsys):
    # A time or raw run that failed or ran out of memory has no rates: --report once died on its record (KeyError),
    # and a failed measurement exited 0 without its cause.
    results, base = tmp_path / "scaling", ["--results", str(tmp_path / "scaling"), "--run_dir", str(tmp_path / "runs")]
    shutil.copytree(common.DOCS / "scaling", results)  # the committed results, plus the failures below

    def child(module, args, env=None, nproc=None):
        oom = args[args.index("--num_envs") + 1] == "131072"
        raise RuntimeError("python -m lab.benchmarks.train_throughput --child ... failed (1):\nTraceback (...)\n"
                           + ("torch.OutOfMemoryError: CUDA out of memory" if oom else
                              "AssertionError: Torch not compiled with CUDA enabled"))

    monkeypatch.setattr(common, "run_child", child)
    with pytest.raises(SystemExit, match="failed at 8192 envs"):
        scaling.main(["--kind", "time", "--num_envs", "8192", "131072", *base])
    out = capsys.readouterr().out
    assert "time_gpu_0008192.json: the measurement failed: AssertionError: Torch not compiled with CUDA" in out
    assert "time_gpu_0131072.json: oom" in out  # a result: no failure
    with pytest.raises(SystemExit, match="failed at 2048 envs"):
        scaling.main(["--kind", "raw", "--num_envs", "2048", *base])
    with pytest.raises(SystemExit, match="failed at 8192 envs"):  # kept, not measured again: still failed
        scaling.main(["--kind", "time", "--num_envs", "8192", *base])
    assert "kept time_gpu_0008192.json (status error; --redo error measures it again)" in capsys.readouterr().out
    scaling.main(["--report", *base[:2]])
    text = (tmp_path / "scaling.md").read_text()
    for n, status in (("8,192", "error"), ("131,072", "oom")):
        assert f"| GPU (mujoco-warp) | {n} |{' - |' * 8} {status} |" in text
    assert "| 4,096 | 116,255 |" in text  # the measured rows as before


@pytest.mark.slow  # a faulty training run of 15 s (two rollouts at least on a loaded 2-core machine)
def test_tiny_soak_on_the_cpu(tmp_path):
    code = soak.main(["--num_envs", "8", "--minutes", "0.25", "--device", "cpu", "--fault_every", "40",
                      "--out", str(tmp_path), "--run_dir", str(tmp_path / "runs")])
    report = json.loads((tmp_path / "soak.json").read_text())
    assert code == 0 and report["results"] and not [c for c in report["results"] if not c["ok"]]
    faults = report["meta"]["faults"]
    assert faults["fault_events"] >= 1 and faults["monitor"]["nan_worlds"] == faults["fault_events"]
    assert [r["rollout"] for r in faults["memory_series"]] == list(range(1, len(faults["memory_series"]) + 1))
    assert (tmp_path / "soak_memory.png").stat().st_size > 1000


def test_train_throughput_counts_the_whole_set_up_and_the_cores_of_the_timed_training_only(tmp_path, monkeypatch):
    # setup_s once counted only the argument parsing (the set-up happens inside train(), before its clock starts),
    # and cores_used_mean divided the set-up's CPU time too by the training's wall time. Here train() keeps a core
    # busy for 0.4 s setting up, then its timed training idles for 0.3 s.
    from tocabi_torchrl.rl import trainer

    def train(cfg):
        end = time.process_time() + 0.4
        while time.process_time() < end:  # building the env, compiling, the agent
            pass
        trainer.make_collector(cfg, None, None, None, 0)  # the trainer starts its clock right after
        time.sleep(0.3)
        rows = [{"env_steps": str(64 * k), "wall_s": str(0.1 * k), "update_s": "0.01"} for k in (1, 2, 3)]
        return SimpleNamespace(env_steps=192, wall_seconds=0.3, iterations=3, env_graph=False), rows

    monkeypatch.setattr(trainer, "make_collector", lambda *a, **k: "collector")
    monkeypatch.setattr(common, "train", train)
    monkeypatch.setattr(train_throughput, "STARTED", time.perf_counter())  # as if this process started now
    r = train_throughput.measure(8, 2, 1, 0, "cpu", str(tmp_path), {})
    assert r["train_wall_s"] == 0.3 and r["setup_s"] >= 0.4 and r["cores_used_mean"] < 0.5, r
    assert trainer.make_collector(None) == "collector"  # the trainer is itself again


def _children_started(monkeypatch) -> list:
    """The argument lists of the children ``train_throughput.main`` starts, each start ending the parent at once."""
    children = []

    def run_child(name, argv, nproc=None):
        children.append(argv)
        raise SystemExit(0)

    monkeypatch.setattr(common, "run_child", run_child)
    return children


def test_train_throughput_compile_loss_sets_ppo_compile_loss_in_the_child(tmp_path, monkeypatch):
    from tocabi_torchrl.rl import trainer

    seen = {}

    def train(cfg):
        seen["compile_loss"] = cfg.ppo.compile_loss  # what the trainer builds its update step from
        trainer.make_collector(cfg, None, None, None, 0)
        rows = [{"env_steps": str(64 * k), "wall_s": str(0.1 * k), "update_s": "0.01"} for k in (1, 2, 3)]
        return SimpleNamespace(env_steps=192, wall_seconds=0.3, iterations=3, env_graph=False), rows

    monkeypatch.setattr(trainer, "make_collector", lambda *a, **k: "collector")
    monkeypatch.setattr(common, "train", train)
    for compiled in (True, False):
        r = train_throughput.measure(8, 2, 1, 0, "cpu", str(tmp_path), {}, compile_loss=compiled)
        assert r["compile_loss"] is compiled and seen["compile_loss"] is compiled
        assert r["overrides"] == {}  # the flag is recorded as such, not as a --set entry
    # The parent hands the flag to each child it starts.
    children = _children_started(monkeypatch)
    with pytest.raises(SystemExit):
        train_throughput.main(["--device", "cpu", "--num_envs", "8", "--compile_loss", "--out", str(tmp_path)])
    assert "--compile_loss" in children[0]
    with pytest.raises(SystemExit):  # no training iteration: nothing to compile
        train_throughput.main(["--device", "cpu", "--num_envs", "8", "--compile_loss", "--iterations", "0",
                               "--warmup", "0", "--out", str(tmp_path)])
    assert len(children) == 1


def test_train_throughput_compact_reset_sets_the_small_pass_of_the_childs_env(tmp_path, monkeypatch):
    from tocabi_torchrl.rl import trainer
    from tocabi_torchrl.sim import warp_backend

    rule, seen = warp_backend.compact_reset_capacity, []

    def train(cfg):
        seen.append(warp_backend.compact_reset_capacity(16384))  # what the env the run builds would use
        trainer.make_collector(cfg, None, None, None, 0)
        rows = [{"env_steps": str(64 * k), "wall_s": str(0.1 * k), "update_s": "0.01"} for k in (1, 2, 3)]
        return SimpleNamespace(env_steps=192, wall_seconds=0.3, iterations=3, env_graph=False), rows

    monkeypatch.setattr(trainer, "make_collector", lambda *a, **k: "collector")
    monkeypatch.setattr(common, "train", train)
    for value in (0, 64, None):
        r = train_throughput.measure(8, 2, 1, 0, "cpu", str(tmp_path), {}, compact_reset=value)
        assert r["compact_reset"] == value and warp_backend.compact_reset_capacity is rule
    assert seen == [0, 64, rule(16384)]
    children = _children_started(monkeypatch)
    with pytest.raises(SystemExit):
        train_throughput.main(["--device", "cpu", "--num_envs", "8", "--compact_reset", "2", "--out", str(tmp_path)])
    assert children[0][-2:] == ["--compact_reset", "2"]
    with pytest.raises(SystemExit):  # as many as the envs: not a small Data
        train_throughput.main(["--device", "cpu", "--num_envs", "8", "--compact_reset", "8", "--out", str(tmp_path)])
    assert len(children) == 1


def test_train_throughput_ceiling_refuses_several_ranks_and_a_captured_env_step(tmp_path, capsys):
    with pytest.raises(SystemExit):
        train_throughput.main(["--device", "cpu", "--num_envs", "8", "--nproc", "2", "--ceiling"])
    assert "--ceiling times the physics of one rank's timed training iterations: use --nproc 1" in \
        capsys.readouterr().err
    with pytest.raises(SystemExit, match="ppo.cuda_graph=off"):
        train_throughput.measure(8, 1, 1, 0, "cpu", str(tmp_path), {"ppo.cuda_graph": "on"}, ceiling=True)


class _Mark:
    """A stand-in for a completed CUDA event at ``at`` ms on one clock."""

    def __init__(self, at):
        self.at = at

    def elapsed_time(self, other):
        return other.at - self.at


def test_the_ceiling_counts_only_the_steps_no_update_ran_beside():
    # Times on one clock (ms from the origin): steps at 0-1, 2-3 and 5-6; an update ran from 2.5 to 5.5, beside the
    # second and the third, so the ceiling is the first step's 1 ms alone.
    physics = SimpleNamespace(cuda=True, spans=[(_Mark(0.0), _Mark(1.0)), (_Mark(2.0), _Mark(3.5)),
                                                  (_Mark(5.0), _Mark(6.5))], summary=lambda n: {})
    assert train_throughput.uncontended_ms(physics, [(_Mark(2.5), _Mark(5.5))], _Mark(-1.0)) == (1.0, 1)
    with pytest.raises(RuntimeError, match="every timed simulator step ran beside an update"):
        train_throughput.uncontended_ms(physics, [(_Mark(-0.5), _Mark(9.0))], _Mark(-1.0))
    physics.cuda = False  # host clocks, no updates beside: every step
    physics.spans = [(0.0, 0.001), (0.002, 0.004)]
    ms, steps = train_throughput.uncontended_ms(physics, [])
    assert steps == 2 and ms == pytest.approx(1.5)


def test_the_host_split_takes_medians_without_the_first_and_the_last_update():
    # The first update captures its graph, the last is read at once at the run's end: neither is a steady one.
    spans = [(_Mark(0.0), _Mark(d)) for d in (90.0, 20.0, 30.0, 40.0, 500.0)]  # ms on the side stream
    overlap = SimpleNamespace(launch_s=[9.0, 0.002, 0.004, 0.003, 0.5], finish_s=[0.0, 0.010, 0.030, 0.020, 0.6],
                              spans=spans)
    split = train_throughput.update_host_split([overlap])
    assert split == pytest.approx({"update_launch_ms": 3.0, "update_finish_ms": 20.0, "update_span_ms": 30.0})
    # Inline (no side stream, no spans) and with two updates only (both kept): no span, and the plain median.
    inline = SimpleNamespace(launch_s=[0.001, 0.003], finish_s=[0.0, 0.002], spans=[])
    assert train_throughput.update_host_split([inline]) == pytest.approx({"update_launch_ms": 2.0,
                                                                          "update_finish_ms": 1.0})
    assert train_throughput.update_host_split([]) == {}
    # Per launch, the host's time in each mini-batch call and the allocator's counts: medians over the middle updates.
    calls = [[0.05, 0.05], [1e-5, 0.2, 1e-5], [2e-5, 2e-5, 0.002], [0.3]]
    allocs = [{"num_device_alloc": 9}, {"num_device_alloc": 2}, {"num_device_alloc": 4}, {"num_device_alloc": 0}]
    traced = SimpleNamespace(launch_s=[1.0, 0.3, 0.01, 0.4], finish_s=[0.0] * 4, spans=[], calls=calls, allocs=allocs,
                             pending=[5, 3, 1, 0])
    split = train_throughput.update_host_split([traced])
    assert split["update_calls"] == 3 and split["update_calls_over_1ms"] == 1
    assert split["update_call_max_ms"] == pytest.approx(101.0)  # the median of the middle updates' 200 and 2 ms
    assert split["update_launch_num_device_alloc"] == 3
    assert split["update_launch_steps_pending"] == 2  # the median of the middle launches' 3 and 1 steps


class _Event(_Mark):
    """A CUDA event's face: reached (the GPU ran past it) or not yet."""

    def __init__(self, at, done=True):
        super().__init__(at)
        self.done = done

    def query(self):
        return self.done


def test_the_steps_the_gpu_has_still_to_run_and_the_gaps_between_rollouts():
    # Two rollouts of three steps on one clock (ms): within a rollout the steps are 1 ms apart, between the two 50 ms
    # (the boundary: the second rollout starts at recorded step 3).
    starts = [0.0, 3.0, 6.0, 58.0, 61.0, 64.0]
    physics = SimpleNamespace(cuda=True, spans=[(_Event(t), _Event(t + 2.0)) for t in starts])
    gaps = train_throughput.rollout_gaps(physics, [0, 3, 6])  # 0 and 6 bound nothing recorded on both sides
    assert gaps == pytest.approx({"rollout_gap_ms": 50.0, "step_gap_ms": 1.0})
    assert train_throughput.rollout_gaps(physics, []) == pytest.approx({"step_gap_ms": 1.0})
    # The host is two steps ahead when the last two end events are not reached; host clocks never are.
    physics.spans[-1][1].done = physics.spans[-2][1].done = False
    assert train_throughput.steps_pending(physics.spans) == 2
    assert train_throughput.steps_pending(physics.spans, last=1) == 1
    assert train_throughput.steps_pending([(0.0, 0.001), (0.002, 0.003)]) == 0


def test_train_throughput_ceiling_times_the_physics_of_the_timed_iterations_in_place(tmp_path):
    # --ceiling: the simulator's own time over exactly the steady rate's iterations (2 timed iterations of 8 envs x 8
    # steps: 16 policy steps), its ceiling num_envs / time, and train / ceiling beside train / raw. The run overlaps
    # its updates (ppo.overlap_update); on the CPU nothing runs beside the rollout, so every timed step counts.
    train_throughput.main(["--device", "cpu", "--num_envs", "8", "--iterations", "2", "--warmup", "1", "--ceiling",
                           "--raw_steps", "0", "--set", "ppo.steps_per_env=8", "ppo.actor_hidden=8 8",
                           "ppo.overlap_update=true", "--out", str(tmp_path), "--run_dir", str(tmp_path / "runs")])
    (r,) = json.loads((tmp_path / "train_throughput.json").read_text())["results"]
    assert r["physics_steps_timed"] == r["physics_steps_recorded"] == 16 and r["physics_ms_per_policy_step"] > 0
    assert "update_ms_last" not in r  # overlapped: the update is no part of the step, the host's wait is the measure
    # The host's time between rollouts, split: queuing the update (on the CPU: running it), then waiting for it
    # (update_host_split, below: three updates, so the medians are the second's).
    assert r["update_launch_ms"] > 0 and r["update_finish_ms"] >= 0
    assert "update_span_ms" not in r  # no side stream on the CPU
    # Within each launch, every mini-batch call is timed: 4 mini-batches of the 64 frames (common.run_config takes a
    # quarter) x 5 epochs; eager on the CPU, each call runs its step, so none is free. No CUDA allocator off CUDA.
    assert r["update_calls"] == 20 and 0 < r["update_call_max_ms"] <= r["update_launch_ms"]
    assert not [k for k in r if k.startswith("update_launch_num_")]
    # Host clocks mark a step once it has run: the host is never ahead of them. Between the two timed rollouts GAE and
    # the whole update ran (on the CPU the launch runs its 20 mini-batch steps), so the gap there is many times the
    # gap between two steps; a boundary one step off would measure an ordinary step gap.
    assert r["update_launch_steps_pending"] == 0
    assert r["rollout_gap_ms"] > 5 * r["step_gap_ms"] > 0
    assert r["ceiling_env_steps_per_s"] == pytest.approx(8e3 / r["physics_ms_per_policy_step"])
    # The physics is part of the training step: training cannot outrun it.
    assert 0 < r["ratio_train_over_ceiling"] < 1
    assert r["ratio_train_over_ceiling"] == pytest.approx(r["train_env_steps_per_s"] / r["ceiling_env_steps_per_s"])
    page = (tmp_path / "train_throughput.md").read_text()
    assert "| train / ceiling |" in page and f"| {r['ratio_train_over_ceiling']:.3f} |" in page
    # Inline, the update's own time is recorded (GPU events around it on CUDA, the host's clock here).
    train_throughput.main(["--device", "cpu", "--num_envs", "8", "--iterations", "2", "--warmup", "1", "--ceiling",
                           "--raw_steps", "0", "--set", "ppo.steps_per_env=8", "ppo.actor_hidden=8 8",
                           "--out", str(tmp_path / "inline"), "--run_dir", str(tmp_path / "runs")])
    (r,) = json.loads((tmp_path / "inline" / "train_throughput.json").read_text())["results"]
    assert r["update_ms_last"] > 0
    # The phase benchmarks time one phase at a time: they refuse an overlapped run.
    with pytest.raises(SystemExit, match="ppo.overlap_update=false"):
        common.eager_step_config("step_timeline", 8, 2, {"ppo.overlap_update": True}, str(tmp_path), "t", "cpu")
