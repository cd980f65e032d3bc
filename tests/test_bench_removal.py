"""Smoke test of benchmarks/removal.py's tables and summary on fake rows (no pipeline run)."""

from __future__ import annotations

import json
import math
import tempfile

import numpy as np
import pytest
from conftest import load_benchmark


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("removal")


def _row(method: str, psnr: float) -> dict:
    return {"method": method, "psnr_mask": psnr, "psnr_bbox": psnr + 1, "psnr_full": psnr + 5, "ssim_mask": 0.5,
            "feat_mask": math.nan, "ssim_bbox": 0.6, "ssim_full": 0.8, "psnr_hole": psnr - 3, "detail": 0.75,
            "cons": 0.01, "cons2d": None,
            "seconds": {"fit": 10.0, "finetune": 3.0}, "total_seconds": 13.0, "wall_seconds": None}


def test_tables_and_summary(bench, capsys):
    methods = ["ours", "delete-only", "fsr-refit", "no-sbm", "no-rpr"]
    scene = {"scene": "synthetic", "rows": [_row(m, 25.0 - 1.5 * i) for i, m in enumerate(methods)],
             "wall_seconds": 100.0, "demo_seconds": 300.0, "hole_fraction_of_mask": 0.2, "hole_pixels": 20,
             "mask_pixels": 100}
    table = bench.format_removal_table(scene)
    assert all(m in table for m in methods) and "PSNR mask" in table and "20 of 100" in table
    assert "detail" in table and "0.750" in table
    prop = {"scene": "statue", "iou": {1: 0.8, 2: 0.9}, "iou_min": {2: 0.7}, "wall_seconds": 5.0,
            "evaluated_views": 27}
    assert "0.900" in bench.format_propagation_table([prop, {"scene": "room", "skipped": "no data"}])
    assert "skipped: x" in bench.format_removal_table({"scene": "lund", "skipped": "x"})
    summary, checks = bench.summarise({"synthetic": scene, "lund": {"scene": "lund", "skipped": "x"},
                                       "statue": prop})
    for suf in ("", "_delete_only", "_fsr_refit", "_no_sbm", "_no_rpr"):
        assert f"synthetic_mask_psnr{suf}" in summary
    assert summary["synthetic_target_beats_baselines"] and summary["synthetic_sbm_helps"]
    assert summary["statue_mask_iou_2views"] == 0.9 and summary["demo_seconds"] == 300.0
    assert any("PASS" in c for c in checks)
    assert not any("feature distance" in c for c in checks)  # no feat column: no perceptual line
    assert np.isnan(summary["synthetic_mask_feat"])
    strict = json.dumps(bench.strict_json(summary), allow_nan=False)  # the --json line: NaN as null
    assert json.loads(strict)["synthetic_mask_feat"] is None
    # the supplementary no-sbm-no-rpr row: an [INFO] line, not part of the target
    scene_rpr = dict(scene, rows=scene["rows"] + [_row("no-sbm-no-rpr", 30.0)], refined_blocks=0)
    summary2, checks2 = bench.summarise({"synthetic": scene_rpr})
    assert summary2["synthetic_target_beats_baselines"]
    assert summary2["synthetic_rpr_gain_on_fsr_fill"] == pytest.approx((25.0 - 4.5) - 30.0)
    assert any("RPR on the FSR fill" in c and "refined 0 block" in c for c in checks2)
    # with the perceptual feature distance: its column, keys and the line naming the lowest
    for i, row in enumerate(scene["rows"]):
        row["feat_mask"] = 0.2 - 0.01 * i
    assert "0.1600" in bench.format_removal_table(scene)
    summary, checks = bench.summarise({"synthetic": scene})
    assert summary["synthetic_mask_feat_fsr_refit"] == pytest.approx(0.18)
    assert any("feature distance" in c and "lowest: no-rpr" in c for c in checks)


def test_synthetic_box_scene_has_its_own_keys_and_no_demo_time(bench):
    # the second synthetic scene (a box: large holes) is judged on its own and is not the demo
    assert bench.SYNTHETIC_SCENES["synthetic-box"] == {"object_kind": "box"}
    rows = [_row(m, 25.0 - 1.5 * i) for i, m in enumerate(["ours", "delete-only", "no-sbm"])]
    summary, checks = bench.summarise({"synthetic-box": {"scene": "synthetic-box", "rows": rows, "wall_seconds": 1.0,
                                                         "demo_seconds": 300.0}})
    assert summary["synthetic_box_mask_psnr"] == 25.0 and summary["synthetic_box_mask_psnr_no_sbm"] == 22.0
    assert "demo_seconds" not in summary and "synthetic_mask_psnr" not in summary
    assert any(c.startswith("[PASS] synthetic-box: SBM helps") for c in checks)


def test_fit_seeds_table_and_targets_on_the_mean_gain(bench):
    """With several fit seeds the targets are judged on the mean paired gain (ours - method on the same
    fit), and the table shows every seed, the mean and the gain's range."""
    methods = ["ours", "delete-only", "fsr-refit", "no-sbm", "no-rpr"]
    # seed 0: ours leads every baseline by 2.5 dB or more; seed 7: no-sbm beats ours by 2 dB
    run0 = {"scene": "synthetic", "rows": [_row(m, 25.0 - 2.0 * (i > 0) - 0.5 * i) for i, m in enumerate(methods)],
            "wall_seconds": 1.0, "demo_seconds": 300.0}
    run1 = {"scene": "synthetic", "rows": [_row(m, v) for m, v in zip(methods, [24.0, 21.0, 20.0, 26.0, 23.0])],
            "wall_seconds": 1.0}
    fs = bench.seed_runs([(0, run0), (7, run1)])
    assert fs["seeds"] == [0, 7]
    assert fs["mask_psnr"]["no-sbm"] == [21.5, 26.0]
    assert fs["gains"]["no-sbm"] == pytest.approx([3.5, -2.0])
    table = bench.format_seed_table("synthetic", fs)
    assert "seed 7" in table and "+0.75 (-2.00 .. +3.50)" in table
    single, _ = bench.summarise({"synthetic": run0})
    assert single["synthetic_target_beats_baselines"]
    summary, checks = bench.summarise({"synthetic": dict(run0, fit_seeds=fs)})
    assert summary["synthetic_mask_psnr_no_sbm_seeds"] == [21.5, 26.0]
    assert summary["synthetic_mask_psnr_seed_mean"] == pytest.approx(24.5)
    assert summary["synthetic_fit_seeds"] == [0, 7]
    assert summary["synthetic_mask_psnr"] == 25.0  # the first seed's keys are unchanged
    assert summary["synthetic_sbm_helps"]  # mean gain +0.75 dB >= 0.1
    assert not summary["synthetic_target_beats_baselines"]  # no-sbm: mean +0.75 < 1 dB
    line = next(c for c in checks if "beats every baseline" in c)
    assert "mean over fit seeds 0, 7" in line and "no-sbm -2.00 .. +3.50" in line


def test_iou_and_sheet(bench, tmp_path):
    a = np.zeros((8, 8), bool)
    a[:4] = True
    assert bench.iou(a, a) == 1.0 and bench.iou(a, ~a) == 0.0
    img = np.random.default_rng(0).random((20, 30, 3)).astype(np.float32)
    bench.contact_sheet([[img, bench.mask_overlay(img, np.ones((20, 30), bool))]], ["a", "b"], tmp_path / "s.png",
                        height=40)
    assert (tmp_path / "s.png").is_file()


def test_one_mask_scene_reports_the_propagated_masks_iou(bench, tmp_path):
    """synthetic-box-1mask (and synthetic-raised-cast-1mask) runs with one given mask; the IoU of the
    masks stage's masks against the true ones is taken on the views not given, and printed and stored
    beside the removal."""
    from sgpor_pipeline.imageio import write_mask01

    for one, every in (("synthetic-box-1mask", "synthetic-box"),
                       ("synthetic-raised-cast-1mask", "synthetic-raised-cast")):
        assert bench.SYNTHETIC_SCENES[one] == bench.SYNTHETIC_SCENES[every]
        assert "masks.max_given=1" in bench.ONE_MASK[one] and one in bench.PREFIX
    truth, masks = tmp_path / "truth", tmp_path / "masks"
    (masks / "masks").mkdir(parents=True)
    truth.mkdir()
    square = np.zeros((10, 10), bool)
    square[2:6, 2:6] = True
    for name, shift in (("a", 0), ("b", 0), ("c", 2)):  # a: given; b: exact; c: shifted by 2 px
        write_mask01(truth / f"{name}.png", square)
        write_mask01(masks / "masks" / f"{name}.png", np.roll(square, shift, axis=1) if name != "a" else ~square)
    (masks / "masks.json").write_text(json.dumps({"given": ["a"]}))
    r = bench.propagation_iou(masks, truth)
    assert r["given"] == ["a"] and r["propagation_iou_min"] == pytest.approx(8 / 24)
    assert r["propagation_iou"] == pytest.approx((1 + 8 / 24) / 2)
    rows = [_row(m, 25.0 - 1.5 * i) for i, m in enumerate(["ours", "delete-only"])]
    summary, checks = bench.summarise({"synthetic-box-1mask": {"scene": "synthetic-box-1mask", "rows": rows,
                                                               "wall_seconds": 1.0, **r}})
    assert summary["synthetic_box_1mask_propagation_iou"] == pytest.approx(r["propagation_iou"])
    assert any("masks propagated from a: IoU against the truth 0.667 (min 0.333)" in c for c in checks), checks


def test_the_photos_scene_is_the_demo_without_its_cameras(bench):
    """synthetic-photos: the demo's scene, run through SfM (no cameras given) at a camera model that
    keeps the photos' pixels, so every truth-reading figure stays in the photos' frame."""
    assert bench.SYNTHETIC_SCENES["synthetic-photos"] == bench.SYNTHETIC_SCENES["synthetic"]
    assert bench.FROM_PHOTOS["synthetic-photos"] == ["sfm.camera_model=SIMPLE_PINHOLE"]
    assert "synthetic-photos" in bench.GT_SCENES and bench.PREFIX["synthetic-photos"] == "synthetic_photos"
    assert set(bench.FROM_PHOTOS) <= set(bench.SYNTHETIC_SCENES)


def test_the_video_scene_takes_its_photos_from_an_mp4(bench, tmp_path):
    """synthetic-video: the views written as a video, photos taken by `frames`, each with the true
    mask and object-free view of the frame it is."""
    from sgpor_pipeline.demo import ensure_demo_scene
    from sgpor_pipeline.imageio import read_image, read_mask
    from sgpor_pipeline.synthetic import SceneParams

    assert {"synthetic-video"} <= set(bench.VIDEO) & set(bench.FROM_PHOTOS) & set(bench.ONE_MASK)
    scene_dir = ensure_demo_scene(tmp_path / "scene", SceneParams(rig="forward", n_views=9, width=96, height=72))
    folder = bench.video_capture(scene_dir, tmp_path / "video", 3)
    photos = sorted((folder / "images").glob("*.png"))
    assert len(photos) == 3 and all(p.stem.startswith("frame_") for p in photos)
    for p in photos:
        view = f"view_{int(p.stem.split('_')[1]):03d}.png"
        assert np.array_equal(read_mask(folder / "masks" / p.name), read_mask(scene_dir / "masks" / view))
        assert np.array_equal(read_image(folder / "groundtruth" / p.name), read_image(scene_dir / "groundtruth" / view))
        # the photo is the frame through a lossy codec: close to the view, not equal
        err = np.abs(read_image(p) - read_image(scene_dir / "images" / view)).mean()
        assert 0 < err < 0.05
    assert bench.video_capture(scene_dir, tmp_path / "video", 3) == folder  # made once


def test_parser_rejects_unknown_scene(bench):
    with pytest.raises(SystemExit):
        bench.main(["--scenes", "nope"])


def test_oracle_holes_psnr_replaces_only_the_holes(bench, tmp_path):
    """The inpainting headroom: hole pixels take the truth, the rest of the mask keeps its error."""
    from sgpor_pipeline.imageio import write_mask01, write_png

    truth = np.full((10, 10, 3), 0.5, np.float32)
    mask = np.zeros((10, 10), bool)
    mask[2:8, 2:8] = True  # 36 pixels
    hole = np.zeros((10, 10), bool)
    hole[2:5, 2:8] = True  # 18 of them
    for sub in ("holes", "masks", "truth"):
        (tmp_path / sub).mkdir()
    write_mask01(tmp_path / "holes" / "v.png", hole)
    write_mask01(tmp_path / "masks" / "v.png", mask)
    write_png(tmp_path / "truth" / "v.png", truth)
    truth = np.round(truth * 255) / 255  # as read back from the PNG
    deleted = truth.copy()
    deleted[mask] += 0.1  # every mask pixel off by 0.1: 20 dB
    ceiling = bench.oracle_holes_psnr({"v": deleted}, tmp_path, tmp_path / "masks", tmp_path / "truth")
    # half the mask pixels are fixed: MSE 0.01 -> 0.005, i.e. +3.01 dB
    assert ceiling == pytest.approx(10 * np.log10(1 / 0.005), abs=0.05)
    # the split of the mask every method is scored on: its holes and the rest, pooled
    fixed = np.where(hole[..., None], truth + 0.2, deleted)  # holes off by 0.2 (~14 dB), the rest by 0.1
    split = bench.split_psnr({"v": fixed}, tmp_path, tmp_path / "truth")
    assert split["psnr_unseen"] == pytest.approx(10 * np.log10(1 / 0.04), abs=0.05)
    assert split["psnr_seen"] == pytest.approx(20.0, abs=0.05)
    scene = {"scene": "lund", "rows": [_row(m, 20.0) for m in ("ours", "delete-only", "fsr-refit", "no-sbm", "no-rpr")],
             "wall_seconds": 1.0, "mask_psnr_holes_oracle": 23.0}
    assert "23.00 dB" in bench.format_removal_table(scene)
    summary, checks = bench.summarise({"lund": scene})
    assert summary["lund_inserted_mask_psnr_holes_oracle"] == 23.0
    assert any("+3.00 dB over delete-only" in c and "+3.00 dB over no-sbm" in c for c in checks)
    assert not any("ours' split of the mask" in c for c in checks)  # rows without the split: no line
    for i, row in enumerate(scene["rows"]):
        row.update(psnr_unseen=13.0 + i, psnr_seen=15.0 - i)
    summary, checks = bench.summarise({"lund": dict(scene, hole_fraction_of_mask=0.83)})
    assert summary["lund_inserted_unseen_psnr_fsr_refit"] == 15.0
    assert summary["lund_inserted_seen_psnr_fsr_refit"] == 13.0
    assert any("holes (83 % of it" in c and "ours 13.00" in c and "fsr-refit 15.00" in c and "fsr-refit 13.00" in c
               for c in checks)


def test_blurred_truth_holes_psnr_falls_with_the_blur_and_names_the_blur_a_target_needs(bench, tmp_path):
    """Ours' holes take the truth blurred by each sigma: a flat truth stays exact, a textured one loses more
    with a wider blur; the [INFO] line says which blur a +1 dB target over the baselines asks for."""
    from sgpor_pipeline.imageio import write_mask01, write_png

    rng = np.random.default_rng(0)
    truth = rng.uniform(0.2, 0.8, (32, 32, 3)).astype(np.float32)
    mask = np.zeros((32, 32), bool)
    mask[4:28, 4:28] = True
    hole = np.zeros((32, 32), bool)
    hole[10:22, 10:22] = True
    for sub in ("holes", "masks", "truth"):
        (tmp_path / sub).mkdir()
    write_mask01(tmp_path / "holes" / "v.png", hole)
    write_mask01(tmp_path / "masks" / "v.png", mask)
    write_png(tmp_path / "truth" / "v.png", truth)
    truth = np.round(truth * 255) / 255
    final = truth.copy()
    final[mask & ~hole] += 0.05  # the rest of the mask keeps its error (26 dB there)
    got = bench.blurred_truth_holes_psnr({"v": final}, tmp_path, tmp_path / "masks", tmp_path / "truth")
    assert list(got) == ["1", "2", "3", "5"]
    vals = list(got.values())
    assert all(a > b for a, b in zip(vals, vals[1:]))  # a wider blur is further from the truth
    assert vals[0] < 10 * np.log10(1 / (0.05 ** 2 * (mask & ~hole).sum() / mask.sum()))  # below exact holes
    flat = np.full_like(truth, 0.5)
    write_png(tmp_path / "truth" / "v.png", flat)
    got_flat = bench.blurred_truth_holes_psnr({"v": np.where(hole[..., None], 0.0, flat)}, tmp_path,
                                              tmp_path / "masks", tmp_path / "truth")
    assert all(v == bench.PSNR_CAP for v in got_flat.values())  # nothing to lose: exact everywhere
    # the [INFO] line interpolates the blur at which ours would beat the best baseline (not no-rpr) by 1 dB
    rows = [_row(m, p) for m, p in (("ours", 24.0), ("delete-only", 22.0), ("fsr-refit", 20.0), ("no-sbm", 24.5),
                                    ("no-rpr", 24.0))]
    scene = {"scene": "synthetic", "rows": rows, "wall_seconds": 1.0, "demo_seconds": 100.0,
             "mask_psnr_holes_blurred_truth": {"1": 28.0, "2": 26.0, "3": 25.0, "5": 24.0}}
    summary, checks = bench.summarise({"synthetic": scene})
    assert summary["synthetic_mask_psnr_holes_blurred_truth"]["2"] == 26.0
    line = next(c for c in checks if "truth blurred by sigma" in c)
    assert "needs 25.50" in line and "delete-only, fsr-refit, no-sbm needs" in line
    assert "blurred by 2.4 px" in line  # 25.5 lies halfway between 2 px (26) and 3 px (25) on a log scale
    scene["mask_psnr_holes_blurred_truth"] = {"1": 25.0, "2": 24.0}
    line = next(c for c in bench.summarise({"synthetic": scene})[1] if "truth blurred by sigma" in c)
    assert "closer to the truth than the truth blurred by 1 px" in line


def test_detail_ratio_is_one_for_the_truth_and_lower_for_a_blur(bench, tmp_path):
    import cv2
    import skimage.data

    from sgpor_pipeline.imageio import write_mask01, write_png

    truth = cv2.resize(skimage.data.astronaut(), (96, 80)).astype(np.float32) / 255.0
    (tmp_path / "truth").mkdir()
    (tmp_path / "masks").mkdir()
    write_png(tmp_path / "truth" / "v.png", truth)
    mask = np.zeros((80, 96), bool)
    mask[20:60, 30:70] = True
    write_mask01(tmp_path / "masks" / "v.png", mask)
    same = bench.detail_ratio({"v": truth}, tmp_path / "masks", tmp_path / "truth")
    blurred = bench.detail_ratio({"v": cv2.GaussianBlur(truth, (9, 9), 3)}, tmp_path / "masks", tmp_path / "truth")
    assert same == pytest.approx(1.0, abs=0.01)  # (the truth goes through an 8-bit PNG)
    assert blurred < 0.6


def test_speed_error_plot(bench, tmp_path):
    rows = [_row(m, 25.0 - i) for i, m in enumerate(["ours", "delete-only", "fsr-refit"])]
    results = {"synthetic": {"scene": "synthetic", "rows": rows, "mask_psnr_holes_oracle": 26.0},
               "lund": {"scene": "lund", "skipped": "x"}}
    path = bench.speed_error_plot(results, tmp_path / "p.png")
    from sgpor_pipeline.imageio import read_image

    assert path is not None and read_image(path).shape[1] == 550  # one 5.5-inch panel at 100 dpi
    assert bench.speed_error_plot({"lund": {"scene": "lund", "skipped": "x"}}, tmp_path / "q.png") is None


def test_novel_split_and_scene(bench, tmp_path):
    """Protocol (d): a quarter of the views is held out; their files are withheld, their cameras kept
    as novel cameras, and the split is stable and resumable."""
    from sgpor_pipeline.imageio import write_mask01, write_png
    from sgpor_pipeline.scene import Camera, load_cameras, save_cameras

    names = [f"v{i:02d}" for i in range(10)]
    train, test = bench.novel_split(list(reversed(names)))
    assert test == ["v02", "v06"] and len(train) == 8 and not set(train) & set(test)
    assert bench.novel_split(names, every=1) == (names, [])  # (every view held out would leave none to train)
    scene = tmp_path / "scene"
    for sub in ("images", "masks", "groundtruth"):
        (scene / sub).mkdir(parents=True)
    cams = []
    for n in names:
        write_png(scene / "images" / f"{n}.png", np.zeros((6, 8, 3), np.float32))
        write_png(scene / "groundtruth" / f"{n}.png", np.zeros((6, 8, 3), np.float32))
        write_mask01(scene / "masks" / f"{n}.png", np.ones((6, 8), bool))
        cams.append(Camera(n, 8, 6, np.diag([5.0, 5.0, 1.0]), np.eye(4), image=n))
    save_cameras(scene / "cameras.json", cams)
    out = tmp_path / "novel"
    assert bench.make_novel_scene(scene, out) == (train, test)
    for sub in ("images", "masks", "groundtruth"):
        assert sorted(p.stem for p in (out / sub).iterdir()) == train
    loaded = load_cameras(out / "cameras.json")
    assert [c.image for c in loaded] == train + [None, None]
    assert [c.name for c in loaded if c.image is None] == ["test_v02", "test_v06"]
    stamp = (out / "stamp.json").stat().st_mtime_ns
    assert bench.make_novel_scene(scene, out) == (train, test)  # unchanged input: nothing rewritten
    assert (out / "stamp.json").stat().st_mtime_ns == stamp


def test_novel_table_and_summary(bench):
    methods = ["ours", "delete-only", "fsr-refit", "no-sbm", "no-rpr"]
    scene = {"scene": "lund", "rows": [_row(m, 20.0) for m in methods], "wall_seconds": 1.0}
    scene["novel"] = {"scene": "lund", "test_views": ["03", "07"], "train_views": 6, "wall_seconds": 2.0,
                      "rows": [dict(_row(m, 18.0 - i), feat_mask=0.1 * (i + 1), wall_seconds=3.0)
                               for i, m in enumerate(methods)]}
    table = bench.format_novel_table(scene["novel"])
    assert "03, 07" in table and "trained on 6" in table and all(m in table for m in methods)
    summary, checks = bench.summarise({"lund": scene})
    assert summary["lund_inserted_novel_mask_psnr"] == 18.0
    assert summary["lund_inserted_novel_mask_psnr_fsr_refit"] == 16.0
    assert summary["lund_inserted_novel_mask_feat_no_rpr"] == pytest.approx(0.5)
    assert any("novel views" in c and "fsr-refit +2.00 dB" in c for c in checks)


def test_method_subset_runs_ours_first_and_leaves_the_target_unjudged(bench, tmp_path, monkeypatch):
    """--methods: ours always runs (first); with a baseline missing the target is neither passed nor failed,
    and an ablation that did not run is not reported as helping or not."""
    assert [v[0] for v in bench.selected_variants(["fsr-refit"])] == ["ours", "fsr-refit"]
    assert [v[0] for v in bench.selected_variants(None)] == [v[0] for v in bench.VARIANTS if v[0] != "truth-fill"]
    assert [v[0] for v in bench.selected_variants(["truth-fill"])] == ["ours", "truth-fill"]  # only when named
    with pytest.raises(ValueError, match="nope"):
        bench.selected_variants(["nope"])
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    with pytest.raises(SystemExit):
        bench.main(["--methods", "nope"])
    assert not any(tmp_path.iterdir()), "a rejected call leaves no output folder behind"
    scene = {"scene": "statue-box", "rows": [_row(m, v) for m, v in
                                             (("ours", 25.0), ("delete-only", 20.0), ("fsr-refit", 22.0))],
             "wall_seconds": 1.0}
    summary, checks = bench.summarise({"statue-box": scene})
    assert summary["statue_inserted_target_beats_baselines"] is None
    assert summary["statue_inserted_mask_psnr_fsr_refit"] == 22.0
    line = next(c for c in checks if "beats every baseline" in c)
    assert line.startswith("[----]") and "not judged: no-sbm, no-rpr" in line
    assert not any("helps" in c for c in checks)


def test_plane_fill_psnr_scores_the_plane_textures_fill_against_the_rectified_truth(bench, tmp_path):
    """The inpaint stage's plane texture (the floor under the object, filled once) against the object-free
    truth warped onto it: its own fill scores well above a black fill, and it is absent (None) without
    the texture's hole file or without a texture; the summary and an [INFO] line carry it."""
    from sgpor_pipeline.dag import StageContext
    from sgpor_pipeline.imageio import read_image, read_mask, write_png
    from sgpor_pipeline.removal.multiview import write_remove_fixture
    from sgpor_pipeline.stages.inpaint import InpaintParams, InpaintStage
    from sgpor_pipeline.synthetic import SceneParams, generate_scene

    scene = generate_scene(SceneParams(seed=0, rig="forward", n_views=4, width=160, height=120))
    remove = write_remove_fixture(scene, tmp_path / "remove", holes="mask")
    (tmp_path / "truth").mkdir()
    for cam, img in zip(scene.cameras, scene.images_gt):
        write_png(tmp_path / "truth" / f"{cam.name}.png", img)
    ctx = StageContext.standalone(tmp_path / "run", "inpaint", InpaintParams(thick_reference="plane"),
                                  {"remove": remove})
    InpaintStage().run(ctx)
    plane = ctx.out_dir / "plane"
    own = bench.plane_fill_psnr(ctx.out_dir, remove, tmp_path / "truth")
    assert own is not None and own > 18.0, own
    hole = read_mask(plane / "hole.png")
    filled = read_image(plane / "filled.png")
    write_png(plane / "filled.png", np.where(hole[..., None], 0.0, filled))
    black = bench.plane_fill_psnr(ctx.out_dir, remove, tmp_path / "truth")
    assert black < own - 5.0, (black, own)
    (plane / "hole.png").unlink()
    assert bench.plane_fill_psnr(ctx.out_dir, remove, tmp_path / "truth") is None
    assert bench.plane_fill_psnr(tmp_path / "nowhere", remove, tmp_path / "truth") is None
    row = dict(_row("ours", 25.0), plane_fill_psnr=own)
    summary, checks = bench.summarise({"synthetic": {"scene": "synthetic", "rows": [row], "wall_seconds": 1.0,
                                                     "demo_seconds": 100.0}})
    assert summary["synthetic_plane_fill_psnr"] == own
    assert any("plane_fill_psnr" in c and f"ours {own:.2f}" in c for c in checks)


def test_the_inserted_one_mask_scene_gives_the_largest_whole_mask(bench, tmp_path):
    """lund-1mask shares lund's folders and is given the mask of the view where the object is largest
    without touching the frame (a user paints it large and whole); if every mask touches it, the largest."""
    from sgpor_pipeline.imageio import write_mask01

    for scene, base in (("lund-1mask", "lund"), ("statue-box-1mask", "statue-box")):
        assert bench.INSERTED[scene] == bench.INSERTED[base] and bench.INSERTED_ONE_MASK[scene] == base
        assert scene in bench.GT_SCENES and bench.PREFIX[scene] == bench.PREFIX[base] + "_1mask"
    masks = np.zeros((3, 20, 30), bool)
    masks[0, 5:9, 5:9] = True  # small, whole
    masks[1, 4:14, 6:16] = True  # larger, whole
    masks[2, 0:18, 0:25] = True  # largest, at the border
    for name, m in zip(("01", "02", "03"), masks):
        write_mask01(tmp_path / f"{name}.png", m)
    assert bench.one_mask_view(tmp_path) == "02"
    write_mask01(tmp_path / "02.png", np.roll(masks[1], 10, axis=0))  # now it touches the border
    assert bench.one_mask_view(tmp_path) == "01"
    masks[0, :, 0] = True
    write_mask01(tmp_path / "01.png", masks[0])
    assert bench.one_mask_view(tmp_path) == "03"  # every mask touches it


def test_truth_fill_puts_the_truth_in_the_hole_pixels_only(bench, tmp_path, monkeypatch):
    """The truth-fill variant (the re-fit's ceiling): the refine stage's images get the truth in their
    holes, the rest as refine left it; its cache keys are its own (another VERSION)."""
    from types import SimpleNamespace

    from sgpor_pipeline.dag import RunInputs
    from sgpor_pipeline.imageio import read_rgb8, write_png

    stages = bench.truth_fill_stages()
    cls = stages["refine"]
    base = cls.__mro__[1]
    assert cls.VERSION == base.VERSION + 1000 and bench.variant_stages("ours") is None
    rng = np.random.default_rng(0)
    fill = rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
    truth = rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
    hole = np.zeros((12, 16), bool)
    hole[3:7, 4:11] = True
    for sub in ("gt", "remove/holes", "out/images"):
        (tmp_path / sub).mkdir(parents=True)
    write_png(tmp_path / "gt" / "v0.png", truth)
    write_png(tmp_path / "remove" / "holes" / "v0.png", hole)
    linked = tmp_path / "other_entry.png"  # refine's image as a link into another cache entry
    write_png(linked, fill)

    def refine_run(self, ctx):  # the refine stage's own work (tested with it): its image for v0
        (ctx.out_dir / "images" / "v0.png").hardlink_to(linked)

    monkeypatch.setattr(base, "run", refine_run)
    ctx = SimpleNamespace(run_inputs=RunInputs(images=tmp_path, extra={"groundtruth": tmp_path / "gt"}),
                          inputs={"remove": tmp_path / "remove"}, out_dir=tmp_path / "out")
    cls().run(ctx)
    got = read_rgb8(tmp_path / "out" / "images" / "v0.png")
    assert np.array_equal(got[hole], truth[hole]) and np.array_equal(got[~hole], fill[~hole])
    assert np.array_equal(read_rgb8(linked), fill)  # the other entry's file is untouched
    rows = [_row(m, v) for m, v in (("ours", 16.0), ("delete-only", 14.8), ("fsr-refit", 16.05), ("no-sbm", 15.7),
                                     ("no-rpr", 16.0), ("truth-fill", 17.2))]
    summary, checks = bench.summarise({"lund": {"scene": "lund", "rows": rows, "wall_seconds": 1.0}})
    assert summary["lund_inserted_mask_psnr_truth_fill"] == 17.2
    line = next(c for c in checks if "re-fit's ceiling" in c)
    assert "gives 17.20 dB" in line and "+1.15 dB over the best baseline (fsr-refit)" in line
    assert "truth-fill" not in next(c for c in checks if "beats every baseline" in c)  # not a baseline
