"""Configuration dataclasses: one per scene type, one for training.

`SceneConfig` is what `scene.json` holds (DESIGN §6). It decides which parts of the
pipeline are built: Bayer filtering only when `bayer` is set, cylinder clipping only when
`cylinder` is set, the distortion path only when k1 or k2 is non-zero.

Units: times in integer microseconds, lengths in world units, angles in degrees,
colours in display space [0, 1] (the space the field renders and ground truth is stored in;
linear intensity is `c ** 2.2`, DESIGN §9).
"""

from __future__ import annotations

import dataclasses
import json
import math
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from .errors import InputError


@dataclass
class IntrinsicsConfig:
    """Pinhole intrinsics in pixels (OpenCV), radial distortion k1, k2."""

    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0


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
    """Density clip (supplement A.2): zero outside x² + z² ≤ radius², y_min ≤ y ≤ y_max."""

    radius: float = 0.25
    y_min: float = -0.35
    y_max: float = 0.15


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
        _check(self.intrinsics.fx > 0 and self.intrinsics.fy > 0, where, "intrinsics.fx/fy",
               "must be positive")
        _check(self.pos_threshold > 0 and self.neg_threshold > 0, where, "pos/neg_threshold",
               "must be positive")
        _check(self.t_end_us > self.t_start_us, where, "t_end_us", "must be after t_start_us")
        _check(self.n_views >= 2, where, "n_views", "must be at least 2")
        _check(len(self.aabb) == 6 and all(math.isfinite(a) for a in self.aabb), where, "aabb",
               "must be 6 finite numbers [xmin, ymin, zmin, xmax, ymax, zmax]")
        _check(all(self.aabb[i] < self.aabb[i + 3] for i in range(3)), where, "aabb",
               "min must be below max on every axis")
        tr = self.trajectory
        if tr.kind == "timed":
            _check(bool(tr.poses_file), where, "trajectory.poses_file", "is required for 'timed'")
        else:
            _check(tr.radius > 0 and tr.period_us > 0, where, "trajectory.radius/period_us",
                   "must be positive")
        if self.background is not None:
            _check(len(self.background) == 3, where, "background", "must be [r, g, b] or null")
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
        try:
            d = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise InputError(f"{path}: not valid JSON ({e})") from None
        if not isinstance(d, dict):
            raise InputError(f"{path}: top level must be an object")
        return cls.from_dict(d, str(path))

    def save(self, path: str | Path) -> Path:
        from .io import write_json

        path = Path(path)
        return write_json(path / "scene.json" if path.is_dir() else path, self.to_dict())


def _check(cond: bool, where: str, key: str, msg: str) -> None:
    if not cond:
        raise InputError(f"{where}: '{key}' {msg}")


def from_dict(cls: type, d: Any, where: str, prefix: str = "") -> Any:
    """Build dataclass `cls` from a JSON object, with one-line errors naming the key path."""
    if not isinstance(d, dict):
        raise InputError(f"{where}: '{prefix.rstrip('.') or cls.__name__}' must be an object")
    hints = typing.get_type_hints(cls)
    kwargs = {}
    names = {f.name for f in dataclasses.fields(cls)}
    for key in d:
        if key not in names:
            raise InputError(f"{where}: unknown key '{prefix}{key}'")
    for f in dataclasses.fields(cls):
        key = prefix + f.name
        if f.name not in d:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise InputError(f"{where}: missing key '{key}'")
            continue
        kwargs[f.name] = _coerce(hints[f.name], d[f.name], where, key)
    return cls(**kwargs)


def _coerce(tp: Any, v: Any, where: str, key: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if v is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _coerce(inner[0], v, where, key)
    if dataclasses.is_dataclass(tp):
        return from_dict(tp, v, where, key + ".")
    if origin is Literal:
        if v not in args:
            raise InputError(f"{where}: '{key}' must be one of {list(args)}, got {v!r}")
        return v
    if origin is list:
        if not isinstance(v, list):
            raise InputError(f"{where}: '{key}' must be a list")
        return [_coerce(args[0], x, where, f"{key}[{i}]") for i, x in enumerate(v)]
    if tp is bool:
        if not isinstance(v, bool):
            raise InputError(f"{where}: '{key}' must be true or false")
        return v
    if tp in (int, float):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise InputError(f"{where}: '{key}' must be a number, got {v!r}")
        if tp is int and float(v) != int(v):
            raise InputError(f"{where}: '{key}' must be an integer, got {v!r}")
        if not math.isfinite(v):
            raise InputError(f"{where}: '{key}' is not finite")
        return tp(v)
    if tp is str:
        if not isinstance(v, str):
            raise InputError(f"{where}: '{key}' must be a string")
        return v
    return v
