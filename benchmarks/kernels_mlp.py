"""Benchmark of the fused MLP (kernels/mlp.py) against the same MLPs in plain PyTorch.

For the ngp field's two MLPs (density 32 -> 64 -> 16, colour 31 -> 64 -> 64 -> 3 unpadded, no
biases; `benchmarks.mlp_widths` times the colour one padded as the field runs it),
times the forward (no grad) and the forward + backward (gradients w.r.t. x and every weight) of
- ``torch_fp32``: the field's `nn.Sequential` in float32,
- ``torch_bf16``: the same under ``torch.autocast(device, torch.bfloat16)`` (what training
  runs on a GPU),
- ``fused``: `fused_mlp` for each tile size, block size and precision asked for.
Medians in ms (CUDA events, `inner` calls between two events, after warm-up; wall clock on the
CPU). Each row also has its max error against a float64 reference on the first rows
(relative to the reference's largest value) and, for the fused variants, the first call's time
(the kernels' compilation where they are not cached yet).

    python -m benchmarks.kernels_mlp --n 1048576 --device cuda --tiles 32 64 128
    python -m benchmarks.kernels_mlp --device cpu --n 4096        # smoke run

Prints a table; ``--out FILE`` also writes the rows as JSON.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import time

import torch

from benchmarks.cli import JSON_FILE, benchmark_main
from benchmarks.timing import time_ms
from fastenerf.errors import require
from fastenerf.fields.ngp import _mlp
from fastenerf.io import write_json
from fastenerf.kernels.mlp import DEFAULT_BLOCK_DIM, DEFAULT_TILE, fused_mlp
from fastenerf.outputs import claim_output

SHAPES = {"density": (32, 64, 16, 1), "color": (31, 64, 3, 2)}  # n_in, hidden, n_out, hidden layers


def _sync(device: str) -> None:
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()


def _reference(x: torch.Tensor, weights) -> torch.Tensor:
    h = x.double()
    for k, w in enumerate(weights):
        h = h @ w.double().T
        if k < len(weights) - 1:
            h = torch.relu(h)
    return h


def _rel_err(y: torch.Tensor, ref: torch.Tensor) -> float:
    return ((y.double() - ref).abs().max() / ref.abs().max().clamp_min(1e-30)).item()


def _row(name: str, fn_fwd, fn_fwdbwd, device: str, repeats: int, inner: int) -> dict:
    return {
        "variant": name,
        "fwd_ms": time_ms(fn_fwd, device, repeats, inner=inner),
        "fwdbwd_ms": time_ms(fn_fwdbwd, device, repeats, inner=inner),
    }


def _fused_row(base, x, weights, g, ref, kw, device, repeats, inner) -> dict:
    """Timings of fused_mlp with options kw, its first call's time and its error."""
    t0 = time.perf_counter()
    y = fused_mlp(x, weights, **kw)
    torch.autograd.grad(y, [x, *weights], g)
    _sync(device)
    first = time.perf_counter() - t0

    def fwd():
        with torch.no_grad():
            return fused_mlp(x, weights, **kw)

    def fwdbwd():
        return torch.autograd.grad(fused_mlp(x, weights, **kw), [x, *weights], g)

    name = f"fused t{kw['tile']} b{kw['block_dim']}" + (" tf32" if kw["tf32"] else "")
    name += "" if kw["blocks"] is None else f" nb{kw['blocks']}"
    r = {**base, **_row(name, fwd, fwdbwd, device, repeats, inner), **kw}
    r["first_call_s"] = first
    with torch.no_grad():
        r["rel_err"] = _rel_err(fused_mlp(x[: ref.shape[0]], weights, **kw), ref)
    return r


def bench_shape(
    shape: str,
    n: int,
    device: str,
    tiles=(DEFAULT_TILE,),
    block_dims=(DEFAULT_BLOCK_DIM,),
    tf32=(False,),
    blocks=(None,),
    repeats: int = 20,
    inner: int = 5,
    col_major: bool = False,
) -> list[dict]:
    """Rows for one MLP shape ("density" or "color"); see the module docstring."""
    n_in, hidden, n_out, n_hidden = SHAPES[shape]
    gen = torch.Generator().manual_seed(0)
    net = _mlp(n_in, hidden, n_out, n_hidden).to(device)
    weights = [p for p in net.parameters()]
    x = torch.randn(n, n_in, generator=gen).to(device)
    if col_major:  # as hash_grid_encode returns its features: a transposed (C, N) array
        x = x.t().contiguous().t()
    x.requires_grad_(True)
    g = torch.randn(n, n_out, generator=gen).to(device)
    m = min(n, 4096)
    ref = _reference(x[:m].detach(), [w.detach() for w in weights])
    autocast = torch.autocast(torch.device(device).type, torch.bfloat16)
    base = {"shape": shape, "n": n, "device": str(device), "x_col_major": col_major}

    def torch_rows(name, ctx_of):
        def fwd():
            with torch.no_grad(), ctx_of():
                return net(x)

        def fwdbwd():
            with ctx_of():
                y = net(x)
            return torch.autograd.grad(y, [x, *weights], g.to(y.dtype))

        r = {**base, **_row(name, fwd, fwdbwd, device, repeats, inner)}
        with torch.no_grad(), ctx_of():
            r["rel_err"] = _rel_err(net(x[:m]).float(), ref)
        return r

    rows = [torch_rows("torch_fp32", contextlib.nullcontext)]
    rows.append(torch_rows("torch_bf16", lambda: autocast))
    for tile, block_dim, tf, nb in itertools.product(tiles, block_dims, tf32, blocks):
        kw = dict(tile=tile, block_dim=block_dim, tf32=tf, blocks=nb)
        rows.append(_fused_row(base, x, weights, g, ref, kw, device, repeats, inner))
    fp32, bf16 = rows[0], rows[1]
    for r in rows:
        r["speedup_fwdbwd_vs_fp32"] = fp32["fwdbwd_ms"] / r["fwdbwd_ms"]
        r["speedup_fwdbwd_vs_bf16"] = bf16["fwdbwd_ms"] / r["fwdbwd_ms"]
    return rows


def format_table(rows: list[dict]) -> str:
    head = f"{'shape':8} {'variant':24} {'fwd ms':>9} {'fwd+bwd ms':>11} {'vs fp32':>8} "
    head += f"{'vs bf16':>8} {'rel err':>9}"
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(
            f"{r['shape']:8} {r['variant']:24} {r['fwd_ms']:9.3f} {r['fwdbwd_ms']:11.3f} "
            f"{r['speedup_fwdbwd_vs_fp32']:7.2f}x {r['speedup_fwdbwd_vs_bf16']:7.2f}x "
            f"{r['rel_err']:9.1e}"
        )
    return "\n".join(lines)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--n", type=int, default=2**20, help="rows (samples) per call")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--tiles", type=int, nargs="+", default=[DEFAULT_TILE], help="rows per tile")
    p.add_argument("--block-dims", type=int, nargs="+", default=[DEFAULT_BLOCK_DIM])
    p.add_argument("--tf32", action="store_true", help="also time TF32 products (CUDA)")
    p.add_argument(
        "--blocks", type=int, nargs="+", default=None, help="persistent blocks (default: auto)"
    )
    p.add_argument("--col-major", action="store_true", help="x column-major (hash-grid output)")
    p.add_argument("--shapes", nargs="+", default=list(SHAPES), choices=list(SHAPES))
    p.add_argument("--repeats", type=int, default=None, help="timed batches (default 20; CPU 3)")
    p.add_argument("--out", default=None, help="write the rows as JSON here (a .json file)")


def run(a: argparse.Namespace) -> int:
    for name in ("n", "repeats"):
        v = getattr(a, name)
        require(v is None or v >= 1, f"--{name} must be at least 1, got {v}")
    for name in ("tiles", "block_dims", "blocks"):
        v = getattr(a, name) or []
        require(all(x >= 1 for x in v), f"--{name.replace('_', '-')} must be at least 1: {v}")
    if a.out:
        claim_output(a.out, JSON_FILE, force=None)
    cpu = not str(a.device).startswith("cuda")
    repeats = a.repeats or (3 if cpu else 20)
    rows = []
    for shape in a.shapes:
        rows += bench_shape(
            shape,
            a.n,
            a.device,
            tiles=a.tiles,
            block_dims=a.block_dims,
            tf32=(False, True) if a.tf32 else (False,),
            blocks=a.blocks or (None,),
            repeats=repeats,
            inner=1 if cpu else 5,
            col_major=a.col_major,
        )
    print(format_table(rows))
    if a.out:
        write_json(a.out, rows)
    return 0


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    return benchmark_main("kernels_mlp", __doc__, add_arguments, run, argv, prog)


if __name__ == "__main__":
    raise SystemExit(main())
