"""Data-parallel PPO pieces on 2 gloo ranks (CPU): averaged gradients equal the 1-rank gradient of the union of the
ranks' mini-batches, so parameters stay identical across ranks and equal a 1-rank run over the same data; running
observation statistics merge exactly; the torchrun layout is read and checked."""

from __future__ import annotations

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from tensordict import TensorDict
from torch.nn.parallel import DistributedDataParallel
from torchrl.modules import ValueOperator
from torchrl.objectives import ClipPPOLoss

from tocabi_torchrl.rl.actors import make_actor
from tocabi_torchrl.rl.curves import read_metrics
from tocabi_torchrl.rl import distributed
from tocabi_torchrl.rl.distributed import (DistInfo, GradientAllReduce, RunningStatsSync, all_reduce_mean,
                                           broadcast_module, from_environment, init_distributed, rank_seed, shutdown)
from tocabi_torchrl.rl.networks import make_mlp
from tocabi_torchrl.config import RunConfig
from tocabi_torchrl.rl.trainer import _episode_metrics, make_update_step
from tocabi_torchrl.rl.update_step import MinibatchStep
from tocabi_torchrl.transforms.normalize import RunningNormalization

pytestmark = pytest.mark.skipif(not dist.is_available() or not dist.is_gloo_available(),
                                reason="torch.distributed with gloo is needed")

OBS, ACT, ROWS, STEPS = 9, 4, 64, 3


def _agent(seed: int):
    torch.manual_seed(seed)
    actor = make_actor(OBS, ACT, (32, 16), "elu", init_std=0.2, learn_std=False)
    critic = ValueOperator(make_mlp(OBS, (32, 16), 1, "elu"), in_keys=["observation"])
    # Mini-batch advantage normalisation would make each rank's loss depend on its half only: off, so that the mean
    # of the ranks' losses is exactly the loss of the union.
    loss = ClipPPOLoss(actor, critic, clip_epsilon=0.2, entropy_bonus=False, normalize_advantage=False)
    loss.set_keys(sample_log_prob="action_log_prob")
    params = [p for p in [*actor.parameters(), *critic.parameters()] if p.requires_grad]
    return actor, critic, loss, params


def _batch(rows: int) -> TensorDict:
    g = torch.Generator().manual_seed(7)
    return TensorDict({
        "observation": torch.randn(rows, OBS, generator=g),
        "action": torch.randn(rows, ACT, generator=g),
        "action_log_prob": -torch.rand(rows, generator=g) * 4,
        "advantage": torch.randn(rows, 1, generator=g),
        "value_target": torch.randn(rows, 1, generator=g),
        "state_value": torch.randn(rows, 1, generator=g),
    }, batch_size=[rows])


def _flat(params) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in params])


def _train_steps(rows: TensorDict, info: DistInfo, init_seed: int,
                 grad_sync: str | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    actor, critic, loss, params = _agent(init_seed)
    broadcast_module(actor, info)
    broadcast_module(critic, info)
    opt = torch.optim.Adam(params, lr=3e-3)
    if grad_sync is None:
        step = MinibatchStep(loss, opt, params, max_grad_norm=0.5, grad_sync=GradientAllReduce(info))
    else:  # as train() builds it from the config
        cfg = RunConfig()
        cfg.ppo.max_grad_norm, cfg.ppo.grad_sync, cfg.ppo.update_graph = 0.5, grad_sync, False
        cfg.validate()
        step = make_update_step(cfg, loss, opt, torch.device("cpu"), info)
        assert step.grad_sync is None and isinstance(step.loss_module, DistributedDataParallel), "DDP not used"
    stats = torch.zeros(4)
    for _ in range(STEPS):
        stats += step(rows)
    return _flat(params), all_reduce_mean(stats / STEPS, info)


def test_stats_sync_refuses_a_normalizer_not_yet_sized():
    # Sized later by its first observation, its merge would broadcast a (1,) base over (2D + 1,) moments.
    with pytest.raises(ValueError, match="RunningStatsSync needs sized statistics"):
        RunningStatsSync([RunningNormalization(init_count=1000.0)], DistInfo(0, 2, 0))
    RunningStatsSync([RunningNormalization(dim=3)], DistInfo(0, 2, 0))  # sized: taken


def _worker(rank: int, world: int, init_file: str, out: dict, run_dir: str = "", runs: tuple = ()) -> None:
    """The pieces above on this rank, then the training ``runs`` (:func:`_train_runs`) in the same process group."""
    info = DistInfo(rank, world, rank)
    init_distributed(info, torch.device("cpu"), init_method=f"file://{init_file}")
    try:
        full = _batch(ROWS)
        half = full[rank * ROWS // world:(rank + 1) * ROWS // world]
        # Different initial weights per rank: the broadcast must make them rank 0's.
        params, stats = _train_steps(half, info, init_seed=100 + rank)
        params_ddp, _ = _train_steps(half, info, init_seed=100 + rank, grad_sync="ddp")
        gathered = [torch.zeros_like(params) for _ in range(world)]
        dist.all_gather(gathered, params)

        # Running statistics: each rank folds in its own rows, then the sync merges them.
        norm = RunningNormalization(dim=OBS, init_mean=[0.5] * OBS, init_var=[2.0] * OBS, init_count=10.0)
        sync = RunningStatsSync([norm], info)
        g = torch.Generator().manual_seed(11)
        data = [torch.randn(30 + 7 * r, OBS, generator=g) * (1 + r) + r for r in range(world)]
        norm.update(data[rank])
        sync.sync()
        norm.update(data[rank][:5] * 3)  # a second rollout: only what was added since the last sync is merged
        sync.sync()
        out[rank] = {"params": params, "params_ddp": params_ddp, "all": torch.stack(gathered), "stats": stats,
                     "norm": (norm.count.clone(), norm.mean.clone(), norm.var.clone()), "data": data,
                     "episodes": _episode_metrics(_rollout(rank), info),
                     "episodes_rank0_none": _episode_metrics(_rollout(rank, finish=rank == 1), info),
                     "runs": _train_runs(info, run_dir, runs)}
    finally:
        dist.destroy_process_group()


def _rollout(rank: int, finish: bool = True) -> TensorDict:
    """A (4 envs, 5 steps) batch whose ranks finish different numbers of episodes (rank 0: 1, rank 1: 3; none
    with ``finish`` False)."""
    done = torch.zeros(4, 5, 1, dtype=torch.bool)
    done[0, 2] = finish
    if rank == 1 and finish:
        done[1, 4] = done[2, 0] = True
    g = torch.Generator().manual_seed(rank)
    nxt = {"done": done, "terminated": done.clone(), "reward": torch.rand(4, 5, 1, generator=g),
           "episode_reward": torch.rand(4, 5, 1, generator=g) * 100 * (rank + 1),
           "step_count": torch.randint(1, 1000, (4, 5, 1), generator=g),
           "reward_terms": TensorDict({"qpos": torch.rand(4, 5, generator=g)}, batch_size=[4, 5])}
    return TensorDict({"next": TensorDict(nxt, batch_size=[4, 5])}, batch_size=[4, 5])


def _one_rank_run(run_dir, **options):
    """A 1-rank cpu_smoke run of 2 envs x 4 steps in ``run_dir`` (a new one, or ``resume`` one)."""
    from tocabi_torchrl.rl import preset_config
    from tocabi_torchrl.rl.trainer import train

    return train(preset_config("cpu_smoke", device="cpu", **{"env.num_envs": 2, "ppo.steps_per_env": 4,
                 "ppo.minibatch_size": 4}, run_dir=str(run_dir), checkpoint_every=1, progress_bar=False,
                               eval_at_end=False, **options))


@pytest.fixture(scope="module")
def two_ranks(tmp_path_factory):
    """Two gloo ranks, spawned once for the module (each spawned interpreter spends seconds importing torch, torchrl
    and the package): ``[rank]`` holds the pieces' results and, under "runs", the two 2-rank training runs of
    test_two_ranks_train_end_to_end_and_resume_on_one: a new run "dp", then the 1-rank run "one" continued. "one"
    is trained here first; "root" is the runs' folder, "one" the 1-rank run's result, std curve and iteration 3
    and 4 env steps as they were before the ranks continued it."""
    root = tmp_path_factory.mktemp("gloo")
    one = _one_rank_run(root, total_env_steps=32, name="one", checkpoint_keep_last=0)
    std_one = [float(r["action_std"]) for r in read_metrics(root / "one")]
    saved = {i: torch.load(root / "one" / "checkpoints" / f"iter_{i:06d}.pt", weights_only=True)["env_steps"]
             for i in (3, 4)}
    more = {"name": "one", "total_env_steps": 64, "resume": str(root / "one"), "checkpoint_keep_last": 0}
    out = mp.Manager().dict()
    mp.spawn(_worker, args=(2, str(root / "init"), out, str(root), ({}, more)), nprocs=2, join=True)
    return {**dict(out), "root": root, "one": (one.iterations, std_one, saved)}


def test_two_ranks_keep_identical_parameters(two_ranks):
    torch.testing.assert_close(two_ranks[0]["all"][0], two_ranks[0]["all"][1], rtol=0, atol=0)
    torch.testing.assert_close(two_ranks[0]["params"], two_ranks[1]["params"], rtol=0, atol=0)
    start, _, _, params = _agent(100)
    assert not torch.allclose(two_ranks[0]["params"], _flat(params)), "nothing trained"


def test_two_ranks_equal_one_rank_on_the_union_of_their_minibatches(two_ranks):
    one, stats = _train_steps(_batch(ROWS), DistInfo(), init_seed=100)
    torch.testing.assert_close(two_ranks[0]["params"], one, rtol=1e-5, atol=1e-6)
    # The mean of the ranks' mean losses is the loss of the union (equal halves): the logged stats agree too.
    torch.testing.assert_close(two_ranks[0]["stats"][:2], stats[:2], rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(two_ranks[0]["stats"], two_ranks[1]["stats"], rtol=0, atol=0)


def test_ddp_around_the_loss_averages_gradients_as_the_all_reduce_does(two_ranks):
    """ppo.grad_sync=ddp (DistributedDataParallel around the TorchRL loss, eager): the same parameters on both ranks,
    equal to the captured-all-reduce path's after the same mini-batch steps."""
    torch.testing.assert_close(two_ranks[0]["params_ddp"], two_ranks[1]["params_ddp"], rtol=0, atol=0)
    torch.testing.assert_close(two_ranks[0]["params_ddp"], two_ranks[0]["params"], rtol=1e-6, atol=1e-7)


def test_ddp_is_refused_with_a_captured_update_and_unknown_syncs_are_named():
    cfg = RunConfig()
    cfg.ppo.grad_sync = "ddp"
    with pytest.raises(ValueError, match="set ppo.update_graph=false"):
        cfg.validate()
    cfg.ppo.update_graph = False
    cfg.validate()
    cfg.ppo.grad_sync = "horovod"
    with pytest.raises(ValueError, match="grad_sync.*allreduce.*ddp"):
        cfg.validate()
    # One rank: the loss is not wrapped and nothing is exchanged, whatever the option says.
    cfg.ppo.grad_sync = "ddp"
    _, _, loss, params = _agent(0)
    step = make_update_step(cfg, loss, torch.optim.Adam(params), torch.device("cpu"), DistInfo())
    assert step.loss_module is loss and step.grad_sync is None


def test_running_statistics_merge_exactly(two_ranks):
    data = two_ranks[0]["data"]
    ref = RunningNormalization(dim=OBS, init_mean=[0.5] * OBS, init_var=[2.0] * OBS, init_count=10.0)
    ref.update(torch.cat(data))
    ref.update(torch.cat([d[:5] * 3 for d in data]))
    for rank in (0, 1):
        count, mean, var = two_ranks[rank]["norm"]
        assert count.item() == pytest.approx(ref.count.item())
        torch.testing.assert_close(mean, ref.mean, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(var, ref.var, rtol=1e-9, atol=1e-10)


def test_episode_statistics_weigh_each_ranks_episodes(two_ranks):
    """Merged over 2 ranks that finished 1 and 3 episodes: the values of the union of both batches (4 episodes),
    not the mean of the two ranks' means."""
    union = _episode_metrics(torch.cat([_rollout(0), _rollout(1)], dim=0))
    assert union["episodes_finished"] == 4
    for rank in (0, 1):
        merged = two_ranks[rank]["episodes"]
        assert merged.keys() == union.keys()
        for key, value in union.items():
            assert merged[key] == pytest.approx(value, rel=1e-6), key
    # A rank that finished no episode adds nothing (before: its NaN made the merged value NaN).
    only_rank1 = _episode_metrics(_rollout(1))
    for rank in (0, 1):
        merged = two_ranks[rank]["episodes_rank0_none"]
        assert merged["episodes_finished"] == 3
        assert merged["episode_return"] == pytest.approx(only_rank1["episode_return"], rel=1e-6)
        assert merged["episode_length"] == pytest.approx(only_rank1["episode_length"], rel=1e-6)
    alone = [_episode_metrics(_rollout(r)) for r in (0, 1)]
    naive = (alone[0]["episode_return"] + alone[1]["episode_return"]) / 2
    assert union["episode_return"] != pytest.approx(naive, rel=1e-3)  # the data makes the weighting matter


def test_torchrun_layout_is_read_and_checked():
    assert from_environment({}) == DistInfo(0, 1, 0) and not DistInfo().enabled and DistInfo().is_main
    info = from_environment({"RANK": "3", "WORLD_SIZE": "4", "LOCAL_RANK": "1"})
    assert (info.rank, info.world_size, info.local_rank, info.enabled, info.is_main) == (3, 4, 1, True, False)
    assert rank_seed(5, info) == 8 and rank_seed(5, DistInfo()) == 5
    with pytest.raises(ValueError, match="RANK < WORLD_SIZE"):
        from_environment({"RANK": "2", "WORLD_SIZE": "2"})
    with pytest.raises(ValueError, match="WORLD_SIZE='two' is not an integer"):
        from_environment({"WORLD_SIZE": "two"})


def test_one_rank_helpers_are_no_ops():
    info = DistInfo()
    t = torch.tensor([1.0, 3.0])
    assert all_reduce_mean(t, info) is t and t.tolist() == [1.0, 3.0]
    assert init_distributed(info, torch.device("cpu")) == torch.device("cpu") and not dist.is_initialized()
    w = torch.nn.Parameter(torch.ones(2))
    w.grad = torch.full((2,), 4.0)
    GradientAllReduce(info)([w])
    assert w.grad.tolist() == [4.0, 4.0]



def test_shutdown_destroys_a_gloo_group_and_ends_an_nccl_rank_without_teardown(tmp_path, monkeypatch):
    info = DistInfo(0, 2, 0)
    shutdown(DistInfo())  # one rank: nothing to leave
    dist.init_process_group("gloo", rank=0, world_size=1, init_method=f"file://{tmp_path / 'init'}")
    try:
        ended = []
        monkeypatch.setattr(distributed.os, "_exit", lambda code: ended.append(code))
        monkeypatch.setattr(distributed.dist, "get_backend", lambda: "nccl")
        shutdown(info, code=3)  # NCCL: the process would end here, the group left as it is (pytorch#115388)
        assert ended == [3] and dist.is_initialized()
        monkeypatch.undo()
        shutdown(info)  # gloo: destroyed, and the call returns
        assert not dist.is_initialized()
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()


def _train_runs(info: DistInfo, run_dir: str, runs) -> list[dict]:
    """Train each of ``runs`` (preset overrides of a 2-envs x 4-steps cpu_smoke run named "dp") in turn on this
    rank of the process group; one result per run."""
    import dataclasses

    from tocabi_torchrl.rl import preset_config
    from tocabi_torchrl.rl.trainer import build_env, train

    results = []
    for options in runs:
        # A new run with running statistics, so that their merge is part of it (the presets use the reference's fixed
        # ones); a resumed run with the statistics it was saved with.
        normalization = "fixed" if "resume" in options else "running"
        cfg = preset_config("cpu_smoke", device="cpu", **{"env.num_envs": 2, "ppo.steps_per_env": 4,
                            "ppo.minibatch_size": 4, "transforms.normalization": normalization,
                            "total_env_steps": info.world_size * 2 * 16, "name": "dp", **options}, run_dir=run_dir,
                            checkpoint_every=1, progress_bar=False, eval_at_end=False)
        env = build_env(dataclasses.replace(cfg, seed=rank_seed(cfg.seed, info)), torch.device("cpu"),
                        for_training=True)
        result = train(cfg, env=env, dist_info=info)
        norm = next((t for t in env.transform if isinstance(t, RunningNormalization)), None)
        params = _flat([*result.agent.actor.parameters(), *result.agent.critic.parameters()])
        results.append({"iterations": result.iterations, "env_steps": result.env_steps, "params": params,
                        "norm": None if norm is None else (norm.count.clone(), norm.mean.clone())})
    return results


def test_two_ranks_train_end_to_end_and_resume_on_one(two_ranks):
    # The module's spawn trained the 1-rank run "one" (32 env steps), then on two ranks the new run "dp" and "one"
    # continued (its 32 steps done are 2 of their 16-step iterations).
    tmp_path, (one_iterations, std_one, saved) = two_ranks["root"], two_ranks["one"]
    assert one_iterations == 4
    (r0, r0_one), (r1, _) = two_ranks[0]["runs"], two_ranks[1]["runs"]
    # 2 ranks x 2 envs x 4 steps = 16 env steps per iteration: 4 iterations for the 64-step budget.
    assert r0["iterations"] == r1["iterations"] == 4 and r0["env_steps"] == r1["env_steps"] == 64
    torch.testing.assert_close(r0["params"], r1["params"], rtol=0, atol=0)
    assert r0["norm"][0].item() == r1["norm"][0].item() > 64  # both ranks' rows (plus the initial weight)
    torch.testing.assert_close(r0["norm"][1], r1["norm"][1], rtol=0, atol=0)
    run = tmp_path / "dp"
    ckpt = torch.load(run / "checkpoints" / "latest.pt", weights_only=True)
    assert ckpt["env_steps"] == 64
    rows = read_metrics(run)
    assert len(rows) == 4, "rank 0 alone logs: one row per iteration"
    assert sorted(p.name for p in run.iterdir()) == sorted(["checkpoints", "config.json", "metrics"])

    # With the budget scaled by the rank count (docs/training.md), the scheduled std falls per update exactly as in
    # a 1-rank run of the unscaled budget.
    std_dp = [float(r["action_std"]) for r in rows]
    assert std_dp == std_one and len(set(std_dp)) > 1, (std_dp, std_one)  # and it does fall

    # The same run goes on with one rank: the 64 steps done are 8 of its 8-step iterations, so its schedules go on
    # from there, while its files and metrics rows go on from its own iteration 4.
    result = _one_rank_run(tmp_path, total_env_steps=80, name="dp", resume=str(run),
                           **{"transforms.normalization": "running"})  # as "dp" was trained (and saved)
    assert result.iterations == 6 and result.env_steps == 80
    assert [int(float(r["iteration"])) for r in read_metrics(run)] == [1, 2, 3, 4, 5, 6]

    # The 1-rank run went on with two: numbered from the 2 two-rank iterations its 32 steps make, the new files
    # would have overwritten its iteration 3 and 4 files and repeated their metrics rows; they are 5 and 6.
    assert r0_one["iterations"] == 6 and r0_one["env_steps"] == 64
    files = tmp_path / "one" / "checkpoints"
    assert {i: torch.load(files / f"iter_{i:06d}.pt", weights_only=True)["env_steps"] for i in (3, 4, 5, 6)} == {
        **saved, 5: 48, 6: 64}
    assert [int(float(r["iteration"])) for r in read_metrics(tmp_path / "one")] == [1, 2, 3, 4, 5, 6]


def _torchrun_recipe(tmp_path, name: str, *options: str):
    """``torchrun --nproc_per_node 2 recipes/ppo_walk.py`` on the CPU: a 32-step cpu_smoke run named ``name``."""
    import os
    import shutil
    import subprocess
    from pathlib import Path

    torchrun = shutil.which("torchrun") or pytest.skip("torchrun is not on PATH")
    recipe = Path(__file__).resolve().parents[1] / "recipes" / "ppo_walk.py"
    return subprocess.run(
        [torchrun, "--standalone", "--nproc_per_node", "2", str(recipe), "--preset", "cpu_smoke", "--device", "cpu",
         "--env.num_envs", "2", "--ppo.steps_per_env", "4", "--ppo.minibatch_size", "4", "--total_env_steps", "32",
         *options,
         "--run_dir", str(tmp_path), "--name", name, "--eval_at_end", "false", "--progress_bar", "false"],
        capture_output=True, text=True, timeout=600, env={**os.environ, "PYTHONUNBUFFERED": "1"}, cwd=tmp_path)


def test_torchrun_runs_the_recipe_on_two_gloo_ranks(tmp_path):
    """The command the README gives, on the CPU: rank 0 alone writes the run folder."""
    proc = _torchrun_recipe(tmp_path, "dp")
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "done on 2 ranks: 32 env steps" in proc.stdout
    assert torch.load(tmp_path / "dp" / "checkpoints" / "latest.pt", weights_only=True)["env_steps"] == 32
    # The same command again: rank 0 refuses the existing run, and both ranks end with a one-line error each.
    proc = _torchrun_recipe(tmp_path, "dp")
    assert proc.returncode != 0 and 'ppo_walk.py", line' not in proc.stderr  # no rank's traceback
    assert "error (rank 0): run folder" in proc.stderr and "already holds a run" in proc.stderr
    assert "error (rank 1): another rank could not open the run" in proc.stderr


def test_torchrun_trains_the_recipe_with_ddp_on_two_gloo_ranks(tmp_path):
    """--ppo.grad_sync ddp from the command line to the trainer: two ranks train and end, rank 0 writes the run."""
    proc = _torchrun_recipe(tmp_path, "ddp", "--ppo.grad_sync", "ddp", "--ppo.update_graph", "false")
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "done on 2 ranks: 32 env steps" in proc.stdout
    saved = torch.load(tmp_path / "ddp" / "checkpoints" / "latest.pt", weights_only=True)
    assert saved["env_steps"] == 32 and saved["config"]["ppo"]["grad_sync"] == "ddp"


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available() or torch.cuda.device_count() < 2, reason="needs 2 GPUs")
@pytest.mark.parametrize("grad_sync", ["allreduce", "ddp"])
def test_torchrun_trains_on_two_gpus_with_nccl_and_ends(tmp_path, grad_sync):
    """NCCL between two GPUs, the all-reduce captured in the update graph (or DDP around the loss, eager): the recipe
    trains, rank 0 writes the run, and both ranks end (destroy_process_group after such a capture hung on an H100
    pair: pytorch#115388)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    recipe = Path(__file__).resolve().parents[1] / "recipes" / "ppo_walk.py"
    proc = subprocess.run(
        [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2", str(recipe),
         "--preset", "cpu_smoke", "--device", "cuda", "--env.num_envs", "64", "--ppo.steps_per_env", "8",
         "--ppo.minibatch_size", "256", "--total_env_steps", str(2 * 2 * 64 * 8), "--ppo.update_graph",
         str(grad_sync == "allreduce").lower(),
         "--ppo.grad_sync", grad_sync, "--run_dir", str(tmp_path),
         "--name", "dp", "--eval_at_end", "false", "--progress_bar", "false"],
        capture_output=True, text=True, timeout=900, env={**os.environ, "PYTHONUNBUFFERED": "1"}, cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "as a CUDA graph failed" not in proc.stderr  # the all-reduce really ran inside the captured update
    assert f"done on 2 ranks: {2 * 2 * 64 * 8:,} env steps" in proc.stdout
    assert torch.load(tmp_path / "dp" / "checkpoints" / "latest.pt", weights_only=True)["env_steps"] == 2 * 2 * 64 * 8
