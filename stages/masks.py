"""masks: an object mask for every view, propagated from the masks the user gave for some.

Out: ``masks/<view>.png`` (0/1, every registered view, in the undistorted sfm images' pixels),
``prob/<view>.png`` (the soft object probability, 8-bit), ``object_ids.npy`` (indices of the
object's Gaussians in the fit stage's ``gaussians.ply``), ``scores.npy``, ``masks.json``
(per-view confidence and source: "given" or "propagated"; selection counts; the margin measured
around the given masks and added around the propagated ones). Views given by the user keep their
masks. See :mod:`sgpor_pipeline.removal.selection` for the method.

Given masks are often drawn generously, with a margin of background (the mip-NeRF 360 kitchen's are
dilated by ~15 px at 520 px): the object is selected from their pixels in FRONT of the background
carried in from around them (``tighten``, :func:`~sgpor_pipeline.removal.selection.tighten_mask`),
and the propagated masks get the measured margin back. Without it, the margin's floor seeded the
selection and the kitchen's propagated masks leaked onto the table (blobs away from the object).

Each propagated mask is then snapped to the object in its photo (``grabcut``,
:func:`~sgpor_pipeline.removal.selection.grabcut_mask`) and the object is selected again from ALL
views' masks (``reselect``): with one given view, the parts it cannot see (the kitchen bulldozer's far
track, its bucket teeth at the table's depth) were left in the scene after deletion; the views that
see them now say so. What GrabCut adds is kept only where its surface point lies in the given views'
visual cone (room's beige slippers on a light rug: GrabCut took the rug, which view 1 shows outside
its mask). Measured (benchmarks/removal.py, IoU against
the dataset's masks on the views not given, from 1 / 2 / 4 given masks): statue 0.946 / 0.946 /
0.945 (0.951 / 0.951 / 0.953 without GrabCut, 0.954 / 0.956 / 0.961 before the tightening: GrabCut
follows the object's edges, the dataset's masks are a little wider); room 0.572 / 0.740 / 0.794
(0.654 / 0.740 / 0.794 before; 3 evaluated views, its SfM registers 5-7 of 24).
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import cv2
import numpy as np

from sgpor_pipeline.dag import Stage, StageContext
from sgpor_pipeline.errors import PipelineError
from sgpor_pipeline.gaussians.ply import read_ply
from sgpor_pipeline.imageio import read_image, read_mask, write_mask01, write_png
from sgpor_pipeline.removal.selection import (
    SelectionParams,
    TightParams,
    grabcut_mask,
    inside_given_cone,
    margin_width,
    mask_confidence,
    refine_mask,
    render_object_probability,
    select_object,
    tighten_mask,
)
from sgpor_pipeline.sfm import load_sfm

MIN_MARGIN = 2.0


@dataclass
class MasksParams:
    score_threshold: float = 0.6
    grow_radius: float = 2.5
    render_threshold: float = 0.5
    guided_radius: int = 4
    use_sfm_points: bool = True
    # Use only the first N given masks (0 = all): the benchmark measures propagation from 1, 2, 4.
    max_given: int = 0
    # Given masks drawn with a margin of background: select the object from their pixels in front of
    # the background around them (selection.tighten_mask), and give the propagated masks the same
    # margin: ``margin`` px (-1 = the median margin measured on the given masks, 0 = none).
    tighten: bool = True
    margin: int = -1
    # Propagated masks snapped to the object in each photo (GrabCut, selection.grabcut_mask), then the
    # object selected again from ALL views' masks (the visual hull of many views instead of the cone
    # of a few): parts one given view could not see are found in the views that see them.
    grabcut: bool = True
    grabcut_band: float = 0.3  # the band GrabCut may grow into: this x sqrt(mask area), in px
    grabcut_max_growth: float = 2.0  # a GrabCut result larger than this x the mask is rejected
    reselect: bool = True
    backend: str = "auto"


class MasksStage(Stage):
    name = "masks"
    VERSION = 10
    Params = MasksParams
    inputs = ("sfm", "fit")

    def run(self, ctx: StageContext) -> None:
        p = ctx.params
        sel_params = SelectionParams(score_threshold=p.score_threshold, grow_radius=p.grow_radius,
                                     render_threshold=p.render_threshold, guided_radius=p.guided_radius,
                                     backend=p.backend)
        sfm = load_sfm(ctx.inputs["sfm"])
        model = read_ply(ctx.inputs["fit"] / "gaussians.ply")
        posed = sfm.posed
        given = [(c, read_mask(sfm.mask_path(c.image))) for c in posed if sfm.mask_path(c.image) is not None]
        given = [(c, m) for c, m in given if m.any()]
        if p.max_given > 0:
            given = given[: p.max_given]
        if not given:
            raise PipelineError("no view has a non-empty object mask", path=ctx.run_inputs.masks,
                                fix="pass --masks with the object painted in at least one photo")
        cams = [c for c, _ in given]
        masks = [m for _, m in given]
        sfm_pts = None
        if p.use_sfm_points and len(sfm.points):
            pts = sfm.points
            sfm_pts = (pts.xyz, pts.obs_point, pts.obs_view, pts.obs_xy)
        tight, widths, behind = masks, [0.0] * len(masks), None  # widths: margin of each given mask, px
        if p.tighten:
            tp = TightParams()
            triples = [tighten_mask(model, c, m, tp, p.backend) for c, m in given]
            tight, widths, behind = [t[0] for t in triples], [t[1] for t in triples], [t[2] for t in triples]
        selection = select_object(model, cams, tight, sel_params, sfm_pts, [sfm.index(c.image) for c in cams],
                                  cone_masks=masks, background_depths=behind,
                                  depth_tol=TightParams.depth_tol)
        if not selection.is_object.any():
            raise PipelineError("no Gaussian of the fitted scene falls inside the given masks",
                                path=ctx.run_inputs.masks,
                                fix="check that the masks cover the object (non-zero = object)")
        given_names = {c.image for c in cams}
        given_mask = {c.image: m for c, m in given}
        given_index = {c.image: i for i, c in enumerate(cams)}
        propagated: dict[str, tuple[np.ndarray, np.ndarray, dict]] = {}  # view -> (mask, prob, info)
        for cam in ctx.progress(posed, total=len(posed), desc="masks"):
            if cam.image in given_names:
                continue
            prob = render_object_probability(model, selection.is_object, cam, p.backend)
            image = read_image(sfm.image_path(cam.image))
            mask = refine_mask(prob, image, sel_params)
            info = {"source": "propagated", "confidence": round(mask_confidence(prob, mask), 4)}
            if p.grabcut:
                snapped = grabcut_mask(prob, mask, image, band=p.grabcut_band, max_growth=p.grabcut_max_growth)
                info["grabcut"] = None if snapped is None else round(float(snapped.sum()) / max(1, int(mask.sum())), 3)
                if snapped is not None:
                    # what GrabCut adds must lie in the given views' cone: the room's light rug around
                    # beige slippers was taken by GrabCut, but view 1 shows it outside its mask
                    added = inside_given_cone(model, cam, snapped & ~mask, cams, masks, sel_params.cone_dilate,
                                              p.backend)
                    mask = (snapped & mask) | added
            propagated[cam.image] = (mask, prob, info)
        first = selection
        if p.reselect and p.grabcut and propagated:  # (without the photo's evidence it would be circular)
            # every view's mask now bounds the object: select again from all of them
            all_cams = [c for c in posed if c.image in given_names or propagated[c.image][0].any()]
            all_masks = [tight[given_index[c.image]] if c.image in given_names else propagated[c.image][0]
                         for c in all_cams]
            cone = [given_mask[c.image] if c.image in given_names else propagated[c.image][0] for c in all_cams]
            depths = [behind[given_index[c.image]] if (behind is not None and c.image in given_names) else None
                      for c in all_cams]
            again = select_object(model, all_cams, all_masks, sel_params, sfm_pts,
                                  [sfm.index(c.image) for c in all_cams], cone_masks=cone,
                                  background_depths=depths if behind is not None else None,
                                  depth_tol=TightParams.depth_tol)
            if again.is_object.any():
                selection = again
        given_prob: dict[str, np.ndarray] = {}  # rendered with the final selection, written below
        if p.grabcut and propagated:
            # the margin in the style of the given masks: how far each reaches beyond the mask this
            # stage would have propagated to its view (also where depth cannot tell: a flat object)
            for i, (c, m) in enumerate(given):
                prob = given_prob[c.image] = render_object_probability(model, selection.is_object, c, p.backend)
                image = read_image(sfm.image_path(c.image))
                own = refine_mask(prob, image, sel_params)
                own = (grabcut_mask(prob, own, image, band=p.grabcut_band, max_growth=p.grabcut_max_growth)
                       if own.any() else None)
                if own is not None:
                    widths[i] = max(widths[i], margin_width(m, own & m))
        # (a median margin under MIN_MARGIN px is the edge blur of a mask drawn tight: no margin)
        measured = float(np.median(widths))
        margin = p.margin if p.margin >= 0 else (int(round(measured)) if measured >= MIN_MARGIN else 0)
        np.save(ctx.out_dir / "object_ids.npy", np.flatnonzero(selection.is_object))
        np.save(ctx.out_dir / "scores.npy", selection.score.astype(np.float32))
        (ctx.out_dir / "masks").mkdir()
        (ctx.out_dir / "prob").mkdir()
        per_view = {}
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1,) * 2) if margin > 0 else None
        for cam in posed:
            if cam.image in given_names:
                mask = given_mask[cam.image]
                prob = given_prob.get(cam.image)
                if prob is None:
                    prob = render_object_probability(model, selection.is_object, cam, p.backend)
                info = {"source": "given", "confidence": 1.0}
            else:
                mask, prob, info = propagated[cam.image]
                if selection is not first:
                    prob = render_object_probability(model, selection.is_object, cam, p.backend)
                if kernel is not None and mask.any():
                    mask = cv2.dilate(mask.astype(np.uint8), kernel) > 0
            info["pixels"] = int(mask.sum())
            write_mask01(ctx.out_dir / "masks" / f"{cam.image}.png", mask)
            write_png(ctx.out_dir / "prob" / f"{cam.image}.png", prob)
            per_view[cam.image] = info
        summary = {"views": per_view, "object_gaussians": int(selection.is_object.sum()),
                   "object_gaussians_first_pass": int(first.is_object.sum()), "reselected": selection is not first,
                   "gaussians": len(model), "seeds": selection.seeds, "from_sfm_points": selection.from_points,
                   "grown": selection.grown, "given": sorted(given_names),
                   "given_margin_px": [round(w, 2) for w in widths], "margin_px": margin,
                   "given_pixels_selecting": [int(t.sum()) for t in tight]}
        (ctx.out_dir / "masks.json").write_text(json.dumps(summary, indent=1))
        ctx.notes.update({k: v for k, v in summary.items() if k != "views"})
