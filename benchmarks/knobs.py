"""Accuracy knobs of the ngp fast path against speed: which default to ship.

    python -m benchmarks.knobs --scene DIR [--budget-s 60] [--out OUT] [--device cuda] \
        [--variants NAME ...] [--variants-file FILE.json] [--resume] [--max-wall-s 540]

Each variant is the `fast` preset with overrides of `NGPOptions` (marching step `cone_angle`,
`dt_min`; occupancy `density_threshold`; hash table `log2_table_size`, `n_levels`) and/or of
`TrainConfig` (`rays_per_step`, `amp`). Every variant trains for the same budget of training
seconds (timed as in benchmarks.error_vs_time: synchronised clock, evaluation and a warm-up
excluded) and is evaluated once at the budget, as `fastenerf eval` does, on every k-th test
view. Reported per variant: PSNR and SSIM at the budget, steps taken, mean training time per
step (train_s / steps) and samples per step.

Outputs in OUT: knobs.json, knobs.png (PSNR at the budget against time per step, points
labelled, the Pareto front joined, the default a star), knobs.md (the table, sorted by PSNR,
with the Pareto front and the front variant closest to the default marked).

Two relative knobs are resolved per scene: `dt_min_scale` multiplies the smallest step
(`--set dt_min=...`, else the default √3/1024 · box size) into `dt_min`, and
`rays_per_step_scale` multiplies the rays per step (`--set`, else the device's default).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import signal
import sys
import time
from pathlib import Path
from typing import Any

from benchmarks.cli import benchmark_main
from benchmarks.curve import load_scene_dir, make_config, read_curve, train_curve
from benchmarks.error_vs_time import collect, parse_sets
from benchmarks.session import finite, jsonable, session_info
from fastenerf.errors import InputError
from fastenerf.evaluate import make_eval_set
from fastenerf.hooks import StopOnSignal
from fastenerf.io import atomic_path, write_json
from fastenerf.run import resolve_device

# name -> {"ngp": NGPOptions overrides, "train": TrainConfig overrides}; "default" has none.
VARIANTS: list[dict[str, Any]] = [
    {"name": "default"},
    # the default cone follows the budget (config.ngp_cone_for_budget): try both settings
    {"name": "cone_0", "ngp": {"cone_angle": 0.0}},
    {"name": "cone_1/256", "ngp": {"cone_angle": 1 / 256}},
    # the default starts as fog of optical depth 9 across the box (ngp.INIT_OPTICAL_DEPTH)
    {"name": "density_bias_0", "ngp": {"density_bias": 0.0}},
    {"name": "dt_min_x2", "ngp": {"dt_min_scale": 2.0}},
    {"name": "dt_min_x4", "ngp": {"dt_min_scale": 4.0}},
    {"name": "occ_thresh_0.005", "ngp": {"density_threshold": 0.005}},
    {"name": "occ_thresh_0.05", "ngp": {"density_threshold": 0.05}},
    {"name": "table_2^17", "ngp": {"log2_table_size": 17}},
    {"name": "table_2^21", "ngp": {"log2_table_size": 21}},
    {"name": "levels_8", "ngp": {"n_levels": 8}},
    {"name": "levels_12", "ngp": {"n_levels": 12}},
    {"name": "rays_x0.5", "train": {"rays_per_step_scale": 0.5}},
    {"name": "rays_x2", "train": {"rays_per_step_scale": 2.0}},
    {"name": "fp32", "train": {"amp": False}},
]


def variant_by_name(names: list[str], variants: list[dict]) -> list[dict]:
    known = {v["name"]: v for v in variants}
    missing = [n for n in names if n not in known]
    if missing:
        raise InputError(f"unknown variant(s) {missing}; known: {list(known)}")
    return [known[n] for n in names]


def read_variants_file(path: str | Path) -> list[dict]:
    """A JSON list of {"name": str, "ngp": {...}, "train": {...}}."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise InputError(f"{path}: cannot read variants ({e})") from None
    if not isinstance(data, list) or not all(
        isinstance(v, dict) and isinstance(v.get("name"), str) for v in data
    ):
        raise InputError(f"{path}: must be a JSON list of objects with a 'name'")
    for v in data:
        extra = sorted(set(v) - {"name", "ngp", "train"})
        if extra:
            raise InputError(f"{path}: variant {v['name']!r}: unknown key(s) {extra}")
    return data


def resolve_variant(variant: dict, scene, device: str, budget_s: float, base: dict):
    """The TrainConfig of `variant` on `scene`: fast preset + base (--set) + the variant."""
    from fastenerf.kernels.occupancy import default_step_size

    train = {**base["train"], **variant.get("train", {})}
    ngp = {**base["backend_options"], **variant.get("ngp", {})}
    if "dt_min_scale" in ngp:  # relative to the base's dt_min, else to the default step
        ref = base["backend_options"].get("dt_min") or default_step_size(scene.config.aabb)
        ngp["dt_min"] = float(ngp.pop("dt_min_scale")) * ref
    scale = train.pop("rays_per_step_scale", None)
    cfg = make_config("ngp", "fast", budget_s, device, train, ngp)
    if scale is not None:
        rps = cfg.resolved(scene.config, device).rays_per_step
        w = cfg.windows_per_step
        cfg.rays_per_step = max(w, int(round(rps * float(scale) / w)) * w)
    return cfg.validate()


def pareto(rows: list[dict]) -> None:
    """Set row["pareto"]: no other row is at least as fast and as accurate, and better in one."""
    for r in rows:
        r["pareto"] = finite(r["psnr"]) and not any(
            finite(o["psnr"])
            and o is not r
            and o["psnr"] >= r["psnr"]
            and o["step_ms"] <= r["step_ms"]
            and (o["psnr"] > r["psnr"] or o["step_ms"] < r["step_ms"])
            for o in rows
        )


def closest_to_default(rows: list[dict]) -> dict | None:
    """The Pareto-front row nearest the default (other than it) in (log time/step, PSNR),
    each axis divided by its spread over all rows."""
    default = next((r for r in rows if r["default"]), None)
    front = [r for r in rows if r["pareto"] and not r["default"]]
    if default is None or not front or not finite(default["psnr"]):
        return None
    ok = [r for r in rows if finite(r["psnr"])]
    lt = [math.log(r["step_ms"]) for r in ok]
    ps = [r["psnr"] for r in ok]
    st, sp = max(max(lt) - min(lt), 1e-9), max(max(ps) - min(ps), 1e-9)

    def dist(r):
        return math.hypot(
            (math.log(r["step_ms"]) - math.log(default["step_ms"])) / st,
            (r["psnr"] - default["psnr"]) / sp,
        )

    return min(front, key=dist)


def rows_from_curves(curves: list[dict], variants: dict[str, dict]) -> list[dict]:
    rows = []
    for c in curves:
        p = c["points"][-1] if c["points"] else None
        v = variants[c["variant"]]
        rows.append(
            {
                "name": c["variant"],
                "overrides": {"ngp": v.get("ngp", {}), "train": v.get("train", {})},
                "default": not v.get("ngp") and not v.get("train"),
                "finished": bool(c.get("finished")),
                "psnr": p["psnr"] if p else float("nan"),
                "ssim": p["ssim"] if p else float("nan"),
                "train_s": p["train_s"] if p else float("nan"),
                "steps": p["step"] if p else 0,
                "step_ms": 1e3 * p["train_s"] / p["step"] if p and p["step"] else float("nan"),
                "samples_per_step": p["samples_per_step"] if p else float("nan"),
                "rays_per_step": c["train_config"]["rays_per_step"],
                "amp": c["train_config"]["amp"],
            }
        )
    pareto(rows)
    return rows


def markdown(result: dict) -> str:
    rows = sorted(result["variants"], key=lambda r: -(r["psnr"] if finite(r["psnr"]) else -1e9))
    machines = " / ".join(result["machines"])
    lines = [f"### ngp accuracy knobs at a {result['budget_s']:g} s budget — {machines}", ""]
    if result["cpu_numbers"]:
        lines += [
            f"**CPU numbers** (measured on {machines}): reduced-size runs, not what the "
            "GPU default should be chosen from.",
            "",
        ]
    if not result["complete"]:
        lines += ["**Incomplete:** some variants have not run yet (continue with `--resume`).", ""]
    lines += [
        f"Scene {result['scene']}; commit {', '.join(result['git_commits'])}. The `fast` preset "
        "with the overrides shown; PSNR/SSIM colour-corrected at the budget; time per step = "
        "training seconds / steps (synchronised clock, occupancy updates included).",
        "",
        "| variant | overrides | PSNR | SSIM | steps | ms/step | samples/step | Pareto |",
        "|---|---|---:|---:|---:|---:|---:|:---:|",
    ]

    def fmt(x, f):
        return format(x, f) if finite(x) else "—"

    for r in rows:
        ov = {**r["overrides"]["ngp"], **r["overrides"]["train"]}
        ov_s = (
            ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in ov.items())
            or "(none)"
        )
        name = f"**{r['name']}**" if r["default"] else r["name"]
        lines.append(
            f"| {name} | {ov_s} | {fmt(r['psnr'], '.2f')} | {fmt(r['ssim'], '.3f')} | "
            f"{r['steps']} | {fmt(r['step_ms'], '.1f')} | "
            f"{fmt(r['samples_per_step'], ',.0f')} | {'★' if r['pareto'] else ''} |"
        )
    c = result.get("closest_to_default")
    d = next((r for r in rows if r["default"]), None)
    lines.append("")
    if d is not None:
        lines.append(
            f"Default: {fmt(d['psnr'], '.2f')} dB at {fmt(d['step_ms'], '.1f')} ms/step"
            f" ({'on' if d['pareto'] else 'not on'} the Pareto front)."
        )
    if c is not None and d is not None:
        lines.append(
            f"Pareto-front variant closest to the default: {c['name']} "
            f"({c['psnr'] - d['psnr']:+.2f} dB, {c['step_ms'] / d['step_ms']:.2f}× "
            "the time per step)."
        )
    best = rows[0] if rows and finite(rows[0]["psnr"]) else None
    if best is not None:
        lines.append(f"Best PSNR at the budget: {best['name']} ({best['psnr']:.2f} dB).")
    lines.append("")
    return "\n".join(lines)


def write_outputs(result: dict, out: Path) -> dict[str, Path]:
    from benchmarks.plots import plot_pareto

    paths = {"json": out / "knobs.json", "png": out / "knobs.png", "md": out / "knobs.md"}
    write_json(paths["json"], jsonable(result))
    title = (
        ("CPU numbers — " if result["cpu_numbers"] else "") + f"{result['scene']}, "
        f"{result['budget_s']:g} s budget — " + " / ".join(result["machines"])
    )
    plot_pareto(result["variants"], paths["png"], title)
    with atomic_path(paths["md"]) as tmp:
        tmp.write_text(markdown(result))
    return paths


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", metavar="DIR", help="scene folder with test views (required)")
    p.add_argument("--budget-s", type=float, default=60.0, help="training seconds per variant")
    p.add_argument(
        "--variants",
        nargs="+",
        default=None,
        metavar="NAME",
        help="run only these (default: all; see --list)",
    )
    p.add_argument(
        "--variants-file",
        default=None,
        help='JSON list of {"name", "ngp": {...}, "train": {...}} replacing the list',
    )
    p.add_argument("--list", action="store_true", help="print the variants and exit")
    p.add_argument(
        "--set",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        help="TrainConfig field or ngp option applied to every variant (JSON value)",
    )
    p.add_argument("--out", default="runs/bench/knobs", help="output folder")
    p.add_argument("--device", default="auto", help="cuda, cuda:N, cpu or auto")
    p.add_argument("--eval-views", type=int, default=10)
    p.add_argument("--eval-scale", type=float, default=1.0)
    p.add_argument("--warmup-steps", type=int, default=2)
    p.add_argument(
        "--resume",
        action="store_true",
        help="keep finished variants in --out, continue unfinished ones",
    )
    p.add_argument(
        "--max-wall-s",
        type=float,
        default=None,
        help="do not start a variant that would not finish within this many seconds",
    )
    p.add_argument("--commit", default=None, help="git commit to record")
    p.add_argument("--quiet", action="store_true")


def run(args: argparse.Namespace) -> int:
    t_start = time.perf_counter()
    variants = read_variants_file(args.variants_file) if args.variants_file else VARIANTS
    if args.list:
        for v in variants:
            print(v["name"], json.dumps({k: v[k] for k in ("ngp", "train") if k in v}))
        return 0
    if args.variants:
        variants = variant_by_name(args.variants, variants)
    if not args.scene:
        raise InputError("--scene DIR is required")
    if not args.budget_s > 0:
        raise InputError("--budget-s must be positive")
    device = resolve_device(args.device)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene = load_scene_dir(args.scene)
    base = parse_sets(args.set, ["ngp"])["ngp"]
    cfgs = {
        v["name"]: resolve_variant(v, scene, str(device), args.budget_s, base) for v in variants
    }
    ev = make_eval_set(scene, args.eval_views, args.eval_scale)
    session = session_info(device, args.commit)
    if session["machine"]["cpu_numbers"]:
        print(f"CPU numbers: {session['machine']['name']}")
    by_name = {v["name"]: v for v in variants}
    stop = StopOnSignal((signal.SIGINT, signal.SIGTERM))
    curves: list[dict] = []
    deadline = None if args.max_wall_s is None else t_start + args.max_wall_s
    per_variant_s = None  # wall seconds the last variant took (to decide whether one more fits)
    for v in variants:
        run_dir = out / "runs" / re.sub(r"[^A-Za-z0-9_.^-]+", "_", v["name"])
        t0 = time.perf_counter()
        need = per_variant_s if per_variant_s is not None else 1.2 * args.budget_s + 10.0
        done = _existing(run_dir) if args.resume else None
        if done is not None and done.get("finished") and done["budget_s"] == args.budget_s:
            curve = done
        elif stop.received or (deadline is not None and t0 + need > deadline):
            if done is None:
                continue
            curve = done  # unfinished: shown as such, continued by the next --resume
        else:
            curve = train_curve(
                scene,
                cfgs[v["name"]],
                run_dir,
                ev,
                [args.budget_s],
                label={
                    "scene": Path(args.scene).resolve().name,
                    "backend": "ngp",
                    "variant": v["name"],
                },
                session=session,
                resume=args.resume,
                deadline=deadline,
                stop=stop,
                warmup_steps=args.warmup_steps,
                progress=not args.quiet,
            )
            per_variant_s = time.perf_counter() - t0
        curves.append(curve)
    if not curves:
        raise InputError("no variant ran (--max-wall-s too small for one budget?)")
    result = summarize(curves, by_name, args, scene, len(variants))
    paths = write_outputs(result, out)
    for k in ("json", "png", "md"):
        print(f"wrote {paths[k]}")
    print(markdown(result))
    if not result["complete"]:
        print("incomplete: run again with --resume to do the remaining variants")
    return 0


def _existing(run_dir: Path) -> dict | None:
    c = read_curve(run_dir / "curve.json")
    return c if c and c.get("points") else None


def summarize(curves: list[dict], variants: dict[str, dict], args, scene, n_variants: int) -> dict:
    base = collect(curves, {"budget_s": args.budget_s})
    rows = rows_from_curves(curves, variants)
    close = closest_to_default(rows)
    return {
        "benchmark": "knobs",
        "scene": Path(args.scene).resolve().name,
        "scene_dir": str(Path(args.scene).resolve()),
        "budget_s": args.budget_s,
        "eval_views": [int(i) for i in curves[0]["eval_views"]],
        "eval_scale": args.eval_scale,
        "cpu_numbers": base["cpu_numbers"],
        "machines": base["machines"],
        "git_commits": base["git_commits"],
        "torch": base["torch"],
        "warp": base["warp"],
        "complete": len(curves) == n_variants and all(c.get("finished") for c in curves),
        "variants": rows,
        "closest_to_default": close,
        "runs": curves,
    }


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    return benchmark_main("knobs", __doc__, add_arguments, run, argv, prog, out_folder=True)


if __name__ == "__main__":
    sys.exit(main())
