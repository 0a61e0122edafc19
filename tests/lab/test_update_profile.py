"""lab.benchmarks.update_profile on the CPU at toy size: the third update's profile, its report, its refusals."""

from __future__ import annotations

import json
from types import SimpleNamespace

import pytest
import torch

from lab.benchmarks import update_profile


def test_the_profile_of_one_update_lists_its_heaviest_ops_and_their_total(tmp_path, monkeypatch):
    from tocabi_torchrl.rl import trainer

    profiled, update_stats = [], trainer._update_stats

    def counted(*args, **kwargs):  # which of the run's updates ran under the profiler
        profiled.append(torch.autograd.profiler._is_profiler_enabled)
        return update_stats(*args, **kwargs)

    monkeypatch.setattr(trainer, "_update_stats", counted)
    update_profile.main(["--device", "cpu", "--num_envs", "8", "--rows", "200", "--out", str(tmp_path),
                         "--run_dir", str(tmp_path / "runs"), "--name", "up"])
    assert profiled == [False, False, True, False]  # the third of four, alone
    r = json.loads((tmp_path / "up.json").read_text())["results"]
    # 8 envs x 48 steps, mini-batches of a quarter of the rollout (the throughput benchmarks' rule), 5 epochs.
    assert (r["minibatch_size"], r["minibatch_steps"], r["clock"]) == (96, 20, "host")
    own = [e["own_ms"] for e in r["top"]]
    assert own == sorted(own, reverse=True) and 0 < sum(own) <= r["update_ms"] + 1e-9
    # One update's twenty mini-batch steps: one optimiser step each, no more, no fewer.
    assert {e["name"]: e["calls"] for e in r["top"]}["Optimizer.step#Adam.step"] == 20
    page = (tmp_path / "up.md").read_text()
    assert f"**{r['update_ms']:.1f} ms** of host time" in page and "the loss eager" in page


def test_on_a_gpu_the_total_counts_each_kernel_once():
    from torch.autograd import DeviceType

    def entry(key, device_type, own_gpu_us, annotation=False):
        return SimpleNamespace(key=key, device_type=device_type, self_device_time_total=own_gpu_us,
                               self_cpu_time_total=5.0, is_user_annotation=annotation)

    table = [entry("aten::index", DeviceType.CPU, 14.0),  # the op: its own GPU time is its kernel's
             entry("index_elementwise_kernel", DeviceType.CUDA, 14.0),
             entry("gemm", DeviceType.CUDA, 30.0), entry("my_range", DeviceType.CUDA, 44.0, annotation=True)]
    pairs = update_profile.own_times(table, cuda=True)
    assert [(e.key, us) for e, us in pairs] == [("gemm", 30.0), ("index_elementwise_kernel", 14.0)]
    assert [us for _, us in update_profile.own_times(table, cuda=False)] == [5.0] * 4


def test_the_profile_refuses_an_overlapped_update_and_bad_counts(tmp_path, capsys):
    with pytest.raises(SystemExit, match="leave ppo.overlap_update off"):
        update_profile.profile_update(8, "cpu", {"ppo.overlap_update": True}, str(tmp_path))
    with pytest.raises(SystemExit):
        update_profile.main(["--device", "cpu", "--rows", "0"])
    assert "--num_envs and --rows take counts >= 1" in capsys.readouterr().err
