"""Region-wise progressive refinement (RPR) and the refine stage."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from sgpor_pipeline.dag import StageContext
from sgpor_pipeline.imageio import read_image
from sgpor_pipeline.removal.multiview import write_remove_fixture
from sgpor_pipeline.removal.rpr import RPRParams, block_energies, hf_energy, refine_view, refined_overlay
from sgpor_pipeline.removal.sbm import SBMParams, build_source_bank, match_blocks, target_positions
from sgpor_pipeline.synthetic import SceneParams, generate_scene

S = 15


@pytest.fixture(scope="module")
def setup():
    """A synthetic view whose hole is filled with the truth, its target blocks and ranked sources."""
    sc = generate_scene(SceneParams(seed=0, rig="forward", n_views=4, width=224, height=168))
    names = [c.name for c in sc.cameras]
    holes = [m.copy() for m in sc.masks]
    renders = []
    for i in range(4):
        r = sc.images_gt[i].copy()
        r[holes[i]] = 0.0
        renders.append(r)
    p = SBMParams(block_size=S, top_k=4)
    bank = build_source_bank(names, renders, list(sc.masks), holes, p)
    hole = holes[0]
    targets = target_positions(hole, S, p.target_stride, p.tau)
    cand = match_blocks(sc.images_gt[0], np.ones(hole.shape, bool), targets, bank, p)[0]
    return sc, renders, hole, targets, cand


def test_hf_energy_is_sobel_abs_sum():
    flat = np.full((20, 30, 3), 0.4, np.float32)
    assert np.allclose(hf_energy(flat), 0.0, atol=1e-6)
    step = flat.copy()
    step[:, 15:] = 0.9
    e = hf_energy(step)
    assert e.shape == (20, 30) and e.dtype == np.float32
    assert e[10, 14] > 0.1 and e[10, 15] > 0.1
    assert np.allclose(e[:, :12], 0, atol=1e-6) and np.allclose(e[:, 18:], 0, atol=1e-6)


def test_blurred_block_is_detected_and_replaced_textured_blocks_left_alone(setup):
    sc, renders, hole, targets, cand = setup
    gt = sc.images_gt[0]
    params = RPRParams()
    before = block_energies(hf_energy(gt), hole, targets, S, params)
    # on the truth, (almost) every block has detail like its surroundings: those are left alone
    res0 = refine_view(gt, hole, targets, cand, renders, params, S)
    assert res0.low_before.sum() <= 0.05 * len(targets)
    assert (res0.count[~res0.low_before] == 0).all() and res0.rounds <= params.max_rounds
    # flatten (blur to its mean colour) the most textured block lying well inside the hole, with a
    # 5-pixel margin so that the flattened square's own edges stay outside the block
    inner = cv2.erode(hole.astype(np.uint8), np.ones((15, 15), np.uint8)).astype(bool)
    full = np.array([inner[y:y + S, x:x + S].all() for y, x in targets])
    assert full.any()
    b = int(np.argmax(np.where(full, before.block, -1)))
    y, x = targets[b]
    img = gt.copy()
    sl = (slice(y - 5, y + S + 5), slice(x - 5, x + S + 5))
    img[sl] = img[sl].reshape(-1, 3).mean(0)
    eb = block_energies(hf_energy(img), hole, targets, S, params)
    assert eb.block[b] < params.ratio * eb.surround[b]  # detected: HF below 15 % of its surroundings
    res = refine_view(img, hole, targets, cand, renders, params, S)
    assert res.low_before[b] and res.count[b] >= 1
    assert res.energy_after.block[b] > 3 * eb.block[b] and not res.low_after[b]
    # blocks that were not low-detail are never refined, and pixels away from refined blocks are untouched
    assert (res.count[~res.low_before] == 0).all()
    touched = np.zeros(hole.shape, bool)
    for (ty, tx), c in zip(targets, res.count):
        if c:
            touched[ty:ty + S, tx:tx + S] = True
    assert np.array_equal(res.image[~touched], img[~touched])
    assert np.array_equal(res.image[~hole], img[~hole])
    vis = refined_overlay(res.image, targets, res.count, S, hole)
    assert vis.shape == (168, 224, 3) and vis.dtype == np.uint8



def test_a_view_without_target_blocks_passes_through(setup):
    """A view whose hole the reference's projection filled has no blocks of its own (an empty candidate
    array as saved by the inpaint stage): nothing to refine, the image comes back unchanged."""
    sc, renders, hole, _, _ = setup
    for cand in (np.zeros((0,), np.int64), np.zeros((0, 4, 3), np.int64)):
        res = refine_view(sc.images_gt[0], hole, np.zeros((0, 2), np.int64), cand, renders, RPRParams(), S)
        assert np.array_equal(res.image, sc.images_gt[0].astype(np.float32))
        assert len(res.count) == 0 and res.rounds == 0

def test_rounds_are_bounded(setup):
    sc, renders, hole, targets, cand = setup
    flat = sc.images_gt[0].copy()
    flat[hole] = flat[hole].mean(0)  # everything in the hole is low-detail
    res = refine_view(flat, hole, targets, cand, renders, RPRParams(ratio=1e6, max_rounds=2), S)
    assert res.rounds == 2 and res.count.max() == 2
    res = refine_view(flat, hole, targets, cand, renders, RPRParams(ratio=1e6, max_rounds=10), S)
    assert res.rounds == cand.shape[1] - 1  # stops when every block has used all its next-best sources
    assert res.count.max() <= cand.shape[1] - 1
    res = refine_view(flat, hole, targets, cand, renders, RPRParams(max_rounds=0), S)
    assert res.rounds == 0 and np.array_equal(res.image, flat)




def test_refine_stage_sharpens_a_smooth_baseline_fill(setup, tmp_path):
    from sgpor_pipeline.stages.inpaint import InpaintParams, InpaintStage
    from sgpor_pipeline.stages.refine import RefineParams, RefineStage

    sc = setup[0]
    remove = write_remove_fixture(sc, tmp_path / "remove", holes="mask")
    # (each view fills its own hole: with the plane texture, most of a view's whole-mask hole takes what
    # the other views saw there, and little of the smooth fill is left to refine)
    ctx = StageContext.standalone(tmp_path, "inpaint", InpaintParams(backend="opencv", thick_reference="none"),
                                  {"remove": remove})
    InpaintStage().run(ctx)
    ctx2 = StageContext.standalone(tmp_path, "refine", RefineParams(), {"inpaint": ctx.out_dir, "remove": remove})
    RefineStage().run(ctx2)
    report = json.loads((ctx2.out_dir / "refined.json").read_text())
    assert report["low_before"] > 0 and report["refined_blocks"] > 0
    assert report["low_after"] < report["low_before"]
    assert all(v["rounds"] <= 3 for v in report["views"].values())
    gain = []
    for i, cam in enumerate(sc.cameras):
        hole = sc.masks[i]
        a = read_image(ctx.out_dir / "images" / f"{cam.name}.png")
        b = read_image(ctx2.out_dir / "images" / f"{cam.name}.png")
        assert (ctx2.out_dir / "refined" / f"{cam.name}.png").is_file()
        assert np.array_equal(a[~hole], b[~hole])
        e_gt, e_a, e_b = (float(hf_energy(x)[hole].mean()) for x in (sc.images_gt[i], a, b))
        gain.append(abs(np.log(e_a / e_gt)) - abs(np.log(e_b / e_gt)))
    assert np.mean(gain) > 0  # the refined fill's detail is closer to the truth's
    # RPR off (the fsr-refit baseline): a pass-through that retrieves nothing
    ctx3 = StageContext.standalone(tmp_path / "off", "refine", RefineParams(max_rounds=0),
                                   {"inpaint": ctx.out_dir, "remove": remove})
    RefineStage().run(ctx3)
    off = json.loads((ctx3.out_dir / "refined.json").read_text())
    assert off["refined_blocks"] == 0 and not any(v["retrieved"] for v in off["views"].values())
    for cam in sc.cameras:
        assert np.array_equal(read_image(ctx.out_dir / "images" / f"{cam.name}.png"),
                              read_image(ctx3.out_dir / "images" / f"{cam.name}.png"))
