"""Peer benchmark (issue 25): mjlab's registered task, runner and config, training env-steps/s against the raw
mujoco-warp ceiling of mjlab's own model, in one process (docs/benchmarks.md, "Peer: mjlab"). It runs as a plain
script in mjlab's pinned environment (mujoco 3.11), so nothing at module level imports mjlab or anything of ours. In
our environment, ``python -m lab.benchmarks.mjlab_peer --ours OURS.json`` merges our train_throughput row into its report
and writes the page (:func:`render`).
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import importlib.util
import json
import os
import platform
import shlex
import sys
import time
import types
from dataclasses import asdict
from importlib import metadata
from pathlib import Path

TASK = "Mjlab-Velocity-Flat-Unitree-G1"
OUT = Path(__file__).resolve().parents[2] / "docs" / "benchmarks" / "mjlab_peer.json"
#: Where a run off CUDA writes instead of :data:`OUT` (ignored by git): lab.benchmarks.common.report_dir's rule, which this
#: script cannot import.
CPU_OUT = Path(__file__).resolve().parents[2] / "runs" / "benchmarks_cpu" / "mjlab_peer.json"
# Modules mjlab imports that this run never uses: its __init__ points mediapy at imageio-ffmpeg's ffmpeg (videos), the
# G1 runner module imports wandb (W&B logging). Stand-ins where missing keep ~35 MB of wheels off the GPU machine.
STAND_INS = {"mediapy": {"set_ffmpeg": lambda path: None}, "imageio_ffmpeg": {"get_ffmpeg_exe": lambda: "ffmpeg"},
             "wandb": {"run": None}}
T0 = time.perf_counter()


def log(message: str) -> None:
    # Seconds since start: a new machine compiles warp kernels for minutes before anything else shows.
    print(f"[mjlab_peer {time.perf_counter() - T0:7.1f} s] {message}", flush=True)


def install_stand_ins() -> list[str]:
    """A stand-in module for each of :data:`STAND_INS` that cannot be imported; the names replaced."""
    replaced = [name for name in STAND_INS if importlib.util.find_spec(name) is None]
    for name in replaced:
        sys.modules[name] = types.ModuleType(name, "stand-in of lab/benchmarks/mjlab_peer.py (not installed)")
        sys.modules[name].__dict__.update(STAND_INS[name])
    return replaced


def train_seconds(runner, iterations: int, warmup: int, sync, run_dir: Path) -> float:
    """Seconds of ``iterations`` PPO iterations after ``warmup``, in one ``learn`` call as mjlab's train.py makes it.
    rsl_rl's logger logs once at the end of each iteration: the window's ends are taken (and synced) there."""
    total, marks, original, start = warmup + iterations, {}, runner.logger.log, runner.current_learning_iteration
    run_dir.mkdir(parents=True, exist_ok=True)

    def timed_log(*a, it: int, **k) -> None:
        with open(run_dir / "runner_console.log", "a") as f, contextlib.redirect_stdout(f):
            original(*a, it=it, **k)  # rsl_rl's console block, to a file
        done = it + 1 - start
        if done in (warmup, total):
            sync()
            marks[done] = time.perf_counter()
        log(f"iteration {done}/{total}{' (warm-up)' if done <= warmup else ''}")

    runner.logger.log = timed_log
    sync()
    marks[0] = time.perf_counter()
    runner.learn(num_learning_iterations=total, init_at_random_ep_len=True)
    return marks[total] - marks[warmup]


def raw_rate(base, steps: int, sync, warmup: int = 10) -> float:
    """Policy steps/s (all worlds each): ``mujoco_warp.step`` x decimation on the env's own model and data, one step
    captured as a CUDA graph exactly when mjlab's Simulation captures one."""
    import mujoco_warp as mjw
    import torch
    import warp as wp

    sim = base.sim
    # All worlds reset, then one zero-action env step: the joint-position targets (the default pose) reach the position
    # actuators, which hold the robots there. Inference mode, as rsl_rl's rollout made the env's buffers.
    with torch.inference_mode():
        base.reset()
        base.step(torch.zeros(base.num_envs, base.action_manager.total_action_dim, device=base.device))
    model, data = sim.wp_model, sim.wp_data
    with wp.ScopedDevice(sim.wp_device):
        mjw.step(model, data)  # every kernel compiled before a capture
        substep = lambda: mjw.step(model, data)
        if sim.use_cuda_graph:
            gc.disable()  # as mjlab's Simulation: no finaliser may be recorded into the graph
            try:
                with wp.ScopedCapture() as capture:
                    mjw.step(model, data)
            finally:
                gc.enable()
            substep = lambda: wp.capture_launch(capture.graph)
        for i in range(warmup + steps):
            if i == warmup:
                sync()
                t0 = time.perf_counter()
            for _ in range(base.cfg.decimation):
                substep()
        sync()
    return steps / (time.perf_counter() - t0)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default=TASK, help=f"mjlab's registered task to train (default: {TASK})")
    parser.add_argument("--num_envs", type=int, default=4096, help="robots (parallel envs) (default: 4096)")
    parser.add_argument("--iterations", type=int, default=10, help="timed PPO iterations")
    parser.add_argument("--warmup", type=int, default=3, help="PPO iterations before the timed ones")
    parser.add_argument("--raw_steps", type=int, default=200, help="raw policy steps timed (0: no raw ceiling)")
    parser.add_argument("--device", default="cuda:0", help="as mjlab's train.py names it; cpu for a smoke run")
    parser.add_argument("--run_dir", default="/tmp/mjlab_peer_runs", help="scratch folder of rsl_rl's logs")
    parser.add_argument("--out", type=Path, default=OUT,
                        help="the report's JSON file; with --ours its page .md goes beside it (default: "
                             "docs/benchmarks/mjlab_peer.json; off CUDA runs/benchmarks_cpu/mjlab_peer.json)")
    parser.add_argument("--ours", type=Path, help="our env only: merge this train_throughput report into --out")
    args = parser.parse_args(argv)
    if args.ours:
        return merge(args.out, args.ours)
    if not args.device.startswith("cuda") and args.out.resolve() == OUT.resolve():  # a smoke run keeps the GPU report
        print(f"measured on {args.device}: writing to {CPU_OUT}, not {OUT}, which holds the published GPU results",
              flush=True)
        args.out = CPU_OUT
    os.environ.setdefault("GIT_PYTHON_REFRESH", "quiet")  # rsl_rl imports GitPython, which wants a git binary
    # Set, not defaulted: nothing is rendered, and under egl (inherited or mjlab's default) mujoco needs libEGL and
    # PyOpenGL, without which it lacks mujoco.Renderer, read by mjlab's viewer at import.
    os.environ["MUJOCO_GL"] = "disable"
    stand_ins = install_stand_ins()
    log(f"importing mjlab (task {args.task}, {args.num_envs} envs on {args.device}; stand-ins: {stand_ins})")
    try:
        import mjlab.tasks  # noqa: F401 (registers every task)
        import torch
        import warp
        from mjlab.envs import ManagerBasedRlEnv
        from mjlab.rl import MjlabOnPolicyRunner, RslRlVecEnvWrapper
        from mjlab.tasks import registry
        from mjlab.utils.torch import configure_torch_backends
    except ImportError as err:
        raise SystemExit(f"mjlab_peer: cannot import mjlab ({err}): run it in mjlab's pinned environment "
                         "(docs/benchmarks.md, 'Peer: mjlab')") from None
    if args.task not in registry.list_tasks():
        raise SystemExit(f"mjlab_peer: mjlab has no task {args.task!r}; it has: {', '.join(registry.list_tasks())}")
    cuda = args.device.startswith("cuda")
    sync = (lambda: torch.cuda.synchronize(args.device)) if cuda else (lambda: None)

    log("building the env and the runner (a new machine compiles mujoco-warp's kernels first: minutes)")
    env_cfg, agent_cfg = registry.load_env_cfg(args.task), registry.load_rl_cfg(args.task)
    env_cfg.scene.num_envs, env_cfg.seed = args.num_envs, agent_cfg.seed
    agent_cfg.logger = "tensorboard"  # mjlab's offline choice: its default, wandb, needs an account and a network
    configure_torch_backends()
    env = RslRlVecEnvWrapper(ManagerBasedRlEnv(cfg=env_cfg, device=args.device), clip_actions=agent_cfg.clip_actions)
    runner_cls = registry.load_runner_cls(args.task) or MjlabOnPolicyRunner
    run_dir = Path(args.run_dir) / time.strftime("%Y-%m-%d_%H-%M-%S")
    runner = runner_cls(env, asdict(agent_cfg), str(run_dir), args.device)
    base, steps = env.unwrapped, agent_cfg.num_steps_per_env
    r = {"num_envs": args.num_envs, "decimation": base.cfg.decimation, "physics_dt": base.physics_dt,
         "steps_per_env": steps, "iterations": args.iterations, "warmup": args.warmup, "runner": runner_cls.__name__,
         "setup_s": time.perf_counter() - T0}

    log(f"training {args.warmup} + {args.iterations} iterations of {steps} steps ({runner_cls.__name__})")
    r["train_wall_s"] = train_seconds(runner, args.iterations, args.warmup, sync, run_dir)
    r["train_env_steps_per_s"] = args.num_envs * steps * args.iterations / r["train_wall_s"]
    if cuda:
        r["torch_peak_reserved_gib"] = torch.cuda.max_memory_reserved(args.device) / 2**30
    r["raw_policy_steps_per_s"], r["raw_graph"] = None, bool(base.sim.use_cuda_graph)
    if args.raw_steps:
        log(f"raw mujoco-warp ceiling: {args.raw_steps} policy steps of {base.cfg.decimation} substeps")
        r["raw_policy_steps_per_s"] = args.num_envs * raw_rate(base, args.raw_steps, sync)
    r["ratio_train_over_raw"] = r["raw_policy_steps_per_s"] and r["train_env_steps_per_s"] / r["raw_policy_steps_per_s"]

    versions = {}
    for dist in ("mjlab", "mujoco", "mujoco-warp", "rsl-rl-lib", "tensordict", "torch"):
        with contextlib.suppress(metadata.PackageNotFoundError):
            versions[dist] = metadata.version(dist)
    versions["warp"] = warp.__version__  # the GPU machine's warp is unpacked without its metadata
    gpu = torch.cuda.get_device_name(args.device) if cuda else platform.machine()
    command = shlex.join(["python3", "lab/benchmarks/mjlab_peer.py", *(sys.argv[1:] if argv is None else argv)])
    data = {"meta": {"gpu": gpu, "device": args.device, "task": args.task, "date": time.strftime("%Y-%m-%d"),
                     "python": platform.python_version(), "versions": versions, "stand_ins": stand_ins,
                     "command": command}, "results": [r]}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(data, indent=2) + "\n")
    log(f"wrote {args.out}: train {r['train_env_steps_per_s']:,.0f} env-steps/s, raw "
        f"{r['raw_policy_steps_per_s'] or 0:,.0f} policy steps/s, train/raw {r['ratio_train_over_raw'] or 0:.2f}")
    return data


def merge(path: Path, ours_path: Path) -> dict:
    """Our env: our default-preset 1-GPU row of the peer's env count (with our physics per env step, which our report
    lacks) into the peer report under "ours"; writes the page beside it."""
    from lab.benchmarks import common
    from tocabi_torchrl import robot

    try:  # a damaged report is named, not a decoder's traceback
        data, ours = (common.read_json(p, f"write it again with {tool}") for p, tool in
                      ((path, "lab.benchmarks.mjlab_peer"), (ours_path, "lab.benchmarks.train_throughput")))
    except ValueError as err:
        raise SystemExit(f"mjlab_peer: {err}") from None
    n = data["results"][0]["num_envs"]
    rows = [r for r in ours["results"] if r["num_envs"] == n and r.get("gpus", 1) == 1 and not r["overrides"]
            and r.get("ratio_train_over_raw")]
    if not rows:
        raise SystemExit(f"mjlab_peer: {ours_path} has no default 1-GPU row of {n} envs with both rates: run "
                         f"`python -m lab.benchmarks.train_throughput --num_envs {n} --name mjlab_peer_ours` there")
    physics = {"substeps": common.config("default").env.sim.substeps, "physics_dt": robot.load_model().opt.timestep}
    data["ours"] = {"meta": ours["meta"], "result": {**rows[0], **physics}}
    common.publish(path.parent, path.stem, data, render)
    return data


def render(data: dict, out=None) -> str:
    """The page of a merged report (lab.benchmarks.regenerate calls this too)."""
    from lab.benchmarks import common

    (peer,), m, ours, om = data["results"], data["meta"], data["ours"]["result"], data["ours"]["meta"]
    sides = [("tocabi-torchrl", "TOCABI walk, default preset", ours, ours["substeps"], om["gpu"]),
             (f"mjlab {m['versions']['mjlab']}", m["task"], peer, peer["decimation"], m["gpu"])]
    body = common.table(
        ("stack", "task", "envs", "physics per env step", "train env-steps/s", "raw mujoco-warp policy steps/s",
         "train / raw", "GPU"),
        [(stack, task, r["num_envs"], f"{k} x {r['physics_dt'] * 1e3:g} ms", common.fmt(r["train_env_steps_per_s"]),
          common.fmt(r["raw_policy_steps_per_s"]), common.fmt(r["ratio_train_over_raw"], ".2f"), gpu)
         for stack, task, r, k, gpu in sides])
    same = (m["gpu"], m["date"]) == (om["gpu"], om["date"])
    notes = [f"Both sides ran on {m['gpu']} on {m['date']}." if same else
             f"**Not one run**: mjlab on {m['gpu']} ({m['date']}), ours on {om['gpu']} ({om['date']}): compare the "
             "train / raw ratios, not the rates.",
             *([data["context"]] if data.get("context") else []),
             f"Our command: `{om['command']}`.",
             "mjlab's set: " + ", ".join(f"{k} {v}" for k, v in m["versions"].items())
             + f"; stand-ins: {', '.join(m['stand_ins']) or 'none'}.",
             "What each column measures: [benchmarks.md](../benchmarks.md#peer-mjlab-issue-25)."]
    return common.page("Peer benchmark: mjlab", data, body + "\n\n" + "\n".join(f"- {n}" for n in notes))


if __name__ == "__main__":
    main()
