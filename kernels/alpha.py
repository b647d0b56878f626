"""Per-sample opacity maths shared by the compositors (`composite`, `composite_block`) and the
sample pruner: a sample of density sigma (1/world units) over [t0, t1] (world units) has optical
depth tau = sigma * (t1 - t0) (dimensionless) and opacity alpha = 1 - exp(-tau)."""

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
