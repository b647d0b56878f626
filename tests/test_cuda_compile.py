"""Every Warp kernel of the training path compiles for the GPU (sm_90 SASS through Warp's
ahead-of-time compile and NVRTC: no GPU needed).

The other kernel tests run the CPU builds. Code under `__CUDA_ARCH__` (the hash grid's vector
loads and reductions, `kernels/vector_memory.py`) and the GPU-only variants (the marcher's
runs) are compiled only for CUDA; this catches an error there here rather than on a lease.
The fused MLP (`kernels/mlp.py`, not wired into training) is left out.
"""

from __future__ import annotations

import importlib
import itertools
import pkgutil

import pytest
import warp as wp

import fastenerf.kernels as kernels_pkg
from fastenerf.fields.ngp import NGPField
from fastenerf.kernels import (
    composite,
    composite_block,
    hashgrid,
    hashgrid_runs,
    occupancy,
    raymarch,
    sh,
)

ARCH = 90  # H100 / H200


def training_kernels() -> list:
    """The package's module-level kernels and its kernel factories at the settings training
    and rendering use (every flag combination where a factory takes flags)."""
    out = []
    for info in pkgutil.iter_modules(kernels_pkg.__path__):
        mod = importlib.import_module(f"fastenerf.kernels.{info.name}")
        out += [v for v in vars(mod).values() if isinstance(v, wp.Kernel)]
    for bf16 in (False, True):  # the features and their gradient in float32 or bfloat16
        out += [*hashgrid._kernels(2, bf16=bf16), hashgrid._tracked_backward(2, bf16)]
        out += [hashgrid_runs.run_backward(2, 4, bf16), *sh._sh_kernels(bf16)]
    for flags in itertools.product((False, True), repeat=4):
        out += [composite._composite_bwd_kernel(*flags)]
        out += [composite_block.composite_bwd_block_kernel(*flags)]
    grid = NGPField([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0], device="cpu").sampler.grid
    out.append(occupancy._lookup_kernel(grid.n_cascades))
    for cylinder, runs in itertools.product((False, True), repeat=2):
        out.append(raymarch._march_kernel(grid.n_cascades, cylinder, grid.block, runs))
        out.append(raymarch._march_kernel(0, False, 1, runs))
    return out


def test_every_training_kernel_compiles_for_sm90(tmp_path):
    wp.init()
    if ARCH not in wp.get_cuda_supported_archs():  # a Warp build without NVRTC (e.g. macOS)
        pytest.skip(f"this Warp build cannot compile for sm_{ARCH}")
    modules = {id(k.module): k.module for k in training_kernels()}
    assert len(modules) >= 40  # the static modules, the hash grid's and the factories'
    failed = []
    for mod in modules.values():
        try:
            wp.compile_aot_module(mod, arch=ARCH, module_dir=tmp_path, use_ptx=False)
        except Exception as e:  # noqa: BLE001 - every failure is listed, not the first only
            if "No compilable kernels" not in str(e):
                failed.append(f"{mod.name}: {str(e).splitlines()[0][:300]}")
    assert not failed, failed
    assert len(list(tmp_path.glob(f"*.sm{ARCH}.cubin"))) >= 40
