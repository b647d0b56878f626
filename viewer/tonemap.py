"""What the viewer shows of a rendered frame: exposure, depth / opacity colouring, 8-bit.

The exposure (a log-space gain, an offset in stops and a display gamma) is
`fastenerf.tonemap`'s, the one `fastenerf render` applies: a frame looks the same in the
viewer and in a rendered video. Everything runs in torch on the frame's device, before the
8-bit upload.
"""

from __future__ import annotations

import torch

from fastenerf.tonemap import DISPLAY_GAMMA, Exposure, apply_exposure, invert_exposure

__all__ = [
    "DISPLAY_GAMMA",
    "Exposure",
    "apply_exposure",
    "invert_exposure",
    "colormap_lut",
    "depth_range",
    "depth_to_rgb",
    "gray_to_rgb",
    "to_uint8",
]

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
