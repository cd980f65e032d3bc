"""Which Gaussians are the object, and the object's mask in every view.

Cues, in the order they are used (DESIGN.md section 7, "use every cue the scene offers"):

1. **Contribution scores.** Rendered at a view with a given mask, each Gaussian's blending weight
   (sum of alpha*T) splits into the part that lands inside the mask and the part outside. The
   ratio over all given views is its object score; the Gaussians with a high score and a real
   contribution are the object's visible surface (the seeds).
2. **SfM points** observed inside the given masks (and never outside) are object points; Gaussians
   close to them join the seeds.
3. **Region growing inside the visual cone.** The parts of the object that no given view sees
   (its back, with one mask) are reached from the seeds through a radius graph, restricted to the
   Gaussians that project inside every given mask (dilated) that sees them. Background hidden
   behind the object is rarely connected to it at the object's own point spacing.
4. **Rendering.** The object set is rendered into every view with all Gaussians as occluders
   (colour = object indicator), giving a soft object probability; it is sharpened on the image
   with a guided filter (edges follow the photo) and thresholded.
5. **The given masks' surface** (:class:`LiftedSurface`): the given pixels lifted at the fit's median
   depth and projected into every view, whatever Gaussians draw the object there.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..gaussians.model import GaussianModel
from ..gaussians.rasterizer import rasterization
from ..imageio import opencv_contrib
from ..scene import Camera


@dataclass
class SelectionParams:
    score_threshold: float = 0.6  # object score (share of a Gaussian's weight inside the masks)
    background_score: float = 0.25  # a seen Gaussian scoring below this is background: growing stops there
    min_weight: float = 0.05  # ignore Gaussians whose total blending weight over given views is below
    point_radius: float = 1.5  # Gaussians within this x local spacing of an object SfM point are seeds
    grow_radius: float = 2.5  # region growing link length, x the median nearest-neighbour spacing
    cone_dilate: int = 3  # pixels the given masks are dilated by for the visual-cone test
    render_threshold: float = 0.5  # object probability threshold of the propagated masks
    guided_radius: int = 4  # guided-filter window radius (pixels) for mask edges; 0 = no edge refinement
    guided_eps: float = 1e-3  # guided-filter regulariser (image intensities in [0,1])
    backend: str = "auto"


def _stack_cameras(cameras: list[Camera]) -> tuple[torch.Tensor, torch.Tensor]:
    vm = torch.from_numpy(np.stack([c.cam_from_world for c in cameras])).float()
    K = torch.from_numpy(np.stack([c.K for c in cameras])).float()
    return vm, K


def _render_one(model: GaussianModel, camera: Camera, colors: torch.Tensor | None, render_mode: str, backend: str,
                contribution_mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    act = model.activated(sh=False)  # (the colours are the caller's channels)
    vm, K = _stack_cameras([camera])
    cmask = None if contribution_mask is None else torch.from_numpy(np.asarray(contribution_mask, bool))[None]
    with torch.no_grad():
        img, alpha, meta = rasterization(act["means"].detach(), act["quats"].detach(), act["scales"].detach(),
                                         act["opacities"].detach(), colors, vm, K, camera.width, camera.height,
                                         render_mode=render_mode, backend=backend, contribution_mask=cmask)
    return img[0].numpy(), alpha[0, ..., 0].numpy(), meta


def render_channels(model: GaussianModel, camera: Camera, colors: torch.Tensor, backend: str = "auto",
                    contribution_mask: np.ndarray | None = None, depth: bool = False
                    ) -> tuple[np.ndarray, np.ndarray, dict]:
    """Render per-Gaussian feature channels [N,D] (no SH) at one camera: (image [H,W,D(+1)], alpha [H,W], meta)."""
    return _render_one(model, camera, colors, "RGB+ED" if depth else "RGB", backend, contribution_mask)


def render_median_depth(model: GaussianModel, camera: Camera, backend: str = "auto") -> np.ndarray:
    """The median depth [H,W] (render_mode "MD": 0 where the pixel never gets half opaque)."""
    return _render_one(model, camera, None, "MD", backend)[0][..., 0]


def contribution_scores(model: GaussianModel, cameras: list[Camera], masks: list[np.ndarray],
                        backend: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """Per Gaussian: (weight inside the masks, total weight), summed over the given views."""
    (inside,), total = contribution_scores_of_sets(model, cameras, [masks], backend)
    return inside, total


def contribution_scores_of_sets(model: GaussianModel, cameras: list[Camera], mask_sets: list[list[np.ndarray]],
                                backend: str = "auto") -> tuple[list[np.ndarray], np.ndarray]:
    """:func:`contribution_scores` for several sets of masks (each one mask per camera): the weight
    inside each set's masks, and the total weight, rendered once per view for all the sets."""
    insides = [np.zeros(len(model)) for _ in mask_sets]
    total = np.zeros(len(model))
    colors = model.colors_dc()
    for i, cam in enumerate(cameras):
        for inside, masks in zip(insides, mask_sets):
            _, _, meta_in = render_channels(model, cam, colors, backend, contribution_mask=masks[i])
            inside += meta_in["contrib"][0].double().numpy()
        _, _, meta_all = render_channels(model, cam, colors, backend)
        total += meta_all["contrib"][0].double().numpy()
    return insides, total


def within_margin(mask: np.ndarray, margin: int) -> np.ndarray:
    """``mask`` grown by ``margin`` px (a square kernel: every pixel within ``margin`` px in x and y).
    The one margin of the object mask's mixed edge pixels: the visual cone's tolerance, the remove
    stage's context band and hole rim, and the finetune's band where the photos do not supervise."""
    mask = np.asarray(mask, bool)
    if margin <= 0:
        return mask.copy()
    return cv2.dilate(mask.astype(np.uint8), np.ones((2 * margin + 1,) * 2, np.uint8)) > 0


def in_visual_cone(points: np.ndarray, cameras: list[Camera], masks: list[np.ndarray], dilate: int,
                   min_views: int = 1) -> np.ndarray:
    """Points that project inside every given (dilated) mask whose image they fall in, and fall in at
    least ``min_views`` of those images."""
    ok = np.ones(len(points), bool)
    seen = np.zeros(len(points), np.int64)
    for cam, mask in zip(cameras, masks):
        m = within_margin(mask, dilate)
        px, _, inside = cam.pixels(points)
        hit = np.zeros(len(points), bool)
        hit[inside] = m[px[inside, 1], px[inside, 0]]
        ok &= ~inside | hit
        seen += inside
    return ok & (seen >= min_views)


def object_points(points_xyz: np.ndarray, obs_point: np.ndarray, obs_view: np.ndarray, obs_xy: np.ndarray,
                  view_masks: dict[int, np.ndarray]) -> np.ndarray:
    """SfM points observed inside a given mask at least once and never outside one: bool [P]."""
    votes_in = np.zeros(len(points_xyz), int)
    votes_out = np.zeros(len(points_xyz), int)
    for vi, mask in view_masks.items():
        sel = obs_view == vi
        if not sel.any():
            continue
        px = np.floor(obs_xy[sel]).astype(np.int64)
        px[:, 0] = px[:, 0].clip(0, mask.shape[1] - 1)
        px[:, 1] = px[:, 1].clip(0, mask.shape[0] - 1)
        hit = mask[px[:, 1], px[:, 0]]
        np.add.at(votes_in, obs_point[sel][hit], 1)
        np.add.at(votes_out, obs_point[sel][~hit], 1)
    return (votes_in > 0) & (votes_out == 0)


def grow_region(means: np.ndarray, seeds: np.ndarray, allowed: np.ndarray, radius: float) -> np.ndarray:
    """Gaussians connected to a seed through ``allowed`` Gaussians with links shorter than ``radius``."""
    cand = np.flatnonzero(allowed | seeds)
    if cand.size == 0 or not seeds.any():
        return seeds.copy()
    tree = cKDTree(means[cand])
    pairs = tree.query_pairs(radius, output_type="ndarray")
    n = cand.size
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n)) if len(pairs) else \
        coo_matrix((n, n))
    _, labels = connected_components(graph, directed=False)
    seed_labels = np.unique(labels[seeds[cand]])
    out = seeds.copy()
    out[cand[np.isin(labels, seed_labels)]] = True
    return out


def median_spacing(means: np.ndarray) -> float:
    if len(means) < 2:
        return 1.0
    d, _ = cKDTree(means).query(means, k=2)
    return float(np.median(d[:, 1])) or 1.0


@dataclass
class Selection:
    is_object: np.ndarray  # bool [N]
    score: np.ndarray  # float [N]: share of weight inside the given masks (nan: never seen by a given view)
    seeds: int
    from_points: int
    grown: int


def select_object(model: GaussianModel, cameras: list[Camera], masks: list[np.ndarray], params: SelectionParams,
                  sfm_points: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
                  camera_index: list[int] | None = None, cone_masks: list[np.ndarray] | None = None,
                  background_depths: list[np.ndarray | None] | None = None, depth_tol: float = 0.02,
                  hidden: bool = False) -> Selection:
    """The object's Gaussians from masks given for ``cameras`` (see the module docstring).

    ``sfm_points`` = (xyz, obs_point, obs_view, obs_xy) with ``obs_view`` numbering given by
    ``camera_index`` (the index of each given camera in the SfM camera list). ``cone_masks`` (default:
    ``masks``) bound the visual cone that growing stays in: the masks as given when ``masks`` are
    their tightened versions (:func:`tighten_mask`; the object's foot, at the floor's depth, is
    outside those but inside the given ones). ``background_depths`` (per given view, from
    :func:`tighten_mask`): seeds must lie in front of them (:func:`in_front_of`): a Gaussian of the
    floor seen through a gap of the object or at the mask's margin is no seed. (Growing is not
    restricted so: the lower part of an object standing on a floor is as deep as the floor carried in
    from below it; measured on the test scene, restricting growing too took recall from 0.93 to 0.63.)
    With ``hidden`` (and ``background_depths``), every Gaussian whose centre lies inside every given
    mask and in front of the background carried under it is a seed too: the object's parts no given
    view sees (its far side) lie there, and growing does not reach them where the fit covers them
    sparsely (a box from one given view, 360 degrees around it: 55 % of its Gaussians selected, 95 %
    with these)."""
    inside, total = contribution_scores(model, cameras, masks, params.backend)
    with np.errstate(invalid="ignore", divide="ignore"):
        score = np.where(total > 0, inside / total, np.nan)
    seeds = (total >= params.min_weight) & (score >= params.score_threshold)
    means = model.means.detach().double().numpy()
    spacing = median_spacing(means)
    n_from_points = 0
    if sfm_points is not None and camera_index is not None and len(sfm_points[0]):
        xyz, obs_point, obs_view, obs_xy = sfm_points
        obj = object_points(xyz, obs_point, obs_view, obs_xy, dict(zip(camera_index, masks)))
        if obj.any():
            d, _ = cKDTree(xyz[obj]).query(means, k=1)
            near = (d <= params.point_radius * spacing) & ~(score < 1 - params.score_threshold)
            n_from_points = int((near & ~seeds).sum())
            seeds |= near
    if background_depths is not None:
        front = seeds & in_front_of(means, cameras, background_depths, depth_tol)
        if front.any():  # (a filter, never the reason nothing is selected)
            seeds = front
        if hidden:
            seeds |= in_visual_cone(means, cameras, masks, 0) & in_front_of(means, cameras, background_depths,
                                                                              depth_tol, min_views=1)
    # Link length from the object's own point spacing (the seeds), not the scene's: background
    # touching the object (the floor under it) must not be reachable through coarser links.
    seed_spacing = median_spacing(means[seeds]) if seeds.sum() >= 2 else spacing
    cone = in_visual_cone(means, cameras, masks if cone_masks is None else cone_masks, params.cone_dilate)
    # Growing may not pass through Gaussians that a given view clearly shows outside its mask
    # (background). The object's rim straddles the mask edge (scores near 0.5): it must stay
    # passable, since it joins the seen front to the unseen back.
    # Its centre must be outside the mask too: an object Gaussian on the far side of the rim is
    # hidden at its centre and shows only its tail outside the silhouette (a near-zero score).
    centre_in_masks = in_visual_cone(means, cameras, masks, 0)
    clearly_background = (total >= params.min_weight) & (score < params.background_score) & ~centre_in_masks
    grown = grow_region(means, seeds, cone & ~clearly_background, params.grow_radius * seed_spacing)
    return Selection(grown, score, int(seeds.sum()), n_from_points, int((grown & ~seeds).sum()))


@dataclass
class TightParams:
    """Given masks are often drawn generously (dilated by a margin of background around the object).
    Inside such a margin the rendered depth continues the background around the mask; the object is
    in front of it. Only the pixels in front select the object (a margin would otherwise seed the
    floor under the object and let region growing walk along it through the visual cone)."""

    enabled: bool = True
    ring: int = 6  # px: the background ring outside the mask whose depth is carried inside ...
    gap: int = 2  # ... starting this many px away from it
    depth_tol: float = 0.02  # relative: nearer than the carried background by more than this = object
    min_keep: float = 0.2  # keep the mask as given when fewer of its pixels than this are in front


def tighten_mask(model: GaussianModel, camera: Camera, mask: np.ndarray, params: TightParams,
                 backend: str = "auto") -> tuple[np.ndarray, float, np.ndarray | None]:
    """(the mask's pixels in front of the background carried in from its surroundings, the margin
    width in pixels that was removed: (given area - kept area) / kept perimeter, the carried
    background z-depth inside the mask: HxW, 0 elsewhere; None when nothing could be carried)."""
    from .holes import complete_depth  # (holes imports this module)

    mask = np.asarray(mask, bool)
    if not params.enabled or not mask.any():
        return mask, 0.0, None
    img, alpha, _ = render_channels(model, camera, model.colors_dc(), backend, depth=True)
    depth = img[..., 3]
    # the ring skips the pixels right next to the mask: the object's rendered edge spills onto them
    near = cv2.dilate(mask.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * params.gap + 1,) * 2))
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * (params.ring + params.gap) + 1,) * 2)
    ring = (cv2.dilate(mask.astype(np.uint8), k) > 0) & ~(near > 0)
    valid = ring & (alpha > 0.5) & (depth > 0)
    if valid.sum() < 10:
        return mask, 0.0, None
    # harmonic completion of the ring's inverse depth across the mask (exact for a plane behind it),
    # on the mask's bounding box grown by the ring: far-away structure does not pull the estimate
    ys, xs = np.nonzero(mask | ring)
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    crop = (slice(y0, y1), slice(x0, x1))
    background = np.zeros_like(depth)
    inner = (near > 0) & ~ring
    background[crop] = complete_depth(np.where(valid[crop], depth[crop], 0.0), valid[crop], inner[crop])
    front = mask & (alpha > 0.5) & (depth > 0) & (depth < background * (1 - params.depth_tol))
    front = cv2.morphologyEx(front.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)) > 0
    if front.sum() < params.min_keep * mask.sum():
        return mask, 0.0, None
    return front, margin_width(mask, front), np.where(mask, background, 0.0).astype(np.float32)


def in_front_of(points: np.ndarray, cameras: list[Camera], depths: list[np.ndarray | None],
                tol: float, min_views: int = 0) -> np.ndarray:
    """Points that lie nearer than ``depths`` x (1 - tol) in most of the views where they project
    onto a pixel with a depth (0 = no constraint; points fewer than ``min_views`` views constrain
    pass when it is 0, fail otherwise): in a given view the object lies in front of the background
    that continues under its mask; the floor behind or under it does not. A majority, not every view:
    one view's carried depth can be wrong (a ring crossing another object)."""
    behind_votes = np.zeros(len(points), np.int32)
    votes = np.zeros(len(points), np.int32)
    for cam, depth in zip(cameras, depths):
        if depth is None:
            continue
        px, z, inside = cam.pixels(points)
        d = np.zeros(len(points), np.float32)
        d[inside] = depth[px[inside, 1], px[inside, 0]]
        constrained = inside & (d > 0)
        votes += constrained
        behind_votes += constrained & (z >= d * (1 - tol))
    return (2 * behind_votes <= votes) & (votes >= min_views)


@dataclass
class LiftedSurface:
    """The given masks' visible surface: each of their pixels (tightened ones, or all of a mask drawn on
    the object's edge) lifted to the world at the fit's median depth there. It is the object wherever
    the fit put its Gaussians, and projects into every view whatever Gaussians the fit drew the object
    with in that view (a sparse capture's fit draws a far view's object with floaters of its own, which
    the object's Gaussians do not render)."""

    points: np.ndarray  # [N,3] world points
    pixel_size: np.ndarray  # [N] the world size of the pixel each was lifted from (its depth / focal)

    def __len__(self) -> int:
        return len(self.points)

    @staticmethod
    def concat(surfaces: list[LiftedSurface]) -> LiftedSurface:
        if not surfaces:
            return LiftedSurface(np.zeros((0, 3)), np.zeros(0))
        return LiftedSurface(np.concatenate([s.points for s in surfaces]),
                             np.concatenate([s.pixel_size for s in surfaces]))


def lift_mask(model: GaussianModel, camera: Camera, mask: np.ndarray, backend: str = "auto") -> LiftedSurface:
    """The mask's pixels lifted at the median depth (pixels that never get half opaque are skipped).
    The median depth lies on a surface, where the expected depth of an edge pixel lies between the
    object and the background behind it."""
    depth = render_median_depth(model, camera, backend)
    ys, xs = np.nonzero(np.asarray(mask, bool) & (depth > 0))
    z = depth[ys, xs].astype(np.float64)
    return LiftedSurface(camera.unproject(ys, xs, z), z / float(camera.K[0, 0]))


def splat_surface(surface: LiftedSurface, camera: Camera) -> np.ndarray:
    """The lifted surface's footprint in ``camera`` [H,W] bool: every point's pixel, the gaps closed at
    the points' median spacing in this view (no occlusion test: the fit's depth is least reliable in
    the views that need this, see :class:`LiftedSurface`)."""
    out = np.zeros((camera.height, camera.width), np.uint8)
    if not len(surface):
        return out.astype(bool)
    px, z, inside = camera.pixels(surface.points)
    if not inside.any():
        return out.astype(bool)
    out[px[inside, 1], px[inside, 0]] = 1
    spacing = float(np.median(surface.pixel_size[inside] * camera.K[0, 0] / z[inside]))  # px per lifted pixel
    k = 2 * int(np.ceil(max(1.0, spacing))) + 1
    out = cv2.morphologyEx(out, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    return out > 0


def reaching_beyond(extra: np.ndarray, mask: np.ndarray, margin: int) -> np.ndarray:
    """The parts of ``extra`` outside ``mask`` that reach more than ``margin`` px beyond it, with the
    pixels between them and ``mask``: what another cue found and ``mask`` missed, without the
    slivers along ``mask``'s edge where two cues' edges differ by a pixel."""
    outside = np.asarray(extra, bool) & ~np.asarray(mask, bool)
    core = outside & ~within_margin(mask, margin)
    return outside & within_margin(core, margin)


def lifted_additions(footprint: np.ndarray, mask: np.ndarray, edge: int = 2, min_share: float = 0.02) -> np.ndarray:
    """What a lifted surface's footprint (:func:`splat_surface`) adds to a view's propagated ``mask``:
    its parts reaching more than ``edge`` px beyond the mask (:func:`reaching_beyond`), without the
    specks (parts under 3 px wide, or under ``min_share`` of the footprint): a fit's floaters at the
    object's edge in a given view lift there and scatter as specks into the other views."""
    opened = cv2.morphologyEx(np.asarray(footprint, bool).astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    added = reaching_beyond(opened > 0, mask, edge).astype(np.uint8)
    if not added.any():
        return added.astype(bool)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(added, connectivity=8)
    big = stats[:, cv2.CC_STAT_AREA] >= max(9.0, min_share * float(np.count_nonzero(footprint)))
    big[0] = False
    return big[labels]


def render_object_probability(model: GaussianModel, is_object: np.ndarray, camera: Camera,
                              backend: str = "auto") -> np.ndarray:
    """Soft object mask [H,W] in [0,1]: the object's share of the blended weight, every Gaussian occluding."""
    colors = torch.from_numpy(is_object.astype(np.float32))[:, None]
    img, alpha, _ = render_channels(model, camera, colors, backend)
    return np.where(alpha > 1e-3, img[..., 0] / np.maximum(alpha, 1e-3), 0.0).clip(0.0, 1.0)


def refine_mask(prob: np.ndarray, image: np.ndarray, params: SelectionParams) -> np.ndarray:
    """Threshold the soft mask after a guided filter that snaps its edges to the photo's edges."""
    p = prob.astype(np.float32)
    if params.guided_radius > 0:
        guided_filter = opencv_contrib("ximgproc", "guidedFilter", "the masks' edges, masks.guided_radius")
        p = guided_filter(image.astype(np.float32), p, params.guided_radius, params.guided_eps)
    return p >= params.render_threshold


def grabcut_mask(prob: np.ndarray, mask: np.ndarray, image: np.ndarray, band: float = 0.3,
                 iterations: int = 4, max_growth: float = 2.0, seed: int = 0) -> np.ndarray | None:
    """The propagated mask snapped to the object in the photo (OpenCV GrabCut): colour models of the
    object (the mask, certain where ``prob`` > 0.9) and of a band around it (``band`` x the mask's
    size); outside the band is background. Parts of the object the selection missed but that look
    like it and touch it (a far side one given view could not see, a foot at the floor's depth) join;
    margin pixels leave. None when GrabCut gives up or its result is implausible (under 30 % of the
    mask, or over ``max_growth`` x): keep the mask then. What it adds must still be checked against
    the given views (:func:`inside_given_cone`)."""
    mask = np.asarray(mask, bool)
    area = int(mask.sum())
    if area < 50:
        return None
    r = max(5, int(band * np.sqrt(area)))
    ring = cv2.dilate(mask.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2)) > 0
    gc = np.full(mask.shape, cv2.GC_BGD, np.uint8)
    gc[ring] = cv2.GC_PR_BGD
    gc[mask] = cv2.GC_PR_FGD
    sure = cv2.erode(((prob > 0.9) & mask).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    gc[sure] = cv2.GC_FGD
    img8 = np.ascontiguousarray((np.clip(image[..., :3], 0, 1) * 255 + 0.5).astype(np.uint8)[..., ::-1])
    # (GrabCut's k-means draws from OpenCV's global generator: seeded, a view's mask no longer depends
    # on what ran before it in the process; unseeded, 102 pixels of synthetic-raised-cast-1mask's masks
    # moved between two benchmark runs, and its mask PSNR by 0.16 dB)
    cv2.setRNGSeed(seed)
    try:
        cv2.grabCut(img8, gc, None, np.zeros((1, 65)), np.zeros((1, 65)), iterations, cv2.GC_INIT_WITH_MASK)
    except cv2.error:
        return None
    out = (gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)
    if not 0.3 * area <= out.sum() <= max_growth * area:
        return None
    return out


def photo_margin(mask: np.ndarray, image: np.ndarray, band: float = 0.3, seed: int = 0) -> float | None:
    """The margin a given mask was drawn with, as its photo alone shows it: GrabCut from the mask (no
    render, no sure pixels), the mean width of the band it drops (:func:`margin_width`). A mask drawn on
    the object's edge keeps nearly all of it (lund + box: 0.0-0.8 px); one dilated around the object
    drops the dilation (mip360 kitchen's: 14-23 px; SPIn-NeRF statue's: 3.4 px). None when GrabCut
    gives up. Unlike the margins measured against the fit's depth or render, a poor fit does not
    enlarge it."""
    mask = np.asarray(mask, bool)
    snapped = grabcut_mask(np.zeros(mask.shape, np.float32), mask, image, band=band, seed=seed)
    return None if snapped is None else margin_width(mask, snapped & mask)


def inside_given_cone(model: GaussianModel, camera: Camera, pixels: np.ndarray, cameras: list[Camera],
                      masks: list[np.ndarray], dilate: int, backend: str = "auto") -> np.ndarray:
    """Of ``pixels`` (a HxW bool map of ``camera``), those whose surface point (rendered depth) lies in
    the visual cone of the given masks: GrabCut may add what the given views could not see or showed
    inside their masks, never what a given view showed outside its mask (a floor of the object's
    colour)."""
    pixels = np.asarray(pixels, bool)
    if not pixels.any():
        return pixels
    img, alpha, _ = render_channels(model, camera, model.colors_dc(), backend, depth=True)
    ys, xs = np.nonzero(pixels & (alpha > 0.5) & (img[..., 3] > 0))
    out = np.zeros_like(pixels)
    if len(ys):
        points = camera.unproject(ys, xs, img[ys, xs, 3])
        ok = in_visual_cone(points, cameras, masks, dilate)
        out[ys[ok], xs[ok]] = True
    return out


def margin_width(given: np.ndarray, inner: np.ndarray) -> float:
    """Mean width in pixels of the band ``given`` has beyond ``inner``: their area difference over
    ``inner``'s perimeter (0 when ``inner`` is empty)."""
    inner = np.asarray(inner, bool)
    if not inner.any():
        return 0.0
    contours, _ = cv2.findContours(inner.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    perimeter = max(1.0, sum(cv2.arcLength(c, True) for c in contours))
    return float((np.asarray(given, bool) & ~inner).sum()) / perimeter


def mask_confidence(prob: np.ndarray, mask: np.ndarray) -> float:
    """1 when the soft mask is decisive around the object, lower when many pixels are ambiguous."""
    near = cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    if not near.any():
        return 1.0 if prob.max(initial=0.0) < 0.25 else 0.0
    ambiguous = (prob > 0.25) & (prob < 0.75) & near
    return float(1.0 - ambiguous.sum() / near.sum())


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0
