"""What the benchmarks share: metadata, timing, the raw mujoco-warp ceiling, memory sampling, the library's training
entry points (one place to adapt when they change), fresh-process runs and reports (``<name>.json`` holding
``{"meta", "results"}``, ``<name>.md`` rendered from it, plots beside it; ``lab.benchmarks.regenerate`` re-renders them).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import re
import resource
import shutil
import subprocess
import sys
import threading
import time
import typing
from collections.abc import Callable, Sequence
from pathlib import Path

import torch

from tocabi_torchrl import robot
from tocabi_torchrl.atomic import atomic_write_text
from tocabi_torchrl.cli import suggest_options
from tocabi_torchrl.config import RunConfig
from tocabi_torchrl.rl import checkpoint, trainer
from tocabi_torchrl.rl.config import PRESETS, parse_tree, preset_config
from tocabi_torchrl.rl.curves import read_metrics
from tocabi_torchrl.evaluation.env_reuse import build_sections, remember_built_state, restore_built_state
from tocabi_torchrl.evaluation.gait_test import evaluate_policy
from tocabi_torchrl.evaluation.output import json_safe
from tocabi_torchrl.evaluation.record import fixed_command, nominal_config
from tocabi_torchrl.tree import get_path, item_type, leaf_types

from lab.new_files import write_new_files

GIB = 2**30
#: Raw policy steps run before the ceiling is measured (the robots settle onto the floor first).
RAW_WARMUP = 20
DOCS = Path(__file__).resolve().parents[2] / "docs" / "benchmarks"
#: Where a report measured on the CPU goes instead of :data:`DOCS` (ignored by git): see :func:`report_dir`.
CPU_OUT = Path(__file__).resolve().parents[2] / "runs" / "benchmarks_cpu"


def meta(script: str, argv: Sequence[str] | None, on: str = "cuda", **extra) -> dict:
    """The device this run measured ``on``, versions, date and the command line of this run."""
    args = list(sys.argv[1:] if argv is None else argv)
    cuda = on.startswith("cuda") and torch.cuda.is_available()
    return {"gpu": torch.cuda.get_device_name() if cuda else platform.processor() or platform.machine() or "cpu",
            "torch": torch.__version__, "python": platform.python_version(), "date": time.strftime("%Y-%m-%d"),
            "command": " ".join([f"python -m lab.benchmarks.{script}", *args]), **extra}


def require_cuda(parser: argparse.ArgumentParser, device: str, fix: str) -> None:
    """End the command with ``parser.error`` (one line, exit 2) when ``device`` names CUDA and torch sees no GPU,
    rather than with a traceback from deep inside an env build; ``fix`` says what to pass instead."""
    if device.startswith("cuda") and not torch.cuda.is_available():
        parser.error(f"--device {device}: torch sees no CUDA GPU here; {fix}")


def per_second(step: Callable[[], object], steps: int, device: str | torch.device, warmup: int = 0) -> float:
    """Calls of ``step`` per second over ``steps`` calls after ``warmup``, the device's queued work included."""
    sync = torch.cuda.synchronize if torch.device(device).type == "cuda" else (lambda: None)
    for _ in range(warmup):
        step()
    sync()
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    sync()
    return steps / (time.perf_counter() - t0)


def env_rate(env, steps: int, warmup: int = 10, autoreset: bool = False) -> float:
    """Env-steps/s of ``env.step`` (or the collectors' ``step_and_maybe_reset``) with the legs PD-held on the initial
    pose (torque-mode actions as fractions of the limits), so every benchmark steps the same standing robots."""
    as_t = lambda x: torch.as_tensor(x, dtype=torch.float32, device=env.device)
    kp, kv, limits, q0 = map(as_t, (robot.LEG_KP, robot.LEG_KV, robot.LEG_TORQUE_LIMITS, robot.INIT_JOINT_POS[:12]))
    state = {"td": env.reset()}

    def step() -> None:
        td = state["td"]
        legs = ((kp * (q0 - td["joint_pos"][:, :12]) - kv * td["joint_vel"][:, :12]) / limits).clamp(-1.0, 1.0)
        td.set("action", torch.cat((legs, torch.zeros_like(legs[:, :1])), dim=-1))
        state["td"] = env.step_and_maybe_reset(td)[1] if autoreset else env.step(td)["next"]

    return env.batch_size[0] * per_second(step, steps, env.device, warmup)


def raw_policy_step(num_worlds: int, device: str = "cuda") -> Callable[[], None]:
    """One raw mujoco-warp policy step of ``num_worlds`` worlds on the backend's model and buffers, a leg PD-hold
    kernel then ``mujoco_warp.step`` x 8 (every sensor, every substep), recorded as one graph (compiled and warmed
    once); calling it replays the graph on PyTorch's current stream. Its ``wp_data`` is the worlds' warp ``Data``."""
    import mujoco_warp as mjw
    import warp as wp

    from tocabi_torchrl.sim import add_contact_sensors
    from tocabi_torchrl.sim.buffers import CONTACT_SENSOR_MAXMATCH, NCONMAX, NJMAX
    from tocabi_torchrl.sim.graph import Recorded

    @wp.kernel(enable_backward=False)
    def hold(qpos: wp.array2d(dtype=float), qvel: wp.array2d(dtype=float), q0: wp.array(dtype=float),
             kp: wp.array(dtype=float), kv: wp.array(dtype=float), ctrl: wp.array2d(dtype=float)):
        w, j = wp.tid()
        ctrl[w, j] = kp[j] * (q0[j] - qpos[w, 7 + j]) - kv[j] * qvel[w, 6 + j]

    mj, legs = add_contact_sensors(robot.load_spec()).compile(), robot.NUM_LEG_JOINTS
    with wp.ScopedDevice(wp.get_device(device)):
        m = mjw.put_model(mj)
        m.opt.contact_sensor_maxmatch, m.opt.warn_overflow = CONTACT_SENSOR_MAXMATCH, 0  # the backend's settings
        d = mjw.make_data(mj, nworld=num_worlds, nconmax=NCONMAX, njmax=NJMAX)
        ctrl = torch.zeros(num_worlds, robot.NUM_JOINTS)
        ctrl[:, legs:] = torch.as_tensor(robot.INIT_JOINT_POS[legs:])  # upper body on its servos
        d.qpos.assign(torch.as_tensor(robot.INIT_QPOS, dtype=torch.float32).repeat(num_worlds, 1).numpy())
        d.ctrl.assign(ctrl.numpy())
        mjw.forward(m, d)
        consts = [wp.array(x[:legs].astype("float32"), dtype=float)
                  for x in (robot.INIT_JOINT_POS, robot.LEG_KP, robot.LEG_KV)]

        def body() -> None:
            wp.launch(hold, dim=(num_worlds, legs), inputs=[d.qpos, d.qvel, *consts], outputs=[d.ctrl])
            for _ in range(8):
                mjw.step(m, d)

        body()  # compile before recording
        wp.synchronize_device()
        step = Recorded(body, wp.get_device(device))
        step.wp_data = d  # what the step writes, for benchmarks that read the solver's counts (solver_load)
        return step


def raw_policy_steps_per_second(num_worlds: int, steps: int, device: str = "cuda", warmup: int = RAW_WARMUP) -> float:
    """The ceiling the other benchmarks divide by: policy steps/s of :func:`raw_policy_step`."""
    return num_worlds * per_second(raw_policy_step(num_worlds, device), steps, device, warmup)


def device_used_gib(device: str | torch.device = "cuda") -> float | None:
    """Device-wide memory in use (``cudaMemGetInfo``: warp's buffers and the CUDA context too); None on the CPU."""
    info = torch.cuda.mem_get_info(torch.device(device)) if torch.device(device).type == "cuda" else None
    return None if info is None else (info[1] - info[0]) / GIB


def rss_gib() -> float:
    """This process's resident set now (0 where /proc is missing)."""
    try:
        return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / GIB
    except OSError:
        return 0.0


@contextlib.contextmanager
def memory_peaks(device: str | torch.device = "cuda", every_s: float = 0.05):
    """Yields a dict holding, after the block, the peaks of the device memory in use (:func:`device_used_gib`, sampled
    every ``every_s``; None on the CPU), of this process's RSS and of the torch allocator (zeros without CUDA)."""
    peak, stop = {"device_peak_used_gib": None}, threading.Event()

    def sample() -> None:
        used = device_used_gib(device)
        peak["device_peak_used_gib"] = None if used is None else max(peak["device_peak_used_gib"] or 0.0, used)

    def loop() -> None:
        while not stop.wait(every_s):
            sample()

    thread = threading.Thread(target=loop, daemon=True)
    sample()
    thread.start()
    try:
        yield peak
    finally:
        stop.set()
        thread.join()
        sample()
        cuda = torch.cuda.is_available() and torch.cuda.is_initialized()
        peak.update(peak_rss_gib=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / GIB,
                    torch_peak_allocated_gib=torch.cuda.max_memory_allocated() / GIB if cuda else 0.0,
                    torch_peak_reserved_gib=torch.cuda.max_memory_reserved() / GIB if cuda else 0.0)


# The library's entry points: the only place the benchmarks touch its config, trainer and checkpoints.
config = preset_config  # config(preset, **overrides): a training config
presets = sorted(PRESETS)  # the names config() takes, for the scripts' --preset checks


def run_config(n: int, iterations: int, overrides: dict, run_dir: str, name: str, device: str, ranks: int = 1):
    """A preset (``overrides["preset"]``, default ``"default"``) as the throughput benchmarks train it: ``n`` envs per
    rank for ``iterations`` PPO iterations in all (``ranks`` ranks), a mini-batch of at most a quarter of a rollout,
    every iteration logged, no checkpoint, progress bar or closing evaluation; ``overrides`` (dotted paths) on top."""
    overrides = dict(overrides)
    preset = overrides.pop("preset", "default")
    steps = overrides.get("ppo.steps_per_env", config(preset).ppo.steps_per_env)
    return config(preset, **{"ppo.minibatch_size": min(49152, n * steps // 4), **overrides, "env.num_envs": n,
                                "total_env_steps": iterations * n * steps * ranks, "run_dir": run_dir, "name": name,
                                "checkpoint_every": 10**9, "progress_bar": False, "eval_at_end": False,
                                "log_every": 1, "device": device})
read_checkpoint = checkpoint.read_checkpoint  # a checkpoint (file or run folder) as a dict, loaded weights-only


def parse_overrides(items: Sequence[str], *, warn_repeats: bool = True) -> dict:
    """``PATH=VALUE`` strings (a path of the config tree such as ``ppo.lr`` or ``env.num_envs``) typed by the tree,
    as ``recipes/ppo_walk.py``'s ``--PATH VALUE`` would read them, by path. A tuple's entries are separated by spaces
    or commas (``delay_substeps=4 20``, ``=4,20``, ``=(4, 20)``); any other value is one argument, spaces and all
    (a name, a path, ``env.scene.obstacles``' JSON). A path given twice keeps its last value, with a warning
    (``warn_repeats=False``: a script that appends its own overrides to the user's on purpose checks the user's
    items alone, so that the warning names only what the user gave twice)."""
    kinds = leaf_types(RunConfig())
    argv = []
    for item in items:
        field, _, value = item.partition("=")
        if field not in kinds:
            near = suggest_options(field, kinds)
            hint = f"; did you mean {' or '.join(near)}?" if near else ""
            raise SystemExit(f"error: --set {item}: the training config has no option {field!r}{hint} (options are "
                             "dotted paths such as ppo.lr or env.num_envs: recipes/ppo_walk.py --help)")
        argv += [f"--{field}", *_set_arguments(kinds[field], value)]
    # A path given twice keeps its last value: said, not silent.
    last = {item.partition("=")[0]: item for item in items}
    for field, item in last.items():
        if (warn_repeats and (times := sum(i.partition("=")[0] == field for i in items)) > 1
                and os.environ.get("RANK", "0") == "0"):
            print(f"warning: --set {field} is given {times} times; the last applies: {item}", file=sys.stderr,
                  flush=True)
    cfg = parse_tree(argv, RunConfig())
    return {field: get_path(cfg, field) for field in last}


def _set_arguments(kind, value: str) -> list[str]:
    """The command-line arguments of a ``--set`` value for a leaf annotated ``kind``: a tuple of plain values (not
    of items, which take JSON) split at spaces and commas, brackets around it dropped; anything else whole. Splitting
    every value at spaces broke a JSON list or a name with spaces into stray arguments."""
    if typing.get_origin(kind) is tuple and item_type(kind) is None:
        return [v for v in re.split(r"[\s,]+", value.strip().strip("()[]")) if v]
    return [value]


def train(cfg, env=None, wrap_policy: Callable | None = None):
    """Train ``cfg``; returns the trainer's result and its logged metric rows. ``wrap_policy(policy)`` replaces the
    collector's policy (the soak's fault injector), so that what it does to actions reaches PPO's rollout too."""
    make_collector = trainer.make_collector
    if wrap_policy is not None:  # train() builds its collector through this module attribute
        trainer.make_collector = lambda c, e, actor, *a, **k: make_collector(c, e, wrap_policy(actor), *a, **k)
    try:
        result = trainer.train(cfg, env=env)
    finally:
        trainer.make_collector = make_collector
    return result, read_metrics(result.run_dir)


def stamp(cuda: bool):
    """A point in time on the device's queue: a recorded CUDA event (nothing waits), or the host clock off CUDA."""
    if not cuda:
        return time.perf_counter()
    event = torch.cuda.Event(enable_timing=True)
    event.record()
    return event


def elapsed_ms(start, end, cuda: bool) -> float:
    """Milliseconds between two :func:`stamp` marks (CUDA events must have completed: synchronize first)."""
    return start.elapsed_time(end) if cuda else 1e3 * (end - start)


def wrap_method(obj, name: str, before, after, undo: list) -> None:
    """Replace the method ``obj.name`` on this instance by one that calls ``before()`` and ``after()`` around it;
    appends to ``undo`` what puts the original back."""
    inner, own = getattr(obj, name), name in vars(obj)

    def wrapped(*args, **kwargs):
        before()
        out = inner(*args, **kwargs)
        after()
        return out

    setattr(obj, name, wrapped)
    undo.append(lambda: setattr(obj, name, inner) if own else delattr(obj, name))


def eager_step_config(script: str, n: int, iterations: int, overrides: dict, run_dir: str, name: str, device: str):
    """``run_config`` for a benchmark that marks the trainer's eager env step, and the device it runs on. Refuses
    (naming the fix) a config whose env step would be captured, which has no points to mark, and clears the
    benchmark's scratch run folder."""
    cfg = run_config(n, iterations, overrides, run_dir, name, device)
    at = trainer.resolve_device(device)
    if cfg.ppo.overlap_update:
        raise SystemExit(f"{script} times the trainer's phases one after another, and ppo.overlap_update runs the "
                         "update beside the next rollout: pass --set ppo.overlap_update=false")
    refuse_captured_env_step(script, cfg, at, n)
    shutil.rmtree(Path(run_dir) / cfg.name, ignore_errors=True)
    return cfg, at


def refuse_captured_env_step(script: str, cfg, at: torch.device, n: int) -> None:
    """Exit, naming the fix, when ``cfg``'s trainer would capture the env step at ``n`` envs on ``at``: a captured
    step has no points to mark."""
    if cfg.ppo.cuda_graph == "on" or trainer.plan_graphs(cfg, at, n).env_step:
        raise SystemExit(f"{script} marks the eager env step, and ppo.cuda_graph={cfg.ppo.cuda_graph!r} captures it at "
                         f"{n} envs (a captured step has no points to mark): pass --set ppo.cuda_graph=off")


@contextlib.contextmanager
def trainer_patched(replacements: dict, undo: list):
    """The trainer module's functions ``replacements`` (name -> function) in place while the block runs; on exit,
    also after an error, the originals are back and ``undo``'s callables have run, last first (what the
    replacements wrapped or hooked on the objects the trainer built)."""
    saved = {name: getattr(trainer, name) for name in replacements}
    for name, fn in replacements.items():
        setattr(trainer, name, fn)
    try:
        yield
    finally:
        for name, fn in saved.items():
            setattr(trainer, name, fn)
        for put_back in reversed(undo):
            put_back()


def trainer_benchmark(argv, name: str, doc: str, measure: Callable, render: Callable, *, min_warmup: int,
                      min_raw_steps: int, device_help: str) -> dict:
    """The command line of the benchmarks that run the real trainer at each ``--num_envs`` and raw mujoco-warp in the
    same process (step_timeline, solver_load): parses ``argv``, calls ``measure(n, iterations, warmup, raw_steps,
    device, run_dir, overrides)`` per env count, publishes ``<out>/<name>.{json,md}`` and returns the data. With
    ``--child`` it measures the first env count, prints the record as the ``RESULT`` line :func:`run_child` reads and
    publishes nothing (another benchmark's measurement in a process of its own)."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--num_envs", type=int, nargs="+", default=[4096],
                        help="robot counts, one measurement each (default: 4096)")
    parser.add_argument("--iterations", type=int, default=3, help="training iterations measured")
    parser.add_argument("--warmup", type=int, default=3, help=f"training iterations first, not measured (>= {min_warmup})")
    parser.add_argument("--raw_steps", type=int, default=200,
                        help=f"raw mujoco-warp policy steps measured (>= {min_raw_steps}"
                             + ("; 0 skips them)" if min_raw_steps == 0 else ")"))
    parser.add_argument("--set", nargs="*", default=[], metavar="PATH=VALUE",
                        help="config overrides (ablations): dotted paths, e.g. ppo.cuda_graph=off; preset=NAME "
                             "measures that training preset (default: default)")
    parser.add_argument("--device", default="cuda", help=device_help)
    parser.add_argument("--run_dir", default=f"/tmp/tocabi_bench_runs/{name}",
                        help=f"scratch folder of the training runs (default: /tmp/tocabi_bench_runs/{name})")
    parser.add_argument("--out", default=str(DOCS), help="folder of the report <name>.json and .md (default: "
                        "docs/benchmarks; a CPU measurement goes to runs/benchmarks_cpu instead)")
    parser.add_argument("--name", default=name, help=f"the report's file name, <out>/<name>.json (default: {name})")
    parser.add_argument("--child", action="store_true", help="measure the first env count, report it, publish "
                                                             "nothing (internal: common.run_child)")
    args = parser.parse_args(argv)
    if args.warmup < min_warmup or args.iterations < 1 or args.raw_steps < min_raw_steps or min(args.num_envs) < 1:
        parser.error(f"--warmup must be >= {min_warmup}, --iterations >= 1, --raw_steps >= {min_raw_steps} and "
                     f"--num_envs >= 1")
    require_cuda(parser, args.device, f"pass --device cpu ({device_help})")
    overrides = parse_overrides(args.set)
    if args.child:
        record = measure(args.num_envs[0], args.iterations, args.warmup, args.raw_steps, args.device, args.run_dir,
                         overrides)
        print("RESULT " + json.dumps(record), flush=True)
        return {"results": [record]}
    results = [measure(n, args.iterations, args.warmup, args.raw_steps, args.device, args.run_dir, overrides)
               for n in args.num_envs]
    data = {"meta": meta(name, argv, args.device, name=args.name), "results": results}
    print(publish(args.out, args.name, data, render, measured_on=args.device))
    return data


def build_env(cfg, **kwargs):
    """The env of ``cfg`` on its device (``kwargs``: the trainer's ``build_env`` options)."""
    return trainer.build_env(cfg, trainer.resolve_device(cfg.device), **kwargs)


def gait_test(state: dict, path, command, out, num_envs: int, seconds: float, device: str, envs: dict) -> dict:
    """The evaluation summary of checkpoint ``state`` at a fixed command; ``envs`` caches one env per command and
    checkpoint config across checkpoints (building one costs more than the test)."""
    cfg, device = nominal_config(checkpoint.config_from_checkpoint(state, path)), torch.device(device)
    key = (command, str(device), num_envs, build_sections(cfg))  # a checkpoint of another config gets its own env
    if key not in envs:
        envs[key] = trainer.build_env(cfg, device, num_envs=num_envs, command=fixed_command(command))
        remember_built_state(envs[key])
    env = envs[key]
    restore_built_state(env)  # nothing the checkpoint before this one loaded into the env stays
    agent = trainer.checkpoint_agent(state, cfg, env, path)
    return evaluate_policy(agent.actor, cfg, out, num_envs=num_envs, device=device, seconds=seconds, command=command,
                           video_envs=0, env=env, progress=False, source=path)


def run_child(module: str, args: Sequence[str], env: dict | None = None, nproc: int | None = None) -> dict:
    """``python -m lab.benchmarks.<module> --child ARGS`` in a fresh process (its memory peaks are its own), or under
    torchrun as ``nproc`` data-parallel ranks (rank 0 reports); the JSON of its last ``RESULT <json>`` line, or an
    error carrying the output's tail."""
    launch = [] if nproc is None else ["-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(nproc)]
    cmd = [sys.executable, *launch, "-m", f"lab.benchmarks.{module}", "--child", *args]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False, cwd=DOCS.parents[1],  # the repository root: lab/ is importable from there
                          env={**os.environ, **(env or {})})
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    if proc.returncode != 0 or not lines:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stdout[-3000:]}{proc.stderr[-3000:]}")
    return json.loads(lines[-1][len("RESULT "):])


def table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A markdown table, columns right-aligned."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---:|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(map(str, r)) + " |" for r in rows])


def page(title: str, data: dict, body: str) -> str:
    """A report page: title with the device and date, the command that made it, then ``body``."""
    m = data["meta"]
    return f"# {title} ({m['gpu']}, {m['date']})\n\nCommand: `{m['command']}`\n\n{body.strip()}\n"


def read_json(path: str | Path, fix: str):
    """The JSON of ``path``, a file a benchmark wrote (a run's ``train.json``, a measurement's result). Invalid JSON
    (a file cut short by a copy, or edited by hand) raises ``ValueError`` naming the file and ``fix``, what writes it
    again: the decoder's message alone named neither, and where it was not caught it ended in a traceback."""
    try:
        return json.loads(Path(path).read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path} is not valid JSON ({err}): the file is damaged; {fix}") from None


def write_json(path: str | Path, data: dict, replace: bool = True) -> Path:
    """``data`` as strict JSON (a NaN or infinite number as ``null``: bare ``NaN`` tokens are not JSON, and a
    case shorter than a gait cycle has no tracking error), written atomically; returns the path written.
    ``replace=False``: never over a file at ``path``; one that appeared since the script checked is left as it is and
    the JSON goes beside it (:func:`lab.new_files.write_new_files` says where)."""
    text = _json_text(data)
    return atomic_write_text(Path(path), text) if replace else write_new_files({Path(path): text})[0]


def _json_text(data: dict) -> str:
    return json.dumps(json_safe(data), indent=2, allow_nan=False) + "\n"


def report_dir(out: str | Path, measured_on: str | None = None) -> Path:
    """Where a report measured on ``measured_on`` (a device string; None: not measured here, e.g. GPU results merged
    or re-rendered on this machine) goes: ``out``, except that a CPU measurement is never published into
    :data:`DOCS` or a folder in it, which hold the GPU results; it goes to the same place under :data:`CPU_OUT`
    instead, saying so."""
    out = Path(out)
    docs = DOCS.resolve()
    if measured_on is None or str(measured_on).startswith("cuda"):
        return out
    if out.resolve() == docs or docs in out.resolve().parents:
        moved = CPU_OUT / out.resolve().relative_to(docs)
        print(f"measured on {measured_on}: writing to {moved}, not {out}, which holds the published GPU results",
              flush=True)
        return moved
    return out


def publish(out: str | Path, name: str, data: dict, render: Callable[[dict, Path], str],
            measured_on: str | None = None, replace: bool = True) -> str:
    """Write ``<out>/<name>.json`` and its page ``render(data, out)`` as ``<name>.md`` (atomically, saying where);
    ``out`` as :func:`report_dir` gives it for ``measured_on``. ``replace=False`` (a script that checked at its
    start that the report is not there, and was not given ``--overwrite``): neither file is written over; when
    either appeared during the measurement, both go beside their names as a pair (:func:`lab.new_files.write_new_files`
    says where), so that no minutes of results are lost and no JSON is left without its page."""
    out = report_dir(out, measured_on)
    out.mkdir(parents=True, exist_ok=True)  # render may write plots beside the page
    text = render(data, out)  # first: a page that fails to render replaces nothing (JSON and page stay one pair)
    if replace:
        write_json(out / f"{name}.json", data)
        atomic_write_text(out / f"{name}.md", text)
        print(f"wrote {out / name}.json and .md", flush=True)
    else:  # both names checked before either is written: a page that appeared leaves no JSON without its page
        written = write_new_files({out / f"{name}.json": _json_text(data), out / f"{name}.md": text})
        print(f"wrote {written[0]} and {written[1]}", flush=True)
    return text


def plot(path: Path, panels: Sequence[dict], title: str = "") -> None:
    """Line panels side by side, each ``{"lines": {label: (x, y)}, "hlines": [(y, label[, linestyle])], "vlines": [x],
    **axes}``
    (``axes``: ``ax.set`` options such as ylabel, xscale); nothing where matplotlib is missing (plots are optional)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4), squeeze=False)
    for ax, panel in zip(axes[0], panels, strict=True):
        for label, (x, y) in panel.pop("lines").items():
            ax.plot(x, y, "o-", ms=3, label=label)
        for y, label, *style in panel.pop("hlines", ()):
            ax.axhline(y, color="k", ls=style[0] if style else "--", lw=0.8, label=label)
        for x in panel.pop("vlines", ()):
            ax.axvline(x, color="grey", ls=":", lw=0.8)
        ax.set(**panel)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def fmt(x, spec: str = ",.0f", none: str = "-") -> str:
    """``format(x, spec)``, or ``none`` for a missing value."""
    return none if x is None else format(x, spec)
