"""What the viewer shows of a rendered frame: exposure, depth / opacity colouring, 8-bit.

Events fix a scene's colours only up to exposure (DESIGN §3): the log intensity the field
learnt is right up to a gain and an offset. The exposure control therefore acts in log
space: `L = log(c**2.2 + eps)`, `L' = gain * L + ev * ln 2`, back to display space, then a
display gamma. All of it runs in torch on the frame's device, before the 8-bit upload.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

DISPLAY_GAMMA = 2.2  # linear intensity = c ** 2.2 (DESIGN §9)


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


_LUTS: dict[tuple[str, str], torch.Tensor] = {}


def colormap_lut(name: str = "turbo", device: torch.device | str = "cpu") -> torch.Tensor:
    """(256, 3) float32 colour table of matplotlib colormap `name`, on `device`."""
    key = (name, str(device))
    if key not in _LUTS:
        import matplotlib

        lut = matplotlib.colormaps[name](torch.linspace(0, 1, 256).numpy())[:, :3]
        _LUTS[key] = torch.as_tensor(lut, dtype=torch.float32, device=device)
    return _LUTS[key]


def depth_range(
    depth: torch.Tensor, opacity: torch.Tensor, min_opacity: float = 0.5
) -> tuple[float, float]:
    """Robust (1st, 99th percentile) range of the surface depth `depth / opacity`, world
    units, over pixels at least `min_opacity` opaque; (0, 1) when there are none."""
    mask = opacity > min_opacity
    if not bool(mask.any()):
        return 0.0, 1.0
    d = (depth[mask] / opacity[mask]).float()
    if d.numel() > 65536:  # quantile sorts: a strided subset is plenty for a display range
        d = d[:: d.numel() // 65536 + 1]
    lo, hi = torch.quantile(d, torch.tensor([0.01, 0.99], device=d.device)).tolist()
    return lo, max(hi, lo + 1e-6)


def depth_to_rgb(
    depth: torch.Tensor, opacity: torch.Tensor, lo: float, hi: float, cmap: str = "turbo"
) -> torch.Tensor:
    """Depth (H, W) world units (expected distance, i.e. weighted by opacity) -> (H, W, 3):
    the surface depth `depth / opacity` mapped lo..hi through `cmap`, faded by opacity."""
    d = depth / opacity.clamp_min(1e-6)
    u = ((d - lo) / max(hi - lo, 1e-12)).clamp(0.0, 1.0)
    lut = colormap_lut(cmap, depth.device)
    return lut[(u * 255.0 + 0.5).long()] * opacity.clamp(0.0, 1.0)[..., None]


def gray_to_rgb(x: torch.Tensor) -> torch.Tensor:
    """(H, W) in [0, 1] -> (H, W, 3)."""
    return x.clamp(0.0, 1.0)[..., None].expand(*x.shape, 3)


def to_uint8(img: torch.Tensor) -> torch.Tensor:
    """(H, W, 3) float in [0, 1] -> contiguous uint8, rounded to nearest (as io.write_image)."""
    return (torch.nan_to_num(img).clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8).contiguous()
