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

import math
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
}
# dt_min = √3 · the box's longest side / NGP_CPU_DIAGONAL_STEPS (the GPU's default: / 1024).
NGP_CPU_DIAGONAL_STEPS = 64
# Pixels per step (each rendered at the window's start and end).
NGP_CPU_RAYS = 256


def cpu_dt_min(aabb, cylinder=None) -> float:
    """The CPU preset's smallest marching step for a scene box (world units).

    aabb: [xmin, ymin, zmin, xmax, ymax, zmax]; cylinder: a CylinderConfig (the ngp field's
    box is the box shrunk to it) or None.
    """
    box = [float(v) for v in aabb] if cylinder is None else cylinder.clip_box(aabb)
    side = max(box[i + 3] - box[i] for i in range(3))
    return math.sqrt(3.0) * side / NGP_CPU_DIAGONAL_STEPS


def ngp_cpu_options(options: dict | None, aabb, cylinder=None) -> dict:
    """`options` (ngp backend options, flat or nested) with every preset key it leaves unset
    filled in (dt_min from the scene's box)."""
    out = dict(options or {})
    preset = {**NGP_CPU_OPTIONS, "dt_min": cpu_dt_min(aabb, cylinder)}
    for key, value in preset.items():
        if get_option("ngp", out, key) is None:
            out = set_option("ngp", out, key, value)
    return out
