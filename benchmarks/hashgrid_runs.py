"""The hash grid's table backward with R consecutive points per thread (`backward_run`, issue
#17), on samples in ray order and on uniform points.

    python -m benchmarks.hashgrid_runs [--device cuda] [--runs 1 2 4 8 16] [--json OUT]

Ray order is what training gives the backward: the marcher emits a ray's samples one after
another, dt_min = √3/1024 of the box apart (a budgeted run's constant step), so at the coarse
levels several samples share a cell and R of them reach the table in one reduction per
corner. Uniform points share no cell: there the runs only cost. Each R is timed against R = 1
in the same call; `max_rel_diff` is the largest difference of the table gradient from R = 1's,
relative to its largest entry (float rounding order only).
"""

from __future__ import annotations

import argparse
import math

import torch

from benchmarks.cli import JSON_FILE, benchmark_main
from benchmarks.timing import time_ms
from fastenerf.errors import require
from fastenerf.io import write_json
from fastenerf.kernels.gridconfig import HashGridConfig
from fastenerf.kernels.hashgrid import _Variant, hash_grid_encode, init_table
from fastenerf.outputs import claim_output


def ray_ordered_points(n_rays: int, per_ray: int, step: float, gen: torch.Generator, device):
    """(n_rays * per_ray, 3) float32 in [0, 1]^3, ray by ray, `step` apart along each ray
    (box units), every ray inside the box."""
    o = torch.rand(n_rays, 3, generator=gen) * 0.5 + 0.25
    d = torch.nn.functional.normalize(torch.randn(n_rays, 3, generator=gen), dim=1)
    t = torch.arange(per_ray, dtype=torch.float32) * step
    x = (o[:, None, :] + t[None, :, None] * d[:, None, :]).reshape(-1, 3)
    return x.clamp(0.0, 1.0).to(device)


def time_runs(x: torch.Tensor, runs: list[int], repeats: int, log2_T: int = 19) -> list[dict]:
    """Backward(table) ms of each run length on points x (N, 3), one table and cotangent."""
    device = x.device.type
    cfg = HashGridConfig(log2_table_size=log2_T)
    table = init_table(cfg, x.device).requires_grad_(True)
    g = torch.randn(x.shape[0], cfg.n_output_dims, device=x.device)
    rows, base = [], None
    for r in runs:
        v = _Variant(run=r)
        out = hash_grid_encode(x, table, cfg, v)
        (grad,) = torch.autograd.grad(out, table, g, retain_graph=True)
        base = grad if base is None else base
        ms = time_ms(
            lambda out=out: torch.autograd.grad(out, table, g, retain_graph=True),
            device,
            repeats,
            3,
            10,
        )
        scale = base.abs().max().item() or 1.0
        rows.append(
            {"run": r, "bwd_ms": ms, "max_rel_diff": (grad - base).abs().max().item() / scale}
        )
    for row in rows:
        row["speedup_vs_first"] = rows[0]["bwd_ms"] / row["bwd_ms"]
    return rows


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--runs", type=int, nargs="+", default=[1, 2, 4, 8, 16])
    p.add_argument("--rays", type=int, default=None, help="rays (default 8192; CPU 64)")
    p.add_argument("--per-ray", type=int, default=128, help="samples per ray")
    p.add_argument("--repeats", type=int, default=None, help="timed batches (default 30; CPU 3)")
    p.add_argument("--json", default=None, help="write the results here (a .json file)")


def run(a: argparse.Namespace) -> int:
    for name, values in (("runs", a.runs), ("rays", [a.rays]), ("per-ray", [a.per_ray])):
        bad = [v for v in values if v is not None and v < 1]
        require(not bad, f"--{name} must be at least 1, got {bad[0] if bad else None}")
    if a.json:
        claim_output(a.json, JSON_FILE, force=None)
    small = a.device == "cpu"
    n_rays = a.rays or (64 if small else 8192)
    repeats = a.repeats or (3 if small else 30)
    gen = torch.Generator().manual_seed(0)
    step = math.sqrt(3) / 1024
    sets = {
        "ray_order": ray_ordered_points(n_rays, a.per_ray, step, gen, a.device),
        "uniform": torch.rand(n_rays * a.per_ray, 3, generator=gen).to(a.device),
    }
    name = torch.cuda.get_device_name() if a.device == "cuda" else "cpu"
    res = {"device": name, "n_points": n_rays * a.per_ray, "step": step, "sets": {}}
    print(f"hash grid backward(table), {res['n_points']:,} points, {name}")
    print("| points | run | ms | vs first | max rel diff |\n|---|---:|---:|---:|---:|")
    for key, x in sets.items():
        res["sets"][key] = time_runs(x, a.runs, repeats)
        for r in res["sets"][key]:
            print(
                f"| {key} | {r['run']} | {r['bwd_ms']:.3f} | {r['speedup_vs_first']:.2f}x | "
                f"{r['max_rel_diff']:.1e} |"
            )
    if a.json:
        write_json(a.json, res)
    return 0


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    return benchmark_main("hashgrid_runs", __doc__, add_arguments, run, argv, prog)


if __name__ == "__main__":
    raise SystemExit(main())
