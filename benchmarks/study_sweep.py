"""One table of a pose-study sweep (`benchmarks/gpu_sweep.sh`): every option at every level.

    python -m benchmarks.study_sweep OUT [MORE ...]

Reads OUT/sweep_SCENE_NAME_L<level>/STUDY.json (one level each, STUDY a pose study: pose-error
or mount-error; and MORE sweeps' folders, an option's name prefixed with its folder's) and
writes OUT/sweep.md and OUT/sweep.json: per scene, option and level the PSNR, the remaining
mean rotation error and centre offset of the refined poses, the steps and train seconds (runs
side by side: not a step time), with a study column when the sweeps hold more than one; and
OUT/sweep.png: per scene, each option's PSNR at 1° against its PSNR at 0° (the trade-off:
refinement must win at 1° without costing at 0°); and OUT/sweep_levels.png: per scene, each
option's PSNR against the level (a line where it ran several levels, a point where one).
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

from benchmarks.cli import benchmark_main
from benchmarks.session import jsonable
from benchmarks.study_levels import POSE_STUDIES
from fastenerf.errors import InputError
from fastenerf.io import atomic_path, write_json

_DIR = re.compile(r"sweep_(?P<scene>[^_]+)_(?P<name>.+)_L(?P<level>[0-9.]+)$")


def collect(out: Path, prefix: str = "") -> list[dict]:
    """One row per finished run (a folder may hold runs of each pose study), sorted by scene,
    option name, study and level."""
    rows = []
    for d in sorted(out.glob("sweep_*_L*")):
        m = _DIR.match(d.name)
        if not m:
            continue
        for name in sorted(POSE_STUDIES):
            if (d / f"{name}.json").is_file():
                study = json.loads((d / f"{name}.json").read_text())
                rows += [_row(m, prefix + m["name"], name, study, lv) for lv in study["levels"]]
    return sorted(rows, key=_order)


def _row(m: re.Match, option: str, name: str, study: dict, lv: dict) -> dict:
    stats = (lv.get("self_calibration") or {}).get("stats", {})
    return {
        "scene": m["scene"],
        "name": option,
        "study": name,
        "level": float(lv["level"]),
        "psnr": lv.get("psnr"),
        "gauge_deg": stats.get("pose_gauge_deg"),
        "pose_error_deg": stats.get("pose_error_deg"),
        "pose_centre_error": stats.get("pose_centre_error"),
        "steps": lv.get("steps"),
        "train_s": lv.get("train_s"),
        "commit": (study.get("git_commits") or [None])[0],
    }


def _order(r: dict) -> tuple:
    return (r["scene"], r["name"], r["study"], r["level"])


def _mixed(rows: list[dict]) -> bool:
    """Whether the rows hold more than one study (then each option names its study)."""
    return len({r["study"] for r in rows}) > 1


def markdown(rows: list[dict]) -> str:
    def f(v, fmt):
        return "—" if v is None else format(v, fmt)

    mixed = _mixed(rows)
    lines = [
        "| scene | option |" + (" study |" if mixed else "") + " level | PSNR (dB) | "
        "pose error (°) | shared turn (°) | centre offset | steps | train s |",
        "|---|---|" + ("---|" if mixed else "") + "---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        study = f" {r['study']} |" if mixed else ""
        lines.append(
            f"| {r['scene']} | {r['name']} |{study} {r['level']:g}° | {f(r['psnr'], '.2f')} | "
            f"{f(r['pose_error_deg'], '.3f')} | "
            f"{f(r['gauge_deg'], '.3f')} | {f(r['pose_centre_error'], '.4f')} | "
            f"{f(r['steps'], 'd')} | {f(r['train_s'], '.0f')} |"
        )
    return "\n".join(lines) + "\n"


def _psnr_by_option(rows: list[dict], scene: str) -> dict[str, dict[float, float]]:
    """{option name (with its study when the rows mix studies): {level: PSNR}} of one scene."""
    mixed, by = _mixed(rows), {}
    for r in rows:
        if r["scene"] == scene and r["psnr"] is not None:
            name = f"{r['name']} ({r['study']})" if mixed else r["name"]
            by.setdefault(name, {})[r["level"]] = r["psnr"]
    return by


def _panels(n: int, width: float, height: float):
    """A figure of n panels side by side (at least one): (fig, list of axes)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, max(1, n), figsize=(width * max(1, n), height), squeeze=False)
    return fig, list(axes[0])


def _save(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path


def plot(rows: list[dict], path: Path) -> Path:
    """PSNR at 1° against PSNR at 0°, one point per option that ran both, a panel per scene."""
    scenes = sorted({r["scene"] for r in rows})
    fig, axes = _panels(len(scenes), 5.5, 4.6)
    for ax, s in zip(axes, scenes, strict=False):
        by = _psnr_by_option(rows, s)
        pts = [(n, v[0.0], v[1.0]) for n, v in sorted(by.items()) if 0.0 in v and 1.0 in v]
        for n, x, y in pts:
            ax.scatter(x, y, s=18)
            ax.annotate(n, (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
        lo = min([p[2] for p in pts] + [p[1] for p in pts], default=0.0)
        hi = max([p[1] for p in pts], default=1.0)
        ax.plot([lo, hi], [lo, hi], "k:", lw=0.8, label="1° = 0°")
        ax.plot([lo, hi], [lo - 1, hi - 1], "k--", lw=0.8, label="1° = 0° − 1 dB")
        for n, v in by.items():  # runs without refinement: the 0° PSNR to keep
            if n.split(":")[-1].split(" ")[0] == "plain" and 0.0 in v:
                ax.axvline(v[0.0], color="grey", lw=0.8, label=f"{n} at 0°")
        ax.set(title=s, xlabel="PSNR at 0° (dB)", ylabel="PSNR at 1° (dB)")
        ax.legend(fontsize=7)
    return _save(fig, path)


def plot_levels(rows: list[dict], path: Path) -> Path:
    """PSNR against level, one line (or point) per option, a panel per scene."""
    scenes = sorted({r["scene"] for r in rows})
    fig, axes = _panels(len(scenes), 4.2, 3.8)
    for ax, s in zip(axes, scenes, strict=False):
        for name, v in sorted(_psnr_by_option(rows, s).items()):
            lv = sorted(v)
            ax.plot(lv, [v[x] for x in lv], "o-" if len(lv) > 1 else "s", ms=4, label=name)
        ax.set(title=s, xlabel="level (°)", ylabel="PSNR (dB)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    return _save(fig, path)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", help="the sweep's OUT folder (the table and plot go here)")
    p.add_argument("more", nargs="*", help="other sweeps' OUT folders to table beside it")


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    for d in (out, *map(Path, args.more)):
        if not d.is_dir():
            raise InputError(f"{d}: not a folder (a sweep's OUT, benchmarks/gpu_sweep.sh)")
    rows = collect(out)
    for m in args.more:
        rows += collect(Path(m), prefix=f"{Path(m).name}:")
    if not rows:  # an empty table must not replace a sweep's own
        raise InputError(f"{out}: no finished run (sweep_SCENE_NAME_L<level>/STUDY.json)")
    rows.sort(key=_order)
    try:
        plot(rows, out / "sweep.png")
        plot_levels(rows, out / "sweep_levels.png")
        write_json(out / "sweep.json", jsonable({"runs": rows}))
        with atomic_path(out / "sweep.md") as tmp:
            tmp.write_text(markdown(rows))
    except OSError as e:
        raise InputError(f"{out}: cannot write the table there ({e.strerror})") from None
    print(markdown(rows), end="")
    return 0


def main(argv: list[str] | None = None) -> int:
    return benchmark_main("study_sweep", __doc__, add_arguments, run, argv)


if __name__ == "__main__":
    raise SystemExit(main())
