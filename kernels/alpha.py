"""Maths shared by the compositors (`composite`, `composite_block`) and the sample pruner: a
sample of density sigma (1/world units) over [t0, t1] (world units) has optical depth
tau = sigma * (t1 - t0) (dimensionless) and opacity alpha = 1 - exp(-tau); and a ray's output
gradients as both compositors' backward passes read them."""

from __future__ import annotations

import warp as wp


@wp.func
def one_minus_exp_neg(x: float) -> float:
    """1 - exp(-x) for x >= 0, accurate to a few ulp also for tiny x (an expm1).

    Plain ``1 - exp(-x)`` rounds to 0 below x ~ 6e-8 in float32, so a sample with a tiny
    step or density would get no weight and no gradient. Kahan's trick:
    expm1(y) = (u - 1) * y / log(u) with u = exp(y) cancels the rounding error of exp.
    """
    if x >= 1.0:
        return 1.0 - wp.exp(-x)
    u = wp.exp(-x)
    if u == 1.0:
        return x
    return (1.0 - u) * x / (-wp.log(u))


@wp.func
def optical_depth(sigma: float, t0: float, t1: float) -> float:
    """sigma * delta with delta clamped at 0; a zero-length step has zero optical depth even
    for sigma = inf (0 * inf would be NaN)."""
    delta = t1 - t0
    if delta > 0.0:
        return sigma * delta
    return 0.0


@wp.func
def ray_output_grads(
    r: int,
    b: wp.vec3,
    out_rgb: wp.array(dtype=wp.vec3),
    out_depth: wp.array(dtype=float),
    out_opacity: wp.array(dtype=float),
    g_rgb: wp.array(dtype=wp.vec3),
    g_depth: wp.array(dtype=float),
    g_opacity: wp.array(dtype=float),
    has_rgb: bool,
    has_depth: bool,
    has_opacity: bool,
):
    """Ray r's gradients of rgb, depth and opacity (zero where absent: that array is a
    placeholder and is not read) and sum_j e_j w_j over them, from the forward outputs
    (out_rgb - bg = sum w c - opacity * bg); the per-weight terms are the caller's."""
    gc = wp.vec3(0.0)
    gd = wp.float32(0.0)
    go = wp.float32(0.0)
    total = wp.float32(0.0)
    if has_rgb:
        gc = g_rgb[r]
        total += wp.dot(gc, out_rgb[r] - b)
    if has_depth:
        gd = g_depth[r]
        total += gd * out_depth[r]
    if has_opacity:
        go = g_opacity[r]
        total += go * out_opacity[r]
    return gc, gd, go, total
