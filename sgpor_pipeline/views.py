"""The ingested views: what the ingest stage writes and every later stage reads."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from .imageio import read_image, read_mask

VIEWS_FILE = "views.json"


@dataclass
class View:
    name: str  # the photo's base name without extension; the identity used everywhere
    image: str  # relative path of the normalised RGB PNG inside the ingest folder
    mask: str | None  # relative path of the 0/1 mask PNG, None when the user gave no mask
    width: int
    height: int
    source: str  # the original file name
    source_width: int
    source_height: int
    # where the photo was taken (EXIF GPS): [latitude, longitude, altitude in metres or None]; None when
    # it carries none (or was ingested by a version that did not read it)
    gps: list | None = None


def save_views(folder: Path, views: list[View]) -> None:
    (Path(folder) / VIEWS_FILE).write_text(json.dumps([asdict(v) for v in views], indent=1))


def load_views(folder: Path) -> list[View]:
    return [View(**d) for d in json.loads((Path(folder) / VIEWS_FILE).read_text())]


def load_view_image(folder: Path, view: View) -> np.ndarray:
    return read_image(Path(folder) / view.image)


def load_view_mask(folder: Path, view: View) -> np.ndarray | None:
    return None if view.mask is None else read_mask(Path(folder) / view.mask)
