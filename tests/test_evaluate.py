"""Colour correction (the reference's log-domain affine fit), PSNR, SSIM, LPIPS availability."""

from __future__ import annotations

import numpy as np
import pytest

from fastenerf.errors import InputError
from fastenerf.evaluate import (
    color_correct,
    comparison_sheet,
    fit_color_correction,
    from_log,
    lpips_score,
    psnr,
    ssim,
    to_log,
)


def test_color_correction_recovers_a_known_log_affine_map():
    rng = np.random.default_rng(0)
    gt = rng.uniform(0.2, 0.9, (3, 12, 16, 3))
    # A per-channel affine distortion in the log(x**2.2 + 0.1) domain, chosen so that the
    # distorted prediction stays inside [0, 1] (no clipping to undo).
    a = np.array([0.9, 1.15, 0.95])
    b = np.array([-0.15, 0.1, 0.05])
    pred = from_log((to_log(gt) - b) / a)
    assert pred.min() > 0 and pred.max() < 1
    assert psnr(pred, gt) < 30  # visibly off before the correction
    fa, fb = fit_color_correction(pred, gt)
    assert np.allclose(fa, a, atol=1e-6) and np.allclose(fb, b, atol=1e-6)
    corrected = color_correct(pred, gt)
    assert corrected.dtype == np.float32 and corrected.shape == gt.shape
    assert np.abs(corrected - gt).max() < 1e-5
    assert psnr(corrected, gt) > 90


def test_color_correction_is_joint_over_views_and_clipped():
    rng = np.random.default_rng(1)
    gt = rng.uniform(0, 1, (2, 8, 8, 3))
    pred = gt.copy()
    pred[1] = 1 - pred[1]  # the second view disagrees: one fit must serve both views
    corrected = color_correct(pred, gt)
    assert corrected.min() >= 0 and corrected.max() <= 1
    assert not np.allclose(corrected[0], gt[0], atol=1e-3)
    with pytest.raises(InputError):
        color_correct(pred[:, :4], gt)


def test_psnr_and_ssim():
    gt = np.full((2, 16, 16, 3), 0.5)
    assert psnr(gt + 0.1, gt) == pytest.approx(20.0)
    assert psnr(gt, gt) == float("inf")
    rng = np.random.default_rng(2)
    img = rng.uniform(0, 1, (2, 16, 16, 3))
    assert ssim(img, img) == pytest.approx(1.0)
    assert ssim(np.clip(img + rng.normal(0, 0.2, img.shape), 0, 1), img) < 0.9
    sheet = comparison_sheet(img.astype(np.float32), img.astype(np.float32))
    assert sheet.shape == (2 * 16 + 2, 3 * 16 + 4, 3)


def test_lpips_is_null_without_local_weights():
    img = np.zeros((1, 16, 16, 3), np.float32)
    value, note = lpips_score(img, img)
    try:
        import lpips  # noqa: F401
    except ImportError:
        assert value is None and "not installed" in note
        return
    if value is None:
        assert note.startswith("LPIPS: weights not found at ")
    else:
        assert value == pytest.approx(0.0, abs=1e-6)
