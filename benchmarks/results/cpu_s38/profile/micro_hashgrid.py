"""Micro-benchmark of fastenerf.kernels.hashgrid.hash_grid_encode on CPU: forward, backward with
the table gradient only (x.requires_grad False), and backward with table + x gradients; each
Warp kernel timed on its own (CPU launches are synchronous) through a wrapped Launcher.
    cd /work/main && python /work/scratch/s38prof/micro_hashgrid.py [N]"""

import sys
import time
from collections import defaultdict

sys.path.insert(0, "/work/main")
import torch  # noqa: E402

import fastenerf.kernels.common as C  # noqa: E402
from fastenerf.kernels.gridconfig import HashGridConfig  # noqa: E402
from fastenerf.kernels.hashgrid import hash_grid_encode, init_table  # noqa: E402

T = defaultdict(list)
_orig = C.Launcher.__call__


def _timed(self, *a, **k):
    t0 = time.perf_counter()
    r = _orig(self, *a, **k)
    T[self.kernel.key.replace("_kernels__locals__", "")].append(time.perf_counter() - t0)
    return r


C.Launcher.__call__ = _timed


def points(n, kind, g):
    if kind == "uniform":
        return torch.rand(n, 3, generator=g)
    # ray-like: 64 samples per ray on a segment through the box, in order (training's layout)
    per = 64
    r = -(-n // per)
    o = torch.rand(r, 3, generator=g) * 0.2 + 0.4
    d = torch.nn.functional.normalize(torch.randn(r, 3, generator=g), dim=1)
    t = torch.linspace(-0.35, 0.35, per)
    return (o[:, None] + t[None, :, None] * d[:, None]).reshape(-1, 3)[:n].clamp(0, 1).contiguous()


def bench(cfg, name, n, kind, reps=5):
    g = torch.Generator().manual_seed(0)
    table = init_table(cfg, generator=g).requires_grad_(True)
    x0 = points(n, kind, g)
    gout = torch.randn(n, cfg.n_output_dims, generator=g)
    w = torch.linspace(1, 0, cfg.n_levels)[:, None].expand(-1, cfg.n_features).reshape(-1)
    res = {}
    for mode in ("fwd", "bwd_table", "bwd_table_x", "bwd_table_x_c2f"):
        for rep in range(reps + 1):
            if rep == 1:
                T.clear()
            x = x0.clone().requires_grad_(mode.startswith("bwd_table_x"))
            t0 = time.perf_counter()
            if mode == "fwd":
                with torch.no_grad():
                    hash_grid_encode(x, table, cfg)
            else:
                y = hash_grid_encode(x, table, cfg, x_grad_weights=w if "c2f" in mode else None)
                ins = (table, x) if x.requires_grad else (table,)
                t1 = time.perf_counter()
                torch.autograd.grad(y, ins, gout)
                t0 = t1  # backward only
            dt = time.perf_counter() - t0
            if rep:
                T["total " + mode].append(dt)
        res[mode] = {k: 1e3 * sum(v) / len(v) for k, v in T.items()}
    fwd = res["fwd"]["forward"]
    bt = res["bwd_table"]["backward_table"]
    bx = res["bwd_table_x"]["backward_x"]
    print(
        f"\n## {name}: L={cfg.n_levels} F={cfg.n_features} T=2^{cfg.log2_table_size} "
        f"maxres={cfg.max_resolution}, N={n:,} {kind} points, torch threads "
        f"{torch.get_num_threads()} (ms per call, mean of {reps})"
    )
    for mode, d in res.items():
        print(f"  {mode:16s} " + "  ".join(f"{k}={v:.2f}" for k, v in d.items()))
    print(
        f"  ratio backward_x : backward_table : forward = {bx / fwd:.2f} : {bt / fwd:.2f} : 1"
        f"  (grad_x adds {100 * bx / (fwd + bt):.0f} % to forward+table-backward)"
    )


n = int(sys.argv[1]) if len(sys.argv) > 1 else 200_000
gpu = HashGridConfig(n_levels=16, n_features=2, log2_table_size=19, max_resolution=2048)
cpu = HashGridConfig(n_levels=8, n_features=2, log2_table_size=14, max_resolution=256)
for kind in ("rays", "uniform"):
    bench(gpu, "GPU sizes", n, kind)
    bench(cpu, "CPU preset sizes", n, kind)
