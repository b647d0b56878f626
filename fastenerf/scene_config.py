"""The scene's configuration: what `scene.json` holds (DESIGN §6).

`SceneConfig` decides which parts of the pipeline are built: Bayer filtering only when `bayer`
is set, cylinder clipping only when `cylinder` is set, the distortion path only when k1 or k2 is
non-zero. Units: times in integer µs, lengths in world units, angles in degrees, colours in
display space [0, 1] (what the field renders and ground truth is stored in; linear intensity is
`c ** 2.2`, DESIGN §9). `fastenerf.config` re-exports these beside the training configuration.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from .errors import InputError
from .schema import check as _check
from .schema import from_dict


@dataclass
class IntrinsicsConfig:
    """Pinhole intrinsics in pixels (OpenCV), radial distortion k1, k2.

    `distortion_model` says what k1, k2 mean on normalised coordinates (r² = x² + y²):
      "opencv":    x_d = x_u · (1 + k1 r_u² + k2 r_u⁴)  (OpenCV's radial terms)
      "eventnerf": x_u = x_d / (1 + k1 r_d² + k2 r_d⁴)  (the EventNeRF authors' ray code,
                   so their released k1, k2 give exactly their rays)
    """

    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    distortion_model: Literal["opencv", "eventnerf"] = "opencv"


@dataclass
class TrajectoryConfig:
    """Camera pose as a function of time.

    kind "timed": `poses_file` (relative to the scene folder) is an npz with `t` (M,) int64 µs
    and `c2w` (M, 4, 4) float64, OpenCV camera-to-world; poses between samples are slerped.
    kind "turntable": the camera moves uniformly on a circle of `radius` around `center`
    looking at it, `elevation_deg` above the circle's plane, the plane tilted by `tilt_deg`
    about the world x axis (supplement A.1), one revolution per `period_us`, starting at
    `phase_deg` at time `t0_us`. The rotation axis is world +y.
    """

    kind: Literal["timed", "turntable"] = "turntable"
    poses_file: str | None = None
    radius: float = 4.0
    center: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    tilt_deg: float = 0.0
    elevation_deg: float = 0.0
    period_us: int = 1_000_000
    phase_deg: float = 0.0
    t0_us: int = 0
    clockwise: bool = False


@dataclass
class CylinderConfig:
    """Density clip (supplement A.2): zero outside x² + z² ≤ radius², y_min ≤ y ≤ y_max (world
    units, y the turntable axis); of both field backends, the occupancy grid and the mesher."""

    radius: float = 0.25
    """Radius about the world y axis, world units."""
    y_min: float = -0.35
    """Bottom of the cylinder (world y)."""
    y_max: float = 0.15
    """Top of the cylinder (world y)."""

    @classmethod
    def parse(cls, text: str, where: str = "--cylinder") -> CylinderConfig | None:
        """ "R,YMIN,YMAX" -> CylinderConfig; "none" / "off" -> None (no clip)."""
        if text.strip().lower() in ("none", "off"):
            return None
        parts = [p for p in text.replace(" ", ",").split(",") if p]
        try:
            r, y0, y1 = (float(p) for p in parts)
        except ValueError:
            raise InputError(
                f"{where}: expected R,YMIN,YMAX (three numbers, world units) or none, got {text!r}"
            ) from None
        cyl = cls(r, y0, y1)
        cyl.check(where)
        return cyl

    def check(self, where: str) -> None:
        """One line unless the values are finite with radius > 0 and y_min < y_max."""
        vals = (self.radius, self.y_min, self.y_max)
        if not all(math.isfinite(v) for v in vals):
            raise InputError(f"{where}: cylinder values must be finite, got {vals}")
        if not (self.radius > 0 and self.y_min < self.y_max):
            raise InputError(
                f"{where}: 'cylinder' needs radius > 0 and y_min < y_max, got r={self.radius:g}, "
                f"y {self.y_min:g}..{self.y_max:g}"
            )

    def bounding_box(self) -> list[float]:
        """[xmin, ymin, zmin, xmax, ymax, zmax] of the cylinder, world units."""
        r = self.radius
        return [-r, self.y_min, -r, r, self.y_max, r]

    def clip_box(self, box) -> list[float]:
        """The box [xmin, ymin, zmin, xmax, ymax, zmax] shrunk to the cylinder's bounding box
        (empty where they do not overlap: some min >= its max)."""
        b, cb = [float(v) for v in box], self.bounding_box()
        return [max(b[i], cb[i]) for i in range(3)] + [min(b[i], cb[i]) for i in range(3, 6)]


# The EventNeRF authors' released real scenes (their `nextnextgen/` configs, DESIGN §9): radius
# 0.25 and y_max 0.195 for all, y_min and event threshold per scene. Applied when an EventNeRF
# real-capture folder of that name is read.
EVENTNERF_REAL_Y_MIN = {
    "bottle": -0.14,
    "chicken": -0.08,
    "controller": -0.04,
    "cube": 0.045,
    "dragon": -0.15,
    "microphone": -0.14,
    "multimeter": -0.06,
    "plant": -0.065,
    "tapes": -0.12,
}
EVENTNERF_REAL_THRESHOLD = {"cube": 0.20}  # every other released scene: 0.10


def eventnerf_real_cylinder(name: str) -> CylinderConfig | None:
    """The clip of the authors' released real scene `name` (case-insensitive), else None."""
    y_min = EVENTNERF_REAL_Y_MIN.get(name.lower())
    return None if y_min is None else CylinderConfig(0.25, y_min, 0.195)


@dataclass
class SceneConfig:
    """Everything about one capture that is not the events themselves (scene.json)."""

    name: str
    width: int
    height: int
    intrinsics: IntrinsicsConfig
    trajectory: TrajectoryConfig
    bayer: Literal["rggb"] | None = "rggb"
    pos_threshold: float = 0.25
    neg_threshold: float = 0.25
    polarity_offset: float = 0.0
    time_unit: Literal["us"] = "us"
    t_start_us: int = 0
    t_end_us: int = 1_000_000
    n_views: int = 1000
    loop: bool = True
    aabb: list[float] = field(default_factory=lambda: [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0])
    near: float = 1e-4
    cylinder: CylinderConfig | None = None
    background: list[float] | None = field(default_factory=lambda: [0.0, 0.0, 0.0])
    events_file: str = "events.npz"
    sim_log_eps: float | None = None
    kind: Literal["synthetic", "real"] = "synthetic"

    @property
    def mono(self) -> bool:
        return self.bayer is None

    def validate(self, where: str = "scene.json") -> SceneConfig:
        """Check values that types alone cannot; raise `InputError` naming the key."""
        _check(self.width > 0 and self.height > 0, where, "width/height", "must be positive")
        _check(self.bayer in (None, "rggb"), where, "bayer", "must be 'rggb' or null")
        for k in ("fx", "fy", "cx", "cy", "k1", "k2"):
            v = getattr(self.intrinsics, k)
            _check(math.isfinite(v), where, f"intrinsics.{k}", f"is not finite ({v})")
        ok = self.intrinsics.fx > 0 and self.intrinsics.fy > 0
        _check(ok, where, "intrinsics.fx/fy", "must be positive")
        ok = self.pos_threshold > 0 and self.neg_threshold > 0
        _check(ok, where, "pos/neg_threshold", "must be positive")
        _check(self.t_end_us > self.t_start_us, where, "t_end_us", "must be after t_start_us")
        _check(self.n_views >= 2, where, "n_views", "must be at least 2")
        from .memory import check_memory, views_bytes  # the window grid holds n_views poses

        check_memory(views_bytes(self.n_views), f"{where}: n_views {self.n_views:,}")
        ok = len(self.aabb) == 6 and all(math.isfinite(a) for a in self.aabb)
        _check(ok, where, "aabb", "must be 6 finite numbers [xmin, ymin, zmin, xmax, ymax, zmax]")
        ok = all(self.aabb[i] < self.aabb[i + 3] for i in range(3))
        _check(ok, where, "aabb", "min must be below max on every axis")
        tr = self.trajectory
        _check(
            len(tr.center) == 3 and all(math.isfinite(c) for c in tr.center),
            where,
            "trajectory.center",
            f"must be 3 finite numbers [x, y, z], got {tr.center}",
        )
        if tr.kind == "timed":
            _check(bool(tr.poses_file), where, "trajectory.poses_file", "is required for 'timed'")
        else:
            ok = tr.radius > 0 and tr.period_us > 0
            _check(ok, where, "trajectory.radius/period_us", "must be positive")
            # at ±90° the camera looks along the turntable axis: look-at has no "up"
            _check(
                abs(tr.elevation_deg) < 90,
                where,
                "trajectory.elevation_deg",
                "must be strictly between -90 and 90",
            )
        if self.background is not None:
            _check(len(self.background) == 3, where, "background", "must be [r, g, b] or null")
        _check(self.near >= 0, where, "near", "must not be negative")
        if self.cylinder is not None:
            self.cylinder.check(where)
            c = self.cylinder.clip_box(self.aabb)
            _check(
                all(c[i] < c[i + 3] for i in range(3)),
                where,
                "cylinder",
                f"does not overlap the box {self.aabb} (the clip would leave nothing)",
            )
        return self

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str = "scene.json") -> SceneConfig:
        return from_dict(cls, d, where).validate(where)

    @classmethod
    def load(cls, path: str | Path) -> SceneConfig:
        """Read and validate a scene.json; every problem is one line naming the file and key."""
        path = Path(path)
        if path.is_dir():
            path = path / "scene.json"
        if not path.is_file():
            raise InputError(f"{path}: no scene.json here (is this a scene folder?)")
        from .io import read_json_object

        return cls.from_dict(read_json_object(path), str(path))

    def save(self, path: str | Path) -> Path:
        from .io import write_json

        path = Path(path)
        return write_json(path / "scene.json" if path.is_dir() else path, self.to_dict())
