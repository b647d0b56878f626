"""Multiresolution hash-grid encoding (instant-ngp), forward and backward as Warp kernels.

Resolution convention (simple, exact, no wrap-around): level l has an integer resolution
``N_l = floor(N_min * b**l)`` with ``b = exp((ln N_max - ln N_min) / (L - 1))``; a point
``x in [0, 1]^3`` lands at ``pos = x * N_l`` on a lattice of ``(N_l + 1)^3`` vertices, cell
``c = min(floor(pos), N_l - 1)`` and trilinear fraction ``f = pos - c`` (so ``x = 1`` is the far
face of the last cell, f = 1). A level whose ``(N_l + 1)^3 <= T`` is stored densely in
``(N_l + 1)^3`` rows (``ix + (N_l+1)*(iy + (N_l+1)*iz)``; the slice is padded to a multiple
of 8 rows, as instant-ngp does, so every level starts 64-byte aligned); finer levels hash the
vertex with ``(ix * 1) ^ (iy * 2654435761) ^ (iz * 805459861)`` in uint32 arithmetic, modulo
T = 2^k.

Parameters live in one table ``(n_params, F)`` float32, level-major: level l occupies rows
``[offset_l, offset_l + size_l)``. Points outside ``[0, 1]^3`` are clamped to the box (their
gradient w.r.t. x is zero, as ``torch.clamp``'s); NaN coordinates give NaN features but never
index out of bounds.

GPU design (each choice measured on an H100 with ``benchmarks/kernels_encoding.py --variants``;
16 levels x 2 features, T = 2^19, 2^20 uniform points: forward 0.57 ms, backward 1.47 ms,
forward+backward 2.0 ms, vs 23 ms for the same op in plain PyTorch):
- one thread per (level, point), level the slow index: the threads in flight touch one level's
  table slice (4 MB, L2-resident) for the gathers and the atomics (point-major order: 3.3 ms);
- features written feature-major, ``(L*F, N)`` storage returned as its transposed ``(N, L*F)``
  view, so adjacent threads write adjacent words (``(N, L*F)`` rows: 3.1 ms);
- sm_90 vector reductions, ``red.global.add.v2.f32`` per corner instead of F scalar atomics
  (4.0 ms without), and x-adjacent corners that share an aligned row pair (x even: dense rows
  are consecutive and the hash flips only bit 0) go through one 16-byte ``ld.v4`` /
  ``red.v4`` (2.4 ms without);
- the backward takes levels 4 at a time with the level as the fastest index, so a row-major
  ``(N, L*F)`` gradient (what a Linear layer's backward gives) is read in whole 32-byte sectors,
  in place with its strides, no transposing copy (2.3 ms ungrouped);
- with ``HashGridConfig.backward_run`` R > 1 the table's backward takes R consecutive points
  per thread and sends one reduction per corner per cell they share (`hashgrid_runs.py`).
Host cost per op is ~60 µs (cached Warp views, recorded launches, cached streams).
"""

import dataclasses
import functools
from dataclasses import dataclass

import numpy as np
import torch
import warp as wp

from .common import FEATURE_DTYPES, as_float32, device_of, fast_view, features_dtype, init, launch
from .gridconfig import HashGridConfig
from .hashgrid_cells import (
    cell_of,
    corner_weight,
    grad_loader,
    grid_index,
    grouped,
    pair_rows,
)
from .hashgrid_runs import run_backward, run_threads
from .rows import tracker_of
from .vector_memory import gather_pair, scatter_func, scatter_pair

init()


def init_table(cfg: HashGridConfig, device="cpu", generator: torch.Generator | None = None):
    """Fresh parameters: (n_params, F) float32, uniform in [-1e-4, 1e-4]."""
    t = torch.empty(cfg.n_params, cfg.n_features, dtype=torch.float32, device=device)
    return t.uniform_(-1e-4, 1e-4, generator=generator)


@wp.kernel(enable_backward=False)
def _grid_index_kernel(
    ijk: wp.array(dtype=wp.vec3i),
    levels: wp.array(dtype=wp.vec4i),
    level: int,
    out: wp.array(dtype=wp.int64),
):
    i = wp.tid()
    v = ijk[i]
    lv = levels[level]
    out[i] = wp.int64(lv[1] + grid_index(v[0], v[1], v[2], lv))


@functools.cache
def _kernels(
    F: int,
    level_outer: bool = True,
    feature_major: bool = True,
    vector_red: bool = True,
    pairs: bool = True,
    group: int = 4,
    bf16: bool = False,
):
    """Forward / backward(table) / backward(x) kernels specialised to F and a launch layout.

    level_outer: thread id -> (level = tid // N, point = tid % N), else (point, level) order.
    feature_major: features stored (L*F, N) (coalesced per feature), else (N, L*F).
    vector_red: scatter with one vector reduction per corner (CUDA sm_90), else Warp's atomics.
    pairs (F = 2 only): x-adjacent corners through one 16-byte access when they share a pair.
    group (backward, with level_outer): levels are taken `group` at a time with the level the
      fastest index, so a row-major (N, L*F) gradient is read in whole 32-byte sectors while the
      table slices in flight (group x 4 MB at T = 2^19) still fit in L2.
    bf16: the features are written, and their gradient read, as bfloat16 (`features_dtype`);
      the arithmetic and the table stay float32.
    The gradient w.r.t. the features is read as an (N, L*F) array with whatever strides it has.
    """
    vec = wp.types.vector(length=F, dtype=wp.float32)
    ft = features_dtype(bf16)
    scatter = scatter_func(F)
    pairs = pairs and F == 2

    @wp.func
    def split(tid: int, n: int, n_levels: int):
        if wp.static(level_outer):
            lv = tid // n
            return lv, tid - lv * n
        i = tid // n_levels
        return tid - i * n_levels, i

    @wp.func
    def split_grouped(tid: int, n: int, n_levels: int):
        if wp.static(level_outer and group > 1):
            return grouped(tid, n, group)
        return split(tid, n, n_levels)

    @wp.func
    def store(out: wp.array2d(dtype=ft), i: int, lv: int, v: vec):
        for k in range(F):
            if wp.static(feature_major):
                out[lv * F + k, i] = ft(v[k])
            else:
                out[i, lv * F + k] = ft(v[k])

    load = grad_loader(F, bf16)

    @wp.func
    def weights_yz(f: wp.vec3, dy: int, dz: int) -> float:
        return wp.where(dy != 0, f[1], 1.0 - f[1]) * wp.where(dz != 0, f[2], 1.0 - f[2])

    @wp.kernel(enable_backward=False, module="unique")
    def forward(
        x: wp.array(dtype=wp.vec3),
        table: wp.array(dtype=vec),
        levels: wp.array(dtype=wp.vec4i),
        n: int,
        n_levels: int,
        out: wp.array2d(dtype=ft),
    ):
        lv, i = split(wp.tid(), n, n_levels)
        level = levels[lv]
        c, f = cell_of(x[i], level[0])
        acc = vec()
        for k in range(4):
            r0, r1 = pair_rows(c, k, level)
            w = weights_yz(f, k & 1, k >> 1)
            if wp.static(pairs):
                q = gather_pair(table, r0, r1)
                acc += (w * (1.0 - f[0])) * vec(q[0], q[1]) + (w * f[0]) * vec(q[2], q[3])
            else:
                acc += (w * (1.0 - f[0])) * table[r0] + (w * f[0]) * table[r1]
        store(out, i, lv, acc)

    @wp.kernel(enable_backward=False, module="unique")
    def backward_table(
        x: wp.array(dtype=wp.vec3),
        grad: wp.array2d(dtype=ft),
        levels: wp.array(dtype=wp.vec4i),
        n: int,
        n_levels: int,
        grad_table: wp.array(dtype=vec),
    ):
        lv, i = split_grouped(wp.tid(), n, n_levels)
        if lv >= n_levels:
            return
        level = levels[lv]
        g = load(grad, i, lv)
        # A point without gradient scatters nothing: the padding of a fixed-capacity march
        # (all at one point, so its atomics would serialise) and samples past a ray's end.
        if wp.length_sq(g) == 0.0:
            return
        c, f = cell_of(x[i], level[0])
        for k in range(4):
            r0, r1 = pair_rows(c, k, level)
            w = weights_yz(f, k & 1, k >> 1)
            g0 = (w * (1.0 - f[0])) * g
            g1 = (w * f[0]) * g
            if wp.static(pairs and vector_red):
                scatter_pair(grad_table, r0, r1, wp.vec4(g0[0], g0[1], g1[0], g1[1]))
            elif wp.static(vector_red):
                scatter(grad_table, r0, g0)
                scatter(grad_table, r1, g1)
            else:
                wp.atomic_add(grad_table, r0, g0)
                wp.atomic_add(grad_table, r1, g1)

    @wp.kernel(enable_backward=False, module="unique")
    def backward_x(
        x: wp.array(dtype=wp.vec3),
        grad: wp.array2d(dtype=ft),
        table: wp.array(dtype=vec),
        levels: wp.array(dtype=wp.vec4i),
        n_levels: int,
        weights: wp.array(dtype=float),
        weighted: int,
        rows: wp.array(dtype=wp.uint8),
        masked: int,
        grad_x: wp.array(dtype=wp.vec3),
    ):
        i = wp.tid()
        if masked != 0 and rows[i] == wp.uint8(0):
            grad_x[i] = wp.vec3()  # a point whose gradient nobody reads: no table reads
            return
        p = x[i]
        dpos = wp.vec3()
        for lv in range(n_levels):
            level = levels[lv]
            g = load(grad, i, lv)
            if weighted != 0:  # x_grad_weights: this level's columns weighted in place
                on = wp.float32(0.0)  # a dynamic variable: the loop adds to it
                for k in range(F):
                    on += wp.abs(weights[lv * F + k])
                    g[k] = g[k] * weights[lv * F + k]
                if on == 0.0:
                    continue  # a level coarse-to-fine holds off adds exactly 0: no table reads
            c, f = cell_of(p, level[0])
            d = wp.vec3()
            for k in range(8):
                dx = k & 1
                dy = (k >> 1) & 1
                dz = (k >> 2) & 1
                row = level[1] + grid_index(c[0] + dx, c[1] + dy, c[2] + dz, level)
                s = wp.dot(g, table[row])
                wx = wp.where(dx != 0, f[0], 1.0 - f[0])
                wy = wp.where(dy != 0, f[1], 1.0 - f[1])
                wz = wp.where(dz != 0, f[2], 1.0 - f[2])
                sx = wp.where(dx != 0, 1.0, -1.0)
                sy = wp.where(dy != 0, 1.0, -1.0)
                sz = wp.where(dz != 0, 1.0, -1.0)
                d += s * wp.vec3(sx * wy * wz, wx * sy * wz, wx * wy * sz)
            dpos += d * float(level[0])
        # torch.clamp's convention: the gradient passes inside [0, 1] (bounds included).
        for k in range(3):
            if p[k] < 0.0 or p[k] > 1.0:
                dpos[k] = 0.0
        grad_x[i] = dpos

    return forward, backward_table, backward_x


@functools.cache
def _tracked_backward(F: int, bf16: bool = False):
    """backward(table) that also marks every row it writes in a `RowTracker`'s mask: the
    row-sparse optimiser's input (kernels/rows.py). One thread per (level, point), level the
    slow index; plain atomics (the CPU's scatter; correct on CUDA too). bf16: the gradient
    arrives as bfloat16."""
    vec = wp.types.vector(length=F, dtype=wp.float32)
    ft = features_dtype(bf16)
    load = grad_loader(F, bf16)

    @wp.kernel(enable_backward=False, module="unique")
    def backward_table_tracked(
        x: wp.array(dtype=wp.vec3),
        grad: wp.array2d(dtype=ft),
        levels: wp.array(dtype=wp.vec4i),
        n: int,
        grad_table: wp.array(dtype=vec),
        mask: wp.array(dtype=wp.uint8),
    ):
        tid = wp.tid()
        lv = tid // n
        i = tid - lv * n
        level = levels[lv]
        g = load(grad, i, lv)
        if wp.length_sq(g) == 0.0:  # as backward_table: nothing to scatter, no row touched
            return
        c, f = cell_of(x[i], level[0])
        for k in range(8):
            dx = k & 1
            dy = (k >> 1) & 1
            dz = (k >> 2) & 1
            row = level[1] + grid_index(c[0] + dx, c[1] + dy, c[2] + dz, level)
            wp.atomic_add(grad_table, row, corner_weight(f, dx, dy, dz) * g)
            mask[row] = wp.uint8(1)

    return backward_table_tracked


@functools.cache
def _unused(dtype, device: str) -> wp.array:
    """A one-element array for an optional kernel argument switched off (never read)."""
    return wp.zeros(1, dtype=dtype, device=device)


@functools.cache
def _vec(F: int):
    return wp.types.vector(length=F, dtype=wp.float32)


@functools.cache
def _levels_wp(cfg: HashGridConfig, device: str) -> wp.array:
    rows = [
        (res, off, int(h), cfg.table_size - 1)
        for res, off, h in zip(cfg.resolutions, cfg.level_offsets[:-1], cfg.hashed, strict=True)
    ]
    return wp.array(np.asarray(rows, dtype=np.int32), dtype=wp.vec4i, device=device)


@dataclass(frozen=True)
class _Variant:
    level_outer: bool = True
    feature_major: bool = True
    vector_red: bool = True
    pairs: bool = True
    group: int = 4
    run: int = 0  # points per thread in the table's backward (`run_backward`); 0: the cfg's

    def kernels(self, F: int, bf16: bool = False):
        return _kernels(
            F, self.level_outer, self.feature_major, self.vector_red, self.pairs, self.group, bf16
        )

    def backward_threads(self, n: int, n_levels: int) -> int:
        g = self.group if self.level_outer else 1
        return n * (-(-n_levels // g) * g)


DEFAULT_VARIANT = _Variant()


def grid_indices(ijk: torch.Tensor, level: int, cfg: HashGridConfig) -> torch.Tensor:
    """Absolute table rows of integer vertices ``ijk`` (M, 3) int32 at ``level`` -> (M,) int64.

    Runs the kernels' own `grid_index`; for tests of the hash and the dense/hashed switch.
    """
    ijk = ijk.to(torch.int32).contiguous()
    dev = device_of(ijk)
    out = torch.empty(ijk.shape[0], dtype=torch.int64, device=ijk.device)
    launch(
        _grid_index_kernel,
        ijk.shape[0],
        ijk,
        [fast_view(ijk, wp.vec3i), _levels_wp(cfg, dev), int(level), out],
    )
    return out


def _alloc_out(
    n: int, cfg: HashGridConfig, variant: _Variant, device, dtype=torch.float32
) -> torch.Tensor:
    """Output storage in the variant's layout: (L*F, N) feature-major or (N, L*F)."""
    rows, cols = cfg.n_output_dims, n
    if not variant.feature_major:
        rows, cols = cols, rows
    return torch.empty(rows, cols, dtype=dtype, device=device)


def _launch_forward(x, table, cfg: HashGridConfig, variant: _Variant, storage: torch.Tensor):
    """Write the features of x into ``storage`` (from `_alloc_out`); returns the (N, L*F) view."""
    n, F, L = x.shape[0], cfg.n_features, cfg.n_levels
    dev = device_of(x)
    if variant.pairs and table.data_ptr() % 16:
        variant = dataclasses.replace(variant, pairs=False)  # 16-byte loads need alignment
    fwd, _, _ = variant.kernels(F, storage.dtype == torch.bfloat16)
    if n:
        launch(
            fwd,
            n * L,
            x,
            [
                fast_view(x, wp.vec3),
                fast_view(table, _vec(F)),
                _levels_wp(cfg, dev),
                n,
                L,
                fast_view(storage),
            ],
        )
    return storage.t() if variant.feature_major else storage


def _launch_tracked(x, g_wp, cfg: HashGridConfig, grad_table, tracker, bf16: bool) -> None:
    """Scatter the gradient into grad_table and mark the rows written in `tracker`."""
    n, F = x.shape[0], cfg.n_features
    launch(
        _tracked_backward(F, bf16),
        n * cfg.n_levels,
        x,
        [
            fast_view(x, wp.vec3),
            g_wp,
            _levels_wp(cfg, device_of(x)),
            n,
            fast_view(grad_table, _vec(F)),
            tracker.mask,
        ],
    )
    tracker.passes += 1


def _gather_points(features: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """(M, C) features in either of the forward's layouts -> (N, C) of `rows` (N,), int32 or
    int64, in the same layout (feature-major storage gathered along its points)."""
    if features.shape[1] > 1 and features.stride(0) == 1:
        return features.t().index_select(1, rows).t()
    return features.index_select(0, rows)


class _HashGridEncode(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, table, cfg, variant, x_grad_weights, x_grad_mask, out_dtype, from_rows):
        if from_rows is not None:
            out = _gather_points(*from_rows)
        else:
            storage = _alloc_out(x.shape[0], cfg, variant, x.device, out_dtype)
            out = _launch_forward(x, table, cfg, variant, storage)
        ctx.save_for_backward(x, table)
        ctx.cfg, ctx.variant, ctx.x_grad_weights = cfg, variant, x_grad_weights
        ctx.x_grad_mask = x_grad_mask
        ctx.tracker = tracker_of(table)  # the rows the backward writes go to its tracker
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):
        x, table = ctx.saved_tensors
        cfg, variant = ctx.cfg, ctx.variant
        n, F, L = x.shape[0], cfg.n_features, cfg.n_levels
        dev = device_of(x)
        bf16 = grad_out.dtype == torch.bfloat16  # autograd hands it in the output's dtype
        _, bwd_table, bwd_x = variant.kernels(F, bf16)
        # Read in place with its strides (a transposing copy would cost more than the reads);
        # zero strides (an expanded gradient) are materialised.
        g = grad_out.contiguous() if 0 in grad_out.stride() else grad_out
        g_wp = fast_view(g)
        vec = _vec(F)
        grad_x = grad_table = None
        if ctx.needs_input_grad[1]:
            grad_table = torch.zeros_like(table)
            run = variant.run or cfg.backward_run
            if n and ctx.tracker is not None:
                _launch_tracked(x, g_wp, cfg, grad_table, ctx.tracker, bf16)
            elif n:
                by_runs = run > 1 and variant.level_outer
                launch(
                    run_backward(F, run, bf16) if by_runs else bwd_table,
                    run_threads(n, L, run) if by_runs else variant.backward_threads(n, L),
                    x,
                    [
                        fast_view(x, wp.vec3),
                        g_wp,
                        _levels_wp(cfg, dev),
                        n,
                        L,
                        fast_view(grad_table, vec),
                    ],
                )
        if ctx.needs_input_grad[0]:
            grad_x = torch.empty_like(x)
            w, mask = ctx.x_grad_weights, ctx.x_grad_mask
            weights = _unused(float, dev) if w is None else fast_view(w)
            rows = _unused(wp.uint8, dev) if mask is None else fast_view(mask.view(torch.uint8))
            if n:
                launch(
                    bwd_x,
                    n,
                    x,
                    [
                        fast_view(x, wp.vec3),
                        g_wp,
                        fast_view(table, vec),
                        _levels_wp(cfg, dev),
                        L,
                        weights,
                        int(w is not None),
                        rows,
                        int(mask is not None),
                        fast_view(grad_x, wp.vec3),
                    ],
                )
        return grad_x, grad_table, None, None, None, None, None, None


def hash_grid_encode(
    x: torch.Tensor,
    table: torch.Tensor,
    cfg: HashGridConfig,
    _variant: _Variant = DEFAULT_VARIANT,
    x_grad_weights: torch.Tensor | None = None,
    x_grad_mask: torch.Tensor | None = None,
    out_dtype: torch.dtype = torch.float32,
    from_rows: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> torch.Tensor:
    """Encode points x: (N, 3) float32 in [0, 1]^3 with table (n_params, F) -> (N, L*F) float32.

    Differentiable w.r.t. ``table`` (scatter-add of dL/dfeature) and ``x`` (only computed when
    x.requires_grad). The result is a transposed view of (L*F, N) storage (feature-major, see the
    module docstring): use ``.contiguous()`` before ``.view``. Runs on x's device.
    x_grad_weights: optional (L*F,) float32 weights of the output columns in the gradient
    w.r.t. x only (coarse-to-fine on the pose gradient, `fastenerf.fields.level_weights`); the
    value and the table's gradient are unweighted.
    x_grad_mask: optional (N,) bool, the points whose gradient w.r.t. x is wanted; the others
    get 0 without their corners being read (a ray whose pose gradient is dropped anyway,
    `PoseCalibration.grad_rays`). The value and the table's gradient are unchanged.
    out_dtype: float32, or bfloat16 for an MLP that runs in it: the features rounded to
    nearest even (as `.to(torch.bfloat16)` of the float32 ones) and their gradient read as
    bfloat16, without a cast's pass over the (N, L*F) features either way; the arithmetic
    and the table stay float32.
    from_rows: optional (features, rows): this encoding of M points made before, in
    out_dtype (e.g. under no_grad, for a prune's density pass), and rows (N,) int32 or int64,
    each of x's points' row in it: the value is gathered from it instead of encoded again
    (the caller vouches that those rows are x's encoding); the backward is unchanged.
    """
    if out_dtype not in FEATURE_DTYPES:
        raise ValueError(
            f"hash_grid_encode: out_dtype must be one of {FEATURE_DTYPES}, got {out_dtype}"
        )
    if x.ndim != 2 or x.shape[1] != 3 or x.dtype != torch.float32:
        raise ValueError(
            f"hash_grid_encode: x must be (N, 3) float32, got {tuple(x.shape)} {x.dtype}"
        )
    if table.shape != (cfg.n_params, cfg.n_features) or table.dtype != torch.float32:
        raise ValueError(
            f"hash_grid_encode: table must be ({cfg.n_params}, {cfg.n_features}) float32, "
            f"got {tuple(table.shape)} {table.dtype}"
        )
    if table.device != x.device:
        raise ValueError(f"hash_grid_encode: x on {x.device} but table on {table.device}")
    if not table.is_contiguous():
        raise ValueError("hash_grid_encode: table must be contiguous")
    if x_grad_weights is not None and x_grad_weights.shape != (cfg.n_output_dims,):
        raise ValueError(
            f"hash_grid_encode: x_grad_weights must be ({cfg.n_output_dims},), "
            f"got {tuple(x_grad_weights.shape)}"
        )
    if x_grad_mask is not None and (
        x_grad_mask.shape != (x.shape[0],)
        or x_grad_mask.dtype != torch.bool
        or x_grad_mask.device != x.device
    ):
        raise ValueError(
            f"hash_grid_encode: x_grad_mask must be ({x.shape[0]},) bool on {x.device}, got "
            f"{tuple(x_grad_mask.shape)} {x_grad_mask.dtype} on {x_grad_mask.device}"
        )
    if from_rows is not None:
        _check_from_rows(*from_rows, x, cfg, out_dtype)
    mask = None if x_grad_mask is None else x_grad_mask.contiguous()
    w = None if x_grad_weights is None else as_float32(x_grad_weights, x.device)
    args = (x.contiguous(), table, cfg, _variant, w, mask, out_dtype, from_rows)
    return _HashGridEncode.apply(*args)


def _check_from_rows(features, rows, x, cfg: HashGridConfig, out_dtype) -> None:
    """ValueError unless `hash_grid_encode`'s from_rows fit x and the encoding."""
    c = cfg.n_output_dims
    if features.ndim != 2 or features.shape[1] != c or features.dtype != out_dtype:
        raise ValueError(
            f"hash_grid_encode: from_rows' features must be (M, {c}) {out_dtype}, got "
            f"{tuple(features.shape)} {features.dtype}"
        )
    if rows.shape != (x.shape[0],) or rows.dtype not in (torch.int32, torch.int64):
        raise ValueError(
            f"hash_grid_encode: from_rows' rows must be ({x.shape[0]},) int32 or int64, got "
            f"{tuple(rows.shape)} {rows.dtype}"
        )
    if features.device != x.device or rows.device != x.device:
        raise ValueError(f"hash_grid_encode: from_rows must be on x's device, {x.device}")
