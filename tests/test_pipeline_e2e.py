"""The whole pipeline on a small synthetic scene, as ``sgpor-pipeline demo`` runs it: every stage,
the evaluation against ground truth, the export folder, and a resumed run that is all cache hits."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from sgpor_pipeline.dag import RunInputs, discover_stages
from sgpor_pipeline.imageio import read_image, read_mask
from sgpor_pipeline.metrics import psnr
from sgpor_pipeline.runner import pipeline_status, run_pipeline
from sgpor_pipeline.synthetic import SceneParams, generate_scene, save_scene

STAGES = ["ingest", "sfm", "fit", "masks", "remove", "inpaint", "refine", "finetune", "evaluate", "export"]
FAST = ["fit.iterations=300", "fit.eval_every=0", "finetune.iterations=60", "export.mesh_target_faces=5000"]


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("e2e")
    scene = generate_scene(SceneParams(seed=1, rig="forward", n_views=10, width=96, height=72))
    folder = save_scene(scene, root / "scene")
    inputs = RunInputs(images=folder / "images", masks=folder / "masks", cameras=folder / "cameras.json",
                       extra={"groundtruth": folder / "groundtruth"})
    out = root / "out"
    result = run_pipeline(out, inputs, overrides=FAST)
    return out, inputs, result


@pytest.mark.slow
def test_every_stage_runs_and_exports(finished_run):
    out, _, result = finished_run
    assert set(STAGES) <= set(discover_stages())
    assert [s for s in STAGES if s in result.ran] == STAGES
    export = out / "export"
    for name in ("scene.ply", "scene.splat", "scene.spz", "scene.glb", "mesh.glb", "scene.usda", "scene.usdz",
                 "report.html"):
        assert (export / name).is_file(), name
    assert len(list((export / "renders").glob("*.png"))) == 10
    metrics = json.loads((result.path("evaluate") / "metrics.json").read_text())
    assert metrics["views"] == 10
    for name in ("final", "delete_only", "inpainted_2d"):
        for key in ("psnr_mask", "psnr_bbox", "psnr_full", "ssim_mask"):
            assert metrics["means"][name][key] == metrics["means"][name][key]  # not NaN
    # Plumbing, not fit quality (tests/test_fit.py bounds that): a 300-iteration fit is blurry, yet
    # its object-free renders must beat the best constant image (each view's mean true colour), and
    # the finetune must not make the scene worse than it was right after deletion.
    truth = [read_image(p) for p in sorted((out.parent / "scene" / "groundtruth").glob("*.png"))]
    constant = np.mean([psnr(np.broadcast_to(t.mean(axis=(0, 1)), t.shape), t) for t in truth])
    final, deleted = metrics["means"]["final"], metrics["means"]["delete_only"]
    assert final["psnr_full"] > constant, (final, constant)
    assert final["psnr_full"] > deleted["psnr_full"] - 0.5, (final, deleted)
    # by default the fit trains on every photo (the removal re-fits and scores every view)
    fit = json.loads((result.path("fit") / "fit.json").read_text())
    assert fit["heldout_views"] == [] and len(fit["train_views"]) == 10 and fit["heldout_is_training"]
    # the inpainter completed the photos (context = photos), not the blurry renders, around the holes
    name = sorted(p.stem for p in (result.path("remove") / "context").glob("*.png"))[0]
    photo = read_image(result.path("sfm") / "images" / f"{name}.png")
    mask = read_mask(result.path("remove") / "masks" / f"{name}.png")
    far = cv2.dilate(mask.astype(np.uint8), np.ones((7, 7), np.uint8)) == 0  # beyond the 2 px context margin
    inpainted = read_image(result.path("inpaint") / "images" / f"{name}.png")
    assert far.any() and np.array_equal(inpainted[far], photo[far])
    # inside the grown mask the context is the render divided by its opacity: never darker than the
    # render, and brighter where the deletion left the background partly transparent
    brighter = 0
    for rp in sorted((result.path("remove") / "renders").glob("*.png")):
        render, context = read_image(rp), read_image(result.path("remove") / "context" / rp.name)
        band = ~(cv2.dilate(read_mask(result.path("remove") / "masks" / rp.name).astype(np.uint8),
                            np.ones((5, 5), np.uint8)) == 0)
        assert (context[band] >= render[band] - 1.5 / 255).all(), rp.name
        brighter += int((context[band] > render[band] + 2.5 / 255).any(axis=1).sum())
    assert brighter > 0
    seconds = {s: json.loads((result.path(s) / "manifest.json").read_text())["seconds"] for s in STAGES}
    print("seconds per stage:", {k: round(v, 1) for k, v in seconds.items()})


@pytest.mark.slow
def test_resumed_run_is_all_hits_and_status_lists_every_stage(finished_run):
    out, inputs, _ = finished_run
    again = run_pipeline(out, inputs, overrides=FAST)
    assert again.ran == [] and set(again.hits) == set(STAGES)
    states = {r.name: r.state for r in pipeline_status(out)}
    assert all(states[s] == "hit" for s in STAGES), states


@pytest.mark.slow
def test_a_full_disk_is_an_error_to_act_on_and_keeps_the_finished_stages(finished_run, tmp_path, monkeypatch):
    """Too little free disk for the remove stage's maps: refused before it renders anything. The disk
    filling up while a stage writes: one error naming the run folder and the fix, no build folder left
    behind, and the same command then resumes from the finished stages."""
    import errno
    import shutil
    from collections import namedtuple

    from sgpor_pipeline import scratch
    from sgpor_pipeline.errors import PipelineError

    out, inputs, _ = finished_run
    run = tmp_path / "out"
    shutil.copytree(out, run)
    usage = namedtuple("usage", "total used free")
    with monkeypatch.context() as m:
        m.setattr(scratch.shutil, "disk_usage", lambda path: usage(10**9, 10**9 - 10**5, 10**5))
        with pytest.raises(PipelineError, match="need about .* GB of free disk here, and 0.0 GB is free") as e:
            run_pipeline(run, inputs, overrides=FAST, until="remove", force=["remove"])
    assert e.value.path == str(run / "cache" / "remove") and "--out on a larger disk" in str(e.value)

    def full(self, array):
        raise OSError(errno.ENOSPC, "No space left on device", str(self.folder / "0.npy"))

    with monkeypatch.context() as m:
        m.setattr(scratch.ArraysOnDisk, "append", full)
        with pytest.raises(PipelineError, match="the disk filled up while the remove stage wrote") as e:
            run_pipeline(run, inputs, overrides=FAST, until="remove", force=["remove"])
    assert e.value.path == str(run) and "run the same command" in str(e.value)
    assert isinstance(e.value.__cause__, OSError)
    assert not list((run / "cache" / "remove").glob(".tmp-*"))  # nothing of the failed build is left
    again = run_pipeline(run, inputs, overrides=FAST, until="remove")
    assert again.ran == [] and set(again.hits) == {"ingest", "sfm", "fit", "masks", "remove"}


@pytest.mark.slow
def test_with_every_mask_given_the_fit_leaves_the_object_out(finished_run, tmp_path):
    """Every view has a mask here, so ``fit.object_masks=auto`` (the default) fits without the masked
    pixels: the masks stage selects no Gaussian and keeps every given mask, the remove stage deletes
    nothing by its object score (a Gaussian mostly inside the masks is background other views saw
    behind the object), and the holes are what no view saw. With ``fit.object_masks=fit`` the object
    is fitted, selected and deleted."""
    out, inputs, result = finished_run
    assert json.loads((result.path("fit") / "fit.json").read_text())["object_masks"] == "ignore"
    masks_dir, remove_dir = result.path("masks"), result.path("remove")
    info = json.loads((masks_dir / "masks.json").read_text())
    assert info["fit_object_masks"] == "ignore" and info["object_gaussians"] == 0
    assert np.load(masks_dir / "object_ids.npy").size == 0
    for name in info["views"]:
        given = read_mask(inputs.masks / f"{name}.png")
        assert np.array_equal(read_mask(masks_dir / "masks" / f"{name}.png"), given), name
    stats = json.loads((remove_dir / "remove.json").read_text())
    assert stats["from_masks_stage"] == 0 and stats["by_score"] == 0 and stats["object_fitted"] is False
    assert 0 < stats["hole_pixels"] < stats["mask_pixels"]  # some of the mask is background other views saw
    export = out / "export"
    assert (export / "scene.ply").is_file() and not (export / "object").exists()  # no object modelled, no asset
    fitted = run_pipeline(tmp_path / "out", inputs, overrides=[*FAST, "fit.object_masks=fit"], until="remove")
    assert json.loads((fitted.path("fit") / "fit.json").read_text())["object_masks"] == "fit"
    selected = json.loads((fitted.path("masks") / "masks.json").read_text())["object_gaussians"]
    deleted = json.loads((fitted.path("remove") / "remove.json").read_text())
    assert selected > 0 and deleted["from_masks_stage"] == selected
    assert deleted["deleted"] > 10 * max(stats["deleted"], 1)


def test_evaluate_scores_over_the_input_masks_when_asked(finished_run, tmp_path):
    """``evaluate.score_masks=input``: the scores cover the masks the run was given (the truth in a
    benchmark that gives the pipeline only some of them), not the masks stage's. Emulated: the masks
    stage's masks cut to their left half, as a propagation that missed part of the object."""
    import shutil

    from sgpor_pipeline.dag import StageContext
    from sgpor_pipeline.errors import PipelineError
    from sgpor_pipeline.imageio import write_mask01
    from sgpor_pipeline.stages.evaluate import EvaluateParams, EvaluateStage

    _, inputs, result = finished_run
    stage_inputs = {s: result.path(s) for s in EvaluateStage.inputs}
    cut = tmp_path / "masks"
    shutil.copytree(result.path("masks"), cut)
    for path in (cut / "masks").glob("*.png"):
        mask = read_mask(path)
        mask[:, mask.shape[1] // 2:] = False
        write_mask01(path, mask)

    def evaluate(name: str, masks, **params) -> dict:
        ctx = StageContext.standalone(tmp_path / name, "evaluate", EvaluateParams(features="off", **params),
                                      {**stage_inputs, "masks": masks})
        ctx.run_inputs = inputs
        EvaluateStage().run(ctx)
        return json.loads((ctx.out_dir / "metrics.json").read_text())["means"]["final"]

    full = evaluate("full", result.path("masks"))
    half = evaluate("half", cut)
    truth = evaluate("input", cut, score_masks="input")
    assert truth == full and half["psnr_bbox"] != full["psnr_bbox"]
    with pytest.raises(PipelineError, match="score_masks"):
        evaluate("bad", cut, score_masks="propagated")


def test_evaluate_maps_ground_truth_given_at_another_size(finished_run, tmp_path):
    """Ground truth at the photos' source size (here a 2x copy) is mapped as the photos were (ingest's
    resize, sfm's undistortion: ``raw_cameras.json``); another aspect ratio is an error naming the file."""
    from sgpor_pipeline.dag import StageContext
    from sgpor_pipeline.errors import PipelineError
    from sgpor_pipeline.stages.evaluate import EvaluateParams, EvaluateStage

    _, inputs, result = finished_run
    stage_inputs = {s: result.path(s) for s in EvaluateStage.inputs}

    def evaluate(name: str, truth_dir) -> dict:
        ctx = StageContext.standalone(tmp_path / name, "evaluate", EvaluateParams(features="off"), stage_inputs)
        ctx.run_inputs = RunInputs(images=inputs.images, masks=inputs.masks, cameras=inputs.cameras,
                                   extra={"groundtruth": truth_dir})
        EvaluateStage().run(ctx)
        return json.loads((ctx.out_dir / "metrics.json").read_text())["means"]["final"]

    given = inputs.extra["groundtruth"]
    doubled, cropped = tmp_path / "doubled", tmp_path / "cropped"
    doubled.mkdir()
    cropped.mkdir()
    for path in sorted(given.glob("*.png")):
        img = cv2.imread(str(path))
        h, w = img.shape[:2]
        # each pixel as 2x2: ingest's area-averaging resize gives the original back exactly
        cv2.imwrite(str(doubled / path.name), cv2.resize(img, (2 * w, 2 * h), interpolation=cv2.INTER_NEAREST))
        cv2.imwrite(str(cropped / path.name), img[:, : w // 2])
    same = evaluate("same", given)
    scaled = evaluate("doubled", doubled)
    assert scaled == same
    with pytest.raises(PipelineError, match="aspect ratio") as err:
        evaluate("cropped", cropped)
    assert "cropped" in str(err.value)


@pytest.mark.slow
def test_under_object_is_recorded_and_the_stages_after_it_run(finished_run):
    """``remove.under_object``: the remove stage says in remove.json what it made holes of (or why
    nothing), writes the object's silhouette when it found one, and the stages after it run on that."""
    out, inputs, _ = finished_run
    result = run_pipeline(out, inputs, overrides=[*FAST, "remove.under_object=true"], until="inpaint")
    remove_dir = result.path("remove")
    info = json.loads((remove_dir / "remove.json").read_text())["under_object"]
    if info["pixels"]:
        assert (remove_dir / "under_object" / "silhouette.png").is_file()
        assert (remove_dir / "under_object" / "camera.json").is_file()
    else:
        assert info["reason"] and not (remove_dir / "under_object").exists()
    assert (result.path("inpaint") / "inpaint.json").is_file()


@pytest.mark.slow
def test_one_given_mask_propagates_all_round_a_box(tmp_path):
    """From ONE given mask of a box photographed all round (the inward rig), the masks stage's masks
    match the true ones in every other view, the far side included, which the given view does not
    see. (This short fit covers the box densely enough for growing alone; the benchmark's longer fit
    did not, which ``masks.hidden`` mends: tests/test_removal.py shows that part.)"""
    import shutil

    # (256 px: at 128 px the inward views match no SIFT pair and the fit has no points to start from)
    scene = generate_scene(SceneParams(seed=0, object_kind="box", n_views=12, width=256, height=192))
    folder = save_scene(scene, tmp_path / "scene")
    one = tmp_path / "one"
    one.mkdir()
    shutil.copy(folder / "masks" / "view_000.png", one / "view_000.png")
    inputs = RunInputs(images=folder / "images", masks=one, cameras=folder / "cameras.json")
    result = run_pipeline(tmp_path / "out", inputs, until="masks", overrides=[*FAST, "fit.object_masks=fit"])
    masks_dir = result.path("masks")
    assert json.loads((masks_dir / "masks.json").read_text())["given"] == ["view_000"]
    ious = []
    for i, cam in enumerate(scene.cameras[1:], start=1):
        mine, truth = read_mask(masks_dir / "masks" / f"{cam.name}.png"), scene.masks[i]
        ious.append((mine & truth).sum() / (mine | truth).sum())
    # (the worst view moves between runs of the whole suite: view_004 0.935, and once 0.847 with the mean
    # 0.948; the SfM or fit upstream is not bitwise repeatable there)
    assert np.mean(ious) > 0.9 and min(ious) > 0.8, ious
    # the remove stage grows the propagated masks (remove.propagated_margin), never the given one
    result = run_pipeline(tmp_path / "out", inputs, until="remove", overrides=[*FAST, "fit.object_masks=fit"])
    remove_dir = result.path("remove")
    stats = json.loads((remove_dir / "remove.json").read_text())
    grown = stats["propagated_masks_grown_px"]
    assert sorted(grown) == [c.name for c in scene.cameras[1:]]
    # (remove.delete_masks=split) the Gaussians only the grown masks delete went to the nearer side
    by_grown = sum(stats[k] for k in ("from_masks_stage", "by_score", "floaters", "hull_centres"))
    assert 0 <= stats["margin_kept"] <= stats["margin"] and stats["deleted"] + stats["margin_kept"] >= by_grown
    for cam in scene.cameras[1:]:  # 0.05 x the square root of the mask's area, px
        area = read_mask(masks_dir / "masks" / f"{cam.name}.png").sum()
        assert grown[cam.name] == round(0.05 * np.sqrt(area)) > 0
    for cam in scene.cameras:
        before = read_mask(masks_dir / "masks" / f"{cam.name}.png")
        after = read_mask(remove_dir / "masks" / f"{cam.name}.png")
        if cam.name == "view_000":
            assert np.array_equal(before, after)
        else:
            assert (after & before).sum() == before.sum() and after.sum() > before.sum()
