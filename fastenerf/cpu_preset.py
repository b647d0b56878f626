"""The ngp backend's CPU preset: sizes for a step a 2-core CPU takes in tens of milliseconds.

On a GPU a step is ~256k samples through a 16-level, 2^19-row hash grid; a CPU runs Warp's
kernels on one thread and the MLPs on a core or two, so every size is cut to what the CPU's
step can afford (measured with `benchmarks.cpu_preset`, figures in benchmarks/RESULTS.md):
fewer, smaller hash levels, narrower MLPs, a coarse occupancy grid, longer marching steps and
fewer rays per step (the fast preset's longer event windows are not the CPU's alone:
`fastenerf.config.FAST_WINDOW_FRACTION`).
`TrainConfig.resolved` applies it for ngp on a CPU device, to the options the user left unset,
so it is recorded in the run's config.json; GPU runs never see it.
"""

from __future__ import annotations

from typing import Any

from .backends import get_option, set_option

# Backend options (see fastenerf.backends.NGPOptions) of the CPU preset.
NGP_CPU_OPTIONS: dict[str, Any] = {
    "early_steps": 0,  # the GPU's early cone was not measured with these sizes
    "log2_table_size": 14,
    "n_levels": 8,
    "max_resolution": 256,
    "grid_resolution": 32,
    "hidden": 32,
    # the smallest step √3 · the field's box side / 64 (the GPU's default: / 1024)
    "diagonal_steps": 64,
}
# Pixels per step (each rendered at the window's start and end).
NGP_CPU_RAYS = 256


def ngp_cpu_options(options: dict | None) -> dict:
    """`options` (ngp backend options, flat or nested) with every preset key it leaves unset
    filled in."""
    out = dict(options or {})
    for key, value in NGP_CPU_OPTIONS.items():
        if get_option("ngp", out, key) is None:
            out = set_option("ngp", out, key, value)
    return out
