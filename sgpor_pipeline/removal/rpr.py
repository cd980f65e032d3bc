"""Region-wise progressive refinement (RPR) of low-detail blocks.

The paper's step (DESIGN.md section 7): per target block, the high-frequency energy is the mean of
Sobel ``|Gx| + |Gy|`` on grey (kornia) over the block's pixels inside the ERODED hole mask (the
erosion keeps the hole's seam out of the measure). The block's *surrounding area* is the known
pixels (outside the hole dilated by the same amount) within ``ring`` pixels of the block; when a
block lies too deep inside a large hole to have enough of them, the ring of known pixels around
the whole hole is used. A block whose energy is below ``ratio`` (15 %) of its surrounding's is
re-inpainted with its next-best source from SBM's top-k list, choosing, among the sources not used
yet, the one whose own high-frequency energy is closest (in log ratio) to the surrounding's. The
replacement is feather-blended into the block's hole pixels. Energies are then recomputed and the
still-low blocks are refined again, for at most ``max_rounds`` rounds: refinement happens only
where needed, and progressively.

Where it fires: on a blurry fill (the paper's SDS output; our ``opencv`` FSR baseline). On SBM's
fills it finds next to nothing: in the removal benchmark's synthetic and lund + box scenes (with
``remove.min_views`` 0 or 1) no target block of the SBM fills, nor of the final renders after the
re-fit, is below 15 % of its surrounding's energy (the per-view median of block / surrounding is
0.4 to 1.8), while the ground truth itself has 4 to 20 such blocks on lund (smooth sky next to
foliage). A lower-detail block is not always a wrong one, which is why the threshold stays the
paper's. With the default multi-view consensus (``inpaint.reference``) every carried hole pixel is
labelled projected and the refine stage leaves those to the consensus, so RPR measures few blocks or
none. Measured over every hole pixel of the consensus fills instead (session 39, fit seed 0): synthetic
0 of 457 blocks low (median block / surrounding 0.59; the truth: 32 low, median 0.95), synthetic-box 86
of 2,535 (median 0.43; the truth: 0 low). On the FSR fill, where RPR refines, lund + box from one mask
scores -0.06 to -0.11 dB mask PSNR with it: PSNR prefers the smooth guess. Session 40 let the refine
stage refine the consensus pixels too (each view on its own; not kept): on the synthetic scene no block
of SBM's or FSR's consensus fill was low (0 of 457), on synthetic-box 1 of SBM's and 38 of FSR's (mask
PSNR 27.93 -> 27.93, FSR 27.42 -> 27.43). Lund + box carries nothing, so its blocks are refined already:
FSR with RPR (633 blocks) -0.03 dB mask PSNR, its detail (high-frequency energy in the mask against the
truth's) 0.385 -> 0.427; SBM's fill 12 blocks, no change.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from sgpor_pipeline.imageio import luminance, to_float32

from .sbm import feather


@dataclass
class RPRParams:
    ratio: float = 0.15  # a block is low-detail when its HF energy < ratio x its surrounding's
    max_rounds: int = 3  # K: at most this many refinement rounds
    erode: int = 2  # erosion of the hole (pixels) before measuring a block's energy
    ring: int = 0  # width (pixels) of the surrounding area around a block; 0 = block size
    min_coverage: float = 0.1  # a block is measured when this fraction of it is in the eroded hole
    min_ring_pixels: int = 20  # fewer known pixels around a block: use the ring around the whole hole


def hf_energy(image: np.ndarray) -> np.ndarray:
    """|Gx| + |Gy| of the Sobel gradient of the grey image (kornia), HxW float32."""
    import kornia
    import torch

    grey = luminance(image)
    with torch.no_grad():
        g = kornia.filters.spatial_gradient(torch.from_numpy(np.ascontiguousarray(grey))[None, None],
                                            mode="sobel", order=1, normalized=True)  # [1,1,2,H,W]
        e = g.abs().sum(dim=2)[0, 0]
    return e.numpy().astype(np.float32)


def _box_sums(values: np.ndarray, mask: np.ndarray, corners: np.ndarray, size: int,
              offset: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Sums of values*mask and of mask over windows of ``size`` with corners ``corners - offset``."""
    pad = size + offset + 1
    vm = cv2.copyMakeBorder((values * mask).astype(np.float32), pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0)
    m = cv2.copyMakeBorder(mask.astype(np.float32), pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0)
    sv = cv2.boxFilter(vm, -1, (size, size), anchor=(0, 0), normalize=False, borderType=cv2.BORDER_CONSTANT)
    sm = cv2.boxFilter(m, -1, (size, size), anchor=(0, 0), normalize=False, borderType=cv2.BORDER_CONSTANT)
    yy = corners[:, 0] - offset + pad
    xx = corners[:, 1] - offset + pad
    return sv[yy, xx], sm[yy, xx]


@dataclass
class BlockEnergy:
    block: np.ndarray  # [T] mean HF energy over the block's eroded-hole pixels
    surround: np.ndarray  # [T] mean HF energy of the surrounding area
    measured: np.ndarray  # [T] bool: enough eroded-hole pixels to judge the block

    def low(self, ratio: float) -> np.ndarray:
        return self.measured & (self.block < ratio * self.surround)


def block_energies(energy: np.ndarray, hole: np.ndarray, targets: np.ndarray, block: int,
                   params: RPRParams) -> BlockEnergy:
    """Per-block HF energy inside the eroded hole and of its surrounding area (vectorised)."""
    e = max(0, params.erode)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * e + 1, 2 * e + 1))
    inner = cv2.erode(hole.astype(np.uint8), kernel).astype(bool) if e else hole
    outer = ~(cv2.dilate(hole.astype(np.uint8), kernel).astype(bool) if e else hole)
    targets = np.asarray(targets, np.int64).reshape(-1, 2)
    if len(targets) == 0:
        z = np.zeros(0, np.float32)
        return BlockEnergy(z, z, np.zeros(0, bool))
    sb, nb = _box_sums(energy, inner, targets, block)
    ring = params.ring or block
    ss, ns = _box_sums(energy, outer, targets, block + 2 * ring, offset=ring)
    # fallback: the ring of known pixels around the whole hole
    k2 = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * (e + ring) + 1, 2 * (e + ring) + 1))
    band = cv2.dilate(hole.astype(np.uint8), k2).astype(bool) & outer
    glob = float(energy[band].mean()) if band.any() else float(energy[outer].mean()) if outer.any() else 0.0
    surround = np.where(ns >= params.min_ring_pixels, ss / np.maximum(ns, 1), glob)
    measured = nb >= params.min_coverage * block * block
    return BlockEnergy((sb / np.maximum(nb, 1)).astype(np.float32), surround.astype(np.float32), measured)


@dataclass
class RPRResult:
    image: np.ndarray  # HxWx3 float32
    count: np.ndarray  # [T] times each target block was refined
    low_before: np.ndarray  # [T] bool
    low_after: np.ndarray  # [T] bool
    chosen: np.ndarray  # [T] index into the block's candidate list finally used (0 = SBM's / unchanged)
    energy_before: BlockEnergy
    energy_after: BlockEnergy
    rounds: int
    info: dict[str, Any] = field(default_factory=dict)


def refine_view(image: np.ndarray, hole: np.ndarray, targets: np.ndarray, cand: np.ndarray,
                source_images: list[np.ndarray], params: RPRParams, block: int = 15,
                source_energy: list[np.ndarray] | None = None, first_used: bool = True) -> RPRResult:
    """Refine the low-detail target blocks of an inpainted view (see the module doc).

    ``targets`` [T,2] block corners and ``cand`` [T,k,3] ranked (view, y, x) sources, as written by
    SBM (entry 0 is the one SBM used, unless ``first_used`` is False, e.g. for candidates retrieved
    for another inpainter's fill; -1 = none); ``source_images`` are the views the candidates index
    (float in [0, 1], or uint8).
    """
    t0 = time.perf_counter()
    cur = np.asarray(image, np.float32).copy()
    hole = np.asarray(hole, bool)
    targets = np.asarray(targets, np.int64).reshape(-1, 2)
    cand = np.asarray(cand, np.int64)
    # (a view whose hole needed no block of its own, e.g. filled from the reference, saves no candidates)
    cand = cand.reshape(len(targets), -1, 3) if len(targets) else np.zeros((0, 1, 3), np.int64)
    nt, k = cand.shape[:2]
    if source_energy is None:
        source_energy = [hf_energy(to_float32(im)) for im in source_images]
    # mean HF energy of every candidate block (in its own view)
    cand_e = np.full((nt, k), np.nan, np.float32)
    for v in np.unique(cand[..., 0]):
        if v < 0:
            continue
        sel = cand[..., 0] == v
        en = source_energy[int(v)]
        h, w = en.shape
        ys = np.clip(cand[..., 1][sel], 0, h - block)
        xs = np.clip(cand[..., 2][sel], 0, w - block)
        s_, n_ = _box_sums(en, np.ones_like(en, bool), np.stack([ys, xs], 1), block)
        cand_e[sel] = s_ / np.maximum(n_, 1)
    used = np.zeros((nt, k), bool)
    used[:, 0] = first_used
    used |= cand[..., 0] < 0
    count = np.zeros(nt, np.int64)
    chosen = np.zeros(nt, np.int64)
    fw = feather(block)
    first: BlockEnergy | None = None
    rounds = 0
    low_before = np.zeros(nt, bool)
    energy = hf_energy(cur)
    be = block_energies(energy, hole, targets, block, params)
    first = be
    low_before = be.low(params.ratio)
    low = low_before
    for _ in range(max(0, params.max_rounds)):
        if not low.any():
            break
        acc = np.zeros_like(cur)
        wsum = np.zeros(hole.shape, np.float32)
        changed = 0
        for b in np.nonzero(low)[0]:
            free = ~used[b] & np.isfinite(cand_e[b])
            if not free.any():
                continue
            target_e = max(float(be.surround[b]), 1e-6)
            gap = np.abs(np.log((cand_e[b] + 1e-6) / target_e))
            j = int(np.argmin(np.where(free, gap, np.inf)))
            used[b, j] = True
            chosen[b] = j
            count[b] += 1
            v, sy, sx = (int(a) for a in cand[b, j])
            ty, tx = int(targets[b, 0]), int(targets[b, 1])
            src = to_float32(np.asarray(source_images[v])[sy:sy + block, sx:sx + block])
            acc[ty:ty + block, tx:tx + block] += fw[:, :, None] * src
            wsum[ty:ty + block, tx:tx + block] += fw
            changed += 1
        if changed == 0:
            break
        rounds += 1
        upd = hole & (wsum > 0)
        a = np.clip(wsum, 0.0, 1.0)[upd][:, None]
        cur[upd] = cur[upd] * (1 - a) + (acc[upd] / wsum[upd][:, None]) * a
        energy = hf_energy(cur)
        be = block_energies(energy, hole, targets, block, params)
        low = be.low(params.ratio)
    info = {"blocks": int(nt), "measured": int(first.measured.sum()), "low_before": int(low_before.sum()),
            "refined_blocks": int((count > 0).sum()), "refinements": int(count.sum()),
            "low_after": int(low.sum()), "rounds": rounds, "seconds": time.perf_counter() - t0}
    return RPRResult(cur, count, low_before, low, chosen, first, be, rounds, info)


def refined_overlay(image: np.ndarray, targets: np.ndarray, count: np.ndarray, block: int,
                    hole: np.ndarray | None = None) -> np.ndarray:
    """Visualisation: the image dimmed, the hole outlined in blue, refined blocks outlined yellow
    (refined once), orange (twice) or red (three times or more)."""
    vis = (np.asarray(image, np.float32) * 0.6).copy()
    if hole is not None and hole.any():
        edge = hole & ~cv2.erode(hole.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        vis[edge] = (0.2, 0.4, 1.0)
    colours = {1: (1.0, 1.0, 0.0), 2: (1.0, 0.55, 0.0)}
    u8 = np.ascontiguousarray(np.clip(vis * 255, 0, 255).astype(np.uint8))
    for (y, x), c in zip(np.asarray(targets).reshape(-1, 2), np.asarray(count)):
        if c <= 0:
            continue
        col = colours.get(int(c), (1.0, 0.0, 0.0))
        cv2.rectangle(u8, (int(x), int(y)), (int(x) + block - 1, int(y) + block - 1),
                      tuple(int(255 * q) for q in col), 1)
    return u8
