"""ESIM-style simulator: analytic cases, sensor model, noise, refractory, mismatch, chunking."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fastenerf.cli import main
from fastenerf.data.formats.native import read_events
from fastenerf.data.rig import BAYER_RGGB
from fastenerf.data.synth.simulator import (
    LUMA_WEIGHTS,
    EventSimulator,
    SimulatorConfig,
    log_intensity,
    sensor_intensity,
    simulate,
)
from fastenerf.errors import InputError

EPS = 1e-3


def frames_from_log(L: np.ndarray, eps: float = EPS) -> np.ndarray:
    """Single-channel frames whose log(I + eps) is exactly `L` (N, H, W)."""
    return np.exp(np.asarray(L, np.float64)) - eps


def mono(**kw) -> SimulatorConfig:
    return SimulatorConfig(bayer=None, **kw)


def expected_ramp_events(L: np.ndarray, t: np.ndarray, C: float):
    """Reference: crossings of the piecewise-linear L(t) of one pixel, walked one by one."""
    ref, out = L[0], []
    for k in range(len(L) - 1):
        a, b = L[k], L[k + 1]
        while b - ref >= C:
            ref += C
            out.append((math.ceil(t[k] + (ref - a) / (b - a) * (t[k + 1] - t[k]) - 1e-6), 1))
        while ref - b >= C:
            ref -= C
            out.append((math.ceil(t[k] + (ref - a) / (b - a) * (t[k + 1] - t[k]) - 1e-6), -1))
    return out


def test_log_linear_ramp_exact_count_and_times():
    C, rate = 0.25, 0.00131  # log units per µs: a crossing every ~190.8 µs
    t = np.arange(0, 5001, 1000, dtype=np.float64)
    L = (-1.0 + rate * t)[:, None, None]
    ev = simulate(frames_from_log(L), t, mono(pos_threshold=C))
    n_expected = math.floor(rate * 5000 / C)
    assert len(ev) == n_expected == 26
    assert np.all(ev.p == 1)
    t_exact = np.arange(1, n_expected + 1) * C / rate
    assert np.abs(t_exact - np.round(t_exact)).min() > 1e-3  # the test's premise: no ties
    np.testing.assert_array_equal(ev.t, np.ceil(t_exact))  # stamped at the next µs


def test_both_polarities_in_order():
    C = 0.25
    t = np.array([0.0, 1000.0, 2000.0])
    L = np.array([0.0, 1.1, -0.3])[:, None, None]
    ev = simulate(frames_from_log(L), t, mono(pos_threshold=C))
    # Up: levels 0.25 .. 1.0 (4 events, ref = 1.0); down: 0.75 .. -0.25 (5 events).
    np.testing.assert_array_equal(ev.p, [1] * 4 + [-1] * 5)
    got = list(zip(ev.t.tolist(), ev.p.tolist(), strict=True))
    assert got == expected_ramp_events(L[:, 0, 0], t, C)


def test_separate_thresholds():
    t = np.array([0.0, 1000.0, 2000.0])
    L = np.array([0.0, 1.05, 0.0])[:, None, None]
    ev = simulate(frames_from_log(L), t, mono(pos_threshold=0.5, neg_threshold=0.2))
    # +: 0.5, 1.0 (ref 1.0); -: 0.8, 0.6, 0.4, 0.2, 0.0 -> 5.
    np.testing.assert_array_equal(ev.p, [1, 1, -1, -1, -1, -1, -1])


def test_many_crossings_in_one_interval_are_evenly_spaced():
    C, dL = 0.25, 10.1
    L = np.array([0.0, dL])[:, None, None]
    ev = simulate(frames_from_log(L), np.array([0.0, 1000.0]), mono(pos_threshold=C))
    k = np.arange(1, 41)
    assert len(ev) == 40
    np.testing.assert_array_equal(ev.t, np.ceil(k * C / dL * 1000 - 1e-6))


def test_random_piecewise_signal_matches_sequential_reference():
    rng = np.random.default_rng(3)
    L = np.cumsum(rng.normal(0, 0.6, 60))
    t = np.cumsum(rng.integers(200, 3000, 60)).astype(np.float64)
    ev = simulate(frames_from_log(L[:, None, None]), t, mono(pos_threshold=0.2))
    ref = expected_ramp_events(L, t, 0.2)
    assert list(zip(ev.t.tolist(), ev.p.tolist(), strict=True)) == ref


def test_zero_intensity_uses_eps_guard():
    # A dim pixel lighting up, then going black (and a slightly negative value, clamped):
    # without eps, log(0) = -inf and the count is garbage.
    frames = np.array([2e-4, 0.5, 0.0, -0.01])[:, None, None]
    t = np.arange(4) * 1000.0
    ev = simulate(frames, t, mono(pos_threshold=0.3, log_eps=EPS))
    assert np.all(np.isfinite(log_intensity(frames, EPS)))
    # up: ln(0.501 / 0.0012) = 6.03 -> 20; down: ln(0.501 / 0.001) - 0.03 -> 20; then none.
    np.testing.assert_array_equal(ev.p, [1] * 20 + [-1] * 20)
    assert np.all((ev.t > 0) & (ev.t <= 2000))
    with pytest.raises(InputError, match="eps"):
        SimulatorConfig(log_eps=0.0).validate()


def test_saturated_and_huge_intensity():
    # A ramp that clips at 1.0 (as the renderer's output does): no events while saturated.
    frames = np.array([0.2, 0.6, 1.0, 1.0, 1.0, 1.0, 3e30])[:, None, None]
    t = np.arange(7) * 1000.0
    ev = simulate(frames, t, mono(pos_threshold=0.25))
    L = np.log(frames[:, 0, 0] + EPS)
    assert not np.any((ev.t > 2000) & (ev.t <= 5000))
    assert np.all(ev.p == 1)
    assert len(ev) == math.floor((L[-1] - L[0]) / 0.25)  # 278: many, all finite
    n_ramp = math.floor((L[2] - L[0]) / 0.25)
    last = ev.t[ev.t > 5000]
    assert len(last) == len(ev) - n_ramp and np.all(last <= 6000)


def test_bayer_channel_selection():
    h, w = 4, 6
    base = np.full((h, w, 3), 0.3)
    for ch in range(3):
        f1 = base.copy()
        f1[..., ch] = 0.9  # only channel ch brightens
        ev = simulate(np.stack([base, f1]), np.array([0.0, 1000.0]), SimulatorConfig())
        hit = np.zeros((h, w), bool)
        hit[ev.y, ev.x] = True
        yy, xx = np.mgrid[0:h, 0:w]
        np.testing.assert_array_equal(hit, BAYER_RGGB[yy % 2, xx % 2] == ch)
        n_per_pixel = math.floor((math.log(0.9 + EPS) - math.log(0.3 + EPS)) / 0.25)
        assert len(ev) == hit.sum() * n_per_pixel


def test_mono_uses_luminance():
    f0 = np.full((1, 2, 2, 3), 0.2)
    f1 = f0.copy()
    f1[..., 0] = 1.0  # red only
    inten = sensor_intensity(np.concatenate([f0, f1]), None)
    np.testing.assert_allclose(inten[1], 0.2 + 0.8 * LUMA_WEIGHTS[0], rtol=1e-6)
    ev = simulate(np.concatenate([f0, f1]), np.array([0.0, 1000.0]), mono())
    dL = math.log(0.2 + 0.8 * LUMA_WEIGHTS[0] + EPS) - math.log(0.2 + EPS)
    assert len(ev) == 4 * math.floor(dL / 0.25)


def test_noise_fraction_and_stream_format():
    rng = np.random.default_rng(0)
    frames = rng.uniform(0.05, 1.0, (30, 12, 16, 3))
    t = np.arange(30) * 1000.0
    clean = simulate(frames, t, SimulatorConfig(seed=1))
    noisy = simulate(frames, t, SimulatorConfig(seed=1, noise=0.15))
    frac = (len(noisy) - len(clean)) / len(noisy)
    assert abs(frac - 0.15) < 1e-3
    assert noisy.t.dtype == np.int64 and noisy.x.dtype == np.uint16 and noisy.p.dtype == np.int8
    assert np.all(np.diff(noisy.t) >= 0)
    assert noisy.t.min() > 0 and noisy.t.max() <= 29000
    assert set(np.unique(noisy.p)) == {-1, 1}
    # The clean events are all still there (noise is added, nothing removed).
    key = lambda e: np.sort(e.t * 10**6 + e.y.astype(np.int64) * 16 + e.x)  # noqa: E731
    assert np.isin(key(clean), key(noisy)).all()


def test_refractory_period_respected():
    C, dL = 0.25, 10.1  # 40 crossings ~25 µs apart in each interval
    L = np.array([0.0, dL, 0.0, dL])[:, None, None]
    t = np.array([0.0, 1000.0, 2000.0, 3000.0])
    ev = simulate(frames_from_log(L), t, mono(pos_threshold=C, refractory_us=100))
    assert np.all(np.diff(ev.t) >= 100)
    # Sequential reference: keep a crossing iff >= 100 µs after the last kept one.
    full = simulate(frames_from_log(L), t, mono(pos_threshold=C))
    kept, last = [], -np.inf
    for ti in full.t:
        if ti - last >= 100:
            kept.append(ti)
            last = ti
    np.testing.assert_array_equal(ev.t, kept)
    assert len(ev) == 24  # crossings ~24.75 µs apart: every 5th one survives, 8 per interval


def test_mismatch_seeded_and_reproducible():
    a = EventSimulator(100, 80, SimulatorConfig(mismatch=0.03, seed=5))
    b = EventSimulator(100, 80, SimulatorConfig(mismatch=0.03, seed=5))
    c = EventSimulator(100, 80, SimulatorConfig(mismatch=0.03, seed=6))
    np.testing.assert_array_equal(a.c_pos, b.c_pos)
    assert not np.array_equal(a.c_pos, c.c_pos)
    assert abs(a.c_pos.std() - 0.03) < 0.003 and abs(a.c_pos.mean() - 0.25) < 0.003
    assert not np.array_equal(a.c_pos, a.c_neg)
    # Changing the noise rate must not change the threshold map (independent streams).
    d = EventSimulator(100, 80, SimulatorConfig(mismatch=0.03, seed=5, noise=0.1))
    np.testing.assert_array_equal(a.c_pos, d.c_pos)
    flat = EventSimulator(10, 10, SimulatorConfig())
    assert np.all(flat.c_pos == 0.25)


def _stream_tuple(ev):
    return ev.x, ev.y, ev.t, ev.p


@pytest.mark.parametrize("chunk", [1, 7])
def test_chunked_equals_unchunked(chunk):
    rng = np.random.default_rng(1)
    frames = np.clip(np.cumsum(rng.normal(0, 0.15, (25, 10, 12, 3)), 0) + 0.5, 0, 1)
    t = np.arange(25) * 1000.0
    cfg = dict(mismatch=0.02, refractory_us=50, noise=0.05, seed=3)
    whole = simulate(frames, t, SimulatorConfig(**cfg), chunk=1000, loop_period_us=25000)
    parts = simulate(frames, t, SimulatorConfig(**cfg), chunk=chunk, loop_period_us=25000)
    assert len(whole) > 100
    for a, b in zip(_stream_tuple(whole), _stream_tuple(parts), strict=True):
        np.testing.assert_array_equal(a, b)


def test_loop_closure_returns_every_pixel_to_its_start():
    rng = np.random.default_rng(2)
    frames = rng.uniform(0.02, 1.0, (12, 8, 10, 3))
    t = np.arange(12) * 1000.0
    ev = simulate(frames, t, SimulatorConfig(), loop_period_us=12000)
    assert ev.t.max() <= 12000 and np.any(ev.t > 11000)  # the wrap interval has events
    net = np.zeros((8, 10))
    np.add.at(net, (ev.y, ev.x), ev.p.astype(np.float64) * 0.25)
    assert np.abs(net).max() < 0.25  # L is back where it started: |sum| < C
    open_ = simulate(frames, t, SimulatorConfig())
    assert open_.t.max() <= 11000


def test_invalid_inputs_are_one_line_errors():
    sim = EventSimulator(4, 3)
    with pytest.raises(InputError, match="NaN"):
        sim.add_frames(np.full((2, 3, 4, 3), np.nan), [0, 1000])
    sim.add_frames(np.full((1, 3, 4, 3), 0.5), [1000])
    with pytest.raises(InputError, match="increase"):
        sim.add_frames(np.full((1, 3, 4, 3), 0.5), [1000])
    with pytest.raises(InputError, match="sensor"):
        sim.add_frames(np.full((1, 5, 4, 3), 0.5), [2000])
    with pytest.raises(InputError):
        SimulatorConfig(noise=1.0).validate()


def test_simulate_command(tmp_path, capsys):
    rng = np.random.default_rng(4)
    frames = rng.uniform(0.0, 1.0, (10, 6, 8, 3)).astype(np.float32)
    t = np.arange(10) * 1e-3  # seconds
    np.savez(tmp_path / "f.npz", frames=frames, t=t)
    out = tmp_path / "e.npz"
    rc = main(
        [
            "simulate",
            "--frames",
            str(tmp_path / "f.npz"),
            "--out",
            str(out),
            "--threshold",
            "0.3",
            "--refractory-us",
            "10",
            "--mismatch",
            "0.01",
        ]
    )
    assert rc == 0
    assert str(out) in capsys.readouterr().out
    ev = read_events(out, 8, 6)
    lib = simulate(
        frames, t * 1e6, SimulatorConfig(pos_threshold=0.3, refractory_us=10, mismatch=0.01)
    )
    np.testing.assert_array_equal(ev.t, lib.t)
    with np.load(out) as z:
        assert int(z["width"]) == 8 and float(z["log_eps"]) == 1e-3
    np.savez(tmp_path / "bad.npz", frames=frames)
    assert main(["simulate", "--frames", str(tmp_path / "bad.npz"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "'t'" in err and len(err.splitlines()) == 1
