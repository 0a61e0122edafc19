"""Compile the simulator's CUDA kernels ahead of time, on any machine, with no GPU needed.

    python -m tocabi_torchrl.sim.precompile --arch 90             # H100 / H200 (sm_90), into warp's own cache
    python -m tocabi_torchrl.sim.precompile --arch 90 --out DIR   # a kernel cache folder to carry to the GPU machine

On a new GPU machine the first mujoco-warp step compiles ~50 kernel modules for 3-4 minutes (an H100 host: 194 s,
three collision kernels alone ~110 s). warp compiles a module for a GPU architecture with NVRTC, which runs on the
CPU, and caches the binary under a name made of the module's name and the hash of its code and options, whatever
machine built it. So the cache can be filled where no GPU is (a login node, a laptop, CI) and used where one is:
copy the folder's contents into the GPU machine's kernel cache (the folder warp prints as "Kernel cache" when it
starts, e.g. ``~/.cache/warp/1.19.0``), or set ``warp.config.kernel_cache_dir`` there to the folder.

How: the env runs a few steps on warp's CPU device with each reset pass, which builds every kernel module this robot's
model needs, then each module is compiled for ``--arch`` with warp's ahead-of-time compiler (:func:`warp.compile_aot_module`,
CUBIN). A few solver modules that mujoco-warp builds only on a CUDA device (its tiled Cholesky and line-search
kernels) are not seen on the CPU; they still compile on the GPU's first run (~35 s on an H100 host).
"""

from __future__ import annotations

import argparse
import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

__all__ = ["collect_modules", "compile_modules", "precompile"]


def collect_modules(num_envs: int = 2, steps: int = 2) -> dict:
    """The warp modules (name -> ``warp.Module``) that stepping and resetting the walking env builds, found by
    running it on warp's CPU device with both reset passes (``env.sim.reset_pass``)."""
    import torch
    import warp as wp

    from .. import make_env
    from ..envs import TocabiWalkConfig

    for reset_pass in ("full", "reduced"):
        config = TocabiWalkConfig()
        config.sim.backend, config.sim.reset_pass = "warp", reset_pass
        env = make_env(num_envs, "cpu", config=config, sync_free_resets=True)
        td = env.reset()
        for _ in range(steps):
            td.set("action", torch.zeros(num_envs, env.action_spec.shape[-1]))
            td = env.step_and_maybe_reset(td)[1]  # the sync-free step runs the reset pass every time
        del env
    try:  # warp lists its modules nowhere public; force_load(modules=None) reads the same registry
        from warp._src.context import user_modules
    except ImportError as err:
        raise RuntimeError(f"warp {wp.__version__} keeps no module registry where this tool reads it "
                           "(warp._src.context.user_modules); it was written for warp 1.19") from err
    return dict(user_modules)


def compile_modules(modules: dict, arch: int, out: str | os.PathLike | None = None, workers: int | None = None,
                    progress=print) -> dict[str, str]:
    """Compile each module for CUDA architecture ``arch`` (e.g. 90) into the kernel cache folder ``out`` (warp's
    own if None), each in the sub-folder a GPU run looks for; returns name -> "compiled", "no kernels" (a module of
    functions only, compiled into the modules that call them) or the one-line error of a module that failed (the
    others are still compiled)."""
    import warp as wp

    def one(item):
        name, module = item
        t0 = time.perf_counter()
        where = None if out is None else Path(out) / module.get_module_identifier()
        try:
            wp.compile_aot_module(module, arch=arch, module_dir=where, use_ptx=False)
        except Exception as err:  # noqa: BLE001 - reported per module; one failure must not stop the others
            text = str(err).splitlines()[0] if str(err) else ""
            if "No compilable kernels" in text:
                return name, "no kernels"
            return name, f"failed: {type(err).__name__}: {text}"
        progress(f"  {name}: {time.perf_counter() - t0:.1f} s")
        return name, "compiled"

    with ThreadPoolExecutor(max_workers=workers or os.cpu_count() or 1) as pool:
        return dict(pool.map(one, sorted(modules.items())))


def precompile(arch: int, out: str | os.PathLike | None = None, workers: int | None = None,
               progress=print) -> dict[str, str]:
    """:func:`collect_modules` then :func:`compile_modules` into the kernel cache folder ``out`` (warp's own if
    None). Returns each module's outcome."""
    import warp as wp

    wp.init()
    target = Path(out).expanduser() if out is not None else Path(wp.config.kernel_cache_dir)
    progress(f"building the walking env on warp's CPU device to find its kernel modules (its CPU kernels go to "
             f"{wp.config.kernel_cache_dir})")
    modules = collect_modules()
    progress(f"compiling {len(modules)} modules for sm_{arch} into {target} (NVRTC on the CPU; a few minutes)")
    t0 = time.perf_counter()
    outcome = compile_modules(modules, arch, out, workers, progress)
    failed = {k: v for k, v in outcome.items() if v not in ("compiled", "no kernels")}
    compiled = sum(v == "compiled" for v in outcome.values())
    progress(f"done in {time.perf_counter() - t0:.0f} s: {compiled} modules compiled for sm_{arch}, "
             f"{len(failed)} failed" + "".join(f"\n  {k}: {v}" for k, v in failed.items()))
    return outcome


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--arch", type=int, required=True,
                        help="CUDA compute capability without the dot: 90 for H100/H200, 89 for L40/RTX 40, 80 for A100")
    parser.add_argument("--out", default=None,
                        help="kernel cache folder to fill (default: warp's own, e.g. ~/.cache/warp/<version>)")
    parser.add_argument("--workers", type=int, default=None, help="parallel compiles (default: the CPU count)")
    args = parser.parse_args(argv)
    if not 50 <= args.arch <= 130:
        parser.error(f"--arch {args.arch} is not a CUDA compute capability like 80, 89 or 90")
    outcome = precompile(args.arch, args.out, args.workers)
    return 0 if all(v in ("compiled", "no kernels") for v in outcome.values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
