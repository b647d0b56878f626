"""Event-window query kernel vs brute force over random streams (DESIGN §4, §5)."""

import numpy as np
import pytest
import torch

from fastenerf.kernels.events import window_counts, window_sum


def build_index(pix, t, p, n_pix):
    """The EventIndex layout (offsets, times, cum_pos), built here independently."""
    order = np.lexsort((t, pix))
    counts = np.bincount(pix, minlength=n_pix)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    cum_pos = np.concatenate([[0], np.cumsum(p[order] > 0)]).astype(np.int64)
    return [torch.from_numpy(a) for a in (offsets, t[order].astype(np.int64), cum_pos)]


def brute(pix, t, p, qpix, t0, t1):
    n = np.zeros(len(qpix), np.int64)
    npos = np.zeros(len(qpix), np.int64)
    for b, (u, a, c) in enumerate(zip(qpix, t0, t1, strict=True)):
        sel = (pix == u) & (t > a) & (t <= c)
        n[b], npos[b] = sel.sum(), (sel & (p > 0)).sum()
    return n, npos


def random_stream(rng, n_pix, n_ev, t_max):
    pix = rng.integers(0, n_pix, n_ev)
    pix[pix == 3] = 4  # pixel 3 stays empty
    t = np.sort(rng.integers(0, t_max, n_ev))  # small t_max: many duplicate timestamps
    p = rng.choice(np.array([-1, 1], np.int8), n_ev)
    return pix, t, p


def queries(rng, n_pix, t_max, n_q):
    qpix = rng.integers(0, n_pix, n_q)
    t0 = rng.integers(-50, t_max + 50, n_q)  # includes windows before / after all events
    t1 = t0 + rng.integers(-20, t_max // 2, n_q)  # includes t1 < t0
    t1[: n_q // 8] = t0[: n_q // 8]  # t0 == t1
    return qpix, t0, t1


def test_counts_and_sum_vs_brute_force():
    rng = np.random.default_rng()
    n_pix, t_max = 40, 300
    pix, t, p = random_stream(rng, n_pix, 5000, t_max)
    idx = build_index(pix, t, p, n_pix)
    qpix, t0, t1 = queries(rng, n_pix, t_max, 3000)
    qpix[:10] = 3  # the empty pixel
    n_ref, npos_ref = brute(pix, t, p, qpix, t0, t1)
    tq = [torch.from_numpy(a.astype(np.int64)) for a in (qpix, t0, t1)]
    n, npos = window_counts(*idx, *tq)
    assert n.dtype == torch.int32
    np.testing.assert_array_equal(n.numpy(), n_ref)
    np.testing.assert_array_equal(npos.numpy(), npos_ref)
    assert (n_ref == 0).any() and (n_ref > 5).any()

    for c_pos, c_neg, off in ((0.25, 0.25, 0.0), (0.1, 0.3, -0.4), (1e-6, 2e-6, 0.0)):
        e = window_sum(*idx, *tq, c_pos, c_neg, off)
        # DESIGN §9: sum over events of (p_i + offset) * threshold(p_i).
        e_ref = np.array(
            [
                sum(
                    (pi + off) * (c_pos if pi > 0 else c_neg)
                    for pi in p[(pix == u) & (t > a) & (t <= c)].astype(np.float64)
                )
                for u, a, c in zip(qpix[:400], t0[:400], t1[:400], strict=True)
            ]
        )
        np.testing.assert_allclose(e.numpy()[:400], e_ref, rtol=1e-6, atol=1e-12)
        assert e.dtype == torch.float32


def test_matches_event_index_layout():
    from fastenerf.data.events import EventIndex, EventStream

    rng = np.random.default_rng()
    w, h, n_ev = 7, 5, 4000
    t = np.sort(rng.integers(0, 10_000, n_ev))
    s = EventStream.from_arrays(
        rng.integers(0, w, n_ev), rng.integers(0, h, n_ev), t, rng.choice([-1, 1], n_ev), w, h
    )
    ei = EventIndex(s, 0.25, 0.3, polarity_offset=0.1)
    qpix = rng.integers(0, w * h, 2000)
    t0 = rng.integers(-100, 10_100, 2000)
    t1 = t0 + rng.integers(0, 3000, 2000)
    n_ref, npos_ref = ei.counts(qpix, t0, t1)
    d = ei.to_torch("cpu")
    tq = [torch.from_numpy(a.astype(np.int64)) for a in (qpix, t0, t1)]
    n, npos = window_counts(d["offsets"], d["times"], d["cum_pos"], *tq)
    np.testing.assert_array_equal(n.numpy(), n_ref)
    np.testing.assert_array_equal(npos.numpy(), npos_ref)
    e = window_sum(d["offsets"], d["times"], d["cum_pos"], *tq, 0.25, 0.3, 0.1)
    np.testing.assert_array_equal(e.numpy(), ei.weights(n_ref, npos_ref))


def test_hundred_thousand_events_at_one_pixel_with_duplicates():
    rng = np.random.default_rng()
    n_ev = 100_000
    t = np.sort(rng.integers(0, 5_000, n_ev))  # ~20 events per timestamp
    pix = np.full(n_ev, 1)
    p = rng.choice(np.array([-1, 1], np.int8), n_ev)
    idx = build_index(pix, t, p, 3)
    qt = rng.integers(-10, 5_010, (500, 2))
    t0, t1 = qt.min(1), qt.max(1)
    t0[:5], t1[:5] = [-5, 4_999, 0, 2_500, -1], [5_000, 10**12, 0, 2_500, 4_999]
    # Brute force via sorted search (n_ev x 500 masks would be slow).
    lo = np.searchsorted(t, t0, side="right")
    hi = np.searchsorted(t, t1, side="right")
    cp = np.concatenate([[0], np.cumsum(p > 0)])
    qp = torch.ones(500, dtype=torch.int64)
    n, npos = window_counts(*idx, qp, torch.from_numpy(t0), torch.from_numpy(t1))
    np.testing.assert_array_equal(n.numpy(), hi - lo)
    np.testing.assert_array_equal(npos.numpy(), cp[hi] - cp[lo])
    assert n[0] == n_ev and n[2] == 0 and n[3] == 0
    e = window_sum(*idx, qp, torch.from_numpy(t0), torch.from_numpy(t1), 0.25, 0.25, 0.0)
    assert e[0] == pytest.approx(0.25 * (2 * int(cp[-1]) - n_ev))
    # Neighbouring empty pixels see nothing.
    n0, _ = window_counts(
        *idx, torch.tensor([0, 2]), torch.tensor([-1, -1]), torch.tensor([10**9, 10**9])
    )
    assert n0.tolist() == [0, 0]


def test_empty_stream_and_bad_pixels():
    idx = build_index(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int8), 4)
    n, npos = window_counts(*idx, torch.tensor([0, 3, 4, -1]), torch.tensor(0), torch.tensor(9))
    assert n.tolist() == [0, 0, -1, -1] and npos.tolist() == [0, 0, -1, -1]
    e = window_sum(*idx, torch.tensor([0, 5]), torch.tensor(0), torch.tensor(9), 0.2, 0.2)
    assert e[0] == 0 and torch.isnan(e[1])
    with pytest.raises(ValueError, match="int64"):
        window_counts(*idx, torch.tensor([0], dtype=torch.int32), torch.tensor(0), torch.tensor(1))
