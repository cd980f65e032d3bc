"""Straight structure across a hole: the lines that run into it, and the cells they cut it into.

Man-made planes (a table with mats, a floor with a rug, tiles) are bounded by straight edges. A fill
that grows from the hole's rim in layers lets each region of the rim advance at one speed, so where
two regions meet inside the hole their border wanders (mip360 kitchen from one mask: blobs of the
orange mat in the wood between the mats). Here the straight edges near the hole are found on the
known image (OpenCV's LSD on a lightly blurred grey image and on its two CIELAB colour channels, for
borders between colours of about one brightness; segments on the same line merged), kept when they
are long, have contrast across them and their edge meets the hole on both sides (a border passing
under the object; a few px off on the far side, the line is turned through both; or passing beside
it, within ``graze`` px, where the detector cannot see the edge along the rim), or on one side as one
of two borders of a region whose corner the hole hides; they are extended through it (an edge that
stops at the hole's rim, or beside it, is not). The lines
cut the image into cells (the side of every line; the two borders of a hidden corner split off only
their region, the quadrant between them, since beyond the corner they border nothing: on mip360 room
the three other quadrants put the wood at the hole's side into the carpet's part of the hole; and the
quadrant ends where its borders' edges end in view, since the region ends there too: room's rug
quadrant, unbounded, held the wood beyond the rug's far side);
:func:`~sgpor_pipeline.removal.sbm.inpaint_view`
with ``labels`` then fills each target block from source blocks of its own cell, and each pixel mainly
from the blocks of its cell, so the edges continue straight through the hole and meet at corners.

A border the detector sees as no single line (its pieces short, ragged, a few px apart on the two sides
of the hole, with other colours beside it on each side: mip360 kitchen's orange mat, bent under the
bulldozer, dark wood beside it above the hole and pale wood below) is found from where it meets the
hole instead: the colour changes along the hole's rim, each followed away from the hole as the ray with
the most contrast across it, and two such edges that leave the hole in opposite directions along the
line between their entries, with one side's colour the same at both, are joined by that line.

Curved borders (an ellipse, a round rug) give no long segment and nothing changes there.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from sgpor_pipeline.errors import PipelineError

CORNER_MARGIN = 3.0  # px a hidden corner's region reaches beyond its borders' farthest segment ends
OPEN_END = 6.0  # px from the image's border or unknown pixels within which a segment's end may run on unseen
FREE = -1  # label of a pixel whose cell has no known pixels near the hole: no constraint there


@dataclass
class StructureParams:
    min_length: float = 0.0  # px of a line's segments together; 0 = 2 x block
    reach: float = 0.0  # a line's nearest segment end lies within this many px of the hole; 0 = block
    # ... and a hidden corner's border's within this many (its edge is seen up to the rim; 0 = block / 2).
    # mip360 room: a rug's step edge that ended 14.4 px below the hole (a strip of carpet between) was
    # paired with the rug's top edge into a corner that put rug where the carpet is; true borders of the
    # generated hidden corners end 3.0-3.6 px from the hole
    corner_reach: float = 0.0
    min_contrast: float = 0.08  # mean RGB difference (L2, in [0, 1] units) across the line, 3 px each side
    max_lines: int = 8  # the longest this many lines (2^8 cells at most)
    merge_angle: float = 2.0  # degrees: segments this close in angle ...
    merge_distance: float = 1.5  # ... whose ends lie this close (px) to a line extend it
    blur: float = 1.0  # Gaussian sigma (px) before the detector (woven or grainy texture)
    min_cell_pixels: int = 0  # known pixels a cell needs near the hole to constrain it; 0 = block^2
    near: float = 0.0  # "near the hole": within this many px; 0 = 3 x block
    # A border that passes the hole within this many px, or cuts at most this deep into it, is a line
    # too when its edge is seen on both sides of where it passes: the hole is filled from its own side
    # (mip360 room: the hole grazed the rug's border on tan wood, and SBM pasted wood into the rug). The
    # detector cannot see an edge this close to the rim (segments start 2 px in, after a 1 px blur). 0 = off
    graze: float = 3.0
    colour: bool = True  # also the edges of CIELAB's colour channels that the grey image lacks
    # A border seen as no single line (short pieces, a few px apart across the hole, other colours beside
    # it on each side) is continued all the same where two edges leave the hole opposite each other along
    # the line between their entries with one side's colour the same at both (_paired_entries). mip360
    # kitchen from one mask: the orange mat's edge under the bulldozer, whose fill bulged orange into the
    # wood between the mats without it
    paired: bool = True

    def validate(self) -> None:
        if self.max_lines < 1 or self.max_lines > 16:
            raise PipelineError(f"max_lines must be in 1..16 (got {self.max_lines})", fix="use e.g. 8")
        lengths = (self.min_length, self.reach, self.corner_reach, self.min_contrast, self.blur, self.near,
                   self.graze)
        if min(lengths) < 0 or self.min_cell_pixels < 0:
            raise PipelineError("structure lengths, contrast and blur must be >= 0", fix="use the defaults")


@dataclass
class Line:
    """n . p = rho, n a unit normal (x, y); ``length`` the segments' total length (px)."""

    normal: np.ndarray
    rho: float
    length: float
    contrast: float = 0.0
    segments: list[np.ndarray] = field(default_factory=list)  # [4] x0, y0, x1, y1 each
    # A border of a region whose corner the hole hides: (this line's side of the region (+1 / -1), the
    # other border, its side of the region, how far the region reaches from the other border along this
    # one and from this one along the other (px; inf where a border's segments run out of the known
    # image)). The line then splits only that region (the quadrant of the two borders, cut where they
    # end) from the rest; beyond the corner it is no border. (left out of == and repr: the two borders
    # name each other)
    corner: tuple[float, Line, float, float, float] | None = field(default=None, compare=False, repr=False)

    def distance(self, h: int, w: int) -> np.ndarray:
        """[h,w] each pixel's signed distance to the line (px, positive on the normal's side)."""
        ys, xs = np.mgrid[0:h, 0:w]
        return xs * self.normal[0] + ys * self.normal[1] - self.rho

    def side(self, h: int, w: int) -> np.ndarray:
        return self.distance(h, w) > 0

    def ends(self) -> np.ndarray:
        """[2 x segments, 2] the (x, y) ends of the line's segments."""
        return np.concatenate([np.asarray(sg, np.float64).reshape(2, 2) for sg in self.segments])

    def cell_bit(self, h: int, w: int) -> np.ndarray:
        """The pixels on the line's + side, or for a corner's border those in the corner's region."""
        if self.corner is None:
            return self.side(h, w)
        own, other, other_side, reach, reach_other = self.corner
        # distances into the region from each border; it reaches along each border as far as that
        # border's edge was seen (mip360 room: the rug's quadrant, unbounded, held the wood beyond the
        # rug's far side, and SBM pasted it into the rug's part of the hole)
        into_own = self.distance(h, w) * own
        into_other = other.distance(h, w) * other_side
        return (into_own > 0) & (into_other > 0) & (into_other <= reach) & (into_own <= reach_other)

    def to_dict(self) -> dict:
        return {"normal": [float(self.normal[0]), float(self.normal[1])], "rho": float(self.rho),
                "length": float(self.length), "contrast": float(self.contrast), "segments": len(self.segments),
                "corner": self.corner is not None,
                # (how far the corner's region reaches along this border; None: into the unseen)
                "reach": None if self.corner is None or not np.isfinite(self.corner[3]) else float(self.corner[3])}


def _reach(line: Line, border: Line, side: float, open_end: np.ndarray) -> float:
    """How far ``line``'s segments reach from ``border`` into its ``side`` (px, the farthest end); inf
    where that end lies on ``open_end`` (the edge may run on unseen)."""
    ends = line.ends()
    far = ends[int(np.argmax((ends @ border.normal - border.rho) * side))]
    h, w = open_end.shape
    x, y = int(np.clip(np.rint(far[0]), 0, w - 1)), int(np.clip(np.rint(far[1]), 0, h - 1))
    return float("inf") if open_end[y, x] else float((far @ border.normal - border.rho) * side) + CORNER_MARGIN


def _channel_segments(channel: np.ndarray, inner: np.ndarray, blur: float) -> list[tuple]:
    """LSD segments of one uint8 channel (its invalid pixels filled smoothly), cut to their runs on
    ``inner`` pixels."""
    if blur > 0:
        channel = cv2.GaussianBlur(channel, (0, 0), blur)
    lines = cv2.createLineSegmentDetector().detect(channel)[0]
    if lines is None:
        return []
    h, w = inner.shape
    out = []
    for x0, y0, x1, y1 in lines.reshape(-1, 4).astype(np.float64):
        # the runs of the segment on valid pixels (the smooth fill may carry an edge into the hole)
        n = max(2, int(np.ceil(np.hypot(x1 - x0, y1 - y0))) + 1)
        t = np.linspace(0.0, 1.0, n)
        px, py = x0 + t * (x1 - x0), y0 + t * (y1 - y0)
        ok = inner[np.clip(np.rint(py), 0, h - 1).astype(int), np.clip(np.rint(px), 0, w - 1).astype(int)]
        edges = np.flatnonzero(np.diff(np.r_[0, ok.astype(np.int8), 0]))
        for a, b in zip(edges[::2], edges[1::2]):
            if b - a >= 4:
                out.append((px[a], py[a], px[b - 1], py[b - 1]))
    return out


def _covered(segment: tuple, found: np.ndarray, angle_deg: float, dist: float) -> bool:
    """Whether ``found`` [M,4] already has ``segment``: one of about its angle whose line passes within
    ``dist`` px of both its ends and that spans at least half of it."""
    if not len(found):
        return False
    s = np.asarray(segment, np.float64)
    d = found[:, 2:] - found[:, :2]
    length = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
    u = d / length[:, None]
    n = np.stack([-u[:, 1], u[:, 0]], 1)
    sd = s[2:] - s[:2]
    s_len = max(float(np.hypot(*sd)), 1e-9)
    parallel = np.abs(u @ (sd / s_len)) >= np.cos(np.deg2rad(angle_deg))
    near = ((np.abs(np.sum((s[:2] - found[:, :2]) * n, 1)) <= dist)
            & (np.abs(np.sum((s[2:] - found[:, :2]) * n, 1)) <= dist))
    a, b = np.sum((s[:2] - found[:, :2]) * u, 1), np.sum((s[2:] - found[:, :2]) * u, 1)
    overlap = np.minimum(np.maximum(a, b), length) - np.maximum(np.minimum(a, b), 0.0)
    return bool((parallel & near & (overlap >= 0.5 * s_len)).any())


def _segments(image: np.ndarray, valid: np.ndarray, blur: float, colour: bool = True,
              angle_deg: float = 2.0, dist: float = 1.5) -> np.ndarray:
    """LSD segments [M,4] (x0, y0, x1, y1) lying on ``valid`` pixels (2 px in), on a grey image whose
    invalid pixels are filled smoothly (so the rim of the hole makes no edge); with ``colour``, also
    those of the two colour channels of CIELAB that the grey image lacks (a border between two colours
    of about one brightness: mip360 room's light rug on tan wood is 0.06 apart in grey, 0.3 in blue)."""
    u8 = np.clip(np.asarray(image, np.float32) * 255 + 0.5, 0, 255).astype(np.uint8)
    valid = np.asarray(valid, bool)
    inner = cv2.erode(valid.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    grey = cv2.cvtColor(u8, cv2.COLOR_RGB2GRAY)
    channels = np.dstack([grey, cv2.cvtColor(u8, cv2.COLOR_RGB2LAB)[:, :, 1:]]) if colour else grey
    if (~valid).any():  # (TELEA fills each channel alike: one call for the three)
        channels = cv2.inpaint(channels, (~valid).astype(np.uint8), 3, cv2.INPAINT_TELEA)
    channels = channels.reshape(*grey.shape, -1)
    out = _channel_segments(np.ascontiguousarray(channels[:, :, 0]), inner, blur)
    for c in range(1, channels.shape[2]):
        found = np.array(out, np.float64).reshape(-1, 4)
        out += [sg for sg in _channel_segments(np.ascontiguousarray(channels[:, :, c]), inner, blur)
                if not _covered(sg, found, angle_deg, dist)]
    return np.array(out, np.float32).reshape(-1, 4)


def _merge(seg: np.ndarray, angle_deg: float, dist: float) -> list[Line]:
    """Greedy: the longest segment starts a line; a segment of about its angle whose ends lie near it joins."""
    d = seg[:, 2:] - seg[:, :2]
    length = np.hypot(d[:, 0], d[:, 1])
    order = np.argsort(-length, kind="stable")
    lines: list[Line] = []
    cos_tol = np.cos(np.deg2rad(angle_deg))
    for i in order:
        if length[i] <= 0:
            continue
        u = d[i] / length[i]
        for ln in lines:
            direction = np.array([ln.normal[1], -ln.normal[0]])
            if abs(float(u @ direction)) < cos_tol:
                continue
            e = np.abs(seg[i, :2] @ ln.normal - ln.rho), np.abs(seg[i, 2:] @ ln.normal - ln.rho)
            if max(e) <= dist:
                ln.length += float(length[i])
                ln.segments.append(seg[i])
                break
        else:
            n = np.array([-u[1], u[0]])
            lines.append(Line(n, float(seg[i, :2] @ n), float(length[i]), segments=[seg[i]]))
    return lines


def _side_pixels(known: np.ndarray, points: np.ndarray, normal: np.ndarray, offset: float = 3.0
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pixels ``offset`` px either side of ``points`` [..., 2] (x, y) along ``normal`` (broadcast
    against them): (on its side, on the other), integer (x, y) [..., 2] each, and where both are in the
    image and ``known`` [...]. Pixels that are not are (0, 0), so they can index the image as they are."""
    h, w = known.shape
    a = np.rint(points + offset * normal).astype(int)
    b = np.rint(points - offset * normal).astype(int)
    inside = ((a >= 0).all(-1) & (a[..., 0] < w) & (a[..., 1] < h) & (b >= 0).all(-1) & (b[..., 0] < w)
              & (b[..., 1] < h))
    a, b = (np.where(inside[..., None], q, 0) for q in (a, b))
    return a, b, inside & known[a[..., 1], a[..., 0]] & known[b[..., 1], b[..., 0]]


def _sides(image: np.ndarray, known: np.ndarray, points: np.ndarray, normal: np.ndarray,
           offset: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """The colours ``offset`` px either side of ``points`` [K,2] (x, y) along ``normal``: (on its side,
    on the other), [M,3] each, for the points whose two pixels are both in the image and ``known``."""
    a, b, ok = _side_pixels(known, points, normal, offset)
    return image[a[ok, 1], a[ok, 0]], image[b[ok, 1], b[ok, 0]]


def _pairing(a_plus: np.ndarray, a_minus: np.ndarray, b_plus: np.ndarray, b_minus: np.ndarray
             ) -> tuple[float, float]:
    """How far two edges' side colours are apart paired the same way (+ with +) and crosswise: the
    larger difference of each pairing."""
    same = max(np.linalg.norm(a_plus - b_plus), np.linalg.norm(a_minus - b_minus))
    cross = max(np.linalg.norm(a_plus - b_minus), np.linalg.norm(a_minus - b_plus))
    return float(same), float(cross)


def _contrast(image: np.ndarray, valid: np.ndarray, line: Line, offset: float = 3.0) -> float:
    """Mean colour difference (L2) between points ``offset`` px either side of the line's segments."""
    diffs = []
    for s in line.segments:
        n = max(2, int(np.hypot(s[2] - s[0], s[3] - s[1])))
        t = np.linspace(0.0, 1.0, n)
        plus, minus = _sides(image, valid, np.stack([s[0] + t * (s[2] - s[0]), s[1] + t * (s[3] - s[1])], 1),
                             line.normal, offset)
        if len(plus):
            diffs.append(plus - minus)
    if not diffs:
        return 0.0
    return float(np.linalg.norm(np.concatenate(diffs).mean(axis=0)))


def _entries(image: np.ndarray, known: np.ndarray, hole: np.ndarray, line: Line, block: int,
             min_contrast: float, offset: float = 3.0) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Where the line enters the hole with its edge there: for each end of each run of hole pixels
    along the line, the known pixels over the last ``block`` px before it must differ across the line
    (mean colour difference >= ``min_contrast``, measured ``offset`` px either side). Returns those
    entries: (point (x, y), mean colour on the normal's side, on the other)."""
    h, w = hole.shape
    d = np.array([line.normal[1], -line.normal[0]])
    t = np.arange(-(h + w), h + w + 1, dtype=np.float64)
    pts = line.normal * line.rho + t[:, None] * d
    inside = (pts[:, 0] >= 0) & (pts[:, 0] <= w - 1) & (pts[:, 1] >= 0) & (pts[:, 1] <= h - 1)
    t, pts = t[inside], pts[inside]
    if not len(t):
        return []
    on_hole = hole[np.rint(pts[:, 1]).astype(int), np.rint(pts[:, 0]).astype(int)]
    edges = np.flatnonzero(np.diff(np.r_[0, on_hole.astype(np.int8), 0]))
    found = []
    for start, stop in zip(edges[::2], edges[1::2]):  # a run of hole pixels [start, stop)
        for entry, before in ((start, np.arange(start - block - 2, start - 2)),
                              (stop - 1, np.arange(stop + 2, stop + block + 2))):
            before = before[(before >= 0) & (before < len(t))]
            if len(before) < block // 2:
                continue
            plus, minus = _sides(image, known, pts[before], line.normal, offset)
            if len(plus) < block // 2:
                continue
            plus, minus = plus.mean(axis=0), minus.mean(axis=0)
            if np.linalg.norm(plus - minus) >= min_contrast:
                found.append((pts[entry], plus, minus))
    return found


def _realigned(image: np.ndarray, known: np.ndarray, hole: np.ndarray, line: Line, entry: tuple, block: int,
               min_contrast: float, search: int = 6) -> Line | None:
    """A line with one ``entry`` (point, side colours) whose edge may come out on the far side a few px
    off (its angle, fitted on one side, is a little off across a wide hole): the same line shifted by up
    to ``search`` px at each other end of the hole along it; where the shifted line has an edge there
    like the one it has (the same border, not a speck of the floor's texture), the line through both
    entries (None when no shift finds one)."""
    n, d = line.normal, np.array([line.normal[1], -line.normal[0]])
    at, e_plus, e_minus = entry
    best: tuple[float, np.ndarray] | None = None
    for shift in range(-search, search + 1):
        moved = Line(n, line.rho + shift, line.length)
        for point, plus, minus in _entries(image, known, hole, moved, block, min_contrast):
            if abs(float((point - at) @ d)) < 2 * block:  # (the entry it already has)
                continue
            c = float(np.linalg.norm(plus - minus))
            same, cross = _pairing(plus, minus, e_plus, e_minus)
            # about the contrast of the entry it has, its sides paired the same way (mip360 kitchen's
            # orange mat: contrast 0.151 against 0.107, same-side colours 0.129 apart, cross 0.222; the
            # floor's speck beyond a rug's hidden corner: 0.164 against 0.326, 0.192 / 0.354)
            if not (0.6 <= c / float(np.linalg.norm(e_plus - e_minus)) <= 1 / 0.6 and same < 0.6 * cross):
                continue
            if best is None or c > best[0]:
                best = (c, point)
    if best is None:
        return None
    u = best[1] - at
    u = u / max(float(np.linalg.norm(u)), 1e-9)
    normal = np.array([-u[1], u[0]])
    if normal @ n < 0:
        normal = -normal
    return Line(normal, float(at @ normal), line.length, line.contrast, line.segments)


def _corner(a: tuple[Line, tuple], b: tuple[Line, tuple], hole: np.ndarray, tolerance: int = 3
            ) -> tuple[float, float] | None:
    """Whether two lines, each with one entry into the hole (``(line, entry)``), are the two borders of
    one region whose corner the hole hides: they cross within ``tolerance`` px of a hole pixel; their
    sides pair up by colour at the entries (each side like one side of the other line, clearly more than
    like its other side); and for one of the two regions so paired, each line enters on that region's
    side of the other (the region's edges run from their entries to the corner). Returns the region's
    side of a and of b (+1 / -1 each, of their normals), or None."""
    (la, (pa, a_plus, a_minus)), (lb, (pb, b_plus, b_minus)) = a, b
    m = np.array([la.normal, lb.normal])
    if abs(np.linalg.det(m)) < np.sin(np.deg2rad(10.0)):  # (about parallel)
        return None
    x, y = np.linalg.solve(m, [la.rho, lb.rho])
    h, w = hole.shape
    y0, y1 = int(max(0, np.floor(y) - tolerance)), int(min(h, np.ceil(y) + tolerance + 1))
    x0, x1 = int(max(0, np.floor(x) - tolerance)), int(min(w, np.ceil(x) + tolerance + 1))
    if not (y0 < y1 and x0 < x1 and hole[y0:y1, x0:x1].any()):
        return None
    same, cross = _pairing(a_plus, a_minus, b_plus, b_minus)
    if min(same, cross) > 0.5 * max(same, cross):  # the sides do not pair up clearly
        return None
    sign_b_of_a = 1.0 if same < cross else -1.0  # b's side (of its normal) holding a's + side's colour
    side_a_of_b = float(pb @ la.normal - la.rho)  # where b enters, relative to a
    side_b_of_a = float(pa @ lb.normal - lb.rho)
    for region in (1.0, -1.0):  # a's + side (and its partner on b), then a's - side
        if side_a_of_b * region > 0 and side_b_of_a * region * sign_b_of_a > 0:
            return region, region * sign_b_of_a
    return None


def _rim_transitions(image: np.ndarray, known: np.ndarray, hole: np.ndarray, window: int, min_contrast: float,
                     offset: int = 3) -> list[tuple[np.ndarray, int]]:
    """Where colour borders meet the hole: along the contour ``offset`` px outside each part of the hole,
    the points where the mean colour over ``window`` px before differs from that after by at least
    ``min_contrast`` (local maxima along the contour, both windows mostly on ``known`` pixels).
    Returns (point (x, y), index of the hole's part) each."""
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * offset + 1,) * 2)
    grown = cv2.dilate(np.asarray(hole, np.uint8), kernel)
    contours, _ = cv2.findContours(grown, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    steps = np.arange(2, window + 1)
    out = []
    for part, contour in enumerate(contours):
        pts = contour.reshape(-1, 2)
        n = len(pts)
        if n < 4 * window:
            continue
        ok = known[pts[:, 1], pts[:, 0]].astype(np.float64)
        col = image[pts[:, 1], pts[:, 0]].astype(np.float64) * ok[:, None]
        # each point's windows before and after it along the closed contour: their known pixels and mean colours
        before = (np.arange(n)[:, None] - steps[None]) % n
        after = (np.arange(n)[:, None] + steps[None]) % n
        nb, na = ok[before].sum(1), ok[after].sum(1)
        full = (nb >= 0.8 * len(steps)) & (na >= 0.8 * len(steps))
        diff = np.linalg.norm(col[after].sum(1) / np.maximum(na, 1)[:, None]
                              - col[before].sum(1) / np.maximum(nb, 1)[:, None], axis=1) * full
        around = (np.arange(n)[:, None] + np.arange(-window, window + 1)[None]) % n
        peak = (diff >= min_contrast) & (np.argmax(diff[around], axis=1) == window)
        out += [(pts[j].astype(np.float64), part) for j in np.flatnonzero(peak)]
    return out


def _outward_edge(image: np.ndarray, known: np.ndarray, hole: np.ndarray, point: np.ndarray, length: int,
                  to_hole: np.ndarray, offset: float = 3.0, shift: int = 2, angle_step: float = 2.0
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float] | None:
    """The straight edge that leaves the hole at ``point``: over the directions away from the hole and
    start points up to ``shift`` px aside, the ray of ``length`` px (on known pixels) with the largest
    contrast across it (the mean colour difference ``offset`` px either side, as :func:`_contrast`).
    Measured along the edge rather than at the rim, where the hole's own border and the fill's seam
    blur it (mip360 kitchen: the local gradient at the orange mat's entry points along the rim).
    The ray must end at least ``length`` x 0.4 px from the hole (``to_hole``: each pixel's distance to
    it), i.e. leave the rim at 24 degrees or more: a ray along the rim measures the rim's own seam.
    Returns (start point, unit direction (x, y), colours on the direction's left (+normal) side and on
    its right, contrast), or None when no ray has ``length`` / 2 px of known pixels either side."""
    h, w = known.shape
    angles = np.deg2rad(np.arange(0.0, 360.0, angle_step))
    d = np.stack([np.cos(angles), np.sin(angles)], 1)  # [A,2]
    nrm = np.stack([-d[:, 1], d[:, 0]], 1)
    t = np.arange(2, length + 1, dtype=np.float64)
    best = None
    for s in range(-shift, shift + 1):
        start = point[None] + s * nrm  # [A,2]: aside along each ray's normal
        pts = start[:, None] + t[None, :, None] * d[:, None]  # [A,T,2]
        a, b, ok = _side_pixels(known, pts, nrm[:, None], offset)
        c = np.where(ok[..., None], np.rint(pts).astype(int), 0)
        ok &= ~hole[c[..., 1], c[..., 0]]
        count = ok.sum(1)
        plus = (image[a[..., 1], a[..., 0]] * ok[..., None]).sum(1) / np.maximum(count, 1)[:, None]
        minus = (image[b[..., 1], b[..., 0]] * ok[..., None]).sum(1) / np.maximum(count, 1)[:, None]
        end = np.rint(start + length * d).astype(int)
        away = np.zeros(len(d), bool)
        fits = (end[:, 0] >= 0) & (end[:, 0] < w) & (end[:, 1] >= 0) & (end[:, 1] < h)
        away[fits] = to_hole[end[fits, 1], end[fits, 0]] >= 0.4 * length
        contrast = np.linalg.norm(plus - minus, axis=1) * (count >= len(t) // 2) * away
        k = int(np.argmax(contrast))
        if contrast[k] > 0 and (best is None or contrast[k] > best[4]):
            best = (start[k], d[k], plus[k], minus[k], float(contrast[k]))
    if best is None:
        return None
    start, direction, plus, minus, contrast = best
    return start, direction, np.asarray(plus, np.float64), np.asarray(minus, np.float64), contrast


def _paired_entries(image: np.ndarray, known: np.ndarray, hole: np.ndarray, to_hole: np.ndarray, block: int,
                    min_contrast: float, found: list[Line], max_angle: float = 8.0) -> list[Line]:
    """A region's straight border that enters the hole at two places but is seen as no single line (its
    visible pieces short, a few px apart across the hole, or bordering other colours on each side; mip360
    kitchen's orange mat under the bulldozer: parallel pieces 20 texels apart, dark wood beside it above
    the hole and pale wood below): where colour borders meet the hole's rim, each one's edge followed
    away from the hole (:func:`_outward_edge`), and two such edges joined through the hole when they
    leave it in opposite directions, the line between their entry points runs along both (within
    ``max_angle`` degrees), mostly through the hole, and one side's colour is the same at both (the
    region that runs under the object) and clearly unlike the other sides. A border already among
    ``found`` is not found again. ``to_hole``: each pixel's distance to the hole. Returns the joining
    lines, best-aligned first, each entry used once."""
    length = 3 * block
    entries = []
    for point, part in _rim_transitions(image, known, hole, max(3, block // 2), min_contrast):
        edge = _outward_edge(image, known, hole, point, length, to_hole)
        if edge is not None and edge[4] >= min_contrast:
            entries.append((part, *edge))
    near = 4  # px: the line runs through the hole grown by this much; a found border this close is the same
    grown = cv2.dilate(np.asarray(hole, np.uint8),
                       cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * near + 1,) * 2)) > 0
    cos_tol = np.cos(np.deg2rad(max_angle))
    candidates = []
    for i, (part_a, pa, da, a_left, a_right, ca) in enumerate(entries):
        for j in range(i + 1, len(entries)):
            part_b, pb, db, b_left, b_right, cb = entries[j]
            chord = pb - pa
            span = float(np.linalg.norm(chord))
            if part_a != part_b or span < block:
                continue
            u = chord / span  # from a to b: a's edge leaves the hole along -u, b's along +u
            if not (da @ -u >= cos_tol and db @ u >= cos_tol):
                continue
            samples = pa + np.linspace(0.0, 1.0, int(span) + 1)[:, None] * chord
            if grown[np.rint(samples[:, 1]).astype(int), np.rint(samples[:, 0]).astype(int)].mean() < 0.75:
                continue
            # the sides seen from a's direction (-u) and from b's (+u) are mirrored: a's left is b's right
            same = (np.linalg.norm(a_left - b_right), np.linalg.norm(a_right - b_left))
            cross = (np.linalg.norm(a_left - b_left), np.linalg.norm(a_right - b_right),
                     np.linalg.norm(a_left - a_right), np.linalg.norm(b_left - b_right))
            if min(same) >= 0.5 * min(cross):
                continue
            if any(max(abs(float(q @ ln.normal) - ln.rho) for q in (pa, pb)) <= near for ln in found):
                continue
            normal = np.array([-u[1], u[0]])
            line = Line(normal, float(pa @ normal), 2.0 * length, min(ca, cb),
                        [np.r_[pa, pa + length * da], np.r_[pb, pb + length * db]])
            misalign = 2.0 - float(da @ -u) - float(db @ u)
            candidates.append((misalign, i, j, line))
    out, used = [], set()
    for _, i, j, line in sorted(candidates, key=lambda c: c[0]):
        if i in used or j in used:
            continue
        used |= {i, j}
        out.append(line)
    return out


def hole_lines(image: np.ndarray, known: np.ndarray, hole: np.ndarray, block: int,
               params: StructureParams | None = None) -> list[Line]:
    """The straight edges of the ``known`` part of ``image`` (float RGB in [0, 1]) that run through
    ``hole``: long enough, with contrast across them, a segment end near the hole, and the edge there
    where the line enters the hole on both sides (a border that passes under the object, or beside it
    within ``graze`` px: the hole grown by that much), or on one side where it meets another such line
    inside the hole (a hidden corner; its edge then reaches the rim, within ``corner_reach`` px). An
    edge that stops short
    of the hole (a rug's border ending at its corner beside it) or that ends at the hole (an object's
    side the hole cuts off) is not continued. With ``paired``, also the borders seen as no single line
    that :func:`_paired_entries` joins from their two entries. Longest first, at most ``max_lines``."""
    p = params or StructureParams()
    p.validate()
    hole = np.asarray(hole, bool)
    known = np.asarray(known, bool) & ~hole
    if not hole.any() or not known.any():
        return []
    img = np.asarray(image, np.float32)
    min_len = p.min_length or 2.0 * block
    reach = p.reach or float(block)
    corner_reach = p.corner_reach or block / 2.0
    seg = _segments(img, known, p.blur, p.colour, p.merge_angle, p.merge_distance)
    if not len(seg):
        return []
    to_hole = cv2.distanceTransform((~hole).astype(np.uint8), cv2.DIST_L2, 5)
    hy, hx = np.nonzero(hole)
    h, w = hole.shape
    r = int(np.ceil(p.graze))  # the hole grown by ``graze`` px: where a grazing line's entries are found
    grown = cv2.dilate(hole.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2)) > 0

    through: list[Line] = []
    one_sided: list[tuple[Line, tuple]] = []
    for ln in _merge(seg, p.merge_angle, p.merge_distance):
        if ln.length < min_len:
            continue
        across = hx * ln.normal[0] + hy * ln.normal[1] - ln.rho  # the hole's pixels' signed distances
        if np.abs(across).min() > max(1.0, p.graze):  # it misses the hole
            continue
        # how deep the hole reaches across the line on its smaller side (< 0: not at all)
        sliver = min(float(across.max()), float(-across.min()))
        ends = ln.ends()
        ex = np.clip(np.rint(ends[:, 0]), 0, w - 1).astype(int)
        ey = np.clip(np.rint(ends[:, 1]), 0, h - 1).astype(int)
        near_end = float(to_hole[ey, ex].min())
        if near_end > reach:
            continue
        ln.contrast = _contrast(img, known, ln)
        if ln.contrast < p.min_contrast:
            continue
        entries = _entries(img, known, hole, ln, block, p.min_contrast)
        if len(entries) == 1:  # its edge may come out of the hole a few px off the line
            turned = _realigned(img, known, hole, ln, entries[0], block, p.min_contrast)
            through_both = [] if turned is None else _entries(img, known, hole, turned, block, p.min_contrast)
            if len(through_both) >= 2:
                ln, entries = turned, through_both
        if len(entries) >= 2:
            through.append(ln)
        elif (p.graze > 0 and sliver <= p.graze
              and len(_entries(img, known, grown, ln, block, p.min_contrast)) >= 2):
            # a border that passes beside the hole, its edge seen on both sides of where it passes (not
            # a rug's side that ends at its corner by the hole): the hole keeps to its side
            through.append(ln)
        elif len(entries) == 1 and near_end <= corner_reach:
            one_sided.append((ln, entries[0]))
    # an edge whose segment ends this close to the image's border or to unknown pixels may run on unseen
    corners = []
    if len(one_sided) > 1:  # (a hidden corner pairs two one-sided lines)
        open_end = cv2.distanceTransform(np.pad(known, 1).astype(np.uint8), cv2.DIST_L2, 3)[1:-1, 1:-1] <= OPEN_END
        for a in one_sided:
            for b in one_sided:
                found = None if b is a else _corner(a, b, hole)
                if found is not None:
                    # (a border of several hidden corners keeps the first: one region per line)
                    a[0].corner = (found[0], b[0], found[1], _reach(a[0], b[0], found[1], open_end),
                                   _reach(b[0], a[0], found[0], open_end))
                    corners.append(a[0])
                    break
    if p.paired:
        through += _paired_entries(img, known, hole, to_hole, block, p.min_contrast, through + corners)
    out = sorted(through + corners, key=lambda ln: -ln.length)
    return out[: p.max_lines]


def cell_labels(shape: tuple[int, int], lines: list[Line], known: np.ndarray, hole: np.ndarray, block: int,
                params: StructureParams | None = None) -> np.ndarray:
    """int32 label per pixel: the sides of ``lines`` as bits (0 without lines). A cell with fewer than
    ``min_cell_pixels`` known pixels near the hole gets :data:`FREE` (nothing to fill it from)."""
    p = params or StructureParams()
    h, w = shape
    lab = np.zeros((h, w), np.int32)
    for i, ln in enumerate(lines):
        lab |= ln.cell_bit(h, w).astype(np.int32) << i
    if not lines:
        return lab
    near = cv2.distanceTransform((~np.asarray(hole, bool)).astype(np.uint8), cv2.DIST_L2, 5) <= (p.near or 3 * block)
    support = near & np.asarray(known, bool) & ~np.asarray(hole, bool)
    counts = np.bincount(lab[support], minlength=1 << len(lines))
    need = p.min_cell_pixels or block * block
    weak = counts < need
    lab[weak[lab]] = FREE
    return lab


def structure_cells(image: np.ndarray, known: np.ndarray, hole: np.ndarray, block: int,
                    params: StructureParams | None = None) -> tuple[list[Line], np.ndarray | None]:
    """:func:`hole_lines` and, when there are any, their :func:`cell_labels` (else None)."""
    lines = hole_lines(image, known, hole, block, params)
    return lines, (cell_labels(np.shape(hole), lines, known, hole, block, params) if lines else None)


def other_cells(a, b):
    """Where labels ``a`` and ``b`` (numpy arrays or torch tensors, broadcast) name different cells;
    :data:`FREE` on either side matches any."""
    return (a != b) & (a >= 0) & (b >= 0)


def draw_lines(image: np.ndarray, hole: np.ndarray, lines: list[Line]) -> np.ndarray:
    """A picture of the lines: ``image`` with the hole in blue, each line's segments in yellow and its
    extension through the hole in cyan, a hidden corner's borders up to their corner (float RGB)."""
    out = np.array(image, np.float32)
    hole = np.asarray(hole, bool)
    out[hole] = 0.5 * out[hole] + 0.5 * np.array([0.0, 0.0, 1.0], np.float32)
    h, w = hole.shape
    for ln in lines:
        d = np.array([ln.normal[1], -ln.normal[0]])
        c = ln.normal * ln.rho
        a, b = c - 2 * (h + w) * d, c + 2 * (h + w) * d
        ext = np.zeros((h, w), np.uint8)
        cv2.line(ext, (int(round(a[0])), int(round(a[1]))), (int(round(b[0])), int(round(b[1]))), 1, 1)
        ext = (ext > 0) & hole
        if ln.corner is not None:  # (beyond the corner it borders nothing)
            other, other_side = ln.corner[1], ln.corner[2]
            ext &= other.distance(h, w) * other_side >= -1.0
        out[ext] = (0.0, 1.0, 1.0)
        for s in ln.segments:
            p0, p1 = (int(round(s[0])), int(round(s[1]))), (int(round(s[2])), int(round(s[3])))
            cv2.line(out, p0, p1, (1.0, 1.0, 0.0), 1)
    return out
