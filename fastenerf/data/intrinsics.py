"""Camera intrinsics files: read (K.txt in three layouts, or JSON) and write (JSON).

Read by `fastenerf import --intrinsics` and `fastenerf calibrate --intrinsics`; written by
`fastenerf calibrate --chequerboard` when it calibrates the lens itself. Pixel coordinates
follow the project's convention (pixel centres at +0.5, DESIGN §9): a K from OpenCV's own
pixel convention (centres at integers) has cx, cy 0.5 smaller.

Formats:
- text: 3x3 K (OpenCV), or the EventNeRF 4x4 / 5x4 file (5th row: k1 k2 0 0, their
  "division" distortion model);
- JSON: an object of `IntrinsicsConfig` fields, or one with such an object under
  "intrinsics" and optionally the image size ("width", "height") it was calibrated for,
  as `write_intrinsics` writes it.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from ..config import IntrinsicsConfig, from_dict
from ..errors import InputError


def read_intrinsics(path: str | Path, width: int, height: int) -> IntrinsicsConfig:
    """IntrinsicsConfig from `path` (see the module docstring), checked against a
    width x height sensor (pixels). One-line `InputError` naming the file on any problem."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: intrinsics file not found")
    if p.suffix == ".json":
        c = _read_json(p, width, height)
    else:
        c = _read_matrix(p)
    if not all(np.isfinite([c.fx, c.fy, c.cx, c.cy, c.k1, c.k2])):
        raise InputError(f"{p}: intrinsics must be finite numbers")
    if c.fx <= 0 or c.fy <= 0:
        raise InputError(f"{p}: focal lengths must be positive (fx={c.fx}, fy={c.fy})")
    if not (0 <= c.cx <= width and 0 <= c.cy <= height):
        raise InputError(
            f"{p}: principal point ({c.cx}, {c.cy}) lies outside the {width}x{height} sensor"
        )
    return c


def _read_json(p: Path, width: int, height: int) -> IntrinsicsConfig:
    try:
        d = json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{p}: not valid JSON ({e})") from None
    if isinstance(d, dict) and "intrinsics" in d:
        size = (d.get("width"), d.get("height"))
        if size != (None, None) and size != (width, height):
            raise InputError(
                f"{p}: calibrated for {size[0]}x{size[1]} images, but these are {width}x{height}"
            )
        return from_dict(IntrinsicsConfig, d["intrinsics"], str(p), "intrinsics.")
    return from_dict(IntrinsicsConfig, d, str(p))


def _read_matrix(p: Path) -> IntrinsicsConfig:
    try:
        vals = np.array([float(v) for v in p.read_text().split()], dtype=np.float64)
    except (ValueError, UnicodeDecodeError) as e:
        raise InputError(f"{p}: not a matrix of numbers ({e})") from None
    if len(vals) not in (9, 16, 20) or not np.all(np.isfinite(vals)):
        raise InputError(
            f"{p}: expected a 3x3, 4x4 or 5x4 matrix of finite numbers, found {len(vals)} numbers"
        )
    cols = 3 if len(vals) == 9 else 4
    m = vals.reshape(-1, cols)
    if abs(m[0, 1]) > 1e-9 or abs(m[1, 0]) > 1e-9 or np.abs(m[2, :3] - [0, 0, 1]).max() > 1e-9:
        raise InputError(f"{p}: K must be [fx 0 cx; 0 fy cy; 0 0 1] (no skew)")
    k1, k2 = (m[4, 0], m[4, 1]) if len(m) == 5 else (0.0, 0.0)
    return IntrinsicsConfig(
        fx=float(m[0, 0]),
        fy=float(m[1, 1]),
        cx=float(m[0, 2]),
        cy=float(m[1, 2]),
        k1=float(k1),
        k2=float(k2),
        distortion_model="eventnerf" if len(m) == 5 else "opencv",
    )


def write_intrinsics(
    path: str | Path, intr: IntrinsicsConfig, width: int, height: int, extra: dict | None = None
) -> Path:
    """Write `intr` for width x height images as JSON (atomically), readable by
    `read_intrinsics`; `extra` (e.g. the calibration's RMS error) is stored beside it."""
    from ..io import write_json

    return write_json(
        path,
        {"intrinsics": dataclasses.asdict(intr), "width": width, "height": height, **(extra or {})},
    )
