"""Soak test: train while faults are injected, and check that nothing leaks out of the broken worlds; then kill a
training process and resume it.

    python benchmarks/soak.py                                        # GPU: default preset, 16,384 envs, 8 min
    python benchmarks/soak.py --num_envs 8 --minutes 0.2 --device cpu --fault_every 50 --out /tmp/soak   # tiny CPU

``faults`` mode: ``train()`` of the preset (running observation normalisation, so the statistics every world shares
are exposed too) for ``--minutes``; every ``--fault_every`` policy steps three random worlds are hit: NaN into one
world's ``qvel``, the velocity change of a 10x-body-weight push lasting 4 ms into another's base, and actions of
±1e6 and NaN written over a third's sampled action (the policy is wrapped, so the faulty action also reaches PPO's
rollout). A transform appended to the env counts, on the device, NaN/inf in observations and rewards of the other
worlds (must be 0) and whether each NaN world terminated and was reset. Afterwards the checkpoint (network
parameters, optimiser, normaliser) and metrics.csv must be finite, and device memory may grow at most 1 % from the
tenth rollout (after warm-up) to the end; a per-rollout series of device, torch-allocated and torch-reserved memory
is kept in the JSON (host RSS growth is reported).

``kill_resume`` mode: ``recipes/ppo_walk.py`` in a subprocess, SIGKILLed at a random point of an iteration once two
checkpoints exist; every checkpoint left must load, and ``--resume`` must go on at the next iteration with no
repeated metrics rows. Writes ``<out>/soak.{json,md}`` (a single ``--mode`` keeps the other mode's results from an
earlier report there, so the two can run in separate 10-minute device calls); exits 1 if a check fails.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
sys.path.insert(0, str(REPO))

from report import rss_bytes, run_meta, write_report  # noqa: E402
from tensordict.nn import TensorDictModuleBase  # noqa: E402
from torchrl.envs.transforms import Transform  # noqa: E402

from tocabi_torchrl import robot  # noqa: E402
from tocabi_torchrl.rl import trainer  # noqa: E402
from tocabi_torchrl.rl.checkpoint import read_checkpoint  # noqa: E402
from tocabi_torchrl.rl.config import preset_config  # noqa: E402

#: Base velocity change of a push of 10x the robot's weight lasting one 4 ms policy step: F·dt / m = 10·g·dt.
PUSH_DV = 10.0 * robot.GRAVITY * 0.004


def rss_mib() -> float:
    return rss_bytes() / 2**20


def device_used_gib(device: torch.device) -> float | None:
    if device.type != "cuda":
        return None
    free, total = torch.cuda.mem_get_info(device)
    return (total - free) / 2**30


class FaultInjector(TensorDictModuleBase):
    """The policy, plus a fault every ``every`` calls: NaN into one world's qvel, a push into another's base, actions
    of ±1e6 and NaN into a third. ``nan_now`` / ``hit_now`` mark the worlds hit in the current step (device masks)."""

    def __init__(self, actor, sim, every: int, seed: int):
        super().__init__()
        self.actor, self.sim, self.every = actor, sim, every
        self.in_keys, self.out_keys = actor.in_keys, actor.out_keys
        self.rng = random.Random(seed)
        n, dev = sim.num_worlds, sim.device
        self.nan_now = torch.zeros(n, dtype=torch.bool, device=dev)
        self.hit_now = torch.zeros(n, dtype=torch.bool, device=dev)
        self.calls, self.events, self._armed = 0, [], False

    def forward(self, td):
        td = self.actor(td)
        self.calls += 1
        if self._armed:  # the previous step was the faulty one
            self.nan_now.zero_()
            self.hit_now.zero_()
            self._armed = False
        if self.calls % self.every == 0 and self.sim.num_worlds >= 3:
            nan_w, push_w, act_w = self.rng.sample(range(self.sim.num_worlds), 3)
            angle = self.rng.uniform(0.0, 2.0 * math.pi)
            self.sim.qvel[nan_w] = float("nan")
            self.sim.qvel[push_w, 0] += PUSH_DV * math.cos(angle)
            self.sim.qvel[push_w, 1] += PUSH_DV * math.sin(angle)
            action = td.get("action")
            action[act_w, 0::2] = 1e6
            action[act_w, 1::2] = -1e6
            action[act_w, 0] = float("nan")
            self.nan_now[nan_w] = True
            self.hit_now[[nan_w, push_w, act_w]] = True
            self._armed = True
            self.events.append({"step": self.calls, "nan_world": nan_w, "push_world": push_w, "action_world": act_w})
        return td


class SoakMonitor(Transform):
    """Counts, on the device, NaN/inf in each step's observation and reward inside and outside the worlds hit in
    that step, and whether the NaN worlds terminated and were reset with a finite observation."""

    #: Rollouts before the memory baseline: buffers, captured graphs and the allocator's pools are built in the first
    #: iterations (measured from rollout 2 on the H100, device use still rose 21 % by the end; the series shows where).
    WARMUP_ROLLOUTS = 10
    NAMES = ("obs_outside", "reward_outside", "reset_obs_outside", "obs_hit", "reward_hit",
             "nan_worlds", "nan_terminated", "nan_reset")

    def __init__(self, steps_per_env: int, device: torch.device):
        super().__init__()
        self.steps_per_env = steps_per_env
        self.attach(None)
        self.counts = torch.zeros(len(self.NAMES), dtype=torch.int64, device=device)
        self.steps, self.memory_start = 0, None
        #: One row per rollout: (rollout, device GiB in use, torch GiB allocated, torch GiB reserved, host RSS MiB).
        #: Tells a leak (allocated or the non-torch part climbing) from the caching allocator's pool settling.
        self.memory_series: list[tuple[int, float | None, float, float, float]] = []

    def attach(self, injector: FaultInjector | None) -> None:
        """Follow ``injector``'s masks (set when train() builds its collector). Kept out of the module tree: as a
        submodule the wrapped policy would land in the env's transform state, i.e. in every checkpoint."""
        object.__setattr__(self, "injector", injector)

    def _step(self, tensordict, next_tensordict):
        if self.injector is None:
            return next_tensordict
        hit, nan_now = self.injector.hit_now, self.injector.nan_now
        bad_obs = ~torch.isfinite(next_tensordict["observation"]).all(-1)
        bad_rew = ~torch.isfinite(next_tensordict["reward"]).all(-1)
        terminated = next_tensordict["terminated"].squeeze(-1)
        self.counts[[0, 1, 3, 4, 5, 6]] += torch.stack([
            (bad_obs & ~hit).sum(), (bad_rew & ~hit).sum(), (bad_obs & hit).sum(), (bad_rew & hit).sum(),
            nan_now.sum(), (nan_now & terminated).sum()])
        self.steps += 1
        if self.steps % self.steps_per_env == 0:
            device = self.counts.device
            allocated = torch.cuda.memory_allocated(device) / 2**30 if device.type == "cuda" else 0.0
            reserved = torch.cuda.memory_reserved(device) / 2**30 if device.type == "cuda" else 0.0
            self.memory_series.append((self.steps // self.steps_per_env, device_used_gib(device), allocated, reserved,
                                       rss_mib()))
        if self.steps == self.WARMUP_ROLLOUTS * self.steps_per_env:  # rollout buffers, graphs and pools exist now
            self.memory_start = (device_used_gib(self.counts.device), rss_mib())
        return next_tensordict

    def _reset(self, tensordict, tensordict_reset):
        if self.injector is not None and tensordict is not None and "_reset" in tensordict.keys():
            flagged = tensordict["_reset"].squeeze(-1)
            bad = ~torch.isfinite(tensordict_reset["observation"]).all(-1) & flagged
            self.counts[[2, 7]] += torch.stack([(bad & ~self.injector.hit_now).sum(),
                                                (flagged & self.injector.nan_now).sum()])
        return tensordict_reset

    def summary(self) -> dict:
        return dict(zip(self.NAMES, self.counts.tolist()))


def nonfinite(tensors) -> int:
    return int(sum((~torch.isfinite(t)).sum() for t in tensors if torch.is_tensor(t) and t.is_floating_point()))


def flatten(obj):
    if torch.is_tensor(obj):
        yield obj
    elif isinstance(obj, dict):
        for v in obj.values():
            yield from flatten(v)
    elif isinstance(obj, (list, tuple)):
        for v in obj:
            yield from flatten(v)


def soak_config(args, name: str, **extra):
    base = preset_config(args.preset)
    frames = args.num_envs * base.steps_per_env
    # cuda_graph off: SoakMonitor keeps Python-side state in the env step, which a captured step graph (auto: up to
    # 128 envs) would freeze; at the soak's 16,384 envs "auto" is off anyway.
    return preset_config(args.preset, num_envs=args.num_envs, device=args.device, run_dir=args.run_dir, name=name,
                         minibatch_size=min(base.minibatch_size, max(frames // 4, 1)), eval_at_end=False,
                         progress_bar=False, total_env_steps=10**12, cuda_graph="off", **extra)


def run_faults(args) -> tuple[dict, list[dict]]:
    cfg = soak_config(args, "soak_faults", max_minutes=args.minutes, checkpoint_every=10**6)
    shutil.rmtree(Path(cfg.run_dir) / cfg.name, ignore_errors=True)
    device = trainer.resolve_device(cfg.device)
    env = trainer.build_env(cfg, device, for_training=True, normalization=args.normalization)
    monitor = SoakMonitor(cfg.steps_per_env, device)
    env.append_transform(monitor)
    make_collector = trainer.make_collector

    def faulty_collector(cfg_, env_, actor, device_, total_frames=-1):
        injector = FaultInjector(actor, env.base_env.sim, args.fault_every, args.seed)
        monitor.attach(injector)
        return make_collector(cfg_, env_, injector, device_, total_frames)

    trainer.make_collector = faulty_collector  # train() builds its collector through this name: wrap its policy
    try:
        t0 = time.perf_counter()
        result = trainer.train(cfg, env=env)
        wall = time.perf_counter() - t0
    finally:
        trainer.make_collector = make_collector
    injector = monitor.injector
    memory_end = (device_used_gib(device), rss_mib())
    state = read_checkpoint(result.run_dir)
    with open(result.run_dir / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    metric_bad = {}
    for row in rows:
        ended = float(row.get("episodes_finished") or 0) > 0
        for key, value in row.items():
            if key in ("episode_return", "episode_length") and not ended:
                continue  # NaN by design when no episode ended in that iteration
            try:
                if not math.isfinite(float(value)):
                    metric_bad[key] = metric_bad.get(key, 0) + 1
            except (TypeError, ValueError):
                pass
    counts = monitor.summary()
    start = monitor.memory_start or memory_end
    growth = None if start[0] is None else 100.0 * (memory_end[0] - start[0]) / start[0]
    details = {
        "policy_steps": injector.calls, "env_steps": result.env_steps, "iterations": result.iterations,
        "wall_s": wall, "fault_events": len(injector.events), "events": injector.events[:50], "monitor": counts,
        "nonfinite_parameters": nonfinite(flatten(state["agent"])),
        "nonfinite_optimizer": nonfinite(flatten(state.get("optimizer"))),
        "nonfinite_normaliser_and_transforms": nonfinite(flatten(state.get("transforms"))),
        "nonfinite_metrics": metric_bad, "metrics_rows": len(rows),
        "device_used_gib_start": start[0], "device_used_gib_end": memory_end[0], "device_growth_pct": growth,
        "host_rss_mib_start": start[1], "host_rss_mib_end": memory_end[1],
        "host_rss_growth_pct": 100.0 * (memory_end[1] - start[1]) / start[1],
        "memory_baseline_rollout": SoakMonitor.WARMUP_ROLLOUTS,
        "memory_series": [dict(zip(("rollout", "device_used_gib", "torch_allocated_gib", "torch_reserved_gib",
                                    "host_rss_mib"), row)) for row in monitor.memory_series],
    }
    outside = counts["obs_outside"] + counts["reward_outside"] + counts["reset_obs_outside"]
    checks = [
        check("faults injected", len(injector.events), ">= 1", len(injector.events) >= 1),
        check("NaN/inf in observations/rewards outside injected worlds", outside, "0", outside == 0),
        check("NaN/inf in the injected worlds' own outputs", counts["obs_hit"] + counts["reward_hit"], "0",
              counts["obs_hit"] + counts["reward_hit"] == 0),
        check("NaN worlds terminated", f"{counts['nan_terminated']}/{counts['nan_worlds']}", "all",
              counts["nan_terminated"] == counts["nan_worlds"]),
        check("NaN worlds reset", f"{counts['nan_reset']}/{counts['nan_worlds']}", "all",
              counts["nan_reset"] == counts["nan_worlds"]),
        check("NaN/inf in network parameters", details["nonfinite_parameters"], "0",
              details["nonfinite_parameters"] == 0),
        check("NaN/inf in optimiser state", details["nonfinite_optimizer"], "0", details["nonfinite_optimizer"] == 0),
        check("NaN/inf in normaliser / transform state", details["nonfinite_normaliser_and_transforms"], "0",
              details["nonfinite_normaliser_and_transforms"] == 0),
        check("non-finite training metrics", sum(metric_bad.values()), "0", not metric_bad),
        check("device memory growth [%]", "n/a" if growth is None else f"{growth:.2f}", "<= 1",
              growth is None or growth <= 1.0),
        check("host RSS growth [%]", f"{details['host_rss_growth_pct']:.1f}", "reported", True),
    ]
    return details, checks


def run_kill_resume(args) -> tuple[dict, list[dict]]:
    name = "soak_kill"
    run = Path(args.run_dir) / name
    shutil.rmtree(run, ignore_errors=True)
    cfg = soak_config(args, name)
    options = ["--preset", args.preset, "--num_envs", str(args.num_envs), "--device", args.device, "--name", name,
               "--run_dir", args.run_dir, "--minibatch_size", str(cfg.minibatch_size), "--eval_at_end", "false",
               "--progress_bar", "false", "--checkpoint_every", "1"]
    recipe = [sys.executable, str(REPO / "recipes" / "ppo_walk.py")]
    env = {**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    run.parent.mkdir(parents=True, exist_ok=True)
    with open(run.parent / f"{name}.log", "w") as log:
        proc = subprocess.Popen(recipe + options + ["--total_env_steps", str(10**12)], env=env, stdout=log,
                                stderr=subprocess.STDOUT)
    folder, deadline = run / "checkpoints", time.time() + args.kill_timeout
    while time.time() < deadline and proc.poll() is None:
        if folder.is_dir() and len(list(folder.glob("iter_*.pt"))) >= 2:
            time.sleep(random.Random(args.seed).uniform(0.0, args.kill_jitter_s))  # somewhere in an iteration
            break
        time.sleep(0.05)
    killed = proc.poll() is None
    if killed:
        os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    if not killed:
        # The training ended on its own before it could be killed (on the H100 once, 25 s in): say why, from its log.
        log_tail = (run.parent / f"{name}.log").read_text()[-3000:]
        return ({"killed": False, "exit_code": proc.returncode, "training_log_tail": log_tail},
                [check("training process killed mid-run", f"exited by itself with code {proc.returncode}", "true",
                       False)])
    corrupt = []
    for path in sorted(folder.glob("*.pt")) if folder.is_dir() else []:
        try:
            read_checkpoint(path)
        except Exception as err:  # noqa: BLE001 - any failure is a corrupt checkpoint
            corrupt.append(f"{path.name}: {err}")
    last = read_checkpoint(run)["iteration"] if (folder / "latest.pt").is_file() else 0
    budget = (last + 2) * cfg.frames_per_batch
    resumed = subprocess.run(recipe + ["--resume", str(run), "--total_env_steps", str(budget)], env=env,
                             capture_output=True, text=True, timeout=args.kill_timeout)
    with open(run / "metrics.csv", newline="") as f:
        iterations = [int(r["iteration"]) for r in csv.DictReader(f)]
    details = {"killed": killed, "last_checkpoint_iteration": last, "corrupt_checkpoints": corrupt,
               "resume_exit_code": resumed.returncode, "resume_stderr_tail": resumed.stderr[-2000:],
               "metrics_iterations": iterations,
               "stale_temp_files": [p.name for p in folder.glob(".*.tmp")] if folder.is_dir() else []}
    checks = [
        check("training process killed mid-run", killed, "true", killed),
        check("corrupt checkpoints after the kill", len(corrupt), "0", not corrupt),
        check("resume exit code", resumed.returncode, "0", resumed.returncode == 0),
        check("resumed at the next iteration", f"resumed from {last}", f"iteration {last + 1} follows",
              f"at iteration {last} " in resumed.stdout and iterations == list(range(1, last + 3))),
    ]
    return details, checks


def keep_other_modes(path: Path, modes: tuple[str, ...], meta: dict) -> list[dict]:
    """The checks and details of the modes not run now from an earlier report at ``path`` (one mode per command
    fits a 10-minute device call), so soak.json holds both."""
    if not path.is_file():
        return []
    earlier = json.loads(path.read_text())
    for mode in ("faults", "kill_resume"):
        if mode not in modes and mode in earlier.get("meta", {}):
            meta[mode] = earlier["meta"][mode]
            meta[f"{mode}_command"] = earlier["meta"].get(f"{mode}_command", earlier["meta"].get("command"))
    return [c for c in earlier.get("results", []) if c.get("mode") not in modes]


def check(name: str, value, limit: str, ok: bool) -> dict:
    return {"check": name, "value": value, "limit": limit, "ok": bool(ok)}


def plot_memory(json_path: Path, png: Path) -> Path | None:
    """Plot the faults mode's per-rollout memory series of ``json_path`` (soak.json) into ``png``; None without one."""
    meta = json.loads(Path(json_path).read_text())["meta"]
    series = meta.get("faults", {}).get("memory_series")
    if not series:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = [r["rollout"] for r in series]
    fig, ax = plt.subplots(figsize=(7, 3.5))
    for key, label in (("device_used_gib", "device in use (cudaMemGetInfo)"),
                       ("torch_reserved_gib", "torch reserved"), ("torch_allocated_gib", "torch allocated")):
        if series[0][key] is not None:
            ax.plot(x, [r[key] for r in series], label=label)
    ax.axvline(meta["faults"].get("memory_baseline_rollout", 0), color="grey", ls=":", label="baseline rollout")
    for event in meta["faults"].get("events", []):
        ax.axvline(event["step"] / max(1, meta["faults"]["policy_steps"]) * x[-1], color="red", alpha=0.3)
    ax.set_xlabel("rollout (red: faults)")
    ax.set_ylabel("GiB")
    ax.set_title(f"Soak memory: {meta['num_envs']:,} envs, {meta.get('gpu', meta['device'])}")
    ax.legend(fontsize=8, loc="center right")
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)
    return Path(png)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--mode", choices=("both", "faults", "kill_resume"), default="both", help="what to run")
    parser.add_argument("--preset", default="default", help="PPO preset (default: default)")
    parser.add_argument("--num_envs", type=int, default=16384, help="parallel worlds (default: 16384)")
    parser.add_argument("--minutes", type=float, default=8.0, help="training time of the faults mode (default: 8)")
    parser.add_argument("--device", default="cuda", help="cuda or cpu (default: cuda)")
    parser.add_argument("--fault_every", type=int, default=1000, help="policy steps between faults (default: 1000)")
    parser.add_argument("--normalization", default="running", choices=("running", "fixed"),
                        help="observation normalisation of the env (default: running, whose shared statistics a "
                             "NaN used to poison)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the fault placement (default: 0)")
    parser.add_argument("--kill_timeout", type=float, default=900.0,
                        help="seconds to wait for two checkpoints before the kill, and for the resume (default: 900)")
    parser.add_argument("--kill_jitter_s", type=float, default=2.0,
                        help="the kill comes up to this many seconds after the second checkpoint (default: 2)")
    parser.add_argument("--run_dir", default="/tmp/tocabi_soak", help="scratch folder of the runs")
    parser.add_argument("--out", default=str(REPO / "docs" / "benchmarks"), help="where soak.{json,md} go")
    parser.add_argument("--plot_only", action="store_true",
                        help="only redraw <out>/soak_memory.png from <out>/soak.json (no GPU needed)")
    args = parser.parse_args(argv)
    if args.plot_only:
        print(plot_memory(Path(args.out) / "soak.json", Path(args.out) / "soak_memory.png") or "no memory series")
        return 0
    meta = run_meta("soak.py", argv)
    modes = ("faults", "kill_resume") if args.mode == "both" else (args.mode,)
    earlier = keep_other_modes(Path(args.out) / "soak.json", modes, meta)
    checks = []
    for mode, run in (("faults", run_faults), ("kill_resume", run_kill_resume)):
        if mode in modes:
            meta[mode], found = run(args)
            meta[f"{mode}_command"] = meta["command"]
            checks += [{**c, "mode": mode} for c in found]
    meta.update(preset=args.preset, num_envs=args.num_envs, device=args.device, minutes=args.minutes,
                fault_every=args.fault_every, normalization=args.normalization)
    text = write_report(args.out, "soak", f"Soak: {args.num_envs:,} envs, preset {args.preset}, {args.device}", meta,
                        earlier + checks, ("mode", "check", "value", "limit", "ok"),
                        lambda c: (c["mode"], c["check"], str(c["value"]), c["limit"], "yes" if c["ok"] else "**NO**"))
    print(text)
    if "faults" in modes:
        plot_memory(Path(args.out) / "soak.json", Path(args.out) / "soak_memory.png")
    return 0 if all(c["ok"] for c in checks) else 1  # this command's checks


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
