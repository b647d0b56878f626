"""EventStream validation and EventIndex window queries against a brute-force definition."""

from __future__ import annotations

import numpy as np
import pytest

from fastenerf.data.events import EventIndex, EventStream
from fastenerf.errors import InputError


def brute_force(ev: EventStream, pix, t0, t1, c_pos, c_neg, offset, loop, t_start, t_end):
    """E(u; t0, t1] straight from the definition, one (B, N) mask.

    On a loop the stream is periodic with P = t_end - t_start: an event at t also happens at
    t - P, so a window starting before t_start sees the end of the stream (DESIGN §3).
    """
    pix, t0, t1 = (np.asarray(a, np.int64)[:, None] for a in (pix, t0, t1))
    u = ev.y.astype(np.int64) * ev.width + ev.x
    t = ev.t[None, :]
    inside = (t > t0) & (t <= t1)
    if loop:
        inside |= (t - (t_end - t_start) > t0) & (t - (t_end - t_start) <= t1)
    w = np.where(ev.p > 0, (1 + offset) * c_pos, (offset - 1) * c_neg)
    return ((u[None, :] == pix) & inside).astype(np.float64) @ w


def random_windows(rng, ev, n, t_start, t_end, loop):
    """Windows of every kind: random, wrapping, empty, t0 = t1, reversed, on duplicate times."""
    period = t_end - t_start
    lo = t_start - period // 2 if loop else t_start - 10
    t0 = rng.integers(lo, t_end, n)
    t1 = np.minimum(t0 + rng.integers(0, period // 2, n), t_end)
    k = n // 8
    t0[:k] = t1[:k]  # t0 = t1: always empty
    dup = ev.t[np.flatnonzero(np.diff(ev.t) == 0)]  # timestamps that occur more than once
    t0[k : 2 * k], t1[k : 2 * k] = rng.choice(dup, k), rng.choice(dup, k) + rng.integers(0, 50, k)
    t0[2 * k : 3 * k] = t1[2 * k : 3 * k] + 5  # reversed: empty by definition
    pix = rng.integers(0, ev.width * ev.height, n)
    return pix, t0, t1


@pytest.mark.parametrize("loop", [False, True])
@pytest.mark.parametrize("c_pos,c_neg,offset", [(0.25, 0.25, 0.0), (0.2, 0.35, -0.4)])
def test_query_matches_brute_force(rng, random_stream, loop, c_pos, c_neg, offset):
    ev = random_stream(n=3000, width=8, height=6, t_max=20_000)
    assert np.any(np.diff(ev.t) == 0), "the stream must contain duplicate timestamps"
    t_start, t_end = 0, 20_000
    idx = EventIndex(ev, c_pos, c_neg, offset, t_start=t_start, t_end=t_end, loop=loop)
    pix, t0, t1 = random_windows(rng, ev, 800, t_start, t_end, loop)
    got = idx.query(pix, t0, t1)
    want = brute_force(ev, pix, t0, t1, c_pos, c_neg, offset, loop, t_start, t_end)
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-5)
    assert np.all(got[t0 >= t1] == 0)
    assert np.any(got != 0) and (not loop or np.any(got[t0 < t_start] != 0))


@pytest.mark.parametrize("loop", [False, True])
def test_wrap_with_default_bounds_and_edge_timestamps(random_stream, loop):
    """t_start/t_end default to the first/last event; events exactly at both ends count once
    per period, and a wrapped window equals the sum of its two plain halves."""
    ev = random_stream(n=500, width=3, height=2, t_max=1000, t_min=100)
    idx = EventIndex(ev, 0.5, loop=loop)
    assert (idx.t_start, idx.t_end) == (ev.t[0], ev.t[-1])
    pix = np.arange(6)
    for t0, t1 in [(ev.t[0] - 200, ev.t[0] + 50), (ev.t[0] - 1, ev.t[0]), (ev.t[-2], ev.t[-1])]:
        want = brute_force(ev, pix, [t0] * 6, [t1] * 6, 0.5, 0.5, 0.0, loop, *ev.t[[0, -1]])
        np.testing.assert_allclose(idx.query(pix, np.full(6, t0), np.full(6, t1)), want, atol=1e-6)
    if loop:
        plain = EventIndex(ev, 0.5, loop=False)
        t0, t1 = ev.t[0] - 300, ev.t[0] + 40
        whole = idx.query(pix, np.full(6, t0), np.full(6, t1))
        head = plain.query(pix, np.full(6, ev.t[0] - 1), np.full(6, t1))
        tail = plain.query(pix, np.full(6, t0 + idx.period), np.full(6, ev.t[-1]))
        np.testing.assert_allclose(whole, head + tail, atol=1e-6)
        assert np.any(tail != 0) and np.any(head != 0)


@pytest.mark.parametrize("loop", [False, True])
def test_accumulate_equals_per_pixel_query(rng, random_stream, loop):
    ev = random_stream(n=4000, width=10, height=7, t_max=50_000)
    idx = EventIndex(ev, 0.3, 0.2, 0.1, t_start=0, t_end=50_000, loop=loop)
    all_pix = np.arange(ev.width * ev.height)
    for t0, t1 in [
        (-12_000, 3_000),
        (0, 50_000),
        (7_000, 7_000),
        (20_000, 31_000),
        (int(ev.t[100]), int(ev.t[100])),
        (int(ev.t[10]) - 1, int(ev.t[500])),
    ]:
        img = idx.accumulate(t0, t1)
        assert img.shape == (ev.height, ev.width) and img.dtype == np.float32
        q = idx.query(all_pix, np.full(all_pix.size, t0), np.full(all_pix.size, t1))
        np.testing.assert_allclose(img.ravel(), q, rtol=1e-6, atol=1e-5)


def test_hundred_thousand_events_at_one_pixel(rng):
    n = 100_000
    t = np.sort(rng.integers(0, 1_000_000, n))
    p = rng.choice([-1, 1], n)
    ev = EventStream.from_arrays(np.full(n, 5), np.full(n, 3), t, p, 8, 4)
    idx = EventIndex(ev, 0.1, 0.3, t_start=0, t_end=1_000_000)
    u = 3 * 8 + 5
    t0 = np.array([-1, 250_000, 0, 999_999, 400_000])
    t1 = np.array([1_000_000, 750_000, 0, 1_000_000, 400_001])
    pos = [(p[(t > a) & (t <= b)] > 0).sum() for a, b in zip(t0, t1, strict=True)]
    neg = [(p[(t > a) & (t <= b)] < 0).sum() for a, b in zip(t0, t1, strict=True)]
    want = np.array(pos) * 0.1 - np.array(neg) * 0.3
    got = idx.query(np.full(5, u), t0, t1)
    np.testing.assert_allclose(got, want, rtol=1e-6)
    n_all, n_pos_all = idx.counts(np.array([u]), np.array([-1]), np.array([1_000_000]))
    assert (n_all[0], n_pos_all[0]) == (n, (p > 0).sum())  # exact integer counts
    assert np.all(idx.query(np.arange(32)[np.arange(32) != u], -1, 1_000_000) == 0)


def test_empty_pixels_and_windows(random_stream):
    ev = random_stream(n=50, width=20, height=20, t_max=1000)  # most pixels have no event
    idx = EventIndex(ev, 0.25, t_start=0, t_end=1000)
    u = ev.y.astype(np.int64) * 20 + ev.x
    silent = np.setdiff1d(np.arange(400), u)[:10]
    assert np.all(idx.query(silent, np.zeros(10), np.full(10, 1000)) == 0)
    assert idx.accumulate(2000, 3000).sum() == 0  # after the stream
    assert np.all(idx.accumulate(500, 500) == 0)


def test_window_slice_is_half_open_on_the_left():
    t = np.array([10, 20, 20, 30])
    ev = EventStream.from_arrays([0, 1, 2, 3], [0, 0, 0, 0], t, [1, 1, -1, 1], 4, 1)
    idx = EventIndex(ev, 1.0)
    assert idx.window_slice(10, 20) == (1, 3)
    assert idx.window_slice(9, 10) == (0, 1)
    assert idx.window_slice(20, 20) == (3, 3)


# ---------------------------------------------------------------------------- validation

GOOD = dict(x=[0, 1, 2], y=[0, 1, 2], t=[0, 5, 9], p=[1, -1, 1])


@pytest.mark.parametrize(
    "change,words",
    [
        (dict(t=[0, 9, 5]), ["not sorted", "event 2"]),
        (dict(t=[-3, 5, 9]), ["negative", "event 0"]),
        (dict(x=[0, 16, 2]), ["x=16", "event 1", "outside"]),
        (dict(y=[0, 1, 12]), ["y=12", "event 2", "outside"]),
        (dict(x=[0, -1, 2]), ["x=-1", "event 1"]),
        (dict(p=[1, 2, 1]), ["polarity 2", "event 1"]),
        (dict(p=[-1, 0, 1]), ["mixes -1 and 0", "event 1"]),
        (dict(p=[1, 0.5, 1]), ["polarity 0.5", "event 1"]),
        (dict(t=[0.0, np.nan, 9.0]), ["'t'", "NaN or inf", "event 1"]),
        (dict(x=[0.0, 1.0, np.inf]), ["'x'", "NaN or inf", "event 2"]),
        (dict(p=[1.0, np.nan, 1.0]), ["'p'", "NaN or inf", "event 1"]),
        (dict(t=[0.0, 5.5, 9.0]), ["'t'", "event 1", "integer"]),
        (dict(y=[0.0, 1.25, 2.0]), ["'y'", "event 1", "integer"]),
        (dict(x=[], y=[], t=[], p=[]), ["no events"]),
        (dict(x=[0, 1]), ["'x' has 2 entries"]),
        (dict(t=[[0, 5, 9]]), ["'t' must be one-dimensional"]),
        (dict(t=np.array([0, 2**63 - 1, 2**63 - 1], dtype=np.uint64)), ["out of range", "event 1"]),
        (dict(t=["a", "b", "c"]), ["non-numeric"]),
    ],
)
def test_bad_streams_are_one_line_input_errors(change, words):
    arrays = {**GOOD, **change}
    with pytest.raises(InputError) as e:
        EventStream.from_arrays(**arrays, width=16, height=12, source="cam.npz")
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("cam.npz: ")
    for w in words:
        assert w in msg


def test_line_numbers_replace_event_indices():
    with pytest.raises(InputError, match=r"f\.txt: .*line 12"):
        EventStream.from_arrays(
            **{**GOOD, "t": [0, 9, 5]},
            width=16,
            height=12,
            source="f.txt",
            lines=np.array([4, 7, 12]),
        )


@pytest.mark.parametrize("p", [[0, 1, 1], [False, True, True], [-1, 1, 1], [0.0, 1.0, 1.0]])
def test_polarity_conventions_become_plus_minus_one(p):
    ev = EventStream.from_arrays(**{**GOOD, "p": p}, width=16, height=12)
    assert ev.p.dtype == np.int8 and ev.p.tolist() == [-1, 1, 1]
    assert ev.x.dtype == np.uint16 and ev.t.dtype == np.int64


@pytest.mark.parametrize("p,want", [([1, 1, 1], [1, 1, 1]), ([0, 0, 0], [-1, -1, -1])])
def test_all_positive_and_all_zero_polarities(p, want):
    assert EventStream.from_arrays(**{**GOOD, "p": p}, width=16, height=12).p.tolist() == want


def test_empty_allowed_and_stats():
    ev = EventStream.from_arrays([], [], [], [], 4, 3, allow_empty=True)
    assert len(ev) == 0 and ev.stats()["events"] == 0 and ev.duration_us == 0
    with pytest.raises(InputError, match="explicit t_start"):
        EventIndex(ev, 0.25)
    ev = EventStream.from_arrays([1, 1, 2], [0, 0, 2], [0, 500_000, 1_000_000], [1, 1, -1], 4, 3)
    st = ev.stats()
    assert st["busiest_pixel"] == {"x": 1, "y": 0, "events": 2}
    assert st["active_pixels"] == 2 and st["rate_ev_per_s"] == pytest.approx(3.0)
    assert st["positive_fraction"] == pytest.approx(2 / 3)
