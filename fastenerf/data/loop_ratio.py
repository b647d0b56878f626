"""The contrast-threshold ratio C₊/C₋ measured from a recording's closed loop (issue #20).

A pixel that ends a span at the brightness it started with has changed its log intensity by
zero, so its events over the span cancel: Σ (1 + o)·C₊ (per positive event) − (1 − o)·C₋ (per
negative event) = 0 up to less than one threshold (the events not yet fired at either end), with
o the polarity offset (DESIGN §9). Every pixel returns to its brightness when the camera
returns to its pose in a static scene (a turntable's whole turns), so over such a span

    C₊ / C₋ = (1 − o)·N₋ / ((1 + o)·N₊)

with N± the span's positive and negative events. No field, no training: a count. The common
scale of the thresholds is not in it (docs/self-calibration.md). What biases it: noise events
(their polarities balance, pulling the ratio towards 1), pixels that leave the sensor's range,
and a scene that moves or is lit differently at the span's ends.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from .rig import Rig

ROT_TOL_DEG = 0.25  # a pose "returns" within this rotation ...
POS_TOL = 2e-3  # ... and this distance, as a fraction of the trajectory's extent
N_PROBE = 4096  # times at which the trajectory is compared with its start


@dataclass
class LoopRatio:
    """C₊/C₋ from events over [t0_us, t1_us], a span whose end pose is its start pose."""

    ratio: float
    t0_us: int
    t1_us: int
    n_pos: int
    n_neg: int

    def summary(self, c_neg: float) -> str:
        """One line: the ratio, the span, and C₊ at the given C₋."""
        return (
            f"C+/C- = {self.ratio:.4f} from {self.n_pos + self.n_neg:,} events over "
            f"{(self.t1_us - self.t0_us) / 1e6:.3f} s ({self.t0_us}..{self.t1_us} us, the "
            f"camera back at its start pose); with C- = {c_neg:g}: C+ = {self.ratio * c_neg:.4f}"
        )


def _rotation_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles (degrees) between rotations a (3, 3) and each of b (M, 3, 3)."""
    cos = (np.einsum("ij,mij->m", a, b) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def loop_span(rig: Rig, t_start: int, t_end: int) -> tuple[int, int] | None:
    """The longest span [t_start, t1] (µs) whose end pose is the start pose (within
    ROT_TOL_DEG and POS_TOL of the trajectory's extent), or None when the camera never
    returns. Times are probed at N_PROBE points; t1 is the last probe that matches."""
    ts = np.linspace(t_start, t_end, N_PROBE).round().astype(np.int64)
    c2w = rig.pose(ts)
    centres = c2w[:, :3, 3]
    extent = float(np.linalg.norm(centres.max(0) - centres.min(0)))
    if extent == 0.0:
        return None  # a static camera: no loop to close (and every pixel static anyway)
    rot = _rotation_deg(c2w[0, :3, :3], c2w[:, :3, :3])
    dist = np.linalg.norm(centres - centres[0], axis=1)
    back = (rot <= ROT_TOL_DEG) & (dist <= POS_TOL * extent)
    # a return only counts after the camera went away from the start
    away = np.maximum.accumulate(dist > 0.25 * extent)
    hits = np.nonzero(back & away)[0]
    if len(hits) == 0:
        return None
    return int(ts[0]), int(ts[hits[-1]])


def loop_ratio(
    t_us: np.ndarray, p: np.ndarray, rig: Rig, t_start: int, t_end: int, offset: float = 0.0
) -> LoopRatio:
    """C₊/C₋ from the events (t_us (N,) int64 sorted, p (N,) ±1) over the recording's
    longest closed loop; a one-line InputError where the camera never returns to its start
    pose or the loop holds no events of one polarity."""
    span = loop_span(rig, t_start, t_end)
    if span is None:
        raise InputError(
            "threshold ratio from a loop: the camera never returns to its start pose "
            f"(within {ROT_TOL_DEG}° and {POS_TOL:g} of its path's extent) in "
            f"{t_start}..{t_end} us"
        )
    lo, hi = np.searchsorted(t_us, span[0], "left"), np.searchsorted(t_us, span[1], "right")
    pol = p[lo:hi]
    n_pos, n_neg = int((pol > 0).sum()), int((pol < 0).sum())
    if n_pos == 0 or n_neg == 0:
        raise InputError(
            f"threshold ratio from a loop: {n_pos} positive and {n_neg} negative events in "
            f"{span[0]}..{span[1]} us; both are needed"
        )
    ratio = (1.0 - offset) * n_neg / ((1.0 + offset) * n_pos)
    return LoopRatio(float(ratio), span[0], span[1], n_pos, n_neg)


def scene_loop_ratio(scene) -> LoopRatio:
    """`loop_ratio` of a loaded scene (`data.formats.native.Scene`)."""
    cfg, ev = scene.config, scene.events
    return loop_ratio(ev.t, ev.p, scene.rig(), cfg.t_start_us, cfg.t_end_us, cfg.polarity_offset)
