"""Probe (issue #17): ngp's MLPs fully fused in Warp tiles against torch's GEMMs.

    python -m benchmarks.fused_mlp_probe [--device cuda] [--n 1048576] [--out PROBE.json]

The MLPs are a third of a GPU training step (benchmarks/RESULTS.md, the forty-second session),
and what they cost is mostly memory: torch's GEMMs write every sample's hidden activations,
read them back for the ReLU's backward, and again for the weight gradients. A fully fused MLP
(tiny-cuda-nn's) keeps a block of samples' activations on chip. This probe times both of
ngp's shapes (no biases), the density MLP (32 -> 64 -> 16, one hidden ReLU layer) and the
colour MLP (32 -> 64 -> 64 -> 8, two), each both ways, forward and forward+backward, in
float16 with float32 accumulation, before anything is built on it:

- fused: one Warp kernel a pass, `TILE_M` samples a block; the backward recomputes the hidden
  layers from the input rather than reading them, and sums each block's weight gradients over
  its `BACKWARD_TILES` tiles on chip before adding them into float32 buffers
  (`wp.tile_atomic_add`: one add a block, not one a tile, so 2^20 samples make 1,024 adds to
  the same few thousand addresses, not 16,384). Two variants on a GPU (`VARIANTS`): `wp.tile_matmul`
  through cuBLASDx (LTOs compiled on first use) and through Warp's cooperative scalar GEMM;
- torch: `F.linear` and `relu` in float16 under autograd, as the field runs them.

Per network: torch's medians and each fused variant's (ms, CUDA events, warm-up excluded),
each one's largest errors against a float64 reference (relative to each output's largest
value) or the error that stopped it (a tile too large for a block's shared memory is the
colour MLP's risk), and each variant's first call in seconds (its compile on a cold kernel
cache); on the CPU the errors only (the scalar variant), at a small N: a check, not a timing.
Progress on stderr; printed as JSON, or written atomically to --out after every part (an
existing file is refused at the start), so a run cut off by a time limit leaves what it did.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from itertools import pairwise
from pathlib import Path

import numpy as np
import torch
import warp as wp

from fastenerf.errors import require
from fastenerf.kernels.common import launch_tiled
from fastenerf.run import resolve_device

from .cli import benchmark_main, print_or_write_table
from .timing import time_ms

TILE_M = 64  # samples a tile: a forward block's
BACKWARD_TILES = 16  # tiles a backward block: its weight gradients summed on chip first
N_IN, N_HIDDEN, N_OUT, N_RGB = 32, 64, 16, 8  # N_RGB: the colour MLP's padded output


@wp.func
def _relu(v: wp.float32):
    return wp.max(v, wp.float32(0.0))


@wp.func
def _masked(g: wp.float32, h: wp.float32):
    return wp.where(h > wp.float32(0.0), g, wp.float32(0.0))


def _forward(
    x: wp.array2d(dtype=wp.float16),
    w1: wp.array2d(dtype=wp.float16),
    w2: wp.array2d(dtype=wp.float16),
    y: wp.array2d(dtype=wp.float32),
):
    """y = relu(x w1) w2 for one block of TILE_M rows; x (N, 32), w1 (32, 64), w2 (64, 16)."""
    i = wp.tid()
    a = wp.tile_load(x, shape=(TILE_M, N_IN), offset=(i * TILE_M, 0))
    h = wp.tile_zeros(shape=(TILE_M, N_HIDDEN), dtype=wp.float32)
    wp.tile_matmul(a, wp.tile_load(w1, shape=(N_IN, N_HIDDEN)), h)
    h16 = wp.tile_astype(wp.tile_map(_relu, h), wp.float16)
    out = wp.tile_zeros(shape=(TILE_M, N_OUT), dtype=wp.float32)
    wp.tile_matmul(h16, wp.tile_load(w2, shape=(N_HIDDEN, N_OUT)), out)
    wp.tile_store(y, out, offset=(i * TILE_M, 0))


def _backward(
    x: wp.array2d(dtype=wp.float16),
    w1: wp.array2d(dtype=wp.float16),
    w2: wp.array2d(dtype=wp.float16),
    gy: wp.array2d(dtype=wp.float16),
    gx: wp.array2d(dtype=wp.float32),
    gw1: wp.array2d(dtype=wp.float32),
    gw2: wp.array2d(dtype=wp.float32),
):
    """The gradients of `_forward` for one block of `BACKWARD_TILES` tiles: gx (its rows),
    and the block's share of gw1 and gw2 summed over its tiles, then added in (they start at
    zero: one atomic add a block, not one a tile); the hidden layer recomputed from x."""
    i = wp.tid()
    b1 = wp.tile_load(w1, shape=(N_IN, N_HIDDEN))
    b2 = wp.tile_load(w2, shape=(N_HIDDEN, N_OUT))
    d1 = wp.tile_zeros(shape=(N_IN, N_HIDDEN), dtype=wp.float32)
    d2 = wp.tile_zeros(shape=(N_HIDDEN, N_OUT), dtype=wp.float32)
    for t in range(BACKWARD_TILES):
        row = (i * BACKWARD_TILES + t) * TILE_M
        a = wp.tile_load(x, shape=(TILE_M, N_IN), offset=(row, 0))
        g = wp.tile_load(gy, shape=(TILE_M, N_OUT), offset=(row, 0))
        h = wp.tile_zeros(shape=(TILE_M, N_HIDDEN), dtype=wp.float32)
        wp.tile_matmul(a, b1, h)
        h16 = wp.tile_astype(wp.tile_map(_relu, h), wp.float16)
        gh = wp.tile_zeros(shape=(TILE_M, N_HIDDEN), dtype=wp.float32)
        wp.tile_matmul(g, wp.tile_transpose(b2), gh)
        gh16 = wp.tile_astype(wp.tile_map(_masked, gh, h), wp.float16)
        ga = wp.tile_zeros(shape=(TILE_M, N_IN), dtype=wp.float32)
        wp.tile_matmul(gh16, wp.tile_transpose(b1), ga)
        wp.tile_store(gx, ga, offset=(row, 0))
        wp.tile_matmul(wp.tile_transpose(h16), g, d2)
        wp.tile_matmul(wp.tile_transpose(a), gh16, d1)
    wp.tile_atomic_add(gw2, d2)
    wp.tile_atomic_add(gw1, d1)


def _forward2(
    x: wp.array2d(dtype=wp.float16),
    w1: wp.array2d(dtype=wp.float16),
    w2: wp.array2d(dtype=wp.float16),
    w3: wp.array2d(dtype=wp.float16),
    y: wp.array2d(dtype=wp.float32),
):
    """y = relu(relu(x w1) w2) w3 for one block; x (N, 32), w1 (32, 64), w2 (64, 64),
    w3 (64, 8)."""
    i = wp.tid()
    a = wp.tile_load(x, shape=(TILE_M, N_IN), offset=(i * TILE_M, 0))
    h1 = wp.tile_zeros(shape=(TILE_M, N_HIDDEN), dtype=wp.float32)
    wp.tile_matmul(a, wp.tile_load(w1, shape=(N_IN, N_HIDDEN)), h1)
    h2 = wp.tile_zeros(shape=(TILE_M, N_HIDDEN), dtype=wp.float32)
    wp.tile_matmul(wp.tile_astype(wp.tile_map(_relu, h1), wp.float16),
                   wp.tile_load(w2, shape=(N_HIDDEN, N_HIDDEN)), h2)  # fmt: skip
    out = wp.tile_zeros(shape=(TILE_M, N_RGB), dtype=wp.float32)
    wp.tile_matmul(wp.tile_astype(wp.tile_map(_relu, h2), wp.float16),
                   wp.tile_load(w3, shape=(N_HIDDEN, N_RGB)), out)  # fmt: skip
    wp.tile_store(y, out, offset=(i * TILE_M, 0))


def _backward2(
    x: wp.array2d(dtype=wp.float16),
    w1: wp.array2d(dtype=wp.float16),
    w2: wp.array2d(dtype=wp.float16),
    w3: wp.array2d(dtype=wp.float16),
    gy: wp.array2d(dtype=wp.float16),
    gx: wp.array2d(dtype=wp.float32),
    gw1: wp.array2d(dtype=wp.float32),
    gw2: wp.array2d(dtype=wp.float32),
    gw3: wp.array2d(dtype=wp.float32),
):
    """`_forward2`'s gradients for one block of `BACKWARD_TILES` tiles, as `_backward`'s."""
    i = wp.tid()
    b1 = wp.tile_load(w1, shape=(N_IN, N_HIDDEN))
    b2 = wp.tile_load(w2, shape=(N_HIDDEN, N_HIDDEN))
    b3 = wp.tile_load(w3, shape=(N_HIDDEN, N_RGB))
    d1 = wp.tile_zeros(shape=(N_IN, N_HIDDEN), dtype=wp.float32)
    d2 = wp.tile_zeros(shape=(N_HIDDEN, N_HIDDEN), dtype=wp.float32)
    d3 = wp.tile_zeros(shape=(N_HIDDEN, N_RGB), dtype=wp.float32)
    for t in range(BACKWARD_TILES):
        row = (i * BACKWARD_TILES + t) * TILE_M
        a = wp.tile_load(x, shape=(TILE_M, N_IN), offset=(row, 0))
        g = wp.tile_load(gy, shape=(TILE_M, N_RGB), offset=(row, 0))
        p1 = wp.tile_zeros(shape=(TILE_M, N_HIDDEN), dtype=wp.float32)
        wp.tile_matmul(a, b1, p1)
        h1 = wp.tile_astype(wp.tile_map(_relu, p1), wp.float16)
        p2 = wp.tile_zeros(shape=(TILE_M, N_HIDDEN), dtype=wp.float32)
        wp.tile_matmul(h1, b2, p2)
        h2 = wp.tile_astype(wp.tile_map(_relu, p2), wp.float16)
        g2 = wp.tile_zeros(shape=(TILE_M, N_HIDDEN), dtype=wp.float32)
        wp.tile_matmul(g, wp.tile_transpose(b3), g2)
        g2h = wp.tile_astype(wp.tile_map(_masked, g2, p2), wp.float16)
        g1 = wp.tile_zeros(shape=(TILE_M, N_HIDDEN), dtype=wp.float32)
        wp.tile_matmul(g2h, wp.tile_transpose(b2), g1)
        g1h = wp.tile_astype(wp.tile_map(_masked, g1, p1), wp.float16)
        ga = wp.tile_zeros(shape=(TILE_M, N_IN), dtype=wp.float32)
        wp.tile_matmul(g1h, wp.tile_transpose(b1), ga)
        wp.tile_store(gx, ga, offset=(row, 0))
        wp.tile_matmul(wp.tile_transpose(h2), g, d3)
        wp.tile_matmul(wp.tile_transpose(h1), g2h, d2)
        wp.tile_matmul(wp.tile_transpose(a), g1h, d1)
    wp.tile_atomic_add(gw3, d3)
    wp.tile_atomic_add(gw2, d2)
    wp.tile_atomic_add(gw1, d1)


# Each variant's four kernels in a module of their own: `enable_mathdx_gemm` is a module
# option. No adjoints: the backward is written out, and each tile_matmul's adjoint would be
# cuBLASDx LTOs to compile too (the last lease's probe spent its 5 minutes compiling).
VARIANTS = {"scalar": False, "cublasdx": True}  # name -> enable_mathdx_gemm
_KERNELS: dict[str, dict] = {}


def kernels(variant: str) -> dict:
    """The variant's kernels by name (`VARIANTS`: tile_matmul through cuBLASDx on a GPU, or
    Warp's cooperative scalar GEMM), made once."""
    if variant not in _KERNELS:
        opts = {"enable_mathdx_gemm": VARIANTS[variant], "max_unroll": 1}  # a loop, not 16 copies
        _KERNELS[variant] = {
            f.__name__: wp.kernel(
                f,
                name=f"{f.__name__.strip('_')}_{variant}",
                enable_backward=False,
                module="unique",
                module_options=opts,
            )  # fmt: skip
            for f in (_forward, _backward, _forward2, _backward2)
        }
    return _KERNELS[variant]


def fused_forward(x: torch.Tensor, ws: list[torch.Tensor], variant: str = "scalar"):
    """x (N, 32) float16 and the (in, out) float16 weights of either network (`SHAPES`) ->
    y (N, out) float32; N a multiple of TILE_M."""
    y = torch.empty(x.shape[0], ws[-1].shape[1], dtype=torch.float32, device=x.device)
    kernel = kernels(variant)["_forward" if len(ws) == 2 else "_forward2"]
    launch_tiled(kernel, x.shape[0] // TILE_M, TILE_M, x, [x, *ws, y])
    return y


def fused_backward(x, ws, gy, variant: str = "scalar") -> list[torch.Tensor]:
    """`fused_forward`'s gradients for gy (N, out) float16: [gx, gw per weight], float32; N a
    multiple of TILE_M * BACKWARD_TILES."""
    dev = x.device
    grads = [torch.empty(x.shape[0], N_IN, dtype=torch.float32, device=dev)]
    grads += [torch.zeros(w.shape, dtype=torch.float32, device=dev) for w in ws]
    kernel = kernels(variant)["_backward" if len(ws) == 2 else "_backward2"]
    blocks = x.shape[0] // (TILE_M * BACKWARD_TILES)
    launch_tiled(kernel, blocks, TILE_M, x, [x, *ws, gy, *grads])
    return grads


def reference(x, ws, gy) -> list[np.ndarray]:
    """y and the gradients [gx, gw per weight] in float64 (numpy), from the float16 inputs."""
    x, gy = (t.double().cpu().numpy() for t in (x, gy))
    ws = [w.double().cpu().numpy() for w in ws]
    pres, hs = [], [x]
    for w in ws[:-1]:
        pres.append(hs[-1] @ w)
        hs.append(np.maximum(pres[-1], 0.0))
    g, gws = gy, []
    for k in range(len(ws) - 1, -1, -1):
        gws.insert(0, hs[k].T @ g)
        g = g @ ws[k].T
        if k:
            g = g * (pres[k - 1] > 0)
    return [hs[-1] @ ws[-1], g, *gws]


SHAPES = {"density": [N_IN, N_HIDDEN, N_OUT], "colour": [N_IN, N_HIDDEN, N_HIDDEN, N_RGB]}


def problem(n: int, widths: list[int], device: str, seed: int = 0):
    """x ~ N(0, 1) (n, widths[0]), weights (in, out) scaled as torch's init, gy ~ N(0, 1)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, widths[0], generator=g)
    ws = [torch.randn(a, b, generator=g) / a**0.5 for a, b in pairwise(widths)]
    gy = torch.randn(n, widths[-1], generator=g)
    half = [t.half().to(device) for t in (x, *ws, gy)]
    return half[0], half[1:-1], half[-1]


def _torch_leaves(x, ws, backward: bool) -> list[torch.Tensor]:
    """x and the weights as F.linear takes them (out, in), leaves that want a gradient."""
    return [t.detach().contiguous().requires_grad_(backward) for t in (x, *(w.t() for w in ws))]


def _torch_step(leaves: list[torch.Tensor], gy: torch.Tensor | None) -> torch.Tensor:
    """The MLP as the field runs it, and its backward for gy (None: forward only)."""
    y = leaves[0]
    for i, w in enumerate(leaves[1:]):
        y = torch.nn.functional.linear(y, w)
        if i < len(leaves) - 2:
            y = torch.relu(y)
    if gy is not None:
        for t in leaves:
            t.grad = None
        y.backward(gy)
    return y


def _max_errors(got, want) -> list[float]:
    """Each result's largest error against its float64 value, relative to that value's
    largest magnitude."""
    out = []
    for g, w in zip(got, want, strict=True):
        g = g.detach().double().cpu().numpy()
        out.append(float(np.abs(g - w).max() / max(np.abs(w).max(), 1e-30)))
    return out


def _say(text: str, t0: float) -> None:
    """A progress line on stderr, flushed at once (a lease reads it after a timeout)."""
    print(f"[{time.perf_counter() - t0:7.1f} s] {text}", file=sys.stderr, flush=True)


def probe_variant(x, ws, gy, want, variant: str, repeats: int) -> dict:
    """One variant of the fused kernels on one problem: its first call's seconds (the compile
    and load: the kernel cache is cold on a fresh machine), its largest errors against the
    float64 `want`, and on CUDA its medians (ms), forward and forward+backward."""
    t = time.perf_counter()
    got = [fused_forward(x, ws, variant), *fused_backward(x, ws, gy, variant)]
    if x.is_cuda:
        torch.cuda.synchronize(x.device)
    res: dict = {"first_call_s": round(time.perf_counter() - t, 2)}
    res["errors"] = _max_errors(got, want)
    if x.is_cuda:
        res["ms"] = {
            "forward": time_ms(lambda: fused_forward(x, ws, variant), str(x.device), repeats),
            "forward_backward": time_ms(
                lambda: (fused_forward(x, ws, variant), fused_backward(x, ws, gy, variant)),
                str(x.device),
                repeats,
            ),  # fmt: skip
        }
    return res


def probe_network(
    n: int, widths: list[int], device: str, repeats: int = 20, variants=None, report=None
) -> dict:
    """One network: torch's float16 MLP and each fused variant (default: both on CUDA, the
    scalar one on the CPU, where cuBLASDx does not apply), each one's largest errors against
    float64 relative to each output's largest value, and on CUDA the medians (ms), forward
    and forward+backward. A variant that fails (to compile, to launch) is recorded with its
    error. report(res) is called after each part (the probe's partial results)."""
    variants = variants or (list(VARIANTS) if device.startswith("cuda") else ["scalar"])
    report = report or (lambda res: None)
    x, ws, gy = problem(n, widths, device)
    want = reference(x, ws, gy)
    names = ["y", "gx", *(f"gw{k + 1}" for k in range(len(ws)))]
    leaves = _torch_leaves(x, ws, True)
    ty = _torch_step(leaves, gy)
    tgot = [ty, leaves[0].grad, *(t.grad.t() for t in leaves[1:])]
    res: dict = {
        "widths": widths,
        "torch_errors": dict(zip(names, _max_errors(tgot, want), strict=True)),
    }
    if device.startswith("cuda"):
        plain = _torch_leaves(x, ws, False)
        res["torch_ms"] = {
            "forward": time_ms(lambda: _torch_step(plain, None), device, repeats),
            "forward_backward": time_ms(lambda: _torch_step(leaves, gy), device, repeats),
        }
    report(res)
    for variant in variants:
        try:
            part = probe_variant(x, ws, gy, want, variant, repeats)
            part["errors"] = dict(zip(names, part["errors"], strict=True))
        except Exception as e:  # noqa: BLE001 - a probe records what stopped it
            part = {"error": f"{type(e).__name__}: {e}".splitlines()[0]}
        res[variant] = part
        report(res)
    return res


def probe(n: int, device: str, repeats: int = 20, out: Path | None = None) -> dict:
    """Both networks (`SHAPES`), a network or variant that fails recorded with its error and
    the rest still run; progress on stderr, and with `out` the results so far rewritten
    there (atomically) after each part, so a run cut off by a time limit leaves them."""
    rows = TILE_M * BACKWARD_TILES  # a backward block's
    require(n > 0 and n % rows == 0, f"--n must be a positive multiple of {rows}, got {n}")
    res: dict = {"n": n, "device": device, "tile_m": TILE_M}
    t0 = time.perf_counter()

    def report(part: dict, name: str) -> None:
        res[name] = part
        done = [k for k in (*VARIANTS, "torch_ms") if k in part]
        _say(f"{name}: {', '.join(done) or 'torch errors'} done", t0)
        if out is not None:
            print_or_write_table(json.dumps(res, indent=2) + "\n", str(out), quiet=True)

    for name, widths in SHAPES.items():
        try:
            probe_network(n, widths, device, repeats, report=lambda p, k=name: report(p, k))
        except Exception as e:  # noqa: BLE001 - a probe records what stopped it
            report({"widths": widths, "error": f"{type(e).__name__}: {e}".splitlines()[0]}, name)
    return res


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    p.add_argument(
        "--n", type=int, default=None, help="samples (default 2^20 on CUDA, 1024 on the CPU)"
    )
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--out", default=None, help="JSON file to write (default: print)")


def run(args: argparse.Namespace) -> int:
    device = str(resolve_device(args.device))
    n = args.n or (1 << 20 if device.startswith("cuda") else 1024)
    require(args.repeats > 0, f"--repeats must be positive, got {args.repeats}")
    out = None if args.out is None else Path(args.out)
    if out is not None:
        require(out.suffix.lower() == ".json", f"{out}: the probe writes a .json file")
        require(not out.exists(), f"{out} exists: give a new file (nothing was written)")
        require(out.parent.is_dir(), f"{out}: its folder {out.parent} is not a folder")
    res = probe(n, device, args.repeats, out)
    if out is None:
        print(json.dumps(res, indent=2))
    else:
        print(out)
    return 0


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    return benchmark_main("fused_mlp_probe", __doc__, add_arguments, run, argv, prog)


if __name__ == "__main__":
    raise SystemExit(main())
