"""Fully fused MLP (tiny-cuda-nn's FullyFusedMLP) as Warp tile kernels, forward and backward.

Not wired into the ngp field: on an H200 it measured slower than torch's bf16 MLPs (float32
cuBLASDx products without tensor cores, one block per SM in the colour backward; numbers and
command in benchmarks/RESULTS.md), so it stays a benchmarked alternative to tune (TF32, bf16).

The op: ``y = W_{L-1} relu(... relu(W_1 relu(W_0 x)))`` per row, no biases (the ngp field's
density MLP 32 -> 64 -> 16 and its colour MLP's function, 31 -> 64 -> 64 -> 3, which the field
runs padded to 32 -> 64 -> 64 -> 8 for cuBLAS: `fastenerf.fields.mlp`).
- x: (N, C_0) float32, N >= 0 (any N). Row-major, or column-major (a transposed (C_0, N)
  array, as `hash_grid_encode` returns its features) read in place; other strides are copied.
- weights: L tensors (C_{k+1}, C_k) float32 in nn.Linear's (out, in) layout.
- y: (N, C_L) float32. Unitless features; gradients are w.r.t. x (only when asked) and every
  weight. ReLU is torch's: NaN passes through; its derivative is 0 where the output is <= 0, else 1.

Layout and design:
- The weights travel as one flat float32 vector (the row-major weights one after the other,
  one `torch.cat` a call) that each block loads once into shared memory; layer k is a
  reshaped view of it. The weight gradient is the same flat layout; the per-layer gradients
  handed back are views of it.
- One block of `block_dim` threads takes a tile of `tile` consecutive rows at a time: it loads
  the (tile, C_0) slice of x into shared memory and runs every layer on it with
  `wp.tile_matmul` (cuBLASDx on CUDA, a scalar GEMM on the CPU) and elementwise ReLUs, so the
  hidden activations never leave the block: memory traffic is x and y only (plus dy and dx in
  the backward), against every layer's activations written and re-read by separate kernels.
- Blocks are persistent: `blocks` of them (default a few per SM) stride over the tiles, so
  the weights are loaded, and the weight gradient accumulated in shared memory, once per block
  rather than once per tile.
- The backward saves nothing but x and the weights: per tile it recomputes the hidden
  activations layer by layer, then back-propagates (dZ = dH * [H > 0], dW += dZ^T A,
  dA = dZ W). Each block's dW (the flat (sum C_{k+1} C_k,) vector, 25 KB for the colour MLP)
  is accumulated in shared memory over its tiles and added into the global gradient with one
  `tile_atomic_add` at its end. Atomics rather than a deterministic two-pass reduction:
  with persistent blocks there are only a few hundred adds per weight, so contention and a
  (blocks, n_params) scratch buffer plus its reduction kernel buy nothing; the cost is that
  the float32 sum's rounding order, hence its last bits, vary from run to run on CUDA.
- Rows past N in the last tile: Warp 1.19 documents that `tile_load` (bounds_check defaults
  to True) reads coordinates at or past the array's extent as zero, and `tile_store` /
  `tile_atomic_add` skip them; zero rows give zero activations and zero dY, so they add
  nothing to dW. No padding is needed.
- Kernels are generated per (layer widths, tile, precision, x-gradient or not, x layout) and
  cached (Warp compiles each for the block_dim it is launched with); all widths and offsets
  are compile-time constants. `tf32=True` lets cuBLASDx use TF32 tensor cores (float32
  storage and accumulation, ~1e-3 relative products; CUDA only, the CPU ignores it).
- Shared memory per block, float32: forward (n_params + tile * sum C_k) words, backward
  (2 n_params + tile * (sum C_k + 2 max C_{<L})). Colour MLP at tile 64: 65 KB / 122 KB
  (at 128: 106 KB / 194 KB, near the H100's 227 KB per block); density: 40 KB / 84 KB.
  Persistent blocks are sized from these (at most BLOCKS_PER_SM per SM).
- First call on CUDA: each kernel (forward; backward with or without dX) compiles its
  cuBLASDx GEMMs, 1.5-3.5 min apiece for sm_90 on a 2-core machine; Warp caches the result.
- Launches go on torch's current stream from a recorded `wp.Launch`: no host synchronisation,
  allocations sized by shapes only, so a CUDA graph can capture the op. A 0-row input
  launches nothing (empty y, zero weight gradient).
"""

from __future__ import annotations

import functools
from typing import Any

import torch
import warp as wp

from .common import fast_view, init, tiled_launcher

init()

DEFAULT_TILE = 64  # rows per tile
DEFAULT_BLOCK_DIM = 128  # threads per block (4 warps)
BLOCKS_PER_SM = 4  # persistent blocks per SM on CUDA (fewer if shared memory runs out)


# ---------------------------------------------------------------------------------------------
# Elementwise pieces. The kernels pass them to wp.tile_map as wp.static(f): Warp 1.19's cache
# key misses a function that is only an argument, so an edit to one would reuse stale binaries.


@wp.func
def relu(z: float) -> float:
    """max(z, 0), NaN kept (as torch.relu)."""
    return wp.where(z < 0.0, 0.0, z)


@wp.func
def ident(v: float) -> float:
    return v


@wp.func
def relu_grad(h: float, g: float) -> float:
    """0 where the ReLU's output h is <= 0, else g (torch's threshold_backward: NaN passes g)."""
    return wp.where(h <= 0.0, 0.0, g)


# ---------------------------------------------------------------------------------------------
# Kernel factory


class _Plan:
    """Compile-time layout: flat weight offsets and the block's shared workspace.

    Workspace (float32, row-major (tile, C) blocks one after the other): the input of every
    layer a_0 .. a_{L-1} (a_0 = the x tile, a_k = relu(z_{k-1})), then the (tile, C_L) output
    (forward: y; backward: dY), then, backward only, two gradient buffers of
    (tile, max C_0..C_{L-1}) used in turn for dZ / dA.
    """

    def __init__(self, dims: tuple[int, ...], tile: int, tf32: bool, x_cols: bool, kind: str):
        self.dims, self.tile, self.n_layers = dims, tile, len(dims) - 1
        self.tf32, self.x_cols, self.kind = tf32, x_cols, kind  # kind: "fwd", "bwd", "bwd_dx"
        self.want_dx = kind == "bwd_dx"
        self.w_off = [0]
        for k in range(self.n_layers):
            self.w_off.append(self.w_off[-1] + dims[k + 1] * dims[k])
        self.n_params = self.w_off[-1]
        self.act_off = [0]
        for c in dims:
            self.act_off.append(self.act_off[-1] + tile * c)
        self.fwd_size = self.act_off[-1]  # a_0 .. a_{L-1} and the output
        wide = tile * max(dims[:-1])
        self.grad_off = (self.fwd_size, self.fwd_size + wide)
        self.bwd_size = self.fwd_size + 2 * wide

    def dz_buffer(self, k: int) -> int:
        """Workspace offset of layer k's dZ (tile, C_{k+1}): dY for the last layer, else the
        gradient buffers in turn (layer k's dA is layer k-1's dZ)."""
        last = self.n_layers - 1
        return self.act_off[last + 1] if k == last else self.grad_off[(last - 1 - k) % 2]

    def dx_buffer(self) -> int:
        """Workspace offset of dA_0 = dX: the gradient buffer that is not layer 0's dZ."""
        return self.grad_off[1] if self.dz_buffer(0) == self.grad_off[0] else self.grad_off[0]


def _name(plan: _Plan, what: str) -> str:
    """A function name of its own for each kernel variant and part: Warp registers functions
    by name, and generic (Any-typed) ones sharing a name would be taken for one function, their
    tile shapes fixed by the first caller."""
    flags = ("_tf32" if plan.tf32 else "") + ("_xt" if plan.x_cols else "")
    return f"mlp_{'x'.join(map(str, plan.dims))}_t{plan.tile}{flags}_{plan.kind}_{what}"


def _view(name: str, offset: int, rows: int, cols: int):
    """wp.func view(flat) -> the (rows, cols) row-major block of a flat shared tile at offset
    (non-owning: no copy, no shared memory)."""

    @wp.func(name=name)
    def view(flat: Any):
        part = wp.tile_view(flat, offset=(wp.static(offset),), shape=(wp.static(rows * cols),))
        return wp.tile_reshape(part, shape=(wp.static(rows), wp.static(cols)))

    return view


def _matmul(name: str, tf32: bool, beta: float):
    """wp.func mm(a, b, out): out = a @ b + beta * out (TF32 products on CUDA when tf32)."""

    @wp.func(name=name)
    def mm(a: Any, b: Any, out: Any):
        if wp.static(tf32):
            wp.tile_matmul(a, b, out, alpha=1.0, beta=wp.static(beta), precision="tf32")
        else:
            wp.tile_matmul(a, b, out, alpha=1.0, beta=wp.static(beta))

    return mm


def _chain(name: str, steps: list):
    """wp.func f(w_flat, g_flat, work) running steps (functions of the same arguments) in order."""
    if len(steps) == 1:
        return steps[0]
    head, rest = steps[0], _chain(name + "_", steps[1:])

    @wp.func(name=name)
    def chain(w_flat: Any, g_flat: Any, work: Any):
        head(w_flat, g_flat, work)
        rest(w_flat, g_flat, work)

    return chain


def _forward_step(plan: _Plan, k: int):
    """wp.func: a_{k+1} = relu(a_k @ W_k^T) (the output, no ReLU, for the last layer)."""
    d, t, tf32, last = plan.dims, plan.tile, plan.tf32, k == plan.n_layers - 1
    tag = functools.partial(_name, plan)
    a_of = _view(tag(f"a{k}"), plan.act_off[k], t, d[k])
    z_of = _view(tag(f"a{k + 1}"), plan.act_off[k + 1], t, d[k + 1])
    w_of = _view(tag(f"w{k}"), plan.w_off[k], d[k + 1], d[k])
    mm = _matmul(tag(f"mm{k}"), tf32, 0.0)

    @wp.func(name=tag(f"fwd{k}"))
    def step(w_flat: Any, g_flat: Any, work: Any):
        z = z_of(work)
        mm(a_of(work), wp.tile_transpose(w_of(w_flat)), z)
        if wp.static(not last):
            wp.tile_assign(z, wp.tile_map(wp.static(relu), z))  # in place

    return step


def _backward_step(plan: _Plan, k: int):
    """wp.func: dW_k += dZ_k^T a_k; dA_k = dZ_k W_k, then (k > 0) dZ_{k-1} = dA_k [a_k > 0]."""
    d, t, tf32, want_da = plan.dims, plan.tile, plan.tf32, plan.want_dx or k > 0
    tag = functools.partial(_name, plan)
    a_of = _view(tag(f"ba{k}"), plan.act_off[k], t, d[k])
    dz_of = _view(tag(f"dz{k}"), plan.dz_buffer(k), t, d[k + 1])
    da_of = _view(tag(f"da{k}"), plan.dz_buffer(k - 1) if k else plan.dx_buffer(), t, d[k])
    w_of = _view(tag(f"bw{k}"), plan.w_off[k], d[k + 1], d[k])
    mm_dw, mm_da = _matmul(tag(f"mm_dw{k}"), tf32, 1.0), _matmul(tag(f"mm_da{k}"), tf32, 0.0)

    @wp.func(name=tag(f"bwd{k}"))
    def step(w_flat: Any, g_flat: Any, work: Any):
        dz, a = dz_of(work), a_of(work)
        mm_dw(wp.tile_transpose(dz), a, w_of(g_flat))
        if wp.static(want_da):
            da = da_of(work)
            mm_da(dz, w_of(w_flat), da)
            if wp.static(k > 0):
                wp.tile_assign(da, wp.tile_map(wp.static(relu_grad), a, da))  # in place

    return step


def _x_loader(plan: _Plan):
    """wp.func load(x, t, work): rows [t * tile, (t + 1) * tile) of x into a_0 (zeros past N).

    x_cols: the kernel gets x's transpose, a row-major (C_0, N) array (x stored column-major,
    as hash_grid_encode's output), read along N and written through a transposed view."""
    tile, c_in, x_cols = plan.tile, plan.dims[0], plan.x_cols
    a_of = _view(_name(plan, "x_in"), 0, tile, c_in)

    @wp.func(name=_name(plan, "load_x"))
    def load(x: wp.array2d(dtype=float), t: int, work: Any):
        if wp.static(x_cols):
            part = wp.tile_load(x, shape=(c_in, tile), offset=(0, t * tile))
            wp.tile_assign(wp.tile_transpose(a_of(work)), part)
        else:
            wp.tile_assign(a_of(work), wp.tile_load(x, shape=(tile, c_in), offset=(t * tile, 0)))

    return load


@functools.lru_cache(maxsize=64)
def _forward_kernel(dims: tuple[int, ...], tile: int, tf32: bool, x_cols: bool):
    """forward(x, w, n_tiles, n_blocks, y) for layer widths dims = (C_0, ..., C_L): block b
    takes the tiles of `tile` rows b, b + n_blocks, ...; x is (N, C_0), or its (C_0, N)
    transpose when x_cols."""
    plan = _Plan(dims, tile, tf32, x_cols, "fwd")
    c_out, n_params, size = dims[-1], plan.n_params, plan.fwd_size
    load_x = _x_loader(plan)
    y_of = _view(_name(plan, "y_out"), plan.act_off[plan.n_layers], tile, c_out)
    run = _chain(_name(plan, "fwd"), [_forward_step(plan, k) for k in range(plan.n_layers)])

    @wp.kernel(enable_backward=False, module="unique")
    def forward(
        x: wp.array2d(dtype=float),
        w: wp.array1d(dtype=float),
        n_tiles: int,
        n_blocks: int,
        y: wp.array2d(dtype=float),
    ):
        b = wp.tid()
        w_flat = wp.tile_load(w, shape=n_params, storage="shared")
        work = wp.tile_empty(shape=size, dtype=float, storage="shared")
        y_tile = y_of(work)
        for t in range(b, n_tiles, n_blocks):
            load_x(x, t, work)
            run(w_flat, w_flat, work)
            wp.tile_store(y, y_tile, offset=(t * tile, 0))

    return forward


@functools.lru_cache(maxsize=64)
def _backward_kernel(dims: tuple[int, ...], tile: int, tf32: bool, want_dx: bool, x_cols: bool):
    """backward(x, w, dy, n_tiles, n_blocks, dx, dw): dw (flat) += dL/dW; dx = dL/dx, written
    only when want_dx (else any array). Tiles and x as the forward's."""
    plan, L = _Plan(dims, tile, tf32, x_cols, "bwd_dx" if want_dx else "bwd"), len(dims) - 1
    c_in, c_out, n_params, size = dims[0], dims[-1], plan.n_params, plan.bwd_size
    load_x = _x_loader(plan)
    dy_of = _view(_name(plan, "dy_in"), plan.act_off[L], tile, c_out)
    dx_of = _view(_name(plan, "dx_out"), plan.dx_buffer(), tile, c_in)
    steps = [_forward_step(plan, k) for k in range(L - 1)]
    recompute = _chain(_name(plan, "re"), steps) if steps else None
    back = _chain(_name(plan, "bwd"), [_backward_step(plan, k) for k in reversed(range(L))])

    @wp.kernel(enable_backward=False, module="unique")
    def backward(
        x: wp.array2d(dtype=float),
        w: wp.array1d(dtype=float),
        dy: wp.array2d(dtype=float),
        n_tiles: int,
        n_blocks: int,
        dx: wp.array2d(dtype=float),
        dw: wp.array1d(dtype=float),
    ):
        b = wp.tid()
        w_flat = wp.tile_load(w, shape=n_params, storage="shared")
        g_flat = wp.tile_zeros(shape=n_params, dtype=float, storage="shared")
        work = wp.tile_empty(shape=size, dtype=float, storage="shared")
        dy_tile, dx_tile = dy_of(work), dx_of(work)
        for t in range(b, n_tiles, n_blocks):
            load_x(x, t, work)
            wp.tile_assign(dy_tile, wp.tile_load(dy, shape=(tile, c_out), offset=(t * tile, 0)))
            if wp.static(recompute is not None):
                recompute(w_flat, g_flat, work)
            back(w_flat, g_flat, work)
            if wp.static(want_dx):
                wp.tile_store(dx, dx_tile, offset=(t * tile, 0))
        # from registers: a shared source would cost a second shared tile for the old values
        wp.tile_atomic_add(dw, wp.tile_map(wp.static(ident), g_flat))

    return backward


# ---------------------------------------------------------------------------------------------
# Host side


@functools.cache
def _sm_count(index: int) -> int:
    return torch.cuda.get_device_properties(index).multi_processor_count


def _n_blocks(x: torch.Tensor, n_tiles: int, smem_bytes: int, blocks: int | None) -> int:
    """Persistent blocks: `blocks` if given, else as many as fit on the GPU at once (by shared
    memory, at most BLOCKS_PER_SM per SM); one per tile on the CPU (run one after another)."""
    if blocks is None:
        if x.device.type != "cuda":
            return n_tiles
        per_sm = max(1, min(BLOCKS_PER_SM, (227 * 1024) // max(smem_bytes, 1)))
        blocks = _sm_count(x.device.index or 0) * per_sm
    return max(1, min(n_tiles, blocks))


def _x_arg(x: torch.Tensor) -> tuple[wp.array, bool]:
    """(Warp view, x_cols): x as stored, or its transpose where x is column-major."""
    if x.shape[0] > 1 and x.stride(0) == 1 and x.stride(1) >= x.shape[0]:
        return fast_view(x.t()), True
    return fast_view(x), False


class _FusedMLP(torch.autograd.Function):
    @staticmethod
    def forward(ctx, cfg, x, *weights):
        tile, block_dim, tf32, blocks = cfg
        dims = (x.shape[1], *(w.shape[0] for w in weights))
        n, n_tiles = x.shape[0], -(-x.shape[0] // tile)
        flat = torch.cat([w.reshape(-1) for w in weights])
        y = torch.empty(n, dims[-1], dtype=torch.float32, device=x.device)
        if n:
            xv, x_cols = _x_arg(x)
            plan = _Plan(dims, tile, tf32, x_cols, "fwd")
            nb = _n_blocks(x, n_tiles, 4 * (plan.n_params + plan.fwd_size), blocks)
            kernel = _forward_kernel(dims, tile, tf32, x_cols)
            args = [xv, fast_view(flat), n_tiles, nb, fast_view(y)]
            tiled_launcher(kernel, block_dim, cpu_blocks=False)(nb, x, args)
        ctx.save_for_backward(x, flat)
        ctx.cfg, ctx.dims = cfg, dims
        return y

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_y):
        x, flat = ctx.saved_tensors
        (tile, block_dim, tf32, blocks), dims = ctx.cfg, ctx.dims
        want_dx = ctx.needs_input_grad[1]
        n, n_tiles = x.shape[0], -(-x.shape[0] // tile)
        g = grad_y if grad_y.dtype == torch.float32 else grad_y.float()
        g = g.contiguous() if 0 in g.stride() else g  # an expanded gradient is materialised
        dw = torch.zeros_like(flat)
        dx = torch.empty(x.shape, dtype=torch.float32, device=x.device) if want_dx else None
        if n:
            xv, x_cols = _x_arg(x)
            plan = _Plan(dims, tile, tf32, x_cols, "bwd_dx" if want_dx else "bwd")
            nb = _n_blocks(x, n_tiles, 4 * (2 * plan.n_params + plan.bwd_size), blocks)
            kernel = _backward_kernel(dims, tile, tf32, want_dx, x_cols)
            args = [xv, fast_view(flat), fast_view(g), n_tiles, nb]
            args += [fast_view(dx) if want_dx else fast_view(g), fast_view(dw)]
            tiled_launcher(kernel, block_dim, cpu_blocks=False)(nb, x, args)
        grads, off = [], 0
        for k, need in enumerate(ctx.needs_input_grad[2:]):
            size = dims[k + 1] * dims[k]
            grads.append(dw[off : off + size].view(dims[k + 1], dims[k]) if need else None)
            off += size
        return None, dx, *grads


def fused_mlp(
    x: torch.Tensor,
    weights,
    *,
    tile: int = DEFAULT_TILE,
    block_dim: int = DEFAULT_BLOCK_DIM,
    tf32: bool = False,
    blocks: int | None = None,
) -> torch.Tensor:
    """y = W_{L-1} relu(... relu(W_0 x)) for every row of x: (N, C_0) float32 -> (N, C_L).

    weights: L float32 tensors (C_{k+1}, C_k) (nn.Linear's layout, no biases), on x's device.
    Differentiable w.r.t. x (computed only when x requires grad) and every weight. x may be
    row-major or column-major (a transposed view, as hash_grid_encode returns); other strides
    are copied. tile: rows per tile; block_dim: threads per block (CUDA; the CPU runs one);
    tf32: TF32 tensor-core products (CUDA); blocks: persistent blocks (None: enough to fill
    the GPU). See the module docstring for the design.
    """
    weights = tuple(weights)
    if x.ndim != 2 or x.dtype != torch.float32:
        raise ValueError(f"fused_mlp: x must be (N, C) float32, got {tuple(x.shape)} {x.dtype}")
    if not weights:
        raise ValueError("fused_mlp: at least one weight")
    width = x.shape[1]
    for k, w in enumerate(weights):
        if w.ndim != 2 or w.dtype != torch.float32 or w.shape[1] != width:
            raise ValueError(
                f"fused_mlp: weight {k} must be (C_out, {width}) float32, "
                f"got {tuple(w.shape)} {w.dtype}"
            )
        if w.device != x.device:
            raise ValueError(f"fused_mlp: x on {x.device} but weight {k} on {w.device}")
        width = w.shape[0]
    if tile < 1 or block_dim < 1:
        raise ValueError(f"fused_mlp: tile and block_dim must be positive, got {tile}, {block_dim}")
    col_major = x.shape[0] > 1 and x.stride(0) == 1 and x.stride(1) >= x.shape[0]
    if (x.stride(1) != 1 or x.stride(0) < x.shape[1]) and not col_major:
        x = x.contiguous()  # overlapping (expanded) rows too
    cfg = (int(tile), int(block_dim), bool(tf32), None if blocks is None else int(blocks))
    return _FusedMLP.apply(cfg, x, *weights)
