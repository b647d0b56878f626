"""Cooperative compositing: one block of `BLOCK_DIM` threads per ray (``layout="block"``).

Same inputs, outputs and semantics as the one-thread-per-ray kernels of `composite.py` (see its
docstring for the maths); only the schedule differs. A ray's samples are taken in chunks of
``B = wp.block_dim()`` (32 by default): lane k holds sample ``chunk + k``, so a chunk's loads are
contiguous across the lanes (coalesced on a GPU) and a 65k-ray batch keeps 32x more threads busy.

Forward, per chunk, with T the transmittance entering the chunk (the same in every lane):

    E_k   = exclusive tile scan of the optical depths tau      (sum over the lanes before k)
    T_k   = T * exp(-E_k)                                       incoming transmittance of lane k
    stop  = tile min over k of {k : sample past the ray's end, or not (T_k >= t_min)}, or B
    lanes k < stop get w_k = T_k * alpha_k (and write it); lanes >= stop write nothing
    T     = T_{B-1} * exp(-tau_{B-1})  from the chunk's last lane, for the next chunk

A ray stops in the first chunk where stop < B; n_used = chunk + stop, the sequential kernel's
count (its walk visits sample i iff T_i >= t_min, and stops at the first one that is not). The
stop is a min over lanes, not each lane's own test, so the visited samples form a prefix even
where rounding would make T_k non-monotone (a zero tau between two lanes). The per-ray sums are
kept per lane across chunks and reduced once (`tile_sum`) at the end.

Rounding against the per-ray kernels (float32, both correct to a few ulp of the float64 maths):
T_k is T * exp(-(tau_0 + ... + tau_{k-1})) within a chunk instead of a running product of
exp(-tau_j), the sums over samples are added in another order, and the scan's order differs
between the CPU (sequential) and CUDA (Kogge-Stone in a warp). The two T_k differ by float32
rounding of the sums and products of at most the k samples before (relative ~1e-7 typically,
bounded by ~k * 6e-8), so the early-termination test T_k >= t_min can decide differently from
the per-ray kernel only for samples whose T_k lies that close to t_min: n_used then differs by
those samples (usually one), whose weights (each below t_min * alpha_k) one layout keeps and the
other drops. The tests draw cases away from that edge; everywhere else n_used is the same.

Backward, per chunk of the ray's n_used samples: T_k and w_k are recomputed by the same scan as
in the forward pass (bit-identical weights), e_k as in `composite.py`, and the prefix sum of
e_j w_j up to and including lane k by an inclusive tile scan plus the carry from the earlier
chunks, so dL/dsigma_k = delta_k (e_k T_{k+1} - (total - prefix_k)).
"""

from __future__ import annotations

import functools

import warp as wp

from .alpha import one_minus_exp_neg, optical_depth, ray_output_grads

BLOCK_DIM = 32
"""Threads per ray (one warp on CUDA); the kernels read the width from wp.block_dim()."""

_vec5 = wp.types.vector(length=5, dtype=wp.float32)


@wp.func
def lane_sample(
    sigmas: wp.array(dtype=float),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    s: int,
    inside: bool,
):
    """(t0, t1, optical depth) of packed sample s; zeros for a lane past the ray's end, so it
    adds nothing to the chunk's scan."""
    if inside:
        t0 = t_starts[s]
        t1 = t_ends[s]
        return t0, t1, optical_depth(sigmas[s], t0, t1)
    return wp.float32(0.0), wp.float32(0.0), wp.float32(0.0)


@wp.kernel(enable_backward=False)
def composite_fwd_block(
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
    """Launched over (R, B): block r composites ray r; `weights` arrives zeroed, so only the
    visited samples are written. Every tile op is reached by all lanes (the loop's trip count
    and its break depend on block-uniform values only)."""
    r, lane = wp.tid()
    nb = wp.block_dim()
    start = packed_info[r][0]
    n = packed_info[r][1]
    T = wp.float32(1.0)
    acc = _vec5()  # this lane's share of (rgb, depth, opacity), reduced after the walk
    used = wp.int32(0)
    chunk = wp.int32(0)
    while chunk < n:
        i = chunk + lane
        s = start + i
        t0, t1, tau = lane_sample(sigmas, t_starts, t_ends, s, i < n)
        T_in = T * wp.exp(-wp.untile(wp.tile_scan_exclusive(wp.tile(tau))))
        key = nb
        if i >= n or not (T_in >= t_min):  # NaN stops too, as in the per-ray walk
            key = lane
        stop = wp.tile_extract(wp.tile_min(wp.tile(key)), 0)
        if lane < stop:
            w = T_in * one_minus_exp_neg(tau)
            weights[s] = w
            c = w * rgbs[s]
            acc += _vec5(c[0], c[1], c[2], w * 0.5 * (t0 + t1), w)
        if stop < nb:
            used = chunk + stop
            break
        T = wp.tile_extract(wp.tile(T_in * wp.exp(-tau)), nb - 1)
        chunk += nb
        used = chunk
    tot = wp.tile_extract(wp.tile_sum(wp.tile(acc, preserve_type=True)), 0)
    if lane == 0:
        out_rgb[r] = wp.vec3(tot[0], tot[1], tot[2]) + (1.0 - tot[4]) * bg[r * bg_stride]
        out_depth[r] = tot[3]
        out_opacity[r] = tot[4]
        n_used[r] = used


@functools.cache
def composite_bwd_block_kernel(
    has_rgb: bool, has_depth: bool, has_opacity: bool, has_weights: bool
):
    """Backward block kernel; as `composite._composite_bwd_kernel`, only the gradient terms of
    outputs that received one are compiled in."""

    @wp.kernel(enable_backward=False, module="unique")
    def composite_bwd_block(
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
        """Launched over (R, B); gradients arrive zeroed and only the n_used[r] visited
        samples of ray r are written."""
        r, lane = wp.tid()
        nb = wp.block_dim()
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
            part = wp.float32(0.0)
            for j in range(lane, used, nb):
                part += g_weights[start + j] * weights[start + j]
            total += wp.tile_extract(wp.tile_sum(wp.tile(part)), 0)
        T = wp.float32(1.0)
        prefix = wp.float32(0.0)  # sum of e_j w_j over the earlier chunks
        for chunk in range(0, used, nb):
            i = chunk + lane
            s = start + i
            t0, t1, tau = lane_sample(sigmas, t_starts, t_ends, s, i < used)
            # the forward pass's scan on the same lanes: the same T_in and w, bit for bit
            T_in = T * wp.exp(-wp.untile(wp.tile_scan_exclusive(wp.tile(tau))))
            w = T_in * one_minus_exp_neg(tau)
            e = go
            ew = wp.float32(0.0)
            if i < used:
                if wp.static(has_rgb):
                    e += wp.dot(gc, rgbs[s] - b)
                    grad_rgbs[s] = w * gc
                if wp.static(has_depth):
                    e += gd * 0.5 * (t0 + t1)
                if wp.static(has_weights):
                    e += g_weights[s]
                ew = e * w
            incl = prefix + wp.untile(wp.tile_scan_inclusive(wp.tile(ew)))
            T_out = T_in * wp.exp(-tau)
            if i < used:
                delta = wp.max(t1 - t0, 0.0)
                grad_sigmas[s] = delta * (e * T_out - (total - incl))
            carry = wp.tile_extract(wp.tile(wp.vec2(T_out, incl), preserve_type=True), nb - 1)
            T = carry[0]
            prefix = carry[1]

    return composite_bwd_block
