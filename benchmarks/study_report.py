"""A study's results: each level's final evaluation and row, the summary (with where the curve
breaks), and the files it writes (JSON, plot, image grid, Markdown beside the supplement)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks.session import finite, jsonable
from benchmarks.study_levels import (
    LONG_WINDOW_FRACTION,
    POSE_STUDIES,
    SHORT_WINDOW_FRACTION,
    STUDIES,
    level_label,
    locate_break,
    supplement_break,
)
from fastenerf.evaluate import EvalSet, evaluate_field
from fastenerf.io import atomic_path, write_image, write_json
from fastenerf.run import CHECKPOINT, read_progress
from fastenerf.se3 import so3_exp

EVAL_RECORD = "study_eval.json"  # in a level's run folder: its final evaluation
VIEW_TILE = "study_view.png"  # and the grid's view of it (colour-corrected render)
KNOBS = ("win_min", "win_max", "win_redraw", "neg_ratio", "distortion_weight")


def final_eval(run_dir: Path, ev: EvalSet, grid_view: int, device) -> dict[str, Any]:
    """Score a finished level's field (its last checkpoint) on `ev` and keep the grid's view.

    The field is rebuilt from RUN/checkpoint.pt and scored by `evaluate_field` (the one
    evaluation path); the colour-corrected render of `ev`'s view `grid_view` (a position in
    ev.views) goes to RUN/study_view.png, the metrics to RUN/study_eval.json. A record of
    the same step, views and scale is reused (a resumed study renders nothing again).
    """
    from fastenerf.run import field_from_checkpoint, load_checkpoint

    progress = read_progress(run_dir)
    gauge = learnt_gauge(progress.get("self_calibration"))
    key = {
        "step": progress.get("step"),
        "views": [int(v) for v in ev.views],
        "scale": ev.scale,
        "grid_view": int(ev.views[grid_view]),
        "aligned": gauge is not None,
    }
    path = run_dir / EVAL_RECORD
    old = _read_json(path)
    if old is not None and all(old.get(k) == v for k, v in key.items()):
        if (run_dir / VIEW_TILE).is_file():
            return old
    ck = load_checkpoint(run_dir / CHECKPOINT, map_location=device)
    field = field_from_checkpoint(ck, run_dir / CHECKPOINT).to(device).eval()
    chunk = int(ck.get("train_config", {}).get("chunk", 16384) or 16384)
    metrics, corrected = evaluate_field(field, ev, chunk)
    if gauge is not None:
        turned, _ = evaluate_field(field, turned_views(ev, gauge), chunk)
        metrics["psnr_aligned"], metrics["ssim_aligned"] = turned["psnr"], turned["ssim"]
    del field, ck
    write_image(run_dir / VIEW_TILE, corrected[grid_view])
    record = {**key, **metrics, "train_s": progress.get("train_seconds"), "tile": VIEW_TILE}
    write_json(path, jsonable(record))
    return record


def learnt_gauge(stats: dict | None) -> np.ndarray | None:
    """The world rotation W (rotation vector, radians, (3,)) a refined run's training poses
    share against the truth (R_learnt ≈ W · R_true), from its progress stats; None where the
    run learnt no poses or had no true poses to compare with."""
    w = [(stats or {}).get(f"pose_gauge_w{a}") for a in "xyz"]
    return np.array(w, dtype=np.float64) if all(finite(v) for v in w) else None


def turned_views(ev: EvalSet, gauge: np.ndarray) -> EvalSet:
    """`ev` with every test camera turned by W = exp(gauge) about its own centre, as the
    learnt training cameras are (BARF's aligned protocol: the scene is learnt in their frame).
    """
    W = so3_exp(torch.from_numpy(gauge)).numpy()
    c2w = ev.c2w.copy()
    c2w[:, :3, :3] = W @ ev.c2w[:, :3, :3]
    return dataclasses.replace(ev, c2w=c2w)


def _read_json(path: Path) -> dict | None:
    try:
        d = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return d if isinstance(d, dict) else None


def measured_perturbation(study: str, pert: dict | None) -> dict[str, Any]:
    """What the trainer measured on the data it trained with (RUN/config.json
    ["perturbation"]); a zero level was the identity, so it measured zero."""
    pert = pert or {}
    if study in POSE_STUDIES:  # the "pose" or the "mount" report: the same measurements
        p = pert.get(STUDIES[study].report)
        if not p:
            return {"mean_deg": 0.0, "max_deg": 0.0, "min_deg": 0.0, "poses": None}
        out = {
            "mean_deg": p["measured_mean_deg"],
            "max_deg": p["measured_max_deg"],
            "min_deg": p["measured_min_deg"],
            "poses": p.get("poses"),
            "centre_shift_max": p.get("centre_shift_max"),
        }
        if "axis" in p:  # the mount turn's one camera-frame axis
            out["axis"] = p["axis"]
        return out
    if study == "noise":
        n = pert.get("noise")
        if not n:
            return {"fraction": 0.0, "added_events": 0, "clean_events": None}
        return {
            "fraction": n["measured_fraction"],
            "added_events": n["added_events"],
            "clean_events": n["clean_events"],
        }
    return {}


def level_row(
    study: str,
    level: Any,
    run_dir: Path,
    out: Path,
    curve: dict,
    progress: dict,
    fe: dict | None,
    *,
    finished: bool,
    steps_budget: bool,
) -> dict[str, Any]:
    """One level of the study's JSON: measured perturbation, knobs, scores, time, machines."""
    conf = _read_json(run_dir / "config.json") or {}
    train = conf.get("train", {})
    points = [
        {k: p.get(k) for k in ("target_s", "train_s", "step", "psnr", "ssim")}
        for p in curve.get("points", [])
    ]
    final_pt = points[-1] if points and finished and not steps_budget else None
    src = final_pt if final_pt is not None else (fe or {})
    return {
        "level": level,
        "label": level_label(study, level),
        "run": str(run_dir.relative_to(out)),
        "finished": bool(finished and fe is not None),
        "psnr": src.get("psnr", float("nan")),
        "ssim": src.get("ssim", float("nan")),
        "psnr_reloaded": (fe or {}).get("psnr"),  # the last checkpoint scored again
        # refined runs: the test views turned by the learnt poses' shared rotation
        "psnr_aligned": (fe or {}).get("psnr_aligned"),
        "steps": int(progress.get("step", 0) or 0),
        "train_s": progress.get("train_seconds"),
        "perturbation": conf.get("perturbation"),
        "measured": measured_perturbation(study, conf.get("perturbation")),
        "knobs": {k: train.get(k) for k in KNOBS},
        "rays_per_step": train.get("rays_per_step"),
        "self_calibration": calibration_summary(train, conf.get("self_calibration")),
        "pose_smoothing": conf.get("pose_smoothing"),  # the motion prior's report, or None
        "points": points,
        "tile": str((run_dir / VIEW_TILE).relative_to(out)) if fe else None,
        "sessions": [_session_line(s) for s in curve.get("sessions", [])],
    }


CALIBRATION_KNOBS = (
    "refine_poses",
    "refine_shared",
    "refine_optimizer",
    "refine_lr",
    "refine_start",
    "refine_c2f_mode",
    "refine_c2f_start",
    "refine_c2f_end",
    "estimate_threshold",
)


def calibration_summary(train: dict, report: dict | None) -> dict | None:
    """A run's self-calibration (issue #20): its knobs and final stats (pose error left after
    refinement, threshold estimates), or None when neither option was on."""
    if not (train.get("refine_poses") or train.get("estimate_threshold")):
        return None
    return {
        "knobs": {k: train.get(k) for k in CALIBRATION_KNOBS if k in train},
        "stats": (report or {}).get("stats", {}),
    }


def _session_line(s: dict) -> dict:
    return {
        "machine": s["machine"]["name"],
        "device": s["machine"]["device"],
        "cpu_numbers": s["machine"]["cpu_numbers"],
        "torch": s["versions"]["torch"],
        "warp": s["versions"]["warp"],
        "fastenerf": s["versions"].get("fastenerf"),
        "git_commit": s["git_commit"],
        "started": s["started"],
    }


def summarize(study: str, rows: list[dict], levels: list, args, scene) -> dict[str, Any]:
    """The study's JSON object (see benchmarks.study's docstring)."""
    spec = STUDIES[study]
    sessions = [s for r in rows for s in r["sessions"]]

    def uniq(key):
        return list(dict.fromkeys(s[key] for s in sessions))

    result: dict[str, Any] = {
        "benchmark": "study",
        "study": study,
        "scene": Path(args.scene).resolve().name,
        "scene_dir": str(Path(args.scene).resolve()),
        "n_views": scene.config.n_views,
        "sensor": [scene.config.width, scene.config.height],
        "backend": "ngp",
        "preset": "fast",
        "budget": {"steps": args.steps} if args.steps is not None else {"s": args.budget_s},
        "seed": args.seed,
        "eval_views": args.eval_views,
        "eval_scale": args.eval_scale,
        "levels_requested": levels,
        "complete": len(rows) == len(levels) and all(r["finished"] for r in rows),
        "levels_not_run": [x for x in levels if x not in {r["level"] for r in rows}],
        "cpu_numbers": any(s["cpu_numbers"] for s in sessions),
        "machines": uniq("machine"),
        "git_commits": uniq("git_commit"),
        "torch": uniq("torch"),
        "warp": uniq("warp"),
        "levels": rows,
        "supplement": {
            "psnr": {str(k): v for k, v in spec.supplement.items()},
            "note": spec.supplement_note,
            "break": supplement_break(study),
        },
    }
    if spec.numeric:
        result["break"] = locate_break([r["level"] for r in rows], [r["psnr"] for r in rows])
    else:
        n = scene.config.n_views
        result["windows"] = {
            "short_views": max(1, round(SHORT_WINDOW_FRACTION * n)),
            "long_views": max(1, round(LONG_WINDOW_FRACTION * n)),
            "n_views": n,
        }
    return result


def write_outputs(result: dict, out: Path, ev: EvalSet, grid_view: int) -> dict[str, Path]:
    """STUDY.json, STUDY.png, STUDY_grid.png, STUDY.md in `out`; returns their paths."""
    from benchmarks.study_plots import plot_grid, plot_study

    name = result["study"]
    paths = {
        "json": out / f"{name}.json",
        "png": out / f"{name}.png",
        "grid": out / f"{name}_grid.png",
        "md": out / f"{name}.md",
    }
    write_json(paths["json"], jsonable(result))
    plot_study(result, paths["png"], title(result))
    tiles = [(r["label"], r["psnr"], _read_tile(out, r)) for r in result["levels"]]
    plot_grid(ev.gt[grid_view], tiles, paths["grid"], title(result))
    with atomic_path(paths["md"]) as tmp:
        tmp.write_text(markdown(result))
    return paths


def _read_tile(out: Path, row: dict) -> np.ndarray | None:
    import imageio.v3 as iio

    if not row.get("tile"):
        return None
    try:
        return iio.imread(out / row["tile"])[..., :3]
    except (OSError, ValueError):
        return None


def budget_label(b: dict) -> str:
    """A study's budget ({"steps": N} or {"s": S}) as "N steps" or "S s"."""
    return f"{b['steps']} step{'s' * (b['steps'] != 1)}" if "steps" in b else f"{b['s']:g} s"


def cpu_prefix(result: dict) -> str:
    return "CPU numbers — " if result["cpu_numbers"] else ""


def title(result: dict) -> str:
    return (
        f"{cpu_prefix(result)}{result['study']} on {result['scene']}, ngp fast, "
        f"{budget_label(result['budget'])} per level — " + " / ".join(result["machines"])
    )


def _f(x, spec: str) -> str:
    return format(x, spec) if finite(x) else "—"


def markdown(result: dict) -> str:
    """The study's table beside the supplement's numbers, and where the curve breaks."""
    study = result["study"]
    lines = [f"### Study {study}: {title(result)}", ""]
    if result["cpu_numbers"]:
        lines += ["**CPU numbers**: reduced-size runs; the GPU study is the one to read.", ""]
    if not result["complete"]:
        missing = ", ".join(level_label(study, x) for x in result["levels_not_run"])
        lines += [
            "**Incomplete:** some levels have not finished"
            + (f" ({missing} not started)" if missing else "")
            + " — continue with `--resume`.",
            "",
        ]
    lines += [
        f"Scene {result['scene']} ({result['sensor'][0]}×{result['sensor'][1]}, "
        f"{result['n_views']} views per loop); commit {', '.join(result['git_commits'])}; "
        f"perturbation seed {result['seed']}. PSNR/SSIM colour-corrected on the same clean "
        f"test views ({result['eval_views']} views at scale {result['eval_scale']:g}); "
        "Δ = against the first level (the clean run).",
        "",
    ]
    lines += _table(result)
    lines += [""] + _break_lines(result) + [""]
    return "\n".join(lines)


def _table(result: dict) -> list[str]:
    study, rows = result["study"], result["levels"]
    prior = _has_prior(rows)  # a column for the motion prior's error where a level ran one
    sup = {float(k): v for k, v in result["supplement"]["psnr"].items()}
    ref = rows[0]["psnr"] if rows else float("nan")
    if study == "ablation":
        head = "| variant | win_min..win_max (views) | neg_ratio | distortion_weight |"
    elif study in POSE_STUDIES:
        what = study.replace("-", " ")
        col = " after the prior mean (°) |" if prior else ""
        head = f"| {what} | measured mean / max (°) |{col} after refinement mean / max (°) |"
    else:
        head = "| noise | measured added fraction (events) |"
    n_first = head.count("|") - 1
    score = " PSNR | Δ | SSIM | steps | train s |"
    if sup:
        score += " supplement PSNR | supplement Δ |"
    aligned = any(finite(r.get("psnr_aligned")) for r in rows)
    if aligned:
        score += " PSNR, aligned |"
    lines = [head + score, "|---" * n_first + "|---:" * score.count("|") + "|"]
    for r in rows:
        cells = _first_cells(study, r, prior) + _score_cells(r, ref, sup)
        lines.append(cells + (f" {_f(r.get('psnr_aligned'), '.2f')} |" if aligned else ""))
    if study == "ablation":
        w = result["windows"]
        lines += [
            "",
            f"Windows scaled to the loop: short = {w['short_views']} views (1 % of "
            f"{w['n_views']}), long = {w['long_views']} views (5 %), as the authors' synthetic "
            "configs' 10 and 50 of 1000 poses (the supplement's 10 ms / 100 ms are real data). "
            f"The supplement has no ablation numbers: {result['supplement']['note']}.",
        ]
    else:
        lines += ["", f"Supplement's numbers: {result['supplement']['note']}."]
    if aligned:
        lines += [
            "",
            "PSNR, aligned: a refined level's test views turned by the world rotation its "
            "learnt training poses share against the truth (BARF's protocol; the PSNR column "
            "scores them as given). Only the poses' shared turn is taken out.",
        ]
    return lines


def _has_prior(rows: list[dict]) -> bool:
    return any(r.get("pose_smoothing") for r in rows)


def _first_cells(study: str, r: dict, prior: bool = False) -> str:
    name = r["label"] + ("" if r["finished"] else " (unfinished)")
    m, k = r["measured"], r["knobs"]
    if study == "ablation":
        return (
            f"| {name} | {k['win_min']}..{k['win_max']} | {_f(k['neg_ratio'], 'g')} | "
            f"{_f(k['distortion_weight'], 'g')} |"
        )
    if study in POSE_STUDIES:
        cells = f"| {name} | {_f(m['mean_deg'], '.4g')} / {_f(m['max_deg'], '.4g')} |"
        if prior:
            cells += f" {_prior_left(r)} |"
        return cells + f" {_pose_left(r)} |"
    return f"| {name} | {100 * m['fraction']:.3f} % ({m['added_events']:,}) |"


def _prior_left(r: dict) -> str:
    """The mean rotation error (°) the motion prior (`--smooth-poses`) leaves before training,
    or "no prior". A level without a perturbation trains on the exact poses, so there the
    error is the turn the prior gave them."""
    rep = r.get("pose_smoothing")
    if not rep:
        return "no prior"
    return _f(rep.get("error_after_deg", rep.get("mean_turn_deg")), ".3f")


def _pose_left(r: dict) -> str:
    """The pose error a refined run ends with (°; at level 0 the corrections' own size) and,
    where the run reports it, its pose-to-pose part (`pose_jitter_deg`), or "no refinement"."""
    cal = r.get("self_calibration") or {}
    if not (cal.get("knobs") or {}).get("refine_poses"):
        return "no refinement"
    st = cal.get("stats") or {}
    mean = st.get("pose_error_deg", st.get("pose_correction_deg"))
    top = st.get("pose_error_max_deg", st.get("pose_correction_max_deg"))
    jitter = st.get("pose_jitter_deg")
    tail = "" if jitter is None else f" (jitter {_f(jitter, '.3f')})"
    return f"{_f(mean, '.3f')} / {_f(top, '.3f')}{tail}"


def _score_cells(r: dict, ref, sup: dict) -> str:
    d = r["psnr"] - ref if finite(r["psnr"]) and finite(ref) else None
    cells = (
        f" {_f(r['psnr'], '.2f')} | {_f(d, '+.2f')} | {_f(r['ssim'], '.3f')} | {r['steps']} | "
        f"{_f(r['train_s'], '.1f')} |"
    )
    if sup:
        s = sup.get(float(r["level"]))
        sd = s - sup[0.0] if s is not None and 0.0 in sup else None
        cells += f" {_f(s, '.2f')} | {_f(sd, '+.2f')} |"
    return cells


def _break_lines(result: dict) -> list[str]:
    study = result["study"]
    if study == "ablation":
        rows = [r for r in result["levels"] if finite(r["psnr"])]
        if not rows:
            return []
        worst = min(rows, key=lambda r: r["psnr"])
        return [f"Lowest PSNR: {worst['label']} ({worst['psnr']:.2f} dB)."]
    unit = "°" if study in POSE_STUDIES else " %"
    out = []
    pairs = [("Ours", result.get("break"))]
    if result["supplement"]["psnr"]:  # a study the supplement has (not mount-error)
        pairs.append(("Supplement", result["supplement"]["break"]))
    for who, b in pairs:
        if b is None:
            out.append(f"{who}: fewer than two levels with a PSNR, no break to locate.")
            continue
        d = b["largest_drop"]
        first = b["first_below"]
        first_s = (
            f"{first:g}{unit}"
            if first is not None
            else f"none (all within {b['threshold_db']:g} dB)"
        )
        out.append(
            f"{who}: the largest PSNR drop per level step is between {d['from']:g}{unit} and "
            f"{d['to']:g}{unit} ({-d['drop_db']:+.2f} dB); the first level more than "
            f"{b['threshold_db']:g} dB below {b['reference_level']:g}{unit} "
            f"({b['reference_db']:.2f} dB): {first_s}."
        )
    return out
