"""Object selection, mask propagation and hole finding on Gaussians built from a synthetic scene's
true geometry (dense surface samples), so the tests need no slow fit and know the right answers."""

from __future__ import annotations

import cv2
import numpy as np
import open3d as o3d
import pytest
import torch

from sgpor_pipeline.gaussians.model import GaussianModel, rgb_to_sh
from sgpor_pipeline.imageio import to_float32
from sgpor_pipeline.removal.holes import (
    RemoveParams,
    clamp_dc_colours,
    complete_depth,
    concat_models,
    context_image,
    far_side_floor,
    footprint_scales,
    hole_mask,
    initial_colour,
    objects_to_delete,
    observing_views,
    render_background,
    seed_hole_gaussians,
    subset,
    unpremultiplied,
)
from sgpor_pipeline.removal.selection import (
    SelectionParams,
    TightParams,
    contribution_scores,
    iou,
    median_spacing,
    refine_mask,
    render_median_depth,
    render_object_probability,
    select_object,
    tighten_mask,
    within_margin,
)
from sgpor_pipeline.synthetic import SceneParams, generate_scene


def surface_gaussians(mesh: o3d.geometry.TriangleMesh, n: int, seed: int) -> tuple[np.ndarray, float]:
    o3d.utility.random.seed(seed)
    pcd = mesh.sample_points_uniformly(number_of_points=n)
    xyz = np.asarray(pcd.points)
    spacing = float(np.sqrt(mesh.get_surface_area() / n))
    return xyz, spacing


@pytest.fixture(scope="module")
def scene_and_model():
    scene = generate_scene(SceneParams(seed=3, n_views=12, width=96, height=72))
    bg, s_bg = surface_gaussians(scene.background_mesh, 120_000, 0)
    ob, s_ob = surface_gaussians(scene.object_mesh, 6_000, 1)
    xyz = np.concatenate([bg, ob])
    scale = np.concatenate([np.full(len(bg), 0.8 * s_bg), np.full(len(ob), 0.8 * s_ob)])
    model = GaussianModel.empty(len(xyz), 0)
    with torch.no_grad():
        model.params["means"].copy_(torch.from_numpy(xyz).float())
        model.params["scales"].copy_(torch.from_numpy(np.log(scale)).float()[:, None].expand(-1, 3))
        model.params["opacities"].fill_(3.0)
        model.params["sh0"].copy_(rgb_to_sh(torch.full((len(xyz), 3), 0.5))[:, None, :])
    is_object = np.zeros(len(xyz), bool)
    is_object[len(bg):] = True
    return scene, model, is_object


def test_selection_from_one_mask_propagates_to_every_view(scene_and_model):
    scene, model, truth = scene_and_model
    params = SelectionParams()
    sel = select_object(model, [scene.cameras[0]], [scene.masks[0]], params)
    # The fixture samples surfaces no view sees (the floor under the object); a fitted scene has no
    # Gaussians there, so only background that some view sees counts against precision.
    _, seen_weight = contribution_scores(model, scene.cameras, list(scene.masks))
    visible_bg = ~truth & (seen_weight >= params.min_weight)
    precision = (sel.is_object & truth).sum() / (sel.is_object & (truth | visible_bg)).sum()
    recall = (sel.is_object & truth).sum() / truth.sum()
    # One view sees about half of the object's surface; growing inside the visual cone must reach
    # most of the rest (its back) without taking visible background.
    assert precision > 0.95, precision
    assert recall > 0.75, (recall, sel.seeds, sel.grown)
    ious = []
    for cam, image, mask in zip(scene.cameras, scene.images, scene.masks):
        prob = render_object_probability(model, sel.is_object, cam)
        ious.append(iou(refine_mask(prob, image, params), mask))
    # The masks are rendered from surface samples at 96x72: edges are a pixel off at most, so for
    # objects of a few hundred pixels an IoU of 0.8 is what "the same mask" means here.
    assert min(ious) > 0.75 and np.mean(ious) > 0.8, ious


def test_hidden_parts_of_the_object_are_selected_where_growing_cannot_reach_them(scene_and_model):
    """``hidden``: the Gaussians inside the given mask and in front of the background carried under it
    are seeds. With the object's middle cut out (a gap wider than growing's links, as where a fit
    covers the object's far side sparsely), growing from what the view sees stops at the gap; with
    ``hidden`` the far side is selected too, and still no background."""
    scene, model, truth = scene_and_model
    cam, mask = scene.cameras[0], scene.masks[0]
    means = model.means.detach().numpy().astype(np.float64)
    centre = means[truth].mean(axis=0)
    axis = (centre - cam.center) / np.linalg.norm(centre - cam.center)
    depth_along = (means - centre) @ axis  # > 0: the object's far side, as the view looks
    keep = ~(truth & (np.abs(depth_along) < 0.1))
    cut, truth = subset(model, keep), truth[keep]
    far = truth & (depth_along[keep] > 0)
    params = SelectionParams()
    tight, _, behind = tighten_mask(cut, cam, mask, TightParams())
    # (seen by the whole object's views: through the cut, the floor sampled under the object shows)
    _, seen_weight = contribution_scores(model, scene.cameras, list(scene.masks))
    visible_bg = ~truth & (seen_weight[keep] >= params.min_weight)
    found = {}
    for hidden in (False, True):
        sel = select_object(cut, [cam], [tight], params, cone_masks=[mask], background_depths=[behind],
                            hidden=hidden).is_object
        found[hidden] = (sel & far).sum() / far.sum()
        assert (sel & truth).sum() / (sel & (truth | visible_bg)).sum() > 0.95
    assert found[False] < 0.3 and found[True] > 0.8, found


def test_a_generous_mask_is_tightened_and_does_not_select_the_floor(scene_and_model):
    """A given mask drawn with a margin of floor around the object: its pixels in front of the floor
    carried in from around it are (nearly) the true mask, the margin width is measured, and the
    selection from it takes (almost) no background."""
    import cv2

    scene, model, truth = scene_and_model
    cam, true_mask = scene.cameras[0], scene.masks[0]
    given = cv2.dilate(true_mask.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0  # a 4 px margin
    tight, width, behind = tighten_mask(model, cam, given, TightParams())
    assert behind is not None and behind.shape == given.shape and (behind[~given] == 0).all()
    assert (tight <= given).all()
    # pixel level (96x72, the object's rendered edge is a pixel wide): the margin goes, the object stays
    precision_px = (tight & true_mask).sum() / tight.sum()
    assert precision_px > 0.75 and (given & true_mask).sum() / given.sum() < 0.7, precision_px
    assert (tight & true_mask).sum() > 0.85 * true_mask.sum()
    assert 2.0 < width < 6.0, width
    params = SelectionParams()
    _, seen_weight = contribution_scores(model, scene.cameras, list(scene.masks))
    visible_bg = ~truth & (seen_weight >= params.min_weight)

    def precision(sel):
        return (sel.is_object & truth).sum() / (sel.is_object & (truth | visible_bg)).sum()

    sel = select_object(model, [cam], [tight], params, cone_masks=[given], background_depths=[behind])
    recall = (sel.is_object & truth).sum() / truth.sum()
    assert precision(sel) > 0.93 and recall > 0.85, (precision(sel), recall)
    # (the margin as given selects the floor around the object: 0.77 here; tightening prevents it)
    assert precision(select_object(model, [cam], [given], params)) < 0.85
    # nothing to carry (no ring pixel with depth) or tightening off: the mask as given
    off, w0, d0 = tighten_mask(model, cam, given, TightParams(enabled=False))
    assert (off == given).all() and w0 == 0.0 and d0 is None


def test_remove_finds_only_unseen_background_as_hole(scene_and_model):
    scene, model, truth = scene_and_model
    params = RemoveParams()
    delete, stats, surface, _ = objects_to_delete(model, scene.cameras, list(scene.masks), np.flatnonzero(truth),
                                                  params)
    assert delete[truth].all() and surface[truth].all() and not (surface & ~delete).any()
    assert surface.sum() == stats["from_masks_stage"] + stats["by_score"]
    assert (delete & ~truth).sum() < 0.02 * (~truth).sum()
    background = subset(model, ~delete)
    hole_frac = []
    for cam, mask, depth_gt in zip(scene.cameras, scene.masks, scene.depth_gt):
        rgb, alpha, depth = render_background(background, cam)
        hole = hole_mask(mask, alpha, params)
        rim = hole & ~mask  # (darkened pixels just outside the mask, next to the hole)
        near = cv2.dilate((hole & mask).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        assert (rim <= near).all() and (alpha[rim] < params.rim_alpha).all()
        hole = hole & mask
        hole_frac.append(hole.sum() / max(mask.sum(), 1))
        # Where the background is seen, the rendered depth agrees with the true background depth.
        seen = mask & ~hole & (alpha > 0.9)
        if seen.sum() > 20:
            # (the fixture's Gaussians are ~3 cm blobs on a 4 cm grid: a few percent of depth error)
            assert np.median(np.abs(depth[seen] - depth_gt[seen]) / depth_gt[seen]) < 0.1
    # Most of the mask is background that other views saw; the hole is the part under/behind the
    # object that no view sees, a minority of the mask.
    assert np.mean(hole_frac) < 0.6, hole_frac


def test_background_depth_is_the_median_or_the_expected_one(scene_and_model):
    """remove.depth="median" renders the median depth (rasterizer mode "MD") and keeps the expected
    depth where a pixel never gets half opaque; an unknown kind is refused."""
    from sgpor_pipeline.errors import PipelineError

    scene, model, truth = scene_and_model
    obj = subset(model, truth)  # the object alone: its silhouette's edge is thin
    cam = scene.cameras[0]
    rgb, alpha, expected = render_background(obj, cam)
    rgb2, alpha2, median = render_background(obj, cam, depth="median")
    assert np.array_equal(rgb, rgb2) and np.array_equal(alpha, alpha2)
    thin = (alpha < 0.49) & (alpha > 0.01)
    assert thin.any() and np.array_equal(median[thin], expected[thin])
    opaque = alpha > 0.51
    assert np.isfinite(median).all() and (median[opaque] > 0).all()
    assert (median[opaque] != expected[opaque]).mean() > 0.5  # a Gaussian's depth, not the blend
    with pytest.raises(PipelineError, match="remove.depth"):
        render_background(obj, cam, depth="mean")


def test_a_large_gaussian_centred_in_the_hull_is_deleted_despite_its_tails(scene_and_model):
    """A big Gaussian whose centre every view shows inside the mask, but whose tails peek out of the
    object's silhouette (so most of its seen weight is outside the masks: a background-like score),
    would smear across the hole once the object is gone: it is deleted (``hull_centre_views``)."""
    scene, model, truth = scene_and_model
    obj = model.means.detach().double().numpy()[truth]
    centre = obj.mean(0)
    radius = float(np.linalg.norm(obj - centre, axis=1).max())
    big = GaussianModel.empty(1, 0)
    with torch.no_grad():
        big.params["means"].copy_(torch.from_numpy(centre).float()[None])
        big.params["scales"].fill_(float(np.log(1.5 * radius)))
        big.params["opacities"].fill_(0.0)
        big.params["sh0"].copy_(rgb_to_sh(torch.tensor([[0.1, 0.1, 0.1]]))[:, None, :])
    both = concat_models(model, big)
    masks = list(scene.masks)
    inside, total = contribution_scores(both, scene.cameras, masks)
    assert total[-1] >= RemoveParams().min_weight and inside[-1] / total[-1] < 0.5  # looks like background
    ids = np.flatnonzero(truth)
    kept, _, _, _ = objects_to_delete(both, scene.cameras, masks, ids, RemoveParams(hull_centre_views=0))
    assert not kept[-1]  # the score alone spares it
    delete, stats, _, _ = objects_to_delete(both, scene.cameras, masks, ids, RemoveParams())
    assert delete[-1] and stats["hull_centres"] >= 1
    # (the background's own Gaussians centred in every mask are the floor under the object, unseen)
    assert (delete[:-1] & ~truth).sum() < 0.02 * (~truth).sum()


def test_margin_gaussians_go_with_the_nearer_side():
    """closer_to_core: a floor of points from x = -1 to 3 under an object (a cluster at x < 0, above
    it); the margin (0 <= x < 2 on the floor) splits where the floor's chain meets the object's side
    or the rest of the floor: the part nearer the object goes with it, the rest stays."""
    from sgpor_pipeline.removal.holes import closer_to_core

    xs = np.arange(-1.0, 3.0, 0.05)
    floor = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], axis=1)
    g = np.random.default_rng(0)
    obj = np.stack([g.uniform(-1, -0.02, 200), g.uniform(-0.2, 0.2, 200), g.uniform(0.05, 1, 200)], axis=1)
    means = np.concatenate([floor, obj])
    core = np.r_[floor[:, 0] < 0, np.ones(len(obj), bool)]
    margin = np.r_[(floor[:, 0] >= 0) & (floor[:, 0] < 2), np.zeros(len(obj), bool)]
    to_core = closer_to_core(means, core, margin)
    assert not (to_core & ~margin).any()
    x = floor[:, 0]
    assert to_core[:len(floor)][(x >= 0) & (x < 0.9)].all() and not to_core[:len(floor)][(x > 1.1) & (x < 2)].any()
    assert closer_to_core(means, core, np.zeros(len(means), bool)).sum() == 0
    assert closer_to_core(means, np.zeros(len(means), bool), np.ones(len(means), bool)).all()  # nothing outside


def test_over_bright_colours_seen_through_the_masks_are_clamped(scene_and_model):
    """The DC colours above 1 of Gaussians that show through the object masks are clamped to [0, 1];
    the rest of the scene keeps its colours, and the stage's DC renders do not change."""
    scene, model, truth = scene_and_model
    masks = list(scene.masks)
    delete, _, _, share = objects_to_delete(model, scene.cameras, masks, np.flatnonzero(truth), RemoveParams())
    assert share.shape == (len(model),) and np.isfinite(share).all() and ((share >= 0) & (share <= 1)).all()
    background = subset(model, ~delete)
    share_bg = share[~delete]
    behind, elsewhere = share_bg >= 0.5, share_bg == 0
    assert behind.sum() > 20 and elsewhere.sum() > 20
    with torch.no_grad():
        background.params["sh0"][:, 0, :] = rgb_to_sh(torch.tensor([1.4, 0.5, -0.2]))
    before = background.params["sh0"].clone()
    dc_before = render_background(background, scene.cameras[0])[0]
    changed = clamp_dc_colours(background, share_bg >= RemoveParams().clamp_share)
    assert changed == int((share_bg >= RemoveParams().clamp_share).sum())
    rgb = background.params["sh0"][:, 0, :] * 0.28209479177387814 + 0.5
    assert torch.allclose(rgb[torch.from_numpy(behind)], torch.tensor([1.0, 0.5, 0.0]), atol=1e-6)
    assert torch.equal(background.params["sh0"][torch.from_numpy(elsewhere)], before[torch.from_numpy(elsewhere)])
    np.testing.assert_allclose(render_background(background, scene.cameras[0])[0], dc_before, atol=1e-6)


def test_hole_modes():
    """"unseen" keeps only the uncovered mask pixels; "mask" (the per-view 2D baseline) the whole mask;
    an unknown mode is a clear error."""
    mask = np.zeros((20, 30), bool)
    mask[5:15, 5:25] = True
    alpha = np.ones((20, 30), np.float32)
    alpha[8:12, 10:20] = 0.1  # uncovered after deletion
    unseen = hole_mask(mask, alpha, RemoveParams(hole_close=0))
    assert unseen.sum() == 40 and (unseen <= mask).all()
    assert (hole_mask(mask, alpha, RemoveParams(hole_mode="mask")) == mask).all()
    dark = alpha.copy()
    dark[4, :] = 0.2  # a darkened row just above the mask: the whole mask's rim (see the test below)
    rim = hole_mask(mask, dark, RemoveParams(hole_mode="mask")) & ~mask
    assert rim[4, 3:27].all() and rim.sum() == 24
    from sgpor_pipeline.errors import PipelineError

    with pytest.raises(PipelineError, match="hole_mode"):
        hole_mask(mask, alpha, RemoveParams(hole_mode="everything"))


def test_thin_mask_parts_are_holes_as_a_whole():
    """With thin_mask_rim, a part of the object mask no pixel of which lies farther than that from its
    rim becomes a hole entirely (covered background or not); a thicker part keeps only its uncovered
    pixels; 0 leaves the opacity rule alone."""
    mask = np.zeros((80, 120), bool)
    mask[10:20, 10:30] = True  # thin: at most 5 px from its rim
    mask[30:75, 50:110] = True  # thick: 22 px deep
    alpha = np.ones(mask.shape, np.float32)
    alpha[45:55, 70:80] = 0.1  # the only uncovered pixels
    off = hole_mask(mask, alpha, RemoveParams(hole_close=0, thin_mask_rim=0))
    assert off.sum() == 100
    on = hole_mask(mask, alpha, RemoveParams(hole_close=0, thin_mask_rim=8))
    assert on[10:20, 10:30].all() and on.sum() == 200 + 100
    deep = hole_mask(mask, alpha, RemoveParams(hole_close=0, thin_mask_rim=30))
    assert (deep == mask).all()
    assert (hole_mask(mask, alpha, RemoveParams(hole_close=0, thin_mask_rim=8, rim_alpha=0)) <= mask).all()


def test_hole_rim_outside_the_mask():
    """Darkened pixels just outside the mask join the hole where they border it (rim_alpha), within
    context_margin px; far from the hole, or well covered, or with rim_alpha 0, they do not."""
    mask = np.zeros((30, 40), bool)
    mask[10:20, 10:30] = True
    alpha = np.ones(mask.shape, np.float32)
    alpha[10:20, 10:18] = 0.1  # the hole: the mask's left part
    alpha[9, 5:35] = 0.5  # a darkened ring row above the mask...
    alpha[6, 5:35] = 0.5  # ...and one further out than context_margin
    alpha[20, 5:35] = 0.8  # below the mask: darker than hole_alpha but above rim_alpha
    params = RemoveParams(hole_close=0, context_margin=2)
    hole = hole_mask(mask, alpha, params)
    inside = hole & mask
    assert inside.sum() == 80 and (inside == (mask & (alpha < 0.9))).all()
    rim = hole & ~mask
    assert rim[9, 8:20].all()
    assert not rim[9, 20:].any() and not rim[9, :8].any()  # only within 2 px of the hole
    assert not rim[6].any() and not rim[20].any()
    assert rim.sum() == rim[9].sum()
    off = hole_mask(mask, alpha, RemoveParams(hole_close=0, context_margin=2, rim_alpha=0.0))
    assert (off == inside).all()


def test_disagreement_flags_a_misplaced_background_only(scene_and_model):
    """The render behind the object, checked against what the other views' photos show at its points:
    the true background (images_gt) agrees with them; the same background shifted by 12 px (the fit's
    geometry misplaced) does not. Without photos nothing is compared."""
    scene, _, _ = scene_and_model
    masks, depths = list(scene.masks), list(scene.depth_gt)
    params = RemoveParams(min_views=1, view_mask_dilate=1)
    photos = list(scene.images)
    _, right = observing_views(scene.cameras, masks, depths, masks, params, list(scene.images_gt), photos)
    shifted = [np.roll(im, 12, axis=1) for im in scene.images_gt]
    _, wrong = observing_views(scene.cameras, masks, depths, masks, params, shifted, photos)
    r = np.concatenate([d[m] for d, m in zip(right, masks)])
    w = np.concatenate([d[m] for d, m in zip(wrong, masks)])
    assert np.isnan(np.concatenate([d[~m] for d, m in zip(right, masks)])).all()
    seen = ~np.isnan(r)
    assert seen.sum() > 100 and (np.isnan(w) == ~seen).all()  # the same points are compared
    assert np.median(r[seen]) < 0.03 and np.mean(r[seen] > 0.15) < 0.01, (np.median(r[seen]), np.mean(r[seen] > 0.15))
    # (right: mean 0.027, 0.04 % above 0.15; shifted: mean 0.077, 21 % above 0.15)
    assert np.mean(w[seen]) > 2 * np.mean(r[seen]) and np.mean(w[seen] > 0.15) > 0.1
    counts, none = observing_views(scene.cameras, masks, depths, masks, params)
    assert none is None and all((c[m] > 0).mean() > 0.3 for c, m in zip(counts, masks) if m.any())


def test_observing_views_finds_the_background_no_other_view_saw(scene_and_model):
    """With the true background depths: mask pixels whose background point is the floor under the
    object (inside its footprint) are observed by no other view, the rest of the mask by some."""
    scene, _, _ = scene_and_model
    lo, hi = scene.object_bounds
    masks, depths = list(scene.masks), list(scene.depth_gt)
    params = RemoveParams(min_views=1, view_mask_dilate=1)
    under, elsewhere = [], []
    counts, _ = observing_views(scene.cameras, masks, depths, masks, params)
    for i, cam in enumerate(scene.cameras):
        ys, xs = np.nonzero(masks[i])
        if len(ys) == 0:
            continue
        assert counts[i].shape == masks[i].shape and (counts[i][~masks[i]] == 0).all()
        count = counts[i][ys, xs]
        assert count.min() >= 0 and count.max() <= len(scene.cameras) - 1
        wfc = cam.world_from_cam
        z = depths[i][ys, xs]
        pc = np.stack([(xs + 0.5 - cam.K[0, 2]) / cam.K[0, 0] * z, (ys + 0.5 - cam.K[1, 2]) / cam.K[1, 1] * z, z], 1)
        X = pc @ wfc[:3, :3].T + wfc[:3, 3]
        shrink = 0.1 * (hi - lo)  # away from the footprint's edge (pixel-sized mask errors)
        inside = np.all((X[:, :2] > lo[:2] + shrink[:2]) & (X[:, :2] < hi[:2] - shrink[:2]), axis=1)
        under.append(count[inside])
        elsewhere.append(count[~inside])
    under, elsewhere = np.concatenate(under), np.concatenate(elsewhere)
    assert len(under) > 20 and len(elsewhere) > 100
    assert (under == 0).mean() > 0.9, (under == 0).mean()
    assert (elsewhere >= 1).mean() > 0.8, (elsewhere >= 1).mean()
    # the hole rule: unobserved mask pixels join the opacity holes, nothing outside the mask does
    mask = masks[0]
    unobserved = np.zeros_like(mask)
    unobserved[: mask.shape[0] // 2] = True
    hole = hole_mask(mask, np.ones(mask.shape, np.float32), RemoveParams(hole_close=0), unobserved)
    assert (hole == (mask & unobserved)).all()


def test_depth_completion_is_exact_for_planes():
    h, w = 40, 50
    ys, xs = np.mgrid[0:h, 0:w]
    inv = 0.2 + 0.003 * xs + 0.002 * ys  # a plane's inverse depth is affine in pixel coordinates
    depth = (1.0 / inv).astype(np.float32)
    hole = np.zeros((h, w), bool)
    hole[10:30, 15:40] = True
    broken = depth.copy()
    broken[hole] = 0.0
    filled = complete_depth(broken, ~hole, hole)
    assert np.abs(filled[hole] - depth[hole]).max() < 1e-4


def test_far_side_floor_takes_the_background_side_of_a_depth_step():
    """A mask across a depth step (a house front near on the left, a street's far end on the right):
    its hole is completed no nearer than the far side. Where both sides lie at about one depth (a
    floor under an object) there is no floor, and the harmonic completion stands."""
    h, w = 20, 40
    mask = np.zeros((h, w), bool)
    mask[5:15, 10:30] = True
    valid = np.ones((h, w), bool)
    step = np.full((h, w), 2.0, np.float32)
    step[:, 25:] = 6.0
    floor = far_side_floor(mask, step, valid, 1.5)
    assert (floor[mask] == 6.0).all() and (floor[~mask] == 0).all()
    filled = complete_depth(np.where(mask, 0.0, step).astype(np.float32), ~mask, mask, floor)
    assert filled[mask].min() >= 6.0 - 1e-5
    plain = complete_depth(np.where(mask, 0.0, step).astype(np.float32), ~mask, mask)
    assert plain[mask].min() < 3.0  # (without it: between the two)
    # the 2 px beside the mask mix the object in real renders: not read
    edged = step.copy()
    edged[:, 8:10] = 100.0
    edged[:, 30:32] = 100.0
    assert np.array_equal(far_side_floor(mask, edged, valid, 1.5), floor)
    # invalid pixels are skipped: the next valid one out is read
    holed = valid.copy()
    holed[:, 32:36] = False
    far = step.copy()
    far[:, 36:] = 9.0
    assert (far_side_floor(mask, far, holed, 1.5)[mask] == 9.0).all()
    # no step: a gently sloping floor, both sides within the ratio
    ys, xs = np.mgrid[0:h, 0:w]
    slope = (2.0 + 0.02 * xs).astype(np.float32)
    assert not far_side_floor(mask, slope, valid, 1.5).any()
    assert far_side_floor(mask, slope, valid, 1.0)[mask].min() > 2.0  # (every row's far side at ratio 1)
    # a mask at the image's border, or a row with no valid pixel on one side: one side shows no step
    edge_mask = np.zeros((h, w), bool)
    edge_mask[5:15, :12] = True
    assert not far_side_floor(edge_mask, step, valid, 1.5).any()
    one_side = valid.copy()
    one_side[7, :8] = False
    floor = far_side_floor(mask, step, one_side, 1.5)
    assert not floor[7].any() and (floor[8, 10:30] == 6.0).all()


def test_observing_views_and_joint_depths_keep_their_maps_on_disk_bit_for_bit(scene_and_model, tmp_path):
    """The remove stage keeps its per-view maps on disk (scratch.on_disk): the same results as in memory,
    with the inputs themselves read back memory-mapped."""
    import functools

    from sgpor_pipeline.removal.holes import complete_depths_jointly
    from sgpor_pipeline.scratch import on_disk

    scene, _, _ = scene_and_model
    keep = functools.partial(on_disk, tmp_path)
    masks, params = list(scene.masks), RemoveParams(min_views=1, view_mask_dilate=1)
    photos8 = [(im * 255 + 0.5).astype(np.uint8) for im in scene.images]
    args = (scene.cameras, masks, list(scene.depth_gt), masks, params, list(scene.images_gt), photos8)
    counts, dis = observing_views(*args)
    disk = observing_views(scene.cameras, masks, keep("depths", scene.depth_gt), masks, params,
                           keep("renders", scene.images_gt), keep("photos", photos8), keep)
    assert all(np.array_equal(a, b) for a, b in zip(counts, disk[0]))
    assert all(np.array_equal(a, b, equal_nan=True) for a, b in zip(dis, disk[1]))
    assert (tmp_path / "blurred_photos").is_dir() and isinstance(disk[1][0], np.memmap)
    holes = [m.copy() for m in masks]
    depths = [np.where(h, np.inf, d).astype(np.float32) for h, d in zip(holes, scene.depth_gt)]
    joint = complete_depths_jointly(scene.cameras, depths, [~h for h in holes], holes)
    joint_disk = complete_depths_jointly(scene.cameras, keep("raw", depths), [~h for h in holes], holes,
                                         keep=functools.partial(on_disk, tmp_path / "joint"))
    assert all(np.array_equal(a, b) for a, b in zip(joint, joint_disk))


def test_joint_depth_completion_gives_the_views_one_hole_surface():
    """Large holes (object masks grown to span the floor and what stands behind it): completed view by
    view, the hole surfaces disagree between views; completed jointly (smallest hole first), every
    later view takes the surface the earlier ones completed where it sees it."""
    import cv2

    from sgpor_pipeline.removal.holes import complete_depths_jointly

    scene = generate_scene(SceneParams(seed=3, n_views=8, width=96, height=72))
    k = np.ones((21, 21), np.uint8)
    holes = [cv2.dilate(m.astype(np.uint8), k) > 0 for m in scene.masks]
    depths = [d.copy() for d in scene.depth_gt]
    valids = [~h for h in holes]
    alone = [complete_depth(d, v, h) for d, v, h in zip(depths, valids, holes)]
    joint = complete_depths_jointly(scene.cameras, depths, valids, holes)
    for d, j, h in zip(depths, joint, holes):
        assert np.isfinite(j).all() and (j[h] > 0).all()
        assert np.array_equal(j[~h], d[~h])  # only holes change
    smallest = int(np.argmin([h.sum() for h in holes]))
    assert np.array_equal(joint[smallest], alone[smallest])  # the smallest hole is completed on its own
    first = int(np.argmax([h.sum() for h in holes]))

    def disagreement(completed):
        """Median relative depth difference of the other views' hole points against the first view's
        hole surface, where they land in its hole."""
        ref, diffs = scene.cameras[first], []
        for i, cam in enumerate(scene.cameras):
            if i == first:
                continue
            ys, xs = np.nonzero(holes[i])
            px, z, inside = ref.pixels(cam.unproject(ys, xs, completed[i][ys, xs]))
            px, z = px[inside], z[inside]
            hit = holes[first][px[:, 1], px[:, 0]]
            zr = completed[first][px[hit, 1], px[hit, 0]]
            diffs.append(np.abs(z[hit] - zr) / zr)
        return float(np.median(np.concatenate(diffs)))

    assert disagreement(alone) > 0.03, disagreement(alone)
    assert disagreement(joint) < 0.5 * disagreement(alone), (disagreement(joint), disagreement(alone))


def test_seeded_gaussians_lie_on_the_completed_surface(scene_and_model):
    scene, _, _ = scene_and_model
    cam, mask, depth = scene.cameras[0], scene.masks[0], scene.depth_gt[0]
    colour = np.full(depth.shape + (3,), 0.3, np.float32)
    seeds = seed_hole_gaussians([cam], [mask], [depth], [colour], 0.02, 0, RemoveParams(seed_depth_offset=0.0))
    assert len(seeds) > 10
    xyz = seeds.means.detach().double().numpy()
    # Re-project: every seed lands inside the hole at its depth.
    R, t = cam.cam_from_world[:3, :3], cam.cam_from_world[:3, 3]
    pc = xyz @ R.T + t
    u = np.floor(pc[:, 0] / pc[:, 2] * cam.K[0, 0] + cam.K[0, 2]).astype(int)
    v = np.floor(pc[:, 1] / pc[:, 2] * cam.K[1, 1] + cam.K[1, 2]).astype(int)
    assert mask[v, u].all()
    assert np.allclose(pc[:, 2], depth[v, u], rtol=1e-4)
    assert torch.isfinite(seeds.params["scales"]).all()


def test_seeds_that_another_view_sees_through_are_carved(scene_and_model):
    """A hole seed that another view shows in front of background it saw is dropped: on the right
    depth the seeds stay, on a depth far too near (floating in front of the scene) they go."""
    scene, _, _ = scene_and_model
    cams, masks, depths = scene.cameras, list(scene.masks), list(scene.depth_gt)
    holes = [masks[0]] + [np.zeros_like(m) for m in masks[1:]]
    colours = [np.full(d.shape + (3,), 0.3, np.float32) for d in depths]
    observed = [~m for m in masks]  # each view saw the background outside its object mask
    p = RemoveParams()

    def seeds(depth0, carve):
        return len(seed_hole_gaussians(cams, holes, [depth0] + depths[1:], colours, 0.02, 0, p,
                                       observed=observed if carve else None))

    assert seeds(depths[0], False) > 20
    assert seeds(depths[0], True) >= 0.8 * seeds(depths[0], False)
    assert seeds(0.5 * depths[0], True) < 0.3 * seeds(0.5 * depths[0], False)
    # carve_footprint (the default): the same seeds, none larger, those near the seen background beside
    # the too-near hole smaller (footprint_scales)
    near = [0.8 * depths[0]] + depths[1:]
    plain = seed_hole_gaussians(cams, holes, near, colours, 0.02, 0, RemoveParams(carve_footprint=False),
                                observed=observed)
    shrunk = seed_hole_gaussians(cams, holes, near, colours, 0.02, 0, RemoveParams(), observed=observed)
    a, b = plain.params["scales"].detach(), shrunk.params["scales"].detach()
    assert len(plain) > 5 and torch.equal(plain.means, shrunk.means)
    assert (b <= a + 1e-6).all() and (b < a - 1e-6).any()


def test_footprint_scales_shrink_a_seed_off_the_background_seen_behind_it():
    """One camera looks down +z. It saw the background at depth 2 on the left half of its image; the
    right half is its hole. Seeds at depth 1 near the boundary would spread over the seen half: halved
    until they do not (or three times); a seed deep in the hole, or one behind the seen background, keeps
    its scale."""
    from sgpor_pipeline.scene import Camera

    w = h = 100
    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    cam = Camera("v", w, h, K, np.eye(4), image="v")
    seen = np.zeros((h, w), bool)
    seen[:, :50] = True
    depth = np.full((h, w), 2.0, np.float32)
    # pixel x of a point at depth z: 100 x / z + 50; a scale s at depth 1 spans 1.5 x 100 s px at reach 1.5
    xyz = np.array([[0.02, 0.0, 1.0],  # 2 px right of the boundary: clashes until 1.5 x 100 s < 2 px
                    [0.005, 0.0, 1.0],  # half a px from it: still clashes after three halvings
                    [0.40, 0.0, 1.0],  # 40 px into the hole: free
                    [0.04, 0.0, 3.0]])  # behind the seen background (depth 3 > 2): free
    scale = np.full(4, 0.05)  # 7.5 px at depth 1
    out = footprint_scales([cam], [seen], [depth], xyz, scale, depth_tol=0.02)
    assert out[0] == pytest.approx(0.05 / 4)  # reach 1.9 px after two halvings
    assert out[1] == pytest.approx(0.05 / 8)  # at most three
    assert out[2] == scale[2] and out[3] == scale[3]
    assert np.array_equal(scale, np.full(4, 0.05))  # (a copy)
    fewer = footprint_scales([cam], [seen], [depth], xyz, scale, depth_tol=0.02, halvings=1)
    assert fewer[0] == pytest.approx(0.025)


def test_seeds_sit_behind_the_completed_surface_by_the_depth_offset(scene_and_model):
    """remove.seed_depth_offset: each seed moves that many seed spacings away from its view along the
    pixel's ray, so it still projects into the same hole pixel of that view."""
    scene, _, _ = scene_and_model
    cam, mask, depth = scene.cameras[0], scene.masks[0], scene.depth_gt[0]
    colour = np.full(depth.shape + (3,), 0.3, np.float32)
    spacing = 0.001  # finer than the seeds' stride: no two seeds share a voxel, so both sets pair up
    on = seed_hole_gaussians([cam], [mask], [depth], [colour], spacing, 0, RemoveParams(seed_depth_offset=0.0))
    behind = seed_hole_gaussians([cam], [mask], [depth], [colour], spacing, 0, RemoveParams(seed_depth_offset=2.0))
    a, b = on.means.detach().double().numpy(), behind.means.detach().double().numpy()
    assert a.shape == b.shape and len(a) > 10
    ra, rb = np.linalg.norm(a - cam.center, axis=1), np.linalg.norm(b - cam.center, axis=1)
    assert np.allclose(rb - ra, 2 * spacing, atol=2e-5)  # (float32 means)
    assert np.allclose((b - cam.center) / rb[:, None], (a - cam.center) / ra[:, None], atol=1e-5)  # same rays
    uv, _ = cam.project(b)
    u, v = np.floor(uv).astype(int).T
    assert mask[v, u].all()


# --------------------------------------------------------------------------------------------------
# the remove stage's edge cases (issue: empty mask, a mask covering most of the image, an unseen hole)


def _remove(model, cameras, masks, object_ids, params=None):
    """What the remove stage does per run: delete, find holes, complete depth, seed the holes."""
    params = params or RemoveParams()
    delete, _, _, _ = objects_to_delete(model, cameras, masks, object_ids, params)
    background = subset(model, ~delete)
    holes, depths, colours = [], [], []
    for cam, mask in zip(cameras, masks):
        rgb, alpha, depth = render_background(background, cam)
        hole = hole_mask(mask, alpha, params)
        holes.append(hole)
        depths.append(complete_depth(depth, alpha >= params.hole_alpha, hole))
        colours.append(initial_colour(rgb, hole))
    spacing = median_spacing(background.means.detach().double().numpy())
    seeds = seed_hole_gaussians(cameras, holes, depths, colours, spacing, model.max_sh_degree, params)
    return delete, background, holes, depths, seeds


def test_seeds_take_8bit_initial_colours_exactly(scene_and_model):
    """The remove stage keeps the seeds' Telea colours as 8-bit images (on disk, holes only): the same
    seeds, bit for bit, as from the float colours; a view without a hole needs none."""
    scene, model, object_ids = scene_and_model
    masks = list(scene.masks)
    params = RemoveParams()
    delete, background, holes, depths, seeds = _remove(model, scene.cameras, masks, object_ids, params)
    colours8 = []
    for cam, hole in zip(scene.cameras, holes):
        rgb = render_background(background, cam)[0]
        c8 = initial_colour(rgb, hole, as_uint8=True) if hole.any() else None
        if c8 is not None:
            assert c8.dtype == np.uint8 and np.array_equal(to_float32(c8), initial_colour(rgb, hole))
        colours8.append(c8)
    holes[0] = np.zeros_like(holes[0])  # (a view without a hole: its colour is None)
    colours8[0] = None
    spacing = median_spacing(background.means.detach().double().numpy())
    colours = [None if c is None else to_float32(c) for c in colours8]
    a = seed_hole_gaussians(scene.cameras, holes, depths, colours8, spacing, model.max_sh_degree, params)
    b = seed_hole_gaussians(scene.cameras, holes, depths, colours, spacing, model.max_sh_degree, params)
    assert len(a) > 0 and all(torch.equal(a.params[k], b.params[k]) for k in a.params)
    with pytest.raises(ValueError, match="needs a hole"):
        initial_colour(np.zeros((4, 4, 3), np.float32), np.zeros((4, 4), bool), as_uint8=True)


def test_empty_mask_passes_the_scene_through_unchanged(scene_and_model):
    scene, model, _ = scene_and_model
    empty = [np.zeros_like(m) for m in scene.masks]
    delete, background, holes, _, seeds = _remove(model, scene.cameras, empty, np.array([], np.int64))
    assert not delete.any() and len(background) == len(model)
    assert not any(h.any() for h in holes) and len(seeds) == 0
    assert torch.equal(background.means, model.means)


def test_mask_covering_most_of_the_image_still_finishes(scene_and_model):
    """Masks of 90 % of every image: everything in the views' centres counts as object. The stage's
    steps must finish with finite results, holes inside the masks (but for their 2 px rim) and seeds
    on finite depths."""
    scene, model, _ = scene_and_model
    big = []
    for m in scene.masks:
        b = np.zeros_like(m)
        h, w = m.shape
        b[h // 20: h - h // 20, w // 20: w - w // 20] = True
        big.append(b)
    delete, background, holes, depths, seeds = _remove(model, scene.cameras, big, np.array([], np.int64))
    assert delete.any() and len(background) > 0
    for hole, mask, depth in zip(holes, big, depths):
        assert not (hole & ~(cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0)).any()
        assert np.isfinite(depth[hole]).all()
    assert torch.isfinite(seeds.means).all() and torch.isfinite(seeds.params["scales"]).all()


def test_a_hole_no_view_sees_is_filled(scene_and_model):
    """Take the floor under the object away as well (no view can see it: the object stands on it):
    after deleting the object, that part of the masks is a hole; its seeds cover it in the views."""
    scene, model, truth = scene_and_model
    lo, hi = scene.object_bounds
    xyz = model.means.detach().double().numpy()
    pad = 0.05 * (hi - lo)
    footprint = np.all((xyz >= lo - pad) & (xyz <= hi + pad), axis=1) & ~truth
    keep = ~footprint
    m = subset(model, keep)
    ids = np.flatnonzero(truth[keep])
    delete, background, holes, _, seeds = _remove(m, scene.cameras, list(scene.masks), ids)
    assert sum(h.sum() for h in holes) > 20, "the unseen footprint must show up as a hole"
    assert len(seeds) > 0
    cleaned = concat_models(background, seeds)
    covered = []
    for cam, hole in zip(scene.cameras, holes):
        if hole.sum() < 5:
            continue
        _, alpha, _ = render_background(cleaned, cam)
        covered.append(float((alpha[hole] >= 0.5).mean()))
    assert covered and np.mean(covered) > 0.8, covered


def _photo_of(obj: np.ndarray, colour: tuple[float, float, float], seed: int) -> np.ndarray:
    """A photo of an object of one ``colour`` where ``obj`` is, on a blue-grey background, both noisy."""
    rng = np.random.default_rng(seed)
    image = np.empty((*obj.shape, 3), np.float32)
    image[:] = (0.35, 0.45, 0.6)
    image += rng.normal(0, 0.04, image.shape).astype(np.float32)
    image[obj] = colour + rng.normal(0, 0.04, (int(obj.sum()), 3))
    return image.clip(0, 1)


def test_grabcut_snaps_a_partial_mask_to_the_object_in_the_photo():
    """The object's far side was missed by the selection (the mask covers 70 % of it): GrabCut on the
    photo completes it without taking the background; a tiny mask is left alone (None)."""
    from sgpor_pipeline.removal.selection import grabcut_mask

    h, w = 120, 160
    yy, xx = np.mgrid[0:h, 0:w]
    disc = (yy - 60) ** 2 + (xx - 80) ** 2 < 35 ** 2
    image = _photo_of(disc, (0.9, 0.75, 0.1), seed=0)
    partial = disc & (xx < 80 + 0.4 * 35)  # the left 70 %
    snapped = grabcut_mask(partial.astype(np.float32), partial, image)
    assert snapped is not None
    assert iou(snapped, disc) > 0.9 > iou(partial, disc), (iou(snapped, disc), iou(partial, disc))
    # seeded: the same mask whatever drew from OpenCV's global generator before
    cv2.setRNGSeed(12345)
    cv2.randu(np.zeros((64, 64), np.float32), 0.0, 1.0)
    assert np.array_equal(grabcut_mask(partial.astype(np.float32), partial, image), snapped)
    assert grabcut_mask(np.zeros((h, w), np.float32), np.zeros((h, w), bool), image) is None


def test_the_photo_tells_a_mask_drawn_on_the_edge_from_one_drawn_with_a_margin():
    """``photo_margin``: GrabCut from the given mask alone keeps a mask drawn on the object's edge (a
    margin under MIN_MARGIN px) and drops the band of one dilated around it (about its width)."""
    from sgpor_pipeline.removal.selection import photo_margin
    from sgpor_pipeline.stages.masks import MIN_MARGIN

    h, w = 120, 160
    yy, xx = np.mgrid[0:h, 0:w]
    box = (np.abs(yy - 60) < 25) & (np.abs(xx - 80) < 30)
    image = _photo_of(box, (0.8, 0.5, 0.2), seed=1)
    assert photo_margin(box, image) < MIN_MARGIN
    dilated = cv2_dilate(box, 8)
    assert 6 < photo_margin(dilated, image) < 10
    assert photo_margin(np.zeros((h, w), bool), image) is None


def test_grabcut_additions_are_gated_by_the_given_views(scene_and_model):
    """Pixels of another view whose surface the given view showed inside its mask pass; pixels of
    floor the given view showed outside its mask do not."""
    from sgpor_pipeline.removal.selection import inside_given_cone

    scene, model, _ = scene_and_model
    given_cam, given_mask = scene.cameras[0], scene.masks[0]
    cam, mask = scene.cameras[1], scene.masks[1]
    far = ~(cv2_dilate(mask, 15))
    kept = inside_given_cone(model, cam, mask | far, [given_cam], [given_mask], 3)
    assert kept[mask].mean() > 0.8, kept[mask].mean()
    # (a few far pixels are background hidden behind the object from the given view: it cannot
    # rule them out; 9 % here)
    assert kept[far].mean() < 0.15, kept[far].mean()


def _with_floaters_before(model: GaussianModel, truth: np.ndarray, cam) -> tuple[GaussianModel, np.ndarray]:
    """The model with floaters a fifth of the way from ``cam`` to the object (``truth``), in front of it
    in that view only, as a sparse capture's fit draws a far view's object; and its object flags."""
    means = model.means.detach().numpy().astype(np.float64)
    centre = means[truth].mean(axis=0)
    rng = np.random.default_rng(0)
    spread = 0.5 * np.ptp(means[truth], axis=0).max() / 3
    floaters = cam.center + (centre - cam.center) / 5 + rng.normal(0, spread / 2, (400, 3))
    fm = GaussianModel.empty(len(floaters), 0)
    with torch.no_grad():
        fm.params["means"].copy_(torch.from_numpy(floaters).float())
        fm.params["scales"].fill_(float(np.log(spread / 4)))
        fm.params["opacities"].fill_(3.0)
    return concat_models(model, fm), np.concatenate([truth, np.zeros(len(fm), bool)])


def test_the_given_masks_lifted_surface_finds_the_object_where_floaters_draw_it(scene_and_model):
    """A sparse capture's fit draws a far view's object with floaters of that view: the object's
    Gaussians, occluded by them, render nothing there, and the propagated mask missed the object
    (lund + box from one mask: IoU 0 in views 1-16). The given mask's pixels, lifted at the median
    depth, land on the object in that view all the same; and in every view they stay on the object."""
    from sgpor_pipeline.removal.selection import LiftedSurface, lift_mask, splat_surface

    scene, model, truth = scene_and_model
    given_cam, given_mask = scene.cameras[0], scene.masks[0]
    tight = tighten_mask(model, given_cam, given_mask, TightParams())[0]  # (as the masks stage lifts it)
    surface = lift_mask(model, given_cam, tight)
    assert len(surface) == int((tight & (render_median_depth(model, given_cam) > 0)).sum()) > 100
    assert iou(splat_surface(surface, given_cam), given_mask) > 0.9
    for cam, mask in zip(scene.cameras[1:], scene.masks[1:]):
        lifted = splat_surface(surface, cam)
        # the given view's side of the object, inside its silhouette in every view
        assert (lifted & ~cv2_dilate(mask, 1)).sum() <= 0.05 * max(1, lifted.sum()), cam.image
    # the view nearest the given one (30 degrees round the object) sees much of what it saw
    near = int(np.argmin([np.linalg.norm(c.center - given_cam.center) for c in scene.cameras[1:]])) + 1
    cam, mask = scene.cameras[near], scene.masks[near]
    before = iou(splat_surface(surface, cam), mask)
    assert before > 0.5
    fitted, is_object = _with_floaters_before(model, truth, cam)
    # (the given view sees the object as before: the floaters' depth nowhere on its mask)
    assert np.array_equal(render_median_depth(fitted, given_cam)[tight], render_median_depth(model, given_cam)[tight])
    rendered = refine_mask(render_object_probability(fitted, is_object, cam), scene.images[near], SelectionParams())
    assert iou(rendered, mask) < 0.2
    surface = lift_mask(fitted, given_cam, tight)
    assert iou(splat_surface(surface, cam), mask) > 0.95 * before
    assert not splat_surface(LiftedSurface.concat([]), cam).any()


def test_only_what_reaches_beyond_the_edge_joins_a_mask():
    """Another cue's slivers along the mask's edge (a pixel's disagreement) are dropped; a part it
    found that reaches further, away from the mask or touching it, joins whole, with the sliver's
    pixels right beside it."""
    from sgpor_pipeline.removal.selection import reaching_beyond

    mask = np.zeros((40, 60), bool)
    mask[10:30, 10:30] = True
    extra = np.zeros_like(mask)
    extra[9:31, 9:31] = True  # the same object, one pixel wider
    extra[12:18, 45:55] = True  # a part the mask missed, apart from it
    extra[20:24, 30:40] = True  # a part touching it, 10 px long
    got = reaching_beyond(extra, mask, 2)
    assert got[12:18, 45:55].all() and got[20:24, 30:40].all()
    assert not got[9, 9:31].any() and not got[10:30, 9].any() and not got[mask].any()
    assert got.sum() == 6 * 10 + 4 * 10 + 4  # (the touching part's sides: 2 px of the sliver each)
    assert not reaching_beyond(mask, mask, 2).any() and not reaching_beyond(extra, np.zeros_like(mask), 2)[0].any()


def cv2_dilate(mask: np.ndarray, r: int) -> np.ndarray:
    import cv2

    return cv2.dilate(mask.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8)) > 0


def test_completed_hole_depth_never_lies_in_front_of_the_deleted_object():
    """Real fits render the surroundings of an object nearer than the object itself (semi-transparent
    Gaussians in front: lund + box, 2-3x nearer). Completed from them, holes lie in front of the
    object, in space other views see, and new Gaussians are seeded there in mid-air. With the object's
    depth as the floor no view's hole surface lies in front of the object in any view."""
    import cv2

    from sgpor_pipeline.removal.holes import complete_depths_jointly

    scene = generate_scene(SceneParams(seed=3, n_views=8, width=96, height=72))
    k = np.ones((5, 5), np.uint8)
    holes = [cv2.erode(m.astype(np.uint8), k) > 0 for m in scene.masks]
    near = [np.where(m, 0.0, 0.4 * d).astype(np.float32) for m, d in zip(scene.masks, scene.depth_gt)]
    valids = [~m for m in scene.masks]
    floors = [np.where(m, d, 0.0).astype(np.float32) for m, d in zip(scene.masks, scene.depth)]

    def in_front_share(completed):
        """Share of all views' hole points that some view sees in front of the object."""
        front, total = 0, 0
        for i, cam in enumerate(scene.cameras):
            ys, xs = np.nonzero(holes[i])
            pts = cam.unproject(ys, xs, completed[i][ys, xs])
            bad = np.zeros(len(pts), bool)
            for j, other in enumerate(scene.cameras):
                px, z, inside = other.pixels(pts)
                idx = np.flatnonzero(inside)
                f = floors[j][px[idx, 1], px[idx, 0]]
                bad[idx[(f > 0) & (z[idx] < 0.98 * f)]] = True
            front += int(bad.sum())
            total += len(pts)
        return front / total

    plain = complete_depths_jointly(scene.cameras, near, valids, holes)
    floored = complete_depths_jointly(scene.cameras, near, valids, holes, floors)
    for c, f, h in zip(floored, floors, holes):
        assert np.isfinite(c[h]).all() and (c[h] >= f[h] - 1e-6).all()
    assert in_front_share(plain) > 0.5, in_front_share(plain)
    assert in_front_share(floored) < 0.05, in_front_share(floored)
    # each view on its own, too
    alone = [complete_depth(d, v, h, f) for d, v, h, f in zip(near, valids, holes, floors)]
    assert all((a[h] >= f[h] - 1e-6).all() for a, f, h in zip(alone, floors, holes))


def test_context_image_is_the_photo_outside_the_dilated_mask():
    """The inpainter's image: the photo where the object mask (grown by the margin, whose pixels mix
    object and background) is not, the render inside; the render alone without a photo."""
    render, photo = np.zeros((20, 30, 3), np.float32), np.ones((20, 30, 3), np.float32)
    mask = np.zeros((20, 30), bool)
    mask[8:12, 10:15] = True
    out = context_image(render, photo, mask, margin=2)
    grown = np.zeros_like(mask)
    grown[6:14, 8:17] = True
    assert out.dtype == np.float32 and (out[grown] == 0).all() and (out[~grown] == 1).all()
    assert (context_image(render, photo, mask, margin=0)[~mask] == 1).all()
    assert context_image(render, None, mask, margin=2) is render
    # the same margin everywhere (context band, hole rim, finetune band): a square grown mask
    assert (within_margin(mask, 2) == grown).all()
    same = within_margin(mask, 0)
    assert (same == mask).all() and same is not mask


def test_the_context_shows_the_colour_of_a_partly_transparent_background(scene_and_model):
    """After the deletion the background beside a hole is partly transparent, and its render (over
    black) darker than the surface: the context shows the render divided by its opacity. Every
    Gaussian of the fixture is grey 0.5; here they are made faint (opacity 0.2) so that many pixels
    are partly covered."""
    scene, model, truth = scene_and_model
    background = subset(model, ~truth)
    with torch.no_grad():
        background.params["opacities"].fill_(float(np.log(0.2 / 0.8)))
    thin = []
    for cam in scene.cameras:
        rgb, alpha, _ = render_background(background, cam)
        shown = unpremultiplied(rgb, alpha)
        assert shown.dtype == np.float32 and shown.shape == rgb.shape
        partly = (alpha >= 0.5) & (alpha < 0.95)
        thin.append((rgb[partly], shown[partly]))
        faint = alpha < 0.5  # (too little of the surface to divide by: left as rendered)
        assert np.array_equal(shown[faint], rgb[faint].astype(np.float32))
    rendered = np.concatenate([t[0] for t in thin])
    shown = np.concatenate([t[1] for t in thin])
    assert len(rendered) > 100
    assert rendered.mean() < 0.45 and np.abs(shown - 0.5).max() < 0.01, (rendered.mean(), np.abs(shown - 0.5).max())


def test_finetune_views_leave_the_seen_background_unsupervised(tmp_path):
    """The finetune's targets: the photo outside the grown mask, the refine stage's image inside it;
    the grown mask outside the hole (the render after deletion, DC colours only) has loss weight
    ``seen_weight``: 0 by default, no weight map at 1; a negative weight is refused. (With ``harmonize``
    the mask's target is first corrected towards the photo around it.)"""
    from types import SimpleNamespace

    from sgpor_pipeline.errors import PipelineError
    from sgpor_pipeline.imageio import write_mask01, write_png
    from sgpor_pipeline.scene import Camera
    from sgpor_pipeline.stages.finetune import FinetuneParams, FinetuneStage

    h, w = 20, 30
    mask = np.zeros((h, w), bool)
    mask[5:15, 8:20] = True
    hole = np.zeros((h, w), bool)
    hole[8:12, 10:16] = True
    for sub in ("refine/images", "sfm/images", "remove/masks"):
        (tmp_path / sub).mkdir(parents=True)
    write_png(tmp_path / "refine" / "images" / "v.png", np.full((h, w, 3), 0.2, np.float32))
    write_png(tmp_path / "sfm" / "images" / "v.png", np.full((h, w, 3), 0.8, np.float32))
    write_mask01(tmp_path / "remove" / "masks" / "v.png", mask)
    ctx = SimpleNamespace(inputs={s: tmp_path / s for s in ("refine", "sfm", "remove")})
    K = np.array([[20.0, 0, w / 2], [0, 20.0, h / 2], [0, 0, 1]])
    cam = Camera("v", w, h, K, np.eye(4), image="v")
    view = FinetuneStage._view(ctx, cam, hole, FinetuneParams(max_size=0, harmonize=False))
    band = within_margin(mask, 2)
    img = view.image.numpy()
    assert np.allclose(img[band], 0.2, atol=1 / 255) and np.allclose(img[~band], 0.8, atol=1 / 255)
    # harmonize (the default): the mask's target takes the photo's colour at its rim (a constant offset),
    # and the seen part, whose render is that far off (0.6 >= seen_offset), is supervised in full
    on = FinetuneStage._view(ctx, cam, hole, FinetuneParams(max_size=0))
    assert np.allclose(on.image.numpy(), 0.8, atol=2 / 255)
    assert (on.weight.numpy() == 1).all()
    scaled = FinetuneStage._view(ctx, cam, hole, FinetuneParams(max_size=0, seen_offset=1.2)).weight.numpy()
    assert np.allclose(scaled[band & ~hole], 0.5, atol=0.01)  # 0.6 / 1.2
    off = FinetuneStage._view(ctx, cam, hole, FinetuneParams(max_size=0, seen_offset=0)).weight.numpy()
    assert (off[band & ~hole] == 0).all()
    wt = view.weight.numpy()
    assert (wt[band & ~hole] == 0).all() and (wt[hole] == 1).all() and (wt[~band] == 1).all()
    assert FinetuneStage._view(ctx, cam, hole, FinetuneParams(max_size=0, seen_weight=1.0)).weight is None
    half = FinetuneStage._view(ctx, cam, hole, FinetuneParams(max_size=0, seen_weight=0.5,
                                                              harmonize=False)).weight.numpy()
    assert (half[band & ~hole] == 0.5).all()
    with pytest.raises(PipelineError, match="seen_weight"):
        FinetuneStage().run(SimpleNamespace(params=FinetuneParams(seen_weight=-1.0)))
    with pytest.raises(PipelineError, match="seen_offset"):
        FinetuneStage().run(SimpleNamespace(params=FinetuneParams(seen_offset=-1.0)))


def test_masks_given_views_picks_the_given_masks_by_name(tmp_path):
    """``masks.given_views`` uses only the named views' masks (propagation from a chosen view while
    every true mask is given, for scoring); a name without a given mask is an error naming it."""
    from sgpor_pipeline.errors import PipelineError
    from sgpor_pipeline.imageio import write_mask01
    from sgpor_pipeline.sfm import MASKS_DIR, SfmPoints, SfmResult
    from sgpor_pipeline.stages.masks import _read_given_masks

    scene = generate_scene(SceneParams(seed=3, n_views=4, width=48, height=36))
    (tmp_path / MASKS_DIR).mkdir()
    for cam, mask in zip(scene.cameras, scene.masks):
        write_mask01(tmp_path / MASKS_DIR / f"{cam.image}.png", mask)
    empty = SfmPoints(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0), np.zeros(0, np.int64),
                      np.zeros(0, np.int64), np.zeros((0, 2)))
    sfm = SfmResult(tmp_path, list(scene.cameras), empty)
    names = [c.image for c in scene.cameras]
    assert [c.image for c, _ in _read_given_masks(sfm, 0, tmp_path)] == names
    assert [c.image for c, _ in _read_given_masks(sfm, 1, tmp_path)] == names[:1]
    picked = _read_given_masks(sfm, 0, tmp_path, (names[2],))
    assert [c.image for c, _ in picked] == [names[2]] and np.array_equal(picked[0][1], scene.masks[2])
    with pytest.raises(PipelineError, match="view_9"):
        _read_given_masks(sfm, 0, tmp_path, (names[0], "view_9"))


def test_a_view_whose_render_lost_the_object_takes_its_mask_from_the_lifted_surface(scene_and_model, tmp_path):
    """The masks stage's propagation in a view where floaters occlude the selected object: the mask
    is the given mask's lifted footprint snapped by GrabCut (the lifted pixels its sure object, its
    additions unchecked by the cone), and its confidence says the render lost the object; without
    the lifted surface the mask misses it."""
    from sgpor_pipeline.imageio import write_png
    from sgpor_pipeline.removal.selection import Selection, lift_mask
    from sgpor_pipeline.sfm import IMAGES_DIR, SfmPoints, SfmResult
    from sgpor_pipeline.stages.masks import MasksParams, _GivenViews, _propagate_view

    scene, model, truth = scene_and_model
    given_cam, given_mask = scene.cameras[0], scene.masks[0]
    near = int(np.argmin([np.linalg.norm(c.center - given_cam.center) for c in scene.cameras[1:]])) + 1
    cam, mask = scene.cameras[near], scene.masks[near]
    fitted, is_object = _with_floaters_before(model, truth, cam)
    (tmp_path / IMAGES_DIR).mkdir()
    write_png(tmp_path / IMAGES_DIR / f"{cam.image}.png", scene.images[near])
    empty = SfmPoints(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0), np.zeros(0, np.int64),
                      np.zeros(0, np.int64), np.zeros((0, 2)))
    sfm = SfmResult(tmp_path, list(scene.cameras), empty)
    selection = Selection(is_object, np.ones(len(is_object), np.float32), int(is_object.sum()), 0, 0)
    given = _GivenViews([given_cam], [given_mask], [given_mask], None, [True])
    p, sel_params = MasksParams(), SelectionParams()
    lost, _, _ = _propagate_view(fitted, sfm, cam, selection, given, p, sel_params)
    assert iou(lost, mask) < 0.2
    given.surface = lift_mask(fitted, given_cam, given_mask)
    found, _, info = _propagate_view(fitted, sfm, cam, selection, given, p, sel_params)
    assert info["lifted_added"] > 0 and info["lifted_covered"] < 0.5
    assert info["confidence"] <= info["lifted_covered"]
    # (GrabCut's additions checked against the given view's cone, which reads this view's depth, the
    # floaters': 0.59)
    assert iou(found, mask) > 0.7, iou(found, mask)


def test_a_mask_only_on_photos_sfm_lost_stops_the_run_before_the_fit(tmp_path):
    """MasksStage.check_upstream on the sfm result: the object painted only in photos that did not
    register names them and the registered ones to paint instead (asked before the fit runs)."""
    import json

    from sgpor_pipeline.errors import PipelineError
    from sgpor_pipeline.imageio import write_png
    from sgpor_pipeline.scene import Camera, save_cameras
    from sgpor_pipeline.sfm import SfmPoints
    from sgpor_pipeline.stages.masks import MasksParams, MasksStage

    sfm = tmp_path / "sfm"
    (sfm / "masks").mkdir(parents=True)
    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    save_cameras(sfm / "cameras.json", [Camera(f"IMG_{i}", 64, 48, K, np.eye(4), image=f"IMG_{i}") for i in (1, 2, 3)])
    e = np.zeros(0)
    SfmPoints(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), e, e.astype(np.int64), e.astype(np.int64),
              np.zeros((0, 2))).save(sfm / "points.npz")
    (sfm / "sfm.json").write_text(json.dumps({"mode": "sfm", "registered": 3, "images": 4, "unregistered": ["IMG_0"]}))
    write_png(sfm / "masks" / "IMG_2.png", np.zeros((48, 64), bool))  # (an empty mask counts as none)
    with pytest.raises(PipelineError, match=r"1 photo\(s\) did not register \(IMG_0\).*e\.g\. IMG_1, IMG_2, IMG_3"):
        MasksStage.check_upstream(MasksParams(), "sfm", sfm)
    MasksStage.check_upstream(MasksParams(), "ingest", sfm)  # (only the sfm result is checked)
    mask = np.zeros((48, 64), bool)
    mask[10:20, 10:30] = True
    write_png(sfm / "masks" / "IMG_3.png", mask)
    MasksStage.check_upstream(MasksParams(), "sfm", sfm)  # a registered photo has it: the run goes on


@pytest.mark.parametrize("ratio", [0.5, -1.0, float("nan")])
def test_remove_stage_refuses_a_far_side_ratio_below_one(ratio):
    """Below 1 every row would count as a step (the far side is always >= ratio x the near one):
    refused before anything is read, with the fix."""
    from types import SimpleNamespace

    from sgpor_pipeline.errors import PipelineError
    from stages.remove import RemoveStage, RemoveStageParams

    ctx = SimpleNamespace(params=RemoveStageParams(far_side_ratio=ratio))
    with pytest.raises(PipelineError, match="far_side_ratio must be 0"):
        RemoveStage().run(ctx)


def test_remove_stage_refuses_an_unknown_delete_masks():
    """remove.delete_masks is checked before anything is read, naming the values it takes."""
    from types import SimpleNamespace

    from sgpor_pipeline.errors import PipelineError
    from stages.remove import RemoveStage, RemoveStageParams

    ctx = SimpleNamespace(params=RemoveStageParams(delete_masks="grow"))
    with pytest.raises(PipelineError, match="unknown remove.delete_masks 'grow'") as err:
        RemoveStage().run(ctx)
    assert "split" in str(err.value.fix)
