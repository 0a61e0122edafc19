"""tocabi_torchrl.precompile: the simulator's CUDA kernels compile for a GPU architecture on this CPU-only machine,
into the folders a GPU run looks for (warp names them by module and hash, block size included, on any machine)."""

from __future__ import annotations

import pytest

wp = pytest.importorskip("warp")

from warp_cpu import warp_cpu_available

from tocabi_torchrl import precompile
from tocabi_torchrl.sim import kernels


def test_a_module_compiles_for_sm90_at_each_block_size_into_the_folders_a_gpu_run_reads(tmp_path):
    module = wp.get_module(kernels.__name__)
    default = module.options["block_dim"]
    said = []
    outcome = precompile.compile_modules({module.name: (module, {32, default})}, arch=90, out=tmp_path,
                                         progress=said.append)
    assert outcome == {module.name: "compiled"} and said and module.name in said[0]
    assert module.options["block_dim"] == default  # put back
    names = set()
    for size in (32, default):
        module.options["block_dim"] = size
        names.add(name := module.get_module_identifier())  # wp_<module>_<7 hex of its hash>: what a GPU run loads
        module.options["block_dim"] = default
        folder = tmp_path / name
        # CUBIN where the driver is older than warp's toolkit; PTX, at warp's PTX target (sm_75 here), where not.
        assert (folder / f"{name}.sm90.cubin").stat().st_size > 1000 and (folder / f"{name}.meta").is_file()
        assert list(folder.glob(f"{name}.sm*.ptx"))
    assert len(names) == 2  # the block size is part of the name


def test_a_failure_is_reported_per_module_not_raised(tmp_path):
    module = wp.get_module(kernels.__name__)
    default = module.options["block_dim"]
    outcome = precompile.compile_modules({"bad arch": (module, {64})}, arch=1, out=tmp_path, progress=print)
    assert outcome["bad arch"].startswith("failed: ") and module.options["block_dim"] == default
    with pytest.raises(SystemExit):
        precompile.main(["--arch", "7"])  # no NVRTC target: refused by name before anything is built


@pytest.mark.skipif(not warp_cpu_available(), reason="warp's CPU device is unavailable")
def test_the_walking_env_launches_the_modules_a_gpu_run_compiles_at_their_block_sizes():
    launches = precompile.collect_launches()
    # Among the costliest of an H100 host's first run: the collision kernels, forward, smooth, sensors; and ours.
    for name in ("mujoco_warp._src.forward", "mujoco_warp._src.smooth", "mujoco_warp._src.sensor", kernels.__name__):
        assert name in launches
    ccd = [sizes for name, (_, sizes) in launches.items() if name.startswith("ccd_kernel_builder")]
    assert len(ccd) >= 3 and all(64 in sizes for sizes in ccd)
    # Tiled kernels ask for their own block sizes, which name other binaries than the module default's.
    assert any(len(sizes) > 1 for _, sizes in launches.values())
    assert wp.launch.__name__ == "launch" and "noting" not in wp.launch.__qualname__  # warp's own again
