"""Image quality metrics in the three definitions peers use (DESIGN.md section 8).

- ``mask``: PSNR over the mask's pixels only; SSIM = mean of the SSIM map over the mask's pixels.
- ``bbox``: both images cropped to the mask's bounding box (the SPIn-NeRF lineage), then plain
  PSNR / SSIM of the crops.
- ``full``: the whole image.

Images are float RGB in [0, 1], HxWx3 (numpy). SSIM is kornia's (11x11 Gaussian window, sigma 1.5,
the standard constants), computed on the full image once so that ``mask`` and ``full`` share it.
LPIPS needs backbone weights that are not installable here: it is not reported, never faked.

``feat_mask`` (lower = closer, 0 = identical) is a perceptual distance that needs no download:
:func:`feature_distance`, the mean cosine distance between the patch features of a deep backbone
(the DINOv2-like ViT-S/14 of the ``dinov2`` extra) of result and truth, over the patches that cover
the mask. PSNR prefers a smooth guess to a detailed one in the wrong place; deep features do not
(DINO ViT features agree with human similarity judgements better than LPIPS: DreamSim, Fu et al.
2023). It is not LPIPS and is reported under its own name. Lund + inserted box, means over 28
views, the mask replaced by: the truth 0, the truth + noise sigma 0.05 0.041, the truth shifted 3 px
0.072, the truth blurred (sigma 3 px) 0.135, a flat fill of the truth's mean colour 0.424.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass

import cv2
import kornia
import numpy as np
import torch

DEFINITIONS = ("mask", "bbox", "full")


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR in dB of a against b (peak 1), over ``mask`` pixels when given; inf when identical."""
    diff = (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2
    if mask is not None:
        m = np.asarray(mask, bool)
        if not m.any():
            return float("nan")
        diff = diff[m]
    mse = float(diff.mean())
    return float("inf") if mse == 0.0 else float(10.0 * np.log10(1.0 / mse))


def ssim_map(a: np.ndarray, b: np.ndarray, window: int = 11) -> np.ndarray:
    """Per-pixel SSIM (averaged over channels), HxW; borders use reflection padding."""
    ta = torch.from_numpy(np.ascontiguousarray(a, np.float32)).permute(2, 0, 1)[None]
    tb = torch.from_numpy(np.ascontiguousarray(b, np.float32)).permute(2, 0, 1)[None]
    h, w = ta.shape[-2:]
    side = min(h, w)
    window = min(window, side if side % 2 else side - 1)  # odd, and no larger than the image
    with torch.no_grad():
        m = kornia.metrics.ssim(ta, tb, window, max_val=1.0, padding="same")
    return m[0].mean(0).numpy()


def ssim(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    smap = ssim_map(a, b)
    if mask is None:
        return float(smap.mean())
    m = np.asarray(mask, bool)
    return float(smap[m].mean()) if m.any() else float("nan")


def mask_bbox(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """(y0, y1, x0, x1), end-exclusive, of the mask's non-zero pixels; None when empty."""
    ys, xs = np.nonzero(mask)
    if ys.size == 0:
        return None
    return int(ys.min()), int(ys.max()) + 1, int(xs.min()), int(xs.max()) + 1


#: image (HxWx3 float RGB, side ``FEATURE_SIDE``) -> patch features [h, w, C]
PatchFeatures = Callable[[np.ndarray], np.ndarray]
FEATURE_SIDE = 224  # the crop is resized to this square (16 x 16 patches of a /14 ViT)
FEATURE_CONTEXT = 1.5  # the crop's side, in units of the mask's bounding box's longer side
FEATURE_COVER = 0.25  # a patch counts when at least this share of it is mask


def feature_crop(shape: tuple[int, int], mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """(y0, y1, x0, x1): the square around the mask's bounding box (``FEATURE_CONTEXT`` times its longer
    side, plus 8 px) that :func:`feature_distance` compares, clipped to the image; None when empty."""
    box = mask_bbox(mask)
    if box is None:
        return None
    y0, y1, x0, x1 = box
    half = max(y1 - y0, x1 - x0) * FEATURE_CONTEXT / 2 + 8
    cy, cx = (y0 + y1) / 2, (x0 + x1) / 2
    h, w = shape
    return (int(max(0, cy - half)), int(min(h, np.ceil(cy + half))),
            int(max(0, cx - half)), int(min(w, np.ceil(cx + half))))


def feature_distance(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray, features: PatchFeatures,
                     truth_features: np.ndarray | None = None) -> float:
    """Mean cosine distance (1 - cos) of the patch features of ``pred`` and ``truth`` over the patches
    that cover ``mask`` (at least ``FEATURE_COVER`` of a patch), both cropped by :func:`feature_crop` and
    resized to ``FEATURE_SIDE`` squared. ``truth_features``: the truth's, when already computed
    (:func:`crop_features`). NaN for an empty mask."""
    mask = np.asarray(mask, bool)
    crop = feature_crop(mask.shape, mask)
    if crop is None:
        return float("nan")
    ft = truth_features if truth_features is not None else crop_features(truth, mask, features, crop)
    fp = crop_features(pred, mask, features, crop)
    y0, y1, x0, x1 = crop
    share = cv2.resize(mask[y0:y1, x0:x1].astype(np.float32), (ft.shape[1], ft.shape[0]),
                       interpolation=cv2.INTER_AREA)
    cover = share >= FEATURE_COVER
    if not cover.any():  # a mask smaller than a patch: the patch holding most of it
        cover = share >= share.max()
    num = (fp * ft).sum(-1)
    den = np.linalg.norm(fp, axis=-1) * np.linalg.norm(ft, axis=-1)
    cos = np.where(den > 0, num / np.maximum(den, 1e-12), 1.0)
    return float(np.clip(1.0 - cos[cover], 0.0, 2.0).mean())


def crop_features(image: np.ndarray, mask: np.ndarray, features: PatchFeatures,
                  crop: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """Patch features of the :func:`feature_crop` of ``image`` around ``mask`` (``crop``: that box, when
    the caller has it), resized to a square."""
    y0, y1, x0, x1 = crop or feature_crop(mask.shape, np.asarray(mask, bool)) or (0, mask.shape[0], 0, mask.shape[1])
    crop = np.ascontiguousarray(np.asarray(image, np.float32)[y0:y1, x0:x1])
    side = (FEATURE_SIDE, FEATURE_SIDE)
    interp = cv2.INTER_AREA if max(crop.shape[:2]) > FEATURE_SIDE else cv2.INTER_LINEAR
    return np.asarray(features(cv2.resize(crop, side, interpolation=interp)), np.float32)


@dataclass
class ImageScores:
    psnr_mask: float
    ssim_mask: float
    psnr_bbox: float
    ssim_bbox: float
    psnr_full: float
    ssim_full: float
    feat_mask: float = float("nan")  # feature_distance (NaN when no feature backbone is available)

    def to_dict(self) -> dict[str, float]:
        return asdict(self)


def score_image(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray, features: PatchFeatures | None = None,
                truth_features: np.ndarray | None = None) -> ImageScores:
    """PSNR and SSIM of one image in the three definitions; with ``features``, also ``feat_mask``."""
    mask = np.asarray(mask, bool)
    smap = ssim_map(pred, truth)
    box = mask_bbox(mask)
    if box is None:
        p_bbox = s_bbox = float("nan")
    else:
        y0, y1, x0, x1 = box
        p_bbox = psnr(pred[y0:y1, x0:x1], truth[y0:y1, x0:x1])
        s_bbox = ssim(pred[y0:y1, x0:x1], truth[y0:y1, x0:x1])
    return ImageScores(
        psnr_mask=psnr(pred, truth, mask),
        ssim_mask=float(smap[mask].mean()) if mask.any() else float("nan"),
        psnr_bbox=p_bbox,
        ssim_bbox=s_bbox,
        psnr_full=psnr(pred, truth),
        ssim_full=float(smap.mean()),
        feat_mask=(float("nan") if features is None
                   else feature_distance(pred, truth, mask, features, truth_features)),
    )


def mean_scores(scores: list[ImageScores]) -> dict[str, float]:
    """Mean over views of each metric (views where a metric is undefined, e.g. no mask, are skipped).
    PSNR is averaged per view in dB, as the papers do."""
    out = {}
    for key in ImageScores.__dataclass_fields__:
        values = [getattr(s, key) for s in scores]
        defined = [v for v in values if not np.isnan(v)]
        out[key] = float(np.mean(defined)) if defined else float("nan")
    return out
