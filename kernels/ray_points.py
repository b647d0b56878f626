"""Sample points on packed rays, x = o[r] + t·d[r], with a per-ray backward.

The field evaluates its samples at points along the rays marched for them. When the rays
themselves are learnt (pose refinement, issue #20) the gradient of every sample's point must
be summed into its ray. Gathering with `index_select` leaves that sum to an atomic scatter of
every sample (`index_add_`), whose neighbouring threads hit the same ray's three words: on a
GPU that one scatter cost more than the field's MLPs. Samples are packed ray by ray
(`packed_info`, nerfacc's convention), so here one thread per ray walks its own slice and
writes its sum once: no atomics, no contention.

Slots that no packed slice covers (a fixed-capacity buffer's padding, `raymarch_fixed`) get
points like any other but pass no gradient to any ray; the field gives them none anyway.
"""

from __future__ import annotations

import torch
import warp as wp

from .common import as_float32, fast_view, init, launch

init()


@wp.kernel(enable_backward=False)
def _points_forward(
    rays_o: wp.array(dtype=wp.vec3),
    rays_d: wp.array(dtype=wp.vec3),
    t: wp.array(dtype=float),
    ray_indices: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3),
    dirs: wp.array(dtype=wp.vec3),
):
    i = wp.tid()
    r = ray_indices[i]
    d = rays_d[r]
    x[i] = rays_o[r] + t[i] * d
    dirs[i] = d


@wp.kernel(enable_backward=False)
def _points_backward(
    packed_info: wp.array2d(dtype=wp.int32),
    t: wp.array(dtype=float),
    grad_x: wp.array(dtype=wp.vec3),
    grad_dirs: wp.array(dtype=wp.vec3),
    grad_o: wp.array(dtype=wp.vec3),
    grad_d: wp.array(dtype=wp.vec3),
):
    r = wp.tid()
    start = packed_info[r, 0]
    go = wp.vec3()
    gd = wp.vec3()
    for i in range(start, start + packed_info[r, 1]):
        g = grad_x[i]
        go += g
        gd += t[i] * g + grad_dirs[i]
    grad_o[r] = go
    grad_d[r] = gd


class _RayPoints(torch.autograd.Function):
    @staticmethod
    def forward(ctx, rays_o, rays_d, t, ray_indices, packed_info):
        x = torch.empty(len(t), 3, dtype=torch.float32, device=t.device)
        dirs = torch.empty_like(x)
        launch(
            _points_forward,
            len(t),
            t,
            [
                fast_view(rays_o, wp.vec3),
                fast_view(rays_d, wp.vec3),
                t,
                ray_indices,
                fast_view(x, wp.vec3),
                fast_view(dirs, wp.vec3),
            ],
        )
        ctx.save_for_backward(t, packed_info)
        ctx.n_rays = len(rays_o)
        return x, dirs

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_x, grad_dirs):
        t, packed_info = ctx.saved_tensors
        grad_x = torch.zeros(len(t), 3, device=t.device) if grad_x is None else grad_x
        grad_dirs = torch.zeros_like(grad_x) if grad_dirs is None else grad_dirs
        grad_x, grad_dirs = as_float32(grad_x), as_float32(grad_dirs)
        grad_o = torch.empty(ctx.n_rays, 3, dtype=torch.float32, device=t.device)
        grad_d = torch.empty_like(grad_o)
        launch(
            _points_backward,
            ctx.n_rays,
            t,
            [
                packed_info,
                t,
                fast_view(grad_x, wp.vec3),
                fast_view(grad_dirs, wp.vec3),
                fast_view(grad_o, wp.vec3),
                fast_view(grad_d, wp.vec3),
            ],
        )
        return grad_o, grad_d, None, None, None


def ray_points(
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    t: torch.Tensor,
    ray_indices: torch.Tensor,
    packed_info: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Points and directions of packed samples, differentiable w.r.t. the rays.

    rays_o, rays_d: (R, 3) float32 origins (world units) and directions; t: (S,) float32
    distance of each sample along its ray (world units, per unit of |d|); ray_indices: (S,)
    int32 owner ray of each sample; packed_info: (R, 2) int32 (first sample, count) of each
    ray's slice (slots outside every slice get no gradient).
    Returns x (S, 3) = o[r] + t·d[r] and dirs (S, 3) = d[r], float32.
    """
    for name, v in (("rays_o", rays_o), ("rays_d", rays_d)):
        if v.ndim != 2 or v.shape[1] != 3 or v.dtype != torch.float32:
            raise ValueError(f"ray_points: {name} must be (R, 3) float32, got {tuple(v.shape)}")
    if t.ndim != 1 or ray_indices.shape != t.shape or ray_indices.dtype != torch.int32:
        raise ValueError("ray_points: t (S,) float32 and ray_indices (S,) int32 must match")
    if packed_info.shape != (len(rays_o), 2) or packed_info.dtype != torch.int32:
        raise ValueError(f"ray_points: packed_info must be ({len(rays_o)}, 2) int32")
    return _RayPoints.apply(
        rays_o.contiguous(),
        rays_d.contiguous(),
        as_float32(t),
        ray_indices.contiguous(),
        packed_info.contiguous(),
    )
