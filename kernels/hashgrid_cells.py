"""Where a point lands in the hash grid: its cell, trilinear weights and table rows (the
layout of `hashgrid.py`'s module docstring), as Warp functions shared by its kernels."""

import functools

import warp as wp

from .common import features_dtype, init

init()


PRIME_Y = wp.constant(wp.uint32(2654435761))
PRIME_Z = wp.constant(wp.uint32(805459861))


# ---------------------------------------------------------------------------------------------
# Warp functions shared by every kernel variant


@wp.func
def grid_index(ix: int, iy: int, iz: int, level: wp.vec4i) -> int:
    """Row of vertex (ix, iy, iz) relative to the level's offset.

    level = (N, offset, hashed, mask): dense index, or the uint32 XOR hash masked to T rows.
    """
    if level[2] != 0:
        h = wp.uint32(ix) ^ (wp.uint32(iy) * PRIME_Y) ^ (wp.uint32(iz) * PRIME_Z)
        return int(h & wp.uint32(level[3]))
    stride = level[0] + 1
    return ix + stride * (iy + stride * iz)


@wp.func
def pair_rows(c: wp.vec3i, m: int, level: wp.vec4i):
    """Absolute rows of the x-adjacent corner pair m of cell c: (c + (0, dy, dz), c + (1, dy,
    dz)) with dy = m & 1, dz = m >> 1 (m in 0..3; the pair a 16-byte access may serve)."""
    dy = m & 1
    dz = m >> 1
    r0 = level[1] + grid_index(c[0], c[1] + dy, c[2] + dz, level)
    r1 = level[1] + grid_index(c[0] + 1, c[1] + dy, c[2] + dz, level)
    return r0, r1


@wp.func
def cell_of(p: wp.vec3, res: int):
    """Clamp p to the box; return (cell index, fraction in [0, 1]) at resolution res."""
    q = wp.vec3(wp.clamp(p[0], 0.0, 1.0), wp.clamp(p[1], 0.0, 1.0), wp.clamp(p[2], 0.0, 1.0))
    pos = q * float(res)
    c = wp.vec3i(
        wp.clamp(int(wp.floor(pos[0])), 0, res - 1),
        wp.clamp(int(wp.floor(pos[1])), 0, res - 1),
        wp.clamp(int(wp.floor(pos[2])), 0, res - 1),
    )
    f = pos - wp.vec3(float(c[0]), float(c[1]), float(c[2]))
    return c, f


@wp.func
def corner_weight(f: wp.vec3, dx: int, dy: int, dz: int) -> float:
    wx = wp.where(dx != 0, f[0], 1.0 - f[0])
    wy = wp.where(dy != 0, f[1], 1.0 - f[1])
    wz = wp.where(dz != 0, f[2], 1.0 - f[2])
    return wx * wy * wz


@wp.func
def grouped(tid: int, n: int, group: int):
    """Thread id -> (level, item) with levels taken `group` at a time, the level fastest (as
    `_kernels`' backward with level_outer)."""
    gsize = n * group
    gi = tid // gsize
    r = tid - gi * gsize
    i = r // group
    return gi * group + (r - i * group), i


@functools.cache
def grad_loader(F: int, bf16: bool):
    """load(grad, i, lv) -> the F-vector of level lv's gradient at point i, as float32, from
    an (N, L*F) array of `features_dtype(bf16)` with any strides."""
    vec = wp.types.vector(length=F, dtype=wp.float32)
    ft = features_dtype(bf16)

    @wp.func
    def load(g: wp.array2d(dtype=ft), i: int, lv: int) -> vec:
        v = vec()
        for k in range(F):
            v[k] = wp.float32(g[i, lv * F + k])
        return v

    return load
