"""Report of the scaling suite (``benchmarks/scaling.py``): reads every result JSON of a folder and writes
``scaling.json`` (all results, metadata, derived numbers, checks), ``scaling.md`` (tables) and four figures
(``scaling_time.png``, ``scaling_rate.png``, ``scaling_memory.png``, ``scaling_cpu.png``, analogues of TocabiLab's
figures 5.1-5.4). Works on a CPU machine with whatever results exist: what is missing shows as "not measured".

    python benchmarks/scaling.py --part report            # = python benchmarks/scaling_report.py
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from scaling import CHUNKS, DEFAULT_RESULTS, FAILED, PARTS, ROOT, TARGET_ENV_STEPS, shows_fit
from tocabi_torchrl.rl.config import ENV_GRAPH_AUTO_MAX_ENVS  # noqa: E402  (scaling puts the repo root on sys.path)

REPORT_COMMAND = "python benchmarks/scaling.py --part report"
NOT_MEASURED = "not measured"

#: TocabiLab's chapter-5 numbers as the issue quotes them (983,040 env-steps each).
TOCABILAB = {
    "rsl_rl_96": {"label": "TocabiLab: Isaac Lab + rsl_rl, 96 envs, RTX 4070 Ti Super", "num_envs": 96,
                  "seconds": 850.0},
    "sb3_cpu_8": {"label": "TocabiLab: CPU MuJoCo + SB3, 8 envs", "num_envs": 8, "seconds": 1535.0},
    "sb3_cpu_96": {"label": "TocabiLab: CPU MuJoCo + SB3, 96 envs", "num_envs": 96, "seconds": None,
                   "note": "failed"},
}
#: env-steps/s: 983,040 / 850 s rounded as the issue states it, TocabiLab's best reported training rate; every
#: "vs TocabiLab" ratio of the report divides by it.
TOCABILAB_BEST_RATE = 1157.0
TARGET_VS_CPU = 10.0  # GPU at 4,096 envs vs the CPU baseline's best
TARGET_VS_TOCABILAB = 100.0  # GPU at 4,096 envs vs TocabiLab's best
TARGET_RAM_GROWTH = 0.10  # host RAM growth from 1,024 to 16,384 envs
RATED = ("ok", "partial")  # statuses that carry a measured rate
PART_COUNTS = {part: counts for part, (_, _, counts) in PARTS.items()}

E_DEFINITION = (
    "TocabiLab's efficiency metric E (its eq. 5.1) was not available to us (the thesis text could not be found), so "
    "this report does not reproduce it. It uses two transparent resource efficiencies instead: "
    "**E_core** = training env-steps/s ÷ CPU cores busy during training (process CPU time ÷ training wall time), "
    "and, on the GPU, **E_mem** = training env-steps/s ÷ GiB of device memory in use (cudaMemGetInfo at the end "
    "of training, env still alive). Higher is better for both."
)


# ------------------------------------------------------------------------------------------------ loading


def load_results(folder: Path) -> list[dict]:
    """Every result file of ``folder`` (unreadable files are skipped with a note on stderr). A time or memory result
    trained with another recipe than the current default gets status ``stale`` (its own in ``measured_status``), so
    no table, figure or check uses it."""
    from scaling import is_stale, recipe

    current = recipe()
    records = []
    for path in sorted(Path(folder).glob("*.json")):
        try:
            record = json.loads(path.read_text())
        except ValueError as err:
            print(f"skipping {path}: {err}", file=sys.stderr)
            continue
        if {"kind", "backend", "num_envs", "status"} <= set(record):
            if is_stale(record, current):
                record = {**record, "measured_status": record["status"], "status": "stale"}
            records.append(record)
    return records


def index(records: list[dict]) -> dict[tuple[str, str, int], dict]:
    return {(r["kind"], r["backend"], int(r["num_envs"])): r for r in records}


def rate(r: dict | None) -> float | None:
    """Training env-steps/s of a result (from set-up finished to the end), None without one."""
    if r is None or r.get("status") not in RATED or not r.get("env_steps_per_s"):
        return None
    return float(r["env_steps_per_s"])


def time_for_target(r: dict | None) -> float | None:
    """Seconds per 983,040 env-steps at the measured rate (= the measured time when exactly 983,040 were done)."""
    value = rate(r)
    return TARGET_ENV_STEPS / value if value else None


def cores_used(r: dict | None) -> float | None:
    return (r or {}).get("cpu", {}).get("cores_used_mean") if r else None


def device_used(r: dict | None) -> float | None:
    """Device memory in use at the end of the run [GiB] (the env alive; torch keeps its reserved pool)."""
    return (r or {}).get("gpu", {}).get("device_used_end_gib") if r else None


def own_device_used(r: dict | None) -> float | None:
    """Device memory this run added over its bare CUDA context [GiB]."""
    gpu = (r or {}).get("gpu") or {}
    if gpu.get("device_used_end_gib") is None or gpu.get("device_used_before_gib") is None:
        return None
    return gpu["device_used_end_gib"] - gpu["device_used_before_gib"]


def torch_peak(r: dict | None) -> float | None:
    """Torch allocator peak [GiB]."""
    return ((r or {}).get("gpu") or {}).get("torch_peak_allocated_gib")


def peak_rss(r: dict | None) -> float | None:
    if not r or r.get("status") == "stale":
        return None
    return (r.get("host") or {}).get("peak_rss_gib")


def efficiency(r: dict | None) -> tuple[float | None, float | None]:
    """(E_core, E_mem) as defined in :data:`E_DEFINITION`."""
    value, cores, used = rate(r), cores_used(r), device_used(r)
    e_core = value / cores if value and cores else None
    e_mem = value / used if value and used else None
    return e_core, e_mem


def memory_record(idx: dict, n: int) -> dict | None:
    """The GPU memory numbers at ``n`` envs: the short memory run, else (or where the memory run was stopped before
    it showed a fit and the time run did) the 983,040-step run."""
    mem, run = idx.get(("memory", "gpu", n)), idx.get(("time", "gpu", n))
    if mem is None or (run is not None and not shows_fit(mem) and shows_fit(run)):
        return run
    return mem


def gpu_counts(idx: dict) -> list[int]:
    return sorted({n for (kind, backend, n) in idx if backend == "gpu" and kind in ("memory", "time")})


# ------------------------------------------------------------------------------------------------ checks


@dataclass
class Check:
    name: str
    target: str
    measured: str
    passed: bool | None  # None: not measured, or a number the issue asks to show without a target
    value: float | None = None


def _ratio_check(name: str, target: float, num: float | None, den: float | None, what: str) -> Check:
    if not num or not den:
        return Check(name, f"≥ {target:g}×", NOT_MEASURED, None)
    ratio = num / den
    return Check(name, f"≥ {target:g}×", f"{ratio:,.1f}× ({num:,.0f} vs {what} {den:,.0f} env-steps/s)",
                 ratio >= target, ratio)


def best_cpu(idx: dict) -> tuple[int, float] | None:
    """(env count, env-steps/s) of the CPU backend's fastest training run."""
    rated = [(n, rate(r)) for (kind, backend, n), r in idx.items() if kind == "time" and backend == "cpu" and rate(r)]
    return max(rated, key=lambda x: x[1]) if rated else None


def ram_growth(idx: dict, lo: int = 1024, hi: int = 16384) -> float | None:
    a, b = peak_rss(memory_record(idx, lo)), peak_rss(memory_record(idx, hi))
    return (b - a) / a if a and b else None


def gpu_memory_per_env(idx: dict, min_envs: int = 1024) -> dict:
    """Device memory per env [MiB]: least-squares slope of the device use over env counts >= ``min_envs`` that
    fit, and the plain difference between 1,024 and 16,384 envs."""
    points = [(n, device_used(memory_record(idx, n))) for n in gpu_counts(idx) if n >= min_envs]
    points = [(n, u) for n, u in points if u is not None and shows_fit(memory_record(idx, n))]
    out: dict = {"fit_points": [n for n, _ in points], "slope_mib_per_env": None, "intercept_gib": None,
                 "delta_1024_16384_mib_per_env": None}
    if len(points) >= 2:
        xs, ys = [float(n) for n, _ in points], [u for _, u in points]
        mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
        sxx = sum((x - mx) ** 2 for x in xs)
        slope = sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sxx
        out.update(slope_mib_per_env=slope * 1024, intercept_gib=my - slope * mx)
    a, b = device_used(memory_record(idx, 1024)), device_used(memory_record(idx, 16384))
    if a is not None and b is not None:
        out["delta_1024_16384_mib_per_env"] = (b - a) * 1024 / (16384 - 1024)
    return out


def largest_fit(idx: dict) -> tuple[int | None, int | None]:
    """(largest GPU env count that trained, smallest that ran out of memory or failed), None where none. A run
    stopped before it showed either (see ``scaling.shows_fit``) is neither."""
    ok = [n for n in gpu_counts(idx) if shows_fit(memory_record(idx, n))]
    failed = [n for n in gpu_counts(idx) if memory_record(idx, n)["status"] in FAILED]
    return (max(ok) if ok else None), (min(failed) if failed else None)


def checks(records: list[dict]) -> list[Check]:
    """The issue's must-show numbers, each with its measured value and pass/fail where it has a target."""
    idx = index(records)
    gpu4096 = rate(idx.get(("time", "gpu", 4096)))
    cpu = best_cpu(idx)
    out = [
        _ratio_check("GPU training at 4,096 envs vs the CPU backend's best", TARGET_VS_CPU, gpu4096,
                     cpu[1] if cpu else None, f"CPU at {cpu[0]} envs" if cpu else "CPU"),
        _ratio_check("GPU training at 4,096 envs vs TocabiLab's best (1,157 env-steps/s)", TARGET_VS_TOCABILAB,
                     gpu4096, TOCABILAB_BEST_RATE, "TocabiLab"),
    ]
    growth = ram_growth(idx)
    if growth is None:
        out.append(Check("Host RAM growth from 1,024 to 16,384 envs", "< 10 %", NOT_MEASURED, None))
    else:
        lo, hi = peak_rss(memory_record(idx, 1024)), peak_rss(memory_record(idx, 16384))
        out.append(Check("Host RAM growth from 1,024 to 16,384 envs", "< 10 %",
                         f"{100 * growth:+.1f} % ({lo:.2f} → {hi:.2f} GiB peak RSS)", growth < TARGET_RAM_GROWTH,
                         growth))
    per_env = gpu_memory_per_env(idx)
    slope = per_env["slope_mib_per_env"]
    out.append(Check("GPU memory per env", "(shown)",
                     f"{slope:.3f} MiB/env (fit over {', '.join(map(str, per_env['fit_points']))} envs)"
                     if slope is not None else NOT_MEASURED, None, slope))
    fit, fail = largest_fit(idx)
    gpu_name = next((r.get("meta", {}).get("gpu") for r in records if (r.get("meta") or {}).get("gpu")), None)
    if fit is None:
        text = NOT_MEASURED
    else:
        text = f"{fit:,} envs" + (f" ({fail:,} did not fit)" if fail else " (no larger count was tried or failed)")
        text += f" on {gpu_name}" if gpu_name else ""
    out.append(Check("Largest env count that trains on the GPU", "(shown)", text, None, fit))
    return out


# ------------------------------------------------------------------------------------------------ formatting


def _f(value: float | None, fmt: str = ",.0f", suffix: str = "") -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return NOT_MEASURED
    return f"{value:{fmt}}{suffix}"


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---:|" * len(header)]
    return lines + ["| " + " | ".join(row) + " |" for row in rows]


def _status(r: dict | None) -> str:
    if r is None:
        return NOT_MEASURED
    status = r["status"]
    if status == "partial":
        status = f"partial ({r.get('env_steps', 0):,} steps, time extrapolated)"
    if len(r.get("segments") or ()) > 1:  # trained across processes, resumed from checkpoints
        status += f" ({len(r['segments'])} segments)"
    return status


def env_step_mode(r: dict) -> str:
    """How a GPU result's env step ran: one CUDA graph ("graph") or launched op by op ("eager"); "-" on the CPU.
    A run that failed shows the mode it was to run in."""
    from scaling import stored_env_graph

    if r.get("backend") != "gpu":
        return "-"
    ran = r["env_graph"] if "env_graph" in r else stored_env_graph(r)
    return "graph" if ran else "eager"


def time_rows(idx: dict, backend: str, counts: list[int]) -> list[list[str]]:
    rows = []
    system = "GPU (mujoco-warp)" if backend == "gpu" else "CPU (C MuJoCo)"
    for n in counts:
        r = idx.get(("time", backend, n))
        if r is None:
            rows.append([system, f"{n:,}"] + ["-"] * 10 + [NOT_MEASURED])
            continue
        cfg = r.get("config") or {}
        e_core, e_mem = efficiency(r)
        t = time_for_target(r)
        speedup = rate(r) / TOCABILAB_BEST_RATE if rate(r) else None  # the checks' ratio, to the same digit
        rows.append([
            system, f"{n:,}",
            f"{cfg['steps_per_env']} / {cfg['minibatch_size']:,}" if cfg else NOT_MEASURED, env_step_mode(r),
            _f(r.get("env_steps") if rate(r) else None), _f(r.get("train_wall_s") if rate(r) else None, ",.1f"),
            _f(r.get("total_wall_s") if rate(r) else None, ",.1f"), _f(rate(r)), _f(t, ",.1f"),
            _f(speedup, ",.1f", "×"), _f(e_core, ",.0f"), _f(e_mem, ",.0f") if backend == "gpu" else "-",
            _status(r),
        ])
    return rows


def tocabilab_rows() -> list[list[str]]:
    rows = []
    for ref in TOCABILAB.values():
        sec = ref["seconds"]
        rows.append([ref["label"], f"{ref['num_envs']}", "24 / -" if "rsl_rl" in ref["label"] else "-", "-",
                     f"{TARGET_ENV_STEPS:,}" if sec else "-", _f(sec, ",.0f") if sec else ref.get("note", "-"), "-",
                     _f(TARGET_ENV_STEPS / sec) if sec else "-", _f(sec, ",.0f") if sec else "-",
                     _f(TARGET_ENV_STEPS / sec / TOCABILAB_BEST_RATE, ",.2f", "×") if sec else "-", "-", "-",
                     "reported"])
    return rows


def memory_rows(idx: dict) -> list[list[str]]:
    rows = []
    for n in gpu_counts(idx):
        r = memory_record(idx, n)
        cpu = r.get("cpu") or {}
        gpu = r.get("gpu") or {}
        cores = (r.get("meta") or {}).get("available_cores")
        util = cpu.get("cores_used_mean") / cores if cpu.get("cores_used_mean") and cores else None
        rows.append([
            f"{n:,}", "short run" if r["kind"] == "memory" else "983k run", r["status"], _f(peak_rss(r), ".2f"),
            _f(gpu.get("torch_peak_allocated_gib"), ".2f"), _f(gpu.get("torch_peak_reserved_gib"), ".2f"),
            _f(gpu.get("device_used_end_gib"), ".2f"), _f(cpu.get("gpu_used_peak_gib"), ".2f"),
            _f(cpu.get("cores_used_mean"), ".2f"), _f(100 * util if util is not None else None, ".0f", " %"),
            _f(cpu.get("gpu_util_mean"), ".0f", " %"), _f(rate(r)),
        ])
    return rows


def raw_rows(idx: dict) -> list[list[str]]:
    counts = sorted({n for (kind, backend, n) in idx if backend == "gpu" and kind in ("raw", "time")})
    rows = []
    for n in counts:
        raw = idx.get(("raw", "gpu", n))
        raw_rate = raw.get("raw_policy_steps_per_s") if raw and raw["status"] == "ok" else None
        train = rate(idx.get(("time", "gpu", n)))
        rows.append([f"{n:,}", _f(train), _f(raw_rate), _f(train / raw_rate if train and raw_rate else None, ".2f")])
    return rows


def cpu_rows(idx: dict) -> list[list[str]]:
    rows = []
    for (kind, backend, n), r in sorted(idx.items(), key=lambda kv: (kv[0][1], kv[0][2])):
        if kind != "time" or backend != "cpu":
            continue
        cpu = r.get("cpu") or {}
        rows.append([f"{n:,}", r["status"], _f(peak_rss(r), ".2f"), _f(cpu.get("cores_used_mean"), ".2f"),
                     _f(cpu.get("system_busy_cores_mean"), ".2f"), _f(rate(r))])
    return rows


def commands_run(records: list[dict]) -> list[tuple[str, str]]:
    """(command, what it measured) for the commands that produced ``records`` (stale ones and ones that name no
    command left out), in the order they ran (undated last); ``--bundle PATH`` is left out of the command (it only
    says where the device run wrote its copy)."""
    runs: dict[str, list[tuple[dict, str | None]]] = {}
    for r in records:
        if r.get("status") == "stale":
            continue
        # a run trained in several segments (resumed from checkpoints) names each segment's command
        for part in r.get("segments") or [{**r, "date": (r.get("meta") or {}).get("date")}]:
            command = re.sub(r"\s--bundle(?:=|\s+)\S+", "", part.get("part_command") or part.get("command") or "")
            if command.strip():
                runs.setdefault(command.strip(), []).append((r, part.get("date")))

    def first_run(entries: list[tuple[dict, str | None]]) -> tuple[bool, str]:
        dates = [d for _, d in entries if d]
        return (not dates, min(dates, default=""))

    out = []
    for command, entries in sorted(runs.items(), key=lambda kv: first_run(kv[1])):
        rs = [r for r, _ in entries]
        groups: dict[tuple[str, str], list[int]] = {}
        for r in rs:
            groups.setdefault((r["kind"], r["backend"]), []).append(int(r["num_envs"]))
        what = "; ".join(f"{kind} {backend.upper()} at {', '.join(f'{n:,}' for n in sorted(ns))} envs"
                         for (kind, backend), ns in groups.items())
        out.append((command, what))
    return out


def collect_meta(records: list[dict]) -> dict:
    """The machines and software of the results (GPU run's metadata first), plus the commands that made them."""
    gpu_meta = next((r["meta"] for r in records if (r.get("meta") or {}).get("gpu")), None)
    cpu_meta = next((r["meta"] for r in records if r.get("meta") and r["backend"] == "cpu"), None)
    base = gpu_meta or cpu_meta or {}
    dates = sorted(r["meta"]["date"] for r in records if (r.get("meta") or {}).get("date"))
    return {"gpu": base.get("gpu"), "gpu_total_gib": base.get("gpu_total_gib"), "cpu_model": base.get("cpu_model"),
            "available_cores": base.get("available_cores"), "host_ram_gib": base.get("host_ram_gib"),
            "versions": base.get("versions"), "python": base.get("python"), "hosts": sorted(
                {r["meta"]["host"] for r in records if (r.get("meta") or {}).get("host")}),
            "dates": [dates[0], dates[-1]] if dates else [], "commands": [*CHUNKS, REPORT_COMMAND],
            "commands_run": [{"command": c, "measured": w} for c, w in commands_run(records)]}


# ------------------------------------------------------------------------------------------------ figures


def _plt():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    return plt


def _series(idx: dict, kind: str, backend: str, value) -> tuple[list[int], list[float]]:
    points = [(n, value(r)) for (k, b, n), r in idx.items() if k == kind and b == backend]
    points = sorted((n, v) for n, v in points if v is not None)
    return [n for n, _ in points], [v for _, v in points]


def _legend(ax) -> None:
    """A legend where something was drawn (an empty one only warns)."""
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7)


def plot_figures(idx: dict, out: Path) -> list[str]:
    """The four figures; returns the file names written ([] without matplotlib)."""
    plt = _plt()
    if plt is None:
        return []
    written = []

    def save(fig, name: str) -> None:
        fig.tight_layout()
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        written.append(name)

    # (a) training time for 983,040 env-steps
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for backend, label, style in (("gpu", "GPU: mujoco-warp", "o-"), ("cpu", "CPU: C MuJoCo", "s-")):
        xs, ys = _series(idx, "time", backend, time_for_target)
        if xs:
            ax.plot(xs, ys, style, label=label)
    for ref, marker in (("rsl_rl_96", "*"), ("sb3_cpu_8", "X")):
        r = TOCABILAB[ref]
        ax.plot([r["num_envs"]], [r["seconds"]], marker, markersize=11, label=r["label"])
    ax.set(xscale="log", yscale="log", xlabel="parallel envs",
           ylabel=f"training time for {TARGET_ENV_STEPS:,} steps [s]", title="(a) training time vs env count")
    ax.grid(True, which="both", alpha=0.3)
    _legend(ax)
    save(fig, "scaling_time.png")

    # (b) env-steps/s with the raw ceiling
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for kind, backend, label, style in (("time", "gpu", "GPU training", "o-"), ("time", "cpu", "CPU training", "s-"),
                                        ("raw", "gpu", "raw mujoco-warp ceiling", "k--")):
        value = rate if kind == "time" else (lambda r: r.get("raw_policy_steps_per_s") if r["status"] == "ok" else None)
        xs, ys = _series(idx, kind, backend, value)
        if xs:
            ax.plot(xs, ys, style, label=label)
    ax.axhline(TOCABILAB_BEST_RATE, color="tab:red", ls=":", label="TocabiLab best (1,157)")
    ax.set(xscale="log", yscale="log", xlabel="parallel envs", ylabel="env-steps/s",
           title="(b) throughput vs env count")
    ax.grid(True, which="both", alpha=0.3)
    _legend(ax)
    save(fig, "scaling_rate.png")

    # (c) host RAM and GPU memory
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    counts = gpu_counts(idx)
    ok = [n for n in counts if shows_fit(memory_record(idx, n))]
    bad = [n for n in counts if memory_record(idx, n)["status"] in FAILED]
    ax1.plot(ok, [peak_rss(memory_record(idx, n)) for n in ok], "o-", label="GPU runs: peak RSS")
    xs, ys = _series(idx, "time", "cpu", peak_rss)
    if xs:
        ax1.plot(xs, ys, "s-", label="CPU runs: peak RSS")
    ax1.set(xscale="log", xlabel="parallel envs", ylabel="host RAM [GiB]", title="(c) host RAM")
    ax1.set_ylim(bottom=0)
    for label, getter, style in (("device in use (cudaMemGetInfo)", device_used, "o-"),
                                 ("torch peak allocated", torch_peak, "^--")):
        ys = [getter(memory_record(idx, n)) for n in ok]
        pts = [(n, y) for n, y in zip(ok, ys) if y is not None]
        if pts:
            ax2.plot([p[0] for p in pts], [p[1] for p in pts], style, label=label)
    total = next((memory_record(idx, n).get("gpu", {}).get("device_total_gib") for n in ok
                  if (memory_record(idx, n).get("gpu") or {}).get("device_total_gib")), None)
    if total:
        ax2.axhline(total, color="tab:red", ls=":", label=f"device total {total:.0f} GiB")
    for n in bad:
        ax2.plot([n], [total or 0], "rx", markersize=10)
    if bad:
        ax2.plot([], [], "rx", label="did not fit")
    ax2.set(xscale="log", xlabel="parallel envs", ylabel="GPU memory [GiB]", title="(c) GPU memory")
    _legend(ax2)
    for a in (ax1, ax2):
        a.grid(True, which="both", alpha=0.3)
    _legend(ax1)
    save(fig, "scaling_memory.png")

    # (d) CPU utilisation
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    ax.plot(ok, [cores_used(memory_record(idx, n)) for n in ok], "o-", label="GPU training: process cores busy")
    xs, ys = _series(idx, "time", "cpu", cores_used)
    if xs:
        ax.plot(xs, ys, "s-", label="CPU training: process cores busy")
    cores = next((r.get("meta", {}).get("available_cores") for r in idx.values() if r.get("meta")), None)
    if cores:
        ax.axhline(cores, color="tab:red", ls=":", label=f"available cores ({cores})")
    ax.set(xscale="log", xlabel="parallel envs", ylabel="CPU cores busy (CPU time / wall time)",
           title="(d) CPU utilisation during training")
    ax.set_ylim(bottom=0)
    ax.grid(True, which="both", alpha=0.3)
    _legend(ax)
    save(fig, "scaling_cpu.png")
    return written


# ------------------------------------------------------------------------------------------------ markdown


TIME_NOTE = (
    f"*Training time* is TocabiLab's timer: from finished set-up (env, agent and collector built) to the end of the "
    f"last PPO update (`TrainResult.wall_seconds`); *total* adds the process's set-up (imports, CUDA context, env "
    f"construction with warp kernels loaded from the cache, graph capture). *s per {TARGET_ENV_STEPS:,}* is "
    f"{TARGET_ENV_STEPS:,} ÷ env-steps/s: the measured time where exactly {TARGET_ENV_STEPS:,} steps were done, pro "
    "rata where the trainer's whole iterations did more, and extrapolated where a run stopped at its time limit "
    "(status *partial*). A run trained in *segments* (one process per command, each resuming from the checkpoint "
    "the one before saved) adds up the segments' training times and set-ups; its JSON lists each. *Env step*: "
    "whether the env's step (physics, signals, transforms, masked reset) ran as one captured CUDA graph, as the "
    f"default `cuda_graph=\"auto\"` does up to {ENV_GRAPH_AUTO_MAX_ENVS:,} envs (launch-bound there), or eagerly. *vs TocabiLab* is env-steps/s ÷ TocabiLab's best 1,157 (983,040 ÷ 850 s). Steps/env and mini-batch per env count: see Method."
)
RAW_NOTE = (
    "Raw: `raw_policy_steps_per_second` of `benchmarks/sim_throughput.py` (one CUDA graph of a PD kernel and "
    "`mujoco_warp.step` × 8 on the same model), measured by `--part raw` on the same machine."
)
MEMORY_NOTE = (
    "Measured by `--part memory`: 3 PPO iterations per env count, doubling up to the first count that does not "
    "fit, then bisecting between the largest that fit and that one until the two are 8,192 envs apart; an env count without a short "
    "run takes its numbers from its 983,040-step run (*983k run*). Peak RSS is `ru_maxrss` of the measurement's own "
    "process; *device in use* is `cudaMemGetInfo` at the end of training with the env alive (torch keeps its "
    "reserved pool, so this is the peak), *nvidia-smi peak* the highest of samples taken every second; CPU cores "
    "busy = process CPU time ÷ training wall time (sampled every 0.5 s)."
)
def recipe_lines() -> list[str]:
    """The first Method bullets: the recipe every current result was trained with, and the sizing per env count."""
    from scaling import ppo_sizing, recipe

    rec = recipe()
    shown = ", ".join(f"{k}={v}" for k, v in rec.items())
    sizes = []
    for n in (8, 32, 96, 1024, 4096, 16384, 65536):
        steps, minibatch = ppo_sizing(n)
        iterations = -(-TARGET_ENV_STEPS // (n * steps))
        sizes.append(f"{n:,} envs × {steps} steps (mini-batch {minibatch:,}, {iterations} it., "
                     f"{iterations * n * steps:,} steps)")
    return [
        "- Same PPO recipe for every run, the current `preset_config(\"default\")` trained by "
        "`tocabi_torchrl.rl.trainer.train` (training env with the lean rollout of `build_env(for_training=True)`, "
        "no evaluation, no progress bar, one checkpoint at the end). Each result file stores the recipe it ran "
        "with; one trained with another recipe is *stale*: left out here and measured again by the next run of "
        f"its part. Recipe: {shown}.",
        "- Per env count N: the preset's steps per env, but never a rollout below 2,048 transitions, and mini-batches "
        "of a quarter of the rollout capped at the preset's; iterations = ceil(983,040 / rollout): "
        + "; ".join(sizes) + ".",
    ]


METHOD = (
    (
        "- CPU baseline: `device=\"cpu\"`, `backend=\"auto\"` = C MuJoCo on a thread pool over every available "
        "core; its process sees no GPU (`CUDA_VISIBLE_DEVICES=\"\"`), and torch's CPU threads run the policy and "
        "update."
    ),
    (
        "- GPU: mujoco-warp, env, policy, GAE and update on one GPU. Each measurement runs in its own process, so "
        "peak RSS and the torch allocator peaks belong to that configuration alone."
    ),
    (
        "- TocabiLab's numbers (983,040 env-steps; Isaac Lab + rsl_rl at 96 envs: 850 s on an RTX 4070 Ti Super; "
        "CPU MuJoCo + SB3: 1,535 s at 8 envs, failing at 96) are quoted as reported, not re-measured."
    ),
)


def _figure(figures: list[str], name: str, alt: str) -> str:
    return f"![{alt}]({name})" if name in figures else f"*({name}: not drawn, matplotlib missing)*"


def _header(records: list[dict], results_dir: str) -> list[str]:
    meta = collect_meta(records)
    versions = ", ".join(f"{k} {v}" for k, v in (meta.get("versions") or {}).items() if v) or NOT_MEASURED
    machine = f"**{meta['gpu'] or 'GPU ' + NOT_MEASURED}**"
    machine += f" ({meta['gpu_total_gib']:.0f} GiB)" if meta.get("gpu_total_gib") else ""
    machine += f", CPU {meta.get('cpu_model') or NOT_MEASURED}, {meta.get('available_cores') or '?'} cores"
    machine += f", {meta['host_ram_gib']:.0f} GiB RAM" if meta.get("host_ram_gib") else ""
    when = " to ".join(meta["dates"]) if meta["dates"] else NOT_MEASURED
    intro = (f"Every number below comes from the result files in `{results_dir}/` (one fresh process per "
             f"measurement); tables and figures are regenerated with `{REPORT_COMMAND}`. The measurements run on the "
             "GPU machine in chunks of under 10 minutes each (resumable: a finished measurement is skipped):")
    return ["# Efficiency and scalability: TocabiLab's chapter 5 on our system (issue 9)", "",
            f"Machine: {machine}.", f"Software: {versions}. Measured {when}.", "", intro, "",
            *[f"    {c}" for c in CHUNKS], ""]


def _per_env_lines(idx: dict) -> list[str]:
    per_env = gpu_memory_per_env(idx)
    growth = ram_growth(idx)
    points = ", ".join(map(str, per_env["fit_points"])) or "no"
    slope = _f(per_env["slope_mib_per_env"], ".3f", " MiB")
    delta = _f(per_env["delta_1024_16384_mib_per_env"], ".3f", " MiB")
    growth_text = _f(100 * growth if growth is not None else None, "+.1f", " %")
    fixed = _f(per_env["intercept_gib"], ".2f", " GiB")
    if per_env["slope_mib_per_env"] is None:
        memory = f"- GPU memory per env: **{NOT_MEASURED}** (needs the device memory at two env counts >= 1,024)."
    else:
        memory = (f"- GPU memory per env: **{slope}** (least-squares slope of the device memory in use over "
                  f"{points} envs; fixed part {fixed}); from 1,024 to 16,384 envs: {delta} per added env.")
    return [memory, f"- Host RAM growth from 1,024 to 16,384 envs: **{growth_text}** of peak RSS (target < 10 %)."]


def render_markdown(records: list[dict], figures: list[str], results_dir: str) -> str:
    idx = index(records)
    gpu_ns = sorted({n for (k, b, n) in idx if k == "time" and b == "gpu"} | set(PART_COUNTS["gpu_time"]))
    cpu_ns = sorted({n for (k, b, n) in idx if k == "time" and b == "cpu"} | set(PART_COUNTS["cpu_time"]))
    result = {True: "**pass**", False: "**fail**", None: "-"}
    time_header = ["system", "envs", "steps/env / mini-batch", "env step", "env-steps done", "training time [s]",
                   "total incl. set-up [s]", "env-steps/s", f"s per {TARGET_ENV_STEPS:,}", "vs TocabiLab best",
                   "E_core", "E_mem", "status"]
    memory_header = ["envs", "source", "status", "peak RSS [GiB]", "torch peak alloc. [GiB]",
                     "torch peak reserved [GiB]", "device in use [GiB]", "nvidia-smi peak [GiB]", "CPU cores busy",
                     "of available cores", "GPU util", "env-steps/s"]
    cpu_header = ["envs", "status", "peak RSS [GiB]", "process cores busy", "system cores busy", "env-steps/s"]
    lines = [
        *_header(records, results_dir),
        "## Must-show checks", "",
        *_table(["check", "target", "measured", "result"],
                [[c.name, c.target, c.measured, result[c.passed]] for c in checks(records)]), "",
        f"## Training time for {TARGET_ENV_STEPS:,} env-steps", "",
        f"Measured by `--part gpu_time` and `--part cpu_time`. {TIME_NOTE}", "",
        *_table(time_header, time_rows(idx, "gpu", gpu_ns) + time_rows(idx, "cpu", cpu_ns) + tocabilab_rows()), "",
        _figure(figures, "scaling_time.png", "training time vs env count"), "",
        "## Throughput against the raw mujoco-warp ceiling", "", RAW_NOTE, "",
        *_table(["envs", "training env-steps/s", "raw policy steps/s", "train / raw"],
                raw_rows(idx) or [[NOT_MEASURED, "", "", ""]]), "",
        _figure(figures, "scaling_rate.png", "env-steps/s vs env count"), "",
        "## Memory and CPU per env count (GPU)", "", MEMORY_NOTE, "",
        *_table(memory_header, memory_rows(idx) or [[NOT_MEASURED] + [""] * 11]), "",
        _figure(figures, "scaling_memory.png", "host RAM and GPU memory vs env count"), "",
        "CPU backend (983,040-step runs, `--part cpu_time`):", "",
        *_table(cpu_header, cpu_rows(idx) or [[NOT_MEASURED] + [""] * 5]), "",
        _figure(figures, "scaling_cpu.png", "CPU utilisation vs env count"), "",
        "## Per-env cost", "", *_per_env_lines(idx), "",
        "## Efficiency E", "", E_DEFINITION, "",
        "## Method", "", *recipe_lines(), *METHOD, "",
        "## Commands that produced these results", "",
        "On the GPU machine, from the repository root, each followed by `--part unpack` of its bundle here (the "
        "budget and time-limit options size a command to the device's time left; a partial run's rate is "
        "measured over the minutes it ran; `--results /tmp/...` keeps the results outside the repository copy, which "
        "each device call otherwise refreshes from here, so that back-to-back calls see each other's results):", "",
        *_table(["command", "measured"], [[f"`{c}`", w] for c, w in commands_run(records)] or [[NOT_MEASURED, ""]]),
    ]
    return "\n".join(lines) + "\n"


def write_report(results_dir: Path, out_dir: Path) -> str:
    """Write ``scaling.json``, ``scaling.md`` and the figures into ``out_dir``; returns the markdown."""
    results_dir, out_dir = Path(results_dir), Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    records = load_results(results_dir)
    idx = index(records)
    figures = plot_figures(idx, out_dir)
    try:
        shown = results_dir.resolve().relative_to(ROOT)
    except ValueError:
        shown = results_dir
    text = render_markdown(records, figures, str(shown))
    (out_dir / "scaling.md").write_text(text)
    summary = {
        "meta": collect_meta(records), "tocabilab": TOCABILAB, "efficiency_definition": E_DEFINITION,
        "checks": [asdict(c) for c in checks(records)], "per_env": gpu_memory_per_env(idx),
        "host_ram_growth_1024_16384": ram_growth(idx), "figures": figures,
        "results": sorted(records, key=lambda r: (r["kind"], r["backend"], int(r["num_envs"]))),
    }
    (out_dir / "scaling.json").write_text(json.dumps(summary, indent=2, default=str))
    return text


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--results", default=str(DEFAULT_RESULTS))
    parser.add_argument("--out", default=None, help="default: the results folder's parent")
    args = parser.parse_args(argv)
    out = Path(args.out) if args.out else Path(args.results).parent
    print(write_report(Path(args.results), out))


if __name__ == "__main__":
    main()
