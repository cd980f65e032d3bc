"""Regular textures: fill a hole by translating the texture by its dominant period.

A floor of tiles, a patterned rug, parquet or bricks repeats itself: in a rectified texture (the
plane texture of :mod:`sgpor_pipeline.removal.plane`) the hidden part equals the seen part shifted by
one period. Block matching fills such a hole block by block, and each block may settle on another
phase of the pattern, which breaks it (the synthetic scenes' grids of discs and coins). Following He
and Sun ("Statistics of patch offsets for image completion", ECCV 2012), each connected part of the
hole is filled on its own: the dominant offsets of the texture around it (the known pixels within
``context`` x sqrt(its area) px: a rug's pattern, not the floor's that fills the rest of a plane
texture) are the peaks of its autocorrelation (masked, normalised, by FFT) that stand
``min_prominence`` above the valley on the way from the zero offset (a smooth texture correlates
highly at short offsets, but only on the flank of the zero offset's peak). Each is scored by how well
it predicts the known rim of the part (the band within ``rim`` px of it, where at least
``min_rim_cover`` of it has a known source: the rim is seen, so the score is a real test of the
offset, not of its peak). The offsets that repeat the texture
(``min_correlation``) and predict the rim (``min_score``) are used: each hole pixel takes the texture
at the best of them whose source is known. Otherwise (a lawn, a carpet's random pile, a street, two
regions side by side) the texture has no period to follow and the caller fills as before.

The score is 1 - MSE(rim, rim shifted) / (2 var(rim)): 1 for an exact period, about 0 for unrelated
texture (the MSE of two independent samples is twice the variance), below 0 for anti-correlated.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from sgpor_pipeline.errors import PipelineError


@dataclass
class LatticeParams:
    min_score: float = 0.6  # the rim score an offset needs to fill a part by translation
    max_offsets: int = 8  # autocorrelation peaks tried
    min_shift: int = 4  # px: shorter offsets are the texture's smoothness, not its period
    min_overlap: float = 0.25  # share of the known pixels an offset must overlap with themselves
    min_prominence: float = 0.1  # a peak's correlation above the lowest on the way from the zero offset
    # a period repeats over the whole texture: a peak below this is a coincidence of two regions (mip360
    # kitchen's table and mat: 0.35 (rim score 0.57); room's carpet and rug: 0.46, but its rim score is
    # -0.02). Periods: the synthetic scene's grid of discs 0.62, synthetic-box-coins' coins 0.48 (their
    # rows are not quite regular, and the floor around the rug counts too)
    min_correlation: float = 0.4
    rim: int = 7  # px: the band of known pixels around the hole that scores each offset
    min_rim_pixels: int = 30  # fewer rim pixels to score an offset with: not tried
    min_rim_cover: float = 0.5  # share of a part's rim an offset must have known sources for
    # the periods of a hole's part are looked for within context x sqrt(its area) px of it (at least
    # min_context): the pattern around it, not a floor's that fills the rest of the texture
    context: float = 2.0
    min_context: int = 32

    def validate(self) -> None:
        if not self.min_score <= 1.0:
            raise PipelineError(f"lattice min_score must be <= 1 (got {self.min_score})")
        if self.max_offsets < 1 or self.min_shift < 1 or self.rim < 1:
            raise PipelineError("lattice max_offsets, min_shift and rim must be >= 1 "
                                f"(got {self.max_offsets}, {self.min_shift}, {self.rim})")
        if not -1.0 <= self.min_correlation <= 1.0:
            raise PipelineError(f"lattice min_correlation must be in [-1, 1] (got {self.min_correlation})")
        if self.context <= 0 or self.min_context < 1:
            raise PipelineError(f"lattice context must be > 0 and min_context >= 1 (got {self.context}, "
                                f"{self.min_context})")
        if not 0.0 < self.min_rim_cover <= 1.0:
            raise PipelineError(f"lattice min_rim_cover must be in (0, 1] (got {self.min_rim_cover})")
        if not 0.0 < self.min_overlap <= 1.0:
            raise PipelineError(f"lattice min_overlap must be in (0, 1] (got {self.min_overlap})")


@dataclass
class Offset:
    dy: int
    dx: int
    correlation: float  # masked normalised autocorrelation at this offset
    rim_score: float = float("nan")  # how well it predicts the hole's known rim (module doc)


@dataclass
class LatticeFill:
    image: np.ndarray  # HxWx3 float32: the hole filled by translation, the rest as given
    filled: np.ndarray  # HxW bool: the hole pixels it filled
    offsets: list[Offset]  # the offsets used in the largest part it filled, best first (rim_score there)
    info: dict[str, Any] = field(default_factory=dict)


def _correlate(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """sum_p a(p) b(p + o) for every offset o, as a (2H, 2W) array whose index (H, W) is o = 0."""
    h, w = a.shape
    fa = np.fft.rfft2(a, (2 * h, 2 * w))
    fb = np.fft.rfft2(b, (2 * h, 2 * w))
    return np.fft.fftshift(np.fft.irfft2(np.conj(fa) * fb, (2 * h, 2 * w)))


def dominant_offsets(image: np.ndarray, known: np.ndarray, params: LatticeParams) -> list[Offset]:
    """The peaks of the masked, normalised autocorrelation of ``image`` (HxWx3) over the ``known``
    pixels (at most ``max_offsets``; of a pair o, -o both are listed): those within 0.1 of the strongest
    first, shortest first, then the others by strength."""
    known = np.asarray(known, bool)
    n = int(known.sum())
    if n < 4 * params.min_shift ** 2:
        return []
    h, w = known.shape
    k = known.astype(np.float64)
    img = np.asarray(image, np.float64)
    centred = (img - img[known].mean(axis=0)) * k[..., None]
    num = np.zeros((2 * h, 2 * w))
    e_a = np.zeros((2 * h, 2 * w))
    e_b = np.zeros((2 * h, 2 * w))
    for c in range(centred.shape[2]):
        ch = centred[..., c]
        num += _correlate(ch, ch)
        e_a += _correlate(ch * ch, k)  # energy of the first factor where the second is known
        e_b += _correlate(k, ch * ch)
    overlap = _correlate(k, k)
    ncc = num / np.sqrt(np.maximum(e_a * e_b, 1e-12))
    ncc[overlap < 0.5 * params.min_overlap * n] = -1.0  # (too few pixels to correlate: noise)
    # local maxima of the whole function, the zero offset's peak included: a smooth texture (or one
    # upsampled from coarser views) correlates highly at short offsets, but only as the flank of that
    # peak, which holds no maximum; a period is a peak of its own, with a valley before it
    ncc = ncc.astype(np.float32)  # (the maxima test compares it with its dilation, a float32 image)
    peak = ncc >= cv2.dilate(ncc, np.ones((5, 5), np.uint8))
    oy, ox = np.mgrid[-h:h, -w:w]
    peak &= (overlap >= params.min_overlap * n) & (np.hypot(oy, ox) >= params.min_shift) & (ncc > 0.0)
    ys, xs = np.nonzero(peak)
    # a lattice's multiples correlate as well as its basis: among the peaks nearly as strong as the best,
    # the shortest first (a short shift copies from nearby, in the same light), then the rest by strength
    val = ncc[ys, xs]
    near = val >= (val.max() - 0.1 if len(val) else 0.0)
    length = np.hypot(ys - h, xs - w)
    out = []
    t = np.linspace(0.0, 1.0, 33)[1:-1]  # where the valley between the zero offset and a peak is looked for
    for i in np.lexsort((length, np.where(near, 0.0, -val), ~near)):
        y, x = int(ys[i]), int(xs[i])
        valley = float(ncc[np.round(h + t * (y - h)).astype(int), np.round(w + t * (x - w)).astype(int)].min())
        if ncc[y, x] - valley >= params.min_prominence:
            out.append(Offset(y - h, x - w, float(ncc[y, x])))
            if len(out) == params.max_offsets:
                break
    return out


def _shift(a: np.ndarray, dy: int, dx: int, fill: float = 0) -> np.ndarray:
    """out[p] = a[p + (dy, dx)] (``fill`` where that lies off the image)."""
    h, w = a.shape[:2]
    out = np.full_like(a, fill)
    if abs(dy) >= h or abs(dx) >= w:  # (nothing of the image lands on it)
        return out
    ys, yd = (slice(dy, h), slice(0, h - dy)) if dy >= 0 else (slice(0, h + dy), slice(-dy, h))
    xs, xd = (slice(dx, w), slice(0, w - dx)) if dx >= 0 else (slice(0, w + dx), slice(-dx, w))
    out[yd, xd] = a[ys, xs]
    return out


def _rim_scores(img: np.ndarray, known: np.ndarray, band: np.ndarray, offsets: list[Offset],
                params: LatticeParams) -> list[float]:
    """For each offset, 1 - MSE / (2 var) of the ``band`` predicted by the texture at that offset
    (module doc); NaN where under ``min_rim_cover`` of the band has a known source there (a few pixels
    can match by chance)."""
    var2 = 2.0 * float(img[band].var(axis=0).sum()) if band.any() else 0.0
    need = max(params.min_rim_pixels, params.min_rim_cover * band.sum())
    scores = []
    for o in offsets:
        ok = band & _shift(known, o.dy, o.dx, False)
        scores.append(float("nan") if ok.sum() < need or var2 <= 0 else
                      1.0 - float(((img[ok] - _shift(img, o.dy, o.dx)[ok]) ** 2).sum(axis=1).mean()) / var2)
    return scores


def lattice_fill(image: np.ndarray, hole: np.ndarray, known: np.ndarray, params: LatticeParams) -> LatticeFill | None:
    """The ``hole`` of ``image`` filled by translation along the texture's period (module doc); None
    for an empty hole. Where no part has an offset that repeats the texture and predicts the part's
    known rim, nothing is ``filled`` (its info lists each part's offsets and their scores).

    ``known``: the pixels that may be copied (seen, outside the hole). Each connected part of the hole
    is scored on its own rim (a part beside the pattern and a part on the plain floor around it need
    not share a period). A pixel takes the best of its part's offsets whose source is known, else the
    next; sources filled in an earlier pass count as known, so a part wider than the period is filled
    too. A pixel no offset reaches, and a part with no offset, are left as given (the caller fills them).
    """
    params.validate()
    img = np.asarray(image, np.float32)
    hole = np.asarray(hole, bool)
    known = np.asarray(known, bool) & ~hole
    if not hole.any():
        return None
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * params.rim + 1, 2 * params.rim + 1))
    n_parts, parts = cv2.connectedComponents(hole.astype(np.uint8), connectivity=8)
    h, w = hole.shape
    out = img.copy()
    have = known.copy()
    filled = np.zeros_like(hole)
    info_parts: list[dict[str, Any]] = []
    lead: list[Offset] = []  # the offsets of the largest part filled
    lead_size = 0
    passes = 0
    for i in range(1, n_parts):
        part = parts == i
        band = cv2.dilate(part.astype(np.uint8), k).astype(bool) & known
        offsets: list[Offset] = []
        if band.sum() >= params.min_rim_pixels:
            # the periods of the texture around this part (a rug's pattern, not the floor's around it)
            reach = int(max(params.context * np.sqrt(part.sum()), params.min_context))
            ys, xs = np.nonzero(part)
            y0, y1 = max(0, ys.min() - reach), min(h, ys.max() + reach + 1)
            x0, x1 = max(0, xs.min() - reach), min(w, xs.max() + reach + 1)
            near = cv2.distanceTransform((~part[y0:y1, x0:x1]).astype(np.uint8), cv2.DIST_L2, 5) <= reach
            offsets = dominant_offsets(img[y0:y1, x0:x1], known[y0:y1, x0:x1] & near, params)
        scored = list(zip(offsets, _rim_scores(img, known, band, offsets, params)))
        # the offsets that repeat the texture and predict this part's rim, best first
        use = sorted(((o, sc) for o, sc in scored
                      if sc >= params.min_score and o.correlation >= params.min_correlation), key=lambda t: -t[1])
        # each period found: dy, dx, correlation, rim score (None: too little of the rim has a source)
        rec: dict[str, Any] = {"texels": int(part.sum()),
                               "offsets": [[o.dy, o.dx, round(o.correlation, 4),
                                            round(sc, 4) if np.isfinite(sc) else None] for o, sc in scored],
                               "offsets_used": [[o.dy, o.dx, round(sc, 4)] for o, sc in use]}
        info_parts.append(rec)
        if not use:
            continue
        todo = part.copy()
        while todo.any():  # pass after pass: sources filled earlier count
            before = int(todo.sum())
            for o, _ in use:
                take = todo & _shift(have, o.dy, o.dx, False)
                if take.any():
                    out[take] = _shift(out, o.dy, o.dx)[take]
                    todo &= ~take
                    have |= take
            passes += 1
            if int(todo.sum()) == before:
                break
        got = part & ~todo
        filled |= got
        rec["left"] = int(todo.sum())
        if got.any() and rec["texels"] > lead_size:
            lead, lead_size = [Offset(o.dy, o.dx, o.correlation, sc) for o, sc in use], rec["texels"]
    # (where nothing was translated the parts' offsets stay in the info: why not)
    info: dict[str, Any] = {"parts": info_parts, "offsets_used": [[o.dy, o.dx] for o in lead], "passes": passes,
                            "left": int((hole & ~filled).sum())}
    return LatticeFill(out, filled, lead, info)
