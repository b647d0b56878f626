"""The hash grid's table backward over runs of consecutive points (`HashGridConfig.backward_run`).

The marcher emits a ray's samples one after another, and at the coarse levels several fall in
one cell: a thread that takes R consecutive points adds their corner gradients in registers
and sends one reduction per corner when the cell changes, instead of one per sample
(`benchmarks/hashgrid_runs.py` times it against a thread per point).
"""

import functools

import warp as wp

from .common import features_dtype, init
from .hashgrid_cells import cell_of, corner_weight, grad_loader, grouped, pair_rows
from .vector_memory import scatter_func, scatter_pair

init()


GROUP = 4  # levels a thread group takes, the level the fastest index (as `hashgrid._kernels`)


def run_threads(n: int, n_levels: int, run: int) -> int:
    """Threads `run_backward` launches for n points: ceil(n / run) items per level, the
    levels rounded up to whole groups."""
    return -(-n // run) * (-(-n_levels // GROUP) * GROUP)


@functools.cache
def run_backward(F: int, run: int, bf16: bool = False):
    """backward(table) over runs of `run` consecutive points per (level, thread).

    A ray's samples are consecutive and, at the coarse levels, several fall in one cell: the
    thread adds their corner gradients in registers and sends one reduction per corner when
    the cell changes (or the run ends), instead of one per sample. The thread layout of the
    thread-per-point backward (`hashgrid._kernels`: levels 4 at a time, the level fastest),
    over ceil(N / run) items. Arguments as that kernel's: x (N, 3) in [0, 1]^3, grad (N, L*F)
    with any strides (bfloat16 with `bf16`), grad_table (n_params,) F-vectors, added into.
    """
    vec = wp.types.vector(length=F, dtype=wp.float32)
    ft = features_dtype(bf16)
    load = grad_loader(F, bf16)
    corners = wp.types.matrix(shape=(8, F), dtype=wp.float32)
    scatter = scatter_func(F)
    pairs = F == 2

    @wp.func
    def flush(grad_table: wp.array(dtype=vec), level: wp.vec4i, c: wp.vec3i, acc: corners):
        for m in range(4):
            r0, r1 = pair_rows(c, m, level)
            if wp.static(pairs):
                a = acc[2 * m]
                b = acc[2 * m + 1]
                scatter_pair(grad_table, r0, r1, wp.vec4(a[0], a[1], b[0], b[1]))
            else:
                scatter(grad_table, r0, acc[2 * m])
                scatter(grad_table, r1, acc[2 * m + 1])

    @wp.kernel(enable_backward=False, module="unique")
    def backward_table_runs(
        x: wp.array(dtype=wp.vec3),
        grad: wp.array2d(dtype=ft),
        levels: wp.array(dtype=wp.vec4i),
        n: int,
        n_levels: int,
        grad_table: wp.array(dtype=vec),
    ):
        n_items = (n + run - 1) // run
        lv, item = grouped(wp.tid(), n_items, GROUP)
        if lv >= n_levels:
            return
        level = levels[lv]
        acc = corners()
        cur = wp.vec3i(-1, -1, -1)
        begin = item * run
        for i in range(begin, wp.min(begin + run, n)):
            g = load(grad, i, lv)
            # no gradient, nothing to add: a fixed-capacity march's padding, samples past a
            # ray's end (as the default backward)
            if wp.length_sq(g) == 0.0:
                continue
            c, f = cell_of(x[i], level[0])
            if c[0] != cur[0] or c[1] != cur[1] or c[2] != cur[2]:
                if cur[0] >= 0:
                    flush(grad_table, level, cur, acc)
                acc = corners()
                cur = c
            for k in range(8):
                acc[k] = acc[k] + corner_weight(f, k & 1, (k >> 1) & 1, k >> 2) * g
        if cur[0] >= 0:
            flush(grad_table, level, cur, acc)

    return backward_table_runs
