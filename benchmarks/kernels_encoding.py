"""Benchmarks of the encoding and event-query kernels: Warp vs the same op in plain PyTorch.

Each `bench_*` returns a dict of medians in milliseconds (CUDA events on GPU, warm-up excluded),
max errors against a float64 reference on a subset, a minimal-bytes estimate and the achieved
GB/s, next to the device's measured copy bandwidth (DESIGN §8). They run on CPU at tiny sizes
(smoke tests). ``python -m benchmarks.kernels_encoding --device cuda`` prints a table.
"""

import argparse
import itertools
import json
import time

import numpy as np
import torch

from benchmarks.timing import copy_bandwidth_gbs, time_ms
from fastenerf.kernels.events import window_sum
from fastenerf.kernels.hashgrid import (
    HashGridConfig,
    _Variant,
    hash_grid_encode,
    init_table,
)
from fastenerf.kernels.sh import sh_encode

P1, P2, M32 = 2654435761, 805459861, 0xFFFFFFFF


def _time_ms(fn, device: str, repeats: int, warmup: int = 3, inner: int = 10) -> float:
    return time_ms(fn, device, repeats, warmup, inner)


# ---------------------------------------------------------------------------------------------
# Hash grid


def torch_hash_grid_encode(x: torch.Tensor, table: torch.Tensor, cfg: HashGridConfig):
    """The same encoding in plain PyTorch: vectorised per level, index_select (index_add_ back)."""
    feats = []
    corners = torch.tensor(list(itertools.product((0, 1), repeat=3)), device=x.device)
    for res, off, hashed in zip(cfg.resolutions, cfg.level_offsets, cfg.hashed, strict=False):
        p = x.clamp(0, 1) * res
        c = torch.floor(p).clamp_(0, res - 1)
        f = p - c
        v = c.long()[:, None, :] + corners[None]  # (N, 8, 3)
        if hashed:
            idx = (v[..., 0] ^ ((v[..., 1] * P1) & M32) ^ ((v[..., 2] * P2) & M32)) & (
                cfg.table_size - 1
            )
        else:
            idx = v[..., 0] + (res + 1) * (v[..., 1] + (res + 1) * v[..., 2])
        w = torch.where(corners[None].bool(), f[:, None, :], 1 - f[:, None, :]).prod(-1)
        rows = table.index_select(0, (idx + off).reshape(-1)).view(x.shape[0], 8, -1)
        feats.append((w[..., None] * rows).sum(1))
    return torch.cat(feats, 1)


def bench_hashgrid(
    device="cuda", n_points=2**20, log2_T=19, repeats=50, variant=None, with_torch=True
) -> dict:
    """Hash grid (16 levels x 2 features, T = 2**log2_T) forward / backward(table) timings.

    On uniform points, which share no cell: the default table backward (runs of 16 points,
    `backward_run`) gains nothing there and costs ~3 %; `benchmarks.hashgrid_runs` times it on
    ray-ordered samples, as training sends them."""
    cfg = HashGridConfig(log2_table_size=log2_T)
    variant = variant or _Variant()
    L, F = cfg.n_levels, cfg.n_features
    table = init_table(cfg, device).requires_grad_(True)
    x = torch.rand(n_points, 3, device=device)
    g = torch.randn(n_points, L * F, device=device)

    def fwd():
        with torch.no_grad():
            return hash_grid_encode(x, table, cfg, variant)

    out = hash_grid_encode(x, table, cfg, variant)

    def bwd():
        return torch.autograd.grad(out, table, g, retain_graph=True)

    def fwdbwd():
        return torch.autograd.grad(hash_grid_encode(x, table, cfg, variant), table, g)

    r = {
        "device": str(device),
        "n_points": n_points,
        "log2_T": log2_T,
        "n_params": cfg.n_params,
        "variant": str(variant),
    }
    r["warp_fwd_ms"] = _time_ms(fwd, device, repeats)
    r["warp_bwd_ms"] = _time_ms(bwd, device, repeats)
    r["warp_fwdbwd_ms"] = _time_ms(fwdbwd, device, repeats)
    # The same backward reading a feature-major gradient (coalesced): the cost of strided reads.
    g_fm = g.t().contiguous().t()
    r["warp_bwd_fm_grad_ms"] = _time_ms(
        lambda: torch.autograd.grad(out, table, g_fm, retain_graph=True), device, repeats
    )

    # Errors vs float64 on a subset (values and the table gradient of that subset).
    m = min(n_points, 4096)
    xs, gs = x[:m], g[:m]
    t64 = table.detach().double().requires_grad_(True)
    ref = torch_hash_grid_encode(xs.double(), t64, cfg)
    (gt64,) = torch.autograd.grad(ref, t64, gs.double())
    tw = table.detach().clone().requires_grad_(True)
    enc = hash_grid_encode(xs, tw, cfg, variant)
    (gtw,) = torch.autograd.grad(enc, tw, gs)
    r["max_abs_err"] = (enc.double() - ref).abs().max().item()
    r["max_abs_err_grad_table"] = (gtw.double() - gt64).abs().max().item()

    if with_torch:

        def tfwdbwd():
            return torch.autograd.grad(torch_hash_grid_encode(x, table, cfg), table, g)

        def tfwd():
            with torch.no_grad():
                return torch_hash_grid_encode(x, table, cfg)

        reps = max(2, repeats // 10)
        r["torch_fwd_ms"] = _time_ms(tfwd, device, reps, warmup=1, inner=2)
        r["torch_fwdbwd_ms"] = _time_ms(tfwdbwd, device, reps, warmup=1, inner=2)
        r["speedup_fwdbwd"] = r["torch_fwdbwd_ms"] / r["warp_fwdbwd_ms"]

    # Minimal bytes: x once, features once, the table (and its gradient) once.
    feat_bytes = 4 * L * F * n_points
    table_bytes = 4 * F * cfg.n_params
    fwd_bytes = 12 * n_points + feat_bytes + table_bytes
    bwd_bytes = 12 * n_points + feat_bytes + 2 * table_bytes  # zero-fill + scatter
    r["fwd_GBps"] = fwd_bytes / r["warp_fwd_ms"] * 1e-6
    r["fwdbwd_GBps"] = (fwd_bytes + bwd_bytes) / r["warp_fwdbwd_ms"] * 1e-6
    # Gathered / scattered bytes (8 corners x L x F floats per point), mostly L2 traffic.
    r["corner_bytes_fwdbwd"] = 2 * 8 * L * F * 4 * n_points
    r["copy_GBps"] = copy_bandwidth_gbs(device)
    return r


# ---------------------------------------------------------------------------------------------
# Spherical harmonics


def torch_sh_encode(d: torch.Tensor) -> torch.Tensor:
    x, y, z = d.unbind(-1)
    xy, xz, yz, x2, y2, z2 = x * y, x * z, y * z, x * x, y * y, z * z
    return torch.stack(
        [
            torch.full_like(x, 0.28209479177387814),
            -0.48860251190291987 * y,
            0.48860251190291987 * z,
            -0.48860251190291987 * x,
            1.0925484305920792 * xy,
            -1.0925484305920792 * yz,
            0.94617469575755997 * z2 - 0.31539156525251999,
            -1.0925484305920792 * xz,
            0.54627421529603959 * (x2 - y2),
            0.59004358992664352 * y * (y2 - 3 * x2),
            2.8906114426405538 * xy * z,
            0.45704579946446572 * y * (1 - 5 * z2),
            0.3731763325901154 * z * (5 * z2 - 3),
            0.45704579946446572 * x * (1 - 5 * z2),
            1.4453057213202769 * z * (x2 - y2),
            0.59004358992664352 * x * (3 * y2 - x2),
        ],
        -1,
    )


def bench_sh(device="cuda", n_points=2**20, repeats=50) -> dict:
    d = torch.nn.functional.normalize(torch.randn(n_points, 3, device=device), dim=1)
    d.requires_grad_(True)
    g = torch.randn(n_points, 16, device=device)
    r = {"device": str(device), "n_points": n_points}

    def wfwd():
        with torch.no_grad():
            return sh_encode(d)

    def wfb():
        return torch.autograd.grad(sh_encode(d), d, g)

    gb = g.to(torch.bfloat16)

    def wfwd_bf16():
        with torch.no_grad():
            return sh_encode(d, out_dtype=torch.bfloat16)

    def wfb_bf16():
        return torch.autograd.grad(sh_encode(d, out_dtype=torch.bfloat16), d, gb)

    def tfwd():
        with torch.no_grad():
            return torch_sh_encode(d)

    def tfb():
        return torch.autograd.grad(torch_sh_encode(d), d, g)

    r["warp_fwd_ms"] = _time_ms(wfwd, device, repeats)
    r["warp_fwdbwd_ms"] = _time_ms(wfb, device, repeats)
    r["warp_fwd_bf16_ms"] = _time_ms(wfwd_bf16, device, repeats)
    r["warp_fwdbwd_bf16_ms"] = _time_ms(wfb_bf16, device, repeats)
    r["torch_fwd_ms"] = _time_ms(tfwd, device, repeats)
    r["torch_fwdbwd_ms"] = _time_ms(tfb, device, repeats)
    r["speedup_fwdbwd"] = r["torch_fwdbwd_ms"] / r["warp_fwdbwd_ms"]
    m = min(n_points, 65536)
    d64 = d[:m].detach().double().requires_grad_(True)
    ref = torch_sh_encode(d64)
    (gref,) = torch.autograd.grad(ref, d64, g[:m].double())
    dw = d[:m].detach().clone().requires_grad_(True)
    out = sh_encode(dw)
    (gw,) = torch.autograd.grad(out, dw, g[:m])
    r["max_abs_err"] = (out.double() - ref).abs().max().item()
    r["max_abs_err_grad"] = (gw.double() - gref).abs().max().item()
    fwd_bytes = (12 + 64) * n_points
    r["fwd_GBps"] = fwd_bytes / r["warp_fwd_ms"] * 1e-6
    r["fwdbwd_GBps"] = (fwd_bytes + (64 + 12 + 12) * n_points) / r["warp_fwdbwd_ms"] * 1e-6
    r["copy_GBps"] = copy_bandwidth_gbs(device)
    return r


# ---------------------------------------------------------------------------------------------
# Event-window queries


def bench_event_query(
    device="cuda", n_events=10**7, width=346, height=260, n_queries=2**18, repeats=50
) -> dict:
    """E(u; t0, t1] for random queries on a random stream: Warp binary search vs torch.searchsorted
    over composite (pixel, time) keys."""
    n_pix = width * height
    gen = np.random.default_rng()
    pix = torch.from_numpy(gen.integers(0, n_pix, n_events)).to(device)
    t = torch.from_numpy(np.sort(gen.integers(0, 10**7, n_events))).to(device)
    pos = torch.from_numpy(gen.random(n_events) < 0.5).to(device)
    key, order = torch.sort(pix * 2**32 + t)  # pixel-major, time-minor (t < 2**32)
    times = t[order]
    counts = torch.bincount(pix, minlength=n_pix)
    zero = torch.zeros(1, dtype=torch.int64, device=device)
    offsets = torch.cat([zero, counts.cumsum(0)])
    cum_pos = torch.cat([zero, pos[order].long().cumsum(0)])
    qpix = torch.randint(0, n_pix, (n_queries,), device=device)
    t0 = torch.randint(0, 10**7, (n_queries,), device=device)
    t1 = t0 + torch.randint(0, 10**6, (n_queries,), device=device)
    c_pos, c_neg, off = 0.25, 0.25, 0.0

    def warp_q():
        return window_sum(offsets, times, cum_pos, qpix, t0, t1, c_pos, c_neg, off)

    def torch_q():
        lo = torch.searchsorted(key, qpix * 2**32 + t0, right=True)
        hi = torch.searchsorted(key, qpix * 2**32 + torch.maximum(t0, t1), right=True)
        n_p = cum_pos[hi] - cum_pos[lo]
        return (n_p * (1 + off) * c_pos + (hi - lo - n_p) * (off - 1) * c_neg).float()

    r = {"device": str(device), "n_events": n_events, "n_queries": n_queries}
    r["warp_ms"] = _time_ms(warp_q, device, repeats)
    r["torch_ms"] = _time_ms(torch_q, device, repeats)
    r["speedup"] = r["torch_ms"] / r["warp_ms"]
    r["max_abs_err"] = (warp_q() - torch_q()).abs().max().item()
    r["queries_per_s"] = n_queries / r["warp_ms"] * 1e3
    return r


VARIANTS = [  # the default (runs of points in the table's backward), then a thread per point
    _Variant(),
    _Variant(run=1),
    _Variant(group=1, run=1),
    _Variant(group=2, run=1),
    _Variant(pairs=False, run=1),
    _Variant(pairs=False, vector_red=False, run=1),
    _Variant(feature_major=False, run=1),
    _Variant(level_outer=False, run=1),
]


def bench_hashgrid_variants(device="cuda", n_points=2**20, log2_T=19, repeats=30) -> list[dict]:
    """Launch layouts of the hash-grid kernels (for choosing the default)."""
    return [
        bench_hashgrid(device, n_points, log2_T, repeats, variant=v, with_torch=False)
        for v in VARIANTS
    ]


def bench_hashgrid_levels(device="cuda", n_points=2**20, log2_T=19, repeats=20) -> list[dict]:
    """Forward / backward time of each level of the default grid alone (a 1-level grid).

    At 2^20 points a single level is ~0.1 ms of GPU work, close to the ~60 µs host cost per op:
    read these as upper bounds.
    """
    out = []
    x = torch.rand(n_points, 3, device=device)
    g = torch.randn(n_points, 2, device=device)
    for res in HashGridConfig(log2_table_size=log2_T).resolutions:
        cfg = HashGridConfig(
            n_levels=1, log2_table_size=log2_T, base_resolution=res, max_resolution=res
        )
        table = init_table(cfg, device).requires_grad_(True)
        y = hash_grid_encode(x, table, cfg)
        with torch.no_grad():
            fwd = _time_ms(lambda: hash_grid_encode(x, table, cfg), device, repeats)  # noqa: B023
        bwd = _time_ms(
            lambda: torch.autograd.grad(y, table, g, retain_graph=True),  # noqa: B023
            device,
            repeats,
        )
        out.append(
            {
                "res": res,
                "hashed": cfg.hashed[0],
                "rows": cfg.n_params,
                "fwd_ms": fwd,
                "bwd_ms": bwd,
            }
        )
    return out


def launch_overhead_us(device="cuda", calls=200) -> dict:
    """Host time per call at one element (Python + Warp launch), microseconds."""
    cfg = HashGridConfig(log2_table_size=12)
    table = init_table(cfg, device)
    x = torch.rand(1, 3, device=device)
    d = torch.nn.functional.normalize(torch.randn(1, 3, device=device), dim=1)
    z = torch.zeros(1, dtype=torch.int64, device=device)
    idx = [
        torch.zeros(2, dtype=torch.int64, device=device),
        torch.zeros(0, dtype=torch.int64, device=device),
        torch.zeros(1, dtype=torch.int64, device=device),
    ]
    fns = {
        "hashgrid_fwd": lambda: hash_grid_encode(x, table, cfg),
        "sh_fwd": lambda: sh_encode(d),
        "window_sum": lambda: window_sum(*idx, z, z, z, 0.25, 0.25),
    }
    out = {}
    for k, fn in fns.items():
        for _ in range(10):
            fn()
        if device != "cpu":
            torch.cuda.synchronize()
        t = time.perf_counter()
        for _ in range(calls):
            fn()
        if device != "cpu":
            torch.cuda.synchronize()
        out[k] = (time.perf_counter() - t) / calls * 1e6
    return out


def check_cuda(device="cuda") -> dict:
    """Max differences of every kernel on `device` vs float64 PyTorch / numpy references."""
    out = {}
    cfg = HashGridConfig(log2_table_size=14)
    x = torch.rand(20000, 3)
    x[:8] = torch.tensor(
        [
            [0.0, 0, 0],
            [1, 1, 1],
            [0.5, 0.25, 1],
            [1, 0, 0.125],
            [-0.2, 0.5, 1.3],
            [1 / 16, 2 / 16, 3 / 16],
            [0.999999, 1e-7, 0.5],
            [0.75, 0.75, 0.75],
        ]
    )
    table = torch.rand(cfg.n_params, 2) * 2 - 1
    g = torch.randn(20000, cfg.n_output_dims)
    t64 = table.double().requires_grad_(True)
    y0 = torch_hash_grid_encode(x.double(), t64, cfg)
    (gt0,) = torch.autograd.grad(y0, t64, g.double())
    for v in VARIANTS:
        xx = x.to(device).requires_grad_(True)
        tt = table.to(device).requires_grad_(True)
        y = hash_grid_encode(xx, tt, cfg, v)
        gx, gt = torch.autograd.grad(y, (xx, tt), g.to(device))
        out[f"hashgrid {v}"] = max(
            (y.cpu().double() - y0).abs().max().item(),
            (gt.cpu().double() - gt0).abs().max().item() / gt0.abs().max().item(),
        )
        out[f"hashgrid {v} finite dx"] = float(not torch.isfinite(gx).all().item())
    d = torch.nn.functional.normalize(torch.randn(5000, 3), dim=1)
    gd = torch.randn(5000, 16)
    d64 = d.double().requires_grad_(True)
    y0 = torch_sh_encode(d64)
    (gd0,) = torch.autograd.grad(y0, d64, gd.double())
    dd = d.to(device).requires_grad_(True)
    y = sh_encode(dd)
    (gdd,) = torch.autograd.grad(y, dd, gd.to(device))
    out["sh"] = max(
        (y.cpu().double() - y0).abs().max().item(), (gdd.cpu().double() - gd0).abs().max().item()
    )
    rng = np.random.default_rng()
    n_pix, n_ev = 500, 100000
    pix = rng.integers(0, n_pix, n_ev)
    t = np.sort(rng.integers(0, 10**5, n_ev))
    p = rng.random(n_ev) < 0.5
    order = np.lexsort((t, pix))
    arrays = [
        np.concatenate([[0], np.cumsum(np.bincount(pix, minlength=n_pix))]),
        t[order],
        np.concatenate([[0], np.cumsum(p[order])]),
    ]
    q = [rng.integers(0, n_pix, 4096), rng.integers(0, 10**5, 4096)]
    q.append(q[1] + rng.integers(-10, 10**4, 4096))
    key = pix[order] * 2**32 + t[order]
    lo = np.searchsorted(key, q[0] * 2**32 + q[1], side="right")
    hi = np.searchsorted(key, q[0] * 2**32 + np.maximum(q[1], q[2]), side="right")
    n_p = arrays[2][hi] - arrays[2][lo]
    e0 = n_p * 1.1 * 0.25 + (hi - lo - n_p) * (0.1 - 1) * 0.2
    a = [torch.from_numpy(np.asarray(v, dtype=np.int64)).to(device) for v in arrays + q]
    out["events"] = np.abs(window_sum(*a, 0.25, 0.2, 0.1).cpu().numpy() - e0).max()
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--variants", action="store_true", help="time every hash-grid layout")
    ap.add_argument("--json", default=None, help="write all results here")
    ap.add_argument("--check", action="store_true", help="compare every kernel with references")
    ap.add_argument("--levels", action="store_true", help="time each hash-grid level alone")
    a = ap.parse_args(argv)
    if a.check:
        for k, v in check_cuda(a.device).items():
            print(f"check {k:<75} max diff {v:.2e}")
    small = a.device == "cpu"
    n = 2**14 if small else 2**20
    res = {}
    if a.variants:
        res["variants"] = bench_hashgrid_variants(a.device, n, repeats=5 if small else 30)
        for r in res["variants"]:
            print(
                f"{r['variant']:<82} fwd {r['warp_fwd_ms']:.3f}  bwd {r['warp_bwd_ms']:.3f}  "
                f"fwd+bwd {r['warp_fwdbwd_ms']:.3f} ms  err {r['max_abs_err']:.1e}"
            )
    if a.levels:
        for r in bench_hashgrid_levels(a.device, n, repeats=5 if small else 20):
            print(
                "level",
                json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in r.items()}),
            )
    print(
        "launch overhead us",
        json.dumps({k: round(v, 1) for k, v in launch_overhead_us(a.device).items()}),
    )
    res["hashgrid"] = bench_hashgrid(a.device, n, repeats=5 if small else 50)
    res["sh"] = bench_sh(a.device, n, repeats=5 if small else 50)
    res["events"] = bench_event_query(
        a.device,
        10**5 if small else 10**7,
        n_queries=2**12 if small else 2**18,
        repeats=5 if small else 50,
    )
    for k, r in res.items():
        if k != "variants":
            print(
                k,
                json.dumps(
                    {kk: (round(v, 4) if isinstance(v, float) else v) for kk, v in r.items()}
                ),
            )
    if a.json:
        with open(a.json, "w") as f:
            json.dump(res, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
