"""One viewer frame: render the field through the eval renderer, then shade it for display.

`render_raw` produces the renderer's own outputs (rgb, depth, opacity on the field's device);
`shade` turns them into the 8-bit image shown, per display mode. Keeping the two apart lets
the viewer re-shade a cached frame when only exposure or the mode's colouring changes.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from fastenerf.data.rig import Intrinsics
from fastenerf.fields.base import view_cone
from fastenerf.render import field_device, render_image

from .tonemap import Exposure, apply_exposure, depth_range, depth_to_rgb, gray_to_rgb, to_uint8

MODES = ("rgb", "depth", "opacity", "occupancy")


@dataclass
class ViewSettings:
    """What the viewer draws. near/far in world units along the unit ray; `background` (3,)
    display-space colour behind the field or None (black, no background term)."""

    mode: str = "rgb"
    exposure: Exposure = field(default_factory=Exposure)
    near: float = 1e-4
    far: float = 100.0
    background: tuple[float, float, float] | None = None
    depth_lo: float | None = None  # depth colouring range, world units; None: automatic
    depth_hi: float | None = None
    # rays per render call: on an H100 at 800x600 (trained ngp scene) 2^16 gave 35 fps, 2^18
    # 72 fps, 2^20 76 fps (render only; benchmarks/RESULTS.md): per-call overhead dominates
    chunk: int = 1 << 18
    # at least this cone angle while rendering (ngp; None: the field's own): a run trained with
    # cone 0 marches ~4x the samples of 1/256, instant-ngp's rendering default (RESULTS.md)
    cone_angle: float | None = 1.0 / 256


def render_raw(
    f, c2w: np.ndarray, intr: Intrinsics, s: ViewSettings, lock=None
) -> dict[str, torch.Tensor]:
    """Render one view: {rgb (H, W, 3), depth (H, W), opacity (H, W)} on the field's device.

    RGB / depth / opacity go through `fastenerf.render.render_image`, the renderer eval uses;
    "occupancy" marches the field's occupancy grid instead. `lock` (e.g. a Trainer's) is held
    for the whole render so that weights do not change under it.
    """
    dev = field_device(f)
    bg = (
        None
        if s.background is None
        else torch.tensor(s.background, dtype=torch.float32, device=dev)
    )
    with lock or contextlib.nullcontext(), torch.no_grad(), view_cone(s.cone_angle):
        if s.mode == "occupancy":
            return render_occupancy(f, c2w, intr, near=s.near, far=s.far, chunk=s.chunk)
        return render_image(
            f, np.asarray(c2w, np.float64), intr, near=s.near, background=bg, chunk=s.chunk
        )


def shade(raw: dict[str, torch.Tensor], s: ViewSettings, alpha: bool = False) -> torch.Tensor:
    """Renderer outputs -> (H, W, 3) uint8 display image on the same device; (H, W, 4) with
    an opaque alpha channel when `alpha` (GL drivers take RGBA uploads faster than RGB)."""
    if s.mode == "rgb":
        img = apply_exposure(raw["rgb"], s.exposure)
    elif s.mode == "opacity":
        img = gray_to_rgb(raw["opacity"])
    elif s.mode in ("depth", "occupancy"):
        lo, hi = s.depth_lo, s.depth_hi
        if lo is None or hi is None:
            alo, ahi = depth_range(raw["depth"], raw["opacity"])
            lo, hi = (alo if lo is None else lo), (ahi if hi is None else hi)
        img = depth_to_rgb(raw["depth"], raw["opacity"], lo, hi)
        if s.mode == "occupancy":  # checker by cell so that single cells can be told apart
            img = img * (0.65 + 0.35 * raw["cell_parity"][..., None])
    else:
        raise ValueError(f"unknown view mode {s.mode!r} (one of {MODES})")
    out = to_uint8(img)
    if alpha:
        out = torch.cat([out, torch.full_like(out[..., :1], 255)], -1)
    return out


def image_rays(intr: Intrinsics, c2w: np.ndarray, device) -> tuple[torch.Tensor, torch.Tensor]:
    """All rays of a view, (H*W, 3) each, float32 on `device`, flat pixel order y * W + x."""
    from fastenerf.render import camera_directions, generate_rays

    c2w_t = torch.as_tensor(np.asarray(c2w, np.float32), device=device)
    return generate_rays(camera_directions(intr, device), c2w_t)


def _occupied_fn(f):
    """x (N, 3) -> bool (N,): the ngp occupancy grid where the field has one; otherwise a
    density test (alpha over one 1/128 cell of the box above 1%)."""
    grid = getattr(f, "grid", None)
    if grid is not None and hasattr(grid, "occupied"):
        return grid.occupied
    box = f.aabb.detach().float()
    cell = float((box[3:] - box[:3]).max()) / 128.0

    def occupied(x):
        return f.density(x) * cell > 0.01

    return occupied


def render_occupancy(
    f,
    c2w: np.ndarray,
    intr: Intrinsics,
    *,
    near: float,
    far: float,
    chunk: int = 1 << 16,
    max_steps: int = 1024,
) -> dict[str, torch.Tensor]:
    """First occupied grid cell along each ray: {depth (H, W) world units, opacity (H, W)
    1 on a hit, cell_parity (H, W) in {0, 1}}. Samples every half cell inside the box."""
    dev = field_device(f)
    occupied = _occupied_fn(f)
    grid = getattr(f, "grid", None)
    if grid is not None and hasattr(grid, "occupied"):
        # march the grid's whole extent (all cascades) at cascade 0's finest cell
        box = torch.tensor(
            grid.outer_aabb() if hasattr(grid, "outer_aabb") else grid.aabb_list,
            dtype=torch.float32,
            device=dev,
        )
        a0 = torch.as_tensor(grid.aabb_list, dtype=torch.float32, device=dev)
        res = int(grid.resolution)
    else:
        box = a0 = f.aabb.detach().float().to(dev)
        res = 128
    cell = (a0[3:] - a0[:3]) / res
    step = float(cell.min()) * 0.5
    rays_o, rays_d = image_rays(intr, c2w, dev)
    depth = torch.zeros(len(rays_o), device=dev)
    hit = torch.zeros(len(rays_o), dtype=torch.bool, device=dev)
    parity = torch.zeros(len(rays_o), device=dev)
    for a in range(0, len(rays_o), max(1, chunk // 64)):
        o, d = rays_o[a : a + chunk // 64], rays_d[a : a + chunk // 64]
        inv = 1.0 / torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
        t0 = (box[:3] - o) * inv
        t1 = (box[3:] - o) * inv
        tmin = torch.minimum(t0, t1).amax(-1).clamp_min(near)
        tmax = torch.maximum(t0, t1).amin(-1).clamp_max(far)
        n = int(min(max_steps, math.ceil(float((tmax - tmin).clamp_min(0).max()) / step)))
        if n == 0:
            continue
        t = tmin[:, None] + (torch.arange(n, device=dev) + 0.5) * step  # (R, n)
        x = o[:, None] + t[..., None] * d[:, None]
        inside = t < tmax[:, None]
        occ = occupied(x.reshape(-1, 3)).reshape(t.shape) & inside
        any_hit = occ.any(-1)
        k = occ.float().argmax(-1)  # first True
        tk = t.gather(1, k[:, None])[:, 0]
        xk = o + tk[:, None] * d
        ijk = ((xk - a0[:3]) / cell).floor().long()
        depth[a : a + len(o)] = torch.where(any_hit, tk, 0.0)
        hit[a : a + len(o)] = any_hit
        parity[a : a + len(o)] = (ijk.sum(-1) % 2).float() * any_hit
    h, w = intr.height, intr.width
    return {
        "depth": depth.reshape(h, w),
        "opacity": hit.float().reshape(h, w),
        "cell_parity": parity.reshape(h, w),
        "rgb": torch.zeros(h, w, 3, device=dev),
    }
