"""The distortion loss with one block of `BLOCK_DIM` threads per ray (``layout="block"``).

Same inputs, outputs and maths as the one-thread-per-ray kernels in `composite.py` (its
"Distortion loss" section has the formulas); only the schedule differs, as in
`composite_block.py`: lane k holds sample ``chunk + k`` of its ray, so a chunk's loads are
contiguous across the lanes and a batch of R rays runs R * 32 threads instead of R. The
per-ray walk's running sums W = sum w and WM = sum w m over the samples before i become a
carry from the earlier chunks plus an exclusive tile scan within the chunk:

    W_<k  = W_carry  + exclusive scan of w     over the lanes before k
    WM_<k = WM_carry + exclusive scan of w m
    forward:  lane k adds w_k (m_k W_<k - WM_<k) and w_k^2 delta_k; reduced once per ray
    backward: dL/dw_k = g (2 (m_k W_<k - WM_<k + WM_>k - m_k W_>k) + 2/3 w_k delta_k),
              with the suffix sums the forward's totals minus the inclusive prefixes

Lanes past the ray's end hold w = m = delta = 0, so they add nothing to a scan or a sum. The
sums are taken in another order than the per-ray walk's, so the two layouts agree to float32
rounding, both within a few ulp of the float64 double sum.
"""

from __future__ import annotations

import warp as wp

from .composite_block import BLOCK_DIM

__all__ = ["BLOCK_DIM", "distortion_bwd_block", "distortion_fwd_block"]


@wp.func
def lane_wmd(
    weights: wp.array(dtype=float),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    s: int,
    inside: bool,
):
    """(weight, interval midpoint, interval length) of packed sample s; zeros for a lane past
    the ray's end."""
    if inside:
        t0 = t_starts[s]
        t1 = t_ends[s]
        return weights[s], 0.5 * (t0 + t1), t1 - t0
    return wp.float32(0.0), wp.float32(0.0), wp.float32(0.0)


@wp.func
def chunk_prefixes(w: float, wm: float, W: float, WM: float, nb: int):
    """(W_<k, WM_<k) of this lane from the carries W, WM of the earlier chunks and this
    chunk's exclusive scans of w and w m; then the carries into the next chunk (the last
    lane's inclusive sums, in every lane)."""
    W_before = W + wp.untile(wp.tile_scan_exclusive(wp.tile(w)))
    WM_before = WM + wp.untile(wp.tile_scan_exclusive(wp.tile(wm)))
    W_next = wp.tile_extract(wp.tile(W_before + w), nb - 1)
    WM_next = wp.tile_extract(wp.tile(WM_before + wm), nb - 1)
    return W_before, WM_before, W_next, WM_next


@wp.kernel(enable_backward=False)
def distortion_fwd_block(
    weights: wp.array(dtype=float),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    packed_info: wp.array(dtype=wp.vec2i),
    loss: wp.array(dtype=float),
    totals: wp.array(dtype=wp.vec2),
):
    """Launched over (R, B): block r writes loss[r] and totals[r] = (sum w, sum w m), which
    the backward pass reads. Every tile op is reached by all lanes (the loop's trip count
    depends on block-uniform values only)."""
    r, lane = wp.tid()
    nb = wp.block_dim()
    start = packed_info[r][0]
    n = packed_info[r][1]
    W = wp.float32(0.0)
    WM = wp.float32(0.0)
    acc = wp.vec2()  # this lane's (pair term, unary term), reduced after the walk
    for chunk in range(0, n, nb):
        i = chunk + lane
        w, m, d = lane_wmd(weights, t_starts, t_ends, start + i, i < n)
        W_before, WM_before, W, WM = chunk_prefixes(w, w * m, W, WM, nb)
        acc += wp.vec2(w * (m * W_before - WM_before), w * w * d)
    tot = wp.tile_extract(wp.tile_sum(wp.tile(acc, preserve_type=True)), 0)
    if lane == 0:
        loss[r] = 2.0 * tot[0] + tot[1] / 3.0
        totals[r] = wp.vec2(W, WM)


@wp.kernel(enable_backward=False)
def distortion_bwd_block(
    weights: wp.array(dtype=float),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    packed_info: wp.array(dtype=wp.vec2i),
    totals: wp.array(dtype=wp.vec2),
    g_loss: wp.array(dtype=float),
    grad_weights: wp.array(dtype=float),
):
    """Launched over (R, B); `grad_weights` arrives zeroed and each ray's samples are
    written."""
    r, lane = wp.tid()
    nb = wp.block_dim()
    start = packed_info[r][0]
    n = packed_info[r][1]
    g = g_loss[r]
    W_tot = totals[r][0]
    WM_tot = totals[r][1]
    W = wp.float32(0.0)
    WM = wp.float32(0.0)
    for chunk in range(0, n, nb):
        i = chunk + lane
        s = start + i
        w, m, d = lane_wmd(weights, t_starts, t_ends, s, i < n)
        W_before, WM_before, W, WM = chunk_prefixes(w, w * m, W, WM, nb)
        if i < n:
            W_after = W_tot - W_before - w
            WM_after = WM_tot - WM_before - w * m
            pair = m * W_before - WM_before + WM_after - m * W_after
            grad_weights[s] = g * (2.0 * pair + 2.0 / 3.0 * w * d)
