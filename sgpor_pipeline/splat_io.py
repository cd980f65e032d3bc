"""The ``.splat`` format of antimatter15's WebGL viewer (and many web viewers after it).

32 bytes per Gaussian, no header, little-endian::

    position  3 x float32
    scale     3 x float32   linear (exp of the log-scales)
    colour    4 x uint8     RGB = 255 (0.5 + SH_C0 * f_dc), A = 255 sigmoid(opacity logit)
    rotation  4 x uint8     (q / |q|) * 128 + 128, (w, x, y, z) order

Values are clipped to [0, 255] and truncated to integers (``astype(uint8)``), and the Gaussians are
sorted by importance ``exp(scale_0 + scale_1 + scale_2) * sigmoid(opacity)``, largest first, as
the reference converter (``convert.py`` of antimatter15/splat) does; ties keep the file order. Only
the DC colour survives: view-dependent SH terms are dropped by the format.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

SH_C0 = 0.28209479177387814
SPLAT_DTYPE = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
assert SPLAT_DTYPE.itemsize == 32


def splat_order(log_scales: np.ndarray, opacity_logits: np.ndarray) -> np.ndarray:
    """Indices sorting Gaussians by decreasing importance (volume x opacity), stable."""
    ls = np.asarray(log_scales, np.float64)
    importance = np.exp(ls.sum(axis=1)) / (1.0 + np.exp(-np.asarray(opacity_logits, np.float64)))
    return np.argsort(-importance, kind="stable")


def splat_records(means: np.ndarray, log_scales: np.ndarray, quats: np.ndarray, opacity_logits: np.ndarray,
                  sh_dc: np.ndarray) -> np.ndarray:
    """The structured [N] array of ``.splat`` records (sorted) from pre-activation parameters.

    ``sh_dc`` is [N,3] (or [N,1,3]); ``quats`` (w, x, y, z) any norm.
    """
    n = len(means)
    order = splat_order(log_scales, opacity_logits)
    out = np.zeros(n, SPLAT_DTYPE)
    out["position"] = np.asarray(means, np.float32)[order]
    out["scale"] = np.exp(np.asarray(log_scales, np.float32)[order])
    dc = np.asarray(sh_dc, np.float32).reshape(n, 3)[order]
    alpha = (1.0 / (1.0 + np.exp(-np.asarray(opacity_logits, np.float32)[order])))[:, None]
    color = np.concatenate([0.5 + SH_C0 * dc, alpha], axis=1)
    out["rgba"] = np.clip(color * 255, 0, 255).astype(np.uint8)
    q = np.asarray(quats, np.float32)[order]
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    out["rot"] = np.clip(q * 128 + 128, 0, 255).astype(np.uint8)
    return out


def write_bytes_atomically(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file beside it, so a reader never sees half a file
    (the splat formats' writers: ``.splat``, :mod:`.spz_io`, :mod:`.splat_gltf`); the temporary file is
    removed if the write fails."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_splat(path: str | Path, model: object) -> Path:
    """Write a :class:`~sgpor_pipeline.gaussians.model.GaussianModel` as ``.splat`` (atomically)."""
    p = model.numpy()  # type: ignore[attr-defined]
    rec = splat_records(p["means"], p["scales"], p["quats"], p["opacities"], p["sh0"])
    return write_bytes_atomically(path, rec.tobytes())


def read_splat(path: str | Path) -> dict[str, np.ndarray]:
    """Read a ``.splat`` file: ``means`` [N,3], ``scales`` [N,3] linear, ``rgba`` [N,4] uint8,
    ``colors`` [N,3] and ``opacities`` [N] in [0,1], ``quats`` [N,4] (w,x,y,z) decoded to [-1,1]."""
    data = Path(path).read_bytes()
    if len(data) % SPLAT_DTYPE.itemsize:
        raise ValueError(f"{path}: size {len(data)} is not a multiple of 32 bytes: not a .splat file")
    rec = np.frombuffer(data, SPLAT_DTYPE)
    rgba = rec["rgba"].copy()
    return {"means": rec["position"].astype(np.float32), "scales": rec["scale"].astype(np.float32),
            "rgba": rgba, "colors": rgba[:, :3].astype(np.float32) / 255.0,
            "opacities": rgba[:, 3].astype(np.float32) / 255.0,
            "quats": (rec["rot"].astype(np.float32) - 128.0) / 128.0}
