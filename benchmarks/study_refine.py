"""Issue #20's targets from one session's studies (`benchmarks/gpu_refine.sh`), in one table.

    python -m benchmarks.study_refine OUT

Reads, under OUT: study_SCENE_plain/pose-error.json and study_SCENE_refine/pose-error.json
(the pose study without and with `--refine-poses`, levels 0, 1, 2 degrees; any other
study_SCENE_NAME folder, one of EXTRA_VARIANTS, is tabled and plotted beside them),
time_{plain,refine,threshold,both}/profile_step.json (each option's steady-state step,
`benchmarks.profile_step`, alone on the device; an older session's time_*/pose-error.json is
read too) and threshold/threshold.json (the threshold study). Writes
OUT/refine_summary.json, OUT/refine_summary.md (every target, met or not, with its numbers)
and OUT/refine_summary.png (PSNR against the pose error, with and without refinement, per
scene). Missing inputs are reported as missing, not guessed.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from benchmarks.cli import benchmark_main
from benchmarks.session import finite, write_report

# The targets: PSNR at 1 and 2 degrees with refinement within this of the plain 0 run
WITHIN_DB = {1.0: 1.0, 2.0: 2.0}
COST_DB, COST_STEP = 0.2, 0.15  # at 0 degrees: PSNR and step-time cost of the options


def _load(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _psnr(study: dict | None) -> dict[float, float]:
    if not study:
        return {}
    return {float(r["level"]): r["psnr"] for r in study["levels"] if finite(r["psnr"])}


def _ms_per_step(folder: Path) -> float | None:
    """A timing run's ms/step: the steady-state step of `benchmarks.profile_step` (its
    profile_step.json), else a short study's train seconds over its steps (pose-error.json,
    start-up and compilation included: earlier sessions' runs)."""
    prof = _load(folder / "profile_step.json")
    if prof and finite(prof.get("wall_ms_unprofiled")):
        return float(prof["wall_ms_unprofiled"])
    study = _load(folder / "pose-error.json")
    if not study or not study["levels"]:
        return None
    r = study["levels"][0]
    return 1000.0 * r["train_s"] / r["steps"] if r.get("train_s") and r.get("steps") else None


def summarize(out: Path) -> dict[str, Any]:
    scenes = sorted(
        p.name[len("study_") : -len("_plain")] for p in out.glob("study_*_plain") if p.is_dir()
    )
    res: dict[str, Any] = {"scenes": {}, "step_time": {}, "threshold": None, "targets": []}
    for s in scenes:
        runs = {  # plain, refine, and any EXTRA_VARIANT study of the scene
            p.name[len(f"study_{s}_") :]: _psnr(_load(p / "pose-error.json"))
            for p in sorted(out.glob(f"study_{s}_*"))
            if p.is_dir()
        }
        plain, ref = runs.get("plain", {}), runs.get("refine", {})
        res["scenes"][s] = runs
        base = plain.get(0.0)
        for lv, tol in WITHIN_DB.items():
            got = ref.get(lv)
            gap = None if got is None or base is None else base - got
            res["targets"].append(
                {
                    "what": f"{s}: refine at {lv:g}° within {tol:g} dB of plain 0°",
                    "value_db": gap,
                    "met": gap is not None and gap <= tol,
                }
            )
        cost = None if base is None or ref.get(0.0) is None else base - ref[0.0]
        res["targets"].append(
            {
                "what": f"{s}: refine at 0° costs <= {COST_DB:g} dB",
                "value_db": cost,
                "met": cost is not None and cost <= COST_DB,
            }
        )
    times = {k: _ms_per_step(out / f"time_{k}") for k in ("plain", "refine", "threshold", "both")}
    res["step_time"] = times
    for k in ("refine", "threshold", "both"):
        if times["plain"] and times[k]:
            extra = times[k] / times["plain"] - 1.0
            res["targets"].append(
                {
                    "what": f"step time with {k} <= +{100 * COST_STEP:g} %",
                    "value": extra,
                    "met": extra <= COST_STEP,
                }
            )
    thr = _load(out / "threshold" / "threshold.json")
    if thr:
        res["threshold"] = thr["targets"]
        res["targets"].append(
            {"what": "threshold: ratio within 10 %", "met": thr["targets"]["ratio_met"]}
        )
        res["targets"].append(
            {"what": "threshold: PSNR >= 95 % of the true run's", "met": thr["targets"]["psnr_met"]}
        )
    return res


def markdown(res: dict) -> str:
    lines = ["### Issue #20 targets (from this session's studies)", ""]
    lines += ["| scene | run | 0° | 1° | 2° |", "|---|---|---:|---:|---:|"]
    for s, d in res["scenes"].items():
        for k in d:
            cells = " | ".join(f"{d[k][lv]:.2f}" if lv in d[k] else "—" for lv in (0.0, 1.0, 2.0))
            lines.append(f"| {s} | {k} | {cells} |")
    t = res["step_time"]
    lines += [
        "",
        "Step time alone at 0° (ms/step): "
        + ", ".join(f"{k} {v:.2f}" if v else f"{k} —" for k, v in t.items()),
    ]
    lines += ["", "| target | value | met |", "|---|---:|---|"]
    for g in res["targets"]:
        v = g.get("value_db")
        val = (
            f"{v:+.2f} dB"
            if v is not None
            else (f"{100 * g['value']:+.1f} %" if g.get("value") is not None else "—")
        )
        lines.append(f"| {g['what']} | {val} | {'yes' if g['met'] else '**no**'} |")
    return "\n".join(lines) + "\n"


def plot(res: dict, path: Path) -> Path:
    from benchmarks.plots import plt, save_figure

    n = max(1, len(res["scenes"]))
    fig, axes = plt.subplots(1, n, figsize=(5 * n, 4), layout="constrained", squeeze=False)
    for ax, (s, d) in zip(axes[0], res["scenes"].items(), strict=False):
        colors = {"plain": "tab:red", "refine": "tab:blue"}
        for k in d:
            lv = sorted(d[k])
            ax.plot(lv, [d[k][x] for x in lv], "o-", color=colors.get(k), label=k)
        ax.set_title(s)
        ax.set_xlabel("pose error (°)")
        ax.set_ylabel("PSNR (dB)")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    return save_figure(fig, path)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", metavar="OUT", help="the folder gpu_refine.sh wrote")


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    res = summarize(out)
    plot(res, out / "refine_summary.png")
    write_report(out, "refine_summary", res, markdown(res))
    return 0


def main(argv: list[str] | None = None) -> int:
    return benchmark_main("study_refine", __doc__, add_arguments, run, argv)


if __name__ == "__main__":
    sys.exit(main())
