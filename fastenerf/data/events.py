"""Event streams and window queries.

`EventStream` holds the raw events (x, y, t in integer µs, p = ±1) of one sensor and
validates them at the boundary. `EventIndex` answers E(u; t0, t1], the signed,
threshold-weighted event sum at pixel u over a window (DESIGN §3), in O(log n) per query
from per-pixel sorted times and prefix counts; `fastenerf.kernels.events` runs the same
query as a Warp kernel on the same arrays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..errors import InputError


@dataclass(frozen=True)
class EventStream:
    """Events of one sensor, sorted by time.

    x, y: (N,) uint16 pixel coordinates; t: (N,) int64 µs, non-decreasing;
    p: (N,) int8 in {-1, +1}; width, height: sensor size in pixels.
    """

    x: np.ndarray
    y: np.ndarray
    t: np.ndarray
    p: np.ndarray
    width: int
    height: int

    @classmethod
    def from_arrays(cls, x, y, t, p, width: int, height: int, source: str = "events",
                    allow_empty: bool = False) -> EventStream:
        """Validate and convert raw arrays; every problem is one line naming `source`.

        Polarity may be given as {-1, +1}, {0, 1} or bool; it is stored as ±1.
        """
        arrays = {"x": x, "y": y, "t": t, "p": p}
        arrays = {k: np.asarray(v) for k, v in arrays.items()}
        n = len(arrays["t"])
        for k, a in arrays.items():
            if a.ndim != 1:
                raise InputError(f"{source}: '{k}' must be one-dimensional, has shape {a.shape}")
            if len(a) != n:
                raise InputError(f"{source}: '{k}' has {len(a)} entries but 't' has {n}")
            if a.dtype.kind not in "iub f":
                raise InputError(f"{source}: '{k}' has non-numeric dtype {a.dtype}")
            if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
                i = int(np.flatnonzero(~np.isfinite(a))[0])
                raise InputError(f"{source}: '{k}' is NaN or inf at event {i}")
        if n == 0 and not allow_empty:
            raise InputError(f"{source}: the stream has no events")
        if width <= 0 or height <= 0 or width > 65535 or height > 65535:
            raise InputError(f"{source}: sensor size {width}x{height} is not valid")
        xs, ys, ts, ps = arrays["x"], arrays["y"], arrays["t"], arrays["p"]
        for k, a, lim in (("x", xs, width), ("y", ys, height)):
            if n and (a.min() < 0 or a.max() >= lim):
                i = int(np.flatnonzero((a < 0) | (a >= lim))[0])
                raise InputError(
                    f"{source}: event {i} has {k}={a[i]} outside the {width}x{height} sensor"
                )
            if a.dtype.kind == "f" and np.any(a != np.round(a)):
                raise InputError(f"{source}: '{k}' has non-integer coordinates")
        if ts.dtype.kind == "f" and np.any(ts != np.round(ts)):
            raise InputError(f"{source}: 't' must be integer microseconds (got fractions)")
        ts = ts.astype(np.int64)
        if n and ts[0] < 0:
            raise InputError(f"{source}: negative timestamp {ts[0]} at event 0")
        if n > 1:
            back = np.flatnonzero(np.diff(ts) < 0)
            if len(back):
                i = int(back[0]) + 1
                raise InputError(
                    f"{source}: timestamps are not sorted (event {i} at t={ts[i]} comes after "
                    f"t={ts[i - 1]})"
                )
        pv = ps.astype(np.int64) if ps.dtype != bool else ps.astype(np.int64)
        values = set(np.unique(pv).tolist()) if n else set()
        if values <= {-1, 1}:
            p8 = pv.astype(np.int8)
        elif values <= {0, 1}:
            p8 = (2 * pv - 1).astype(np.int8)
        else:
            bad = sorted(values - {-1, 0, 1})[:3]
            raise InputError(f"{source}: polarity must be ±1 or 0/1, found {bad}")
        return cls(xs.astype(np.uint16), ys.astype(np.uint16), ts, p8, int(width), int(height))

    def __len__(self) -> int:
        return len(self.t)

    @property
    def duration_us(self) -> int:
        return int(self.t[-1] - self.t[0]) if len(self) else 0

    def slice_time(self, t0: int, t1: int) -> EventStream:
        """Events with t0 <= t < t1 (a view, no copy)."""
        i0, i1 = np.searchsorted(self.t, [t0, t1], side="left")
        return EventStream(self.x[i0:i1], self.y[i0:i1], self.t[i0:i1], self.p[i0:i1],
                           self.width, self.height)

    def stats(self) -> dict:
        """Summary numbers for `fastenerf info`."""
        n = len(self)
        counts = np.bincount(self.y.astype(np.int64) * self.width + self.x, minlength=1)
        busiest = int(np.argmax(counts)) if n else 0
        dur = self.duration_us
        return {
            "events": n,
            "sensor": f"{self.width}x{self.height}",
            "t_first_us": int(self.t[0]) if n else None,
            "t_last_us": int(self.t[-1]) if n else None,
            "duration_s": dur * 1e-6,
            "rate_ev_per_s": n / (dur * 1e-6) if dur > 0 else None,
            "positive_fraction": float((self.p > 0).mean()) if n else None,
            "busiest_pixel": {"x": busiest % self.width, "y": busiest // self.width,
                              "events": int(counts[busiest]) if n else 0},
            "active_pixels": int((counts > 0).sum()),
        }


class EventIndex:
    """Window queries E(u; t0, t1] over one stream (DESIGN §3, §4).

    Layout (shared with `fastenerf.kernels.events`):
      offsets: (H*W + 1,) int64 — pixel u's events are entries [offsets[u], offsets[u+1]).
      times:   (N,) int64 µs    — event times sorted by (pixel, t).
      cum_pos: (N+1,) int64     — number of positive events among the first i entries.
    Each event weighs (p + offset) · (C_pos if p > 0 else C_neg); counts are integers so the
    sum is exact however long the stream.

    Loop streams: a window that starts before the stream's start `t_start` wraps to its end
    (period `t_end - t_start`): E(t0, t1] = E(t0 + P, t_end] + E(t_start, t1].
    """

    def __init__(self, stream: EventStream, pos_threshold: float, neg_threshold: float | None = None,
                 polarity_offset: float = 0.0, t_start: int | None = None,
                 t_end: int | None = None, loop: bool = False):
        self.width, self.height = stream.width, stream.height
        self.pos_threshold = float(pos_threshold)
        self.neg_threshold = float(pos_threshold if neg_threshold is None else neg_threshold)
        self.polarity_offset = float(polarity_offset)
        self.t_start = int(stream.t[0] if t_start is None else t_start)
        self.t_end = int(stream.t[-1] if t_end is None else t_end)
        self.loop = loop
        pix = stream.y.astype(np.int64) * self.width + stream.x.astype(np.int64)
        # Stable sort keeps time order within a pixel (the stream is time-sorted).
        order = np.argsort(pix, kind="stable")
        counts = np.bincount(pix, minlength=self.width * self.height)
        self.offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self.times = stream.t[order]
        self.cum_pos = np.concatenate([[0], np.cumsum(stream.p[order] > 0)]).astype(np.int64)
        # Time-sorted pixel ids, for drawing event pixels of a window (positive samples).
        self.pixels_by_time = pix
        self.times_sorted = stream.t
        self.positive_by_time = stream.p > 0

    @property
    def period(self) -> int:
        return self.t_end - self.t_start

    def weights(self, n: np.ndarray, n_pos: np.ndarray) -> np.ndarray:
        """E from counts: n_pos·(1+off)·C_pos + (n−n_pos)·(off−1)·C_neg, float32."""
        off = self.polarity_offset
        e = n_pos * (1.0 + off) * self.pos_threshold + (n - n_pos) * (off - 1.0) * self.neg_threshold
        return np.asarray(e, dtype=np.float32)

    def counts(self, pix, t0, t1) -> tuple[np.ndarray, np.ndarray]:
        """(n, n_pos) events at flat pixels `pix` (B,) within (t0, t1] (B,) µs, no wrap."""
        pix = np.asarray(pix, dtype=np.int64)
        t0 = np.broadcast_to(np.asarray(t0, dtype=np.int64), pix.shape)
        t1 = np.broadcast_to(np.asarray(t1, dtype=np.int64), pix.shape)
        lo = _segment_searchsorted(self.times, self.offsets, pix, t0)
        hi = _segment_searchsorted(self.times, self.offsets, pix, np.maximum(t1, t0))
        n = hi - lo
        n_pos = self.cum_pos[hi] - self.cum_pos[lo]
        return n, n_pos

    def split_wrapped(self, t0, t1):
        """Split windows that begin before `t_start` of a loop into two plain windows.

        Returns (t0a, t1a, t0b, t1b): E = E(t0a, t1a] + E(t0b, t1b]; the second part is empty
        (t0b = t1b) for windows that do not wrap.
        """
        t0 = np.asarray(t0, dtype=np.int64)
        t1 = np.asarray(t1, dtype=np.int64)
        wraps = (t0 < self.t_start) & self.loop
        t0a = np.where(wraps, self.t_start - 1, t0)  # (t_start - 1, t1] includes t_start
        t0b = np.where(wraps, t0 + self.period, self.t_end)
        t1b = np.where(wraps, self.t_end, self.t_end)
        return t0a, t1, t0b, t1b

    def query(self, pix, t0, t1) -> np.ndarray:
        """E(u; t0, t1] for flat pixels `pix` (B,) int, windows t0, t1 (B,) int64 µs -> (B,) float32."""
        t0a, t1a, t0b, t1b = self.split_wrapped(t0, t1)
        n, n_pos = self.counts(pix, t0a, t1a)
        if self.loop:
            n2, n_pos2 = self.counts(pix, t0b, t1b)
            n, n_pos = n + n2, n_pos + n_pos2
        return self.weights(n, n_pos)

    def window_slice(self, t0: int, t1: int) -> tuple[int, int]:
        """Index range [i0, i1) of the time-sorted stream with t0 < t <= t1 (no wrap)."""
        i0, i1 = np.searchsorted(self.times_sorted, [t0, t1], side="right")
        return int(i0), int(i1)

    def accumulate(self, t0: int, t1: int) -> np.ndarray:
        """Dense E image (H, W) float32 for one window (wraps on loops); for tests and pictures."""
        t0a, t1a, t0b, t1b = (int(v) for v in self.split_wrapped(t0, t1))
        img = np.zeros(self.width * self.height, dtype=np.float64)
        for a, b in ((t0a, t1a), (t0b, t1b)):
            if b <= a:
                continue
            i0, i1 = self.window_slice(a, b)
            pix = self.pixels_by_time[i0:i1]
            n = np.bincount(pix, minlength=img.size)
            npos = np.bincount(pix[self.positive_by_time[i0:i1]], minlength=img.size)
            img += self.weights(n, npos)
        return img.reshape(self.height, self.width).astype(np.float32)

    def to_torch(self, device: str | torch.device) -> dict[str, torch.Tensor]:
        """The index arrays as torch tensors on `device`, for `fastenerf.kernels.events`."""
        return {
            "offsets": torch.from_numpy(self.offsets).to(device),
            "times": torch.from_numpy(self.times).to(device),
            "cum_pos": torch.from_numpy(self.cum_pos).to(device),
        }


def _segment_searchsorted(values: np.ndarray, offsets: np.ndarray, seg: np.ndarray,
                          q: np.ndarray) -> np.ndarray:
    """For each query, the first index in values[offsets[s]:offsets[s+1]] with value > q.

    Vectorised bisection over all queries at once: O(B log n) without a Python loop per query.
    """
    lo = offsets[seg].copy()
    hi = offsets[seg + 1].copy()
    while True:
        active = lo < hi
        if not active.any():
            return lo
        mid = (lo + hi) // 2
        midv = values[np.minimum(mid, len(values) - 1)] if len(values) else mid * 0
        go_right = active & (midv <= q)
        lo = np.where(go_right, mid + 1, lo)
        hi = np.where(active & ~go_right, mid, hi)
