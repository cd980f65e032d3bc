"""Image quality metrics in the three definitions peers use (DESIGN.md section 8).

- ``mask``: PSNR over the mask's pixels only; SSIM = mean of the SSIM map over the mask's pixels.
- ``bbox``: both images cropped to the mask's bounding box (the SPIn-NeRF lineage), then plain
  PSNR / SSIM of the crops.
- ``full``: the whole image.

Images are float RGB in [0, 1], HxWx3 (numpy). SSIM is kornia's (11x11 Gaussian window, sigma 1.5,
the standard constants), computed on the full image once so that ``mask`` and ``full`` share it.
LPIPS needs backbone weights that are not installable here: it is not reported, never faked.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

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


@dataclass
class ImageScores:
    psnr_mask: float
    ssim_mask: float
    psnr_bbox: float
    ssim_bbox: float
    psnr_full: float
    ssim_full: float

    def to_dict(self) -> dict[str, float]:
        return asdict(self)


def score_image(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> ImageScores:
    """PSNR and SSIM of one image in the three definitions."""
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
