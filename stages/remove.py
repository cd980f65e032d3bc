"""remove: delete the object's Gaussians, find the truly unseen holes, seed the holes.

Out (the contract the inpaint and refine stages read):

- ``cameras.json``: the training cameras (PINHOLE; novel cameras dropped),
- ``renders/<view>.png``: RGB render of the scene after deletion (before any new Gaussian),
- ``context/<view>.png``: what the inpainter completes and takes source blocks from (``context``):
  the photo outside the object mask dilated by ``context_margin`` px and the render inside, or the
  render alone; the render divided by its opacity (the deletion left the background beside the holes
  partly transparent: over black it rendered darker than the surface it shows),
- ``holes/<view>.png``: 0/1, object pixels the remaining background does not cover (opacity below
  ``hole_alpha``; with ``min_views`` > 0 also those fewer other views observed, and, with
  ``max_disagreement``, those whose render differs from what the views that observed them photographed
  there), and their rim: the pixels within ``context_margin`` px outside the mask whose opacity is
  below ``rim_alpha``: what to inpaint,
- ``masks/<view>.png``: 0/1 object mask of every view (from the masks stage; the ones it propagated
  grown by ``propagated_margin`` x the square root of their area); holes are inside it but for their rim,
- ``depth/<view>.npy``: float32 z-depth of the background with the hole completed from its surroundings
  and, with ``consistent_depth``, from the hole surfaces of the views with smaller holes (one surface
  for all views: :func:`~sgpor_pipeline.removal.holes.complete_depths_jointly`),
- ``gaussians.ply``: the background Gaussians followed by the new hole Gaussians,
  ``seed_ids.npy``: indices of the new ones; ``object.ply``: the deleted Gaussians (a reusable asset
  when the fit modelled the object: ``object_fitted`` in remove.json),
- ``under_object/``, with ``under_object`` when it found the plane under the object: ``silhouette.png``,
  the object seen straight down that plane's normal by the camera in ``camera.json``,
- ``remove.json``: counts (``propagated_masks_grown_px``: the px each propagated mask was grown by;
  ``hull_centres``: Gaussians deleted because no view shows their centre outside its mask;
  ``disagreeing_pixels``: the mask pixels ``max_disagreement`` made holes; with
  ``under_object``, ``under_object``: the mask pixels it made holes, or why none) and per-view hole
  sizes (``hole_pixels_by_opacity``: before ``min_views``).

After a fit without the masked pixels (``fit.object_masks = "ignore"``) nothing is deleted by its object
score: a Gaussian mostly inside the masks is then background that other views saw behind the object.
The floaters and hull centres (unsupervised there) still go.
"""

from __future__ import annotations

import dataclasses
import functools
import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from sgpor_pipeline.dag import Stage, StageContext
from sgpor_pipeline.errors import PipelineError
from sgpor_pipeline.gaussians.model import GaussianModel
from sgpor_pipeline.gaussians.ply import read_ply, write_ply
from sgpor_pipeline.imageio import read_mask, read_rgb8, to_float32, write_mask01, write_png
from sgpor_pipeline.removal.holes import (
    RemoveParams,
    clamp_dc_colours,
    closer_to_core,
    complete_depth,
    complete_depths_jointly,
    concat_models,
    context_image,
    far_side_floor,
    hole_mask,
    initial_colour,
    median_spacing,
    object_depth,
    objects_to_delete,
    observing_views,
    render_background,
    seed_hole_gaussians,
    subset,
    unpremultiplied,
)
from sgpor_pipeline.removal.plane import under_object
from sgpor_pipeline.removal.selection import contribution_scores_of_sets
from sgpor_pipeline.scene import Camera, save_cameras
from sgpor_pipeline.scratch import ArraysOnDisk, Keeper, in_memory, on_disk, release, require_free_disk
from sgpor_pipeline.sfm import load_sfm
from sgpor_pipeline.stages.fit import fit_ignored_masks, run_cameras_file

DELETE_MASKS = ("grown", "as_given", "split")


@dataclass
class RemoveStageParams(RemoveParams):
    seed: int = 0
    # The masks the masks stage propagated (not the given ones) are grown before any use (deletion,
    # holes, context, the later stages) by this fraction of the square root of each one's area, in px
    # (rounded; 0 = off): a propagated mask that misses the object's edge by a pixel or two leaves that
    # edge in the photos around the hole, where it stays fitted and is copied into the fill. Given masks
    # are kept as drawn, and so are the masks stage's own outputs (its IoU). Relative to the object's
    # size, as the ring's cost is: the ring is inpainted, and around a small object it is a large share.
    # benchmarks/removal.py from one given mask (fit seed 0), ours mask PSNR / feat, off -> 0.05 [-> a fixed
    # 4 px]: synthetic-box-1mask 25.74 / 0.118 -> 27.22 / 0.074 [27.50 / 0.075] (3-4 px there; with every
    # mask given 27.88), synthetic-raised-cast-1mask 24.41 / 0.176 -> 24.67 / 0.114 [24.71 / 0.112],
    # lund-1mask 15.20 / 0.233 -> 15.21 / 0.233 [15.17 / 0.226] (1 px), statue-box from its first view's
    # mask 21.61 / 0.135 -> 21.42 / 0.121 [20.66 / 0.162] (2 px; a 33 px box), statue-box-1mask (the
    # largest whole mask given) 21.59 / 0.132 -> 21.38 / 0.121. The propagated masks missed 1.6 % of the
    # object's pixels on synthetic-box-1mask (up to 425 px a view, 1-7 px from the mask), 5.5 % on
    # statue-box. mip360 kitchen from one mask (13 px): the orange mat's fill keeps its straight edge and
    # the wood between the mats, without the dark smudges; two views' renders agree with their inpainted
    # images in the hole to 35.1 / 28.9 dB (33.8 / 24.1 before). mip360 room (4 px): its carpet fill
    # changes (a dark tongue and specks before, a dark blob and wood patches now): the plane fill there
    # is fragile to the hole's shape.
    propagated_margin: float = 0.05
    # Which masks decide the deletion (the object score, the visual hull's floaters, the hull centres;
    # the holes always use the grown masks). "split" (default): the Gaussians only the grown masks would
    # delete (the margin) go with the side they are nearer to in 3D (:func:`closer_to_core`), the
    # object's (deleted) or the background's (kept), so the floor around the object stays; "grown": all
    # of the margin deleted (before session 79); "as_given": the masks stage's masks, ungrown. Only runs
    # with propagated masks differ. Benchmark, one given mask, ours' mask PSNR grown / split / as_given:
    # synthetic-box 26.27 / 26.04 / 26.42, synthetic-raised-cast 24.64 / 25.14 / 25.27, lund + box 13.88
    # / 13.98 / 13.80, statue + box 21.96 / 21.89 / 22.02. mip360 kitchen from one mask: grown deleted
    # the mats' ring round the bulldozer (their weave and edges lost in the fill, the orange mat spilt
    # onto the wood); as_given kept the object's haze (a pale blob on the grey mat in every view); split
    # kept 7,309 of the 12,823 margin Gaussians and the mats' edges (benchmarks/removal_results.md).
    delete_masks: str = "split"


def mask_sources(masks_dir: Path) -> dict[str, str]:
    """Each view's mask source in the masks stage's ``masks.json`` ("given" or "propagated"), by view."""
    path = Path(masks_dir) / "masks.json"
    views = json.loads(path.read_text()).get("views", {}) if path.is_file() else {}
    return {name: str(info.get("source", "")) for name, info in views.items()}


def grown_propagated(masks: list[np.ndarray], names: list[str], sources: dict[str, str], margin: float
                     ) -> tuple[list[np.ndarray], dict[str, int]]:
    """``masks`` with the propagated ones grown by ``margin`` x the square root of their area (px,
    rounded; an ellipse), and the px each grown one was grown by (by view)."""
    out, grown = [], {}
    for m, name in zip(masks, names):
        px = int(round(margin * float(np.sqrt(m.sum())))) if sources.get(name) == "propagated" else 0
        if px > 0:
            kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * px + 1,) * 2)
            m = cv2.dilate(m.astype(np.uint8), kernel) > 0
            grown[name] = px
        out.append(m)
    return out, grown


def hole_floor(front: GaussianModel, cam: Camera, mask: np.ndarray, depth: np.ndarray, alpha: np.ndarray,
               p: RemoveParams) -> np.ndarray:
    """The least depth of a view's holes (0 = none): the deleted object's surface (``behind_object``)
    and the far side of a depth step across the mask (``far_side_ratio``)."""
    floor = (object_depth(front, cam, p.backend) if p.behind_object
             else np.zeros((cam.height, cam.width), np.float32))
    if p.far_side_ratio > 0:
        floor = np.maximum(floor, far_side_floor(mask, depth, alpha >= p.hole_alpha, p.far_side_ratio))
    return floor


def complete_hole_depths(cameras: list[Camera], depths: list[np.ndarray], valids: list[np.ndarray],
                         holes: list[np.ndarray], p: RemoveParams,
                         floors: list[np.ndarray] | None = None, keep: Keeper = in_memory) -> list[np.ndarray]:
    """The holes' depths, jointly (one surface, ``consistent_depth``) or each view on its own; at least
    ``floors`` (:func:`hole_floor`) where given. ``keep`` holds them (:mod:`sgpor_pipeline.scratch`)."""
    if p.consistent_depth:
        return complete_depths_jointly(cameras, depths, valids, holes, floors, keep)
    return keep("completed_depths", (complete_depth(d, v, h, f) for d, v, h, f in
                                     zip(depths, valids, holes, floors or [None] * len(holes))))


CONTEXTS = ("photos", "renders")
# Free disk the stage needs, per pixel of every view: its scratch maps' peak (45 bytes, measured on 24
# views of 800x600, benchmarks/memory.py) and its outputs (~8: renders, context, holes, depths); the
# two Gaussian files (gaussians.ply, object.ply) besides
DISK_BYTES_PER_PIXEL = 53


class RemoveStage(Stage):
    name = "remove"
    VERSION = 16  # 3: the hole-depth floor renders the object proper only (no floaters); 4: rim holes;
    # 5: rim holes with hole_mode mask too; 6: seeds behind the completed surface (seed_depth_offset 4);
    # 7: the median depth, and holes where no other view saw the background (min_views 1, tolerance 0.02);
    # 8: DC colours clamped behind the masks (clamp_share); 9: seeds carved by the views that saw through them;
    # 10: holes where the render disagrees with the photos that saw its point (max_disagreement);
    # 11: the photos are compared blurred in float16 (memory; the disagreement moves by < 0.001);
    # 13 (12 skipped): the context's render is divided by its opacity (unpremultiplied);
    # 14: the propagated masks grown by propagated_margin (0.05 x the square root of their area);
    # 15: the seeds' scales shrunk off the background other views saw beside them (carve_footprint);
    # 16: holes completed no nearer than the far side of a depth step across the mask (far_side_ratio)
    Params = RemoveStageParams
    inputs = ("sfm", "fit", "masks")

    def run(self, ctx: StageContext) -> None:
        p = ctx.params
        if p.context not in CONTEXTS:
            raise PipelineError(f"unknown remove.context {p.context!r}", fix=f"use one of {', '.join(CONTEXTS)}")
        if p.delete_masks not in DELETE_MASKS:
            raise PipelineError(f"unknown remove.delete_masks {p.delete_masks!r}",
                                fix=f"use one of {', '.join(DELETE_MASKS)}")
        if p.propagated_margin < 0:
            raise PipelineError(f"remove.propagated_margin must be >= 0 (got {p.propagated_margin})",
                                fix="use 0 (the propagated masks as the masks stage wrote them) or e.g. 0.05")
        if not (p.far_side_ratio == 0 or p.far_side_ratio >= 1):  # (NaN fails too)
            raise PipelineError(f"remove.far_side_ratio must be 0 (off) or >= 1 (got {p.far_side_ratio})",
                                fix="use e.g. 1.5: a hole is completed on the far side where one side of the "
                                    "mask is 1.5x as far as the other")
        # the fit's cameras: their poses refined with the Gaussians (fit.pose_refine)
        sfm = load_sfm(ctx.inputs["sfm"], run_cameras_file(ctx.inputs["fit"], ctx.inputs["sfm"]))
        cameras = sfm.posed
        # before any rendering: the disk the scratch maps and the outputs need
        pixels = sum(c.width * c.height for c in cameras)
        ply = (ctx.inputs["fit"] / "gaussians.ply").stat().st_size
        require_free_disk(ctx.scratch_dir, DISK_BYTES_PER_PIXEL * pixels + 2 * ply,
                          f"the remove stage's maps of {len(cameras)} views ({pixels / 1e6:.0f} M pixels)",
                          shown=ctx.out_dir.parent)  # (the build folder itself is removed after the error)
        model = read_ply(ctx.inputs["fit"] / "gaussians.ply")
        masks_dir = ctx.inputs["masks"] / "masks"
        masks = [read_mask(masks_dir / f"{c.image}.png") for c in cameras]
        as_given = masks
        masks, grown = grown_propagated(masks, [c.image for c in cameras], mask_sources(ctx.inputs["masks"]),
                                        p.propagated_margin)
        object_ids = np.load(ctx.inputs["masks"] / "object_ids.npy")
        select = p
        object_fitted = not fit_ignored_masks(ctx.inputs["fit"])
        if not object_fitted:
            # no object was fitted: a Gaussian mostly inside the masks is background other views saw
            # behind the object (the floaters no view shows outside the masks are still deleted)
            select = dataclasses.replace(p, score_threshold=float("inf"))
        if p.delete_masks == "split" and grown:
            # both mask sets' scores from one render of each view's total weights
            (inside, inside_given), total = contribution_scores_of_sets(model, cameras, [masks, as_given], p.backend)
            delete, stats, surface, share = objects_to_delete(model, cameras, masks, object_ids, select,
                                                              scores=(inside, total))
            core, _, core_surface, _ = objects_to_delete(model, cameras, as_given, object_ids, select,
                                                         scores=(inside_given, total))
            margin = delete & ~core
            to_object = closer_to_core(model.means.detach().double().numpy(), core, margin)
            stats["margin"], stats["margin_kept"] = int(margin.sum()), int((margin & ~to_object).sum())
            surface &= core_surface | to_object
            delete = core | to_object
            stats["deleted"] = int(delete.sum())
        else:
            delete, stats, surface, share = objects_to_delete(model, cameras, as_given if p.delete_masks == "as_given"
                                                              else masks, object_ids, select)
        if grown:
            stats["propagated_masks_grown_px"] = grown
        background = subset(model, ~delete)
        if p.clamp_share > 0:  # (the renders below use clamped DC colours anyway: unchanged)
            stats["dc_clamped"] = clamp_dc_colours(background, share[~delete] >= p.clamp_share)
        write_ply(ctx.out_dir / "object.ply", subset(model, delete))
        save_cameras(ctx.out_dir / "cameras.json", cameras)
        for sub in ("renders", "holes", "masks", "depth", "context"):
            (ctx.out_dir / sub).mkdir()
        # every view's float maps (renders, opacities, depths, ...) on disk while the stage runs, read back
        # memory-mapped: held in memory they took ~60 bytes a pixel of every view (scratch.py); the bool
        # masks stay in memory (1 byte a pixel each)
        keep = functools.partial(on_disk, ctx.scratch_dir)
        renders, alphas, raw_depths = (ArraysOnDisk(ctx.scratch_dir / n) for n in ("renders", "alphas", "raw_depths"))
        for cam in ctx.progress(cameras, total=len(cameras), desc="remove: render"):
            rgb, alpha, depth = render_background(background, cam, p.backend, p.depth)
            renders.append(rgb)
            alphas.append(alpha)
            raw_depths.append(depth)
        holes = [hole_mask(m, a, p) for m, a in zip(masks, alphas)]
        front = subset(model, surface)
        floors = None
        if p.behind_object or p.far_side_ratio > 0:
            floors = keep("floors", (hole_floor(front, cam, m, d, a, p)
                                     for cam, m, d, a in zip(cameras, masks, raw_depths, alphas)))
        depths = complete_hole_depths(cameras, raw_depths, [a >= p.hole_alpha for a in alphas], holes, p, floors,
                                      keep)
        second_pass = p.min_views > 0 and p.hole_mode == "unseen"
        photos: ArraysOnDisk | None = None  # (read here only when compared with the renders)
        if second_pass:  # mask pixels that too few other views observed become holes too
            seen = [m & ~h for m, h in zip(masks, holes)]
            if p.max_disagreement > 0:
                photos = keep("photos", (self._photo(sfm, cam, p) for cam in cameras))
            counts, disagree = observing_views(cameras, masks, depths, seen, p,
                                               renders if photos is not None else None, photos, keep)
            unobserved = [s & (c < p.min_views) for s, c in zip(seen, counts)]
            if disagree is not None:  # (NaN: no photo shows the point; compares False)
                stats["disagreeing_pixels"] = int(sum(int((s & (d > p.max_disagreement)).sum())
                                                      for s, d in zip(seen, disagree)))
                unobserved = [u | (s & (d > p.max_disagreement)) for u, s, d in zip(unobserved, seen, disagree)]
            release(counts)  # (the disk the scratch maps take: only while they are needed)
            release(disagree)
            holes = [hole_mask(m, a, p, u) for m, a, u in zip(masks, alphas, unobserved)]
        observed = [(a >= p.hole_alpha) & ~h for a, h in zip(alphas, holes)]  # background each view saw
        if second_pass:
            first_depths = depths
            depths = complete_hole_depths(cameras, raw_depths, observed, holes, p, floors,
                                          functools.partial(on_disk, ctx.scratch_dir / "second_pass"))
            release(first_depths)
        release(raw_depths)
        release(floors)
        if p.under_object and p.hole_mode == "unseen":
            under, why = under_object(cameras, masks, holes, depths, depth_tol=p.view_depth_tol,
                                      rim=p.under_object_rim)
            if under is None:
                ctx.log.info(f"remove: under_object: {why}; nothing added to the holes")
                stats["under_object"] = {"pixels": 0, "reason": why}
            else:
                # (their completed depth is their rendered depth: the plane)
                holes = [h | u for h, u in zip(holes, under.pixels)]
                observed = [o & ~u for o, u in zip(observed, under.pixels)]
                stats["under_object"] = under.info
                (ctx.out_dir / "under_object").mkdir()
                save_cameras(ctx.out_dir / "under_object" / "camera.json", [under.camera])
                write_mask01(ctx.out_dir / "under_object" / "silhouette.png", under.silhouette)
                ctx.log.info(f"remove: {under.info['pixels']} mask pixels lay on the plane under the object: holes")
        colours = ArraysOnDisk(ctx.scratch_dir / "colours")
        per_view = {}
        for i, (cam, mask, rgb, alpha, hole, filled_depth) in enumerate(zip(cameras, masks, renders, alphas, holes,
                                                                            depths)):
            photo = photos[i] if photos is not None else self._photo(sfm, cam, p)
            photo = None if photo is None else to_float32(photo)
            write_png(ctx.out_dir / "renders" / f"{cam.image}.png", rgb)
            write_png(ctx.out_dir / "context" / f"{cam.image}.png",
                      context_image(unpremultiplied(rgb, alpha), photo, mask, p.context_margin))
            write_mask01(ctx.out_dir / "holes" / f"{cam.image}.png", hole)
            write_mask01(ctx.out_dir / "masks" / f"{cam.image}.png", mask)
            np.save(ctx.out_dir / "depth" / f"{cam.image}.npy", filled_depth)
            colours.append(initial_colour(rgb, hole, as_uint8=True) if hole.any() else None)  # (seeds: holes only)
            per_view[cam.image] = {"mask_pixels": int(mask.sum()), "hole_pixels": int(hole.sum()),
                                   "rim_pixels": int((hole & ~mask).sum()),
                                   "hole_pixels_by_opacity": int((mask & (alpha < p.hole_alpha)).sum())}
        spacing = median_spacing(background.means.detach().double().numpy())
        seeds = seed_hole_gaussians(cameras, holes, depths, colours, spacing, model.max_sh_degree, p, p.seed,
                                    observed if p.carve_seeds else None)
        cleaned = concat_models(background, seeds)
        write_ply(ctx.out_dir / "gaussians.ply", cleaned)
        np.save(ctx.out_dir / "seed_ids.npy", np.arange(len(background), len(cleaned)))
        mask_px = sum(v["mask_pixels"] for v in per_view.values())
        hole_px = sum(v["hole_pixels"] for v in per_view.values())
        rim_px = sum(v["rim_pixels"] for v in per_view.values())
        summary = {**stats, "object_fitted": object_fitted,
                   "gaussians_before": len(model), "background": len(background), "seeds": len(seeds),
                   "mask_pixels": mask_px, "hole_pixels": hole_px, "rim_pixels": rim_px,
                   "hole_fraction_of_mask": (hole_px - rim_px) / mask_px if mask_px else 0.0, "views": per_view}
        (ctx.out_dir / "remove.json").write_text(json.dumps(summary, indent=1))
        ctx.notes.update({k: v for k, v in summary.items() if k != "views"})

    @staticmethod
    def _photo(sfm, cam: Camera, p: RemoveStageParams) -> np.ndarray | None:
        """The view's undistorted photo (uint8 RGB) for ``context = photos`` (None: renders, or no photo on
        disk)."""
        path = sfm.image_path(cam.image)
        if p.context != "photos" or not path.is_file():
            return None
        photo = read_rgb8(path)  # (uint8: a quarter of the float image's memory, held for every view)
        if photo.shape[:2] != (cam.height, cam.width):
            raise PipelineError(f"the photo of view {cam.image} is {photo.shape[1]}x{photo.shape[0]}, its camera "
                                f"{cam.width}x{cam.height}", path=path, fix="rerun from the sfm stage (--force sfm)")
        return photo
