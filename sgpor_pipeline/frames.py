"""Photos from a video: the sharpest frame of each of ``count`` equal stretches of the video.
(Likewise from a folder with too many photos: :func:`select_photos`.)

A phone video walked around the object is the quickest capture, but its frames are many, nearly
alike and often motion-blurred. SfM and the fit want a few dozen sharp photos spread over the walk:
the video is cut into ``count`` stretches of equal length, and from each the frame with the most
detail (variance of the Laplacian of its grey image, the usual blur measure) is written as a photo.
Frames are named after their index in the video (``frame_00123.jpg``), so a mask drawn on one
(``frame_00123.png`` in a masks folder) keeps its name when the frames are extracted again.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sgpor_pipeline.errors import PipelineError
from sgpor_pipeline.imageio import UnreadableImageError, list_images, read_rgb8, target_size, write_bgr

VIDEO_EXTENSIONS = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm", ".mts", ".3gp")
CONVERT = "convert it to MP4 (H.264), e.g. ffmpeg -i IN -c:v libx264 out.mp4"


@dataclass
class FrameParams:
    """How :func:`extract_frames` picks and writes frames."""

    count: int = 40  # photos to write: one per equal stretch of the video
    # frames looked at per stretch (evenly spaced; the others are skipped undecoded where the codec
    # allows): enough to find a sharp one, without converting every frame of a long video
    candidates: int = 8
    max_size: int = 1600  # longest side of the written photos in pixels (0 = as in the video)
    sharpness_size: int = 480  # the blur measure is taken on the frame shrunk to this longest side
    format: str = "jpg"  # "jpg" (quality 95) or "png"


def sharpness(frame: np.ndarray, size: int = 480, rgb: bool = False) -> float:
    """Variance of the Laplacian of the frame's grey image shrunk to ``size`` px (higher = sharper).
    A colour frame is BGR as OpenCV decodes video, or RGB with ``rgb``."""
    if frame.ndim == 3:
        grey = cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY if rgb else cv2.COLOR_BGR2GRAY)
    else:
        grey = frame
    scale = size / max(grey.shape)
    if scale < 1:
        grey = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def is_video(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in VIDEO_EXTENSIONS


def _no_progress(iterable: Iterable, **_: Any) -> Iterable:
    return iterable


def _looks(total: int, count: int, candidates: int) -> dict[int, int]:
    """The items to look at among ``total`` in order, cut into ``count`` equal stretches: up to
    ``candidates`` evenly spaced in each. Item index -> stretch."""
    count = min(count, total)
    bounds = np.linspace(0, total, count + 1).round().astype(int)
    looks: dict[int, int] = {}
    for s in range(count):
        lo, hi = int(bounds[s]), max(int(bounds[s + 1]), int(bounds[s]) + 1)
        for i in np.unique(np.linspace(lo, hi - 1, min(candidates, hi - lo)).round().astype(int)):
            looks[int(i)] = s
    return looks


def _sharpest(scored: Iterable[tuple[int, float, Any]]) -> list[Any]:
    """From (stretch, sharpness, item) triples, the sharpest item of each stretch, in stretch order
    (the first of equals)."""
    best: dict[int, tuple[float, Any]] = {}
    for s, score, item in scored:
        if s not in best or score > best[s][0]:
            best[s] = (score, item)
    return [best[s][1] for s in sorted(best)]


def _check(p: FrameParams) -> None:
    if p.count < 3 or p.candidates < 1 or p.max_size < 0 or p.format not in ("jpg", "png"):
        raise PipelineError(f"frames: need count >= 3, candidates >= 1, max_size >= 0 and format jpg or png "
                            f"(got {p.count}, {p.candidates}, {p.max_size}, {p.format!r})",
                            fix="e.g. --count 40 (SfM needs at least 3 photos; 30-60 cover a walk around)")


def select_photos(folder: Path, out_dir: Path, params: FrameParams | None = None,
                  progress: Callable[..., Iterable] | None = None) -> list[Path]:
    """Too many photos (a burst, a photo every step): cut the folder's photos, in name order, into
    ``params.count`` stretches and copy the sharpest of each into ``out_dir`` unchanged (name, EXIF
    and GPS kept, so masks named after them still match). Returns the copies in name order."""
    import shutil

    p = params or FrameParams()
    _check(p)
    photos = list_images(folder)
    if len(photos) < 3:
        raise PipelineError(f"{len(photos)} photo(s) here; at least 3 are needed", path=folder,
                            fix="point at the folder that holds the photos")
    looks = _looks(len(photos), p.count, p.candidates)

    def scored() -> Iterable[tuple[int, float, Path]]:
        for i in (progress or _no_progress)(sorted(looks), total=len(looks), desc="photos"):
            try:
                yield looks[i], sharpness(read_rgb8(photos[i]), p.sharpness_size, rgb=True), photos[i]
            except UnreadableImageError:
                continue  # (ingest names unreadable files; here they are only not chosen)

    chosen = _sharpest(scored())
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    return [Path(shutil.copy2(photo, out_dir / photo.name)) for photo in chosen]


def extract_frames(video: Path, out_dir: Path, params: FrameParams | None = None,
                   progress: Callable[..., Iterable] | None = None) -> list[Path]:
    """Write the sharpest frame of each of ``params.count`` equal stretches of ``video`` into
    ``out_dir`` and return their paths in video order."""
    p = params or FrameParams()
    _check(p)
    if not Path(video).is_file():
        raise PipelineError("video not found", path=video, fix="check the path")
    cap = cv2.VideoCapture(str(video))
    if not cap.isOpened():
        if not str(Path(video).resolve()).isascii():  # OpenCV's video reader takes narrow paths (Windows: ANSI)
            raise PipelineError("cannot open this video: unknown format, damaged file, or its path's non-ASCII "
                                "characters (OpenCV's video reader cannot open those on Windows)", path=video,
                                fix="move or rename it to a path of plain ASCII characters; if that fails, "
                                    + CONVERT)
        raise PipelineError("cannot open this video (unknown format or damaged file)", path=video, fix=CONVERT)
    try:
        total = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        if total <= 0:
            raise PipelineError("the video reports no frame count", path=video, fix=CONVERT)
        looks = _looks(total, p.count, p.candidates)

        def scored() -> Iterable[tuple[int, float, tuple[int, np.ndarray]]]:
            last = max(looks)
            for index in (progress or _no_progress)(range(last + 1), total=last + 1, desc="frames"):
                if index not in looks:
                    if not cap.grab():
                        return
                    continue
                ok, frame = cap.read()
                if not ok:
                    return
                yield looks[index], sharpness(frame, p.sharpness_size), (index, frame)

        chosen = _sharpest(scored())
    finally:
        cap.release()
    if len(chosen) < 3:
        raise PipelineError(f"only {len(chosen)} frame(s) could be decoded (of {total} the video reports)",
                            path=video, fix=CONVERT)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    digits = max(5, len(str(total)))  # (zero-padded: file-name order is video order, for sequential matching)
    for index, frame in chosen:
        h, w = frame.shape[:2]
        size = target_size(w, h, p.max_size)
        if size != (w, h):
            frame = cv2.resize(frame, size, interpolation=cv2.INTER_AREA)
        path = out_dir / f"frame_{index:0{digits}d}.{p.format}"
        args = [cv2.IMWRITE_JPEG_QUALITY, 95] if p.format == "jpg" else []
        try:
            write_bgr(path, frame, args)
        except OSError as e:
            raise PipelineError(f"cannot write a frame ({e})", path=path,
                                fix="check the folder's permissions and free space") from e
        written.append(path)
    return written
