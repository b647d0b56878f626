"""Perturbations of a scene's training data for the robustness studies (supplement I, J).

- pose error (`perturb_poses`): every training pose's rotation is turned by a fixed angle X about
  its own random axis (uniform on the sphere); the camera centre stays. A timed trajectory has
  each of its samples turned; a turntable is first sampled on the training pose grid
  (`pose_grid_times`, the grid `WindowSampler` draws windows on) and becomes a timed
  trajectory of those poses. The angles reported are measured from the rotations.
- mount error (`perturb_mount`): every training pose turned by one shared rotation M (a fixed
  angle about ONE random axis) in the camera's own frame, c2w · M: a camera mis-mounted on its
  turntable. With the pose error too, the mount turn comes first: c2w · M · Δ_i.
- noise events (`add_noise_events`): uniformly random events (x, y over the sensor, t over the
  stream's time range, polarity ±1 with equal odds), F times the clean count, merged in time
  order.
- `perturb_training_data` applies a `PerturbConfig` to a loaded scene's rig and events.

Test views are never touched: they live in `Scene.test_c2w`, not in the rig. Each perturbation
draws from its own random stream of the one seed, so the pose axes do not depend on whether
noise is added too.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .config import PerturbConfig, SceneConfig
from .data.events import EventStream
from .data.formats.native import Scene
from .data.rig import Rig, TimedPoses
from .errors import InputError

# Salts of the per-perturbation random streams (one user seed, independent draws).
_POSE_STREAM = 0x9E05E
_NOISE_STREAM = 0x7015E
_MOUNT_STREAM = 0x3047E

# Two samples of a loop at t_start and t_start + P whose poses agree this closely (matrix
# entries, world units) are one view: they get one perturbation.
_SAME_VIEW_TOL = 1e-6


def pose_grid_times(cfg: SceneConfig) -> np.ndarray:
    """The training pose grid, (n_views + 1,) int64 µs: t_j = t_start + j (t_end − t_start) / n,
    integer-divided exactly as `fastenerf.sampling.WindowSampler.grid_times`."""
    j = np.arange(cfg.n_views + 1, dtype=np.int64)
    return cfg.t_start_us + (j * (cfg.t_end_us - cfg.t_start_us)) // cfg.n_views


def rotation_angles_deg(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Geodesic angle between rotations (N, 3, 3) and (N, 3, 3), (N,) float64 degrees.

    Measured as the magnitude of R_aᵀ R_b through its quaternion (2·atan2(|v|, |w|)), which keeps
    full precision at small angles where arccos((tr − 1) / 2) loses half the digits.
    """
    from scipy.spatial.transform import Rotation

    rel = np.einsum("nji,njk->nik", np.asarray(R_a, np.float64), np.asarray(R_b, np.float64))
    return np.rad2deg(Rotation.from_matrix(rel).magnitude())


def random_axes(rng: np.random.Generator, n: int) -> np.ndarray:
    """n unit vectors uniform on the sphere, (n, 3) float64 (normalised Gaussian draws)."""
    v = rng.normal(size=(n, 3))
    norm = np.linalg.norm(v, axis=1)
    while np.any(norm < 1e-12):  # a near-zero draw has no direction: draw it again
        bad = norm < 1e-12
        v[bad] = rng.normal(size=(int(bad.sum()), 3))
        norm = np.linalg.norm(v, axis=1)
    return v / norm[:, None]


def timed_samples(traj: TimedPoses) -> tuple[np.ndarray, np.ndarray]:
    """The samples of a timed trajectory: t (M,) int64 µs, c2w (M, 4, 4) float64."""
    return traj.t.copy(), traj(traj.t)


def perturb_poses(
    rig: Rig, angle_deg: float, seed: int = 0, grid_t: np.ndarray | None = None
) -> tuple[Rig, dict]:
    """Turn every training pose's rotation by `angle_deg` about its own random axis.

    rig: the scene's training rig (timed or turntable); angle_deg: degrees in [0, 180);
    seed: non-negative int; grid_t: (G,) int64 µs training pose grid (`pose_grid_times`),
    required for a turntable rig (the poses it is sampled at), optional for a timed one (then
    the report also gives the angles on the grid: between samples slerp blends two turns about
    different axes, mostly less than the angle asked).
    Returns a rig with a timed trajectory of the turned poses (same intrinsics, Bayer, loop)
    and a report: measured mean / max / min angle (degrees) between old and new rotations at the
    samples, the largest camera-centre shift (world units), the number of poses and the seed.
    """
    PerturbConfig(pose_error_deg=angle_deg, seed=seed).validate("perturb_poses")
    t, c2w, sampled = _samples(rig, grid_t, "perturb_poses")
    rng = np.random.default_rng([_POSE_STREAM, int(seed)])
    delta = _axis_angle_matrices(random_axes(rng, len(t)), np.deg2rad(float(angle_deg)))
    return _turned(rig, t, c2w, delta, grid_t, sampled, angle_deg, seed)


def mount_axis(seed: int) -> np.ndarray:
    """The camera-frame unit axis (3,) of `perturb_mount`'s turn for `seed`."""
    return random_axes(np.random.default_rng([_MOUNT_STREAM, int(seed)]), 1)[0]


def perturb_mount(
    rig: Rig, angle_deg: float, seed: int = 0, grid_t: np.ndarray | None = None
) -> tuple[Rig, dict]:
    """Turn every training pose by one shared rotation M in the camera's own frame,
    c2w_i · M (about the centre): `angle_deg` about ONE random axis (uniform on the sphere),
    the camera mis-mounted. Arguments and report as `perturb_poses` (the report adds "axis",
    the camera-frame axis of M); M being shared, slerp between samples keeps it exactly."""
    PerturbConfig(mount_error_deg=angle_deg, seed=seed).validate("perturb_mount")
    t, c2w, sampled = _samples(rig, grid_t, "perturb_mount")
    axis = mount_axis(seed)[None]
    delta = np.repeat(_axis_angle_matrices(axis, np.deg2rad(float(angle_deg))), len(t), 0)
    out, report = _turned(rig, t, c2w, delta, grid_t, sampled, angle_deg, seed)
    report["axis"] = axis[0].tolist()
    return out, report


def _samples(rig: Rig, grid_t: np.ndarray | None, where: str):
    """The poses to turn: t (M,) int64 µs, c2w (M, 4, 4) float64 and how they were sampled."""
    traj = rig.trajectory
    if isinstance(traj, TimedPoses):
        return *timed_samples(traj), "timed samples"
    if grid_t is None:
        raise InputError(f"{where}: a turntable rig needs the training pose grid grid_t")
    t = np.asarray(grid_t, dtype=np.int64)
    return t, traj(t), "turntable sampled on the training pose grid"


def _turned(rig, t, c2w, delta, grid_t, sampled, angle_deg, seed) -> tuple[Rig, dict]:
    """The rig of the poses c2w (at t) turned by delta (M, 3, 3) in their own frames, and
    the report of what the rigs give (not what was asked)."""
    traj = rig.trajectory
    twin = _loop_twin(rig, t, c2w)
    if twin:
        delta[-1] = delta[0]  # the loop's end is its start: one view, one perturbation
    new = c2w.copy()
    new[:, :3, :3] = c2w[:, :3, :3] @ delta  # R' = R·Δ: the axis is in the camera's frame
    new_traj = TimedPoses(t, new, source="perturbed poses")
    out = dataclasses.replace(rig, trajectory=new_traj)

    before, after = traj(t), new_traj(t)  # what the rigs give, not what was asked
    ang = rotation_angles_deg(before[:, :3, :3], after[:, :3, :3])
    report = {
        "angle_deg": float(angle_deg),
        "seed": int(seed),
        "poses": len(t) - int(twin),
        "sampled": sampled,
        "measured_mean_deg": float(ang.mean()),
        "measured_max_deg": float(ang.max()),
        "measured_min_deg": float(ang.min()),
        "centre_shift_max": float(np.abs(after[:, :3, 3] - before[:, :3, 3]).max()),
    }
    if grid_t is not None:
        g = np.asarray(grid_t, dtype=np.int64)
        ga = rotation_angles_deg(traj(g)[:, :3, :3], new_traj(g)[:, :3, :3])
        report["grid"] = {
            "poses": len(g),
            "measured_mean_deg": float(ga.mean()),
            "measured_max_deg": float(ga.max()),
        }
    return out, report


def _axis_angle_matrices(axes: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rotations (N, 3, 3) by `angle_rad` about unit `axes` (N, 3) (Rodrigues)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(axes * angle_rad).as_matrix()


def _loop_twin(rig: Rig, t: np.ndarray, c2w: np.ndarray) -> bool:
    """True when the first and last samples are one view: a loop's two ends at one pose."""
    if rig.loop_period_us is None or len(t) < 3:
        return False
    ends = t[0] == rig.loop_start_us and t[-1] - t[0] == rig.loop_period_us
    return bool(ends and np.abs(c2w[-1] - c2w[0]).max() < _SAME_VIEW_TOL)


def merge_events(a: EventStream, b: EventStream) -> tuple[EventStream, np.ndarray]:
    """Events of `a` and `b` (same sensor) in one time-sorted stream.

    Within equal times `a`'s events come first; each stream's own order is kept. Returns the
    stream and a (N_a + N_b,) bool mask, True where the event came from `b`.
    """
    if (a.width, a.height) != (b.width, b.height):
        raise InputError(
            f"merge_events: sensors differ ({a.width}x{a.height} vs {b.width}x{b.height})"
        )
    n = len(a) + len(b)
    # b's i-th event goes after every a event with t <= its t and after b's earlier events.
    at = np.searchsorted(a.t, b.t, side="right") + np.arange(len(b))
    from_b = np.zeros(n, dtype=bool)
    from_b[at] = True
    arrays = []
    for ka, kb in ((a.x, b.x), (a.y, b.y), (a.t, b.t), (a.p, b.p)):
        out = np.empty(n, dtype=ka.dtype)
        out[from_b], out[~from_b] = kb, ka
        arrays.append(out)
    return EventStream(*arrays, a.width, a.height), from_b


def noise_events(
    n: int, width: int, height: int, t_first: int, t_last: int, seed: int = 0
) -> EventStream:
    """n uniformly random events: x, y uniform over the width x height sensor, t uniform over
    the integer µs [t_first, t_last], polarity +1 or −1 with probability 1/2; sorted by t."""
    rng = np.random.default_rng([_NOISE_STREAM, int(seed)])
    t = np.sort(rng.integers(int(t_first), int(t_last) + 1, size=n, dtype=np.int64))
    x = rng.integers(0, width, size=n).astype(np.uint16)
    y = rng.integers(0, height, size=n).astype(np.uint16)
    p = np.where(rng.random(n) < 0.5, 1, -1).astype(np.int8)
    return EventStream(x, y, t, p, int(width), int(height))


def add_noise_events(
    events: EventStream, fraction: float, seed: int = 0
) -> tuple[EventStream, dict]:
    """The stream with round(fraction · N) uniform noise events merged in (see `noise_events`;
    t over the stream's own [first, last] µs).

    events: the clean stream (N events); fraction: in [0, 10]; seed: non-negative int.
    Returns the noisy stream (sorted, valid) and a report: clean and added counts, the
    measured fraction added / clean, the time range and the noise's positive share.
    """
    PerturbConfig(noise_fraction=fraction, seed=seed).validate("add_noise_events")
    n = len(events)
    k = int(round(float(fraction) * n))
    t0, t1 = (int(events.t[0]), int(events.t[-1])) if n else (0, 0)
    noise = noise_events(k, events.width, events.height, t0, t1, seed)
    out = merge_events(events, noise)[0] if k else events
    report = {
        "fraction": float(fraction),
        "seed": int(seed),
        "clean_events": n,
        "added_events": k,
        "measured_fraction": k / n if n else 0.0,
        "t_range_us": [t0, t1],
        "sensor": f"{events.width}x{events.height}",
        "noise_positive_fraction": float((noise.p > 0).mean()) if k else None,
    }
    return out, report


def perturb_training_data(
    scene: Scene, cfg: PerturbConfig, rig: Rig | None = None
) -> tuple[Rig, EventStream, dict]:
    """Apply `cfg` to a loaded scene's training data: (rig, events, report).

    rig: the training rig to perturb (default `scene.rig()`). Zero levels return `rig` and
    `scene.events` themselves (the identity). report: {"config": cfg as a dict, "pose": the
    `perturb_poses` report or None, "mount": the `perturb_mount` report or None, "noise": the
    `add_noise_events` report or None}. The mount turn comes before the per-pose one.
    Test views (`scene.test_c2w`) are not read or changed.
    """
    cfg.validate()
    rig = scene.rig() if rig is None else rig
    events = scene.events
    report: dict = {"config": cfg.to_dict(), "pose": None, "mount": None, "noise": None}
    grid = pose_grid_times(scene.config)
    if cfg.mount_error_deg > 0:  # first: c2w · M, then each pose's own turn, c2w · M · Δ_i
        rig, report["mount"] = perturb_mount(rig, cfg.mount_error_deg, cfg.seed, grid)
    if cfg.pose_error_deg > 0:
        rig, report["pose"] = perturb_poses(rig, cfg.pose_error_deg, cfg.seed, grid)
    if cfg.noise_fraction > 0:
        events, report["noise"] = add_noise_events(events, cfg.noise_fraction, cfg.seed)
    return rig, events, report
