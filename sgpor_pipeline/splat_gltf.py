"""Gaussians as binary glTF with the Khronos extension ``KHR_gaussian_splatting`` (ratified).

One point primitive (``mode`` POINTS) whose vertices are the Gaussians; the attributes, all float32
but ``COLOR_0``, as the extension defines them for its ``ellipse`` kernel:

=============================================  ======  ==============================================
attribute                                      type    value
=============================================  ======  ==============================================
``POSITION``                                   VEC3    centre (with the accessor's min / max, which
                                                       glTF requires)
``KHR_gaussian_splatting:ROTATION``            VEC4    unit quaternion, (x, y, z, w) order
``KHR_gaussian_splatting:SCALE``               VEC3    LINEAR standard deviations (exp of our logs)
``KHR_gaussian_splatting:OPACITY``             SCALAR  sigmoid of the logit, in [0, 1]
``KHR_gaussian_splatting:SH_DEGREE_0_COEF_0``  VEC3    the DC coefficient (colour = 0.2821 c + 0.5)
``KHR_gaussian_splatting:SH_DEGREE_l_COEF_n``  VEC3    degree l >= 1, n = 0 .. 2l (order m = n - l),
                                                       every degree up to the model's
``COLOR_0``                                    VEC4    fallback for viewers without the extension:
                                                       the DC colour in linear RGB (glTF's vertex
                                                       colours are linear), alpha = opacity; bytes
=============================================  ======  ==============================================

The SH basis is INRIA 3DGS's (gsplat's), which is the extension's: real SH with the Condon-Shortley
phase, (r, g, b) per coefficient. ``colorSpace`` is ``srgb_rec709_display``: the photos trained them.
The writer takes the Gaussians as they are: glTF is right-handed with +Y up, so the caller passes them
in such a frame (the ``gltf`` exporter rotates the Z-up export frame with
:data:`sgpor_pipeline.orientation.GLTF_FROM_ZUP`, SH included). Cameras, optionally, become glTF
perspective cameras (glTF cameras look down -Z with +Y up; no principal-point offset in glTF).

Viewers that read it (2026): Babylon.js, PlayCanvas, CesiumJS. :func:`read_splat_glb` reads the files
this module writes and others that follow the extension: float or quantised (normalized byte / short)
attributes, cameras in any node hierarchy (:func:`read_gltf_cameras`). Drafts of the extension said
SCALE holds logarithms, and the text of one version still does; writers (PlayCanvas, Cesium) store the
standard deviations, as we do, and the reader takes a file with negative scales for logarithms. Checked against
PlayCanvas ``splat-transform`` 3.7.0's GLB writer: the same attributes, value for value, but
``COLOR_0``, which it stores sRGB-encoded.
"""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path
from typing import Any

import numpy as np

from .gaussians._raster_common import SH_C0
from .imageio import srgb_to_linear
from .orientation import quat_from_matrix, quat_to_matrix
from .scene import Camera
from .splat_io import write_bytes_atomically

EXTENSION = "KHR_gaussian_splatting"
PREFIX = EXTENSION + ":"
MODE_POINTS = 0
FLOAT, UNSIGNED_BYTE = 5126, 5121  # glTF componentType
#: the component types a reader meets: the extension lets ROTATION, SCALE and OPACITY be quantised to
#: (normalized) signed bytes / shorts or unsigned bytes / shorts
_DTYPES = {5120: np.dtype("i1"), 5121: np.dtype("u1"), 5122: np.dtype("<i2"), 5123: np.dtype("<u2"),
           5125: np.dtype("<u4"), FLOAT: np.dtype("<f4")}
ARRAY_BUFFER = 34962  # bufferView target: vertex attributes
#: OpenCV camera axes (x right, y down, z forward) -> glTF camera axes (x right, y up, looks down -z)
CV_TO_GLTF_CAMERA = np.diag([1.0, -1.0, -1.0])
_COMPONENTS = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}
#: glTF cameras have an aspect ratio and a vertical field of view but no pixel size: a camera without
#: our ``sgpor_size`` extra is read at this height (the pixel scale moves K, not the view)
DEFAULT_CAMERA_HEIGHT = 1080


def sh_attribute(degree: int, n: int) -> str:
    """The attribute name of SH coefficient ``n`` (0 .. 2 degree) of band ``degree``."""
    return f"{PREFIX}SH_DEGREE_{degree}_COEF_{n}"


def _finite(name: str, a: np.ndarray, path: Path) -> np.ndarray:
    if not np.isfinite(a).all():
        bad = int((~np.isfinite(a)).reshape(len(a), -1).any(1).sum())
        raise ValueError(f"{path}: {bad} Gaussians have a non-finite {name}; the model is broken (NaN or inf), "
                         f"refit it or drop those Gaussians before exporting")
    return a


def splat_attributes(model: Any, path: Path | str = "<memory>") -> dict[str, np.ndarray]:
    """The glTF attribute arrays of a GaussianModel, in the extension's activated form."""
    path = Path(path)
    p = model.numpy()
    n = len(model)
    q = _finite("rotation", p["quats"].astype(np.float64), path)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norm > 1e-12, q / np.maximum(norm, 1e-12), np.array([1.0, 0.0, 0.0, 0.0]))
    logit = _finite("opacity", p["opacities"].astype(np.float64), path)
    opacity = 1.0 / (1.0 + np.exp(-logit))
    sh0 = _finite("colour", p["sh0"].reshape(n, 3).astype(np.float64), path)
    out = {
        "POSITION": _finite("position", p["means"].astype(np.float32), path),
        PREFIX + "ROTATION": q[:, [1, 2, 3, 0]].astype(np.float32),
        PREFIX + "SCALE": np.exp(_finite("scale", p["scales"].astype(np.float64), path)).astype(np.float32),
        PREFIX + "OPACITY": opacity.astype(np.float32),
        sh_attribute(0, 0): sh0.astype(np.float32),
    }
    shN = _finite("SH coefficient", p["shN"].astype(np.float32), path)
    for degree in range(1, model.max_sh_degree + 1):
        for k in range(2 * degree + 1):
            out[sh_attribute(degree, k)] = np.ascontiguousarray(shN[:, degree * degree - 1 + k])
    linear = srgb_to_linear(SH_C0 * sh0 + 0.5)
    rgba = np.concatenate([linear, opacity[:, None]], axis=1)
    out["COLOR_0"] = np.clip(np.round(rgba * 255.0), 0, 255).astype(np.uint8)
    return out


def gltf_camera(cam: Camera, znear: float) -> tuple[dict[str, Any], dict[str, Any]]:
    """A glTF perspective camera and the node that places it (rotation xyzw, translation)."""
    fy = float(cam.K[1, 1])
    camera = {"type": "perspective", "name": cam.name,
              "perspective": {"yfov": 2.0 * math.atan(cam.height / (2.0 * fy)),
                              "aspectRatio": cam.width / cam.height, "znear": float(znear)}}
    world_from_cam = cam.world_from_cam
    R = world_from_cam[:3, :3] @ CV_TO_GLTF_CAMERA
    w, x, y, z = quat_from_matrix(R)
    node = {"name": cam.name, "rotation": [float(x), float(y), float(z), float(w)],
            "translation": [float(v) for v in world_from_cam[:3, 3]]}
    extras = {"sgpor_size": [cam.width, cam.height]}
    if cam.image is not None:
        extras["sgpor_image"] = cam.image
    node["extras"] = extras
    return camera, node


def build_glb(attributes: dict[str, np.ndarray], cameras: list[Camera] | None = None, znear: float = 0.01,
              generator: str = "sgpor-pipeline", extras: dict[str, Any] | None = None) -> bytes:
    """The GLB bytes of one splat primitive (``attributes`` from :func:`splat_attributes`) and cameras.
    Without Gaussians (everything deleted) there is no primitive, since glTF forbids empty accessors."""
    count = len(next(iter(attributes.values()))) if attributes else 0
    blob = bytearray()
    accessors: list[dict[str, Any]] = []
    views: list[dict[str, Any]] = []
    prim_attrs: dict[str, int] = {}
    for name, a in attributes.items() if count else ():
        a = np.ascontiguousarray(a)
        kind = "SCALAR" if a.ndim == 1 else f"VEC{a.shape[1]}"
        blob += b"\0" * (-len(blob) % 4)  # every view starts 4-byte aligned
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": a.nbytes, "target": ARRAY_BUFFER})
        blob += a.astype(a.dtype.newbyteorder("<"), copy=False).tobytes()
        acc: dict[str, Any] = {"bufferView": len(views) - 1, "count": int(len(a)), "type": kind,
                               "componentType": UNSIGNED_BYTE if a.dtype == np.uint8 else FLOAT}
        if a.dtype == np.uint8:
            acc["normalized"] = True
        if name == "POSITION":  # required for POSITION
            acc["min"] = [float(v) for v in a.min(0)]
            acc["max"] = [float(v) for v in a.max(0)]
        prim_attrs[name] = len(accessors)
        accessors.append(acc)
    blob += b"\0" * (-len(blob) % 4)
    doc: dict[str, Any] = {"asset": {"version": "2.0", "generator": generator}, "scene": 0}
    if extras:
        doc["asset"]["extras"] = extras
    nodes: list[dict[str, Any]] = []
    roots: list[int] = []
    if count:
        primitive = {"attributes": prim_attrs, "mode": MODE_POINTS,
                     "extensions": {EXTENSION: {"kernel": "ellipse", "colorSpace": "srgb_rec709_display",
                                                "projection": "perspective", "sortingMethod": "cameraDistance"}}}
        doc.update({"extensionsUsed": [EXTENSION], "meshes": [{"name": "Gaussians", "primitives": [primitive]}],
                    "accessors": accessors, "bufferViews": views, "buffers": [{"byteLength": len(blob)}]})
        roots.append(len(nodes))
        nodes.append({"name": "Gaussians", "mesh": 0})
    if cameras:
        gl_cams = []
        first = len(nodes)
        for cam in cameras:
            c, node = gltf_camera(cam, znear)
            node["camera"] = len(gl_cams)
            gl_cams.append(c)
            nodes.append(node)
        doc["cameras"] = gl_cams
        roots.append(len(nodes))
        nodes.append({"name": "Cameras", "children": list(range(first, len(nodes)))})
    doc["nodes"] = nodes
    doc["scenes"] = [{"nodes": roots}]
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)  # the JSON chunk is padded with spaces
    if 12 + 8 + len(text) + 8 + len(blob) >= 1 << 32:
        raise ValueError(f"{count:,} Gaussians make a GLB over glTF's 4 GB limit ({(len(blob) + len(text)) / 1e9:.1f} "
                         f"GB): export scene.spz instead, or fewer Gaussians (fit.budget)")
    chunks = struct.pack("<I4s", len(text), b"JSON") + text
    if blob:
        chunks += struct.pack("<I4s", len(blob), b"BIN\0") + bytes(blob)
    return struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks


def write_splat_glb(path: str | Path, model: Any, cameras: list[Camera] | None = None, znear: float = 0.01,
                    extras: dict[str, Any] | None = None) -> Path:
    """Write a GaussianModel (already in a Y-up frame) and optional cameras as a GLB, atomically."""
    path = Path(path)
    attributes = splat_attributes(model, path)
    try:
        data = build_glb(attributes, cameras, znear, extras=extras)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
    return write_bytes_atomically(path, data)


def read_glb(path: str | Path) -> tuple[dict[str, Any], bytes]:
    """A GLB's JSON document and binary chunk (header, lengths and chunk types checked)."""
    path = Path(path)
    data = path.read_bytes()
    if len(data) < 20 or data[:4] != b"glTF":
        raise ValueError(f"{path}: not a binary glTF file (no 'glTF' magic)")
    version, total = struct.unpack_from("<II", data, 4)
    json_len, json_type = struct.unpack_from("<I4s", data, 12)
    if version != 2 or total != len(data) or json_type != b"JSON" or 20 + json_len > len(data):
        raise ValueError(f"{path}: a damaged or unsupported GLB (version {version}, {total} bytes declared, "
                         f"{len(data)} present)")
    doc = json.loads(data[20:20 + json_len])
    rest = data[20 + json_len:]
    binary = b""
    if len(rest) >= 8:
        bin_len, bin_type = struct.unpack_from("<I4s", rest)
        if bin_type != b"BIN\0" or 8 + bin_len > len(rest):
            raise ValueError(f"{path}: the GLB's binary chunk is damaged")
        binary = rest[8:8 + bin_len]
    return doc, binary


def _accessor(doc: dict[str, Any], binary: bytes, index: int) -> np.ndarray:
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    comps = _COMPONENTS[acc["type"]]
    dtype = _DTYPES[acc["componentType"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    stride = view.get("byteStride", comps * dtype.itemsize)
    count = acc["count"]
    raw = np.frombuffer(binary, np.uint8, max(0, (count - 1) * stride + comps * dtype.itemsize) if count else 0,
                        start)
    if count and stride != comps * dtype.itemsize:
        rows = np.lib.stride_tricks.as_strided(raw, (count, comps * dtype.itemsize), (stride, 1))
        raw = np.ascontiguousarray(rows).reshape(-1)
    out = raw.view(dtype).reshape((count, comps) if comps > 1 else (count,))
    if dtype.kind == "f":
        return out
    if acc.get("normalized"):  # glTF's decoding: c / max, signed ones clamped at -1
        return np.maximum(out.astype(np.float32) / np.iinfo(dtype).max, -1.0)
    return out.astype(np.float32)


def read_splat_glb(path: str | Path) -> dict[str, Any]:
    """The first ``KHR_gaussian_splatting`` primitive of a GLB: ``means`` [N,3], ``quats`` [N,4] (w, x,
    y, z), ``scales`` [N,3] linear, ``opacities`` [N] in [0,1], ``sh`` [N,K,3] (DC first), ``sh_degree``,
    ``color`` [N,4] (COLOR_0, or None), and ``cameras``: (glTF camera, node) pairs."""
    path = Path(path)
    doc, binary = read_glb(path)
    for mesh in doc.get("meshes", []):
        for prim in mesh.get("primitives", []):
            if EXTENSION in prim.get("extensions", {}):
                attrs = prim["attributes"]
                get = {name: _accessor(doc, binary, i) for name, i in attrs.items()}
                degree = 0
                while sh_attribute(degree + 1, 0) in get:
                    degree += 1
                sh = [get[sh_attribute(d, k)] for d in range(degree + 1) for k in range(2 * d + 1)]
                q = get[PREFIX + "ROTATION"]
                cams = [(doc["cameras"][n["camera"]], n) for n in doc.get("nodes", []) if "camera" in n]
                return {"means": get["POSITION"], "quats": q[:, [3, 0, 1, 2]], "scales": get[PREFIX + "SCALE"],
                        "opacities": get[PREFIX + "OPACITY"], "sh": np.stack(sh, axis=1), "sh_degree": degree,
                        "color": get.get("COLOR_0"), "cameras": cams, "document": doc}
    raise ValueError(f"{path}: no primitive with the {EXTENSION} extension")


def _node_matrix(node: dict[str, Any]) -> np.ndarray:
    """A node's local transform (its ``matrix``, column-major, or translation x rotation x scale)."""
    if "matrix" in node:
        return np.asarray(node["matrix"], np.float64).reshape(4, 4).T
    m = np.eye(4)
    x, y, z, w = node.get("rotation", (0.0, 0.0, 0.0, 1.0))
    m[:3, :3] = quat_to_matrix(np.array([w, x, y, z])) * np.asarray(node.get("scale", (1.0, 1.0, 1.0)))
    m[:3, 3] = node.get("translation", (0.0, 0.0, 0.0))
    return m


def read_gltf_cameras(doc: dict[str, Any], path: Path | str = "<memory>") -> list[Camera]:
    """The perspective cameras placed by a glTF document's nodes (parents' transforms applied), in our
    convention (OpenCV axes, pinhole K with the principal point at the centre). The pixel size comes
    from :func:`gltf_camera`'s ``sgpor_size`` extra when the file has it, else
    :data:`DEFAULT_CAMERA_HEIGHT` and the aspect ratio. Orthographic cameras are left out."""
    nodes = doc.get("nodes", [])
    parent = {child: i for i, n in enumerate(nodes) for child in n.get("children", [])}
    cameras = []
    for index, node in enumerate(nodes):
        if "camera" not in node:
            continue
        gl = doc["cameras"][node["camera"]]
        if gl.get("type") != "perspective":
            continue
        world, i, seen = _node_matrix(node), index, {index}
        while i in parent:
            i = parent[i]
            if i in seen:
                raise ValueError(f"{path}: the glTF node hierarchy has a cycle at node {i}")
            seen.add(i)
            world = _node_matrix(nodes[i]) @ world
        rot = world[:3, :3]
        scale = np.linalg.norm(rot, axis=0)
        if np.any(scale <= 0) or not np.all(np.isfinite(world)):
            raise ValueError(f"{path}: camera node {node.get('name', index)!r} has a degenerate transform")
        extras = node.get("extras", {})
        persp = gl["perspective"]
        if "sgpor_size" in extras:
            width, height = (int(v) for v in extras["sgpor_size"])
        else:
            height = DEFAULT_CAMERA_HEIGHT
            width = max(1, round(height * float(persp.get("aspectRatio", 1.0))))
        fy = height / (2.0 * math.tan(float(persp["yfov"]) / 2.0))
        K = np.array([[fy, 0.0, width / 2.0], [0.0, fy, height / 2.0], [0.0, 0.0, 1.0]])
        world_from_cam = np.eye(4)
        world_from_cam[:3, :3] = (rot / scale) @ CV_TO_GLTF_CAMERA  # its own inverse: glTF axes -> OpenCV's
        world_from_cam[:3, 3] = world[:3, 3]
        name = node.get("name") or gl.get("name") or f"camera{len(cameras)}"
        cameras.append(Camera(name, width, height, K, np.linalg.inv(world_from_cam), image=extras.get("sgpor_image")))
    return cameras
