"""Metrics in the three definitions (mask, bbox, full) against hand-computable cases."""

from __future__ import annotations

import numpy as np
import pytest
from skimage.metrics import structural_similarity

from sgpor_pipeline.metrics import mask_bbox, mean_scores, psnr, score_image, ssim


def test_psnr_known_values():
    a = np.zeros((8, 8, 3), np.float32)
    b = np.full((8, 8, 3), 0.1, np.float32)
    assert psnr(a, b) == pytest.approx(20.0, abs=1e-4)
    assert psnr(a, a) == float("inf")
    mask = np.zeros((8, 8), bool)
    mask[2:4, 2:4] = True
    c = a.copy()
    c[mask] = 0.01
    assert psnr(a, c, mask) == pytest.approx(40.0, abs=1e-3)  # error only inside the mask
    assert psnr(a, c) == pytest.approx(40.0 + 10 * np.log10(64 / 4), abs=1e-3)


def test_three_definitions_differ_as_expected():
    rng = np.random.default_rng(0)
    truth = rng.random((48, 64, 3)).astype(np.float32)
    pred = truth.copy()
    mask = np.zeros((48, 64), bool)
    mask[10:20, 30:50] = True
    pred[mask] = np.clip(pred[mask] + 0.2, 0, 1)
    s = score_image(pred, truth, mask)
    assert mask_bbox(mask) == (10, 20, 30, 50)
    # The mask holds all the error: mask PSNR equals bbox PSNR here (the box is the mask) and both
    # are worse than the full-image PSNR, which averages in the untouched pixels.
    assert s.psnr_mask == pytest.approx(s.psnr_bbox, abs=1e-6)
    assert s.psnr_full > s.psnr_mask + 5
    assert s.ssim_full > s.ssim_mask and s.ssim_mask < 0.99


def test_ssim_agrees_with_scikit_image():
    rng = np.random.default_rng(1)
    a = rng.random((40, 40, 3)).astype(np.float32)
    b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1).astype(np.float32)
    ours = ssim(a, b)
    ref = structural_similarity(a, b, channel_axis=2, data_range=1.0, gaussian_weights=True, sigma=1.5,
                                use_sample_covariance=False)
    assert ours == pytest.approx(ref, abs=0.02)  # border handling differs slightly
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-5)
    assert 0 < ssim(a[:5, :5], b[:5, :5]) <= 1  # smaller than the window


def test_empty_mask_and_mean():
    a = np.zeros((8, 8, 3), np.float32)
    s = score_image(a, a + 0.1, np.zeros((8, 8), bool))
    assert np.isnan(s.psnr_mask) and np.isnan(s.psnr_bbox) and s.psnr_full == pytest.approx(20.0, abs=1e-4)
    m = mean_scores([s, score_image(a, a + 0.01, np.ones((8, 8), bool))])
    assert m["psnr_mask"] == pytest.approx(40.0, abs=1e-3)  # the undefined view is skipped
    assert m["psnr_full"] == pytest.approx(30.0, abs=1e-3)  # mean of 20 and 40 dB
