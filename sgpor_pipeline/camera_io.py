"""Import and export of known cameras: COLMAP models and nerfstudio / instant-ngp ``transforms.json``
(both ways), LLFF ``poses_bounds.npy`` and the cameras of a binary glTF (read).

Every reader returns a list of :class:`sgpor_pipeline.scene.Camera` (OpenCV axes, ``cam_from_world``).
Bad input raises :class:`sgpor_pipeline.errors.PipelineError` naming the file and the fix.

Conventions:

- COLMAP: ``Camera.name`` and ``Camera.image`` are the stem of the image's base name
  (``sub/IMG_01.JPG`` -> ``IMG_01``); ``model`` is the COLMAP model name, ``K`` comes from its
  focal length / principal point and ``distortion`` holds the remaining parameters. Images without
  a pose (not registered) are skipped. Our writer stores a camera without an image under its bare
  name (no file extension) and the reader maps an image name without an extension back to
  ``image=None``.
- transforms.json: ``transform_matrix`` is camera-to-world in the OpenGL/Blender convention (x right,
  y up, z backward). Intrinsics per frame or global (``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h``,
  or ``camera_angle_x`` / ``camera_angle_y``), distortion ``k1, k2, p1, p2`` (-> OPENCV),
  ``k3, k4`` (-> FULL_OPENCV) or ``camera_model: OPENCV_FISHEYE``. Our writer adds ``sgpor_name`` /
  ``sgpor_image`` keys to each frame (ignored by other tools) so names and image-less cameras survive
  a round trip. ``applied_transform`` (nerfstudio) is ignored: poses stay in the file's world frame.
- LLFF ``poses_bounds.npy`` (LLFF, SPIn-NeRF): rows in the sorted order of the ``images/`` folder
  beside the file, camera-to-world with columns down, right, back; PINHOLE at the file's full size
  (ingest scales it to the photos).
- ``.glb``: its perspective cameras (:func:`sgpor_pipeline.splat_gltf.read_gltf_cameras`), in the
  glTF file's frame, the frame of the Gaussians it may hold; the pixel size from our writer's
  ``sgpor_size`` extra, else 1080 px high.
- USD (``.usd``, ``.usda``, ``.usdc``, ``.usdz``): its perspective ``UsdGeom.Camera`` prims
  (:mod:`sgpor_pipeline.splat_usd`), in the stage's world frame.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from pathlib import Path, PurePosixPath

import numpy as np

from .errors import PipelineError
from .imageio import IMAGE_EXTENSIONS
from .scene import CAMERAS_FORMAT, Camera
from .splat_usd import USD_SUFFIXES

log = logging.getLogger(__name__)

# OpenGL/Blender camera axes (x right, y up, z back) <-> OpenCV (x right, y down, z forward)
_GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])

_CAMERA_FIX = ("pass a COLMAP model folder (cameras/images .bin or .txt), a nerfstudio/instant-ngp "
               "transforms.json, an LLFF poses_bounds.npy, a .glb or USD file with cameras, or a cameras.json "
               "written by sgpor-pipeline")


# --------------------------------------------------------------------------------------------------
# COLMAP


def colmap_cam_from_world(image: object) -> np.ndarray:
    """A posed pycolmap Image's cam_from_world as a 4x4 float64 matrix."""
    T = np.eye(4)
    T[:3, :] = np.asarray(image.cam_from_world().matrix(), np.float64)  # type: ignore[attr-defined]
    return T


def _has_model(folder: Path) -> bool:
    return any((folder / f"cameras{ext}").is_file() and (folder / f"images{ext}").is_file()
               for ext in (".bin", ".txt"))


def find_colmap_model(path: str | Path) -> Path | None:
    """The COLMAP model folder at ``path``, or under ``path/sparse/0``, ``path/0`` or ``path/sparse``."""
    path = Path(path)
    for cand in (path, path / "sparse" / "0", path / "0", path / "sparse"):
        if cand.is_dir() and _has_model(cand):
            return cand
    return None


def _image_stem(name: str) -> str:
    """``sub/IMG_01.JPG`` -> ``IMG_01`` (also for Windows separators)."""
    return PurePosixPath(name.replace("\\", "/")).stem


def read_colmap_model(path: str | Path) -> list[Camera]:
    """Cameras of the registered images of a COLMAP model (binary or text), in image-id order."""
    import pycolmap

    path = Path(path)
    if not path.exists():
        raise PipelineError("COLMAP model folder does not exist", path, fix=_CAMERA_FIX)
    model = find_colmap_model(path)
    if model is None:
        raise PipelineError("no COLMAP model here (expected cameras.bin/images.bin or cameras.txt/images.txt, "
                            "directly or in sparse/0 or 0/)", path, fix=_CAMERA_FIX)
    try:
        rec = pycolmap.Reconstruction(str(model))
    except Exception as e:  # pycolmap raises ValueError/RuntimeError with C++ messages
        raise PipelineError(f"pycolmap could not read this COLMAP model: {e}", model,
                            fix="re-export the model with COLMAP (File > Export model) or "
                                "check that the files are complete") from e
    cams: list[Camera] = []
    skipped = 0
    for _, image in sorted(rec.images.items()):
        if not image.has_pose:
            skipped += 1
            continue
        cam = rec.cameras[image.camera_id]
        params = np.asarray(cam.params, np.float64)
        K = np.asarray(cam.calibration_matrix(), np.float64)
        extra = [float(params[i]) for i in cam.extra_params_idxs()]
        T = colmap_cam_from_world(image)
        stem = _image_stem(image.name)
        has_image = bool(PurePosixPath(image.name.replace("\\", "/")).suffix)
        cams.append(Camera(name=stem, width=cam.width, height=cam.height, K=K, cam_from_world=T,
                           image=stem if has_image else None, model=cam.model.name, distortion=extra))
    if skipped:
        log.info("%s: skipped %d images without a pose", model, skipped)
    if not cams:
        raise PipelineError("the COLMAP model has no registered images", model,
                            fix="run the reconstruction again or pass a model with posed images")
    _check_unique([c.name for c in cams], model)
    return cams


def _check_unique(names: Sequence[str], path: Path) -> None:
    seen: set[str] = set()
    dup = sorted({n for n in names if n in seen or seen.add(n)})
    if dup:
        raise PipelineError(f"several images share the base name(s) {', '.join(dup[:5])}", path,
                            fix="give every image a unique file name (cameras are matched to images by name)")


def write_colmap_model(cameras: Sequence[Camera], folder: str | Path, binary: bool = False,
                       image_ext: str = ".png") -> Path:
    """Write cameras as a COLMAP model (one camera per image, no 3D points) and return the folder.

    PINHOLE cameras are written as PINHOLE; cameras with a COLMAP model and distortion keep them.
    Image names are ``<image><image_ext>``; a camera without an image is written under its bare
    ``name`` (no extension), which :func:`read_colmap_model` reads back as ``image=None``.
    """
    import pycolmap

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rec = pycolmap.Reconstruction()
    names = [f"{c.image}{image_ext}" if c.image else c.name for c in cameras]
    _check_unique(names, folder)
    for i, (c, name) in enumerate(zip(cameras, names), start=1):
        model = c.model if c.distortion else "PINHOLE"
        pc = pycolmap.Camera.create_from_model_name(i, model, float(c.K[0, 0]), c.width, c.height)
        params = np.array(pc.params, np.float64)
        fi = list(pc.focal_length_idxs())
        if len(fi) == 2:
            params[fi[0]], params[fi[1]] = c.K[0, 0], c.K[1, 1]
        else:
            if not math.isclose(c.K[0, 0], c.K[1, 1], rel_tol=1e-9):
                raise PipelineError(f"camera {c.name}: model {model} has one focal length but fx != fy",
                                    folder, fix="use a PINHOLE/OPENCV camera model")
            params[fi[0]] = c.K[0, 0]
        pi = list(pc.principal_point_idxs())
        params[pi[0]], params[pi[1]] = c.K[0, 2], c.K[1, 2]
        ei = list(pc.extra_params_idxs())
        if len(c.distortion) != len(ei):
            raise PipelineError(f"camera {c.name}: model {model} needs {len(ei)} distortion parameters, "
                                f"got {len(c.distortion)}", folder, fix="fix the camera's distortion list")
        for j, val in zip(ei, c.distortion):
            params[j] = val
        pc.params = params
        rec.add_camera_with_trivial_rig(pc)
        image = pycolmap.Image(name=name, camera_id=i, image_id=i)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(np.asarray(c.cam_from_world[:3, :4])))
    if binary:
        rec.write_binary(str(folder))
    else:
        rec.write_text(str(folder))
    return folder


# --------------------------------------------------------------------------------------------------
# transforms.json (nerfstudio / instant-ngp)


def _get(frame: dict, top: dict, key: str, default=None):
    v = frame.get(key, top.get(key, default))
    return default if v is None else v


def _image_size(path: Path, file_path: str) -> tuple[int, int] | None:
    """(w, h) of the image a frame names, trying the common extensions when it has none."""
    base = path.parent / file_path
    cands = [base] if base.suffix else []
    cands += [base.with_name(base.name + ext) for ext in (".png", ".jpg", ".jpeg", ".PNG", ".JPG")]
    for c in cands:
        if c.is_file():
            try:
                from PIL import Image

                with Image.open(c) as im:
                    return im.size
            except Exception:
                return None
    return None


def read_transforms_json(path: str | Path) -> list[Camera]:
    """Cameras of a nerfstudio or instant-ngp ``transforms.json`` (in the order of its frames)."""
    path = Path(path)
    data = _read_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise PipelineError("not a transforms.json: no 'frames' list", path,
                            fix="pass a nerfstudio/instant-ngp transforms.json")
    cams: list[Camera] = []
    for i, fr in enumerate(data["frames"]):
        where = f"frame {i}"
        if not isinstance(fr, dict) or "transform_matrix" not in fr or "file_path" not in fr:
            raise PipelineError(f"{where} lacks 'file_path' or 'transform_matrix'", path,
                                fix="every frame needs file_path and a 4x4 transform_matrix")
        try:
            c2w_gl = np.asarray(fr["transform_matrix"], np.float64)
            if c2w_gl.shape == (3, 4):
                c2w_gl = np.vstack([c2w_gl, [0, 0, 0, 1]])
            if c2w_gl.shape != (4, 4) or not np.all(np.isfinite(c2w_gl)):
                raise ValueError("shape")
        except (ValueError, TypeError) as e:
            raise PipelineError(f"{where}: transform_matrix is not a finite 4x4 matrix", path,
                                fix="write transform_matrix as 4 rows of 4 numbers") from e
        file_path = str(fr["file_path"])
        w = _get(fr, data, "w")
        h = _get(fr, data, "h")
        if w is None or h is None:
            size = _image_size(path, file_path)
            if size is None:
                raise PipelineError(f"{where}: image size unknown (no 'w'/'h' and image {file_path!r} not "
                                    "found next to the json)", path,
                                    fix="add \"w\" and \"h\" (pixels) to the json or put the images next to it")
            w, h = size
        w, h = int(w), int(h)
        try:
            fx, fy = _focal(fr, data, w, h)
            cx = float(_get(fr, data, "cx", w / 2))
            cy = float(_get(fr, data, "cy", h / 2))
            k = {n: float(_get(fr, data, n, 0.0)) for n in ("k1", "k2", "k3", "k4", "p1", "p2")}
        except (ValueError, TypeError) as e:
            raise PipelineError(f"{where}: intrinsics are not numbers ({e})", path,
                                fix="write fl_x, fl_y, cx, cy, w, h as numbers") from e
        if fx is None:
            raise PipelineError(f"{where}: no focal length (fl_x/fl_y or camera_angle_x)", path,
                                fix="add fl_x (pixels) or camera_angle_x (radians)")
        model_name = str(_get(fr, data, "camera_model", "OPENCV")).upper()
        if model_name == "OPENCV_FISHEYE":
            model, dist = "OPENCV_FISHEYE", [k["k1"], k["k2"], k["k3"], k["k4"]]
        elif k["k3"] or k["k4"]:
            model, dist = "FULL_OPENCV", [k["k1"], k["k2"], k["p1"], k["p2"], k["k3"], k["k4"], 0.0, 0.0]
        elif k["k1"] or k["k2"] or k["p1"] or k["p2"]:
            model, dist = "OPENCV", [k["k1"], k["k2"], k["p1"], k["p2"]]
        else:
            model, dist = "PINHOLE", []
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        c2w_cv = c2w_gl @ _GL_FROM_CV
        stem = _image_stem(file_path)
        name = str(fr.get("sgpor_name", stem))
        image = fr["sgpor_image"] if "sgpor_image" in fr else stem
        cams.append(Camera(name=name, width=w, height=h, K=K, cam_from_world=np.linalg.inv(c2w_cv),
                           image=image, model=model, distortion=dist))
    if not cams:
        raise PipelineError("transforms.json has no frames", path, fix="add at least one frame")
    _check_unique([c.name for c in cams], path)
    return cams


def _focal(fr: dict, top: dict, w: int, h: int) -> tuple[float | None, float | None]:
    fx = _get(fr, top, "fl_x")
    fy = _get(fr, top, "fl_y")
    if fx is None and fy is not None:
        fx = fy
    if fx is None:
        ax = _get(fr, top, "camera_angle_x")
        if ax is None and _get(fr, top, "x_fov") is not None:  # instant-ngp, degrees
            ax = math.radians(float(_get(fr, top, "x_fov")))
        if ax is not None:
            fx = 0.5 * w / math.tan(0.5 * float(ax))
    if fy is None:
        ay = _get(fr, top, "camera_angle_y")
        if ay is None and _get(fr, top, "y_fov") is not None:
            ay = math.radians(float(_get(fr, top, "y_fov")))
        fy = 0.5 * h / math.tan(0.5 * float(ay)) if ay is not None else fx
    return (None if fx is None else float(fx)), (None if fy is None else float(fy))


def write_transforms_json(cameras: Sequence[Camera], path: str | Path, image_dir_prefix: str = "images/",
                          image_ext: str = ".png", file_paths: Sequence[str] | None = None) -> Path:
    """Write a nerfstudio ``transforms.json`` (OpenGL camera-to-world) and return its path.

    Each frame's ``file_path`` is ``image_dir_prefix`` + the image's (or the camera's) name +
    ``image_ext``, or, given, the matching entry of ``file_paths`` (relative to the file's folder).
    Shared intrinsics are written once at the top level, otherwise per frame. Supported camera models:
    PINHOLE, SIMPLE_PINHOLE, OPENCV, FULL_OPENCV (k5 = k6 = 0), SIMPLE_RADIAL, RADIAL, OPENCV_FISHEYE.
    """
    path = Path(path)
    if file_paths is not None and len(file_paths) != len(cameras):
        raise ValueError(f"{len(file_paths)} file paths for {len(cameras)} cameras")
    frames = []
    intr = []
    for k, c in enumerate(cameras):
        d = _intrinsics_dict(c, path)
        intr.append(d)
        c2w_gl = np.linalg.inv(c.cam_from_world) @ _GL_FROM_CV
        stem = c.image if c.image else c.name
        frames.append({"file_path": f"{image_dir_prefix}{stem}{image_ext}" if file_paths is None else file_paths[k],
                       "transform_matrix": c2w_gl.tolist(),
                       "sgpor_name": c.name, "sgpor_image": c.image})
    out: dict = {}
    if intr and all(d == intr[0] for d in intr):
        out.update(intr[0])
    else:
        for fr, d in zip(frames, intr):
            fr.update(d)
    out["frames"] = frames
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1))
    return path


def _intrinsics_dict(c: Camera, path: Path) -> dict:
    d: dict = {"w": c.width, "h": c.height, "fl_x": float(c.K[0, 0]), "fl_y": float(c.K[1, 1]),
               "cx": float(c.K[0, 2]), "cy": float(c.K[1, 2])}
    dist = list(c.distortion)
    model = c.model if dist else "PINHOLE"
    if model in ("PINHOLE", "SIMPLE_PINHOLE"):
        d["camera_model"] = "OPENCV"
    elif model in ("OPENCV", "FULL_OPENCV", "SIMPLE_RADIAL", "RADIAL"):
        if model == "FULL_OPENCV" and any(dist[6:8]):
            raise PipelineError(f"camera {c.name}: FULL_OPENCV k5/k6 cannot be written to transforms.json",
                                path, fix="undistort the images first")
        padded = {"SIMPLE_RADIAL": [dist[0], 0, 0, 0], "RADIAL": [dist[0], dist[1], 0, 0]}.get(model, dist)
        names = ("k1", "k2", "p1", "p2", "k3", "k4")
        d.update({n: float(v) for n, v in zip(names, padded)})
        d["camera_model"] = "OPENCV"
    elif model == "OPENCV_FISHEYE":
        d.update({n: float(v) for n, v in zip(("k1", "k2", "k3", "k4"), dist)})
        d["camera_model"] = "OPENCV_FISHEYE"
    else:
        raise PipelineError(f"camera {c.name}: model {model} cannot be written to transforms.json", path,
                            fix="undistort the images first (PINHOLE cameras)")
    return d


# --------------------------------------------------------------------------------------------------
# any format


def _read_json(path: Path):
    if not path.is_file():
        raise PipelineError("camera file does not exist", path, fix=_CAMERA_FIX)
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise PipelineError(f"malformed JSON ({e})", path, fix="repair or re-export the file") from e


def llff_image_names(path: Path) -> list[str]:
    """The base names an LLFF ``poses_bounds.npy`` belongs to: its rows follow the sorted file names
    of the ``images/`` folder beside it (LLFF's imgs2poses.py sorts COLMAP's image names)."""
    folder = Path(path).parent / "images"
    files = sorted(p.name for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")
                   and p.suffix.lower() in IMAGE_EXTENSIONS) if folder.is_dir() else []
    if not files:
        raise PipelineError("an LLFF poses_bounds.npy lists its poses in the sorted order of the photos in the "
                            "images/ folder beside it, and there is none", path,
                            fix="keep the file in its dataset folder next to images/ (as LLFF and SPIn-NeRF "
                                "ship it), or convert the cameras to a transforms.json")
    return [PurePosixPath(f).stem for f in files]


def read_llff_poses(path: str | Path, names: Sequence[str] | None = None, width: int | None = None,
                    height: int | None = None) -> list[Camera]:
    """Cameras from an LLFF ``poses_bounds.npy`` ([N,17]: a 3x5 camera-to-world pose whose columns are
    down, right, back, then height, width, focal; then near, far), one per name in ``names`` (default:
    :func:`llff_image_names`), PINHOLE, principal point at the centre. ``width`` x ``height``: the
    images' size (the focal is scaled from the file's full size); default the file's own size."""
    path = Path(path)
    try:
        pb = np.load(path)
    except (OSError, ValueError) as e:
        raise PipelineError(f"not a readable .npy array ({e})", path, fix=_CAMERA_FIX) from e
    names = llff_image_names(path) if names is None else list(names)
    if pb.ndim != 2 or pb.shape[1] != 17 or len(pb) != len(names):
        raise PipelineError(f"expected an LLFF poses_bounds array of {len(names)} x 17 (one row per photo), got "
                            f"{pb.shape}", path, fix="pass the poses_bounds.npy that belongs to these images")
    cams = []
    for name, row in zip(names, pb):
        P = row[:15].reshape(3, 5)
        h, w, f = P[:, 4]
        W = int(round(w)) if width is None else width
        H = int(round(h)) if height is None else height
        c2w = np.eye(4)
        c2w[:3, :3] = np.stack([P[:, 1], P[:, 0], -P[:, 2]], axis=1)  # OpenCV axes: right, down, forward
        c2w[:3, 3] = P[:, 3]
        K = np.array([[f * W / w, 0, W / 2], [0, f * H / h, H / 2], [0, 0, 1]])
        cams.append(Camera(name, W, H, K, np.linalg.inv(c2w), image=name))
    return cams


def proper_poses(cameras: list[Camera], path: Path) -> list[Camera]:
    """The cameras with rotations checked: a pose whose rotation carries a uniform scale (a camera
    object scaled in Blender, say) is divided by it, which keeps its centre and its image (warned
    once); a mirrored (left-handed) or sheared one is an error naming the camera. Without this the
    scaled poses' centres came out scaled and the mirrored ones contradicted the photos."""
    scaled = []
    for cam in cameras:
        R = cam.cam_from_world[:3, :3]
        det = float(np.linalg.det(R))
        k = math.copysign(abs(det) ** (1 / 3), det)
        if not k > 1e-12 or not np.allclose(R @ R.T / (k * k), np.eye(3), atol=1e-4):
            what = ("mirrored (a left-handed frame)" if k < -1e-12 else
                    "not a rotation (sheared, scaled unevenly or singular)")
            raise PipelineError(f"camera {cam.name!r}: its pose is {what}", path,
                                fix="write each pose as a rotation and a translation (a right-handed frame; "
                                    "for a transforms.json, camera-to-world in OpenGL axes)")
        if abs(k - 1.0) > 1e-6:
            cam.cam_from_world = cam.cam_from_world.copy()
            cam.cam_from_world[:3, :4] /= k
            scaled.append((cam.name, 1.0 / k))
    if scaled:
        log.warning(f"{path}: {len(scaled)} camera pose(s) carry a scale ({scaled[0][0]}: x{scaled[0][1]:.4g}); "
                    "taken out, the cameras' positions kept")
    return cameras


def read_glb_cameras(path: str | Path) -> list[Camera]:
    """The perspective cameras of a binary glTF file (see the module doc); none is an error."""
    from .splat_gltf import read_glb, read_gltf_cameras

    path = Path(path)
    try:
        cams = read_gltf_cameras(read_glb(path)[0], path)
    except (ValueError, KeyError, IndexError, TypeError) as e:  # read_glb's messages name the file
        raise PipelineError(f"unreadable glTF cameras ({e})", path, fix="re-export the .glb, or pass its cameras "
                                                                         "in another format") from None
    if not cams:
        raise PipelineError("the .glb holds no perspective camera; the cameras the Gaussians were trained "
                            "with are needed", path, fix=_CAMERA_FIX)
    return cams


def read_stage_cameras(path: str | Path) -> list[Camera]:
    """The perspective cameras of a USD stage (:func:`sgpor_pipeline.splat_usd.read_usd_cameras`)."""
    from .splat_usd import read_usd_cameras

    path = Path(path)
    try:
        cams = read_usd_cameras(path)
    except (ValueError, TypeError) as e:  # the messages name the file
        raise PipelineError(f"unreadable USD cameras ({e})", path, fix="re-export the stage, or pass its cameras "
                                                                        "in another format") from None
    if not cams:
        raise PipelineError("the USD stage holds no perspective camera; the cameras the Gaussians were trained "
                            "with are needed", path, fix=_CAMERA_FIX)
    return cams


def load_cameras_any(path: str | Path) -> list[Camera]:
    """Cameras from a COLMAP model folder, a transforms.json, an LLFF poses_bounds.npy, a .glb, a USD
    stage or our cameras.json (format detected), their poses checked (:func:`proper_poses`)."""
    path = Path(path)
    return proper_poses(_load_cameras_any(path), path)


def _load_cameras_any(path: Path) -> list[Camera]:
    if not path.exists():
        raise PipelineError("camera file or folder does not exist", path, fix=_CAMERA_FIX)
    if path.is_dir():
        if find_colmap_model(path) is not None:
            return read_colmap_model(path)
        for name in ("transforms.json", "cameras.json"):
            if (path / name).is_file():
                return _load_cameras_any(path / name)
        raise PipelineError("folder holds no COLMAP model (cameras/images .bin or .txt, also looked in "
                            "sparse/0 and 0/) and no transforms.json", path, fix=_CAMERA_FIX)
    if path.suffix.lower() in (".bin", ".txt") and path.stem in ("cameras", "images", "points3D"):
        return read_colmap_model(path.parent)
    if path.suffix.lower() == ".npy":
        return read_llff_poses(path)
    if path.suffix.lower() == ".glb":
        return read_glb_cameras(path)
    if path.suffix.lower() in USD_SUFFIXES:
        return read_stage_cameras(path)
    if path.suffix.lower() != ".json":
        raise PipelineError(f"unrecognised camera file type {path.suffix!r}", path, fix=_CAMERA_FIX)
    data = _read_json(path)
    if isinstance(data, dict) and data.get("format") == CAMERAS_FORMAT:
        try:
            cams = [Camera.from_dict(d) for d in data["cameras"]]
        except (KeyError, TypeError, ValueError) as e:
            raise PipelineError(f"malformed {CAMERAS_FORMAT} file (bad or missing key: {e})", path,
                                fix="re-export the cameras with sgpor-pipeline") from e
        if not cams:
            raise PipelineError("cameras.json has no cameras", path, fix="add at least one camera")
        return cams
    if isinstance(data, dict) and "frames" in data:
        return read_transforms_json(path)
    raise PipelineError("unrecognised JSON: neither a transforms.json (no 'frames') nor a "
                        f"{CAMERAS_FORMAT} file", path, fix=_CAMERA_FIX)
