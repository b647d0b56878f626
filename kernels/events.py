"""Event-window queries E(u; t0, t1] as a Warp kernel: two binary searches per query.

Data layout (identical to `fastenerf.data.events.EventIndex`, built there in numpy):
  offsets: (H*W + 1,) int64 — pixel u's events are entries [offsets[u], offsets[u+1]).
  times:   (N,) int64 µs    — event times sorted by (pixel, t).
  cum_pos: (N+1,) int64     — number of positive events among the first i entries.
For a query (u, t0, t1): lo = first index of u's range with t > t0, hi = first with t > t1,
n = hi − lo, n_pos = cum_pos[hi] − cum_pos[lo] (n = 0 when t1 <= t0), and
E = n_pos·(1 + offset)·C_pos + (n − n_pos)·(offset − 1)·C_neg (DESIGN §3, §9). O(log n) per
query, exact integer counts. Windows that wrap around a loop are split by the caller.
A pixel id outside [0, H*W) gives n = n_pos = −1 and E = NaN instead of reading out of bounds.
"""

import torch
import warp as wp

from .common import fast_view, init, launch

init()


@wp.func
def upper_bound(times: wp.array(dtype=wp.int64), lo: wp.int64, hi: wp.int64, q: wp.int64):
    """First index in [lo, hi) whose time is > q (hi if none)."""
    while lo < hi:
        mid = lo + (hi - lo) // wp.int64(2)
        if times[mid] <= q:
            lo = mid + wp.int64(1)
        else:
            hi = mid
    return lo


@wp.func
def window_range(
    offsets: wp.array(dtype=wp.int64),
    times: wp.array(dtype=wp.int64),
    u: wp.int64,
    t0: wp.int64,
    t1: wp.int64,
):
    """[lo, hi) of pixel u's events with t0 < t <= t1 (empty, lo = hi, when t1 <= t0)."""
    end = offsets[u + wp.int64(1)]
    lo = upper_bound(times, offsets[u], end, t0)
    hi = lo
    if t1 > t0:
        hi = upper_bound(times, lo, end, t1)
    return lo, hi


@wp.kernel(enable_backward=False)
def _window_counts_kernel(
    offsets: wp.array(dtype=wp.int64),
    times: wp.array(dtype=wp.int64),
    cum_pos: wp.array(dtype=wp.int64),
    pix: wp.array(dtype=wp.int64),
    t0: wp.array(dtype=wp.int64),
    t1: wp.array(dtype=wp.int64),
    n_pix: wp.int64,
    n_out: wp.array(dtype=wp.int32),
    n_pos_out: wp.array(dtype=wp.int32),
):
    b = wp.tid()
    u = pix[b]
    if u < wp.int64(0) or u >= n_pix:
        n_out[b] = -1
        n_pos_out[b] = -1
        return
    lo, hi = window_range(offsets, times, u, t0[b], t1[b])
    n_out[b] = wp.int32(hi - lo)
    n_pos_out[b] = wp.int32(cum_pos[hi] - cum_pos[lo])


@wp.kernel(enable_backward=False)
def _window_sum_kernel(
    offsets: wp.array(dtype=wp.int64),
    times: wp.array(dtype=wp.int64),
    cum_pos: wp.array(dtype=wp.int64),
    pix: wp.array(dtype=wp.int64),
    t0: wp.array(dtype=wp.int64),
    t1: wp.array(dtype=wp.int64),
    n_pix: wp.int64,
    a_pos: wp.float64,
    c_pos: wp.float64,
    a_neg: wp.float64,
    c_neg: wp.float64,
    e_out: wp.array(dtype=wp.float32),
):
    b = wp.tid()
    u = pix[b]
    if u < wp.int64(0) or u >= n_pix:
        e_out[b] = wp.nan
        return
    lo, hi = window_range(offsets, times, u, t0[b], t1[b])
    n_pos = cum_pos[hi] - cum_pos[lo]
    # float64, in EventIndex.weights' order of operations, rounded to float32 once at the end.
    e = wp.float64(n_pos) * a_pos * c_pos + wp.float64(hi - lo - n_pos) * a_neg * c_neg
    e_out[b] = wp.float32(e)


def _prepare(offsets, times, cum_pos, pix, t0, t1):
    dev = pix.device
    for name, t in (("offsets", offsets), ("times", times), ("cum_pos", cum_pos), ("pix", pix)):
        if t.dtype != torch.int64 or t.ndim != 1 or t.device != dev:
            raise ValueError(
                f"event query: '{name}' must be 1-D int64 on {dev}, got "
                f"{tuple(t.shape)} {t.dtype} on {t.device}"
            )
    if cum_pos.shape[0] != times.shape[0] + 1 or offsets.shape[0] < 2:
        raise ValueError("event query: need len(cum_pos) == len(times) + 1 and len(offsets) >= 2")
    t0 = torch.as_tensor(t0, dtype=torch.int64, device=dev).expand_as(pix)  # stride 0 is fine
    t1 = torch.as_tensor(t1, dtype=torch.int64, device=dev).expand_as(pix)
    arrays = [fast_view(a) for a in (offsets, times, cum_pos, pix, t0, t1)]
    return arrays + [offsets.shape[0] - 1]


def window_counts(offsets, times, cum_pos, pix, t0, t1) -> tuple[torch.Tensor, torch.Tensor]:
    """Counts of events at flat pixels ``pix`` (B,) int64 within (t0, t1] (B,) int64 µs.

    Returns (n, n_pos): (B,) int32 each, on pix's device.
    """
    n = torch.empty(pix.shape[0], dtype=torch.int32, device=pix.device)
    n_pos = torch.empty_like(n)
    if pix.shape[0]:
        args = _prepare(offsets, times, cum_pos, pix, t0, t1) + [fast_view(n), fast_view(n_pos)]
        launch(_window_counts_kernel, pix.shape[0], pix, args)
    return n, n_pos


def window_sum(
    offsets,
    times,
    cum_pos,
    pix,
    t0,
    t1,
    pos_threshold: float,
    neg_threshold: float,
    polarity_offset: float = 0.0,
) -> torch.Tensor:
    """E(u; t0, t1] = sum over events of (p + offset)·C_p, (B,) float32 on pix's device."""
    e = torch.empty(pix.shape[0], dtype=torch.float32, device=pix.device)
    weights = [
        1.0 + polarity_offset,
        float(pos_threshold),
        polarity_offset - 1.0,
        float(neg_threshold),
    ]
    if pix.shape[0]:
        args = _prepare(offsets, times, cum_pos, pix, t0, t1) + weights + [fast_view(e)]
        launch(_window_sum_kernel, pix.shape[0], pix, args)
    return e
