"""Error against training time: ngp and vanilla trained side by side on the same machine.

    python -m benchmarks.error_vs_time --scenes DIR [DIR ...] --backends ngp vanilla \
        [--budget-s ngp=300 vanilla=480] [--preset fast] [--out OUT] [--device cuda] \
        [--eval-views 10] [--eval-scale 1.0] [--resume] [--max-wall-s 540]

Protocol (DESIGN §8):
- Each (scene, backend) trains through the one training loop with the hooks of
  `benchmarks.curve.train_curve` (scheduled evaluation, curve writer, checkpoints, stop). The
  training clock is the trainer's, synchronised with the device after every step: set-up,
  evaluation and checkpoint writes are outside it (evaluation time is reported per point).
  The learning-rate schedule spans the backend's budget (`TrainConfig.minutes`).
- Before a run's clock starts, a throwaway copy of it takes `--warmup-steps` steps and one
  evaluation, so one-time costs (Warp kernel compilation, CUDA context, cuBLAS handles) are not
  charged to whichever backend happens to run first.
- At a schedule of training times (`--schedule`: "dense" 1, 1.5, 2, 3, 4, 5, 6, 8, 10, ... s
  for ngp, whose early points decide the time-to-PSNR ratio; "coarse" 1, 2, 4, 8, 15, 30, ...
  s for vanilla, whose evaluations cost seconds each; the budget always last), the field is
  evaluated by the one evaluation path (`fastenerf.evaluate.evaluate_field`, what `fastenerf
  eval` runs) at `--eval-scale`: colour correction fitted over all evaluated views together,
  PSNR from the pooled MSE, SSIM. The views are `--eval-views` evenly spaced test views
  (`fastenerf.evaluate.eval_view_indices`), the same for every backend and point. A point
  is taken at the first step whose clock passes a scheduled time, so its `train_s` is the
  true training time (a little past the schedule).
- A call can stop before the budgets are spent (`--max-wall-s`, SIGTERM, Ctrl-C): it writes a
  checkpoint and the outputs so far; `--resume` continues every run from its checkpoint, its
  training clock and curve carrying on.

Outputs in OUT: error_vs_time.json (every point, with machine, versions and git commit),
error_vs_time.png (PSNR and SSIM against training seconds), error_vs_time.md (the table for
benchmarks/RESULTS.md), and runs/<scene>-<backend>/ (the Trainer's run folder + curve.json).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import signal
import sys
import time
from pathlib import Path
from typing import Any

from benchmarks.cli import benchmark_main
from benchmarks.curve import (
    DEFAULT_BUDGETS,
    DEFAULT_SCHEDULES,
    SCHEDULES,
    load_scene_dir,
    make_config,
    schedule,
    train_curve,
)
from benchmarks.session import finite, jsonable, session_info
from fastenerf.backends import BACKEND_NAMES
from fastenerf.errors import InputError
from fastenerf.evaluate import COLOR_CORRECTION, make_eval_set
from fastenerf.hooks import StopOnSignal
from fastenerf.io import atomic_path, write_json
from fastenerf.run import resolve_device

TARGET_SPEEDUP = 50.0
TARGET_GAP_DB = 0.5


# -- summaries ------------------------------------------------------------------------------------


def best_point(points: list[dict]) -> dict | None:
    """The point of highest PSNR (the earliest of equals)."""
    ok = [p for p in points if finite(p["psnr"])]
    return max(ok, key=lambda p: (p["psnr"], -p["train_s"])) if ok else None


def time_to_reach(points: list[dict], psnr: float) -> dict[str, float | None] | None:
    """When a curve first reaches `psnr`: {"upper": train_s of the first point at or above it,
    "lower": train_s of the point before (0 if none), "interp": the crossing interpolated
    linearly in PSNR against log time between those two (None without a point before)}, or None
    if never reached."""
    pts = sorted((p for p in points if finite(p["psnr"])), key=lambda p: p["train_s"])
    for i, p in enumerate(pts):
        if p["psnr"] >= psnr:
            if i == 0:
                return {"upper": p["train_s"], "lower": 0.0, "interp": None}
            q = pts[i - 1]
            lo, hi = math.log(q["train_s"]), math.log(p["train_s"])
            # q is below psnr, p at or above: a proper crossing; a flat step gives hi
            f = (psnr - q["psnr"]) / (p["psnr"] - q["psnr"]) if p["psnr"] > q["psnr"] else 1.0
            return {
                "upper": p["train_s"],
                "lower": q["train_s"],
                "interp": math.exp(lo + f * (hi - lo)),
            }
    return None


def summarize_scene(runs: dict[str, dict]) -> dict[str, Any]:
    """The numbers of DESIGN §8 for one scene; runs: backend -> curve."""
    out: dict[str, Any] = {"backends": {}}
    for b, r in runs.items():
        pts = r["points"]
        best = best_point(pts)
        last = max(pts, key=lambda p: p["train_s"]) if pts else None
        out["backends"][b] = {
            "best_psnr": best and best["psnr"],
            "best_ssim": best and best["ssim"],
            "time_to_best_s": best and best["train_s"],
            "step_at_best": best and best["step"],
            "last_train_s": last and last["train_s"],
            "last_psnr": last and last["psnr"],
            "budget_s": r.get("budget_s"),
            "finished": bool(r.get("finished")),
            "n_points": len(pts),
        }
    ngp, van = runs.get("ngp"), runs.get("vanilla")
    if ngp and van and ngp["points"] and van["points"]:
        vb = best_point(van["points"])
        first = min(van["points"], key=lambda p: p["train_s"])
        # A vanilla run whose best is its first evaluation never learned within its budget:
        # that PSNR is what a near-empty field scores (high on a scene that is mostly known
        # background), and "time to reach it" measures nothing.
        learned = vb is not None and (len(van["points"]) == 1 or vb is not first)
        hit = time_to_reach(ngp["points"], vb["psnr"]) if learned else None
        t_v = vb and vb["train_s"]
        out["ngp_vs_vanilla"] = {
            "vanilla_learned": learned,
            "vanilla_best_psnr": vb and vb["psnr"],
            "vanilla_time_to_best_s": t_v,
            # the first ngp point at or above: an upper bound on the time, so `speedup` is a
            # lower bound; `speedup_interp` interpolates between the bracketing points
            "ngp_time_to_same_s": hit and hit["upper"],
            "ngp_time_to_same_lower_s": hit and hit["lower"],
            "ngp_time_to_same_interp_s": hit and hit["interp"],
            "speedup": (t_v / hit["upper"]) if hit else None,
            "speedup_upper": (t_v / hit["lower"]) if hit and hit["lower"] > 0 else None,
            "speedup_interp": (t_v / hit["interp"]) if hit and hit["interp"] else None,
            "reached": hit is not None,
        }
        if not learned:
            for k in ("speedup", "speedup_upper", "speedup_interp"):
                out["ngp_vs_vanilla"][k] = None
    if ngp and ngp["points"]:
        pts = sorted(ngp["points"], key=lambda p: p["train_s"])
        at60 = next((p for p in pts if p["train_s"] >= 60.0), None)
        last = pts[-1]
        if at60 is not None and at60 is not last and finite(at60["psnr"]) and finite(last["psnr"]):
            out["ngp_60s"] = {
                "psnr_at_60s": at60["psnr"],
                "train_s": at60["train_s"],
                "last_psnr": last["psnr"],
                "last_train_s": last["train_s"],
                "gap_db": last["psnr"] - at60["psnr"],
                "met": last["psnr"] - at60["psnr"] <= TARGET_GAP_DB,
            }
        else:
            out["ngp_60s"] = None
    return out


def _f(x, fmt: str = ".2f", none: str = "—") -> str:
    if not finite(x):
        return none
    return format(x, fmt)


def markdown(result: dict) -> str:
    """The Markdown table for benchmarks/RESULTS.md."""
    machines = result["machines"]
    lines = [f"### Error against training time — {' / '.join(machines)}", ""]
    if result["cpu_numbers"]:
        lines += [
            f"**CPU numbers** (measured on {' / '.join(machines)}): reduced-size runs, "
            "not comparable with the GPU targets of DESIGN §8.",
            "",
        ]
    if len(machines) > 1:
        lines += [
            "**Warning:** the points were measured on more than one machine (resumed "
            "calls landed on different hardware); times are not comparable across them.",
            "",
        ]
    if not result["complete"]:
        lines += [
            "**Incomplete:** some runs have not spent their budget yet (continue with `--resume`).",
            "",
        ]
    lines += [_md_protocol(result), ""]
    lines += _md_backend_table(result["summary"])
    lines += _md_comparison_table(result["summary"])
    lines += [
        "",
        "The vanilla backend's best is its best within its budget, not its converged "
        "value (the reference trains for days); where that best is its first evaluation "
        "(an untrained field's score) there is no speed-up to report. ngp's last point stands "
        "in for its "
        "converged PSNR. Each run's learning rate decays over its own budget, so ngp's 60 s "
        "point of a longer run is taken mid-schedule (a run with `--budget-s ngp=60` measures "
        "a 60 s schedule).",
        "",
    ]
    return "\n".join(lines)


def _md_protocol(result: dict) -> str:
    """One paragraph: versions, preset, budgets, evaluation and timing rules, schedules."""
    proto = result["protocol"]
    return (
        f"Commit {', '.join(result['git_commits'])}; torch {', '.join(result['torch'])}, "
        f"warp {', '.join(result['warp'])}. Preset {proto['preset']}; budgets "
        + ", ".join(f"{b} {s:g} s" for b, s in proto["budgets_s"].items())
        + "; evaluation on evenly spaced test views ("
        + ", ".join(f"{s}: {len(v)}" for s, v in proto["eval_views_used"].items())
        + ") at "
        f"{proto['eval_scale']:g}× resolution, colour-corrected over all evaluated views "
        "together, PSNR from the pooled MSE. Training time excludes evaluation, checkpoints "
        f"and a {proto['warmup_steps']}-step warm-up (kernel compilation). Times to a PSNR are "
        "those of the first evaluation point at or above it, so they are upper bounds and the "
        "speed-ups lower bounds (the point before is given after the dash; schedules: "
        + "; ".join(
            f"{b} {lad} " + ", ".join(f"{t:g}" for t in SCHEDULES[lad][:12]) + " … s"
            for b, lad in proto.get("schedules", {"all": "coarse"}).items()
        )
        + ")."
    )


def _md_backend_table(summary: dict) -> list[str]:
    """One row per (scene, backend): best PSNR and SSIM, time and steps to it, last point."""
    lines = [
        "| scene | backend | best PSNR | SSIM there | train s to best | steps | last point s "
        "| PSNR there |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for scene, s in summary.items():
        for b, v in s["backends"].items():
            flag = "" if v["finished"] else " (unfinished)"
            lines.append(
                f"| {scene} | {b}{flag} | {_f(v['best_psnr'])} | "
                f"{_f(v['best_ssim'], '.3f')} | {_f(v['time_to_best_s'], '.1f')} | "
                f"{_f(v['step_at_best'], 'd')} | {_f(v['last_train_s'], '.1f')} | "
                f"{_f(v['last_psnr'])} |"
            )
    return lines


def _md_comparison_table(summary: dict) -> list[str]:
    """One row per scene: ngp's speed-up to vanilla's best PSNR and its 60 s gap vs targets."""
    lines = [
        "",
        "| scene | vanilla best PSNR | vanilla s to best | ngp s to same PSNR (point before) "
        f"| speed-up (target ≥ {TARGET_SPEEDUP:g}×) | ngp PSNR at 60 s | ngp PSNR last "
        f"(s) | gap (target ≤ {TARGET_GAP_DB:g} dB) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for scene, s in summary.items():
        lines.append(f"| {scene} " + _md_speedup_cells(s) + _md_gap_cells(s.get("ngp_60s")))
    return lines


def _md_speedup_cells(s: dict) -> str:
    """The comparison row's vanilla best, its time, ngp's time to it and the speed-up."""
    c = s.get("ngp_vs_vanilla")
    if c is None:
        return "| — | — | — | — (needs both backends) "
    vanilla = f"| {_f(c['vanilla_best_psnr'])} | {_f(c['vanilla_time_to_best_s'], '.1f')} "
    if not c.get("vanilla_learned", True):
        return vanilla + "| — | none: vanilla never rose above its first evaluation "
    if not c["reached"]:
        ngp_b = s["backends"]["ngp"]
        return vanilla + f"| not reached in {_f(ngp_b['last_train_s'], '.0f')} s | not reached "
    met = "met" if c["speedup"] >= TARGET_SPEEDUP else "not met"
    interp = f"; {c['speedup_interp']:.0f}× interpolated" if finite(c["speedup_interp"]) else ""
    return vanilla + (
        f"| {_f(c['ngp_time_to_same_s'], '.1f')} "
        f"({_f(c['ngp_time_to_same_lower_s'] or None, '.1f', 'first point')}) "
        f"| ≥ {c['speedup']:.1f}× ({met}{interp}) "
    )


def _md_gap_cells(g: dict | None) -> str:
    """The comparison row's ngp PSNR at 60 s, its last PSNR and the gap against the target."""
    if g is None:
        return "| n/a (ngp budget ≤ 60 s or no ngp run) | — | — |"
    return (
        f"| {_f(g['psnr_at_60s'])} ({_f(g['train_s'], '.0f')} s) | "
        f"{_f(g['last_psnr'])} ({_f(g['last_train_s'], '.0f')}) | "
        f"{g['gap_db']:+.2f} dB ({'met' if g['met'] else 'not met'}) |"
    )


def collect(curves: list[dict], protocol: dict) -> dict:
    """The error_vs_time.json object from the run curves."""
    points, machines, commits, torch_v, warp_v = [], [], [], [], []
    for c in curves:
        for p in c["points"]:
            s = c["sessions"][p["session"]]
            points.append(
                {
                    **p,
                    "machine": s["machine"]["name"],
                    "device": s["machine"]["device"],
                    "torch": s["versions"]["torch"],
                    "warp": s["versions"]["warp"],
                    "git_commit": s["git_commit"],
                }
            )
        for s in c["sessions"]:
            for lst, v in (
                (machines, s["machine"]["name"]),
                (commits, s["git_commit"]),
                (torch_v, s["versions"]["torch"]),
                (warp_v, s["versions"]["warp"]),
            ):
                if v not in lst:
                    lst.append(v)
    by_scene: dict[str, dict[str, dict]] = {}
    for c in curves:
        by_scene.setdefault(c["scene"], {})[c["backend"]] = c
    cpu = any(s["machine"]["cpu_numbers"] for c in curves for s in c["sessions"])
    return {
        "benchmark": "error_vs_time",
        "cpu_numbers": cpu,
        "machines": machines,
        "git_commits": commits,
        "torch": torch_v,
        "warp": warp_v,
        "complete": all(c.get("finished") for c in curves),
        "protocol": protocol,
        "summary": {s: summarize_scene(r) for s, r in by_scene.items()},
        "runs": curves,
        "points": points,
    }


def write_outputs(result: dict, out: Path) -> dict[str, Path]:
    from benchmarks.plots import plot_error_vs_time

    paths = {
        "json": out / "error_vs_time.json",
        "png": out / "error_vs_time.png",
        "md": out / "error_vs_time.md",
    }
    write_json(paths["json"], jsonable(result))
    title = ("CPU numbers — " if result["cpu_numbers"] else "") + " / ".join(result["machines"])
    plot_error_vs_time(result["runs"], paths["png"], title)
    with atomic_path(paths["md"]) as tmp:
        tmp.write_text(markdown(result))
    return paths


# -- the command ----------------------------------------------------------------------------------


def parse_budgets(items: list[str], backends: list[str]) -> dict[str, float]:
    """["ngp=300", "vanilla=480"] or ["60"] (every backend) -> {backend: seconds}."""
    out = {b: DEFAULT_BUDGETS.get(b, 60.0) for b in backends}
    for item in items or []:
        key, _, val = item.rpartition("=")
        try:
            sec = float(val)
        except ValueError:
            raise InputError(f"--budget-s: {item!r} is not BACKEND=SECONDS or SECONDS") from None
        if not (sec > 0 and math.isfinite(sec)):
            raise InputError(f"--budget-s: {item!r}: seconds must be positive")
        if key and key not in backends:
            raise InputError(f"--budget-s: {key!r} is not one of the --backends {backends}")
        for b in [key] if key else backends:
            out[b] = sec
    return out


def parse_presets(items: list[str], backends: list[str]) -> dict[str, str]:
    """["fast"] or ["ngp=fast", "vanilla=eventnerf"] -> {backend: preset}."""
    out = dict.fromkeys(backends, "fast")
    for item in items or []:
        key, _, val = item.rpartition("=")
        if key and key not in backends:
            raise InputError(f"--preset: {key!r} is not one of the --backends {backends}")
        for b in [key] if key else backends:
            out[b] = val
    return out


def parse_schedules(items: list[str], backends: list[str]) -> dict[str, str]:
    """["dense"] or ["ngp=dense", "vanilla=coarse"] -> {backend: ladder name}."""
    out = {b: DEFAULT_SCHEDULES.get(b, "coarse") for b in backends}
    for item in items or []:
        key, _, val = item.rpartition("=")
        if key and key not in backends:
            raise InputError(f"--schedule: {key!r} is not one of the --backends {backends}")
        if val not in SCHEDULES:
            raise InputError(f"--schedule: {val!r} is not one of {sorted(SCHEDULES)}")
        for b in [key] if key else backends:
            out[b] = val
    return out


def parse_sets(items: list[str], backends: list[str]) -> dict[str, dict[str, dict]]:
    """--set [BACKEND:]KEY=JSON_VALUE -> {backend: {"train": {...}, "backend_options": {...}}}.

    KEY is a TrainConfig field, else a backend option (NGPOptions / VanillaField argument).
    """
    from fastenerf.config import TrainConfig

    fields = {f.name for f in dataclasses.fields(TrainConfig)}
    out = {b: {"train": {}, "backend_options": {}} for b in backends}
    for item in items or []:
        lhs, eq, raw = item.partition("=")
        if not eq:
            raise InputError(f"--set: {item!r} is not [BACKEND:]KEY=VALUE")
        who, _, key = lhs.rpartition(":")
        if who and who not in backends:
            raise InputError(f"--set: {who!r} is not one of the --backends {backends}")
        try:
            val = json.loads(raw)
        except json.JSONDecodeError:
            val = raw  # a bare word: a string
        for b in [who] if who else backends:
            out[b]["train" if key in fields else "backend_options"][key] = val
    return out


def scene_labels(dirs: list[str]) -> list[str]:
    """Folder names, made unique with -2, -3, ... (two folders may share a name)."""
    labels: list[str] = []
    for d in dirs:
        name = Path(d).resolve().name or "scene"
        label, i = name, 2
        while label in labels:
            label, i = f"{name}-{i}", i + 1
        labels.append(label)
    return labels


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--scenes",
        nargs="+",
        required=True,
        metavar="DIR",
        help="scene folders with ground-truth test views",
    )
    p.add_argument(
        "--backends", nargs="+", default=list(BACKEND_NAMES), choices=list(BACKEND_NAMES)
    )
    p.add_argument(
        "--budget-s",
        nargs="+",
        default=[],
        metavar="[BACKEND=]S",
        help="training seconds per backend (default ngp=300 vanilla=480)",
    )
    p.add_argument(
        "--preset",
        nargs="+",
        default=["fast"],
        metavar="[BACKEND=]NAME",
        help="training preset, for all or per backend (default fast)",
    )
    p.add_argument(
        "--set",
        nargs="+",
        default=[],
        metavar="[BACKEND:]KEY=VALUE",
        help="TrainConfig field or backend option (JSON value), e.g. "
        "rays_per_step=4096 ngp:log2_table_size=21",
    )
    p.add_argument("--out", default="runs/bench/error_vs_time", help="output folder")
    p.add_argument("--device", default="auto", help="cuda, cuda:N, cpu or auto")
    p.add_argument(
        "--eval-views",
        type=int,
        default=10,
        help="evenly spaced test views to evaluate on (the one rule of fastenerf eval)",
    )
    p.add_argument(
        "--eval-scale",
        type=float,
        default=1.0,
        help="evaluation resolution as a fraction of the sensor's",
    )
    p.add_argument(
        "--schedule",
        nargs="+",
        default=[],
        metavar="[BACKEND=]LADDER",
        help="evaluation times: dense or coarse, for all or per backend "
        "(default ngp=dense vanilla=coarse)",
    )
    p.add_argument(
        "--first-s", type=float, default=1.0, help="first scheduled evaluation (s of training)"
    )
    p.add_argument(
        "--warmup-steps",
        type=int,
        default=2,
        help="steps of a throwaway run before the clock starts (0: none)",
    )
    p.add_argument(
        "--resume", action="store_true", help="continue the runs in --out from their checkpoints"
    )
    p.add_argument(
        "--max-wall-s",
        type=float,
        default=None,
        help="stop (checkpoint, write outputs) after this many wall seconds",
    )
    p.add_argument(
        "--commit", default=None, help="git commit to record (for copies of the tree without .git)"
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    t_start = time.perf_counter()
    deadline = None if args.max_wall_s is None else t_start + args.max_wall_s
    if args.eval_views < 1 or args.eval_scale <= 0:
        raise InputError("--eval-views must be >= 1 and --eval-scale > 0")
    backends = list(dict.fromkeys(args.backends))
    budgets = parse_budgets(args.budget_s, backends)
    presets = parse_presets(args.preset, backends)
    sets = parse_sets(args.set, backends)
    ladders = parse_schedules(args.schedule, backends)
    device = resolve_device(args.device)
    out = Path(args.out)
    session = session_info(device, args.commit)
    scenes = [load_scene_dir(d) for d in args.scenes]
    labels = scene_labels(args.scenes)
    # Validate every configuration (as each trainer will resolve it for each scene) before
    # the first minute of training is spent and before the output folder is made: a refused
    # run leaves nothing behind.
    cfgs = {b: make_config(b, presets[b], budgets[b], str(device), **sets[b]) for b in backends}
    for cfg in cfgs.values():
        for scene in scenes:
            cfg.resolved(scene.config, str(device))
    out.mkdir(parents=True, exist_ok=True)
    if session["machine"]["cpu_numbers"]:
        print(f"CPU numbers: {session['machine']['name']}")
    stop = StopOnSignal((signal.SIGINT, signal.SIGTERM))
    curves: list[dict] = []
    protocol: dict[str, Any] = {
        "preset": ", ".join(sorted(set(presets.values()))),
        "presets": presets,
        "budgets_s": budgets,
        "schedules": ladders,
        "overrides": sets,
        "eval_views": args.eval_views,
        "eval_scale": args.eval_scale,
        "eval_views_used": {},
        "warmup_steps": args.warmup_steps,
        "device": str(device),
        "clock": "the trainer's clock around each step, synchronised with the device; "
        "evaluation, checkpoints and set-up excluded",
        "color_correction": COLOR_CORRECTION,
    }
    paths: dict[str, Path] = {}
    for scene, label, sdir in zip(scenes, labels, args.scenes, strict=True):
        ev = make_eval_set(scene, args.eval_views, args.eval_scale)
        protocol["eval_views_used"][label] = ev.views.tolist()
        for b in backends:
            run_dir = out / "runs" / f"{label}-{b}"
            curve = train_curve(
                scene,
                cfgs[b],
                run_dir,
                ev,
                schedule(budgets[b], args.first_s, ladders[b]),
                label={"scene": label, "backend": b, "scene_dir": str(Path(sdir).resolve())},
                session=session,
                resume=args.resume,
                deadline=deadline,
                stop=stop,
                warmup_steps=args.warmup_steps,
                progress=not args.quiet,
            )
            curves.append(curve)
            paths = write_outputs(collect(curves, protocol), out)
    result = collect(curves, protocol)
    paths = write_outputs(result, out)
    for k in ("json", "png", "md"):
        print(f"wrote {paths[k]}")
    if not result["complete"]:
        print("incomplete: budgets not spent yet; run again with --resume to continue")
    else:
        print(markdown(result))
    return 0


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    return benchmark_main("error_vs_time", __doc__, add_arguments, run, argv, prog, out_folder=True)


if __name__ == "__main__":
    sys.exit(main())
