"""Ray marching into fixed-capacity sample buffers, with no host sync (CUDA-graph capturable).

`march_rays` sizes its outputs from the sample count, which the host must read back: every call
waits for the GPU. Here the caller fixes the capacity. The same compiled kernel runs the same two
passes (count, write; or one, `march_scratch.SINGLE_PASS`); between them an exclusive scan
(torch.cumsum) and one small kernel place ray r's samples at [start_r, start_r + n_r), in ray
order, exactly where `march_rays` puts them, all on the device. So when everything fits, the
first `n_used` slots are `march_rays`' output bit for bit.

Overflow is never silent: a ray whose slice would end past `capacity` gets no samples (count 0)
and is flagged in `overflow`. Slices are laid out in ray order, so the rays that do not fit are
the last ones with samples (in training, a random subset of the batch). `n_wanted` is what an
unbounded buffer would have held: the caller reads it later, without waiting (a non-blocking
copy), and grows the capacity for a later step.

Padding: slots [n_used, capacity) hold t_start = t_end = 0 and ray index 0, zero-width
intervals at ray 0's origin that no packed slice covers. A field may be evaluated on all
`capacity` samples: `composite` reads only the packed slices, so pixels and gradients equal the
exact-size path's, and the padding's sigma / rgb get zero gradient. Losses that sum over all
samples (not per packed slice) must mask slots >= n_used themselves.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import torch
import warp as wp

from .common import fast_view, launch
from .occupancy import OccupancyGrid
from .raymarch import count_samples, plan_march, write_samples


class FixedSamples(NamedTuple):
    """Output of `march_rays_fixed` (unpacks like a tuple, in this order).

    packed_info: (R, 2) int32 (first slot, count); count 0 for rays that overflowed.
    t_starts, t_ends: (capacity,) float32 world units; padding slots are 0, 0.
    ray_indices: (capacity,) int32 owner ray of each slot; padding slots are 0.
    overflow: (R,) bool, True where the ray had samples that did not fit.
    n_used: (1,) int32 slots written, <= capacity.
    n_wanted: (1,) int32 slots an unbounded buffer would have held.
    """

    packed_info: torch.Tensor
    t_starts: torch.Tensor
    t_ends: torch.Tensor
    ray_indices: torch.Tensor
    overflow: torch.Tensor
    n_used: torch.Tensor
    n_wanted: torch.Tensor


@wp.kernel
def reserve_slices(
    csum: wp.array(dtype=wp.int32),
    seg_counts: wp.array(dtype=wp.int32),
    n_seg: int,
    capacity: int,
    packed_info: wp.array(dtype=wp.vec2i),
    seg_info: wp.array(dtype=wp.vec2i),
    overflow: wp.array(dtype=wp.bool),
    n_used: wp.array(dtype=wp.int32),
    n_wanted: wp.array(dtype=wp.int32),
):
    """One thread per ray (`prune.py` reuses it with n_seg 1). csum: inclusive scan of
    seg_counts (R * n_seg,). Ray ends are nondecreasing, so the rays that fit are a prefix and
    its last ray's end is n_used: written by the one thread at the boundary (no atomics,
    nothing to zero first)."""
    r = wp.tid()
    R = csum.shape[0] / n_seg
    end = csum[r * n_seg + n_seg - 1]
    first = csum[r * n_seg] - seg_counts[r * n_seg]
    fits = end <= capacity
    n = end - first
    for j in range(n_seg):
        s = r * n_seg + j
        c = wp.int32(0)
        if fits:
            c = seg_counts[s]
        seg_info[s] = wp.vec2i(csum[s] - seg_counts[s], c)
    if fits:
        packed_info[r] = wp.vec2i(first, n)
    else:
        packed_info[r] = wp.vec2i(wp.min(first, capacity), 0)
    overflow[r] = (not fits) and n > 0
    next_fits = False
    if r + 1 < R:
        next_fits = csum[r * n_seg + 2 * n_seg - 1] <= capacity
    if fits and not next_fits:
        n_used[0] = end
    if r == 0 and not fits:
        n_used[0] = 0
    if r == R - 1:
        n_wanted[0] = end


@wp.kernel
def pad_tail(
    n_used: wp.array(dtype=wp.int32),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    ray_indices: wp.array(dtype=wp.int32),
):
    """One thread per slot: slots at or past n_used[0] become padding (t 0, 0, ray 0)."""
    i = wp.tid()
    if i >= n_used[0]:
        t_starts[i] = 0.0
        t_ends[i] = 0.0
        ray_indices[i] = 0


def empty_fixed_samples(n_rays: int, capacity: int, device) -> FixedSamples:
    """Output buffers for `march_rays_fixed` (pass as `out=` to reuse them every step)."""
    if capacity < 0 or capacity >= 2**31:
        raise ValueError(f"capacity must be in [0, 2^31), got {capacity}")
    i32 = dict(dtype=torch.int32, device=device)
    return FixedSamples(
        torch.empty(n_rays, 2, **i32),
        torch.empty(capacity, dtype=torch.float32, device=device),
        torch.empty(capacity, dtype=torch.float32, device=device),
        torch.empty(capacity, **i32),
        torch.empty(n_rays, dtype=torch.bool, device=device),
        torch.empty(1, **i32),
        torch.empty(1, **i32),
    )


@functools.cache
def _dtypes() -> tuple[torch.dtype, ...]:
    """The dtypes of `empty_fixed_samples`' buffers, in field order (found once: a check every
    step that allocated its reference buffers would cost seven ops)."""
    return tuple(t.dtype for t in empty_fixed_samples(0, 0, "cpu"))


def check_fixed_out(out: FixedSamples, R: int, capacity: int, dev: torch.device) -> None:
    """ValueError unless `out` holds R rays' and `capacity` slots' contiguous buffers of
    `empty_fixed_samples`' dtypes on `dev`."""
    want = FixedSamples((R, 2), (capacity,), (capacity,), (capacity,), (R,), (1,), (1,))
    for name, t, shape, dtype in zip(FixedSamples._fields, out, want, _dtypes(), strict=True):
        if tuple(t.shape) != shape or t.dtype != dtype or t.device != dev:
            raise ValueError(
                f"out.{name} must be {shape} {dtype} on {dev}, got {tuple(t.shape)} "
                f"{t.dtype} on {t.device}"
            )
        if not t.is_contiguous():
            raise ValueError(f"out.{name} must be contiguous")


def march_rays_fixed(
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    aabb,
    grid: OccupancyGrid | None,
    near: float = 0.0,
    far: float | None = None,
    cone_angle: float = 0.0,
    dt_min: float | None = None,
    dt_max: float | None = None,
    max_samples: int = 1024,
    jitter: torch.Tensor | None = None,
    segments: int | None = None,
    single_pass: bool | None = None,
    *,
    capacity: int,
    out: FixedSamples | None = None,
) -> FixedSamples:
    """`march_rays` into buffers of `capacity` samples, with no host sync (see module doc).

    Args: as `march_rays` (aabb a list or CPU tensor: reading a GPU tensor would sync), plus
        capacity: slots in the sample buffers (a Python int, fixed across steps so that a
            CUDA graph can replay the call).
        out: buffers from `empty_fixed_samples(R, capacity, device)` to write into (reused
            across steps), or None to allocate them.
    Returns:
        FixedSamples(packed_info, t_starts, t_ends, ray_indices, overflow, n_used, n_wanted).
    """
    if isinstance(aabb, torch.Tensor) and aabb.device.type != "cpu":
        raise ValueError("aabb must be a list or a CPU tensor (reading a GPU tensor syncs)")
    p = plan_march(
        rays_o,
        rays_d,
        aabb,
        grid,
        near,
        far,
        cone_angle,
        dt_min,
        dt_max,
        max_samples,
        jitter,
        segments,
    )
    dev = p.like.device
    capacity = int(capacity)
    if out is None:
        out = empty_fixed_samples(p.R, capacity, dev)
    else:
        check_fixed_out(out, p.R, capacity, dev)
    if p.R == 0:
        out.n_used.zero_()
        out.n_wanted.zero_()
    else:
        seg_counts, scratch = count_samples(p, single_pass)
        csum = torch.cumsum(seg_counts, 0, dtype=torch.int32)
        seg_info = torch.empty(p.R * p.n_seg, 2, dtype=torch.int32, device=dev)
        launch(
            reserve_slices,
            p.R,
            p.like,
            [
                csum,
                seg_counts,
                p.n_seg,
                capacity,
                fast_view(out.packed_info, wp.vec2i),
                fast_view(seg_info, wp.vec2i),
                out.overflow,
                out.n_used,
                out.n_wanted,
            ],
        )
        write_samples(p, seg_info, out.t_starts, out.t_ends, out.ray_indices, scratch)
    launch(pad_tail, capacity, p.like, [out.n_used, out.t_starts, out.t_ends, out.ray_indices])
    return out
