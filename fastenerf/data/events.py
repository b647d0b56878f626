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
    def from_arrays(
        cls,
        x,
        y,
        t,
        p,
        width: int,
        height: int,
        source: str = "events",
        allow_empty: bool = False,
        lines: np.ndarray | None = None,
    ) -> EventStream:
        """Validate and convert raw arrays; every problem is one line naming `source` and where.

        x, y: (N,) integer-valued pixel coordinates; t: (N,) integer-valued µs, non-negative,
        non-decreasing; p: (N,) polarity as {-1, +1}, {0, 1} or bool, stored as ±1.
        lines: optional (N,) line numbers of the events in a text source, so that messages
        say "line 17" instead of "event 15".
        """

        def at(i: int) -> str:
            return f"line {int(lines[i])}" if lines is not None else f"event {i}"

        arrays = {"x": x, "y": y, "t": t, "p": p}
        arrays = {k: np.asarray(v) for k, v in arrays.items()}
        for k, a in arrays.items():
            if a.ndim != 1:
                raise InputError(f"{source}: '{k}' must be one-dimensional, has shape {a.shape}")
        n = len(arrays["t"])
        for k, a in arrays.items():
            if len(a) != n:
                raise InputError(f"{source}: '{k}' has {len(a)} entries but 't' has {n}")
            if a.dtype.kind not in "iubf":
                raise InputError(f"{source}: '{k}' has non-numeric dtype {a.dtype}")
            if a.dtype.kind == "f":
                bad = ~np.isfinite(a)
                if bad.any():
                    raise InputError(f"{source}: '{k}' is NaN or inf at {at(int(np.argmax(bad)))}")
                frac = a != np.round(a)
                if k != "p" and frac.any():
                    i = int(np.argmax(frac))
                    raise InputError(
                        f"{source}: '{k}' = {a[i]} at {at(i)} is not an integer"
                        + (" (t must be integer microseconds)" if k == "t" else "")
                    )
        if n == 0 and not allow_empty:
            raise InputError(f"{source}: the stream has no events")
        if width <= 0 or height <= 0 or width > 65535 or height > 65535:
            raise InputError(f"{source}: sensor size {width}x{height} is not valid")
        xs, ys, ts, ps = arrays["x"], arrays["y"], arrays["t"], arrays["p"]
        for k, a, lim in (("x", xs, width), ("y", ys, height)):
            if n and (a.min() < 0 or a.max() >= lim):
                i = int(np.argmax((a < 0) | (a >= lim)))
                raise InputError(
                    f"{source}: {k}={a[i]} at {at(i)} is outside the {width}x{height} sensor"
                )
        if n and ts.max() > _T_MAX:  # int64 µs overflow (also catches absurd float times)
            i = int(np.argmax(ts > _T_MAX))
            raise InputError(f"{source}: timestamp {ts[i]} at {at(i)} is out of range")
        ts = ts.astype(np.int64)
        if n and ts.min() < 0:
            i = int(np.argmax(ts < 0))
            raise InputError(f"{source}: negative timestamp {ts[i]} at {at(i)}")
        if n > 1:
            back = np.diff(ts) < 0
            if back.any():
                i = int(np.argmax(back)) + 1
                raise InputError(
                    f"{source}: timestamps are not sorted ({at(i)} at t={ts[i]} comes after "
                    f"t={ts[i - 1]})"
                )
        return cls(
            xs.astype(np.uint16),
            ys.astype(np.uint16),
            ts,
            _polarity(ps, source, at),
            int(width),
            int(height),
        )

    def __len__(self) -> int:
        return len(self.t)

    @property
    def duration_us(self) -> int:
        return int(self.t[-1] - self.t[0]) if len(self) else 0

    def slice_time(self, t0: int, t1: int) -> EventStream:
        """Events with t0 <= t < t1 (a view, no copy)."""
        i0, i1 = np.searchsorted(self.t, [t0, t1], side="left")
        return EventStream(
            self.x[i0:i1], self.y[i0:i1], self.t[i0:i1], self.p[i0:i1], self.width, self.height
        )

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
            "busiest_pixel": {
                "x": busiest % self.width,
                "y": busiest // self.width,
                "events": int(counts[busiest]) if n else 0,
            },
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
    (period P = `t_end - t_start`): E(t0, t1] = E(t0 + P, min(t1 + P, t_end)] + E[t_start, t1]
    (events at exactly t_start count in wrapped windows; windows are shorter than P).
    """

    def __init__(
        self,
        stream: EventStream,
        pos_threshold: float,
        neg_threshold: float | None = None,
        polarity_offset: float = 0.0,
        t_start: int | None = None,
        t_end: int | None = None,
        loop: bool = False,
    ):
        self.width, self.height = stream.width, stream.height
        self.pos_threshold = float(pos_threshold)
        self.neg_threshold = float(pos_threshold if neg_threshold is None else neg_threshold)
        self.polarity_offset = float(polarity_offset)
        if len(stream) == 0 and (t_start is None or t_end is None):
            raise InputError("EventIndex: an empty stream needs explicit t_start and t_end")
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
        e = (
            n_pos * (1.0 + off) * self.pos_threshold
            + (n - n_pos) * (off - 1.0) * self.neg_threshold
        )
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
        # t1 + P, not t_end: a window that ends before t_start (or has t0 = t1) stays short.
        t1b = np.where(wraps, np.minimum(t1 + self.period, self.t_end), self.t_end)
        return t0a, t1, t0b, t1b

    def query(self, pix, t0, t1) -> np.ndarray:
        """E(u; t0, t1] for flat pixels `pix` (B,), windows t0, t1 (B,) int64 µs -> (B,) float32."""
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


_T_MAX = 2**62  # µs: ~146,000 years; leaves int64 headroom for window arithmetic


def _polarity(p: np.ndarray, source: str, at) -> np.ndarray:
    """Polarity as int8 ±1 from {-1, +1}, {0, 1} or bool; anything else is an InputError."""
    if p.dtype == bool:
        return np.where(p, 1, -1).astype(np.int8)
    if not len(p):
        return p.astype(np.int8)
    pos, neg, zero = p == 1, p == -1, p == 0
    bad = ~(pos | neg | zero)
    if bad.any():
        i = int(np.argmax(bad))
        raise InputError(f"{source}: polarity {p[i]} at {at(i)} is not -1/+1 or 0/1")
    if neg.any() and zero.any():  # {-1, 0, 1}: 0 means neither convention
        i = max(int(np.argmax(neg)), int(np.argmax(zero)))
        raise InputError(f"{source}: polarity mixes -1 and 0 (at {at(i)}); use -1/+1 or 0/1")
    return np.where(pos, 1, -1).astype(np.int8)


def _segment_searchsorted(
    values: np.ndarray, offsets: np.ndarray, seg: np.ndarray, q: np.ndarray
) -> np.ndarray:
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
