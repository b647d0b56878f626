"""The event loss against hand-computed values, its eps guard, and the distortion regulariser."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fastenerf.config import TrainConfig, TrajectoryConfig, train_preset
from fastenerf.data.rig import Intrinsics, Rig, Turntable
from fastenerf.errors import InputError
from fastenerf.fields.vanilla import distortion_loss_dense
from fastenerf.losses import (
    LUMA_709,
    event_loss,
    event_prediction,
    log_intensity,
    total_loss,
)

# Two pixels, rendered at t0 and t1 (display-space colours).
RGB0 = torch.tensor([[0.2, 0.5, 0.9], [0.6, 0.3, 0.1]], dtype=torch.float64)
RGB1 = torch.tensor([[0.4, 0.5, 0.3], [0.6, 0.8, 0.7]], dtype=torch.float64)
TARGET = torch.tensor([0.5, -0.25], dtype=torch.float64)


def L(c: float, eps: float) -> float:
    return math.log(c**2.2 + eps)


def bayer_rig(width: int = 4, height: int = 2) -> Rig:
    return Rig(
        Intrinsics(10, 10, width / 2, height / 2, width, height),
        Turntable(TrajectoryConfig()),
        "rggb",
    )


def test_bayer_two_pixels_by_hand():
    # Flat pixel 0 is (row 0, col 0): R; flat pixel 1 is (row 0, col 1): G (RGGB).
    rig = bayer_rig()
    ch = rig.channel(torch.tensor([0, 1]))
    assert ch.tolist() == [0, 1]
    eps = 0.1
    pred0 = L(0.4, eps) - L(0.2, eps)  # red of pixel 0
    pred1 = L(0.8, eps) - L(0.3, eps)  # green of pixel 1
    want = ((pred0 - 0.5) ** 2 + (pred1 + 0.25) ** 2) / 2
    got = event_loss(RGB0, RGB1, TARGET, ch, gamma=2.2, eps=eps)
    assert float(got) == pytest.approx(want, rel=1e-6)
    # Blue at (odd, odd): a 2x2 sensor's flat pixel 3.
    assert bayer_rig(2, 2).channel(torch.tensor([2, 3])).tolist() == [1, 2]


def test_mono_two_pixels_by_hand():
    eps = 1e-5
    w = LUMA_709

    def Y(c):
        return sum(wk * ck**2.2 for wk, ck in zip(w, c, strict=True))

    pred = [
        math.log(Y(RGB1[i].tolist()) + eps) - math.log(Y(RGB0[i].tolist()) + eps) for i in range(2)
    ]
    want = ((pred[0] - 0.5) ** 2 + (pred[1] + 0.25) ** 2) / 2
    got = event_loss(RGB0, RGB1, TARGET, None, gamma=2.2, eps=eps)
    assert float(got) == pytest.approx(want, rel=1e-6)


def test_zero_radiance_is_finite_with_the_eps_guard():
    # A field that renders black at t0: log(0) without eps.
    rgb0 = torch.zeros(2, 3, requires_grad=True)
    rgb1 = torch.full((2, 3), 0.5, requires_grad=True)
    ch = torch.tensor([0, 2])
    for eps in (0.1, 1e-5):
        loss = event_loss(rgb0, rgb1, torch.tensor([1.0, 0.0]), ch, eps=eps)
        loss.backward()
        assert torch.isfinite(loss)
        assert torch.isfinite(rgb0.grad).all() and torch.isfinite(rgb1.grad).all()
        rgb0.grad = rgb1.grad = None
    # The guard is what makes it finite: without eps the loss is infinite.
    assert torch.isinf(log_intensity(torch.zeros(1, 3), None, eps=0.0)).all()
    bad = event_loss(rgb0, rgb1, torch.tensor([1.0, 0.0]), ch, eps=0.0)
    assert not torch.isfinite(bad)
    # ... and the config refuses to switch it off.
    with pytest.raises(InputError, match="log_eps"):
        TrainConfig(log_eps=0.0).validate()


def test_prediction_is_a_log_difference_per_channel():
    rgb = torch.rand(5, 3)
    ch = torch.tensor([0, 1, 2, 1, 0])
    assert torch.allclose(event_prediction(rgb, rgb, ch), torch.zeros(5))
    pred = event_prediction(rgb, rgb * 0 + 1.0, ch, eps=0.1)
    want = torch.log(torch.tensor(1.1)) - torch.log(rgb.gather(1, ch[:, None])[:, 0] ** 2.2 + 0.1)
    assert torch.allclose(pred, want, atol=1e-6)


def brute_distortion(w, m, d):
    out = []
    for wi, mi, di in zip(w, m, d, strict=True):
        bi = sum(wi[a] * wi[b] * abs(mi[a] - mi[b]) for a in range(len(wi)) for b in range(len(wi)))
        out.append(bi + sum(wi[a] ** 2 * di[a] for a in range(len(wi))) / 3)
    return float(np.mean(out))


def test_distortion_loss_matches_the_double_sum():
    g = torch.Generator().manual_seed(0)
    edges = torch.sort(torch.rand(3, 9, generator=g, dtype=torch.float64), -1).values
    m = 0.5 * (edges[:, 1:] + edges[:, :-1])
    d = edges[:, 1:] - edges[:, :-1]
    w = torch.rand(3, 8, generator=g, dtype=torch.float64) / 8
    got = float(distortion_loss_dense(w, m, d).mean())
    assert got == pytest.approx(brute_distortion(w.tolist(), m.tolist(), d.tolist()), rel=1e-9)


def test_total_loss_sums_levels_and_regulariser():
    rgb = torch.cat([RGB0, RGB1]).float()
    ch = torch.tensor([0, 1])
    base, parts = total_loss({"rgb": rgb}, TARGET.float(), ch, gamma=2.2, eps=0.1)
    assert set(parts) == {"event"}
    out = {"rgb": rgb, "rgb_coarse": rgb, "distortion": torch.tensor(2.0)}
    both, parts = total_loss(out, TARGET.float(), ch, gamma=2.2, eps=0.1, distortion_weight=1e-4)
    assert float(both) == pytest.approx(2 * float(base) + 2e-4, rel=1e-6)
    assert set(parts) == {"event", "event_coarse", "distortion"}
    # Weight 0: the regulariser is not even added.
    _, parts = total_loss(out, TARGET.float(), ch, gamma=2.2, eps=0.1, distortion_weight=0.0)
    assert "distortion" not in parts


def test_presets_hold_the_reference_values(scene_config):
    # The reference's loops have 1000 views; window lengths scale with a scene's view count.
    synth = scene_config(64, 48, n_views=1000)
    real = scene_config(64, 48, kind="real", n_views=1000)
    assert train_preset("eventnerf", "vanilla").resolved(scene_config(64, 48)).win_max == 5
    ref = train_preset("eventnerf", "vanilla")
    a, b = ref.resolved(synth), ref.resolved(real)
    assert (a.log_eps, a.win_max, a.neg_ratio, a.distortion_weight) == (0.1, 50, 0.1, 1e-4)
    assert (b.log_eps, b.win_max, b.neg_ratio, b.distortion_weight) == (1e-5, 100, 0.05, 0.0)
    assert (a.rays_per_step, a.windows_per_step, a.lr, a.lr_final, a.win_redraw, a.gamma) == (
        1024,
        1,
        5e-4,
        None,
        "load",
        2.2,
    )
    fast = train_preset("fast", "ngp", minutes=1).resolved(synth)
    assert fast.win_redraw == "step" and fast.windows_per_step > 1 and fast.lr_final < fast.lr
    with pytest.raises(InputError, match="preset"):
        train_preset("slow")


def test_lr_decay_start_holds_the_lr_then_decays_over_the_rest():
    from types import SimpleNamespace

    from fastenerf.field_restart import RestartClock
    from fastenerf.train import Trainer

    def lr_at(cfg, step, clock=None):  # Trainer.lr_at on a budget of 1000 steps, no trainer
        fake = SimpleNamespace(cfg=cfg, progress=lambda s: s / 1000, clock=clock or RestartClock())
        return Trainer.lr_at(fake, step)

    late = train_preset("fast", "ngp", steps=1000, lr_decay_start=0.5)
    assert lr_at(late, 0) == lr_at(late, 500) == late.lr
    ratio = late.lr_final / late.lr
    assert lr_at(late, 750) == pytest.approx(late.lr * ratio**0.5, rel=1e-12)
    assert lr_at(late, 1000) == pytest.approx(late.lr_final, rel=1e-12)
    # the fast preset holds the lr for 70 % of the budget; 0 is the plain exponential decay
    # from the first step, bit for bit
    assert train_preset("fast", "ngp", steps=1000).lr_decay_start == 0.7
    plain = train_preset("fast", "ngp", steps=1000, lr_decay_start=0.0)
    assert plain.lr_decay_start == 0.0
    assert lr_at(plain, 250) == plain.lr * ratio**0.25
    # a field restarted at step 400 (refine_restart): its schedule over the 600 steps left
    clock = RestartClock(step=400, progress=0.4, restarts=1)
    assert lr_at(late, 400, clock) == lr_at(late, 700, clock) == late.lr
    assert lr_at(late, 850, clock) == pytest.approx(late.lr * ratio**0.5, rel=1e-12)
    assert lr_at(late, 1000, clock) == pytest.approx(late.lr_final, rel=1e-12)
