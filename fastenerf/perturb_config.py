"""The robustness studies' perturbations of the training data, as configuration.

A section of the training configuration (`TrainConfig.perturb`); the perturbations themselves
are `fastenerf.perturb`'s.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from .schema import check as _check
from .schema import from_dict


@dataclass
class PerturbConfig:
    """What is done to a scene's training data before training (RUN/config.json records it).

    Only the training rig and events change; the test views stay exact. All zeros is the
    identity (the clean scene).
    """

    pose_error_deg: float = 0.0
    """Degrees: every training pose's rotation is turned by exactly this angle about its own
    random axis (uniform on the sphere), about the camera centre (supplement I). In [0, 180)."""

    noise_fraction: float = 0.0
    """Uniformly random events (x, y, t, polarity ±1) added to the training stream, their
    number this fraction of the clean stream's count (0.05 = 5 %; supplement J). In [0, 10]."""

    seed: int = 0
    """Seed of the perturbations (pose axes, noise events); independent of the training seed,
    so runs at one level with other training seeds see the same perturbed data."""

    mount_error_deg: float = 0.0
    """Degrees: every training pose's rotation is turned by exactly this angle about ONE shared
    random axis in the camera's own frame (c2w · M, a camera mis-mounted), about the camera
    centre; before the per-pose turn when both are set. In [0, 180)."""

    @property
    def active(self) -> bool:
        """True when anything is perturbed (False: the clean scene, the identity)."""
        levels = (self.pose_error_deg, self.mount_error_deg, self.noise_fraction)
        return any(v != 0.0 for v in levels)

    def validate(self, where: str = "perturb") -> PerturbConfig:
        import numbers  # here, not at the top: this section is appended to a shared file

        for key in ("pose_error_deg", "mount_error_deg", "noise_fraction"):
            v = getattr(self, key)
            ok = isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v)
            _check(ok, where, key, f"must be a finite number, got {v!r}")
        for key in ("pose_error_deg", "mount_error_deg"):
            v = getattr(self, key)
            _check(0.0 <= v < 180.0, where, key, f"must be in [0, 180) degrees, got {v}")
        _check(
            0.0 <= self.noise_fraction <= 10.0,
            where,
            "noise_fraction",
            f"must be in [0, 10] (a fraction of the clean count), got {self.noise_fraction}",
        )
        _check(
            isinstance(self.seed, numbers.Integral)
            and not isinstance(self.seed, bool)
            and self.seed >= 0,
            where,
            "seed",
            f"must be a non-negative integer, got {self.seed!r}",
        )
        return self

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str = "perturb") -> PerturbConfig:
        return from_dict(cls, d, where).validate(where)
