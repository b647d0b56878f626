"""One table of a pose-study sweep (`benchmarks/gpu_sweep.sh`): every option at every level.

    python -m benchmarks.study_sweep OUT

Reads OUT/sweep_SCENE_NAME_L<level>/pose-error.json (one level each) and writes
OUT/sweep.md and OUT/sweep.json: per scene, option and level the PSNR, the remaining mean
rotation error and centre offset of the refined poses, the steps and train seconds (runs
side by side: not a step time).
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

from benchmarks.cli import benchmark_main
from benchmarks.session import jsonable
from fastenerf.io import atomic_path, write_json

_DIR = re.compile(r"sweep_(?P<scene>[^_]+)_(?P<name>.+)_L(?P<level>[0-9.]+)$")


def collect(out: Path) -> list[dict]:
    """One row per finished run, sorted by scene, option name and level."""
    rows = []
    for d in sorted(out.glob("sweep_*_L*")):
        m = _DIR.match(d.name)
        if not m or not (d / "pose-error.json").is_file():
            continue
        study = json.loads((d / "pose-error.json").read_text())
        for lv in study["levels"]:
            stats = (lv.get("self_calibration") or {}).get("stats", {})
            rows.append(
                {
                    "scene": m["scene"],
                    "name": m["name"],
                    "level": float(lv["level"]),
                    "psnr": lv.get("psnr"),
                    "pose_error_deg": stats.get("pose_error_deg"),
                    "pose_centre_error": stats.get("pose_centre_error"),
                    "steps": lv.get("steps"),
                    "train_s": lv.get("train_s"),
                    "commit": (study.get("git_commits") or [None])[0],
                }
            )
    return sorted(rows, key=lambda r: (r["scene"], r["name"], r["level"]))


def markdown(rows: list[dict]) -> str:
    def f(v, fmt):
        return "—" if v is None else format(v, fmt)

    lines = [
        "| scene | option | level | PSNR (dB) | pose error (°) | centre offset | steps | train s |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']} | {r['name']} | {r['level']:g}° | {f(r['psnr'], '.2f')} | "
            f"{f(r['pose_error_deg'], '.3f')} | {f(r['pose_centre_error'], '.4f')} | "
            f"{f(r['steps'], 'd')} | {f(r['train_s'], '.0f')} |"
        )
    return "\n".join(lines) + "\n"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", help="the sweep's OUT folder")


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    rows = collect(out)
    write_json(out / "sweep.json", jsonable({"runs": rows}))
    with atomic_path(out / "sweep.md") as tmp:
        tmp.write_text(markdown(rows))
    print(markdown(rows), end="")
    return 0


def main(argv: list[str] | None = None) -> int:
    return benchmark_main("study_sweep", __doc__, add_arguments, run, argv)


if __name__ == "__main__":
    raise SystemExit(main())
