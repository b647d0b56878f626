"""Probe (issue #17): ngp's MLPs fully fused in Warp tiles against torch's GEMMs.

    python -m benchmarks.fused_mlp_probe [--device cuda] [--n 1048576] [--out PROBE.json]

The MLPs are a third of a GPU training step (benchmarks/RESULTS.md, the forty-second session),
and what they cost is mostly memory: torch's GEMMs write every sample's hidden activations,
read them back for the ReLU's backward, and again for the weight gradients. A fully fused MLP
(tiny-cuda-nn's) keeps a block of samples' activations on chip. This probe times the
density MLP's shape (32 -> 64 -> 16, one hidden ReLU layer, no biases) both ways, forward
and forward+backward, in float16 with float32 accumulation, before anything is built on it:

- fused: one Warp kernel a pass, `TILE_M` samples a block (`wp.tile_matmul`, cuBLASDx on a
  GPU); the backward recomputes the hidden layer from the input rather than reading it, and
  adds each block's weight gradients into float32 buffers (`wp.tile_atomic_add`);
- torch: `F.linear` and `relu` in float16 under autograd, as the field runs them.

Each variant's median ms (CUDA events; warm-up excluded) and both ways' largest errors
against a float64 reference (relative to each output's largest value); on the CPU the errors
only, at a small N: a check, not a timing. Printed as
JSON, or written atomically to --out (an existing file is refused).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
import warp as wp

from fastenerf.errors import InputError, require
from fastenerf.io import atomic_path
from fastenerf.kernels.common import launch_tiled

from .cli import benchmark_main
from .timing import time_ms

TILE_M = 64  # samples a block
N_IN, N_HIDDEN, N_OUT = 32, 64, 16


@wp.func
def _relu(v: wp.float32):
    return wp.max(v, wp.float32(0.0))


@wp.func
def _masked(g: wp.float32, h: wp.float32):
    return wp.where(h > wp.float32(0.0), g, wp.float32(0.0))


@wp.kernel
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


@wp.kernel
def _backward(
    x: wp.array2d(dtype=wp.float16),
    w1: wp.array2d(dtype=wp.float16),
    w2: wp.array2d(dtype=wp.float16),
    gy: wp.array2d(dtype=wp.float16),
    gx: wp.array2d(dtype=wp.float32),
    gw1: wp.array2d(dtype=wp.float32),
    gw2: wp.array2d(dtype=wp.float32),
):
    """The gradients of `_forward` for one block: gx (its rows), and the block's share of gw1
    and gw2 added in (they start at zero); the hidden layer recomputed from x."""
    i = wp.tid()
    a = wp.tile_load(x, shape=(TILE_M, N_IN), offset=(i * TILE_M, 0))
    b1 = wp.tile_load(w1, shape=(N_IN, N_HIDDEN))
    b2 = wp.tile_load(w2, shape=(N_HIDDEN, N_OUT))
    g = wp.tile_load(gy, shape=(TILE_M, N_OUT), offset=(i * TILE_M, 0))
    h = wp.tile_zeros(shape=(TILE_M, N_HIDDEN), dtype=wp.float32)
    wp.tile_matmul(a, b1, h)
    h16 = wp.tile_astype(wp.tile_map(_relu, h), wp.float16)
    gh = wp.tile_zeros(shape=(TILE_M, N_HIDDEN), dtype=wp.float32)
    wp.tile_matmul(g, wp.tile_transpose(b2), gh)
    gh16 = wp.tile_astype(wp.tile_map(_masked, gh, h), wp.float16)
    ga = wp.tile_zeros(shape=(TILE_M, N_IN), dtype=wp.float32)
    wp.tile_matmul(gh16, wp.tile_transpose(b1), ga)
    wp.tile_store(gx, ga, offset=(i * TILE_M, 0))
    d2 = wp.tile_zeros(shape=(N_HIDDEN, N_OUT), dtype=wp.float32)
    wp.tile_matmul(wp.tile_transpose(h16), g, d2)
    wp.tile_atomic_add(gw2, d2)
    d1 = wp.tile_zeros(shape=(N_IN, N_HIDDEN), dtype=wp.float32)
    wp.tile_matmul(wp.tile_transpose(a), gh16, d1)
    wp.tile_atomic_add(gw1, d1)


def fused_forward(x, w1, w2) -> torch.Tensor:
    """x (N, 32) float16, w1 (32, 64), w2 (64, 16) float16 -> y (N, 16) float32; N a
    multiple of TILE_M."""
    y = torch.empty(x.shape[0], N_OUT, dtype=torch.float32, device=x.device)
    launch_tiled(_forward, x.shape[0] // TILE_M, TILE_M, x, [x, w1, w2, y])
    return y


def fused_backward(x, w1, w2, gy) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """`fused_forward`'s gradients for gy (N, 16) float16: gx (N, 32), gw1, gw2 float32."""
    dev = x.device
    gx = torch.empty(x.shape[0], N_IN, dtype=torch.float32, device=dev)
    gw1 = torch.zeros(N_IN, N_HIDDEN, dtype=torch.float32, device=dev)
    gw2 = torch.zeros(N_HIDDEN, N_OUT, dtype=torch.float32, device=dev)
    launch_tiled(_backward, x.shape[0] // TILE_M, TILE_M, x, [x, w1, w2, gy, gx, gw1, gw2])
    return gx, gw1, gw2


def reference(x, w1, w2, gy) -> tuple[np.ndarray, ...]:
    """y and the gradients in float64 (numpy), from the float16 inputs."""
    x, w1, w2, gy = (t.double().cpu().numpy() for t in (x, w1, w2, gy))
    pre = x @ w1
    h = np.maximum(pre, 0.0)
    gh = (gy @ w2.T) * (pre > 0)
    return h @ w2, gh @ w1.T, x.T @ gh, h.T @ gy


def problem(n: int, device: str, seed: int = 0):
    """Inputs at the density MLP's shape: x ~ N(0, 1), weights scaled as torch's init."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, N_IN, generator=g)
    w1 = torch.randn(N_IN, N_HIDDEN, generator=g) / N_IN**0.5
    w2 = torch.randn(N_HIDDEN, N_OUT, generator=g) / N_HIDDEN**0.5
    gy = torch.randn(n, N_OUT, generator=g)
    return tuple(t.half().to(device) for t in (x, w1, w2, gy))


def _torch_leaves(x, w1, w2, backward: bool) -> list[torch.Tensor]:
    """x and the weights as F.linear takes them (out, in), leaves that want a gradient."""
    return [t.detach().contiguous().requires_grad_(backward) for t in (x, w1.t(), w2.t())]


def _torch_step(leaves: list[torch.Tensor], gy: torch.Tensor | None) -> torch.Tensor:
    """The MLP as the field runs it, and its backward for gy (None: forward only)."""
    x, w1, w2 = leaves
    y = torch.nn.functional.linear(torch.relu(torch.nn.functional.linear(x, w1)), w2)
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


def probe(n: int, device: str, repeats: int = 20) -> dict:
    """Medians (ms) of both ways, forward and forward+backward, and the fused results' largest
    errors against float64 relative to each output's largest value."""
    require(n > 0 and n % TILE_M == 0, f"--n must be a positive multiple of {TILE_M}, got {n}")
    x, w1, w2, gy = problem(n, device)
    want = reference(x, w1, w2, gy)
    y = fused_forward(x, w1, w2)
    gx, gw1, gw2 = fused_backward(x, w1, w2, gy)
    leaves = _torch_leaves(x, w1, w2, True)
    ty = _torch_step(leaves, gy)
    tgrads = [leaves[0].grad, leaves[1].grad.t(), leaves[2].grad.t()]
    names = ("y", "gx", "gw1", "gw2")
    res = {
        "n": n,
        "device": device,
        "tile_m": TILE_M,
        "errors": dict(zip(names, _max_errors([y, gx, gw1, gw2], want), strict=True)),
        "torch_errors": dict(zip(names, _max_errors([ty, *tgrads], want), strict=True)),
    }
    if device.startswith("cuda"):
        plain = _torch_leaves(x, w1, w2, False)
        res["ms"] = {
            "fused_forward": time_ms(lambda: fused_forward(x, w1, w2), device, repeats),
            "fused_forward_backward": time_ms(
                lambda: (fused_forward(x, w1, w2), fused_backward(x, w1, w2, gy)), device, repeats
            ),
            "torch_forward": time_ms(lambda: _torch_step(plain, None), device, repeats),
            "torch_forward_backward": time_ms(lambda: _torch_step(leaves, gy), device, repeats),
        }
    return res


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument(
        "--n", type=int, default=None, help="samples (default 2^20 on CUDA, 1024 on the CPU)"
    )
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--out", default=None, help="JSON file to write (default: print)")


def run(args: argparse.Namespace) -> int:
    n = args.n or (1 << 20 if args.device.startswith("cuda") else 1024)
    require(args.repeats > 0, f"--repeats must be positive, got {args.repeats}")
    out = None if args.out is None else Path(args.out)
    if out is not None:
        require(out.suffix.lower() == ".json", f"{out}: the probe writes a .json file")
        require(not out.exists(), f"{out} exists: give a new file (nothing was written)")
    text = json.dumps(probe(n, args.device, args.repeats), indent=2) + "\n"
    if out is None:
        print(text, end="")
        return 0
    try:
        with atomic_path(out) as tmp:
            tmp.write_text(text)
    except OSError as e:
        raise InputError(f"{out}: cannot be written ({e.strerror or e})") from None
    print(out)
    return 0


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    return benchmark_main("fused_mlp_probe", __doc__, add_arguments, run, argv, prog)


if __name__ == "__main__":
    raise SystemExit(main())
