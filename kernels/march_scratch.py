"""The single-pass march's scratch rows (issue #17): each thread of the march keeps its first
samples in a row of its own while it counts them, and once the counts are capped and scanned
one copy puts every slice in place (`kernels/raymarch.py`: `count_samples`, `write_samples`).

Rows are sized by the most samples a thread can take (`thread_bound`), so a slice longer than
its row is rare (a ray with no direction marches to max_samples); the march's write pass takes
those again and its other threads return at once. The output is the two passes' bit for bit.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import warp as wp

from .common import launch

SINGLE_PASS: bool = False
"""March once (scratch rows, then a copy); False: march twice (count, then write). The same
samples either way; which is faster is the GPU's to say (benchmarks/RESULTS.md)."""
SCRATCH_MAX_SLOTS = 2**27
"""The rows hold at most this many samples (two float32 each, 1 GiB): more threads than that
allows get shorter rows, and a slice longer than its row is marched again."""


class Scratch(NamedTuple):
    """Thread i's first samples at [i * stride, (i + 1) * stride), world units."""

    t_starts: torch.Tensor
    t_ends: torch.Tensor
    stride: int


def thread_bound(box: list[float], dt_min: float, max_samples: int, n_seg: int) -> int:
    """The most samples one thread (a ray's segment) takes: a ray crosses the box in at most
    its diagonal / dt_min lattice intervals (steps never fall below dt_min), two more for the
    jitter and the ends, split over n_seg segments. Rays with no direction or an unbounded
    range can take more (to max_samples): the single pass marches those again."""
    diag = math.sqrt(sum((box[i + 3] - box[i]) ** 2 for i in range(3)))
    per_ray = math.ceil(min(diag / dt_min, 1e9)) + 4
    return max(1, min(max_samples, -(-per_ray // n_seg) + 2))


def scratch_stride(threads: int, bound: int, single_pass: bool | None) -> int:
    """Slots per row for `threads` threads that take at most `bound` samples each, or 0:
    march twice (`SINGLE_PASS` unless single_pass is given)."""
    if not (SINGLE_PASS if single_pass is None else single_pass) or threads == 0:
        return 0
    return min(bound, SCRATCH_MAX_SLOTS // threads)


def new_scratch(threads: int, stride: int, device) -> Scratch:
    """Uninitialised rows for `threads` threads (the march writes what it keeps)."""
    n = threads * stride
    f32 = dict(dtype=torch.float32, device=device)
    return Scratch(torch.empty(n, **f32), torch.empty(n, **f32), stride)


@wp.kernel(enable_backward=False)
def _place_rows(
    rows_s: wp.array(dtype=float),
    rows_e: wp.array(dtype=float),
    stride: int,
    n_seg: int,
    seg_info: wp.array(dtype=wp.vec2i),
    t_starts: wp.array(dtype=float),
    t_ends: wp.array(dtype=float),
    ray_indices: wp.array(dtype=wp.int32),
):
    """One thread per (ray, segment): its slice copied from its row (a slice longer than the
    row is left to the march's write pass)."""
    i = wp.tid()
    first, n = seg_info[i][0], seg_info[i][1]
    if n > stride:
        return
    r = i / n_seg
    for k in range(n):
        t_starts[first + k] = rows_s[i * stride + k]
        t_ends[first + k] = rows_e[i * stride + k]
        ray_indices[first + k] = r


def place_rows(scratch: Scratch, n_seg: int, seg_info, t_starts, t_ends, ray_indices) -> None:
    """Every slice that fits its row, from the row to seg_info's (first slot, count):
    seg_info a (threads,) wp.vec2i view; t_starts, t_ends (S,) float32, ray_indices (S,) int32."""
    threads = seg_info.shape[0]
    args = [scratch.t_starts, scratch.t_ends, scratch.stride, n_seg, seg_info]
    launch(_place_rows, threads, scratch.t_starts, [*args, t_starts, t_ends, ray_indices])
