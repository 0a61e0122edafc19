"""Physics backend throughput against raw mujoco-warp stepping of the same model, measured in one run.

    python benchmarks/sim_throughput.py --nworld 1024 4096 16384 --steps 200

For each world count, in the same process, on the same model (the shipped TOCABI with the backend's contact
sensors), with the same buffers (``nconmax``/``njmax``) and the same control:

  * raw: one CUDA graph of [PD kernel, ``mujoco_warp.step`` x 8]; ``mujoco_warp.step`` evaluates every sensor in
    every substep, as it always does;
  * backend: ``WarpSim.step()`` (one graph: ``step2`` + 7 ``step`` with sensor evaluation skipped, a forward pass with
    all sensors, the contact/health flag kernel) after the same PD kernel in its own recorded graph.

The control is a PD hold of the initial pose on the legs (``robot.LEG_KP``/``LEG_KV``, torque written once per
policy step, as a policy would) and the upper-body servo targets, so the worlds stay upright. Reports physics steps/s
(worlds x substeps / s), policy steps/s (worlds / s) and backend/raw (target >= 0.95 at 4096 and 16384 worlds), the
median of ``--repeats`` interleaved timings of ``--steps`` policy steps each. Writes ``sim_throughput.json``, ``.md``
and (with matplotlib) ``.png`` under ``--out`` and prints one table.

``raw_policy_steps_per_second`` is the shared ceiling the env and training benchmarks divide by.
"""

from __future__ import annotations

import argparse
import gc
import json
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Callable

import mujoco
import mujoco_warp as mjw
import numpy as np
import torch
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tocabi_torchrl import robot  # noqa: E402
from tocabi_torchrl.sim import SimConfig, WarpSim, add_contact_sensors  # noqa: E402
from tocabi_torchrl.sim.buffers import CONTACT_SENSOR_MAXMATCH, NCONMAX, NJMAX  # noqa: E402
from tocabi_torchrl.sim.graph import Recorded  # noqa: E402

SUBSTEPS = 8
LEGS = robot.NUM_LEG_JOINTS


@wp.kernel(enable_backward=False)
def pd_hold(
    qpos: wp.array2d(dtype=float),
    qvel: wp.array2d(dtype=float),
    q0: wp.array(dtype=float),
    kp: wp.array(dtype=float),
    kv: wp.array(dtype=float),
    ctrl: wp.array2d(dtype=float),
):
    """Leg torque [N·m] of a PD hold of ``q0``: ``kp (q0 - q) - kv q̇`` (joint j sits at qpos 7+j, qvel 6+j)."""
    w, j = wp.tid()
    ctrl[w, j] = kp[j] * (q0[j] - qpos[w, 7 + j]) - kv[j] * qvel[w, 6 + j]


class _PdHold:
    """The PD kernel's constants on one device; ``launch(data)`` writes the leg torques of every world."""

    def __init__(self, device: wp.Device):
        with wp.ScopedDevice(device):
            self.q0 = wp.array(robot.INIT_JOINT_POS[:LEGS].astype(np.float32), dtype=float)
            self.kp = wp.array(robot.LEG_KP.astype(np.float32), dtype=float)
            self.kv = wp.array(robot.LEG_KV.astype(np.float32), dtype=float)

    def launch(self, d: mjw.Data) -> None:
        wp.launch(pd_hold, dim=(d.nworld, LEGS), inputs=[d.qpos, d.qvel, self.q0, self.kp, self.kv], outputs=[d.ctrl])


def build_model() -> mujoco.MjModel:
    """The model both sides step: the shipped robot with the backend's contact sensors."""
    return add_contact_sensors(robot.load_spec()).compile()


def _initial_state(n: int) -> tuple[np.ndarray, np.ndarray]:
    qpos = np.tile(robot.INIT_QPOS, (n, 1)).astype(np.float32)
    ctrl = np.zeros((n, robot.NUM_JOINTS), dtype=np.float32)
    ctrl[:, LEGS:] = robot.INIT_JOINT_POS[LEGS:]
    return qpos, ctrl


class RawStepper:
    """``mujoco_warp.step`` x substeps after the PD kernel, all in one recorded graph (the ceiling)."""

    def __init__(self, mj: mujoco.MjModel, n: int, device: str, substeps: int = SUBSTEPS):
        self.device = wp.get_device(device)
        with wp.ScopedDevice(self.device):
            self.m = mjw.put_model(mj)
            # The backend's settings: same contact-sensor slots, no in-kernel overflow prints.
            self.m.opt.contact_sensor_maxmatch = CONTACT_SENSOR_MAXMATCH
            self.m.opt.warn_overflow = 0
            self.d = mjw.make_data(mj, nworld=n, nconmax=NCONMAX, njmax=NJMAX)
            qpos, ctrl = _initial_state(n)
            self.d.qpos.assign(qpos)
            self.d.ctrl.assign(ctrl)
            mjw.forward(self.m, self.d)
            self.pd = _PdHold(self.device)

            def body() -> None:
                self.pd.launch(self.d)
                for _ in range(substeps):
                    mjw.step(self.m, self.d)

            body()  # compile before recording
            wp.synchronize_device(self.device)
            self.graph = Recorded(body, self.device)

    def __call__(self) -> None:
        self.graph()

    def base_height(self) -> np.ndarray:
        return self.d.qpos.numpy()[:, 2]


class BackendStepper:
    """The same PD kernel (its own recorded graph), then ``WarpSim.step()``."""

    def __init__(self, mj: mujoco.MjModel, n: int, device: str, substeps: int = SUBSTEPS):
        self.sim = WarpSim(SimConfig(num_worlds=n, device=device, substeps=substeps), model=mj)
        qpos, ctrl = _initial_state(n)
        dev = self.sim.device
        self.sim.reset(
            torch.ones(n, dtype=torch.bool, device=dev),
            torch.as_tensor(qpos, device=dev),
            torch.zeros(self.sim.nv, device=dev),
            torch.as_tensor(ctrl, device=dev),
        )
        self.pd = _PdHold(self.sim.wp_device)
        with wp.ScopedDevice(self.sim.wp_device):
            _sync(device)  # the reset above ran on torch's stream, this compile launch on warp's
            self.pd.launch(self.sim.wp_data)
            wp.synchronize_device(self.sim.wp_device)
        self.pd_graph = Recorded(lambda: self.pd.launch(self.sim.wp_data), self.sim.wp_device)

    def __call__(self) -> None:
        self.pd_graph()
        self.sim.step()

    def base_height(self) -> np.ndarray:
        return self.sim.base_pos[:, 2].cpu().numpy()


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize(device)


def _seconds(step: Callable[[], None], steps: int, device: str) -> float:
    _sync(device)
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    _sync(device)
    return time.perf_counter() - t0


def raw_policy_steps_per_second(num_worlds: int, steps: int, device: str = "cuda", warmup: int = 20) -> float:
    """Policy steps/s (worlds x control steps per second) of raw mujoco-warp, 8 PD-held substeps per control step."""
    raw = RawStepper(build_model(), num_worlds, device)
    for _ in range(warmup):
        raw()
    rate = num_worlds * steps / _seconds(raw, steps, device)
    del raw
    gc.collect()
    return rate


def _device_used_gib(device: str) -> float | None:
    if not device.startswith("cuda"):
        return None
    free, total = torch.cuda.mem_get_info(torch.device(device))
    return (total - free) / 2**30


def measure(n: int, steps: int, repeats: int, warmup: int, device: str) -> dict:
    """Interleaved timings of raw and backend stepping for ``n`` worlds; medians and their ratio."""
    mj = build_model()
    used0 = _device_used_gib(device)
    raw = RawStepper(mj, n, device)
    used_raw = _device_used_gib(device)
    backend = BackendStepper(mj, n, device)
    used_backend = _device_used_gib(device)
    for _ in range(warmup):
        raw()
        backend()
    t_raw, t_backend = [], []
    for _ in range(repeats):
        t_raw.append(_seconds(raw, steps, device))
        t_backend.append(_seconds(backend, steps, device))
    raw_sps = n * steps / statistics.median(t_raw)
    backend_sps = n * steps / statistics.median(t_backend)
    row = {
        "nworld": n,
        "steps": steps,
        "repeats": repeats,
        "substeps": SUBSTEPS,
        "raw_policy_steps_per_s": raw_sps,
        "raw_physics_steps_per_s": raw_sps * SUBSTEPS,
        "backend_policy_steps_per_s": backend_sps,
        "backend_physics_steps_per_s": backend_sps * SUBSTEPS,
        "ratio_backend_over_raw": backend_sps / raw_sps,
        "upright_raw": float(np.mean(raw.base_height() > 0.8)),
        "upright_backend": float(np.mean(backend.base_height() > 0.8)),
        "backend_healthy": float(backend.sim.healthy.float().mean()),
        "device_gib_raw": None if used0 is None else used_raw - used0,
        "device_gib_backend": None if used0 is None else used_backend - used_raw,
    }
    del raw, backend
    gc.collect()
    _sync(device)
    return row


def _environment(device: str) -> dict:
    if device.startswith("cuda"):
        name = torch.cuda.get_device_name(torch.device(device))
    else:
        name = platform.processor() or platform.machine()
    return {
        "device": device,
        "device_name": name,
        "mujoco": mujoco.__version__,
        "mujoco_warp": mjw.__version__,
        "warp": wp.config.version,
        "torch": torch.__version__,
        "nconmax": NCONMAX,
        "njmax": NJMAX,
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
    }


def _table(rows: list[dict]) -> str:
    lines = [
        "| worlds | raw physics steps/s | backend physics steps/s | raw policy steps/s | backend policy steps/s "
        "| backend / raw | upright raw / backend |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['nworld']} | {r['raw_physics_steps_per_s']:,.0f} | {r['backend_physics_steps_per_s']:,.0f} "
            f"| {r['raw_policy_steps_per_s']:,.0f} | {r['backend_policy_steps_per_s']:,.0f} "
            f"| {r['ratio_backend_over_raw']:.3f} | {r['upright_raw']:.0%} / {r['upright_backend']:.0%} |"
        )
    return "\n".join(lines)


def _markdown(rows: list[dict], env: dict) -> str:
    return (
        "# Physics backend throughput (WarpSim vs raw mujoco-warp)\n\n"
        f"Generated by `python benchmarks/sim_throughput.py` on {env['device_name']} ({env['device']}), "
        f"{env['date']}; mujoco {env['mujoco']}, mujoco-warp {env['mujoco_warp']}, warp {env['warp']}, "
        f"torch {env['torch']}; nconmax={env['nconmax']}, njmax={env['njmax']}, {SUBSTEPS} substeps per policy step, "
        f"median of {rows[0]['repeats']} x {rows[0]['steps']} policy steps.\n\n"
        + _table(rows)
        + "\n\nRaw: one graph of [leg PD kernel, `mujoco_warp.step` x 8] (sensors evaluated in every substep). "
        "Backend: the same PD kernel, then `WarpSim.step()`: `step2` (reusing the previous forward pass) + "
        "7 x `step` with sensors skipped, a forward pass with all sensors so everything describes the post-step state, "
        "and the contact/health kernel. Target: backend / raw >= 0.95 at 4096 and 16384 worlds.\n"
    )


def _plot(rows: list[dict], path: Path) -> bool:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    x = np.arange(len(rows))
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.bar(x - 0.2, [r["raw_policy_steps_per_s"] for r in rows], 0.4, label="raw mujoco-warp")
    ax.bar(x + 0.2, [r["backend_policy_steps_per_s"] for r in rows], 0.4, label="WarpSim")
    for i, r in enumerate(rows):
        ax.annotate(f"{r['ratio_backend_over_raw']:.2f}", (i + 0.2, r["backend_policy_steps_per_s"]), ha="center",
                    va="bottom", fontsize=8)
    ax.set_xticks(x, [str(r["nworld"]) for r in rows])
    ax.set_xlabel("worlds")
    ax.set_ylabel("policy steps / s")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--nworld", type=int, nargs="+", default=[1024, 4096, 16384])
    p.add_argument("--steps", type=int, default=200, help="policy steps per timing")
    p.add_argument("--repeats", type=int, default=3, help="interleaved timings per side (median reported)")
    p.add_argument("--warmup", type=int, default=20)
    p.add_argument("--device", default="cuda")
    p.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "docs" / "benchmarks")
    args = p.parse_args(argv)
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        p.error("CUDA is not available; pass --device cpu for a (slow) smoke run")

    env = _environment(args.device)
    rows = []
    for n in args.nworld:
        rows.append(measure(n, args.steps, args.repeats, args.warmup, args.device))
        r = rows[-1]
        print(f"{n} worlds: raw {r['raw_policy_steps_per_s']:,.0f}, backend {r['backend_policy_steps_per_s']:,.0f} "
              f"policy steps/s, ratio {r['ratio_backend_over_raw']:.3f}", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "sim_throughput.json").write_text(json.dumps({"environment": env, "results": rows}, indent=2) + "\n")
    (args.out / "sim_throughput.md").write_text(_markdown(rows, env))
    _plot(rows, args.out / "sim_throughput.png")
    print(_table(rows))


if __name__ == "__main__":
    main()
