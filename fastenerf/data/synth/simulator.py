"""ESIM-style event simulator: rendered frames -> an `EventStream`.

Model (Rebecq et al., ESIM, CoRL 2018), per pixel u:
  - sensor intensity I(u) from LINEAR RGB: the pixel's Bayer channel for a colour sensor
    (RGGB: R at (even row, even col), G at (even, odd) and (odd, even), B at (odd, odd);
    `fastenerf.data.rig.BAYER_RGGB`), or the Rec. 709 luminance
    0.2126 R + 0.7152 G + 0.0722 B for a mono sensor (`LUMA_WEIGHTS`);
  - log intensity L = log(max(I, 0) + eps); eps (default 1e-3, as ESIM's `log_eps`) keeps
    black pixels finite and damps the log's blow-up in the dark; it is recorded in
    scene.json as `sim_log_eps`;
  - between two frames L moves linearly in time; every time it crosses ref ± C the pixel
    fires an event of polarity ±1 at the interpolated crossing time, and ref moves by ±C
    (several events per interval when the change is large). The initial ref is L of the
    first frame.
Timestamps are integer µs: a crossing at real time s in (t_a, t_b] is stamped ceil(s), so
events of a frame interval stay inside (t_a, t_b] and a window (t_i, t_j] between two frames
counts exactly the crossings between those two frames.

Options: separate positive / negative thresholds; per-pixel threshold mismatch (Gaussian, σ
in log units, seeded, thresholds clamped at 0.01); refractory period (a crossing within
`refractory_us` of the pixel's last emitted event is dropped, but ref still moves, so the
change is lost as on a real sensor that is blind while it resets); uniform noise events
(`noise` = fraction of the final stream that is noise, at uniformly random pixels, times
and polarities, seeded). Frames are consumed in chunks: memory holds the per-pixel state
and the events, never all frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import InputError
from ..events import EventStream
from ..rig import BAYER_RGGB

LUMA_WEIGHTS = np.array([0.2126, 0.7152, 0.0722], dtype=np.float64)  # Rec. 709, linear RGB
DEFAULT_LOG_EPS = 1e-3
MIN_THRESHOLD = 0.01  # mismatch draws below this are clamped (a threshold must stay > 0)
_TIE = 1e-9  # relative tolerance (of C) for a level reached exactly


@dataclass
class SimulatorConfig:
    """Sensor and noise model; thresholds and `mismatch` are in log-intensity units."""

    pos_threshold: float = 0.25
    neg_threshold: float | None = None  # None: same as pos_threshold
    bayer: str | None = "rggb"
    log_eps: float = DEFAULT_LOG_EPS
    mismatch: float = 0.0
    refractory_us: float = 0.0
    noise: float = 0.0
    seed: int = 0

    def validate(self) -> SimulatorConfig:
        neg = self.pos_threshold if self.neg_threshold is None else self.neg_threshold
        if not (self.pos_threshold > 0 and neg > 0):
            raise InputError(f"thresholds must be positive (got {self.pos_threshold}, {neg})")
        if self.bayer not in (None, "rggb"):
            raise InputError(f"bayer must be 'rggb' or mono (None), got {self.bayer!r}")
        if not self.log_eps > 0:
            raise InputError(f"log eps must be positive (got {self.log_eps}): log(0) is -inf")
        if self.mismatch < 0 or self.refractory_us < 0:
            raise InputError("mismatch and refractory period must not be negative")
        if not 0 <= self.noise < 1:
            raise InputError(f"noise is a fraction of the stream in [0, 1), got {self.noise}")
        return self


def sensor_intensity(frames: np.ndarray, bayer: str | None) -> np.ndarray:
    """What each pixel measures: (B, H, W, 3) linear RGB -> (B, H, W) float32.

    Frames that are already single-channel (B, H, W) are returned as they are. float64
    input stays float64 (exact analytic tests); anything else becomes float32.
    """
    frames = np.asarray(frames)
    dtype = np.float64 if frames.dtype == np.float64 else np.float32
    if frames.ndim == 3:
        return frames.astype(dtype, copy=False)
    if frames.ndim != 4 or frames.shape[-1] != 3:
        raise InputError(f"frames must be (N, H, W, 3) or (N, H, W), got {frames.shape}")
    if bayer is None:
        return (frames @ LUMA_WEIGHTS.astype(dtype)).astype(dtype, copy=False)
    b, h, w, _ = frames.shape
    chan = BAYER_RGGB[np.arange(h)[:, None] % 2, np.arange(w)[None, :] % 2]
    idx = np.arange(h * w) * 3 + chan.ravel()
    return frames.reshape(b, -1)[:, idx].reshape(b, h, w).astype(dtype, copy=False)


def log_intensity(intensity: np.ndarray, eps: float) -> np.ndarray:
    """L = log(max(I, 0) + eps), float64 (timestamps are interpolated in L)."""
    return np.log(np.maximum(np.asarray(intensity, dtype=np.float64), 0.0) + eps)


class EventSimulator:
    """Streaming simulator: feed frames in time order with `add_frames`, then `finish`.

    width, height: sensor size in pixels; config: `SimulatorConfig`.
    """

    def __init__(self, width: int, height: int, config: SimulatorConfig | None = None):
        self.cfg = (config or SimulatorConfig()).validate()
        self.width, self.height = int(width), int(height)
        n = self.width * self.height
        seeds = np.random.SeedSequence(self.cfg.seed).spawn(2)  # independent streams
        self._noise_rng = np.random.default_rng(seeds[1])
        c_pos = self.cfg.pos_threshold
        c_neg = c_pos if self.cfg.neg_threshold is None else self.cfg.neg_threshold
        self.c_pos = np.full(n, c_pos, np.float64)
        self.c_neg = np.full(n, c_neg, np.float64)
        if self.cfg.mismatch > 0:
            rng = np.random.default_rng(seeds[0])
            self.c_pos = np.maximum(self.c_pos + rng.normal(0, self.cfg.mismatch, n), MIN_THRESHOLD)
            self.c_neg = np.maximum(self.c_neg + rng.normal(0, self.cfg.mismatch, n), MIN_THRESHOLD)
            self._c_pos_lo, self._c_neg_lo = self.c_pos * (1 - _TIE), -self.c_neg * (1 - _TIE)
        else:  # scalars: cheaper than per-pixel arrays in the per-interval full-sensor pass
            self._c_pos_lo, self._c_neg_lo = c_pos * (1 - _TIE), -c_neg * (1 - _TIE)
        self._ref: np.ndarray | None = None  # (n,) reference log level
        self._last_L: np.ndarray | None = None
        self._last_t: float | None = None
        self._first: tuple[np.ndarray, float] | None = None  # (L, t) of the first frame
        self._last_event = np.full(n, -np.inf)  # for the refractory period
        self._events: list[tuple[np.ndarray, ...]] = []  # per chunk: pix, t, p
        self.n_frames = 0

    @property
    def n_events(self) -> int:
        return sum(len(e[0]) for e in self._events)

    def add_frames(self, frames: np.ndarray, t_us) -> None:
        """Consume frames (B, H, W, 3) linear RGB (or (B, H, W) sensor intensity) at times
        t_us (B,) µs, strictly increasing and after every frame seen before."""
        frames = np.asarray(frames)
        if frames.shape[1:3] != (self.height, self.width):
            raise InputError(
                f"frames are {frames.shape[2]}x{frames.shape[1]} but the sensor is "
                f"{self.width}x{self.height}"
            )
        t = np.atleast_1d(np.asarray(t_us, dtype=np.float64))
        if len(t) != len(frames):
            raise InputError(f"{len(frames)} frames but {len(t)} timestamps")
        if not np.all(np.isfinite(t)):
            raise InputError("frame timestamps contain NaN or inf")
        prev = [] if self._last_t is None else [self._last_t]
        if np.any(np.diff(np.concatenate([prev, t])) <= 0):
            raise InputError("frame timestamps must increase strictly")
        intensity = sensor_intensity(frames, self.cfg.bayer).reshape(len(frames), -1)
        if not np.all(np.isfinite(intensity)):
            raise InputError("frames contain NaN or inf")
        L = log_intensity(intensity, self.cfg.log_eps)
        out: list[tuple[np.ndarray, ...]] = []
        for i in range(len(L)):
            if self._ref is None:
                self._ref = L[i].copy()
                self._first = (L[i].copy(), float(t[i]))
            else:
                ev = self._interval(self._last_L, L[i], self._last_t, float(t[i]))
                if ev is not None:
                    out.append(ev)
            self._last_L, self._last_t = L[i], float(t[i])
            self.n_frames += 1
        if out:
            pix, t_ev, p = (np.concatenate(a) for a in zip(*out, strict=True))
            self._events.append((pix.astype(np.int32), t_ev, p))  # int32 pixel ids: 4 B/event

    def close_loop(self, period_us: float) -> None:
        """Simulate the transition from the last frame back to the first, which is seen again
        at t_first + period_us (a closed trajectory such as one turntable revolution)."""
        if self._first is None:
            raise InputError("no frames to close the loop with")
        L0, t0 = self._first
        t_end = t0 + period_us
        if t_end <= self._last_t:
            raise InputError(f"loop period {period_us} µs ends before the last frame")
        ev = self._interval(self._last_L, L0, self._last_t, t_end)
        if ev is not None:
            self._events.append(ev)
        self._last_L, self._last_t = L0, t_end

    def _interval(self, L0: np.ndarray, L1: np.ndarray, ta: float, tb: float):
        """Events of one frame interval (ta, tb], sorted by time: (pix, t, p) or None."""
        ref = self._ref
        d = L1 - ref
        # Cheap full-sensor pass to find the pixels that fire; the rest is per active pixel.
        # A level reached to within rounding counts as crossed: ref only ever moves in
        # multiples of C from L(first frame), so a pixel that returns exactly to an earlier
        # value (e.g. the loop closing on frame 0) sits exactly on a level.
        active = np.flatnonzero((d >= self._c_pos_lo) | (d <= self._c_neg_lo))
        if len(active) == 0:
            return None
        da = d[active]
        up = da > 0
        step = np.where(up, self.c_pos[active], self.c_neg[active])
        k = (np.abs(da) / step + _TIE).astype(np.int64)  # >= 1, several for large changes
        signed = np.where(up, step, -step)
        pix = np.repeat(active, k)
        # j = 1..k within each pixel: the j-th crossing of this interval.
        j = np.arange(len(pix)) - np.repeat(np.cumsum(k) - k, k) + 1
        level = ref[pix] + np.repeat(signed, k) * j
        a = L0[pix]
        frac = np.clip((level - a) / (L1[pix] - a), 0.0, 1.0)  # L1 != L0 where a level is crossed
        lo = np.floor(ta) + 1
        t_ev = np.clip(np.ceil(ta + frac * (tb - ta) - 1e-6), lo, max(lo, np.ceil(tb)))
        t_ev = t_ev.astype(np.int64)
        p = np.repeat(np.where(up, 1, -1).astype(np.int8), k)
        ref[active] += signed * k
        if self.cfg.refractory_us > 0:
            keep = self._refractory(pix, j, t_ev)
            pix, t_ev, p = pix[keep], t_ev[keep], p[keep]
        order = np.argsort(t_ev, kind="stable")  # pix is ascending, so ties stay pixel-ordered
        return pix[order], t_ev[order], p[order]

    def _refractory(self, pix: np.ndarray, j: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Mask of events outside their pixel's refractory period, one crossing rank at a
        time (within a pixel, rank j is later than rank j - 1)."""
        keep = np.zeros(len(pix), dtype=bool)
        for jj in range(1, int(j.max()) + 1):
            sel = np.flatnonzero(j == jj)
            ok = t[sel] - self._last_event[pix[sel]] >= self.cfg.refractory_us
            keep[sel[ok]] = True
            self._last_event[pix[sel[ok]]] = t[sel[ok]]
        return keep

    def finish(self, t_range: tuple[float, float] | None = None) -> EventStream:
        """All events so far plus noise, sorted by time, as an `EventStream`.

        t_range: (t_start, t_end) µs over which noise is spread as integer times in
        (t_start, t_end]; default the first and last frame times (or loop end).
        """
        if self._events:
            pix, t, p = (np.concatenate(a) for a in zip(*self._events, strict=True))
        else:
            pix, t, p = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int8)
        if self.cfg.noise > 0 and len(t):
            lo, hi = t_range if t_range is not None else (self._first[1], self._last_t)
            n_noise = int(round(len(t) * self.cfg.noise / (1.0 - self.cfg.noise)))
            rng = self._noise_rng
            tn = np.sort(rng.integers(int(np.floor(lo)) + 1, int(np.ceil(hi)) + 1, n_noise))
            pn = rng.integers(0, self.width * self.height, n_noise)
            sn = (rng.integers(0, 2, n_noise) * 2 - 1).astype(np.int8)
            at = np.searchsorted(t, tn, side="right")  # merge: both are sorted by time
            pix, t, p = np.insert(pix, at, pn), np.insert(t, at, tn), np.insert(p, at, sn)
        w = self.width
        return EventStream(
            (pix % w).astype(np.uint16),
            (pix // w).astype(np.uint16),
            t.astype(np.int64),
            p.astype(np.int8),
            self.width,
            self.height,
        )


def simulate(
    frames: np.ndarray,
    t_us: np.ndarray,
    config: SimulatorConfig | None = None,
    loop_period_us: float | None = None,
    chunk: int = 64,
) -> EventStream:
    """Events of frames (N, H, W, 3) linear RGB (or (N, H, W) intensity) at times t_us (N,).

    loop_period_us: if given, the last frame also transitions back to the first, seen again
    at t_us[0] + loop_period_us. Frames are processed `chunk` at a time.
    """
    frames = np.asarray(frames)
    if frames.ndim not in (3, 4) or len(frames) < 2:
        raise InputError(f"need at least 2 frames (N, H, W[, 3]), got shape {frames.shape}")
    sim = EventSimulator(frames.shape[2], frames.shape[1], config)
    for i in range(0, len(frames), chunk):
        sim.add_frames(frames[i : i + chunk], np.asarray(t_us)[i : i + chunk])
    if loop_period_us is not None:
        sim.close_loop(loop_period_us)
        return sim.finish((float(t_us[0]), float(t_us[0]) + loop_period_us))
    return sim.finish()
