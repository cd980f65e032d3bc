"""evaluate (optional): object-free renders against ground truth, with seconds per stage beside them.

Runs when the run has ground truth (``RunInputs.extra["groundtruth"]``: a folder of object-free
photos named like the inputs; ``sgpor-pipeline demo`` provides one). Metrics are PSNR and SSIM in
the three definitions of DESIGN.md section 8 (``mask``, ``bbox``, ``full``), over the object mask
of each view, for the final scene (finetune) and, in the same run, for delete-only (the render
after deletion, holes left empty) and the inpainted images before re-fitting. Seconds per stage are
each stage's cost from scratch (its run plus what the per-item results it reused once cost).

Out: ``metrics.json`` (means, per view, seconds per stage), ``metrics.md`` (a table).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from sgpor_pipeline.cache import read_manifest
from sgpor_pipeline.dag import RunInputs, Stage, StageContext
from sgpor_pipeline.errors import PipelineError
from sgpor_pipeline.imageio import IMAGE_EXTENSIONS, read_image, read_mask
from sgpor_pipeline.metrics import mean_scores, score_image
from sgpor_pipeline.scene import load_cameras

TIMED_STAGES = ("ingest", "sfm", "fit", "masks", "remove", "inpaint", "refine", "finetune")


def find_truth(folder: Path, view: str) -> Path | None:
    for ext in IMAGE_EXTENSIONS:
        for candidate in (folder / f"{view}{ext}", folder / f"{view}{ext.upper()}"):
            if candidate.is_file():
                return candidate
    return None


class EvaluateStage(Stage):
    name = "evaluate"
    VERSION = 2  # 2: seconds from scratch
    inputs = ("ingest", "sfm", "fit", "masks", "remove", "inpaint", "refine", "finetune")
    raw_inputs = ("groundtruth",)
    optional = True

    @classmethod
    def wanted(cls, params: Any, run_inputs: RunInputs) -> bool:
        return run_inputs.get("groundtruth") is not None

    def run(self, ctx: StageContext) -> None:
        truth_dir = ctx.run_inputs.get("groundtruth")
        if truth_dir is None or not Path(truth_dir).is_dir():
            raise PipelineError("no ground-truth folder for evaluation", path=truth_dir,
                                fix="give object-free photos named like the inputs, or skip the evaluate stage")
        remove_dir = ctx.inputs["remove"]
        cameras = [c for c in load_cameras(remove_dir / "cameras.json") if c.image is not None]
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
            mask = read_mask(ctx.inputs["masks"] / "masks" / f"{cam.image}.png")
            if truth.shape[:2] != mask.shape:
                raise PipelineError(f"ground truth is {truth.shape[1]}x{truth.shape[0]}, the view is "
                                    f"{mask.shape[1]}x{mask.shape[0]}", path=truth_path,
                                    fix="give ground truth at the input photos' size (undistorted)")
            per_view[cam.image] = {}
            for name, folder in sources.items():
                s = score_image(read_image(folder / f"{cam.image}.png"), truth, mask)
                scores[name].append(s)
                per_view[cam.image][name] = s.to_dict()
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
        result = {"views": len(per_view), "means": means, "seconds": seconds,
                  "total_seconds": round(sum(seconds.values()), 3), "per_view": per_view}
        (ctx.out_dir / "metrics.json").write_text(json.dumps(result, indent=1))
        lines = ["| result | PSNR mask | SSIM mask | PSNR bbox | SSIM bbox | PSNR full | SSIM full |",
                 "|---|---|---|---|---|---|---|"]
        for name, m in means.items():
            lines.append(f"| {name} | {m['psnr_mask']:.2f} | {m['ssim_mask']:.4f} | {m['psnr_bbox']:.2f} | "
                         f"{m['ssim_bbox']:.4f} | {m['psnr_full']:.2f} | {m['ssim_full']:.4f} |")
        lines.append("")
        lines.append("seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in seconds.items()))
        (ctx.out_dir / "metrics.md").write_text("\n".join(lines) + "\n")
        ctx.notes.update(views=len(per_view), final_psnr_mask=means["final"]["psnr_mask"],
                         delete_only_psnr_mask=means["delete_only"]["psnr_mask"])
        ctx.log.info("evaluate: " + " | ".join(f"{k} PSNR(mask) {v['psnr_mask']:.2f}" for k, v in means.items()))
