"""Gaussians and cameras read from a USD stage (``.usd``, ``.usda``, ``.usdc``, ``.usdz``).

The Gaussians are the stage's ``UsdVol.ParticleField3DGaussianSplat`` prims (what our ``usd`` exporter
writes, and NVIDIA's PLY-to-USD converter): ``positions``, ``orientations`` (quaternions, real part
first in USD's ``GfQuatf``), linear ``scales``, ``opacities`` in [0, 1] and the radiance SH,
coefficient-major with ``elementSize`` (degree + 1)^2, each in float or half precision (the ``...h``
attributes). Several prims are concatenated, each mapped by its local-to-world transform (which must be
a similarity: rotation, uniform scale, translation), the SH of lower degrees padded with zeros.

The cameras are its ``UsdGeom.Camera`` prims (perspective ones), in OpenCV's convention. Our exporter
stores each camera's pixel size, name and photo in the prim's custom data (``sgpor:size``,
``sgpor:name``, ``sgpor:image``); a camera without them is read 1080 px high at its apertures' aspect.

Everything is read as stored, in the stage's frame (its up axis and units are not applied): the frame of
the cameras that stage holds.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .scene import Camera

USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
#: OpenCV camera axes (x right, y down, z forward) <-> USD camera axes (x right, y up, looks down -z)
CV_TO_USD_CAMERA = np.diag([1.0, -1.0, -1.0])
DEFAULT_CAMERA_HEIGHT = 1080  # px, for a camera that does not say its pixel size


def open_stage(path: str | Path) -> Any:
    """The USD stage of a file; ValueError naming the file when USD cannot open it."""
    from pxr import Usd

    path = Path(path)
    try:
        stage = Usd.Stage.Open(str(path))
    except Exception as e:  # pxr raises Tf.ErrorException with USD's own diagnostics
        raise ValueError(f"{path}: USD cannot open it ({str(e).strip().splitlines()[-1]})") from None
    if stage is None:
        raise ValueError(f"{path}: USD cannot open it")
    return stage


def _world_matrices(stage: Any, prims: list[Any]) -> list[np.ndarray]:
    """Each prim's local-to-world transform as a 4x4 matrix for column vectors."""
    from pxr import Usd, UsdGeom

    cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    return [np.array(cache.GetLocalToWorldTransform(p), np.float64).T for p in prims]


def _similarity(matrix: np.ndarray, what: str) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) of a 4x4 similarity; ValueError naming ``what`` for a shear or a mirror."""
    A = matrix[:3, :3]
    det = float(np.linalg.det(A))
    s = abs(det) ** (1.0 / 3.0)
    R = A / s if s > 0 else A
    if det <= 0 or np.abs(R @ R.T - np.eye(3)).max() > 1e-5:
        raise ValueError(f"{what}: its transform is not a rotation, uniform scale and translation")
    return s, R, matrix[:3, 3].copy()


def _array(attr_float: Any, attr_half: Any, width: int) -> np.ndarray | None:
    """An attribute's values, float or half precision (whichever is authored), as float64 [N, width]."""
    for attr in (attr_float, attr_half):
        if attr and attr.HasAuthoredValue():
            value = attr.Get()
            if value is not None:
                return np.asarray(value, np.float64).reshape(-1, width)
    return None


def read_usd_gaussians(path: str | Path) -> dict[str, Any]:
    """The stage's Gaussians, in world space: ``means`` [N,3], ``quats`` [N,4] (w, x, y, z), ``scales``
    [N,3] linear, ``opacities`` [N] in [0,1], ``sh`` [N,K,3] (DC first) and ``sh_degree``. No splat prim:
    ValueError; a stage of splat prims with no points gives N = 0."""
    from pxr import UsdVol

    from .orientation import quat_from_matrix, quat_to_matrix, rotate_sh

    path = Path(path)
    stage = open_stage(path)
    prims = [p for p in stage.Traverse() if p.IsA(UsdVol.ParticleField3DGaussianSplat)]
    if not prims:
        raise ValueError(f"{path}: no UsdVol.ParticleField3DGaussianSplat prim in the stage")
    parts = []
    for prim, world in zip(prims, _world_matrices(stage, prims)):
        g = UsdVol.ParticleField3DGaussianSplat(prim)
        where = f"{path}:{prim.GetPath()}"
        means = _array(g.GetPositionsAttr(), g.GetPositionshAttr(), 3)
        scales = _array(g.GetScalesAttr(), g.GetScaleshAttr(), 3)
        if means is None or scales is None:
            raise ValueError(f"{where}: no positions or no scales authored")
        n = len(means)
        quats = _array(g.GetOrientationsAttr(), g.GetOrientationshAttr(), 4)  # GfQuatf: (x, y, z, w) in numpy
        quats = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)) if quats is None else quats[:, [3, 0, 1, 2]]
        opacities = _array(g.GetOpacitiesAttr(), g.GetOpacitieshAttr(), 1)
        opacities = np.ones(n) if opacities is None else opacities[:, 0]
        degree_attr = g.GetRadianceSphericalHarmonicsDegreeAttr()
        degree = int(degree_attr.Get()) if degree_attr and degree_attr.HasAuthoredValue() else 0
        k = (degree + 1) ** 2
        sh = _array(g.GetRadianceSphericalHarmonicsCoefficientsAttr(),
                    g.GetRadianceSphericalHarmonicsCoefficientshAttr(), 3)
        sh = np.zeros((n, k, 3)) if sh is None else sh
        if len(sh) != n * k or len(scales) != n or len(quats) != n or len(opacities) != n:
            raise ValueError(f"{where}: {n} positions but {len(scales)} scales, {len(quats)} orientations, "
                             f"{len(opacities)} opacities and {len(sh)} SH coefficients (degree {degree})")
        sh = sh.reshape(n, k, 3)
        if not np.allclose(world, np.eye(4)):
            s, R, t = _similarity(world, where)
            means = s * means @ R.T + t
            scales = s * scales
            q = quats / np.maximum(np.linalg.norm(quats, axis=1, keepdims=True), 1e-12)
            quats = quat_from_matrix(R @ quat_to_matrix(q))
            sh = np.concatenate([sh[:, :1], rotate_sh(sh[:, 1:], R)], axis=1)
        parts.append((means, quats, scales, opacities, sh, degree))
    degree = max(p[5] for p in parts)
    k = (degree + 1) ** 2
    pad = [np.concatenate([p[4], np.zeros((len(p[0]), k - p[4].shape[1], 3))], axis=1) for p in parts]
    return {"means": np.concatenate([p[0] for p in parts]), "quats": np.concatenate([p[1] for p in parts]),
            "scales": np.concatenate([p[2] for p in parts]), "opacities": np.concatenate([p[3] for p in parts]),
            "sh": np.concatenate(pad), "sh_degree": degree}


def read_usd_cameras(path: str | Path) -> list[Camera]:
    """The stage's perspective ``UsdGeom.Camera`` prims as cameras (see the module doc)."""
    from pxr import UsdGeom

    path = Path(path)
    stage = open_stage(path)
    prims = [p for p in stage.Traverse() if p.IsA(UsdGeom.Camera)]
    cams: list[Camera] = []
    for prim, world in zip(prims, _world_matrices(stage, prims)):
        cam = UsdGeom.Camera(prim)
        if cam.GetProjectionAttr().Get() != UsdGeom.Tokens.perspective:
            continue
        get = {key: float(prim.GetAttribute(key).Get()) for key in (
            "focalLength", "horizontalAperture", "verticalAperture", "horizontalApertureOffset",
            "verticalApertureOffset")}
        ha, va, focal = get["horizontalAperture"], get["verticalAperture"], get["focalLength"]
        size = prim.GetCustomDataByKey("sgpor:size")  # (a key path: the exporter's nested "sgpor" dictionary)
        if size:
            width, height = (int(v) for v in str(size).split("x"))
        else:
            height = DEFAULT_CAMERA_HEIGHT
            width = max(1, round(height * ha / va))
        K = np.array([[focal * width / ha, 0.0, width / 2 - get["horizontalApertureOffset"] * width / ha],
                      [0.0, focal * height / va, height / 2 + get["verticalApertureOffset"] * height / va],
                      [0.0, 0.0, 1.0]])
        rot = world[:3, :3]
        scale = np.linalg.norm(rot, axis=0)
        if np.any(scale <= 0) or not np.all(np.isfinite(world)):
            raise ValueError(f"{path}:{prim.GetPath()}: the camera's transform is degenerate")
        world_from_cam = np.eye(4)
        world_from_cam[:3, :3] = (rot / scale) @ CV_TO_USD_CAMERA  # its own inverse: USD's axes -> OpenCV's
        world_from_cam[:3, 3] = world[:3, 3]
        name = str(prim.GetCustomDataByKey("sgpor:name") or prim.GetName())
        image = prim.GetCustomDataByKey("sgpor:image")
        cams.append(Camera(name, width, height, K, np.linalg.inv(world_from_cam),
                           image=None if image is None else str(image)))
    return cams
