"""sm_90 vector loads and reductions on a table's rows, for the hash grid's kernels.

Each is a `wp.func_native` with the CUDA path under `__CUDA_ARCH__` and scalar Warp code
elsewhere (the CPU backend the tests run on), so every kernel that uses them keeps one source.
"""

import functools

import warp as wp

from .common import init

init()

# sm_90 vector memory ops. Corners (x, y, z) and (x+1, y, z) often share an aligned row pair
# (dense: x even; hashed: x even flips only bit 0 of the hash): then one 16-byte load or one
# `red.v4.f32` serves both; otherwise two 8-byte ones. Scalar Warp code elsewhere (CPU).
_PAIR_GATHER = """
#if defined(__CUDA_ARCH__)
    const float* p0 = reinterpret_cast<const float*>(wp::address(buf, r0));
    float a, b, c, d;
    if (r1 == r0 + 1 && (r0 & 1) == 0) {
        asm("ld.global.nc.v4.f32 {%0, %1, %2, %3}, [%4];"
            : "=f"(a), "=f"(b), "=f"(c), "=f"(d) : "l"(p0));
    } else {
        const float* p1 = reinterpret_cast<const float*>(wp::address(buf, r1));
        asm("ld.global.nc.v2.f32 {%0, %1}, [%2];" : "=f"(a), "=f"(b) : "l"(p0));
        asm("ld.global.nc.v2.f32 {%0, %1}, [%2];" : "=f"(c), "=f"(d) : "l"(p1));
    }
    return wp::vec_t<4, float>(a, b, c, d);
#else
    wp::vec_t<2, float> u = wp::index(buf, r0);
    wp::vec_t<2, float> v = wp::index(buf, r1);
    return wp::vec_t<4, float>(u.c[0], u.c[1], v.c[0], v.c[1]);
#endif
"""

_PAIR_SCATTER = """
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
    float* p0 = reinterpret_cast<float*>(wp::address(buf, r0));
    if (r1 == r0 + 1 && (r0 & 1) == 0) {
        asm volatile("red.global.add.v4.f32 [%0], {%1, %2, %3, %4};" :: "l"(p0),
                     "f"(v.c[0]), "f"(v.c[1]), "f"(v.c[2]), "f"(v.c[3]) : "memory");
    } else {
        float* p1 = reinterpret_cast<float*>(wp::address(buf, r1));
        asm volatile("red.global.add.v2.f32 [%0], {%1, %2};" :: "l"(p0), "f"(v.c[0]), "f"(v.c[1])
                     : "memory");
        asm volatile("red.global.add.v2.f32 [%0], {%1, %2};" :: "l"(p1), "f"(v.c[2]), "f"(v.c[3])
                     : "memory");
    }
#else
    wp::atomic_add(buf, r0, wp::vec_t<2, float>(v.c[0], v.c[1]));
    wp::atomic_add(buf, r1, wp::vec_t<2, float>(v.c[2], v.c[3]));
#endif
"""

_SCATTER = """
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ >= 900
    float* p = reinterpret_cast<float*>(wp::address(buf, row));
    if (NF == 2) {
        asm volatile("red.global.add.v2.f32 [%0], {%1, %2};" :: "l"(p), "f"(v.c[0]), "f"(v.c[1])
                     : "memory");
    } else if (NF == 4) {
        asm volatile("red.global.add.v4.f32 [%0], {%1, %2, %3, %4};" :: "l"(p),
                     "f"(v.c[0]), "f"(v.c[1]), "f"(v.c[2]), "f"(v.c[3]) : "memory");
    } else {
        for (int k = 0; k < NF; ++k) atomicAdd(p + k, v.c[k]);
    }
#else
    wp::atomic_add(buf, row, v);
#endif
"""


@wp.func_native(_PAIR_GATHER)
def gather_pair(buf: wp.array(dtype=wp.vec2), r0: int, r1: int) -> wp.vec4: ...


@wp.func_native(_PAIR_SCATTER)
def scatter_pair(buf: wp.array(dtype=wp.vec2), r0: int, r1: int, v: wp.vec4): ...


@functools.cache
def scatter_func(F: int):
    """scatter_add(buf, row, v): one F-vector reduction into buf[row] (`red.v2`/`red.v4` on
    sm_90, scalar atomics elsewhere)."""
    vec = wp.types.vector(length=F, dtype=wp.float32)

    def scatter_add(buf: wp.array(dtype=vec), row: int, v: vec): ...

    scatter_add.__qualname__ = f"scatter_add_f{F}"
    return wp.func_native(_SCATTER.replace("NF", str(F)))(scatter_add)
