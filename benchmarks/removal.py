"""Removal benchmark: the whole pipeline against ground truth, with its baselines and ablations in one run.

    python benchmarks/removal.py [--quick] [--json] [--out DIR] [--data DIR]
                                 [--scenes synthetic,synthetic-box,lund,statue,room[,statue-box,
                                           synthetic-box-contact,synthetic-box-cast,
                                           synthetic-raised-cast,synthetic-box-1mask,synthetic-cast,
                                           synthetic-raised-cast-1mask,lund-1mask,statue-box-1mask,
                                           synthetic-box-edge,synthetic-box-corner,synthetic-box-round,
                                           synthetic-photos,synthetic-video,
                                           synthetic-raised,synthetic-box-coins,synthetic-box-brick]]
                                 [--set STAGE.PARAM=VALUE ...]   (overrides for every run of (a), (b), (c))
                                 [--preset detail|fast]   (a named parameter set, under the --set items)
                                 [--novel]   (+ the novel-view protocol (d) on the scenes of (a) and (b))
                                 [--fit-seeds 0,1,2]   (every method on each seed's fit; targets on the mean)
                                 [--methods ours,fsr-refit]   (only these methods: experiments; targets not judged)

What was measured with it, session by session (which option won what, and by how much), is in
``benchmarks/removal_results.md``; this docstring says what it measures and how.

Every number comes from FULL pipeline runs (:func:`sgpor_pipeline.runner.run_pipeline`, ingest ..
finetune + evaluate, no export). The variants of a scene run in the SAME run folder with different
config overrides, so the content-addressed cache shares ingest / sfm / fit / masks / remove between
them (one fit per scene) and a rerun with the same ``--out`` resumes from the cache. The rasterizer
kernel's build (x86-64 level, printed in the header and stored as ``kernel``) and the library
versions change every fit, so compare methods within one run.

Methods (rows), DESIGN.md sections 7 and 8:

* ``ours``: the default configuration (SBM inpainting, multi-view fills, RPR, finetune).
* ``delete-only``: the remove stage's render (object Gaussians deleted, holes left as they are); the
  evaluate stage reports it from the same run as ``delete_only``.
* ``fsr-refit``: per-view 2D inpainting of the WHOLE object mask with OpenCV xphoto FSR, then re-fit
  (the SPIn-NeRF-style baseline: no use of what other views saw behind the object):
  ``remove.hole_mode=mask inpaint.backend=opencv inpaint.multiview=false refine.max_rounds=0``
  (finetune on). Multi-view fusion is switched off too, otherwise the "per-view" baseline would still
  fuse the views' fills (``inpaint.reference``; stages/inpaint.py does that for any backend).
* ``no-sbm``: ours with FSR instead of SBM: ``inpaint.backend=opencv`` (multi-view + RPR + finetune;
  RPR then retrieves source blocks itself for the FSR fill, see stages/refine.py).
* ``no-rpr``: ours without RPR: ``refine.max_rounds=0``.
* ``no-sbm-no-rpr`` (not a baseline of the target): FSR without RPR. SBM's fills have no block with
  too little detail, so ours vs no-rpr cannot show what RPR does; no-sbm vs this row shows it where it
  has work (an [INFO] line).

Protocols:

(a) Generated scenes with exact cameras, every mask given and object-free renders as the truth.
    ``synthetic`` is the embedded demo scene (``SceneParams()``: 24 views 256x192, inward rig), i.e.
    exactly ``sgpor-pipeline demo``; ``demo_seconds`` is the sum of the stage build times ingest ..
    finetune of its ``ours`` run (from the cache manifests: the cold-run time even when resumed).
    The others change one thing of it (``SYNTHETIC_SCENES`` in the code): ``synthetic-box`` a box in place of the
    sphere, whose flat base hides about 29 % of its mask from every view (where inpainting decides);
    ``-contact`` / ``-cast`` its photos (not the truth) carry its ambient occlusion / hard shadow;
    ``synthetic-raised[-cast]`` the box on short feet; ``-edge`` / ``-corner`` the rug's edge or corner
    under the box; ``synthetic-cast`` the sphere's shadow; ``-1mask`` scenes from ONE given mask
    (scored over the true masks, ``evaluate.score_masks=input``; the propagated masks' IoU is
    reported); ``synthetic-photos`` the demo run as photos, SfM estimating the cameras;
    ``synthetic-video`` a forward-facing walk of 120 views written as an MP4, 24 photos taken from it
    by ``sgpor-pipeline frames``, SfM, and the object from ONE given mask.
(b) A synthetic object inserted into a real capture. Our SfM runs on the untouched photos at full
    size; its undistorted PINHOLE images are downscaled to 320 px (``lund``; 240 with ``--quick``) or
    384 px (``statue-box``), intrinsics scaled alike. A textured box is composited into them with
    :func:`sgpor_pipeline.synthetic.insert_object` (placed at the SfM point seen near the image centre
    by the most cameras, moved 15 % towards those cameras so that nothing real occludes it:
    ``place_object``). The pipeline runs on the photos with the box and the exact masks, importing the
    cameras as known cameras (the ``--cameras`` route: poses kept, points re-triangulated, so the truth
    matches pixel for pixel); evaluate compares with the untouched photos. ``lund-1mask`` /
    ``statue-box-1mask`` (opt-in) give only the mask of the view where the box is largest.
(c) ``statue`` (SPIn-NeRF statue, 29 views, 384 px) and ``room`` (mip-NeRF 360 room, 24 views 256 px),
    our own SfM, no ground truth: mask propagation from 1, 2 or 4 given masks (``masks.max_given``,
    the first N views in name order), IoU of each propagated mask against the given one on the views
    whose mask was NOT given; then the full removal from 2 masks, its multi-view consistency and a
    contact sheet.
(d) ``--novel``, the SPIn-NeRF protocol: every ``NOVEL_EVERY``-th view of (a) and (b) is held out (its
    photo, mask and truth withheld, only its camera given as a novel camera); every method runs on the
    other views in a run folder of its own, and its final Gaussians are rendered at the held-out
    cameras and scored inside the object's mask there (``<scene>_novel_mask_psnr<suffix>``, ...). A
    method cannot memorise its own 2D fill at a view it never saw. Opt-in: about 13 more minutes.

Beside the methods, each ground-truth table prints [INFO] lines that say what a target can reach:

* the *inpainting headroom* (``..._mask_psnr_holes_oracle``): the delete-only renders with their hole
  pixels replaced by the truth: the most any filling of the holes can reach while the background other
  views saw stays as fitted;
* the *re-fit's ceiling* (``..._mask_psnr_truth_fill``, with ``--methods ...,truth-fill`` only): ours
  with the truth in every hole pixel of the refine stage's images, then re-fitted and scored as the
  methods are: what a perfect inpainting of the holes gives after the re-fit (the headroom above is
  before it), against the best baseline;
* every method scored on the two parts of the mask as ours splits it, its holes and the rest
  (``psnr_unseen`` / ``psnr_seen``, pooled);
* the *blurred-truth bound* (``..._mask_psnr_holes_blurred_truth``): ours' final renders with their
  hole pixels replaced by the truth blurred by sigma 1 / 2 / 3 / 5 px, and the blur at which ours would
  beat each baseline by the target's 1 dB. Those pixels are the ones no view saw: no method knows them,
  and a sharp plausible guess of them scores below a blurred truth;
* the *plane fill* (``..._plane_fill_psnr``): where the inpaint stage filled one texture of the plane
  under the object, that texture's hole against the truth warped onto it, apart from the re-fit.

Metrics beside PSNR / SSIM (``mask``, ``bbox``, ``full``):

* ``cons`` (lower = more consistent): for up to 6 views with the largest masks, every ordered pair, the
  colours inside the mask of view i carried into view j through the remove stage's completed depth
  (:func:`~sgpor_pipeline.removal.multiview.warp_from_reference`) against view j's own, mean absolute
  difference; on the final renders and on the 2D fills before the re-fit (``cons2d``).
* ``detail`` (1 = as much as the truth): RPR's high-frequency energy (Sobel |Gx| + |Gy| on grey) over
  the mask pixels, relative to the truth's. PSNR prefers a smooth guess to a detailed one in the wrong
  place; this column shows how much detail a result keeps (it is not a quality score: noise raises it).
* ``feat`` (lower = closer): the evaluate stage's ``feat_mask``, DINOv2-like patch features' cosine
  distance to the truth over the mask (:func:`sgpor_pipeline.metrics.feature_distance`); it does not
  reward blur. Empty unless the ``dinov2`` extra and its model are installed. Not LPIPS (that needs
  backbone weights we cannot install).

Fit seeds (``--fit-seeds``): a fit's trajectory is chaotic (densification amplifies rounding), so one
fit's numbers move by tenths of a dB to a dB with ``fit.seed`` while the methods compared on it differ
by as little. With several seeds every method runs on every seed's fit (paired), a table per scene
lists mask PSNR by seed with the mean, spread and paired gain ``ours - method``, and the targets are
judged on the mean gain. The JSON keeps the first seed's keys and adds ``..._seeds`` / ``_seed_mean`` /
``_seed_std`` and ``<scene>_fit_seeds``. Each extra seed costs one fit and every variant again
(synthetic ~8, lund ~10 minutes on 2 cores).

Sizes (to fit ~60 min on a shared 2-core CPU): the synthetic scenes use the demo configuration; the
real scenes are downscaled at ingest (320 / 384 px) and fitted with ``fit.iterations=1500``.
``--quick`` = a smoke run: 12 synthetic views, fit 300 and finetune 100 iterations everywhere, lund
at 240 px, statue at 192 px, masks 1 and 2 only.

Out (``--out``, default a temporary folder): one run folder per scene, ``*_sheet.png`` contact sheets
(input | mask | delete-only | result | truth for the evaluated scenes), ``removal_speed_error.png``
(mask PSNR against seconds per method), ``removal_benchmark.json``.
With ``--json`` the last printed line is one JSON object (its keys: ``summarise`` in the code).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
import tempfile
import time
import warnings
from collections.abc import Sequence
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from sgpor_pipeline.presets import PRESETS, as_overrides

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DATA = ROOT.parent / "shared" / "data"
STAGES = ("ingest", "sfm", "fit", "masks", "remove", "inpaint", "refine", "finetune")
METRICS = ("psnr_mask", "psnr_bbox", "psnr_full", "ssim_mask", "ssim_bbox", "ssim_full", "feat_mask")

# name, overrides, JSON suffix
VARIANTS: list[tuple[str, list[str], str]] = [
    ("ours", [], ""),
    ("fsr-refit", ["remove.hole_mode=mask", "inpaint.backend=opencv", "inpaint.multiview=false",
                   "refine.max_rounds=0"], "_fsr_refit"),
    ("no-sbm", ["inpaint.backend=opencv"], "_no_sbm"),
    ("no-rpr", ["refine.max_rounds=0"], "_no_rpr"),
    # not a baseline of the target: RPR where it has work (SBM's fills have no low-detail block)
    ("no-sbm-no-rpr", ["inpaint.backend=opencv", "refine.max_rounds=0"], "_no_sbm_no_rpr"),
    # not a method: the re-fit's ceiling, ours with the truth in every hole pixel before the re-fit
    # (truth_fill_stages); run only when named in --methods
    ("truth-fill", [], "_truth_fill"),
]
OPT_IN = ("truth-fill",)  # variants that run only when --methods names them
BASELINES = ("delete-only", "fsr-refit", "no-sbm", "no-rpr")  # what ours must beat by TARGET_GAIN_DB
SUFFIX = {name: suf for name, _, suf in VARIANTS} | {"delete-only": "_delete_only"}
TARGET_GAIN_DB = 1.0
HELPS_DB = 0.1  # an ablation "helps" when removing it costs at least this much mask PSNR
TARGET_IOU = 0.85
TARGET_DEMO_SECONDS = 600.0
PSNR_CAP = 50.0  # dB: a perfect view in a mean over views (the headroom oracle)
LUND_SFM_SIZE = 0  # full 1024x768: at 640 px only 15 of the 29 photos register
# protocol (b), a box inserted into a real capture: scene -> (capture folder, SfM ingest size, removal size)
INSERTED: dict[str, tuple[str, int, int]] = {
    "lund": ("lund", LUND_SFM_SIZE, 320),
    "statue-box": ("statue", 0, 384),  # a second capture to check what was tuned on lund (the statue stays)
    # lund + box from ONE given mask (INSERTED_ONE_MASK): its SfM, inserted photos and fit are lund's
    "lund-1mask": ("lund", LUND_SFM_SIZE, 320),
    "statue-box-1mask": ("statue", 0, 384),
}
# the inserted scenes run from one given mask -> the scene whose folders (SfM, inserted photos) they share.
# The given mask is the view's where the object is largest without touching the frame (one_mask_view):
# where a user would paint it, large and whole.
INSERTED_ONE_MASK = {"lund-1mask": "lund", "statue-box-1mask": "statue-box"}
# protocol (a): scene -> SceneParams fields (the rest are the demo's)
SYNTHETIC_SCENES: dict[str, dict[str, Any]] = {
    "synthetic": {},  # the demo: a sphere on the rug; about 3 % of its mask pixels no other view sees
    "synthetic-box": {"object_kind": "box"},  # a box on the rug: about 29 % no other view sees
    # the same box darkening the floor in the photos (not in the truth): its ambient occlusion, and
    # that plus its key-light shadow; what ``remove.under_object`` is for
    "synthetic-box-contact": {"object_kind": "box", "object_shadow": "contact"},
    "synthetic-box-cast": {"object_kind": "box", "object_shadow": "cast"},
    # a box on four short feet (the rest of the scene as synthetic-box): the photos see the floor under
    # it through the gap, in its shadow (occlusion and key light), and the truth does not: a real
    # footprint, as under mip360 kitchen's bulldozer
    "synthetic-raised-cast": {"object_kind": "raised_box", "object_shadow": "cast"},
    # the same box on feet without its shadows: thin holes under it on the floor, nothing to lift
    "synthetic-raised": {"object_kind": "raised_box"},
    # the demo's sphere whose photos (not the truth) carry its shadows: its hull reaches the floor in
    # about half of its silhouette (a box's in all of it)
    "synthetic-cast": {"object_shadow": "cast"},
    # synthetic-box from ONE given mask (ONE_MASK): the object fitted, selected from that mask, its
    # masks propagated to the other views (protocol (c) with ground truth, all round a compact object)
    "synthetic-box-1mask": {"object_kind": "box"},
    # synthetic-raised-cast from ONE given mask: the fit models the box and the shadowed floor seen
    # under it; what is left of them after the selection is what the plane texture must cover
    "synthetic-raised-cast-1mask": {"object_kind": "raised_box", "object_shadow": "cast"},
    # synthetic-box with the rug moved so that its edge, or its corner, runs under the box: a straight
    # border through what the box hides (as the mats on mip360 kitchen's table); inpaint.plane_structure
    "synthetic-box-edge": {"object_kind": "box", "rug_place": "edge"},
    "synthetic-box-corner": {"object_kind": "box", "rug_place": "corner"},
    # ... and a round rug's curved border under it (no straight structure to continue)
    "synthetic-box-round": {"object_kind": "box", "rug_place": "edge", "rug_shape": "ellipse"},
    # synthetic-box on a rug with a regular pattern: a grid of coins, a wall of bricks (tiles, parquet,
    # a patterned rug); inpaint.plane_lattice
    "synthetic-box-coins": {"object_kind": "box", "rug_texture": "coins"},
    "synthetic-box-brick": {"object_kind": "box", "rug_texture": "brick"},
    # the demo from its photos, as a user runs it: SfM estimates the cameras (FROM_PHOTOS)
    "synthetic-photos": {},
    # a phone-video capture: a forward-facing walk of 120 frames as an MP4, 24 sharp frames taken by
    # `sgpor-pipeline frames`, SfM, the object from ONE given mask (VIDEO)
    "synthetic-video": {"rig": "forward", "n_views": 120},
}
# scenes given as a video (sgpor_pipeline.frames): how many photos `frames` takes from it
VIDEO = {"synthetic-video": 24}
# scenes run without their cameras: SfM on the photos. SIMPLE_PINHOLE (the photos have no distortion)
# keeps the views at the photos' pixels, where every hole and headroom figure reads the truth.
FROM_PHOTOS = {"synthetic-photos": ["sfm.camera_model=SIMPLE_PINHOLE"],
               "synthetic-video": ["sfm.camera_model=SIMPLE_PINHOLE"]}
# a run from one given mask: the fit models the object, the masks stage propagates it, and it is scored
# over the true masks (evaluate.score_masks=input: a propagated mask that missed part of the object must
# not leave that part out of the score); its propagated masks' IoU against the truth is reported beside
# the removal. Which mask: the first view's (ONE_MASK) or one_mask_view's (INSERTED_ONE_MASK).
ONE_MASK_RUN = ["fit.object_masks=fit", "evaluate.score_masks=input"]
ONE_MASK = {scene: [*ONE_MASK_RUN, "masks.max_given=1"]
            for scene in ("synthetic-box-1mask", "synthetic-raised-cast-1mask", "synthetic-video")}
GT_SCENES = (*SYNTHETIC_SCENES, *INSERTED)
PREFIX = {"synthetic": "synthetic", "synthetic-box": "synthetic_box", "synthetic-box-contact": "synthetic_box_contact",
          "synthetic-box-cast": "synthetic_box_cast", "synthetic-raised-cast": "synthetic_raised_cast",
          "synthetic-raised": "synthetic_raised",
          "synthetic-box-1mask": "synthetic_box_1mask", "synthetic-cast": "synthetic_cast",
          "synthetic-raised-cast-1mask": "synthetic_raised_cast_1mask",
          "synthetic-box-edge": "synthetic_box_edge", "synthetic-box-corner": "synthetic_box_corner",
          "synthetic-box-round": "synthetic_box_round",
          "synthetic-box-coins": "synthetic_box_coins", "synthetic-box-brick": "synthetic_box_brick",
          "synthetic-photos": "synthetic_photos", "synthetic-video": "synthetic_video",
          "lund": "lund_inserted", "lund-1mask": "lund_inserted_1mask",
          "statue-box": "statue_inserted", "statue-box-1mask": "statue_inserted_1mask"}
NOVEL_EVERY = 4  # --novel: every 4th view (from the third, in name order) is a held-out test view
NOVEL_METRICS = ("psnr_mask", "psnr_bbox", "ssim_mask", "feat_mask")

log = logging.getLogger("sgpor_pipeline.bench.removal")


# --------------------------------------------------------------------------------------------------
# helpers


def _img_u8(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img)
    if img.dtype != np.uint8:
        img = np.clip(np.round(np.asarray(img, np.float32) * 255), 0, 255).astype(np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    return img


def mask_overlay(image: np.ndarray, mask: np.ndarray, colour=(255, 40, 40)) -> np.ndarray:
    import cv2

    out = _img_u8(image).astype(np.float32)
    m = np.asarray(mask, bool)
    out[m] = 0.5 * out[m] + 0.5 * np.array(colour, np.float32)
    edge = cv2.morphologyEx(m.astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
    out[edge] = colour
    return out.astype(np.uint8)


def contact_sheet(rows: list[list[np.ndarray]], labels: list[str], path: Path, height: int = 160) -> None:
    """rows of equally many images (any sizes) -> one PNG, columns labelled."""
    import cv2

    if not rows:
        return
    lines = []
    for row in rows:
        cells = []
        for img in row:
            img = _img_u8(img)
            h, w = img.shape[:2]
            cells.append(cv2.resize(img, (max(1, round(w * height / h)), height), interpolation=cv2.INTER_AREA))
        lines.append(np.concatenate([np.pad(c, ((2, 2), (2, 2), (0, 0)), constant_values=255) for c in cells], 1))
    width = max(line.shape[1] for line in lines)
    lines = [np.pad(line, ((0, 0), (0, width - line.shape[1]), (0, 0)), constant_values=255) for line in lines]
    cell_w = lines[0].shape[1] // max(1, len(rows[0]))
    head = np.full((22, width, 3), 255, np.uint8)
    for i, label in enumerate(labels):
        cv2.putText(head, label, (i * cell_w + 4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    sheet = np.concatenate([head] + lines, 0)
    cv2.imwrite(str(path), sheet[..., ::-1])


def consistency(images: dict[str, np.ndarray], remove_dir: Path, max_views: int = 6) -> float:
    """Mean absolute colour difference of the object-mask pixels carried between views (see the doc)."""
    from sgpor_pipeline.imageio import read_mask
    from sgpor_pipeline.removal.multiview import warp_from_reference
    from sgpor_pipeline.scene import load_cameras

    cams = {c.image: c for c in load_cameras(remove_dir / "cameras.json") if c.image is not None}
    names = [n for n in images if n in cams and (remove_dir / "depth" / f"{n}.npy").is_file()]
    masks = {n: read_mask(remove_dir / "masks" / f"{n}.png") for n in names}
    names = sorted((n for n in names if masks[n].sum() > 50), key=lambda n: -int(masks[n].sum()))[:max_views]
    depth = {n: np.load(remove_dir / "depth" / f"{n}.npy") for n in names}
    errs = []
    for a in names:
        for b in names:
            if a == b:
                continue
            cols, got = warp_from_reference(images[a], cams[a], depth[a], masks[a], cams[b], depth[b], masks[b],
                                            "backward", 0.01)
            if got.sum() > 20:
                errs.append(float(np.abs(cols[got] - images[b][got]).mean()))
    return float(np.mean(errs)) if errs else float("nan")


def split_psnr(images: dict[str, np.ndarray], remove_dir: Path, truth_dir: Path) -> dict[str, float]:
    """Pooled PSNR (one MSE over all views) against the ground truth on the two parts of the object
    mask as ``remove_dir``'s remove stage splits it: ``psnr_unseen`` over its holes (the part no view
    saw: where inpainting matters; the whole hole where a view has no mask file), ``psnr_seen`` over the
    rest of the mask (background other views saw, kept as fitted by ours; fsr-refit repaints it). One
    pass: each view's hole, mask and truth are read once."""
    from sgpor_pipeline.imageio import read_image, read_mask

    se = {"psnr_unseen": 0.0, "psnr_seen": 0.0}
    n = {"psnr_unseen": 0, "psnr_seen": 0}
    for name, img in images.items():
        truth_path = truth_dir / f"{name}.png"
        if not truth_path.is_file():
            continue
        hole = read_mask(remove_dir / "holes" / f"{name}.png")
        mask_path = remove_dir / "masks" / f"{name}.png"
        parts = {"psnr_unseen": hole}
        if mask_path.is_file():  # (not the hole's rim outside the mask)
            mask = read_mask(mask_path)
            parts = {"psnr_unseen": hole & mask, "psnr_seen": mask & ~hole}
        if not any(part.any() for part in parts.values()):
            continue
        err = ((img - read_image(truth_path)) ** 2).mean(axis=-1)
        for key, part in parts.items():
            se[key] += float(err[part].sum())
            n[key] += int(part.sum())
    return {key: float(10 * np.log10(1.0 / max(se[key] / n[key], 1e-12))) if n[key] else float("nan") for key in se}


def hole_psnr(images: dict[str, np.ndarray], remove_dir: Path, truth_dir: Path) -> float:
    """PSNR over the remove stage's hole pixels, pooled over all views (:func:`split_psnr`)."""
    return split_psnr(images, remove_dir, truth_dir)["psnr_unseen"]


def detail_ratio(images: dict[str, np.ndarray], masks_dir: Path, truth_dir: Path) -> float:
    """High-frequency energy (RPR's Sobel |Gx| + |Gy|) over every view's object-mask pixels, relative to
    the truth's: 1 = as detailed as the truth, below 1 = smoother (see the module doc)."""
    from sgpor_pipeline.imageio import read_image, read_mask
    from sgpor_pipeline.removal.rpr import hf_energy

    ours, truth_sum = 0.0, 0.0
    for name, img in images.items():
        mask = read_mask(masks_dir / f"{name}.png")
        truth = truth_dir / f"{name}.png"
        if not mask.any() or not truth.is_file():
            continue
        ours += float(hf_energy(img)[mask].sum())
        truth_sum += float(hf_energy(read_image(truth))[mask].sum())
    return ours / truth_sum if truth_sum > 0 else float("nan")


def truth_in_holes_psnr(images: dict[str, np.ndarray], remove_dir: Path, masks_dir: Path, truth_dir: Path,
                        sigmas: Sequence[float] = (0.0,)) -> dict[str, float]:
    """Mask PSNR (evaluate's definition: mean over views) of ``images`` with their HOLE pixels replaced by
    the truth blurred by a Gaussian of each sigma (px; 0 = the truth itself), keyed by ``f"{sigma:g}"``.
    A view whose whole mask is a hole and gets the exact truth (``remove.thin_mask_rim``) is perfect:
    its PSNR counts as ``PSNR_CAP`` dB (8-bit images that agree to the last bit), not inf."""
    import cv2

    from sgpor_pipeline.imageio import read_image, read_mask
    from sgpor_pipeline.metrics import psnr

    values: dict[str, list[float]] = {f"{s:g}": [] for s in sigmas}
    for name, img in images.items():
        truth_path = truth_dir / f"{name}.png"
        mask = read_mask(masks_dir / f"{name}.png")
        if not truth_path.is_file() or not mask.any():
            continue
        truth = read_image(truth_path)
        hole = read_mask(remove_dir / "holes" / f"{name}.png")[..., None]
        for s in sigmas:
            fill = cv2.GaussianBlur(truth, (0, 0), s) if s > 0 else truth
            values[f"{s:g}"].append(min(PSNR_CAP, psnr(np.where(hole, fill, img), truth, mask)))
    return {k: float(np.mean(v)) if v else float("nan") for k, v in values.items()}


def oracle_holes_psnr(deleted: dict[str, np.ndarray], remove_dir: Path, masks_dir: Path, truth_dir: Path) -> float:
    """The inpainting headroom: the delete-only renders with the exact truth in their holes. The most
    any inpainting of the holes can reach while the background seen by other views stays as fitted
    (before a re-fit); its distance to delete-only is the headroom of the inpainting methods."""
    return truth_in_holes_psnr(deleted, remove_dir, masks_dir, truth_dir)["0"]


BLUR_SIGMAS = (1.0, 2.0, 3.0, 5.0)  # px: the blurred-truth fills of ours' holes (blurred_truth_holes_psnr)


def blurred_truth_holes_psnr(final: dict[str, np.ndarray], remove_dir: Path, masks_dir: Path, truth_dir: Path,
                             sigmas: Sequence[float] = BLUR_SIGMAS) -> dict[str, float]:
    """Mask PSNR of ours' final renders with their HOLE pixels replaced by the truth blurred by each
    sigma (px): how close to the truth a fill of the holes must be for ours to reach a given mask PSNR,
    the re-fit's effect on the rest of the mask kept. The methods differ from ours mainly in the holes,
    so this says what a target over them asks of any inpainting: no method can know the pixels no view
    saw, and a sharp guess of them scores below a blurred truth."""
    return truth_in_holes_psnr(final, remove_dir, masks_dir, truth_dir, sigmas)


def plane_fill_psnr(inpaint_dir: Path, remove_dir: Path, truth_dir: Path) -> float | None:
    """PSNR of the plane texture's filled hole (``inpaint/plane``, built where the holes' thick parts lie on
    one plane) against the object-free truth rectified the same way: each view's truth image warped onto
    the texture (the view's completed depth snapped to the plane where within 10 %, as the views take the
    texture), the per-texel median. It scores that one fill, which decides the views' holes on a table or
    floor, apart from the re-fit. None without a texture, or where the truth covers under half its hole."""
    import cv2

    from sgpor_pipeline.imageio import read_image, read_mask
    from sgpor_pipeline.removal.multiview import load_remove_folder, warp_from_reference
    from sgpor_pipeline.removal.plane import PlaneParams, snapped_depth
    from sgpor_pipeline.scene import Camera
    from sgpor_pipeline.stages.evaluate import find_truth

    folder = inpaint_dir / "plane"
    if not (folder / "hole.png").is_file():
        return None
    info = json.loads((folder / "plane.json").read_text())
    hole = read_mask(folder / "hole.png")
    if not info.get("built") or not hole.any():
        return None
    vcam = Camera.from_dict(info["camera"])
    vdepth = np.full(hole.shape, info["height_above_plane"], np.float32)
    normal = np.asarray(info["normal"], np.float64)
    snap = PlaneParams.rim_band  # (as the inpaint stage snaps the views' hole depths onto the plane)
    samples = []
    for v in load_remove_folder(remove_dir).views:
        truth = find_truth(truth_dir, v.name)
        if v.camera is None or v.depth_path is None or truth is None:
            continue
        img = read_image(truth)
        if img.shape[:2] != (v.camera.height, v.camera.width):
            img = cv2.resize(img, (v.camera.width, v.camera.height), interpolation=cv2.INTER_AREA)
        depth = v.depth()
        depth = snapped_depth(vcam, vdepth, normal, v.camera, depth, np.ones(depth.shape, bool), snap)
        col, got = warp_from_reference(img, v.camera, depth, np.ones(depth.shape, bool), vcam, vdepth, hole)
        samples.append(np.where(got[hole][:, None], col[hole], np.nan))
    if not samples:
        return None
    with warnings.catch_warnings():  # (texels no view's truth reaches: all NaN)
        warnings.simplefilter("ignore", RuntimeWarning)
        truth_tex = np.nanmedian(np.stack(samples), axis=0)
    ok = np.isfinite(truth_tex).all(axis=1)
    if ok.sum() < 0.5 * len(ok):
        return None
    filled = read_image(folder / "filled.png")[hole][ok]
    return float(10 * np.log10(1.0 / max(float(((filled - truth_tex[ok]) ** 2).mean()), 1e-12)))


def read_folder(folder: Path, names: list[str]) -> dict[str, np.ndarray]:
    from sgpor_pipeline.imageio import read_image

    return {n: read_image(folder / f"{n}.png") for n in names if (folder / f"{n}.png").is_file()}


# --------------------------------------------------------------------------------------------------
# one scene with ground truth: every variant in the same run folder


def selected_variants(methods: Sequence[str] | None) -> list[tuple[str, list[str], str]]:
    """VARIANTS restricted to ``methods`` (None: all but OPT_IN); ours always runs, first (the others are scored on
    its split of the mask, and delete-only comes from its run)."""
    if methods is None:
        return [v for v in VARIANTS if v[0] not in OPT_IN]
    unknown = set(methods) - {name for name, _, _ in VARIANTS} - {"delete-only"}
    if unknown:
        raise ValueError(f"unknown method(s) {', '.join(sorted(unknown))}; known: "
                         + ", ".join(name for name, _, _ in VARIANTS))
    return [v for v in VARIANTS if v[0] == "ours" or v[0] in methods]


def truth_fill_stages() -> dict[str, type]:
    """The pipeline's stages with a refine stage whose images get the truth (the run's
    ``groundtruth`` folder) in every hole pixel after it ran: the ``truth-fill`` method, the most the
    re-fit can make of a perfect inpainting of the holes, at their completed depth (its own cache keys:
    the stage's VERSION + 1000)."""
    from sgpor_pipeline.dag import discover_stages
    from sgpor_pipeline.imageio import read_mask, read_rgb8, write_png
    from sgpor_pipeline.stages.evaluate import find_truth

    stages = discover_stages()
    refine = stages["refine"]

    class TruthFillRefine(refine):  # type: ignore[misc, valid-type]
        VERSION = refine.VERSION + 1000

        def run(self, ctx: Any) -> None:
            super().run(ctx)
            truth_dir = Path(ctx.run_inputs.extra["groundtruth"])
            holes = Path(ctx.inputs["remove"]) / "holes"
            for path in sorted((ctx.out_dir / "images").glob("*.png")):
                truth = find_truth(truth_dir, path.stem)
                if truth is None:
                    continue
                img, want = read_rgb8(path), read_rgb8(truth)
                if want.shape != img.shape:
                    raise RuntimeError(f"{truth}: {want.shape} against the run's {img.shape}")
                hole = read_mask(holes / path.name)[..., None]
                path.unlink()  # (a fresh file: never written through a link into another entry)
                write_png(path, np.where(hole, want, img))

    return {**stages, "refine": TruthFillRefine}


def variant_stages(name: str) -> dict[str, type] | None:
    """The stages a variant runs with (None: the pipeline's own)."""
    return truth_fill_stages() if name == "truth-fill" else None


def run_variants(scene: str, run_out: Path, inputs: Any, base: list[str], out: Path,
                 sheet_name: str | None = None, methods: Sequence[str] | None = None) -> dict[str, Any]:
    from sgpor_pipeline.imageio import read_image, read_mask
    from sgpor_pipeline.runner import run_pipeline
    from sgpor_pipeline.stages.evaluate import find_truth

    rows: list[dict[str, Any]] = []
    truth_dir = Path(inputs.extra["groundtruth"])
    t_scene = time.perf_counter()
    ours_paths: dict[str, Path] = {}
    for name, overrides, _ in selected_variants(methods):
        t0 = time.perf_counter()
        log.warning(f"[{scene}] variant {name}: {' '.join(overrides) or '(defaults)'}")
        res = run_pipeline(run_out, inputs, overrides=base + overrides, until="evaluate",
                           stages=variant_stages(name))
        wall = time.perf_counter() - t0
        ev = json.loads((res.path("evaluate") / "metrics.json").read_text())
        remove_dir = res.path("remove")
        names = sorted(ev["per_view"])
        final = read_folder(res.path("finetune") / "renders", names)
        inpainted = read_folder(res.path("refine") / "images", names)
        # every method on the same pixels: ours' holes and the rest of the mask ("ours" runs first)
        ours_remove = ours_paths.get("remove", remove_dir)
        split = split_psnr(final, ours_remove, truth_dir)
        own_holes = split["psnr_unseen"] if remove_dir == ours_remove else hole_psnr(final, remove_dir, truth_dir)
        row = {"method": name, "overrides": overrides, **{k: ev["means"]["final"].get(k, math.nan) for k in METRICS},
               "psnr_hole": own_holes, **split,
               "detail": detail_ratio(final, res.path("masks") / "masks", truth_dir),
               "plane_fill_psnr": plane_fill_psnr(res.path("inpaint"), remove_dir, truth_dir),
               "seconds": ev["seconds"], "total_seconds": ev["total_seconds"], "wall_seconds": wall,
               "ran": res.ran, "views": ev["views"],
               "cons": consistency(final, remove_dir), "cons2d": consistency(inpainted, remove_dir),
               "inpainted_2d": {k: ev["means"]["inpainted_2d"].get(k, math.nan) for k in METRICS}}
        rows.append(row)
        if name == "ours":
            ours_paths = {s: res.path(s) for s in ("sfm", "masks", "remove", "refine", "finetune")}
            deleted = read_folder(remove_dir / "renders", names)
            secs = {s: v for s, v in ev["seconds"].items() if s in STAGES[:5]}
            split = split_psnr(deleted, remove_dir, truth_dir)
            rows.append({"method": "delete-only", "overrides": [],
                         **{k: ev["means"]["delete_only"].get(k, math.nan) for k in METRICS},
                         "psnr_hole": split["psnr_unseen"], **split,
                         "detail": detail_ratio(deleted, res.path("masks") / "masks", truth_dir),
                         "seconds": secs, "total_seconds": sum(secs.values()), "wall_seconds": None, "ran": [],
                         "views": ev["views"], "cons": consistency(deleted, remove_dir), "cons2d": None})
            oracle = oracle_holes_psnr(deleted, remove_dir, ours_paths["masks"] / "masks", truth_dir)
            blurred = blurred_truth_holes_psnr(final, remove_dir, ours_paths["masks"] / "masks", truth_dir)
        log.warning(f"[{scene}] {name}: PSNR mask {row['psnr_mask']:.2f} (wall {wall:.0f} s, ran {res.ran})")
    # before / after pictures of the default method
    rm = json.loads((ours_paths["remove"] / "remove.json").read_text())
    hole_info = {"hole_fraction_of_mask": rm.get("hole_fraction_of_mask"),
                 "hole_pixels": rm.get("hole_pixels", 0) - rm.get("rim_pixels", 0),  # (inside the masks)
                 "mask_pixels": rm.get("mask_pixels")}
    names = sorted(json.loads((ours_paths["remove"] / "remove.json").read_text())["views"].items(),
                   key=lambda kv: -kv[1]["mask_pixels"])
    pick = [n for n, _ in names[:4]]
    sheet = []
    for n in pick:
        img = read_image(ours_paths["sfm"] / "images" / f"{n}.png")
        mask = read_mask(ours_paths["masks"] / "masks" / f"{n}.png")
        truth = find_truth(truth_dir, n)
        sheet.append([img, mask_overlay(img, mask), read_image(ours_paths["remove"] / "renders" / f"{n}.png"),
                      read_image(ours_paths["refine"] / "images" / f"{n}.png"),
                      read_image(ours_paths["finetune"] / "renders" / f"{n}.png"),
                      read_image(truth) if truth is not None else np.zeros_like(img)])
    sheet_path = out / (sheet_name or f"{scene}_sheet.png")
    contact_sheet(sheet, ["input", "mask", "delete-only", "inpainted 2D", "ours (final)", "truth"], sheet_path)
    refined = json.loads((ours_paths["refine"] / "refined.json").read_text()).get("refined_blocks")
    return {"scene": scene, "rows": rows, "wall_seconds": time.perf_counter() - t_scene, "sheet": str(sheet_path),
            "masks_dir": str(ours_paths["masks"]),
            "mask_psnr_holes_oracle": oracle, "mask_psnr_holes_blurred_truth": blurred, "refined_blocks": refined,
            **hole_info}


# --------------------------------------------------------------------------------------------------
# protocols


def protocol_synthetic(out: Path, quick: bool, extra: Sequence[str] = (), novel: bool = False,
                       tag: str = "", methods: Sequence[str] | None = None, scene: str = "synthetic") -> dict[str, Any]:
    from sgpor_pipeline.dag import RunInputs
    from sgpor_pipeline.demo import ensure_demo_scene
    from sgpor_pipeline.synthetic import SceneParams

    params = SceneParams(**{**SYNTHETIC_SCENES[scene], **({"n_views": 3 * VIDEO.get(scene, 4)} if quick else {})})
    scene_dir = ensure_demo_scene(out / scene / "scene", params)
    if scene in VIDEO:
        scene_dir = video_capture(scene_dir, out / scene / "video", VIDEO[scene] // (2 if quick else 1))
    inputs = RunInputs(images=scene_dir / "images", masks=scene_dir / "masks",
                       cameras=None if scene in FROM_PHOTOS else scene_dir / "cameras.json",
                       extra={"groundtruth": scene_dir / "groundtruth"})
    base = ((["fit.iterations=300", "finetune.iterations=100"] if quick else []) + ONE_MASK.get(scene, [])
            + FROM_PHOTOS.get(scene, []) + list(extra))
    r = run_variants(scene, out / scene / "run", inputs, base, out, f"{scene}{tag}_sheet.png", methods)
    if scene in ONE_MASK:
        r.update(propagation_iou(Path(r["masks_dir"]), scene_dir / "masks"))
    if scene == "synthetic":  # the demo's configuration: its time is the demo target's
        ours = next(x for x in r["rows"] if x["method"] == "ours")
        r["demo_seconds"] = float(sum(ours["seconds"].get(s, 0.0) for s in STAGES))
    r["note"] = f"{params.n_views} views {params.width}x{params.height}, {params.object_kind} object, demo " \
                "configuration" + (" (quick: fit 300 / finetune 100 iterations)" if quick else "")
    if novel and scene in FROM_PHOTOS:
        log.warning(f"[{scene}] no novel-view protocol: it gives the held-out views as known cameras")
    elif novel:
        r["novel"] = run_novel(scene, scene_dir, out / scene / "novel_run", base, out, methods)
    return r


def video_capture(scene_dir: Path, folder: Path, count: int) -> Path:
    """The generated views in name order as an MP4 (10 fps, OpenCV's MPEG-4 codec: lossy, as a phone's
    video), and ``count`` photos taken from it by :func:`sgpor_pipeline.frames.extract_frames`, with the
    true masks and object-free views of the frames they are: a folder laid out as the scene's."""
    import shutil

    import cv2

    from sgpor_pipeline.frames import FrameParams, extract_frames

    views = sorted((scene_dir / "images").glob("*.png"))
    if (folder / "done.json").is_file() and json.loads((folder / "done.json").read_text()) == [v.name for v in views]:
        return folder
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    first = cv2.imread(str(views[0]))
    writer = cv2.VideoWriter(str(folder / "walk.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 10.0,
                             (first.shape[1], first.shape[0]))
    for v in views:
        writer.write(cv2.imread(str(v)))
    writer.release()
    photos = extract_frames(folder / "walk.mp4", folder / "images", FrameParams(count=count, format="png"))
    for sub in ("masks", "groundtruth"):
        (folder / sub).mkdir()
        for p in photos:
            shutil.copy2(scene_dir / sub / views[int(p.stem.split("_")[1])].name, folder / sub / f"{p.stem}.png")
    (folder / "done.json").write_text(json.dumps([v.name for v in views]))
    return folder


def place_object(sfm_dir: Path, cams: list) -> tuple[np.ndarray, float]:
    """A point in view of as many cameras as possible, hovering in front of the scene.

    Among the SfM points, the one that projects into the central 60 % of the most images (ties: the
    one nearest the median of the tied points) is moved 15 % of the way towards the mean centre of
    those cameras (so the real surface is behind it and nothing can occlude it); the object's size is
    0.12 x the median distance of those cameras to it."""
    pts = np.load(sfm_dir / "points.npz")["xyz"]
    if len(pts) > 5000:
        pts = pts[np.random.default_rng(0).choice(len(pts), 5000, replace=False)]
    seen = np.zeros((len(cams), len(pts)), bool)
    for i, c in enumerate(cams):
        uv, z = c.project(pts)
        seen[i] = ((z > 0) & (np.abs(uv[:, 0] / c.width - 0.5) < 0.3) & (np.abs(uv[:, 1] / c.height - 0.5) < 0.3))
    count = seen.sum(0)
    best = np.flatnonzero(count == count.max())
    med = np.median(pts[best], axis=0)
    p = pts[best[np.argmin(np.linalg.norm(pts[best] - med, axis=1))]]
    viewers = np.flatnonzero(seen[:, best[np.argmin(np.linalg.norm(pts[best] - med, axis=1))]])
    centres = np.array([cams[i].center for i in viewers])
    pos = p + 0.15 * (centres.mean(0) - p)
    size = 0.12 * float(np.median(np.linalg.norm(centres - pos, axis=1)))
    return pos, size


def one_mask_view(masks_dir: Path) -> str:
    """The view whose mask is largest without touching the image's border (the largest, if all do)."""
    from sgpor_pipeline.imageio import read_mask

    best, key = "", (False, -1)
    for f in sorted(masks_dir.glob("*.png")):
        m = read_mask(f)
        whole = not (m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any())
        if (whole, int(m.sum())) > key:
            best, key = f.stem, (whole, int(m.sum()))
    return best


def protocol_inserted(data: Path, scene: str, out: Path, quick: bool, extra: Sequence[str] = (),
                      novel: bool = False, tag: str = "", methods: Sequence[str] | None = None) -> dict[str, Any]:
    """Protocol (b) on the capture ``INSERTED[scene]``: our SfM on the untouched photos, a box inserted
    with those cameras, the removal run on the photos with the box, the untouched photos as truth."""
    import cv2

    from sgpor_pipeline.dag import RunInputs
    from sgpor_pipeline.imageio import read_rgb8
    from sgpor_pipeline.runner import run_pipeline
    from sgpor_pipeline.scene import Camera, load_cameras, save_cameras
    from sgpor_pipeline.synthetic import insert_object

    capture, sfm_size, full_size = INSERTED[scene]
    root = out / INSERTED_ONE_MASK.get(scene, scene)  # (the SfM run and the inserted photos)
    folder = data / capture / "images"
    if not folder.is_dir():
        return {"scene": scene, "skipped": f"{folder} not found"}
    size = 240 if quick else full_size
    t0 = time.perf_counter()
    # SIFT needs more pixels than the removal: SfM at full size, then the undistorted photos and their
    # cameras are scaled down to ``size`` for the removal run.
    base_sfm = run_pipeline(root / "sfm_run", RunInputs(images=folder),
                            overrides=[f"ingest.max_size={sfm_size}"], until="sfm")
    sfm_dir = base_sfm.path("sfm")
    cams = [c for c in load_cameras(sfm_dir / "cameras.json") if c.image is not None]
    n_images = len([p for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png")])
    sfm_seconds = time.perf_counter() - t0
    if len(cams) < 3:
        return {"scene": scene, "skipped": f"our SfM registered only {len(cams)} of {n_images} photos"}
    scene_dir = root / "inserted"
    stamp = scene_dir / "stamp.json"
    want = json.dumps({"sfm": base_sfm.outcomes["sfm"].key, "seed": 0, "size": size, "version": 3})
    if not (stamp.is_file() and stamp.read_text() == want):
        small, photos = [], []
        for c in cams:
            photo = read_rgb8(sfm_dir / "images" / f"{c.image}.png")
            s = size / max(c.width, c.height)
            w, h = max(1, round(c.width * s)), max(1, round(c.height * s))
            K = np.diag([w / c.width, h / c.height, 1.0]) @ c.K
            small.append(Camera(c.image, w, h, K, c.cam_from_world, image=c.image))
            photos.append(cv2.resize(photo, (w, h), interpolation=cv2.INTER_AREA))
        pos, obj_size = place_object(sfm_dir, small)
        with_obj, masks = insert_object(photos, small, seed=0, position=pos, size=obj_size, kind="box")
        for sub in ("images", "masks", "groundtruth"):
            (scene_dir / sub).mkdir(parents=True, exist_ok=True)
        for c, photo, img, m in zip(small, photos, with_obj, masks):
            cv2.imwrite(str(scene_dir / "images" / f"{c.image}.png"), img[..., ::-1])
            cv2.imwrite(str(scene_dir / "groundtruth" / f"{c.image}.png"), photo[..., ::-1])
            cv2.imwrite(str(scene_dir / "masks" / f"{c.image}.png"), m.astype(np.uint8) * 255)
        save_cameras(scene_dir / "cameras.json", small)
        (scene_dir / "object.json").write_text(json.dumps({"position": pos.tolist(), "size": obj_size,
                                                           "coverage": [float(m.mean()) for m in masks],
                                                           "size_px": [small[0].width, small[0].height]}))
        stamp.write_text(want)
    coverage = json.loads((scene_dir / "object.json").read_text())["coverage"]
    inputs = RunInputs(images=scene_dir / "images", masks=scene_dir / "masks", cameras=scene_dir / "cameras.json",
                       extra={"groundtruth": scene_dir / "groundtruth"})
    base = (["fit.iterations=300", "finetune.iterations=100"] if quick else ["fit.iterations=1500"]) + list(extra)
    given = one_mask_view(scene_dir / "masks") if scene in INSERTED_ONE_MASK else None
    if given is not None:
        base = [*ONE_MASK_RUN, f"masks.given_views={given}", *base]
    r = run_variants(scene, out / scene / "run", inputs, base, out, f"{scene}{tag}_sheet.png", methods)
    if given is not None:
        r.update(propagation_iou(Path(r["masks_dir"]), scene_dir / "masks"))
    r["wall_seconds"] += sfm_seconds
    wh = json.loads((scene_dir / "object.json").read_text())["size_px"]
    r["note"] = (f"{len(cams)}/{n_images} photos registered by our SfM at {cams[0].width}x{cams[0].height}, "
                 f"removal at {wh[0]}x{wh[1]}; "
                 f"object in {sum(c > 0 for c in coverage)} views, mean coverage {np.mean(coverage) * 100:.1f} %")
    r["registered"], r["images"] = len(cams), n_images
    if novel and scene in FROM_PHOTOS:
        log.warning(f"[{scene}] no novel-view protocol: it gives the held-out views as known cameras")
    elif novel:
        r["novel"] = run_novel(scene, scene_dir, out / scene / "novel_run", base, out, methods)
    return r


# --------------------------------------------------------------------------------------------------
# (d) novel views: held-out object-free test views (the SPIn-NeRF protocol)


def novel_split(names: Sequence[str], every: int = NOVEL_EVERY) -> tuple[list[str], list[str]]:
    """(training views, held-out test views): every ``every``-th name in sorted order, from the third
    (none for ``every`` <= 1)."""
    ordered = sorted(names)
    test = ordered[min(2, every - 1)::every] if every > 1 else []
    return [n for n in ordered if n not in test], test


def view_file(folder: Path, view: str) -> Path:
    """The view's file in ``folder`` (images, masks or groundtruth), whatever its image extension."""
    from sgpor_pipeline.stages.evaluate import find_truth

    path = find_truth(folder, view)
    if path is None:
        raise FileNotFoundError(f"{folder} has no file for view {view}")
    return path


def make_novel_scene(scene_dir: Path, out_dir: Path, every: int = NOVEL_EVERY) -> tuple[list[str], list[str]]:
    """Writes ``out_dir``: the ground-truth scene folder ``scene_dir`` without its held-out views' photos,
    masks and truth; their cameras stay in cameras.json as novel cameras named ``test_<view>`` (``image``
    None). Returns (training view names, held-out view names)."""
    import shutil
    from dataclasses import replace

    from sgpor_pipeline.scene import load_cameras, save_cameras

    cams = load_cameras(scene_dir / "cameras.json")
    by_image = {c.image: c for c in cams if c.image is not None}
    train, test = novel_split(list(by_image), every)
    stamp = json.dumps({"scene": [(p.name, p.stat().st_size, p.stat().st_mtime_ns)
                                  for p in sorted((scene_dir / "images").iterdir())], "test": test})
    if (out_dir / "stamp.json").is_file() and (out_dir / "stamp.json").read_text() == stamp:
        return train, test
    if out_dir.exists():
        shutil.rmtree(out_dir)
    for sub in ("images", "masks", "groundtruth"):
        (out_dir / sub).mkdir(parents=True)
        for n in train:
            src = view_file(scene_dir / sub, n)
            shutil.copyfile(src, out_dir / sub / src.name)
    novel = [replace(by_image[n], name=f"test_{n}", image=None) for n in test]
    save_cameras(out_dir / "cameras.json", [by_image[n] for n in train] + novel)
    (out_dir / "stamp.json").write_text(stamp)
    return train, test


def render_rgb(model: Any, cam: Any) -> np.ndarray:
    from sgpor_pipeline.gaussians.train import render_view

    return render_view(model, cam).clamp(0.0, 1.0).numpy()


def run_novel(scene: str, scene_dir: Path, run_out: Path, base: list[str], out: Path,
              methods: Sequence[str] | None = None) -> dict[str, Any]:
    """Protocol (d) on one ground-truth scene: every method trained without the held-out views, then
    rendered and scored at them (see the module doc)."""
    from sgpor_pipeline.dag import RunInputs
    from sgpor_pipeline.gaussians.ply import read_ply
    from sgpor_pipeline.imageio import read_image, read_mask
    from sgpor_pipeline.metrics import crop_features, feature_crop, mean_scores, score_image
    from sgpor_pipeline.removal.holes import subset
    from sgpor_pipeline.runner import run_pipeline
    from sgpor_pipeline.scene import load_cameras
    from sgpor_pipeline.stages.evaluate import EvaluateParams, load_features
    from sgpor_pipeline.stages.fit import run_cameras_file

    t_scene = time.perf_counter()
    novel_dir = out / scene / "novel_scene"
    train, test = make_novel_scene(scene_dir, novel_dir)
    # (the truth of every view: the truth-fill variant reads the training views' from it; it enters no
    # stage's key before evaluate, which the novel runs stop short of)
    inputs = RunInputs(images=novel_dir / "images", masks=novel_dir / "masks", cameras=novel_dir / "cameras.json",
                       extra={"groundtruth": scene_dir / "groundtruth"})
    features, why = load_features(EvaluateParams())
    truth = {n: read_image(view_file(scene_dir / "groundtruth", n)) for n in test}
    masks = {n: read_mask(view_file(scene_dir / "masks", n)) for n in test}
    test = [n for n in test if masks[n].any()]
    truth_feats = {n: None if features is None else crop_features(truth[n], masks[n], features) for n in test}

    def score(method: str, model: Any, cams: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
        renders, per_view = {}, []
        for n in test:
            cam = cams[f"test_{n}"]
            if (cam.height, cam.width) != masks[n].shape:
                raise RuntimeError(f"novel camera test_{n} is {cam.width}x{cam.height}, its truth "
                                   f"{masks[n].shape[1]}x{masks[n].shape[0]}")
            renders[n] = render_rgb(model, cam)
            per_view.append(score_image(renders[n], truth[n], masks[n], features, truth_feats[n]))
        means = mean_scores(per_view)
        return {"method": method, **{k: means.get(k, math.nan) for k in NOVEL_METRICS}, "renders": renders, **extra}

    rows: list[dict[str, Any]] = []
    for name, overrides, _ in selected_variants(methods):
        t0 = time.perf_counter()
        log.warning(f"[{scene} novel] variant {name}: {' '.join(overrides) or '(defaults)'}")
        res = run_pipeline(run_out, inputs, overrides=base + overrides, until="finetune",
                           stages=variant_stages(name))
        # (the run's cameras, as `render` uses them: with pose refinement they carry the corrections)
        cams = {c.name: c for c in load_cameras(run_cameras_file(res.path("fit"), res.path("sfm")))
                if c.image is None}
        missing = [n for n in test if f"test_{n}" not in cams]
        if missing:
            raise RuntimeError(f"the run dropped the novel cameras of {missing}")
        row = score(name, read_ply(res.path("finetune") / "gaussians.ply"), cams,
                    {"wall_seconds": time.perf_counter() - t0, "ran": res.ran})
        rows.append(row)
        log.warning(f"[{scene} novel] {name}: PSNR mask {row['psnr_mask']:.2f}")
        if name == "ours":
            removed = read_ply(res.path("remove") / "gaussians.ply")
            seeds = np.load(res.path("remove") / "seed_ids.npy")
            keep = np.ones(len(removed), bool)
            keep[seeds] = False
            rows.append(score("delete-only", subset(removed, keep), cams, {"wall_seconds": None, "ran": []}))
    by = {r["method"]: r for r in rows}
    pick = sorted(test, key=lambda n: -int(masks[n].sum()))[:4]
    shown = [m for m in ("delete-only", "fsr-refit", "ours") if m in by]
    sheet = []
    for n in pick:  # the view, then the methods and the truth around the mask (the feature distance's crop)
        y0, y1, x0, x1 = feature_crop(masks[n].shape, masks[n])
        sheet.append([mask_overlay(truth[n], masks[n])]
                     + [img[y0:y1, x0:x1] for img in [by[m]["renders"][n] for m in shown] + [truth[n]]])
    sheet_path = out / f"{scene}_novel_sheet.png"
    contact_sheet(sheet, ["held-out view, mask", *(m + (" (crop)" if i == 0 else "") for i, m in enumerate(shown)),
                          "truth"], sheet_path)
    for r in rows:
        r.pop("renders")
    return {"scene": scene, "rows": rows, "test_views": test, "train_views": len(train), "features": why,
            "sheet": str(sheet_path), "wall_seconds": time.perf_counter() - t_scene}


def format_novel_table(r: dict[str, Any]) -> str:
    head = f"{'method':<14} {'PSNR mask':>9} {'bbox':>6} {'SSIM mask':>9} {'feat':>6} {'wall s':>6}"
    lines = [f"## {r['scene']}, novel views (SPIn-NeRF protocol): {len(r['test_views'])} held-out views "
             f"({', '.join(r['test_views'])}), trained on {r['train_views']}", head, "-" * len(head)]
    for x in r["rows"]:
        lines.append(f"{x['method']:<14} {_f(x['psnr_mask'], '.2f'):>9} {_f(x['psnr_bbox'], '.2f'):>6} "
                     f"{_f(x['ssim_mask'], '.4f'):>9} {_f(x['feat_mask'], '.4f'):>6} "
                     f"{_f(x.get('wall_seconds'), '.0f'):>6}")
    return "\n".join(lines)


def propagation_iou(masks_dir: Path, truth_dir: Path) -> dict[str, Any]:
    """The masks stage's masks against the true ones on the views whose mask was not given: mean and
    min IoU, and the views given."""
    from sgpor_pipeline.imageio import read_mask

    info = json.loads((masks_dir / "masks.json").read_text())
    given = set(info.get("given", []))
    ious = [iou(read_mask(masks_dir / "masks" / f"{view}.png"), read_mask(truth_dir / f"{view}.png"))
            for view in sorted(info.get("views") or (f.stem for f in (masks_dir / "masks").glob("*.png")))
            if view not in given and (truth_dir / f"{view}.png").is_file()]
    return {"propagation_iou": float(np.mean(ious)) if ious else None,
            "propagation_iou_min": float(np.min(ious)) if ious else None, "given": sorted(given),
            "views_scored": len(ious), "views": len(info.get("views") or ())}


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def protocol_propagation(scene: str, folder: Path, out: Path, quick: bool,
                         overrides: Sequence[str] = ()) -> dict[str, Any]:
    from sgpor_pipeline.dag import RunInputs
    from sgpor_pipeline.imageio import read_image, read_mask
    from sgpor_pipeline.runner import run_pipeline

    if not (folder / "images").is_dir() or not (folder / "masks").is_dir():
        return {"scene": scene, "skipped": f"{folder}/images or masks not found"}
    t_scene = time.perf_counter()
    run_out = out / scene / "run"
    inputs = RunInputs(images=folder / "images", masks=folder / "masks")
    base = []
    if scene == "statue":
        base.append(f"ingest.max_size={192 if quick else 384}")
    base += ["fit.iterations=300", "finetune.iterations=100"] if quick else ["fit.iterations=1500"]
    # propagation from 1, 2, 4 of the dataset's masks: the fit must model the object, not leave every
    # given mask out (fit.object_masks=ignore / auto would, as all views have one)
    base.append("fit.object_masks=fit")
    base += list(overrides)
    counts = (1, 2) if quick else (1, 2, 4)
    result: dict[str, Any] = {"scene": scene, "iou": {}, "iou_min": {}, "given": {}, "seconds": {}}
    for n in counts:
        t0 = time.perf_counter()
        log.warning(f"[{scene}] mask propagation from {n} given mask(s)")
        res = run_pipeline(run_out, inputs, overrides=base + [f"masks.max_given={n}"], until="masks")
        prop = propagation_iou(res.path("masks"), res.path("sfm") / "masks")
        result["iou"][n] = prop["propagation_iou"] if prop["views_scored"] else float("nan")
        result["iou_min"][n] = prop["propagation_iou_min"] if prop["views_scored"] else float("nan")
        result["given"][n] = prop["given"]
        result["seconds"][n] = time.perf_counter() - t0
        result["registered"] = prop["views"]
        result["evaluated_views"] = prop["views_scored"]
        log.warning(f"[{scene}] IoU from {n} mask(s): {result['iou'][n]:.3f} over {prop['views_scored']} views")
    # the full removal from 2 given masks: consistency and pictures
    n = 2
    res = run_pipeline(run_out, inputs, overrides=base + [f"masks.max_given={n}"], until="finetune")
    info = json.loads((res.path("masks") / "masks.json").read_text())
    names = sorted(info["views"])
    final = read_folder(res.path("finetune") / "renders", names)
    result["cons"] = consistency(final, res.path("remove"))
    result["cons2d"] = consistency(read_folder(res.path("refine") / "images", names), res.path("remove"))
    result["stage_seconds"] = {s: float(json.loads((res.path(s) / "manifest.json").read_text())["seconds"])
                               for s in STAGES}
    not_given = [v for v in names if v not in set(info["given"])]
    pick = [not_given[i] for i in np.linspace(0, len(not_given) - 1, min(4, len(not_given))).round().astype(int)]
    sheet = []
    for v in pick:
        img = read_image(res.path("sfm") / "images" / f"{v}.png")
        sheet.append([img, mask_overlay(img, read_mask(res.path("masks") / "masks" / f"{v}.png")),
                      mask_overlay(img, read_mask(res.path("sfm") / "masks" / f"{v}.png"), (40, 200, 40)),
                      read_image(res.path("remove") / "renders" / f"{v}.png"), final[v]])
    sheet_path = out / f"{scene}_sheet.png"
    contact_sheet(sheet, ["input", "propagated (2 given)", "given mask (ref)", "delete-only", "result"], sheet_path)
    result["sheet"] = str(sheet_path)
    result["wall_seconds"] = time.perf_counter() - t_scene
    return result


# --------------------------------------------------------------------------------------------------
# tables and summary


def seed_runs(runs: list[tuple[int, dict[str, Any]]]) -> dict[str, Any]:
    """Per method, mask PSNR and feat of every fit seed's run (runs: (seed, protocol result)), and the
    paired gains ours - method (each seed's methods share that seed's fit)."""
    runs = [(seed, r) for seed, r in runs if r.get("rows")]
    methods = [x["method"] for x in runs[0][1]["rows"]] if runs else []
    psnr = {m: [next(x["psnr_mask"] for x in r["rows"] if x["method"] == m) for _, r in runs] for m in methods}
    feat = {m: [next(x.get("feat_mask", math.nan) for x in r["rows"] if x["method"] == m) for _, r in runs]
            for m in methods}
    gains = {m: [o - v for o, v in zip(psnr["ours"], psnr[m])] for m in methods if m != "ours"}
    return {"seeds": [seed for seed, _ in runs], "mask_psnr": psnr, "feat_mask": feat, "gains": gains}


def format_seed_table(scene: str, fs: dict[str, Any]) -> str:
    seeds = fs["seeds"]
    head = (f"{'method':<14} " + " ".join(f"{'seed ' + str(s):>7}" for s in seeds) + f" {'mean':>7} {'std':>5} | "
            f"{'ours - method: mean (min .. max)':>32} | {'feat mean':>9}")
    lines = [f"## {scene}: mask PSNR on the fit of every seed (fit.seed; each seed's methods share its fit)", head,
             "-" * len(head)]
    for m, vals in fs["mask_psnr"].items():
        g = fs["gains"].get(m)
        gain = f"{np.mean(g):+.2f} ({min(g):+.2f} .. {max(g):+.2f})" if g else ""
        lines.append(f"{m:<14} " + " ".join(f"{v:>7.2f}" for v in vals) + f" {np.mean(vals):>7.2f} "
                     f"{np.std(vals):>5.2f} | {gain:>32} | {_f(float(np.mean(fs['feat_mask'][m])), '.4f'):>9}")
    return "\n".join(lines)


def _f(v: Any, fmt: str) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, fmt)


def format_removal_table(r: dict[str, Any]) -> str:
    if "skipped" in r:
        return f"## {r['scene']}: skipped: {r['skipped']}"
    head = (f"{'method':<14} {'PSNR mask':>9} {'bbox':>6} {'full':>6} {'SSIM mask':>9} {'bbox':>6} {'full':>6} "
            f"{'hole':>6} {'detail':>6} {'feat':>6} {'cons':>6} {'cons2d':>6} | seconds: "
            + " ".join(f"{s[:6]:>6}" for s in STAGES) + f" {'total':>6} {'wall':>6}")
    hole = ""
    if r.get("hole_fraction_of_mask") is not None:
        hole = (f"\nholes (object pixels no view saw, what inpainting fills): {r['hole_pixels']} of {r['mask_pixels']} "
                f"mask pixels ({100 * r['hole_fraction_of_mask']:.1f} %); 'hole' = PSNR over those pixels only")
    if r.get("mask_psnr_holes_oracle") is not None:
        hole += (f"\ninpainting headroom: delete-only with its holes replaced by the truth scores "
                 f"{_f(r['mask_psnr_holes_oracle'], '.2f')} dB mask PSNR (the most filling the holes can give "
                 "while the background other views saw stays as fitted)")
    lines = [f"## {r['scene']}" + (f" ({r['note']})" if r.get("note") else "") + hole, head, "-" * len(head)]
    for x in r["rows"]:
        secs = " ".join(f"{_f(x['seconds'].get(s), '.0f'):>6}" for s in STAGES)
        lines.append(f"{x['method']:<14} {_f(x['psnr_mask'], '.2f'):>9} {_f(x['psnr_bbox'], '.2f'):>6} "
                     f"{_f(x['psnr_full'], '.2f'):>6} {_f(x['ssim_mask'], '.4f'):>9} {_f(x['ssim_bbox'], '.3f'):>6} "
                     f"{_f(x['ssim_full'], '.3f'):>6} {_f(x.get('psnr_hole'), '.2f'):>6} "
                     f"{_f(x.get('detail'), '.3f'):>6} {_f(x.get('feat_mask'), '.4f'):>6} {_f(x['cons'], '.4f'):>6} "
                     f"{_f(x.get('cons2d'), '.4f'):>6} | "
                     f"seconds: {secs} {_f(x['total_seconds'], '.0f'):>6} {_f(x.get('wall_seconds'), '.0f'):>6}")
    return "\n".join(lines)


def format_propagation_table(rows: list[dict[str, Any]]) -> str:
    lines = ["## mask propagation (IoU on the views whose mask was not given) and removal from 2 masks",
             f"{'scene':<8} {'IoU 1':>6} {'IoU 2':>6} {'IoU 4':>6} {'min 2':>6} {'views':>5} {'cons':>6} {'cons2d':>6} "
             f"{'wall s':>7}"]
    for r in rows:
        if "skipped" in r:
            lines.append(f"{r['scene']:<8} skipped: {r['skipped']}")
            continue
        iou_ = r["iou"]
        lines.append(f"{r['scene']:<8} {_f(iou_.get(1), '.3f'):>6} {_f(iou_.get(2), '.3f'):>6} "
                     f"{_f(iou_.get(4), '.3f'):>6} {_f(r['iou_min'].get(2), '.3f'):>6} "
                     f"{r.get('evaluated_views', 0):>5} {_f(r.get('cons'), '.4f'):>6} "
                     f"{_f(r.get('cons2d'), '.4f'):>6} {r['wall_seconds']:>7.0f}")
        if r.get("stage_seconds"):
            lines.append(f"{'':<8} stage seconds (2 masks): "
                         + ", ".join(f"{k} {v:.0f}" for k, v in r["stage_seconds"].items()))
    return "\n".join(lines)


def speed_error_plot(results: dict[str, dict[str, Any]], path: Path) -> Path | None:
    """Mask PSNR against seconds from scratch (ingest..finetune) of every method, one panel per scene with
    ground truth; the dashed line is the headroom (delete-only with the truth in every hole pixel)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    scenes = [r for r in results.values() if r.get("rows")]
    if not scenes:
        return None
    fig = Figure(figsize=(5.5 * len(scenes), 4.5), dpi=100)
    for k, r in enumerate(scenes):
        ax = fig.add_subplot(1, len(scenes), k + 1)
        for i, row in enumerate(r["rows"]):
            x, y = row["total_seconds"], row["psnr_mask"]
            ax.plot([x], [y], "o", color=f"C{i % 10}", label=row["method"])
            ax.annotate(row["method"], (x, y), textcoords="offset points", xytext=(5, 4), fontsize=8)
        oracle = r.get("mask_psnr_holes_oracle")
        if oracle is not None and np.isfinite(oracle):
            ax.axhline(oracle, color="grey", ls="--", lw=1, label="perfect holes")
        ax.set_xlabel(f"seconds from scratch, ingest..finetune ({os.cpu_count()} cores)")
        ax.set_ylabel("mask PSNR (dB)")
        ax.set_title(f"{r['scene']}: speed vs error")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    FigureCanvasAgg(fig).print_png(str(path))
    return path


def summarise(results: dict[str, dict[str, Any]]) -> tuple[dict[str, Any], list[str]]:
    summary: dict[str, Any] = {}
    checks: list[str] = []
    for scene, prefix in PREFIX.items():
        r = results.get(scene)
        if r is None:
            continue
        if "skipped" in r:
            summary[f"{prefix}_skipped"] = r["skipped"]
            continue
        by = {x["method"]: x for x in r["rows"]}
        for method, x in by.items():
            suf = SUFFIX[method]
            summary[f"{prefix}_mask_psnr{suf}"] = x["psnr_mask"]
            for m in METRICS:
                kind, region = m.split("_")
                if m != "psnr_mask":
                    summary[f"{prefix}_{region}_{kind}{suf}"] = x.get(m)
            summary[f"{prefix}_cons{suf}"] = x["cons"]
            summary[f"{prefix}_hole_psnr{suf}"] = x.get("psnr_hole")
            summary[f"{prefix}_unseen_psnr{suf}"] = x.get("psnr_unseen")
            summary[f"{prefix}_seen_psnr{suf}"] = x.get("psnr_seen")
            summary[f"{prefix}_detail{suf}"] = x.get("detail")
            summary[f"{prefix}_plane_fill_psnr{suf}"] = x.get("plane_fill_psnr")
            summary[f"{prefix}_seconds{suf}"] = x["seconds"]
        summary[f"{prefix}_wall_seconds"] = r["wall_seconds"]
        summary[f"{prefix}_hole_fraction_of_mask"] = r.get("hole_fraction_of_mask")
        if r.get("propagation_iou") is not None:
            summary[f"{prefix}_propagation_iou"] = r["propagation_iou"]
            checks.append(f"[INFO] {scene}: masks propagated from {', '.join(r['given'])}: IoU against the truth "
                          f"{r['propagation_iou']:.3f} (min {r['propagation_iou_min']:.3f})")
        summary[f"{prefix}_mask_psnr_holes_oracle"] = r.get("mask_psnr_holes_oracle")
        summary[f"{prefix}_mask_psnr_holes_blurred_truth"] = r.get("mask_psnr_holes_blurred_truth")
        fills = {m: x["plane_fill_psnr"] for m, x in by.items() if x.get("plane_fill_psnr") is not None}
        if fills:
            checks.append(f"[INFO] {scene}: the plane texture's filled hole against the truth rectified onto it "
                          "(plane_fill_psnr): " + ", ".join(f"{m} {v:.2f}" for m, v in fills.items()) + " dB")
        ours = by["ours"]["psnr_mask"]
        gains = {m: ours - x["psnr_mask"] for m, x in by.items() if m in BASELINES}
        fs = r.get("fit_seeds")
        seeds_note = ""
        if fs and len(fs["seeds"]) > 1:
            # several fits: the targets are judged on the mean paired gain, the spread is printed
            summary[f"{prefix}_fit_seeds"] = fs["seeds"]
            for method, vals in fs["mask_psnr"].items():
                summary[f"{prefix}_mask_psnr{SUFFIX[method]}_seed_mean"] = float(np.mean(vals))
                summary[f"{prefix}_mask_psnr{SUFFIX[method]}_seed_std"] = float(np.std(vals))
                summary[f"{prefix}_mask_psnr{SUFFIX[method]}_seeds"] = vals
            gains = {m: float(np.mean(fs["gains"][m])) for m in gains}
            seeds_note = (f" (mean over fit seeds {', '.join(map(str, fs['seeds']))}; min .. max: "
                          + ", ".join(f"{m} {min(fs['gains'][m]):+.2f} .. {max(fs['gains'][m]):+.2f}" for m in gains)
                          + ")")
        absent = [m for m in BASELINES if m not in gains]
        ok = all(g >= TARGET_GAIN_DB for g in gains.values()) and not absent
        summary[f"{prefix}_target_beats_baselines"] = None if absent else ok
        verdict = f"[{'PASS' if ok else 'FAIL'}]" if not absent else "[----]"
        checks.append(f"{verdict} {scene}: ours beats every baseline by >= {TARGET_GAIN_DB} dB "
                      "mask PSNR: " + ", ".join(f"{m} {g:+.2f} dB" for m, g in gains.items()) + seeds_note
                      + (f" (not judged: {', '.join(absent)} did not run)" if absent else ""))
        oracle = r.get("mask_psnr_holes_oracle")
        if oracle is not None and "delete-only" in by:
            room = oracle - by["delete-only"]["psnr_mask"]
            line = (f"[INFO] {scene}: perfect holes (truth in every hole pixel) would give {room:+.2f} dB "
                    f"over delete-only before the re-fit; the target asks {TARGET_GAIN_DB:+.1f} dB")
            if "no-sbm" in by:
                # the ablation differs from ours in the hole pixels only: what any hole filling could add
                line += (f"; {oracle - by['no-sbm']['psnr_mask']:+.2f} dB over no-sbm (the most a better fill "
                         "than no-sbm's could add, unless the re-fit also mends the background around the holes)")
            checks.append(line)
        blurred = r.get("mask_psnr_holes_blurred_truth") or {}
        # (no-rpr is ours with RPR off: a better fill would be its fill too)
        rivals = {m: x["psnr_mask"] for m, x in by.items() if m in BASELINES and m != "no-rpr"}
        if blurred and rivals:
            need = max(rivals.values()) + TARGET_GAIN_DB
            sig = np.array([float(k) for k in blurred])
            order = np.argsort(sig)
            sig, val = sig[order], np.array(list(blurred.values()))[order]
            if need > val[0]:
                reach = f"closer to the truth than the truth blurred by {sig[0]:g} px"
            elif need <= val[-1]:
                reach = f"as close as the truth blurred by {sig[-1]:g} px or more"
            else:  # PSNR falls with sigma: interpolate log(sigma) between the bracketing points
                j = int(np.nonzero(val < need)[0][0])
                t = (val[j - 1] - need) / (val[j - 1] - val[j])
                s_need = float(np.exp(np.log(sig[j - 1]) + t * (np.log(sig[j]) - np.log(sig[j - 1]))))
                reach = f"as close to the truth as the truth blurred by {s_need:.1f} px"
            first = f" (fit seed {fs['seeds'][0]})" if fs and len(fs["seeds"]) > 1 else ""
            checks.append(f"[INFO] {scene}{first}: ours' final renders with the truth blurred by sigma px in their "
                          "holes: "
                          + ", ".join(f"{k} px {v:.2f}" for k, v in zip((f"{x:g}" for x in sig), val))
                          + f" dB mask PSNR; {TARGET_GAIN_DB:+.1f} dB over {', '.join(rivals)} needs {need:.2f}: "
                          f"a fill of the pixels no view saw {reach}")
        if "truth-fill" in by:
            ceiling = by["truth-fill"]["psnr_mask"]
            line = (f"[INFO] {scene}: the re-fit's ceiling: the truth in every hole pixel before the re-fit "
                    f"(truth-fill) gives {ceiling:.2f} dB mask PSNR after it, ours {by['ours']['psnr_mask']:.2f}")
            if rivals:
                best = max(rivals, key=rivals.get)
                line += (f"; {ceiling - rivals[best]:+.2f} dB over the best baseline ({best}), where the target "
                         f"asks {TARGET_GAIN_DB:+.1f} of ours")
            checks.append(line)
        if all(np.isfinite(x.get("psnr_unseen", math.nan)) for x in by.values()):
            frac = r.get("hole_fraction_of_mask")
            checks.append(f"[INFO] {scene}: where the methods differ, pooled PSNR on ours' split of the mask: "
                          f"holes ({_f(100 * frac if frac is not None else None, '.0f')} % of it, no view saw) "
                          + ", ".join(f"{m} {x['psnr_unseen']:.2f}" for m, x in by.items())
                          + "; the rest (background other views saw, as fitted) "
                          + ", ".join(f"{m} {_f(x.get('psnr_seen'), '.2f')}" for m, x in by.items()))
        feats = {m: x.get("feat_mask", math.nan) for m, x in by.items()}
        if all(np.isfinite(v) for v in feats.values()):
            best = min(feats, key=feats.get)
            checks.append(f"[INFO] {scene}: perceptual feature distance (feat, lower = closer): "
                          + ", ".join(f"{m} {v:.4f}" for m, v in feats.items()) + f"; lowest: {best}")
        if "no-sbm" in by and "no-sbm-no-rpr" in by:
            g = by["no-sbm"]["psnr_mask"] - by["no-sbm-no-rpr"]["psnr_mask"]
            summary[f"{prefix}_rpr_gain_on_fsr_fill"] = g
            checks.append(f"[INFO] {scene}: RPR on the FSR fill (no-sbm - no-sbm-no-rpr) {g:+.3f} dB mask PSNR, feat "
                          f"{_f(feats['no-sbm'], '.4f')} vs {_f(feats['no-sbm-no-rpr'], '.4f')}; on ours, RPR "
                          f"refined {_f(r.get('refined_blocks'), 'd')} block(s)")
        nv = r.get("novel")
        if nv is not None:
            nby = {x["method"]: x for x in nv["rows"]}
            for method, x in nby.items():
                for m in NOVEL_METRICS:
                    kind, region = m.split("_")
                    summary[f"{prefix}_novel_{region}_{kind}{SUFFIX[method]}"] = x.get(m)
            o = nby["ours"]
            checks.append(f"[INFO] {scene}, novel views (held out): ours - baseline mask PSNR "
                          + ", ".join(f"{m} {o['psnr_mask'] - x['psnr_mask']:+.2f} dB" for m, x in nby.items()
                                      if m in BASELINES) + "; feat "
                          + ", ".join(f"{m} {_f(x.get('feat_mask'), '.4f')}" for m, x in nby.items()))
        for ablation, what in (("no-sbm", "SBM"), ("no-rpr", "RPR")):
            if ablation not in gains:
                continue
            g = gains[ablation]
            ok = g >= HELPS_DB
            checks.append(f"[{'PASS' if ok else 'FAIL'}] {scene}: {what} helps (ours - {ablation} = {g:+.3f} dB "
                          f"mask PSNR{', mean over fit seeds' if seeds_note else ''}; 'helps' = >= {HELPS_DB} dB)")
            summary[f"{prefix}_{what.lower()}_helps"] = bool(ok)
        if scene == "synthetic":
            summary["demo_seconds"] = r["demo_seconds"]
            ok = r["demo_seconds"] <= TARGET_DEMO_SECONDS
            checks.append(f"[{'PASS' if ok else 'FAIL'}] demo (ingest..finetune, default settings) "
                          f"{r['demo_seconds']:.0f} s <= {TARGET_DEMO_SECONDS:.0f} s")
    for scene in ("statue", "room"):
        r = results.get(scene)
        if r is None:
            continue
        if "skipped" in r:
            summary[f"{scene}_skipped"] = r["skipped"]
            continue
        for n, v in r["iou"].items():
            summary[f"{scene}_mask_iou_{n}view" + ("s" if n > 1 else "")] = v
        summary[f"{scene}_cons"] = r.get("cons")
        summary[f"{scene}_wall_seconds"] = r["wall_seconds"]
    if "statue_mask_iou_2views" in summary:
        v = summary["statue_mask_iou_2views"]
        checks.append(f"[{'PASS' if v >= TARGET_IOU else 'FAIL'}] statue mask IoU from 2 views {v:.3f} >= {TARGET_IOU}")
    return summary, checks


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="a smoke run (fewer views and iterations)")
    ap.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    ap.add_argument("--out", type=Path, default=None, help="output folder (default: a temporary folder); "
                                                             "reusing one resumes from its cache")
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder holding lund/, statue/, mip360-room/")
    ap.add_argument("--scenes", default="synthetic,synthetic-box,lund,statue,room",
                    help="comma-separated: synthetic, synthetic-box, lund, statue, room, statue-box (protocol (b) "
                         "on statue), synthetic-box-contact, synthetic-box-cast (the box with its shadow), "
                         "synthetic-raised-cast (a box on feet, its footprint in the photos), synthetic-box-1mask "
                         "(the box from one given mask), synthetic-cast (the sphere with its shadows), "
                         "synthetic-raised-cast-1mask (the box on feet from one given mask), lund-1mask (lund + "
                         "box from one given mask), statue-box-1mask (statue + box, likewise), synthetic-box-edge, "
                         "synthetic-box-corner (the rug's edge or corner under the box), synthetic-box-round (a round "
                         "rug's curved edge under it), synthetic-box-coins, "
                         "synthetic-box-brick (the box on a rug of coins in a grid, or of bricks), synthetic-photos "
                         "(the demo from its photos: SfM instead of its cameras), synthetic-video (photos "
                         "taken from a video by `frames`, one mask)")
    ap.add_argument("--verbose", action="store_true", help="log every stage")
    ap.add_argument("--novel", action="store_true",
                    help="also protocol (d): every method scored at held-out views it never saw (a second run "
                         "per ground-truth scene)")
    ap.add_argument("--fit-seeds", default=None, metavar="S,S,...",
                    help="fit.seed values for the ground-truth scenes (default: the configured seed only): every "
                         "method runs on each seed's fit; with several, a table per scene of mask PSNR by seed, "
                         "and the targets are judged on the mean paired gain (fits differ more between seeds "
                         "than some methods do)")
    ap.add_argument("--methods", default=None, metavar="M,M,...",
                    help="run only these methods of the ground-truth scenes (ours and delete-only always "
                         "run): for experiments; a target whose baselines did not all run is not judged")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override added to every variant of the ground-truth scenes and to the "
                         "runs of statue and room (e.g. remove.min_views=2); repeatable")
    ap.add_argument("--preset", choices=sorted(PRESETS), metavar="NAME",
                    help="a named parameter set (as the command line's --preset) under the --set items: "
                         + ", ".join(sorted(PRESETS)))
    args = ap.parse_args(argv)
    if args.preset:
        args.set = [*as_overrides(args.preset), *args.set]
    from sgpor_pipeline.allocator import keep_freed_memory

    keep_freed_memory()  # as the command line does: the timings are the user's
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    unknown = set(scenes) - {*GT_SCENES, "statue", "room"}
    if unknown:
        ap.error(f"unknown scene(s): {', '.join(sorted(unknown))}")
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(asctime)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    os.environ.setdefault("TQDM_DISABLE", "1")
    try:
        fit_seeds = [int(v) for v in args.fit_seeds.split(",") if v.strip()] if args.fit_seeds else []
    except ValueError:
        ap.error(f"--fit-seeds takes comma-separated integers, got {args.fit_seeds!r}")

    methods = [m.strip() for m in args.methods.split(",") if m.strip()] if args.methods else None
    try:
        selected_variants(methods)
    except ValueError as e:
        ap.error(str(e))

    # the output folder only once the arguments are known to be good (a rejected call leaves no folder)
    out = (args.out or Path(tempfile.mkdtemp(prefix="sgpor-bench-removal-"))).resolve()
    out.mkdir(parents=True, exist_ok=True)
    data = args.data.resolve()

    def ground_truth_protocol(scene: str) -> dict[str, Any]:
        protocol = partial(partial(protocol_synthetic, scene=scene) if scene in SYNTHETIC_SCENES
                           else partial(protocol_inserted, data, scene), methods=methods)
        if not fit_seeds:
            return protocol(out, args.quick, args.set, args.novel)
        runs = []
        for i, seed in enumerate(fit_seeds):  # the novel protocol (a second fit per method) on the first only
            runs.append((seed, protocol(out, args.quick, [*args.set, f"fit.seed={seed}"], args.novel and i == 0,
                                        tag="" if i == 0 else f"_seed{seed}")))
            if len(fit_seeds) > 1 and runs[-1][1].get("rows"):
                print(format_removal_table(runs[-1][1]).replace(f"## {scene}", f"## {scene}, fit.seed {seed}", 1),
                      flush=True)
        first = runs[0][1]
        if len(fit_seeds) > 1 and first.get("rows"):
            first["fit_seeds"] = seed_runs(runs)
            first["seed_results"] = {seed: r for seed, r in runs[1:]}
        return first

    results: dict[str, dict[str, Any]] = {}
    for scene in scenes:
        t0 = time.perf_counter()
        if scene in SYNTHETIC_SCENES:
            r = ground_truth_protocol(scene)
        elif not data.is_dir():
            r = {"scene": scene, "skipped": f"data folder {data} not found (pass --data)"}
        elif scene in INSERTED:
            r = ground_truth_protocol(scene)
        else:
            folder = data / ("statue" if scene == "statue" else "mip360-room")
            r = protocol_propagation(scene, folder, out, args.quick, args.set)
        r.setdefault("wall_seconds", time.perf_counter() - t0)
        results[scene] = r
        print(format_removal_table(r) if scene in GT_SCENES else format_propagation_table([r]),
              flush=True)
        if r.get("novel"):
            print(format_novel_table(r["novel"]), flush=True)
        (out / "removal_benchmark.json").write_text(json.dumps(results, indent=1, default=str))

    kernel = rasterizer_kernel()
    versions = library_versions()
    print("\n# removal benchmark" + (" (quick)" if args.quick else "") + f": {out} (rasterizer kernel {kernel}; "
          "numbers compare within one kernel build and one set of library versions only)")
    print("# libraries: " + ", ".join(f"{k} {v}" for k, v in versions.items()))
    for scene in GT_SCENES:
        if scene in results:
            print()
            print(format_removal_table(results[scene]))
            if results[scene].get("fit_seeds"):
                print()
                print(format_seed_table(scene, results[scene]["fit_seeds"]))
            if results[scene].get("novel"):
                print()
                print(format_novel_table(results[scene]["novel"]))
    prop = [results[s] for s in ("statue", "room") if s in results]
    if prop:
        print()
        print(format_propagation_table(prop))
    summary, checks = summarise(results)
    summary["quick"] = args.quick
    summary["kernel"] = kernel
    summary["versions"] = versions
    summary["protocol_wall_seconds"] = {s: r.get("wall_seconds") for s, r in results.items()}
    if checks:
        print("\n# targets")
        print("\n".join(checks))
    sheets = [r["sheet"] for r in results.values() if r.get("sheet")]
    sheets += [r["novel"]["sheet"] for r in results.values() if r.get("novel")]
    plot = speed_error_plot(results, out / "removal_speed_error.png")
    if plot is not None:
        sheets.append(str(plot))
    if sheets:
        print("\npictures: " + ", ".join(sheets))
    (out / "removal_benchmark.json").write_text(json.dumps(strict_json({"results": results, "summary": summary}),
                                                           indent=1, default=str))
    if args.json:
        print(json.dumps(strict_json(summary), default=str))
    return 0


def rasterizer_kernel() -> str:
    """The CPU kernel build in use (e.g. ``x86_64_v3``). Builds for different x86-64 levels round
    differently (v3/v4 contract multiply-adds into FMAs, v2 cannot: one render of the synthetic fit
    differs in 80 % of its pixels, by up to 2.5e-5; the backward pass also sums SIMD lanes in a tree
    whose shape follows the vector width), so a fit's trajectory and every number downstream
    depend on the machine: the synthetic demo's mask PSNR was 26.05 in an earlier session and is 24.99
    on an x86_64_v3 machine with the same code and seed (delete-only 24.39 / 23.30). Compare methods
    within one run."""
    from sgpor_pipeline.gaussians._raster_cpu import kernel_name

    return kernel_name() or "none (pure PyTorch)"


def library_versions() -> dict[str, str]:
    """Versions of the libraries whose output the numbers depend on (the synthetic scenes' textures,
    SfM, image resampling and blending, torch's own CPU kernels), printed and stored with the numbers.
    Session 18 (AVX-512 machine, fresh install: opencv 5.0.0.93, numpy 2.4.6, pycolmap 4.2.1,
    scikit-image 0.26.0, open3d 0.20.0, kornia 0.9.0, scipy 1.17.1) got synthetic seed-0 mask PSNR
    25.32 where session 17 got 26.13 with the same code. But that benchmark's synthetic fit also
    differs from two runs of ``sgpor-pipeline demo`` with the same cache key (which agree bitwise
    with each other): the fit inside this benchmark's process is not bit-identical to the CLI's.
    Neither time-based checkpoints nor two busy loops on the cores changed a 700-iteration fit, so
    the cause is not known, nor which of the two moved the number. It did not reproduce in session
    19 (same machine type and versions): this benchmark's synthetic seed-0 fit and a concurrent
    ``sgpor-pipeline demo --until fit`` wrote bit-identical ``gaussians.ply`` and renders (79442
    Gaussians), and the benchmark's ``ours`` scored 26.48, the demo's final mask PSNR. Session 18's
    25.32 came from a fit cached earlier in that session's benchmark folder."""
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for dist in ("numpy", "torch", "opencv-contrib-python-headless", "pycolmap", "open3d", "scikit-image",
                 "kornia", "scipy"):
        try:
            out[dist] = version(dist)
        except PackageNotFoundError:
            out[dist] = "not installed"
    return out


def strict_json(value: Any) -> Any:
    """NaN and infinities as null (JSON has no such numbers; e.g. ``feat`` without its model)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: strict_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict_json(v) for v in value]
    return value


if __name__ == "__main__":
    sys.exit(main())
