"""Rays in torch and chunked rendering through any Field (eval, viewer, render command).

Ray generation runs on the field's device: a per-pixel camera-direction table (H*W, 3) is
computed once per intrinsics (undistortion happens there, so distorted and pinhole cameras
cost the same per ray), and a ray is that direction rotated by its camera-to-world.
"""

from __future__ import annotations

import numpy as np
import torch

from .data.rig import Intrinsics
from .fields.base import Field, RenderOutput


def camera_directions(intrinsics: Intrinsics, device: str | torch.device = "cpu") -> torch.Tensor:
    """Camera-frame ray directions through every pixel centre, (H*W, 3) float32, z = 1.

    Row i is flat pixel i = y * width + x; the +0.5 pixel-centre offset and the radial
    undistortion (only when k1 or k2 is non-zero) are applied here once.
    """
    w, h = intrinsics.width, intrinsics.height
    pix = np.arange(w * h, dtype=np.int64)
    d = intrinsics.pixel_to_camera(pix % w + 0.5, pix // w + 0.5)
    return torch.from_numpy(d.astype(np.float32)).to(device)


def generate_rays(dirs_cam: torch.Tensor, c2w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World rays from camera directions.

    dirs_cam: (N, 3) camera-frame directions; c2w: (N, 4, 4) or (4, 4) camera-to-world.
    Returns rays_o (N, 3) world units and rays_d (N, 3) unit vectors, float32.
    """
    c2w = c2w.to(dirs_cam.dtype)
    if c2w.dim() == 2:
        d = dirs_cam @ c2w[:3, :3].T
        o = c2w[:3, 3].expand_as(d)
    else:
        d = torch.einsum("nij,nj->ni", c2w[:, :3, :3], dirs_cam)
        o = c2w[:, :3, 3]
    return o.contiguous(), torch.nn.functional.normalize(d, dim=-1)


def field_device(field: Field) -> torch.device:
    for p in field.parameters():
        return p.device
    for b in field.buffers():
        return b.device
    return torch.device("cpu")


def render_rays(
    field: Field,
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    *,
    near: float,
    background: torch.Tensor | None,
    train: bool = False,
    chunk: int = 16384,
) -> RenderOutput:
    """Render rays (R, 3) each in chunks of `chunk` rays; no autograd unless `train`.

    Per-ray outputs are concatenated; a scalar `distortion` is averaged weighted by chunk size.
    """
    n = rays_o.shape[0]
    outs = []
    with torch.set_grad_enabled(train and torch.is_grad_enabled()):
        for i in range(0, max(n, 1), chunk):
            o = field.render(
                rays_o[i : i + chunk],
                rays_d[i : i + chunk],
                near=near,
                background=background,
                train=train,
            )
            outs.append((min(chunk, n - i), o))
    if len(outs) == 1:
        return outs[0][1]
    merged: dict = {}
    for key, value in outs[0][1].items():
        if isinstance(value, torch.Tensor) and value.dim() > 0:
            merged[key] = torch.cat([o[key] for _, o in outs], 0)
        elif isinstance(value, torch.Tensor):
            merged[key] = sum(o[key] * m for m, o in outs) / max(n, 1)
        elif isinstance(value, (int, float)):
            merged[key] = sum(o[key] for _, o in outs)
    return merged  # type: ignore[return-value]


_DIRS_CACHE: dict = {}


def render_image(
    field: Field,
    c2w: np.ndarray,
    intrinsics: Intrinsics,
    *,
    near: float,
    background: torch.Tensor | np.ndarray | list | None,
    chunk: int = 16384,
) -> dict[str, torch.Tensor]:
    """Render one view: c2w (4, 4) camera-to-world (OpenCV), at `intrinsics`' size.

    Returns rgb (H, W, 3) display space, depth (H, W) world units, opacity (H, W); torch
    tensors on the field's device.
    """
    device = field_device(field)
    key = (intrinsics, str(device))
    dirs = _DIRS_CACHE.get(key)
    if dirs is None:
        if len(_DIRS_CACHE) > 8:
            _DIRS_CACHE.clear()
        dirs = _DIRS_CACHE[key] = camera_directions(intrinsics, device)
    c2w_t = torch.as_tensor(np.asarray(c2w, dtype=np.float32), device=device)
    rays_o, rays_d = generate_rays(dirs, c2w_t)
    if background is not None and not isinstance(background, torch.Tensor):
        background = torch.as_tensor(np.asarray(background, np.float32), device=device)
    was_training = field.training
    field.eval()
    try:
        out = render_rays(
            field, rays_o, rays_d, near=near, background=background, train=False, chunk=chunk
        )
    finally:
        field.train(was_training)
    h, w = intrinsics.height, intrinsics.width
    return {
        "rgb": out["rgb"].float().reshape(h, w, 3),
        "depth": out["depth"].float().reshape(h, w),
        "opacity": out["opacity"].float().reshape(h, w),
    }
