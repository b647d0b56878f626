"""Ray–AABB intersection and occupancy-guided ray marching into packed samples.

Samples are the intervals of a lattice along each ray (lattice.py: instant-ngp's cone rule
dt = clamp(t * cone_angle, dt_min, dt_max), in closed form). A candidate interval is kept when
the cell holding its midpoint is occupied (and, with a cylinder clip, the midpoint lies in the
cylinder). The march jumps over an empty cell (or an empty block of cells) in O(1), to the first
interval whose midpoint is past its exit, and takes an occupied cell's further samples as one
run up to the first midpoint past its exit; so the result equals dense stepping over every
interval (tests check exactly that, up to midpoints within float rounding of a cell face) while
touching only occupied cells. Runs and block jumps change no sample of the per-sample,
cell-by-cell march, except a midpoint within float rounding of a block face, which the jump
may place on the other side.

Output (nerfacc's packed convention): packed_info (R, 2) int32 (first sample, count),
t_starts/t_ends (S,) float32 world units along the unit direction, ray_indices (S,) int32.
Two passes run the same compiled kernel (so they agree bit for bit): count, exclusive scan
(torch.cumsum), write. A pass may split each ray's lattice over several threads (`segments`),
which changes nothing in the output; the max_samples cap keeps each ray's nearest samples.
Jumps in empty space go cell by cell at the cascade of the sample (no mip from dt, unlike
instant-ngp), and block by block where the grid's `blocks` (F**3 cells) are empty. No
gradients: sample positions are not differentiated. `march_rays_fixed` (raymarch_fixed.py) runs
the same passes into fixed-size buffers with no host sync.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import torch
import warp as wp

from . import march_scratch
from .common import as_float32, fast_view, init, launch
from .lattice import StepRule, lattice_point, make_lattice, run_end, step_rule, u_of
from .occupancy import (
    OccupancyGrid,
    bit_at,
    block_bit,
    block_corner,
    cell_lo,
    cell_size,
    default_step_size,
    locate_func,
)

_empty = torch.empty

RUNS: bool | str = "auto"
"""An occupied cell's samples as one run (False: one test per sample); "auto": on CUDA only.
The run's closed form pays where it spares a GPU's threads their per-sample branches; the CPU
backend runs a thread's samples one after another, and there it costs more than it saves."""
_PARALLEL = 1e-12  # |d_k| below this: the ray is parallel to the slab (avoids 0 * inf = NaN)


@wp.func
def ray_box(o: wp.vec3, d: wp.vec3, lo: wp.vec3, hi: wp.vec3):
    """Slab test: (t_min, t_max) of the line o + t d inside [lo, hi] (t_min > t_max: miss).

    An axis with d_k ~ 0 constrains nothing when lo_k <= o_k <= hi_k and misses otherwise, so
    rays lying in a face plane are handled without forming 0 * inf.
    """
    tmin = wp.float32(-1e30)
    tmax = wp.float32(1e30)
    for k in range(3):
        if wp.abs(d[k]) < _PARALLEL:
            if o[k] < lo[k] or o[k] > hi[k]:
                tmin = wp.float32(1e30)
                tmax = wp.float32(-1e30)
        else:
            ta = (lo[k] - o[k]) / d[k]
            tb = (hi[k] - o[k]) / d[k]
            tmin = wp.max(tmin, wp.min(ta, tb))
            tmax = wp.min(tmax, wp.max(ta, tb))
    return tmin, tmax


@wp.kernel
def _ray_aabb(
    rays_o: wp.array(dtype=wp.vec3),
    rays_d: wp.array(dtype=wp.vec3),
    lo: wp.vec3,
    hi: wp.vec3,
    near: float,
    far: float,
    t_near: wp.array(dtype=float),
    t_far: wp.array(dtype=float),
):
    r = wp.tid()
    tmin, tmax = ray_box(rays_o[r], rays_d[r], lo, hi)
    tmin = wp.max(tmin, near)
    tmax = wp.min(tmax, far)
    if tmax > tmin:
        t_near[r] = tmin
        t_far[r] = tmax
    else:
        t_near[r] = wp.inf
        t_far[r] = wp.inf


@wp.func
def safe_inverse(d: wp.vec3) -> wp.vec3:
    """1 / d per axis, 0 where the ray is parallel to the axis' slabs."""
    inv = wp.vec3(0.0)
    for k in range(3):
        if wp.abs(d[k]) >= _PARALLEL:
            inv[k] = 1.0 / d[k]
    return inv


@wp.func
def cell_exit(o: wp.vec3, d: wp.vec3, inv_d: wp.vec3, lo: wp.vec3, hi: wp.vec3) -> float:
    """t at which the ray leaves the box [lo, hi] it is inside (1e30 if never)."""
    t = wp.float32(1e30)
    for k in range(3):
        if d[k] >= _PARALLEL:
            t = wp.min(t, (hi[k] - o[k]) * inv_d[k])
        elif d[k] <= -_PARALLEL:
            t = wp.min(t, (lo[k] - o[k]) * inv_d[k])
    return t


@functools.cache
def _march_kernel(n_cascades: int, cylinder: bool, block: int = 1, runs: bool = True):
    """Marcher specialised to the grid: `n_cascades` = 0 means no grid (all occupied); the
    cylinder test is compiled in only when the scene has one; `block` > 1: an empty cell in an
    empty block of block**3 cells skips the whole block; `runs`: an occupied cell's further
    samples are taken as one run (not with a cylinder, and only on rays whose lattice points
    are strictly increasing in float32: steps over ~1e-6 of t, under 4e6 intervals).

    One thread marches one segment of one ray: segment j of n_seg covers lattice intervals
    [K j / n_seg, K (j + 1) / n_seg) of the ray's K, the last one open-ended. Decisions depend
    only on each interval's midpoint, so any split gives the same samples; splitting gives the
    GPU enough threads when rays are few."""
    locate = locate_func(max(n_cascades, 1))

    @wp.kernel(module="unique")
    def march(
        rays_o: wp.array(dtype=wp.vec3),
        rays_d: wp.array(dtype=wp.vec3),
        lo: wp.vec3,
        hi: wp.vec3,
        near: float,
        far: float,
        rule: StepRule,
        center: wp.vec3,
        half: wp.vec3,
        inv_half: wp.vec3,
        res: int,
        bitfield: wp.array(dtype=wp.uint8),
        blocks: wp.array(dtype=wp.uint8),
        cyl: wp.vec3,
        jitter: wp.array(dtype=float),
        use_jitter: int,
        max_samples: int,
        n_seg: int,
        write: int,
        stride: int,
        counts: wp.array(dtype=wp.int32),
        seg_info: wp.array(dtype=wp.vec2i),
        t_starts: wp.array(dtype=float),
        t_ends: wp.array(dtype=float),
        ray_indices: wp.array(dtype=wp.int32),
    ):
        tid = wp.tid()
        # write 0: count (to max_samples); 1: write seg_info's slice (with stride > 0 only
        # the slices longer than stride: the shorter came from the scratch); 2: count and
        # keep the first `stride` samples in this thread's scratch rows (single pass)
        limit = max_samples
        base = wp.int32(0)
        if write == 1:
            base = seg_info[tid][0]
            limit = seg_info[tid][1]
            if stride > 0 and limit <= stride:
                return
        if write == 2:
            base = tid * stride
        r = tid / n_seg
        seg = tid - r * n_seg
        o = rays_o[r]
        d = rays_d[r]
        t0, t1 = ray_box(o, d, lo, hi)
        t0 = wp.max(t0, near)
        t1 = wp.min(t1, far)
        jm1 = wp.float32(-1.0)
        if use_jitter != 0:
            jm1 = jitter[r] - 1.0
        lat = make_lattice(rule, t0, jm1)
        k = wp.int32(0)
        k_hi = wp.int32(1 << 30)
        if n_seg > 1 and t1 > t0:
            K = int(wp.min(u_of(rule, lat, t1) - jm1, 6.0e7)) + 2
            k = (K * seg) / n_seg
            if seg < n_seg - 1:
                k_hi = (K * (seg + 1)) / n_seg
        inv_d = safe_inverse(d)
        n = wp.int32(0)
        # runs only where the lattice is strictly increasing in float32 (steps of >= ~8 ulps of
        # t, fewer than 2^22 intervals): else a run would take the empty intervals that the
        # per-sample test drops; this also keeps t1 ~ 1e30 (d ~ 0, no far) off the run path
        run_ok = rule.a * 1048576.0 > wp.max(wp.abs(t0), wp.abs(t1))
        if run_ok:
            run_ok = u_of(rule, lat, t1) - jm1 < 4.0e6
        ta = lattice_point(rule, lat, k)
        tb_raw = lattice_point(rule, lat, k + 1)
        # t before which midpoints are known to lie in the current (occupied) cell: saves the
        # cell lookup for the ~4 samples per cell after the first
        occ_until = wp.float32(-1.0)
        while n < limit and k < k_hi and ta < t1:
            tb = wp.min(tb_raw, t1)
            step = wp.int32(1)
            if tb > ta:  # else: empty first interval (no jitter) or rounding
                mid = 0.5 * (ta + tb)
                p = o + mid * d
                occ = wp.int32(1)
                if wp.static(n_cascades > 0):
                    if mid >= occ_until:
                        c = locate(p, center, inv_half, res)
                        occ = bit_at(bitfield, c, res)
                        size = cell_size(c[0], half, res)
                        clo = cell_lo(c, center, half, res)
                        chi = clo + size
                        if wp.static(block > 1):
                            if occ == 0 and c[0] >= 0:
                                if block_bit(blocks, c, res, block) == 0:
                                    # the block's faces as its first / last cells compute theirs
                                    c0 = block_corner(c, block)
                                    clo = cell_lo(c0, center, half, res)
                                    c1 = c0 + wp.vec4i(0, block - 1, block - 1, block - 1)
                                    chi = cell_lo(c1, center, half, res) + size
                        B = cell_exit(o, d, inv_d, clo, chi)
                        if occ != 0:
                            occ_until = B
                        else:
                            # Skip the empty cell: to the first interval whose midpoint is past
                            # its exit B. B lies in interval floor(u(B) - j + 1); that one or the
                            # next. (Rounding only matters where the midpoint is at B.)
                            if B >= t1:
                                break
                            ub = wp.min(u_of(rule, lat, B) - jm1, 1.0e9)
                            kk = wp.max(k + 1, int(wp.floor(ub)))
                            if kk < k_hi:
                                qa = lattice_point(rule, lat, kk)
                                qb = wp.min(lattice_point(rule, lat, kk + 1), t1)
                                if qa < t1 and 0.5 * (qa + qb) < B:
                                    kk += 1
                            step = kk - k
                if occ != 0:
                    if wp.static(cylinder):
                        if (
                            p[0] * p[0] + p[2] * p[2] > cyl[0] * cyl[0]
                            or p[1] < cyl[1]
                            or (p[1] > cyl[2])
                        ):
                            occ = 0
                    if occ != 0:
                        if write == 1 or (write == 2 and n < stride):
                            t_starts[base + n] = ta
                            t_ends[base + n] = tb
                            if write == 1:
                                ray_indices[base + n] = r
                        n += 1
                        if wp.static(runs and not cylinder):
                            if run_ok:
                                # The cell's further samples in one run (their midpoints lie before
                                # its exit): counted at once, written without a test each.
                                end = occ_until
                                if wp.static(n_cascades == 0):
                                    end = wp.float32(1.0e30)
                                # capped at the samples still allowed: bounded work, no int overflow
                                kk_cap = k + 1 + wp.min(k_hi - k - 1, limit - n)
                                kk = run_end(rule, lat, k, kk_cap, t1, end)
                                m = wp.min(kk - k - 1, limit - n)
                                if write != 0:
                                    m_w = m
                                    if write == 2:
                                        m_w = wp.max(wp.min(m, stride - n), 0)
                                    t = tb_raw
                                    for i in range(m_w):
                                        t_next = lattice_point(rule, lat, k + 2 + i)
                                        t_starts[base + n + i] = t
                                        t_ends[base + n + i] = wp.min(t_next, t1)
                                        if write == 1:
                                            ray_indices[base + n + i] = r
                                        t = t_next
                                n += m
                                step = kk - k
            k += step
            if step == 1:
                ta = tb_raw
            else:
                ta = lattice_point(rule, lat, k)
            tb_raw = lattice_point(rule, lat, k + 1)
        if write == 1:
            # never reached (both passes run this same code); keeps the buffer fully written
            for i in range(n, limit):
                t_starts[base + i] = t1
                t_ends[base + i] = t1
                ray_indices[base + i] = r
        else:
            counts[tid] = n

    return march


def _box_of(aabb) -> list[float]:
    a = [float(v) for v in (aabb.tolist() if isinstance(aabb, torch.Tensor) else aabb)]
    if len(a) != 6:
        raise ValueError(f"aabb must have 6 values, got {len(a)}")
    return a


def ray_aabb(
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    aabb,
    near: float = 0.0,
    far: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry and exit distance of each ray in the box, clamped to [near, far].

    Args:
        rays_o, rays_d: (R, 3) float32 origins and directions, world units.
        aabb: (6,) [xmin, ymin, zmin, xmax, ymax, zmax].
    Returns:
        t_near, t_far: (R,) float32; a ray starting inside has t_near = near; a ray that
        misses (or only touches the box, zero length) has t_near = t_far = inf.
    """
    init()
    a = _box_of(aabb)
    rays_o = as_float32(rays_o)
    rays_d = as_float32(rays_d)
    R = rays_o.shape[0]
    t_near = _empty(R, dtype=torch.float32, device=rays_o.device)
    t_far = _empty(R, dtype=torch.float32, device=rays_o.device)
    if R > 0:
        launch(
            _ray_aabb,
            R,
            rays_o,
            [
                fast_view(rays_o, wp.vec3),
                fast_view(rays_d, wp.vec3),
                wp.vec3(*a[:3]),
                wp.vec3(*a[3:]),
                float(near),
                1e30 if far is None else float(far),
                t_near,
                t_far,
            ],
        )
    return t_near, t_far


class MarchPlan(NamedTuple):
    """A march's compiled kernel, its leading launch arguments and its sizes."""

    kernel: object
    head: list
    R: int
    n_seg: int
    max_samples: int
    like: torch.Tensor
    bound: int  # samples a thread takes at most, degenerate rays aside (march_scratch)


def plan_march(
    rays_o, rays_d, aabb, grid, near, far, cone_angle, dt_min, dt_max, max_samples, jitter, segments
) -> MarchPlan:
    """Checks the arguments and gathers what both passes of a march launch with (no sync)."""
    init()
    box = _box_of(aabb)
    if grid is not None:
        outer = grid.outer_aabb()
        box = [max(box[i], outer[i]) for i in range(3)] + [min(box[i], outer[i]) for i in (3, 4, 5)]
    if dt_min is None:
        dt_min = grid.step_size if grid is not None else default_step_size(box)
    if dt_max is None:
        if grid is not None:
            a = grid.aabb_list
            edge = max(a[3] - a[0], a[4] - a[1], a[5] - a[2]) * 2 ** (grid.n_cascades - 1)
            edge /= grid.resolution
        else:
            edge = max(box[3] - box[0], box[4] - box[1], box[5] - box[2]) / 128
        dt_max = max(dt_min, math.sqrt(3.0) * edge)
    rule = step_rule(float(cone_angle), float(dt_min), float(dt_max))
    if max_samples < 0:
        raise ValueError(f"max_samples must be >= 0, got {max_samples}")
    rays_o = as_float32(rays_o)
    rays_d = as_float32(rays_d)
    R, dev = rays_o.shape[0], rays_o.device
    if jitter is not None:
        jitter = as_float32(jitter, dev)
        if jitter.shape != (R,):
            raise ValueError(f"jitter must be ({R},), got {tuple(jitter.shape)}")
    runs = bool(RUNS) if RUNS != "auto" else dev.type == "cuda"
    if grid is not None:
        kernel = _march_kernel(grid.n_cascades, grid.cylinder is not None, grid.block, runs)
        geom = [grid.center, grid.half, grid.inv_half, grid.resolution, grid.bitfield, grid.blocks]
        cyl = wp.vec3(*grid.cylinder) if grid.cylinder is not None else wp.vec3(0.0)
    else:
        kernel = _march_kernel(0, False, 1, runs)
        geom = [wp.vec3(0.0), wp.vec3(1.0), wp.vec3(1.0), 2, *[_dummy(dev, torch.uint8)] * 2]
        cyl = wp.vec3(0.0)
    if segments is None:
        # Measured on an H100 (shell scene, 128^3): 4096 rays 1.35 -> 0.95 ms with 8 segments,
        # 16384 rays 1.36 -> 1.13 ms with 2, 65536 rays slower with any split. The CPU backend
        # runs threads one after another: no split.
        segments = 1 if dev.type == "cpu" else max(1, min(8, 2**15 // max(R, 1)))
    n_seg = int(segments)
    if n_seg < 1:
        raise ValueError(f"segments must be >= 1, got {segments}")
    head = [
        fast_view(rays_o, wp.vec3),
        fast_view(rays_d, wp.vec3),
        wp.vec3(*box[:3]),
        wp.vec3(*box[3:]),
        float(near),
        1e30 if far is None else float(far),
        rule,
        *geom,
        cyl,
        jitter if jitter is not None else _dummy(dev, torch.float32),
        int(jitter is not None),
        int(max_samples),
        n_seg,
    ]
    bound = march_scratch.thread_bound(box, rule.a, int(max_samples), n_seg)
    return MarchPlan(kernel, head, R, n_seg, int(max_samples), rays_o, bound)


@functools.cache
def _dummy_cached(dev: torch.device, dtype: torch.dtype, width: int) -> torch.Tensor:
    return torch.zeros((1,) if width == 1 else (1, width), dtype=dtype, device=dev)


def _dummy(dev: torch.device, dtype: torch.dtype, width: int = 1) -> torch.Tensor:
    """A placeholder for an unread kernel argument, (1,) or (1, width) (cached: no per-call
    allocation, which also keeps the launch graph-capturable)."""
    return _dummy_cached(torch.device(dev), dtype, width)


@wp.kernel(enable_backward=False)
def _cap_segments(counts: wp.array(dtype=wp.int32), n_seg: int, max_samples: int):
    """One thread per ray: its segments' counts capped in place so that they add up to at most
    max_samples, the nearest segments first (segment j keeps what the earlier ones left)."""
    r = wp.tid()
    left = max_samples
    for j in range(n_seg):
        take = wp.min(counts[r * n_seg + j], left)
        counts[r * n_seg + j] = take
        left = left - take


def count_samples(
    p: MarchPlan, single_pass: bool | None = None
) -> tuple[torch.Tensor, march_scratch.Scratch | None]:
    """Samples of each (ray, segment), (R * n_seg,) int32, the per-ray cap applied; with a
    single pass (`march_scratch.SINGLE_PASS` unless given) also the samples, in scratch rows."""
    dev, threads = p.like.device, p.R * p.n_seg
    counts = _empty(threads, dtype=torch.int32, device=dev)
    f0, i0 = _dummy(dev, torch.float32), _dummy(dev, torch.int32)
    si0 = _dummy(dev, torch.int32, 2)  # never read while counting
    stride = march_scratch.scratch_stride(threads, p.bound, single_pass)
    scratch = march_scratch.new_scratch(threads, stride, dev) if stride else None
    ts, te = (scratch.t_starts, scratch.t_ends) if stride else (f0, f0)
    args = [*p.head, 2 if stride else 0, stride, counts, fast_view(si0, wp.vec2i), ts, te, i0]
    launch(p.kernel, p.R * p.n_seg, p.like, args)
    if p.n_seg > 1:
        # the cap keeps each ray's nearest samples; one kernel, where a row-wise cumsum, clamp
        # and diff took five (the cumsum alone 0.1 ms of an H200 step at 8,192 rays x 4)
        launch(_cap_segments, p.R, p.like, [counts, p.n_seg, p.max_samples])
    return counts, scratch


def write_samples(p: MarchPlan, seg_info, t_starts, t_ends, ray_indices, scratch=None) -> None:
    """Writes segment j's samples at seg_info[j] = (first slot, count), (R * n_seg, 2) int32:
    marched again, or copied from `count_samples`' scratch rows (a slice longer than its row
    marched again, in a launch whose other threads return at once)."""
    counts, stride, si = _dummy(p.like.device, torch.int32), 0, fast_view(seg_info, wp.vec2i)
    if scratch is not None:
        stride = scratch.stride
        march_scratch.place_rows(scratch, p.n_seg, si, t_starts, t_ends, ray_indices)
    args = [*p.head, 1, stride, counts, si, t_starts, t_ends, ray_indices]
    launch(p.kernel, p.R * p.n_seg, p.like, args)


def march_rays(
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
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Sample intervals along rays at occupied cells only (no gradients).

    Args:
        rays_o: (R, 3) float32 origins, world units.
        rays_d: (R, 3) float32 unit directions (t is then distance).
        aabb: (6,) box to march in; it is also clipped to the grid's outermost cascade.
        grid: occupancy grid, or None to treat the whole box as occupied.
        near, far: range of t, world units (far None: unbounded).
        cone_angle: dt grows as t * cone_angle (0: constant steps of dt_min).
        dt_min: smallest step (default: the grid's step_size, or √3/1024 · max box side).
        dt_max: largest step (default: √3 · coarsest cell edge, instant-ngp's choice).
        max_samples: cap on samples per ray (the nearest ones are kept).
        jitter: (R,) float32 in [0, 1) shifts each ray's lattice (training), None: no shift.
            Fixed jitter gives bit-identical output.
        segments: threads per ray (each marches a contiguous part of the ray's lattice; the
            output does not depend on it). Default: 1 on CPU; on GPU 2^15 / R, in 1..8.
        single_pass: march once into scratch rows, then copy (`count_samples`), instead of
            twice; the same output. None: `SINGLE_PASS`.
    Returns:
        packed_info (R, 2) int32, t_starts (S,), t_ends (S,) float32, ray_indices (S,) int32.
        S is read back from the GPU (one host sync): `march_rays_fixed` avoids it.
    """
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
    R, n_seg, dev = p.R, p.n_seg, p.like.device
    seg_counts, scratch = count_samples(p, single_pass)
    csum = torch.cumsum(seg_counts, 0, dtype=torch.int32)
    seg_info = torch.stack([csum - seg_counts, seg_counts], 1).contiguous()
    per_ray = seg_counts.view(R, n_seg).sum(1, dtype=torch.int32)
    packed_info = torch.stack([seg_info.view(R, n_seg, 2)[:, 0, 0], per_ray], 1).contiguous()
    S = int(csum[-1]) if R > 0 else 0
    t_starts = _empty(S, dtype=torch.float32, device=dev)
    t_ends = _empty(S, dtype=torch.float32, device=dev)
    ray_indices = _empty(S, dtype=torch.int32, device=dev)
    if S > 0:
        write_samples(p, seg_info, t_starts, t_ends, ray_indices, scratch)
    return packed_info, t_starts, t_ends, ray_indices
