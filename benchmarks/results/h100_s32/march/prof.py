# ruff: noqa: B023, B905, E501, E702, E731  (the script as it ran on the device, formatted)
"""GPU time per kernel of march_rays and march_rays_fixed on the kernels_render shell scene."""

import os

import torch
from torch.profiler import ProfilerActivity, profile

from benchmarks import kernels_render as kr
from fastenerf.kernels.raymarch import march_rays
from fastenerf.kernels.raymarch_fixed import empty_fixed_samples, march_rays_fixed

for n in (65536,):
    grid, shell, o, d = kr._scene("cuda", n, 128)
    dt = grid.step_size
    box = [-1.0, -1, -1, 1, 1, 1]
    args = (o, d, box, grid, 0.0, None, 0.0, dt, dt, 1024, None)
    ref = march_rays(*args)
    cap = int(ref[1].numel() * 1.25)
    buf = empty_fixed_samples(n, cap, "cuda")
    for _ in range(3):
        march_rays(*args)
        march_rays_fixed(*args, capacity=cap, out=buf)
    torch.cuda.synchronize()
    for name, fn in (
        ("march_rays", lambda: march_rays(*args)),
        ("fixed", lambda: march_rays_fixed(*args, capacity=cap, out=buf)),
    ):
        with profile(activities=[ProfilerActivity.CUDA, ProfilerActivity.CPU]) as p:
            for _ in range(10):
                fn()
            torch.cuda.synchronize()
        t = p.key_averages().table(sort_by="cuda_time_total", row_limit=14)
        print(name, n)
        print(t)
        open(os.path.join(os.environ["OUT"], f"prof_{name}.txt"), "w").write(t)
