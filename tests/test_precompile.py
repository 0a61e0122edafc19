"""tocabi_torchrl.sim.precompile: the simulator's CUDA kernels compile for a GPU architecture on this CPU-only machine,
into the folders a GPU run looks for (warp names them by module and hash, the same on any machine)."""

from __future__ import annotations

import pytest

wp = pytest.importorskip("warp")

from tocabi_torchrl.sim import kernels, precompile


def _warp_cpu() -> bool:
    try:
        wp.init()
        return wp.get_device("cpu") is not None
    except (RuntimeError, ValueError):
        return False


def test_a_module_compiles_for_sm90_into_the_folder_a_gpu_run_reads(tmp_path):
    module = wp.get_module(kernels.__name__)
    said = []
    outcome = precompile.compile_modules({module.name: module}, arch=90, out=tmp_path, progress=said.append)
    assert outcome == {module.name: "compiled"} and said and module.name in said[0]
    name = module.get_module_identifier()  # wp_<module>_<first 7 hex of its hash>: what a GPU run loads
    assert name.startswith(f"wp_{module.name}_")
    assert (tmp_path / name / f"{name}.sm90.cubin").stat().st_size > 1000 and (tmp_path / name / f"{name}.meta").is_file()


def test_function_only_modules_are_not_failures_and_a_failure_is_reported_not_raised(tmp_path):
    import mujoco_warp  # noqa: F401 - registers its modules

    functions_only = wp.get_module("mujoco_warp._src.math")  # functions, compiled into the modules that call them
    broken = wp.get_module(kernels.__name__)
    outcome = precompile.compile_modules({"math": functions_only, "bad arch": broken}, arch=1, out=tmp_path,
                                         progress=lambda line: None)
    assert outcome["math"] == "no kernels"
    assert outcome["bad arch"].startswith("failed: ")  # sm_1 does not exist: named, and the other module still ran
    with pytest.raises(SystemExit):
        precompile.main(["--arch", "7"])  # not a compute capability: refused before anything is built


@pytest.mark.skipif(not _warp_cpu(), reason="warp's CPU device is unavailable")
def test_the_walking_env_registers_the_modules_a_gpu_run_compiles():
    modules = precompile.collect_modules()
    # The costliest on an H100 host's first run (docs/benchmarks.md): the collision kernels, forward, smooth, and ours.
    for name in ("mujoco_warp._src.forward", "mujoco_warp._src.smooth", "mujoco_warp._src.sensor",
                 kernels.__name__):
        assert name in modules
    assert sum(name.startswith("ccd_kernel_builder") for name in modules) >= 3
