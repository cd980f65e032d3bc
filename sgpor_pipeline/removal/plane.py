"""The plane under an object, as one texture: fill a thick planar hole once, for every view.

Where an object stands on a plane (a table, a floor), most of its hole is the plane under it, and
every view's hole there is the same patch of that plane seen in another perspective. Filled in
each view on its own, the textures do not line up and the re-fit blurs them; filled in one
reference view, the fill inherits that view's foreshortening and its occlusions. Here the plane is
filled once, in its own frame:

1. :func:`fit_plane`: a plane through the views' thick planar hole pixels lifted with their
   completed depth, with the outliers trimmed; then (``PlaneParams.rim``, :func:`refit_to_rim`)
   refitted to the floor the views saw around their holes: the completed depth is exact for a planar
   rim, but a rim is rarely only the plane (the object's feet, its shadowed floor), and it leaned.
2. A virtual pinhole camera looks straight down at the plane (:func:`plane_camera`): the plane is
   fronto-parallel to it, so its image is the plane's texture rectified (a similarity of the
   plane: no foreshortening), and every texel's z-depth is the camera's height.
3. :func:`plane_texture`: every texel takes the per-channel median colour of the (at most 5) views
   that see it at the finest resolution (pixel footprint on the plane), among the views that see it
   unoccluded (their depth agrees) outside their holes; the median outvotes a view whose mask missed
   part of the object. Texels no view saw near the lifted holes are the texture's hole; other
   unseen texels get a smooth fill (OpenCV Telea) so they are harmless context, and are kept out of
   the source blocks. With :func:`under_object`'s silhouette, the texels under the object are hole
   too (its contact shadow).
4. The caller fills the texture's hole (SBM over the texture itself: source blocks at the plane's
   true scale) and :func:`sample_into_view` carries the filled texture into each view's hole
   pixels that lie on the plane (depths within ``depth_tol``, or, snapped, where their rays meet it),
   low-pass filtered to the view's footprint so far views do not alias.
5. :func:`contact_shading` (the inpaint stage's ``lift_shadow``): how the object darkened the plane
   around it, from its visual hull over the plane (:func:`hull_columns`): its ambient occlusion
   (:func:`ambient_occlusion`) and, optionally, its hard shadow under one light (:func:`hull_shadow`,
   direction searched), each scaled by a share of the light fitted to the texture's colour groups.
   The caller divides it out of the texture before the fill and out of every view's pixels on the
   plane (:func:`shading_into_view`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from scipy.ndimage import distance_transform_edt

from sgpor_pipeline.imageio import luminance
from sgpor_pipeline.scene import Camera

from .multiview import origin_of, warp_from_reference

PLANE_NAME = "plane"


@dataclass
class PlaneParams:
    max_size: int = 1024  # longest side of the texture (texels); coarser texels beyond it
    # the texture spans the lifted holes' extent plus this fraction of it per side: more room for source
    # blocks. synthetic-box mask PSNR, fit.seed 0 / 1 / 2, 0.5 -> 1: 27.96 / 27.80 / 27.10 -> 28.77 /
    # 28.42 / 27.36; mip360 room (no truth): the dark carpet no longer grows into the light one
    margin: float = 1.0
    max_rms: float = 0.02  # the lifted hole points' RMS distance to the plane, x the cameras' distance to it
    sample_points: int = 4000  # per view: hole pixels lifted to fit the plane
    # then the plane is refitted to the views' seen pixels within this many px of their holes that lie
    # within ``rim_band`` x its height of it (:func:`refit_to_rim`: the floor measured there, not the
    # depth completed across the holes, which leaned 8 degrees on synthetic-raised-cast from one mask,
    # where the views' floor then failed the texture's depth test); 0: off (the inpaint stage's plane_rim)
    rim: int = 0
    rim_band: float = 0.1
    footprint_quantile: float = 0.2  # texel size: this quantile of the views' pixel footprints on the plane
    votes: int = 5  # a texel's colour: the median of at most this many views that see it, finest first
    vote_ratio: float = 2.0  # ... whose pixel footprint there is at most this x the finest one's
    # ... or the finest view's own colour where it is within this of that median (largest RGB
    # difference; 0: the median everywhere). The views' rectified images differ by a pixel or so, and
    # their median averages a fine weave away; one view keeps it where no other view outvotes it.
    finest_within: float = 0.0
    # how the views are resampled into the texture and the texture into the views (warp_from_reference)
    interpolation: str = "linear"
    # texels within this many of the hole that only the views' renders coloured (``rendered``: inside their
    # object masks, outside their holes) join it; 0: off (the inpaint stage's plane_render_rim)
    render_rim: int = 0
    shadow_grow: float = 0.02  # the object's silhouette on the plane is grown by this x the texture's side
    # the object's contact shadow (:func:`contact_shading`): lifted when ``lift_shadow``
    lift_shadow: bool = False
    shading_grid: int = 160  # the hull's grid for the occlusion: at most this many texels across
    shading_reach: float = 2.0  # the occlusion is computed within this x the object's height of it
    shading_max: float = 0.9  # the largest share of the light the object may have taken (k)
    shading_chroma: float = 0.02  # texels are grouped by chromaticity (r, g over r + g + b) in bins this wide
    shading_evidence: float = 0.01  # k must explain at least this share of the luminance scatter, else none
    # the share of the object's silhouette where its hull must reach the plane for its shadow to be sought
    # (a sphere on the floor: about half; the inpaint stage's shadow_standing)
    shading_standing: float = 0.5
    # also the object's hard shadow under one light (direction and share searched; :func:`_fit_cast`)
    lift_cast: bool = False
    cast_grid: int = 64  # the direction search runs on the hull at most this many texels across
    cast_evidence: float = 0.05  # the shadow must lower the scatter by this share of it, else none
    # The seen texels under the object's hull (larger than the object: beside it) take the occlusion at
    # the silhouette's nearest edge, not none: they are in its deepest contact shadow, and stayed dark;
    # the fill copied that dark rim into the hole. Fit seed 0 / 1, mask PSNR ours (with ``rim``):
    # synthetic-box-contact 25.19 / 25.88 -> 27.10 / 27.53, synthetic-box-cast 24.22 / 25.14 -> 24.20 /
    # 25.14, synthetic-raised-cast 23.80 -> 23.82, synthetic-cast 22.07 -> 22.18
    under_edge_ao: bool = True


@dataclass
class Plane:
    normal: np.ndarray  # [3] unit, towards the cameras
    offset: float  # normal . x + offset = 0 on the plane
    rms: float  # RMS distance of the inliers to the plane
    inliers: np.ndarray  # [M,3] the lifted points kept
    kept: np.ndarray  # [N] bool: which of the points given were kept
    # :func:`refit_to_rim`: the rim points it took, and how far it turned (degrees) and moved (world
    # units, at the hole points' centre) the plane fitted to the holes
    refit: dict[str, Any] = field(default_factory=dict)

    def distance(self, points: np.ndarray) -> np.ndarray:
        return np.asarray(points, np.float64) @ self.normal + self.offset


def fit_plane(points: np.ndarray, centers: np.ndarray, rounds: int = 3) -> Plane | None:
    """Least-squares plane through ``points`` [N,3] (SVD), refitted ``rounds`` times without the points
    farther than 3 x the median absolute distance; the normal points towards the mean of ``centers``
    (the cameras). None with fewer than 3 points."""
    pts = np.asarray(points, np.float64)
    keep = np.ones(len(pts), bool)
    normal, offset = np.zeros(3), 0.0
    for _ in range(max(1, rounds)):
        if keep.sum() < 3:
            return None
        c = pts[keep].mean(0)
        _, _, vt = np.linalg.svd(pts[keep] - c, full_matrices=False)
        normal = vt[2]
        offset = -float(normal @ c)
        dist = np.abs(pts @ normal + offset)
        mad = float(np.median(dist[keep]))
        keep = dist <= max(3.0 * mad, 1e-12)
    if np.mean(np.asarray(centers, np.float64) @ normal + offset) < 0:
        normal, offset = -normal, -offset
    inl = pts[keep]
    return Plane(normal, offset, float(np.sqrt(np.mean((inl @ normal + offset) ** 2))), inl, keep)


def plane_camera(plane: Plane, height: float, texel: float, max_size: int, margin: float) -> Camera:
    """A pinhole camera ``height`` above the plane looking straight down its normal, its image
    covering the inliers' extent grown by ``margin`` x per side at ``texel`` world units per pixel (or
    coarser, to stay within ``max_size``). x follows the inliers' main direction on the plane."""
    n = plane.normal
    pts = plane.inliers - np.outer(plane.distance(plane.inliers), n)  # onto the plane
    c = pts.mean(0)
    _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
    x = vt[0] - (vt[0] @ n) * n
    x /= np.linalg.norm(x)
    z = -n
    y = np.cross(z, x)
    ab = (pts - c) @ np.stack([x, y], 1)
    lo, hi = ab.min(0), ab.max(0)
    span = hi - lo
    grow = margin * max(float(span.max()), 1e-9)
    lo, hi = lo - grow, hi + grow
    texel = max(texel, float((hi - lo).max()) / max_size)
    w, h = (int(np.ceil(v)) for v in (hi - lo) / texel)
    centre = c + x * (lo[0] + hi[0]) / 2 + y * (lo[1] + hi[1]) / 2
    eye = centre + n * height
    R = np.stack([x, y, z])
    cam_from_world = np.eye(4)
    cam_from_world[:3, :3] = R
    cam_from_world[:3, 3] = -R @ eye
    f = height / texel
    K = np.array([[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]])
    return Camera(PLANE_NAME, w, h, K, cam_from_world)


def footprint(cam: Camera, points: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """[N] the side of ``cam``'s pixel on the plane at ``points`` (world units): z / f stretched by
    1 / |cos| of the angle between the viewing ray and the plane's ``normal``."""
    pc = points @ cam.cam_from_world[:3, :3].T + cam.cam_from_world[:3, 3]
    z = pc[:, 2]
    rays = points - cam.center
    cos = np.abs(rays @ normal) / np.maximum(np.linalg.norm(rays, axis=1), 1e-12)
    return np.abs(z) / cam.K[0, 0] / np.maximum(cos, 0.05)


@dataclass
class PlaneTexture:
    camera: Camera  # the virtual camera; its image is the texture
    image: np.ndarray  # HxWx3 float32: the views' colours, unseen texels away from the holes smoothed
    depth: np.ndarray  # HxW float32: the plane's z-depth in the virtual camera (its height)
    seen: np.ndarray  # HxW bool: texels some view saw outside its hole
    hole: np.ndarray  # HxW bool: unseen texels where the views' holes lie: what to fill
    best_view: np.ndarray  # HxW int16: the view each seen texel came from (-1: none)
    plane: Plane
    info: dict[str, Any] = field(default_factory=dict)


def lift_parts(cameras: list[Camera], depths: list[np.ndarray], parts: list[np.ndarray], sample: int
               ) -> tuple[np.ndarray, np.ndarray]:
    """World points of (a regular subsample of at most ``sample``) pixels of each view's ``parts``,
    lifted with its depth; and the view of each point."""
    pts, view = [], []
    for j, (cam, depth, part) in enumerate(zip(cameras, depths, parts)):
        if cam is None or part is None:
            continue
        ys, xs = np.nonzero(part & np.isfinite(depth) & (depth > 0))
        if len(ys) == 0:
            continue
        pick = np.unique(np.linspace(0, len(ys) - 1, min(sample, len(ys))).astype(np.int64))
        pts.append(cam.unproject(ys[pick], xs[pick], depth[ys[pick], xs[pick]]))
        view.append(np.full(len(pick), j))
    if not pts:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    return np.concatenate(pts), np.concatenate(view)


def fit_hole_plane(cameras: list[Camera], depths: list[np.ndarray], parts: list[np.ndarray | None], sample: int,
                   max_rms: float, holes: list[np.ndarray] | None = None, rim: int = 0,
                   rim_band: float = PlaneParams.rim_band
                   ) -> tuple[tuple[Plane, float, np.ndarray, np.ndarray] | None, str]:
    """:func:`fit_plane` through the views' hole ``parts`` lifted with their ``depths``
    (:func:`lift_parts`), refused when its RMS distance exceeds ``max_rms`` x the cameras' (median)
    distance to it. With ``holes`` and ``rim`` > 0 the plane is then refitted to the pixels outside the
    holes within ``rim`` px of them whose lifted points lie within ``rim_band`` x that distance of it
    (:func:`refit_to_rim`). Returns ((plane, that distance, the lifted points, their views), "") or
    (None, why not)."""
    pts, pview = lift_parts(cameras, depths, parts, sample)
    centers = np.stack([c.center for c in cameras if c is not None])
    plane = fit_plane(pts, centers) if len(pts) >= 3 else None
    if plane is None:
        return None, "fewer than 3 pixels of thick holes on a planar rim to fit a plane to"
    distance = float(np.median(np.abs(plane.distance(centers))))
    if plane.rms > max_rms * distance:
        return None, (f"the holes do not lie on one plane (RMS {plane.rms / distance:.3f} of the cameras' "
                      f"distance, limit {max_rms})")
    if holes is not None and rim > 0:
        plane = refit_to_rim(plane, centers, cameras, depths, holes, sample, rim, rim_band * distance)
        distance = float(np.median(np.abs(plane.distance(centers))))
    return (plane, distance, pts, pview), ""


def refit_to_rim(plane: Plane, centers: np.ndarray, cameras: list[Camera],
                 depths: list[np.ndarray], holes: list[np.ndarray], sample: int, rim: int, band: float,
                 tol: float = 0.2, max_tilt_deg: float = 20.0, trials: int = 500, seed: int = 0) -> Plane:
    """``plane`` (fitted to the holes' lifted points) refitted to the views' seen pixels within ``rim`` px
    of their ``holes`` whose lifted points lie within ``band`` (world units) of it: the surface the
    views measured around the holes, where the holes' depths were only completed from it (and may lean:
    8 degrees on synthetic-raised-cast from one mask). A RANSAC of ``trials`` planes through 3 of those
    points, tilted at most ``max_tilt_deg`` from ``plane``, keeps the one with the most points within
    ``tol`` x ``band``; then least squares on those. Its inliers stay ``plane``'s (the hole points: they
    place the texture and the holes' footprint on it). ``plane`` itself when fewer than 100 rim points qualify."""
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rim + 1, 2 * rim + 1))
    rims = [None if cam is None or hole is None or not hole.any() else
            (cv2.dilate(hole.astype(np.uint8), k) > 0) & ~hole for cam, hole in zip(cameras, holes)]
    around, _ = lift_parts(cameras, depths, rims, sample)
    around = around[np.abs(plane.distance(around)) <= band]
    if len(around) < 100:
        return plane
    rng = np.random.default_rng(seed)
    tri = around[rng.integers(0, len(around), (trials, 3))]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(normals, axis=1)
    ok = norm > 1e-12
    normals = normals[ok] / norm[ok, None]
    upright = np.abs(normals @ plane.normal) >= np.cos(np.radians(max_tilt_deg))
    normals, tri = normals[upright], tri[ok][upright]
    if not len(normals):
        return plane
    offsets = -np.einsum("ij,ij->i", normals, tri[:, 0])
    count = np.zeros(len(normals), np.int64)
    for i in range(0, len(normals), 64):  # (chunks: trials x points distances)
        count[i:i + 64] = (np.abs(around @ normals[i:i + 64].T + offsets[i:i + 64]) <= tol * band).sum(0)
    best = int(np.argmax(count))
    on = np.abs(around @ normals[best] + offsets[best]) <= tol * band
    refit = fit_plane(around[on], centers)  # (least squares, trimmed: a wall's foot within tol)
    if refit is None:
        return plane
    # (the hole points kept as the first fit trimmed them: their extent sizes the texture and the grown
    # silhouette under the object; retrimmed against the new plane they spread, 180 -> 507 texels across)
    inl = plane.inliers
    moved = {"rim_points": int(on.sum()),
             "tilt_deg": float(np.degrees(np.arccos(np.clip(abs(refit.normal @ plane.normal), 0.0, 1.0)))),
             "shift": float(abs(refit.distance(inl.mean(0)[None])[0]))}
    return Plane(refit.normal, refit.offset, float(np.sqrt(np.mean((inl @ refit.normal + refit.offset) ** 2))),
                 inl, plane.kept, moved)


def grown(mask: np.ndarray, grow: float) -> np.ndarray:
    """``mask`` (HxW) as bool, dilated by a disc of radius ``grow`` x its longer side (rounded to pixels):
    the object's silhouette on the plane with a margin for its contact shadow."""
    r = int(round(grow * max(mask.shape)))
    if r <= 0:
        return np.asarray(mask, bool)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2)
    return cv2.dilate(np.asarray(mask, np.uint8), k) > 0


def rim_dark_share(image: np.ndarray, hole: np.ndarray, seen: np.ndarray, rim: int = 8,
                   around: tuple[int, int] = (15, 45), factor: float = 0.4) -> float:
    """The share of the seen texels within ``rim`` texels of the ``hole`` darker than ``factor`` x the
    median luminance of the seen texels ``around`` texels away (NaN when either ring is empty). An
    object standing on the plane leaves its footprint and contact shadow there: what the views saw of
    the plane right beside it, through its gaps and below its sides, is dark, and SBM continues that
    rim into the hole (mip360 kitchen from one given mask: 0.21 while its far track was left standing,
    0.03 since masks.hidden selects it; with remove.under_object, whose holes take in the plane under
    the object's silhouette: 0.01; synthetic-box, without shadow, 0.04)."""
    hole = np.asarray(hole, bool)
    seen = np.asarray(seen, bool) & ~hole
    if not hole.any():
        return float("nan")
    dist = cv2.distanceTransform((~hole).astype(np.uint8), cv2.DIST_L2, 3)
    lum = luminance(image)
    inner = seen & (dist <= rim)
    outer = seen & (dist > around[0]) & (dist <= around[1])
    if not inner.any() or not outer.any():
        return float("nan")
    return float((lum[inner] < factor * np.median(lum[outer])).mean())


def plane_texture(cameras: list[Camera], images: list[np.ndarray], knowns: list[np.ndarray],
                  depths: list[np.ndarray], parts: list[np.ndarray], params: PlaneParams,
                  depth_tol: float = 0.02, under: tuple[Camera, np.ndarray] | None = None,
                  rendered: list[np.ndarray] | None = None) -> tuple[PlaneTexture | None, str]:
    """The texture of the plane under the views' thick planar hole ``parts`` (see the module doc).

    ``images``: what the views show (the remove stage's context images); ``knowns``: their pixels that
    may give colour (outside the holes); ``depths``: their completed depths. ``under``, when given, is
    the removed object's silhouette on the plane (:func:`under_object`: a camera looking straight down
    and its mask): the texels under it, grown by ``shadow_grow``, are part of the hole, whatever the
    views saw there (its contact shadow, seen through its gaps). ``rendered`` (per view, bool HxW): the
    pixels of ``images`` that are the fit's render, not the photo; with ``params.render_rim`` the texels
    beside the hole that only those coloured join the hole. Returns (texture, "") or (None, why not: too
    few points, or the parts do not lie on one plane)."""
    fitted, why = fit_hole_plane(cameras, depths, parts, params.sample_points, params.max_rms,
                                 [~k for k in knowns], params.rim, params.rim_band)
    if fitted is None:
        return None, why
    plane, height, pts, pview = fitted
    # texel: a low quantile of the views' median pixel footprints at the hole points
    feet = []
    for j in np.unique(pview[plane.kept]):
        own = pts[plane.kept & (pview == j)]
        feet.append(float(np.median(footprint(cameras[j], own[:: max(1, len(own) // 500)], plane.normal))))
    texel = float(np.quantile(feet, params.footprint_quantile))
    vcam = plane_camera(plane, height, texel, params.max_size, params.margin)
    h, w = vcam.height, vcam.width
    vdepth = np.full((h, w), height, np.float32)
    # every texel: the per-channel median of the (at most ``votes``) finest views that see it,
    # unoccluded, outside their holes, among those within ``vote_ratio`` of the finest footprint: a
    # view whose object mask missed part of the object (its photo shows the object there) is outvoted
    ys, xs = np.mgrid[0:h, 0:w]
    world = vcam.unproject(ys.ravel(), xs.ravel(), vdepth.ravel())
    # the ``votes`` finest so far per texel, updated view by view (memory: votes x texels, any view count)
    votes = max(1, params.votes)
    kept_feet = np.full((votes, h * w), np.inf, np.float32)
    cols = np.zeros((votes, h * w, 3), np.float32)
    views = np.full((votes, h * w), -1, np.int32)
    track = rendered is not None and params.render_rim > 0  # which kept votes are renders (render_rim)
    rflag = np.zeros((votes, h * w) if track else (0, 0), bool)
    everything = np.ones((h, w), bool)
    for j, cam in enumerate(cameras):
        if cam is None:
            continue
        col, got = warp_from_reference(images[j], cam, depths[j], knowns[j], vcam, vdepth, everything,
                                       "backward", depth_tol, params.interpolation)
        idx = np.nonzero(got.ravel())[0]
        if not len(idx):
            continue
        fp = footprint(cam, world[idx], plane.normal).astype(np.float32)
        better = fp < kept_feet[-1, idx]  # finer than the coarsest kept
        idx, fp = idx[better], fp[better]
        f = np.concatenate([kept_feet[:, idx], fp[None]])  # [votes + 1, n]
        c = np.concatenate([cols[:, idx], col.reshape(-1, 3)[idx][None]])
        v = np.concatenate([views[:, idx], np.full((1, len(idx)), j, np.int32)])
        order = np.argsort(f, axis=0, kind="stable")[:votes]
        if track:
            px = np.clip(cam.pixels(world[idx])[0], 0, [cam.width - 1, cam.height - 1])
            rf = np.asarray(rendered[j], bool)[px[:, 1], px[:, 0]]
            rflag[:, idx] = np.take_along_axis(np.concatenate([rflag[:, idx], rf[None]]), order, 0)
        kept_feet[:, idx] = np.take_along_axis(f, order, 0)
        cols[:, idx] = np.take_along_axis(c, order[..., None], 0)
        views[:, idx] = np.take_along_axis(v, order, 0)
    ok = np.isfinite(kept_feet) & (kept_feet <= params.vote_ratio * kept_feet[:1])
    seen_flat = ok[0]
    colour = np.zeros((h * w, 3), np.float32)
    if seen_flat.any():
        picked = np.where(ok[:, seen_flat, None], cols[:, seen_flat], np.nan)
        voted = np.nanmedian(picked, axis=0)
        if params.finest_within > 0:  # (the finest view's own colour where the median agrees with it)
            finest = cols[0, seen_flat]
            agrees = np.abs(finest - voted).max(axis=1) <= params.finest_within
            voted[agrees] = finest[agrees]
        colour[seen_flat] = voted
    best_view = np.where(seen_flat, views[0], -1).astype(np.int16)
    del cols
    seen = (best_view >= 0).reshape(h, w)
    blocked = np.zeros((h, w), bool)
    if under is not None:
        ucam, sil = under
        upx, _, uin = ucam.pixels(world)
        flat = np.zeros(h * w, bool)
        flat[uin] = np.asarray(sil, bool)[upx[uin, 1], upx[uin, 0]]
        blocked = grown(flat.reshape(h, w), params.shadow_grow)
        seen &= ~blocked
        best_view[blocked.ravel()] = -1
    # the holes' footprint: the lifted hole points, splatted and closed over the gaps between them
    fpx, _, inside = vcam.pixels(plane.inliers)
    foot = np.zeros((h, w), np.uint8)
    foot[fpx[inside, 1], fpx[inside, 0]] = 1
    gap = int(np.ceil(max(np.max(feet) / texel, 1.0))) + 2
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * gap + 1, 2 * gap + 1))
    foot = cv2.morphologyEx(foot, cv2.MORPH_CLOSE, k)
    foot = cv2.dilate(foot, k) > 0
    hole = (foot | blocked) & ~seen
    if track and hole.any():
        render_only = (seen.ravel() & ~(ok & ~rflag).any(0)).reshape(h, w)
        kr = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * params.render_rim + 1,) * 2)
        grow = render_only & (cv2.dilate(hole.astype(np.uint8), kr) > 0)
        hole |= grow
        seen &= ~grow
        best_view[grow.ravel()] = -1
    image = colour.reshape(h, w, 3)
    other = ~seen & ~hole
    if other.any() and seen.any():  # harmless context (kept out of the source blocks by the caller)
        # smoothed from the seen texels only: with the hole's texels (black) as known neighbours, the
        # unseen texels beside it turned dark and the hole's fill continued them (mip360 kitchen)
        u8 = np.clip(image * 255 + 0.5, 0, 255).astype(np.uint8)
        image = cv2.inpaint(u8, (other | hole).astype(np.uint8), 3, cv2.INPAINT_TELEA).astype(np.float32) / 255.0
        image[hole] = 0.0
    info = {"width": w, "height": h, "texel": height / vcam.K[0, 0], "height_above_plane": height,
            "rms_relative": plane.rms / height, "points": int(len(pts)), "inliers": int(len(plane.inliers)),
            "seen_texels": int(seen.sum()), "hole_texels": int(hole.sum()), "under_object_texels": int(blocked.sum()),
            "views_used": int(len(np.unique(best_view[best_view >= 0]))), "refit": plane.refit}
    return PlaneTexture(vcam, image.astype(np.float32), vdepth, seen, hole, best_view.reshape(h, w), plane, info), ""


def plane_depth(vcam: Camera, vdepth: np.ndarray, normal: np.ndarray, cam: Camera,
                shape: tuple[int, int] | None = None) -> np.ndarray:
    """z-depth in ``cam`` where each pixel's ray meets the plane of the texture camera ``vcam``
    (``vdepth`` above it, looking down its unit ``normal``); inf where the ray does not meet it ahead.
    ``shape``: that of ``cam``'s arrays (a :class:`~.multiview.CropCamera`'s crop), else its image."""
    n = np.asarray(normal, np.float64)
    on_plane = vcam.center - float(vdepth.flat[0]) * n
    oy, ox = origin_of(cam)
    h, w = shape if shape is not None else (cam.height, cam.width)
    ys, xs = np.mgrid[oy:oy + h, ox:ox + w]
    rays = cam.unproject(ys.ravel(), xs.ravel(), np.ones(xs.size)) - cam.center  # unit camera z
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (n @ (on_plane - cam.center)) / (rays @ n)
    return np.where(np.isfinite(t) & (t > 0), t, np.inf).reshape(h, w)


def snapped_depth(vcam: Camera, vdepth: np.ndarray, normal: np.ndarray, cam: Camera, depth: np.ndarray,
                  target: np.ndarray, tol: float) -> np.ndarray:
    """``depth`` (``cam``'s) with its ``target`` pixels within ``tol`` (relative) of the texture camera's
    plane taken where their rays meet it (:func:`plane_depth`); float32."""
    on = plane_depth(vcam, vdepth, normal, cam, depth.shape)
    snap = target & np.isfinite(on) & (np.abs(depth - on) <= tol * on)
    return np.where(snap, on, depth).astype(np.float32)


def sample_into_view(texture: np.ndarray, vcam: Camera, vdepth: np.ndarray, normal: np.ndarray, cam: Camera,
                     depth: np.ndarray, target: np.ndarray, depth_tol: float = 0.02, snap_tol: float = 0.0,
                     interpolation: str = "linear") -> tuple[np.ndarray, np.ndarray]:
    """Colours for ``cam``'s ``target`` pixels that lie on the plane (unit ``normal``; their completed ``depth`` within
    ``depth_tol`` of it), from the filled ``texture`` low-pass filtered to the view's pixel footprint.
    With ``snap_tol`` > 0, a target pixel whose depth is within ``snap_tol`` (relative) of the plane is
    taken where its ray meets the plane (:func:`plane_depth`): a hole's depth is only completed from
    around it, and leans where the plane was refitted to the floor seen there (``PlaneParams.rim``).
    ``interpolation``: :func:`~.multiview.warp_from_reference`'s. Returns (colours HxWx3 float32, got bool HxW)."""
    if snap_tol > 0:
        depth = snapped_depth(vcam, vdepth, normal, cam, depth, target, snap_tol)
    ys, xs = np.nonzero(target & np.isfinite(depth) & (depth > 0))
    if len(ys) == 0:
        return np.zeros((*target.shape, 3), np.float32), np.zeros(target.shape, bool)
    pick = np.unique(np.linspace(0, len(ys) - 1, min(500, len(ys))).astype(np.int64))
    pts = cam.unproject(ys[pick], xs[pick], depth[ys[pick], xs[pick]])
    texel = float(vdepth.flat[0]) / vcam.K[0, 0]
    ratio = float(np.median(footprint(cam, pts, np.asarray(normal, np.float64)))) / texel
    tex = np.asarray(texture, np.float32)
    if ratio > 1.25:  # a texel smaller than the view's pixel: average them first (no aliasing)
        sigma = 0.5 * np.sqrt(ratio * ratio - 1.0)
        tex = cv2.GaussianBlur(tex, (0, 0), sigma)
    return warp_from_reference(tex, vcam, vdepth, np.ones(vdepth.shape, bool), cam, depth, target,
                               "backward", depth_tol, interpolation)


def blend_into_view(image: np.ndarray, colours: np.ndarray, got: np.ndarray, texture_ring: np.ndarray,
                    ring: np.ndarray, anchor: float = 1e-3) -> np.ndarray:
    """The texture's ``colours`` for a view's hole pixels ``got`` shifted smoothly to the view's own
    colours around them (Poisson image editing): inside, the texture's differences; at the ``ring``
    (known pixels beside ``got`` where the texture was sampled too, ``texture_ring``), the view's
    ``image``. A woven mat or a glossy floor looks lighter or darker from each side, and one texture
    for all views cannot; its fill then showed as a darker patch in views that saw the mat lighter.
    Elsewhere around ``got`` (the rest of the hole, pixels off the plane) nothing is imposed; ``anchor``
    keeps a part with no ring at the texture's colours. Returns HxWx3 float32 (``got`` changed only)."""
    from .sbm import poisson_blend

    guide = np.where(ring[..., None], texture_ring, colours).astype(np.float32)
    base = np.asarray(image, np.float32).copy()
    base[got] = colours[got]
    out = poisson_blend(base, guide, got, boundary=ring & ~got, anchor=anchor)
    return out.astype(np.float32)


@dataclass
class UnderObject:
    """Where the removed object stood on a plane: what lay under it, in every view."""

    pixels: list[np.ndarray]  # per view HxW bool: mask pixels on the plane under the object's silhouette
    plane: Plane
    silhouette: np.ndarray  # HxW bool: the object seen straight down the plane's normal (``camera``)
    camera: Camera
    info: dict[str, Any] = field(default_factory=dict)


def hull_columns(plane: Plane, vcam: Camera, cameras: list[Camera], masks: list[np.ndarray], top: float,
                 levels: int = 48, dilate: int = 2, min_views: int = 2) -> np.ndarray:
    """[levels, H, W] bool: which points of each texel's column (the plane's normal through it, at
    heights (k + 0.5) / levels x ``top`` above the plane) lie in the object's visual hull: inside every
    mask (dilated by ``dilate`` px) of the views they fall in, and in at least ``min_views`` views."""
    from .selection import in_visual_cone, within_margin

    masks = [within_margin(m, dilate) for m in masks]  # once, not at every height
    h, w = vcam.height, vcam.width
    ys, xs = np.mgrid[0:h, 0:w]
    base = vcam.unproject(ys.ravel(), xs.ravel(), np.full(h * w, abs(float(plane.distance(vcam.center[None])[0]))))
    out = np.zeros((levels, h * w), bool)
    for k in range(levels):
        pts = base + plane.normal * (top * (k + 0.5) / levels)
        out[k] = in_visual_cone(pts, cameras, masks, 0, min_views=min_views)
    return out.reshape(levels, h, w)


@dataclass
class StandingHull:
    """The object's visual hull over a plane it stands on (:func:`standing_hull`)."""

    columns: np.ndarray  # [levels, H, W] bool: :func:`hull_columns`, kept to the silhouette
    silhouette: np.ndarray  # [H, W] bool: the object seen straight down the normal
    top: float  # world height of the columns' top (level ``levels`` - 0.5 is just below it)
    height: float  # world height of the object (95th percentile of its columns' tops)
    standing: float  # fraction of the silhouette where the hull reaches down to the plane


def standing_hull(cols: np.ndarray, top: float, max_lift: float = 0.1, min_part: float = 0.1,
                  min_standing: float = 0.5) -> tuple[StandingHull | None, str]:
    """The hull columns' silhouette, kept to parts of at least ``min_part`` x the largest (not specks
    of hull where few views' masks meet, at the edges of the views), if the object stands on the
    plane: in at least half of the silhouette the hull reaches down to within ``max_lift`` x its
    height. Returns (hull, "") or (None, why not)."""
    sil = cols.any(0)
    if not sil.any():
        return None, "no view's mask covers the plane over the holes"
    _, labels, st, _ = cv2.connectedComponentsWithStats(sil.astype(np.uint8), connectivity=8)
    area = st[1:, cv2.CC_STAT_AREA]
    sil = np.isin(labels, 1 + np.nonzero(area >= min_part * area.max())[0])
    cols = cols & sil[None]
    lowest = np.argmax(cols, axis=0)[sil] + 0.5  # in levels
    highest = cols.shape[0] - np.argmax(cols[::-1], axis=0)[sil]
    height = float(np.percentile(highest, 95))
    standing = float(np.mean(lowest <= max(1.0, max_lift * height)))
    if standing < min_standing:
        return None, (f"the object does not stand on the plane of the holes (its visual hull reaches the plane "
                      f"in {100 * standing:.0f} % of its silhouette)")
    return StandingHull(cols, sil, top, height / cols.shape[0] * top, standing), ""


def hemisphere(n: int) -> np.ndarray:
    """[n, 3] directions over a plane (z up), cosine-weighted: Fibonacci points on the unit disc lifted
    onto the hemisphere (Malley), so their plain mean is the cosine-weighted integral."""
    k = np.arange(n) + 0.5
    r = np.sqrt(k / n)
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1.0 - r * r)], axis=1)


def _around(hull: StandingHull, texel: float, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """(rows, columns) of the grid's texels outside the silhouette within ``reach`` (world units) of it."""
    outside = ~hull.silhouette
    near = cv2.distanceTransform(outside.astype(np.uint8), cv2.DIST_L2, 5) * texel <= reach
    return np.nonzero(near & outside)


def _meets_hull(hull: StandingHull, texel: float, reach: float, ys: np.ndarray, xs: np.ndarray,
                direction: np.ndarray) -> np.ndarray:
    """[n] bool: whether ``direction`` (unit, z up the normal, c > 0), marched from the texels (``ys``,
    ``xs``) on the plane a texel or a level at a time, meets the hull before it passes over the object
    or leaves ``reach``."""
    cols = hull.columns
    levels, h, w = cols.shape
    dz = hull.top / levels
    a, b, c = (float(v) for v in direction)
    horiz = float(np.hypot(a, b))
    t_max = min(hull.height / max(c, 1e-6), reach / max(horiz, 1e-6))
    dt = min(texel / max(horiz, 1e-6), dz / max(c, 1e-6))
    t = dt * (np.arange(int(np.ceil(t_max / dt))) + 1.0)
    u = np.rint(xs[:, None] + (t * a / texel)[None]).astype(np.int64)
    v = np.rint(ys[:, None] + (t * b / texel)[None]).astype(np.int64)
    lev = np.broadcast_to(np.minimum((t * c / dz).astype(np.int64), levels - 1)[None], u.shape)
    ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    blocked = np.zeros(u.shape, bool)
    blocked[ok] = cols[lev[ok], v[ok], u[ok]]
    return blocked.any(1)


def ambient_occlusion(hull: StandingHull, texel: float, reach: float, directions: int = 64) -> np.ndarray:
    """[H, W] float32: the cosine-weighted fraction of the sky over each texel of the plane (outside the
    silhouette, within ``reach`` of it; world units) that the object's hull hides. The hull grid is
    the columns' (``texel`` world units per texel, ``hull.top`` / levels per level); each direction
    is marched a texel or a level at a time until it passes over the object or leaves ``reach``."""
    ao = np.zeros(hull.silhouette.shape, np.float32)
    ys, xs = _around(hull, texel, reach)
    if not len(ys):
        return ao
    hit = np.zeros(len(ys), np.float32)
    for d in hemisphere(directions):
        hit += _meets_hull(hull, texel, reach, ys, xs, d)
    ao[ys, xs] = hit / directions
    return ao


def hull_shadow(hull: StandingHull, texel: float, reach: float, direction: np.ndarray) -> np.ndarray:
    """[H, W] bool: the texels of the plane (outside the silhouette, within ``reach`` of it) from which
    ``direction`` (unit, in the grid's frame: x, y along its image axes, z up the normal) meets the
    object's hull: its hard shadow under a light that way."""
    out = np.zeros(hull.silhouette.shape, bool)
    ys, xs = _around(hull, texel, reach)
    if len(ys) and direction[2] > 0:
        out[ys, xs] = _meets_hull(hull, texel, reach, ys, xs, direction)
    return out


@dataclass
class ContactShading:
    """How the removed object darkened the plane around it (:func:`contact_shading`)."""

    factor: np.ndarray  # [H, W] float32 in (0, 1]: the texture = albedo x factor (1 away from the object)
    under: np.ndarray  # [H, W] bool: the object's silhouette on the texture (its hull seen straight down)
    info: dict[str, Any] = field(default_factory=dict)


def _grid_camera(cam: Camera, max_size: int) -> Camera:
    """``cam`` (looking straight down at the plane) with coarser texels if its image is more than
    ``max_size`` across."""
    scale = max(cam.width, cam.height) / max_size
    if scale <= 1.0:
        return cam
    w, h = max(1, int(round(cam.width / scale))), max(1, int(round(cam.height / scale)))
    K = np.array([[cam.K[0, 0] / scale, 0.0, w / 2.0], [0.0, cam.K[1, 1] / scale, h / 2.0], [0.0, 0.0, 1.0]])
    return Camera(cam.name, w, h, K, cam.cam_from_world)


def _window_camera(cam: Camera, centre: np.ndarray, half: float, height: float) -> Camera:
    """A camera like ``cam`` (looking straight down at the plane from ``height``) over the square of
    half-side ``half`` (world units) around ``centre`` (on the plane), at ``cam``'s texel."""
    R = cam.cam_from_world[:3, :3]
    eye = centre - R[2] * height  # R[2]: the viewing direction, minus the plane's normal
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ eye
    side = max(1, int(np.ceil(2.0 * half * cam.K[0, 0] / height)))
    K = np.array([[cam.K[0, 0], 0.0, side / 2.0], [0.0, cam.K[1, 1], side / 2.0], [0.0, 0.0, 1.0]])
    return Camera(cam.name, side, side, K, T)


def contact_shading(texture: PlaneTexture, cameras: list[Camera], masks: list[np.ndarray],
                    params: PlaneParams) -> tuple[ContactShading | None, str]:
    """The object's contact shadow on the plane texture, from geometry and one fitted strength.

    The object's visual hull over the plane (:func:`hull_columns` of the views' object ``masks``, on a
    grid of at most ``shading_grid`` texels across) gives each texel its ambient occlusion ``ao`` by
    the object (:func:`ambient_occlusion`, within ``shading_reach`` x the object's height). A real
    object takes away the share ``k`` of the light that comes from all around: the texture is albedo x
    (1 - k ao). ``k`` is fitted on the seen texels within that reach: the texels are grouped by
    chromaticity (bins of ``shading_chroma``; a shadow dims a colour without changing its hue, while a
    rug and the floor around it differ in hue), each group gets its own albedo (the median), and ``k``
    is the one that leaves the least L1 scatter of log luminance around them. An albedo that only
    happens to be darker near the object (the rug under it) is then not taken for a shadow. ``k`` is
    0 unless it explains at least ``shading_evidence`` of the scatter. Returns (shading, "") or (None,
    why not)."""
    h, w = texture.image.shape[:2]
    height = float(texture.depth.flat[0])
    top = 0.5 * height
    # first over the whole texture, coarsely, to find the object; then over a window around it (its
    # silhouette plus the reach), so that a small object on a large texture is resolved as well
    grid = _grid_camera(texture.camera, params.shading_grid)
    hull, why = standing_hull(hull_columns(texture.plane, grid, cameras, masks, top), top,
                              min_standing=params.shading_standing)
    if hull is None:
        return None, why
    ys, xs = np.nonzero(hull.silhouette)
    centre = grid.unproject(np.array([(ys.min() + ys.max()) / 2.0]), np.array([(xs.min() + xs.max()) / 2.0]),
                            np.array([height]))[0]
    half = height / grid.K[0, 0] * (max(ys.max() - ys.min(), xs.max() - xs.min()) + 1) / 2.0
    half += params.shading_reach * hull.height
    grid = _grid_camera(_window_camera(texture.camera, centre, half, height), params.shading_grid)
    hull, why = standing_hull(hull_columns(texture.plane, grid, cameras, masks, top), top,
                              min_standing=params.shading_standing)
    if hull is None:
        return None, why
    reach = params.shading_reach * hull.height
    grid_texel = height / grid.K[0, 0]
    ao_grid = ambient_occlusion(hull, grid_texel, reach)
    near_grid = np.zeros(hull.silhouette.shape, bool)
    near_grid[_around(hull, grid_texel, reach)] = True
    # onto the texture's texels (the cameras share their axes and height)
    ty, tx = np.mgrid[0:h, 0:w]
    uv, _ = grid.project(texture.camera.unproject(ty.ravel(), tx.ravel(), np.full(h * w, height)))
    mx = (uv[:, 0] - 0.5).reshape(h, w).astype(np.float32)
    my = (uv[:, 1] - 0.5).reshape(h, w).astype(np.float32)
    ao = cv2.remap(ao_grid, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)

    def on_texture(mask: np.ndarray) -> np.ndarray:
        return cv2.remap(mask.astype(np.uint8), mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT) > 0

    under = on_texture(hull.silhouette)
    if params.under_edge_ao and under.any() and (~under).any():
        # seen under the hull's silhouette, which is larger than the object: beside it, in its deepest
        # occlusion; the occlusion at the silhouette's nearest edge texel (inside, the hull covers all)
        iy, ix = distance_transform_edt(under, return_distances=False, return_indices=True)
        ao = ao[iy, ix]
    else:
        ao[under] = 0.0  # under the object: not a shadow to lift (remove.under_object's business)
    fit = texture.seen & ~under & on_texture(near_grid)
    info: dict[str, Any] = {"grid": [grid.width, grid.height], "grid_texel": grid_texel, "object_height": hull.height,
                            "texels": int(fit.sum()),
                            "max_occlusion": float(ao.max()), "strength": 0.0}
    if (fit & (ao > 0.05)).sum() < 50:
        return None, f"the object's occlusion reaches only {int((fit & (ao > 0.05)).sum())} seen texels"
    groups = _ColourGroups(texture.image[fit], params.shading_chroma)
    occ = ao[fit].astype(np.float64)
    ks = np.linspace(0.0, params.shading_max, 91)
    cost = np.array([groups.scatter(1.0 - k * occ) for k in ks])
    k = float(ks[int(np.argmin(cost))])
    explained = 1.0 - float(cost.min() / max(cost[0], 1e-12))
    info.update(groups=groups.count, explained=explained)
    cast = None
    # (a hard shadow next to the object darkens where its occlusion does too: without that, no search)
    if params.lift_cast and explained >= params.shading_evidence:
        cast = _fit_cast(hull, grid_texel, reach, params, k, occ, groups, mx, my, fit, float(cost.min()))
        if cast is not None:
            info["cast"] = {kk: v for kk, v in cast.items() if kk != "map"}
            explained = 1.0 - cast["cost"] / max(cost[0], 1e-12)
            k = cast["ambient"]
    if explained < params.shading_evidence:
        return None, (f"no contact shadow: the object's occlusion explains {100 * explained:.1f} % of the "
                      f"luminance around it (< {100 * params.shading_evidence:.0f} %)")
    factor = (1.0 - k * ao).astype(np.float32)
    if cast is not None:
        factor = np.clip(factor - cast["strength"] * cast["map"], 0.05, 1.0).astype(np.float32)
        info["explained"] = explained
    info.update(strength=k, mean_gain=float(np.mean(1.0 / factor[fit & (ao > 0.05)])),
                max_gain=float(1.0 / factor.min()))
    return ContactShading(factor, under, info), ""


class _ColourGroups:
    """Texels grouped by chromaticity (r, g over r + g + b, in bins ``chroma`` wide): a shadow dims a
    colour without changing its hue, so each group has one albedo, its median."""

    def __init__(self, colours: np.ndarray, chroma: float):
        img = np.clip(colours, 1.0 / 255.0, None).astype(np.float64)
        total = img.sum(axis=1)
        bins = np.floor(img[:, :2] / total[:, None] / chroma).astype(np.int64)
        self.group = np.unique(bins[:, 0] * 100_000 + bins[:, 1], return_inverse=True)[1].ravel()
        self.count = int(self.group.max() + 1)
        ordered = np.sort(self.group)
        starts = np.searchsorted(ordered, np.arange(self.count))
        ends = np.searchsorted(ordered, np.arange(self.count), side="right")
        self.middle = (starts + ends - 1) // 2  # each group's median, in (group, value) order
        self.lum = np.log(total / 3.0)

    def albedo(self, factor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(log luminance with the shading ``factor`` divided out, its group's median) per texel."""
        r = self.lum - np.log(factor)
        order = np.lexsort((r, self.group))
        return r, r[order][self.middle][self.group]

    def scatter(self, factor: np.ndarray) -> float:
        """The L1 scatter of the log luminance, ``factor`` divided out, around the groups' medians."""
        r, median = self.albedo(factor)
        return float(np.abs(r - median).sum())


def _fit_cast(hull: StandingHull, texel: float, reach: float, params: PlaneParams, k_ambient: float,
              occ: np.ndarray, groups: _ColourGroups, mx: np.ndarray, my: np.ndarray, fit: np.ndarray,
              ambient_cost: float) -> dict[str, Any] | None:
    """The object's hard shadow under one light (:func:`hull_shadow`): its direction searched over a
    grid of azimuths and elevations, on a coarse copy of the hull, and its share of the light, by the
    same grouped L1 scatter as the occlusion; then both shares refined together. None unless the
    shadow lowers the scatter by ``cast_evidence`` of it."""
    step = max(1, int(np.ceil(max(hull.columns.shape[1:]) / params.cast_grid)))
    small = StandingHull(hull.columns[:, ::step, ::step], hull.silhouette[::step, ::step], hull.top, hull.height,
                         hull.standing)
    # the small grid's texel centres on the texture: (x + 0.5) / step - 0.5 in its pixels
    sx, sy = (mx + 0.5) / step - 0.5, (my + 0.5) / step - 0.5

    def on_fit(shadow: np.ndarray, sub_x: np.ndarray, sub_y: np.ndarray) -> np.ndarray:
        soft = cv2.remap(shadow.astype(np.float32), sub_x, sub_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        return soft[fit].astype(np.float64)

    def scatter(ka: float, ks: float, sh: np.ndarray) -> float:
        return groups.scatter(np.clip(1.0 - ka * occ - ks * sh, 0.05, None))

    best: tuple[float, float, float, float] | None = None  # cost, azimuth, elevation, share
    shares = np.linspace(0.1, params.shading_max, 9)
    for el in np.radians(np.arange(20.0, 81.0, 10.0)):
        for az in np.radians(np.arange(0.0, 360.0, 10.0)):
            d = np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
            sh = on_fit(hull_shadow(small, texel * step, reach, d), sx, sy)
            if sh.sum() < 20:
                continue
            for ks in shares:
                c = scatter(k_ambient, float(ks), sh)
                if best is None or c < best[0]:
                    best = (c, float(az), float(el), float(ks))
    if best is None or best[0] > (1.0 - params.cast_evidence) * ambient_cost:
        return None
    _, az, el, _ = best
    d = np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
    full = hull_shadow(hull, texel, reach, d)
    sh = on_fit(full, mx, my)
    grid = [(scatter(ka, ks, sh), ka, ks) for ka in np.linspace(0.0, params.shading_max, 19)
            for ks in np.linspace(0.0, params.shading_max, 19) if ka + ks <= 1.0]
    c, ka, ks = min(grid)
    if c > (1.0 - params.cast_evidence) * ambient_cost or ks <= 0.0:
        return None
    shadow_map = cv2.remap(full.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    # The hull is larger than the object, and so is its shadow: on the seen texels keep it only where
    # the texel is darker than its colour group by at least half the shadow's drop
    albedo = groups.albedo(np.clip(1.0 - ka * occ - ks * sh, 0.05, None))[1]
    drop = groups.lum - np.log(np.clip(1.0 - ka * occ, 0.05, None)) - albedo
    seen_map = shadow_map[fit]
    seen_map[drop > 0.5 * np.log(1.0 - ks)] = 0.0
    shadow_map[fit] = seen_map
    shadow_map = cv2.medianBlur(shadow_map, 3)
    return {"map": shadow_map, "cost": c, "ambient": float(ka), "strength": float(ks),
            "azimuth_deg": float(np.degrees(az)), "elevation_deg": float(np.degrees(el)),
            "texels": int((shadow_map > 0.5).sum())}


def shading_into_view(factor: np.ndarray, vcam: Camera, vdepth: np.ndarray, cam: Camera, depth: np.ndarray,
                      depth_tol: float = 0.02, min_gain: float = 1.002) -> tuple[np.ndarray, np.ndarray]:
    """The gain that lifts the contact shadow (1 / :class:`ContactShading`'s factor) at ``cam``'s pixels
    whose completed ``depth`` puts them on the plane within the texture. Returns (gain HxW float32, 1
    elsewhere; relit bool HxW: where the gain exceeds ``min_gain``)."""
    f3 = np.repeat(np.asarray(factor, np.float32)[..., None], 3, axis=2)
    cols, got = warp_from_reference(f3, vcam, vdepth, np.ones(vdepth.shape, bool), cam, depth,
                                    np.ones(depth.shape, bool), "backward", depth_tol)
    gain = np.ones(depth.shape, np.float32)
    gain[got] = 1.0 / np.maximum(cols[got, 0], 1e-3)
    return gain, gain > min_gain


def under_object(cameras: list[Camera], masks: list[np.ndarray], holes: list[np.ndarray], depths: list[np.ndarray],
                 grow: float = 0.02, depth_tol: float = 0.02, thin: int = 15, min_thin: int = 3, max_rms: float = 0.02,
                 max_lift: float = 0.1, sample: int = 4000, resolution: int = 256, rim: int = 0
                 ) -> tuple[UnderObject | None, str]:
    """The mask pixels of each view whose background lies on the plane under the object.

    The plane is fitted to the holes' parts deeper than ``thin`` px on a planar rim
    (:func:`~.multiview.planar_parts`), lifted with their completed ``depths``; where none is, to those
    deeper than ``min_thin`` px (0: none): an object on feet leaves thin holes, the views having seen
    the floor under it (synthetic-raised-cast, remove.under_object, mask PSNR: with every mask given
    22.95 -> 22.85, from one given mask 19.63 -> 20.19; without the fallback the option did nothing).
    The plane is then refitted to the floor seen within ``rim`` px of the holes (:func:`refit_to_rim`;
    0: off), as the inpaint stage's plane texture is.
    The object is its visual hull (the masks' cones; whether or not the fit modelled it), seen straight
    down the plane's normal by a virtual camera over the holes (:func:`hull_columns`, ``resolution``
    texels across): its
    silhouette is the texels whose column meets the hull, grown by ``grow`` x the texture's side. The
    object must stand on the plane: in most of the silhouette the hull reaches down to within
    ``max_lift`` x its height of it. A mask pixel outside the holes whose completed depth lifts it onto
    the plane (within ``depth_tol`` x its depth) inside that silhouette lay under the object: in its
    contact shadow, seen, if at all, at a grazing angle. Returns (UnderObject, "") or (None, why not)."""
    from .multiview import pinned_parts, planar_parts

    # the thick parts on a planar rim, as the inpaint stage's plane texture takes them
    planar = [planar_parts(h, d, 0.1) if h.any() else None for h, d in zip(holes, depths)]
    parts = [None if q is None else q & ~pinned_parts(h, thin) for q, h in zip(planar, holes)]
    if min_thin > 0 and sum(int(q.sum()) for q in parts if q is not None) < 3:
        # no thick part (an object on feet: the views saw the floor under it, its holes are thin): the
        # parts deeper than min_thin, as the inpaint stage's plane_thin_rim takes them
        parts = [None if q is None else q & ~pinned_parts(h, min_thin) for q, h in zip(planar, holes)]
    fitted, why = fit_hole_plane(cameras, depths, parts, sample, max_rms, holes, rim)
    if fitted is None:
        return None, why
    plane, distance = fitted[:2]
    extent = float(np.ptp(plane.inliers - np.outer(plane.distance(plane.inliers), plane.normal), axis=0).max())
    vcam = plane_camera(plane, distance, 2.0 * extent / resolution, 4 * resolution, 0.5)
    top = 0.5 * distance
    hull, why = standing_hull(hull_columns(plane, vcam, cameras, masks, top), top, max_lift)
    if hull is None:
        return None, why
    sil, height, standing = hull.silhouette, hull.height, hull.standing
    sil = grown(sil, grow)
    pixels = []
    for cam, mask, hole, depth in zip(cameras, masks, holes, depths):
        out = np.zeros(mask.shape, bool)
        ys, xs = np.nonzero(mask & ~hole & np.isfinite(depth) & (depth > 0))
        if len(ys):
            z = depth[ys, xs].astype(np.float64)
            world = cam.unproject(ys, xs, z)
            on = np.abs(plane.distance(world)) <= depth_tol * z
            px, _, inside = vcam.pixels(world)
            hit = on & inside
            hit[hit] = sil[px[hit, 1], px[hit, 0]]
            out[ys[hit], xs[hit]] = True
        pixels.append(out)
    info = {"rms_relative": plane.rms / distance, "refit": plane.refit, "object_height": height, "standing": standing,
            "silhouette_texels": int(sil.sum()), "pixels": int(sum(int(u.sum()) for u in pixels))}
    return UnderObject(pixels, plane, sil, vcam, info), ""
