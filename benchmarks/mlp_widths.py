"""The ngp colour MLP with and without tensor-core widths (fastenerf/fields/mlp.py), side by side.

Times the forward and the forward + backward (gradients w.r.t. the inputs and every weight, as
a training step takes them) under bf16 autocast, as training runs them on a GPU, of
- ``unpadded``: geometry features (G, bf16) and SH (16, float32) concatenated, G + 16 wide,
  through `mlp(G + 16, hidden, 3, 2)`: the colour MLP before the thirty-first session;
- ``padded``: `ColorMLP(G, hidden)` on the density MLP's whole output (1 + G) and SH, the
  same initial weights where they act;
- ``padded_cat``: the same MLP fed as before the thirty-second session: the σ logit's input
  column multiplied by 0 and torch.cat (``padded`` masks the weights and concatenates words);
- ``density``: the density MLP (32 -> hidden -> 1 + G), aligned either way, for scale.
Medians in ms (CUDA events, after warm-up; wall clock on the CPU); `max_diff` is the largest
difference of a variant's colour logits from the unpadded one's. Needs no Warp, so it runs on
the device machine before Warp is staged.

    python -m benchmarks.mlp_widths --n 1900000 --device cuda --out mlp_widths.json
    python -m benchmarks.mlp_widths --device cpu --n 4096        # smoke run

Prints a table; ``--out FILE`` also writes the rows as JSON.
"""

from __future__ import annotations

import argparse

import torch

from benchmarks.cli import JSON_FILE, benchmark_main
from benchmarks.timing import time_ms
from fastenerf.errors import require
from fastenerf.fields.mlp import ColorMLP, mlp
from fastenerf.io import write_json
from fastenerf.outputs import claim_output


def _variants(n: int, geo: int, hidden: int, device: str) -> dict:
    """name -> (forward () -> output, parameters, inputs) on one shared random batch."""
    torch.manual_seed(0)
    padded = ColorMLP(geo, hidden).to(device)
    torch.manual_seed(0)
    plain = mlp(geo + 16, hidden, 3, 2).to(device)
    density = mlp(32, hidden, 1 + geo, 1).to(device)
    gen = torch.Generator().manual_seed(1)
    # h as the density MLP hands it over under autocast (bf16), SH as its kernel does: float32,
    # the (N, 16) view of (16, N) storage (kernels/sh.py)
    h = torch.randn(n, 1 + geo, generator=gen).to(device, torch.bfloat16).requires_grad_(True)
    sh_storage = torch.randn(16, n, generator=gen).to(device).requires_grad_(True)
    sh = sh_storage.t()
    feats = torch.randn(n, 32, generator=gen).to(device).requires_grad_(True)

    def unpadded():
        return plain(torch.cat([h[:, 1:], sh.to(h.dtype)], 1))

    h_mask = torch.ones(1 + geo, device=device)
    h_mask[0] = 0.0

    def padded_cat():
        x = [h * h_mask.to(h.dtype), sh.to(h.dtype)]
        if padded.n_pad:
            x.append(h.new_zeros(()).expand(n, padded.n_pad))
        return torch.nn.Sequential.forward(padded, torch.cat(x, 1))[:, :3]

    return {
        "unpadded": (unpadded, list(plain.parameters()), [h, sh_storage]),
        "padded": (lambda: padded(h, sh), list(padded.parameters()), [h, sh_storage]),
        "padded_cat": (padded_cat, list(padded.parameters()), [h, sh_storage]),
        "density": (lambda: density(feats), list(density.parameters()), [feats]),
    }


def bench(n: int, geo: int, hidden: int, device: str, repeats: int, inner: int) -> list[dict]:
    """One row per variant (module docstring), with its speed-up over `unpadded`."""
    kind = torch.device(device).type
    amp = torch.autocast(kind, torch.bfloat16)
    rows, outs = [], {}
    for name, (fwd, params, inputs) in _variants(n, geo, hidden, device).items():
        g = None

        def run_fwd(fwd=fwd):
            with torch.no_grad(), amp:
                return fwd()

        def run_fwdbwd(fwd=fwd, params=params, inputs=inputs):
            nonlocal g
            with amp:
                y = fwd()
            g = torch.ones_like(y) if g is None else g
            return torch.autograd.grad(y, [*inputs, *params], g)

        outs[name] = run_fwd().float()
        rows.append(
            {
                "variant": name,
                "n": n,
                "device": str(device),
                "fwd_ms": time_ms(run_fwd, device, repeats, inner=inner),
                "fwdbwd_ms": time_ms(run_fwdbwd, device, repeats, inner=inner),
            }
        )
    for r in rows:
        out = outs[r["variant"]]
        same = out.shape == outs["unpadded"].shape
        r["max_diff"] = float((out - outs["unpadded"]).abs().max()) if same else None
        r["speedup_fwdbwd"] = rows[0]["fwdbwd_ms"] / r["fwdbwd_ms"]
    return rows


def format_table(rows: list[dict]) -> str:
    head = f"{'variant':10} {'fwd ms':>9} {'fwd+bwd ms':>11} {'vs unpadded':>12} {'max diff':>9}"
    lines = [head, "-" * len(head)]
    for r in rows:
        diff = "—" if r["max_diff"] is None else f"{r['max_diff']:.1e}"
        lines.append(
            f"{r['variant']:10} {r['fwd_ms']:9.3f} {r['fwdbwd_ms']:11.3f} "
            f"{r['speedup_fwdbwd']:11.2f}x {diff:>9}"
        )
    return "\n".join(lines)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--n", type=int, default=2**20, help="rows (samples) per call")
    p.add_argument("--geo", type=int, default=15, help="geometry features (NGPOptions)")
    p.add_argument("--hidden", type=int, default=64, help="hidden width (NGPOptions)")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--repeats", type=int, default=None, help="timed batches (default 20; CPU 3)")
    p.add_argument("--out", default=None, help="write the rows as JSON here (a .json file)")


def run(a: argparse.Namespace) -> int:
    for name in ("n", "geo", "hidden", "repeats"):
        v = getattr(a, name)
        require(v is None or v >= 1, f"--{name} must be at least 1, got {v}")
    if a.out:
        claim_output(a.out, JSON_FILE, force=None)
    cpu = not str(a.device).startswith("cuda")
    rows = bench(a.n, a.geo, a.hidden, a.device, a.repeats or (3 if cpu else 20), 1 if cpu else 5)
    print(format_table(rows))
    if a.out:
        write_json(a.out, rows)
    return 0


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    return benchmark_main("mlp_widths", __doc__, add_arguments, run, argv, prog)


if __name__ == "__main__":
    raise SystemExit(main())
