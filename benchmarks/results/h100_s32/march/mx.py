# ruff: noqa: B023, B905, E501, E702, E731  (the script as it ran on the device, formatted)
"""march variants on the kernels_render shell scene: threads per block and segments per ray."""

import json
import os

import torch
import warp as wp

from benchmarks import kernels_render as kr
from benchmarks.timing import time_ms
from fastenerf.kernels import common
from fastenerf.kernels import raymarch as rm
from fastenerf.kernels.raymarch import march_rays

res, orig_launch, orig_launcher = {}, wp.launch, common.launcher
for n in (65536, 16384):
    grid, shell, o, d = kr._scene("cuda", n, 128)
    dt = grid.step_size
    box = [-1.0, -1, -1, 1, 1, 1]
    ref = march_rays(o, d, box, grid, 0.0, None, 0.0, dt, dt, 1024, None)
    kern = rm._march_kernel(grid.n_cascades, False, grid.block)
    for bd in (256, 128, 64, 32):
        for seg in (1, 2, 4):
            L = common.Launcher(kern)  # fresh: its recorded launch takes this block_dim
            wp.launch = lambda *a, bd=bd, **k: orig_launch(*a, **{**k, "block_dim": bd})
            common.launcher = lambda k, L=L: L if k is kern else orig_launcher(k)
            f = lambda seg=seg: march_rays(o, d, box, grid, 0.0, None, 0.0, dt, dt, 1024, None, seg)
            same = all(torch.equal(x, y) for x, y in zip(f(), ref))
            ms = time_ms(f, "cuda", 20)
            res[f"{n} bd{bd} seg{seg}"] = [round(ms, 4), same]
            print(n, bd, seg, round(ms, 4), same, flush=True)
            wp.launch, common.launcher = orig_launch, orig_launcher
json.dump(res, open(os.path.join(os.environ.get("OUT", "."), "mx.json"), "w"), indent=1)
