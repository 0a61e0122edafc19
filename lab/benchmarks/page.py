"""``python -m lab.benchmarks.page``: write docs/benchmarks.md, the current results on one page, from the committed JSON.

Every section reads one committed report under docs/ and prints what it measured with the command that measured it,
its date and its hardware, all taken from the file. The page is never edited by hand: ``tests/test_benchmark_page.py``
checks that the committed page equals its regeneration, so a new result is a new JSON file plus a section here.
Standard library only: the page renders without torch, mujoco or a GPU.
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import sys
from pathlib import Path
from collections.abc import Callable

from lab.library_table.table import run_date
from tocabi_torchrl.config import preset_now

#: The repository's docs/ folder (the page links relative to it).
DOCS = Path(__file__).resolve().parents[2] / "docs"
PAGE = DOCS / "benchmarks.md"

#: How each kind of kick acts in the robust test (``RobustTestConfig.push_kind``), for this page and
#: robust_policies.py's report; a report made before the test recorded the kind had "force".
KICK_NOTE = {"velocity": "kicks: velocity kicks of the whole robot (every body's velocity changes by the kick's speed)",
             "force": "kicks: a force on the pelvis alone of the same momentum (the test's kicks before they became "
                      "velocity kicks of the whole robot: the limbs lag and the joints are kicked too, a harder push)"}


def kick_note(results: list[dict]) -> str:
    """What the kicks of the policies' reports were (:data:`KICK_NOTE`; a report without ``push_kind`` had force)."""
    return "; ".join(KICK_NOTE[k] for k in sorted({r.get("push_kind", "force") for r in results}))


HEADER = """# Benchmarks

Current results, one section per measurement. Each names the committed report it is generated from, the command
that measured it, the date and the hardware. Ratios "x raw" divide by raw `mujoco_warp.step` of the same model
measured in the same run (one CUDA graph of 8 physics substeps of 0.5 ms plus a leg PD hold): a policy step is 8
substeps. Commands are as they were run; the benchmark scripts now live in `lab/benchmarks/`
(`python -m lab.benchmarks.<name>`), and `python -m lab.benchmarks.regenerate` re-renders each detail page from
its JSON. This page is written by `python -m lab.benchmarks.page` from the same files (do not edit it by hand)."""


#: The reports the section being rendered has read so far (docs-relative), for :func:`render`'s error message.
_READ: list[str] = []


def _load(rel: str, docs: Path) -> dict | list:
    _READ.append(rel)
    return json.loads((docs / rel).read_text())


def _k(x: float) -> str:
    """An env-steps/s rate: in thousands from 10,000 on (``129k``), else whole (``877``)."""
    return f"{x / 1000:,.0f}k" if x >= 10_000 else f"{x:,.0f}"


def _source(rel: str, command: str, date: str, hardware: str, detail: str | None = None) -> list[str]:
    link = f"[{Path(rel).name}]({rel})" + (f", [details]({detail})" if detail else "")
    return [f"- command: `{command}`", f"- date: {date}; hardware: {hardware}; report: {link}"]


def env_throughput(docs: Path) -> list[str]:
    d = _load("benchmarks/env_throughput.json", docs)
    m = d["meta"]
    rows = ["| envs | raw policy steps/s | `TocabiWalk` step | env / raw | `make_env` / raw | transforms' share |",
            "|---:|---:|---:|---:|---:|---:|"]
    rows += [f"| {r['num_envs']:,} | {_k(r['raw_policy_steps_per_s'])} | {_k(r['env_steps_per_s'])} | "
             f"{r['env_over_raw']:.3f} | {r['make_env_over_raw']:.3f} | "
             f"{100 * r['transform_share_of_env_step']:.1f} % |"
             for r in d["results"]]
    return ["## Environment step vs raw mujoco-warp", "", *rows, "",
            *_source("benchmarks/env_throughput.json", m["command"], m["date"], m["gpu"],
                     "benchmarks/env_throughput.md")]


def train_throughput(docs: Path) -> list[str]:
    d, mem = _load("benchmarks/train_throughput.json", docs), _load("benchmarks/train_throughput_16k_memfix.json", docs)
    rows = ["| envs | training env-steps/s | raw policy steps/s | train / raw | peak GPU memory |",
            "|---:|---:|---:|---:|---:|"]
    rows += [f"| {r['num_envs']:,} | {_k(r['train_env_steps_per_s'])} | {_k(r['raw_policy_steps_per_s'])} | "
             f"{r['ratio_train_over_raw']:.2f} | {r['device_peak_used_gib']:.1f} GiB |" for r in d["results"]]
    r = mem["results"][0]
    rows.append(f"| {r['num_envs']:,} (second run) | {_k(r['train_env_steps_per_s'])} | "
                f"{_k(r['raw_policy_steps_per_s'])} | {r['ratio_train_over_raw']:.2f} | "
                f"{r['device_peak_used_gib']:.1f} GiB |")
    big = _load("benchmarks/train_throughput_131k.json", docs)
    r = big["results"][0]
    rows.append(f"| {r['num_envs']:,} ({r['device_name']}) | {_k(r['train_env_steps_per_s'])} | "
                f"{_k(r['raw_policy_steps_per_s'])} | {r['ratio_train_over_raw']:.2f} | "
                f"{r['device_peak_used_gib']:.1f} GiB ({1024 * r['device_peak_used_gib'] / r['num_envs']:.2f} MiB "
                "per env) |")
    m, mm, mb = d["meta"], mem["meta"], big["meta"]
    return ["## PPO training throughput (default preset, collection + update)", "", *rows, "",
            *_source("benchmarks/train_throughput.json", m["command"], m["date"], m["gpu"],
                     "benchmarks/train_throughput.md"),
            *_source("benchmarks/train_throughput_16k_memfix.json", mm["command"], mm["date"], mm["gpu"]),
            *_source("benchmarks/train_throughput_131k.json", mb["command"], mb["date"], mb["gpu"],
                     "benchmarks/train_throughput_131k.md"),
            f"- The {r['num_envs']:,}-env row: {r['iterations']} iterations of an untrained policy and a short raw "
            "measurement, a check that so many envs train on one GPU (torch itself peaked at "
            f"{r['torch_peak_allocated_gib']:.1f} GiB allocated, {r['torch_peak_reserved_gib']:.1f} GiB reserved; "
            "the rest is mujoco-warp's), not a steady rate. The raw column steps standing robots; the untrained "
            "robots fall and reset, so a train / raw above 1 breaks no ceiling."]


def several_gpus(docs: Path) -> list[str]:
    out = ["## Several GPUs of one host (data-parallel, 4,096 envs per GPU)", "",
           "| GPU | gradient exchange | 1 GPU env-steps/s | 2 GPUs env-steps/s | speed-up |",
           "|---|---|---:|---:|---:|"]
    sources = []
    for rel, how in (("benchmarks/multi_gpu.json", "all-reduce captured in the update"),
                     ("benchmarks/multi_gpu_h200.json", "all-reduce captured in the update"),
                     ("benchmarks/multi_gpu_h200_ddp.json", "torch DDP, eager update")):
        d = _load(rel, docs)
        by = {r["gpus"]: r["train_env_steps_per_s"] for r in d["results"]}
        out.append(f"| {d['meta']['gpu']} | {how} | {_k(by[1])} | {_k(by[2])} | {by[2] / by[1]:.2f}x |")
        sources += _source(rel, d["meta"]["command"], d["meta"]["date"], f"{d['meta']['gpu']} (one host)")
    return [*out, "", *sources]


def _ratio(r: dict) -> str:
    """A run's train / raw cell: "–" where its raw ceiling was not measured (trained with ``--raw_steps 0``)."""
    return "–" if r.get("train_over_raw") is None else f"{r['train_over_raw']:.2f}"


def _require(r: dict, fields: tuple[str, ...], rel: str) -> None:
    """Raise ``ValueError`` naming ``docs/<rel>``, the run and each of ``fields`` that its record ``r`` lacks."""
    missing = [f for f in fields if f not in r]
    if missing:
        run = r.get("name", r.get("preset", "?"))
        date = (" (the date: the day its training last ran, as time_to_walk train records it)"
                if "date" in missing else "")
        raise ValueError(f"docs/{rel}: the record of run {run!r} has no {', '.join(map(repr, missing))}, which this "
                         f"page shows{date}: add it to the run's train.json and render the report again")


def _preset_then(name: str, date: str) -> str:
    """``name`` as a table cell, with its name now where a run of before a rename trained it."""
    now = preset_now(name, date)
    return f"`{name}` (now `{now}`)" if now != name else f"`{name}`"


def time_to_walk(docs: Path) -> list[str]:
    rel = "benchmarks/time_to_walk.json"
    d = _load(rel, docs)
    rows = ["| preset | GPUs | envs per GPU | first passes the gait test at | env steps | train / raw | date |",
            "|---|---|---:|---:|---:|---:|---|"]
    cmds = []
    for r in d["records"]:
        # Every row carries its date (the page's rule); a record from an older train.json may lack it.
        _require(r, ("preset", "gpu", "config", "train_seconds", "commands", "date"), rel)
        gpus = f"{r.get('gpus', 1)} x {r['gpu']}"
        envs = r["config"].get("env", {}).get("num_envs") or r["config"].get("num_envs")
        ttw = r["time_to_walk"]
        walks = (f"**{ttw['train_minutes']:.1f} min**" if ttw
                 else f"not yet when the run ended ({r['train_seconds'] / 60:.1f} min)")
        steps = f"{ttw['env_steps'] / 1e6:.0f} M" if ttw else "–"
        rows.append(f"| {_preset_then(r['preset'], r['date'])} | {gpus} | {envs:,} | {walks} | {steps} | {_ratio(r)} "
                    f"| {r['date']} |")
        train = r["commands"][0] if isinstance(r["commands"], list) else r["commands"]
        now = preset_now(r["preset"], r["date"])
        again = f" (now `--preset {now}`)" if now != r["preset"] else ""
        cmds.append(f"- `{r.get('name', r['preset'])}`: `{train}`{again}")
    return ["## Time to walk (training minutes until a checkpoint passes the 8 s gait test)", "",
            "Checkpoints are gait-tested every 2 training minutes (256 robots, command (0.5, 0) m/s, 8 s).", "",
            *rows, "", "Training commands (the first of each run):", "", *cmds, "",
            f"- report: [time_to_walk.json](benchmarks/time_to_walk.json), "
            f"[details and curves](benchmarks/time_to_walk.md); rendered by `{d['command'].split(' --runs')[0]}`",
            "", *_test_time_to_walk(docs, ROBUST_TIME_TO_WALK, _ROBUST_TEST), "",
            *[line for report in (*TORQUE_TIME_TO_WALK, MODEL_BASED_TIME_TO_WALK, PD_TIME_TO_WALK)
              for line in (*_test_time_to_walk(docs, report, _DIVERSE_TEST), "")][:-1]]


#: The robust preset's time to walk under the robust gait test (docs/evaluation.md), one run's report.
ROBUST_TIME_TO_WALK = "training/robust/h100_run23/time_to_walk_robust.json"
#: The torque preset's time to walk under the robust gait test's unperturbed cases, one run's report per seed.
TORQUE_TIME_TO_WALK = ("training/torque/h100_base_vel_seed0/time_to_walk_diverse.json",
                       "training/torque/h100_base_vel_seed1/time_to_walk_diverse.json")
#: The model_based preset's, under the same cases. Its run set the preset's recipe on the command line over the
#: ``robust`` preset, before the preset was that recipe (tests/test_config_tree.py checks the two agree).
MODEL_BASED_TIME_TO_WALK = "training/model_based/h100_robust_seed0/time_to_walk_diverse.json"
#: The pd preset's, under the same cases; its run too set the preset's recipe over the ``robust`` preset.
PD_TIME_TO_WALK = "training/pd/h100_seed0/time_to_walk_diverse.json"
#: What the page says of a run whose record names another preset than the one whose recipe it trained.
RECIPE_NOTES = {MODEL_BASED_TIME_TO_WALK: "with the overrides below, the `model_based` preset's recipe",
                PD_TIME_TO_WALK: "with the overrides below, the `pd` preset's recipe"}
#: The section's reports of single runs, beside docs/benchmarks/time_to_walk.json.
RUN_TIME_TO_WALK = (ROBUST_TIME_TO_WALK, *TORQUE_TIME_TO_WALK, MODEL_BASED_TIME_TO_WALK, PD_TIME_TO_WALK)
_ROBUST_TEST = "the robust gait test (diverse starts, changing commands, the `tocabi_lab` randomisation and kicks"
_DIVERSE_TEST = ("the robust gait test's `nominal` and `commands` cases (diverse starts, changing commands; no "
                 "randomisation, no kicks")


def _test_time_to_walk(docs: Path, rel: str, test: str) -> list[str]:
    """One run's time to walk under ``test`` (words up to the robots per case), from its report ``rel``."""
    d = _load(rel, docs)
    lines, note = [], f"{RECIPE_NOTES[rel]}; " if rel in RECIPE_NOTES else ""
    for r in d["records"]:
        ttw = r["time_to_walk"]
        walks = (f"**{ttw['train_minutes']:.1f} min** ({ttw['env_steps'] / 1e6:.0f} M env steps)" if ttw
                 else f"not within its {r['train_seconds'] / 60:.1f} minutes")
        envs = r["config"]["env"]["num_envs"]
        robots = sorted({e["settings"]["num_envs"] for e in r["evaluations"].values()})
        lines.append(f"Under {test}; {'/'.join(f'{n:,}' for n in robots)} robots per case; checkpoints from "
                     f"{min(e['train_seconds'] for e in r['evaluations'].values()) / 60:.1f} training minutes on), "
                     f"`{r['preset']}` ({note}seed {r['config']['seed']}) on "
                     f"{r.get('gpus', 1)} x {r['gpu']} at {envs:,} envs, trained {r['date']}, first passes at {walks}"
                     + ("." if r.get("train_over_raw") is None else
                        f", training at {r['train_over_raw']:.2f}x raw mujoco-warp."))
        lines.append("")
        lines += [f"- training command: `{c}`" for c in r["commands"]]
    md = rel.replace(".json", ".md")
    return [*lines, f"- report: [{Path(rel).name}]({rel}), [table and curve]({md}), rendered by `{d['command']}`"]


def library_table(docs: Path) -> list[str]:
    d = _load("adapters_table.json", docs)
    rows = ["| library | version | preset | envs | env-steps/s | walks at (training min) | GPU | date |",
            "|---|---|---|---:|---:|---:|---|---|"]
    for r in sorted(d, key=lambda r: (r["preset"] != "default", r["library"], r["num_envs"])):
        walks = f"{r['walks_minutes']:.1f}" if r.get("walks_minutes") else f"no (within {r['cap_minutes']:.0f})"
        date = run_date(r)
        ran = r.get("preset_then", r["preset"])  # a table call may have saved a renamed row under its name now
        rows.append(f"| {r['library']} | {r['version']} | {_preset_then(ran, date)} | {r['num_envs']:,} | "
                    f"{_k(r['env_steps_per_s'])} | {walks} | {r['device']} | {date} |")
    return ["## Other RL libraries on the same task (one GPU per row, 30-minute cap)", "", *rows, "",
            "- command: `python -m lab.library_table --libraries LIB --preset PRESET --num_envs N` "
            "(every row's own commands: [adapters_table.md](adapters_table.md))",
            "- report: [adapters_table.json](adapters_table.json)"]


def mjlab_peer(docs: Path) -> list[str]:
    d = _load("benchmarks/mjlab_peer.json", docs)
    theirs, ours = d["results"][0], d["ours"]["result"]
    rows = ["| trainer | task | env-steps/s | its raw mujoco-warp | train / raw |", "|---|---|---:|---:|---:|",
            f"| mjlab {d['meta']['versions'].get('mjlab', '')} | {d['meta']['task']} | "
            f"{_k(theirs['train_env_steps_per_s'])} | {_k(theirs['raw_policy_steps_per_s'])} | "
            f"{theirs['ratio_train_over_raw']:.2f} |",
            f"| tocabi-torchrl | TOCABI walking, default preset | {_k(ours['train_env_steps_per_s'])} | "
            f"{_k(ours['raw_policy_steps_per_s'])} | {ours['ratio_train_over_raw']:.2f} |"]
    m, om = d["meta"], d["ours"]["meta"]
    return ["## Peer: mjlab's training at 4,096 envs against its own raw mujoco-warp", "", *rows, "",
            *_source("benchmarks/mjlab_peer.json", m["command"], m["date"], m["gpu"], "benchmarks/mjlab_peer.md"),
            *_source("benchmarks/mjlab_peer_ours.json", om["command"], om["date"], om["gpu"])]


def scaling(docs: Path) -> list[str]:
    d = _load("benchmarks/scaling.json", docs)
    m = d["meta"]
    rows = ["| check | target | measured |", "|---|---|---|"]
    rows += [f"| {c['name']} | {c['target']} | {c['measured']} |" for c in d["checks"]]
    cmd = "; ".join(f"`{c}`" for c in m["commands"])
    return ["## TocabiLab's benchmark: 983,040 env steps, scaling and memory", "", *rows, "",
            f"- commands: {cmd}",
            f"- dates: {m['dates'][0][:10]} to {m['dates'][-1][:10]}; hardware: {m['gpu']}, "
            f"{m['available_cores']} CPU cores; report: [scaling.json](benchmarks/scaling.json), "
            "[details](benchmarks/scaling.md)"]


def randomization(docs: Path) -> list[str]:
    d = _load("benchmarks/randomization/train_throughput.json", docs)
    rows = ["| what is randomised (the perfect-robot torque preset, now `torque_ideal`) | env-steps/s "
            "| over nothing randomised |", "|---|---:|---:|"]
    rows += [f"| {r['what']} | {_k(r['train_env_steps_per_s'])} | {r['over_plain']:.2f} |" for r in d["results"]]
    m = d["meta"]
    latest = [*preset_cost(docs), *(randomization_cost(docs) if (docs / RANDOMIZATION_COST).is_file() else [])]
    earlier = ["Per piece, an earlier measurement (each piece switched on alone, before the start pool):", ""]
    return ["## The cost of randomisation in training", "", *latest, *(earlier if latest else []), *rows, "",
            f"- command: `{d['results'][-1]['command']}` (each row's own in the report)",
            f"- date: {m['date']}; hardware: {m['gpu']}, {m['num_envs']:,} envs; report: "
            "[train_throughput.json](benchmarks/randomization/train_throughput.json)", "", *step_ops(docs), "",
            *substep_iterations(docs), *averaged_delay(docs)]


def averaged_delay(docs: Path) -> list[str]:
    """The shipped robust policy under the lab's delay per substep and averaged (lab/analysis/averaged_delay.py),
    when that report exists."""
    name = "benchmarks/randomization/averaged_delay.json"
    if not (docs / name).is_file():
        return []
    d = _load(name, docs)
    m = d["meta"]
    rows = ["| kicks | torque delay | survival | robots whose outcome differs from the first row's | forward "
            "distance [m] | lateral drift [m] |", "|---:|---|---:|---:|---:|---:|"]
    rows += [f"| {r['kick_speed_mps']:g} m/s | {r['variant']} | {r['survival']:.3f} | {r['outcomes_changed']} | "
             f"{r['forward_distance_m']:.2f} | {r['lateral_drift_m']:.2f} |" for r in d["results"]]
    return ["", "Whether a policy meets the same robot when the delay is averaged over each period "
            f"(`env.control.actuators.delay_average`): {RUN9_POLICY}, trained with the delay per substep, "
            f"on C MuJoCo under the robust test's pushed cases, {m['num_robots']} robots, every draw alike between "
            "the rows of a kick speed (the third row: the per-substep delay with the start joint angles offset by "
            "1e-6 rad, how many outcomes a meaningless difference changes in a chaotic gait):", "", *rows, "",
            f"- command: `{d['command']}`",
            f"- date: {m['date']}; hardware: {m['hardware']}; report: [{Path(name).name}]({name})"]


RANDOMIZATION_COST = "benchmarks/randomization/randomization_cost.json"


def randomization_cost(docs: Path) -> list[str]:
    """The issue's measure: the preset with everything on against the same preset with every piece at its identity,
    alternating rounds in one run (lab/benchmarks/randomization_cost.py)."""
    d = _load(RANDOMIZATION_COST, docs)
    m, s = d["meta"], d["summary"]
    rows = ["| round | seed | variant | train env-steps/s | train / raw standing |", "|---:|---:|---|---:|---:|"]
    rows += [f"| {r['round']} | {r.get('seed', 0)} | {r['variant']} | {_k(r['train_env_steps_per_s'])} | "
             + ("-" if r.get("ratio_train_over_raw") is None else f"{r['ratio_train_over_raw']:.2f}") + " |"
             for r in d["results"]]
    how = (f"the median of {m['rounds']} rounds' own ratios, each round a seed of its own"
           if "round_on_over_off" in s else f"medians of {m['rounds']} alternating rounds")
    verdict = "meets" if s["on_over_off"] >= 0.95 else "misses"
    split = _pieces_and_physics(d, RANDOMIZATION_COST.removesuffix(".json") + ".md")
    if not split and (docs / RANDOMIZATION_PIECES).is_file():
        # The latest run has no per-piece split; the last one that had shows where the gap came from then.
        p = _load(RANDOMIZATION_PIECES, docs)
        pm = p["meta"]
        split = [f"Piece by piece, an earlier run ({pm['date']}, {pm['gpu']}, {pm['num_envs']:,} envs, seed 0, one "
                 f"round: on / off {p['summary']['on_over_off']:.3f}x; `{pm['command']}`):", "",
                 *_pieces_and_physics(p, RANDOMIZATION_PIECES.removesuffix(".json") + ".md")]
    return [f"With everything of the `{m['preset']}` preset of {m['date']} on (dynamics, actuators, sensor noise, "
            f"kicks at full strength, diverse starts), training runs at **{s['on_over_off']:.3f}x** the same preset "
            f"with every piece at its identity ({how}, {m['num_envs']:,} envs); this {verdict} the 0.95x target.", "",
            *rows, "",
            *_source(RANDOMIZATION_COST, m["command"], m["date"], m["gpu"],
                     "benchmarks/randomization/randomization_cost.md"), "", *split, *delay_average_cost(docs),
            *solver_cap_cost(docs), *envs_16k_cost(docs)]


#: The last ``randomization_cost`` run with ``--pieces`` and ``--physics`` (each piece alone; the solver's share).
RANDOMIZATION_PIECES = "benchmarks/randomization/pieces_2026-12-03.json"


def _pieces_and_physics(d: dict, detail: str) -> list[str]:
    """A ``randomization_cost`` report's per-piece ratios and physics split, when it measured them."""
    m, s = d["meta"], d["summary"]
    ms = {name: v["ms_per_policy_step"] for name, v in d.get("physics", {}).items()}
    pieces = [f"- `{name}` alone over none: {ratio:.3f}x in training"
              + (f", physics {ms['off'] / ms[f'off+{name}']:.3f}x" if f"off+{name}" in ms and "off" in ms else "")
              for name, ratio in s.get("piece_over_off", {}).items()]
    physics = []
    if "physics_off_over_on" in s and {"on", "off"} <= ms.keys():
        # Each variant's own training states replayed through raw mujoco-warp (eager steps): the solver's share of the
        # gap. With the rest of a training step as long as off's, on / off would be off's step over off's rest plus
        # on's physics.
        step_off, n = 1.0 / s["off_median"], m["num_envs"]
        same_rest = step_off / (step_off - ms["off"] * 1e-3 / n + ms["on"] * 1e-3 / n)
        physics = [f"The physics alone (raw mujoco-warp replaying each variant's own training states, eager steps, "
                   f"`--physics`): off / on = **{s['physics_off_over_on']:.3f}**: the solver works harder on the "
                   f"states a randomised robot visits. Were the rest of a training step as long as off's, on / off "
                   f"would be {same_rest:.3f}; the randomisation's own work is the remaining "
                   f"{same_rest - s['on_over_off']:.3f} ([details]({detail})).", ""]
    return [*pieces, *([""] if pieces else []), *physics]


DELAY_AVERAGE_COST = "benchmarks/randomization/delay_average_cost"
#: ``randomization_cost --rounds 3`` of the preset with the averaged delay.
DELAY_AVERAGE_THREE_ROUNDS = f"{DELAY_AVERAGE_COST}/three_rounds.json"


SOLVER_CAP_COST = "benchmarks/randomization/solver_cap_cost"
#: ``randomization_cost --rounds 3`` of the preset with the solver capped at 4 iterations.
SOLVER_CAP_THREE_ROUNDS = f"{SOLVER_CAP_COST}/three_rounds.json"
#: From-scratch runs of the preset with the solver capped (time_to_walk records of the robust test), in order.
SOLVER_CAP_RUNS = ("training/robust/h200_run12/time_to_walk_robust.json",
                   "training/robust/h200_run13/time_to_walk_robust.json",
                   "training/robust/h200_run14/time_to_walk_robust.json",
                   "training/robust/h200_run15/time_to_walk_robust.json",
                   "training/robust/h200_run16/time_to_walk_robust.json",
                   "training/robust/h200_run17/time_to_walk_robust.json",
                   "training/robust/h100_run19/time_to_walk_robust.json",
                   "training/robust/h100_run20/time_to_walk_robust.json")


ENVS_16K = "benchmarks/randomization/envs_16k"
#: ``randomization_cost`` at 16,384 envs: (report, how the delay is drawn).
ENVS_16K_REPORTS = ((f"{ENVS_16K}/delay_every_substep.json", "the delay on every substep, as the preset"),
                    (f"{ENVS_16K}/delay_1ms_grid.json",
                     "the delay on a 1 ms grid (`env.control.actuators.delay_stride=2`)"),
                    (f"{ENVS_16K}/robust_16k_stride2_spe12.json",
                     "the delay on a 1 ms grid and 12 steps per env (`ppo.steps_per_env=12`)"))


#: The ``randomization_cost`` report of the committed ``robust`` preset's configuration. It was run with the preset's
#: env count, delay grid and steps per env on its command line, before they became the preset's values; the preset's
#: other values since (the KL target, the held rate's bound) set the size of the optimiser's steps, not an
#: iteration's work.
PRESET_COST = f"{ENVS_16K}/robust_16k_stride2_spe12.json"
#: The from-scratch run of the committed ``robust`` preset that passed the robust gait test.
PRESET_RUN = "training/robust/h100_run23/README.md"


def preset_cost(docs: Path) -> list[str]:
    """The issue's measure for the committed ``robust`` preset (everything on against every piece at its identity,
    the same run), when its report is committed."""
    if not (docs / PRESET_COST).is_file():
        return []
    d = _load(PRESET_COST, docs)
    m, s = d["meta"], d["summary"]
    rounds = ", ".join(f"{r:.3f}" for r in s["round_on_over_off"])
    verdict = "meets" if s["on_over_off"] >= 0.95 else "misses"
    return [f"With everything of the committed `{m['preset']}` preset on (dynamics, actuators, sensor noise, kicks at "
            f"full strength, diverse starts; {m['num_envs']:,} envs), training runs at **{s['on_over_off']:.3f}x** "
            f"the same preset with every piece at its identity (the median of {m['rounds']} rounds' own ratios, each "
            f"round a seed of its own: {rounds}; on {_k(s['on_median'])} against off {_k(s['off_median'])} "
            f"env-steps/s); this {verdict} the 0.95x target. It was measured with the preset's env count, delay grid "
            "and steps per env on the command line, before they became its values; of its values since, the KL "
            "target and the held rate's bound (`ppo.desired_kl`, `ppo.assist_lr_max`) set the size of the "
            f"optimiser's steps, not an iteration's work. Its from-scratch run: [run 23]({PRESET_RUN}).", "",
            *_source(PRESET_COST, m["command"], m["date"], m["gpu"], PRESET_COST.removesuffix(".json") + ".md"), ""]


def envs_16k_cost(docs: Path) -> list[str]:
    """The preset's cost at 16,384 envs, with the delay on every substep and on a 1 ms grid, when committed."""
    lines = []
    for path, how in (r for r in ENVS_16K_REPORTS if (docs / r[0]).is_file()):
        d = _load(path, docs)
        m, s = d["meta"], d["summary"]
        rounds = ", ".join(f"{r:.3f}" for r in s["round_on_over_off"])
        lines.append(f"- At {m['num_envs']:,} envs with {how}: **{s['on_over_off']:.3f}x** ({m['rounds']} rounds, "
                     f"seeds {', '.join(map(str, m['seeds']))}: {rounds}; {m['date']}, {m['gpu']}; "
                     f"[report]({path.removesuffix('.json')}.md)).")
    if lines:
        lines += [f"- The preset takes the last row's settings with a KL target of 0.02 and the held rate bounded at "
                  f"7.5e-5: its from-scratch run passed the robust gait test from 13 training minutes ([run 23]"
                  f"({PRESET_RUN})). Without those two, runs at 16,384 envs with 48 and with 12 steps per env fell "
                  f"four to twenty times as often per env step as the preset at 4,096 did and were stopped at 8 "
                  f"minutes ([details]({ENVS_16K}/README.md)).", ""]
    return lines


def solver_cap_cost(docs: Path) -> list[str]:
    """The three-round cost of the preset with the solver capped, when it is committed."""
    if not (docs / SOLVER_CAP_THREE_ROUNDS).is_file():
        return []
    d = _load(SOLVER_CAP_THREE_ROUNDS, docs)
    m, s = d["meta"], d["summary"]
    rounds = ", ".join(f"{r:.3f}" for r in s["round_on_over_off"])
    return [f"With the solver capped at 4 iterations per substep (the preset plus `env.sim.solver_iterations: 4`), "
            f"{m['rounds']} rounds (seeds {', '.join(map(str, m['seeds']))}: {rounds}) gave "
            f"**{s['on_over_off']:.3f}x**, on {_k(s['on_median'])} against off {_k(s['off_median'])} env-steps/s "
            f"({m['date']}, {m['gpu']}; [details]({SOLVER_CAP_COST}/README.md)). The preset keeps the model's "
            "solver until a from-scratch run with the cap passes the robust gait test.", *_capped_runs(docs),
            *_screened_runs(docs), *_symmetric_copy(docs), ""]


#: From-scratch runs of the capped preset whose marks were screened and went to no verdict: (screen report, README).
SOLVER_CAP_SCREENED = (("training/robust/h200_run18/screen_gpu/robust_policies.json",
                        "training/robust/h200_run18/README.md", "`ppo.symmetry=equivariant`"),)


def _screened_runs(docs: Path) -> list[str]:
    """One line per committed capped run that a screen stopped before the full test."""
    lines = []
    for report, readme, also in (r for r in SOLVER_CAP_SCREENED if (docs / r[0]).is_file()):
        d = _load(report, docs)
        m, results = d["meta"], d["results"]
        kept = [r["cases"]["nominal"]["survival"] for r in results]
        kicks = [r["cases"]["robust_1.0"]["survival"] for r in results]
        lines.append(f"- The capped preset's from-scratch run with {also} went to no verdict: a screen of "
                     f"{len(results)} marks ({m['num_envs']:,} robots per case; {m['date']}, {m['gpu']}) kept "
                     f"{min(kept):.2f}-{max(kept):.2f} of the robots up in `nominal` and {min(kicks):.2f}-"
                     f"{max(kicks):.2f} under the 1.0 m/s kicks: [README]({readme}).")
    return lines


#: The full robust test of run 12's 16-minute mark made symmetric after training (lab/analysis/symmetrize.py).
SYMMETRIC_COPY = "training/robust/symmetrized/gpu_verdict_run12/robust_policies.json"


def _symmetric_copy(docs: Path) -> list[str]:
    """One line for the verdict of run 12's symmetric copy, when it is committed."""
    if not (docs / SYMMETRIC_COPY).is_file():
        return []
    d = _load(SYMMETRIC_COPY, docs)
    m, r = d["meta"], d["results"][0]
    c = r["cases"]
    verdict = "passes" if r["passes"] else "does not pass"
    return [f"- Run 12's 16-minute mark made left-right symmetric after training {verdict} the whole robust test "
            f"({m['num_envs']:,} robots per case: `nominal` drift p95 {c['nominal']['lateral_drift_m.p95']:.4f} m, "
            f"`robust_1.0` survival {c['robust_1.0']['survival']:.3f}; {m['date']}, {m['gpu']}; "
            "[details](training/robust/symmetrized/README.md)). `ppo.symmetric_policy` makes such a copy a run's "
            "policy; the from-scratch run with it and the cap (`robust_v19`, above) did not pass, so the preset "
            "takes neither."]


def _set_items(overrides: dict, skip: tuple[str, ...] = ()) -> str:
    """``overrides`` {path: value} as the ``--set`` items that gave them, each in backticks (a switch as true or
    false), those of ``skip`` left out.

    >>> _set_items({"ppo.overlap_update": True, "ppo.lr": 1e-4, "seed": 2}, skip=("seed",))
    '`ppo.overlap_update=true` `ppo.lr=0.0001`'
    """
    return " ".join(f"`{k}={str(v).lower() if isinstance(v, bool) else v}`" for k, v in overrides.items()
                    if k not in skip)


def _capped_runs(docs: Path) -> list[str]:
    """One line per committed from-scratch run of the capped preset: its verdict at the marks it tested."""
    lines = []
    for path in (p for p in SOLVER_CAP_RUNS if (docs / p).is_file()):
        record = _load(path, docs)["records"][0]
        # A mark by its checkpoint's name (wall_00750s: 12.5 min), not its train_seconds, which run a little past it;
        # config.wall_seconds parsed here, the page being standard library only.
        marks = sorted(int(stem[len("wall_"):-1]) for stem in record["evaluations"])
        tested = ", ".join(f"{seconds / 60:g}" for seconds in marks)
        walk, trained = record["time_to_walk"], f"{record['train_seconds'] / 60:.1f}"
        verdict = (f"passes at {walk['train_minutes']:.1f} training minutes" if walk else
                   f"does not pass at the marks in its record ({tested} training minutes, of {trained})" if marks
                   else f"has no tested mark in its record ({trained} training minutes)")
        extra = _set_items(record.get("overrides", {}), skip=("env.sim.solver_iterations",))
        also = f"; also {extra}" if extra else ""
        lines.append(f"- The capped preset's from-scratch run `{record['name']}` ({record['gpu']}{also}) {verdict}: "
                     f"[README]({path.rsplit('/', 1)[0]}/README.md).")
    return lines


def delay_average_cost(docs: Path) -> list[str]:
    """The averaged delay's one-round ratios, seed by seed (``rounds/rc_seed*.md``), and its three-round run, when
    they are committed."""
    reports = sorted((docs / DELAY_AVERAGE_COST / "rounds").glob("rc_seed*.md"),
                     key=lambda p: int(p.stem.removeprefix("rc_seed")))
    ratios = {int(p.stem.removeprefix("rc_seed")): float(re.search(r"on / off = \*\*([0-9.]+)\*\*", p.read_text())[1])
              for p in reports}
    three = []
    if (docs / DELAY_AVERAGE_THREE_ROUNDS).is_file():
        d = _load(DELAY_AVERAGE_THREE_ROUNDS, docs)
        m, s = d["meta"], d["summary"]
        rounds = ", ".join(f"{r:.3f}" for r in s["round_on_over_off"])
        seeds = ", ".join(map(str, m["seeds"]))
        three = [f"On the code of the figure above, the averaged delay's {m['rounds']} rounds in one run "
                 f"(seeds {seeds}: {rounds}) gave **{s['on_over_off']:.3f}x**, which "
                 f"{'meets' if s['on_over_off'] >= 0.95 else 'misses'} the target "
                 f"([three_rounds.md]({DELAY_AVERAGE_THREE_ROUNDS.removesuffix('.json')}.md); "
                 f"{m['date']}, {m['gpu']}).", ""]
    if not ratios:
        return three
    seeds = ", ".join(f"{seed}: {r:.3f}" for seed, r in ratios.items())
    # The rest of the step (all but the physics), on over off, in the 10-iteration timelines of each seed.
    rest = {}
    for path in (docs / DELAY_AVERAGE_COST / "timelines").glob("tl10_*_s*.json"):
        r = json.loads(path.read_text())["results"][0]
        variant, seed = path.stem.split("_")[1:]
        rest.setdefault(seed, {})[variant] = r["step_ms"] - r["ms_per_policy_step"]["physics (sim.step)"]
    extra = [v["on"] - v["off"] for v in rest.values() if {"on", "off"} <= v.keys()]
    split = ("Step timelines split the gap into the physics, which follows the robots' motion, and a steady "
             f"+{statistics.mean(extra):.2f} ms of small kernels" if extra else "Step timelines split the gap")
    return [f"With the delay averaged over each policy step (`env.control.actuators.delay_average`, not in the preset "
            f"yet), one round per seed gave on / off {seeds} (median {statistics.median(ratios.values()):.3f}): a "
            "seed's round is one sample of how hard its untrained robots' physics is, hence the rounds of different "
            f"seeds. {split} ([details]({DELAY_AVERAGE_COST}/README.md)).", "", *three]


def step_ops(docs: Path) -> list[str]:
    d = _load("benchmarks/randomization/step_ops.json", docs)
    m, before = d["meta"], d["meta"].get("before")  # the earlier count's column, where the report has one
    count = lambda v: "-" if v is None else f"{v:,.0f}"
    kernels = "kernels_per_step" in d["results"][0]  # reports from before the kernel count have ops only
    head = "| switched on | torch ops per env step |" + (" of them kernels |" if kernels else "")
    head += (f" at {before['code']}: ops |" + (" kernels |" if kernels else "")) if before else ""
    rows = [head, "|---|" + "---:|" * (head.count("|") - 2)]
    for r in d["results"]:
        row = f"| {r['what']} | {r['ops_per_step']:,.0f} ({r['over_nothing']:+.0f}) |"
        row += f" {r['kernels_per_step']:,.0f} ({r['kernels_over_nothing']:+.0f}) |" if kernels else ""
        if before:
            row += f" {count(r.get('ops_per_step_before'))} |"
            row += f" {count(r.get('kernels_per_step_before'))} |" if kernels else ""
        rows.append(row)
    also = f" (and {before['code']}: {before['what']})" if before else ""
    what = (" The kernels are the ops that do work outside the simulator (no views, no casts to the same dtype): on"
            " a GPU each costs about 2.5 us at 4,096 envs.") if kernels else ""
    return ["Where the per-step overhead comes from: torch ops of one training env step, one piece of the robust "
            f"preset's randomisation at a time.{what}", "", *rows, "",
            f"- command: `{m['command']}`; code {m['code']}{also}",
            f"- date: {m['date']}; hardware: {m['hardware']}, {m['num_envs']} envs, torch {m['torch']}; report: "
            "[step_ops.json](benchmarks/randomization/step_ops.json)"]


#: The same count with the solver capped (``--iterations``), a report per cap: a column each in the table.
CAPPED_ITERATIONS = {5: "benchmarks/randomization/substep_iterations_cap5.json",
                     4: "benchmarks/randomization/substep_iterations_cap4.json",
                     3: "benchmarks/randomization/substep_iterations_cap3.json"}


def substep_iterations(docs: Path) -> list[str]:
    """Newton iterations per substep under the lab's delay against none (C MuJoCo, ``substep_iterations.py``), with
    the capped runs' columns when their reports are committed."""
    d = _load("benchmarks/randomization/substep_iterations.json", docs)
    m = d["meta"]
    capped = {cap: _load(name, docs) for cap, name in CAPPED_ITERATIONS.items() if (docs / name).is_file()}
    lockstep = {cap: {r["variant"]: r["lockstep_per_period"] for r in c["results"]} for cap, c in capped.items()}
    rows = ["| leg actuators | solver iterations per period, each robot's own | lockstep (most of any robot, per "
            "substep) |" + "".join(f" lockstep, solver capped at {cap} |" for cap in capped),
            "|---|---:|---:|" + "---:|" * len(capped)]
    rows += [f"| {r['variant']} ({r['delay_substeps'][0]}-{r['delay_substeps'][1]} substeps"
             + (f", every {r['delay_stride']}" if r["delay_stride"] != 1 else "")
             + (", mean over each period" if r.get("delay_average") else "")
             + f") | {r['own_per_period']:.1f} | {r['lockstep_per_period']:.1f} |"
             + "".join(f" {lockstep[cap].get(r['variant'], float('nan')):.1f} |" for cap in capped)
             for r in d["results"]]
    return ["What likely makes the actuators cost physics time: a torque change makes the substep it lands in solve "
            "longer. Without a delay every robot's lands in substep 0; the delay spreads them over all substeps, and "
            "mujoco-warp iterates a substep's worlds until the slowest converges; on a grid of one period "
            "(`env.control.actuators.delay_stride`) they land in one substep again, and averaged over each period "
            "(`env.control.actuators.delay_average`) in substep 0, as without a delay. Measured with C MuJoCo "
            "standing in for mujoco-warp (the GPU's per-substep counts are not measured yet), robots driven by "
            f"{RUN9_POLICY}, {m['num_robots']} robots, {m['seconds']:g} s"
            + (", each started with the robust test's random joint and pelvis velocities (a batch of robots in "
               "different states, as in training)" if m.get("start_velocity") else ", started at rest") + ":",
            "", *rows, "",
            f"- command: `{d['command']}`",
            f"- date: {m['date']}; hardware: {m['hardware']}; report: "
            "[substep_iterations.json](benchmarks/randomization/substep_iterations.json)", *_at_rest(docs),
            *_capped_note({r["variant"]: r["lockstep_per_period"] for r in d["results"]}, lockstep, capped)]


def _capped_note(uncapped: dict[str, float], lockstep: dict[int, dict[str, float]],
                 capped: dict[int, dict]) -> list[str]:
    """What a cap does to the lab's delay per substep against no delay, one line per capped report (``uncapped``,
    ``lockstep[cap]``: lockstep iterations per period by variant)."""
    def extra(by: dict[str, float]) -> float:
        return by["tocabi_lab delay"] / by["no delay"] - 1

    lines = []
    for cap, d in capped.items():
        name = CAPPED_ITERATIONS[cap]
        lines.append(f"- solver capped at {cap} iterations per substep (`env.sim.solver_iterations`): the lab's delay "
                     f"per substep costs {100 * extra(lockstep[cap]):+.1f} % lockstep iterations over no delay, "
                     f"against {100 * extra(uncapped):+.1f} % uncapped; the cap cuts the slowest worlds' solves short "
                     f"in the substeps the delayed torques jump in as in the others ([{Path(name).name}]({name}); "
                     f"`{d['command']}`; {d['meta']['date']}, {d['meta']['hardware']})")
    return lines


def _at_rest(docs: Path) -> list[str]:
    """The same count with the robots started at rest (a report of its own, when there is one): alike robots
    converge alike, so there the delay's spread shows alone."""
    name = "benchmarks/randomization/substep_iterations_at_rest.json"
    if not (docs / name).is_file():
        return []
    d = _load(name, docs)
    counts = "; ".join(f"{r['variant']} {r['lockstep_per_period']:.1f}" for r in d["results"])
    return [f"- the same with {d['meta']['num_robots']} robots started at rest, lockstep iterations per period: "
            f"{counts} ([{Path(name).name}]({name}); `{d['command']}`). Robots in alike states solve alike, so "
            "there the lockstep count grows with how many different delays the robots drew as much as with where "
            "their torque changes land"]


def solver_load(docs: Path) -> list[str]:
    d = _load("benchmarks/solver_load.json", docs)
    rows = ["| envs | physics ms per policy step: training states | standing robots (raw ceiling) | ratio |",
            "|---:|---:|---:|---:|"]
    rows += [f"| {r['num_envs']:,} | {r['training']['ms_per_policy_step']:.1f} | "
             f"{r['standing (raw ceiling)']['ms_per_policy_step']:.1f} | "
             f"{r['physics_ratio_standing_over_training']:.3f} |" for r in d["results"]]
    m = d["meta"]
    return ["## The physics of training states against the raw ceiling", "",
            "The raw ceiling steps standing robots; training states have more solver iterations in their slowest "
            "world, which caps train / raw below 1 before anything else runs.", "", *rows, "",
            *_source("benchmarks/solver_load.json", m["command"], m["date"], m["gpu"], "benchmarks/solver_load.md"),
            *train_over_ceiling(docs), *solver_settings(docs)]


SOLVER_TOLERANCE = "benchmarks/solver_tolerance.json"


def solver_settings(docs: Path) -> list[str]:
    """Newton iterations per control period under looser tolerances and lower iteration caps
    (lab/analysis/solver_tolerance.py), when that report is committed."""
    if not (docs / SOLVER_TOLERANCE).is_file():
        return []
    d = _load(SOLVER_TOLERANCE, docs)
    m = d["meta"]
    results = [r for r in d["results"] if r.get("case", "walking") == "walking"]
    kicked = [r for r in d["results"] if r.get("case") == "robust_1.0"]
    base = results[0]["lockstep_per_period"]
    rows = ["| tolerance | iteration cap | iterations per period: own | lockstep | lockstep over the model's | "
            "survival | parity sequence: largest joint difference [rad] |", "|---|---|---:|---:|---:|---:|---:|"]
    own = lambda value, model: f"model ({model:g})" if value is None else f"{value:g}"
    rows += [f"| {own(r['tolerance'], m['model_tolerance'])} | {own(r['iterations'], m['model_iterations'])} | "
             f"{r['own_per_period']:.2f} | {r['lockstep_per_period']:.2f} | {r['lockstep_per_period'] / base:.3f} | "
             f"{r['survival']:.3f} | {r['parity_deviation_rad']:.1e} |" for r in results]
    return ["", "Where the solver could do less: Newton iterations per control period (8 substeps) of "
            f"{m['num_robots']} robots walking the shipped torque policy for {m['seconds']:g} s from the robust test's "
            "diverse starts, C MuJoCo standing in for mujoco-warp (own: each robot's; lockstep: the most any robot "
            "needs in each substep, what a GPU pays), and how far each setting moves the parity test's 0.25 s "
            "torque sequence (the test allows 1e-3 rad):", "", *rows, "",
            *([f"Under the robust test's 1.0 m/s kicks ({RUN9_POLICY}, {m['num_robots']} robots, the "
               "lab's randomisation), where impacts need the most iterations, survival: "
               + ", ".join(f"{own(r['iterations'], m['model_iterations'])} iterations {r['survival']:.3f}"
                           for r in kicked) + ".", ""] if kicked else []),
            f"- command: `{d['command']}`",
            f"- date: {m['date']}; hardware: {m['hardware']}; report: [{Path(SOLVER_TOLERANCE).name}]"
            f"({SOLVER_TOLERANCE})"]


TRAIN_OVER_CEILING = "benchmarks/train_over_ceiling.json"
#: The share of the training-state ceiling that training is to reach, per env count.
CEILING_TARGETS = {4096: 0.9, 16384: 0.95}


def train_over_ceiling(docs: Path) -> list[str]:
    """Training against the physics of its own states, timed in place in the same run (``train_throughput
    --ceiling``), when that report is committed."""
    if not (docs / TRAIN_OVER_CEILING).is_file():
        return []
    d = _load(TRAIN_OVER_CEILING, docs)
    m = d["meta"]
    rows = ["| envs | train env-steps/s | physics ms per policy step | ceiling of training states | train / ceiling | "
            "target | train / raw standing |", "|---:|---:|---:|---:|---:|---:|---:|"]
    split = ["| envs | whole policy step [ms] | physics | PPO update (last iteration's, per policy step) | the rest |",
             "|---:|---:|---:|---:|---:|"]
    gpu_timed = True
    for r in d["results"]:
        target = CEILING_TARGETS.get(r["num_envs"])
        met = "" if target is None else (" (met)" if r["ratio_train_over_ceiling"] >= target else " (missed)")
        rows.append(f"| {r['num_envs']:,} | {_k(r['train_env_steps_per_s'])} | {r['physics_ms_per_policy_step']:.2f} | "
                    f"{_k(r['ceiling_env_steps_per_s'])} | **{r['ratio_train_over_ceiling']:.3f}** | "
                    f"{'-' if target is None else f'{target:g}{met}'} | "
                    + ("-" if r.get("ratio_train_over_raw") is None else f"{r['ratio_train_over_raw']:.3f}") + " |")
        if r.get("update_s_last") and r.get("iterations") and r.get("env_steps") and r.get("gpus", 1) == 1:
            # One GPU: every env takes env_steps / iterations / num_envs policy steps per iteration. A result with
            # update_ms_last timed the update's own work (CUDA events around it); older ones the host's wait for it.
            step = r["num_envs"] * 1e3 / r["train_env_steps_per_s"]
            gpu_timed = gpu_timed and "update_ms_last" in r
            update = (r["update_ms_last"] if "update_ms_last" in r else r["update_s_last"] * 1e3) / (
                r["env_steps"] / r["iterations"] / r["num_envs"])
            physics = r["physics_ms_per_policy_step"]
            split.append(f"| {r['num_envs']:,} | {step:.2f} | {physics:.2f} | {update:.2f} | "
                         f"{step - physics - update:.2f} |")
    update_is = ("its last iteration's GPU time (CUDA events around it) over the iteration's policy steps"
                 if gpu_timed else "its last iteration's host time from the rollout's end (GAE and the update) over "
                 "the iteration's policy steps")
    split = ["", f"Where a training step's time goes (ms per policy step of all envs; the update is {update_is}, "
             "the rest is everything else: policy, observations, rewards, resets):", "",
             *split] if len(split) > 2 else []
    return ["", "Training against that ceiling in the same run: the simulator's step timed in place (CUDA events) "
            "over the timed iterations, the ceiling its env count over that time:", "", *rows, *split, "",
            *_source(TRAIN_OVER_CEILING, m["command"], m["date"], m["gpu"],
                     TRAIN_OVER_CEILING.removesuffix(".json") + ".md"), *train_over_ceiling_variants(docs)]


#: The same measurement with the update overlapped and TF32, which the presets do not use yet: one report per env
#: count, ``envs<N>.json``.
TRAIN_OVER_CEILING_OVERLAP = "benchmarks/train_over_ceiling_overlap"
#: Later runs of the same options, listed after those of their env count: the simulator's reset pass over the reset
#: worlds alone (library code at 558ec91 and fc5b42b, the same); its row copies fused and the update's smaller
#: selection (086d9f3: both counts in one run, and one with two epochs a PPO update instead of five); the `pd`
#: preset with the overlapped update (928dc1e: both counts in one run, and 16,384 with two epochs); the default
#: preset's options with two epochs, both counts in one run (f4759b2).
TRAIN_OVER_CEILING_NEWER = ("h100_558ec91/envs4096.json", "h100_fc5b42b/envs16384_sms0.json",
                            "h100_086d9f3/envs16384_4096.json", "h100_086d9f3/envs16384_epochs2.json",
                            "h100_928dc1e/pd_overlap_envs16384_4096.json",
                            "h100_928dc1e/pd_overlap_epochs2_envs16384.json",
                            "h100_f4759b2/envs16384_4096_epochs2.json",
                            "h100_bf16/envs16384_4096_bf16_compiled.json",
                            "h100_bf16/envs16384_bf16_compiled_r2.json")


def train_over_ceiling_variants(docs: Path) -> list[str]:
    """One line per result of the committed ``--ceiling`` reports in :data:`TRAIN_OVER_CEILING_OVERLAP` (the preset
    with options switched on by ``--set``), in env-count order, each against the target of its env count; a result
    without a training rate is left out."""
    found = []
    folder = docs / TRAIN_OVER_CEILING_OVERLAP
    reports = [p for p in folder.glob("envs*.json") if p.stem.removeprefix("envs").isdigit()]
    reports += [folder / rel for rel in TRAIN_OVER_CEILING_NEWER if (folder / rel).is_file()]
    for order, path in enumerate(reports):
        d = json.loads(path.read_text())
        found += [(r["num_envs"], order, path, d, r) for r in d["results"]
                  if r.get("ratio_train_over_ceiling") is not None]
    lines = []
    for _, _, path, d, r in sorted(found, key=lambda item: item[:2]):
        ratio, target = r["ratio_train_over_ceiling"], CEILING_TARGETS.get(r["num_envs"])
        verdict = "" if target is None else f", {'meets' if ratio >= target else 'misses'} the target {target:g}"
        rel = path.relative_to(folder).as_posix()
        lines.append(f"- {r['num_envs']:,} envs with {_set_items(r.get('overrides', {})) or 'no option'}: "
                     f"**{ratio:.3f}** of the ceiling ({_k(r['train_env_steps_per_s'])} against "
                     f"{_k(r['ceiling_env_steps_per_s'])} env-steps/s{verdict}; {d['meta']['date']}, "
                     f"{d['meta']['gpu']}; [{rel}]({TRAIN_OVER_CEILING_OVERLAP}/{rel})).")
    if not lines:
        return []
    return ["", "With options that no preset uses yet, measured the same way, one run each (repeats, other GPUs and "
            f"ablations: [details]({TRAIN_OVER_CEILING_OVERLAP}/README.md)); per env count, earlier code first:", "",
            *lines]


def soak(docs: Path) -> list[str]:
    d = _load("benchmarks/soak.json", docs)
    m = d["meta"]
    rows = ["| check | measured | limit | ok |", "|---|---|---|---|"]
    rows += [f"| {r['check']} | {r['value']} | {r['limit']} | {'yes' if r['ok'] else '**no**'} |" for r in d["results"]]
    return ["## Soak: faults stay in their worlds, a killed run resumes", "", *rows, "",
            f"- commands: `{m['faults_command']}`; `{m['kill_resume_command']}`",
            f"- date: {m['date']}; hardware: {m['gpu']}, {m['num_envs']:,} envs; report: "
            "[soak.json](benchmarks/soak.json), [details](benchmarks/soak.md)"]


def cpu_backends(docs: Path) -> list[str]:
    out = ["## CPU backends: C MuJoCo threads against mujoco-warp's CPU device", "",
           "| machine | envs | C MuJoCo env-steps/s | warp CPU env-steps/s | ratio |", "|---|---:|---:|---:|---:|"]
    sources = []
    for rel in ("benchmarks/cpu_backends_2core.json", "benchmarks/cpu_backends_h100-16core.json"):
        d = _load(rel, docs)
        m = d["meta"]
        out += [f"| {m['cores']} cores | {r['num_envs']} | {r['mujoco']['env_steps_per_s']:,.0f} | "
                f"{r['warp_cpu']['env_steps_per_s']:,.0f} | {r['mujoco_over_warp']:.1f}x |" for r in d["results"]]
        sources += _source(rel, m["command"], m["date"], f"{m['cores']} CPU cores ({m['gpu']} host)"
                           if m["gpu"] != "cpu" else f"{m['cores']} CPU cores")
    retired = "- the script was retired on 2026-11-25; it is `benchmarks/cpu_backends.py` at commit dab4ad2"
    return [*out, "", *sources, retired]


#: The robust policy the analyses of the delay and the solver ran (lab/analysis/averaged_delay.py,
#: substep_iterations.py, solver_tolerance.py): run 9's 16-minute mark, shipped until run 23's replaced it.
RUN9_POLICY = "run 9's robust policy (the shipped one until 2026-12-06)"
#: Where the shipped robust policy's verdict is: the report of its run's checkpoints, and the checkpoint that
#: assets/policies/tocabi_walk_robust.pt was written from (tocabi_torchrl.rl.checkpoint.write_policy_file).
ROBUST_SHIPPED = ("training/robust/h100_run23/verdict/robust_policies.json", "wall_00840s", "tocabi_walk_robust")


def robust_policies(docs: Path) -> list[str]:
    d = _load("benchmarks/robust/robust_policies.json", docs)
    ours_file, ours_checkpoint, ours_name = ROBUST_SHIPPED
    ours = _load(ours_file, docs)
    kicks = kick_note(d["results"])
    m, mo = d["meta"], ours["meta"]
    rows = ["| policy | nominal survival / drift p95 | commands survival / tracking | robust_0.5 survival | "
            "robust_1.0 survival | passes |", "|---|---:|---:|---:|---:|---|"]
    shipped = [r for r in ours["results"] if r["policy"] == ours_checkpoint]
    if len(shipped) != 1:
        raise ValueError(f"docs/{ours_file} has no result of {ours_checkpoint} (ROBUST_SHIPPED)")
    for name, r in [(ours_name, shipped[0])] + [(r["policy"], r) for r in d["results"]]:
        c = r["cases"]
        f = lambda value, spec: "-" if value is None else format(value, spec)  # null: no value (a short test)
        nominal, commands = c["nominal"], c["commands"]
        rows.append(f"| {name} | {f(nominal['survival'], '.3f')} / {f(nominal['lateral_drift_m.p95'], '.2f')} m | "
                    f"{f(commands['survival'], '.3f')} / {f(commands['tracking_error_mps.mean'], '.3f')} m/s | "
                    f"{f(c['robust_0.5']['survival'], '.3f')} | {f(c['robust_1.0']['survival'], '.3f')} | "
                    f"{'yes' if r['passes'] else 'no'} |")
    return ["## Robust gait test", "",
            f"{m['num_envs']:,} robots per case, {m['seconds']:g} s (docs/evaluation.md: nominal needs survival >= "
            "0.99, mean distance >= 2.6 m and drift p95 <= 0.3 m, commands survival >= 0.99 and tracking <= 0.12 m/s, "
            "robust_0.5 survival >= 0.97, "
            f"robust_1.0 >= 0.85). {kicks[0].upper() + kicks[1:]}. `{ours_name}` is the `{ours_checkpoint}` "
            f"checkpoint of a from-scratch run of the `robust` preset ({Path(ours_file).parent.parent}/README.md), "
            f"tested with {mo['num_envs']:,} robots per case in that run's verdict; the other three in one run of the "
            "command below.", "",
            *rows, "",
            *_source(ours_file, mo["command"], mo["date"], mo["gpu"], ours_file.replace(".json", ".md")),
            *_source("benchmarks/robust/robust_policies.json", m["command"], m["date"], m["gpu"],
                     "benchmarks/robust/robust_policies.md")]


def viewer(docs: Path) -> list[str]:
    d, play = _load("benchmarks/viewer_overhead/viewer_overhead.json", docs), \
        _load("benchmarks/viewer_overhead/viewer_play.json", docs)
    rows = ["| what | measured |", "|---|---:|"]
    rows += [f"| training, {r['num_envs']:,} envs, viewer streaming / not (same run) | {r['ratio']:.3f} |"
             for r in d["results"]]
    rows += [f"| policy page, {r['num_envs']} robots | {r['frames_per_s']:.1f} frames/s, "
             f"{r['policy_steps_per_s']:.0f} policy steps/s |" for r in play["results"]]
    return ["## Live viewer", "", *rows, "",
            *_source("benchmarks/viewer_overhead/viewer_overhead.json", d["meta"]["command"], d["meta"]["date"],
                     d["meta"]["gpu"], "benchmarks/viewer_overhead/viewer_overhead.md"),
            *_source("benchmarks/viewer_overhead/viewer_play.json", play["meta"]["command"], play["meta"]["date"],
                     play["meta"]["gpu"], "benchmarks/viewer_overhead/viewer_play.md")]


#: The page's sections, in order.
SECTIONS: tuple[Callable[[Path], list[str]], ...] = (
    time_to_walk, train_throughput, env_throughput, several_gpus, mjlab_peer, scaling, library_table,
    robust_policies, randomization, viewer, solver_load, soak, cpu_backends)


def render(docs: Path = DOCS) -> str:
    """The markdown of docs/benchmarks.md from the committed reports under ``docs``."""
    parts = [HEADER]
    for section in SECTIONS:
        _READ.clear()
        try:
            parts.append("\n".join(section(docs)))
        except (KeyError, IndexError) as err:  # a report rewritten without a field or row this page shows
            files = ", ".join(f"docs/{rel}" for rel in dict.fromkeys(_READ)) or "its reports"
            raise ValueError(f"the {section.__name__} section: {files} lack(s) {err} ({type(err).__name__}), which "
                             "the page shows: add it to the report, or change what lab/benchmarks/page.py "
                             "reads") from err
    return "\n\n".join(parts) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true", help="only report whether docs/benchmarks.md is current")
    args = p.parse_args(argv)
    try:
        text = render()
    except ValueError as err:  # a report the page cannot show: named, not a traceback
        p.exit(1, f"error: {err}\n")
    if args.check:
        current = PAGE.is_file() and PAGE.read_text() == text
        print(f"{PAGE} is {'current' if current else 'stale: run python -m lab.benchmarks.page'}")
        return 0 if current else 1
    PAGE.write_text(text)
    print(f"wrote {PAGE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
