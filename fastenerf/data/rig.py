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

# RGGB: R at (even row, even col), G at (even, odd) and (odd, even), B at (odd, odd).
BAYER_RGGB = np.array([[0, 1], [1, 2]], dtype=np.int64)


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels with radial distortion (k1, k2)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    k1: float = 0.0
    k2: float = 0.0

    @classmethod
    def from_config(cls, c: IntrinsicsConfig, width: int, height: int) -> Intrinsics:
        return cls(c.fx, c.fy, c.cx, c.cy, width, height, c.k1, c.k2)

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
        return Intrinsics(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, w, h,
                          self.k1, self.k2)

    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Normalised undistorted (N, 2) -> normalised distorted (N, 2)."""
        r2 = (xy**2).sum(-1, keepdims=True)
        return xy * (1.0 + self.k1 * r2 + self.k2 * r2**2)

    def undistort(self, xy_d: np.ndarray, iters: int = 20) -> np.ndarray:
        """Normalised distorted (N, 2) -> undistorted, by fixed-point iteration (as OpenCV)."""
        xy = xy_d.copy()
        for _ in range(iters):
            r2 = (xy**2).sum(-1, keepdims=True)
            xy = xy_d / (1.0 + self.k1 * r2 + self.k2 * r2**2)
        return xy

    def pixel_to_camera(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N,) each (pixel centres are at +0.5) -> camera ray dirs (N, 3), z=1."""
        xy = np.stack([(np.asarray(u, np.float64) - self.cx) / self.fx,
                       (np.asarray(v, np.float64) - self.cy) / self.fy], -1)
        if self.distorted:
            xy = self.undistort(xy)
        return np.concatenate([xy, np.ones_like(xy[:, :1])], -1)

    def project(self, p_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3), z > 0 -> pixel coordinates (N, 2)."""
        xy = p_cam[:, :2] / p_cam[:, 2:3]
        if self.distorted:
            xy = self.distort(xy)
        return np.stack([xy[:, 0] * self.fx + self.cx, xy[:, 1] * self.fy + self.cy], -1)


class TimedPoses:
    """pose(t) from timed samples: rotation slerp, translation lerp; clamped at the ends."""

    def __init__(self, t_us: np.ndarray, c2w: np.ndarray, source: str = "poses"):
        t_us = np.asarray(t_us)
        c2w = np.asarray(c2w, dtype=np.float64)
        if c2w.ndim != 3 or c2w.shape[1:] not in ((4, 4), (3, 4)):
            raise InputError(f"{source}: poses must be (M, 4, 4) or (M, 3, 4), got {c2w.shape}")
        if len(t_us) != len(c2w):
            raise InputError(f"{source}: {len(c2w)} poses but {len(t_us)} timestamps")
        if len(c2w) == 0:
            raise InputError(f"{source}: no poses")
        if not np.all(np.isfinite(c2w)):
            i = int(np.flatnonzero(~np.isfinite(c2w).reshape(len(c2w), -1).all(1))[0])
            raise InputError(f"{source}: pose {i} contains NaN or inf")
        if np.any(np.diff(t_us) <= 0):
            raise InputError(f"{source}: pose timestamps must increase strictly")
        R = c2w[:, :3, :3]
        if np.abs(np.einsum("nij,nik->njk", R, R) - np.eye(3)).max() > 1e-3:
            raise InputError(f"{source}: a pose's rotation is not orthonormal")
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
        p = np.stack([np.sin(th) * np.cos(el), np.full_like(th, np.sin(el)),
                      np.cos(th) * np.cos(el)], -1) * c.radius
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
    """Intrinsics + trajectory + colour filter of one capture."""

    intrinsics: Intrinsics
    trajectory: TimedPoses | Turntable
    bayer: str | None

    @classmethod
    def from_scene(cls, cfg: SceneConfig, folder: str | Path | None = None) -> Rig:
        intr = Intrinsics.from_config(cfg.intrinsics, cfg.width, cfg.height)
        tr = cfg.trajectory
        if tr.kind == "timed":
            path = Path(folder or ".") / tr.poses_file
            from .formats.native import load_poses

            t, c2w = load_poses(path)
            traj = TimedPoses(t, c2w, source=str(path))
        else:
            traj = Turntable(tr)
        return cls(intr, traj, cfg.bayer)

    def pose(self, t_us) -> np.ndarray:
        """Camera-to-world (N, 4, 4) float64 at times (N,) µs."""
        return self.trajectory(t_us)

    def channel(self, pix: np.ndarray | torch.Tensor):
        """Colour channel (0 R, 1 G, 2 B) seen by flat pixels `pix` (N,); None on a mono sensor."""
        if self.bayer is None:
            return None
        w = self.intrinsics.width
        lib = torch if isinstance(pix, torch.Tensor) else np
        y, x = pix // w, pix % w
        table = BAYER_RGGB if lib is np else torch.as_tensor(BAYER_RGGB, device=pix.device)
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
    for i in range(1, len(q)):  # keep neighbours in one hemisphere so slerp takes the short way
        if np.dot(q[i], q[i - 1]) < 0:
            q[i] = -q[i]
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
