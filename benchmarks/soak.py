"""Soak test: train while faults are injected and check that nothing leaks out of the broken worlds; then kill a
training process and resume it.

    python -m benchmarks.soak --mode faults        # GPU: default preset, 16,384 envs, 8 min
    python -m benchmarks.soak --mode kill_resume
    python -m benchmarks.soak --num_envs 8 --minutes 0.25 --device cpu --fault_every 40 --out /tmp/soak   # tiny CPU

``faults``: training with running observation normalisation (statistics every world shares); every ``--fault_every``
policy steps one world gets NaN in its ``qvel``, another a push of 10x body weight for 4 ms, a third actions of ±1e6
and NaN (the policy is wrapped, so PPO's rollout sees them too). A transform counts, on the device, NaN/inf in the
other worlds' observations and rewards (must be 0) and whether each NaN world terminated and reset. Afterwards
parameters, optimiser and normaliser state and metrics must be finite, and device memory may grow at most 1 % from the
tenth rollout on. ``kill_resume``: ``recipes/ppo_walk.py`` is SIGKILLed mid-iteration once two checkpoints exist;
every checkpoint must load and ``--resume`` go on at the next iteration. One mode per command keeps the other's
results in ``soak.json``; exit status 1 when a check fails.
"""

from __future__ import annotations

import argparse
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
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.transforms import Transform

from tocabi_torchrl import robot
from tocabi_torchrl.rl.curves import read_metrics

from . import common

REPO = Path(__file__).resolve().parents[1]
PUSH_DV = 10.0 * robot.GRAVITY * 0.004  # velocity change of 10x body weight for one 4 ms policy step
WARMUP_ROLLOUTS = 10  # memory baseline: buffers, graphs and allocator pools exist by then


class FaultInjector(TensorDictModuleBase):
    """The policy plus, every ``every`` calls, three faults in three random worlds; ``nan_now``/``hit_now`` are device
    masks of the worlds hit in the current step."""

    def __init__(self, actor, sim, every: int, seed: int):
        super().__init__()
        self.actor, self.sim, self.every, self.rng = actor, sim, every, random.Random(seed)
        self.in_keys, self.out_keys = actor.in_keys, actor.out_keys
        self.nan_now = torch.zeros(sim.num_worlds, dtype=torch.bool, device=sim.device)
        self.hit_now = torch.zeros_like(self.nan_now)
        self.calls, self.events = 0, []

    def forward(self, td):
        td = self.actor(td)
        self.calls += 1
        self.nan_now.zero_()
        self.hit_now.zero_()
        if self.calls % self.every == 0 and self.sim.num_worlds >= 3:
            nan_w, push_w, act_w = self.rng.sample(range(self.sim.num_worlds), 3)
            angle = self.rng.uniform(0.0, 2.0 * math.pi)
            self.sim.qvel[nan_w] = float("nan")
            self.sim.qvel[push_w, 0] += PUSH_DV * math.cos(angle)
            self.sim.qvel[push_w, 1] += PUSH_DV * math.sin(angle)
            action = td.get("action")
            action[act_w, 0::2], action[act_w, 1::2], action[act_w, 0] = 1e6, -1e6, float("nan")
            self.nan_now[nan_w] = True
            self.hit_now[[nan_w, push_w, act_w]] = True
            self.events.append({"step": self.calls, "nan_world": nan_w, "push_world": push_w, "action_world": act_w})
        return td


class SoakMonitor(Transform):
    """Device counters of NaN/inf inside and outside the worlds hit in each step, of NaN worlds that terminated and
    reset, and one memory row per rollout (device, torch allocated and reserved, host RSS)."""

    NAMES = ("obs_outside", "reward_outside", "reset_obs_outside", "obs_hit", "reward_hit", "nan_worlds",
             "nan_terminated", "nan_reset")

    def __init__(self, steps_per_env: int, device: torch.device):
        super().__init__()
        self.steps_per_env, self.steps, self.memory_start, self.series = steps_per_env, 0, None, []
        self.counts = torch.zeros(len(self.NAMES), dtype=torch.int64, device=device)
        object.__setattr__(self, "injector", None)  # not a submodule: it would land in every checkpoint

    def _step(self, tensordict, next_td):
        inj = self.injector
        if inj is None:
            return next_td
        bad_obs = ~torch.isfinite(next_td["observation"]).all(-1)
        bad_rew = ~torch.isfinite(next_td["reward"]).all(-1)
        hit, nan = inj.hit_now, inj.nan_now
        self.counts[[0, 1, 3, 4, 5, 6]] += torch.stack([(bad_obs & ~hit).sum(), (bad_rew & ~hit).sum(),
                                                         (bad_obs & hit).sum(), (bad_rew & hit).sum(), nan.sum(),
                                                         (nan & next_td["terminated"].squeeze(-1)).sum()])
        self.steps += 1
        if self.steps % self.steps_per_env == 0:
            dev = self.counts.device
            cuda = dev.type == "cuda"
            self.series.append({"rollout": self.steps // self.steps_per_env, "device_used_gib": common.device_used_gib(
                dev), "torch_allocated_gib": torch.cuda.memory_allocated(dev) / common.GIB if cuda else 0.0,
                "torch_reserved_gib": torch.cuda.memory_reserved(dev) / common.GIB if cuda else 0.0,
                "host_rss_mib": common.rss_gib() * 1024})
        if self.steps == WARMUP_ROLLOUTS * self.steps_per_env:
            self.memory_start = (common.device_used_gib(self.counts.device), common.rss_gib() * 1024)
        return next_td

    def _reset(self, tensordict, tensordict_reset):
        if self.injector is not None and tensordict is not None and "_reset" in tensordict.keys():
            flagged = tensordict["_reset"].squeeze(-1)
            bad = ~torch.isfinite(tensordict_reset["observation"]).all(-1) & flagged
            self.counts[[2, 7]] += torch.stack([(bad & ~self.injector.hit_now).sum(),
                                                (flagged & self.injector.nan_now).sum()])
        return tensordict_reset


def nonfinite(obj) -> int:
    """NaN/inf entries in the floating tensors of a nested dict/list."""
    if torch.is_tensor(obj):
        return int((~torch.isfinite(obj)).sum()) if obj.is_floating_point() else 0
    values = obj.values() if isinstance(obj, dict) else obj if isinstance(obj, (list, tuple)) else ()
    return sum(nonfinite(v) for v in values)


def check(name: str, value, limit: str, ok: bool) -> dict:
    return {"check": name, "value": value, "limit": limit, "ok": bool(ok)}


def soak_config(args, name: str, **extra):
    base = common.config(args.preset)
    # cuda_graph off: the monitor keeps Python-side state in the env step, which a captured graph would freeze.
    return common.config(args.preset, num_envs=args.num_envs, device=args.device, run_dir=args.run_dir, name=name,
                         minibatch_size=min(base.minibatch_size, max(args.num_envs * base.steps_per_env // 4, 1)),
                         eval_at_end=False, progress_bar=False, total_env_steps=10**12, cuda_graph="off", **extra)


def run_faults(args) -> tuple[dict, list[dict]]:
    cfg = soak_config(args, "soak_faults", max_minutes=args.minutes, checkpoint_every=10**6)
    shutil.rmtree(Path(cfg.run_dir) / cfg.name, ignore_errors=True)  # the soak's own scratch run
    env = common.build_env(cfg, for_training=True, normalization=args.normalization)
    monitor = SoakMonitor(cfg.steps_per_env, env.device)
    env.append_transform(monitor)

    def wrap(actor):
        injector = FaultInjector(actor, env.base_env.sim, args.fault_every, args.seed)
        object.__setattr__(monitor, "injector", injector)
        return injector

    t0 = time.perf_counter()
    result, rows = common.train_wrapping_policy(cfg, env, wrap)
    wall, inj, c = time.perf_counter() - t0, monitor.injector, dict(zip(SoakMonitor.NAMES, monitor.counts.tolist()))
    end = (common.device_used_gib(env.device), common.rss_gib() * 1024)
    start = monitor.memory_start or end
    state = common.read_checkpoint(result.run_dir)
    bad_metrics = {}
    for row in rows:  # return and length are NaN by design in an iteration where no episode ended
        skip = () if float(row.get("episodes_finished") or 0) > 0 else ("episode_return", "episode_length")
        for key, value in row.items():
            try:
                if key not in skip and not math.isfinite(float(value)):
                    bad_metrics[key] = bad_metrics.get(key, 0) + 1
            except (TypeError, ValueError):
                pass
    growth = None if start[0] is None else 100.0 * (end[0] - start[0]) / start[0]
    d = {"policy_steps": inj.calls, "env_steps": result.env_steps, "iterations": result.iterations, "wall_s": wall,
         "fault_events": len(inj.events), "events": inj.events[:50], "monitor": c,
         "nonfinite_parameters": nonfinite(state["agent"]), "nonfinite_optimizer": nonfinite(state.get("optimizer")),
         "nonfinite_normaliser_and_transforms": nonfinite(state.get("transforms")), "nonfinite_metrics": bad_metrics,
         "metrics_rows": len(rows), "device_used_gib_start": start[0], "device_used_gib_end": end[0],
         "device_growth_pct": growth, "host_rss_mib_start": start[1], "host_rss_mib_end": end[1],
         "host_rss_growth_pct": 100.0 * (end[1] - start[1]) / start[1], "memory_baseline_rollout": WARMUP_ROLLOUTS,
         "memory_series": monitor.series}
    outside, own = c["obs_outside"] + c["reward_outside"] + c["reset_obs_outside"], c["obs_hit"] + c["reward_hit"]
    return d, [
        check("faults injected", len(inj.events), ">= 1", inj.events),
        check("NaN/inf in observations/rewards outside injected worlds", outside, "0", outside == 0),
        check("NaN/inf in the injected worlds' own outputs", own, "0", own == 0),
        check("NaN worlds terminated", f"{c['nan_terminated']}/{c['nan_worlds']}", "all",
              c["nan_terminated"] == c["nan_worlds"]),
        check("NaN worlds reset", f"{c['nan_reset']}/{c['nan_worlds']}", "all", c["nan_reset"] == c["nan_worlds"]),
        check("NaN/inf in network parameters", d["nonfinite_parameters"], "0", d["nonfinite_parameters"] == 0),
        check("NaN/inf in optimiser state", d["nonfinite_optimizer"], "0", d["nonfinite_optimizer"] == 0),
        check("NaN/inf in normaliser / transform state", d["nonfinite_normaliser_and_transforms"], "0",
              d["nonfinite_normaliser_and_transforms"] == 0),
        check("non-finite training metrics", sum(bad_metrics.values()), "0", not bad_metrics),
        check("device memory growth [%]", "n/a" if growth is None else f"{growth:.2f}", "<= 1",
              growth is None or growth <= 1.0),
        check("host RSS growth [%]", f"{d['host_rss_growth_pct']:.1f}", "reported", True)]


def run_kill_resume(args) -> tuple[dict, list[dict]]:
    name, run = "soak_kill", Path(args.run_dir) / "soak_kill"
    shutil.rmtree(run, ignore_errors=True)
    cfg = soak_config(args, name)
    recipe = [sys.executable, str(REPO / "recipes" / "ppo_walk.py")]
    options = ["--preset", args.preset, "--num_envs", str(args.num_envs), "--device", args.device, "--name", name,
               "--run_dir", args.run_dir, "--minibatch_size", str(cfg.minibatch_size), "--eval_at_end", "false",
               "--progress_bar", "false", "--checkpoint_every", "1"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (str(REPO), os.environ.get("PYTHONPATH"))))}
    run.parent.mkdir(parents=True, exist_ok=True)
    log_path, folder = run.parent / f"{name}.log", run / "checkpoints"
    with open(log_path, "w") as log:
        proc = subprocess.Popen([*recipe, *options, "--total_env_steps", str(10**12)], env=env, stdout=log,
                                stderr=subprocess.STDOUT)
    deadline = time.time() + args.kill_timeout
    while time.time() < deadline and proc.poll() is None:
        if folder.is_dir() and len(list(folder.glob("iter_*.pt"))) >= 2:
            time.sleep(random.Random(args.seed).uniform(0.0, args.kill_jitter_s))  # somewhere in an iteration
            break
        time.sleep(0.05)
    killed = proc.poll() is None
    if killed:
        os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    if not killed:  # it ended by itself (on an H100 once, 25 s in): say why, from its log
        return ({"killed": False, "exit_code": proc.returncode, "training_log_tail": log_path.read_text()[-3000:]},
                [check("training process killed mid-run", f"exited by itself with code {proc.returncode}", "true",
                       False)])
    corrupt = []
    for path in sorted(folder.glob("*.pt")):
        try:
            common.read_checkpoint(path)
        except Exception as err:  # noqa: BLE001 - any failure is a corrupt checkpoint
            corrupt.append(f"{path.name}: {err}")
    last = common.read_checkpoint(run)["iteration"] if (folder / "latest.pt").is_file() else 0
    resumed = subprocess.run([*recipe, "--resume", str(run), "--total_env_steps", str((last + 2) *
                              cfg.frames_per_batch)], env=env, capture_output=True, text=True, timeout=args.kill_timeout)
    iterations = [int(r["iteration"]) for r in read_metrics(run / "metrics.csv")]
    d = {"killed": killed, "last_checkpoint_iteration": last, "corrupt_checkpoints": corrupt,
         "resume_exit_code": resumed.returncode, "resume_stderr_tail": resumed.stderr[-2000:],
         "metrics_iterations": iterations, "stale_temp_files": [p.name for p in folder.glob(".*.tmp")]}
    return d, [check("training process killed mid-run", killed, "true", killed),
               check("corrupt checkpoints after the kill", len(corrupt), "0", not corrupt),
               check("resume exit code", resumed.returncode, "0", resumed.returncode == 0),
               check("resumed at the next iteration", f"resumed from {last}", f"iteration {last + 1} follows",
                     f"at iteration {last} " in resumed.stdout and iterations == list(range(1, last + 3)))]


def render(data: dict, out: Path) -> str:
    m = data["meta"]
    series = m.get("faults", {}).get("memory_series")
    plt = common.pyplot()
    if series and plt is not None:
        fig, ax = plt.subplots(figsize=(7, 3.5))
        x = [r["rollout"] for r in series]
        for key in ("device_used_gib", "torch_reserved_gib", "torch_allocated_gib"):
            if series[0][key] is not None:
                ax.plot(x, [r[key] for r in series], label=key.replace("_gib", ""))
        ax.axvline(m["faults"]["memory_baseline_rollout"], color="grey", ls=":", label="baseline rollout")
        for event in m["faults"]["events"]:
            ax.axvline(event["step"] / max(1, m["faults"]["policy_steps"]) * x[-1], color="red", alpha=0.3)
        ax.set(xlabel="rollout (red: faults)", ylabel="GiB", title=f"Soak memory: {m['num_envs']:,} envs")
        ax.legend(fontsize=8)
        common.save(fig, out / "soak_memory.png")
    rows = [(c["mode"], c["check"], c["value"], c["limit"], "yes" if c["ok"] else "**NO**") for c in data["results"]]
    commands = "\n".join(f"- {mode}: `{m[mode + '_command']}`" for mode in ("faults", "kill_resume")
                         if mode + "_command" in m)
    return common.page(f"Soak: {m['num_envs']:,} envs, preset {m['preset']}, {m['device']}", data,
                       common.table(("mode", "check", "value", "limit", "ok"), rows) + f"\n\n{commands}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--mode", choices=("both", "faults", "kill_resume"), default="both")
    parser.add_argument("--preset", default="default")
    parser.add_argument("--num_envs", type=int, default=16384)
    parser.add_argument("--minutes", type=float, default=8.0, help="training time of the faults mode")
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--fault_every", type=int, default=1000, help="policy steps between faults")
    parser.add_argument("--normalization", default="running", choices=("running", "fixed"))
    parser.add_argument("--seed", type=int, default=0, help="seed of the fault placement")
    parser.add_argument("--kill_timeout", type=float, default=900.0, help="seconds to wait for checkpoints and resume")
    parser.add_argument("--kill_jitter_s", type=float, default=2.0, help="kill up to this long after checkpoint 2")
    parser.add_argument("--run_dir", default="/tmp/tocabi_soak", help="scratch folder of the runs")
    parser.add_argument("--out", default=str(common.DOCS))
    args = parser.parse_args(argv)
    modes = ("faults", "kill_resume") if args.mode == "both" else (args.mode,)
    meta = common.meta("soak", argv, args.device, preset=args.preset, num_envs=args.num_envs, device=args.device,
                       minutes=args.minutes, fault_every=args.fault_every, normalization=args.normalization)
    earlier = Path(args.out) / "soak.json"
    earlier = json.loads(earlier.read_text()) if earlier.is_file() else {"meta": {}, "results": []}
    checks = [c for c in earlier["results"] if c["mode"] not in modes]  # the other mode's, from an earlier command
    meta.update({k: v for k, v in earlier["meta"].items() if k.split("_command")[0] not in modes and
                 k.split("_command")[0] in ("faults", "kill_resume")})
    for mode, run in (("faults", run_faults), ("kill_resume", run_kill_resume)):
        if mode in modes:
            meta[mode], found = run(args)
            meta[f"{mode}_command"] = meta["command"]
            checks += [{**c, "mode": mode} for c in found]
    print(common.publish(args.out, "soak", {"meta": meta, "results": checks}, render))
    return 0 if all(c["ok"] for c in checks if c["mode"] in modes) else 1


if __name__ == "__main__":
    sys.exit(main())
