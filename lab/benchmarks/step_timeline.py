"""Where a training iteration's GPU time goes, phase by phase, in one run of the real trainer (issue 25).

    python -m lab.benchmarks.step_timeline --num_envs 4096 --iterations 3     # GPU; docs/benchmarks/step_timeline.*
    python -m lab.benchmarks.step_timeline --num_envs 4096 --set env.sim.reset_pass=full --name step_timeline_full

``trainer.train`` runs the default preset as it always does; only marks are added, by wrapping what it calls (the
actor, the env's step and reset, the simulator's step, the rollout guard, GAE and the update), and removed after.
A mark is a CUDA event recorded on the stream, so nothing waits: the time between two marks is the GPU time of the
work queued between them, idle gaps included where the host lagged. The intervals tile the timed iterations, so
they add up to them. Where the GPU is the bottleneck (at 4,096 envs the physics fills it: the overlap probe,
docs/benchmarks.md), each phase's share is what it costs the training rate; where the host is, a phase's interval
also holds the host's lag, and the ~10 event records per step add a little host time of their own.

Phases per policy step: the policy's forward; the collector's work between policy and env; the env before the physics
(action checks, controls); the physics (``sim.step``: 8 substeps and the step's forward pass); signals, rewards,
transforms and ``step_mdp``; the masked reset (every step, all worlds, in the sync-free env of GPU training) in three
parts: the env's bookkeeping up to the simulator's reset, the simulator's reset (full or reduced pass) and the
observation after it; the reset's merge; the collector's storage until the next step (the last step's also holds the
end of the rollout: the collector's stacking, the trainer's shallow copy, the read of the previous update's numbers
with its learning rate and log row, and, on several ranks, the statistics sync). Per iteration: the rollout guard;
GAE; the selection of the loss's keys and the flattening (and the torque assist's bookkeeping, the scheduled rate and
std); the PPO update (mini-batch gathers included); the iteration's end (the assist and kick schedules, the metrics'
copy, checkpoints). Reported in ms per policy step of all envs (iteration phases divided by the rollout length),
beside raw mujoco-warp's policy step measured in the same process. The env step must run eagerly: a captured step
(``ppo.cuda_graph`` "on", or "auto" at up to ``cuda_graphs.ENV_GRAPH_AUTO_MAX_ENVS`` envs) has no points to mark and
is refused. Off CUDA the marks are host clocks (a smoke run).
"""

from __future__ import annotations

import contextlib

import torch

from . import common

NAME = "step_timeline"
#: Phases in the order they occur; a mark starts its phase, which lasts until the next mark.
STEP_PHASES = ("policy forward", "collector between policy and env", "env before the physics", "physics (sim.step)",
               "signals, rewards, transforms, step_mdp", "masked reset: env before the simulator",
               "masked reset: simulator", "masked reset: observation", "reset merge", "collector storage")
ITERATION_PHASES = ("rollout guard", "GAE", "loss keys and flattening", "PPO update",
                    "iteration end (assist, kicks, metrics copy, checkpoints)")


class Timeline:
    """Marks on the device's queue (CUDA events, or host clocks off CUDA); ``collecting`` gates the per-step marks,
    which the actor's hooks would otherwise also set inside the update (the loss calls the actor)."""

    def __init__(self, device: torch.device):
        self.cuda = device.type == "cuda"
        self.marks: list[tuple[str, object]] = []
        self.iteration_ends: list[int] = []  # index of each "iteration end" mark
        self.collecting = True

    def mark(self, phase: str) -> None:
        if self.cuda and torch.cuda.is_current_stream_capturing():
            return  # a graph being captured (the update step) takes no timing events
        self.marks.append((phase, common.stamp(self.cuda)))

    def step_mark(self, phase: str) -> None:
        if self.collecting:
            self.mark(phase)

    def window(self, first: int, last: int) -> dict[str, float]:
        """Milliseconds per phase from iteration ``first``'s end mark to iteration ``last``'s (0-based)."""
        if self.cuda:
            torch.cuda.synchronize()
        lo, hi = self.iteration_ends[first], self.iteration_ends[last]
        totals: dict[str, float] = {}
        for (phase, a), (_, b) in zip(self.marks[lo:hi], self.marks[lo + 1:hi + 1]):
            totals[phase] = totals.get(phase, 0.0) + common.elapsed_ms(a, b, self.cuda)
        return totals


@contextlib.contextmanager
def marked_trainer(timeline: Timeline):
    """The trainer's functions, and the env, simulator, actor and GAE it builds, with marks around them; all put
    back on exit, also after an error."""
    trainer = common.trainer
    saved = {k: getattr(trainer, k) for k in ("make_collector", "make_loss", "guard_rollout", "_update_stats")}
    undo: list = []
    mark = {phase: (lambda p=phase: timeline.step_mark(p)) for phase in STEP_PHASES}
    policy, between, env_in, physics, signals, reset, reset_sim, reset_obs, merge, storage = STEP_PHASES

    def make_collector(cfg, env, actor, *args, **kwargs):
        undo.append(actor.register_forward_pre_hook(lambda *_: mark[policy]()).remove)
        undo.append(actor.register_forward_hook(lambda *_: mark[between]()).remove)
        common.wrap_method(env, "step_and_maybe_reset", mark[env_in], mark[storage], undo)
        common.wrap_method(env.base_env.sim, "step", mark[physics], mark[signals], undo)
        # Sync-free envs reset every step (masked); others only when an episode ended, where their phase shows it.
        common.wrap_method(env, "_reset", mark[reset], mark[merge], undo)
        for name in ("reset", "reset_to_start"):  # the full pass, or the reduced one: whichever the env calls
            if hasattr(env.base_env.sim, name):
                common.wrap_method(env.base_env.sim, name, mark[reset_sim], mark[reset_obs], undo)
        return saved["make_collector"](cfg, env, actor, *args, **kwargs)

    def make_loss(*args, **kwargs):
        loss_module, advantage = saved["make_loss"](*args, **kwargs)
        common.wrap_method(advantage, "forward", lambda: timeline.mark(ITERATION_PHASES[1]),
                           lambda: timeline.mark(ITERATION_PHASES[2]), undo)
        return loss_module, advantage

    def guard_rollout(*args, **kwargs):
        timeline.collecting = False  # the rollout is in: what follows is the iteration's own work
        timeline.mark(ITERATION_PHASES[0])
        return saved["guard_rollout"](*args, **kwargs)

    def update(*args, **kwargs):
        timeline.mark(ITERATION_PHASES[3])
        stats = saved["_update_stats"](*args, **kwargs)  # queued: its losses are read an iteration later
        timeline.iteration_ends.append(len(timeline.marks))
        timeline.mark(ITERATION_PHASES[4])
        timeline.collecting = True
        return stats

    with common.trainer_patched({"make_collector": make_collector, "make_loss": make_loss,
                                 "guard_rollout": guard_rollout, "_update_stats": update}, undo):
        yield


def measure(n: int, iterations: int, warmup: int, raw_steps: int, device: str, run_dir: str, overrides: dict) -> dict:
    """One env count: ``warmup`` iterations, then the phases of ``iterations`` more, then the raw ceiling."""
    cfg, at = common.eager_step_config(NAME, n, warmup + iterations, overrides, run_dir, f"timeline_{n}", device)
    timeline = Timeline(at)
    with marked_trainer(timeline):
        common.train(cfg)
    steps = cfg.ppo.steps_per_env
    totals = timeline.window(warmup - 1, warmup - 1 + iterations)
    for phase in (*STEP_PHASES, *ITERATION_PHASES):
        if phase not in totals:  # e.g. no episode ended in an env that resets only then; never in GPU training
            print(f"step_timeline: no mark of phase {phase!r} in the timed iterations; it is reported as 0", flush=True)
    per_step = {phase: ms / (iterations * steps) for phase, ms in totals.items()}
    step_ms = sum(per_step.values())
    raw = common.raw_policy_steps_per_second(n, raw_steps, device) if raw_steps else None
    raw_ms = 1e3 * n / raw if raw else None
    return {"num_envs": n, "iterations": iterations, "warmup": warmup, "steps_per_env": steps, "overrides": overrides,
            "ms_per_policy_step": {p: per_step.get(p, 0.0) for p in (*STEP_PHASES, *ITERATION_PHASES)},
            "step_ms": step_ms, "train_env_steps_per_s": 1e3 * n / step_ms,
            "raw_policy_steps_per_s": raw, "raw_step_ms": raw_ms,
            "ratio_train_over_raw": raw_ms / step_ms if raw_ms else None}


def render(data: dict, out) -> str:
    parts = []
    for r in data["results"]:
        ms, total, raw = r["ms_per_policy_step"], r["step_ms"], r["raw_step_ms"]
        rows = [(phase, f"{v:.3f}", f"{100 * v / total:.1f} %") for phase, v in ms.items()]
        rows.append(("**all** (train env-steps/s: " + common.fmt(r["train_env_steps_per_s"]) + ")", f"{total:.3f}",
                     "100 %"))
        if raw:
            label = f"raw mujoco-warp policy step (same process), train / raw = {r['ratio_train_over_raw']:.3f}"
            rows.append((label, f"{raw:.3f}", f"{100 * raw / total:.1f} %"))
        parts.append(f"### {r['num_envs']:,} envs, {r['iterations']} iterations of {r['steps_per_env']} steps after "
                     f"{r['warmup']} warm-up, overrides {r['overrides'] or 'none'}\n\n"
                     + common.table(("phase", "ms per policy step", "share"), rows))
    return common.page("Phases of a training iteration", data, "\n\n".join(parts))


def main(argv=None) -> dict:
    return common.trainer_benchmark(argv, NAME, __doc__, measure, render, min_warmup=1, min_raw_steps=0,
                                    device_help="cuda, or cpu for a smoke run (host clocks)")


if __name__ == "__main__":
    main()
