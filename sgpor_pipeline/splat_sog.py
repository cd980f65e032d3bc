"""Gaussians read from PlayCanvas's SOG (Spatially Ordered Gaussians): what SuperSplat publishes
and PlayCanvas's ``splat-transform`` writes for the web.

A SOG is a ``meta.json`` beside lossless WebP images, either bundled in a ``.sog`` file (a zip) or
unbundled in a folder (give its ``meta.json``). Gaussian ``i`` is pixel ``(i % width, i // width)``
of each image, channels R, G, B, A:

- means: ``means_l`` (low byte) and ``means_u`` (high byte) give 16 bits per axis, a lerp between
  the axis's ``mins`` and ``maxs`` of ``sign(x) ln(|x| + 1)``, undone on reading;
- quats: the three smallest components of the unit quaternion (w, x, y, z) as bytes of
  ``sqrt2 * c`` in [-1, 1]; A = 252 + the index of the largest, rebuilt as positive;
- version 2 (``"version": 2``): scales and colours are bytes indexing 256-entry codebooks (log-scales
  per axis; the SH DC colour in RGB, the opacity as A / 255 after the sigmoid); the higher SH bands
  are a palette (``shN_centroids``: 64 entries per row, ``coeffs`` pixels each, bytes indexing the
  ``shN`` codebook) and a 16-bit palette label per Gaussian (``shN_labels``: R + 256 G);
- version 1 (no ``version``): the same images, but scales, colours (A: the opacity logit) and SH are
  bytes lerped between ``mins`` and ``maxs``.

Positions are in the frame of the 3DGS PLY the SOG was made from (splat-transform reads a SOG into
the PLY's frame), so the file is read as stored. Decoding follows the reader of splat-transform 2.7.1;
other versions are refused with a clear error.
"""

from __future__ import annotations

import json
import zipfile
from collections.abc import Callable
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

SOG_SUFFIX = ".sog"
SOG_META = "meta.json"
SH_COEFFS_PER_BAND_COUNT = (0, 3, 8, 15)  # SH coefficients above the DC term, by the number of bands
V1_SH_BANDS_BY_WIDTH = {192: 1, 512: 2, 960: 3}  # version 1: palette width 64 * coeffs
QUAT_TAG_BASE = 252  # A byte of a quaternion pixel: 252 + the index of its largest component


def is_sog(path: str | Path) -> bool:
    """Whether ``path`` names a SOG: a ``.sog`` bundle or an unbundled SOG's ``meta.json``."""
    p = Path(path)
    return p.suffix.lower() == SOG_SUFFIX or p.name.lower() == SOG_META


def _decode_webp(data: bytes, where: str) -> np.ndarray:
    """An image's pixels as [H, W, 4] uint8 RGBA (OpenCV decodes to BGR(A); grey is widened)."""
    import cv2

    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.dtype != np.uint8:
        raise ValueError(f"{where}: not an 8-bit image OpenCV can decode (a SOG holds lossless WebP)")
    if img.ndim == 2:
        img = img[:, :, None].repeat(3, axis=2)
    rgb = img[:, :, 2::-1]
    alpha = img[:, :, 3:4] if img.shape[2] == 4 else np.full(img.shape[:2] + (1,), 255, np.uint8)
    return np.concatenate([rgb, alpha], axis=2)


def _reader(path: Path) -> tuple[dict[str, Any], Callable[[str], np.ndarray]]:
    """The parsed meta.json and a function from an image name (as meta.json gives it) to its RGBA pixels."""
    if path.suffix.lower() == SOG_SUFFIX:
        try:
            bundle = zipfile.ZipFile(path)
        except (zipfile.BadZipFile, OSError) as e:
            raise ValueError(f"{path}: not a SOG bundle (a zip holding meta.json and WebP images): {e}") from None
        names = {PurePosixPath(n).name.lower(): n for n in bundle.namelist()}
        if SOG_META not in names:
            raise ValueError(f"{path}: the bundle holds no {SOG_META}")
        base = PurePosixPath(names[SOG_META]).parent

        def read_bytes(name: str) -> bytes:
            member = str(base / name) if str(base) != "." else name
            try:
                return bundle.read(member)
            except KeyError:
                raise ValueError(f"{path}: {name}, named in {SOG_META}, is not in the bundle") from None

        meta_bytes = bundle.read(names[SOG_META])
    else:
        def read_bytes(name: str) -> bytes:
            try:
                return (path.parent / name).read_bytes()
            except OSError:
                raise ValueError(f"{path}: {name}, named there, is not beside it") from None

        meta_bytes = path.read_bytes()
    try:
        meta = json.loads(meta_bytes)
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: {SOG_META} is not JSON: {e}") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: {SOG_META} is not a JSON object")
    return meta, lambda name: _decode_webp(read_bytes(name), f"{path}: {name}")


def _pixels(image: np.ndarray, count: int, what: str, path: Path) -> np.ndarray:
    """The first ``count`` pixels of an image in Gaussian order, [count, 4] uint8."""
    flat = image.reshape(-1, 4)
    if len(flat) < count:
        raise ValueError(f"{path}: the {what} image has {len(flat)} pixels for {count} Gaussians")
    return flat[:count]


def _inv_log_transform(v: np.ndarray) -> np.ndarray:
    """The inverse of ``sign(x) ln(|x| + 1)``."""
    return np.sign(v) * np.expm1(np.abs(v))


def _means(px_lo: np.ndarray, px_hi: np.ndarray, mins: Any, maxs: Any) -> np.ndarray:
    u16 = px_lo[:, :3].astype(np.float64) + 256.0 * px_hi[:, :3].astype(np.float64)
    lo, hi = np.asarray(mins, np.float64), np.asarray(maxs, np.float64)
    span = np.where(hi - lo != 0, hi - lo, 1.0)  # as the reference reader: a flat axis spans 1
    return _inv_log_transform(lo + span * (u16 / 65535.0))


def _quats(px: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z); an invalid tag gives the identity, as the reference reader."""
    n = len(px)
    tag = px[:, 3].astype(np.int64) - QUAT_TAG_BASE
    valid = (tag >= 0) & (tag <= 3)
    largest = np.where(valid, tag, 0)
    small = (px[:, :3].astype(np.float64) / 255.0 * 2.0 - 1.0) / np.sqrt(2.0)
    q = np.zeros((n, 4))
    others = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[largest]  # [n, 3] slots of the small three
    np.put_along_axis(q, others, small, axis=1)
    q[np.arange(n), largest] = np.sqrt(np.maximum(0.0, 1.0 - (small**2).sum(axis=1)))
    q[~valid] = (1.0, 0.0, 0.0, 0.0)
    return q


def _codebook(meta: dict[str, Any], key: str, path: Path) -> np.ndarray:
    book = np.asarray(meta[key].get("codebook", []), np.float64)
    if book.shape != (256,):
        raise ValueError(f"{path}: {SOG_META} {key}.codebook has {book.size} entries, not 256")
    return book


def read_sog(path: str | Path) -> dict[str, Any]:
    """A SOG's Gaussians (``.sog`` bundle or unbundled ``meta.json``), as stored.

    Returns ``means`` [N,3], ``quats`` [N,4] (w, x, y, z, unit), ``scales`` [N,3] (log), ``opacities``
    [N] (after the sigmoid), ``sh0`` [N,1,3], ``shN`` [N,K-1,3] (the 3DGS SH basis, float64) and
    ``sh_degree``. Raises ValueError naming the file for a file that is not a SOG this reader knows.
    """
    path = Path(path)
    meta, image = _reader(path)
    version = meta.get("version")
    if version not in (None, 1, 2):
        raise ValueError(f"{path}: SOG version {version!r}; this reader knows versions 1 and 2 "
                         f"(splat-transform 2.7.1 writes 2)")
    try:
        return _decode(path, meta, image, 2 if version == 2 else 1)
    except (KeyError, TypeError, IndexError) as e:
        raise ValueError(f"{path}: {SOG_META} lacks or mis-states {e} for a version "
                         f"{2 if version == 2 else 1} SOG") from None


def _decode(path: Path, meta: dict[str, Any], image: Callable[[str], np.ndarray], version: int) -> dict[str, Any]:
    count = int(meta["count"]) if version == 2 else int(meta["means"]["shape"][0])
    if count < 0:
        raise ValueError(f"{path}: a count of {count} Gaussians")

    def pixels(key: str, which: int = 0) -> np.ndarray:
        return _pixels(image(meta[key]["files"][which]), count, f"{key} ({meta[key]['files'][which]})", path)

    means = _means(pixels("means", 0), pixels("means", 1), meta["means"]["mins"], meta["means"]["maxs"])
    quats = _quats(pixels("quats"))
    scale_px, colour_px = pixels("scales")[:, :3], pixels("sh0")
    if version == 2:
        scales = _codebook(meta, "scales", path)[scale_px]
        sh0 = _codebook(meta, "sh0", path)[colour_px[:, :3]]
        opacities = colour_px[:, 3] / 255.0
    else:
        def lerp(px: np.ndarray, mins: Any, maxs: Any) -> np.ndarray:
            lo, hi = np.asarray(mins, np.float64), np.asarray(maxs, np.float64)
            return lo + (hi - lo) * (px / 255.0)

        scales = lerp(scale_px, meta["scales"]["mins"], meta["scales"]["maxs"])
        rgba = lerp(colour_px, meta["sh0"]["mins"][:4], meta["sh0"]["maxs"][:4])
        sh0, opacities = rgba[:, :3], 1.0 / (1.0 + np.exp(-rgba[:, 3]))
    bands, shN = _higher_bands(path, meta, image, count, version)
    return {"means": means, "quats": quats, "scales": scales, "opacities": opacities,
            "sh0": sh0.reshape(count, 1, 3), "shN": shN, "sh_degree": bands}


def _higher_bands(path: Path, meta: dict[str, Any], image: Callable[[str], np.ndarray], count: int,
                  version: int) -> tuple[int, np.ndarray]:
    """The SH bands above DC from the palette: (degree, [N, coeffs, 3]); none without ``shN``."""
    sh = meta.get("shN")
    if not sh:
        return 0, np.zeros((count, 0, 3))
    centroids, labels_img = image(sh["files"][0]), image(sh["files"][1])
    height, width = centroids.shape[:2]
    if version == 2:
        bands = int(sh["bands"])
        if bands not in (1, 2, 3):
            raise ValueError(f"{path}: shN.bands = {bands}; SOG stores 1 to 3")
        coeffs = SH_COEFFS_PER_BAND_COUNT[bands]
        if width != 64 * coeffs:
            raise ValueError(f"{path}: the shN palette is {width} px wide, not 64 x {coeffs} for {bands} bands")
        palette_size, book = int(sh["count"]), _codebook(meta, "shN", path)
    else:
        if width not in V1_SH_BANDS_BY_WIDTH:
            raise ValueError(f"{path}: the shN palette is {width} px wide, none of 192, 512, 960 (1-3 bands)")
        bands = V1_SH_BANDS_BY_WIDTH[width]
        coeffs = SH_COEFFS_PER_BAND_COUNT[bands]
        palette_size = (width // coeffs) * height
        lo, hi = float(sh["mins"]), float(sh["maxs"])
        book = lo + (hi - lo) * (np.arange(256) / 255.0)
    labels_px = _pixels(labels_img, count, f"shN labels ({sh['files'][1]})", path)
    labels = labels_px[:, 0].astype(np.int64) + 256 * labels_px[:, 1].astype(np.int64)
    # palette entry e, coefficient j: pixel ((e % 64) * coeffs + j, e // 64); RGB = the three channels
    entries = np.arange(min(palette_size, 64 * height))
    cols = (entries % 64)[:, None] * coeffs + np.arange(coeffs)[None, :]
    palette = book[centroids[(entries // 64)[:, None], cols, :3]]  # [entries, coeffs, 3]
    shN = np.zeros((count, coeffs, 3))
    known = labels < len(entries)  # the reference reader leaves a label past the palette at zero
    shN[known] = palette[labels[known]]
    return bands, shN
