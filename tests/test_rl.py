"""PPO pieces: std schedule, actors, GAE with truncation vs termination, config errors, a tiny end-to-end run."""

from __future__ import annotations

import json
from pathlib import Path
import math

import pytest
import torch
from graph_emulation import EmulatedCapture
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.objectives.value import GAE

from tocabi_torchrl.rl import StdSchedule, action_std, make_actor, parse_args, preset_config, set_action_std
from tocabi_torchrl.rl.curves import read_metrics


@pytest.mark.parametrize("progress_remaining, std", [(1.0, 0.1), (0.9, 0.09), (0.75, 0.075), (0.6, 0.06),
                                                     (0.5, 0.05), (0.3, 0.05), (0.0, 0.05)])
def test_reference_std_schedule(progress_remaining, std):
    # std = 0.1·b + 0.05·(1 − b), b = 2P − 1 for P > 0.5 else 0 (spec §10.4), interpolated in std space.
    assert StdSchedule()(progress_remaining) == pytest.approx(std, abs=1e-12)


def test_std_schedule_is_not_log_linear():
    # At P = 0.75 a log-space interpolation would give sqrt(0.1 · 0.05) = 0.0707.
    assert StdSchedule()(0.75) != pytest.approx(math.sqrt(0.1 * 0.05), abs=1e-3)


def test_scheduled_actor_std_is_set_not_learned():
    actor = make_actor(237, 13, hidden=(32,), init_std=0.1)
    td = actor(TensorDict({"observation": torch.randn(5, 237)}, batch_size=[5]))
    torch.testing.assert_close(td["scale"], torch.full((5, 13), 0.1))
    assert not any("log_std" in n for n, p in actor.named_parameters()), "scheduled std must not be a parameter"
    set_action_std(actor, 0.05)
    torch.testing.assert_close(action_std(actor), torch.full((13,), 0.05))
    # The log-probability belongs to the unclipped sample.
    td = actor(TensorDict({"observation": torch.randn(5, 237)}, batch_size=[5]))
    dist = torch.distributions.Normal(td["loc"], td["scale"])
    torch.testing.assert_close(td["action_log_prob"], dist.log_prob(td["action"]).sum(-1))


def test_learned_std_actor_has_parameter():
    actor = make_actor(10, 3, hidden=(8,), init_std=0.5, learn_std=True)
    names = [n for n, _ in actor.named_parameters()]
    assert any("log_std" in n for n in names)
    torch.testing.assert_close(action_std(actor), torch.full((3,), 0.5))


def test_gae_bootstraps_truncation_but_not_termination():
    gamma, value = 0.9, 2.0
    critic = TensorDictModule(lambda obs: torch.full((*obs.shape[:-1], 1), value), in_keys=["observation"],
                              out_keys=["state_value"])
    gae = GAE(gamma=gamma, lmbda=1.0, value_network=critic, average_gae=False)
    obs = torch.zeros(2, 1, 3)
    reward = torch.ones(2, 1, 1)
    terminated = torch.tensor([True, False]).view(2, 1, 1)
    truncated = torch.tensor([False, True]).view(2, 1, 1)
    td = TensorDict(
        {"observation": obs,
         "next": {"observation": obs.clone(), "reward": reward, "terminated": terminated, "truncated": truncated,
                  "done": terminated | truncated}},
        batch_size=[2, 1],
    )
    gae(td)
    adv = td["advantage"].flatten()
    assert adv[0].item() == pytest.approx(1.0 - value)  # terminated: no bootstrap
    assert adv[1].item() == pytest.approx(1.0 + gamma * value - value)  # timeout: bootstrap from the final state


@pytest.mark.parametrize("path, value, match", [
    ("env.num_envs", 0, "num_envs"), ("ppo.gamma", 1.5, "gamma"), ("ppo.lr", 0.0, "lr"),
    ("ppo.lr_schedule", "cosine", "lr_schedule"), ("ppo.std_mode", "fixed", "std_mode"),
    ("loggers", ("csv", "mlflow"), "mlflow"), ("ppo.minibatch_size", 10**9, "rollout"),
    ("ppo.activation", "gelu", "activation"), ("env.control.mode", "velocity", "env.control.mode"),
    ("env.control.pd_action_scale", 0.0, "pd_action_scale"),
    ("transforms.reward_weights", ("body_vel=0.9",), "must be a RewardWeights"),
    ("transforms.reward_weights.body_vel", float("nan"), "transforms.reward_weights.body_vel must be a finite number"),
    ("transforms.reward_weights.speed", 1.0, "reward_weights has no 'speed'"),
    ("ppo.cuda_graph", "sometimes", "cuda_graph must be one of"),
])
def test_bad_config_values(path, value, match):
    with pytest.raises(ValueError, match=match):
        preset_config("default", **{path: value})


def test_unknown_preset_and_field():
    with pytest.raises(ValueError, match="unknown preset"):
        preset_config("fastest")
    with pytest.raises(ValueError, match=r"unknown config option 'learning_rate'"):
        preset_config("default", learning_rate=1e-3)


def test_command_line_overrides(capsys):
    cfg, _ = parse_args(["--preset", "reference", "--env.num_envs", "16", "--ppo.actor_hidden", "64", "32",
                         "--eval_at_end", "false", "--transforms.reward_weights.body_vel", "0.9",
                         "--transforms.reward_weights.qpos", "0.5"])
    assert cfg.transforms.reward_weight_map() == {"body_vel": 0.9, "qpos": 0.5}
    assert parse_args(["--preset", "reference"])[0].transforms.reward_weight_map() == {}  # the reference weights
    assert cfg.preset == "reference" and cfg.env.num_envs == 16 and cfg.ppo.actor_hidden == (64, 32)
    assert cfg.eval_at_end is False and cfg.ppo.minibatch_size == 128 and cfg.ppo.value_head_lr == 5e-4
    with pytest.raises(SystemExit):
        parse_args(["--env.num_envs", "many"])
    assert "Error parsing --env.num_envs: expected an int" in " ".join(capsys.readouterr().err.split())


@pytest.mark.parametrize("value, mode", [(True, "on"), (False, "off"), ("true", "on"), ("False", "off"),
                                         ("auto", "auto"), ("on", "on"), ("off", "off"), ("yes", "on"),
                                         ("no", "off"), (" ON ", "on"), ("Auto", "auto"), (1, "on"), (0, "off")])
def test_cuda_graph_reads_old_bool_configs_as_on_off(value, mode):
    # Checkpoints and scripts from before "auto" carry a bool (or true/false on a command line).
    assert preset_config("default", **{"ppo.cuda_graph": value}).ppo.cuda_graph == mode
    assert parse_args(["--ppo.cuda_graph", str(value)])[0].ppo.cuda_graph == mode


def test_env_graph_auto_captures_small_counts_on_the_gpu_only():
    from tocabi_torchrl.cuda_graphs import ENV_GRAPH_AUTO_MAX_ENVS, plan_graphs

    def uses_env_graph(cfg, device, num_envs=None):
        return plan_graphs(cfg, device, num_envs).env_step

    def config(num_envs, mode="auto"):
        return preset_config("default", **{"env.num_envs": num_envs, "ppo.minibatch_size": 64, "ppo.cuda_graph": mode})

    cuda, cpu = torch.device("cuda"), torch.device("cpu")
    small, large = ENV_GRAPH_AUTO_MAX_ENVS, ENV_GRAPH_AUTO_MAX_ENVS + 1
    assert uses_env_graph(config(small), cuda) and not uses_env_graph(config(small), cpu)
    assert not uses_env_graph(config(small), cuda, num_envs=large)  # an explicit count wins over cfg.num_envs
    assert not uses_env_graph(config(large), cuda)
    assert uses_env_graph(config(large, "on"), cuda) and not uses_env_graph(config(large, "on"), cpu)
    assert not uses_env_graph(config(small, "off"), cuda)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.parametrize("num_envs, graphed", [(8, True), (1024, False)])
def test_gpu_train_captures_the_env_step_when_auto_says_so(tmp_path, num_envs, graphed):
    from tocabi_torchrl.rl.trainer import train

    cfg = preset_config("default", **{"env.num_envs": num_envs, "ppo.steps_per_env": 8,
                        "ppo.minibatch_size": 2 * num_envs},
                        total_env_steps=num_envs * 24,
                        device="cuda", run_dir=str(tmp_path), eval_at_end=False, progress_bar=False,
                        **{"ppo.actor_hidden": (32,), "ppo.critic_hidden": (32,)})
    result = train(cfg)
    assert result.env_graph is graphed and result.env_steps == num_envs * 24


def test_build_env_asks_make_env_for_the_graph_only_where_it_can_be_captured(monkeypatch):
    # make_env is replaced by a recorder, so the CUDA decision is checked without a GPU.
    import tocabi_torchrl
    from tocabi_torchrl.rl.trainer import build_env

    asked = []
    monkeypatch.setattr(tocabi_torchrl, "make_env", lambda *args, **kwargs: asked.append(kwargs.get("cuda_graph")))
    cuda = torch.device("cuda")
    auto, on = (preset_config("default", **{"env.num_envs": 4, "ppo.minibatch_size": 16,
                "ppo.cuda_graph": m}) for m in ("auto", "on"))
    build_env(auto, cuda)
    build_env(auto, cuda, num_envs=4096)
    build_env(auto, cuda, sync_free_resets=False)  # TorchRL's stock resets read the host: not capturable
    build_env(auto, cuda, compile_reward=True)  # make_env refuses a compiled reward inside a capture
    build_env(on, cuda, compile_reward=True)  # asked for explicitly: make_env says why it cannot
    build_env(auto, cuda, cuda_graph=False)  # the caller's choice wins
    build_env(auto, torch.device("cpu"))
    assert asked == [True, False, False, False, True, False, None]


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_gpu_build_env_with_stock_resets_stays_eager():
    # cuda_graph="auto" at a small count must not turn a stock-reset env (profiling, comparisons) into an error.
    from tocabi_torchrl.rl.trainer import build_env

    cfg = preset_config("default", **{"env.num_envs": 4, "ppo.minibatch_size": 16})
    env = build_env(cfg, torch.device("cuda"), sync_free_resets=False)
    assert not getattr(env, "cuda_graph", False)
    assert build_env(cfg, torch.device("cuda")).cuda_graph


def test_help_lists_options(capsys):
    with pytest.raises(SystemExit):
        parse_args(["--help"])
    text = capsys.readouterr().out
    for option in ("--env.num_envs", "--ppo.lr_schedule", "--ppo.std_start", "--resume", "--max_minutes"):
        assert option in text


def test_two_tiny_iterations_write_a_loadable_checkpoint(tmp_path):
    from tocabi_torchrl.rl.checkpoint import CheckpointError, load_checkpoint
    from tocabi_torchrl.rl.trainer import build_agent, train

    cfg = preset_config("cpu_smoke", device="cpu", **{"env.num_envs": 4, "ppo.steps_per_env": 8,
                        "ppo.minibatch_size": 16},
                        total_env_steps=64, run_dir=str(tmp_path), name="tiny", checkpoint_every=1,
                        progress_bar=False, eval_at_end=False)
    result = train(cfg)
    assert result.iterations == 2 and result.env_steps == 64
    run = tmp_path / "tiny"
    assert (run / "checkpoints" / "iter_000002.pt").is_file()
    rows = read_metrics(run)  # torchrl's CSVLogger: one file per metric under run/metrics/scalars
    assert len(rows) == 2 and "reward_terms/qpos" in rows[0] and "kl" in rows[0]
    assert json.loads((run / "config.json").read_text())["env"]["num_envs"] == 4
    agent = build_agent(cfg, 237, 13, torch.device("cpu"))
    state = load_checkpoint(run, agent)
    assert state["iteration"] == 2
    trained = torch.load(run / "checkpoints" / "latest.pt", weights_only=True)["agent"]["actor"]
    for key, value in agent.actor.state_dict().items():
        torch.testing.assert_close(value, trained[key])
    # Two iterations of the reference schedule over a 2-iteration run: std went 0.1 -> 0.075 -> 0.05.
    torch.testing.assert_close(action_std(agent.actor), torch.full((13,), 0.05))
    with pytest.raises(CheckpointError, match="not found"):
        load_checkpoint(tmp_path / "missing", agent)
    # Resume continues the iteration count.
    cfg2 = preset_config("cpu_smoke", **{**cfg.to_dict(), "total_env_steps": 96,
                                         "resume": str(run)})
    assert train(cfg2).iterations == 3


def test_train_closes_the_env_it_built_when_its_start_fails(tmp_path, monkeypatch):
    # The collector's shutdown closes the env after a run; a start that failed before the collector existed (here the
    # logger) left the env it had built open, and on the CPU backend its worker threads outlived the call.
    import threading

    from tocabi_torchrl.rl import trainer

    def sim_threads() -> set[int]:
        return {t.ident for t in threading.enumerate() if t.name.startswith("MujocoSim")}

    before = sim_threads()
    cfg = preset_config("cpu_smoke", device="cpu", **{"env.num_envs": 2, "ppo.steps_per_env": 4,
                        "ppo.minibatch_size": 8},
                        total_env_steps=8, run_dir=str(tmp_path), name="closes", progress_bar=False, eval_at_end=False)
    trainer.train(cfg)
    assert sim_threads() == before

    def no_logger(*args, **kwargs):
        raise OSError("cannot write the run's logs")

    monkeypatch.setattr(trainer, "RunLogger", no_logger)
    with pytest.raises(OSError, match="cannot write"):
        trainer.train(preset_config("cpu_smoke", **{**cfg.to_dict(), "name": "fails"}))
    assert sim_threads() == before


def test_evaluation_and_curves_from_a_tiny_run(tmp_path):
    from tocabi_torchrl.rl.curves import plot_curves
    from tocabi_torchrl.evaluation.gait_test import evaluate_run
    from tocabi_torchrl.rl.trainer import train

    cfg = preset_config("cpu_smoke", device="cpu", **{"env.num_envs": 2, "ppo.steps_per_env": 4,
                        "ppo.minibatch_size": 8},
                        total_env_steps=16, run_dir=str(tmp_path), name="ev", progress_bar=False, eval_at_end=False)
    train(cfg)
    run = tmp_path / "ev"
    # No video: nothing here reads it, and the README's train command (tests/test_readme.py) runs this evaluation
    # with its video, its output naming the walk.mp4 written; the encoder took a third of this test's time.
    summary = evaluate_run(run, num_envs=2, device="cpu", seconds=0.1, video_envs=0)
    saved = json.loads((run / "eval" / "summary.json").read_text())
    assert saved["num_envs"] == 2 and saved["command_mps"] == [0.5, 0.0] and saved["seconds"] == 0.1
    for key in ("survival", "forward_distance_m", "lateral_drift_m", "speed_tracking_error_mps", "knee_rms_rad"):
        assert math.isfinite(summary[key]), key
    assert 0.0 <= summary["survival"] <= 1.0 and summary["knee_rms_rad"] >= 0.0
    assert (run / "eval" / "knees.png").stat().st_size > 10_000
    import matplotlib

    before = matplotlib.get_backend()
    try:  # the curves are drawn on their own canvas: a notebook's backend is left alone
        matplotlib.use("svg")
        png = plot_curves(run, tmp_path / "curves.png")
        assert matplotlib.get_backend() == "svg"
    finally:
        matplotlib.use(before)
    assert png.read_bytes()[:4] == b"\x89PNG" and png.stat().st_size > 10_000


def test_reference_preset_gives_the_value_head_its_own_constant_lr():
    from tocabi_torchrl.rl.trainer import _param_groups, build_agent

    cfg = preset_config("reference", device="cpu")
    agent = build_agent(cfg, 237, 13, torch.device("cpu"))
    groups = _param_groups(agent, cfg)
    assert [g["name"] for g in groups] == ["policy", "value_head"]
    head = groups[1]
    assert head["lr"] == 5e-4 and head.get("fixed") and sum(p.numel() for p in head["params"]) == 256 + 1
    # The reference's actor optimiser also trains the critic's hidden layers (spec §10.2).
    policy_ids = {id(p) for p in groups[0]["params"]}
    assert all(id(p) in policy_ids for p in agent.critic.module[0].parameters())
    assert groups[0]["lr"] == 1e-5
    assert len(_param_groups(agent, preset_config("default", device="cpu"))) == 1


def test_each_update_runs_with_the_linear_lr_and_std_of_the_progress_after_its_rollout(tmp_path, monkeypatch):
    # Spec §10.2 and §10.4: the reference sets the learning rate and the std from P_k = 1 - k/K after rollout k,
    # before update k. They were set after the update, so update k ran with P_(k-1)'s: one iteration behind.
    from tocabi_torchrl.rl import trainer

    seen, std_now, update, set_std = [], [0.1], trainer._update_stats, trainer.set_action_std

    def setting(actor, std):
        std_now[0] = std
        set_std(actor, std)

    def recording(cfg, flat, step, *rest):
        seen.append((step.optimizer.param_groups[0]["lr"], std_now[0]))
        return update(cfg, flat, step, *rest)

    monkeypatch.setattr(trainer, "_update_stats", recording)
    monkeypatch.setattr(trainer, "set_action_std", setting)
    cfg = preset_config("cpu_smoke", device="cpu", **{"env.num_envs": 2, "ppo.steps_per_env": 4,
                        "ppo.minibatch_size": 8},
                        total_env_steps=32, run_dir=str(tmp_path), name="sched", progress_bar=False,
                        eval_at_end=False, **{"ppo.lr_schedule": "linear", "ppo.lr": 1e-3, "ppo.lr_end": 0.0,
                                              "ppo.std_start": 0.1, "ppo.std_end": 0.05, "ppo.std_hold": 0.0})
    trainer.train(cfg)
    k = len(seen)
    assert k == 4
    for it, (lr, std) in enumerate(seen, start=1):
        progress = 1 - it / k
        assert lr == pytest.approx(1e-3 * progress) and std == pytest.approx(0.05 + 0.05 * progress), it


SHIPPED_POLICY = Path(__file__).resolve().parents[1] / "assets" / "policies" / "tocabi_walk_ppo.pt"


@pytest.mark.skipif(not SHIPPED_POLICY.is_file(), reason="shipped policy not present")
def test_shipped_policy_walks_on_the_cpu_backend(tmp_path):
    """The committed default-preset policy walks forward at 0.5 m/s on C MuJoCo (4 robots, 4 s)."""
    from tocabi_torchrl.evaluation.gait_test import evaluate_run

    summary = evaluate_run(SHIPPED_POLICY, num_envs=4, device="cpu", seconds=4.0, command=(0.5, 0.0), video_envs=0,
                           out_dir=tmp_path)
    assert summary["survival"] == 1.0
    assert summary["forward_distance_m"] > 1.4  # 0.35 m/s or better
    assert summary["lateral_drift_m"] < 0.3
    assert summary["knee_rms_rad"] < 0.15


@pytest.mark.parametrize("name, mode, now", [("tocabi_walk_torque.pt", "torque", "torque_ideal"),
                                             ("tocabi_walk_model_based.pt", "model_based", "model_based_ideal")])
def test_shipped_torque_level_policies_walk_on_the_cpu_backend(tmp_path, name, mode, now):
    """The committed torque-preset policy (12 leg torques + phase rate, no PD on the legs) and model_based-preset
    policy (12 residual leg torques on the computed-torque law + phase rate) walk forward at 0.5 m/s on C MuJoCo
    (4 robots, 4 s). Both were trained with their preset's perfect-robot recipe, named ``now`` since."""
    from tocabi_torchrl.rl.checkpoint import config_from_checkpoint, read_checkpoint
    from tocabi_torchrl.evaluation.gait_test import evaluate_run

    path = SHIPPED_POLICY.parent / name
    if not path.is_file():
        pytest.skip(f"shipped policy {name} not present")
    cfg = config_from_checkpoint(read_checkpoint(path))
    assert cfg.env.control.mode == mode and cfg.preset == mode
    assert cfg.env.control == preset_config(now).env.control
    summary = evaluate_run(path, num_envs=4, device="cpu", seconds=4.0, command=(0.5, 0.0), video_envs=0,
                           out_dir=tmp_path, progress=False)
    assert summary["survival"] == 1.0
    assert summary["forward_distance_m"] > 1.4  # 0.35 m/s or better
    assert summary["lateral_drift_m"] < 0.3
    assert summary["knee_rms_rad"] < 0.15


def test_training_env_stores_fewer_keys_with_the_same_dynamics():
    # The lean training env drops env signals from its outputs; the transforms that read the previous step's
    # signals (torque_diff, qacc, contact-force changes) must still see them, so rewards and observations match.
    from tocabi_torchrl.rl.trainer import build_env, training_keys

    cfg = preset_config("default", **{"env.num_envs": 3, "ppo.minibatch_size": 16}, device="cpu",
                        **{"env.task.max_episode_steps": 12})
    device = torch.device("cpu")
    full = build_env(cfg, device, sync_free_resets=True)
    lean = build_env(cfg, device, sync_free_resets=True, for_training=True)
    assert "foot_force" in training_keys(full) and "joint_vel" in training_keys(full)
    gen = torch.Generator().manual_seed(1)
    td_full, td_lean = full.reset(), lean.reset()
    lean_keys = set(td_lean.keys(True, True))
    assert "joint_pos" not in lean_keys and "base_pos" not in lean_keys and "observation" in lean_keys
    nbytes = lambda td: sum(v.numel() * v.element_size() for v in td.values(True, True))  # noqa: E731
    assert nbytes(td_lean) < 0.65 * nbytes(td_full)
    for _ in range(20):  # past the 12-step truncation, so the masked reset path runs too
        action = torch.rand(3, 13, generator=gen) * 2 - 1
        out_full, td_full = full.step_and_maybe_reset(td_full.set("action", action))
        out_lean, td_lean = lean.step_and_maybe_reset(td_lean.set("action", action.clone()))
        for key in ("observation", "reward", "done", "step_count", "episode_reward", ("reward_terms", "torque_diff")):
            torch.testing.assert_close(out_lean["next", key], out_full["next", key], rtol=0, atol=0)
        torch.testing.assert_close(td_lean["observation"], td_full["observation"], rtol=0, atol=0)


def test_chunked_gae_equals_unchunked():
    # The trainer evaluates the critic in chunks along the env dim to bound GAE's memory; values must not change.
    from tocabi_torchrl.rl.networks import make_mlp
    from torchrl.modules import ValueOperator

    torch.manual_seed(0)
    critic = ValueOperator(make_mlp(6, (16, 8), 1, "elu"), in_keys=["observation"])
    n, t = 10, 5
    done = torch.rand(n, t, 1) < 0.2
    batch = TensorDict({
        "observation": torch.randn(n, t, 6),
        "next": {"observation": torch.randn(n, t, 6), "reward": torch.randn(n, t, 1), "done": done,
                 "terminated": done & (torch.rand(n, t, 1) < 0.5)},
    }, batch_size=[n, t], names=[None, "time"])
    plain = GAE(gamma=0.99, lmbda=0.95, value_network=critic, average_gae=False)
    chunked = GAE(gamma=0.99, lmbda=0.95, value_network=critic, average_gae=False, value_chunk_size=3)
    with torch.no_grad():
        a, b = plain(batch.clone()), chunked(batch.clone())
    for key in ("advantage", "value_target", "state_value"):
        torch.testing.assert_close(b[key], a[key])


@pytest.mark.filterwarnings("error:SyncFreeResetEnv")  # no eager fallback for a changed key layout
def test_collector_drives_the_graph_wiring_like_the_eager_env():
    # A TorchRL Collector over the training env, once eager and once through SyncFreeResetEnv's graph path (with
    # an emulated capture, as no GPU is needed): the key layout must settle so the graph path is taken, and
    # the collected batches must be identical.
    from torchrl.collectors import Collector

    from tocabi_torchrl.rl.trainer import build_agent, build_env

    cfg = preset_config("default", **{"env.num_envs": 3, "ppo.minibatch_size": 16}, device="cpu",
                        **{"ppo.steps_per_env": 8, "env.task.max_episode_steps": 5})
    device = torch.device("cpu")
    batches = []
    for wired in (False, True):
        torch.manual_seed(0)
        env = build_env(cfg, device, sync_free_resets=True, for_training=True)
        env.set_cuda_graph(wired, capturer=EmulatedCapture())
        agent = build_agent(cfg, 237, 13, device)
        collector = Collector(env, agent.actor, frames_per_batch=24, total_frames=72, device=device,
                              storing_device=device, auto_register_policy_transforms=False, track_traj_ids=False,
                              return_same_td=True, no_cuda_sync=True)
        batches.append([b.clone() for b in collector])
        collector.shutdown()
        assert env.graph_captured == wired
    for eager, graphed in zip(*batches):
        assert set(graphed.keys(True, True)) == set(eager.keys(True, True))
        for key in eager.keys(True, True):
            torch.testing.assert_close(graphed[key], eager[key], rtol=0, atol=0, msg=lambda m, k=key: f"{k}: {m}")


def test_gait_test_stops_once_every_robot_has_fallen(tmp_path):
    # An untrained torque policy applies almost no leg torque: every robot falls within the first second, and the
    # 8 s test stops there with the same metrics (fallen robots count for nothing after their fall).
    from tocabi_torchrl.evaluation.gait_test import evaluate_policy
    from tocabi_torchrl.evaluation.record import fixed_command
    from tocabi_torchrl.rl.trainer import build_agent, build_env

    cfg = preset_config("cpu_smoke", device="cpu", **{"env.control.mode": "torque"})
    device = torch.device("cpu")
    env = build_env(cfg, device, num_envs=2, command=fixed_command((0.5, 0.0)))  # the test's command
    agent = build_agent(cfg, 237, 13, device)
    calls = []
    step = env.step
    env.step = lambda td: calls.append(1) or step(td)
    summary = evaluate_policy(agent.actor, cfg, tmp_path, num_envs=2, device=device, seconds=8.0, video_envs=0,
                              env=env, progress=False)
    assert summary["survival"] == 0.0 and summary["seconds"] == 8.0
    assert 0 < len(calls) < 1000 and len(calls) % 50 == 0  # stopped at the first check after the last fall


def test_read_metrics_and_steady_rate(tmp_path):
    from tocabi_torchrl.rl.curves import read_metrics, steady_rate

    # A resumed run appends rows whose wall_s restarts: the rate comes from the longest segment, after its warm-up.
    rows = [(1, 100, 1), (2, 200, 2), (4, 600, 3), (1, 700, 4), (3, 900, 5)]
    path = tmp_path / "metrics.csv"
    path.write_text("iteration,wall_s,env_steps\n" + "".join(f"{i},{w},{s}\n" for w, s, i in rows))
    read = read_metrics(path)
    assert [r["iteration"] for r in read] == ["1", "2", "3", "4", "5"] and read_metrics(tmp_path / "none.csv") == []
    assert steady_rate(read, skip=1) == pytest.approx((600 - 200) / (4 - 2))
    assert steady_rate(read[:2], skip=1) is None


def test_adaptive_learning_rate_rule():
    # The trainer's KL-adaptive rule (shared with the rsl_rl recipe's --lr_schedule per_iteration): /1.5 above twice
    # the target, x1.5 below half of it, unchanged between, within [1e-5, 1e-2].
    from tocabi_torchrl.rl.update_step import adapt_lr

    assert adapt_lr(1e-3, 0.021, 0.01) == pytest.approx(1e-3 / 1.5)
    assert adapt_lr(1e-3, 0.0049, 0.01) == pytest.approx(1.5e-3)
    assert adapt_lr(1e-3, 0.01, 0.01) == 1e-3
    assert adapt_lr(1.2e-5, 1.0, 0.01) == 1e-5 and adapt_lr(9e-3, 0.0, 0.01) == 1e-2
    # ppo.lr_min raises the floor (never lowers it below the range).
    assert adapt_lr(6e-5, 1.0, 0.01, 5e-5) == 5e-5 and adapt_lr(1.2e-5, 1.0, 0.01, 1e-6) == 1e-5
    assert adapt_lr(1e-3, 1.0, 0.01, 5e-5) == pytest.approx(1e-3 / 1.5)
    from tocabi_torchrl.config import preset_config

    assert preset_config("default").ppo.lr_min == 1e-5
    for bad in (1e-6, 2e-3, float("nan"), True):
        with pytest.raises(ValueError, match="ppo.lr_min"):
            preset_config("default", **{"ppo.lr_min": bad})


def test_the_adaptive_rate_stops_at_ppo_lr_min(tmp_path):
    # A KL target no update meets: the rule lowers the rate every iteration, down to the floor and no further.
    from tocabi_torchrl.rl import preset_config
    from tocabi_torchrl.rl.metrics_files import read_metrics
    from tocabi_torchrl.rl.trainer import train

    cfg = preset_config("cpu_smoke", device="cpu", run_dir=str(tmp_path), name="floor", progress_bar=False,
                        eval_at_end=False, log_every=1, total_env_steps=4 * 8 * 16,
                        **{"ppo.lr": 2e-4, "ppo.lr_min": 1e-4, "ppo.desired_kl": 1e-12})
    train(cfg)
    rates = [float(r["lr"]) for r in read_metrics(tmp_path / "floor")]
    assert rates[0] == pytest.approx(2e-4 / 1.5) and rates[1:] == pytest.approx([1e-4] * (len(rates) - 1))


def test_a_zero_value_loss_weight_is_refused_before_the_run_starts():
    # TorchRL's ClipPPOLoss drops its critic term at critic_coeff 0: the critic GAE reads never learned, and the
    # first update failed with a KeyError on "loss_critic", after config.json and the metrics folder were written.
    with pytest.raises(ValueError, match=r"ppo.value_coef must be > 0 .*got 0.0"):
        preset_config("cpu_smoke", **{"ppo.value_coef": 0.0})
    assert preset_config("reference").ppo.value_coef == 0.5  # a positive weight stays accepted
