"""The training poses fitted to a smooth trajectory before training (#20): a motion prior.

A camera's path is smooth in time, so a pose error that is independent from one pose to the
next (tracking jitter, or the pose study's per-pose turn) is the high-frequency part of the
given poses. `smooth_poses` removes it with a local polynomial fit along the training pose
grid (Savitzky–Golay): every entry of the rotation matrix is fitted by a polynomial of degree
`order` over `window` consecutive poses, and the fit is projected back onto the rotations (the
nearest one, by SVD). The centres stay as given: a turn of 1° moves the image by 10–15 px,
while a polynomial through an orbit's centres would pull them inwards. An error shared by
neighbouring poses (a mis-mounted camera, a slow drift) is smooth itself and stays: that is
the pose refinement's job.

On a loop the fit wraps around (the grid's last pose is its first); elsewhere the ends are
fitted by the polynomial of the first and last full window. A uniform turn about a fixed axis
(a turntable) comes out exact for any window: averaging it only scales the rotation's
in-plane entries, which the projection undoes.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .data.rig import Rig, TimedPoses
from .errors import InputError
from .perturb import rotation_angles_deg

MIN_WINDOW = 5
LOOP_TOL = 1e-6  # a grid's first and last poses this close (entries): one view, a loop


def check_window(window: int, n_poses: int, where: str = "smooth_poses") -> None:
    """Raise a one-line InputError unless `window` is 0 (off) or odd, >= MIN_WINDOW and at
    most the number of poses it is fitted over."""
    if window == 0:
        return
    if window < MIN_WINDOW or window % 2 == 0:
        raise InputError(
            f"{where}: smooth_poses must be 0 (off) or odd and >= {MIN_WINDOW}, got {window}"
        )
    if window > n_poses:
        raise InputError(
            f"{where}: smooth_poses {window} is longer than the {n_poses} "
            "training poses it would smooth"
        )


def nearest_rotations(M: np.ndarray) -> np.ndarray:
    """The rotations nearest (Frobenius) to matrices M (N, 3, 3): U·diag(1, 1, det)·Vᵀ."""
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    d[d == 0] = 1.0
    U = U.copy()
    U[:, :, -1] *= d[:, None]
    return U @ Vt


def smooth_poses(c2w: np.ndarray, window: int, loop: bool, order: int = 2) -> np.ndarray:
    """The poses c2w (G, 4, 4) float64 along the grid, each fitted over `window` neighbours.

    window: odd number of poses (>= MIN_WINDOW, <= the poses fitted); loop: c2w[-1] is the
    pose of c2w[0] (one view) and the fit wraps around; order: polynomial degree (< window).
    Returns (G, 4, 4) float64: the smoothed rotations, the given centres.
    """
    from scipy.signal import savgol_filter

    c2w = np.asarray(c2w, dtype=np.float64)
    g = len(c2w) - 1 if loop else len(c2w)
    check_window(window, g, "smooth_poses")
    x = c2w[:g, :3, :3].reshape(g, 9)
    y = savgol_filter(x, window, order, axis=0, mode="wrap" if loop else "interp")
    out = c2w.copy()
    out[:g, :3, :3] = nearest_rotations(y.reshape(g, 3, 3))
    if loop:
        out[g, :3, :3] = out[0, :3, :3]
    return out


def smoothed_rig(
    rig: Rig,
    grid_t: np.ndarray,
    window: int,
    exact_c2w: np.ndarray | None = None,
    where: str = "smooth_poses",
) -> tuple[Rig, dict]:
    """The rig whose trajectory is its poses on the training grid, smoothed.

    rig: the (perhaps perturbed) training rig; grid_t: (G,) int64 µs training pose grid
    (`WindowSampler.grid_times`); window: as `smooth_poses`; exact_c2w: optional (G, 4, 4)
    true poses on the grid (a study's), for the report's errors; where: the error's prefix.
    The grid is a loop when its first and last poses agree (a closed loop's grid spans one
    period). Returns the new rig (a timed trajectory on the grid; same intrinsics, Bayer, loop)
    and a report: the window, whether it wrapped, the mean and largest turn the smoothing gave
    a pose, and with exact_c2w the mean rotation error before and after (degrees).
    """
    t = np.asarray(grid_t, dtype=np.int64)
    given = rig.pose(t)
    loop = rig.loop_period_us is not None and np.allclose(given[0], given[-1], atol=LOOP_TOL)
    check_window(window, len(t) - int(loop), where)
    new = smooth_poses(given, window, loop)
    turn = rotation_angles_deg(given[:, :3, :3], new[:, :3, :3])
    report = {
        "window": int(window),
        "loop": bool(loop),
        "poses": int(len(t)),
        "mean_turn_deg": float(turn.mean()),
        "max_turn_deg": float(turn.max()),
    }
    if exact_c2w is not None:
        R = np.asarray(exact_c2w)[:, :3, :3]
        report["error_before_deg"] = float(rotation_angles_deg(R, given[:, :3, :3]).mean())
        report["error_after_deg"] = float(rotation_angles_deg(R, new[:, :3, :3]).mean())
    traj = TimedPoses(t, new, source="smoothed training poses")
    return dataclasses.replace(rig, trajectory=traj), report
