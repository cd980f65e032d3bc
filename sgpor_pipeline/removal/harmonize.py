"""Seamless with the photo: a view's mask region corrected by the photo's colours around it.

Inside an object's mask a view shows what the pipeline made (the render after deletion where other
views saw the background, the inpainted fill in the holes); around it, the photo. Where they differ
at the mask's rim, the difference is mostly low-frequency: the fit's colours of a region this view
never saw are those the other views taught it (another exposure, white balance or viewing angle),
its geometry is a little off, and a fill blended into the render inherits the render's offset. The
correction is the harmonic field (Laplace in the region) that equals, on the ring around the
region, the difference photo - image smoothed along the ring: texture and noise on the ring do not
enter it, its slow changes do (Poisson image editing with the image's own gradients as guide).
"""

from __future__ import annotations

import cv2
import numpy as np

from .sbm import poisson_blend


def rim_harmonized(image: np.ndarray, photo: np.ndarray, region: np.ndarray, ring: int = 3,
                   sigma: float = 2.0, exclude: np.ndarray | None = None) -> np.ndarray:
    """``image`` (float HxWx3 in [0, 1]) with its ``region`` pixels corrected towards ``photo`` at the
    region's rim.

    The difference ``photo - image`` is taken on the ``ring`` px around ``region`` (without the
    ``exclude`` pixels: e.g. pixels whose target is not the photo), smoothed there by a normalised
    Gaussian of ``sigma`` px, and spread over the region harmonically. The ring's pixels get the image
    plus that smoothed difference (the photo's slow colours with the image's detail), the rest of the
    image is returned unchanged. A region part with no ring pixel keeps its colours."""
    out = np.array(image, np.float64)
    region = np.asarray(region, bool)
    if not region.any():
        return out.astype(np.asarray(image).dtype)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * ring + 1, 2 * ring + 1))
    band = (cv2.dilate(region.astype(np.uint8), k) > 0) & ~region
    if exclude is not None:
        band &= ~np.asarray(exclude, bool)
    if not band.any():
        return out.astype(np.asarray(image).dtype)
    w = band.astype(np.float64)
    diff = (np.asarray(photo, np.float64) - out) * w[..., None]
    smooth = cv2.GaussianBlur(diff, (0, 0), sigma) / np.maximum(cv2.GaussianBlur(w, (0, 0), sigma), 1e-9)[..., None]
    # f = image + c: lap(f) = lap(image) in the region, f = image + smoothed difference on the ring's
    # pixels that touch it; pixels beside the region that are not on the ring (excluded) are Neumann
    target = np.where(band[..., None], out + smooth, out)
    # (anchor: a region part that touches no ring pixel keeps the image's colours)
    fixed = poisson_blend(target, out, region, boundary=band, anchor=1e-6)
    out[region] = fixed[region]
    out[band] = np.clip(target[band], 0.0, 1.0)
    return out.astype(np.asarray(image).dtype)
