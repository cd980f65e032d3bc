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
selection and the kitchen's propagated masks leaked onto the table (blobs away from the object). The
photo has the last word on the margin (``photo_margin``): a mask that GrabCut from the photo alone
keeps was drawn on the object's edge, and a poor fit's depth or render in its view does not give it a
margin (lund + box's view 27, 34 px).
The same carried background finds the object's far side, which no given view sees: every Gaussian
inside the given masks and in front of it is selected too (``hidden``); region growing alone did not
reach it where the fit covers it sparsely (a box from one given mask kept its far side standing).

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

Where the selection's render loses the object, the given masks' surface takes over (``lift``,
:class:`~sgpor_pipeline.removal.selection.LiftedSurface`): each given mask's pixels (tightened, or all
of them when drawn on the object's edge) lifted at the fit's median depth and projected into the view.
A sparse forward capture's fit draws a far view's object with floaters of that view, in front of the
object's own Gaussians, so their render there is empty. There the lifted pixels are GrabCut's sure
object, and what GrabCut adds (the faces the given view does not see) is not checked against the given
views' cone, which would read the view's rendered depth: the floaters'. Lund + box from ONE mask, IoU
against the true masks on the other views (session 38, fit seed 0), before -> with ``lift`` and
``photo_margin``: given view 24 (the box 4,495 px there, 257 px in view 1) 0.269 (0 in views 1-16) ->
0.845; view 27 (the benchmark's ``lund-1mask``) 0.109 -> 0.840; view 28 (the box cut by the frame)
0.225 -> 0.649; view 14 (the fit's depth there is a floater's, 0.6 of the box's) stays poor (0.006 ->
0.360). Statue and room, whose renders do not lose the object, are unchanged (0.951 / 0.952 / 0.951
and 0.750 / 0.758 / 0.767 from 1 / 2 / 4 masks).

After a fit that left the given masks' pixels out (``fit.object_masks = "ignore"``, which needs a mask
for every view) there is no object to select: ``object_ids.npy`` is empty, every view keeps its given
mask (none given: empty) and ``masks.json`` says ``"fit_object_masks": "ignore"``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sgpor_pipeline.config import added_param
from sgpor_pipeline.dag import RunInputs, Stage, StageContext
from sgpor_pipeline.errors import PipelineError, named
from sgpor_pipeline.gaussians.model import GaussianModel
from sgpor_pipeline.gaussians.ply import read_ply
from sgpor_pipeline.imageio import read_image, read_mask, write_mask01, write_png
from sgpor_pipeline.removal.selection import (
    LiftedSurface,
    Selection,
    SelectionParams,
    TightParams,
    grabcut_mask,
    inside_given_cone,
    lift_mask,
    lifted_additions,
    margin_width,
    mask_confidence,
    photo_margin,
    refine_mask,
    render_object_probability,
    select_object,
    splat_surface,
    tighten_mask,
)
from sgpor_pipeline.scene import Camera
from sgpor_pipeline.sfm import SfmResult, load_sfm
from sgpor_pipeline.stages.fit import fit_ignored_masks, run_cameras_file

MIN_MARGIN = 2.0
LIFT_EDGE_PX = 2  # the lifted surface adds to a propagated mask only what reaches beyond its edge by more
LIFT_MAX_COVERED = 0.5  # ... and only where the rendered mask covers less than this share of its footprint

_SfmPoints = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # (xyz, obs_point, obs_view, obs_xy)
_Propagated = dict[str, tuple[np.ndarray, np.ndarray, dict[str, Any]]]  # view -> (mask, prob, info)


@dataclass
class MasksParams:
    score_threshold: float = 0.6
    grow_radius: float = 2.5
    render_threshold: float = 0.5
    guided_radius: int = 4
    use_sfm_points: bool = True
    # Use only the first N given masks (0 = all): the benchmark measures propagation from 1, 2, 4.
    max_given: int = 0
    # Use only the given masks of these views (image names; empty = every given mask), e.g. to measure
    # propagation from a chosen view with every true mask given for scoring (evaluate.score_masks=input).
    given_views: tuple[str, ...] = added_param(())
    # Given masks drawn with a margin of background: select the object from their pixels in front of
    # the background around them (selection.tighten_mask), and give the propagated masks the same
    # margin: ``margin`` px (-1 = the median margin measured on the given masks, 0 = none).
    tighten: bool = True
    margin: int = -1
    # The first selection also takes every Gaussian inside the given masks and in front of the
    # background carried under them (selection.select_object's ``hidden``; needs ``tighten``): the
    # object's far side, which no given view sees and which growing did not reach where the fit covers
    # it sparsely (its Gaussians' nearest-neighbour spacing, which sets growing's links, is that of the
    # densely fitted near side). From ONE given mask (benchmarks/removal.py, fit.object_masks=fit,
    # masks.max_given=1, fit seed 0), the propagated masks' mean IoU against the truth (min), and the
    # removal's mask PSNR, off -> on: synthetic-box 0.53 (0.18) -> 0.98 (0.92), ours 19.33 -> 25.56,
    # delete-only 17.03 -> 20.61 (the box's far side was left standing in the views opposite the given
    # one); synthetic-raised-cast 0.53 (0.20) -> 0.94 (0.92), ours 19.09 -> 19.63, delete-only 17.80 ->
    # 19.16 (the object's Gaussians selected 55 % -> 95 %). Real captures: mip360 kitchen from one mask,
    # IoU against the dataset's (dilated) masks 0.82 -> 0.84 (min 0.74 -> 0.77); SPIn-NeRF statue
    # 0.957 either way.
    hidden: bool = True
    # Propagated masks snapped to the object in each photo (GrabCut, selection.grabcut_mask), then the
    # object selected again from ALL views' masks (the visual hull of many views instead of the cone
    # of a few): parts one given view could not see are found in the views that see them.
    grabcut: bool = True
    grabcut_band: float = 0.3  # the band GrabCut may grow into: this x sqrt(mask area), in px
    grabcut_max_growth: float = 2.0  # a GrabCut result larger than this x the mask is rejected
    reselect: bool = True
    # The given masks' surface (their tightened pixels lifted at the fit's median depth,
    # selection.LiftedSurface) projected into every view joins its propagated mask. The rendered
    # selection misses the object wherever the fit drew it with other Gaussians: a sparse forward
    # capture's fit draws a far view's object with floaters of that view (lund + box from one mask,
    # view 24 of 28: IoU 0 in views 1-16 without it). It joins only where the rendered mask lost the
    # object (covers under LIFT_MAX_COVERED of the footprint), and only what reaches beyond the
    # rendered mask (selection.lifted_additions).
    lift: bool = True
    # A given mask whose photo shows no margin (selection.photo_margin under MIN_MARGIN px: GrabCut from
    # the photo alone keeps it) was drawn on the object's edge: its margin is that, whatever the fit's
    # depth and render in its view say, and it is lifted whole. A poor fit's render covered a third of
    # lund + box's view 27 (its tightening kept 6,036 of 17,959 px) and the measured 34 px margin grew
    # every propagated mask by 34 px (view 1: 5,225 px for the box's 257).
    photo_margin: bool = True
    seed: int = 0  # GrabCut's k-means
    backend: str = "auto"


class MasksStage(Stage):
    name = "masks"
    VERSION = 12  # 12: the given masks' lifted surface (lift); the photo's margin (photo_margin); GrabCut seeded
    Params = MasksParams
    inputs = ("sfm", "fit")

    @classmethod
    def check_inputs(cls, params: MasksParams, run_inputs: RunInputs) -> None:
        """The object to remove is the one painted in the given masks: without a mask folder there is
        nothing to select, and the run stops before SfM and the fit rather than after them."""
        if run_inputs.masks is not None:
            return
        images = Path(run_inputs.images)
        beside = [d for d in (images.parent / "masks", images / "masks") if d.is_dir()]
        found = f" ({beside[0]} looks like one)" if beside else ""
        raise PipelineError("no object masks given: the pipeline removes the object painted in them", path=images,
                            fix=f"pass --masks DIR{found}: masks named like the photos, non-zero = the object, "
                                "for one photo or more; or --until fit to reconstruct the scene only")

    @classmethod
    def check_upstream(cls, params: MasksParams, upstream: str, folder: Path) -> None:
        """Right after SfM, before the fit: a mask painted only on photos SfM could not register leaves
        no object to select."""
        if upstream == "sfm":
            _read_given_masks(load_sfm(folder), params.max_given, None, params.given_views)

    def run(self, ctx: StageContext) -> None:
        p = ctx.params
        sel_params = _selection_params(p)
        # the fit's cameras: their poses refined with the Gaussians (fit.pose_refine)
        sfm = load_sfm(ctx.inputs["sfm"], run_cameras_file(ctx.inputs["fit"], ctx.inputs["sfm"]))
        model = read_ply(ctx.inputs["fit"] / "gaussians.ply")
        if fit_ignored_masks(ctx.inputs["fit"]):
            summary = _write_given_only(ctx.out_dir, model, sfm, _read_given_masks(sfm, 0, ctx.run_inputs.masks))
            ctx.log.info("masks: the fit left the masked pixels out (fit.object_masks=ignore): no object "
                         "Gaussians to select, every view keeps its given mask")
            if p.max_given > 0 or p.given_views:
                ctx.log.warning(f"masks: max_given={p.max_given} / given_views={list(p.given_views)} are not "
                                "used: the fit needed every view's mask (fit.object_masks=ignore)")
            ctx.notes.update({k: v for k, v in summary.items() if k != "views"})
            return
        given_pairs = _read_given_masks(sfm, p.max_given, ctx.run_inputs.masks, p.given_views)
        sfm_pts = _sfm_points(sfm) if p.use_sfm_points else None
        given, widths = _tighten_given(model, sfm, given_pairs, p)
        if p.lift:
            given.surface = LiftedSurface.concat([lift_mask(model, c, given.lifting(i), p.backend)
                                                  for i, c in enumerate(given.cams)])
        first = _first_selection(model, sfm, given, sel_params, sfm_pts, ctx.run_inputs.masks, p.hidden)
        propagated = _propagate(ctx, model, sfm, first, given, p, sel_params)
        lost = sorted(v for v, (_, _, info) in propagated.items() if info.get("lifted_added"))
        if lost:
            ctx.log.info(f"masks: the selection's render lost the object in {len(lost)} of {len(propagated)} views "
                         f"({named(lost, 8)}); their masks take the given "
                         "masks' lifted surface (masks.lift)")
        selection = first
        if p.reselect and p.grabcut and propagated:  # (without the photo's evidence it would be circular)
            selection = _reselect(model, sfm, first, given, propagated, sel_params, sfm_pts)
        given_prob: dict[str, np.ndarray] = {}  # rendered with the final selection, written below
        if p.grabcut and propagated:
            widths, given_prob = _measure_given_margins(model, sfm, selection, given, widths, p, sel_params)
        margin = _margin_px(widths, p.margin)
        _write_selection(ctx.out_dir, selection)
        per_view = _write_view_masks(ctx.out_dir, model, sfm, selection, first, given, propagated, given_prob,
                                     margin, p.backend)
        summary = _summary(per_view, model, selection, first, given, widths, margin)
        (ctx.out_dir / "masks.json").write_text(json.dumps(summary, indent=1))
        ctx.notes.update({k: v for k, v in summary.items() if k != "views"})


@dataclass
class _GivenViews:
    """The views given a mask: their cameras, masks as given, the masks that select the object
    (tightened, or as given) and the background depth carried into each (None: not tightened)."""

    cams: list[Camera]
    masks: list[np.ndarray]
    tight: list[np.ndarray]
    behind: list[np.ndarray | None] | None
    drawn_tight: list[bool] | None = None  # masks drawn on the object's edge (MasksParams.photo_margin)
    photos: list[np.ndarray] | None = None  # the views' photos, when read already (photo_margin)
    surface: LiftedSurface | None = None  # the masks lifted to the world (lifting(); MasksParams.lift)
    names: set[str] = field(init=False)
    index: dict[str, int] = field(init=False)  # view -> its position in the lists above

    def __post_init__(self) -> None:
        self.names = {c.image for c in self.cams}
        self.index = {c.image: i for i, c in enumerate(self.cams)}

    def is_drawn_tight(self, i: int) -> bool:
        return bool(self.drawn_tight and self.drawn_tight[i])

    def lifting(self, i: int) -> np.ndarray:
        """The pixels of given view ``i`` to lift: the whole mask when it was drawn on the object's edge."""
        return self.masks[i] if self.is_drawn_tight(i) else self.tight[i]


def _write_given_only(out_dir: Path, model: GaussianModel, sfm: SfmResult,
                      given: list[tuple[Camera, np.ndarray]]) -> dict[str, Any]:
    """The stage's output after a fit that ignored the masks: no object Gaussians, every view's mask as
    given (the fit needed one for every view; an absent mask file is an empty mask), masks.json."""
    np.save(out_dir / "object_ids.npy", np.zeros(0, np.int64))
    np.save(out_dir / "scores.npy", np.zeros(len(model), np.float32))
    (out_dir / "masks").mkdir()
    (out_dir / "prob").mkdir()
    masks = {c.image: m for c, m in given}
    per_view = {}
    for cam in sfm.posed:
        mask = masks.get(cam.image)
        if mask is None:
            mask = np.zeros((cam.height, cam.width), bool)
        write_mask01(out_dir / "masks" / f"{cam.image}.png", mask)
        write_png(out_dir / "prob" / f"{cam.image}.png", mask.astype(np.float32))
        per_view[cam.image] = {"source": "given", "confidence": 1.0, "pixels": int(mask.sum())}
    summary = {"views": per_view, "object_gaussians": 0, "object_gaussians_first_pass": 0, "reselected": False,
               "gaussians": len(model), "given": sorted(masks), "fit_object_masks": "ignore"}
    (out_dir / "masks.json").write_text(json.dumps(summary, indent=1))
    return summary


def _selection_params(p: MasksParams) -> SelectionParams:
    """The object selection's parameters, from the stage's."""
    return SelectionParams(score_threshold=p.score_threshold, grow_radius=p.grow_radius,
                           render_threshold=p.render_threshold, guided_radius=p.guided_radius, backend=p.backend)


def _read_given_masks(sfm: SfmResult, max_given: int, masks_path: Path | None,
                      only: Sequence[str] = ()) -> list[tuple[Camera, np.ndarray]]:
    """The posed views' non-empty given masks (of the views ``only`` names, when it names any; the first
    ``max_given``, 0 = all); PipelineError if none."""
    wanted = set(only)
    given = [(c, read_mask(sfm.mask_path(c.image))) for c in sfm.posed
             if sfm.mask_path(c.image) is not None and (not wanted or c.image in wanted)]
    given = [(c, m) for c, m in given if m.any()]
    if wanted:
        unknown = sorted(wanted - {c.image for c, _ in given})
        if unknown:
            raise PipelineError(f"masks.given_views names views without a given (non-empty) mask: {unknown}",
                                path=masks_path, fix="name views whose photo has a mask, or leave it empty")
    if max_given > 0:
        given = given[:max_given]
    if not given:
        lost = sfm.summary.get("unregistered") or []
        if lost:  # (their masks, if any, were not carried: the photos have no pose to carry them with)
            posed = [c.image for c in sfm.posed]
            raise PipelineError(f"no photo SfM registered has a non-empty object mask; {len(lost)} photo(s) did not "
                                f"register ({named(lost, 5)}), and a mask painted there cannot be used",
                                path=masks_path, fix=f"paint the object in one of the registered photos, e.g. "
                                                     f"{named(posed, 3)}")
        raise PipelineError("no view has a non-empty object mask", path=masks_path,
                            fix="pass --masks with the object painted in at least one photo")
    return given


def _sfm_points(sfm: SfmResult) -> _SfmPoints | None:
    """The SfM points and their observations as select_object takes them; None when there are none."""
    if not len(sfm.points):
        return None
    pts = sfm.points
    return (pts.xyz, pts.obs_point, pts.obs_view, pts.obs_xy)


def _tighten_given(model: GaussianModel, sfm: SfmResult, given: list[tuple[Camera, np.ndarray]],
                   p: MasksParams) -> tuple[_GivenViews, list[float]]:
    """The given views with their masks tightened (``p.tighten``), and the margin of each, px: the one
    tightening removed, or the photo's (``p.photo_margin``) where that says the mask was drawn tight."""
    cams = [c for c, _ in given]
    masks = [m for _, m in given]
    drawn_tight, photo, photos = None, [0.0] * len(masks), None
    if p.photo_margin:
        photos = [read_image(sfm.image_path(c.image)) for c in cams]
        measured = [photo_margin(m, im, p.grabcut_band, p.seed) for m, im in zip(masks, photos)]
        drawn_tight = [w is not None and w < MIN_MARGIN for w in measured]
        photo = [w or 0.0 for w in measured]
    tight, behind, widths = masks, None, [0.0] * len(masks)
    if p.tighten:
        tp = TightParams()
        triples = [tighten_mask(model, c, m, tp, p.backend) for c, m in given]
        tight, behind = [t[0] for t in triples], [t[2] for t in triples]
        widths = [photo[i] if drawn_tight and drawn_tight[i] else t[1] for i, t in enumerate(triples)]
    return _GivenViews(cams, masks, tight, behind, drawn_tight, photos), widths


def _first_selection(model: GaussianModel, sfm: SfmResult, given: _GivenViews, sel_params: SelectionParams,
                     sfm_pts: _SfmPoints | None, masks_path: Path | None, hidden: bool = False) -> Selection:
    """The object selected from the given views' masks; PipelineError when that selects nothing."""
    selection = select_object(model, given.cams, given.tight, sel_params, sfm_pts,
                              [sfm.index(c.image) for c in given.cams], cone_masks=given.masks,
                              background_depths=given.behind, depth_tol=TightParams.depth_tol, hidden=hidden)
    if not selection.is_object.any():
        raise PipelineError("no Gaussian of the fitted scene falls inside the given masks", path=masks_path,
                            fix="check that the masks cover the object (non-zero = object)")
    return selection


def _propagate(ctx: StageContext, model: GaussianModel, sfm: SfmResult, selection: Selection, given: _GivenViews,
               p: MasksParams, sel_params: SelectionParams) -> _Propagated:
    """A mask for every view not given one, from the selection's render (see :func:`_propagate_view`)."""
    posed = sfm.posed
    propagated: _Propagated = {}
    for cam in ctx.progress(posed, total=len(posed), desc="masks"):
        if cam.image in given.names:
            continue
        propagated[cam.image] = _propagate_view(model, sfm, cam, selection, given, p, sel_params)
    return propagated


def _propagate_view(model: GaussianModel, sfm: SfmResult, cam: Camera, selection: Selection, given: _GivenViews,
                    p: MasksParams, sel_params: SelectionParams) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """One view's (mask, probability, info): the selection's rendered probability, refined, snapped by GrabCut."""
    prob, image, mask = _rendered_mask(model, sfm, cam, selection, p, sel_params)
    info: dict[str, Any] = {"source": "propagated", "confidence": round(mask_confidence(prob, mask), 4)}
    lifted = np.zeros_like(mask)
    if given.surface is not None:
        footprint = splat_surface(given.surface, cam)
        covered = float((footprint & mask).sum()) / max(1, int(footprint.sum()))
        # Only where the render lost the object (it covers under LIFT_MAX_COVERED of the footprint):
        # elsewhere the rendered mask is the better one. A mask drawn with a margin that depth cannot
        # tell from the object (mip360 room's ellipses around slippers on a rug) lifts the margin too,
        # and its footprint in another view is a shifted ellipse. And only what the render missed by
        # more than an edge's pixel or two, without specks (the slivers along the rendered edge
        # widened statue's masks by 5 % from 4 given views).
        if footprint.any() and covered < LIFT_MAX_COVERED:
            lifted = lifted_additions(footprint, mask, LIFT_EDGE_PX)
            # (the render, whose decisiveness the confidence measures, lost the object here)
            info["confidence"] = round(min(info["confidence"], covered), 4)
        info.update(lifted_pixels=int(footprint.sum()), lifted_covered=round(covered, 3),
                    lifted_added=int(lifted.sum()))
    lost = bool(lifted.any())
    if p.grabcut:
        # Where the render lost the object, the lifted pixels are GrabCut's sure object, and what it
        # adds is not checked against the given views' cone: that check reads the view's rendered
        # depth, the floaters' that lost the object. (lund + box from one mask: the box's side faces,
        # which the given view does not see, join; IoU from view 27 0.754 -> 0.840, 24 0.790 -> 0.845,
        # 28 0.522 -> 0.649; without the sure pixels 0.809 / 0.824 / 0.571, with the check 0.754 / 0.790.)
        snap_prob = np.maximum(prob, lifted.astype(np.float32)) if lost else prob
        mask, info["grabcut"] = _snap_to_photo(model, cam, snap_prob, mask | lifted, image, given, p, sel_params,
                                               gate=not lost)
    # (GrabCut does not take the lifted pixels away: in a far view's few hundred pixels it dropped
    # two thirds of them)
    return mask | lifted, prob, info


def _rendered_mask(model: GaussianModel, sfm: SfmResult, cam: Camera, selection: Selection, p: MasksParams,
                   sel_params: SelectionParams, photo: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(probability render of the selection, the view's photo (``photo``, or read), the probability
    refined on the photo)."""
    prob = render_object_probability(model, selection.is_object, cam, p.backend)
    image = read_image(sfm.image_path(cam.image)) if photo is None else photo
    return prob, image, refine_mask(prob, image, sel_params)


def _snap_to_photo(model: GaussianModel, cam: Camera, prob: np.ndarray, mask: np.ndarray, image: np.ndarray,
                   given: _GivenViews, p: MasksParams, sel_params: SelectionParams,
                   gate: bool = True) -> tuple[np.ndarray, float | None]:
    """The mask snapped by GrabCut, its additions kept inside the given views' cone (``gate``); and
    GrabCut's area ratio."""
    snapped = grabcut_mask(prob, mask, image, band=p.grabcut_band, max_growth=p.grabcut_max_growth, seed=p.seed)
    if snapped is None:  # (GrabCut gave up or was implausible: the mask is kept)
        return mask, None
    ratio = round(float(snapped.sum()) / max(1, int(mask.sum())), 3)
    # what GrabCut adds must lie in the given views' cone: the room's light rug around
    # beige slippers was taken by GrabCut, but view 1 shows it outside its mask
    added = snapped & ~mask
    if gate:
        added = inside_given_cone(model, cam, added, given.cams, given.masks, sel_params.cone_dilate, p.backend)
    return (snapped & mask) | added, ratio


def _reselect(model: GaussianModel, sfm: SfmResult, first: Selection, given: _GivenViews, propagated: _Propagated,
              sel_params: SelectionParams, sfm_pts: _SfmPoints | None) -> Selection:
    """The object selected again from every view's mask (each now bounds it); ``first`` if that selects nothing."""
    all_cams = [c for c in sfm.posed if c.image in given.names or propagated[c.image][0].any()]
    all_masks = [given.tight[given.index[c.image]] if c.image in given.names else propagated[c.image][0]
                 for c in all_cams]
    cone = [given.masks[given.index[c.image]] if c.image in given.names else propagated[c.image][0]
            for c in all_cams]
    depths = None if given.behind is None else [
        given.behind[given.index[c.image]] if c.image in given.names else None for c in all_cams]
    again = select_object(model, all_cams, all_masks, sel_params, sfm_pts,
                          [sfm.index(c.image) for c in all_cams], cone_masks=cone,
                          background_depths=depths, depth_tol=TightParams.depth_tol)
    return again if again.is_object.any() else first


def _measure_given_margins(model: GaussianModel, sfm: SfmResult, selection: Selection, given: _GivenViews,
                           widths: list[float], p: MasksParams,
                           sel_params: SelectionParams) -> tuple[list[float], dict[str, np.ndarray]]:
    """Each given mask's margin (at least ``widths``) and its view's probability render, reused when writing."""
    # the margin in the style of the given masks: how far each reaches beyond the mask this
    # stage would have propagated to its view (also where depth cannot tell: a flat object)
    widths = list(widths)
    given_prob: dict[str, np.ndarray] = {}
    for i, (c, m) in enumerate(zip(given.cams, given.masks)):
        prob, image, own = _rendered_mask(model, sfm, c, selection, p, sel_params,
                                          given.photos[i] if given.photos is not None else None)
        given_prob[c.image] = prob
        own = (grabcut_mask(prob, own, image, band=p.grabcut_band, max_growth=p.grabcut_max_growth, seed=p.seed)
               if own.any() else None)
        if own is not None and not given.is_drawn_tight(i):  # (there the render measures the fit, not the mask)
            widths[i] = max(widths[i], margin_width(m, own & m))
    return widths, given_prob


def _margin_px(widths: list[float], margin: int) -> int:
    """The margin added around the propagated masks: ``margin``, or (-1) the given masks' median margin."""
    # (a median margin under MIN_MARGIN px is the edge blur of a mask drawn tight: no margin)
    measured = float(np.median(widths))
    return margin if margin >= 0 else (int(round(measured)) if measured >= MIN_MARGIN else 0)


def _write_selection(out_dir: Path, selection: Selection) -> None:
    """object_ids.npy (the object's Gaussians) and scores.npy."""
    np.save(out_dir / "object_ids.npy", np.flatnonzero(selection.is_object))
    np.save(out_dir / "scores.npy", selection.score.astype(np.float32))


def _write_view_masks(out_dir: Path, model: GaussianModel, sfm: SfmResult, selection: Selection, first: Selection,
                      given: _GivenViews, propagated: _Propagated, given_prob: dict[str, np.ndarray], margin: int,
                      backend: str) -> dict[str, dict[str, Any]]:
    """masks/ and prob/ for every view (propagated masks grown by ``margin`` px); each view's info."""
    (out_dir / "masks").mkdir()
    (out_dir / "prob").mkdir()
    per_view = {}
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1,) * 2) if margin > 0 else None
    for cam in sfm.posed:
        if cam.image in given.names:
            mask = given.masks[given.index[cam.image]]
            prob = given_prob.get(cam.image)
            if prob is None:
                prob = render_object_probability(model, selection.is_object, cam, backend)
            info = {"source": "given", "confidence": 1.0}
        else:
            mask, prob, info = propagated[cam.image]
            if selection is not first:
                prob = render_object_probability(model, selection.is_object, cam, backend)
            if kernel is not None and mask.any():
                mask = cv2.dilate(mask.astype(np.uint8), kernel) > 0
        info["pixels"] = int(mask.sum())
        write_mask01(out_dir / "masks" / f"{cam.image}.png", mask)
        write_png(out_dir / "prob" / f"{cam.image}.png", prob)
        per_view[cam.image] = info
    return per_view


def _summary(per_view: dict[str, dict[str, Any]], model: GaussianModel, selection: Selection, first: Selection,
             given: _GivenViews, widths: list[float], margin: int) -> dict[str, Any]:
    """masks.json's content (also the stage's notes, less "views")."""
    return {"views": per_view, "object_gaussians": int(selection.is_object.sum()),
            "object_gaussians_first_pass": int(first.is_object.sum()), "reselected": selection is not first,
            "gaussians": len(model), "seeds": selection.seeds, "from_sfm_points": selection.from_points,
            "grown": selection.grown, "given": sorted(given.names),
            "given_margin_px": [round(w, 2) for w in widths], "margin_px": margin,
            "given_drawn_tight": [given.is_drawn_tight(i) for i in range(len(given.cams))],
            "given_pixels_selecting": [int(t.sum()) for t in given.tight]}
