"""Gaussians: ``scene.ply`` (INRIA 3DGS layout, read by SuperSplat and most splat viewers) and
``scene.splat`` (antimatter15's 32-byte records), both in the export frame (Z up, metres when a
scale is known; see :mod:`sgpor_pipeline.orientation`), plus ``export_frame.json`` with the similarity
from the SfM frame (the frame of ``cameras/`` and of the stage cache) to the export frame; ``scene.glb``
(glTF ``KHR_gaussian_splatting``, with the cameras) and ``scene.spz`` (Niantic's compressed format),
both in that frame turned to +Y up, as their formats define.

This module is also the one place that says where the exporters read the scene from
(:data:`SCENE_STAGE`), and holds the writers of the removed object's own asset
(:func:`write_object_assets`), which the ``remove`` stage or a future ``object`` exporter calls.

A user can bring Gaussians from another trainer: :func:`sgpor_pipeline.gaussians.ply.read_ply`
reads any INRIA-layout PLY (SH degree 0..3), and what it reads writes back bit-exactly.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from sgpor_pipeline.dag import Exporter, StageContext
from sgpor_pipeline.orientation import ExportFrame, FrameSettings, compute_export_frame, transform_model
from sgpor_pipeline.scene import Camera, load_cameras
from sgpor_pipeline.sfm import given_frame
from sgpor_pipeline.views import VIEWS_FILE, load_views

#: The stage whose cache folder holds the scene's Gaussians (``gaussians.ply``) that every exporter
#: reads. ``finetune`` (the cleaned scene) replaces ``fit`` here once it exists.
SCENE_STAGE = "finetune"
#: File name of the Gaussians in the :data:`SCENE_STAGE` folder (INRIA 3DGS PLY layout).
SCENE_FILE = "gaussians.ply"
#: The stage whose folder holds ``cameras.json`` and ``images/<view>.png``.
CAMERAS_STAGE = "sfm"
#: The stage whose ``cameras.json`` holds the cameras the Gaussians were fitted with (the training
#: views' poses refined, ``fit.pose_refine``); the exporters read the run's cameras from there.
POSES_STAGE = "fit"
FRAME_FILE = "export_frame.json"
#: The stage whose ``views.json`` holds the photos' GPS positions (the export frame's metric scale); an
#: optional input of every exporter that writes in the export frame.
GPS_STAGE = "ingest"

log = logging.getLogger(__name__)


def scene_path(ctx: StageContext) -> Path:
    return ctx.inputs[SCENE_STAGE] / SCENE_FILE


def load_scene(ctx: StageContext) -> Any:
    """The scene's GaussianModel in the SfM frame."""
    from sgpor_pipeline.gaussians.ply import read_ply

    return read_ply(scene_path(ctx))


def load_run_cameras(ctx: StageContext) -> list[Camera]:
    """All cameras of the run (registered views with ``image`` set, novel cameras with None), SfM frame,
    with the poses the Gaussians were fitted with."""
    from sgpor_pipeline.stages.fit import run_cameras_file

    sfm_dir = ctx.inputs[CAMERAS_STAGE]
    if POSES_STAGE not in ctx.inputs:  # (export_external: the cameras given with the Gaussians)
        return load_cameras(sfm_dir / "cameras.json")
    return load_cameras(run_cameras_file(ctx.inputs[POSES_STAGE], sfm_dir))


def registered(cameras: list[Camera]) -> list[Camera]:
    return [c for c in cameras if c.image is not None]


def camera_clip(cameras: list[Camera]) -> tuple[float, float]:
    """(near, far) clipping distances for the exported cameras: 0.005 and 1000 x the scene's radius as the
    registered ones (else all) see it, or, for a degenerate rig, as their centres spread."""
    from sgpor_pipeline.orientation import scene_center_radius

    try:
        _, r = scene_center_radius(registered(cameras) or cameras)
    except Exception:  # degenerate rigs: a generous range
        r = float(np.ptp([c.center for c in cameras], axis=0).max()) if len(cameras) > 1 else 1.0
    return max(1e-4, 0.005 * r), 1000.0 * r


def scene_background(ctx: StageContext) -> list[float] | None:
    """The background colour the scene was fitted with (``fit.json`` "background"), if recorded."""
    path = ctx.inputs.get("fit", ctx.inputs[SCENE_STAGE]) / "fit.json"
    try:
        bg = json.loads(path.read_text()).get("background")
    except (OSError, ValueError, AttributeError):
        return None
    if isinstance(bg, (list, tuple)) and len(bg) == 3 and all(isinstance(v, (int, float)) for v in bg):
        return [float(v) for v in bg]
    return None


def export_frame(ctx: StageContext, model: Any, cameras: list[Camera], out_dir: Path | None = None) -> ExportFrame:
    """The export frame of this run: found, written to ``export_frame.json`` and logged by the first
    exporter that asks; the others read it back (the ground plane's search and the GPS fit run once)."""
    import torch

    if out_dir is not None and (out_dir / FRAME_FILE).is_file():
        return ExportFrame.from_dict(json.loads((out_dir / FRAME_FILE).read_text()))
    settings = FrameSettings.from_params(ctx.params)
    with torch.no_grad():
        opac = model.opacities_activated().numpy()
    frame = compute_export_frame(registered(cameras) or cameras, settings, model.numpy()["means"], opac,
                                 photo_gps(ctx), sfm_points(ctx), given_frame(ctx.inputs[CAMERAS_STAGE]))
    if out_dir is not None:
        (out_dir / FRAME_FILE).write_text(json.dumps(frame.to_dict(), indent=1))
        ctx.log.info(frame.describe())
        if not frame.metric:
            ctx.log.warning("export: no scale given, the exported scene is in arbitrary units (recorded as "
                            "sgpor:units = 'arbitrary' in the USD and in export_frame.json)")
    return frame


def sfm_points(ctx: StageContext) -> np.ndarray | None:
    """The SfM points (``points.npz`` of the :data:`CAMERAS_STAGE`), or None where the run has none."""
    from sgpor_pipeline.sfm import POINTS_FILE

    path = Path(ctx.inputs[CAMERAS_STAGE]) / POINTS_FILE
    if not path.is_file():
        return None
    try:
        with np.load(path) as data:
            return np.asarray(data["xyz"], np.float64)
    except (OSError, ValueError, KeyError):
        return None


def scene_radius(ctx: StageContext, model: Any, cameras: list[Camera]) -> float:
    """The scene's size for meshing: the registered cameras' median distance to the middle of the scene,
    found with the SfM points, else the model's opaque Gaussians
    (:func:`sgpor_pipeline.orientation.scene_center_radius`)."""
    import torch

    from sgpor_pipeline.orientation import scene_center_radius, surface_points

    with torch.no_grad():
        opacities = model.opacities_activated().numpy()
    points, _ = surface_points(sfm_points(ctx), model.numpy()["means"], opacities)
    return scene_center_radius(registered(cameras) or cameras, points)[1]


def photo_gps(ctx: StageContext) -> dict[str, list] | None:
    """The photos' EXIF GPS positions as the ingest stage read them (view name -> [latitude, longitude,
    altitude]), or None when the run has no ingest stage (Gaussians from elsewhere) or no photo has one."""
    folder = ctx.inputs.get(GPS_STAGE)
    if folder is None or not (Path(folder) / VIEWS_FILE).is_file():
        return None
    gps = {v.name: v.gps for v in load_views(Path(folder)) if v.gps is not None}
    return gps or None


def scene_in_export_frame(ctx: StageContext, out_dir: Path) -> tuple[Any, ExportFrame, list[Camera]]:
    """(GaussianModel in the export frame, the frame, the run's cameras in the SfM frame)."""
    model = load_scene(ctx)
    cameras = load_run_cameras(ctx)
    frame = export_frame(ctx, model, cameras, out_dir)
    return transform_model(model, frame.transform), frame, cameras


def _mb(path: Path) -> str:
    return f"{path.stat().st_size / 1e6:.1f} MB"


class SceneFileExporter(Exporter):
    """An exporter of the scene's Gaussians in the export frame: it reads the cameras, the fit's poses,
    the scene, and the photos' GPS where the run has them (the export frame's scale)."""

    needs = (CAMERAS_STAGE, POSES_STAGE, SCENE_STAGE)
    optional_needs = (GPS_STAGE,)


class PlyExporter(SceneFileExporter):
    name = "ply"
    VERSION = 1
    description = ("the Gaussians as scene.ply (INRIA 3DGS layout, export frame: SuperSplat and most splat "
                   "viewers) and export_frame.json (the similarity from the SfM frame)")
    outputs = ("scene.ply", "export_frame.json")

    def export(self, ctx: StageContext, out_dir: Path) -> None:
        from sgpor_pipeline.gaussians.ply import write_ply

        t0 = time.perf_counter()
        model, _, _ = scene_in_export_frame(ctx, out_dir)
        path = write_ply(out_dir / "scene.ply", model)
        ctx.log.info(f"ply: {len(model)} Gaussians -> {path.name} ({_mb(path)}) in {time.perf_counter() - t0:.1f} s")


class SplatExporter(SceneFileExporter):
    name = "splat"
    VERSION = 1
    description = "the Gaussians as scene.splat (antimatter15's web viewers; export frame, DC colour only)"
    outputs = ("scene.splat",)

    def export(self, ctx: StageContext, out_dir: Path) -> None:
        from sgpor_pipeline.splat_io import write_splat

        t0 = time.perf_counter()
        model, _, _ = scene_in_export_frame(ctx, out_dir)
        path = write_splat(out_dir / "scene.splat", model)
        ctx.log.info(f"splat: {len(model)} Gaussians -> {path.name} ({_mb(path)}) in "
                     f"{time.perf_counter() - t0:.1f} s")


def scene_y_up(ctx: StageContext, out_dir: Path) -> tuple[Any, ExportFrame, list[Camera]]:
    """(GaussianModel, the export frame, the run's cameras: registered then novel) in the export frame
    turned so that its +Z (up) is +Y (:data:`~sgpor_pipeline.orientation.GLTF_FROM_ZUP`), the SH
    rotated with it: glTF's frame and SPZ's (RUB: x right, y up, z back)."""
    from sgpor_pipeline.orientation import GLTF_FROM_ZUP, Similarity

    model, frame, cameras = scene_in_export_frame(ctx, out_dir)
    y_up = Similarity(1.0, GLTF_FROM_ZUP)
    ordered = registered(cameras) + [c for c in cameras if c.image is None]
    cams = [y_up.camera(frame.transform.camera(c)) for c in ordered]
    return transform_model(model, y_up), frame, cams


class GltfExporter(SceneFileExporter):
    """``scene.glb``: the Gaussians as glTF's ``KHR_gaussian_splatting`` point primitive (every SH degree
    the model has, :mod:`sgpor_pipeline.splat_gltf`) and the run's cameras as glTF cameras, in glTF's
    frame: the export frame rotated so that its +Z (up) is glTF's +Y (:data:`GLTF_FROM_ZUP`), SH rotated
    with it; same units as the export frame."""

    name = "gltf"
    VERSION = 1
    description = ("the Gaussians as scene.glb (glTF KHR_gaussian_splatting: Babylon.js, PlayCanvas, CesiumJS; "
                   "Y up, full SH) with the cameras")
    outputs = ("scene.glb",)

    def export(self, ctx: StageContext, out_dir: Path) -> None:
        from sgpor_pipeline.splat_gltf import write_splat_glb

        t0 = time.perf_counter()
        model, frame, cams = scene_y_up(ctx, out_dir)
        path = write_splat_glb(out_dir / "scene.glb", model, cams, znear=camera_clip(cams)[0],
                               extras={"sgpor_units": frame.units, "sgpor_up": "+Y (export frame's +Z)"})
        ctx.log.info(f"gltf: {len(model)} Gaussians (SH degree {model.max_sh_degree}), {len(cams)} cameras -> "
                     f"{path.name} ({_mb(path)}) in {time.perf_counter() - t0:.1f} s")


class SpzExporter(SceneFileExporter):
    """``scene.spz``: the Gaussians in Niantic's compressed ``.spz`` (version 3, about a tenth of the PLY;
    :mod:`sgpor_pipeline.spz_io`), every SH degree up to 3, in SPZ's frame (RUB: the export frame turned
    so that its +Z is +Y, as :func:`scene_y_up`); the positions' fixed point keeps 12 fraction bits
    (0.24 mm in metres) unless the scene reaches beyond 2048 units."""

    name = "spz"
    VERSION = 1
    description = ("the Gaussians as scene.spz (Niantic's compressed format, version 3: Scaniverse, Spark, "
                   "SuperSplat, Babylon.js; Y up, full SH)")
    outputs = ("scene.spz",)

    def export(self, ctx: StageContext, out_dir: Path) -> None:
        from sgpor_pipeline.spz_io import FRACTIONAL_BITS, read_spz_header, write_spz

        t0 = time.perf_counter()
        model, _, _ = scene_y_up(ctx, out_dir)
        path = write_spz(out_dir / "scene.spz", model, fractional_bits=None)
        bits = read_spz_header(path).fractional_bits
        coarser = (f"; positions to {2.0 ** -bits:.3g} units ({bits} fraction bits: the scene is too large "
                   f"for {FRACTIONAL_BITS})" if bits < FRACTIONAL_BITS else "")
        ctx.log.info(f"spz: {len(model)} Gaussians (SH degree {model.max_sh_degree}) -> {path.name} ({_mb(path)}) "
                     f"in {time.perf_counter() - t0:.1f} s{coarser}")


# --------------------------------------------------------------------------------------------------
# the removed object as its own asset


def write_object_assets(folder: Path, object_model: Any, cameras: list[Camera], frame: ExportFrame,
                        mesh_settings: Any = None, background: list[float] | None = None,
                        mesh: bool = True, scene_radius: float | None = None) -> list[Path]:
    """Write the removed object's Gaussians and mesh as ``folder/object/object.ply`` and ``object.glb``.

    ``object_model``: a GaussianModel of the object alone, in the SfM frame (the frame of
    ``cameras``); ``frame``: the run's export frame (:func:`export_frame`), so the object lands where
    it stood in the exported scene. The mesh is fused from renders of the object alone at the
    registered ``cameras`` (see :func:`sgpor_pipeline.meshing.mesh_from_gaussians`); its components
    are not filtered (the object may be small) and its faces are limited to a quarter of the scene
    mesh's; its voxel follows ``scene_radius`` (the scene mesh's: :func:`scene_radius`; default: the
    cameras' distance to their look-at point). Returns the files written.
    """
    from dataclasses import replace

    from sgpor_pipeline.gaussians.ply import write_ply
    from sgpor_pipeline.meshing import MeshSettings, mesh_from_gaussians
    from sgpor_pipeline.orientation import scene_center_radius

    from .mesh import write_mesh

    out = Path(folder) / "object"
    out.mkdir(parents=True, exist_ok=True)
    written = [write_ply(out / "object.ply", transform_model(object_model, frame.transform))]
    if mesh and len(object_model):
        s = mesh_settings or MeshSettings()
        s = replace(s, min_component_rel=0.0, target_faces=max(1000, s.target_faces // 4))
        cams = registered(cameras) or cameras
        radius = scene_radius if scene_radius is not None else scene_center_radius(cams)[1]
        m = mesh_from_gaussians(object_model, cams, s, scene_radius=radius, background=background)
        if len(m):
            written += write_mesh(m.transformed(frame.transform), out, "object", formats=("glb",))
    return written


class ObjectExporter(Exporter):
    """The removed object as its own asset (``object/object.ply`` + ``object/object.glb``), from the
    remove stage's ``object.ply`` (the deleted Gaussians, INRIA layout, SfM frame). After a fit that
    left the object out (``fit.object_masks``: every view had a mask; ``object_fitted`` false in
    remove.json) there is no object to export: nothing is written and the log says why.
    """

    name = "object"
    VERSION = 4  # 2: object.glb's normals of unit length; 3: the scene mesh's radius (SfM points); 4: object.glb's
    # vertex colours linear (glTF's COLOR_0)
    needs = (CAMERAS_STAGE, POSES_STAGE, SCENE_STAGE, "remove")
    optional_needs = (GPS_STAGE,)
    description = "the removed object as object/object.ply and object/object.glb (export frame)"
    outputs = ("object/",)
    OBJECT_FILE = "object.ply"

    def export(self, ctx: StageContext, out_dir: Path) -> None:
        from sgpor_pipeline.gaussians.ply import read_ply
        from sgpor_pipeline.meshing import MeshSettings

        t0 = time.perf_counter()
        info = ctx.inputs["remove"] / "remove.json"
        if info.is_file() and not json.loads(info.read_text()).get("object_fitted", True):
            ctx.log.info("object: the fit left the object out (every view had a mask), so there is no object "
                         "asset; --set fit.object_masks=fit models it (and deletes it) instead")
            return
        scene = load_scene(ctx)
        cameras = load_run_cameras(ctx)
        frame = export_frame(ctx, scene, cameras, out_dir)
        obj = read_ply(ctx.inputs["remove"] / self.OBJECT_FILE)
        files = write_object_assets(out_dir, obj, cameras, frame, MeshSettings.from_params(ctx.params),
                                    scene_background(ctx), scene_radius=scene_radius(ctx, scene, cameras))
        ctx.log.info(f"object: {len(obj)} Gaussians -> {', '.join(p.name for p in files)} in "
                     f"{time.perf_counter() - t0:.1f} s")


def frame_matrix(out_dir: Path) -> np.ndarray | None:
    """The 4x4 export_from_sfm matrix recorded in ``export_frame.json`` of an export folder, if any."""
    path = Path(out_dir) / FRAME_FILE
    if not path.is_file():
        return None
    return np.array(json.loads(path.read_text())["export_from_sfm"]["matrix"])


#: half turns about x, y and z: the frame changes splat tools make on the way (SPZ's RUB and glTF's +Y up
#: from a PLY's y down: about x; PlayCanvas's splat-transform writes a PLY into a .glb turned about z)
HALF_TURNS = {"x": np.diag([1.0, -1.0, -1.0]), "y": np.diag([-1.0, 1.0, -1.0]), "z": np.diag([-1.0, -1.0, 1.0])}


def share_in_view(means: np.ndarray, cameras: list[Camera]) -> float:
    """The share of the points in front of at least one camera and inside its image."""
    seen = np.zeros(len(means), bool)
    for cam in cameras:
        px, z = cam.project(means)
        seen |= (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
    return float(seen.mean()) if len(means) else 1.0


def check_cameras_see_gaussians(model: Any, cameras: list[Camera], source: Path, min_share: float = 0.5,
                                sample: int = 20000, seed: int = 0) -> dict[str, float]:
    """Warn when the cameras see less than ``min_share`` of the opaque Gaussians: the file and the cameras
    are then likely in different frames. Returns the share as read and, when it is low, under each of
    :data:`HALF_TURNS` of the Gaussians, so the warning can name the turn that fits."""
    p = model.numpy()
    means = p["means"][p["opacities"] > 0.0]  # opacity above 0.5
    if len(means) > sample:
        means = means[np.random.default_rng(seed).choice(len(means), sample, replace=False)]
    shares = {"as read": share_in_view(means.astype(np.float64), cameras)}
    if shares["as read"] >= min_share or not len(means):
        return shares
    for axis, turn in HALF_TURNS.items():
        shares[f"turned half about {axis}"] = share_in_view(means.astype(np.float64) @ turn.T, cameras)
    best = max(shares, key=shares.get)
    hint = (f"; turned half about {best[-1]}, {shares[best]:.0%} would be (an .spz: --spz-frame; a .glb made by "
            "PlayCanvas's splat-transform is its PLY turned half about z)" if best != "as read" else "")
    log.warning(f"{source}: the cameras see only {shares['as read']:.0%} of the opaque Gaussians: the cameras are "
                f"likely in another frame than the file{hint}. Pass the cameras in the file's frame: the exports "
                "(renders, the USD cameras, the export frame's up) need both in one frame")
    return shares


def export_external(gaussians: Path, cameras_json: Path, out_dir: Path,
                    formats: tuple[str, ...] = ("ply", "splat", "spz", "gltf", "mesh", "usd", "renders"),
                    params: Any = None, spz_frame: str = "ply") -> Path:
    """Run exporters on Gaussians from another trainer: an INRIA-layout PLY (any SH degree), an
    ``.spz``, a ``.splat``, a ``.glb``, a SOG (``.sog`` or its ``meta.json``) or a USD stage, and the
    cameras it was trained with (a ``cameras.json`` of :mod:`sgpor_pipeline.scene`, in the PLY's
    frame; a ``.glb``'s or a stage's in its own).

    The file is read with :func:`sgpor_pipeline.gaussians.formats.load_gaussians_any` (a PLY exactly;
    an ``.spz`` turned from its RUB frame to the PLY's unless ``spz_frame="stored"``; a ``.glb`` and a
    USD stage as stored). ``params``: the
    export stage's parameters (default ``ExportParams()``). Returns ``out_dir``.
    """
    import shutil
    import tempfile

    from sgpor_pipeline.dag import RunInputs, discover_exporters
    from sgpor_pipeline.gaussians.formats import load_gaussians_any
    from sgpor_pipeline.gaussians.ply import write_ply
    from sgpor_pipeline.stages.export import ExportParams, run_exporters

    exporters = discover_exporters()
    unknown = [f for f in formats if f not in exporters]
    if unknown:
        from sgpor_pipeline.errors import PipelineError

        raise PipelineError(f"unknown export format(s) {unknown}", fix=f"choose from {', '.join(sorted(exporters))}")
    model = load_gaussians_any(gaussians, spz_frame)  # validates the file before any folder is made
    if len(model) == 0:
        log.warning(f"{gaussians}: the file holds no Gaussians; the exports hold the cameras only")
    else:
        check_cameras_see_gaussians(model, load_cameras(cameras_json), Path(gaussians))
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="sgpor-export-") as tmp:
        scene_dir, cam_dir = Path(tmp) / SCENE_STAGE, Path(tmp) / CAMERAS_STAGE
        scene_dir.mkdir()
        cam_dir.mkdir()
        write_ply(scene_dir / SCENE_FILE, model)
        shutil.copyfile(cameras_json, cam_dir / "cameras.json")
        ctx = StageContext(stage="export", params=params or ExportParams(), out_dir=out_dir,
                           inputs={SCENE_STAGE: scene_dir, CAMERAS_STAGE: cam_dir},
                           run_inputs=RunInputs(images=Path(tmp)), log=log, seed_key="external")
        run_exporters({name: exporters[name] for name in formats}, ctx, out_dir)
    return out_dir
