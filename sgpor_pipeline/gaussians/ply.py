"""INRIA 3DGS PLY files (the layout of the original 3DGS code, read by every splat viewer).

One ``vertex`` element, binary little-endian float32, properties in this order::

    x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 ... f_rest_{3(K-1)-1} opacity
    scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3

with pre-activation values (log-scales, opacity logits, unnormalised (w,x,y,z) quaternions; normals
are zero) and ``f_rest`` channel-major: all red coefficients 1..K-1, then green, then blue, i.e.
``shN`` [N,K-1,3] transposed to [N,3,K-1] and flattened. Writing and reading are exact: float32 in,
the same float32 bits out.

:func:`read_ply` also reads PlayCanvas's compressed PLY (``.compressed.ply``, what SuperSplat saves and
splat-transform writes): 16 bytes a Gaussian, its values quantised within 256-Gaussian chunks.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import torch

from ..errors import PipelineError
from ._raster_common import SH_C0
from .model import GaussianModel

_PLY_TYPES = {"float": "f4", "float32": "f4", "double": "f8", "float64": "f8", "uchar": "u1", "uint8": "u1",
              "char": "i1", "int8": "i1", "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
              "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4"}


def property_names(max_sh_degree: int) -> list[str]:
    """The vertex properties of a PLY holding SH up to ``max_sh_degree``, in file order."""
    k = (max_sh_degree + 1) ** 2
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * (k - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def model_to_array(model: GaussianModel) -> np.ndarray:
    """[N, P] float32 rows in the property order of :func:`property_names`."""
    p = model.numpy()
    n = len(model)
    shn = p["shN"]  # (the explicit width: reshape(0, -1) is ambiguous for an empty model)
    rest = np.ascontiguousarray(shn.transpose(0, 2, 1)).reshape(n, shn.shape[1] * shn.shape[2])  # channel-major
    cols = [p["means"], np.zeros((n, 3), np.float32), p["sh0"].reshape(n, 3), rest,
            p["opacities"].reshape(n, 1), p["scales"], p["quats"]]
    return np.concatenate(cols, axis=1).astype(np.float32, copy=False)


def write_ply(path: str | Path, model: GaussianModel) -> Path:
    """Write ``model`` as an INRIA 3DGS PLY, atomically (temporary file, then ``os.replace``)."""
    path = Path(path)
    names = property_names(model.max_sh_degree)
    data = model_to_array(model)
    if not np.isfinite(data).all():
        bad = [n for n, a in model.numpy().items() if not np.isfinite(a).all()]
        raise PipelineError(f"refusing to write Gaussians with NaN/inf values in {bad}", path=path,
                            fix="the fit diverged: rerun with lower learning rates")
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(model)}"]
    header += [f"property float {n}" for n in names]
    header += ["end_header"]
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(data.astype("<f4", copy=False).tobytes())
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    return path


def _parse_header(f) -> tuple[str, list[tuple[str, int, list[tuple[str, str]]]]]:
    first = f.readline()
    if first.strip() != b"ply":
        raise PipelineError("not a PLY file", path=getattr(f, "name", None))
    fmt = ""
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    while True:
        line = f.readline()
        if not line:
            raise PipelineError("PLY header has no end_header", path=getattr(f, "name", None))
        words = line.decode("ascii", "replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            return fmt, elements
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if words[1] == "list":
                raise PipelineError("PLY list properties are not supported in a Gaussian file",
                                    path=getattr(f, "name", None))
            if words[1] not in _PLY_TYPES:
                raise PipelineError(f"unknown PLY property type '{words[1]}'", path=getattr(f, "name", None))
            elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))


#: the compressed PLY of PlayCanvas (SuperSplat, splat-transform): 256 Gaussians per chunk, each packed into
#: four uint32 within its chunk's bounds; SH as bytes in an ``sh`` element
COMPRESSED_CHUNK = 256
_PACKED = ("packed_position", "packed_rotation", "packed_scale", "packed_color")


def _unorm(value: np.ndarray, shift: int, bits: int) -> np.ndarray:
    return ((value >> np.uint32(shift)) & np.uint32((1 << bits) - 1)).astype(np.float64) / ((1 << bits) - 1)


def unpack_compressed(chunk: np.ndarray, vertex: np.ndarray, sh: np.ndarray | None,
                      path: Path) -> dict[str, np.ndarray]:
    """The INRIA properties (pre-activation) of a compressed PLY's ``chunk`` / ``vertex`` / ``sh`` rows:
    positions and log-scales 11-10-11 bits between their chunk's bounds, the quaternion's three smallest
    components in 10 bits each (the 2 high bits say which ``rot_i`` is the largest), RGBA in bytes
    (between the chunk's colour bounds when it has them), SH in bytes over [-4, 4]."""
    n = len(vertex)
    if len(chunk) != -(-n // COMPRESSED_CHUNK):
        raise PipelineError(f"compressed PLY: {len(chunk)} chunks for {n} Gaussians (256 per chunk)", path=path)
    ci = np.arange(n) // COMPRESSED_CHUNK
    names = set(chunk.dtype.names or ())

    def bounded(t: np.ndarray, lo: str, hi: str) -> np.ndarray:
        a, b = chunk[lo][ci].astype(np.float64), chunk[hi][ci].astype(np.float64)
        return a * (1 - t) + b * t

    out: dict[str, np.ndarray] = {}
    for packed, prefix, (ax, ay, az) in (("packed_position", "", ("x", "y", "z")),
                                         ("packed_scale", "scale_", ("0", "1", "2"))):
        v = vertex[packed].astype(np.uint32)
        lo = "min_" if not prefix else "min_scale_"
        hi = "max_" if not prefix else "max_scale_"
        for name, axis, (shift, bits) in zip((ax, ay, az), "xyz", ((21, 11), (11, 10), (0, 11))):
            out[prefix + name] = bounded(_unorm(v, shift, bits), lo + axis, hi + axis)
    r = vertex["packed_rotation"].astype(np.uint32)
    small = np.stack([(_unorm(r, shift, 10) - 0.5) * np.sqrt(2.0) for shift in (20, 10, 0)], axis=1)
    largest = np.sqrt(np.maximum(0.0, 1.0 - (small ** 2).sum(1)))
    which = (r >> np.uint32(30)).astype(np.int64)
    quat = np.empty((n, 4))
    for i in range(4):
        rows = which == i
        quat[rows] = np.insert(small[rows], i, largest[rows], axis=1)
    for i in range(4):
        out[f"rot_{i}"] = quat[:, i]
    c = vertex["packed_color"].astype(np.uint32)
    for i, (channel, shift) in enumerate(zip("rgb", (24, 16, 8))):
        value = _unorm(c, shift, 8)
        if f"min_{channel}" in names:
            value = bounded(value, f"min_{channel}", f"max_{channel}")
        out[f"f_dc_{i}"] = (value - 0.5) / SH_C0
    alpha = np.clip(_unorm(c, 0, 8), 1e-6, 1 - 1e-6)  # bytes 0 and 255 have no finite logit
    out["opacity"] = np.log(alpha / (1 - alpha))
    if sh is not None:
        for name in sh.dtype.names or ():
            b = sh[name].astype(np.float64)
            unit = np.where(b == 0, 0.0, np.where(b == 255, 1.0, (b + 0.5) / 256))
            out[name] = (unit - 0.5) * 8
    return out


def read_ply(path: str | Path) -> GaussianModel:
    """Read an INRIA 3DGS PLY (any SH degree 0..3; float or double properties), or PlayCanvas's
    compressed PLY (:func:`unpack_compressed`), as a model."""
    path = Path(path)
    with open(path, "rb") as f:
        fmt, elements = _parse_header(f)
        if fmt != "binary_little_endian":
            raise PipelineError(f"PLY format '{fmt}' is not supported (binary_little_endian only)", path=path)
        rows: dict[str, np.ndarray] = {}
        for name, count, props in elements:
            dtype = np.dtype([(p, "<" + t) for p, t in props])
            arr = np.fromfile(f, dtype=dtype, count=count)
            if len(arr) != count:
                raise PipelineError(f"PLY is truncated: {len(arr)} of {count} '{name}' rows", path=path)
            rows[name] = arr
            # an INRIA PLY ends with its vertices; a compressed one has chunks before and SH after them
            if name == "vertex" and not set(_PACKED) <= set(arr.dtype.names or ()):
                break
    if "vertex" not in rows:
        raise PipelineError("PLY has no vertex element", path=path)
    data: dict[str, np.ndarray] | np.ndarray = rows["vertex"]
    if set(_PACKED) <= set(rows["vertex"].dtype.names or ()):
        if "chunk" not in rows:
            raise PipelineError("compressed PLY without its chunk element", path=path)
        data = unpack_compressed(rows["chunk"], rows["vertex"], rows.get("sh"), path)
    fields = set(data) if isinstance(data, dict) else set(data.dtype.names or ())
    need = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [n for n in need if n not in fields]
    if missing:
        raise PipelineError(f"not a 3DGS PLY: missing properties {missing}", path=path)
    rest_names = sorted((n for n in fields if re.fullmatch(r"f_rest_\d+", n)), key=lambda s: int(s[7:]))
    n_rest = len(rest_names)
    k_minus_1 = n_rest // 3
    degree = {0: 0, 3: 1, 8: 2, 15: 3}.get(k_minus_1)
    if degree is None or n_rest % 3:
        raise PipelineError(f"{n_rest} f_rest properties do not match an SH degree 0..3", path=path)
    n = len(rows["vertex"])

    def col(*names: str) -> np.ndarray:
        return np.stack([np.asarray(data[c], np.float32) for c in names], axis=1) if names else \
            np.zeros((n, 0), np.float32)

    rest = col(*rest_names).reshape(n, 3, k_minus_1).transpose(0, 2, 1)
    params = {
        "means": torch.from_numpy(col("x", "y", "z").copy()),
        "quats": torch.from_numpy(col("rot_0", "rot_1", "rot_2", "rot_3").copy()),
        "scales": torch.from_numpy(col("scale_0", "scale_1", "scale_2").copy()),
        "opacities": torch.from_numpy(np.asarray(data["opacity"], np.float32).copy()),
        "sh0": torch.from_numpy(col("f_dc_0", "f_dc_1", "f_dc_2").reshape(n, 1, 3).copy()),
        "shN": torch.from_numpy(np.ascontiguousarray(rest)),
    }
    return GaussianModel(params, degree)
