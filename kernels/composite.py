"""Front-to-back volume compositing over packed samples, and the mip-NeRF 360 distortion loss.

Packed-sample convention (as nerfacc): the samples of ray r are contiguous at
``[packed_info[r, 0], packed_info[r, 0] + packed_info[r, 1])``, ordered by t along the ray.

    alpha_i = 1 - exp(-sigma_i * delta_i)          delta_i = t_end_i - t_start_i
    T_i     = prod_{j<i} (1 - alpha_j)             w_i = T_i * alpha_i
    rgb     = sum_i w_i c_i + (1 - opacity) * bg   opacity = sum_i w_i
    depth   = sum_i w_i (t_start_i + t_end_i) / 2  (un-normalised: divide by opacity for the
                                                   expected depth of the visible surface)

A ray stops at the first sample whose incoming transmittance T_i is below `T_MIN` (1e-4); that
sample and all after it get weight 0 and zero gradient, in forward and backward alike.

The backward pass walks each ray's samples again (instant-ngp / torch-ngp `composite_rays_train`):
every output is linear in the weights, so with the per-sample "effective weight gradient"
``e_i = <g_rgb, c_i - bg> + g_depth * z_i + g_opacity + g_w_i`` the gradient is

    dL/dsigma_i = delta_i * (e_i * T_{i+1} - sum_{j>i} e_j w_j)

and the suffix sum is the ray's total (known from the forward outputs) minus the running prefix:
no per-sample tape is stored beyond the weights and the per-ray outputs forward writes.

Two schedules of the same maths (`composite(..., layout=)`): "ray", one thread walks a ray (the
kernels here; the right shape for the CPU), and "block", 32 threads per ray with tile scans over
chunks of samples (`composite_block.py`; coalesced loads and full occupancy on a GPU). "auto"
picks `CUDA_AUTO` on CUDA and "ray" on the CPU. They agree up to float32 rounding (see
composite_block's docstring for where, and what that means for the early-termination test).
"""

from __future__ import annotations

import functools
from typing import Literal

import torch
import warp as wp

from .alpha import one_minus_exp_neg, optical_depth, ray_output_grads
from .common import as_float32, fast_view, init, launch, launch_tiled
from .composite_block import BLOCK_DIM, composite_bwd_block_kernel, composite_fwd_block
from .distortion_block import distortion_bwd_block, distortion_fwd_block

T_MIN = 1e-4
"""Transmittance below which a ray stops (instant-ngp's early termination)."""

# Every output buffer comes from here, so a test can hand out poisoned memory and check
# that the kernels write every element.
_empty = torch.empty
# Per-sample outputs start at zero: samples outside every packed slice (the padding of
# march_rays_fixed's buffers) get weight 0 and gradient 0. One memset, cheap next to the kernels.
_zeros = torch.zeros


@wp.kernel
def _composite_fwd(
    sigmas: wp.array(dtype=float),
    rgbs: wp.array(dtype=wp.vec3),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    packed_info: wp.array(dtype=wp.vec2i),
    bg: wp.array(dtype=wp.vec3),
    bg_stride: int,
    t_min: float,
    weights: wp.array(dtype=float),
    out_rgb: wp.array(dtype=wp.vec3),
    out_depth: wp.array(dtype=float),
    out_opacity: wp.array(dtype=float),
    n_used: wp.array(dtype=wp.int32),
):
    """One thread per ray; `weights` arrives zeroed, so the walk stops at the first sample
    whose outgoing transmittance is below t_min (the rest keep weight 0 unread)."""
    r = wp.tid()
    start = packed_info[r][0]
    n = packed_info[r][1]
    T = wp.float32(1.0)
    c = wp.vec3(0.0)
    d = wp.float32(0.0)
    o = wp.float32(0.0)
    used = wp.int32(0)
    if T >= t_min:  # t_min > 1 stops every ray at once
        for i in range(n):
            s = start + i
            t0 = t_starts[s]
            t1 = t_ends[s]
            tau = optical_depth(sigmas[s], t0, t1)
            w = T * one_minus_exp_neg(tau)
            weights[s] = w
            c += w * rgbs[s]
            d += w * 0.5 * (t0 + t1)
            o += w
            T = T * wp.exp(-tau)
            used = i + 1
            if not (T >= t_min):  # NaN stops too: the ray is NaN from here on anyway
                break
    out_rgb[r] = c + (1.0 - o) * bg[r * bg_stride]
    out_depth[r] = d
    out_opacity[r] = o
    n_used[r] = used


@functools.cache
def _composite_bwd_kernel(has_rgb: bool, has_depth: bool, has_opacity: bool, has_weights: bool):
    """Backward kernel; only the gradient terms of outputs that received one are compiled in
    (an absent gradient is zero: no buffer of zeros is made or read)."""

    @wp.kernel(module="unique")
    def composite_bwd(
        sigmas: wp.array(dtype=float),
        rgbs: wp.array(dtype=wp.vec3),
        t_starts: wp.array(dtype=float),
        t_ends: wp.array(dtype=float),
        packed_info: wp.array(dtype=wp.vec2i),
        bg: wp.array(dtype=wp.vec3),
        bg_stride: int,
        n_used: wp.array(dtype=wp.int32),
        weights: wp.array(dtype=float),
        out_rgb: wp.array(dtype=wp.vec3),
        out_depth: wp.array(dtype=float),
        out_opacity: wp.array(dtype=float),
        g_rgb: wp.array(dtype=wp.vec3),
        g_depth: wp.array(dtype=float),
        g_opacity: wp.array(dtype=float),
        g_weights: wp.array(dtype=float),
        grad_sigmas: wp.array(dtype=float),
        grad_rgbs: wp.array(dtype=wp.vec3),
    ):
        """Gradients arrive zeroed: only the `used` samples (weight possibly > 0) are
        visited."""
        r = wp.tid()
        start = packed_info[r][0]
        used = n_used[r]
        b = bg[r * bg_stride]
        gc, gd, go, total = ray_output_grads(
            r,
            b,
            out_rgb,
            out_depth,
            out_opacity,
            g_rgb,
            g_depth,
            g_opacity,
            wp.static(has_rgb),
            wp.static(has_depth),
            wp.static(has_opacity),
        )
        if wp.static(has_weights):
            for i in range(used):
                total += g_weights[start + i] * weights[start + i]
        T = wp.float32(1.0)
        prefix = wp.float32(0.0)
        for i in range(used):
            s = start + i
            t0 = t_starts[s]
            t1 = t_ends[s]
            tau = optical_depth(sigmas[s], t0, t1)
            w = T * one_minus_exp_neg(tau)  # recomputed: cheaper than reading it back
            e = go
            if wp.static(has_rgb):
                e += wp.dot(gc, rgbs[s] - b)
                grad_rgbs[s] = w * gc
            if wp.static(has_depth):
                e += gd * 0.5 * (t0 + t1)
            if wp.static(has_weights):
                e += g_weights[s]
            T = T * wp.exp(-tau)
            prefix += e * w
            delta = wp.max(t1 - t0, 0.0)
            grad_sigmas[s] = delta * (e * T - (total - prefix))

    return composite_bwd


@functools.cache
def _zero_bg(dev: torch.device) -> torch.Tensor:
    return torch.zeros(1, 3, dtype=torch.float32, device=dev)


def _bg_array(background: torch.Tensor | None, R: int, dev: torch.device) -> torch.Tensor:
    """Background as a (1, 3) or (R, 3) float32 tensor on `dev`; read by the kernels on the
    device (reading it on the host would sync every call)."""
    if background is None:
        return _zero_bg(torch.device(dev))
    bg = background
    if bg.numel() == 3:
        bg = bg.reshape(1, 3)
    elif bg.shape != (R, 3):
        raise ValueError(f"background must be (3,) or ({R}, 3), got {tuple(bg.shape)}")
    return as_float32(bg, dev)


def _check_packed(sigmas, t_starts, t_ends, packed_info) -> None:
    S = sigmas.shape[0]
    if t_starts.shape != (S,) or t_ends.shape != (S,):
        raise ValueError(f"t_starts/t_ends must be ({S},), got {tuple(t_starts.shape)}")
    if packed_info.dtype != torch.int32 or packed_info.ndim != 2 or packed_info.shape[1] != 2:
        raise ValueError("packed_info must be (R, 2) int32")


def _grad(g: torch.Tensor | None, dummy: torch.Tensor) -> torch.Tensor:
    return dummy if g is None else as_float32(g)


Layout = Literal["auto", "ray", "block"]
LAYOUTS = ("auto", "ray", "block")


CUDA_AUTO = "block"
"""What "auto" takes on CUDA: "block", measured faster in training than "ray" on every built-in
scene and the mesh scene at the same PSNR (benchmarks/RESULTS.md); the CPU always takes "ray"
(its blocks are emulated)."""


DISTORTION_CUDA_AUTO = "block"
"""What "auto" takes on CUDA for the distortion loss: "block", shorter in training on every
built-in scene and the mesh scene (benchmarks/RESULTS.md)."""


def resolve_layout(layout: Layout, device: torch.device, cuda_auto: str = CUDA_AUTO) -> str:
    """The kernels `layout` stands for on `device`, "ray" or "block" ("auto": `cuda_auto` on
    CUDA, "ray" elsewhere). Raises ValueError for any other name."""
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    if layout == "auto":
        return cuda_auto if device.type == "cuda" else "ray"
    return layout


def _launch(layout: str, ray_kernel, block_kernel, R: int, like: torch.Tensor, args: list):
    """One thread per ray, or one block of BLOCK_DIM threads per ray (same arguments)."""
    if layout == "block":
        launch_tiled(block_kernel, R, BLOCK_DIM, like, args)
    else:
        launch(ray_kernel, R, like, args)


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, sigmas, rgbs, t_starts, t_ends, packed_info, background, layout):
        init()
        ctx.set_materialize_grads(False)
        ctx.layout = layout
        sigmas, rgbs, t_starts, t_ends = (as_float32(t) for t in (sigmas, rgbs, t_starts, t_ends))
        packed_info = packed_info.contiguous()
        R, S, dev = packed_info.shape[0], sigmas.shape[0], sigmas.device
        bg = _bg_array(background, R, dev)
        weights = _zeros(S, dtype=torch.float32, device=dev)
        rgb = _empty(R, 3, dtype=torch.float32, device=dev)
        depth = _empty(R, dtype=torch.float32, device=dev)
        opacity = _empty(R, dtype=torch.float32, device=dev)
        n_used = _empty(R, dtype=torch.int32, device=dev)
        _launch(
            layout,
            _composite_fwd,
            composite_fwd_block,
            R,
            sigmas,
            [
                sigmas,
                fast_view(rgbs, wp.vec3),
                t_starts,
                t_ends,
                fast_view(packed_info, wp.vec2i),
                fast_view(bg, wp.vec3),
                int(bg.shape[0] > 1),
                T_MIN,
                weights,
                fast_view(rgb, wp.vec3),
                depth,
                opacity,
                n_used,
            ],
        )
        ctx.save_for_backward(
            sigmas, rgbs, t_starts, t_ends, packed_info, bg, n_used, weights, rgb, depth, opacity
        )
        return rgb, depth, opacity, weights

    @staticmethod
    def backward(ctx, g_rgb, g_depth, g_opacity, g_weights):
        sigmas, rgbs, t_starts, t_ends, packed_info, bg, n_used, weights, rgb, depth, opacity = (
            ctx.saved_tensors
        )
        R, S, dev = packed_info.shape[0], sigmas.shape[0], sigmas.device
        grad_sigmas = _zeros(S, dtype=torch.float32, device=dev)
        grad_rgbs = _zeros(S, 3, dtype=torch.float32, device=dev)
        flags = tuple(g is not None for g in (g_rgb, g_depth, g_opacity, g_weights))
        if any(flags):
            # held in a local until the launch: a Warp view keeps no reference to its tensor,
            # and a gradient that arrives strided (e.g. from .sum()) is copied here
            g_rgb = _grad(g_rgb, rgb)
            _launch(
                ctx.layout,
                _composite_bwd_kernel(*flags),
                composite_bwd_block_kernel(*flags),
                R,
                sigmas,
                [
                    sigmas,
                    fast_view(rgbs, wp.vec3),
                    t_starts,
                    t_ends,
                    fast_view(packed_info, wp.vec2i),
                    fast_view(bg, wp.vec3),
                    int(bg.shape[0] > 1),
                    n_used,
                    weights,
                    fast_view(rgb, wp.vec3),
                    depth,
                    opacity,
                    fast_view(g_rgb, wp.vec3),
                    _grad(g_depth, depth),
                    _grad(g_opacity, opacity),
                    _grad(g_weights, weights),
                    grad_sigmas,
                    fast_view(grad_rgbs, wp.vec3),
                ],
            )
        return grad_sigmas, grad_rgbs, None, None, None, None, None


def composite(
    sigmas: torch.Tensor,
    rgbs: torch.Tensor,
    t_starts: torch.Tensor,
    t_ends: torch.Tensor,
    packed_info: torch.Tensor,
    ray_indices: torch.Tensor | None = None,
    background: torch.Tensor | None = None,
    layout: Layout = "auto",
) -> dict[str, torch.Tensor]:
    """Composite packed samples front to back; differentiable w.r.t. `sigmas` and `rgbs`.

    Args:
        sigmas: (S,) float32 >= 0, density in 1/world units (finite or +inf; NaN propagates
            to its ray).
        rgbs: (S, 3) float32 colour of each sample.
        t_starts, t_ends: (S,) float32 interval ends along the unit ray direction, world units.
        packed_info: (R, 2) int32 (first sample, sample count) of each ray.
        ray_indices: (S,) int32 owner ray of each sample; not read (packed_info says it all),
            accepted for symmetry with the marcher's outputs.
        background: (3,) colour composited behind every ray, or (R, 3) one per ray, or None
            (black, i.e. nothing); best on the rays' device (a CPU tensor is copied over,
            which waits for the GPU). Not differentiated.
        layout: "ray" (one thread per ray), "block" (32 threads per ray, tile scans over
            chunks of 32 samples) or "auto" (`CUDA_AUTO` on CUDA, "ray" on the CPU). Same results
            up to float32 rounding.

    Returns:
        dict with rgb (R, 3), depth (R,) un-normalised sum of w * t_mid in world units,
        opacity (R,) = sum of weights, weights (S,); all differentiable (the gradient of
        `weights` flows back to `sigmas`).
    """
    _check_packed(sigmas, t_starts, t_ends, packed_info)
    if rgbs.shape != (sigmas.shape[0], 3):
        raise ValueError(f"rgbs must be ({sigmas.shape[0]}, 3), got {tuple(rgbs.shape)}")
    mode = resolve_layout(layout, sigmas.device)
    rgb, depth, opacity, weights = _Composite.apply(
        sigmas, rgbs, t_starts, t_ends, packed_info, background, mode
    )
    return {"rgb": rgb, "depth": depth, "opacity": opacity, "weights": weights}


# --------------------------------------------------------------------------------------------
# Distortion loss (mip-NeRF 360, eq. 15), O(n) per ray with running sums.
#
#   L_r = sum_{i,j} w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 delta_i
#
# m_i = (t_start_i + t_end_i) / 2 in world units (nerfacc's convention; pass normalised t for
# mip-NeRF 360's s-space). Samples must be sorted along each ray, as the marcher emits them.
#   sum_{i,j} w_i w_j |m_i - m_j| = 2 sum_i w_i (m_i W_{<i} - WM_{<i})
#   dL/dw_i = 2 (m_i W_{<i} - WM_{<i} + WM_{>i} - m_i W_{>i}) + 2/3 w_i delta_i
# --------------------------------------------------------------------------------------------


@wp.kernel
def _distortion_fwd(
    weights: wp.array(dtype=float),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    packed_info: wp.array(dtype=wp.vec2i),
    loss: wp.array(dtype=float),
    totals: wp.array(dtype=wp.vec2),
):
    r = wp.tid()
    start = packed_info[r][0]
    n = packed_info[r][1]
    W = wp.float32(0.0)
    WM = wp.float32(0.0)
    inter = wp.float32(0.0)
    uni = wp.float32(0.0)
    for i in range(n):
        s = start + i
        w = weights[s]
        m = 0.5 * (t_starts[s] + t_ends[s])
        inter += w * (m * W - WM)
        uni += w * w * (t_ends[s] - t_starts[s])
        W += w
        WM += w * m
    loss[r] = 2.0 * inter + uni / 3.0
    totals[r] = wp.vec2(W, WM)


@wp.kernel
def _distortion_bwd(
    weights: wp.array(dtype=float),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    packed_info: wp.array(dtype=wp.vec2i),
    totals: wp.array(dtype=wp.vec2),
    g_loss: wp.array(dtype=float),
    grad_weights: wp.array(dtype=float),
):
    r = wp.tid()
    start = packed_info[r][0]
    n = packed_info[r][1]
    g = g_loss[r]
    W_tot = totals[r][0]
    WM_tot = totals[r][1]
    W = wp.float32(0.0)
    WM = wp.float32(0.0)
    for i in range(n):
        s = start + i
        w = weights[s]
        m = 0.5 * (t_starts[s] + t_ends[s])
        # before: W, WM exclude i; after: totals minus the inclusive prefix
        W_after = W_tot - W - w
        WM_after = WM_tot - WM - w * m
        d = m * W - WM + WM_after - m * W_after
        grad_weights[s] = g * (2.0 * d + 2.0 / 3.0 * w * (t_ends[s] - t_starts[s]))
        W += w
        WM += w * m


class _Distortion(torch.autograd.Function):
    @staticmethod
    def forward(ctx, weights, t_starts, t_ends, packed_info, layout):
        init()
        ctx.layout = layout
        weights, t_starts, t_ends = (as_float32(t) for t in (weights, t_starts, t_ends))
        packed_info = packed_info.contiguous()
        R, dev = packed_info.shape[0], weights.device
        loss = _empty(R, dtype=torch.float32, device=dev)
        totals = _empty(R, 2, dtype=torch.float32, device=dev)
        pi, tot = fast_view(packed_info, wp.vec2i), fast_view(totals, wp.vec2)
        args = [weights, t_starts, t_ends, pi, loss, tot]
        _launch(layout, _distortion_fwd, distortion_fwd_block, R, weights, args)
        ctx.save_for_backward(weights, t_starts, t_ends, packed_info, totals)
        return loss

    @staticmethod
    def backward(ctx, g_loss):
        weights, t_starts, t_ends, packed_info, totals = ctx.saved_tensors
        R = packed_info.shape[0]
        grad = _zeros(weights.shape[0], dtype=torch.float32, device=weights.device)
        # held in a local until the launch (a Warp view keeps no reference to its tensor)
        g_loss = as_float32(g_loss)
        pi, tot = fast_view(packed_info, wp.vec2i), fast_view(totals, wp.vec2)
        args = [weights, t_starts, t_ends, pi, tot, g_loss, grad]
        _launch(ctx.layout, _distortion_bwd, distortion_bwd_block, R, weights, args)
        return grad, None, None, None, None


def distortion_loss(
    weights: torch.Tensor,
    t_starts: torch.Tensor,
    t_ends: torch.Tensor,
    packed_info: torch.Tensor,
    layout: Layout = "auto",
) -> torch.Tensor:
    """Per-ray mip-NeRF 360 distortion loss (R,), differentiable w.r.t. `weights` (S,).

    Midpoints are in the units of `t_starts`/`t_ends` (world units from the marcher); samples
    must be sorted along each ray and not overlap. Take `.mean()` for the regulariser.
    `layout`: "ray" (one thread per ray), "block" (32 threads per ray,
    kernels/distortion_block.py) or "auto" (`DISTORTION_CUDA_AUTO` on CUDA, "ray" on the CPU);
    the same loss up to float32 rounding.
    """
    _check_packed(weights, t_starts, t_ends, packed_info)
    mode = resolve_layout(layout, weights.device, DISTORTION_CUDA_AUTO)
    return _Distortion.apply(weights, t_starts, t_ends, packed_info, mode)
