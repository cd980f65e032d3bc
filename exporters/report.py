"""report: ``report.html`` with its PNGs beside it in ``report/``, readable offline (no script, no
external style sheet or font, every image a local file).

The page is a list of sections (:data:`DEFAULT_SECTIONS`); a section is any object with a ``title``
and ``render(rc: ReportContext) -> str | None`` returning an HTML fragment (None: nothing to show,
the section is left out). Later stages plug in by appending a section or a per-view column
(:class:`StageImageColumn`) and by naming their stage in the report exporter's ``needs`` (only
those stages' folders reach ``ctx.inputs``). Built in:

* summary: the scene (Gaussians, SH degree, cameras) and the export frame (up, units, scale);
* files: what the exporters wrote into the export folder (their ``outputs``), with sizes and each
  exporter's ``description`` (which tools open it). The report's exporter runs after the others
  (``runs_last``) so that their files are there;
* views: per input view the input, the mask (if any: the ``masks`` stage's, else the given one) as an
  overlay, the render of the scene (``renders/<view>.png`` when the renders exporter ran, else
  rendered here), and optional columns that appear when their stage is an input of the export and
  their files exist: ``<remove>/renders/<view>.png`` (after deletion), ``<remove>/holes/<view>.png``
  (hole masks), ``<inpaint>/images/<view>.png`` and ``<refine>/refined/<view>.png`` (refined
  blocks outlined);
* training: ``curve.png``, ``fit.json`` and the held-out renders it lists (and the same of
  ``finetune``, when present);
* speed against error: ``speed_error.png`` of any input stage;
* metrics: the ``evaluate`` stage's ``metrics.json`` (an optional input: present when the run has
  ground truth) as tables: PSNR/SSIM in the ``mask``, ``bbox`` and ``full`` definitions for the final
  scene, the 2D-inpainted views and delete-only, seconds per stage, and per view; the file itself is
  copied beside the report as ``metrics.json``. Any other input stage's ``metrics.json`` is shown as
  key/value rows.
"""

from __future__ import annotations

import html
import json
import math
import re
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol
from urllib.parse import quote

import numpy as np

from sgpor_pipeline.cache import format_size, read_manifest
from sgpor_pipeline.dag import Exporter, StageContext
from sgpor_pipeline.imageio import read_image, read_mask, resize_mask_nearest, write_png
from sgpor_pipeline.scene import Camera

from .gaussians import (
    CAMERAS_STAGE,
    FRAME_FILE,
    POSES_STAGE,
    SCENE_STAGE,
    load_run_cameras,
    load_scene,
    scene_background,
)

REPORT_FILE = "report.html"
REPORT_DIR = "report"
THUMB_WIDTH = 480  # images wider than this are downscaled in the report


def esc(value: Any) -> str:
    """HTML-escape any value's text (quotes included, safe in attributes)."""
    return html.escape(str(value), quote=True)


@dataclass
class ReportContext:
    """What sections may read and where they put their images."""

    inputs: dict[str, Path]  # upstream stage folders (the export stage's ctx.inputs)
    export_dir: Path
    cameras: list[Camera]  # the run's cameras (SfM frame)
    model_loader: Callable[[], Any] | None = None  # the scene's GaussianModel, loaded on first use
    background: list[float] | None = None
    log: Any = None
    _model: Any = None
    _gaussians: Any = None
    _names: set[str] = field(default_factory=set)

    @property
    def report_dir(self) -> Path:
        path = self.export_dir / REPORT_DIR
        path.mkdir(parents=True, exist_ok=True)
        return path

    @property
    def model(self) -> Any:
        if self._model is None and self.model_loader is not None:
            self._model = self.model_loader()
        return self._model

    @property
    def views(self) -> list[Camera]:
        return [c for c in self.cameras if c.image is not None]

    def _unique(self, name: str) -> str:
        stem, _, ext = name.rpartition(".")
        stem = re.sub(r"[^A-Za-z0-9._-]+", "_", stem or "image").strip("._") or "image"
        ext = re.sub(r"[^A-Za-z0-9]+", "", ext or "png") or "png"
        cand, k = f"{stem}.{ext}", 1
        while cand in self._names:
            cand = f"{stem}_{k}.{ext}"
            k += 1
        self._names.add(cand)
        return cand

    def add_image(self, image: Path | np.ndarray, name: str, max_width: int = THUMB_WIDTH) -> str:
        """Put an image (a file, or an RGB/grey array) into ``report/`` as PNG; returns its href."""
        import cv2

        if isinstance(image, Path):
            if image.suffix.lower() == ".png" and max_width <= 0:
                dst = self.report_dir / self._unique(name)
                shutil.copyfile(image, dst)
                return href(dst.relative_to(self.export_dir))
            arr = read_image(image)
        else:
            arr = np.asarray(image)
        if arr.dtype == bool:
            arr = arr.astype(np.float32)
        h, w = arr.shape[:2]
        if max_width > 0 and w > max_width:
            arr = cv2.resize(np.asarray(arr, np.float32), (max_width, max(1, round(h * max_width / w))),
                             interpolation=cv2.INTER_AREA)
        dst = self.report_dir / self._unique(name if name.endswith(".png") else name + ".png")
        write_png(dst, arr)
        return href(dst.relative_to(self.export_dir))


def href(rel: Path | str) -> str:
    """A relative URL for a file path (POSIX separators, percent-encoded)."""
    return quote(Path(rel).as_posix())


class Section(Protocol):
    title: str

    def render(self, rc: ReportContext) -> str | None: ...


def kv_table(rows: Sequence[tuple[Any, Any]]) -> str:
    body = "".join(f"<tr><th>{esc(k)}</th><td>{esc(v)}</td></tr>" for k, v in rows)
    return f"<table class='kv'>{body}</table>"


def flatten_json(data: Any, prefix: str = "", max_list: int = 8) -> list[tuple[str, str]]:
    """(dotted key, short text) rows of a JSON value; long lists are summarised."""
    rows: list[tuple[str, str]] = []
    if isinstance(data, dict):
        for k, v in data.items():
            rows += flatten_json(v, f"{prefix}.{k}" if prefix else str(k), max_list)
    elif isinstance(data, list) and (len(data) > max_list or any(isinstance(v, (dict, list)) for v in data)):
        nums = [v for v in data if isinstance(v, (int, float)) and not isinstance(v, bool)]
        if nums and len(nums) == len(data):
            rows.append((prefix, f"[{len(data)} values, first {_fmt(nums[0])}, last {_fmt(nums[-1])}]"))
        elif len(data) <= max_list:
            for i, v in enumerate(data):
                rows += flatten_json(v, f"{prefix}[{i}]", max_list)
        else:
            rows.append((prefix, f"[{len(data)} items]"))
    else:
        rows.append((prefix or "value", _fmt(data)))
    return rows


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return str(v)


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


# --------------------------------------------------------------------------------------------------
# sections


class SummarySection:
    title = "Scene"

    def render(self, rc: ReportContext) -> str | None:
        rows: list[tuple[str, Any]] = []
        model = rc.model
        if model is not None:
            rows += [("Gaussians", f"{len(model):,}"), ("SH degree", model.max_sh_degree)]
        novel = [c for c in rc.cameras if c.image is None]
        rows += [("input views", len(rc.views)), ("novel cameras", len(novel))]
        frame = _read_json(rc.export_dir / FRAME_FILE)
        if isinstance(frame, dict):
            rows += [("export frame", f"Z up ({frame.get('up_method')}), origin: {frame.get('origin')}"),
                     ("units", frame.get("units")), ("scale", frame.get("scale_source"))]
            ground = frame.get("ground")
            if isinstance(ground, dict) and "fraction" in ground:
                unit = "m" if frame.get("units") == "metres" else "units"
                rows.append(("ground", f"a plane through {100 * ground['fraction']:.0f} % of the "
                                       f"{ground.get('source')}, {ground.get('camera_height', 0.0):.2f} {unit} "
                                       f"below the cameras (median)"))
            elif isinstance(ground, dict):
                rows.append(("ground", f"no plane found: {ground.get('reason')}"))
            if frame.get("units") == "arbitrary":
                rows.append(("note", "no scale was given: distances are in the arbitrary unit of the "
                                     "reconstruction, not metres"))
        return kv_table(rows)


@dataclass
class ViewColumn:
    """One per-view column: ``get(rc, camera)`` returns an image (a file or an array) or None."""

    title: str
    get: Callable[[ReportContext, Camera], Path | np.ndarray | None]
    optional: bool = False  # left out when no view has an image


def _input_image(rc: ReportContext, cam: Camera) -> Path | None:
    path = rc.inputs[CAMERAS_STAGE] / "images" / f"{cam.image}.png" if CAMERAS_STAGE in rc.inputs else None
    return path if path is not None and path.is_file() else None


def _view_mask(rc: ReportContext, cam: Camera) -> np.ndarray | None:
    """The object mask of a view: the ``masks`` stage's (every view), else the given one as the
    ``sfm`` stage undistorted it, else the given one as ingested (``masks/<view>.png`` in each)."""
    path = None
    for stage in ("masks", CAMERAS_STAGE):
        if stage in rc.inputs and (rc.inputs[stage] / "masks" / f"{cam.image}.png").is_file():
            path = rc.inputs[stage] / "masks" / f"{cam.image}.png"
            break
    if path is None and "ingest" in rc.inputs:
        from sgpor_pipeline.views import load_views

        try:
            views = {v.name: v for v in load_views(rc.inputs["ingest"])}
        except (OSError, ValueError, TypeError):
            views = {}
        v = views.get(cam.image or "")
        if v is not None and v.mask is not None:
            path = rc.inputs["ingest"] / v.mask
    if path is None or not path.is_file():
        return None
    return resize_mask_nearest(read_mask(path), cam.width, cam.height)


def mask_overlay(rc: ReportContext, cam: Camera, mask: np.ndarray | None,
                 color: tuple[float, float, float] = (1.0, 0.1, 0.1)) -> np.ndarray | None:
    """The view's input image with ``mask`` tinted and outlined (None when there is no mask)."""
    import cv2

    if mask is None:
        return None
    src = _input_image(rc, cam)
    img = read_image(src) if src is not None else np.zeros((cam.height, cam.width, 3), np.float32)
    if img.shape[:2] != mask.shape:
        mask = resize_mask_nearest(mask, img.shape[1], img.shape[0])
    out = img.copy()
    out[mask] = 0.45 * out[mask] + 0.55 * np.array(color, np.float32)
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, tuple(float(c) for c in color), 1)
    return out


def _mask_overlay(rc: ReportContext, cam: Camera) -> np.ndarray | None:
    return mask_overlay(rc, cam, _view_mask(rc, cam))


def _render(rc: ReportContext, cam: Camera) -> Path | np.ndarray | None:
    from .renders import render_path

    path = render_path(rc.export_dir, cam)
    if path.is_file():
        return path
    if rc.model is None:
        return None
    from sgpor_pipeline.meshing import activated_tensors, render_view

    if rc._gaussians is None:
        rc._gaussians = activated_tensors(rc.model)
    return render_view(rc._gaussians, cam, rc.background, with_depth=False)["rgb"]


@dataclass
class StageImageColumn:
    """An optional per-view column read from a stage folder: ``<stage>/<subdir>/<view>.png``, an
    image, or (``mask=True``) a 0/1 or 0/255 mask shown tinted over the input view."""

    title: str
    stage: str
    subdir: str
    mask: bool = False
    color: tuple[float, float, float] = (1.0, 0.1, 0.1)

    def column(self) -> ViewColumn:
        def get(rc: ReportContext, cam: Camera) -> Path | np.ndarray | None:
            if self.stage not in rc.inputs:
                return None
            path = rc.inputs[self.stage] / self.subdir / f"{cam.image}.png"
            if not path.is_file():
                return None
            if self.mask:
                return mask_overlay(rc, cam, resize_mask_nearest(read_mask(path), cam.width, cam.height), self.color)
            return path

        return ViewColumn(self.title, get, optional=True)


DEFAULT_COLUMNS: list[ViewColumn] = [
    ViewColumn("input", _input_image),
    ViewColumn("mask", _mask_overlay, optional=True),
    ViewColumn("render", _render),
    StageImageColumn("after deletion", "remove", "renders").column(),
    StageImageColumn("hole mask", "remove", "holes", mask=True, color=(0.1, 0.4, 1.0)).column(),
    StageImageColumn("inpainted", "inpaint", "images").column(),
    StageImageColumn("refined blocks", "refine", "refined").column(),
]


@dataclass
class ViewsSection:
    title: str = "Views"
    columns: list[ViewColumn] = field(default_factory=lambda: list(DEFAULT_COLUMNS))

    def render(self, rc: ReportContext) -> str | None:
        views = rc.views
        if not views:
            return None
        cells: list[list[str | None]] = []
        for i, cam in enumerate(views):
            row: list[str | None] = []
            for col in self.columns:
                img = col.get(rc, cam)
                if img is None:
                    row.append(None)
                    continue
                ref = rc.add_image(img, f"{i:03d}_{col.title}_{cam.image}")
                row.append(f"<img src='{esc(ref)}' alt='{esc(col.title)} {esc(cam.image)}' loading='lazy'>")
            cells.append(row)
        shown = [j for j, col in enumerate(self.columns) if not col.optional or any(r[j] for r in cells)]
        head = "<tr><th>view</th>" + "".join(f"<th>{esc(self.columns[j].title)}</th>" for j in shown) + "</tr>"
        sources = mask_sources(rc)
        body = "".join(
            f"<tr><th>{esc(cam.image)}{sources.get(cam.image or '', '')}</th>"
            + "".join(f"<td>{row[j] or '&ndash;'}</td>" for j in shown) + "</tr>"
            for cam, row in zip(views, cells))
        return f"<table class='views'>{head}{body}</table>"


def mask_sources(rc: ReportContext) -> dict[str, str]:
    """Per view, where the ``masks`` stage's mask came from, as a line under the view's name: given,
    propagated (with its confidence), or from the given masks' lifted surface where the selection's
    render lost the object (``masks.lift``). Empty without the stage's ``masks.json``."""
    info = _read_json(rc.inputs["masks"] / "masks.json") if "masks" in rc.inputs else None
    views = info.get("views") if isinstance(info, dict) else None
    if not isinstance(views, dict):
        return {}
    out = {}
    for name, v in views.items():
        if not isinstance(v, dict):
            continue
        what = str(v.get("source", ""))
        if v.get("lifted_added"):
            what += ", lifted (the render lost the object)"
        if what and v.get("confidence") is not None and what != "given":
            what += f", confidence {float(v['confidence']):.2f}"
        if what:
            out[name] = f"<br><span class='meta'>mask: {esc(what)}</span>"
    return out


@dataclass
class TrainingSection:
    title: str = "Training"
    stages: tuple[str, ...] = ("fit", "finetune")

    def render(self, rc: ReportContext) -> str | None:
        parts = []
        for stage in self.stages:
            folder = rc.inputs.get(stage)
            if folder is None:
                continue
            sub = []
            if (folder / "curve.png").is_file():
                ref = rc.add_image(folder / "curve.png", f"{stage}_curve.png", max_width=0)
                sub.append(f"<img class='plot' src='{esc(ref)}' alt='{esc(stage)} training curve'>")
            info = _read_json(folder / f"{stage}.json")
            if info is not None:
                sub.append(kv_table(flatten_json(info)))
                held = [r for r in (info.get("renders") or [] if isinstance(info, dict) else [])
                        if isinstance(r, str) and (folder / r).is_file()][:8]
                if held:
                    refs = [rc.add_image(folder / r, f"{stage}_{Path(r).name}", 640) for r in held]
                    imgs = "".join(f"<figure><img src='{esc(ref)}' alt='{esc(r)}'><figcaption>{esc(r)}</figcaption>"
                                   "</figure>" for ref, r in zip(refs, held))
                    which = "training" if info.get("heldout_is_training") else "held-out"
                    sub.append(f"<p class='meta'>{which} views (render | ground truth):</p>{imgs}")
            if sub:
                parts.append(f"<h3>{esc(stage)}</h3>" + "".join(sub))
        return "".join(parts) or None


@dataclass
class StageFileSection:
    """Shows ``file`` (a PNG, or a JSON as tables) from every input stage folder that has it."""

    title: str
    file: str

    def render(self, rc: ReportContext) -> str | None:
        parts = []
        for stage, folder in sorted(rc.inputs.items()):
            path = folder / self.file
            if not path.is_file():
                continue
            if path.suffix.lower() == ".png":
                ref = rc.add_image(path, f"{stage}_{path.name}", max_width=0)
                parts.append(f"<h3>{esc(stage)}</h3><img class='plot' src='{esc(ref)}' alt='{esc(self.title)}'>")
            elif path.suffix.lower() == ".json":
                data = _read_json(path)
                if data is not None:
                    parts.append(f"<h3>{esc(stage)}</h3>" + kv_table(flatten_json(data)))
        return "".join(parts) or None


#: The results the evaluate stage scores, in the order shown, with what each one is.
METRIC_RESULTS = {
    "final": "the cleaned scene (finetune renders)",
    "inpainted_2d": "the views inpainted in 2D, before re-fitting",
    "delete_only": "object Gaussians deleted, hole left unfilled",
}
METRIC_COLUMNS = [("PSNR mask", "psnr_mask", 2), ("SSIM mask", "ssim_mask", 4), ("PSNR bbox", "psnr_bbox", 2),
                  ("SSIM bbox", "ssim_bbox", 4), ("PSNR full", "psnr_full", 2), ("SSIM full", "ssim_full", 4),
                  ("feat mask", "feat_mask", 4)]
METRICS_FILE = "metrics.json"


def _num(v: Any, digits: int) -> str:
    if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
        return f"{v:.{digits}f}"
    return "&ndash;"  # NaN (e.g. an empty mask) or missing


def metrics_tables(data: dict[str, Any]) -> str:
    """HTML tables of an evaluate ``metrics.json``: means per result, seconds per stage, per view."""
    means = data.get("means") or {}
    names = [n for n in METRIC_RESULTS if n in means] + [n for n in means if n not in METRIC_RESULTS]
    head = "<tr><th>result</th>" + "".join(f"<th>{esc(t)}</th>" for t, _, _ in METRIC_COLUMNS) + "</tr>"
    rows = "".join(
        f"<tr><th title='{esc(METRIC_RESULTS.get(n, ''))}'>{esc(n)}</th>"
        + "".join(f"<td>{_num((means[n] or {}).get(k), d)}</td>" for _, k, d in METRIC_COLUMNS) + "</tr>"
        for n in names)
    parts = [f"<p class='meta'>means over {esc(data.get('views', '?'))} view(s) with ground truth; "
             "<i>mask</i>: object-mask pixels only, <i>bbox</i>: the mask's bounding box, <i>full</i>: the whole "
             "image; " + "; ".join(f"<i>{esc(n)}</i>: {esc(METRIC_RESULTS[n])}" for n in names
                                  if n in METRIC_RESULTS) + "</p>",
             f"<table class='metrics'>{head}{rows}</table>"]
    seconds = data.get("seconds") or {}
    if seconds:
        srows = "".join(f"<tr><th>{esc(k)}</th><td>{_num(v, 1)}</td></tr>" for k, v in seconds.items())
        total = data.get("total_seconds", sum(v for v in seconds.values() if isinstance(v, (int, float))))
        parts.append(f"<table class='kv'><tr><th>stage</th><th>seconds</th></tr>{srows}"
                     f"<tr><th>total</th><td>{_num(total, 1)}</td></tr></table>")
    per_view = data.get("per_view") or {}
    if per_view:
        cols = [(n, k, t, d) for k, t, d in (("psnr_mask", "PSNR mask", 2), ("ssim_mask", "SSIM mask", 4))
                for n in names]
        vhead = "<tr><th>view</th>" + "".join(f"<th>{esc(t)}<br>{esc(n)}</th>" for n, _, t, _ in cols) + "</tr>"
        vrows = "".join(
            f"<tr><th>{esc(view)}</th>"
            + "".join(f"<td>{_num(((res or {}).get(n) or {}).get(k), d)}</td>" for n, k, _, d in cols) + "</tr>"
            for view, res in per_view.items())
        parts.append(f"<details><summary>per view ({len(per_view)})</summary>"
                     f"<table class='metrics'>{vhead}{vrows}</table></details>")
    return "".join(parts)


@dataclass
class MetricsSection:
    """The ``evaluate`` stage's metrics (when the run has it) as tables, and ``metrics.json`` of any
    other input stage as key/value rows."""

    title: str = "Metrics"
    stage: str = "evaluate"

    def render(self, rc: ReportContext) -> str | None:
        parts = []
        for stage, folder in sorted(rc.inputs.items(), key=lambda kv: (kv[0] != self.stage, kv[0])):
            path = folder / METRICS_FILE
            data = _read_json(path) if path.is_file() else None
            if not isinstance(data, dict):
                continue
            if isinstance(data.get("means"), dict):
                if stage == self.stage:  # the file beside the report: what the tables show, all digits
                    shutil.copyfile(path, rc.export_dir / METRICS_FILE)
                    link = f" <a href='{esc(href(METRICS_FILE))}'>{esc(METRICS_FILE)}</a>"
                else:
                    link = ""
                parts.append(f"<h3>{esc(stage)}{link}</h3>" + metrics_tables(data))
            else:
                parts.append(f"<h3>{esc(stage)}</h3>" + kv_table(flatten_json(data)))
        return "".join(parts) or None


@dataclass
class PlaneSection:
    """The inpaint stage's texture of the plane under the object (``plane/``, inpaint.thick_reference =
    plane): the views' colours rectified, and with its hole filled, side by side, and its numbers; with
    inpaint.lift_shadow also the texture as seen and the contact shadow divided out of it; with straight
    edges continued through its hole (inpaint.plane_structure) the picture of those lines."""

    title: str = "The plane under the object, as one texture"

    def render(self, rc: ReportContext) -> str | None:
        folder = rc.inputs.get("inpaint")
        if folder is None or not (folder / "plane" / "filled.png").is_file():
            return None
        figs = []
        for name, caption in (("texture_as_seen.png", "the views' colours, with the object's contact shadow"),
                              ("shading.png", "the contact shadow found (inpaint.lift_shadow; white: none)"),
                              ("texture.png", "the views' colours, rectified (black: its hole; smooth: context no "
                                              "view saw)"),
                              ("structure.png", "the straight edges continued through its hole (yellow: seen, "
                                                "cyan: continued; inpaint.plane_structure)"),
                              ("filled.png", "its hole filled, as every view takes it")):
            path = folder / "plane" / name
            if path.is_file():
                ref = rc.add_image(path, f"plane_{name}", 640)
                figs.append(f"<figure><img src='{esc(ref)}' alt='{esc(caption)}'><figcaption>{esc(caption)}"
                            "</figcaption></figure>")
        info = _read_json(folder / "plane" / "plane.json")
        keys = ("width", "height", "texel", "hole_texels", "under_object_texels", "views_used", "rms_relative",
                "seconds")
        rows = [(k, _fmt(info[k])) for k in keys if k in info] if isinstance(info, dict) else []
        shadow = info.get("shadow") if isinstance(info, dict) else None
        if isinstance(shadow, dict):  # inpaint.lift_shadow: the strength found, or why none
            found = _fmt(shadow["strength"]) if "strength" in shadow else shadow.get("reason", "")
            rows.append(("contact shadow", found))
        structure = info.get("structure") if isinstance(info, dict) else None
        if isinstance(structure, dict):  # inpaint.plane_structure: how many lines were continued
            rows.append(("straight edges continued", _fmt(len(structure.get("lines", [])))))
        table = kv_table(rows) if rows else ""
        return "".join(figs) + table


def _size(path: Path) -> tuple[int, int]:
    """(bytes, files) of a file or of a folder's files."""
    if path.is_file():
        return path.stat().st_size, 1
    files = [f for f in path.rglob("*") if f.is_file()]
    return sum(f.stat().st_size for f in files), len(files)


class FilesSection:
    """The export folder's files, each with its size and what its exporter says it is (which tools
    open it); the report's exporter runs after the others (``runs_last``), so their files are there."""

    title = "Files"

    def render(self, rc: ReportContext) -> str | None:
        from sgpor_pipeline.dag import discover_exporters

        rows = []
        for name, exporter in sorted(discover_exporters().items()):
            if exporter.runs_last:
                continue  # (the report's own files: this page, its images and the metrics it links)
            for out in exporter.outputs:
                path = rc.export_dir / out.rstrip("/")
                if not path.exists():
                    continue
                size, count = _size(path)
                shown = format_size(size, 1000)  # (as the exporters' log lines: MB = 1e6 bytes)
                what = f"{count} files, {shown}" if path.is_dir() else shown
                link = href(out.rstrip("/")) + ("/" if out.endswith("/") else "")
                rows.append(f"<tr><td><a href='{esc(link)}'>{esc(out)}</a></td><td>{esc(what)}</td>"
                            f"<td>{esc(name)}: {esc(exporter.description)}</td></tr>")
        if not rows:
            return None
        return ("<table class='files'><tr><th>file</th><th>size</th><th>exporter: what it is</th></tr>"
                + "".join(rows) + "</table>")


DEFAULT_SECTIONS: list[Any] = [
    SummarySection(),
    FilesSection(),  # (near the top: which file to open in which tool)
    MetricsSection(),
    ViewsSection(),
    PlaneSection(),
    TrainingSection(),
    StageFileSection("Speed against error", "speed_error.png"),
]

_CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',sans-serif;margin:1.5em;color:#222;background:#fafafa}
h1{font-size:1.5em}h2{font-size:1.2em;border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:.5em 0}th,td{border:1px solid #ddd;padding:4px 8px;text-align:left;
vertical-align:top}table.kv th{background:#f0f0f0;font-weight:600}table.views img{max-width:320px;display:block}
img.plot{max-width:100%;border:1px solid #ddd;background:#fff}table.metrics td{text-align:right}
figure{display:inline-block;margin:.3em}
figcaption{font-size:.8em;color:#666}.meta{color:#666;font-size:.9em}
"""


def results_stamp(inputs: dict[str, Path]) -> str:
    """When the newest of the report's inputs was computed (UTC, from their cache manifests), not when the
    page was written: a re-export of the same results gives the same bytes."""
    created = [float((read_manifest(folder) or {}).get("created", 0.0)) for folder in inputs.values()]
    newest = max(created, default=0.0)
    if newest <= 0.0:
        return "results of unknown date"
    return "results of " + time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(newest))


def build_html(rc: ReportContext, sections: Sequence[Any], title: str = "sgpor-pipeline report") -> str:
    """The report page: every section that has something to show, in order."""
    body = []
    toc = []
    for i, sec in enumerate(sections):
        try:
            frag = sec.render(rc)
        except Exception as e:  # one broken optional section must not lose the report
            if rc.log is not None:
                rc.log.warning(f"report: section {sec.title!r} failed: {e}")
            frag = f"<p class='meta'>this section could not be made: {esc(e)}</p>"
        if frag:
            anchor = f"s{i}"
            toc.append(f"<a href='#{anchor}'>{esc(sec.title)}</a>")
            body.append(f"<h2 id='{anchor}'>{esc(sec.title)}</h2>\n{frag}")
    stamp = results_stamp(rc.inputs)
    return ("<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
            f"<meta name='viewport' content='width=device-width, initial-scale=1'><title>{esc(title)}</title>"
            f"<style>{_CSS}</style></head><body><h1>{esc(title)}</h1>"
            f"<p class='meta'>{esc(stamp)} &middot; " + " &middot; ".join(toc) + "</p>\n"
            + "\n".join(body) + "\n</body></html>\n")


def write_report(rc: ReportContext, sections: Sequence[Any] | None = None,
                 title: str = "sgpor-pipeline report") -> Path:
    """Write ``report.html`` (and its images under ``report/``) into ``rc.export_dir``."""
    page = build_html(rc, DEFAULT_SECTIONS if sections is None else sections, title)
    path = rc.export_dir / REPORT_FILE
    path.write_text(page, encoding="utf-8")
    return path


#: Stages whose folders the report shows when they are upstream of the scene anyway (reading them
#: then adds no work to a run): the removal chain, once the cleaned scene comes from ``finetune``.
REPORT_STAGES = ("fit", "masks", "remove", "inpaint", "refine") if SCENE_STAGE == "finetune" else ()


class ReportExporter(Exporter):
    name = "report"
    VERSION = 7  # 2: evaluate's metrics as tables (and metrics.json beside the report); 3: the plane texture;
    # 4: its contact shadow (inpaint.lift_shadow); 5: its straight edges (inpaint.plane_structure); 6: dated by
    # its results, not its writing; 7: the export folder's files (it runs after the other exporters)
    needs = ("ingest", CAMERAS_STAGE, POSES_STAGE, SCENE_STAGE, *REPORT_STAGES)
    optional_needs = ("evaluate",)  # when the run has ground truth; its key then enters export's key
    description = ("report.html (+ report/ PNGs): inputs, masks, renders, training curve, metrics (with ground "
                   "truth), the export's files; offline")
    outputs = (REPORT_FILE, f"{REPORT_DIR}/", METRICS_FILE)
    runs_last = True  # (its Files section lists what the other exporters wrote)

    def export(self, ctx: StageContext, out_dir: Path) -> None:
        t0 = time.perf_counter()
        rc = ReportContext(inputs=dict(ctx.inputs), export_dir=out_dir, cameras=load_run_cameras(ctx),
                           model_loader=lambda: load_scene(ctx), background=scene_background(ctx), log=ctx.log)
        path = write_report(rc)
        n = len(list(rc.report_dir.iterdir()))
        ctx.log.info(f"report: {path.name} with {n} images in {REPORT_DIR}/ in {time.perf_counter() - t0:.1f} s")
