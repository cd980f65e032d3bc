"""Render a finished run's Gaussians at any cameras (``sgpor-pipeline render OUT --cameras FILE``).

The scene is read from the cache of the run in ``OUT``: the Gaussians (``gaussians.ply``) of one
stage's result, :data:`~sgpor_pipeline.exporters.gaussians.SCENE_STAGE` (the cleaned scene) unless
told otherwise, located through the keys the last run recorded (nothing is recomputed; a missing
result is an error that names the command building it). Cameras come from any file
:func:`~sgpor_pipeline.camera_io.load_cameras_any` reads (COLMAP model, transforms.json, cameras.json)
and are either in the run's frame (the SfM frame: the frame of the stage cache and of
``export/cameras/``), or in another frame that shares image names with the run's registered views:
then a similarity (scale, rotation, translation) fitted to the shared cameras' centres
(:func:`umeyama`) maps every camera of the file into the run's frame. A run whose given cameras the sfm
stage moved (georeferenced, or kilometres: :func:`~sgpor_pipeline.sfm.conditioning_frame`) takes a file
with fewer shared names as in the frame of those given cameras (``--align none``: the run's frame).
A camera named like a run photo is then rendered at that photo's run pose (with ``fit.pose_refine``,
SfM's corrected), and every other camera turned and moved as its nearest such cameras were
(:func:`carry_run_corrections`): the Gaussians were fitted at the run's poses, and the fit's
corrections share a small turn that novel cameras need too.

Out (``output``): ``<camera>.png`` per camera (file names made safe), ``depth/<camera>.npy`` (float32
z-depth in the cameras file's units, 0 = nothing rendered) on request, ``cameras.json`` (the cameras
as rendered, run frame) and ``render.json`` (what was rendered, from which result, the alignment).
Intrinsics and size are the file's; distortion is ignored (rendered as PINHOLE, with a warning).
"""

from __future__ import annotations

import json
import logging
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Literal

import numpy as np

from .errors import PipelineError
from .orientation import Similarity, rotation_angle_deg, umeyama
from .scene import Camera, load_cameras, save_cameras

log = logging.getLogger("sgpor_pipeline.render")

ALIGN_MODES = ("auto", "none", "similarity")
MIN_SHARED = 3  # camera centres needed for a similarity (7 unknowns, 3 per centre)
# A residual above this fraction of the camera spread means the shared names probably do not name
# the same photos (or the poses disagree): warned about, the render still runs.
RESIDUAL_WARN = 0.05
# Below this ratio of the second to the first principal spread the centres are (nearly) collinear:
# the rotation about that line is then taken from the cameras' orientations.
COLLINEAR = 1e-3
# Shared cameras this close to the run's (relative centre residual, degrees) are the run's own: no
# similarity is applied, so the renders equal the renders exporter's bit for bit.
SAME_FRAME = 1e-9
SAME_FRAME_DEG = 1e-4
RENDER_FILE = "render.json"
CAMERAS_FILE = "cameras.json"
DEPTH_DIR = "depth"


@dataclass
class RenderParams:
    """Options of :func:`render_run` (the ``render`` command's flags)."""

    stage: str | None = None  # stage whose gaussians.ply is rendered; None = SCENE_STAGE (finetune)
    align: Literal["auto", "none", "similarity"] = "auto"
    depth: bool = False  # also write depth/<camera>.npy


# --------------------------------------------------------------------------------------------------
# alignment


def _mean_rotation(rotations: list[np.ndarray]) -> np.ndarray:
    """The rotation closest (chordal L2) to the mean of ``rotations``."""
    U, _, Vt = np.linalg.svd(np.sum(rotations, axis=0))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt)) or 1.0
    return U @ D @ Vt


@dataclass
class Alignment:
    """How the file's cameras were put into the run's frame."""

    method: str  # "similarity", "given" (the run's given cameras' frame) or "none"
    transform: Similarity  # run_from_file (identity for "none")
    shared: list[str] = field(default_factory=list)  # image names shared with the run's views
    rms: float | None = None  # centre residual after the transform, run units (shared cameras)
    max: float | None = None
    relative: float | None = None  # rms / spread of the run's shared camera centres
    rotation_deg: float | None = None  # mean angle between the aligned and the run's orientations
    message: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"method": self.method, "shared": len(self.shared), "shared_names": self.shared,
                "run_from_file": self.transform.to_dict(),
                "residual": {"rms": self.rms, "max": self.max, "relative_to_spread": self.relative,
                             "rotation_deg": self.rotation_deg},
                "message": self.message}


def _match_key(cam: Camera) -> str:
    return cam.image if cam.image is not None else cam.name


def shared_views(file_cams: list[Camera], run_cams: list[Camera]) -> list[tuple[Camera, Camera]]:
    """(file camera, run camera) pairs that name the same image (the run's registered views)."""
    run_by_image = {c.image: c for c in run_cams if c.image is not None}
    return [(c, run_by_image[_match_key(c)]) for c in file_cams if _match_key(c) in run_by_image]


def _residuals(pairs: list[tuple[Camera, Camera]], sim: Similarity) -> tuple[float, float, float | None, float]:
    """(rms, max, rms / spread (None for one camera), mean rotation error in degrees) of the mapped
    shared cameras."""
    src = np.array([f.center for f, _ in pairs])
    dst = np.array([r.center for _, r in pairs])
    err = np.linalg.norm(sim.apply(src) - dst, axis=1)
    spread = float(np.sqrt(((dst - dst.mean(0)) ** 2).sum(1).mean()))
    rms = float(np.sqrt((err ** 2).mean()))
    rot = float(np.mean([rotation_angle_deg(sim.camera(f).cam_from_world[:3, :3], r.cam_from_world[:3, :3])
                         for f, r in pairs]))
    return rms, float(err.max()), (rms / spread if spread > 1e-12 else None), rot


def fit_similarity(pairs: list[tuple[Camera, Camera]]) -> Similarity:
    """run_from_file from shared cameras: Umeyama on the centres; when the centres are (nearly)
    collinear the rotation comes from the cameras' orientations and scale/translation from the centres."""
    src = np.array([f.center for f, _ in pairs])
    dst = np.array([r.center for _, r in pairs])
    sv = np.linalg.svd(src - src.mean(0), compute_uv=False)
    sv_d = np.linalg.svd(dst - dst.mean(0), compute_uv=False)
    if sv[0] <= 1e-12 * max(1.0, np.abs(src).max()) or sv_d[0] <= 1e-12 * max(1.0, np.abs(dst).max()):
        raise PipelineError("the shared cameras all sit at one point: no scale can be estimated",
                            fix="include cameras from different positions, or pass --align none if the "
                                "cameras are already in the run's frame")
    if sv[1] > COLLINEAR * sv[0]:
        return umeyama(src, dst)
    # a straight camera path: cam_from_world_run = cam_from_world_file R^T, so R = Rc_run^T Rc_file
    R = _mean_rotation([r.cam_from_world[:3, :3].T @ f.cam_from_world[:3, :3] for f, r in pairs])
    xs, xd = src - src.mean(0), dst - dst.mean(0)
    s = float(np.sum(xd * (xs @ R.T)) / np.sum(xs ** 2))
    return Similarity(s, R, dst.mean(0) - s * R @ src.mean(0))


def align_cameras(file_cams: list[Camera], run_cams: list[Camera], mode: str = "auto",
                  given: Similarity | None = None) -> Alignment:
    """Put ``file_cams`` into the run's frame (see :class:`Alignment`); ``mode``: auto, none, similarity.
    ``given``: sfm_from_input of a run whose given cameras the sfm stage moved
    (:func:`~sgpor_pipeline.sfm.conditioning_frame`); in ``auto`` a file without enough shared names is
    then taken as in the frame of those given cameras."""
    if mode not in ALIGN_MODES:
        raise PipelineError(f"unknown alignment {mode!r}", fix=f"use one of {', '.join(ALIGN_MODES)}")
    pairs = shared_views(file_cams, run_cams)
    names = [_match_key(f) for f, _ in pairs]
    if mode == "similarity" and len(pairs) < MIN_SHARED:
        raise PipelineError(f"--align similarity needs at least {MIN_SHARED} cameras named like the run's "
                            f"images, the file has {len(pairs)}",
                            fix="name the cameras like the run's photos (their base names), or pass --align none "
                                "if the cameras are already in the run's frame")
    if mode == "auto" and len(pairs) < MIN_SHARED and given is not None:
        al = Alignment("given", given, names, message=(
            f"cameras taken as in the frame of the cameras given to the run ({len(pairs)} image name(s) shared; "
            f"the run moved those by scale {given.s:g}, translation {np.array2string(given.t, precision=4)})"))
        if pairs:
            al.rms, al.max, al.relative, al.rotation_deg = _residuals(pairs, given)
        return al
    if mode == "none" or len(pairs) < MIN_SHARED:
        ident = Similarity()
        if mode == "none":
            msg = "cameras taken as in the run's frame (--align none)"
        else:
            msg = (f"cameras taken as in the run's frame: they share {len(pairs)} image name(s) with the run "
                   f"({MIN_SHARED} are needed to estimate an alignment)")
        al = Alignment("none", ident, names, message=msg)
        if pairs:  # how far the shared cameras are from the run's: a frame mismatch shows here
            al.rms, al.max, al.relative, al.rotation_deg = _residuals(pairs, ident)
            spread = "" if al.relative is None else f" ({100 * al.relative:.1f}% of their spread)"
            al.message += f"; the {len(pairs)} shared camera(s) are {al.rms:.3g} units{spread} from the run's"
        return al
    if mode == "auto":
        rms, mx, rel, rot = _residuals(pairs, Similarity())
        # already the run's cameras: keep them bit for bit
        if rel is not None and rel < SAME_FRAME and rot < SAME_FRAME_DEG:
            return Alignment("none", Similarity(), names, rms, mx, rel, rot,
                             f"the {len(pairs)} shared cameras coincide with the run's: taken as in the run's frame")
    sim = fit_similarity(pairs)
    rms, mx, rel, rot = _residuals(pairs, sim)
    msg = (f"similarity from {len(pairs)} shared cameras: scale {sim.s:.6g}, residual RMS {rms:.3g} "
           f"(max {mx:.3g}; {100 * (rel or 0.0):.2f}% of the camera spread), orientation error {rot:.2f} deg")
    return Alignment("similarity", sim, names, rms, mx, rel, rot, msg)


# --------------------------------------------------------------------------------------------------
# the run


def safe_file_stem(name: str, taken: set[str]) -> str:
    """A file name stem for a camera name (letters, digits, ``._-``), unique within ``taken``."""
    stem = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "camera"
    cand, k = stem, 1
    while cand.lower() in taken:  # case-insensitive: also unique on macOS / Windows file systems
        cand = f"{stem}_{k}"
        k += 1
    taken.add(cand.lower())
    return cand


def carry_run_corrections(cams: list[Camera], run_cams: list[Camera]) -> tuple[list[Camera], str]:
    """``cams`` (in the run's frame) turned and moved as their nearest cameras named like run photos
    must be to reach those photos' run poses, in their own camera axes
    (:func:`~sgpor_pipeline.gaussians.pose.carry_corrections`): a camera named like a run photo gets
    that photo's pose; the others take what their neighbours needed. The Gaussians were fitted at the
    run's poses (with ``fit.pose_refine``, SfM's corrected, the corrections sharing a small turn a
    novel camera needs too); a file of the run's own cameras (``export/cameras/``) is unchanged.
    Returns the cameras and a line saying what was done."""
    matched = shared_views(cams, run_cams)
    if not matched:
        return cams, "none: no camera names a run photo"
    from .gaussians.pose import carry_corrections

    turns = [rotation_angle_deg(c.cam_from_world[:3, :3], r.cam_from_world[:3, :3]) for c, r in matched]
    carried = carry_corrections([c for c, _ in matched], [r for _, r in matched], cams)
    return carried, (f"carried from {len(matched)} camera(s) named like run photos (turned {np.median(turns):.3f} "
                     f"degrees at the median to their run poses)")


@dataclass
class RenderResult:
    output: Path
    files: list[Path]
    alignment: Alignment
    stage: str
    seconds: float


def render_run(out: Path, cameras_path: Path, output: Path | None = None,
               params: RenderParams | None = None, progress: Any = None) -> RenderResult:
    """Render the Gaussians of a finished run in ``out`` at the cameras of ``cameras_path``.

    ``output`` defaults to ``out/renders/<cameras file stem>``. See the module docstring for what is
    written. Raises PipelineError for a missing run or stage result, or an unreadable cameras file.
    """
    from .camera_io import load_cameras_any
    from .dag import discover_stages
    from .exporters.gaussians import CAMERAS_STAGE, POSES_STAGE, SCENE_FILE, SCENE_STAGE, scene_background
    from .gaussians.ply import read_ply
    from .imageio import write_png
    from .meshing import activated_tensors, render_view
    from .runner import stage_result
    from .sfm import given_frame
    from .stages.fit import run_cameras_file

    p = params or RenderParams()
    stage = p.stage or SCENE_STAGE
    stages = discover_stages()
    if stage not in stages:
        raise PipelineError(f"unknown stage '{stage}' for --stage",
                            fix=f"use a stage that fits Gaussians (fit, finetune; default {SCENE_STAGE}); "
                                f"installed stages: {', '.join(sorted(stages))}")
    out, cameras_path = Path(out), Path(cameras_path)
    t0 = time.perf_counter()
    scene_dir, scene_key = stage_result(out, stage)
    if not (scene_dir / SCENE_FILE).is_file():
        raise PipelineError(f"stage '{stage}' holds no Gaussians ({SCENE_FILE})", path=scene_dir,
                            fix=f"pass --stage with a stage that fits Gaussians (fit, finetune; default {SCENE_STAGE})")
    sfm_dir, _ = stage_result(out, CAMERAS_STAGE)
    try:
        fit_dir = stage_result(out, POSES_STAGE)[0]
    except PipelineError:  # (a run without a fit: the background colour from the scene's stage)
        fit_dir = scene_dir
    run_cams = load_cameras(run_cameras_file(fit_dir, sfm_dir))  # the poses the Gaussians were fitted with
    background = scene_background(SimpleNamespace(inputs={"fit": fit_dir, SCENE_STAGE: scene_dir}))
    file_cams = load_cameras_any(cameras_path)  # before the Gaussians: a bad file fails at once
    log.info(f"render: {len(file_cams)} camera(s) from {cameras_path}")
    model = read_ply(scene_dir / SCENE_FILE)
    log.info(f"render: {len(model):,} Gaussians of stage '{stage}' (key {scene_key[:10]}) of {out}")
    al = align_cameras(file_cams, run_cams, p.align, given_frame(sfm_dir))
    if al.relative is not None and al.relative > RESIDUAL_WARN:
        hint = ("pass --align similarity if the cameras are in another frame" if al.method == "none" else
                "check that the file's camera names refer to the run's photos")
        log.warning(f"align: {al.message}: large ({hint})")
    else:
        log.info(f"align: {al.message}")
    cams = [al.transform.camera(c) for c in file_cams]
    cams, carried = carry_run_corrections(cams, run_cams)
    log.info(f"render: the fit's pose corrections: {carried}")
    distorted = [c.name for c in cams if any(float(d) != 0.0 for d in c.distortion)]
    if distorted:
        log.warning(f"render: {len(distorted)} camera(s) have lens distortion, rendered as PINHOLE (undistorted): "
                    + ", ".join(distorted[:5]) + (" ..." if len(distorted) > 5 else ""))

    output = Path(output) if output is not None else out / "renders" / _default_name(cameras_path)
    output.mkdir(parents=True, exist_ok=True)
    if p.depth:
        (output / DEPTH_DIR).mkdir(exist_ok=True)
    g = activated_tensors(model)
    taken: set[str] = set()
    files, entries = [], []
    run_images = {c.image for c in run_cams if c.image is not None}
    for cam in (progress(cams) if progress else cams):
        stem = safe_file_stem(cam.name, taken)
        res = render_view(g, cam, background, with_depth=p.depth)
        path = output / f"{stem}.png"
        write_png(path, res["rgb"])
        files.append(path)
        entry: dict[str, Any] = {"name": cam.name, "image": cam.image, "file": path.name,
                                 "width": cam.width, "height": cam.height,
                                 "run_view": _match_key(cam) if _match_key(cam) in run_images else None}
        if p.depth:
            # the aligned camera sees the scene s times larger than in the file's frame: back to file units
            depth = (res["depth"] / al.transform.s).astype(np.float32)
            np.save(output / DEPTH_DIR / f"{stem}.npy", depth)
            entry["depth"] = f"{DEPTH_DIR}/{stem}.npy"
        entries.append(entry)
    save_cameras(output / CAMERAS_FILE, cams)
    seconds = time.perf_counter() - t0
    record = {"run": str(out.resolve()), "stage": stage, "stage_key": scene_key,
              "cameras_file": str(cameras_path.resolve()), "gaussians": len(model), "background": background,
              "alignment": al.to_dict(), "pose_corrections": carried,
              "depth_units": "cameras file" if p.depth else None, "renders": entries, "seconds": round(seconds, 3)}
    (output / RENDER_FILE).write_text(json.dumps(record, indent=1))
    log.info(f"render: {len(files)} image(s) -> {output} in {seconds:.1f} s")
    return RenderResult(output, files, al, stage, seconds)


def _default_name(cameras_path: Path) -> str:
    p = Path(cameras_path)
    if p.is_dir():
        return p.name or "cameras"
    if p.stem in ("cameras", "images", "points3D") and p.suffix.lower() in (".bin", ".txt"):
        return p.parent.name or "cameras"  # a file inside a COLMAP model folder
    return p.stem
