"""Benchmarks of the rendering kernels (marching, compositing): Warp vs the same op in PyTorch.

Each `bench_*` returns a dict of medians in milliseconds (CUDA events on GPU, warm-up excluded),
errors against a float64 reference, a minimal-bytes estimate, the achieved GB/s and the device's
measured copy bandwidth (DESIGN §8). They also run on CPU at tiny sizes (a smoke test does).
``python -m benchmarks.kernels_render --device cuda`` prints the results as JSON.

Compositing and the distortion loss are timed in both Warp layouts (`composite(...,
layout="ray" | "block")`, `distortion_loss(...)`: a thread per ray, or 32 threads per ray with
tile scans), each with its speed-up over PyTorch.

Plain-PyTorch baselines (`benchmarks/render_torch.py`):
  - compositing: packed samples scattered into a dense (rays x max samples) array, exclusive
    transmittance with cumprod, early-stop mask, segment sums with index_add; autograd backward;
  - the distortion loss: segmented prefix sums over the packed samples, index_add per ray;
  - marching: dense uniform steps over every ray's box interval, occupancy lookup of each
    midpoint in the dense bool grid, compaction with boolean masks (the same intervals as the
    Warp marcher with cone_angle = 0 and no jitter, so sample counts must agree).

The march is also timed on a copy of the grid without empty-space blocks (`block=1`, cell by
cell), in the same call, with a check that both give the same samples.

`march_rays_fixed` (fixed-capacity buffers, no host sync) is timed beside `march_rays` with
25 % spare capacity: eagerly, and on CUDA also replayed from a CUDA graph, with a check that a
call makes no host sync (torch's sync debug mode) and that its samples are march_rays' own.
"""

from __future__ import annotations

import argparse
import functools
import json
import math

import torch

from benchmarks.cli import benchmark_main
from benchmarks.render_torch import torch_composite, torch_distortion, torch_march
from benchmarks.timing import copy_bandwidth_gbs, time_ms
from fastenerf.errors import require
from fastenerf.io import atomic_path
from fastenerf.kernels.composite import composite, distortion_loss, resolve_layout
from fastenerf.kernels.occupancy import OccupancyGrid
from fastenerf.kernels.raymarch import march_rays
from fastenerf.kernels.raymarch_fixed import empty_fixed_samples, march_rays_fixed
from fastenerf.outputs import OutputKind, claim_output


def _time_ms(fn, device: str, repeats: int, warmup: int = 3, inner: int = 1) -> float:
    return time_ms(fn, device, repeats, warmup, inner)


# ---------------------------------------------------------------------------------------------
# Benchmarks


def _packed_case(n_rays, mean_samples, device, seed=0):
    g = torch.Generator(device="cpu").manual_seed(seed)
    counts = torch.randint(0, 2 * mean_samples + 1, (n_rays,), generator=g).int()
    csum = torch.cumsum(counts, 0, dtype=torch.int32)
    packed = torch.stack([csum - counts, counts], 1)
    S = int(csum[-1])
    dt = torch.empty(S).uniform_(2e-3, 1e-2, generator=g)
    sig = torch.empty(S).exponential_(1.0, generator=g) * 20
    ray = torch.repeat_interleave(torch.arange(n_rays), counts.long())
    excl = torch.cumsum(dt, 0) - dt
    t_s = excl - excl[packed[ray, 0].long()] + 0.5
    rgbs = torch.rand(S, 3, generator=g)
    to = lambda x: x.to(device).contiguous()  # noqa: E731
    return to(sig), to(rgbs), to(t_s), to(t_s + dt), to(packed)


def bench_composite(device="cuda", n_rays=2**16, mean_samples=64, repeats=20) -> dict:
    """Compositing forward / forward+backward: both Warp layouts ("ray": a thread per ray,
    "block": 32 threads per ray) side by side against plain PyTorch, same device.

    Per layout L: `L_fwd_ms`, `L_fwdbwd_ms`, `speedup_L_fwd`, `speedup_L_fwdbwd` (PyTorch time
    over Warp time), `L_fwd_GBps`, `L_fwdbwd_GBps` and `L_max_*` errors vs float64. The
    unprefixed `warp_*`, `speedup_*`, `*_GBps` and `max_*` keys are those of `warp_layout`,
    the one `layout="auto"` picks on this device (what training runs). On CUDA also
    `L_host_sync` and `L_graph_matches` (see `_composite_cuda_checks`)."""
    sig, rgbs, t_s, t_e, packed = _packed_case(n_rays, mean_samples, device)
    S = sig.shape[0]
    bg = torch.tensor([0.3, 0.5, 0.7], device=device)
    g_rgb = torch.randn(n_rays, 3, device=device)
    auto = resolve_layout("auto", torch.device(device))
    r = {"device": str(device), "n_rays": n_rays, "n_samples": S, "warp_layout": auto}

    def run(fn, backward):
        s = sig.clone().requires_grad_(backward)
        c = rgbs.clone().requires_grad_(backward)
        out = fn(s, c, t_s, t_e, packed, background=bg)
        if backward:
            torch.autograd.grad((out["rgb"] * g_rgb).sum() + out["depth"].sum(), (s, c))
        return out

    fns = {L: functools.partial(composite, layout=L) for L in ("ray", "block")}
    fns["torch"] = torch_composite
    for name, fn in fns.items():
        with torch.no_grad():
            r[f"{name}_fwd_ms"] = _time_ms(lambda fn=fn: run(fn, False), device, repeats)
        r[f"{name}_fwdbwd_ms"] = _time_ms(lambda fn=fn: run(fn, True), device, repeats)

    # errors vs float64 (values and sigma / rgb gradients)
    s64, c64 = sig.double().requires_grad_(), rgbs.double().requires_grad_()
    ref = torch_composite(s64, c64, t_s.double(), t_e.double(), packed, bg.double())
    gs64, gc64 = torch.autograd.grad(
        (ref["rgb"] * g_rgb.double()).sum() + ref["depth"].sum(), (s64, c64)
    )
    # minimal bytes: per sample sigma, t0, t1, rgb in, weight out (fwd); grads out (bwd)
    fwd = 28 * S + 32 * n_rays
    bwd = 40 * S + 52 * n_rays
    for L in ("ray", "block"):
        s32, c32 = sig.clone().requires_grad_(), rgbs.clone().requires_grad_()
        out = composite(s32, c32, t_s, t_e, packed, background=bg, layout=L)
        gs, gc = torch.autograd.grad((out["rgb"] * g_rgb).sum() + out["depth"].sum(), (s32, c32))
        r[f"{L}_max_abs_err_rgb"] = (out["rgb"].double() - ref["rgb"]).abs().max().item()
        r[f"{L}_max_abs_err_depth"] = (out["depth"].double() - ref["depth"]).abs().max().item()
        rel = (gs.double() - gs64).abs().max() / gs64.abs().max()
        r[f"{L}_max_rel_err_grad_sigma"] = rel.item()
        r[f"{L}_max_abs_err_grad_rgb"] = (gc.double() - gc64).abs().max().item()
        for m in ("fwd", "fwdbwd"):
            r[f"speedup_{L}_{m}"] = r[f"torch_{m}_ms"] / r[f"{L}_{m}_ms"]
        r[f"{L}_fwd_GBps"] = fwd / r[f"{L}_fwd_ms"] * 1e-6
        r[f"{L}_fwdbwd_GBps"] = (fwd + bwd) / r[f"{L}_fwdbwd_ms"] * 1e-6
    tout = torch_composite(sig, rgbs, t_s, t_e, packed, bg)
    r["torch_fp32_max_abs_err_rgb"] = (tout["rgb"].double() - ref["rgb"]).abs().max().item()
    for k in ("fwd_ms", "fwdbwd_ms"):
        r[f"warp_{k}"] = r[f"{auto}_{k}"]
    for k in ("speedup_fwd", "speedup_fwdbwd"):
        r[k] = r[k.replace("speedup_", f"speedup_{auto}_")]
    for k in ("fwd_GBps", "fwdbwd_GBps"):
        r[k] = r[f"{auto}_{k}"]
    for k in ("rgb", "depth", "grad_rgb"):
        r[f"max_abs_err_{k}"] = r[f"{auto}_max_abs_err_{k}"]
    r["max_rel_err_grad_sigma"] = r[f"{auto}_max_rel_err_grad_sigma"]
    r["copy_GBps"] = copy_bandwidth_gbs(device)
    if str(device).startswith("cuda"):
        for L in ("ray", "block"):
            r.update(_composite_cuda_checks(L, sig, rgbs, t_s, t_e, packed, bg, g_rgb))
        r.update(_graph_fwdbwd_ms(sig, rgbs, t_s, t_e, packed, bg, g_rgb, repeats))
    return r


def _graph_fwdbwd_ms(sig, rgbs, t_s, t_e, packed, bg, g_rgb, repeats) -> dict:
    """CUDA only: forward+backward of each layout and of plain PyTorch, each captured once into
    a CUDA graph and replayed, so the time is the device's alone, without the host's Python,
    autograd and launches (the training step is replayed from a graph too; the eager timings
    above are host-bound where the kernels are short). `{name}_fwdbwd_graph_ms` for ray, block
    and torch, `speedup_{L}_fwdbwd_graph`; `{name}_graph_time_error` where a capture failed."""
    fns = {L: functools.partial(composite, layout=L) for L in ("ray", "block")}
    fns["torch"] = functools.partial(torch_composite, n_max=int(packed[:, 1].max()))
    r: dict = {}
    for name, fn in fns.items():
        s, c = sig.clone().requires_grad_(), rgbs.clone().requires_grad_()

        def step(fn=fn, s=s, c=c):
            out = fn(s, c, t_s, t_e, packed, background=bg)
            return torch.autograd.grad((out["rgb"] * g_rgb).sum() + out["depth"].sum(), (s, c))

        try:
            graph, _ = _captured(step)
            r[f"{name}_fwdbwd_graph_ms"] = _time_ms(graph.replay, "cuda", repeats)
        except Exception as e:  # report, do not hide the other timings
            r[f"{name}_graph_time_error"] = f"{type(e).__name__}: {e}".splitlines()[0]
        del step
    for L in ("ray", "block"):
        if f"{L}_fwdbwd_graph_ms" in r and "torch_fwdbwd_graph_ms" in r:
            r[f"speedup_{L}_fwdbwd_graph"] = r["torch_fwdbwd_graph_ms"] / r[f"{L}_fwdbwd_graph_ms"]
    return r


def _host_sync(fn) -> str:
    """CUDA: "none" if fn() runs without a host sync, else torch's error (its first line)."""
    try:
        torch.cuda.synchronize()
        torch.cuda.set_sync_debug_mode("error")  # raises on any host sync inside the call
        fn()
        return "none"
    except RuntimeError as e:
        return str(e).splitlines()[0]
    finally:
        torch.cuda.set_sync_debug_mode(0)


def _captured(fn):
    """(graph, what fn returned while captured): fn warmed up on a side stream, as torch asks,
    then captured into a CUDA graph (not yet replayed)."""
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        fn()
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        out = fn()
    return graph, out


def _composite_cuda_checks(layout, sig, rgbs, t_s, t_e, packed, bg, g_rgb) -> dict:
    """CUDA only: `{layout}_host_sync` ("none", or torch's error for a forward+backward run in
    sync debug mode) and `{layout}_graph_matches` (a forward+backward captured into a CUDA
    graph, as training captures it, replays to the eager result bit for bit), or
    `{layout}_graph_error`."""
    s, c = sig.clone().requires_grad_(), rgbs.clone().requires_grad_()

    def step():
        out = composite(s, c, t_s, t_e, packed, background=bg, layout=layout)
        gs, gc = torch.autograd.grad((out["rgb"] * g_rgb).sum() + out["depth"].sum(), (s, c))
        return out["rgb"].detach(), gs, gc

    eager = step()
    r = {f"{layout}_host_sync": _host_sync(step)}
    try:
        graph, captured = _captured(step)
        graph.replay()
        torch.cuda.synchronize()
        same = all(torch.equal(a, b) for a, b in zip(captured, eager, strict=True))
        r[f"{layout}_graph_matches"] = same
    except Exception as e:  # report, do not hide the timings
        r[f"{layout}_graph_error"] = f"{type(e).__name__}: {e}".splitlines()[0]
    return r


def _scene(device, n_rays, resolution, seed=0):
    """Occupied spherical shell (0.35 < |x| < 0.6) seen from cameras on a radius-2.5 sphere."""
    g = torch.Generator(device="cpu").manual_seed(seed)
    grid = OccupancyGrid([-1, -1, -1, 1, 1, 1], resolution=resolution, device=device)

    def shell(x):
        r = x.norm(dim=-1)
        return ((r > 0.35) & (r < 0.6)).float() * 1e3

    torch.manual_seed(seed)
    grid.update(0, shell)
    o = torch.nn.functional.normalize(torch.randn(n_rays, 3, generator=g), dim=-1) * 2.5
    target = (torch.rand(n_rays, 3, generator=g) - 0.5) * 1.2
    d = torch.nn.functional.normalize(target - o, dim=-1)
    return grid, shell, o.to(device), d.to(device)


def bench_march_composite(
    device="cuda", n_rays=2**16, resolution=128, max_samples=1024, repeats=10
) -> dict:
    """Marching (+ an analytic field + compositing fwd/bwd): Warp vs plain PyTorch."""
    grid, shell, o, d = _scene(device, n_rays, resolution)
    aabb = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]
    dt = grid.step_size
    binary = grid.binary[0]
    r = {
        "device": str(device),
        "n_rays": n_rays,
        "resolution": resolution,
        "dt": dt,
        "occupied_fraction": binary.float().mean().item(),
    }

    margs = (o, d, aabb, grid, 0.0, None, 0.0, dt, dt, max_samples, None)

    def wmarch():
        return march_rays(*margs)

    def tmarch():
        return torch_march(o, d, aabb, binary, dt, max_samples)

    def field(packed, t_s, t_e, ri):
        mid = 0.5 * (t_s + t_e)
        p = o[ri.long()] + mid[:, None] * d[ri.long()]
        return shell(p) * 0.05, torch.sigmoid(p * 3)

    def pipeline(march, comp):
        packed, t_s, t_e, ri = march()
        sig, rgb = field(packed, t_s, t_e, ri)
        sig.requires_grad_(True)
        rgb.requires_grad_(True)
        out = comp(sig, rgb, t_s, t_e, packed)
        torch.autograd.grad(out["rgb"].sum(), (sig, rgb))
        return out

    r["warp_march_ms"] = _time_ms(wmarch, device, repeats)
    r["torch_march_ms"] = _time_ms(tmarch, device, max(2, repeats // 2), warmup=1)
    r["speedup_march"] = r["torch_march_ms"] / r["warp_march_ms"]
    r.update(_bench_march_cellwise(margs, grid, wmarch(), device, repeats))
    r["warp_pipeline_ms"] = _time_ms(lambda: pipeline(wmarch, composite), device, repeats)
    r["torch_pipeline_ms"] = _time_ms(
        lambda: pipeline(tmarch, torch_composite), device, max(2, repeats // 2), warmup=1
    )
    r["speedup_pipeline"] = r["torch_pipeline_ms"] / r["warp_pipeline_ms"]
    pw = wmarch()
    r.update(_bench_march_fixed(margs, pw, field, device, repeats))
    r["speedup_march_fixed"] = r["torch_march_ms"] / r["warp_march_fixed_ms"]
    r.update(_bench_march_single(margs, pw, device, repeats, r["torch_march_ms"]))
    r["speedup_pipeline_fixed"] = r["torch_pipeline_ms"] / r["warp_pipeline_fixed_ms"]

    # sample sets vs the float64 dense reference (same intervals: counts must agree)
    p64 = torch_march(o.double(), d.double(), aabb, binary, dt, max_samples)
    S = int(pw[0][:, 1].sum())
    r["n_samples"] = S
    r["samples_per_ray"] = S / n_rays
    r["count_mismatch_fraction"] = (pw[0][:, 1] - p64[0][:, 1]).abs().sum().item() / max(
        1, int(p64[0][:, 1].sum())
    )
    same = pw[0][:, 1] == p64[0][:, 1]
    mask = torch.repeat_interleave(same, pw[0][:, 1].long())
    mask64 = torch.repeat_interleave(same, p64[0][:, 1].long())
    r["max_abs_err_t_start"] = (
        (pw[1][mask].double() - p64[1][mask64]).abs().max().item() if mask.any() else 0.0
    )
    out_w = pipeline(wmarch, composite)
    packed, t_s, t_e, ri = p64
    sig64, rgb64 = field(packed, t_s, t_e, ri)
    ref = torch_composite(sig64.double(), rgb64.double(), t_s, t_e, packed)
    # end to end: includes the few samples float32 and float64 place in different cells
    r["max_abs_err_rgb"] = (out_w["rgb"].double() - ref["rgb"]).abs().max().item()

    # minimal bytes of the two marching passes: rays in twice, counts, samples out
    march_bytes = 12 * S + n_rays * (2 * 24 + 4 + 8)
    r["march_GBps"] = march_bytes / r["warp_march_ms"] * 1e-6
    r["march_blocks_speedup"] = r["warp_march_cellwise_ms"] / r["warp_march_ms"]
    r["copy_GBps"] = copy_bandwidth_gbs(device)
    return r


def _bench_march_cellwise(margs, grid, exact, device, repeats) -> dict:
    """march_rays on a copy of `grid` with no blocks (empty space crossed cell by cell) against
    the grid's own blocks (`exact`: its output): times in one call, and whether they agree."""
    cellwise = OccupancyGrid(
        grid.aabb_list, grid.resolution, grid.n_cascades, device=device, block=1
    )
    cellwise.load_state_dict(grid.state_dict())
    cargs = (*margs[:3], cellwise, *margs[4:])
    r = {"block": grid.block, "empty_block_fraction": (grid.blocks == 0).float().mean().item()}
    r["warp_march_cellwise_ms"] = _time_ms(lambda: march_rays(*cargs), device, repeats)
    out = march_rays(*cargs)
    r["march_cellwise_matches"] = all(torch.equal(x, y) for x, y in zip(out, exact, strict=True))
    return r


def _bench_march_single(margs, exact, device, repeats, torch_ms: float) -> dict:
    """The single pass (`single_pass=True`: march once into scratch rows, then copy) against
    the two passes, side by side: at the benchmark's rays (exact and fixed buffers, the fixed
    one also replayed from a CUDA graph) and at a quarter of them (training's 2 x 8,192 rays
    at the former default split into segments); whether the samples are the two passes' own; the
    single pass's speed-up over plain PyTorch's march (`torch_ms`)."""
    S = int(exact[0][:, 1].sum())
    capacity = S + S // 4 + 1
    buf = empty_fixed_samples(margs[0].shape[0], capacity, margs[0].device)
    quarter = (margs[0][: len(margs[0]) // 4], margs[1][: len(margs[1]) // 4], *margs[2:])
    r = {}
    for key, single in (("two", False), ("single", True)):
        r[f"warp_march_{key}_ms"] = _time_ms(
            lambda single=single: march_rays(*margs, single_pass=single), device, repeats
        )

        def fixed(single=single):
            return march_rays_fixed(*margs, single_pass=single, capacity=capacity, out=buf)

        r[f"warp_march_fixed_{key}_ms"] = _time_ms(fixed, device, repeats)
        if str(device).startswith("cuda"):
            try:
                graph, _ = _captured(fixed)
                r[f"warp_march_fixed_{key}_graph_ms"] = _time_ms(graph.replay, device, repeats)
            except Exception as e:  # report, do not hide the other timings
                r[f"march_fixed_{key}_graph_error"] = f"{type(e).__name__}: {e}".splitlines()[0]
        r[f"warp_march_quarter_{key}_ms"] = _time_ms(
            lambda single=single: march_rays(*quarter, single_pass=single), device, repeats
        )
    one = march_rays(*margs, single_pass=True)
    f = march_rays_fixed(*margs, single_pass=True, capacity=capacity, out=buf)
    r["march_single_matches"] = bool(
        all(torch.equal(x, y) for x, y in zip(one, exact, strict=True))
        and int(f.n_used) == S
        and torch.equal(f.packed_info, exact[0])
        and torch.equal(f.t_starts[:S], exact[1])
        and torch.equal(f.t_ends[:S], exact[2])
        and torch.equal(f.ray_indices[:S], exact[3])
    )
    r["speedup_march_single"] = torch_ms / r["warp_march_single_ms"]
    two, one = r["warp_march_quarter_two_ms"], r["warp_march_quarter_single_ms"]
    r["single_over_two"] = r["warp_march_two_ms"] / r["warp_march_single_ms"]
    r["single_over_two_quarter"] = two / one
    return r


def _bench_march_fixed(margs, exact, field, device, repeats) -> dict:
    """march_rays_fixed on march_rays' arguments `margs` with 25 % spare capacity: eager and
    CUDA-graph timings, host-sync check, equality with march_rays' output `exact`."""
    S = int(exact[0][:, 1].sum())
    capacity = S + S // 4 + 1
    buf = empty_fixed_samples(margs[0].shape[0], capacity, margs[0].device)

    def fixed():
        return march_rays_fixed(*margs, capacity=capacity, out=buf)

    def pipeline():  # the field runs on every slot, padding included
        packed, t_s, t_e, ri = fixed()[:4]
        sig, rgb = field(packed, t_s, t_e, ri)
        sig.requires_grad_(True)
        rgb.requires_grad_(True)
        out = composite(sig, rgb, t_s, t_e, packed)
        torch.autograd.grad(out["rgb"].sum(), (sig, rgb))

    r = {"fixed_capacity": capacity}
    r["warp_march_fixed_ms"] = _time_ms(fixed, device, repeats)
    r["warp_pipeline_fixed_ms"] = _time_ms(pipeline, device, repeats)
    f = fixed()
    r["march_fixed_matches_march_rays"] = bool(
        int(f.n_used) == S
        and int(f.n_wanted) == S
        and not bool(f.overflow.any())
        and torch.equal(f.packed_info, exact[0])
        and torch.equal(f.t_starts[:S], exact[1])
        and torch.equal(f.ray_indices[:S], exact[3])
    )
    if not str(device).startswith("cuda"):
        return r
    r["march_fixed_host_sync"] = _host_sync(fixed)
    try:
        graph, _ = _captured(fixed)
        r["warp_march_fixed_graph_ms"] = _time_ms(graph.replay, device, repeats)
        graph.replay()
        torch.cuda.synchronize()
        r["march_fixed_graph_matches"] = bool(torch.equal(buf.t_starts[:S], exact[1]))
    except Exception as e:  # report, do not hide the other timings
        r["march_fixed_graph_error"] = f"{type(e).__name__}: {e}".splitlines()[0]
    return r


def kernel_outputs(device="cuda", n_rays=4096, seed=0) -> dict:
    """Every kernel's outputs on fixed inputs (moved to the CPU), to compare devices with
    `compare_outputs`: the CPU backend is what the tests check against float64."""
    g = torch.Generator().manual_seed(seed)
    cyl = (0.6, -0.5, 0.5)
    grid = OccupancyGrid(
        [-1] * 3 + [1] * 3, resolution=64, n_cascades=2, cylinder=cyl, device=device
    )
    sd = grid.state_dict()
    occ = (torch.rand(grid.density.shape, generator=g) < 0.5).float()
    sd["density"] = torch.where(sd["density"] < 0, sd["density"], occ)
    sd["threshold"] = torch.tensor([0.5])
    grid.load_state_dict(sd)
    o = torch.randn(n_rays, 3, generator=g) * 2
    d = torch.nn.functional.normalize(torch.rand(n_rays, 3, generator=g) - 0.5 - o * 0.3, dim=-1)
    jit = torch.rand(n_rays, generator=g)
    x = torch.rand(100000, 3, generator=g) * 6 - 3
    out = {}
    march = march_rays(
        o.to(device),
        d.to(device),
        [-2.0] * 3 + [2.0] * 3,
        grid,
        0.01,
        6.0,
        0.01,
        0.005,
        0.05,
        512,
        jit.to(device),
    )
    for k, v in zip(("packed_info", "t_starts", "t_ends", "ray_indices"), march, strict=True):
        out[k] = v.cpu()
    out["occupied"] = grid.occupied(x.to(device)).cpu()
    K = torch.tensor([[200.0, 0, 64], [0, 200.0, 48], [0, 0, 1]])
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[2, 3] = -3.0
    grid.mark_unseen(K, c2w[None], 128, 96, 0.1)
    out["valid"] = grid.valid.cpu()
    sig, rgbs, t_s, t_e, packed = _packed_case(n_rays, 32, device, seed)
    s, c = sig.requires_grad_(), rgbs.requires_grad_()
    res = composite(s, c, t_s, t_e, packed, background=torch.tensor([0.1, 0.2, 0.3]))
    (res["rgb"].sum() + res["weights"].sum()).backward()
    for k in ("rgb", "depth", "weights"):
        out["composite_" + k] = res[k].detach().cpu()
    out["composite_grad_sigma"], out["composite_grad_rgb"] = s.grad.cpu(), c.grad.cpu()
    return out


def compare_outputs(a: dict, b: dict) -> dict:
    """Disagreements between two `kernel_outputs` results (0 / tiny when the devices agree)."""
    same = a["packed_info"][:, 1] == b["packed_info"][:, 1]
    ma = torch.repeat_interleave(same, a["packed_info"][:, 1].long())
    mb = torch.repeat_interleave(same, b["packed_info"][:, 1].long())
    r = {
        "n_samples": (a["t_starts"].numel(), b["t_starts"].numel()),
        "march_rays_count_mismatch": int((~same).sum()),
        "march_max_abs_diff_t": (a["t_starts"][ma] - b["t_starts"][mb]).abs().max().item(),
        "occupied_mismatch": int((a["occupied"] != b["occupied"]).sum()),
        "mark_unseen_mismatch": int((a["valid"] != b["valid"]).sum()),
    }
    for k in a:
        if k.startswith("composite_"):
            r[k + "_max_abs_diff"] = (a[k] - b[k]).abs().max().item()
    return r


DUMP_FILE = OutputKind("kernel outputs file", False, lambda p: p.suffix.lower() == ".pt")


def bench_distortion(device="cuda", n_rays=2**16, mean_samples=64, repeats=20) -> dict:
    """The distortion loss forward / forward+backward in both Warp layouts ("ray", "block")
    side by side against plain PyTorch, same device: `L_fwd_ms`, `L_fwdbwd_ms`,
    `speedup_L_fwdbwd` (PyTorch over Warp), `L_max_rel_err_loss` and `L_max_rel_err_grad`
    (against float64), and `block_over_ray_fwdbwd` (the block layout's time over the ray
    layout's)."""
    _, _, t_s, t_e, packed = _packed_case(n_rays, mean_samples, device)
    S = t_s.shape[0]
    w = torch.rand(S, generator=torch.Generator().manual_seed(1)).to(device) * 0.1
    g = torch.randn(n_rays, generator=torch.Generator().manual_seed(2)).to(device)
    r = {"device": str(device), "n_rays": n_rays, "n_samples": S}
    fns = {L: functools.partial(distortion_loss, layout=L) for L in ("ray", "block")}
    fns["torch"] = torch_distortion

    def run(fn, backward):
        x = w.clone().requires_grad_(backward)
        loss = fn(x, t_s, t_e, packed)
        if backward:
            torch.autograd.grad((loss * g).sum(), x)

    for name, fn in fns.items():
        with torch.no_grad():
            r[f"{name}_fwd_ms"] = _time_ms(lambda fn=fn: run(fn, False), device, repeats)
        r[f"{name}_fwdbwd_ms"] = _time_ms(lambda fn=fn: run(fn, True), device, repeats)
    w64 = w.double().requires_grad_()
    ref = torch_distortion(w64, t_s.double(), t_e.double(), packed)
    (g64,) = torch.autograd.grad((ref * g.double()).sum(), w64)
    for L in ("ray", "block"):
        x = w.clone().requires_grad_()
        loss = fns[L](x, t_s, t_e, packed)
        (gx,) = torch.autograd.grad((loss * g).sum(), x)
        rel = (loss.double() - ref).abs().max() / ref.abs().max()
        r[f"{L}_max_rel_err_loss"] = rel.item()
        r[f"{L}_max_rel_err_grad"] = ((gx.double() - g64).abs().max() / g64.abs().max()).item()
        r[f"speedup_{L}_fwdbwd"] = r["torch_fwdbwd_ms"] / r[f"{L}_fwdbwd_ms"]
    r["block_over_ray_fwdbwd"] = r["block_fwdbwd_ms"] / r["ray_fwdbwd_ms"]
    return r


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--n-rays", type=int, default=None)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--mean-samples", type=int, default=64, help="composite: samples per ray")
    ap.add_argument(
        "--only",
        choices=("composite", "distortion", "march_composite"),
        help="run one benchmark, not all three",
    )
    ap.add_argument("--dump", help="also save kernel_outputs() here, a .pt file (compare_outputs)")


def run(a: argparse.Namespace) -> int:
    for flag in ("n_rays", "repeats", "mean_samples"):
        v = getattr(a, flag)
        require(v is None or v >= 1, f"--{flag.replace('_', '-')} must be at least 1, got {v}")
    if a.dump:
        claim_output(a.dump, DUMP_FILE, force=None)
    cuda = a.device.startswith("cuda")
    n = a.n_rays or (2**16 if cuda else 2**10)
    res = {}
    if a.only in (None, "composite"):
        res["composite"] = bench_composite(a.device, n, a.mean_samples, repeats=a.repeats)
    if a.only in (None, "distortion"):
        res["distortion"] = bench_distortion(a.device, n, a.mean_samples, repeats=a.repeats)
    if a.only in (None, "march_composite"):
        res["march_composite"] = bench_march_composite(
            a.device, n, resolution=128 if cuda else 64, repeats=a.repeats
        )
    if a.dump:
        with atomic_path(a.dump) as tmp:
            torch.save(kernel_outputs(a.device), tmp)
    print(json.dumps(res, indent=1, default=lambda x: float(x) if math.isfinite(x) else str(x)))
    return 0


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    return benchmark_main("kernels_render", __doc__, add_arguments, run, argv, prog)


if __name__ == "__main__":
    raise SystemExit(main())
