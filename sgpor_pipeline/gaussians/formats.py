"""Gaussians from the splat files other tools write: ``.ply`` (INRIA 3DGS layout), ``.spz`` (Niantic),
``.splat`` (antimatter15), ``.glb`` (glTF's ``KHR_gaussian_splatting``), PlayCanvas's SOG (a ``.sog``
bundle, or an unbundled SOG's ``meta.json``) and USD (``.usd``, ``.usda``, ``.usdc``, ``.usdz``:
``UsdVol.ParticleField3DGaussianSplat``), as one
:class:`~sgpor_pipeline.gaussians.model.GaussianModel`.

Frames: a 3DGS PLY is in its trainer's frame, the frame of its COLMAP cameras (x right, y down, z
forward: RDF). ``.splat`` stores the PLY's positions as they were (antimatter15's ``convert.py``), so
it is read as stored, and so is a SOG (:mod:`sgpor_pipeline.splat_sog`: splat-transform reads it into the
PLY's frame). SPZ defines its frame as RUB (x right, y up, z back); the reference library
converts a PLY to it on the way in (y and z negated) and back on the way out when asked for RDF, so
an ``.spz`` is turned back into the PLY's frame by default (``spz_frame="ply"``: a half turn about x,
orientations and SH rotated with it) and kept as stored with ``spz_frame="stored"``. A ``.glb`` is
read as stored, in glTF's frame (+Y up), the frame of the glTF cameras it may carry
(:func:`sgpor_pipeline.splat_gltf.read_gltf_cameras`): no PLY frame is recorded in it to go back to.
A USD stage is read as stored too, in its world frame (:mod:`sgpor_pipeline.splat_usd`), the frame of
its cameras.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from sgpor_pipeline.errors import PipelineError

from .model import GaussianModel, inverse_sigmoid

GAUSSIAN_SUFFIXES = (".ply", ".spz", ".splat", ".glb", ".sog", ".usd", ".usda", ".usdc", ".usdz")
#: an unbundled SOG is named by its meta.json (the WebP images beside it)
GAUSSIAN_FILE_NAMES = ("meta.json",)
SpzFrame = Literal["ply", "stored"]
SPZ_FRAMES: tuple[str, ...] = ("ply", "stored")
MAX_SH_DEGREE = 3  # the rasterizer's and the PLY layout's highest SH degree
#: RUB -> RDF: x kept, y and z negated (a proper rotation: the half turn about x)
RUB_TO_RDF = np.diag([1.0, -1.0, -1.0])


def model_from_activated(means: np.ndarray, quats_wxyz: np.ndarray, log_scales: np.ndarray,
                         opacities: np.ndarray, sh0: np.ndarray, shN: np.ndarray, sh_degree: int) -> GaussianModel:
    """A GaussianModel (pre-activation float32 parameters) from activated opacities in [0, 1]; ``sh0``
    [N,1,3] and ``shN`` [N,K-1,3] in the 3DGS SH basis. Opacities 0 and 1 (a byte of 0 or 255), which
    have no finite logit, are clamped by :func:`~sgpor_pipeline.gaussians.model.inverse_sigmoid`."""
    n = len(means)

    def f32(a: np.ndarray, *shape: int) -> torch.Tensor:  # a writable copy (the readers' arrays may be views)
        return torch.from_numpy(np.array(a, np.float32).reshape(n, *shape))

    tensors = {"means": f32(means, 3), "quats": f32(quats_wxyz, 4), "scales": f32(log_scales, 3),
               "opacities": inverse_sigmoid(f32(opacities)), "sh0": f32(sh0, 1, 3),
               "shN": f32(shN, (sh_degree + 1) ** 2 - 1, 3)}
    return GaussianModel(tensors, sh_degree)


def read_spz_model(path: str | Path, frame: SpzFrame = "ply") -> GaussianModel:
    """An ``.spz`` file as a GaussianModel, in the PLY's frame (``frame="ply"``) or as stored."""
    from sgpor_pipeline.orientation import Similarity, transform_model
    from sgpor_pipeline.spz_io import read_spz

    if frame not in SPZ_FRAMES:
        raise ValueError(f"spz frame {frame!r}: choose from {SPZ_FRAMES}")
    d = read_spz(path)
    degree, shN = _highest_bands(path, int(d["sh_degree"]), d["shN"])
    model = model_from_activated(d["means"], d["quats"], d["scales"], d["opacities"], d["sh0"], shN, degree)
    return transform_model(model, Similarity(1.0, RUB_TO_RDF)) if frame == "ply" else model


def _highest_bands(path: str | Path, degree: int, shN: np.ndarray) -> tuple[int, np.ndarray]:
    """SH up to the rasterizer's degree (the bands up to 3 are exact without the higher ones)."""
    if degree <= MAX_SH_DEGREE:
        return degree, shN
    logging.getLogger("sgpor_pipeline").warning(
        f"{path}: SH degree {degree}; the rasterizer renders up to {MAX_SH_DEGREE}, the higher bands are dropped")
    return MAX_SH_DEGREE, shN[:, :(MAX_SH_DEGREE + 1) ** 2 - 1]


def read_glb_model(path: str | Path) -> GaussianModel:
    """The ``KHR_gaussian_splatting`` primitive of a ``.glb`` as a GaussianModel, as stored (glTF's
    frame). A GLB without meshes (our exporter's file of no Gaussians) is an empty model; one whose
    meshes are not Gaussians raises ValueError."""
    from sgpor_pipeline.splat_gltf import EXTENSION as EXTENSION_NAME
    from sgpor_pipeline.splat_gltf import read_glb, read_splat_glb

    doc, _ = read_glb(path)
    if not doc.get("meshes"):
        return GaussianModel.empty(0, 0)
    try:
        d = read_splat_glb(path)
    except (KeyError, IndexError) as e:  # a missing attribute, accessor or component type
        raise ValueError(f"{path}: its {EXTENSION_NAME} primitive is incomplete or of a layout not read here "
                         f"(float32 attributes; {type(e).__name__} {e})") from None
    degree, sh = _highest_bands(path, int(d["sh_degree"]), d["sh"][:, 1:])
    scales = np.asarray(d["scales"], np.float64)
    if (scales < 0).any():
        # linear standard deviations are never negative: a writer that followed the drafts of the
        # extension that stored them as logs (as a 3DGS PLY does)
        logging.getLogger("sgpor_pipeline").warning(
            f"{path}: negative {EXTENSION_NAME}:SCALE values, so its scales are read as logarithms (as "
            "drafts of the extension stored them), not as the standard deviations themselves")
        log_scales = scales
    else:
        with np.errstate(divide="ignore"):  # a zero scale (a flat Gaussian) is kept as the smallest float
            log_scales = np.log(np.maximum(scales, np.finfo(np.float32).tiny))
    return model_from_activated(d["means"], d["quats"], log_scales, d["opacities"], d["sh"][:, :1], sh, degree)


def read_usd_model(path: str | Path) -> GaussianModel:
    """The ``ParticleField3DGaussianSplat`` prims of a USD stage as one GaussianModel, in the stage's world
    frame (:func:`sgpor_pipeline.splat_usd.read_usd_gaussians`)."""
    from sgpor_pipeline.splat_usd import read_usd_gaussians

    d = read_usd_gaussians(path)
    degree, sh = _highest_bands(path, int(d["sh_degree"]), d["sh"][:, 1:])
    with np.errstate(divide="ignore"):  # a zero scale (a flat Gaussian) is kept as the smallest float
        log_scales = np.log(np.maximum(d["scales"], np.finfo(np.float32).tiny))
    return model_from_activated(d["means"], d["quats"], log_scales, d["opacities"], d["sh"][:, :1], sh, degree)


def read_splat_model(path: str | Path) -> GaussianModel:
    """A ``.splat`` file as a GaussianModel of SH degree 0 (the format keeps the DC colour only)."""
    from sgpor_pipeline.splat_io import SH_C0, read_splat

    d = read_splat(path)
    n = len(d["means"])
    with np.errstate(divide="ignore"):  # a zero scale (a flat Gaussian) is kept as the smallest float
        log_scales = np.log(np.maximum(d["scales"].astype(np.float64), np.finfo(np.float32).tiny))
    q = d["quats"].astype(np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norm > 1e-6, q / np.maximum(norm, 1e-12), np.array([1.0, 0.0, 0.0, 0.0]))
    sh0 = (d["colors"].astype(np.float64) - 0.5) / SH_C0
    return model_from_activated(d["means"], q, log_scales, d["opacities"], sh0, np.zeros((n, 0, 3)), 0)


def read_sog_model(path: str | Path) -> GaussianModel:
    """A SOG (``.sog`` bundle or unbundled ``meta.json``) as a GaussianModel, as stored (the PLY's frame)."""
    from sgpor_pipeline.splat_sog import read_sog

    d = read_sog(path)
    return model_from_activated(d["means"], d["quats"], d["scales"], d["opacities"], d["sh0"], d["shN"],
                                int(d["sh_degree"]))


def load_gaussians_any(path: str | Path, spz_frame: SpzFrame = "ply") -> GaussianModel:
    """The Gaussians of a ``.ply`` / ``.spz`` / ``.splat`` / ``.glb`` / SOG / USD file, by its suffix, in the
    frame its cameras use (see the module doc). Raises :class:`PipelineError` naming the file when it cannot be read."""
    from .ply import read_ply

    path = Path(path)
    suffix = path.suffix.lower()
    if spz_frame not in SPZ_FRAMES:
        raise PipelineError(f"unknown .spz frame {spz_frame!r}", fix=f"use one of {', '.join(SPZ_FRAMES)}")
    known = suffix in GAUSSIAN_SUFFIXES or path.name.lower() in GAUSSIAN_FILE_NAMES
    if not known or not path.is_file():
        raise PipelineError(f"not a {', '.join(GAUSSIAN_SUFFIXES + GAUSSIAN_FILE_NAMES)} file" if path.is_file()
                            else "no such file", path=path,
                            fix="give the trainer's 3DGS PLY, or its .spz, .splat, .glb, .sog or USD file")
    if suffix == ".ply":
        return read_ply(path)
    try:
        readers = {".spz": lambda: read_spz_model(path, spz_frame), ".splat": lambda: read_splat_model(path),
                   ".glb": lambda: read_glb_model(path), ".sog": lambda: read_sog_model(path),
                   ".json": lambda: read_sog_model(path)}
        model = readers[suffix]() if suffix in readers else read_usd_model(path)
    except ValueError as e:  # the readers' messages name the file already
        what = "SOG folder (meta.json and its WebP images)" if suffix == ".json" else f"{suffix} file"
        raise PipelineError(str(e), fix=f"give an intact {what}, or the trainer's PLY") from None
    bad = model.non_finite()
    if bad:
        raise PipelineError(f"non-finite values in {', '.join(bad)}", path=path,
                            fix="export the Gaussians again from their trainer")
    return model
