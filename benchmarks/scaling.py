"""Efficiency and scalability of PPO training (issue 9: TocabiLab's chapter 5 on our system).

Measures, with the same PPO recipe (``preset_config("default")`` trained by ``tocabi_torchrl.rl.trainer.train``):

* ``cpu_time``: training time for 983,040 env-steps on the classic-MuJoCo CPU backend (``device="cpu"``, every core),
  at 8, 32 and 96 envs;
* ``gpu_time``: the same on mujoco-warp (``device="cuda"``) at 8, 32, 96, 1,024, 4,096, 16,384 and 65,536 envs;
* ``memory``: short runs (3 PPO iterations) at 8, 16, 32, ... envs until one does not fit on the GPU, then bisection
  between the largest count that fit and the smallest that did not until the two are 8,192 envs apart: peak host RSS,
  GPU memory (torch allocator peak and the device-wide use), CPU utilisation;
* ``raw``: the raw mujoco-warp ceiling of the same model (``sim_throughput.raw_policy_steps_per_second``);
* ``report``: ``docs/benchmarks/scaling.{json,md}`` and four PNG figures (``benchmarks/scaling_report.py``).

Every measurement runs in a fresh process (``--one``; peak RSS is monotonic in a process) and writes one JSON file
into the results folder (default ``docs/benchmarks/scaling/``). The suite is resumable: a measurement whose JSON
exists is skipped (``--redo partial error`` repeats those statuses). A command stops launching measurements when its
``--budget_minutes`` (default 9) runs low, a training run stops itself at its deadline through ``PPOConfig.max_minutes``
(status ``partial``: the rate is measured, the time for 983,040 steps extrapolated, and a checkpoint is saved), so
every command ends inside the GPU machine's 10-minute limit; rerun the same command to continue. A partial time run
trains on from its checkpoint (``<run_dir>/<name>/checkpoints/latest.pt``; ``--no_continue`` skips it instead,
``--redo partial`` starts it over): the result then adds the segments up (steps, TocabiLab's training time, set-up)
and lists each one under ``segments``. The run folder lives in ``--run_dir`` (default under /tmp, which survives
between calls on a warm GPU machine); without its checkpoint a partial run is skipped with a note.

On the GPU machine (1x H100, 16 cores), from the repository root, after the device set-up of
``../shared/device/README.md`` (``export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1``), one command per call, in
this order, each with ``--bundle $OUT/scaling_bundle.json`` appended (estimated minutes; the first GPU chunk on a
fresh machine adds ~3-4 min of warp kernel compilation unless the warp cache is restored; in a call that also runs
the device install, add ``--budget_minutes 7``):

    python3 benchmarks/scaling.py --part raw                                         # ~2-3
    python3 benchmarks/scaling.py --part gpu_time --num_envs 1024 4096 16384 65536   # ~3-4
    python3 benchmarks/scaling.py --part gpu_time --num_envs 96 32                   # ~9, twice (32 continues)
    python3 benchmarks/scaling.py --part gpu_time --num_envs 8                       # ~9, three times
    python3 benchmarks/scaling.py --part memory                                      # ~9, two or three times
    python3 benchmarks/scaling.py --part cpu_time --num_envs 96 32                   # ~9, three times
    python3 benchmarks/scaling.py --part cpu_time --num_envs 8                       # ~9, four times

(On an H100, 983,040 steps take ~6 and ~26 min of training at 32 and 8 GPU envs, ~12 and ~28 min at 32 and 8 CPU
envs: each rerun of the chunk trains them on from their checkpoints on the same warm machine; a partial run's rate
is measured over the minutes it ran, and ``--max_minutes`` shortens a segment where device time is short.)

``--bundle`` rewrites one JSON file holding every result after each measurement (the device tool returns at most
8 files from $OUT). Back here, unpack it into the results folder (so that the next call's working tree carries it
and the next chunk skips what is done), then render the report (CPU is enough; needs matplotlib for the figures):

    python benchmarks/scaling.py --part unpack --bundle PATH/TO/scaling_bundle.json
    python benchmarks/scaling.py --part report

``python3 benchmarks/scaling.py --part all`` runs raw, gpu_time, memory, cpu_time in that order within one budget;
repeating it until it prints "nothing left to measure" also covers the suite.

PPO sizing per env count N (the recipe is the current default preset, see ``recipe``): the preset's 48 steps per env,
but never a rollout under 2,048 transitions, so that 8 and 32 envs still get mini-batches worth an update
(8 envs x 256, 32 x 64), and ``minibatch_size = min(preset's 49,152, frames_per_batch // 4)``. The trainer rounds
iterations up (``ceil(983,040 / frames_per_batch)``), so most env counts do a few more steps: the JSON has the steps
done. Each JSON stores the recipe it was trained with; a result of another recipe is stale: the driver measures it
again (``--keep_stale`` to keep it) and the report leaves it out.
"""

from __future__ import annotations

import time

_T0 = time.perf_counter()  # "total wall time including set-up" counts from here (before torch is imported)

import argparse
import itertools
import json
import math
import os
import platform
import resource
import shutil
import socket
import subprocess
import sys
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(ROOT))

from report import rss_bytes  # noqa: E402  (benchmarks/, put on the path above)

TARGET_ENV_STEPS = 983_040  # TocabiLab's training budget: 4,096 envs x 24 steps x 10 iterations
MIN_ROLLOUT = 2048
#: PPOConfig fields that are bookkeeping or sized per env count, not the training recipe (see ``recipe``).
NOT_RECIPE = ("preset", "name", "run_dir", "seed", "device", "num_envs", "steps_per_env", "minibatch_size",
              "total_env_steps", "max_minutes", "log_every", "checkpoint_every", "loggers", "resume", "eval_at_end",
              "eval_envs", "eval_seconds", "progress_bar",
              # How the update and the env step are launched (CUDA graphs or eagerly), not what they compute; each
              # result records its env-step mode instead (``env_graph_planned``, see ``is_stale``).
              "update_graph", "cuda_graph")
DEFAULT_RESULTS = ROOT / "docs" / "benchmarks" / "scaling"
DEFAULT_RUN_DIR = "/tmp/tocabi_scaling_runs"
DEFAULT_LOG_DIR = "/tmp/tocabi_scaling_logs"
GIB = 2**30

#: part -> (kind, backend, default env counts). ``memory`` goes up until one does not fit.
#: Time runs go from the quickest to the slowest, so a command that runs out of budget has done the most it could.
PARTS: dict[str, tuple[str, str, tuple[int, ...]]] = {
    "raw": ("raw", "gpu", (8, 32, 96, 1024, 4096, 16384, 65536)),
    "gpu_time": ("time", "gpu", (4096, 16384, 65536, 1024, 96, 32, 8)),
    "memory": ("memory", "gpu", tuple(2**k for k in range(3, 17)) + (98304, 131072, 262144)),
    "cpu_time": ("time", "cpu", (96, 32, 8)),
}
ALL_ORDER = ("raw", "gpu_time", "memory", "cpu_time")
#: The chunks of the docstring, in order (each < 10 min on the GPU machine); the report lists them.
CHUNKS = (
    "python3 benchmarks/scaling.py --part raw",
    "python3 benchmarks/scaling.py --part gpu_time --num_envs 1024 4096 16384 65536",
    "python3 benchmarks/scaling.py --part gpu_time --num_envs 96 32",
    "python3 benchmarks/scaling.py --part gpu_time --num_envs 8",
    "python3 benchmarks/scaling.py --part memory",
    "python3 benchmarks/scaling.py --part cpu_time --num_envs 96 32",
    "python3 benchmarks/scaling.py --part cpu_time --num_envs 8",
)
#: Seconds a command must have left to start a measurement of this kind (the first one of a command always starts).
# The largest memory runs need ~100 s (90,112 envs: 95.5 s on the H100): a second or later one launched with less
# would be cut short and prove nothing about fitting, so it waits for the next command.
MIN_LAUNCH_S = {"time": 240.0, "memory": 120.0, "raw": 45.0}
#: Statuses a result can have; ``ok`` and ``partial`` carry a rate.
STATUSES = ("ok", "partial", "oom", "error", "timeout")
FAILED = ("oom", "error", "timeout")  # statuses of a run that did not train
#: Lower-case fragments of the messages torch, CUDA and warp give when device memory runs out.
OOM_MARKERS = ("out of memory", "outofmemory", "cuda_error_out_of_memory", "cudaerrormemoryallocation",
               "failed to allocate")
#: The memory sweep bisects between the largest env count that fits and the smallest that does not, down to this.
REFINE_STEP = 8192
STOP_MARGIN_S = 30.0  # a training run stops this long before its deadline, to save, clean up and write its JSON
KILL_GRACE_S = 60.0  # past its deadline a measurement process is killed after this long


# --------------------------------------------------------------------------------------------- what one run is


def _default_preset():
    from tocabi_torchrl.rl.config import preset_config

    return preset_config("default")


def ppo_sizing(num_envs: int, min_rollout: int = MIN_ROLLOUT) -> tuple[int, int]:
    """(steps_per_env, minibatch_size) for ``num_envs``: the default preset's steps per env, but a rollout of at
    least ``min_rollout`` transitions, and mini-batches of a quarter of the rollout capped at the preset's size."""
    base = _default_preset()
    steps = max(base.steps_per_env, math.ceil(min_rollout / num_envs))
    return steps, max(1, min(base.minibatch_size, num_envs * steps // 4))


def recipe(cfg=None) -> dict:
    """The training recipe of ``cfg`` (default: the current default preset): every PPOConfig field except the
    bookkeeping and per-env-count sizing in ``NOT_RECIPE``, JSON-ready. A result measured with another recipe is
    stale: the driver measures it again and the report leaves it out."""
    cfg = cfg if cfg is not None else _default_preset()
    return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(cfg).items() if k not in NOT_RECIPE}


def spec_recipe(spec: RunSpec) -> dict | None:
    """The recipe ``spec`` trains with; None for the raw ceiling and for tiny test networks (never the current one).

    Every result of a training spec carries it, failures included, so that "98,304 envs ran out of memory" is
    known to be about the current recipe.
    """
    if spec.kind == "raw" or spec.hidden:
        return None
    return recipe(spec.ppo_config())


def shows_fit(record: dict) -> bool:
    """Whether a time or memory result proves that its env count trains: it finished (``ok``), or its deadline
    stopped it (``partial``) after at least the iterations a memory run does. A memory run stopped earlier proves
    nothing: out-of-memory can strike late (98,304 envs failed well into training)."""
    if record.get("status") == "ok":
        return True
    return record.get("status") == "partial" and (record.get("iterations") or 0) >= record.get("memory_iterations", 3)


def _recipe_part(stored: dict | None) -> dict | None:
    """A stored recipe without the fields that are not recipe now (older results recorded some of them)."""
    return {k: v for k, v in stored.items() if k not in NOT_RECIPE} if isinstance(stored, dict) else stored


def planned_env_graph(spec: RunSpec) -> bool:
    """Whether the default preset captures the env step of ``spec``'s training (``PPOConfig.cuda_graph``)."""
    import torch

    from tocabi_torchrl.rl.config import uses_env_graph

    return uses_env_graph(spec.ppo_config(), torch.device(spec.device), spec.num_envs)


def stored_env_graph(record: dict) -> bool:
    """The env-step mode a result was measured with: its own record, or for results from before that was recorded,
    the ``cuda_graph`` flag of their stored recipe (False then)."""
    if record.get("backend") != "gpu":
        return False  # the CPU backend never captures its step
    if "env_graph_planned" in record:
        return bool(record["env_graph_planned"])
    return str((record.get("recipe") or {}).get("cuda_graph")).lower() in ("true", "on")


def is_stale(record: dict, current: dict | None = None) -> bool:
    """Whether a time or memory result was trained with another recipe than ``current`` (raw results never are),
    or with another env-step mode (CUDA graph or eager) than the default now picks for its backend and env count:
    its speed would not describe what users run."""
    if record.get("kind") == "raw":
        return False
    current = current if current is not None else recipe()
    if _recipe_part(record.get("recipe")) != current:
        return True
    if record.get("backend") not in ("cpu", "gpu") or not record.get("num_envs"):
        return False  # every measured record names both; without them there is no mode to compare
    try:
        spec = RunSpec("time", record["backend"], int(record["num_envs"]))
    except (TypeError, ValueError):
        return True  # a malformed env count describes nothing the suite would measure now
    return stored_env_graph(record) != planned_env_graph(spec)


@dataclass
class RunSpec:
    """One measurement: ``kind`` (time | memory | raw) of ``backend`` (cpu | gpu) at ``num_envs``."""

    kind: str
    backend: str
    num_envs: int
    total_env_steps: int = TARGET_ENV_STEPS  # kind "time"
    memory_iterations: int = 3  # kind "memory": PPO iterations of a short run
    hidden: tuple[int, ...] = ()  # () = the preset's networks; tests pass tiny ones
    min_rollout: int = MIN_ROLLOUT
    raw_steps: int = 200  # kind "raw": policy steps timed
    max_minutes: float = 9.0  # cap on a training run's own clock (the deadline may stop it earlier)
    run_dir: str = DEFAULT_RUN_DIR

    def __post_init__(self) -> None:
        if self.kind not in ("time", "memory", "raw"):
            raise ValueError(f"unknown kind {self.kind!r}")
        if self.backend not in ("cpu", "gpu"):
            raise ValueError(f"unknown backend {self.backend!r}")
        if self.kind == "raw" and self.backend != "gpu":
            raise ValueError("the raw ceiling is mujoco-warp on the GPU")
        if self.num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {self.num_envs}")

    @property
    def name(self) -> str:
        """File stem of the result: sorts by kind, backend, then env count."""
        return f"{self.kind}_{self.backend}_{self.num_envs:07d}"

    @property
    def device(self) -> str:
        return "cuda" if self.backend == "gpu" else "cpu"

    def planned_env_steps(self) -> int:
        steps, _ = ppo_sizing(self.num_envs, self.min_rollout)
        if self.kind == "memory":
            return self.memory_iterations * self.num_envs * steps
        return self.total_env_steps

    def ppo_config(self, **overrides):
        """The default preset, sized for this env count, with benchmark-friendly logging and no evaluation."""
        from tocabi_torchrl.rl.config import preset_config

        steps, minibatch = ppo_sizing(self.num_envs, self.min_rollout)
        frames = self.num_envs * steps
        iterations = max(1, -(-self.planned_env_steps() // frames))
        extra = {"actor_hidden": self.hidden, "critic_hidden": self.hidden} if self.hidden else {}
        return preset_config(
            "default", num_envs=self.num_envs, steps_per_env=steps, minibatch_size=minibatch,
            total_env_steps=self.planned_env_steps(), device=self.device, run_dir=self.run_dir, name=self.name,
            eval_at_end=False, progress_bar=False, checkpoint_every=10**9, log_every=max(1, iterations // 10),
            max_minutes=self.max_minutes, **extra, **overrides,
        )

    def to_argv(self) -> list[str]:
        """Options of ``--one`` that rebuild this spec in the measurement process."""
        argv = ["--kind", self.kind, "--backend", self.backend, "--num_envs", str(self.num_envs),
                "--total_env_steps", str(self.total_env_steps), "--memory_iterations", str(self.memory_iterations),
                "--min_rollout", str(self.min_rollout), "--raw_steps", str(self.raw_steps),
                "--max_minutes", str(self.max_minutes), "--run_dir", self.run_dir]
        if self.hidden:
            argv += ["--hidden", ",".join(map(str, self.hidden))]
        return argv


# ----------------------------------------------------------------------------------------- host-side sampling


def _system_cpu_ticks() -> tuple[int, int]:
    """(busy, total) clock ticks of all CPUs since boot, from the first line of /proc/stat."""
    try:
        fields = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    except (OSError, ValueError):
        return 0, 0
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)  # idle + iowait
    return sum(fields[:8]) - idle, sum(fields[:8])


def _process_cpu_s() -> float:
    """User + system CPU seconds of this process, all threads (C MuJoCo's pool and torch's included)."""
    t = os.times()
    return t.user + t.system


def peak_rss_bytes() -> int:
    """Peak resident set of this process (``ru_maxrss`` is KiB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


class NvidiaSmi:
    """Device-wide memory in use [MiB] and utilisation [%] of one GPU through ``nvidia-smi`` (None without it).

    An external process rather than ``cudaMemGetInfo`` from the sampling thread: it cannot disturb the training
    process's CUDA streams or graph captures.
    """

    def __init__(self, index: int = 0):
        self.exe = shutil.which("nvidia-smi")
        self.index = index

    def query(self) -> tuple[float, float] | None:
        if self.exe is None:
            return None
        try:
            out = subprocess.run([self.exe, "--query-gpu=memory.used,utilization.gpu", "--format=csv,noheader,nounits",
                                  "-i", str(self.index)], capture_output=True, text=True, timeout=5, check=False).stdout
            used, util = (float(x) for x in out.strip().splitlines()[0].split(","))
            return used, util
        except (OSError, ValueError, IndexError, subprocess.SubprocessError):
            return None


def _visible_gpu_index() -> int:
    """nvidia-smi's index of torch's cuda:0 (the first entry of CUDA_VISIBLE_DEVICES when it is a number)."""
    first = os.environ.get("CUDA_VISIBLE_DEVICES", "0").split(",")[0].strip()
    return int(first) if first.isdigit() else 0


class Sampler(threading.Thread):
    """Samples RSS, process CPU time, system CPU ticks (and the GPU through nvidia-smi) every ``interval`` s."""

    def __init__(self, interval: float = 0.5, gpu: NvidiaSmi | None = None, gpu_every: int = 2):
        super().__init__(daemon=True)
        self.interval, self.gpu, self.gpu_every = interval, gpu, gpu_every
        self.samples: list[dict] = []
        self._stop_event = threading.Event()
        self._lock = threading.Lock()

    def sample_now(self, with_gpu: bool = False) -> None:
        busy, total = _system_cpu_ticks()
        row = {"t": time.perf_counter(), "rss": rss_bytes(), "cpu_s": _process_cpu_s(), "sys_busy": busy,
               "sys_total": total}
        if with_gpu and self.gpu is not None:
            q = self.gpu.query()
            if q is not None:
                row["gpu_used_mib"], row["gpu_util"] = q
        with self._lock:
            self.samples.append(row)

    def run(self) -> None:
        k = 0
        while not self._stop_event.is_set():
            self.sample_now(with_gpu=k % self.gpu_every == 0)
            k += 1
            self._stop_event.wait(self.interval)

    def stop(self) -> None:
        self._stop_event.set()
        if self.is_alive():
            self.join(timeout=10)
        self.sample_now(with_gpu=True)

    def summary(self, t_start: float | None = None, t_end: float | None = None) -> dict:
        """CPU use over [t_start, t_end] (whole run where None) and peaks over the whole run."""
        with self._lock:
            rows = list(self.samples)
        if not rows:
            return {}
        # The window starts at the last sample taken before t_start, so short runs still get two samples.
        before = [i for i, r in enumerate(rows) if t_start is not None and r["t"] <= t_start]
        window = [r for r in rows[before[-1] if before else 0:] if t_end is None or r["t"] <= t_end]
        if len(window) < 2:
            window = rows
        first, last = window[0], window[-1]
        dt = max(last["t"] - first["t"], 1e-9)
        cores = [(b["cpu_s"] - a["cpu_s"]) / max(b["t"] - a["t"], 1e-9) for a, b in itertools.pairwise(window)]
        ticks = max(last["sys_total"] - first["sys_total"], 1)
        ncpu = os.cpu_count() or 1
        gpu_used = [r["gpu_used_mib"] for r in rows if "gpu_used_mib" in r]
        gpu_util = [r["gpu_util"] for r in window if "gpu_util" in r]
        return {
            "samples": len(rows),
            "window_s": dt,
            "cores_used_mean": (last["cpu_s"] - first["cpu_s"]) / dt,
            "cores_used_max": max(cores) if cores else None,
            # /proc/stat counts every process on the machine: the system's busy cores over the same window
            "system_busy_cores_mean": ncpu * (last["sys_busy"] - first["sys_busy"]) / ticks,
            "rss_peak_sampled_gib": max(r["rss"] for r in rows) / GIB,
            "rss_end_gib": rows[-1]["rss"] / GIB,
            "gpu_used_peak_gib": max(gpu_used) / 1024 if gpu_used else None,
            "gpu_util_mean": sum(gpu_util) / len(gpu_util) if gpu_util else None,
        }


# ------------------------------------------------------------------------------------------ metadata


def _version(dist: str, module: str | None = None) -> str | None:
    """Installed version of a distribution (or the module's ``__version__``), None when it is absent."""
    from importlib import metadata

    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        pass
    try:
        return getattr(__import__(module or dist), "__version__", None)
    except Exception:  # noqa: BLE001 - a broken optional import only loses a version string
        return None


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def collect_meta(device: str) -> dict:
    """Machine, versions and date of this measurement process (CUDA is only touched when it is in use anyway)."""
    import torch

    from tocabi_torchrl.sim.config import available_cores

    meta = {"host": socket.gethostname(), "cpu_model": _cpu_model(), "cpu_count": os.cpu_count(),
            "available_cores": available_cores(), "torch_threads": torch.get_num_threads(),
            "python": platform.python_version(), "date": time.strftime("%Y-%m-%d %H:%M:%S"),
            "versions": {name: _version(dist, mod) for name, dist, mod in (
                ("torch", "torch", None), ("warp", "warp-lang", "warp"), ("mujoco", "mujoco", None),
                ("mujoco_warp", "mujoco-warp", "mujoco_warp"), ("torchrl", "torchrl", None),
                ("tensordict", "tensordict", None), ("numpy", "numpy", None))},
            "host_ram_gib": os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / GIB}
    meta.update(gpu=None, gpu_total_gib=None)
    if device.startswith("cuda"):
        try:
            _free, total = torch.cuda.mem_get_info()
            meta.update(gpu=torch.cuda.get_device_name(), gpu_total_gib=total / GIB)
        except Exception as err:  # noqa: BLE001 - after a failed run the context may be unusable
            meta["gpu_error"] = f"{type(err).__name__}: {err}"
    return meta


# ------------------------------------------------------------------------------------------ one measurement


def _is_oom(text: str) -> bool:
    low = text.lower()
    return any(marker in low for marker in OOM_MARKERS)


def _gpu_memory(before_used: float | None) -> dict:
    """Torch allocator peaks and the device-wide use now (the env is still alive, torch keeps what it reserved)."""
    import torch

    free, total = torch.cuda.mem_get_info()
    return {"torch_peak_allocated_gib": torch.cuda.max_memory_allocated() / GIB,
            "torch_peak_reserved_gib": torch.cuda.max_memory_reserved() / GIB,
            "device_used_end_gib": (total - free) / GIB, "device_used_before_gib": before_used,
            "device_total_gib": total / GIB}


def _metrics_rows(csv_path: Path) -> list[dict]:
    """The logged iterations of a training run's ``metrics.csv`` ([] when it has none)."""
    import csv

    try:
        with open(csv_path, newline="") as f:
            return list(csv.DictReader(f))
    except OSError:
        return []


def _steady_window(rows: list[dict]) -> dict | None:
    """Env-steps and seconds between the first and last of ``rows`` (logged iterations of one process: the window
    leaves out its first iteration, the warm-up), None with fewer than two rows."""
    if len(rows) < 2:
        return None
    dt = float(rows[-1]["wall_s"]) - float(rows[0]["wall_s"])
    steps = float(rows[-1]["env_steps"]) - float(rows[0]["env_steps"])
    return {"env_steps": steps, "wall_s": dt} if dt > 0 else None


def _steady_rate(windows: Iterable[dict | None]) -> float | None:
    """Env-steps/s over the steady windows of a run's segments."""
    windows = [w for w in windows if w]
    dt = sum(w["wall_s"] for w in windows)
    return sum(w["env_steps"] for w in windows) / dt if dt > 0 else None


def _start_cuda() -> float:
    """Create the CUDA context and return the device memory in use before anything of ours is allocated [GiB]."""
    import torch

    torch.cuda.init()
    torch.cuda.reset_peak_memory_stats()
    free, total = torch.cuda.mem_get_info()
    return (total - free) / GIB


def checkpoint_path(spec: RunSpec) -> Path:
    """Where a training run of ``spec`` leaves its latest checkpoint (the trainer saves one when it stops)."""
    return Path(spec.run_dir) / spec.name / "checkpoints" / "latest.pt"


def _check_chain(spec: RunSpec, previous: dict, cfg) -> None:
    """Refuse to continue ``previous`` with another sizing or recipe than it ran with (``cfg`` is this process's
    config), or from a checkpoint that is not where that result ended."""
    import torch

    was = previous.get("config") or {}
    now = {"frames_per_batch": cfg.frames_per_batch, "total_env_steps_target": cfg.total_env_steps,
           "actor_hidden": list(cfg.actor_hidden), "critic_hidden": list(cfg.critic_hidden)}
    differ = {k: (was.get(k), v) for k, v in now.items() if was.get(k) != v}
    if _recipe_part(previous.get("recipe")) != spec_recipe(spec):
        differ["recipe"] = "another training recipe"
    if stored_env_graph(previous) != planned_env_graph(spec):
        differ["env step"] = "another env-step mode (CUDA graph vs eager)"
    if differ:
        raise ValueError(f"{spec.name} cannot continue with other settings than it started with: {differ} "
                         "(--redo partial measures from scratch)")
    path = checkpoint_path(spec)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path} to continue {spec.name} from")
    steps = torch.load(path, map_location="cpu", weights_only=True).get("env_steps")  # tensors and plain data only
    if steps != previous.get("env_steps"):
        raise ValueError(f"the checkpoint {path} is at {steps} env-steps but the result at "
                         f"{previous.get('env_steps')}: they do not chain (--redo partial measures from scratch)")


def measure_training(spec: RunSpec, deadline: float | None, sampler: Sampler, previous: dict | None = None) -> dict:
    """Train ``spec`` with ``train(cfg, env)``; the env is built here so it stays alive for the memory reading.
    With ``previous`` (a partial result of ``spec``), training resumes from its checkpoint and the returned
    numbers are of this segment alone (see :func:`merge_segments`)."""
    from tocabi_torchrl.rl.trainer import build_env, resolve_device, train

    gpu_before = _start_cuda() if spec.backend == "gpu" else None
    cfg = spec.ppo_config()
    if previous is None:
        shutil.rmtree(Path(cfg.run_dir) / cfg.name, ignore_errors=True)  # metrics.csv appends: start clean
    else:
        _check_chain(spec, previous, cfg)
        cfg.resume = str(checkpoint_path(spec))
    done_before = previous["env_steps"] if previous else 0
    metrics_csv = Path(cfg.run_dir) / cfg.name / "metrics.csv"
    rows_before = len(_metrics_rows(metrics_csv))  # a resumed run appends its rows after the earlier segments'
    env = build_env(cfg, resolve_device(cfg.device), for_training=True)
    if deadline is not None:
        left_min = (deadline - time.time() - STOP_MARGIN_S) / 60.0
        cfg.max_minutes = max(0.05, min(cfg.max_minutes or math.inf, left_min))
    result = train(cfg, env=env)
    t_end = time.perf_counter()
    out = {
        "config": {"steps_per_env": cfg.steps_per_env, "frames_per_batch": cfg.frames_per_batch,
                   "minibatch_size": cfg.minibatch_size, "epochs": cfg.epochs, "iterations_planned": cfg.iterations,
                   "total_env_steps_target": cfg.total_env_steps, "actor_hidden": list(cfg.actor_hidden),
                   "critic_hidden": list(cfg.critic_hidden), "max_minutes": cfg.max_minutes},
        "iterations": result.iterations,
        "env_steps": result.env_steps - done_before,  # of this process (a resumed run counts on from its checkpoint)
        "train_wall_s": result.wall_seconds,  # TocabiLab's timer: from finished set-up to the end
        "total_wall_s": t_end - _T0,  # imports, CUDA, env (warp kernels), agent, collector included
        "setup_s": t_end - _T0 - result.wall_seconds,
        "env_steps_per_s": result.env_steps_per_second,
        "env_graph": result.env_graph,  # whether the env step actually ran as a CUDA graph (a failed capture: no)
        "steady_window": (window := _steady_window(_metrics_rows(metrics_csv)[rows_before:])),
        "steady_env_steps_per_s": _steady_rate([window]),
        "status": "ok" if result.env_steps >= cfg.total_env_steps else "partial",
    }
    sampler.stop()
    out["cpu"] = sampler.summary(t_end - result.wall_seconds)  # to the final sample stop() took at t_end
    if spec.backend == "gpu":
        out["gpu"] = _gpu_memory(gpu_before)
    del env
    return out


def measure_raw(spec: RunSpec, sampler: Sampler) -> dict:
    """Raw mujoco-warp policy steps/s of the same model at ``num_envs`` worlds (the ceiling)."""
    before = _start_cuda()
    from sim_throughput import raw_policy_steps_per_second

    rate = raw_policy_steps_per_second(spec.num_envs, spec.raw_steps)
    sampler.stop()
    return {"status": "ok", "raw_policy_steps_per_s": rate, "raw_steps": spec.raw_steps,
            "total_wall_s": time.perf_counter() - _T0, "cpu": sampler.summary(), "gpu": _gpu_memory(before)}


#: Per-segment numbers of a training run that resumed from checkpoints (TocabiLab's timer sums the segments).
SEGMENT_KEYS = ("env_steps", "train_wall_s", "setup_s", "total_wall_s", "env_steps_per_s", "steady_window", "command",
                "part_command", "env_graph")


def _segments(record: dict) -> list[dict]:
    """The training segments of a time result: its own list, or the record itself as the only one."""
    if record.get("segments"):
        return [dict(seg) for seg in record["segments"]]
    return [{**{k: record.get(k) for k in SEGMENT_KEYS}, "date": (record.get("meta") or {}).get("date")}]


def _weighted_cpu(parts: list[dict]) -> dict:
    """CPU use over several segments: means weighted by each segment's window, peaks as peaks."""
    parts = [p for p in parts if p and p.get("window_s")]
    if not parts:
        return {}
    window = sum(p["window_s"] for p in parts)
    out = dict(parts[-1])
    for key in ("cores_used_mean", "system_busy_cores_mean", "gpu_util_mean"):
        values = [(p[key], p["window_s"]) for p in parts if p.get(key) is not None]
        out[key] = sum(v * w for v, w in values) / sum(w for _, w in values) if values else None
    for key in ("cores_used_max", "rss_peak_sampled_gib", "gpu_used_peak_gib"):
        values = [p[key] for p in parts if p.get(key) is not None]
        out[key] = max(values) if values else None
    out.update(samples=sum(p.get("samples", 0) for p in parts), window_s=window)
    return out


def merge_segments(previous: dict, segment: dict) -> dict:
    """One time result from ``previous`` (partial) and ``segment`` (the next process's training, resumed from the
    checkpoint ``previous`` ended at). Steps, training time (TocabiLab's timer), set-up and total times add up; the
    rate is all steps over all training time; CPU means are weighted by time; memory readings are the latest
    segment's (the same env count and networks) with peaks over all. ``segments`` lists each process's own numbers."""
    segments = _segments(previous) + _segments(segment)
    merged = {**previous, **segment}
    for key in ("env_steps", "train_wall_s", "setup_s", "total_wall_s"):
        merged[key] = sum(seg[key] or 0 for seg in segments)
    merged["env_steps_per_s"] = merged["env_steps"] / merged["train_wall_s"] if merged["train_wall_s"] else None
    merged["steady_env_steps_per_s"] = _steady_rate(seg.get("steady_window") for seg in segments)
    modes = [seg["env_graph"] for seg in segments if seg.get("env_graph") is not None]  # None: not recorded then
    if modes:  # "graph" only if every segment's step ran captured
        merged["env_graph"] = all(modes)
    merged.pop("steady_window", None)  # each segment keeps its own
    merged["cpu_segments"] = [*previous.get("cpu_segments", [previous.get("cpu")]), segment.get("cpu")]
    merged["cpu"] = _weighted_cpu(merged["cpu_segments"])
    merged["host"] = {"peak_rss_gib": max((r.get("host") or {}).get("peak_rss_gib") or 0 for r in (previous, segment))}
    if previous.get("gpu") and segment.get("gpu"):
        merged["gpu"] = {**segment["gpu"], **{k: max(previous["gpu"].get(k) or 0, segment["gpu"].get(k) or 0)
                                              for k in ("torch_peak_allocated_gib", "torch_peak_reserved_gib")}}
    merged["status"] = "ok" if merged["env_steps"] >= previous["total_env_steps"] else "partial"
    merged["segments"] = segments
    merged.pop("continue_failed", None)
    return merged


def run_one(spec: RunSpec, out_path: Path, deadline: float | None = None, command: str = "",
            resume: bool = False) -> dict:
    """Measure ``spec`` in this process and write its JSON; out-of-memory becomes status ``oom``, not a crash.
    With ``resume``, the partial time result at ``out_path`` trains on from its checkpoint and the two are merged
    (:func:`merge_segments`); if that fails, the partial result stays as it was, with the failure noted in it."""
    import torch

    previous = _read(out_path) if resume else None
    if resume and (spec.kind != "time" or previous is None or previous.get("status") != "partial"):
        raise SystemExit(f"--continue needs a partial time result at {out_path}")

    if spec.backend == "gpu" and not torch.cuda.is_available():
        raise SystemExit("this measurement needs a CUDA GPU")
    if spec.kind == "raw":
        import warp as wp

        wp.config.quiet = True
    gpu = NvidiaSmi(_visible_gpu_index()) if spec.backend == "gpu" else None
    sampler = Sampler(gpu=gpu)
    sampler.start()
    record = {"schema": 1, **{k: v for k, v in asdict(spec).items() if k not in ("run_dir",)},
              "name": spec.name, "command": command, "part_command": os.environ.get("SCALING_PART_COMMAND", "")}
    try:
        if spec.kind != "raw":
            record["recipe"] = spec_recipe(spec)
            record["env_graph_planned"] = planned_env_graph(spec)
        record.update(measure_raw(spec, sampler) if spec.kind == "raw"
                      else measure_training(spec, deadline, sampler, previous))
    except Exception as err:  # noqa: BLE001 - every failure is a result to record, OOM especially
        sampler.stop()
        text = f"{type(err).__name__}: {err}"
        if previous is not None:  # the measured part stays; the failed continuation is noted, not a result
            previous["continue_failed"] = {"error": text[-2000:], "command": command,
                                           "date": time.strftime("%Y-%m-%d %H:%M:%S"), "time": time.time()}
            write_json(out_path, previous)
            return previous
        record.update(status="oom" if _is_oom(text) else "error", error=text[-2000:], cpu=sampler.summary())
        if spec.kind != "raw":  # when it failed: at set-up (0) or after some iterations (memory runs log each one)
            record["iterations_logged"] = len(_metrics_rows(Path(spec.run_dir) / spec.name / "metrics.csv"))
        if spec.backend == "gpu":
            try:
                record["gpu"] = _gpu_memory(None)
            except Exception as gpu_err:  # noqa: BLE001 - the context may be unusable after the failure
                record["gpu"] = {"error": f"{type(gpu_err).__name__}: {gpu_err}"}
    record["host"] = {"peak_rss_gib": peak_rss_bytes() / GIB}
    record["meta"] = collect_meta(spec.device)
    if previous is not None:
        record = merge_segments(previous, record)
    write_json(out_path, record)
    return record


def write_json(path: Path, data: dict) -> None:
    """Atomic write: a killed process never leaves half a result that resume would take as done."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(data, indent=2, default=str))
    tmp.replace(path)


# --------------------------------------------------------------------------------------------- the driver


def plan(parts: Sequence[str], num_envs: Sequence[int] | None = None, **spec_fields) -> list[RunSpec]:
    """The measurements of ``parts`` (``all`` = raw, gpu_time, memory, cpu_time), at ``num_envs`` if given."""
    names = [p for part in parts for p in (ALL_ORDER if part == "all" else (part,))]
    specs = []
    for part in names:
        kind, backend, default_ns = PARTS[part]
        ns = list(num_envs) if num_envs else list(default_ns)
        if kind == "memory":
            ns = sorted(ns)  # the sweep stops at the first env count that does not fit
        specs += [RunSpec(kind, backend, n, **spec_fields) for n in ns]
    return specs


def _result_counts(results: Path, backend: str) -> tuple[list[int], list[int]]:
    """(env counts that trained, env counts that did not fit) among the current recipe's memory and time results;
    a run stopped before it proved either (see :func:`shows_fit`) counts as neither."""
    fit, failed = [], []
    for path in [*Path(results).glob(f"memory_{backend}_*.json"), *Path(results).glob(f"time_{backend}_*.json")]:
        record = _read(path)
        if record is None or is_stale(record):
            continue
        n = int(path.stem.rsplit("_", 1)[1])
        if shows_fit(record):
            fit.append(n)
        elif record.get("status") in FAILED:
            failed.append(n)
    return fit, failed


def refine_count(results: Path, backend: str = "gpu", step: int = REFINE_STEP) -> int | None:
    """The next env count of the memory sweep's bisection: the multiple of ``step`` that halves the gap between the
    largest count that trained and the smallest larger one that did not fit (current recipe's memory and time
    results of ``backend``, see :func:`_result_counts`). None when nothing has trained yet, nothing above the largest
    fit has failed, the gap is ``step`` or less, or no multiple of ``step`` lies strictly inside it. A failure below
    the largest fit (a one-off error, say) does not bound the search."""
    fit, failed = _result_counts(results, backend)
    if not fit:
        return None
    largest = max(fit)
    above = [n for n in failed if n > largest]
    if not above or min(above) - largest <= step:
        return None
    mid = (largest + min(above)) // 2 // step * step
    return mid if largest < mid < min(above) else None


def with_refinement(specs: Sequence[RunSpec], results: Path) -> Iterator[RunSpec]:
    """``specs``, and right after the last memory run, memory runs that narrow down the largest env count that fits
    (bisection between the largest that trained and the smallest that did not, see :func:`refine_count`). Lazy:
    each refinement is chosen from the results of the runs before it."""
    last_memory = max((i for i, s in enumerate(specs) if s.kind == "memory"), default=None)
    for i, spec in enumerate(specs):
        yield spec
        if i != last_memory:
            continue
        tried: set[int] = set()
        while (n := refine_count(results, spec.backend)) is not None and n not in tried:
            tried.add(n)  # a run the budget cut leaves no result: never offer the same count twice
            yield replace(spec, num_envs=n)


def _read(path: Path) -> dict | None:
    """An existing result file, None when there is none (or it is unreadable)."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


def load_status(path: Path) -> str | None:
    """Status of an existing result file, None when there is none (or it is unreadable)."""
    return (_read(path) or {}).get("status")


def _stale_file(path: Path) -> bool:
    record = _read(path)
    return record is not None and is_stale(record)


def _sweep_blocked(spec: RunSpec, results: Path) -> int | None:
    """For a memory run: the smallest smaller env count (memory or time run) that did not fit, else None."""
    _, failed = _result_counts(results, spec.backend)
    smaller = [n for n in failed if n < spec.num_envs]
    return min(smaller) if smaller else None


Launcher = Callable[[RunSpec, Path, float, bool, bool], str]


def launch(spec: RunSpec, out_path: Path, deadline: float, record_timeout: bool, resume: bool = False,
           log_dir: str = DEFAULT_LOG_DIR, part_command: str = "") -> str:
    """Run ``spec`` in a fresh process (``--one``) until ``deadline``; returns its status, or "cut" where the
    command's budget (not the measurement's own timeout) killed it, which leaves no result so a rerun repeats it.
    ``resume``: continue the partial time result at ``out_path`` from its checkpoint (``--continue``)."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--one", *spec.to_argv(), "--out", str(out_path),
           "--deadline", f"{deadline:.1f}", *(["--continue"] if resume else [])]
    env = dict(os.environ, PYTHONUNBUFFERED="1", SCALING_PART_COMMAND=part_command)
    if spec.backend == "cpu":
        env["CUDA_VISIBLE_DEVICES"] = ""  # the CPU baseline: nothing of this process may touch the GPU
    log_path = Path(log_dir) / f"{spec.name}.log"
    log_path.parent.mkdir(parents=True, exist_ok=True)
    before = _mtime(out_path)  # a result being measured again is still there: only a newer file is this run's
    with open(log_path, "w") as log:
        try:
            rc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, env=env, cwd=str(ROOT),
                                timeout=max(1.0, deadline - time.time() + KILL_GRACE_S), check=False).returncode
        except subprocess.TimeoutExpired:
            rc = None
    if _mtime(out_path) not in (None, before):
        return load_status(out_path) or "error"
    tail = log_path.read_text(errors="replace")[-3000:] if log_path.exists() else ""
    if rc is None and not record_timeout:
        return "cut"
    if resume:  # the partial result stays; what broke the continuation is in the log
        return f"error (the continuation wrote nothing, see {log_path})"
    status = "timeout" if rc is None else ("oom" if _is_oom(tail) else "error")
    write_json(out_path, {"schema": 1, **{k: v for k, v in asdict(spec).items() if k != "run_dir"}, "name": spec.name,
                          "status": status, "returncode": rc, "error": tail, "command": " ".join(cmd[1:]),
                          "part_command": part_command, "recipe": spec_recipe(spec),
                          "meta": {"date": time.strftime("%Y-%m-%d %H:%M:%S")}})
    return status


def _mtime(path: Path) -> int | None:
    try:
        return Path(path).stat().st_mtime_ns
    except OSError:
        return None


def write_bundle(results: Path, bundle: Path) -> None:
    """All result files of ``results`` in one JSON file (the device tool returns at most 8 files)."""
    data = {p.name: json.loads(p.read_text()) for p in sorted(Path(results).glob("*.json"))}
    write_json(bundle, {"bundle": 1, "results": data})


def unpack_bundle(bundle: Path, results: Path) -> list[str]:
    """Write the result files of a bundle into ``results``; returns their names."""
    data = json.loads(Path(bundle).read_text())["results"]
    for name, record in data.items():
        write_json(Path(results) / Path(name).name, record)
    return sorted(data)


@dataclass
class DriveOptions:
    results: Path = DEFAULT_RESULTS
    budget_s: float = 540.0
    timeout_s: float = 570.0
    redo: tuple[str, ...] = ()
    reuse_time_for_memory: bool = True
    bundle: Path | None = None
    redo_stale: bool = True  # measure again what an older training recipe produced
    continue_partial: bool = True  # a partial time run trains on from its checkpoint (where there is one)


def drive(specs: Iterable[RunSpec], opts: DriveOptions, launcher: Launcher) -> dict[str, str]:
    """Launch every measurement of ``specs`` that has no result yet, within the command's budget.

    Returns {name: status or why it was skipped}. ``launcher(spec, out_path, deadline, record_timeout, resume)``
    measures one spec (``launch`` in a subprocess; tests pass a fake); ``resume`` continues a partial time run
    from its checkpoint in ``spec.run_dir``.
    """
    results = Path(opts.results)
    results.mkdir(parents=True, exist_ok=True)
    t_stop = time.time() + opts.budget_s
    outcome: dict[str, str] = {}
    launched = 0
    for spec in specs:
        path = results / f"{spec.name}.json"
        status = load_status(path)
        if spec.kind == "memory" and status == "partial" and not _stale_file(path):
            # stopped before its iterations were done: it shows neither fit nor failure, so it is measured again
            print(f"[scaling] {spec.name}: its last run was stopped early, measuring again", flush=True)
            status = None
        resume = (spec.kind == "time" and status == "partial" and "partial" not in opts.redo
                  and opts.continue_partial and not _stale_file(path))
        if resume and not checkpoint_path(spec).is_file():
            outcome[spec.name] = f"skipped (partial; no checkpoint at {checkpoint_path(spec)} to continue from)"
            continue
        failed = (_read(path) or {}).get("continue_failed") if resume else None
        if failed and checkpoint_path(spec).stat().st_mtime <= failed.get("time", 0):
            # the same checkpoint would fail the same way: wait for a new one, or --redo partial
            outcome[spec.name] = f"skipped (partial; its last continuation failed: {failed['error'][:200]})"
            continue
        if status is not None and status not in opts.redo and not resume:
            if not (opts.redo_stale and _stale_file(path)):
                outcome[spec.name] = f"skipped ({status})"
                continue
            print(f"[scaling] {spec.name}: measured with an older recipe, measuring again", flush=True)
        if spec.kind == "memory":
            time_path = results / f"time_{spec.backend}_{spec.num_envs:07d}.json"
            if opts.reuse_time_for_memory and load_status(time_path) == "ok" and not _stale_file(time_path):
                outcome[spec.name] = "skipped (the time run has these numbers)"
                continue
            blocked = _sweep_blocked(spec, results)
            if blocked is not None:
                outcome[spec.name] = f"skipped ({blocked} envs did not fit)"
                continue
        left = t_stop - time.time()
        if left < MIN_LAUNCH_S[spec.kind] and (launched or left < MIN_LAUNCH_S["raw"]):
            outcome[spec.name] = "not started (budget)"
            print(f"[scaling] budget reached ({left:.0f} s left): rerun the same command to continue", flush=True)
            break
        own_deadline = time.time() + opts.timeout_s
        deadline = min(own_deadline, t_stop)
        how = "continue from its checkpoint" if resume else "start"
        print(f"[scaling] {spec.name}: {how} ({left:.0f} s of budget left)", flush=True)
        t0 = time.time()
        status = launcher(spec, path, deadline, own_deadline <= t_stop, resume)
        launched += 1
        outcome[spec.name] = status
        print(f"[scaling] {spec.name}: {status} in {time.time() - t0:.0f} s {_brief(path)}", flush=True)
        if opts.bundle is not None:
            write_bundle(results, opts.bundle)
    return outcome


def _brief(path: Path) -> str:
    """One line of a result for the progress log."""
    try:
        r = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return ""
    parts = []
    if r.get("env_steps_per_s"):
        parts.append(f"{r['env_steps']:,} env-steps, {r['train_wall_s']:.1f} s, "
                     f"{r['env_steps_per_s']:,.0f} env-steps/s")
    if r.get("raw_policy_steps_per_s"):
        parts.append(f"raw {r['raw_policy_steps_per_s']:,.0f} policy steps/s")
    if r.get("host"):
        parts.append(f"peak RSS {r['host']['peak_rss_gib']:.2f} GiB")
    if r.get("gpu"):
        parts.append(f"device used {r['gpu'].get('device_used_end_gib') or 0:.2f} GiB")
    for error in (r.get("error"), (r.get("continue_failed") or {}).get("error")):
        if error:
            parts.append(error.strip().splitlines()[-1][:160])
    return "(" + "; ".join(parts) + ")" if parts else ""


# ------------------------------------------------------------------------------------------------ CLI


def _has_gpu() -> bool:
    """An NVIDIA GPU is visible, found without creating a CUDA context in the driver (which would count as used
    device memory in the measurements' readings)."""
    return Path("/dev/nvidia0").exists() or shutil.which("nvidia-smi") is not None


def _hidden(text: str) -> tuple[int, ...]:
    return tuple(int(x) for x in text.split(",") if x)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--part", nargs="+", default=["all"],
                        choices=[*PARTS, "all", "report", "unpack"], help="what to do (several run in order)")
    parser.add_argument("--num_envs", type=int, nargs="+", default=None, help="env counts (default: the part's; given counts also turn off the memory sweep's bisection)")
    parser.add_argument("--results", default=str(DEFAULT_RESULTS), help="folder of the per-measurement JSON files")
    parser.add_argument("--out", default=None, help="report: output folder (default: the results folder's parent); "
                                                    "--one: the result file")
    parser.add_argument("--budget_minutes", type=float, default=9.0, help="stop launching measurements after this")
    parser.add_argument("--timeout_minutes", type=float, default=9.5, help="one measurement's own time limit")
    parser.add_argument("--max_minutes", type=float, default=9.0, help="a training run's own clock limit")
    parser.add_argument("--redo", nargs="*", default=[], choices=STATUSES, help="measure these statuses again")
    parser.add_argument("--no_reuse", action="store_true", help="memory: also rerun env counts a time run covered")
    parser.add_argument("--no_continue", action="store_true",
                        help="skip partial time runs instead of training them on from their checkpoints")
    parser.add_argument("--keep_stale", action="store_true",
                        help="skip results trained with an older recipe instead of measuring them again (the report still "
                             "leaves them out)")
    parser.add_argument("--bundle", default=None, help="one JSON file of every result (rewritten as results come)")
    parser.add_argument("--memory_iterations", type=int, default=3)
    parser.add_argument("--raw_steps", type=int, default=200)
    parser.add_argument("--total_env_steps", type=int, default=TARGET_ENV_STEPS)
    parser.add_argument("--min_rollout", type=int, default=MIN_ROLLOUT)
    parser.add_argument("--hidden", type=_hidden, default=(), help="actor and critic hidden sizes (default: preset)")
    parser.add_argument("--run_dir", default=DEFAULT_RUN_DIR, help="where the training runs write (scratch)")
    parser.add_argument("--log_dir", default=DEFAULT_LOG_DIR, help="one log per measurement process")
    # one measurement in this process (what the driver launches)
    parser.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--kind", choices=("time", "memory", "raw"), help=argparse.SUPPRESS)
    parser.add_argument("--backend", choices=("cpu", "gpu"), help=argparse.SUPPRESS)
    parser.add_argument("--deadline", type=float, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--continue", dest="resume", action="store_true", help=argparse.SUPPRESS)
    return parser


def main(argv: Sequence[str] | None = None) -> dict | None:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    fields = {"total_env_steps": args.total_env_steps, "memory_iterations": args.memory_iterations,
              "hidden": args.hidden, "min_rollout": args.min_rollout, "raw_steps": args.raw_steps,
              "max_minutes": args.max_minutes, "run_dir": args.run_dir}
    if args.one:
        if not (args.kind and args.backend and args.num_envs and args.out):
            raise SystemExit("--one needs --kind, --backend, --num_envs N and --out FILE")
        spec = RunSpec(args.kind, args.backend, args.num_envs[0], **fields)
        return run_one(spec, Path(args.out), args.deadline, "python3 benchmarks/scaling.py " + " ".join(argv),
                       resume=args.resume)
    parts = list(args.part)
    if "unpack" in parts:  # first: the measurements below then skip what the bundle holds
        if not args.bundle:
            raise SystemExit("--part unpack needs --bundle FILE")
        names = unpack_bundle(Path(args.bundle), Path(args.results))
        print(f"[scaling] unpacked {len(names)} results into {args.results}", flush=True)
    measure = [p for p in parts if p not in ("unpack", "report")]
    specs = plan(measure, args.num_envs, **fields)
    if any(spec.backend == "gpu" for spec in specs) and not _has_gpu():
        raise SystemExit("these parts measure the GPU and this machine has none (run them on the GPU machine)")
    if specs:  # one budget for every part of this command
        part_command = "python3 benchmarks/scaling.py " + " ".join(argv)
        opts = DriveOptions(Path(args.results), 60.0 * args.budget_minutes, 60.0 * args.timeout_minutes,
                            tuple(args.redo), not args.no_reuse, Path(args.bundle) if args.bundle else None,
                            redo_stale=not args.keep_stale, continue_partial=not args.no_continue)

        def launcher(spec: RunSpec, path: Path, deadline: float, record_timeout: bool, resume: bool) -> str:
            return launch(spec, path, deadline, record_timeout, resume, args.log_dir, part_command)

        # Only the default sweep bisects: given counts are a request for exactly those (a rerun of one count, say),
        # and a bisection there would spend the call's device time on counts nobody asked for.
        runs = specs if args.num_envs else with_refinement(specs, Path(args.results))
        outcome = drive(runs, opts, launcher)
        for name, status in outcome.items():
            print(f"  {name}: {status}", flush=True)
        if not any(v in ("not started (budget)", "cut") for v in outcome.values()):
            print("[scaling] nothing left to measure in these parts", flush=True)
    if "report" in parts:  # last: it reads what the measurements above wrote
        import scaling_report

        out = Path(args.out) if args.out else Path(args.results).parent
        print(scaling_report.write_report(Path(args.results), out), flush=True)
    return None


if __name__ == "__main__":
    main()
    if "--one" in sys.argv:
        # The result is written: skip interpreter teardown (CUDA, warp and collector clean-up can take long or
        # hang), which the driver would otherwise wait for until the measurement's timeout.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
