"""Soak: train while faults are injected; nothing may leak out of the broken worlds (exit status 1 if a check fails).

    python -m lab.benchmarks.soak                      # GPU: default preset, 16,384 envs, 8 min of training

Every ``--fault_every`` policy steps one world gets NaN in ``qvel``, one a 10x-body-weight push, one actions of ±1e6
and NaN (through the policy, so PPO sees them); the checks are the report's rows (docs/benchmarks.md). The former
``kill_resume`` mode is ``tests/test_runs.py``'s now.
"""

from __future__ import annotations

import argparse
import math
import random
import shutil
import sys
import time
from pathlib import Path

import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.transforms import Transform

from tocabi_torchrl import robot

from . import common

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
        self.steps_per_env, self.steps, self.series = steps_per_env, 0, []
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
        if self.steps % self.steps_per_env == 0:  # one row per rollout: a leak against the allocator's pool settling
            dev, cuda = self.counts.device, self.counts.is_cuda
            self.series.append({"rollout": self.steps // self.steps_per_env, "device_used_gib": common.device_used_gib(
                dev), "torch_allocated_gib": torch.cuda.memory_allocated(dev) / common.GIB if cuda else 0.0,
                "torch_reserved_gib": torch.cuda.memory_reserved(dev) / common.GIB if cuda else 0.0,
                "host_rss_mib": common.rss_gib() * 1024})
        return next_td

    def _reset(self, tensordict, tensordict_reset):
        # A TensorDict refuses `in`: its keys() answer it.
        if self.injector is not None and tensordict is not None and "_reset" in tensordict.keys():  # noqa: SIM118
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


def run_faults(args) -> tuple[dict, list[dict]]:
    base = common.config(args.preset).ppo
    # cuda_graph off: the monitor keeps Python-side state in the env step, which a captured graph would freeze.
    batch = min(base.minibatch_size, max(args.num_envs * base.steps_per_env // 4, 1))
    cfg = common.config(args.preset, **{"env.num_envs": args.num_envs, "ppo.minibatch_size": batch},
                        device=args.device, run_dir=args.run_dir, name="soak",
                        eval_at_end=False, progress_bar=False, total_env_steps=10**12, **{"ppo.cuda_graph": "off"},
                        max_minutes=args.minutes, checkpoint_every=10**6,
                        **{"transforms.normalization": args.normalization})
    shutil.rmtree(Path(cfg.run_dir) / cfg.name, ignore_errors=True)  # the soak's own scratch run
    env = common.build_env(cfg, for_training=True)
    env.append_transform(monitor := SoakMonitor(cfg.ppo.steps_per_env, env.device))

    def wrap(actor):
        object.__setattr__(monitor, "injector", FaultInjector(actor, env.base_env.sim, args.fault_every, args.seed))
        return monitor.injector

    t0 = time.perf_counter()
    result, rows = common.train(cfg, env, wrap_policy=wrap)
    wall, inj, c = time.perf_counter() - t0, monitor.injector, dict(zip(SoakMonitor.NAMES, monitor.counts.tolist()))
    end, state = (common.device_used_gib(env.device), common.rss_gib() * 1024), common.read_checkpoint(result.run_dir)
    start, memory = memory_checks(monitor.series, end)
    bad = {}
    for row in rows:  # return and length are NaN by design in an iteration where no episode ended
        skip = () if float(row.get("episodes_finished") or 0) > 0 else ("episode_return", "episode_length")
        for k, v in row.items():
            if k not in skip and v not in (None, "") and not math.isfinite(float(v)):
                bad[k] = bad.get(k, 0) + 1
    d = {"policy_steps": inj.calls, "env_steps": result.env_steps, "iterations": result.iterations, "wall_s": wall,
         "fault_events": len(inj.events), "events": inj.events[:50], "monitor": c, "nonfinite_metrics": bad,
         "device_used_gib_start": start[0], "device_used_gib_end": end[0], "host_rss_mib_start": start[1],
         "host_rss_mib_end": end[1], "memory_baseline_rollout": WARMUP_ROLLOUTS, "memory_series": monitor.series}
    params, optim, norm = (nonfinite(state.get(k)) for k in ("agent", "optimizer", "transforms"))
    outside, own = c["obs_outside"] + c["reward_outside"] + c["reset_obs_outside"], c["obs_hit"] + c["reward_hit"]
    nan = f"{c['nan_terminated']}/{c['nan_worlds']}", f"{c['nan_reset']}/{c['nan_worlds']}"
    return d, [{"check": name, "value": value, "limit": limit, "ok": bool(ok)} for name, value, limit, ok in [
        ("faults injected", len(inj.events), ">= 1", inj.events),
        ("NaN/inf in observations/rewards outside injected worlds", outside, "0", outside == 0),
        ("NaN/inf in the injected worlds' own outputs", own, "0", own == 0),
        ("NaN worlds terminated", nan[0], "all", c["nan_terminated"] == c["nan_worlds"]),
        ("NaN worlds reset", nan[1], "all", c["nan_reset"] == c["nan_worlds"]),
        ("NaN/inf in network parameters", params, "0", params == 0),
        ("NaN/inf in optimiser state", optim, "0", optim == 0),
        ("NaN/inf in normaliser / transform state", norm, "0", norm == 0),
        ("non-finite training metrics", sum(bad.values()), "0", not bad), *memory]]


def memory_checks(series: list[dict], end: tuple) -> tuple[tuple, list[tuple]]:
    """The memory at the baseline (rollout :data:`WARMUP_ROLLOUTS`'s row of ``series``) and the report's rows of the
    growth from there to ``end`` (device GiB, None off CUDA; host RSS MiB). A run that ended before a rollout after
    the baseline measured no growth: its device check fails rather than passing on the end against itself."""
    if len(series) <= WARMUP_ROLLOUTS:
        short = f"not measured (the run ended at rollout {len(series)}, the baseline is rollout {WARMUP_ROLLOUTS})"
        return (None, None), [("device memory growth [%]", "n/a" if end[0] is None else short, "<= 1", end[0] is None),
                              ("host RSS growth [%]", short, "reported", True)]
    start = series[WARMUP_ROLLOUTS - 1]["device_used_gib"], series[WARMUP_ROLLOUTS - 1]["host_rss_mib"]
    growth = None if start[0] is None else 100.0 * (end[0] - start[0]) / start[0]
    return start, [("device memory growth [%]", common.fmt(growth, ".2f", "n/a"), "<= 1", growth is None or growth <= 1.0),
                   ("host RSS growth [%]", f"{100.0 * (end[1] - start[1]) / start[1]:.1f}", "reported", True)]


def render(data: dict, out: Path) -> str:
    m = data["meta"]
    if series := m.get("faults", {}).get("memory_series"):
        x, f = [r["rollout"] for r in series], m["faults"]
        common.plot(out / "soak_memory.png", [{"lines": {k[:-4]: (x, [r[k] for r in series]) for k in (
            "device_used_gib", "torch_reserved_gib", "torch_allocated_gib") if series[0][k] is not None},
            "vlines": [f["memory_baseline_rollout"], *(e["step"] / f["policy_steps"] * x[-1] for e in f["events"])],
            "xlabel": "rollout (dotted: baseline, then the faults)", "ylabel": "GiB"}], f"Soak: {m['num_envs']:,} envs")
    rows = [(c["mode"], c["check"], c["value"], c["limit"], "yes" if c["ok"] else "**NO**") for c in data["results"]]
    commands = [f"- {mode}: `{m[mode + '_command']}`" for mode in ("faults", "kill_resume") if mode + "_command" in m]
    return common.page(f"Soak: {m['num_envs']:,} envs, preset {m['preset']}, {m['device']}", data,
                       common.table(("mode", "check", "value", "limit", "ok"), rows) + "\n\n" + "\n".join(commands))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--normalization", default="running", choices=("running", "fixed"),
                        help="observation normaliser (transforms.normalization): running statistics updated in "
                             "training, which the faults must not poison, or the fixed reference ones "
                             "(default: running)")
    for name, default, text in (("preset", "default", "training preset"), ("num_envs", 16384, "worlds"),
                                ("minutes", 8.0, "training time"), ("device", "cuda", "cuda or cpu"),
                                ("fault_every", 1000, "policy steps between faults"), ("seed", 0, "fault placement"),
                                ("run_dir", "/tmp/tocabi_soak", "scratch folder of the run"),
                                ("out", str(common.DOCS), "where soak.{json,md} go")):
        parser.add_argument(f"--{name}", type=type(default), default=default, help=f"{text} (default: {default})")
    args = parser.parse_args(argv)
    if args.preset not in common.presets:
        parser.error(f"--preset {args.preset!r}: no such preset; choose one of {', '.join(common.presets)}")
    if args.num_envs < 1 or args.fault_every < 1 or not 0 < args.minutes < math.inf:  # minutes 0: no time limit
        parser.error(f"--num_envs and --fault_every must be >= 1 and --minutes a positive number, got "
                     f"{args.num_envs}, {args.fault_every} and {args.minutes}")
    meta = common.meta("soak", argv, args.device, preset=args.preset, num_envs=args.num_envs, device=args.device,
                       minutes=args.minutes, fault_every=args.fault_every, normalization=args.normalization)
    meta["faults"], results = run_faults(args)
    meta["faults_command"] = meta["command"]
    results = [{**c, "mode": "faults"} for c in results]
    print(common.publish(args.out, "soak", {"meta": meta, "results": results}, render, measured_on=args.device))
    return 0 if all(c["ok"] for c in results) else 1


if __name__ == "__main__":
    sys.exit(main())
