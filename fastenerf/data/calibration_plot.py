"""The calibration picture (`fastenerf calibrate --plot`): a board frame with its detected
corners and axes (chequerboard input), the cameras and the fitted circle in 3D, and the
solver's convergence."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np


@dataclasses.dataclass
class FrameOverlay:
    """One chequerboard frame for the plot. image: (H, W) gray; corners: (N, 2) pixels
    (centres at +0.5); axes: (4, 2) pixels of the board's origin and the tips of its x, y, z
    axes; outline: (K, 2) pixels of the board's edge or None; title: a line under it."""

    image: np.ndarray
    corners: np.ndarray
    axes: np.ndarray
    title: str
    outline: np.ndarray | None = None


def plot_calibration(
    path: str | Path,
    fit,
    c2w: np.ndarray,
    others: dict | None = None,
    frame: FrameOverlay | None = None,
    board_outline: np.ndarray | None = None,
    dpi: int = 80,
) -> Path:
    """PNG: cameras as arrows meeting at the fitted centre, the fitted circle (3D, poses frame),
    and the loss per iteration of this fit (a `TurntableFit`; and of `others`, e.g. the other
    solver). With a chequerboard: `frame`, a detected board drawn over its image, and
    `board_outline` (K, 3), the board's edge in the poses frame, drawn in 3D."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io import atomic_path

    n = 3 if frame is not None else 2
    fig = plt.figure(figsize=(5 * n, 4.2), dpi=dpi)
    k = 1
    if frame is not None:
        _plot_frame(fig.add_subplot(1, n, 1), frame)
        k = 2
    _plot_cameras(fig.add_subplot(1, n, k, projection="3d"), fit, c2w, board_outline)
    _plot_convergence(fig.add_subplot(1, n, k + 1), fit, others)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    return path


def _plot_frame(ax, f: FrameOverlay) -> None:
    h, w = f.image.shape[:2]
    ax.imshow(f.image, cmap="gray", vmin=0, vmax=255, extent=(0, w, h, 0))  # pixel edges
    ax.plot(f.corners[:, 0], f.corners[:, 1], "+", color="orange", ms=5, mew=0.8)
    if f.outline is not None:
        ax.plot(f.outline[:, 0], f.outline[:, 1], "-", color="orange", lw=0.6)
    o = f.axes[0]
    for tip, color, name in zip(f.axes[1:], ("r", "g", "b"), "xyz", strict=True):
        ax.annotate(
            "",
            xy=tip,
            xytext=o,
            arrowprops=dict(arrowstyle="->", color=color, lw=1.6),
        )
        ax.text(*tip, name, color=color, fontsize=9, fontweight="bold")
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_title(f.title, fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])


def _plot_cameras(ax, fit, c2w: np.ndarray, board_outline: np.ndarray | None) -> None:
    from .rig import Turntable

    c2w = np.asarray(c2w, np.float64)
    tr = fit.trajectory
    Ry = fit.world_from_poses[:3, :3]
    C = Ry.T @ np.asarray(tr.center)  # back to the poses frame
    circle = (
        Turntable(dataclasses.replace(tr, clockwise=False, phase_deg=0.0, t0_us=0))(
            np.linspace(0, tr.period_us, 181)
        )[:, :3, 3]
        @ Ry
    )  # rows: Ry.T @ p
    o = c2w[:, :3, 3]
    z = c2w[:, :3, 2]
    L = np.linalg.norm(C - o, axis=1, keepdims=True)
    # World y is up: plot (x, z, y) so that matplotlib's vertical axis is the turntable's.
    ax.quiver(
        o[:, 0],
        o[:, 2],
        o[:, 1],
        z[:, 0] * L[:, 0],
        z[:, 2] * L[:, 0],
        z[:, 1] * L[:, 0],
        color="k",
        linewidth=0.6,
        arrow_length_ratio=0.04,
    )
    ax.plot(circle[:, 0], circle[:, 2], circle[:, 1], "r-", linewidth=1.5, label="fitted circle")
    ax.scatter(o[:, 0], o[:, 2], o[:, 1], color="k", s=6, label="cameras")
    ax.scatter([C[0]], [C[2]], [C[1]], color="r", s=40, depthshade=False, label="centre")
    if board_outline is not None:
        b = np.asarray(board_outline)
        ax.plot(b[:, 0], b[:, 2], b[:, 1], color="tab:blue", linewidth=1.2, label="board")
    axis_end = C + fit.axis * tr.radius * 0.6
    ax.plot([C[0], axis_end[0]], [C[2], axis_end[2]], [C[1], axis_end[1]], "r--", linewidth=1)
    ax.set_xlabel("x")
    ax.set_ylabel("z")
    ax.set_zlabel("y")
    lim = tr.radius * 1.1
    ax.set_xlim(C[0] - lim, C[0] + lim)
    ax.set_ylim(C[2] - lim, C[2] + lim)
    ax.set_zlim(C[1] - lim, C[1] + lim)
    ax.view_init(elev=20, azim=-60)
    res = fit.residuals
    ax.set_title(
        f"tilt α = {tr.tilt_deg:.4f}°, r = {tr.radius:.4g}\n"
        f"axis rms {res['axis_rms']:.2g}, angle rms {res['angle_rms_deg']:.3f}°",
        fontsize=9,
    )
    ax.legend(fontsize=7, loc="upper left")


def _plot_convergence(ax, fit, others: dict | None) -> None:
    fits = {f"{fit.method} ({fit.extras.get('init')} start)": fit}
    for name, f in (others or {}).items():
        fits[f"{name} ({f.extras.get('init')} start)"] = f
    longest = 0
    for name, f in fits.items():
        longest = max(longest, len(f.loss_history))
        ax.semilogy(
            np.arange(len(f.loss_history)),
            f.loss_history,
            ".-" if len(f.loss_history) < 30 else "-",
            label=f"{name}: {f.iterations} it, {f.time_s:.2f} s",
        )
    if longest > 30:  # a long run (Adam) and a short one (least squares) on one axis
        ax.set_xscale("symlog", linthresh=10)
    ax.set_xlabel("iteration")
    ax.set_ylabel("mean squared residual (world units²)")
    ax.set_title("convergence", fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
