"""The training poses fitted to a smooth trajectory before training (#20): a motion prior.

A camera's path is smooth in time, so a pose error that is independent from one pose to the
next (tracking jitter, or the pose study's per-pose turn) is the high-frequency part of the
given poses. `smooth_poses` removes it with a local polynomial fit along the training pose
grid (Savitzky–Golay) done geodesically: about each pose's current estimate, its `window`
neighbours' rotations become rotation vectors (logs), a polynomial of degree `order` is fitted
to them and its value turns the estimate; a few such passes. The centres stay as given: a turn
of 1° moves the image by 10–15 px, while a polynomial through an orbit's centres would pull
them inwards. An error shared by neighbouring poses (a mis-mounted camera, a slow drift) is
smooth itself and stays: that is the pose refinement's job.

On a loop the fit wraps around (the grid's last pose is its first); elsewhere the ends are
fitted by the polynomial of the first and last full window. A turn at a constant rate about
a fixed axis (a turntable) has logs linear along the grid, so it comes out exact for any
window and either order; order 1 then averages the jitter over the window with the least
noise (order 2 also follows a changing rate, at ~1.5x the noise left). Fitting the matrices'
entries instead would shrink a long window's turn and the projection back would amplify the
jitter with it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .data.rig import Rig, TimedPoses
from .errors import InputError
from .perturb import rotation_angles_deg

MIN_WINDOW = 5
MAX_SPAN_DEG = 150.0  # a pose's farthest neighbour in its window: logs stay well inside 180°
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
        hint = max(MIN_WINDOW, int(0.4 * n_poses) // 2 * 2 + 1)  # the studies' 401 of 1000
        fits = f"on a turntable the studies use 40 % of them: {hint}"
        raise InputError(
            f"{where}: smooth_poses {window} is longer than the {n_poses} training poses it "
            f"would smooth ({fits if hint <= n_poses else f'at least {MIN_WINDOW} are needed'})"
        )


def nearest_rotations(M: np.ndarray) -> np.ndarray:
    """The rotations nearest (Frobenius) to matrices M (N, 3, 3): U·diag(1, 1, det)·Vᵀ."""
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    d[d == 0] = 1.0
    U = U.copy()
    U[:, :, -1] *= d[:, None]
    return U @ Vt


def smooth_poses(
    c2w: np.ndarray, window: int, loop: bool, order: int = 2, iters: int = 3
) -> np.ndarray:
    """The poses c2w (G, 4, 4) float64 along the grid, each fitted over `window` neighbours.

    window: odd number of poses (>= MIN_WINDOW, <= the poses fitted); loop: c2w[-1] is the
    pose of c2w[0] (one view) and the fit wraps around; order: polynomial degree (1 or 2,
    < window); iters: refits about the last estimate (the logs are linear about it).
    Returns (G, 4, 4) float64: the smoothed rotations, the given centres.

    The fit is geodesic: about the current estimate R̂_i, the neighbours' rotations are
    logs r_j = log(R̂_iᵀ R_j) (3-vectors), a polynomial in j is fitted to them and its value
    at i turns R̂_i. A turn at a constant rate about a fixed axis has logs linear in j, so it
    is exact for any window and order; and because the logs are not averaged matrix entries,
    a long window does not shrink the turn and amplify the jitter with it.
    """
    from scipy.signal import savgol_coeffs
    from scipy.spatial.transform import Rotation

    c2w = np.asarray(c2w, dtype=np.float64)
    g = len(c2w) - 1 if loop else len(c2w)
    check_window(window, g, "smooth_poses")
    if order not in (1, 2):
        raise InputError(f"smooth_poses: the fit's order must be 1 or 2, got {order}")
    h = window // 2
    i = np.arange(g)
    if loop:  # every pose at its window's centre, the window wrapping round
        idx = (i[:, None] + np.arange(-h, h + 1)[None]) % g
        pos = np.full(g, h)
    else:  # the ends: the first / last full window, evaluated off its centre
        start = np.clip(i - h, 0, g - window)
        idx, pos = start[:, None] + np.arange(window)[None], i - start
    weights = {p: savgol_coeffs(window, order, pos=int(p), use="dot") for p in np.unique(pos)}
    w = np.stack([weights[p] for p in pos])  # (g, window)
    R = c2w[:g, :3, :3]
    est = R.copy()
    rows = max(1, (1 << 20) // window)  # (rows, window, 3, 3) float64 at a time: <= 72 MB
    for _ in range(iters):
        for a in range(0, g, rows):
            b = min(g, a + rows)
            rel = np.einsum("gji,gwjk->gwik", est[a:b], R[idx[a:b]])
            logs = Rotation.from_matrix(rel.reshape(-1, 3, 3)).as_rotvec().reshape(b - a, -1, 3)
            _check_span(logs, window)
            turn = np.einsum("gw,gwk->gk", w[a:b], logs)
            est[a:b] = est[a:b] @ Rotation.from_rotvec(turn).as_matrix()
    out = c2w.copy()
    out[:g, :3, :3] = nearest_rotations(est)
    if loop:
        out[g, :3, :3] = out[0, :3, :3]
    return out


def _check_span(logs: np.ndarray, window: int) -> None:
    """Refuse a window over which the path turns near half a revolution: a log's direction
    is undefined at 180° (either sign fits) and the fit would average opposite vectors."""
    top = float(np.degrees(np.linalg.norm(logs, axis=-1).max()))
    if top > MAX_SPAN_DEG:
        raise InputError(
            f"smooth_poses: the path turns {top:.0f}° within half a window of {window} poses "
            f"(at most {MAX_SPAN_DEG:.0f}°); choose a shorter window"
        )


def smoothed_rig(
    rig: Rig,
    grid_t: np.ndarray,
    window: int,
    exact_c2w: np.ndarray | None = None,
    order: int = 2,
    where: str = "train config",
) -> tuple[Rig, dict]:
    """The rig whose trajectory is its poses on the training grid, smoothed.

    rig: the (perhaps perturbed) training rig; grid_t: (G,) int64 µs training pose grid
    (`WindowSampler.grid_times`); window, order: as `smooth_poses`; exact_c2w: optional
    (G, 4, 4) true poses on the grid (a study's), for the report's errors; where: the error's
    prefix.
    The grid is a loop when its first and last poses agree (a closed loop's grid spans one
    period). Returns the new rig (a timed trajectory on the grid; same intrinsics, Bayer, loop)
    and a report: the window, whether it wrapped, the mean and largest turn the smoothing gave
    a pose, and with exact_c2w the mean rotation error before and after (degrees).
    """
    t = np.asarray(grid_t, dtype=np.int64)
    given = rig.pose(t)
    loop = rig.loop_period_us is not None and np.allclose(given[0], given[-1], atol=LOOP_TOL)
    check_window(window, len(t) - int(loop), where)
    new = smooth_poses(given, window, loop, order)
    turn = rotation_angles_deg(given[:, :3, :3], new[:, :3, :3])
    report = {
        "window": int(window),
        "order": int(order),
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
