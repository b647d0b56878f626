"""Orbit camera for the viewer: orbit / pan / zoom about a target, pure numpy.

The state is the camera-to-world matrix itself (OpenCV: x right, y down, z forward) plus the
distance to the orbit target along +z, so that snapping to a training pose reproduces that
pose's c2w bit for bit (its image too), roll included. Orbiting turns about the scene's up
axis (yaw) and the camera's right axis (pitch), which keeps a level camera level.

Also here: the viewer's pinhole intrinsics from a field of view, and camera-path files
(what the viewer records and `fastenerf render --path` plays back).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fastenerf.data.rig import Intrinsics, look_at
from fastenerf.errors import InputError

# Pitch stops this far from the up/down poles: at the pole the yaw axis and the view axis
# coincide and yaw would spin the image about its centre instead of orbiting.
POLE_MARGIN_DEG = 1.0
MIN_DISTANCE = 1e-3


def rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """(3, 3) rotation by `angle` radians about unit `axis` (3,) (Rodrigues)."""
    a = np.asarray(axis, np.float64)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * (K @ K)


def _orthonormalise(R: np.ndarray) -> np.ndarray:
    """Nearest rotation to R (3, 3): repeated small rotations drift off SO(3)."""
    u, _, vt = np.linalg.svd(R)
    out = u @ vt
    if np.linalg.det(out) < 0:
        u[:, -1] *= -1
        out = u @ vt
    return out


@dataclass
class OrbitCamera:
    """A camera orbiting `target` at `distance` world units; `up` (3,) unit is the scene's up.

    c2w: (4, 4) float64 OpenCV camera-to-world. The target is `eye + distance * forward`.
    """

    c2w: np.ndarray
    distance: float
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    home: tuple[np.ndarray, float] | None = None

    def __post_init__(self):
        self.c2w = np.array(self.c2w, np.float64)
        self.up = np.asarray(self.up, np.float64) / np.linalg.norm(self.up)
        self.distance = max(float(self.distance), MIN_DISTANCE)
        if self.home is None:
            self.home = (self.c2w.copy(), self.distance)

    @classmethod
    def looking_at(cls, eye, target, up=(0.0, 1.0, 0.0)) -> OrbitCamera:
        """A level camera at `eye` (3,) looking at `target` (3,), world units."""
        eye, target = np.asarray(eye, np.float64), np.asarray(target, np.float64)
        return cls(look_at(eye, target, up)[0], float(np.linalg.norm(target - eye)), up)

    @property
    def eye(self) -> np.ndarray:
        return self.c2w[:3, 3].copy()

    @property
    def forward(self) -> np.ndarray:
        return self.c2w[:3, 2].copy()

    @property
    def target(self) -> np.ndarray:
        return self.c2w[:3, 3] + self.distance * self.c2w[:3, 2]

    def orbit(self, yaw: float, pitch: float) -> None:
        """Turn the camera about the target: `yaw` radians about `up`, `pitch` about the
        camera's right axis (positive pitch moves the eye up, looking down more)."""
        target = self.target
        # Clamp pitch so that the view direction stays POLE_MARGIN_DEG away from ±up.
        down = math.asin(float(np.clip(-self.forward @ self.up, -1.0, 1.0)))  # >0: looks down
        lim = math.radians(90.0 - POLE_MARGIN_DEG)
        pitch = float(np.clip(down + pitch, -lim, lim)) - down
        R = rotation(self.up, yaw)
        if pitch != 0.0:
            R = R @ rotation(self.c2w[:3, 0], -pitch)
        rot = _orthonormalise(R @ self.c2w[:3, :3])
        self.c2w[:3, :3] = rot
        self.c2w[:3, 3] = target - self.distance * rot[:, 2]

    def pan(self, dx: float, dy: float) -> None:
        """Slide eye and target together by (dx, dy) × distance along the camera's x and y
        (image right and down): a drag of dx pixels is `pan(dx / fx, dy / fy)` to follow the
        mouse at the target's depth."""
        self.c2w[:3, 3] -= self.distance * (dx * self.c2w[:3, 0] + dy * self.c2w[:3, 1])

    def zoom(self, factor: float) -> None:
        """Scale the distance to the target by `factor` (> 0); the target stays put."""
        target = self.target
        self.distance = max(self.distance * float(factor), MIN_DISTANCE)
        self.c2w[:3, 3] = target - self.distance * self.c2w[:3, 2]

    def reset(self) -> None:
        c2w, dist = self.home
        self.c2w, self.distance = c2w.copy(), dist

    def snap(self, poses: np.ndarray, pivot: np.ndarray | None = None) -> int:
        """Jump to the pose of `poses` (M, 4, 4) nearest this camera; return its index.

        Nearest: smallest eye distance plus (angle between view directions × distance to
        the target), so that poses at one spot looking elsewhere lose. The c2w becomes that
        pose exactly; the orbit target is the point on its view axis closest to `pivot`
        (3,) (default: the current target).
        """
        poses = np.asarray(poses, np.float64)
        if poses.ndim != 3 or len(poses) == 0:
            raise InputError("snap: no poses to snap to")
        d_eye = np.linalg.norm(poses[:, :3, 3] - self.eye, axis=-1)
        cos = np.clip(poses[:, :3, 2] @ self.forward, -1.0, 1.0)
        i = int(np.argmin(d_eye + np.arccos(cos) * self.distance))
        self.set_pose(poses[i], pivot)
        return i

    def set_pose(self, c2w: np.ndarray, pivot: np.ndarray | None = None) -> None:
        """Take `c2w` (4, 4) exactly; orbit about the point of its axis nearest `pivot`."""
        pivot = self.target if pivot is None else np.asarray(pivot, np.float64)
        self.c2w = np.array(c2w, np.float64)
        self.distance = max(float((pivot - self.c2w[:3, 3]) @ self.c2w[:3, 2]), MIN_DISTANCE)


def intrinsics_for_fov(width: int, height: int, fov_y_deg: float) -> Intrinsics:
    """Undistorted pinhole intrinsics (width × height pixels) with vertical field of view
    `fov_y_deg` degrees, square pixels, principal point at the image centre."""
    fy = 0.5 * height / math.tan(math.radians(fov_y_deg) / 2)
    return Intrinsics(fy, fy, width / 2, height / 2, int(width), int(height))


def fov_y_of(intr: Intrinsics) -> float:
    """Vertical field of view of `intr` in degrees."""
    return math.degrees(2 * math.atan(0.5 * intr.height / intr.fy))


def scene_up(cfg) -> np.ndarray:
    """The scene's up axis (3,): world +y, or the turntable's tilted axis (supplement A.1)."""
    tr = getattr(cfg, "trajectory", None)
    if tr is not None and tr.kind == "turntable" and tr.tilt_deg:
        a = math.radians(tr.tilt_deg)
        return np.array([0.0, math.cos(a), math.sin(a)])  # R_x(tilt) @ +y
    return np.array([0.0, 1.0, 0.0])


# ---- camera paths -------------------------------------------------------------------------


def intrinsics_dict(intr: Intrinsics) -> dict:
    return {
        "fx": intr.fx,
        "fy": intr.fy,
        "cx": intr.cx,
        "cy": intr.cy,
        "width": intr.width,
        "height": intr.height,
        "k1": intr.k1,
        "k2": intr.k2,
        "model": intr.model,
    }


def save_camera_path(
    path: str | Path, frames: list[tuple[np.ndarray, Intrinsics]], fps: float = 30.0
) -> Path:
    """Write a camera path JSON (atomically): `{"fps", "frames": [{"c2w": 4×4, "intrinsics":
    {fx, fy, cx, cy, width, height, k1, k2, model}}]}`, OpenCV c2w, world units, pixels."""
    from fastenerf.io import write_json

    return write_json(
        path,
        {
            "format": "fastenerf-camera-path",
            "version": 1,
            "fps": fps,
            "frames": [
                {"c2w": np.asarray(c, np.float64).tolist(), "intrinsics": intrinsics_dict(k)}
                for c, k in frames
            ],
        },
    )


def load_camera_path(path: str | Path) -> list[tuple[np.ndarray, Intrinsics | None]]:
    """Read a camera path or a single pose.

    Accepts what `save_camera_path` writes, a bare 4×4 list, `{"c2w": 4×4[, "intrinsics"]}`,
    or a list of 4×4s. Returns [(c2w (4, 4) float64, Intrinsics or None)].
    """
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: camera path file not found") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: not valid JSON ({e})") from None
    if isinstance(d, dict) and "frames" in d:
        items = d["frames"]
    elif isinstance(d, dict) or (isinstance(d, list) and np.asarray(d, dtype=object).ndim == 2):
        items = [d]
    else:
        items = d
    if not isinstance(items, list) or not items:
        raise InputError(f"{path}: no camera frames")
    out = []
    for i, it in enumerate(items):
        c2w = it.get("c2w") if isinstance(it, dict) else it
        try:
            c2w = np.asarray(c2w, np.float64)
        except (TypeError, ValueError):
            raise InputError(f"{path}: frame {i}: c2w is not a 4x4 matrix of numbers") from None
        if c2w.shape == (3, 4):
            c2w = np.vstack([c2w, [0, 0, 0, 1]])
        if c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
            raise InputError(f"{path}: frame {i}: c2w must be a finite 4x4 (or 3x4) matrix")
        R = c2w[:3, :3]
        if np.abs(R.T @ R - np.eye(3)).max() > 1e-3:
            raise InputError(f"{path}: frame {i}: c2w rotation is not orthonormal")
        intr = None
        if isinstance(it, dict) and it.get("intrinsics") is not None:
            k = it["intrinsics"]
            try:
                intr = Intrinsics(
                    float(k["fx"]),
                    float(k["fy"]),
                    float(k["cx"]),
                    float(k["cy"]),
                    int(k["width"]),
                    int(k["height"]),
                    float(k.get("k1", 0.0)),
                    float(k.get("k2", 0.0)),
                    str(k.get("model", "opencv")),
                )
            except (KeyError, TypeError, ValueError) as e:
                raise InputError(f"{path}: frame {i}: bad intrinsics ({e})") from None
        out.append((c2w, intr))
    return out
