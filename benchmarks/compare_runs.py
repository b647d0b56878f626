"""PSNR against training time of several error-vs-time outputs, one line per label.

    python -m benchmarks.compare_runs OUT.png [PANEL:]LABEL=DIR [...] [--title T]
        [--metric psnr|pose_error_deg|pose_jitter_deg]

DIR is an `error_vs_time` output folder (its error_vs_time.json; the first run in it is
plotted). LABEL may start with "PANEL:" to put that line in a panel of its own (e.g.
"0°:refine=..." and "1°:refine=..."): one panel per distinct prefix, in order of appearance.
The same label in two panels keeps its colour, so a variant reads across them.
--metric pose_error_deg plots the rotation error a perturbed run's poses still have (degrees,
log scale) in place of PSNR, pose_jitter_deg its pose-to-pose part (`pose_refine`); a run that
records none is refused.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from fastenerf.errors import InputError, require
from fastenerf.outputs import IMAGE, claim_output

from .cli import benchmark_main
from .plots import log_x, plt, save_figure

# What --metric can plot: the key in each curve point, the axis label, a log axis or not.
METRICS = {
    "psnr": ("PSNR (dB, colour-corrected)", False),
    "pose_error_deg": ("rotation error left in the poses (°)", True),
    "pose_jitter_deg": ("its pose-to-pose part (°)", True),
}


def load_points(folder: str | Path, metric: str = "psnr") -> list[tuple[float, float]]:
    """(train_s, value of `metric`) of the first run in `folder`/error_vs_time.json, positive
    times and numeric values only."""
    path = Path(folder) / "error_vs_time.json"
    if not path.is_file():
        raise InputError(f"{path}: no error_vs_time.json here")
    runs = json.loads(path.read_text()).get("runs") or []
    if not runs:
        raise InputError(f"{path}: no runs in it")
    pts = [(p["train_s"], p.get(metric)) for p in runs[0]["points"]]
    pts = [(t, v) for t, v in pts if isinstance(v, (int, float)) and t and t > 0]
    if not pts:
        raise InputError(f"{path}: its first run records no {metric}")
    return pts


def parse_item(item: str) -> tuple[str, str, str]:
    """'[PANEL:]LABEL=DIR' -> (panel, label, dir)."""
    lhs, eq, folder = item.rpartition("=")
    if not eq or not lhs or not folder:
        raise InputError(f"{item!r}: expected [PANEL:]LABEL=DIR")
    panel, _, label = lhs.rpartition(":")
    return panel, label, folder


def plot(items: list[str], out: str | Path, title: str = "", metric: str = "psnr") -> Path:
    """One `metric`-vs-time panel per PANEL prefix; returns the written PNG's path."""
    parsed = [parse_item(i) for i in items]
    series = [load_points(folder, metric) for _, _, folder in parsed]  # all read before drawing
    ylabel, log_y = METRICS[metric]
    panels = list(dict.fromkeys(p for p, _, _ in parsed))
    labels = list(dict.fromkeys(lab for _, lab, _ in parsed))
    colours = {lab: plt.cm.tab20(i % 20) for i, lab in enumerate(labels)}
    fig, axes = plt.subplots(1, len(panels), figsize=(6.2 * len(panels), 4.6), squeeze=False)
    for ax, panel in zip(axes[0], panels, strict=True):
        for (p, label, _), pts in zip(parsed, series, strict=True):
            if p == panel:
                t, v = zip(*pts, strict=True)
                ax.plot(t, v, marker="o", ms=3, color=colours[label], label=label)
        log_x(ax)
        if log_y:
            ax.set_yscale("log")
        ax.set_title(panel, fontsize=10)
        ax.set_xlabel("training time (s, evaluation excluded)")
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, loc="upper right" if log_y else "lower right")
    if title:
        fig.suptitle(title, fontsize=10)
    return save_figure(fig, out)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", help="PNG to write")
    p.add_argument("items", nargs="+", metavar="[PANEL:]LABEL=DIR")
    p.add_argument("--title", default="")
    p.add_argument(
        "--metric", default="psnr", choices=sorted(METRICS), help="what the y axis shows"
    )


def run(args: argparse.Namespace) -> int:
    require(Path(args.out).suffix.lower() == ".png", f"{args.out}: the plot is a .png file")
    claim_output(args.out, IMAGE, force=None)  # before reading anything: nothing is lost
    print(plot(args.items, args.out, args.title, args.metric))
    return 0


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    return benchmark_main("compare_runs", __doc__, add_arguments, run, argv, prog)


if __name__ == "__main__":
    raise SystemExit(main())
