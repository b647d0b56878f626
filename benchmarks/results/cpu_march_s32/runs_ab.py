"""The march per sample against runs on the CPU (blocks on in both), kernels_render's shell
scene, median of six: `PYTHONPATH=. python benchmarks/results/cpu_march_s32/runs_ab.py`."""

import time

from benchmarks import kernels_render as kr
from fastenerf.kernels import raymarch as rm

for n, res in ((1024, 64), (4096, 128)):
    grid, shell, o, d = kr._scene("cpu", n, res)
    dt = grid.step_size
    box = [-1.0, -1, -1, 1, 1, 1]
    for runs in (False, True):  # compile both
        rm.RUNS = runs
        rm.march_rays(o, d, box, grid, 0.0, None, 0.0, dt, dt, 1024, None)
    times = {False: [], True: []}
    for _ in range(6):
        for runs in (False, True):
            rm.RUNS = runs
            t = time.perf_counter()
            out = rm.march_rays(o, d, box, grid, 0.0, None, 0.0, dt, dt, 1024, None)
            times[runs].append((time.perf_counter() - t) * 1e3)
    S = out[1].numel()
    print(n, res, "samples", S, {k: round(sorted(v)[len(v) // 2], 2) for k, v in times.items()})
