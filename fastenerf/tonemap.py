"""Exposure of rendered colours: one tone map for `fastenerf render`, its videos and the viewer.

Events fix a scene's colours only up to exposure (DESIGN §3): the log intensity the field
learnt is right up to a gain and an offset. The exposure control therefore acts in log
space: `L = log(c**2.2 + eps)`, `L' = gain * L + ev * ln 2`, back to display space, then a
display gamma. It runs in torch on the frame's device.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .errors import InputError

DISPLAY_GAMMA = 2.2  # linear intensity = c ** 2.2 (DESIGN §9)

# What a user can ask for: beyond these a frame is all black or all white (2^±24 in
# intensity; gain and gamma a factor of 100 either way).
EV_RANGE = (-24.0, 24.0)
GAIN_RANGE = (0.01, 100.0)
GAMMA_RANGE = (0.01, 100.0)


@dataclass
class Exposure:
    """Log-space gain (contrast, > 0), offset in stops (`ev`), display gamma (> 0).

    `eps` keeps log(0) finite; at the defaults the map is the identity up to float rounding.
    """

    gain: float = 1.0
    ev: float = 0.0
    gamma: float = 1.0
    eps: float = 1e-4

    @property
    def is_identity(self) -> bool:
        return self.gain == 1.0 and self.ev == 0.0 and self.gamma == 1.0

    def validated(self, where: str = "exposure") -> Exposure:
        """`self`, or `InputError` naming the first value that is NaN, inf or out of range."""
        for name, v, (lo, hi) in (
            ("ev", self.ev, EV_RANGE),
            ("gain", self.gain, GAIN_RANGE),
            ("gamma", self.gamma, GAMMA_RANGE),
        ):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi):
                raise InputError(f"{where}: {name} must be a number in [{lo:g}, {hi:g}], got {v}")
        return self


def apply_exposure(rgb: torch.Tensor, e: Exposure) -> torch.Tensor:
    """Display-space colours (..., 3) in [0, 1] -> exposed display colours in [0, 1].

    Strictly increasing in each channel for gain, gamma > 0, until it clips at 0 or 1.
    """
    if e.is_identity:
        return rgb.clamp(0.0, 1.0)
    L = torch.log(rgb.clamp_min(0.0) ** DISPLAY_GAMMA + e.eps)
    lin = (torch.exp(e.gain * L + e.ev * math.log(2.0)) - e.eps).clamp_min(0.0)
    out = lin ** (1.0 / DISPLAY_GAMMA)
    if e.gamma != 1.0:
        out = out ** (1.0 / e.gamma)
    return out.clamp(0.0, 1.0)


def invert_exposure(out: torch.Tensor, e: Exposure) -> torch.Tensor:
    """Inverse of `apply_exposure` on its unclipped range: exposed colours -> the field's."""
    lin = out.clamp_min(0.0) ** (e.gamma * DISPLAY_GAMMA)
    L = (torch.log(lin + e.eps) - e.ev * math.log(2.0)) / e.gain
    return (torch.exp(L) - e.eps).clamp_min(0.0) ** (1.0 / DISPLAY_GAMMA)
