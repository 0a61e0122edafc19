"""Training throughput (collection + PPO update) against raw mujoco-warp stepping of the same model, same process.

    python -m lab.benchmarks.train_throughput --num_envs 4096 16384 --iterations 10   # --set ppo.cuda_graph=off: ablations
    python -m lab.benchmarks.train_throughput --num_envs 4096 --nproc 1 2 --name multi_gpu   # data-parallel scaling

Each env count in a fresh process: ``--iterations`` PPO iterations of the default preset after ``--warmup``, then the
raw ceiling. ``--nproc K``: K torchrun ranks of ``--num_envs`` worlds each, one per GPU; rank 0 reports all ranks'
rate, its own GPU's memory and one GPU's raw ceiling (``train / raw`` divides by K x raw). See docs/benchmarks.md.

The raw ceiling steps robots that stand still; training steps robots that walk, stumble and fall, whose physics costs
more (mujoco-warp iterates every world until the slowest converges). ``--ceiling`` also times the simulator's step in
place during the timed iterations (CUDA events around ``sim.step``; nothing waits): the physics of the very states
training visits, on the same model in the same run. Its rate, ``num_envs`` over that time, is the ceiling training
could reach were everything but the physics free; ``train / ceiling`` stands beside ``train / raw``. With
``ppo.overlap_update`` only the steps that ran while no update ran beside them count (each update's span is recorded
on its stream), so the ceiling is the physics alone. It needs the eager env step (at 4,096 envs and more the
trainer's default), one rank. It also splits the host's time between two rollouts (:func:`update_host_split`): queuing
the update, waiting for it, and, with the overlap, the update's GPU span on its side stream; within each launch,
the host's time in each mini-batch call, what the CUDA caching allocator did and how many rollout steps the GPU had
still to run; and the device's time between two rollouts against that between two steps (:func:`rollout_gaps`).

    python -m lab.benchmarks.train_throughput --num_envs 4096 16384 --ceiling --name train_over_ceiling
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import json
import os
import shutil
import statistics
import time
from pathlib import Path

import torch

from tocabi_torchrl.cuda_graphs import CudaGraphCapture
from tocabi_torchrl.rl.curves import steady_rate
from tocabi_torchrl.rl.distributed import ending, from_environment, init_distributed

from . import STARTED, common, solver_load

NAME = "train_throughput"


def measure(n: int, iterations: int, warmup: int, raw_steps: int, device: str, run_dir: str,
            overrides: dict, ceiling: bool = False, same_priority: bool = False,
            compile_loss: bool = False, compact_reset: int | None = None,
            update_sms: int | None = None) -> dict | None:
    """One env count in this process (one rank of a torchrun run): the steady rate after ``warmup`` iterations, the
    whole run's numbers, memory peaks, then the raw ceiling (only that with no iterations at all). None on ranks > 0.
    ``ceiling``: also the simulator's own time per policy step over the same timed iterations (module docstring).
    ``same_priority``: with ``ppo.overlap_update``, the rollout's and the update's streams of one priority.
    ``compile_loss``: the PPO loss wrapped in ``torch.compile`` (``ppo.compile_loss``, as ``--set`` would set it).
    ``compact_reset``: the reduced reset pass's small ``Data`` holds this many worlds (0: the pass over every world)
    instead of ``tocabi_torchrl.sim.config.compact_reset_capacity``'s count (None).
    ``update_sms``: with ``ppo.overlap_update``, the update's side stream is a stream of a CUDA green context of this
    many multiprocessors (``torch.cuda.green_contexts``): the update's blocks run on those alone, and the physics'
    blocks never wait for multiprocessors the update holds beyond them (a probe: no config option does it)."""
    info = from_environment()
    device = str(init_distributed(info, torch.device(device)))  # this rank's GPU, before anything touches cuda:0
    record = {"num_envs": n, "gpus": info.world_size, "overrides": overrides, "same_priority": same_priority,
              "compile_loss": compile_loss, "compact_reset": compact_reset,
              "update_sms": update_sms if device.startswith("cuda") else None,  # no green context off CUDA
              "device_used_at_start_gib": common.device_used_gib(device),
              "device_name": common.meta(NAME, None, device)["gpu"]}
    if iterations + warmup:
        cfg = common.run_config(n, warmup + iterations, {**overrides, **compile_override(compile_loss)}, run_dir,
                                f"train_{n}", device.split(":")[0], info.world_size)
        if info.is_main:  # the benchmark's own scratch run: start afresh
            shutil.rmtree(Path(run_dir) / cfg.name, ignore_errors=True)
        physics, overlaps, update_marks = None, [], []
        overlap_class, step_class, patches = common.trainer.UpdateOverlap, common.trainer.MinibatchStep, {}
        green = None
        if update_sms and not cfg.ppo.overlap_update:  # the inline update would run on those SMs alone
            raise ValueError("--update_sms confines the overlapped update: set ppo.overlap_update=true as well")
        if update_sms and device.startswith("cuda"):
            green = torch.cuda.green_contexts.GreenContext.create(num_sms=update_sms,
                                                                  device_id=torch.device(device).index or 0)
            # Never destroyed: tensors the update's streams used are freed as the interpreter ends, and each free
            # records an event on its stream, which fails once the context is gone.
            ctypes.pythonapi.Py_IncRef(ctypes.py_object(green))

            class GreenCapture(CudaGraphCapture):
                """Warm-up and capture on a stream of the green context: a graph captured on another stream
                replays on all multiprocessors, whatever stream it is launched on."""

                def side_stream(self, device):
                    return green.Stream()

            class GreenStep(step_class):
                def __init__(self, *args, **kwargs):
                    super().__init__(*args, **kwargs, capturer=GreenCapture())

            step_class = patches["MinibatchStep"] = GreenStep

        class Overlap(overlap_class):
            """The trainer's :class:`UpdateOverlap`, its two streams of one priority with ``same_priority``, its side
            stream a green context's with ``update_sms``."""

            def __init__(self, *args, **kwargs):
                super().__init__(*args, **kwargs, collect_first=not same_priority)
                if green is not None and self.stream is not None:
                    self.stream = green.Stream()

        patches["UpdateOverlap"] = Overlap
        if ceiling:
            at = common.trainer.resolve_device(device)
            common.refuse_captured_env_step(f"{NAME} --ceiling", cfg, at, n)
            physics = solver_load.Recorder(at, counts=False)

            class RecordedOverlap(Overlap):
                """The trainer's updates (inline or ``ppo.overlap_update``'s), with the spans they ran in on the side
                stream, the host's time in each launch (queuing the update) and each finish (waiting for it), and,
                per launch, the host's time in each mini-batch call, what the CUDA caching allocator did and, once the
                physics is recorded, where the next rollout's steps begin and how far the GPU was behind."""

                def __init__(self, *args, **kwargs):
                    super().__init__(*args, **kwargs)
                    self.spans, self.launch_s, self.queue_s, self.calls, self.allocs = [], [], [], [], []
                    self.finish_s, self.threaded = [], []
                    #: per launch once the physics is recorded: the recorded steps before it (where the next
                    #: rollout's first step will be) and how many of the last 64 the GPU had not finished yet.
                    self.boundaries, self.pending = [], []
                    self.queuing = False
                    # Before any rollout or update: every later event of either stream comes after it.
                    self.origin = (torch.cuda.current_stream(self.device).record_event(
                        torch.cuda.Event(enable_timing=True)) if self.stream is not None else None)
                    overlaps.append(self)

                def launch(self, update, keep, *, threaded=False):
                    if physics.spans:  # is the host ahead of the GPU as it starts to queue the update?
                        self.boundaries.append(len(physics.spans))
                        self.pending.append(steps_pending(physics.spans))
                    self.threaded.append(bool(threaded and self.stream is not None))

                    def queued():  # on the thread that queues the update (this one, or launch's own)
                        self.calls.append([])  # TimedStep fills it while the update's mini-batches are queued
                        before = allocator_counts(self.device)
                        t, self.queuing = time.perf_counter(), True
                        try:
                            return update()
                        finally:
                            self.queuing = False
                            self.queue_s.append(time.perf_counter() - t)
                            after = allocator_counts(self.device)
                            self.allocs.append({k: after[k] - before[k] for k in after})

                    t = time.perf_counter()
                    super().launch(queued, keep, threaded=threaded)
                    self.launch_s.append(time.perf_counter() - t)

                def finish(self):
                    t = time.perf_counter()
                    out = super().finish()
                    self.finish_s.append(time.perf_counter() - t)
                    return out

            class TimedStep(step_class):
                """The trainer's mini-batch step, with the host's time in each call (queuing one mini-batch: with the
                update captured, its replay) kept in the launch it belongs to."""

                def on_rows(self, idx):
                    return self._timed(super().on_rows, idx)

                def __call__(self, mb):
                    return self._timed(super().__call__, mb)

                def _timed(self, call, arg):
                    t = time.perf_counter()
                    out = call(arg)
                    if overlaps and overlaps[0].queuing:  # a call outside an update's queuing is no part of one
                        overlaps[0].calls[-1].append(time.perf_counter() - t)
                    return out

            patches.update(UpdateOverlap=RecordedOverlap, MinibatchStep=TimedStep)
            cuda, update_stats = at.type == "cuda", common.trainer._update_stats

            def timed_update(*args, **kwargs):
                """The update's own time: marks on the stream it is queued on (the side stream's, overlapped)."""
                start = common.stamp(cuda)
                out = update_stats(*args, **kwargs)
                update_marks.append((start, common.stamp(cuda)))
                return out

            if not cfg.ppo.overlap_update:  # beside the rollout the update is no part of the step (below)
                patches["_update_stats"] = timed_update
        undo = []
        if compact_reset is not None:  # the simulator's rule, replaced while the run builds its env
            from tocabi_torchrl.sim import warp_backend

            rule = warp_backend.compact_reset_capacity
            warp_backend.compact_reset_capacity = lambda _num_worlds: compact_reset
            undo.append(lambda: setattr(warp_backend, "compact_reset_capacity", rule))
        # The physics is timed from the end of iteration max(warmup, 1) on: the iterations of the steady rate.
        with (solver_load.recorded_trainer(physics, max(warmup, 1)) if physics else contextlib.nullcontext(),
              common.trainer_patched(patches, undo)):
            # train() builds the env, agent and collector, then starts its clock (result.wall_seconds): the CPU time
            # is read there, so that the cores busy are those of the timed training, not of the set-up before it.
            at_clock, make_collector = {}, common.trainer.make_collector

            def collector_then_clock(*args, **kwargs):
                collector = make_collector(*args, **kwargs)
                at_clock["cpu"] = os.times()
                return collector

            with (common.trainer_patched({"make_collector": collector_then_clock}, []),
                  common.memory_peaks(device) as peaks):
                result, rows = common.train(cfg)
                cpu1, t_end = os.times(), time.perf_counter()
        if not info.is_main:  # rank 0 logged the rows and reports for every rank
            return None
        cpu0, wall = at_clock["cpu"], result.wall_seconds
        record.update(peaks, train_env_steps_per_s=steady_rate(rows, max(warmup - 1, 0)), env_steps=result.env_steps,
                      update_s_last=float(rows[-1]["update_s"]), iterations=result.iterations, train_wall_s=wall,
                      setup_s=t_end - STARTED - wall, env_graph=result.env_graph,  # all but the timed training
                      status="ok" if result.env_steps >= cfg.total_env_steps else "partial",
                      cores_used_mean=(cpu1.user + cpu1.system - cpu0.user - cpu0.system) / wall)
        if physics:
            ms, alone = uncontended_ms(physics, [span for o in overlaps for span in o.spans],
                                       overlaps[0].origin if overlaps else None)
            rate, top = record["train_env_steps_per_s"], n * 1e3 / ms
            # The update's GPU time, now that the host no longer waits for it between rollouts (beside the rollout,
            # with the overlap, it is no part of the step: the host's wait for it stays the measure there).
            if update_marks:
                if at.type == "cuda":
                    torch.cuda.synchronize(at)
                record["update_ms_last"] = common.elapsed_ms(*update_marks[-1], at.type == "cuda")
            record.update(physics_ms_per_policy_step=ms, physics_steps_timed=alone,
                          physics_steps_recorded=len(physics.spans), ceiling_env_steps_per_s=top,
                          ratio_train_over_ceiling=rate / top if rate else None, **update_host_split(overlaps),
                          **rollout_gaps(physics, overlaps[0].boundaries if overlaps else []))
    raw = common.raw_policy_steps_per_second(n, raw_steps, device) if raw_steps else None
    rate = record.get("train_env_steps_per_s")
    return {**record, "raw_policy_steps_per_s": raw,
            "ratio_train_over_raw": rate / (info.world_size * raw) if raw and rate else None}


def compile_override(compile_loss: bool) -> dict[str, bool]:
    """The ``--set`` entry of the ``--compile_loss`` flag: ``ppo.compile_loss`` on (:func:`make_update_step` compiles
    the loss; the first mini-batch steps, eager before the capture, compile it), or nothing."""
    return {"ppo.compile_loss": True} if compile_loss else {}


def update_host_split(overlaps: list) -> dict[str, float]:
    """Where the host's time between two rollouts goes, as medians over the run's updates but the first (it captures
    the update's graph) and the last (the run's end reads it at once, with no rollout between): ``update_launch_ms``
    in the trainer's call that launches an update (with the overlap, on its side stream), ``update_queue_ms`` queuing
    it (the same time, unless ``update_launch_threaded``, 1 when the trainer queued it from a thread of its own while
    it went on with the next rollout), ``update_finish_ms`` waiting for it once the next
    rollout is collected (inline: the read of its numbers) and, with the overlap, ``update_span_ms``: its GPU time from
    its start to its end on the side stream, time it waited beside the rollout included (the events have completed:
    :func:`uncontended_ms` synchronised). Within each launch: ``update_calls`` mini-batch calls, the slowest one's
    host time ``update_call_max_ms`` and ``update_calls_over_1ms`` (with the update captured a call only copies its
    indices and launches a replay, microseconds), on CUDA ``update_launch_<counter>``: what the caching allocator
    did while the host queued it (:data:`ALLOCATOR_COUNTS`; from a thread, also what the rollout's own thread did
    meanwhile), and ``update_launch_steps_pending``: the rollout's
    simulator steps the GPU had still to run as the host began (:func:`steps_pending`; 0 off CUDA; launches before
    the physics is recorded are not counted). Empty without updates."""
    if not overlaps:
        return {}
    o = overlaps[0]

    def median_ms(seconds: list[float]) -> float | None:
        median = _median_middle(seconds)
        return None if median is None else 1e3 * median

    out = {"update_launch_ms": median_ms(o.launch_s), "update_queue_ms": median_ms(getattr(o, "queue_s", [])),
           "update_launch_threaded": _median_middle([float(t) for t in getattr(o, "threaded", [])]),
           "update_finish_ms": median_ms(o.finish_s),
           "update_span_ms": median_ms([a.elapsed_time(b) / 1e3 for a, b in o.spans])}
    calls = getattr(o, "calls", [])
    if any(calls):
        # Within a launch: is the host held by every mini-batch call alike, or by a few (a blocking allocation)?
        out.update(update_call_max_ms=median_ms([max(c, default=0.0) for c in calls]),
                   update_calls_over_1ms=_median_middle([sum(t > 1e-3 for t in c) for c in calls]),
                   update_calls=_median_middle([len(c) for c in calls]))
    for key in sorted({k for a in getattr(o, "allocs", []) for k in a}):
        out[f"update_launch_{key}"] = _median_middle([a.get(key, 0) for a in o.allocs])
    out["update_launch_steps_pending"] = _median_middle(getattr(o, "pending", []))
    return {k: v for k, v in out.items() if v is not None}


def steps_pending(spans: list[tuple], last: int = 64) -> int:
    """How many of the ``last`` recorded simulator steps (``(start, end)`` marks of :func:`common.stamp`) the GPU has
    not finished yet: how far ahead of the GPU the host is. Asks each end event without waiting for it; 0 off CUDA
    (the host's clock marks a step once it has run)."""
    return sum(1 for _, end in spans[-last:] if hasattr(end, "query") and not end.query())


def rollout_gaps(physics: solver_load.Recorder, boundaries: list[int]) -> dict[str, float]:
    """The device's time between two rollouts against its time between two steps of one, medians in ms:
    ``rollout_gap_ms`` from the end of a rollout's last simulator step to the start of the next rollout's first
    (``boundaries``: the index of each rollout's first recorded step), ``step_gap_ms`` between the steps within a
    rollout (the policy, rewards, observations and resets). Had the GPU waited for the host while it queued the update,
    the first would hold that wait; otherwise only the work queued between two rollouts on their stream (and, with the
    update inline, the update). The marks must have completed (:func:`uncontended_ms` synchronised)."""
    spans = physics.spans
    cuts = {b for b in boundaries if 0 < b < len(spans)}

    def gap(i: int) -> float:
        return common.elapsed_ms(spans[i - 1][1], spans[i][0], physics.cuda)

    out = {"rollout_gap_ms": [gap(i) for i in sorted(cuts)],
           "step_gap_ms": [gap(i) for i in range(1, len(spans)) if i not in cuts]}
    return {k: float(statistics.median(v)) for k, v in out.items() if v}


def _median_middle(values: list) -> float | None:
    """The median of ``values`` without the first and the last (both kept when there are two or fewer)."""
    middle = values[1:-1] if len(values) > 2 else values
    return float(statistics.median(middle)) if middle else None


#: The CUDA caching allocator's counters a launch is checked against (``torch.cuda.memory_stats``): cudaMalloc and
#: cudaFree calls, retries after a failed allocation (the cache freed first) and synchronisations of every stream,
#: each of which can hold the host while the GPU works.
ALLOCATOR_COUNTS = ("num_device_alloc", "num_device_free", "num_alloc_retries", "num_sync_all_streams")


def allocator_counts(device: torch.device) -> dict[str, int]:
    """The allocator counters :data:`ALLOCATOR_COUNTS` now; empty off CUDA."""
    if device.type != "cuda":
        return {}
    stats = torch.cuda.memory_stats(device)
    return {k: int(stats.get(k, 0)) for k in ALLOCATOR_COUNTS}


def uncontended_ms(physics: solver_load.Recorder, updates: list[tuple], origin=None) -> tuple[float, int]:
    """The mean time [ms] of the recorded simulator steps that ran while no update ran beside them (the updates'
    (start, done) CUDA events on their side stream, ``ppo.overlap_update``), and how many such steps there were.
    Without updates beside the rollout every step counts. Events of the two streams are put on one clock by their
    elapsed time from ``origin``, an event recorded before any of them."""
    physics.summary(1)  # synchronises and refuses an empty record
    if not updates:
        spans = [common.elapsed_ms(a, b, physics.cuda) for a, b in physics.spans]
        return sum(spans) / len(spans), len(spans)
    t = origin.elapsed_time
    busy = [(t(a), t(b)) for a, b in updates]
    alone = [t(b) - t(a) for a, b in physics.spans
             if not any(t(a) < end and start < t(b) for start, end in busy)]
    if not alone:
        raise RuntimeError("every timed simulator step ran beside an update: time more iterations")
    return sum(alone) / len(alone), len(alone)


def _speedup(r: dict, results: list[dict]) -> str:
    """``r``'s rate over the 1-GPU row of the same env count and overrides in the same run ("-" without one)."""
    one = [o for o in results if o.get("gpus", 1) == 1 and o["num_envs"] == r["num_envs"]
           and o["overrides"] == r["overrides"] and o.get("train_env_steps_per_s")]
    rate = r.get("train_env_steps_per_s")
    return common.fmt(rate / one[0]["train_env_steps_per_s"] if one and rate else None, ".2f")


def render(data: dict, out) -> str:
    """The page; a raw-only row (``--iterations 0 --warmup 0``) has no training columns: "-" there."""
    results = data["results"]
    # The GPU columns only where a run had several ranks (the 1-GPU pages keep their layout).
    multi = any(r.get("gpus", 1) > 1 for r in results)
    gpus = lambda r: (r.get("gpus", 1), _speedup(r, results)) if multi else ()
    # The training-state ceiling's columns only where a run measured it (--ceiling).
    top = any("ratio_train_over_ceiling" in r for r in results)
    ceiling = lambda r: (common.fmt(r.get("physics_ms_per_policy_step"), ".2f"),
                         common.fmt(r.get("ceiling_env_steps_per_s")),
                         common.fmt(r.get("ratio_train_over_ceiling"), ".3f")) if top else ()
    return common.page("Training throughput", data, common.table(
        (*(("GPUs", "speed-up over 1 GPU") if multi else ()), "envs" + (" per GPU" if multi else ""),
         "train env-steps/s", "raw mujoco-warp policy steps/s" + (" (one GPU)" if multi else ""),
         "train / raw" + (" (GPUs x raw)" if multi else ""),
         *(("physics ms per policy step in training", "ceiling of training states, env-steps/s", "train / ceiling")
           if top else ()),
         "torch peak alloc GiB", "torch peak reserved GiB", "device peak used GiB"),
        [(*gpus(r), r["num_envs"], common.fmt(r.get("train_env_steps_per_s")),
          common.fmt(r["raw_policy_steps_per_s"]), common.fmt(r["ratio_train_over_raw"], ".2f"), *ceiling(r),
          *(common.fmt(r.get(k), ".2f") for k in ("torch_peak_allocated_gib", "torch_peak_reserved_gib",
                                                   "device_peak_used_gib")))
         for r in results]))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--num_envs", type=int, nargs="+", default=[4096, 16384],
                        help="robot counts (per rank), each measured in a fresh process (default: 4096 16384)")
    parser.add_argument("--iterations", type=int, default=10,
                        help="timed PPO iterations per measurement (the steady rate is taken over them)")
    parser.add_argument("--warmup", type=int, default=3, help="untimed PPO iterations before the timed ones")
    parser.add_argument("--raw_steps", type=int, default=200, help="raw mujoco-warp steps timed (0: skip)")
    parser.add_argument("--set", nargs="*", default=[], metavar="PATH=VALUE",
                        help="config overrides (ablations): dotted paths, e.g. ppo.cuda_graph=off; preset=NAME "
                             "measures that training preset (default: default)")
    parser.add_argument("--device", default="cuda", help="cuda, or cpu for a smoke run of the script")
    parser.add_argument("--run_dir", default="/tmp/tocabi_bench_runs", help="scratch folder of the training runs")
    parser.add_argument("--out", default=str(common.DOCS), help="folder of the report <name>.json and .md (default: "
                        "docs/benchmarks; a CPU measurement goes to runs/benchmarks_cpu instead)")
    parser.add_argument("--name", default=NAME, help=f"the report's file name, <out>/<name>.json (default: {NAME})")
    parser.add_argument("--nproc", type=int, nargs="+", default=[1],
                        help="data-parallel ranks (GPUs) per measurement; each K > 1 runs under torchrun")
    parser.add_argument("--ceiling", action="store_true",
                        help="also time the simulator's step in place during the timed iterations: the physics of "
                             "the states training visits, and train / that ceiling (eager env step, one rank)")
    parser.add_argument("--same_priority", action="store_true",
                        help="with ppo.overlap_update: the rollout's and the update's CUDA streams of one priority "
                             "(the trainer gives the rollout's the higher one)")
    parser.add_argument("--compile_loss", action="store_true",
                        help="the PPO loss wrapped in torch.compile (a probe of the update's kernels; no config "
                             "option does it)")
    parser.add_argument("--compact_reset", type=int, default=None,
                        help="worlds the reduced reset pass's small Data holds (0: the pass over every world); "
                             "default: the simulator's rule, tocabi_torchrl.sim.config.compact_reset_capacity")
    parser.add_argument("--update_sms", type=int, default=None,
                        help="with ppo.overlap_update: run the update on a CUDA green context of this many "
                             "multiprocessors (a probe; default: the update's stream may use all of them)")
    parser.add_argument("--child", action="store_true", help="measure one env count in this process (internal)")
    args = parser.parse_args(argv)
    if min(args.num_envs) < 1:
        parser.error(f"--num_envs takes env counts >= 1, not {args.num_envs}")
    common.require_cuda(parser, args.device, "pass --device cpu for a smoke run of the script")
    overrides = common.parse_overrides(args.set)
    if args.child:
        with ending(from_environment()):  # every rank ends, also on a failure (NCCL: the process, here)
            record = measure(args.num_envs[0], args.iterations, args.warmup, args.raw_steps, args.device,
                             args.run_dir, overrides, args.ceiling, args.same_priority, args.compile_loss,
                             args.compact_reset, args.update_sms)
            if record is not None:  # rank 0 of a torchrun run reports for all ranks
                print("RESULT " + json.dumps(record), flush=True)  # what common.run_child reads
        return
    options = ["--iterations", str(args.iterations), "--warmup", str(args.warmup), "--raw_steps", str(args.raw_steps),
               "--device", args.device, "--run_dir", f"{args.run_dir}/{args.name}", "--set", *args.set]
    if min(args.nproc) < 1:
        parser.error(f"--nproc takes rank counts >= 1, not {args.nproc}")
    if args.ceiling and (max(args.nproc) > 1 or not args.iterations):
        parser.error("--ceiling times the physics of one rank's timed training iterations: use --nproc 1 and "
                     "--iterations >= 1")
    options += (["--ceiling"] if args.ceiling else []) + (["--same_priority"] if args.same_priority else [])
    if args.compile_loss and not args.iterations + args.warmup:
        parser.error("--compile_loss compiles the loss of training iterations: give --iterations or --warmup > 0")
    options += ["--compile_loss"] if args.compile_loss else []
    if args.compact_reset is not None and not 0 <= args.compact_reset < min(args.num_envs):
        parser.error(f"--compact_reset takes a world count in [0, the smallest --num_envs), not {args.compact_reset}")
    options += ["--compact_reset", str(args.compact_reset)] if args.compact_reset is not None else []
    if args.update_sms is not None and args.update_sms < 1:
        parser.error(f"--update_sms takes a multiprocessor count >= 1, not {args.update_sms}")
    options += ["--update_sms", str(args.update_sms)] if args.update_sms is not None else []
    if max(args.nproc) > 1 and not args.iterations + args.warmup:
        parser.error("--nproc > 1 measures training: give --iterations or --warmup > 0")
    # Where any K > 1, every child starts under torchrun, the 1-rank one too, so that they share its
    # settings (it sets OMP_NUM_THREADS=1, for one).
    results = [common.run_child(NAME, ["--num_envs", str(n), *options], nproc=k if max(args.nproc) > 1 else None)
               for k in args.nproc for n in args.num_envs]
    print(common.publish(args.out, args.name, {"meta": common.meta(NAME, argv, args.device), "results": results},
                         render, measured_on=args.device))


if __name__ == "__main__":
    main()
