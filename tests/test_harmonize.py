"""removal.harmonize: a mask region made seamless with the photo around it."""

import numpy as np
import pytest

from sgpor_pipeline.removal.harmonize import rim_harmonized


def _scene(seed: int = 0, h: int = 48, w: int = 64):
    rng = np.random.default_rng(seed)
    image = (0.3 + 0.4 * rng.random((h, w, 3))).astype(np.float32)  # textured, away from 0 and 1
    region = np.zeros((h, w), bool)
    region[14:34, 20:44] = True
    return image, region


def test_a_constant_offset_on_the_ring_moves_the_whole_region():
    image, region = _scene()
    offset = np.array([0.08, -0.05, 0.03], np.float32)
    photo = image + offset  # the photo is the image with another exposure
    out = rim_harmonized(image, photo, region, ring=3, sigma=2.0)
    # a constant boundary value has a constant harmonic extension: the region takes the offset
    np.testing.assert_allclose(out[region], (image + offset)[region], atol=1e-4)
    far = np.ones(region.shape, bool)
    far[8:40, 14:50] = False  # beyond the ring
    np.testing.assert_array_equal(out[far], image[far])
    # the ring itself (its sides: the ring is an ellipse's dilation): the image's detail with the
    # photo's slow colour
    sides = np.zeros_like(region)
    sides[14:34, 17:20] = sides[14:34, 44:47] = sides[11:14, 20:44] = sides[34:37, 20:44] = True
    np.testing.assert_allclose(out[sides], photo[sides], atol=1e-4)


def test_the_rings_texture_does_not_leak_into_the_region():
    image, region = _scene()
    rng = np.random.default_rng(1)
    photo = image + rng.choice([-0.1, 0.1], size=image.shape).astype(np.float32)  # fine texture, mean 0
    out = rim_harmonized(image, photo, region, ring=3, sigma=2.0)
    change = np.abs(out - image)[region]
    assert change.mean() < 0.02  # a tenth of the texture's amplitude: smoothed away along the ring
    # without smoothing (sigma tiny) the texture's noise enters the boundary values
    raw = np.abs(rim_harmonized(image, photo, region, ring=3, sigma=0.01) - image)[region]
    assert raw.mean() > change.mean()


def test_a_slow_gradient_is_followed():
    image, region = _scene()
    h, w = region.shape
    ys, xs = np.mgrid[0:h, 0:w]
    ramp = (0.002 * xs - 0.001 * ys).astype(np.float32)[..., None]  # linear: harmonic
    out = rim_harmonized(image, image + ramp, region, ring=3, sigma=2.0)
    err = np.abs(out - (image + ramp))[region]
    assert err.max() < 0.004  # (the smoothing bends a linear field only at the ring's corners)


def test_excluded_pixels_and_degenerate_regions():
    image, region = _scene()
    photo = image.copy()
    ring = np.zeros_like(region)
    ring[11:37, 17:47] = True
    ring &= ~region
    photo[ring] += 0.3  # e.g. a lifted shadow: the target there is not the photo
    out = rim_harmonized(image, photo, region, exclude=ring)
    np.testing.assert_array_equal(out, image)
    np.testing.assert_array_equal(rim_harmonized(image, photo, np.zeros_like(region)), image)
    # a region with no ring around it (the whole image) keeps its colours
    np.testing.assert_allclose(rim_harmonized(image, photo, np.ones_like(region)), image, atol=1e-5)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_dtype_and_range(dtype):
    image, region = _scene()
    out = rim_harmonized(image.astype(dtype), np.clip(image + 0.9, 0, 1).astype(dtype), region)
    assert out.dtype == dtype and out.shape == image.shape
    assert out.min() >= 0.0 and out.max() <= 1.0
