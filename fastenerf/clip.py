"""The real-scene density clip (supplement A.2, DESIGN §9).

On a turntable the object stays inside the cylinder of the plate: density is forced to zero
outside `x² + z² ≤ r²`, `y_min ≤ y ≤ y_max` (world y is the turntable axis). Both field backends
and the mesh extractor use these helpers; boundaries count as inside, as in the reference.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from .config import CylinderConfig
from .errors import InputError

# CylinderConfig is the clip's type everywhere (scene, fields, mesh); a plain (radius, y_min,
# y_max) sequence is accepted by these helpers for numeric callers.
Cylinder = CylinderConfig | Sequence[float]


def cylinder_params(cyl: Cylinder) -> tuple[float, float, float]:
    """(radius, y_min, y_max) from a `CylinderConfig` or a (radius, y_min, y_max) sequence."""
    if isinstance(cyl, CylinderConfig):
        return float(cyl.radius), float(cyl.y_min), float(cyl.y_max)
    r, y0, y1 = (float(v) for v in cyl)
    return r, y0, y1


def cylinder_mask(x: torch.Tensor | np.ndarray, cyl: Cylinder) -> torch.Tensor | np.ndarray:
    """Which points lie inside the clip cylinder: x (N, 3) world units -> (N,) bool.

    Works on torch tensors (any device, autograd-free) and numpy arrays alike.
    """
    r, y0, y1 = cylinder_params(cyl)
    px, py, pz = x[..., 0], x[..., 1], x[..., 2]
    return (px * px + pz * pz <= r * r) & (py >= y0) & (py <= y1)


def clip_density(sigma: torch.Tensor, x: torch.Tensor, cyl: Cylinder | None) -> torch.Tensor:
    """σ (N,) with zeros outside the cylinder (σ unchanged when `cyl` is None).

    A `where`, not a multiply: a NaN or inf outside the cylinder must not leak through as NaN.
    """
    if cyl is None:
        return sigma
    return torch.where(
        cylinder_mask(x, cyl), sigma, torch.zeros((), dtype=sigma.dtype, device=sigma.device)
    )


def clip_aabb(aabb: Sequence[float], cyl: Cylinder | None) -> list[float]:
    """The box [xmin, ymin, zmin, xmax, ymax, zmax] shrunk to the cylinder's bounding box.

    Raises InputError (a ValueError) when they do not overlap (the clip would leave nothing).
    """
    box = [float(v) for v in aabb]
    if cyl is None:
        return box
    r, y0, y1 = cylinder_params(cyl)
    clipped = CylinderConfig(r, y0, y1).clip_box(box)
    lo, hi = clipped[:3], clipped[3:]
    if any(a >= b for a, b in zip(lo, hi, strict=True)):
        raise InputError(f"the clip cylinder (r={r}, y {y0}..{y1}) does not overlap the box {box}")
    return lo + hi
