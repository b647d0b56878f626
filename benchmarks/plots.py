"""Plots shared by the benchmarks (matplotlib, Agg backend, written atomically as PNG).

plot_error_vs_time(runs, path, title)   PSNR and SSIM against training seconds (log x)
plot_pareto(rows, path, title)          PSNR at a fixed budget against time per step
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless: benchmarks run on machines without a display
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter  # noqa: E402

from fastenerf.io import atomic_path  # noqa: E402

BACKEND_STYLE = {"ngp": "-", "vanilla": "--"}


def _num(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


def log_x(ax) -> None:
    """Log x axis ticked at 1, 2, 5 × 10^k with plain numbers (readable over short ranges)."""
    ax.set_xscale("log")
    ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.ticklabel_format(axis="y", useOffset=False)


def save_figure(fig, path: str | Path, dpi: int = 130) -> Path:
    """Save `fig` to `path` (format from the suffix) atomically and close it."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_error_vs_time(runs: list[dict], path: str | Path, title: str = "") -> Path:
    """Two panels, PSNR (dB) and SSIM against training seconds on a log axis.

    runs: dicts with `scene`, `backend` and `points` (each point: `train_s`, `psnr`, `ssim`);
    one line per (scene, backend), solid for ngp, dashed for vanilla.
    """
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6))
    pairs = sorted({(r["scene"], r["backend"]) for r in runs})
    colours = {p: plt.cm.tab10(i % 10) for i, p in enumerate(pairs)}
    for r in runs:
        pts = [
            p for p in r["points"] if _num(p["psnr"]) and _num(p["train_s"]) and p["train_s"] > 0
        ]
        if not pts:
            continue
        t = [p["train_s"] for p in pts]
        style = dict(
            color=colours[(r["scene"], r["backend"])],
            ls=BACKEND_STYLE.get(r["backend"], ":"),
            marker="o",
            ms=3.5,
            label=f"{r['backend']} · {r['scene']}",
        )
        axes[0].plot(t, [p["psnr"] for p in pts], **style)
        axes[1].plot(t, [p["ssim"] if _num(p["ssim"]) else math.nan for p in pts], **style)
    for ax, name in zip(axes, ("PSNR (dB, colour-corrected)", "SSIM"), strict=True):
        log_x(ax)
        ax.set_xlabel("training time (s, evaluation excluded)")
        ax.set_ylabel(name)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8, loc="lower right")
    if title:
        fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)


def plot_pareto(rows: list[dict], path: str | Path, title: str = "") -> Path:
    """PSNR at a fixed budget against mean time per step (ms, log x), one labelled point each.

    rows: dicts with `name`, `psnr`, `step_ms`, `pareto` (bool), `default` (bool). The Pareto
    front (faster or better than every other point) is joined by a line; the default is a star.
    """
    fig, ax = plt.subplots(figsize=(8, 5.5))
    ok = [r for r in rows if _num(r["psnr"]) and _num(r["step_ms"]) and r["step_ms"] > 0]
    for r in ok:
        marker = "*" if r["default"] else "o"
        colour = "tab:red" if r["pareto"] else "tab:gray"
        ax.scatter(
            r["step_ms"],
            r["psnr"],
            marker=marker,
            s=160 if r["default"] else 40,
            color=colour,
            zorder=3,
        )
        ax.annotate(
            r["name"],
            (r["step_ms"], r["psnr"]),
            textcoords="offset points",
            xytext=(5, 4),
            fontsize=8,
        )
    front = sorted((r for r in ok if r["pareto"]), key=lambda r: r["step_ms"])
    if len(front) > 1:
        ax.plot(
            [r["step_ms"] for r in front],
            [r["psnr"] for r in front],
            color="tab:red",
            lw=1,
            alpha=0.6,
            label="Pareto front",
        )
        ax.legend(fontsize=8, loc="lower right")
    log_x(ax)
    ax.set_xlabel("mean time per training step (ms)")
    ax.set_ylabel("PSNR at the budget (dB, colour-corrected)")
    ax.grid(True, which="both", alpha=0.3)
    if title:
        ax.set_title(title, fontsize=10)
    return save_figure(fig, path)
