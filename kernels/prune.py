"""Compacted samples: drop the marched samples a ray can no longer see, before the field's
forward and backward run on them (instant-ngp's compaction; nerfacc's `sigma_fn` pruning).

A march keeps every sample in an occupied cell, most of them behind the first surface where
the transmittance is ~0: they cost a full field evaluation, forward and backward, for no
weight. Given the density of every marched sample (one forward pass of the density network
under no_grad), each ray's packed slice is walked front to back with the compositing rule

    tau_i = sigma_i * (t_end_i - t_start_i)      alpha_i = 1 - exp(-tau_i)
    T_i   = prod_{j<i} exp(-tau_j)               (transmittance before sample i, all j)

and sample i is kept iff ``T_i >= early_stop_eps and alpha_i >= alpha_threshold`` (nerfacc's
`render_visibility_from_density`). T falls monotonically, so the walk stops at the first
sample below the eps. T is the float32 product `composite` forms, so with early_stop_eps equal
to composite's T_MIN (1e-4) and no alpha threshold the kept samples are exactly the ones
`composite` would have weighted: pixels and gradients do not change. A larger eps drops at most
T < eps of each ray's weight; an alpha threshold drops near-transparent samples (their
successors then see slightly more transmittance, as in nerfacc). A NaN density is kept (the
pixel stays NaN, so a training step's guard still sees it) and ends its ray's walk.

Output: the kept samples packed per ray in ray order, the marcher's layout (packed_info (R, 2)
int32 (first, count), t_starts / t_ends (S,) float32, ray_indices (S,) int32).
`prune_samples` sizes it exactly (the host reads the count); `prune_samples_fixed` writes into
fixed-capacity buffers with no host sync, exactly as `march_rays_fixed` does (same scan, same
reservation and padding kernels, same FixedSamples; overflowed rays get count 0 and a flag).
The input may be a FixedSamples itself: only its packed slices are read (padding and
overflowed rays, count 0, are skipped). No gradients: which samples are kept is not
differentiated.
"""

from __future__ import annotations

import torch
import warp as wp

from .common import as_float32, fast_view, init, launch
from .composite import one_minus_exp_neg, optical_depth
from .raymarch_fixed import (
    FixedSamples,
    check_fixed_out,
    empty_fixed_samples,
    pad_tail,
    reserve_slices,
)


@wp.func
def visible(T: float, tau: float, eps: float, alpha_threshold: float) -> bool:
    """Whether a sample with incoming transmittance T and optical depth tau is kept: T >= eps
    and alpha >= alpha_threshold, with a NaN alpha kept (never hide a NaN)."""
    return T >= eps and not (one_minus_exp_neg(tau) < alpha_threshold)


@wp.kernel(enable_backward=False)
def _visibility(
    sigmas: wp.array(dtype=float),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    packed_info: wp.array(dtype=wp.vec2i),
    eps: float,
    alpha_threshold: float,
    keep: wp.array(dtype=wp.bool),
    counts: wp.array(dtype=wp.int32),
):
    """One thread per ray: keep[s] for the samples of its slice up to where the walk stops
    (later flags are left unwritten and never read), counts[r] = samples kept."""
    r = wp.tid()
    start = packed_info[r][0]
    n = packed_info[r][1]
    T = wp.float32(1.0)
    kept = wp.int32(0)
    for i in range(n):
        if not (T >= eps):  # T only falls (NaN: the ray is NaN from here on anyway)
            break
        s = start + i
        tau = optical_depth(sigmas[s], t_starts[s], t_ends[s])
        k = visible(T, tau, eps, alpha_threshold)
        keep[s] = k
        if k:
            kept += 1
        T = T * wp.exp(-tau)
    counts[r] = kept


@wp.kernel(enable_backward=False)
def _compact(
    keep: wp.array(dtype=wp.bool),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    packed_info: wp.array(dtype=wp.vec2i),
    dest: wp.array(dtype=wp.vec2i),
    out_t_starts: wp.array(dtype=float),
    out_t_ends: wp.array(dtype=float),
    out_ray_indices: wp.array(dtype=wp.int32),
    out_src: wp.array(dtype=wp.int32),
):
    """One thread per ray: copies the first dest[r][1] kept samples of its input slice to
    [dest[r][0], dest[r][0] + dest[r][1]), with each one's input slot in out_src (a count of
    0, an overflowed ray, writes nothing)."""
    r = wp.tid()
    s = packed_info[r][0]
    base = dest[r][0]
    n = dest[r][1]
    j = wp.int32(0)
    while j < n:
        if keep[s]:
            out_t_starts[base + j] = t_starts[s]
            out_t_ends[base + j] = t_ends[s]
            out_ray_indices[base + j] = r
            out_src[base + j] = s
            j += 1
        s += 1


def _inputs(sigmas, packed_info, t_starts, t_ends, early_stop_eps, alpha_threshold):
    """Checked, contiguous float32 inputs (sigma cast from half / bf16, detached)."""
    init()
    S = t_starts.shape[0]
    if sigmas.shape != (S,) or t_ends.shape != (S,):
        raise ValueError(
            f"sigmas and t_ends must be ({S},) like t_starts, got {tuple(sigmas.shape)} and "
            f"{tuple(t_ends.shape)}"
        )
    if packed_info.dtype != torch.int32 or packed_info.ndim != 2 or packed_info.shape[1] != 2:
        raise ValueError("packed_info must be (R, 2) int32")
    for name, v in (("early_stop_eps", early_stop_eps), ("alpha_threshold", alpha_threshold)):
        if not 0.0 <= v <= 1.0:
            raise ValueError(f"{name} must be in [0, 1], got {v}")
    return (
        as_float32(sigmas),
        packed_info.contiguous(),
        as_float32(t_starts),
        as_float32(t_ends),
    )


def _visibility_pass(sigmas, packed_info, t_starts, t_ends, eps, alpha_threshold):
    """(keep (max(S, 1),) bool, counts (R,) int32) of `_visibility`."""
    dev = sigmas.device
    keep = torch.empty(max(sigmas.shape[0], 1), dtype=torch.bool, device=dev)
    counts = torch.empty(packed_info.shape[0], dtype=torch.int32, device=dev)
    args = [sigmas, t_starts, t_ends, fast_view(packed_info, wp.vec2i), float(eps)]
    launch(_visibility, packed_info.shape[0], sigmas, [*args, float(alpha_threshold), keep, counts])
    return keep, counts


def _compact_pass(keep, t_starts, t_ends, packed_info, dest, outs) -> None:
    """`_compact` into outs = (t_starts, t_ends, ray_indices, src)."""
    args = [keep, t_starts, t_ends, fast_view(packed_info, wp.vec2i), fast_view(dest, wp.vec2i)]
    launch(_compact, packed_info.shape[0], t_starts, [*args, *outs])


def prune_samples(
    sigmas: torch.Tensor,
    packed_info: torch.Tensor,
    t_starts: torch.Tensor,
    t_ends: torch.Tensor,
    early_stop_eps: float = 1e-4,
    alpha_threshold: float = 0.0,
    return_src: bool = False,
) -> tuple[torch.Tensor, ...]:
    """The visible samples of packed rays, packed again (see module doc; no gradients).

    Args:
        sigmas: (S,) density of every input slot, 1/world units (float32, or half / bf16:
            cast); slots outside every packed slice are not read.
        packed_info: (R, 2) int32 (first slot, count) of each ray, e.g. `march_rays`' or a
            FixedSamples' (overflowed rays have count 0).
        t_starts, t_ends: (S,) float32 interval ends along the unit direction, world units.
        early_stop_eps: drop samples whose incoming transmittance T is below it, in [0, 1]
            (0: none on this ground).
        alpha_threshold: drop samples whose alpha is below it, in [0, 1] (0: none).
        return_src: also return src (S',) int32, each kept sample's input slot (what was
            computed for the input's samples, gathered by it, is the kept samples').
    Returns:
        packed_info (R, 2) int32, t_starts (S',) float32, t_ends (S',) float32, ray_indices
        (S',) int32: `march_rays`' layout; then src with return_src. S' is read back from the
        device (one host sync): `prune_samples_fixed` avoids it.
    """
    sigmas, packed_info, t_starts, t_ends = _inputs(
        sigmas, packed_info, t_starts, t_ends, early_stop_eps, alpha_threshold
    )
    keep, counts = _visibility_pass(
        sigmas, packed_info, t_starts, t_ends, early_stop_eps, alpha_threshold
    )
    csum = torch.cumsum(counts, 0, dtype=torch.int32)
    out_info = torch.stack([csum - counts, counts], 1).contiguous()
    S = int(csum[-1]) if len(csum) else 0
    dev = sigmas.device
    out_t_s = torch.empty(S, dtype=torch.float32, device=dev)
    out_t_e = torch.empty(S, dtype=torch.float32, device=dev)
    out_ri = torch.empty(S, dtype=torch.int32, device=dev)
    src = torch.empty(S, dtype=torch.int32, device=dev)
    if S > 0:
        _compact_pass(
            keep, t_starts, t_ends, packed_info, out_info, (out_t_s, out_t_e, out_ri, src)
        )
    return (out_info, out_t_s, out_t_e, out_ri) + ((src,) if return_src else ())


def prune_samples_fixed(
    sigmas: torch.Tensor,
    packed_info: torch.Tensor,
    t_starts: torch.Tensor,
    t_ends: torch.Tensor,
    early_stop_eps: float = 1e-4,
    alpha_threshold: float = 0.0,
    *,
    capacity: int,
    out: FixedSamples | None = None,
    return_src: bool = False,
) -> FixedSamples | tuple[FixedSamples, torch.Tensor]:
    """`prune_samples` into buffers of `capacity` samples, with no host sync.

    Args: as `prune_samples`, plus
        capacity: slots in the output sample buffers (a Python int, fixed across steps so
            that a CUDA graph can replay the call).
        out: buffers from `empty_fixed_samples(R, capacity, device)` to write into (reused
            across steps; not the input's own buffers), or None to allocate them.
        return_src: also return src (capacity,) int32, each slot's input slot (padding: 0).
    Returns:
        FixedSamples as `march_rays_fixed`'s: a ray whose kept slice would end past
        `capacity` gets count 0 and overflow True; n_used (1,) int32 slots written, n_wanted
        (1,) int32 samples kept over all rays; slots [n_used, capacity) are padding
        (t_start = t_end = 0, ray 0). With return_src, (that, src).
    """
    sigmas, packed_info, t_starts, t_ends = _inputs(
        sigmas, packed_info, t_starts, t_ends, early_stop_eps, alpha_threshold
    )
    R, dev, capacity = packed_info.shape[0], sigmas.device, int(capacity)
    if out is None:
        out = empty_fixed_samples(R, capacity, dev)
    else:
        check_fixed_out(out, R, capacity, dev)
    src = torch.zeros(capacity, dtype=torch.int32, device=dev)  # padding reads slot 0
    if R == 0:
        out.n_used.zero_()
        out.n_wanted.zero_()
    else:
        keep, counts = _visibility_pass(
            sigmas, packed_info, t_starts, t_ends, early_stop_eps, alpha_threshold
        )
        csum = torch.cumsum(counts, 0, dtype=torch.int32)
        scratch = torch.empty(R, 2, dtype=torch.int32, device=dev)  # reserve's per-segment info
        args = [csum, counts, 1, capacity, fast_view(out.packed_info, wp.vec2i)]
        args += [fast_view(scratch, wp.vec2i), out.overflow, out.n_used, out.n_wanted]
        launch(reserve_slices, R, sigmas, args)
        outs = (out.t_starts, out.t_ends, out.ray_indices, src)
        _compact_pass(keep, t_starts, t_ends, packed_info, out.packed_info, outs)
    launch(pad_tail, capacity, sigmas, [out.n_used, out.t_starts, out.t_ends, out.ray_indices])
    return (out, src) if return_src else out
