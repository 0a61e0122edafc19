"""What every benchmark shares: run metadata, timing, the raw mujoco-warp ceiling, memory sampling, the library's
training entry points (one place to adapt when they change), fresh-process runs and report writing.

A report is ``<name>.json`` (``{"meta": ..., "results": ...}``) plus ``<name>.md`` rendered from it, and a plot where
the benchmark draws one; ``python -m benchmarks.regenerate`` re-renders every committed report from its JSON.
"""

from __future__ import annotations

import json
import os
import platform
import resource
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import torch

from tocabi_torchrl import robot
from tocabi_torchrl.rl.atomic import atomic_write_text
from tocabi_torchrl.rl.curves import read_metrics

GIB = 2**30
DOCS = Path(__file__).resolve().parents[1] / "docs" / "benchmarks"
SUBSTEPS = 8  # physics substeps per policy step, as the env steps


# ------------------------------------------------------------------------------------------------ metadata, timing


def meta(script: str, argv: Sequence[str] | None, device: str = "cuda", **extra) -> dict:
    """Device, versions, date and the command line of this run."""
    args = list(sys.argv[1:] if argv is None else argv)
    cuda = device.startswith("cuda") and torch.cuda.is_available()
    name = torch.cuda.get_device_name() if cuda else platform.processor() or platform.machine() or "cpu"
    return {"gpu": name, "torch": torch.__version__, "python": platform.python_version(),
            "command": " ".join([f"python -m benchmarks.{script}", *args]), "date": time.strftime("%Y-%m-%d"),
            **extra}


def sync(device: str | torch.device) -> None:
    """Wait for the device's queued work (a no-op on the CPU), so that wall-clock timings cover it."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def per_second(step: Callable[[], object], steps: int, device: str | torch.device, warmup: int = 0) -> float:
    """Calls of ``step`` per second over ``steps`` calls after ``warmup`` untimed ones."""
    for _ in range(warmup):
        step()
    sync(device)
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    sync(device)
    return steps / (time.perf_counter() - t0)


def pd_hold(device: str | torch.device) -> Callable:
    """``action(td)``: leg torques of a PD hold of the initial pose as fractions of the limits, phase rate 0 (the
    torque-mode action that keeps robots standing, so the physics is the same in every benchmark)."""
    as_t = lambda x: torch.as_tensor(x, dtype=torch.float32, device=device)
    kp, kv, limits = as_t(robot.LEG_KP), as_t(robot.LEG_KV), as_t(robot.LEG_TORQUE_LIMITS)
    q0, legs = as_t(robot.INIT_JOINT_POS[:robot.NUM_LEG_JOINTS]), robot.NUM_LEG_JOINTS

    def action(td):
        q, qd = td["joint_pos"][:, :legs], td["joint_vel"][:, :legs]
        torque = ((kp * (q0 - q) - kv * qd) / limits).clamp(-1.0, 1.0)
        return torch.cat((torque, torch.zeros_like(torque[:, :1])), dim=-1)

    return action


def env_rate(env, steps: int, warmup: int = 10, autoreset: bool = False) -> float:
    """Env-steps/s of ``env.step`` (or the collectors' ``step_and_maybe_reset``) under the PD-hold action."""
    action = pd_hold(env.device)
    holder = {"td": env.reset()}

    def step() -> None:
        td = holder["td"].set("action", action(holder["td"]))
        holder["td"] = env.step_and_maybe_reset(td)[1] if autoreset else env.step(td)["next"]

    return env.batch_size[0] * per_second(step, steps, env.device, warmup)


# ------------------------------------------------------------------------------------------------ raw ceiling


def raw_stepper(num_worlds: int, device: str = "cuda"):
    """``step()`` of raw mujoco-warp on the backend's model and buffers: a leg PD-hold kernel then ``mujoco_warp.step``
    x 8 (every sensor, every substep), recorded as one graph on CUDA. The ceiling the other benchmarks divide by."""
    import mujoco_warp as mjw
    import warp as wp

    from tocabi_torchrl.sim import add_contact_sensors
    from tocabi_torchrl.sim.buffers import CONTACT_SENSOR_MAXMATCH, NCONMAX, NJMAX
    from tocabi_torchrl.sim.graph import Recorded

    legs = robot.NUM_LEG_JOINTS

    @wp.kernel(enable_backward=False)
    def hold(qpos: wp.array2d(dtype=float), qvel: wp.array2d(dtype=float), q0: wp.array(dtype=float),
             kp: wp.array(dtype=float), kv: wp.array(dtype=float), ctrl: wp.array2d(dtype=float)):
        w, j = wp.tid()
        ctrl[w, j] = kp[j] * (q0[j] - qpos[w, 7 + j]) - kv[j] * qvel[w, 6 + j]

    mj = add_contact_sensors(robot.load_spec()).compile()
    wp_device = wp.get_device(device)
    with wp.ScopedDevice(wp_device):
        m = mjw.put_model(mj)
        m.opt.contact_sensor_maxmatch = CONTACT_SENSOR_MAXMATCH  # the backend's settings
        m.opt.warn_overflow = 0
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
            for _ in range(SUBSTEPS):
                mjw.step(m, d)

        body()  # compile before recording
        wp.synchronize_device(wp_device)
        graph = Recorded(body, wp_device)
    # What sim_throughput reuses for the backend side: the state, the model and the PD kernel with its constants.
    graph.data, graph.model, graph.hold_launch = d, mj, (hold, consts)
    return graph


def raw_policy_steps_per_second(num_worlds: int, steps: int, device: str = "cuda", warmup: int = 20) -> float:
    """Policy steps/s (worlds x control steps per second) of :func:`raw_stepper`."""
    step = raw_stepper(num_worlds, device)
    return num_worlds * per_second(step, steps, device, warmup)


# ------------------------------------------------------------------------------------------------ memory


def device_used_gib(device: str | torch.device = "cuda") -> float | None:
    """Device-wide memory in use (``cudaMemGetInfo``: warp's buffers and the CUDA context too); None on the CPU."""
    if torch.device(device).type != "cuda":
        return None
    free, total = torch.cuda.mem_get_info(torch.device(device))
    return (total - free) / GIB


def rss_gib() -> float:
    """Current resident set of this process (0 where /proc is missing)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024 / GIB
    except OSError:
        pass
    return 0.0


def peak_rss_gib() -> float:
    """Peak resident set of this process (``ru_maxrss`` is KiB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / GIB


class MemoryPeak:
    """Peaks of device memory in use and of this process's RSS, sampled every ``every_s`` while the block runs."""

    def __init__(self, device: str | torch.device = "cuda", every_s: float = 0.05):
        self.device, self.every_s = device, every_s
        self.device_gib, self.rss_gib = None, 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _sample(self) -> None:
        used = device_used_gib(self.device)
        if used is not None:
            self.device_gib = max(self.device_gib or 0.0, used)
        self.rss_gib = max(self.rss_gib, rss_gib())

    def _run(self) -> None:
        while not self._stop.wait(self.every_s):
            self._sample()

    def __enter__(self) -> MemoryPeak:
        self._sample()
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self._sample()


def torch_peaks() -> dict:
    """The torch allocator's peaks since the process started (zeros on the CPU)."""
    cuda = torch.cuda.is_available() and torch.cuda.is_initialized()
    return {"torch_peak_allocated_gib": torch.cuda.max_memory_allocated() / GIB if cuda else 0.0,
            "torch_peak_reserved_gib": torch.cuda.max_memory_reserved() / GIB if cuda else 0.0}


# ------------------------------------------------------------------------------------------------ the library


def config(preset: str = "default", **overrides):
    """A training config of ``preset`` with ``overrides`` (the benchmarks' one door into the config)."""
    from tocabi_torchrl.rl.config import preset_config

    return preset_config(preset, **overrides)


def parse_overrides(items: Sequence[str]) -> dict:
    """``FIELD=VALUE`` strings as typed config overrides; a clear error names an unknown field."""
    from tocabi_torchrl.rl.config import PPOConfig, _parse_value

    defaults, out = PPOConfig(), {}
    for item in items:
        field, _, value = item.partition("=")
        if not hasattr(defaults, field):
            raise SystemExit(f"--set {item}: the training config has no field {field!r}")
        kind = type(getattr(defaults, field))
        if kind is tuple:  # sizes such as actor_hidden: comma-separated integers
            out[field] = tuple(int(x) for x in value.split(",") if x)
        else:
            out[field] = _parse_value(bool, value) if kind is bool else kind(value)
    return out


def train(cfg, env=None):
    """Train ``cfg``; returns the trainer's result and its logged metric rows."""
    from tocabi_torchrl.rl.trainer import train as run

    result = run(cfg, env=env)
    return result, read_metrics(result.run_dir / "metrics.csv")


def window_rate(rows: Sequence[dict], skip: int = 1) -> float | None:
    """Env-steps/s between the ``skip``-th logged row and the last of the longest process segment (``wall_s``
    restarts when a run resumes); None with too few rows."""
    segments: list[list[dict]] = [[]]
    for row in rows:
        if segments[-1] and float(row["wall_s"]) < float(segments[-1][-1]["wall_s"]):
            segments.append([])
        segments[-1].append(row)
    rows = max(segments, key=len)
    if len(rows) <= skip + 1:
        return None
    a, b = rows[skip], rows[-1]
    return (float(b["env_steps"]) - float(a["env_steps"])) / (float(b["wall_s"]) - float(a["wall_s"]))


def run_child(module: str, args: Sequence[str], env: dict | None = None, timeout: float | None = None) -> dict:
    """Run ``python -m benchmarks.<module> --child ARGS`` in a fresh process (its memory peaks are its own) and return
    the JSON of its ``RESULT`` line; a clear error with the output's tail when it fails."""
    cmd = [sys.executable, "-m", f"benchmarks.{module}", "--child", *args]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False, timeout=timeout,
                          cwd=Path(__file__).resolve().parents[1], env={**os.environ, **(env or {})})
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    if proc.returncode != 0 or not lines:
        raise RuntimeError(f"{' '.join(cmd)} failed (exit {proc.returncode}):\n{proc.stdout[-3000:]}"
                           f"{proc.stderr[-3000:]}")
    return json.loads(lines[-1][len("RESULT "):])


def child_result(record: dict) -> None:
    """The ``RESULT`` line :func:`run_child` reads."""
    print("RESULT " + json.dumps(record), flush=True)


# ------------------------------------------------------------------------------------------------ reports


def table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A markdown table, numbers right-aligned."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---:|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(map(str, r)) + " |" for r in rows])


def page(title: str, data: dict, body: str) -> str:
    """A report page: title with the device, the command that made it, then ``body``."""
    m = data["meta"]
    return f"# {title} ({m['gpu']}, {m['date']})\n\nCommand: `{m['command']}`\n\n{body.strip()}\n"


def write_json(path: str | Path, data: dict) -> Path:
    """``data`` as indented JSON, atomically."""
    return atomic_write_text(Path(path), json.dumps(data, indent=2) + "\n")


def publish(out: str | Path, name: str, data: dict, render: Callable[[dict, Path], str]) -> str:
    """Write ``<out>/<name>.json`` and the page ``render(data, out)`` as ``<name>.md`` (plots beside it)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / f"{name}.json", data)
    text = render(data, out)
    atomic_write_text(out / f"{name}.md", text)
    print(f"wrote {out / name}.json and .md", flush=True)
    return text


def pyplot():
    """matplotlib's pyplot on the Agg backend, or None where matplotlib is not installed (plots are optional)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    return plt


def save(fig, path: Path) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    fig.clf()
    import matplotlib.pyplot as plt

    plt.close(fig)


def fmt(x, spec: str = ",.0f", none: str = "-") -> str:
    """``format(x, spec)``, or ``none`` for a missing value."""
    return none if x is None else format(x, spec)


def build_env(cfg, **kwargs):
    """The training env of ``cfg`` on its device (``kwargs``: the trainer's ``build_env`` options)."""
    from tocabi_torchrl.rl import trainer

    return trainer.build_env(cfg, trainer.resolve_device(cfg.device), **kwargs)


def train_wrapping_policy(cfg, env, wrap: Callable):
    """``train(cfg, env)`` with the collector's policy replaced by ``wrap(policy)`` (the soak's fault injector), so
    that what the wrapper does to actions also reaches PPO's rollout."""
    from tocabi_torchrl.rl import trainer

    make_collector = trainer.make_collector

    def wrapped(cfg_, env_, actor, device, total_frames=-1):
        return make_collector(cfg_, env_, wrap(actor), device, total_frames)

    trainer.make_collector = wrapped  # train() builds its collector through this module attribute
    try:
        return train(cfg, env=env)
    finally:
        trainer.make_collector = make_collector


def read_checkpoint(path):
    """A checkpoint (file or run folder) as a dict, loaded with ``weights_only=True``."""
    from tocabi_torchrl.rl.checkpoint import read_checkpoint as read

    return read(path)


def config_from_checkpoint(state: dict, path):
    """The training config a checkpoint was saved with."""
    from tocabi_torchrl.rl.checkpoint import config_from_checkpoint as read

    return read(state, path)


def gait_test(cfg, state: dict, path, command, out, num_envs: int, seconds: float, device: str, envs: dict) -> dict:
    """Evaluate checkpoint ``state`` deterministically at a fixed ``command`` (vx, vy); returns the evaluation's
    summary. ``envs`` caches one env per command across checkpoints (building one costs more than the test)."""
    import torch

    from tocabi_torchrl.rl.checkpoint import apply_checkpoint
    from tocabi_torchrl.rl.evaluate import _fixed_command, evaluate_policy
    from tocabi_torchrl.rl.trainer import build_agent
    from tocabi_torchrl.rl.trainer import build_env as build

    device = torch.device(device)
    if command not in envs:
        envs[command] = build(cfg, device, num_envs=num_envs, command=_fixed_command(command))
    env = envs[command]
    agent = build_agent(cfg, env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1], device)
    apply_checkpoint(state, agent, env=env, path=path)
    return evaluate_policy(agent.actor, cfg, out, num_envs=num_envs, device=device, seconds=seconds, command=command,
                           video_envs=0, env=env, progress=False)
