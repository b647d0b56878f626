"""`fastenerf eval`: score a trained run on its scene's ground-truth test views."""

from __future__ import annotations

import argparse

HELP = "evaluate a run: render the test views, colour-correct, PSNR / SSIM / LPIPS"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir", metavar="RUN_DIR", help="a training run folder")
    p.add_argument(
        "--views",
        type=int,
        default=None,
        help="evaluate this many evenly spaced test views (default: all)",
    )
    p.add_argument(
        "--scale",
        type=float,
        default=1.0,
        help="render at this fraction of the sensor size (default 1)",
    )
    p.add_argument(
        "--out",
        metavar="DIR",
        default=None,
        help="folder for the corrected images and sheet (default RUN_DIR/eval)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--force", action="store_true", help="write into --out even if it is not an eval folder"
    )


def run(args: argparse.Namespace) -> int:
    from ..errors import InputError
    from ..evaluate import evaluate_run, format_metrics

    if args.scale <= 0 or (args.views is not None and args.views < 1):
        raise InputError("--scale must be positive and --views at least 1")
    check_eval_outputs(args)
    m = evaluate_run(
        args.run_dir,
        max_views=args.views,
        scale=args.scale,
        out_dir=args.out,
        progress=not args.no_progress,
    )
    print(format_metrics(m))
    print(f"wrote {m['images']}/metrics.json, images in {m['images']}/, sheet {m['sheet']}")
    return 0


def check_eval_outputs(args: argparse.Namespace) -> None:
    """--out may be written and the renders fit in memory (before the run is loaded)."""
    from pathlib import Path

    from ..outputs import EVAL, claim_output

    out = args.out if args.out is not None else Path(args.run_dir) / "eval"
    claim_output(out, EVAL, force=args.force)
    check_render_memory(args.run_dir, args.scale, args.views or 1, "eval")


def check_render_memory(run_dir, scale: float, views: int, command: str) -> None:
    """Refuse (`check_memory`) `views` renders at `scale` x the run's sensor that cannot fit."""
    from ..memory import check_memory, image_bytes
    from ..run import read_run_config

    sc = read_run_config(run_dir).get("scene")
    if isinstance(sc, dict) and all(
        isinstance(sc.get(k), int | float) for k in ("width", "height")
    ):
        w, h = round(sc["width"] * scale), round(sc["height"] * scale)
        what = f"{command} --scale {scale:g} ({views:,} views at {w}x{h})"
        check_memory(image_bytes(w, h, views, 9 if command == "eval" else 3), what)
