"""Translation fills of regular textures (sgpor_pipeline.removal.lattice)."""

from __future__ import annotations

import numpy as np
import pytest

from sgpor_pipeline.errors import PipelineError
from sgpor_pipeline.removal.lattice import LatticeParams, dominant_offsets, lattice_fill


def discs(h: int = 120, w: int = 150, period: tuple[float, float] = (13.0, 17.0), angle: float = 0.0,
          noise: float = 0.02, seed: int = 0) -> np.ndarray:
    """A grid of violet discs on a grey floor (the synthetic scene's rug), rotated by ``angle``."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    c, s = np.cos(angle), np.sin(angle)
    u, v = (c * x + s * y) / period[1], (-s * x + c * y) / period[0]
    d = np.hypot(u - np.round(u), v - np.round(v))
    disc = (d < 0.3).astype(np.float64)
    img = np.stack([0.35 + 0.35 * disc, 0.3 + 0.1 * disc, 0.35 + 0.4 * disc], axis=2)
    img += np.random.default_rng(seed).normal(0.0, noise, img.shape)
    return np.clip(img, 0, 1).astype(np.float32)


def blob(h: int, w: int, cy: int, cx: int, r: int) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w]
    return (y - cy) ** 2 + (x - cx) ** 2 <= r * r


def disc_hole_bank():
    """A grid of discs with a round hole, and SBM's parameters and source bank for it."""
    from sgpor_pipeline.removal.sbm import SBMParams, build_source_bank

    truth = discs(96, 128, period=(14.0, 19.0), angle=0.3)
    hole = blob(96, 128, 48, 64, 15)
    img = truth.copy()
    img[hole] = 0.0
    p = SBMParams()
    return truth, hole, img, p, build_source_bank(["t"], [img], [hole], [hole], p)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10 * np.log10(max(float(((a - b) ** 2).mean()), 1e-12)))


@pytest.mark.parametrize("angle", [0.0, 0.4])
def test_a_grid_of_discs_is_filled_in_phase(angle):
    truth = discs(angle=angle)
    hole = blob(*truth.shape[:2], 60, 75, 16)  # wider than a period: filled pass after pass
    img = truth.copy()
    img[hole] = 0.0
    res = lattice_fill(img, hole, ~hole, LatticeParams())
    assert res is not None and res.filled.dtype == bool and res.filled.sum() == hole.sum()
    assert res.image.shape == truth.shape and res.image.dtype == np.float32
    assert res.offsets[0].rim_score > 0.8 and res.offsets[0].correlation > 0.8
    np.testing.assert_array_equal(res.image[~hole], img[~hole])  # the known pixels stay
    # the pattern's phase: only the noise (31 dB) and, rotated, the rounding of the period to pixels differ
    assert psnr(res.image[hole], truth[hole]) > 25.0
    # every offset used is a lattice vector: the pattern shifted by it is the pattern
    for o in res.offsets:
        shifted = np.roll(discs(angle=angle, noise=0.0), (-o.dy, -o.dx), axis=(0, 1))
        inner = (slice(20, -20), slice(20, -20))
        assert psnr(shifted[inner], discs(angle=angle, noise=0.0)[inner]) > 12.0, o
    assert res.info["offsets_used"] and res.info["left"] == 0 and res.info["passes"] >= 1
    assert min(np.hypot(o.dy, o.dx) for o in res.offsets) < 20  # the basis, not only its multiples


def test_each_part_follows_the_pattern_around_it():
    """A rug of discs on a larger floor of noise: the part of the hole on the rug is translated by the
    rug's period (found around it: over the whole image the floor's noise drowns it), the part on the
    floor is left to the caller."""
    rng = np.random.default_rng(3)
    h, w = 220, 240
    img = rng.uniform(0.2, 0.8, (h, w, 3)).astype(np.float32)
    truth = img.copy()
    truth[70:150, 80:170] = discs(80, 90, period=(12.0, 15.0))
    on_rug = blob(h, w, 110, 125, 9)
    on_floor = blob(h, w, 30, 40, 8)
    img = truth.copy()
    img[on_rug | on_floor] = 0.0
    res = lattice_fill(img, on_rug | on_floor, ~(on_rug | on_floor), LatticeParams())
    assert res is not None
    assert res.filled[on_rug].all() and not res.filled[on_floor].any()
    assert psnr(res.image[on_rug], truth[on_rug]) > 25.0
    assert sorted(p["texels"] for p in res.info["parts"]) == sorted([int(on_floor.sum()), int(on_rug.sum())])
    far = dominant_offsets(img, ~(on_rug | on_floor), LatticeParams())
    assert not far or far[0].correlation < 0.4  # the whole image: no period stands out


def test_dominant_offsets_of_stripes_are_their_period():
    y, x = np.mgrid[0:80, 0:90]
    stripes = np.repeat(((x % 10) < 5)[..., None], 3, axis=2).astype(np.float32)
    offs = dominant_offsets(stripes, np.ones((80, 90), bool), LatticeParams())
    assert offs and all(o.dx % 10 == 0 and o.correlation > 0.9 for o in offs[:2])
    assert min(abs(o.dx) for o in offs) == 10


@pytest.mark.parametrize("kind", ["noise", "smooth", "two_regions"])
def test_a_texture_without_a_period_gets_no_translation(kind):
    """Grass-like noise, a smooth field (high correlation at short offsets, but only as the flank of the
    zero offset's peak) and two regions (mip360 kitchen's table and mat) are left to the caller."""
    rng = np.random.default_rng(1)
    h, w = 100, 120
    if kind == "noise":
        img = rng.uniform(0, 1, (h, w, 3))
    elif kind == "smooth":
        import cv2

        img = cv2.GaussianBlur(rng.uniform(0, 1, (h, w, 3)), (0, 0), 6)
        img = (img - img.min()) / (img.max() - img.min())
    else:
        y, x = np.mgrid[0:h, 0:w]
        img = np.where((x + 0.3 * y < 70)[..., None], [0.6, 0.4, 0.3], [0.5, 0.6, 0.6]) + rng.normal(0, 0.03, (h, w, 3))
    img = img.astype(np.float32)
    hole = blob(h, w, 50, 60, 14)
    res = lattice_fill(img, hole, ~hole, LatticeParams())
    assert res is not None and not res.filled.any() and not res.offsets
    np.testing.assert_array_equal(res.image, img)
    assert len(res.info["parts"]) == 1 and res.info["parts"][0]["offsets_used"] == []


def test_nothing_to_do_and_too_little_to_learn_from():
    img = discs(60, 60)
    assert lattice_fill(img, np.zeros((60, 60), bool), np.ones((60, 60), bool), LatticeParams()) is None
    hole = blob(60, 60, 30, 30, 8)
    assert not lattice_fill(img, hole, np.zeros((60, 60), bool), LatticeParams()).filled.any()  # nothing known
    assert dominant_offsets(img, np.zeros((60, 60), bool), LatticeParams()) == []


def test_shift_moves_by_the_offset_and_pads():
    from sgpor_pipeline.removal.lattice import _shift

    a = np.arange(12.0).reshape(3, 4)
    np.testing.assert_array_equal(_shift(a, 1, 2), [[6, 7, 0, 0], [10, 11, 0, 0], [0, 0, 0, 0]])
    np.testing.assert_array_equal(_shift(a, -1, -1, fill=-1), [[-1, -1, -1, -1], [-1, 0, 1, 2], [-1, 4, 5, 6]])
    assert (_shift(a, 3, 0) == 0).all() and (_shift(a, 0, -9) == 0).all()


def test_lattice_params_are_checked():
    for bad in (dict(min_score=1.5), dict(max_offsets=0), dict(min_shift=0), dict(rim=0), dict(min_overlap=0.0),
                dict(min_correlation=2.0)):
        with pytest.raises(PipelineError):
            LatticeParams(**bad).validate()


def test_sbm_guided_by_the_translation_keeps_the_pattern():
    """The plane texture's use: SBM with the translation as the hole's initial content (inpaint_view's
    ``guide``) lands closer to the truth than SBM alone on a grid of discs."""
    from sgpor_pipeline.removal.sbm import inpaint_view

    truth, hole, img, p, bank = disc_hole_bank()
    lat = lattice_fill(img, hole, ~hole, LatticeParams())
    assert lat is not None and lat.filled[hole].all()
    alone = inpaint_view(img, hole, bank, p).image
    guided = inpaint_view(img, hole, bank, p, guide=lat.image).image
    assert guided.shape == truth.shape and guided.dtype == np.float32
    assert psnr(guided[hole], truth[hole]) > psnr(alone[hole], truth[hole]) + 1.0


def test_inpaint_stage_keeps_the_coins_grid_under_the_box(tmp_path):
    """inpaint.plane_lattice on a box standing on a rug of coins in a grid (SceneParams.rug_texture):
    the plane texture finds the grid's period and its fill keeps the coins in phase, so the views' fills
    come closer to the truth in the masks; off, no period is looked for."""
    from conftest import inpaint_plane_on_off

    from sgpor_pipeline.dag import StageContext
    from sgpor_pipeline.stages.inpaint import InpaintParams, InpaintStage
    from sgpor_pipeline.synthetic import SceneParams, generate_scene

    sc = generate_scene(SceneParams(seed=0, object_kind="box", rug_texture="coins", n_views=8, width=256,
                                    height=192))
    # (the translation alone: the smooth start of the rest of the hole is another option's work)
    score, plane, _ = inpaint_plane_on_off(tmp_path, sc, "plane_lattice", plane_smooth_guide=0.0)
    assert "lattice" not in plane[False]
    lat = plane[True]["lattice"]
    assert lat["used"] and lat["left"] < 0.05 * plane[True]["hole_texels"], lat  # (a sliver beside the rug: SBM's)
    assert score[True] > score[False] + 0.5, score
    with pytest.raises(PipelineError, match="min_correlation"):
        InpaintStage().run(StageContext.standalone(tmp_path / "bad", "inpaint",
                                                   InpaintParams(plane_lattice_correlation=3.0),
                                                   {"remove": tmp_path / "remove"}))


def test_the_guide_counts_only_where_its_mask_says():
    """A guide for part of the hole (the parts a translation filled): the rest starts empty, as
    without a guide, so garbage there does not steer the blocks."""
    from sgpor_pipeline.removal.sbm import inpaint_view

    truth, hole, img, p, bank = disc_hole_bank()
    alone = inpaint_view(img, hole, bank, p).image
    garbage = np.ones_like(img)  # white: nothing like the pattern
    masked_out = inpaint_view(img, hole, bank, p, guide=garbage, guide_mask=np.zeros_like(hole)).image
    np.testing.assert_array_equal(masked_out, alone)
    steered = inpaint_view(img, hole, bank, p, guide=garbage).image
    assert not np.array_equal(steered, alone)
