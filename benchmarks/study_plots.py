"""The studies' pictures: PSNR / SSIM against the level, and the grid of one test view per level.

plot_study(result, path, title)         two panels against the level; numeric levels on a log
                                        axis with 0 drawn one decade left of the smallest
                                        positive level (marked by an axis break), the
                                        supplement's PSNR dashed beside ours
plot_grid(gt, tiles, path, title)       ground truth, then one labelled tile per level
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from benchmarks.plots import plt, save_figure
from benchmarks.session import finite
from benchmarks.study_levels import POSE_STUDIES

EARLY_STYLE = {"color": "tab:blue", "lw": 0.8, "alpha": 0.35, "marker": ".", "ms": 4}


def zero_position(levels: list[float]) -> float:
    """Where 0 is drawn on a log axis: one decade left of the smallest positive level."""
    pos = [x for x in levels if x > 0]
    return min(pos) / 10.0 if pos else 1.0


def plot_study(result: dict, path: str | Path, title: str = "") -> Path:
    """PSNR (dB) and SSIM against the level. result: a study's JSON object (rows in
    result["levels"], each with level, label, psnr, ssim, points)."""
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6), layout="constrained")
    if result["study"] == "ablation":
        _categorical(axes, result)
    else:
        _numeric(axes, result)
    for ax, name in zip(axes, ("PSNR (dB, colour-corrected)", "SSIM"), strict=True):
        ax.set_ylabel(name)
        ax.ticklabel_format(axis="y", useOffset=False)
        ax.grid(True, which="major", alpha=0.3)
    axes[0].legend(fontsize=8, loc="best")
    if title:
        fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)


def _numeric(axes, result: dict) -> None:
    rows = [r for r in result["levels"] if finite(r["psnr"])]
    sup = {float(k): v for k, v in result["supplement"]["psnr"].items()}
    levels = sorted({r["level"] for r in rows} | set(sup))
    x0 = zero_position(levels)

    def xs(values):
        return [x0 if v == 0 else v for v in values]

    unit = "°" if result["study"] in POSE_STUDIES else " %"
    for key, ax in (("psnr", axes[0]), ("ssim", axes[1])):
        _early_lines(ax, rows, key, xs)
        _line(ax, xs([r["level"] for r in rows]), [r[key] for r in rows], "ours (at the budget)")
        if key == "psnr" and sup:
            lv = sorted(sup)
            _line(
                ax,
                xs(lv),
                [sup[v] for v in lv],
                "supplement (Drums)",
                color="tab:gray",
                ls="--",
                marker="s",
            )
        ax.set_xscale("log")
        ax.set_xticks(xs(levels), [f"{v:g}" for v in levels])
        ax.minorticks_off()
        ax.set_xlabel(result["study"].replace("-", " ") + f" ({unit.strip()}; 0 at the break)")
        if any(v == 0 for v in levels) and any(v > 0 for v in levels):
            _axis_break(ax, math.sqrt(x0 * min(v for v in levels if v > 0)))


def _line(ax, x, y, label, color="tab:blue", ls="-", marker="o") -> None:
    """A curve whose first segment (from the 0 level, not to scale on a log axis) is dotted."""
    if not x:
        return
    if len(x) > 1 and x[0] < x[1] / 5:
        ax.plot(x[:2], y[:2], color=color, ls=":", lw=1)
        ax.plot(x[1:], y[1:], color=color, ls=ls, marker=marker, ms=4, label=label)
        ax.plot(x[:1], y[:1], color=color, marker=marker, ms=4, ls="none")
    else:
        ax.plot(x, y, color=color, ls=ls, marker=marker, ms=4, label=label)


def _early_lines(ax, rows: list[dict], key: str, xs) -> None:
    """Faint lines of the earlier evaluations (budget/4, budget/2) when every row has them."""
    n = min((len(r["points"]) for r in rows), default=0)
    for i in range(n - 1):
        t = [r["points"][i] for r in rows]
        if all(finite(p.get(key)) for p in t):
            target = t[0].get("target_s")
            label = f"at {target:g} s" if finite(target) else None
            ax.plot(xs([r["level"] for r in rows]), [p[key] for p in t], label=label, **EARLY_STYLE)


def _axis_break(ax, x: float) -> None:
    """Two slashes on the x axis at data x: the log scale does not run through 0."""
    trans = ax.get_xaxis_transform()  # x in data, y in axes fraction
    for dx in (0.97, 1.03):
        ax.plot(
            [x * dx / 1.04, x * dx * 1.04],
            [-0.02, 0.02],
            transform=trans,
            color="k",
            lw=1,
            clip_on=False,
        )


def _categorical(axes, result: dict) -> None:
    """Named variants: one point each, its value written beside it (a dot plot: a bar on a
    cut y axis would exaggerate small differences)."""
    rows = result["levels"]
    x = np.arange(len(rows))
    for key, ax in (("psnr", axes[0]), ("ssim", axes[1])):
        y = [r[key] if finite(r[key]) else np.nan for r in rows]
        ax.plot(x, y, "o", color="tab:blue", ms=7, label="ours (at the budget)")
        for xi, yi in zip(x, y, strict=True):
            if np.isfinite(yi):
                ax.annotate(
                    f"{yi:.2f}" if key == "psnr" else f"{yi:.3f}",
                    (xi, yi),
                    textcoords="offset points",
                    xytext=(7, 0),
                    va="center",
                    fontsize=8,
                )
        ax.set_xticks(x, [r["label"] for r in rows], rotation=20)
        ax.set_xlim(-0.5, len(rows) - 0.3)
        ax.set_xlabel("variant")


def plot_grid(gt: np.ndarray, tiles: list, path: str | Path, title: str = "") -> Path:
    """Ground truth, then per level its render with "label · PSNR" above it.

    gt: (H, W, 3) float in [0, 1] or uint8; tiles: [(label, psnr_db, image (H, W, 3) or None)]
    (None: the level has no render yet, drawn as an empty tile).
    """
    n = 1 + len(tiles)
    cols = min(n, 4)
    rows = math.ceil(n / cols)
    h, w = gt.shape[:2]
    tile_in = 3.0
    fig, axes = plt.subplots(
        rows, cols, figsize=(cols * tile_in, rows * tile_in * h / w + 0.6 * rows), squeeze=False
    )
    cells = [("ground truth", None, gt), *tiles] + [(None, None, None)] * (rows * cols - n)
    for ax, (label, psnr, img) in zip(axes.flat, cells, strict=True):
        ax.set_axis_off()
        if label is None:
            continue
        if img is None:
            ax.imshow(np.full((h, w, 3), 0.85))
            ax.text(w / 2, h / 2, "not run", ha="center", va="center", fontsize=9)
        else:
            ax.imshow(np.asarray(img), interpolation="nearest")
        sub = f"{label} · {psnr:.2f} dB" if finite(psnr) else str(label)
        ax.set_title(sub, fontsize=9)
    if title:
        fig.suptitle(title, fontsize=9)
    return save_figure(fig, path)


THRESHOLD_COLORS = {"true": "tab:green", "start": "tab:red", "estimate": "tab:blue"}


def plot_threshold(result: dict, path: str | Path, title: str = "") -> Path:
    """The threshold study: PSNR per true C₊ and run (true / wrong start / estimate), and the
    ratio C₊/C₋ each run used against the true ratio (the diagonal is exact)."""
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4.6), layout="constrained")
    runs = result["runs"]
    for v, color in THRESHOLD_COLORS.items():
        rs = [r for r in runs if r["variant"] == v]
        if not rs:
            continue
        x = [r["level"] for r in rs]
        a.plot(x, [r["psnr"] for r in rs], "o-", color=color, ms=5, label=v)
        b.plot(
            [r["true"]["ratio"] for r in rs],
            [r["ratio_used"] for r in rs],
            "o",
            color=color,
            ms=6,
            label=v,
        )
    ratios = [r["true"]["ratio"] for r in runs] + [r["ratio_used"] for r in runs]
    lo, hi = min(ratios) * 0.9, max(ratios) * 1.1
    b.plot([lo, hi], [lo, hi], color="k", lw=0.8, ls="--", label="exact")
    b.fill_between(
        [lo, hi], [lo * 0.9, hi * 0.9], [lo * 1.1, hi * 1.1], color="k", alpha=0.08, label="±10 %"
    )
    a.set_xlabel("true C₊ (C₋ fixed)")
    a.set_ylabel("PSNR (dB, colour-corrected)")
    b.set_xlabel("true C₊/C₋")
    b.set_ylabel("C₊/C₋ the run used")
    for ax in (a, b):
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="best")
    if title:
        fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)
