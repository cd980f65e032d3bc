"""ingest: normalise photos and masks, and import known cameras.

Out: ``images/<view>.png`` (8-bit RGB, EXIF orientation applied, optionally downscaled),
``masks/<view>.png`` (0/1) for the views that have a mask, ``views.json`` (with each photo's EXIF GPS
position, when it has one: the export's metric scale, :mod:`sgpor_pipeline.gps`), and ``cameras.json``
when ``--cameras`` was given (cameras without an image are kept as novel views).
Each photo is a cached item: adding a photo to the folder processes only that photo.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from sgpor_pipeline.config import added_param
from sgpor_pipeline.dag import Stage, StageContext
from sgpor_pipeline.errors import PipelineError, named
from sgpor_pipeline.gps import read_gps
from sgpor_pipeline.imageio import (
    IMAGE_EXTENSIONS,
    UnreadableImageError,
    list_images,
    read_mask,
    read_rgb8,
    resize_mask_nearest,
    same_aspect,
    target_size,
    write_mask01,
    write_png,
)
from sgpor_pipeline.scene import Camera, save_cameras
from sgpor_pipeline.views import View, save_views

MIN_IMAGES = 3
FULL_MASK_SHARE = 0.99  # every mask at least this full: the photos given as masks, not a scene to rebuild
# A mask more than this full whose zero part reaches at most one side of the photo looks inverted (the
# object painted black): a real object's surroundings reach three or four sides.
INVERTED_SHARE = 0.5


@dataclass
class IngestParams:
    # Longest image side after downscaling, in pixels; 0 keeps the original size. The Gaussians are
    # fitted and re-fitted at 640 px (fit / finetune max_size) and SIFT runs at most at 1600 px
    # (sfm.max_image_size), but masks, remove, inpaint and refine work at this size, in time and memory
    # about linear in the pixels. Session 31, lund + box (28 views): at 960x718 remove 31 s / 1.8 GB,
    # inpaint 83 s / 2.3 GB peak; the same photos at 4032x3016, downscaled to 1600x1197: remove 89 s,
    # inpaint 245 s, the whole run to inpaint 11 min and 4.4 GB. At 4032 px they would be 6x that.
    # 1600 keeps SIFT's input as it was.
    max_size: int = 1600
    # Which value of a mask is the object: "auto" takes non-zero (white) and stops the run when every
    # mask looks inverted (INVERTED_SHARE; warns about some), "object" takes non-zero without that check,
    # "inverted" takes zero (black) as the object.
    mask_polarity: Literal["auto", "object", "inverted"] = added_param("auto")


def _by_stem(paths: list[Path], what: str) -> dict[str, Path]:
    out: dict[str, Path] = {}
    for p in paths:
        if p.stem in out:
            raise PipelineError(f"two {what} share the base name '{p.stem}': {out[p.stem].name} and {p.name}",
                                path=p.parent, fix="rename or remove one of them")
        out[p.stem] = p
    return out


# How mask files are often named after their photo IMG_01.jpg, besides IMG_01.png: IMG_01_mask.png,
# mask_IMG_01.png, IMG_01.jpg.png (the photo's whole name). Matched case-insensitively; a mask of the
# photo's own base name always wins.
MASK_SUFFIXES = ("_mask", "-mask", ".mask", " mask", "_masks", "_seg", "-seg", "_label", "_matte", "_alpha")
MASK_PREFIXES = ("mask_", "mask-", "masks_")


def mask_base_names(stem: str) -> list[str]:
    """The photo base names a mask's base name ``stem`` may stand for, most specific first: itself, the
    name without an image extension left in it (``IMG_01.jpg``), without a mask suffix or prefix."""
    names = [stem]
    inner = Path(stem)
    if inner.suffix.lower() in IMAGE_EXTENSIONS:
        names.append(inner.stem)
    lower = stem.lower()
    for suffix in MASK_SUFFIXES:
        if lower.endswith(suffix) and len(stem) > len(suffix):
            bare = stem[:-len(suffix)]
            names += [bare] + ([Path(bare).stem] if Path(bare).suffix.lower() in IMAGE_EXTENSIONS else [])
    for prefix in MASK_PREFIXES:
        if lower.startswith(prefix) and len(stem) > len(prefix):
            names.append(stem[len(prefix):])
    return list(dict.fromkeys(names))


def match_masks(paths: list[Path], photos: set[str]) -> tuple[dict[str, Path], list[str]]:
    """Each photo's mask among ``paths``, by :func:`mask_base_names`: (photo base name -> mask file, the
    masks that name no photo). A mask of the photo's own base name wins over one named by a rule; two
    masks that only a rule gives the same photo are an error naming both."""
    exact = _by_stem(paths, "masks")
    out = {stem: p for stem, p in exact.items() if stem in photos}
    by_rule: dict[str, Path] = {}
    orphans = []
    for stem, p in exact.items():
        if stem in photos:
            continue
        name = next((n for n in mask_base_names(stem)[1:] if n in photos), None)
        if name is None or name in out:  # (no photo, or the photo has a mask of its own name)
            orphans.append(stem)
        elif name in by_rule:
            raise PipelineError(f"two masks name the photo '{name}': {by_rule[name].name} and {p.name}",
                                path=p.parent, fix="keep one mask per photo")
        else:
            by_rule[name] = p
    return {**out, **by_rule}, sorted(orphans)


def _link_or_copy(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def looks_inverted(mask: np.ndarray) -> bool:
    """Whether a bool mask looks painted the wrong way round (:data:`INVERTED_SHARE`)."""
    if not INVERTED_SHARE < mask.mean() < 1.0:
        return False
    zero = ~mask
    return sum(bool(edge.any()) for edge in (zero[0], zero[-1], zero[:, 0], zero[:, -1])) <= 1


def build_view_item(image_path: Path, mask_path: Path | None, max_size: int, folder: Path,
                    invert_mask: bool = False) -> None:
    """Normalise one photo (and its mask, zero = object where ``invert_mask``) into ``folder``:
    image.png, mask.png, info.json."""
    rgb = read_rgb8(image_path)
    h0, w0 = rgb.shape[:2]
    w, h = target_size(w0, h0, max_size)
    if (w, h) != (w0, h0):
        rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
    info = {"width": w, "height": h, "source_width": w0, "source_height": h0, "mask_pixels": None}
    if mask_path is not None:
        mask = read_mask(mask_path)
        if invert_mask:
            mask = ~mask
        mh, mw = mask.shape
        if not same_aspect(mw, mh, w0, h0):
            raise PipelineError(
                f"mask is {mw}x{mh} but its image {image_path.name} is {w0}x{h0} (another aspect ratio)",
                path=mask_path, fix="export the mask at the image's size (or a scaled copy of it)")
        mask = resize_mask_nearest(mask, w, h)
        write_mask01(folder / "mask.png", mask)
        info["mask_pixels"] = int(mask.sum())
    write_png(folder / "image.png", rgb)
    (folder / "info.json").write_text(json.dumps(info))


def import_cameras(path: Path, views: list[View]) -> list[Camera]:
    """Known cameras matched to the views by base name, scaled to the ingested image size."""
    from sgpor_pipeline.camera_io import load_cameras_any

    cameras = load_cameras_any(path)
    by_name = {v.name: v for v in views}
    cam_names = {c.name for c in cameras}
    missing = [v.name for v in views if v.name not in cam_names]
    if missing:
        shown = ", ".join(missing[:8]) + (" ..." if len(missing) > 8 else "")
        raise PipelineError(f"{len(missing)} image(s) have no camera in the cameras file: {shown}",
                            path=path, fix="add cameras for them, remove those images, or omit --cameras to "
                                           "estimate all cameras with SfM")
    out: list[Camera] = []
    view_scale: tuple[float, float] | None = None
    for cam in cameras:
        view = by_name.get(cam.name)
        if view is None:
            continue
        if not same_aspect(cam.width, cam.height, view.source_width, view.source_height):
            raise PipelineError(
                f"camera '{cam.name}' is {cam.width}x{cam.height} but its image is "
                f"{view.source_width}x{view.source_height} (another aspect ratio)",
                path=path, fix="give cameras for these images (EXIF rotation is applied to images)")
        scaled = cam.scaled(view.width, view.height)
        scaled.image = view.name
        view_scale = (view.width / cam.width, view.height / cam.height)
        out.append(scaled)
    for cam in cameras:  # novel views: no image; scaled like the photos so they share the frame's pixels
        if cam.name in by_name:
            continue
        sx, sy = view_scale or (1.0, 1.0)
        novel = cam.scaled(max(1, round(cam.width * sx)), max(1, round(cam.height * sy)))
        novel.image = None
        out.append(novel)
    return out


class IngestStage(Stage):
    name = "ingest"
    VERSION = 2  # 2: a mask PNG with varying transparency is its opaque part (imageio.read_mask)
    Params = IngestParams
    raw_inputs = ("images", "masks", "cameras")

    def run(self, ctx: StageContext) -> None:
        image_dir = Path(ctx.run_inputs.images)
        photos = list_images(image_dir)
        mask_dir = ctx.run_inputs.masks
        beside = mask_dir is not None and Path(mask_dir).is_dir() and Path(mask_dir).resolve() == image_dir.resolve()
        # masks beside their photos (IMG_01.jpg, IMG_01_mask.png): a file that a mask rule names after
        # another file of the folder is a mask, not a photo
        stems = {p.stem for p in photos}
        named_masks = [p for p in photos if any(n in stems for n in mask_base_names(p.stem)[1:])]
        if named_masks and mask_dir is None:
            raise PipelineError(f"{len(named_masks)} file(s) here look like masks of the photos beside them "
                                f"({named([p.name for p in named_masks], 3)}), and no --masks was given",
                                path=image_dir,
                                fix=f"pass --masks {image_dir} to use them as the object's masks, or move them out "
                                    "of the photo folder")
        if beside:
            photos = [p for p in photos if p not in named_masks]
        images = _by_stem(photos, "images")
        if not images:
            nested = {d.name: len(list_images(d)) for d in sorted(Path(image_dir).iterdir())
                      if d.is_dir() and not d.name.startswith(".")}
            nested = {name: n for name, n in nested.items() if n}
            where = (f"; its subfolders hold some: {named([f'{k} ({n})' for k, n in nested.items()], 3)}"
                     if nested else "")
            raise PipelineError(f"no images found (JPEG, PNG, TIFF, BMP, WebP, HEIC){where}", path=image_dir,
                                fix="point the command at the folder that holds your photos"
                                    + (f", e.g. {Path(image_dir) / next(iter(nested))}" if nested else ""))
        masks: dict[str, Path] = {}
        if mask_dir is not None:
            if not Path(mask_dir).is_dir():
                raise PipelineError("mask folder not found", path=mask_dir, fix="check the --masks path")
            # (beside the photos without mask-named files: the photos are passed as their own masks)
            mask_files = named_masks if beside and named_masks else list_images(mask_dir)
            masks, orphans = match_masks(mask_files, set(images))
            if orphans:
                ctx.log.warning(f"{len(orphans)} mask(s) have no image of the same base name and are ignored: "
                                f"{', '.join(orphans)}")
            if not masks:
                raise PipelineError("no mask has the base name of an image", path=mask_dir,
                                    fix="name each mask like its photo (IMG_01.jpg -> IMG_01.png, IMG_01_mask.png "
                                        "or IMG_01.jpg.png)")
            renamed = sorted(f"{p.name} -> {stem}" for stem, p in masks.items() if p.stem != stem)
            if renamed:
                ctx.log.info(f"{len(renamed)} mask(s) matched to their photo by name: {named(renamed, 3)}")

        (ctx.out_dir / "images").mkdir()
        (ctx.out_dir / "masks").mkdir()
        views: list[View] = []
        unreadable: list[str] = []
        empty_masks: list[str] = []
        mask_share: dict[str, float] = {}
        inverted: list[str] = []  # masks that look painted the wrong way round
        invert = ctx.params.mask_polarity == "inverted"
        for stem, path in ctx.progress(sorted(images.items()), total=len(images), desc="ingest"):
            mask_path = masks.get(stem)
            key = {"image": ctx.file_digest(path), "mask": None if mask_path is None else ctx.file_digest(mask_path)}
            try:
                item = ctx.cached_item(key, lambda folder, p=path, m=mask_path:
                                       build_view_item(p, m, ctx.params.max_size, folder, invert))
            except UnreadableImageError as e:
                unreadable.append(str(e).split(": ", 1)[0])
                continue
            info = json.loads((item / "info.json").read_text())
            _link_or_copy(item / "image.png", ctx.out_dir / "images" / f"{stem}.png")
            mask_rel = None
            if (item / "mask.png").exists():
                mask_rel = f"masks/{stem}.png"
                _link_or_copy(item / "mask.png", ctx.out_dir / mask_rel)
                if info["mask_pixels"] == 0:
                    empty_masks.append(stem)
                mask_share[stem] = info["mask_pixels"] / max(info["width"] * info["height"], 1)
                if (ctx.params.mask_polarity == "auto" and mask_share[stem] > INVERTED_SHARE
                        and looks_inverted(read_mask(item / "mask.png"))):
                    inverted.append(stem)
            gps = read_gps(path)  # (read here, not in the item: cheap, and items cached before it stay valid)
            views.append(View(stem, f"images/{stem}.png", mask_rel, info["width"], info["height"], path.name,
                              info["source_width"], info["source_height"], None if gps is None else list(gps)))

        if unreadable:
            ctx.log.warning(f"skipped {len(unreadable)} unreadable file(s): {', '.join(unreadable)} (fix: re-export "
                            "them, or move them out of the folder; the other photos are used)")
        if len(views) < MIN_IMAGES:
            raise PipelineError(f"only {len(views)} usable image(s); at least {MIN_IMAGES} are needed",
                                path=image_dir, fix="add more overlapping photos of the scene"
                                + (" or replace the unreadable ones" if unreadable else ""))
        masked = [v for v in views if v.mask is not None]
        if masks and masked and len(empty_masks) == len(masked):
            raise PipelineError("every mask is empty (no non-zero pixel): there is no object to remove",
                                path=mask_dir, fix="paint the object non-zero (white) in at least one mask")
        full = [v for v in masked if mask_share[v.name] >= FULL_MASK_SHARE]
        if masks and masked and len(full) == len(masked):
            raise PipelineError(f"every mask covers {FULL_MASK_SHARE:.0%} or more of its photo: nothing of the scene "
                                "is left to rebuild the background from", path=mask_dir,
                                fix="pass the folder of masks, not of photos: the object non-zero (white), the rest "
                                    "zero (black)")
        polarity_fix = ("if the object is black (zero) in your masks: --set ingest.mask_polarity=inverted; "
                        "to take them as they are: --set ingest.mask_polarity=object")
        if masks and masked and len(inverted) == len([v for v in masked if v.name not in empty_masks]):
            raise PipelineError(f"every mask looks inverted: more than {INVERTED_SHARE:.0%} of each photo is non-zero "
                                "(the object) while the rest, reaching at most one side of the photo, looks like the "
                                f"object ({named(inverted, 3)})", path=mask_dir, fix=polarity_fix)
        if inverted:
            ctx.log.warning(f"{len(inverted)} mask(s) look inverted (the object zero, the rest non-zero): "
                            f"{named(inverted, 5)}; {polarity_fix}")
        if empty_masks:
            ctx.log.warning(f"{len(empty_masks)} mask(s) are empty; the object is taken as not visible there: "
                            f"{', '.join(empty_masks)}")
        save_views(ctx.out_dir, views)
        if ctx.run_inputs.cameras is not None:
            cameras = import_cameras(Path(ctx.run_inputs.cameras), views)
            save_cameras(ctx.out_dir / "cameras.json", cameras)
            ctx.notes["cameras_imported"] = len(cameras)
            ctx.notes["novel_cameras"] = sum(c.image is None for c in cameras)
        sizes = np.array([[v.width, v.height] for v in views])
        downscaled = [v for v in views if (v.width, v.height) != (v.source_width, v.source_height)]
        if downscaled:
            v = downscaled[0]
            ctx.log.info(f"ingest: {len(downscaled)} of {len(views)} photos downscaled to at most "
                         f"{ctx.params.max_size} px (e.g. {v.source_width}x{v.source_height} -> {v.width}x{v.height}; "
                         f"--set ingest.max_size=0 keeps the original size)")
        with_gps = sum(v.gps is not None for v in views)
        if with_gps:
            ctx.log.info(f"ingest: {with_gps} of {len(views)} photos carry a GPS position (the export's metric "
                         "scale when they spread far enough: export.scale_from_gps)")
        ctx.notes.update(images=len(views), masks=len(masked), unreadable=unreadable, gps=with_gps,
                         size=[int(sizes[:, 0].max()), int(sizes[:, 1].max())])
