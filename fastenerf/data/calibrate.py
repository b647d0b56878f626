"""Turntable calibration from observed camera poses (supplement A.1).

Input: camera-to-world poses (M, 4, 4), OpenCV, of the event camera around a chequerboard
standing on the turntable's axis (e.g. from chequerboard detection in the DAVIS frames), in a
y-up world (the board's vertical ≈ +y), optionally with their times.

Model (`fastenerf.data.rig.Turntable`, `TrajectoryConfig`): each camera sits on a circle around
the rotation axis n, at distance `radius` from the centre C on the axis where all optical axes
meet, `elevation` above the circle's plane, looking at C with "up" along n. The fit finds n
(the tilt α from the world's +y), C, radius, elevation and each pose's turntable angle; given
times, the angles give period, phase and direction by a linear fit.

Two solvers minimise the same residuals (camera centre − model centre, radius · (optical axis −
model axis), 6 per pose, world units):
- "lm" (default): closed-form start (plane of the camera centres by SVD → axis; algebraic
  circle fit in that plane → circle centre and radius; the point of the axis closest to all
  optical axes → C and elevation), then trust-region least squares (scipy) with the
  Jacobian's block sparsity. A handful of iterations, residual at the noise floor.
- "adam": Adam with the learning rate halved on plateaus, from a naive start (centroid of the
  camera centres, mean camera "up" as the axis), as the paper describes. Kept for comparison:
  on these residuals it reaches the same optimum, but after ~1500 steps (seconds) against the
  least-squares solver's ~5 iterations (tens of ms); see tests/test_calibrate.py.

The axis is parametrised by a tangent offset around the start axis (not by α and an azimuth,
which is singular at α = 0 where the paper's second value, 0.2388°, almost sits).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..config import TrajectoryConfig
from ..errors import InputError

N_GLOBAL = 7  # axis tangent (2), centre (3), log radius, elevation; then one angle per pose


@dataclass
class TurntableFit:
    """Result of `fit_turntable`.

    trajectory: the turntable model in the poses' world turned by `world_yaw_deg` about +y (so
    that the axis tilts about x only, as `TrajectoryConfig` expresses it; 0 when the axis already
    leans in the y-z plane); world_from_poses: (4, 4) that rotation. axis: (3,) unit rotation
    axis, poses frame; angles_deg: (M,) each pose's turntable angle (the model's θ, degrees).
    residuals: RMS errors — `axis_rms` distance of the observed optical axes from the centre
    (world units), `angle_rms_rad`/`angle_rms_deg` angle between each optical axis and the
    direction to the centre, `position_rms` camera centres vs the circle, `roll_rms_deg` camera
    roll about its axis vs the model's (not fitted: the model has none), `time_rms_deg` angles vs
    the uniform-rotation fit (with times).
    """

    trajectory: TrajectoryConfig
    period_fitted: bool
    world_yaw_deg: float
    world_from_poses: np.ndarray
    axis: np.ndarray
    angles_deg: np.ndarray
    residuals: dict
    method: str
    iterations: int
    time_s: float
    loss_history: np.ndarray  # (K,) mean squared residual (world units²) per iteration
    extras: dict = field(default_factory=dict)

    @property
    def tilt_deg(self) -> float:
        return self.trajectory.tilt_deg

    def axis_aligned(self) -> TrajectoryConfig:
        """The same trajectory in the turntable's own frame: origin at the centre, +y the axis.

        A turntable scene has no other world-anchored data, so this frame is free to choose; it
        is the one where the density clip (a cylinder about +y through the origin, supplement
        A.2) surrounds the turntable plate.
        """
        return dataclasses.replace(self.trajectory, tilt_deg=0.0, center=[0.0, 0.0, 0.0])

    def to_dict(self) -> dict:
        return {
            "trajectory": dataclasses.asdict(self.trajectory),
            "trajectory_axis_aligned": dataclasses.asdict(self.axis_aligned()),
            "period_fitted": self.period_fitted,
            "world_yaw_deg": self.world_yaw_deg,
            "world_from_poses": self.world_from_poses.tolist(),
            "axis_in_poses_frame": self.axis.tolist(),
            "residuals": self.residuals,
            "solver": {
                "method": self.method,
                "iterations": self.iterations,
                "time_s": self.time_s,
                "final_loss": float(self.loss_history[-1]),
            },
            "angles_deg": self.angles_deg.tolist(),
            "n_poses": len(self.angles_deg),
        }


# ----------------------------------------------------------------------------------- inputs


def load_calibration_poses(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a poses npz: `c2w` (M, 4, 4) and optional `t` (M,) µs. One-line errors."""
    from ..io import read_npz

    path = Path(path)
    z = read_npz(path, ("c2w",), ("t",), what="poses file")
    c2w, t = z["c2w"], z.get("t")
    if t is not None and t.shape != (len(c2w),):
        raise InputError(f"{path}: {len(c2w)} poses but 't' has shape {t.shape}")
    return np.asarray(c2w, np.float64), (None if t is None else t.astype(np.int64))


def _check_poses(c2w: np.ndarray, t_us, source: str) -> np.ndarray:
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.ndim != 3 or c2w.shape[1:] not in ((4, 4), (3, 4)):
        raise InputError(f"{source}: poses must be (M, 4, 4), got {c2w.shape}")
    if len(c2w) < 5:
        raise InputError(f"{source}: {len(c2w)} poses; a turntable fit needs at least 5")
    if not np.all(np.isfinite(c2w)):
        i = int(np.flatnonzero(~np.isfinite(c2w).reshape(len(c2w), -1).all(1))[0])
        raise InputError(f"{source}: pose {i} contains NaN or inf")
    R = c2w[:, :3, :3]
    err = np.abs(np.einsum("nij,nik->njk", R, R) - np.eye(3)).max((1, 2))
    if err.max() > 1e-3 or np.any(np.linalg.det(R) < 0):
        i = int(np.argmax((err > 1e-3) | (np.linalg.det(R) < 0)))
        raise InputError(f"{source}: pose {i}'s rotation is not a rotation matrix")
    if t_us is not None:
        t = np.asarray(t_us)
        if t.shape != (len(c2w),):
            raise InputError(f"{source}: {len(c2w)} poses but {t.size} timestamps")
        if np.any(np.diff(t) <= 0):
            raise InputError(f"{source}: pose timestamps must increase strictly")
    return c2w


# ------------------------------------------------------------------------------------ model


def _model(q: torch.Tensor, basis: torch.Tensor):
    """Turntable cameras from parameters q (7 + M,), float64, in normalised units.

    basis: (3, 3) rows (u, n0, v), right-handed, n0 the start axis. Returns eye (M, 3), optical
    axis z (M, 3), axis n (3,), in-plane unit ex (3,), ez (3,), centre C (3,), radius r.
    """
    u, n0, v = basis
    n = n0 + q[0] * u + q[1] * v
    n = n / torch.linalg.norm(n)
    ex = u - (u @ n) * n
    ex = ex / torch.linalg.norm(ex)
    ez = torch.linalg.cross(ex, n)  # (ex, n, ez) right-handed, as world (x, y, z)
    C, r, el, th = q[2:5], torch.exp(q[5]), q[6], q[N_GLOBAL:]
    offset = (
        torch.cos(el) * (torch.sin(th)[:, None] * ex + torch.cos(th)[:, None] * ez)
        + torch.sin(el) * n
    )
    eye = C + r * offset
    return eye, -offset, n, ex, ez, C, r


def _residuals(q: torch.Tensor, basis, o: torch.Tensor, z_obs: torch.Tensor) -> torch.Tensor:
    """(6M,) position and r-scaled optical-axis residuals, normalised units."""
    eye, z, *_, r = _model(q, basis)
    return torch.cat([(eye - o).reshape(-1), (r * (z - z_obs)).reshape(-1)])


def _basis(n0: np.ndarray) -> np.ndarray:
    """Rows (u, n0, v): right-handed orthonormal frame with n0 in the middle (u × n0 = v)."""
    n0 = n0 / np.linalg.norm(n0)
    a = np.array([1.0, 0.0, 0.0]) if abs(n0[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    u = a - (a @ n0) * n0
    u /= np.linalg.norm(u)
    return np.stack([u, n0, np.cross(u, n0)])


def _angles(o: np.ndarray, C: np.ndarray, ex: np.ndarray, ez: np.ndarray) -> np.ndarray:
    d = o - C
    return np.arctan2(d @ ex, d @ ez)


# ------------------------------------------------------------------------------ start points


def closed_form_start(o: np.ndarray, z_obs: np.ndarray, up_obs: np.ndarray):
    """Closed-form turntable estimate from camera centres o (M, 3), optical axes z_obs (M, 3)
    and camera "up" vectors up_obs (M, 3) (= −y of OpenCV cameras).

    Returns (basis (3, 3), q (7 + M,)) for `_model`, in the units of o.
    """
    m = o.mean(0)
    _, s, vt = np.linalg.svd(o - m, full_matrices=False)
    if s[1] < 1e-3 * s[0]:
        raise InputError("camera centres are (nearly) on a line: they do not span a circle")
    n = vt[2] * (1.0 if (up_obs @ vt[2]).sum() >= 0 else -1.0)  # axis points "up"
    basis = _basis(n)
    u, _, v = basis
    # Algebraic circle fit in the plane: |p - c|² = ρ² is linear in (c, ρ² - |c|²).
    p2 = np.stack([(o - m) @ u, (o - m) @ v], -1)
    A = np.concatenate([2 * p2, np.ones((len(p2), 1))], 1)
    sol = np.linalg.lstsq(A, (p2**2).sum(-1), rcond=None)[0]
    rho = math.sqrt(max(sol[2] + sol[0] ** 2 + sol[1] ** 2, 1e-30))
    P = m + sol[0] * u + sol[1] * v
    # C = P + s n: the axis point closest (least squares) to all optical axes.
    proj = np.eye(3)[None] - z_obs[:, :, None] * z_obs[:, None, :]
    An, Aw = proj @ n, np.einsum("mij,mj->mi", proj, P - o)
    s_ax = -float((An * Aw).sum() / max((An * An).sum(), 1e-30))
    C = P + s_ax * n
    r = math.hypot(rho, s_ax)
    el = math.atan2(-s_ax, rho)
    ex, ez = u, np.cross(u, n)
    th = _angles(o, C, ex, ez)
    return basis, np.concatenate([[0.0, 0.0], C, [math.log(r), el], th])


def naive_start(o: np.ndarray, up_obs: np.ndarray):
    """The paper-style start: axis = mean camera up, centre = centroid, elevation 0."""
    n = up_obs.mean(0)
    n /= np.linalg.norm(n)
    basis = _basis(n)
    C = o.mean(0)
    r = float(np.linalg.norm(o - C, axis=1).mean())
    th = _angles(o, C, basis[0], np.cross(basis[0], n))
    return basis, np.concatenate([[0.0, 0.0], C, [math.log(r), 0.0], th])


# ---------------------------------------------------------------------------------- solvers


def solve_lm(
    q0: np.ndarray, basis: np.ndarray, o: np.ndarray, z_obs: np.ndarray, max_iters: int = 100
) -> tuple[np.ndarray, list[float], int]:
    """Trust-region least squares from q0; returns (q, loss per iteration, iterations)."""
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix

    m = len(o)
    tb, to, tz = (torch.from_numpy(np.ascontiguousarray(a)) for a in (basis, o, z_obs))

    def fun(q):
        with torch.no_grad():
            return _residuals(torch.from_numpy(q), tb, to, tz).numpy()

    # Pose i's angle moves only its own 6 residuals: finite differences need ~N_GLOBAL + 1
    # evaluations per Jacobian instead of N_GLOBAL + M.
    S = lil_matrix((6 * m, N_GLOBAL + m), dtype=np.int8)
    S[:, :N_GLOBAL] = 1
    for i in range(m):
        for k in range(3):
            S[3 * i + k, N_GLOBAL + i] = 1
            S[3 * m + 3 * i + k, N_GLOBAL + i] = 1
    history = [float(np.mean(fun(q0) ** 2))]

    def callback(intermediate_result):
        history.append(2.0 * float(intermediate_result.cost) / (6 * m))

    res = least_squares(
        fun,
        q0,
        jac_sparsity=S,
        method="trf",
        x_scale="jac",
        xtol=1e-12,
        ftol=1e-12,
        gtol=1e-12,
        max_nfev=max_iters * (N_GLOBAL + 3),
        callback=callback,
    )
    history.append(float(np.mean(res.fun**2)))
    return res.x, history, len(history) - 2


def solve_adam(
    q0: np.ndarray,
    basis: np.ndarray,
    o: np.ndarray,
    z_obs: np.ndarray,
    max_iters: int = 20000,
    lr: float = 1e-2,
    patience: int = 100,
    min_lr: float = 1e-6,
) -> tuple[np.ndarray, list[float], int]:
    """Adam on the mean squared residual, lr halved on plateaus (the paper's optimiser)."""
    tb, to, tz = (torch.from_numpy(np.ascontiguousarray(a)) for a in (basis, o, z_obs))
    q = torch.nn.Parameter(torch.from_numpy(q0.copy()))
    opt = torch.optim.Adam([q], lr=lr)
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(
        opt, factor=0.5, patience=patience, threshold=1e-4
    )
    history = []
    it = 0
    for it in range(1, max_iters + 1):  # noqa: B007 (it is the iteration count afterwards)
        opt.zero_grad(set_to_none=True)
        loss = _residuals(q, tb, to, tz).square().mean()
        loss.backward()
        opt.step()
        history.append(loss.detach().item())
        sched.step(history[-1])
        if opt.param_groups[0]["lr"] < min_lr:
            break
    with torch.no_grad():
        history.append(float(_residuals(q, tb, to, tz).square().mean()))
    return q.detach().numpy().copy(), history, it


# ------------------------------------------------------------------------------------- fit


def fit_turntable(
    c2w: np.ndarray,
    t_us: np.ndarray | None = None,
    method: str = "lm",
    init: str | None = None,
    source: str = "poses",
    **solver_options,
) -> TurntableFit:
    """Fit the turntable model to camera poses.

    c2w: (M, 4, 4) OpenCV camera-to-world, M >= 5, world units; t_us: (M,) int64 µs
    (increasing) or None. method: "lm" (default) or "adam"; init: "closed_form" (default for
    lm) or "naive" (default for adam, as the paper). Raises `InputError` on bad poses.
    """
    if method not in ("lm", "adam"):
        raise InputError(f"unknown calibration method {method!r} (use 'lm' or 'adam')")
    init = init or ("closed_form" if method == "lm" else "naive")
    c2w = _check_poses(c2w, t_us, source)
    o, z_obs, up_obs, m0, scale = _normalised_poses(c2w, source)
    q, basis, history, iters, elapsed = _solve(o, z_obs, up_obs, method, init, solver_options)

    with torch.no_grad():
        eye, z, n, ex, ez, C, r = (
            a.numpy() if isinstance(a, torch.Tensor) else a
            for a in _model(torch.from_numpy(q), torch.from_numpy(basis))
        )
    el = float(q[6])
    el = math.atan2(math.sin(el), abs(math.cos(el)))  # same cameras, with cos(el) >= 0
    C_w = C * scale + m0
    beta, alpha, Ry = _yaw_and_tilt(n)
    # The Turntable's in-plane axes, back in the poses frame, give its angle θ per pose.
    ex_t = Ry.T @ np.array([1.0, 0.0, 0.0])
    ez_t = Ry.T @ _rot_x(alpha) @ np.array([0.0, 0.0, 1.0])
    theta = _angles(eye, C, ex_t, ez_t)

    traj = TrajectoryConfig(
        kind="turntable",
        radius=float(r) * scale,
        center=(Ry @ C_w).tolist(),
        tilt_deg=math.degrees(alpha),
        elevation_deg=math.degrees(el),
    )
    residuals = _residual_stats(c2w, C_w, eye * scale + m0, z, n)
    traj = _place_in_time(traj, t_us, theta, source, residuals)
    W = np.eye(4)
    W[:3, :3] = Ry
    return TurntableFit(
        trajectory=traj,
        period_fitted=t_us is not None,
        world_yaw_deg=math.degrees(beta),
        world_from_poses=W,
        axis=n,
        angles_deg=np.degrees(theta),
        residuals=residuals,
        method=method,
        iterations=iters,
        time_s=elapsed,
        loss_history=np.asarray(history) * scale**2,
        extras={"init": init, "arc_deg": _arc_deg(theta), "normalised_scale": scale},
    )


def _normalised_poses(c2w: np.ndarray, source: str):
    """Camera centres o (M, 3) moved to their centroid m0 (3,) and divided by their mean
    distance from it (scale, world units), so one learning rate / tolerance fits any units;
    with the unit optical axes z_obs (M, 3) and camera "up" vectors up_obs (M, 3)."""
    o_w = c2w[:, :3, 3]
    z_obs = c2w[:, :3, 2] / np.linalg.norm(c2w[:, :3, 2], axis=1, keepdims=True)
    up_obs = -c2w[:, :3, 1]
    m0 = o_w.mean(0)
    scale = float(np.linalg.norm(o_w - m0, axis=1).mean())
    if not scale > 0:
        raise InputError(f"{source}: all camera centres coincide")
    return (o_w - m0) / scale, z_obs, up_obs, m0, scale


def _solve(o, z_obs, up_obs, method: str, init: str, solver_options: dict):
    """Start point and solver run, timed (s): (q (7 + M,), basis (3, 3), loss history,
    iterations, seconds)."""
    import scipy.optimize  # noqa: F401 (imported before the clock starts: time the solve only)

    t_start = time.perf_counter()
    if init == "closed_form":
        basis, q0 = closed_form_start(o, z_obs, up_obs)
    elif init == "naive":
        basis, q0 = naive_start(o, up_obs)
    else:
        raise InputError(f"unknown calibration start {init!r} (use 'closed_form' or 'naive')")
    solve = solve_lm if method == "lm" else solve_adam
    q, history, iters = solve(q0, basis, o, z_obs, **solver_options)
    return q, basis, history, iters, time.perf_counter() - t_start


def _yaw_and_tilt(n: np.ndarray) -> tuple[float, float, np.ndarray]:
    """The axis n (3,) in TrajectoryConfig terms, world = R_y(β) · poses, axis = R_x(α) ŷ:
    (β, α) in radians, β in (-π/2, π/2], and R_y(β) (3, 3)."""
    beta = math.atan2(-n[0], n[2]) if math.hypot(n[0], n[2]) > 1e-12 else 0.0
    if beta > math.pi / 2:
        beta -= math.pi
    elif beta <= -math.pi / 2:
        beta += math.pi
    Ry = _rot_y(beta)
    n_w = Ry @ n
    return beta, math.atan2(n_w[2], n_w[1]), Ry


def _place_in_time(traj: TrajectoryConfig, t_us, theta: np.ndarray, source: str, residuals):
    """Period, phase and direction from the times t_us (M,) µs (adding `time_rms_deg` to
    `residuals`), or without times direction and phase from the poses' order."""
    if t_us is not None:
        traj, time_rms = _fit_rotation(traj, np.asarray(t_us, np.int64), theta, source)
        residuals["time_rms_deg"] = time_rms
    else:
        # Without times, take the poses' order as the capture order for the direction.
        steps = np.angle(np.exp(1j * np.diff(theta)))
        traj.clockwise = bool(np.median(steps) < 0)
        traj.phase_deg = math.degrees(theta[0])
    return traj


def _fit_rotation(traj: TrajectoryConfig, t: np.ndarray, theta: np.ndarray, source: str):
    """Uniform rotation θ(t) = θ0 + ω (t − t0) by least squares on the unwrapped angles."""
    th = np.unwrap(theta)
    if np.max(np.abs(np.diff(th))) > 0.9 * np.pi:
        raise InputError(
            f"{source}: poses are too far apart in angle (> 160° between "
            "neighbours) to follow the rotation; give more poses"
        )
    t0 = int(t[0])
    dt = (t - t0).astype(np.float64)
    A = np.stack([np.ones_like(dt), dt], -1)
    (th0, omega), *_ = np.linalg.lstsq(A, th, rcond=None)
    if abs(omega) < 1e-15:
        raise InputError(f"{source}: the poses do not rotate over time")
    resid = th - (th0 + omega * dt)
    traj = dataclasses.replace(
        traj,
        period_us=int(round(2 * math.pi / abs(omega))),
        phase_deg=math.degrees(th0),
        t0_us=t0,
        clockwise=bool(omega < 0),
    )
    return traj, float(np.degrees(np.sqrt(np.mean(resid**2))))


def _residual_stats(
    c2w: np.ndarray, C: np.ndarray, eye: np.ndarray, z_model: np.ndarray, n: np.ndarray
) -> dict:
    """RMS errors of the observed poses against the fitted model, world units / angles."""
    o = c2w[:, :3, 3]
    z = c2w[:, :3, 2] / np.linalg.norm(c2w[:, :3, 2], axis=1, keepdims=True)
    d = C - o
    along = (d * z).sum(-1)
    axis_dist = np.linalg.norm(d - along[:, None] * z, axis=1)  # centre to optical axis line
    cosang = np.clip(along / np.linalg.norm(d, axis=1), -1.0, 1.0)
    ang = np.arccos(cosang)
    # Model camera x: look-at with up = axis (as `look_at`); roll is the angle between the
    # observed and model x axes about the optical axis.
    x_model = np.cross(-n[None], z_model)
    x_model /= np.linalg.norm(x_model, axis=1, keepdims=True)
    x_obs = c2w[:, :3, 0]
    roll = np.arctan2((np.cross(x_model, x_obs) * z).sum(-1), (x_model * x_obs).sum(-1))
    rms = lambda a: float(np.sqrt(np.mean(np.square(a))))  # noqa: E731
    return {
        "axis_rms": rms(axis_dist),
        "angle_rms_rad": rms(ang),
        "angle_rms_deg": math.degrees(rms(ang)),
        "position_rms": rms(np.linalg.norm(eye - o, axis=1)),
        "roll_rms_deg": math.degrees(rms(roll)),
        "roll_mean_deg": math.degrees(float(np.mean(roll))),
    }


def _arc_deg(theta: np.ndarray) -> float:
    """Angle covered by the poses (360 when they go all round)."""
    s = np.sort(np.mod(theta, 2 * np.pi))
    gaps = np.diff(np.concatenate([s, [s[0] + 2 * np.pi]]))
    return float(np.degrees(2 * np.pi - gaps.max()))


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


# ------------------------------------------------------------------------------ comparison


def compare_solvers(
    c2w: np.ndarray, t_us: np.ndarray | None = None, adam_from_closed_form: bool = False
) -> dict[str, TurntableFit]:
    """Fit with both solvers from their default starts (and, optionally, Adam from the
    closed-form start too, which separates the start's effect from the optimiser's)."""
    fits = {
        "lm": fit_turntable(c2w, t_us, method="lm"),
        "adam": fit_turntable(c2w, t_us, method="adam"),
    }
    if adam_from_closed_form:
        fits["adam_closed_form_start"] = fit_turntable(c2w, t_us, method="adam", init="closed_form")
    return fits


# ---------------------------------------------------------------------------------- output


def write_calibration(path: str | Path, fit: TurntableFit, extra: dict | None = None) -> Path:
    """Write the calibration JSON (atomically)."""
    from ..io import write_json

    d = fit.to_dict()
    if extra:
        d.update(extra)
    return write_json(path, d)


def load_calibration(path: str | Path, frame: str = "turntable") -> tuple[TrajectoryConfig, dict]:
    """(TrajectoryConfig, whole JSON) from a calibration file written by `write_calibration`.

    frame: "turntable" (axis-aligned: origin at the centre, +y the axis) or "poses" (the
    poses' world, up to the recorded yaw).
    """
    import json

    from ..config import from_dict

    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: calibration file not found") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: not valid JSON ({e})") from None
    key = {"turntable": "trajectory_axis_aligned", "poses": "trajectory"}.get(frame)
    if key is None:
        raise InputError(f"unknown frame {frame!r} (use 'turntable' or 'poses')")
    if not isinstance(d, dict) or key not in d:
        raise InputError(f"{path}: no '{key}' here (is this a `fastenerf calibrate` output?)")
    return from_dict(TrajectoryConfig, d[key], str(path), key + "."), d


def synthetic_poses(
    trajectory: TrajectoryConfig,
    n: int,
    t_span_us: int | None = None,
    pos_noise: float = 0.0,
    rot_noise_deg: float = 0.0,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Noisy turntable poses, as chequerboard detection would give: (t (n,) int64 µs sorted,
    c2w (n, 4, 4)). Positions get N(0, pos_noise²) per axis (world units), orientations a
    random rotation with N(0, rot_noise_deg²) per rotation-vector component."""
    from scipy.spatial.transform import Rotation

    from .rig import Turntable

    rng = np.random.default_rng(seed)
    span = trajectory.period_us if t_span_us is None else t_span_us
    t = np.unique(rng.uniform(0, span, n).astype(np.int64))
    c2w = Turntable(trajectory)(t)
    c2w[:, :3, 3] += rng.normal(0.0, pos_noise, (len(t), 3))
    dR = Rotation.from_rotvec(rng.normal(0.0, math.radians(rot_noise_deg), (len(t), 3)))
    c2w[:, :3, :3] = dR.as_matrix() @ c2w[:, :3, :3]
    return t, c2w
