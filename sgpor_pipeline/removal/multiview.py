"""The ``remove`` stage's output contract, and multi-view consistent filling.

The ``remove`` folder (``ctx.inputs["remove"]`` of the inpaint and refine stages) holds:

* ``cameras.json``: the training cameras (:func:`sgpor_pipeline.scene.save_cameras`, PINHOLE);
  ``Camera.image`` is the view name; cameras whose image is None (novel views) are ignored;
* ``renders/<view>.png``: RGB render of the scene after the object's Gaussians were deleted;
* ``context/<view>.png``: what the inpainter sees around the hole and takes its source blocks from:
  the photo outside the object mask (slightly dilated), the render inside it (divided by its opacity).
  Optional: without it the render is the context (:meth:`RemovalView.context`);
* ``holes/<view>.png``: 0/1 mask of the truly unseen region (object pixels the remaining background
  does not cover): THE region to inpaint. Whatever the render shows there is ignored;
* ``masks/<view>.png``: 0/1 object mask of every view (propagated); ``holes`` is a subset of it
  but for their rim (``remove.rim_alpha``).
  Source blocks for SBM must hold no object-mask pixel;
* ``depth/<view>.npy``: float32 HxW z-depth of the background with the hole already completed
  from its surroundings, so a filled pixel can be lifted to 3D. Optional: without it (or without
  cameras) every view is inpainted independently.
* ``under_object/camera.json`` and ``silhouette.png``: the object seen straight down the plane it
  stood on (``remove.under_object``). Optional: the plane texture (``inpaint.thick_reference =
  plane``) then fills what lay under it too.

:func:`load_remove_folder` reads and checks it; :func:`write_remove_fixture` writes one from a
synthetic scene with ground truth (holes = object masks, optionally eroded, or the truly unseen
part of them), which the tests and benchmarks use.

Multi-view consistency (DESIGN.md section 7): a reference view is filled first, its filled pixels
are lifted to 3D with its completed depth and carried into the other views, and only what is still
missing there is inpainted; or (:func:`consensus_fill`, the inpaint stage's default) every view is
filled on its own and each carried pixel takes the median of all views' fills at its surface point.
The inpaint stage carries only the :func:`pinned_parts` and :func:`planar_parts` of a hole, where
the completed depth is held by the surrounding surface. Two ways to carry them: ``backward``
(default: every hole pixel of the other view is lifted with that view's completed depth, projected
into the reference, and takes the reference's filled colour there when the depths agree, i.e. the
same surface point; no cracks) and ``splat`` (the reference's filled pixels are projected into the
other view, z-buffered, nearest pixel, kept where they land on a hole pixel whose completed depth
agrees).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from pathlib import Path

import cv2
import numpy as np

from sgpor_pipeline.errors import PipelineError
from sgpor_pipeline.imageio import read_image, read_mask, read_rgb8, to_float32, write_mask01, write_png
from sgpor_pipeline.scene import Camera, load_cameras, save_cameras

PROJECTION_MODES = ("backward", "splat")
INTERPOLATIONS = ("linear", "cubic")  # warp_from_reference's
REFERENCE_MODES = ("largest", "central")
PROGRESSIVE = "smallest_first"  # no single reference: every view carries what the views before it inpainted
CONSENSUS = "consensus"  # no reference: every view is filled on its own, then each takes the views' median


# --------------------------------------------------------------------------------------------------
# the remove folder


class OnDemand(Sequence):
    """A read-only list of per-view arrays, each read (``read(i)``) when it is indexed, every time: for
    functions that go through the views one by one. Held at once, such arrays take bytes a pixel of
    every view (a capture of 100 photos at 1600 px has 190 M pixels)."""

    def __init__(self, n: int, read: Callable[[int], np.ndarray | None]) -> None:
        self._n, self._read = n, read

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self._read(k) for k in range(*i.indices(self._n))]
        return self._read(range(self._n)[i])  # (negative indices; IndexError past the end)


@dataclass
class RemovalView:
    """One view of the remove stage's output (files are read on demand)."""

    name: str
    camera: Camera | None
    render_path: Path
    hole_path: Path
    mask_path: Path
    depth_path: Path | None
    context_path: Path | None = None

    def render(self) -> np.ndarray:
        return read_image(self.render_path)

    @property
    def context_file(self) -> Path:
        """The image to complete: ``context/<view>.png``, or the render in a folder without one."""
        return self.context_path if self.context_path is not None else self.render_path

    def context(self) -> np.ndarray:
        """The image to complete: its known pixels are the hole's context and the source blocks."""
        return read_image(self.context_file)

    def context8(self) -> np.ndarray:
        """:meth:`context` as stored, uint8 RGB: a quarter of the float image's memory, the same values
        through :func:`~sgpor_pipeline.imageio.to_float32`."""
        return read_rgb8(self.context_file)

    def hole(self) -> np.ndarray:
        return read_mask(self.hole_path)

    def mask(self) -> np.ndarray:
        return read_mask(self.mask_path) | self.hole()

    def depth(self) -> np.ndarray | None:
        if self.depth_path is None:
            return None
        return np.load(self.depth_path).astype(np.float32)

    def files(self) -> list[Path]:
        return [p for p in (self.render_path, self.hole_path, self.mask_path, self.depth_path, self.context_path)
                if p is not None]


@dataclass
class RemovalInputs:
    folder: Path
    views: list[RemovalView]

    @property
    def names(self) -> list[str]:
        return [v.name for v in self.views]

    def by_name(self, name: str) -> RemovalView:
        for v in self.views:
            if v.name == name:
                return v
        raise KeyError(name)

    def contexts8(self) -> OnDemand:
        """Every view's :meth:`RemovalView.context8`, read when indexed."""
        return OnDemand(len(self.views), lambda i: self.views[i].context8())

    def depths(self) -> OnDemand:
        """Every view's completed depth (:meth:`RemovalView.depth`), read when indexed."""
        return OnDemand(len(self.views), lambda i: self.views[i].depth())

    @property
    def has_geometry(self) -> bool:
        return all(v.camera is not None and v.depth_path is not None for v in self.views)

    def under_object(self) -> tuple[Camera, np.ndarray] | None:
        """The removed object's silhouette on the plane it stood on (``under_object/``, written by the
        remove stage with ``remove.under_object``): (a camera looking straight down at the plane, its
        bool mask), or None."""
        folder = self.folder / "under_object"
        if not (folder / "silhouette.png").is_file() or not (folder / "camera.json").is_file():
            return None
        return load_cameras(folder / "camera.json")[0], read_mask(folder / "silhouette.png")


def load_remove_folder(folder: str | Path) -> RemovalInputs:
    """Read and check a ``remove`` folder (see the module doc for the layout)."""
    folder = Path(folder)
    renders = folder / "renders"
    if not renders.is_dir():
        raise PipelineError("the remove stage's folder has no renders/", path=folder,
                            fix="rerun the remove stage (sgpor-pipeline run ... --force remove)")
    cams: dict[str, Camera] = {}
    if (folder / "cameras.json").is_file():
        cams = {c.image: c for c in load_cameras(folder / "cameras.json") if c.image is not None}
    views: list[RemovalView] = []
    for rp in sorted(renders.glob("*.png")):
        name = rp.stem
        hp, mp = folder / "holes" / f"{name}.png", folder / "masks" / f"{name}.png"
        dp = folder / "depth" / f"{name}.npy"
        cp = folder / "context" / f"{name}.png"
        if not hp.is_file():
            raise PipelineError(f"view '{name}' has a render but no hole mask", path=hp,
                                fix="the remove stage must write holes/<view>.png for every render")
        if not mp.is_file():
            mp = hp  # no object mask: the hole is the object mask
        views.append(RemovalView(name, cams.get(name), rp, hp, mp, dp if dp.is_file() else None,
                                 cp if cp.is_file() else None))
    if not views:
        raise PipelineError("the remove stage's folder has no renders/<view>.png", path=renders,
                            fix="rerun the remove stage")
    return RemovalInputs(folder, views)


# --------------------------------------------------------------------------------------------------
# geometry


@dataclass
class CropCamera(Camera):
    """A camera whose arrays (image, depth, mask) are a crop of its image starting at ``origin`` = (row,
    column). Its projection stays in the full image's pixels, so the crop gives exactly the full arrays'
    results (:func:`crop_view`): only the array indices move."""

    origin: tuple[int, int] = (0, 0)


def origin_of(cam: Camera) -> tuple[int, int]:
    """(row, column) of a camera's arrays in its full image: (0, 0) but for a :class:`CropCamera`."""
    return cam.origin if isinstance(cam, CropCamera) else (0, 0)


def crop_view(image: np.ndarray, cam: Camera, depth: np.ndarray, mask: np.ndarray
              ) -> tuple[np.ndarray, CropCamera, np.ndarray, np.ndarray]:
    """A view's (image, camera, depth, mask) cut to the bounding box of ``mask``: as a source of
    :func:`warp_from_reference` (and :func:`on_same_surface`) it gives the full view's colours bit for bit,
    since only the mask's pixels are read (their bilinear neighbours outside it weigh 0 either way). The
    inpaint stage's consensus holds one per view with a hole: the box instead of the image."""
    if isinstance(cam, CropCamera):
        raise ValueError("crop_view takes a full view, not a crop")
    ys, xs = np.nonzero(mask)
    if len(ys) == 0:
        box = (slice(0, 0), slice(0, 0))
    else:
        # (a box from row or column 1 starts at 0: sample_bilinear's float32 offset of 1 is not exact for
        # coordinates below 0.5, those of the pixels beside the box's edge; from 2 on it is)
        box = tuple(slice(0 if lo == 1 else lo, hi + 1) for lo, hi in ((int(ys.min()), int(ys.max())),
                                                                       (int(xs.min()), int(xs.max()))))
    crop = CropCamera(**{f.name: getattr(cam, f.name) for f in fields(Camera)},
                      origin=(box[0].start, box[1].start))
    return (np.ascontiguousarray(image[box]), crop, np.ascontiguousarray(depth[box]),
            np.ascontiguousarray(mask[box]))


def nearest_per_pixel(lin: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Indices of the nearest entry (smallest ``z``) for each distinct linear pixel index in ``lin``:
    a z-buffer for points splatted to pixels."""
    order = np.lexsort((z, lin))  # nearest first within each pixel
    first = np.ones(len(order), bool)
    first[1:] = lin[order][1:] != lin[order][:-1]
    return order[first]


def sample_bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray, row: int = 1024,
                    origin: tuple[int, int] = (0, 0), interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
    """``image`` (HxW or HxWxC float32) bilinearly sampled at N points (x, y: pixel-index coordinates,
    0 = centre of the first pixel; outside = 0): [N] or [N,C]. The maps are laid out in rows of
    ``row`` points because cv2.remap takes maps of fewer than 32767 rows (large masks have more points).
    ``origin`` (row, column): ``image`` is a crop starting there and x, y are in the full image; the
    offset is taken after the float32 rounding of x, y (exact), so a crop samples as the full image.
    ``interpolation``: another cv2.remap flag (``cv2.INTER_CUBIC``: see :func:`warp_from_reference`)."""
    n = len(x)
    rows = max(1, -(-n // row))
    mx = np.full(rows * row, -1e4, np.float32)
    my = np.full(rows * row, -1e4, np.float32)
    mx[:n] = x
    my[:n] = y
    if origin != (0, 0):
        mx[:n] -= np.float32(origin[1])
        my[:n] -= np.float32(origin[0])
    out = cv2.remap(np.asarray(image, np.float32), mx.reshape(rows, row), my.reshape(rows, row), interpolation,
                    borderMode=cv2.BORDER_CONSTANT)
    return out.reshape(rows * row, *image.shape[2:])[:n]


def on_same_surface(points: np.ndarray, cam: Camera, depth: np.ndarray, filled: np.ndarray,
                    depth_tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Where world points [N,3] land in a view: (continuous pixel coordinates [N,2], hit bool [N]).
    A point hits when it lies in front of the camera, inside the image, on a ``filled`` pixel whose
    completed ``depth`` agrees with its own within ``depth_tol`` (relative): the same surface point.
    With a :class:`CropCamera` ``depth`` and ``filled`` are its crop (the coordinates stay full-image)."""
    h, w = filled.shape
    uv, z = cam.project(points)
    oy, ox = origin_of(cam)
    with np.errstate(invalid="ignore"):
        iu, iv = np.floor(uv[:, 0]).astype(np.int64) - ox, np.floor(uv[:, 1]).astype(np.int64) - oy
    hit = (z > 0) & (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h)
    idx = np.nonzero(hit)[0]
    zr, zi = depth[iv[idx], iu[idx]], z[idx]
    hit[idx] = filled[iv[idx], iu[idx]] & np.isfinite(zr) & (np.abs(zr - zi) <= depth_tol * np.abs(zi))
    return uv, hit


def warp_from_reference(ref_image: np.ndarray, ref_cam: Camera, ref_depth: np.ndarray, ref_filled: np.ndarray,
                        cam: Camera, depth: np.ndarray, target: np.ndarray, mode: str = "backward",
                        depth_tol: float = 0.02, interpolation: str = "linear") -> tuple[np.ndarray, np.ndarray]:
    """Colours for ``target`` pixels of ``cam`` taken from the reference's filled pixels.

    Returns (colours HxWx3 float32, got bool HxW); ``got`` is a subset of ``target``. A pixel is
    taken only where both completed depths agree within ``depth_tol`` (relative): the same surface.
    ``ref_image``: float in [0, 1] or uint8.

    ``interpolation`` (``backward`` mode): ``linear``, or ``cubic`` (bicubic where the 4x4 reference
    pixels around the point are all filled, bilinear at the filled region's edge; clipped to [0, 1]).
    A bilinear sample halfway between two pixels is their mean: a pattern near the pixel pitch (a woven
    mat's ribs 3-4 px apart) loses most of its contrast at each resampling, and the plane texture's
    round trip (views -> texture -> view) resamples twice.
    """
    if interpolation not in INTERPOLATIONS:
        raise PipelineError(f"unknown interpolation {interpolation!r}", fix=f"use one of {', '.join(INTERPOLATIONS)}")
    ref_image = to_float32(ref_image)
    h, w = target.shape
    out = np.zeros((h, w, 3), np.float32)
    got = np.zeros((h, w), bool)
    if mode == "backward":
        ys, xs = np.nonzero(target & np.isfinite(depth) & (depth > 0))
        if len(ys) == 0:
            return out, got
        uv, ok = on_same_surface(cam.unproject(ys, xs, depth[ys, xs]), ref_cam, ref_depth, ref_filled, depth_tol)
        ys, xs, u, v = ys[ok], xs[ok], uv[ok, 0], uv[ok, 1]
        if len(ys) == 0:
            return out, got
        # bilinear sample, restricted to filled reference pixels (normalised weights)
        src = np.where(ref_filled[..., None], ref_image, 0.0).astype(np.float32)
        wmap = ref_filled.astype(np.float32)
        origin = origin_of(ref_cam)
        col = sample_bilinear(src, u - 0.5, v - 0.5, origin=origin)
        wt = sample_bilinear(wmap, u - 0.5, v - 0.5, origin=origin)
        good = wt > 1e-3
        col[good] /= wt[good, None]
        if interpolation == "cubic":
            # (the 4x4 neighbours of a point are filled where the bilinear corners' 3x3 neighbourhoods are)
            inner = cv2.erode(ref_filled.astype(np.uint8), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT,
                              borderValue=0).astype(np.float32)
            whole = sample_bilinear(inner, u - 0.5, v - 0.5, origin=origin) > 1.0 - 1e-4
            if whole.any():
                col[whole] = np.clip(sample_bilinear(src, u[whole] - 0.5, v[whole] - 0.5, origin=origin,
                                                     interpolation=cv2.INTER_CUBIC), 0.0, 1.0)
        out[ys[good], xs[good]] = col[good]
        got[ys[good], xs[good]] = True
        return out, got
    if mode == "splat":
        ys, xs = np.nonzero(ref_filled & np.isfinite(ref_depth) & (ref_depth > 0))
        if len(ys) == 0:
            return out, got
        oy, ox = origin_of(ref_cam)
        px, z, ok = cam.pixels(ref_cam.unproject(ys + oy, xs + ox, ref_depth[ys, xs]))  # (cam is target's h x w)
        ys, xs, z, iu, iv = ys[ok], xs[ok], z[ok], px[ok, 0], px[ok, 1]
        ok = target[iv, iu] & (np.abs(depth[iv, iu] - z) <= depth_tol * np.abs(z))
        ys, xs, z, iu, iv = ys[ok], xs[ok], z[ok], iu[ok], iv[ok]
        if len(ys) == 0:
            return out, got
        lin = iv * w + iu
        keep = nearest_per_pixel(lin, z)
        lin, ys, xs = lin[keep], ys[keep], xs[keep]
        out.reshape(-1, 3)[lin] = ref_image[ys, xs]
        got.reshape(-1)[lin] = True
        return out, got
    raise PipelineError(f"unknown projection mode {mode!r}", fix=f"use one of {', '.join(PROJECTION_MODES)}")


def gather_from_views(sources: list[tuple[np.ndarray, Camera, np.ndarray, np.ndarray]], cam: Camera,
                      depth: np.ndarray, target: np.ndarray, mode: str = "backward",
                      depth_tol: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """:func:`warp_from_reference` from several filled views (image, camera, completed depth, mask of
    the pixels to carry), in order: each ``target`` pixel takes the first view that has it."""
    out = np.zeros((*target.shape, 3), np.float32)
    got = np.zeros(target.shape, bool)
    for image, src_cam, src_depth, src_filled in sources:
        todo = target & ~got
        if not todo.any():
            break
        col, g = warp_from_reference(image, src_cam, src_depth, src_filled, cam, depth, todo, mode, depth_tol)
        out[g] = col[g]
        got |= g
    return out, got


def consensus_partners(i: int, filled: list[tuple[np.ndarray, Camera, np.ndarray, np.ndarray] | None],
                       max_views: int, depth_tol: float = 0.02, sample: int = 256) -> list[int]:
    """The (at most ``max_views``) other views whose fills reach most of view i's carried pixels.

    A regular subsample of at most ``sample`` carried pixels of view i is lifted with its completed
    depth and projected into every other view; a view scores the points that land on its own carried
    pixels at the same depth (within ``depth_tol``, relative); among views that reach as many, the
    nearer camera (centre distance) ranks first. Views that reach none are left out. ``max_views``
    <= 0: every view that reaches any point."""
    _, cam, depth, carry = filled[i]
    ys, xs = np.nonzero(carry & np.isfinite(depth) & (depth > 0))
    if len(ys) == 0:
        return []
    pick = np.unique(np.linspace(0, len(ys) - 1, min(sample, len(ys))).astype(np.int64))
    points = cam.unproject(ys[pick], xs[pick], depth[ys[pick], xs[pick]])
    scores: list[tuple[int, float, int]] = []
    for j, other in enumerate(filled):
        if j == i or other is None or not other[3].any():
            continue
        hits = int(on_same_surface(points, other[1], other[2], other[3], depth_tol)[1].sum())
        if hits:
            scores.append((-hits, float(np.linalg.norm(other[1].center - cam.center)), j))
    scores.sort()
    chosen = [j for _, _, j in scores]
    return chosen[:max_views] if max_views > 0 else chosen


def consensus_fill(i: int, filled: list[tuple[np.ndarray, Camera, np.ndarray, np.ndarray] | None],
                   mode: str = "backward", depth_tol: float = 0.02,
                   max_views: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """View i's carried pixels completed by the per-channel median of every view's own fill there.

    ``filled[j]``: (image filled on its own, camera, completed depth, mask of the pixels it may carry
    and receive) or None (no hole). Each carried pixel of view i is lifted with its completed depth
    and looked up in every other view's fill (:func:`warp_from_reference`: the same surface point,
    depths within ``depth_tol``); the median over those colours and view i's own is the result.
    Independent fills disagree where the photos do not decide what lies behind the object; the
    median keeps what most of them agree on, and every view takes it from the same set of fills,
    so the views agree. With ``max_views`` > 0 only that many other views vote: those whose fills
    reach most of view i's carried pixels (:func:`consensus_partners`), so a capture of hundreds of
    views costs N x max_views warps instead of N^2. Returns (image HxWx3 float32: view i's fill with
    those pixels replaced, fused bool HxW: pixels at least one other view contributed to, votes int32
    HxW: fills that reached each carried pixel, its own included). The images may be uint8."""
    image, cam, depth, carry = filled[i]
    out = np.array(to_float32(image), np.float32)  # (a copy)
    votes = np.zeros(carry.shape, np.int32)
    ys, xs = np.nonzero(carry)
    if len(ys) == 0:
        return out, np.zeros(carry.shape, bool), votes
    stack = [out[ys, xs]]
    partners = (consensus_partners(i, filled, max_views, depth_tol) if max_views > 0 else
                [j for j, other in enumerate(filled) if j != i and other is not None and other[3].any()])
    for j in partners:
        other = filled[j]
        col, got = warp_from_reference(other[0], other[1], other[2], other[3], cam, depth, carry, mode, depth_tol)
        stack.append(np.where(got[ys, xs, None], col[ys, xs], np.nan).astype(np.float32))
    values = np.stack(stack)  # [views, pixels, 3]; NaN where a view's fill does not reach the pixel
    n = np.isfinite(values[..., 0]).sum(0)
    out[ys, xs] = np.nanmedian(values, axis=0)
    votes[ys, xs] = n
    return out, votes > 1, votes


def choose_reference(holes: list[np.ndarray], cameras: list[Camera | None], mode: str = "largest",
                     names: list[str] | None = None) -> int:
    """Index of the reference view: ``largest`` hole, the ``central`` camera among views with a hole,
    or a view name."""
    areas = np.array([int(np.asarray(h).sum()) for h in holes])
    if not np.any(areas > 0):
        return -1
    if mode == "largest":
        return int(np.argmax(areas))
    if mode == "central":
        idx = [i for i, (a, c) in enumerate(zip(areas, cameras)) if a > 0 and c is not None]
        if not idx:
            return int(np.argmax(areas))
        centres = np.array([cameras[i].center for i in idx])
        d = np.linalg.norm(centres - centres.mean(0), axis=1)
        return idx[int(np.argmin(d))]
    if names is not None and mode in names:
        return names.index(mode)
    raise PipelineError(f"unknown reference view {mode!r}",
                        fix=f"use {', '.join((CONSENSUS, PROGRESSIVE) + REFERENCE_MODES)} or a view name")


# --------------------------------------------------------------------------------------------------
# fixtures from synthetic scenes (ground truth)


def unseen_holes(scene, depth_tol: float = 0.01) -> list[np.ndarray]:
    """Per view, the object pixels whose background point no other view sees (the truly unseen part).

    A background point (from the object-free depth) counts as seen by another view when it projects
    inside that image, outside that view's object mask, and at that view's object-free depth.
    """
    out = []
    n = len(scene.cameras)
    for i in range(n):
        m = scene.masks[i]
        ys, xs = np.nonzero(m)
        seen = np.zeros(len(ys), bool)
        if len(ys):
            X = scene.cameras[i].unproject(ys, xs, scene.depth_gt[i][ys, xs])
            for j in range(n):
                if j == i:
                    continue
                cam = scene.cameras[j]
                px, z, ok = cam.pixels(X)
                iu, iv = px[:, 0], px[:, 1]
                k = np.nonzero(ok & ~seen)[0]
                dj = scene.depth_gt[j][iv[k], iu[k]]
                vis = (~scene.masks[j][iv[k], iu[k]]) & (np.abs(dj - z[k]) <= depth_tol * z[k])
                seen[k[vis]] = True
        hole = np.zeros_like(m)
        hole[ys[~seen], xs[~seen]] = True
        out.append(hole)
    return out


def write_remove_fixture(scene, folder: str | Path, holes: str = "mask", erode: int = 0, fill: str = "black",
                         views: list[int] | None = None) -> Path:
    """Write a ``remove`` folder from a synthetic scene with ground truth.

    ``holes``: "mask" (the whole object mask: nothing recovered from other views) or "unseen" (the
    part no other view sees, :func:`unseen_holes`); ``erode``: erode the holes by this many pixels
    (emulates background recovered at the rim). Renders = the photo outside the object mask (with
    the object's shadow, if the scene has one), the object-free truth inside it, with the hole pixels
    ``fill``-ed: "black" or "object" (the with-object image; both must be ignored by a correct
    inpainter). Depth = the object-free depth (a perfectly completed depth).
    """
    folder = Path(folder)
    for sub in ("renders", "holes", "masks", "depth"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    idx = list(range(len(scene.cameras))) if views is None else list(views)
    hs = unseen_holes(scene) if holes == "unseen" else [m.copy() for m in scene.masks]
    if erode > 0:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * erode + 1, 2 * erode + 1))
        hs = [cv2.erode(h.astype(np.uint8), kernel).astype(bool) for h in hs]
    for i in idx:
        name = scene.cameras[i].name
        render = np.where(scene.masks[i][..., None], scene.images_gt[i], scene.images[i])
        render[hs[i]] = 0.0 if fill == "black" else scene.images[i][hs[i]]
        write_png(folder / "renders" / f"{name}.png", render)
        write_mask01(folder / "holes" / f"{name}.png", hs[i])
        write_mask01(folder / "masks" / f"{name}.png", scene.masks[i])
        np.save(folder / "depth" / f"{name}.npy", scene.depth_gt[i].astype(np.float32))
    save_cameras(folder / "cameras.json", [scene.cameras[i] for i in idx])
    return folder


# --------------------------------------------------------------------------------------------------
# filling one view (reference or not)


FILLED_NONE, FILLED_PROJECTED, FILLED_INPAINTED = 0, 1, 2


def pinned_parts(hole: np.ndarray, max_rim_distance: float) -> np.ndarray:
    """The connected parts of ``hole`` (8-connected) none of whose pixels lies farther than
    ``max_rim_distance`` pixels from the part's rim: there the completed depth is pinned by the
    surrounding surface on every side, so a fill lifted with it lands in the right place in another
    view. ``max_rim_distance`` <= 0: the whole hole."""
    hole = np.asarray(hole, bool)
    if max_rim_distance <= 0 or not hole.any():
        return hole.copy()
    n, labels = cv2.connectedComponents(hole.astype(np.uint8), connectivity=8)
    rim = cv2.distanceTransform(hole.astype(np.uint8), cv2.DIST_L2, 3)
    deepest = np.zeros(n, np.float32)
    np.maximum.at(deepest, labels[hole], rim[hole])
    thin = deepest <= max_rim_distance
    thin[0] = False  # label 0 is the background
    return thin[labels]


def planar_parts(hole: np.ndarray, depth: np.ndarray, max_misfit: float, ring: int = 3) -> np.ndarray:
    """The connected parts of ``hole`` (8-connected) whose rim, the known pixels within ``ring`` px
    outside the hole, lies on a plane: a plane's inverse depth is affine in pixel coordinates, so an
    affine least-squares fit to the rim's 1 / ``depth`` leaves an RMS residual of at most
    ``max_misfit`` x its mean. That is where the hole's completed depth (harmonic interpolation of
    inverse depth from the rim, exact for planes) can be trusted. A rim across a depth step (a
    foreground object beside the far background) misfits by tens of percent. ``max_misfit`` <= 0: the
    whole hole. A part with fewer than 3 known rim depths is not planar."""
    hole = np.asarray(hole, bool)
    if max_misfit <= 0 or not hole.any():
        return hole.copy()
    n, labels = cv2.connectedComponents(hole.astype(np.uint8), connectivity=8)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * ring + 1, 2 * ring + 1))
    grown = cv2.dilate(labels.astype(np.float32), k)  # the largest label within ring px (touching parts: either)
    z = np.asarray(depth, np.float64)
    rim = ~hole & (grown > 0) & np.isfinite(z) & (z > 0)
    ys, xs = np.nonzero(rim)
    lab, inv = grown[ys, xs].astype(np.int64), 1.0 / z[ys, xs]
    planar = np.zeros(n, bool)
    for part in range(1, n):
        sel = lab == part
        if sel.sum() < 3:
            continue
        A = np.stack([xs[sel], ys[sel], np.ones(int(sel.sum()))], 1).astype(np.float64)
        coef, *_ = np.linalg.lstsq(A, inv[sel], rcond=None)
        misfit = np.sqrt(np.mean((A @ coef - inv[sel]) ** 2)) / np.mean(inv[sel])
        planar[part] = misfit <= max_misfit
    return planar[labels] & hole


def fill_view(render: np.ndarray, hole: np.ndarray, backend: str, bank, params,
              prior: tuple[np.ndarray, np.ndarray] | None = None, depth: np.ndarray | None = None,
              labels: np.ndarray | None = None, guide: tuple[np.ndarray, np.ndarray] | None = None):
    """Complete one view's hole: first the ``prior`` pixels (colours, mask) carried from a reference
    view, then the rest with ``backend`` ("sbm": :func:`~sgpor_pipeline.removal.sbm.inpaint_view`
    with ``bank``, ``params``, the view's completed ``depth``, structure ``labels`` and initial content
    ``guide`` (colours, mask); "opencv": xphoto FSR).

    Returns (image float32 HxWx3, filled_from uint8 HxW: 0 none, 1 projected, 2 inpainted,
    SBMResult or None).
    """
    from .sbm import fsr_inpaint, inpaint_view

    img = np.asarray(render, np.float32).copy()
    hole = np.asarray(hole, bool)
    filled_from = np.zeros(hole.shape, np.uint8)
    known = np.zeros_like(hole)
    if prior is not None:
        colours, got = prior
        got = got & hole
        img[got] = colours[got]
        filled_from[got] = FILLED_PROJECTED
        known = got
    todo = hole & ~known
    result = None
    if todo.any():
        if backend == "sbm":
            result = inpaint_view(img, hole, bank, params, known=known, depth=depth, labels=labels,
                                  guide=None if guide is None else guide[0],
                                  guide_mask=None if guide is None else guide[1])
            img = result.image
        elif backend == "opencv":
            img = fsr_inpaint(img, todo)
        else:
            raise PipelineError(f"unknown inpainting backend {backend!r}", fix="use sbm or opencv")
        filled_from[todo] = FILLED_INPAINTED
    return img, filled_from, result
