"""The robustness studies of supplement H, I, J: how reconstruction degrades with camera-pose
error, with noise events, and without the method's window / sampling / loss choices; and, beside
them, with a camera-mount error (one camera-frame turn shared by every training pose).

    fastenerf bench study pose-error|mount-error|noise|ablation SCENE \
        [--budget-s 60 | --steps N] [--levels ...] [--out DIR] [--resume] [--seed 0] \
        [--device auto] [--eval-views 10] [--eval-scale 1] [--max-wall-s S] [--quiet]

Each level trains the fast backend (ngp, preset `fast`) once on SCENE with the same budget
(training seconds, or `--steps`), in its own run folder OUT/runs/LEVEL, through
`benchmarks.curve.train_curve` (the one training loop; the clock excludes evaluation). Every
run is evaluated on the same clean test views (the pose errors and the noise touch only the
training rig and events) by the one evaluation path (`fastenerf.evaluate`): at budget/4,
budget/2 and the budget with a time budget, at the last step with `--steps`. One process
trains the levels in order; several studies may run side by side on one GPU.

Outputs in OUT (STUDY = pose-error, mount-error, noise or ablation):
  STUDY.json       every level: the measured perturbation (from its run's config.json), the
                   knobs it trained with, PSNR / SSIM (colour-corrected), steps, training
                   seconds, its evaluation points, machine and versions; the supplement's
                   numbers and, for the numeric studies, where the curve breaks (the
                   adjacent levels with the largest PSNR drop, the first level more than 3 dB
                   below level 0's)
  STUDY.png        PSNR and SSIM against the level (log axis with 0 at a marked place)
  STUDY_grid.png   one test view per level (colour-corrected render, labelled with level
                   and PSNR) after the ground truth: the supplement's Figs. 10-12
  STUDY.md         the table, ours beside the supplement's
A study resumes where it stopped: with --resume finished levels are kept and unfinished
ones continue from their checkpoints.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import time
from pathlib import Path
from typing import Any

from benchmarks import study_threshold
from benchmarks.cli import benchmark_main
from benchmarks.curve import load_scene_dir, make_config, read_curve, train_curve
from benchmarks.session import session_info
from benchmarks.study_levels import (
    ABLATION_HELP,
    POSE_STUDIES,
    STUDIES,
    level_overrides,
    level_slug,
    parse_levels,
)
from benchmarks.study_report import final_eval, level_row, summarize, write_outputs
from fastenerf.config import reference_win_max
from fastenerf.errors import InputError
from fastenerf.evaluate import make_eval_set
from fastenerf.hooks import StopOnSignal
from fastenerf.run import read_progress, resolve_device

DEFAULT_BUDGET_S = 60.0
EVAL_FRACTIONS = (0.25, 0.5, 1.0)  # of a time budget: when each run is evaluated


def level_config(study: str, level: Any, scene, args, device: str, base: dict):
    """The TrainConfig of one level: fast preset + --set + the level's overrides + budget."""
    from fastenerf.config import ngp_cone_for_budget

    train = {
        **reference_windows(study, scene.config),
        **base["train"],
        **level_overrides(study, level, scene.config.n_views, args.seed),
    }
    opts = dict(base["backend_options"])
    if args.steps is not None:
        train["steps"] = args.steps
        opts.setdefault("cone_angle", ngp_cone_for_budget(None, args.steps))
        cfg = make_config("ngp", "fast", 60.0, device, train, opts)
        cfg.minutes = None  # a step budget alone: levels compared at equal steps
    else:
        cfg = make_config("ngp", "fast", args.budget_s, device, train, opts)
    return cfg.validate()


def reference_windows(study: str, scene_config) -> dict[str, int]:
    """The ablation's windows unless --set gives them: the reference's U{1..5 % of the loop}
    (10 % real), whatever the device's preset draws (the CPU preset's are longer)."""
    if study != "ablation":
        return {}
    real = scene_config.kind == "real"
    return {"win_min": 1, "win_max": reference_win_max(scene_config.n_views, real)}


def eval_times(budget_s: float | None) -> list[float]:
    """Training times (s) of a time budget's evaluations; a step budget: [inf] (train_curve's
    timed evaluation never fires; the run is evaluated at its last step instead)."""
    if budget_s is None:
        return [math.inf]
    return sorted({f * budget_s for f in EVAL_FRACTIONS})


def level_done(run_dir: Path, args) -> bool:
    """True when the level's run has spent this call's budget (nothing left to train)."""
    if args.steps is not None:
        return int(read_progress(run_dir).get("step", 0) or 0) >= args.steps
    curve = read_curve(run_dir / "curve.json")
    return bool(
        curve
        and curve.get("finished")
        and curve.get("budget_s") == args.budget_s
        and (curve.get("train_s") or 0.0) >= args.budget_s
    )


def run_levels(
    study: str, levels: list, scene, args, device, out: Path, ev, grid_view: int
) -> list[dict]:
    """Train (or resume, or keep) every level in order, each evaluated on `ev`; returns one
    row per level reached (`study_report.level_row`)."""
    base = _base_sets(args.set)
    cfgs = {  # every level's config is built (and checked) before any trains
        lv: level_config(study, lv, scene, args, str(device), base) for lv in levels
    }
    run_dirs = {lv: out / "runs" / level_slug(study, lv) for lv in levels}
    held = [d for d in run_dirs.values() if (d / "checkpoint.pt").is_file()]
    if held and not args.resume:  # refused before anything trains
        raise InputError(
            f"{held[0]}: already holds this level's run; pass --resume to keep or "
            "continue the study, or choose another --out"
        )
    session = session_info(device, args.commit)
    if session["machine"]["cpu_numbers"] and not args.quiet:
        print(f"CPU numbers: {session['machine']['name']}")
    stop = StopOnSignal((signal.SIGINT, signal.SIGTERM))
    t_start = time.perf_counter()
    deadline = None if args.max_wall_s is None else t_start + args.max_wall_s
    warmup = args.warmup_steps
    per_level_s = None  # wall seconds the last trained level took
    rows = []
    for lv in levels:
        run_dir = run_dirs[lv]
        started = (run_dir / "checkpoint.pt").is_file()
        if not (started and level_done(run_dir, args)):
            t0 = time.perf_counter()
            need = per_level_s if per_level_s is not None else _first_level_guess(args)
            if stop.received or (deadline is not None and t0 + need > deadline):
                if started:
                    rows.append(_row(study, lv, run_dir, out, ev, grid_view, args, device))
                continue
            train_curve(
                scene,
                cfgs[lv],
                run_dir,
                ev,
                eval_times(None if args.steps is not None else args.budget_s),
                label={
                    "scene": Path(args.scene).resolve().name,
                    "backend": "ngp",
                    "study": study,
                    "level": lv,
                },
                session=session,
                resume=started,
                deadline=deadline,
                stop=stop,
                warmup_steps=warmup,
                progress=not args.quiet,
            )
            warmup = 0  # one-time costs are paid once per process
            per_level_s = time.perf_counter() - t0
            _free_device_memory()
        rows.append(_row(study, lv, run_dir, out, ev, grid_view, args, device))
    return rows


def _row(study, lv, run_dir, out, ev, grid_view, args, device) -> dict:
    done = level_done(run_dir, args)
    fe = final_eval(run_dir, ev, grid_view, device) if done else None
    curve = read_curve(run_dir / "curve.json") or {}
    return level_row(
        study,
        lv,
        run_dir,
        out,
        curve,
        read_progress(run_dir),
        fe,
        finished=done,
        steps_budget=args.steps is not None,
    )


def _first_level_guess(args) -> float:
    """Wall seconds a level is assumed to take before one has been timed."""
    if args.steps is not None:
        return 0.0  # unknown: start it, the deadline stops it in time
    return 1.2 * args.budget_s + 10.0


def _free_device_memory() -> None:
    """Return the last level's GPU memory before the next level builds its field (a full
    collection costs a fraction of a second on a big heap: only where memory is a device's)."""
    import torch

    if torch.cuda.is_available():
        import gc

        gc.collect()
        torch.cuda.empty_cache()


def _base_sets(items: list[str]) -> dict:
    from benchmarks.error_vs_time import parse_sets

    return parse_sets(items, ["ngp"])["ngp"]


def pick_grid_view(ev, view: int | None) -> int:
    """The test view shown in the grid: `view` (an index of the scene's test views, one of
    the evaluated ones) or the middle evaluated view; returns its position in `ev`."""
    views = [int(v) for v in ev.views]
    if view is None:
        return len(views) // 2
    if view not in views:
        raise InputError(
            f"--grid-view {view}: not one of the evaluated test views {views} (see --eval-views)"
        )
    return views.index(view)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = _top_epilog()
    sub = p.add_subparsers(dest="study", metavar="STUDY", required=True)
    for name, spec in STUDIES.items():
        s = sub.add_parser(
            name,
            help=_study_help(name).replace("%", "%%"),
            description=_study_help(name) + ". " + _levels_help(name),
            epilog=_outputs_epilog(name),
        )
        s.add_argument("scene", metavar="SCENE", help="scene folder with ground-truth test views")
        s.add_argument(
            "--levels",
            nargs="+",
            default=None,
            metavar="L",
            help=f"levels to run (default: {' '.join(_fmt(x) for x in spec.levels)})",
        )
        _add_common(s, name)
    s = sub.add_parser(
        "threshold",
        help="contrast thresholds: estimated from a wrong start vs given (issue #20)",
        description=study_threshold.__doc__.split("\n\n")[1],
        epilog="outputs in --out:" + study_threshold.__doc__.split("Outputs in OUT:")[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    study_threshold.add_arguments(s)
    _add_common(s, "threshold")


def _add_common(s: argparse.ArgumentParser, name: str) -> None:
    budget = s.add_mutually_exclusive_group()
    budget.add_argument(
        "--budget-s",
        type=float,
        default=DEFAULT_BUDGET_S,
        help="training seconds per level (default 60; evaluated at 1/4, 1/2 and all of it)",
    )
    budget.add_argument(
        "--steps", type=int, default=None, help="train N steps per level instead of seconds"
    )
    s.add_argument("--out", default=None, help=f"output folder (default runs/bench/{name}-SCENE)")
    s.add_argument("--resume", action="store_true", help="keep finished levels, continue others")
    s.add_argument("--seed", type=int, default=0, help="perturbation seed (default 0)")
    s.add_argument("--device", default="auto", help="cuda, cuda:N, cpu or auto")
    s.add_argument("--eval-views", type=int, default=10, help="test views evaluated (default 10)")
    s.add_argument(
        "--eval-scale", type=float, default=1.0, help="evaluation resolution scale (default 1)"
    )
    s.add_argument(
        "--grid-view",
        type=int,
        default=None,
        help="test view index shown in the grid (default: the middle evaluated view)",
    )
    s.add_argument(
        "--max-wall-s",
        type=float,
        default=None,
        help="stop (checkpointed, resumable) after this many wall seconds",
    )
    s.add_argument(
        "--set",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        help="TrainConfig field or ngp option for every level (JSON value)",
    )
    s.add_argument("--warmup-steps", type=int, default=2, help="untimed warm-up steps (default 2)")
    s.add_argument("--commit", default=None, help="git commit to record")
    s.add_argument("--quiet", action="store_true", help="no progress bars, no table echo")


def _fmt(x) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def _study_help(name: str) -> str:
    return {
        "pose-error": "camera-pose error: every training pose turned by X° about a random axis",
        "mount-error": "camera-mount error: every training pose turned by X° about ONE random "
        "axis in the camera's own frame (a camera mis-mounted on its turntable; learn it back "
        "with --set refine_poses=true refine_shared=true)",
        "noise": "noise events: uniform random events, X % of the clean count, added to the "
        "training stream",
        "ablation": "the method's choices switched off one at a time (training knobs)",
    }[name]


def _levels_help(name: str) -> str:
    spec = STUDIES[name]
    if name == "ablation":
        return "Variants: " + "; ".join(f"{k}: {v}" for k, v in ABLATION_HELP.items())
    unit = "degrees" if name in POSE_STUDIES else "percent of the clean event count"
    sup = ", ".join(f"{_fmt(k)} → {v:.2f} dB" for k, v in spec.supplement.items())
    sup = f"The supplement on Drums: {sup}." if sup else f"Supplement: {spec.supplement_note}."
    return (
        f"Levels in {unit}, default {' '.join(_fmt(x) for x in spec.levels)}. "
        f"Test views stay exact. {sup}"
    )


def _top_epilog() -> str:
    """The levels of each study and the outputs (from the module docstring)."""
    lines = ["levels (override with --levels):"]
    for name, spec in STUDIES.items():
        unit = {"deg": " degrees", "%": " percent"}.get(spec.unit, "")
        lines.append(f"  {name:<11} {' '.join(_fmt(x) for x in spec.levels)}{unit}")
    outputs = __doc__.split("Outputs in OUT", 1)[1]
    return "\n".join(lines) + "\n\noutputs in --out" + outputs


def _outputs_epilog(name: str) -> str:
    return (
        f"outputs in --out: {name}.json (every level: measured perturbation, knobs, "
        f"PSNR/SSIM, steps, seconds, machine), {name}.png (PSNR and SSIM against the level), "
        f"{name}_grid.png (ground truth + one test view per level), {name}.md (the table beside "
        "the supplement's numbers; for the numeric studies: where the curve breaks); "
        "runs/LEVEL/ holds each level's run folder."
    )


def run(args: argparse.Namespace) -> int:
    study = args.study
    if study == "threshold":
        return study_threshold.run(args)
    levels = parse_levels(study, args.levels)
    if args.steps is not None and args.steps < 1:
        raise InputError("--steps must be at least 1")
    if args.steps is None and not (args.budget_s > 0 and math.isfinite(args.budget_s)):
        raise InputError("--budget-s must be a positive number of seconds")
    if args.eval_views < 1:
        raise InputError("--eval-views must be at least 1")
    if args.seed < 0:
        raise InputError("--seed must be a non-negative integer")
    device = resolve_device(args.device)
    scene = load_scene_dir(args.scene)
    name = Path(args.scene).resolve().name
    out = Path(args.out) if args.out else Path("runs") / "bench" / f"{study}-{name}"
    out.mkdir(parents=True, exist_ok=True)
    ev = make_eval_set(scene, args.eval_views, args.eval_scale)
    grid_view = pick_grid_view(ev, args.grid_view)
    rows = run_levels(study, levels, scene, args, device, out, ev, grid_view)
    if not rows:
        raise InputError("no level ran (--max-wall-s too small for one level?)")
    result = summarize(study, rows, levels, args, scene)
    result["grid_view"] = int(ev.views[grid_view])
    paths = write_outputs(result, out, ev, grid_view)
    for k in ("json", "png", "grid", "md"):
        print(f"wrote {paths[k]}")
    if not args.quiet:
        print(paths["md"].read_text())
    if not result["complete"]:
        print("incomplete: run again with --resume to do the remaining levels")
    return 0


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    return benchmark_main("study", __doc__, add_arguments, run, argv, prog)


if __name__ == "__main__":
    sys.exit(main())
