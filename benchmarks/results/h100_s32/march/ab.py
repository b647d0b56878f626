# ruff: noqa: B023, B905, E501, E702, E731  (the script as it ran on the device, formatted)
"""march_rays and march_rays_fixed: runs on/off x blocks on/off, kernels_render's shell scene."""

import json
import os

import torch

from benchmarks import kernels_render as kr
from benchmarks.timing import time_ms
from fastenerf.kernels import raymarch as rm
from fastenerf.kernels.occupancy import OccupancyGrid
from fastenerf.kernels.raymarch_fixed import empty_fixed_samples, march_rays_fixed

res = {}
for n in (65536, 16384):
    grid, shell, o, d = kr._scene("cuda", n, 128)
    g1 = OccupancyGrid(grid.aabb_list, 128, 1, device="cuda", block=1)
    g1.load_state_dict(grid.state_dict())
    dt = grid.step_size
    box = [-1.0, -1, -1, 1, 1, 1]
    rm.RUNS = False
    ref = rm.march_rays(o, d, box, g1, 0.0, None, 0.0, dt, dt, 1024, None)
    cap = int(ref[1].numel() * 1.25)
    buf = empty_fixed_samples(n, cap, "cuda")
    for rep in range(2):
        for runs in (False, True):
            for g in (g1, grid):
                rm.RUNS = runs
                args = (o, d, box, g, 0.0, None, 0.0, dt, dt, 1024, None)
                out = rm.march_rays(*args)
                same = all(torch.equal(x, y) for x, y in zip(out, ref))
                a = time_ms(lambda: rm.march_rays(*args), "cuda", 30)
                b = time_ms(lambda: march_rays_fixed(*args, capacity=cap, out=buf), "cuda", 30)
                key = f"{n} runs={runs} block={g.block} rep={rep}"
                res[key] = {"march_rays_ms": a, "fixed_ms": b, "same_as_before": same}
                print(key, round(a, 4), round(b, 4), same, flush=True)
    tm = time_ms(lambda: kr.torch_march(o, d, box, grid.binary[0], dt, 1024), "cuda", 10, warmup=1)
    res[f"{n} torch_march_ms"] = tm
    print(n, "torch", round(tm, 4), flush=True)
json.dump(res, open(os.path.join(os.environ.get("OUT", "."), "ab.json"), "w"), indent=1)
