"""Compile the simulator's CUDA kernels ahead of time, on any machine, with no GPU needed.

    python -m tocabi_torchrl.precompile --arch 90             # H100 / H200 (sm_90), into warp's own cache
    python -m tocabi_torchrl.precompile --arch 90 --out DIR   # a kernel cache folder to carry to the GPU machine

On a new GPU machine the first mujoco-warp step compiles ~50 kernel modules for 3-4 minutes (an H100 host: 194 s,
three collision kernels alone ~110 s). warp compiles a module for a GPU architecture with NVRTC, which runs on the
CPU, and caches the binary under a name made of the module's name and the hash of its code and options (the block
size among them), whatever machine built it. So the cache can be filled where no GPU is (a login node, a laptop,
CI) and used where one is: copy the folder's contents into the GPU machine's kernel cache (the folder warp prints as
"Kernel cache" when it starts, e.g. ``~/.cache/warp/1.19.0``), or set ``warp.config.kernel_cache_dir`` there to it.

How: the env runs a few steps on warp's CPU device with each reset pass while every kernel launch is noted with the
block size it asks for; each launched module is then compiled for ``--arch`` at each of those block sizes and its
default with warp's ahead-of-time compiler (:func:`warp.compile_aot_module`): a CUBIN for the architecture, which
warp loads where the GPU's driver is older than warp's CUDA toolkit, and a PTX for ``min(arch, warp's PTX target)``,
which it loads where the driver is as new or newer.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

__all__ = ["collect_launches", "compile_modules", "precompile"]


@contextlib.contextmanager
def _noting_launches(seen: dict):
    """``warp.launch`` and ``warp.launch_tiled`` note each kernel's module and requested block size in ``seen``
    (name -> (module, set of block sizes; None: the module's default)), restored on exit."""
    import warp as wp

    originals = {name: getattr(wp, name) for name in ("launch", "launch_tiled")}

    def noting(inner):
        def launch(kernel, *args, **kwargs):
            seen.setdefault(kernel.module.name, (kernel.module, set()))[1].add(kwargs.get("block_dim"))
            return inner(kernel, *args, **kwargs)

        return launch

    for name, inner in originals.items():
        setattr(wp, name, noting(inner))
    try:
        yield
    finally:
        for name, inner in originals.items():
            setattr(wp, name, inner)


def collect_launches(num_envs: int = 2, steps: int = 2) -> dict:
    """The warp modules the walking env launches (name -> (module, block sizes)), found by stepping it on warp's CPU
    device with each reset pass (``env.sim.reset_pass``); the block sizes are those the launches asked for, plus the
    module's default."""
    import torch

    from . import make_env
    from .envs import TocabiWalkConfig

    seen: dict = {}
    with _noting_launches(seen):
        for reset_pass in ("full", "reduced"):
            config = TocabiWalkConfig()
            config.sim.backend, config.sim.reset_pass = "warp", reset_pass
            env = make_env(num_envs, "cpu", config=config, sync_free_resets=True)
            td = env.reset()
            for _ in range(steps):
                td.set("action", torch.zeros(num_envs, env.action_spec.shape[-1]))
                td = env.step_and_maybe_reset(td)[1]  # the sync-free step runs the reset pass every time
            del env
    return {name: (module, {module.options["block_dim"] if b is None else b for b in sizes} |
                   {module.options["block_dim"]}) for name, (module, sizes) in seen.items()}


def compile_modules(launches: dict, arch: int, out: str | os.PathLike | None = None, workers: int | None = None,
                    progress=print) -> dict[str, str]:
    """Compile each module of ``launches`` (name -> (module, block sizes)) for CUDA architecture ``arch`` at each
    block size into the kernel cache folder ``out`` (warp's own if None), in the sub-folders a GPU run looks for;
    returns name -> "compiled" or the one-line error of a module that failed (the others are still compiled)."""
    import warp as wp
    from warp._src.context import runtime

    ptx_arch = min(arch, runtime.default_ptx_arch)

    def one(item):
        name, (module, sizes) = item
        t0, default = time.perf_counter(), module.options["block_dim"]
        try:
            for size in sorted(sizes):
                module.options["block_dim"] = size  # part of the module's hash, so of the folder's name
                where = None if out is None else Path(out) / module.get_module_identifier()
                wp.compile_aot_module(module, arch=arch, module_dir=where, use_ptx=False)
                wp.compile_aot_module(module, arch=ptx_arch, module_dir=where, use_ptx=True)
        except Exception as err:  # noqa: BLE001 - reported per module; one failure must not stop the others
            return name, f"failed: {type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"
        finally:
            module.options["block_dim"] = default
        progress(f"  {name} (block sizes {', '.join(map(str, sorted(sizes)))}): {time.perf_counter() - t0:.1f} s")
        return name, "compiled"

    workers = workers or min(8, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count())
    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:  # warp generates code under a lock, builds apart
        return dict(pool.map(one, sorted(launches.items())))


def precompile(arch: int, out: str | os.PathLike | None = None, workers: int | None = None,
               progress=print) -> dict[str, str]:
    """:func:`collect_launches` then :func:`compile_modules` into the kernel cache folder ``out`` (warp's own if
    None). Returns each module's outcome. Raises ``ValueError`` for an architecture warp's NVRTC cannot target."""
    import warp as wp

    wp.init()
    from warp._src.context import runtime

    supported = sorted(getattr(runtime, "nvrtc_supported_archs", None) or ())
    if supported and arch not in supported:
        raise ValueError(f"warp {wp.__version__}'s NVRTC cannot compile for sm_{arch}; it targets "
                         f"{', '.join(map(str, supported))}")
    target = Path(out).expanduser() if out is not None else Path(wp.config.kernel_cache_dir)
    progress(f"stepping the walking env on warp's CPU device to find the kernels it launches (its CPU kernels go to "
             f"{wp.config.kernel_cache_dir})")
    launches = collect_launches()
    progress(f"compiling {len(launches)} modules for sm_{arch} into {target} (NVRTC on the CPU; a few minutes)")
    t0 = time.perf_counter()
    outcome = compile_modules(launches, arch, None if out is None else target, workers, progress)
    failed = {k: v for k, v in outcome.items() if v != "compiled"}
    progress(f"done in {time.perf_counter() - t0:.0f} s: {len(outcome) - len(failed)} modules compiled for "
             f"sm_{arch}, {len(failed)} failed" + "".join(f"\n  {k}: {v}" for k, v in failed.items()))
    return outcome


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--arch", type=int, required=True,
                        help="CUDA compute capability without the dot: 90 for H100/H200, 89 for L40/RTX 40, 80 for A100")
    parser.add_argument("--out", default=None,
                        help="kernel cache folder to fill (default: warp's own, e.g. ~/.cache/warp/<version>)")
    parser.add_argument("--workers", type=int, default=None, help="parallel compiles (default: the CPUs, at most 8)")
    args = parser.parse_args(argv)
    try:
        outcome = precompile(args.arch, args.out, args.workers)
    except ValueError as err:
        parser.error(str(err))
    return 0 if all(v == "compiled" for v in outcome.values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
