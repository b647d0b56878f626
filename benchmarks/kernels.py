"""Kernel benchmark: every Warp kernel against the same op in plain PyTorch, one run.

    python -m benchmarks.kernels [--device cuda] [--out DIR]

Runs the hash grid, SH, event-query, compositing and marching benchmarks of
`benchmarks.kernels_encoding` and `benchmarks.kernels_render` on one device, side by side,
and writes `kernels.json` and `kernels.md` (a table for `benchmarks/RESULTS.md`) with the
device, the Warp/torch versions, the speed-up over PyTorch, the achieved GB/s against a copy
bandwidth measured in the same run, and the error against float64. Tiny sizes on CPU.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
from pathlib import Path

import torch

from benchmarks import kernels_encoding as enc
from benchmarks import kernels_render as ren

# (row label, result key, warp-ms key, torch-ms key, GB/s key, error key)
ROWS = [
    ("hash grid fwd", "hashgrid", "warp_fwd_ms", "torch_fwd_ms", "fwd_GBps", "max_abs_err"),
    (
        "hash grid fwd+bwd",
        "hashgrid",
        "warp_fwdbwd_ms",
        "torch_fwdbwd_ms",
        "fwdbwd_GBps",
        "max_abs_err_grad_table",
    ),
    ("SH deg 4 fwd+bwd", "sh", "warp_fwdbwd_ms", "torch_fwdbwd_ms", "fwdbwd_GBps", "max_abs_err"),
    ("event window query", "events", "warp_ms", "torch_ms", None, "max_abs_err"),
    *(
        row
        for L in ("ray", "block")  # composite's two layouts: a thread / 32 threads per ray
        for row in (
            (
                f"composite fwd, {L} layout",
                "composite",
                f"{L}_fwd_ms",
                "torch_fwd_ms",
                f"{L}_fwd_GBps",
                f"{L}_max_abs_err_rgb",
            ),
            (
                f"composite fwd+bwd, {L} layout",
                "composite",
                f"{L}_fwdbwd_ms",
                "torch_fwdbwd_ms",
                f"{L}_fwdbwd_GBps",
                f"{L}_max_abs_err_grad_rgb",
            ),
        )
    ),
    (
        "march",
        "march_composite",
        "warp_march_ms",
        "torch_march_ms",
        "march_GBps",
        "max_abs_err_t_start",
    ),
    (
        "march, fixed capacity",
        "march_composite",
        "warp_march_fixed_ms",
        "torch_march_ms",
        None,
        None,
    ),
    (
        "march+field+composite",
        "march_composite",
        "warp_pipeline_ms",
        "torch_pipeline_ms",
        None,
        "max_abs_err_rgb",
    ),
]


def run(device: str) -> dict:
    cuda = device.startswith("cuda")
    n_pts = 2**20 if cuda else 2**12
    n_rays = 2**16 if cuda else 2**9
    reps = 30 if cuda else 3
    res = {
        "hashgrid": enc.bench_hashgrid(device, n_pts, repeats=reps),
        "sh": enc.bench_sh(device, n_pts, repeats=reps),
        "events": enc.bench_event_query(
            device, 10**7 if cuda else 10**4, n_queries=2**18 if cuda else 2**10, repeats=reps
        ),
        "composite": ren.bench_composite(device, n_rays, repeats=reps),
        "march_composite": ren.bench_march_composite(
            device, n_rays, resolution=128 if cuda else 32, repeats=reps
        ),
    }
    res["copy_GBps"] = enc.copy_bandwidth_gbs(device)
    return res


def machine(device: str) -> str:
    if device.startswith("cuda"):
        return torch.cuda.get_device_name(torch.device(device))
    return f"CPU {platform.processor() or platform.machine()}"


def _get(d: dict, key: str | None):
    if key is None:
        return None
    v = d.get(key)
    return v if isinstance(v, (int, float)) and math.isfinite(v) else None


def _fmt(v, spec: str = ".3f") -> str:
    return "—" if v is None else format(v, spec)


def markdown(res: dict, device: str) -> str:
    import warp as wp

    lines = [
        f"Device: **{machine(device)}**; torch {torch.__version__}, warp {wp.__version__}; "
        f"copy bandwidth measured in the same run: {res['copy_GBps']:.0f} GB/s "
        "(bytes read + written).",
        "",
        "| op | size | Warp ms | PyTorch ms | speed-up | Warp GB/s | % of copy | max err vs f64 |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    copy = res["copy_GBps"]
    for label, key, wk, tk, gk, ek in ROWS:
        r = res.get(key, {})
        w, t, g, e = _get(r, wk), _get(r, tk), _get(r, gk), _get(r, ek)
        keys = ("n_points", "n_rays", "n_samples", "n_events", "n_queries")
        size = ", ".join(f"{k}={r[k]}" for k in keys if k in r)
        speed = "—" if not (w and t) else f"{t / w:.1f}×"
        share = "—" if g is None else f"{100 * g / copy:.0f}%"
        lines.append(
            f"| {label} | {size} | {_fmt(w)} | {_fmt(t)} | {speed} | {_fmt(g, '.0f')} | "
            f"{share} | {_fmt(e, '.1e')} |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--out", default="benchmarks/out", help="folder for kernels.json/.md")
    a = ap.parse_args(argv)
    res = run(a.device)
    md = markdown(res, a.device)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "kernels.json").write_text(json.dumps(res, indent=1, default=str))
    (out / "kernels.md").write_text(md)
    print(md)
    print(f"wrote {out / 'kernels.json'} and {out / 'kernels.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
