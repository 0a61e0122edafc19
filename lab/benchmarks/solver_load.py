"""How much physics a training step asks for, against the raw ceiling's standing robots (issue 25).

    python -m lab.benchmarks.solver_load --num_envs 4096            # GPU: docs/benchmarks/solver_load.{json,md}
    python -m lab.benchmarks.solver_load --device cpu --num_envs 16 --iterations 1 --raw_steps 8   # warp's CPU device

The train / raw ratio divides by raw mujoco-warp stepping robots that stand still under a PD hold
(``common.raw_policy_step``). Training steps other states: robots that step, stumble and fall under an exploring
policy. mujoco-warp's Newton solver iterates every world until the slowest one converges (``wp.capture_while`` on
the count of unconverged worlds), and its constraint rows follow the contacts, so the same 8 substeps can cost more
there. This measures both workloads in one process on the same model: for the real trainer (default preset, from
scratch, ``--warmup`` untimed iterations, then ``--iterations`` timed) the simulator's step, and for the raw ceiling
its recorded step (after the ceiling's own settling steps, ``common.RAW_WARMUP``). Per policy step: its time (CUDA
events around the step, so nothing waits; host clocks off CUDA), and after it, over all worlds: the largest and the
mean solver iteration count of the last solve (the raw step's last substep; the env step's closing forward pass,
warm-started like a substep), the mean number of constraint rows and of contacts. The counts are copied on the
device after each step and read once at the end. The trainer's step runs eagerly (its physics is one recorded graph
either way); a captured env step has no points to mark and is refused.
"""

from __future__ import annotations

import contextlib

import torch

from . import common

NAME = "solver_load"
#: The per-world warp ``Data`` fields recorded after each step (``nacon``, a count over all worlds, is recorded too).
FIELDS = ("solver_niter", "nefc")


class Recorder:
    """Times steps (CUDA events, or host clocks off CUDA) and copies the per-world counts after each, on the device;
    ``on`` gates the recording (the trainer's warm-up iterations are not recorded)."""

    def __init__(self, device: torch.device, counts: bool = True):
        self.cuda = device.type == "cuda"
        self.on = True
        self.spans: list[tuple[object, object]] = []
        #: per-world counts copied after each step (none with ``counts=False``: the times alone, no extra kernels).
        self.counts: dict[str, list[torch.Tensor]] = {name: [] for name in (*FIELDS, "nacon")} if counts else {}
        self._start = None

    def before(self) -> None:
        self._start = common.stamp(self.cuda) if self.on else None

    def after(self, data=None) -> None:
        if self._start is None:  # the step began before the recording did
            return
        self.spans.append((self._start, common.stamp(self.cuda)))
        self._start = None
        import warp as wp

        for name in self.counts:  # device copies after the end mark: not part of the timed step
            self.counts[name].append(wp.to_torch(getattr(data, name)).clone())

    def summary(self, num_worlds: int) -> dict:
        if self.cuda:
            torch.cuda.synchronize()
        ms = [common.elapsed_ms(a, b, self.cuda) for a, b in self.spans]
        if not ms:
            raise RuntimeError("no simulator step was recorded: the env step was captured, or no iteration was timed")
        times = {"steps": len(ms), "ms_per_policy_step": sum(ms) / len(ms)}
        if not self.counts:
            return times
        niter = torch.stack(self.counts["solver_niter"]).float()  # (steps, num_worlds)
        return {**times,
                "niter_max_over_worlds": niter.max(dim=1).values.mean().item(), "niter_mean": niter.mean().item(),
                "niter_max_seen": niter.max().item(),
                "constraint_rows_per_world": torch.stack(self.counts["nefc"]).float().mean().item(),
                "contacts_per_world": torch.stack(self.counts["nacon"]).float().mean().item() / num_worlds}


@contextlib.contextmanager
def recorded_trainer(recorder: Recorder, warmup: int):
    """The trainer with the simulator's step wrapped by ``recorder`` from the end of iteration ``warmup`` on; all put
    back on exit, also after an error."""
    trainer = common.trainer
    # estimate_advantages: once per iteration, on the trainer's own thread, between a rollout and its update (the
    # update itself may be queued from a thread of its own, ppo.overlap_update, while the next rollout steps).
    saved = {k: getattr(trainer, k) for k in ("make_collector", "estimate_advantages")}
    done = {"iterations": 0}
    undo: list = []
    recorder.on = warmup == 0

    def make_collector(cfg, env, actor, *args, **kwargs):
        sim = env.base_env.sim
        # The counts are mujoco-warp's (``wp_data``); a recorder of times alone also times C MuJoCo's step.
        common.wrap_method(sim, "step", recorder.before,
                           lambda: recorder.after(sim.wp_data if recorder.counts else None), undo)
        return saved["make_collector"](cfg, env, actor, *args, **kwargs)

    def advantages(*args, **kwargs):
        done["iterations"] += 1  # rollout `iterations` has ended: the next one is recorded from `warmup` on
        recorder.on = done["iterations"] >= warmup
        return saved["estimate_advantages"](*args, **kwargs)

    with common.trainer_patched({"make_collector": make_collector, "estimate_advantages": advantages}, undo):
        yield


def measure(n: int, iterations: int, warmup: int, raw_steps: int, device: str, run_dir: str, overrides: dict) -> dict:
    """One env count: the trainer's physics over ``iterations`` after ``warmup``, then the raw ceiling's."""
    overrides = {**overrides, "env.sim.backend": "warp"}  # the counts are mujoco-warp's, on either device
    cfg, at = common.eager_step_config(NAME, n, warmup + iterations, overrides, run_dir, f"solver_load_{n}", device)
    training = Recorder(at)
    with recorded_trainer(training, warmup):
        common.train(cfg)
    raw_step = common.raw_policy_step(n, device)
    for _ in range(common.RAW_WARMUP):  # as the ceiling's own rate is measured: after the robots have settled
        raw_step()
    standing = Recorder(at)
    for _ in range(raw_steps):
        standing.before()
        raw_step()
        standing.after(raw_step.wp_data)
    result = {"num_envs": n, "iterations": iterations, "warmup": warmup, "overrides": overrides,
              "training": training.summary(n), "standing (raw ceiling)": standing.summary(n)}
    result["physics_ratio_standing_over_training"] = (result["standing (raw ceiling)"]["ms_per_policy_step"]
                                                      / result["training"]["ms_per_policy_step"])
    return result


def render(data: dict, out) -> str:
    parts = []
    for r in data["results"]:
        rows = []
        for label in ("training", "standing (raw ceiling)"):
            s = r[label]
            rows.append((label, s["steps"], f"{s['ms_per_policy_step']:.3f}", f"{s['niter_max_over_worlds']:.2f}",
                         f"{s['niter_mean']:.2f}", f"{s['niter_max_seen']:.0f}", f"{s['constraint_rows_per_world']:.1f}",
                         f"{s['contacts_per_world']:.1f}"))
        parts.append(f"### {r['num_envs']:,} envs ({r['iterations']} training iterations after {r['warmup']} warm-up, "
                     f"overrides {r['overrides'] or 'none'})\n\n"
                     + common.table(("workload", "policy steps", "physics ms per policy step",
                                     "solver iterations, slowest world (mean over steps)", "mean over worlds",
                                     "most seen", "constraint rows per world", "contacts per world"), rows)
                     + f"\n\nStanding / training physics time: **{r['physics_ratio_standing_over_training']:.3f}** "
                       "(the highest train / raw ratio this env count allows if everything but the physics cost "
                       "nothing).")
    return common.page("Physics load of training against the raw ceiling", data, "\n\n".join(parts))


def main(argv=None) -> dict:
    return common.trainer_benchmark(argv, NAME, __doc__, measure, render, min_warmup=0, min_raw_steps=1,
                                    device_help="cuda, or cpu: warp's CPU device, host clocks")


if __name__ == "__main__":
    main()
