"""The camera rig: intrinsics with radial distortion, pose(t), Bayer pattern, rays.

Conventions (DESIGN §9): OpenCV camera (x right, y down, z forward), camera-to-world 4x4,
pixel centres at +0.5, radial distortion x_d = x_u (1 + k1 r² + k2 r⁴) on normalised
coordinates. World is y-up; a turntable rotates about world +y.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..config import IntrinsicsConfig, SceneConfig, TrajectoryConfig
from ..errors import InputError
from .poses import load_poses

# RGGB: R at (even row, even col), G at (even, odd) and (odd, even), B at (odd, odd).
BAYER_RGGB = np.array([[0, 1], [1, 2]], dtype=np.int64)


_BAYER_TABLES: dict[torch.device, torch.Tensor] = {}


def _bayer_table(device: torch.device) -> torch.Tensor:
    """BAYER_RGGB as a (2, 2) int64 tensor on `device`, made once."""
    t = _BAYER_TABLES.get(device)
    if t is None:
        t = _BAYER_TABLES[device] = torch.as_tensor(BAYER_RGGB, device=device)
    return t


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels with radial distortion (k1, k2).

    `model` (see `IntrinsicsConfig`): "opencv" x_d = x_u (1 + k1 r_u² + k2 r_u⁴), or
    "eventnerf" x_u = x_d / (1 + k1 r_d² + k2 r_d⁴), on normalised coordinates. Each model has
    one closed-form direction; the other is solved by Newton's method on the radius.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    k1: float = 0.0
    k2: float = 0.0
    model: str = "opencv"

    @classmethod
    def from_config(cls, c: IntrinsicsConfig, width: int, height: int) -> Intrinsics:
        return cls(c.fx, c.fy, c.cx, c.cy, width, height, c.k1, c.k2, c.distortion_model)

    @property
    def distorted(self) -> bool:
        return self.k1 != 0.0 or self.k2 != 0.0

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=np.float64)

    def scaled(self, s: float) -> Intrinsics:
        """Intrinsics for the image resized by factor `s` (e.g. 0.5 halves each side)."""
        w, h = max(1, round(self.width * s)), max(1, round(self.height * s))
        sx, sy = w / self.width, h / self.height
        return Intrinsics(
            self.fx * sx,
            self.fy * sy,
            self.cx * sx,
            self.cy * sy,
            w,
            h,
            self.k1,
            self.k2,
            self.model,
        )

    def _factor(self, r2: np.ndarray) -> np.ndarray:
        return 1.0 + self.k1 * r2 + self.k2 * r2**2

    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Normalised undistorted (N, 2) -> normalised distorted (N, 2)."""
        xy = np.asarray(xy, dtype=np.float64)
        if self.model == "opencv":
            return xy * self._factor((xy**2).sum(-1, keepdims=True))
        return self._solve_radius(xy, inverse_of_division=True)

    def undistort(self, xy_d: np.ndarray) -> np.ndarray:
        """Normalised distorted (N, 2) -> normalised undistorted (N, 2)."""
        xy_d = np.asarray(xy_d, dtype=np.float64)
        if self.model == "eventnerf":
            return xy_d / self._factor((xy_d**2).sum(-1, keepdims=True))
        return self._solve_radius(xy_d, inverse_of_division=False)

    def _solve_radius(self, xy: np.ndarray, inverse_of_division: bool, iters: int = 30):
        """Invert the closed-form direction radially by Newton's method on a = |result|.

        opencv undistort: solve a (1 + k1 a² + k2 a⁴) = b;  eventnerf distort: solve
        a / (1 + k1 a² + k2 a⁴) = b, where b = |xy|. The direction of xy is unchanged.
        """
        k1, k2 = self.k1, self.k2
        b = np.sqrt((xy**2).sum(-1))
        a = b.copy()
        for _ in range(iters):
            a2 = a * a
            d = 1.0 + k1 * a2 + k2 * a2 * a2
            if inverse_of_division:
                h, dh = a / d - b, (1.0 - k1 * a2 - 3.0 * k2 * a2 * a2) / (d * d)
            else:
                h, dh = a * d - b, 1.0 + 3.0 * k1 * a2 + 5.0 * k2 * a2 * a2
            a = a - h / np.where(np.abs(dh) > 1e-12, dh, 1e-12)
        scale = np.where(b > 0, a / np.where(b > 0, b, 1.0), 1.0)
        return xy * scale[..., None]

    def pixel_to_camera(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Pixel coordinates u, v (N,) each (centres at +0.5) -> camera ray dirs (N, 3), z = 1."""
        xy = np.stack(
            [
                (np.asarray(u, np.float64) - self.cx) / self.fx,
                (np.asarray(v, np.float64) - self.cy) / self.fy,
            ],
            -1,
        )
        if self.distorted:
            xy = self.undistort(xy)
        return np.concatenate([xy, np.ones_like(xy[:, :1])], -1)

    def project(self, p_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3), z > 0 -> pixel coordinates (N, 2)."""
        p_cam = np.asarray(p_cam, dtype=np.float64)
        xy = p_cam[:, :2] / p_cam[:, 2:3]
        if self.distorted:
            xy = self.distort(xy)
        return np.stack([xy[:, 0] * self.fx + self.cx, xy[:, 1] * self.fy + self.cy], -1)


class TimedPoses:
    """pose(t) from timed samples: rotation slerp, translation lerp; clamped at the ends."""

    def __init__(self, t_us: np.ndarray, c2w: np.ndarray, source: str = "poses"):
        """t_us: (M,) strictly increasing µs; c2w: (M, 4, 4) or (M, 3, 4) camera-to-world."""
        t_us = np.asarray(t_us)
        c2w = np.asarray(c2w, dtype=np.float64)
        if c2w.ndim != 3 or c2w.shape[1:] not in ((4, 4), (3, 4)):
            raise InputError(f"{source}: poses must be (M, 4, 4) or (M, 3, 4), got {c2w.shape}")
        if t_us.ndim != 1 or len(t_us) != len(c2w):
            raise InputError(f"{source}: {len(c2w)} poses but timestamps of shape {t_us.shape}")
        if len(c2w) == 0:
            raise InputError(f"{source}: no poses")
        if t_us.dtype.kind not in "iuf" or not np.all(np.isfinite(t_us)):
            raise InputError(f"{source}: pose timestamps must be finite numbers (µs)")
        if not np.all(np.isfinite(c2w)):
            i = int(np.flatnonzero(~np.isfinite(c2w).reshape(len(c2w), -1).all(1))[0])
            raise InputError(f"{source}: pose {i} contains NaN or inf")
        if np.any(np.diff(t_us) <= 0):
            i = int(np.argmax(np.diff(t_us) <= 0)) + 1
            raise InputError(f"{source}: pose timestamps must increase strictly (pose {i})")
        R = c2w[:, :3, :3]
        err = np.abs(np.einsum("nij,nik->njk", R, R) - np.eye(3)).max((1, 2))
        if err.max() > 1e-3 or np.any(np.linalg.det(R) < 0):
            i = int(np.argmax((err > 1e-3) | (np.linalg.det(R) < 0)))
            raise InputError(f"{source}: pose {i} is not a rotation (orthonormal, det +1)")
        self.t = t_us.astype(np.int64)
        self.quat = _matrix_to_quat(R)
        self.trans = c2w[:, :3, 3].copy()

    def __call__(self, t_us) -> np.ndarray:
        """Camera-to-world (N, 4, 4) float64 at times (N,) µs."""
        t = np.atleast_1d(np.asarray(t_us, dtype=np.float64))
        tt = self.t.astype(np.float64)
        i = np.clip(np.searchsorted(tt, t, side="right") - 1, 0, len(tt) - 1)
        j = np.minimum(i + 1, len(tt) - 1)
        span = np.where(j > i, tt[j] - tt[i], 1.0)
        a = np.clip((t - tt[i]) / span, 0.0, 1.0)
        q = _slerp(self.quat[i], self.quat[j], a)
        out = np.tile(np.eye(4), (len(t), 1, 1))
        out[:, :3, :3] = _quat_to_matrix(q)
        out[:, :3, 3] = self.trans[i] * (1 - a[:, None]) + self.trans[j] * a[:, None]
        return out


class Turntable:
    """A camera circling the world +y axis uniformly, looking at the circle's centre.

    Supplement A.1: the circle's plane is tilted by `tilt_deg` (about world x); the camera may
    sit `elevation_deg` above the plane, still looking at `center`.
    """

    def __init__(self, cfg: TrajectoryConfig):
        self.cfg = cfg

    def angle(self, t_us) -> np.ndarray:
        """Turntable angle in radians at times (N,) µs."""
        c = self.cfg
        t = np.atleast_1d(np.asarray(t_us, dtype=np.float64))
        sign = -1.0 if c.clockwise else 1.0
        return np.deg2rad(c.phase_deg) + sign * 2 * np.pi * (t - c.t0_us) / c.period_us

    def __call__(self, t_us) -> np.ndarray:
        c = self.cfg
        th = self.angle(t_us)
        el = np.deg2rad(c.elevation_deg)
        p = (
            np.stack(
                [np.sin(th) * np.cos(el), np.full_like(th, np.sin(el)), np.cos(th) * np.cos(el)], -1
            )
            * c.radius
        )
        tilt = _rot_x(np.deg2rad(c.tilt_deg))
        center = np.asarray(c.center, dtype=np.float64)
        eye = p @ tilt.T + center
        up = tilt @ np.array([0.0, 1.0, 0.0])
        return look_at(eye, np.broadcast_to(center, eye.shape), up)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world (N, 4, 4) for cameras at `eye` (N, 3) looking at `target` (N, 3)."""
    eye = np.atleast_2d(eye).astype(np.float64)
    z = np.atleast_2d(target) - eye
    z /= np.linalg.norm(z, axis=-1, keepdims=True)
    x = np.cross(np.broadcast_to(-np.asarray(up, np.float64), z.shape), z)  # y points down
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    y = np.cross(z, x)
    out = np.tile(np.eye(4), (len(eye), 1, 1))
    out[:, :3, 0], out[:, :3, 1], out[:, :3, 2], out[:, :3, 3] = x, y, z, eye
    return out


@dataclass
class Rig:
    """Intrinsics + trajectory + colour filter of one capture.

    On a closed loop (`loop_period_us` set) a time before `loop_start_us` is one period
    later, pose(t) = pose(t + P), the same wrap as `EventIndex` applies to windows.
    """

    intrinsics: Intrinsics
    trajectory: TimedPoses | Turntable
    bayer: str | None
    loop_start_us: int | None = None
    loop_period_us: int | None = None

    @classmethod
    def from_scene(
        cls,
        cfg: SceneConfig,
        folder: str | Path | None = None,
        poses: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> Rig:
        """The rig of a scene; a "timed" trajectory takes `poses` = (t (M,) µs, c2w (M, 4, 4))
        when given (poses held in memory, e.g. read from an EventNeRF folder), otherwise
        reads `cfg.trajectory.poses_file` under `folder`."""
        intr = Intrinsics.from_config(cfg.intrinsics, cfg.width, cfg.height)
        tr = cfg.trajectory
        if tr.kind == "timed":
            if poses is not None:
                traj = TimedPoses(*poses, source=f"{cfg.name}: poses")
            else:
                path = Path(folder or ".") / tr.poses_file
                t, c2w = load_poses(path)
                traj = TimedPoses(t, c2w, source=str(path))
        else:
            traj = Turntable(tr)
        if cfg.loop:
            return cls(intr, traj, cfg.bayer, cfg.t_start_us, cfg.t_end_us - cfg.t_start_us)
        return cls(intr, traj, cfg.bayer)

    def pose(self, t_us) -> np.ndarray:
        """Camera-to-world (N, 4, 4) float64 at times (N,) µs."""
        if self.loop_period_us is not None:
            t = np.atleast_1d(np.asarray(t_us))
            t_us = np.where(t < self.loop_start_us, t + self.loop_period_us, t)
        return self.trajectory(t_us)

    def channel(self, pix: np.ndarray | torch.Tensor):
        """Colour channel (0 R, 1 G, 2 B) seen by flat pixels `pix` (N,); None on a mono sensor."""
        if self.bayer is None:
            return None
        w = self.intrinsics.width
        if isinstance(pix, torch.Tensor):  # made once per device: a copy per call would sync
            table = _bayer_table(pix.device)
        else:
            pix, table = np.asarray(pix, dtype=np.int64), BAYER_RGGB
        y, x = pix // w, pix % w
        return table[y % 2, x % 2]

    def rays(self, pix: np.ndarray, c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World rays through pixel centres.

        pix: (N,) int flat pixel ids (y * width + x); c2w: (N, 4, 4) or (4, 4) camera-to-world.
        Returns rays_o (N, 3), rays_d (N, 3) unit, float32, world units.
        """
        pix = np.asarray(pix, dtype=np.int64)
        w = self.intrinsics.width
        d_cam = self.intrinsics.pixel_to_camera(pix % w + 0.5, pix // w + 0.5)
        c2w = np.asarray(c2w, dtype=np.float64)
        if c2w.ndim == 2:
            d = d_cam @ c2w[:3, :3].T
            o = np.broadcast_to(c2w[:3, 3], d.shape)
        else:
            d = np.einsum("nij,nj->ni", c2w[:, :3, :3], d_cam)
            o = c2w[:, :3, 3]
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return np.ascontiguousarray(o, dtype=np.float32), d.astype(np.float32)

    def image_rays(self, c2w: np.ndarray, scale: float = 1.0):
        """All rays of one view (H*W, 3) each, optionally at a reduced resolution `scale`."""
        intr = self.intrinsics if scale == 1.0 else self.intrinsics.scaled(scale)
        rig = Rig(intr, self.trajectory, self.bayer)
        return rig.rays(np.arange(intr.width * intr.height), c2w)


def _rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=np.float64)


def _matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations -> (N, 4) unit quaternions (w, x, y, z), sign-continuous."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(R).as_quat()[:, [3, 0, 1, 2]]
    # Keep neighbours in one hemisphere so slerp takes the short way: flipping q[i] flips its
    # dot with q[i+1] too, so the signs to apply are the running product of the dot signs.
    flip = np.where((q[1:] * q[:-1]).sum(-1) < 0, -1.0, 1.0)
    q[1:] *= np.cumprod(flip)[:, None]
    return q


def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()


def _slerp(q0: np.ndarray, q1: np.ndarray, a: np.ndarray) -> np.ndarray:
    dot = np.clip((q0 * q1).sum(-1), -1.0, 1.0)
    q1 = np.where(dot[:, None] < 0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(dot)
    s = np.sin(theta)
    small = s < 1e-8  # nearly equal rotations: lerp avoids 0/0
    w0 = np.where(small, 1 - a, np.sin((1 - a) * theta) / np.where(small, 1, s))
    w1 = np.where(small, a, np.sin(a * theta) / np.where(small, 1, s))
    q = w0[:, None] * q0 + w1[:, None] * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)
