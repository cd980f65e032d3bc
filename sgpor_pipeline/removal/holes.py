"""Deleting the object and finding what is truly unseen (DESIGN.md section 7).

After the object's Gaussians are gone, most of its mask is still covered by background that other
views saw: that is kept as fitted. Only mask pixels where the remaining Gaussians' accumulated
opacity stays low are a *hole*. The hole's depth is completed from the surrounding background by
harmonic interpolation of inverse depth (exact for planes: a plane's inverse depth is affine in
pixel coordinates, and the harmonic extension of affine boundary values is that affine function),
and new Gaussians are seeded on that completed surface for the later stages to colour.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.linalg import spsolve
from scipy.spatial import cKDTree

from ..config import added_param
from ..errors import PipelineError
from ..gaussians.model import GaussianModel, inverse_sigmoid, rgb_to_sh, sh_to_rgb
from ..imageio import to_float32
from ..scene import Camera
from ..scratch import Keeper, in_memory, release
from . import linsolve
from .multiview import nearest_per_pixel, pinned_parts
from .selection import (
    contribution_scores,
    in_visual_cone,
    median_spacing,
    render_channels,
    render_median_depth,
    within_margin,
)


@dataclass
class RemoveParams:
    score_threshold: float = 0.6  # a Gaussian with this share of its weight inside the masks is object
    min_weight: float = 0.05  # below this total blending weight over all views a Gaussian counts as unseen
    hull_dilate: int = 2  # pixels the masks are dilated by for the visual-hull floater test
    # A Gaussian whose CENTRE lies inside every view's (undilated) mask, in at least this many views,
    # is deleted even when much of its weight showed outside the masks: large Gaussians behind the
    # object peek out of its silhouette with their tails (a low object score) and, once the object is
    # gone, smear across the hole. Synthetic scene: 8 such Gaussians; deleting them takes delete-only
    # mask PSNR 23.21 -> 24.78. 0 = off (only the score decides inside the hull).
    hull_centre_views: int = 2
    # Mask pixels whose background opacity after deletion is below this are holes. 0.9, not 0.5: a
    # half-covered pixel renders darkened over the background colour. Measured (mask PSNR, final):
    # 0.5 / 0.9 / 0.95 / 0.99 -> synthetic inward 23.11 / 23.51 / 23.36 / 22.83, lund + box 13.90 /
    # 14.34 / 14.43 / 14.65; forward synthetic 20.16 / 19.92 (0.5 / 0.9).
    hole_alpha: float = 0.9
    # "unseen": holes are the mask pixels no other view showed (the method); "mask": the whole object
    # mask is a hole in every view (per-view 2D inpainting as in SPIn-NeRF: a baseline)
    hole_mode: str = "unseen"
    hole_close: int = 2  # morphological closing radius of the hole mask (pixels); removes specks
    # "unseen" also makes a hole of every mask pixel whose background point (lifted with the completed
    # depth) fewer than this many other views show outside their object masks and unoccluded
    # (view_depth_tol): Gaussians may cover a region no photo saw. After a fit that left the masked
    # pixels out, the opacity test cannot tell them: where no view saw the floor under an object
    # standing on it, the fit leaves opaque, unsupervised (dark) Gaussians, and they pass it
    # (benchmarks/removal.py's synthetic-box: 29 % of its mask pixels are background no other view
    # saw, ray-cast truth; the opacity test alone finds 17.5 %, precision 0.95, recall 0.57). lund +
    # box: the sky's Gaussians reach down behind the billboard. 0 = opacity only. The test needs a
    # depth on the surface (depth = "median"): with the expected depth, which lies in front of it
    # (-4 % median on the synthetic fit, -15 % at the 5th percentile), the floor next to the object,
    # lifted there, falls inside its silhouette in the other views and false holes cover the well
    # fitted background (the sphere demo: holes 4.9 -> 13 % of the mask, precision 0.18, mask PSNR
    # -1.1 dB), and the loose tolerance it needs (0.05) calls the Gaussians just under the box's
    # floor "observed". Measured (x86_64_v4, mask PSNR, fit.seed 0 / 1 / 2; holes against the
    # truth on seed 0 as share of the mask, precision / recall):
    #   min_views 0 (opacity only):              box 23.22 / 22.59 / 23.24 (17.5 %, 0.95 / 0.57),
    #                                            sphere 26.48 / 25.84 / 25.92 (4.9 %, 0.37 / 0.70)
    #   1, expected depth, view_depth_tol 0.05:  box 25.43 / 24.70 / 25.76 (34.8 %, 0.82 / 0.98),
    #                                            sphere 25.00 / 25.67 / 24.39 (13 %, 0.18 / 0.85)
    #   1, median depth, 0.05 (seed 0):          box 23.88 (30 %, 0.87 / 0.91), sphere 26.71 (8.4 %)
    #   1, median depth, 0.02 (the default):     box 25.77 / 25.48 / 26.26 (34 %, 0.85 / 0.99),
    #                                            sphere 26.51 / 26.21 / 26.06 (9.7 %, 0.27 / 1.00)
    # (fsr-refit on the box: 23.78 / 23.72 / 24.41.) lund + box, seed 0, VERSION 6 -> 7: ours 15.31 ->
    # 15.33, fsr-refit 15.03 -> 15.28 (its seeds sit on the median depth too). Recall decides on the
    # box (every unseen pixel left as "seen" shows the dark Gaussians), precision on the sphere (its
    # floor is well fitted, a fill is worse than it).
    min_views: int = 1
    # The rendered depth the stage lifts, completes and tests views with: "median" (where a pixel's
    # transmittance falls to 0.5: on the surface) or "expected" (sum w z / alpha: in front of it,
    # since Gaussians spread along a surface are composited in the order of their centres; synthetic
    # fit, outside the masks, three views: median -1 to -3 %, expected -5 to -6 % against the true
    # depth). The seeds and the lifted fills sit on the completed depth: median alone (min_views 1,
    # view_depth_tol 0.05) gave the sphere demo 26.71 against 25.22 with the expected depth there.
    depth: str = "median"
    # "unseen": a connected part of the object mask none of whose pixels lies farther than this many px
    # from its rim is a hole as a whole, covered background or not. Around a small object the photo's own
    # surroundings are within a block of every pixel, so a 2D fill is pinned on every side; the fitted
    # background behind it is only as good as the fit's geometry. Measured (benchmarks/removal.py, mask
    # PSNR / feat, fsr-refit on the same fit 15.35 / 0.190): lund + box (a sparse forward capture whose
    # far views see the box small: deepest mask pixel 6.7-14 px in views 1-19 of 28) 0 / 15 / 25 / 30 px:
    # 14.87 / 0.173, 15.25 / 0.180, 15.35 / 0.177, 15.37 / 0.176 (the far views reach fsr-refit's
    # scores, the near views keep ours' lead); synthetic (well fitted, masks 28-34 px deep) 24.99 at 0,
    # 15 and 25 (no view affected), 23.56 at 30: its seen background (28 dB) beats any 2D fill. At lund's
    # held-out views (--novel protocol, 25 px): 14.73 / 0.232 -> 14.90 / 0.236 (fsr-refit 15.18 / 0.264).
    # The rule helps where the fit's geometry is poor, which the mask size does not tell: off by default.
    thin_mask_rim: float = added_param(0.0)
    # Background Gaussians with at least this share of their blending weight (all views) inside the
    # object masks get their DC colour clamped to [0, 1] (0 = off). The fit may leave over-bright
    # colours (> 1) that other Gaussians in front or their own low opacity compensate in the views that
    # trained them; the object hid these Gaussians in some views, which then show them composited
    # differently, untrained. lund + box, seed 0: 5,791 of 76,582 background DC colours exceed 1; the
    # scene after deletion, full SH, at 0 / 0.02 / 0.1 / 0.3: mask PSNR 14.34 / 14.60 / 14.58 / 14.34
    # (far views 9-17: +0.6 to +1.4 dB; 2,850 Gaussians clamped at 0.02), outside the masks 23.33 /
    # 23.29 / 23.31 / 23.33; clamping every Gaussian: 14.60 / 23.21. The synthetic scene: no change.
    clamp_share: float = 0.02
    # Drop the hole seeds that another view shows in front of background it saw (free-space carving;
    # see seed_hole_gaussians). Where a hole's completed depth is too near, its seeds float in front of
    # the scene; unsupervised in the other views (finetune.seen_weight 0), the re-fit keeps them there.
    # Measured (benchmarks/removal.py, seed 0, mask PSNR; seeds before -> after): statue-box 21.67 ->
    # 22.67 (1,274 -> 178 seeds; the seen part of the mask 24.07 -> 25.71 dB, delete-only 25.66),
    # synthetic 26.49 -> 26.51 (733 -> 447), lund + box 14.92 -> 14.92 (7,328 -> 6,223).
    carve_seeds: bool = True
    # The seeds' scales halved (up to three times) while a view shows background it saw behind a seed
    # within 1.5 x its projected scale of its centre (footprint_scales): carving tests the centre only,
    # and a seed on a completed surface that lies in front of background seen beside the hole (across a
    # depth step the interpolation smooths over) spreads its first colour over it. Lund + box, fit seed 0:
    # the seeds changed 10,709 of the 18,431 seen pixels inside the masks (by > 0.05), 84 % of them in
    # front of that background, 71 % within 3 px of the view's own hole; that seen part scored 14.78 dB
    # without the seeds, 13.48 with them, 14.32 after the finetune (.dev/s44/seed_occlusion.py).
    # benchmarks/removal.py, mask PSNR of ours off -> on, fit seed 0 / 1 / 2 (mean change): statue-box
    # 22.33 / 22.00 / 21.84 -> 22.53 / 22.10 / 22.04 (+0.17; feat lower in all three), synthetic 26.53 /
    # 26.66 / 25.49 -> 26.48 / 26.71 / 25.50 (0.00), synthetic-box 27.88 / 27.90 / 27.60 -> 27.88 /
    # 27.88 / 27.60 (-0.01), lund + box 15.60 / 16.01 / 15.85 -> 15.61 / 16.05 / 15.78 (-0.01; its holes
    # pooled 12.42 -> 12.66 and the seen part 14.32 -> 14.64 at seed 0). Held-out views (--novel, seed 0):
    # synthetic 25.71 -> 25.75 (feat 0.086 -> 0.084), lund + box 15.59 -> 15.70 (feat 0.206 -> 0.201).
    # mip360 kitchen from one mask: the final renders look the same (no gaps where seeds shrank).
    carve_footprint: bool = True
    # relative: a point deeper than another view's surface is occluded there (min_views; 0.05 was
    # needed with the expected depth, see min_views: holes against the truth with the median depth,
    # tolerance 0.01 / 0.02 / 0.03 / 0.05: box recall 1.00 / 0.99 / 0.97 / 0.91, sphere precision
    # 0.22 / 0.27 / 0.30 / 0.31)
    view_depth_tol: float = 0.02
    # A mask pixel whose background other views saw is a hole all the same when the render there
    # disagrees with what those views' photos show at its point (lifted with the completed depth): the
    # median over them of the mean absolute RGB difference, both blurred, above this (0 = off). The fit's
    # background behind the object is only as good as its geometry: where it is misplaced or smeared,
    # the views that saw the point show something else, and a fill pinned to the photo around the mask
    # is better. On lund + box (the removal benchmark's fit, seed 0), pooled over the mask pixels other
    # views saw, by disagreement: below 0.1 the render scores 14.9-15.5 dB against the truth and an FSR
    # fill from the photo 16.1-16.4; 0.1-0.2: 13.8 / 15.1; above 0.2: 12.8 / 11.7; on the synthetic
    # scene the render wins in every bin (31.4 dB below 0.03, 20.0 at 0.1-0.2 against FSR's 16.9) and
    # only 1.6 % of those pixels lie above 0.1. benchmarks/removal.py, mask PSNR of ours, fit.seed
    # 0 / 1 / 2 (x86_64_v4), off -> 0.15: lund + box 15.28 / 15.73 / 15.83 (mean 15.61) -> 15.61 / 16.02 /
    # 15.89 (15.84; fsr-refit 15.62 / 15.70 / 15.74, 15.69); synthetic-box 27.80 / 28.18 / 28.22 (28.07)
    # -> 27.34 / 28.38 / 28.79 (28.17); synthetic (seed 0) 26.59 -> 26.60 (162 pixels flagged); statue +
    # box (seed 0) 21.61 -> 21.58 (fsr-refit 20.40). At 0.1:
    # lund 15.81, synthetic-box 28.15, but synthetic 26.17.
    max_disagreement: float = 0.15
    view_mask_dilate: int = 2  # px: other views' object masks are dilated by this (their edge pixels mix)
    # Hole depths completed view by view, smallest hole first, each constrained by the hole surfaces
    # already completed (one surface for what no photo saw, so the views' fills and seeds agree; see
    # complete_depths_jointly); False = every view's hole completed on its own.
    consistent_depth: bool = True
    # A hole's completed depth is at least the deleted object's depth there (what it hid lies behind
    # it): the surroundings' rendered depth can be far nearer than the object (lund + box: 2-3x,
    # semi-transparent Gaussians in front of the street), and a hole completed in front of the object
    # is seeded in mid-air, in space other views see. Lund + box: 39 % of the seeds lay in front of the
    # billboard in some view and 1970 opaque hole Gaussians floated in the street after the finetune;
    # with the floor 3.1 % and 293. Mask PSNR, ours / fsr-refit: synthetic 25.37 / 20.26 -> 25.37 /
    # 21.03, lund 14.29 / 14.09 -> 13.51 / 15.18: the views' hole surfaces now agree, so ours carries the
    # reference's fill into the other views (14000+ pixels instead of 2) and the re-fit keeps it sharp
    # instead of averaging disagreeing fills into a blur, which PSNR prefers (inpaint.multiview = false,
    # independent fills: 14.36; the fsr baseline's independent smooth fills: 15.18).
    behind_object: bool = True
    # Where a mask pixel's row meets the background at clearly different depths left and right of the
    # mask (the farther side at least this x the nearer, each read 2 px outside the mask), its hole is
    # completed no nearer than the farther side (far_side_floor); 0 = off. What an object hides across
    # a depth step continues the background side (depth-image-based rendering fills disocclusions from
    # the background side the same way); the harmonic completion put it on a surface between the two,
    # where the views' fills disagree and the re-fit averages them. Where both sides lie at about one
    # depth (a floor under the object) the harmonic completion stands. Mask PSNR (benchmarks/removal.py,
    # fit seed 0 | 1 | 2, ours / fsr-refit), off -> 1.5: lund + box 15.84 / 15.68 | 16.35 / 16.10 |
    # 16.09 / 16.21 -> 16.01 / 16.03 | 16.49 / 16.42 | 16.18 / 16.28; statue-box (seed 0) 23.08 / 21.01
    # -> 23.19 / 22.30; synthetic 26.77, synthetic-box 28.13 unchanged (no step reaches 1.5). Without
    # the ratio test (every row's farther side) synthetic 26.55, synthetic-box 27.56: a floor's
    # hole went 1-4 % deeper. One floor per mask part from its whole rim: its farthest depth lund + box
    # 16.05; its 90 % quantile lund + box 16.04, synthetic 25.73, synthetic-box 26.14. 0 or >= 1.
    far_side_ratio: float = 1.5
    # The mask pixels whose background lies on the plane under the object are holes too, seen or not
    # (removal.plane.under_object: the plane of the thick planar holes; the object's visual hull seen
    # straight down its normal, grown by 2 %; written to under_object/, and the inpaint stage's plane
    # texture then fills the texels under it too). A real object darkens what lies under it (its
    # contact shadow), and what the views saw there through its gaps, at grazing angles, is that
    # shadow: on mip360 kitchen (no truth) it takes the bulldozer's dark footprint out of every view.
    # Our synthetic objects cast no shadow and the hull is larger than the object, so the truth there
    # can only lose: synthetic-box (fit seed 0) ours 28.77 -> 24.19 mask PSNR (with a plane texture
    # margin of 0.5: 27.96 -> 26.20, no-sbm 28.49 -> 25.30); the sphere, lund + box and statue + box
    # have no thick planar hole (unchanged). Off by default.
    under_object: bool = added_param(False)
    # under_object's plane refitted to the floor seen within this many px of the holes, as the inpaint
    # stage's plane texture is (inpaint.plane_rim); 0: fitted to the holes' completed depths alone.
    under_object_rim: int = added_param(0)
    # What the inpainter sees around the hole and takes its source blocks from (context/<view>.png):
    # "photos": the photo outside the object mask dilated by context_margin px (the finetune trusts the
    # photos there too), the render inside; "renders": the render everywhere. The fitted renders are a
    # blur of the photos (lund + box: the 1500-iteration fit), so blocks matched and copied from them
    # are blurred and their colours averaged. Mask PSNR renders / photos: synthetic 25.37 / 25.39,
    # lund + box 13.51 / 13.77 (the brick facade continues into the hole instead of a white smear).
    context: str = "photos"
    context_margin: int = 2
    # The rim: pixels outside the object mask, within context_margin px of a hole, whose background
    # opacity is below this are holes too. Deleting the object also deletes the part of its Gaussians'
    # footprints that spilled over the mask edge, so the render there (the context) is darkened; SBM
    # matched the dark ring and grew it into dark blotches and outlines (mip360-room: the carpet fill
    # under the slippers). Measured, mask PSNR off / 0.5 / 0.7 / 0.9: synthetic 25.84 / 25.84 / 25.88 /
    # 25.73, lund + billboard 14.33 / 14.29 / 14.27 / 14.27; room (no ground truth): 0.7 and 0.9 remove
    # the blotches, 0.5 only some. Also with hole_mode "mask" (the fsr-refit baseline: synthetic 21.19 ->
    # 21.12, lund 15.03 -> 15.05). 0 = off.
    rim_alpha: float = 0.7
    seed_stride: int = 3  # one new Gaussian per stride x stride hole pixels per view (before merging)
    seed_opacity: float = 0.7
    # Seeds sit this many seed spacings behind the completed depth, along their view's ray (so they
    # still cover the same hole pixels there). The rasterizer composites Gaussians in the order of
    # their centres' depth: a seed on the surface is drawn in front of part of the background fitted
    # there, and where another view saw that surface the seed's blurry first colour paints over it
    # (synthetic, fit.seed 0: the seen background inside the masks falls from 26.58 to 23.54 dB once
    # the seeds are added, and the finetune leaves that band unsupervised). Behind the surface a seed
    # shows where the background is transparent (the holes) and less where it is opaque: 2 / 4 / 8 ->
    # 23.89 / 24.26 / 25.12 dB. Mask PSNR after the finetune (benchmarks/removal.py, x86_64_v4, fit.seed
    # 0 / 1 / 2), offset 0 / 1 / 2 / 4 / 8: 25.32 / 25.56 / 25.32 (mean 25.40), 25.61 / 25.72 / 25.51
    # (25.61), 25.74 / 25.84 / 25.70 (25.76), 25.96 / 25.84 / 25.92 (25.91), 26.08 / 25.64 / 25.89
    # (25.87); the holes alone 18.48 / 18.29 / 18.41 at 0, 18.75 / 18.59 / 18.55 at 4. Lund + box
    # (seed 0) 15.32 / 15.33 (2) / 15.31 (4), statue + box 21.88 / 21.89 (2) / 21.95 (4): level.
    seed_depth_offset: float = 4.0
    max_seeds: int = 30000
    backend: str = "auto"


def objects_to_delete(model: GaussianModel, cameras: list[Camera], masks: list[np.ndarray],
                      object_ids: np.ndarray, params: RemoveParams,
                      scores: tuple[np.ndarray, np.ndarray] | None = None
                      ) -> tuple[np.ndarray, dict, np.ndarray, np.ndarray]:
    """The object's Gaussians (from the masks stage, confirmed with every view's mask) plus floaters
    inside the object's visual hull that no view shows outside the masks, plus every Gaussian whose
    centre no view shows outside its mask (``hull_centre_views``).

    Returns (delete [N] bool, counts per reason, surface [N] bool, share [N]): ``surface`` = the object
    proper (masks stage and score), without the floaters and hull centres, which may lie anywhere in
    the visual cone, even behind the background (:func:`object_depth` renders the surface only);
    ``share`` = each Gaussian's blending weight inside the masks over its total (0 where unseen).
    ``scores``: :func:`contribution_scores` of these masks when already rendered."""
    inside, total = scores if scores is not None else contribution_scores(model, cameras, masks, params.backend)
    with np.errstate(invalid="ignore", divide="ignore"):
        score = np.where(total > 0, inside / total, np.nan)
    delete = np.zeros(len(model), bool)
    delete[object_ids] = True
    by_score = (total >= params.min_weight) & (score >= params.score_threshold)
    means = model.means.detach().double().numpy()
    hull = in_visual_cone(means, cameras, masks, params.hull_dilate)
    floaters = hull & ~((total >= params.min_weight) & (score < 0.5))
    centred = (in_visual_cone(means, cameras, masks, 0, min_views=params.hull_centre_views)
               if params.hull_centre_views > 0 else np.zeros(len(model), bool))
    stats = {"from_masks_stage": int(delete.sum()), "by_score": int((by_score & ~delete).sum())}
    delete |= by_score
    surface = delete.copy()
    stats["floaters"] = int((floaters & ~delete).sum())
    delete |= floaters
    stats["hull_centres"] = int((centred & ~delete).sum())
    delete |= centred
    stats["deleted"] = int(delete.sum())
    return delete, stats, surface, np.nan_to_num(score, nan=0.0)


def closer_to_core(means: np.ndarray, core: np.ndarray, margin: np.ndarray, neighbours: int = 8) -> np.ndarray:
    """[N] bool: the ``margin`` Gaussians nearer (along a chain of margin Gaussians, by their centres'
    distances) to a ``core`` Gaussian than to one of the rest (neither core nor margin); ties go to
    the core. With nothing outside the margin, all of it is core.

    Each margin Gaussian is linked to its ``neighbours`` nearest margin Gaussians and to the nearest
    core and the nearest other Gaussian among its ``neighbours`` nearest outside the margin; the two
    sides' shortest paths through those links decide (a multi-source Dijkstra)."""
    from scipy.sparse.csgraph import dijkstra

    out = np.zeros(len(means), bool)
    idx = np.flatnonzero(margin)
    outside = np.flatnonzero(~margin)
    if len(idx) == 0:
        return out
    if len(outside) == 0:
        out[idx] = True
        return out
    m = len(idx)
    rows, cols, weights = [], [], []
    if m > 1:
        k = min(neighbours + 1, m)
        dist, near = cKDTree(means[idx]).query(means[idx], k=k)
        dist, near = dist.reshape(m, k)[:, 1:], near.reshape(m, k)[:, 1:]
        rows.append(np.repeat(np.arange(m), k - 1))
        cols.append(near.ravel())
        weights.append(dist.ravel())
    k = min(neighbours, len(outside))
    dist, near = cKDTree(means[outside]).query(means[idx], k=k)
    dist, near = dist.reshape(m, k), outside[near.reshape(m, k)]
    for side, node in ((core[near], m), (~core[near], m + 1)):  # node m: the core, m + 1: the rest
        has = side.any(axis=1)
        first = np.where(has, np.where(side, dist, np.inf).min(axis=1), np.inf)
        rows.append(np.full(int(has.sum()), node))
        cols.append(np.flatnonzero(has))
        weights.append(first[has])
    r, c, w = (np.concatenate(a) for a in (rows, cols, weights))
    w = np.maximum(w, 1e-12)  # (a zero weight would read as no link)
    graph = coo_matrix((w, (r, c)), shape=(m + 2, m + 2)).tocsr()
    to_core, to_rest = dijkstra(graph, directed=False, indices=[m, m + 1])[:, :m]
    out[idx] = to_core <= to_rest
    return out


def clamp_dc_colours(model: GaussianModel, select: np.ndarray) -> int:
    """Clamp the DC colour of the Gaussians where ``select`` is True to [0, 1], in place (the higher SH
    bands are kept); returns how many changed."""
    sel = torch.from_numpy(np.asarray(select, bool))
    sh0 = model.params["sh0"]
    with torch.no_grad():
        rgb = sh_to_rgb(sh0[sel, 0, :])
        clamped = rgb.clamp(0.0, 1.0)
        sh0[sel, 0, :] = rgb_to_sh(clamped)
    return int((clamped != rgb).any(1).sum())


def render_background(model: GaussianModel, camera: Camera, backend: str = "auto", depth: str = "expected"
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rgb [H,W,3], alpha [H,W], depth [H,W]) of the DC colours (view-independent). ``depth``:
    "expected" (sum w z / alpha) or "median" (where the transmittance falls to 0.5: on the
    surface; the expected depth where the pixel never gets that opaque)."""
    img, alpha, _ = render_channels(model, camera, model.colors_dc(), backend, depth=True)
    z = img[..., 3]
    if depth == "median":
        med = render_median_depth(model, camera, backend)
        z = np.where(med > 0, med, z)
    elif depth != "expected":
        raise PipelineError(f"unknown remove.depth {depth!r}", fix='use "expected" or "median"')
    return img[..., :3].clip(0.0, 1.0), alpha, z


def hole_mask(object_mask: np.ndarray, alpha: np.ndarray, params: RemoveParams,
              unobserved: np.ndarray | None = None) -> np.ndarray:
    """The part of ``object_mask`` that the background left after deletion does not cover (opacity
    below ``hole_alpha``) or that too few other views observed (``unobserved``, see
    :func:`observing_views`), closed morphologically; with ``hole_mode="mask"`` the whole mask. Either
    plus its rim outside the mask (``rim_alpha``)."""
    if params.hole_mode not in ("unseen", "mask"):
        raise PipelineError(f"unknown remove.hole_mode {params.hole_mode!r}", fix='use "unseen" or "mask"')
    if params.hole_mode == "mask":
        hole = object_mask.copy()
    else:
        hole = object_mask & (alpha < params.hole_alpha)
        if params.thin_mask_rim > 0:
            hole |= pinned_parts(object_mask, params.thin_mask_rim)
        if unobserved is not None:
            hole |= object_mask & unobserved
        if params.hole_close > 0 and hole.any():
            k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * params.hole_close + 1,) * 2)
            hole = cv2.morphologyEx(hole.astype(np.uint8), cv2.MORPH_CLOSE, k) > 0
            hole &= object_mask
    if params.rim_alpha > 0 and params.context_margin > 0 and hole.any():
        # (inside the context's render band: context_image grows the mask the same way)
        hole |= within_margin(hole, params.context_margin) & ~object_mask & (alpha < params.rim_alpha)
    return hole


DISAGREEMENT_BLUR = 1.5  # px: renders are smoother than photos; compare both blurred


def _blurred(img: np.ndarray | None) -> np.ndarray | None:
    """``img`` (float in [0, 1], or uint8) blurred by ``DISAGREEMENT_BLUR`` px, float32."""
    return None if img is None else cv2.GaussianBlur(to_float32(img), (0, 0), DISAGREEMENT_BLUR)


def observing_views(cameras: list[Camera], masks: list[np.ndarray], depths: list[np.ndarray],
                    pixels: list[np.ndarray], params: RemoveParams, renders: list[np.ndarray] | None = None,
                    photos: list[np.ndarray | None] | None = None, keep: Keeper = in_memory
                    ) -> tuple[list[np.ndarray], list[np.ndarray] | None]:
    """Per view i, for its ``pixels[i]`` (HxW bool): how many OTHER views show the pixel's background
    point (lifted with ``depths[i]``): it projects inside their image, outside their (dilated) object
    mask, and not behind their own surface (``depths``: completed background z-depth of every view).
    Returns (HxW int32 maps, 0 outside ``pixels``; with ``renders`` and ``photos`` (float in [0, 1] or
    uint8), HxW float32 maps of how far view i's render there is from what those views' photos show at
    the point: the median over them of the mean absolute RGB difference, both blurred by
    ``DISAGREEMENT_BLUR`` px; NaN where no view with a photo shows it, or outside ``pixels``). ``keep``
    holds the per-view arrays (the blurred photos, the maps returned; see :mod:`sgpor_pipeline.scratch`)."""
    d = max(0, params.view_mask_dilate)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * d + 1, 2 * d + 1)) if d else None
    dilated = [m if kernel is None else cv2.dilate(m.astype(np.uint8), kernel) > 0 for m in masks]
    compare = renders is not None and photos is not None
    # float16: every view's is held at once (and the photos beside them); its rounding (< 0.001) is far
    # below any useful max_disagreement
    blurred_photos = keep("blurred_photos", (None if ph is None else _blurred(ph).astype(np.float16)
                                             for ph in photos)) if compare else []
    counts = keep("counts", [None] * len(cameras))
    disagreements = keep("disagreements", [None] * len(cameras)) if compare else None
    for i, cam_i in enumerate(cameras):
        out = np.zeros(pixels[i].shape, np.int32)
        ys, xs = np.nonzero(pixels[i])
        dis = np.full(pixels[i].shape, np.nan, np.float32)
        if len(ys) == 0:
            counts[i] = out
            if compare:
                disagreements[i] = dis
            continue
        z = depths[i][ys, xs].astype(np.float64)
        good = np.isfinite(z) & (z > 0)
        X = cam_i.unproject(ys, xs, np.where(good, z, 1.0))
        count = np.zeros(len(ys), np.int32)
        own = _blurred(renders[i])[ys, xs] if compare else None
        diffs = []
        for j, cam in enumerate(cameras):
            if j == i:
                continue
            px, zj, inside = cam.pixels(X)
            ok = good & inside
            u, v = px[ok, 0], px[ok, 1]
            ok[ok] = ~dilated[j][v, u] & ~(zj[ok] > depths[j][v, u] * (1 + params.view_depth_tol))
            count += ok
            if compare and blurred_photos[j] is not None and ok.any():
                diff = np.full(len(ys), np.nan, np.float32)
                diff[ok] = np.abs(blurred_photos[j][px[ok, 1], px[ok, 0]].astype(np.float32) - own[ok]).mean(axis=1)
                diffs.append(diff)
        out[ys, xs] = count
        counts[i] = out
        if diffs:
            stacked = np.stack(diffs)
            seen_by = ~np.isnan(stacked).all(axis=0)
            dis[ys[seen_by], xs[seen_by]] = np.nanmedian(stacked[:, seen_by], axis=0)
        if compare:
            disagreements[i] = dis
    release(blurred_photos)
    return counts, disagreements


def complete_depth(depth: np.ndarray, valid: np.ndarray, hole: np.ndarray,
                   floor: np.ndarray | None = None) -> np.ndarray:
    """Fill ``hole`` by harmonic interpolation of inverse depth from the valid pixels around it.

    Unknown pixels = the hole plus invalid pixels connected to it; the Laplace equation is solved
    on them with the valid neighbours as boundary values (a sparse linear system). ``floor`` (HxW,
    0 = none): the completed hole is pushed back to at least this depth (the deleted object's
    surface: what it hid lies behind it)."""
    out = depth.astype(np.float64).copy()
    unknown = hole | ~valid
    if not hole.any():
        return out.astype(np.float32)
    good = valid & ~hole & (depth > 0)
    if not good.any():
        return _apply_floor(out, hole, floor).astype(np.float32)
    inv = np.zeros_like(out)
    inv[good] = 1.0 / out[good]
    h, w = depth.shape
    idx = -np.ones((h, w), np.int64)
    ys, xs = np.nonzero(unknown)
    idx[ys, xs] = np.arange(len(ys))
    n = len(ys)
    rows, cols, vals = [np.arange(n)], [np.arange(n)], [np.zeros(n)]
    rhs = np.zeros(n)
    diag = np.zeros(n)
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        ny, nx = ys + dy, xs + dx
        inside = (ny >= 0) & (ny < h) & (nx >= 0) & (nx < w)
        diag[inside] += 1.0
        nyi, nxi = ny[inside], nx[inside]
        neighbour_unknown = unknown[nyi, nxi]
        src = np.flatnonzero(inside)
        rows.append(src[neighbour_unknown])
        cols.append(idx[nyi[neighbour_unknown], nxi[neighbour_unknown]])
        vals.append(-np.ones(int(neighbour_unknown.sum())))
        known = ~neighbour_unknown
        rhs[src[known]] += inv[nyi[known], nxi[known]] * good[nyi[known], nxi[known]]
        # Invalid-but-not-hole neighbours that are not good carry no value: treat as Neumann (drop).
        bad = known & ~good[nyi, nxi]
        diag[src[bad]] -= 1.0
    vals[0] = diag
    A = coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)).tocsr()
    # Components of unknown pixels that touch no valid pixel have a singular block: regularise lightly
    # towards the median inverse depth so they get a finite, plausible value.
    reg = 1e-6
    A = A + reg * coo_matrix((np.ones(n), (np.arange(n), np.arange(n))), shape=(n, n)).tocsr()
    rhs += reg * float(np.median(inv[good]))
    # (a direct solver's fill-in would take GBs on a large hole: removal/linsolve.py)
    sol = linsolve.solve_spd_multigrid(A, rhs) if linsolve.large(n) else spsolve(A, rhs)
    sol = np.clip(sol, 1e-6, None)
    out[ys, xs] = 1.0 / sol
    return _apply_floor(out, hole, floor).astype(np.float32)


def _apply_floor(depth: np.ndarray, hole: np.ndarray, floor: np.ndarray | None) -> np.ndarray:
    if floor is None:
        return depth
    lift_to = hole & (floor > 0) & ~(depth >= floor)  # also replaces non-finite depths
    depth[lift_to] = floor[lift_to]
    return depth


def far_side_floor(mask: np.ndarray, depth: np.ndarray, valid: np.ndarray, ratio: float, gap: int = 2
                   ) -> np.ndarray:
    """Per ``mask`` pixel: the farther of the depths at the nearest ``valid`` pixels left and right of
    it in its row that lie ``gap`` px or more outside the mask (their edge mixes the object), where it
    is at least ``ratio`` x the nearer one; 0 elsewhere (no floor), also where a side is missing (the
    image's border, no valid pixel): one side shows no step. See :attr:`RemoveParams.far_side_ratio`."""
    h, w = mask.shape
    near_mask = cv2.dilate(mask.astype(np.uint8), np.ones((1, 2 * gap + 1), np.uint8)) > 0
    good = valid & np.isfinite(depth) & (depth > 0) & ~near_mask
    cols = np.broadcast_to(np.arange(w), (h, w))
    left = np.maximum.accumulate(np.where(good, cols, -1), axis=1)  # nearest good column at or left of x
    right = np.minimum.accumulate(np.where(good, cols, w)[:, ::-1], axis=1)[:, ::-1]
    rows = np.arange(h)[:, None]
    z = np.where(good, depth, 0.0).astype(np.float32)
    z_left = np.where(left >= 0, z[rows, np.clip(left, 0, w - 1)], 0.0)
    z_right = np.where(right < w, z[rows, np.clip(right, 0, w - 1)], 0.0)
    far, near = np.maximum(z_left, z_right), np.minimum(z_left, z_right)
    step = (near > 0) & (far >= ratio * near)
    return np.where(mask & step, far, 0.0).astype(np.float32)


def object_depth(obj: GaussianModel, camera: Camera, backend: str = "auto", min_alpha: float = 0.5) -> np.ndarray:
    """z-depth of the deleted object's surface where it covers a pixel (alpha >= ``min_alpha``), else
    0: the lower bound of the hole depth (:func:`complete_depth`'s ``floor``)."""
    if len(obj) == 0:
        return np.zeros((camera.height, camera.width), np.float32)
    _, alpha, depth = render_background(obj, camera, backend)
    return np.where((alpha >= min_alpha) & np.isfinite(depth), depth, 0.0).astype(np.float32)


def complete_depths_jointly(cameras: list[Camera], depths: list[np.ndarray], valids: list[np.ndarray],
                            holes: list[np.ndarray], floors: list[np.ndarray] | None = None,
                            keep: Keeper = in_memory) -> list[np.ndarray]:
    """:func:`complete_depth` for every view, the smallest hole first; the hole surfaces completed so
    far are splatted into each later view's hole (nearest point per pixel) and fixed there, so the
    views complete one surface instead of one each, and the inpaint stage's reference fill can be
    carried into the other views (its projection needs the depths to agree within 2 %).

    Smallest first: a small hole is completed from a nearby boundary, the best-known part of the
    surface; the largest hole (the inpaint reference) then inherits it. Measured (mask PSNR final /
    hole depth error against the truth / reference pixels carried into other views):
    synthetic 25.34 / 2.2 % / 1135 per view alone, 25.37 / 2.0 % / 988 smallest first, 25.21 / 3.6 %
    largest first (before ``floors``); lund + box (28 views, holes 80 % of the mask), with ``floors``:
    13.51 / - / 14000+ jointly: the re-fit reproduces the reference's fill when the surfaces agree
    (sharper, but a hallucinated detail costs PSNR against a blur; per view alone and without the
    floors the re-fit averaged fills on surfaces 13-170 % apart in depth, partly in front of the
    object: 14.34).

    ``floors`` (per view, see :func:`object_depth`): a view's hole depth is at least its floor, and a
    surface point completed by another view is used only where it lies behind this view's floor: a
    hole surface completed in one view can pass through space another view sees in front of the
    object (lund + box: the fitted background around the billboard renders 2-3x nearer than the
    billboard itself, so the holes were completed in front of it and one view's surface cut through
    the next's: completed hole depths of 0.2 where the billboard stands at 1.9). ``keep`` holds the
    completed depths (:mod:`sgpor_pipeline.scratch`)."""
    out = keep("completed_depths", [None] * len(cameras))
    done: list[np.ndarray] = []
    for i in sorted(range(len(cameras)), key=lambda k: int(holes[k].sum())):
        cam, hole = cameras[i], holes[i]
        floor = None if floors is None else floors[i]
        depth, valid, free = depths[i].astype(np.float32), valids[i].copy(), hole.copy()  # (astype copies)
        if done and hole.any():
            px, z, inside = cam.pixels(np.concatenate(done))
            px, z = px[inside], z[inside]
            hit = hole[px[:, 1], px[:, 0]]
            if floor is not None:
                hit &= z >= floor[px[:, 1], px[:, 0]]
            px, z = px[hit], z[hit]
            if len(z):
                lin = px[:, 1] * hole.shape[1] + px[:, 0]
                keep = nearest_per_pixel(lin, z)
                lin = lin[keep]
                depth.reshape(-1)[lin] = z[keep]
                valid.reshape(-1)[lin] = True
                free.reshape(-1)[lin] = False
        completed = complete_depth(depth, valid, free, floor)
        out[i] = completed
        ys, xs = np.nonzero(hole)
        if len(ys):
            done.append(cam.unproject(ys, xs, completed[ys, xs]))
    return out


def unpremultiplied(rgb: np.ndarray, alpha: np.ndarray, min_alpha: float = 0.5) -> np.ndarray:
    """The colour of what covers each pixel: the render (composited over black) divided by its opacity
    where that is at least ``min_alpha``. Next to a hole the deletion left the background partly
    transparent, and its render darker than the surface it shows."""
    a = np.asarray(alpha, np.float32)[..., None]
    return np.where(a >= min_alpha, np.clip(rgb / np.maximum(a, 1e-6), 0.0, 1.0), rgb).astype(np.float32)


def context_image(render: np.ndarray, photo: np.ndarray | None, mask: np.ndarray, margin: int) -> np.ndarray:
    """The inpainter's image: ``photo`` outside ``mask`` dilated by ``margin`` px (its edge pixels mix
    object and background), ``render`` inside; the render alone when there is no photo."""
    if photo is None:
        return render
    return np.where(within_margin(mask, margin)[..., None], render, photo).astype(render.dtype)


def initial_colour(render: np.ndarray, hole: np.ndarray, as_uint8: bool = False) -> np.ndarray:
    """A first colour for the hole (OpenCV Telea diffusion from its border): seeds' starting colour.
    Float32 in [0, 1], or with ``as_uint8`` (a hole to fill) the 8-bit image it comes from, a quarter of
    its size (:func:`~sgpor_pipeline.imageio.to_float32` gives the same values)."""
    if not hole.any():
        if as_uint8:
            raise ValueError("initial_colour(as_uint8=True) needs a hole")
        return render
    img8 = (render.clip(0, 1) * 255 + 0.5).astype(np.uint8)
    filled = cv2.inpaint(img8, hole.astype(np.uint8), 3, cv2.INPAINT_TELEA)
    return filled if as_uint8 else to_float32(filled)


def seed_hole_gaussians(cameras: list[Camera], holes: list[np.ndarray], depths: list[np.ndarray],
                        colours: list[np.ndarray], spacing: float, max_sh_degree: int,
                        params: RemoveParams, seed: int = 0,
                        observed: list[np.ndarray] | None = None) -> GaussianModel:
    """New isotropic Gaussians on the completed hole surfaces of every view, merged on a voxel grid
    (``colours``: float in [0, 1] or uint8 per view; None for a view without a hole).

    With ``observed`` (per view, the pixels whose background was seen: opaque and not a hole), a seed
    that any view shows in front of such a pixel's surface (nearer than its depth by more than
    ``view_depth_tol``) is dropped: that view saw through the place, so nothing is there."""
    pts, cols = [], []
    s = max(1, params.seed_stride)
    for cam, hole, depth, colour in zip(cameras, holes, depths, colours):
        grid = np.zeros_like(hole)
        grid[s // 2::s, s // 2::s] = True
        ys, xs = np.nonzero(hole & grid & (depth > 0))
        if ys.size == 0:
            continue
        z = depth[ys, xs]
        if params.seed_depth_offset:  # along the ray: z grows by the offset's share of the ray length
            ray = np.linalg.norm(cam.unproject(ys, xs, np.ones(len(ys))) - cam.center, axis=1)
            z = z + params.seed_depth_offset * spacing / ray
        pts.append(cam.unproject(ys, xs, z))
        cols.append(to_float32(colour[ys, xs]))
    if not pts:
        return GaussianModel.empty(0, max_sh_degree)
    xyz = np.concatenate(pts)
    rgb = np.concatenate(cols)
    if observed is not None:
        free = np.zeros(len(xyz), bool)
        for cam, seen, depth in zip(cameras, observed, depths):
            px, z, inside = cam.pixels(xyz)
            u, v = px[inside, 0], px[inside, 1]
            free[inside] |= seen[v, u] & (z[inside] < depth[v, u] * (1 - params.view_depth_tol))
        xyz, rgb = xyz[~free], rgb[~free]
        if not len(xyz):
            return GaussianModel.empty(0, max_sh_degree)
    voxel = max(spacing, 1e-9)
    keys = np.floor(xyz / voxel).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    first = np.sort(first)
    if len(first) > params.max_seeds:
        first = np.sort(np.random.default_rng(seed).choice(first, params.max_seeds, replace=False))
    xyz, rgb = xyz[first], rgb[first]
    d, _ = cKDTree(xyz).query(xyz, k=min(4, len(xyz)))
    scale = np.clip(np.mean(d[:, 1:], axis=1) if d.ndim == 2 and d.shape[1] > 1 else np.full(len(xyz), voxel),
                    0.25 * voxel, 4 * voxel)
    if observed is not None and params.carve_footprint:
        scale = footprint_scales(cameras, observed, depths, xyz, scale, params.view_depth_tol)
    model = GaussianModel.empty(len(xyz), max_sh_degree)
    with torch.no_grad():
        model.params["means"].copy_(torch.from_numpy(xyz).float())
        model.params["scales"].copy_(torch.from_numpy(np.log(scale)).float()[:, None].expand(-1, 3))
        model.params["opacities"].fill_(float(inverse_sigmoid(torch.tensor(params.seed_opacity))))
        model.params["sh0"].copy_(rgb_to_sh(torch.from_numpy(rgb).float())[:, None, :])
    return model


def footprint_scales(cameras: list[Camera], observed: list[np.ndarray], depths: list[np.ndarray], xyz: np.ndarray,
                     scale: np.ndarray, depth_tol: float, reach: float = 1.5, halvings: int = 3) -> np.ndarray:
    """The seeds' scales, halved (at most ``halvings`` times) while any view shows background it saw
    behind the seed within ``reach`` x its projected scale of the seed's centre (eight points on that
    circle and four on half of it): the seed's splat would paint over that background. Carving
    (:func:`seed_hole_gaussians`) tests the centre only; a seed on a hole's completed surface, which is
    interpolated across the hole and may lie in front of background seen beside it, spreads over it."""
    scale = np.asarray(scale, np.float64).copy()
    angles = np.linspace(0.0, 2.0 * np.pi, 8, endpoint=False)
    ring = np.concatenate([np.stack([np.cos(angles), np.sin(angles)], 1),
                           0.5 * np.stack([np.cos(angles[::2]), np.sin(angles[::2])], 1)])  # [12, 2]
    # (projected once; a seed whose scale was not halved tests the same again, so only the halved are retested)
    projected = []
    for cam, seen, depth in zip(cameras, observed, depths):
        uv, z = cam.project(xyz)
        ok = (z > 0) & np.isfinite(uv).all(1)
        if ok.any():
            projected.append((cam, seen, depth, uv, z, ok))
    active = np.arange(len(xyz))
    for _ in range(halvings):
        clash = np.zeros(len(xyz), bool)
        for cam, seen, depth, uv, z, ok in projected:
            idx = active[ok[active]]
            r = reach * cam.K[0, 0] * scale[idx] / z[idx]  # px
            pts = uv[idx, None, :] + r[:, None, None] * ring[None]  # [n, 12, 2]
            px = np.floor(pts).astype(np.int64)
            inside = (px[..., 0] >= 0) & (px[..., 1] >= 0) & (px[..., 0] < cam.width) & (px[..., 1] < cam.height)
            u, v = np.where(inside, px[..., 0], 0), np.where(inside, px[..., 1], 0)
            behind = inside & seen[v, u] & (z[idx, None] < depth[v, u] * (1 - depth_tol))
            clash[idx[behind.any(1)]] = True
        active = np.nonzero(clash)[0]
        if not len(active):
            break
        scale[active] *= 0.5
    return scale


def concat_models(a: GaussianModel, b: GaussianModel) -> GaussianModel:
    params = {n: torch.cat([a.params[n].detach(), b.params[n].detach()]) for n in a.params}
    return GaussianModel(params, a.max_sh_degree)


def subset(model: GaussianModel, keep: np.ndarray) -> GaussianModel:
    """The Gaussians ``keep`` selects: a bool mask [N], or indices (taken in their order)."""
    keep = np.asarray(keep)
    sel = torch.from_numpy(keep if keep.dtype == bool else keep.astype(np.int64))
    return GaussianModel({n: p.detach()[sel] for n, p in model.params.items()}, model.max_sh_degree)


__all__ = ["RemoveParams", "objects_to_delete", "closer_to_core", "clamp_dc_colours", "render_background", "hole_mask",
           "complete_depth", "complete_depths_jointly", "object_depth", "observing_views", "initial_colour",
           "seed_hole_gaussians", "footprint_scales", "concat_models", "subset", "median_spacing"]
