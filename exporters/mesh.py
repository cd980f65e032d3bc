"""mesh: a coloured triangle mesh of the scene, fused from depth rendered from the Gaussians.

``mesh.glb`` (glTF: Y up and linear vertex colours, as glTF requires), ``mesh.obj`` and ``mesh.ply``
(export frame: Z up, sRGB vertex colours). How the mesh is made: :mod:`sgpor_pipeline.meshing`.
"""

from __future__ import annotations

import json
import struct
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sgpor_pipeline.dag import Exporter, StageContext
from sgpor_pipeline.imageio import srgb_to_linear
from sgpor_pipeline.meshing import MeshData, MeshSettings, mesh_from_gaussians, unit_normals
from sgpor_pipeline.orientation import GLTF_FROM_ZUP, ExportFrame
from sgpor_pipeline.scene import Camera

from .gaussians import (
    CAMERAS_STAGE,
    GPS_STAGE,
    POSES_STAGE,
    SCENE_STAGE,
    export_frame,
    load_run_cameras,
    load_scene,
    registered,
    scene_background,
    scene_radius,
)

MESH_FILE = "mesh.ply"
GLTF_ARRAY_BUFFER = 34962  # a buffer view's target: vertex attributes
GLTF_ELEMENT_ARRAY_BUFFER = 34963  # ... indices


def _trimesh(mesh: MeshData, rotation: np.ndarray | None = None, linear_colours: bool = False):
    import trimesh

    v = np.asarray(mesh.vertices, np.float64)
    n = unit_normals(v, mesh.faces, mesh.normals)  # (glTF requires unit length)
    if rotation is not None:
        v = v @ rotation.T
        n = n @ rotation.T
    colours = srgb_to_linear(mesh.colors) if linear_colours else mesh.colors
    rgba = np.concatenate([np.clip(np.round(colours * 255), 0, 255).astype(np.uint8),
                           np.full((len(v), 1), 255, np.uint8)], axis=1)
    return trimesh.Trimesh(v, np.asarray(mesh.faces, np.int64), vertex_normals=n, vertex_colors=rgba, process=False)


def glb_with_buffer_targets(glb: bytes) -> bytes:
    """The GLB with each buffer view that holds vertex attributes or indices marked as such
    (``target`` ARRAY_BUFFER / ELEMENT_ARRAY_BUFFER), which trimesh leaves out and the Khronos glTF
    validator asks for (BUFFER_VIEW_TARGET_MISSING); engines use it to upload the buffers."""
    magic, version, _ = struct.unpack_from("<4sII", glb)
    json_len, json_type = struct.unpack_from("<I4s", glb, 12)
    if magic != b"glTF" or version != 2 or json_type != b"JSON":
        raise ValueError("not a binary glTF 2.0 file")
    doc = json.loads(glb[20:20 + json_len])
    views = doc.get("bufferViews", [])
    for mesh in doc.get("meshes", []):
        for prim in mesh.get("primitives", []):
            pairs = [(a, GLTF_ARRAY_BUFFER) for a in prim.get("attributes", {}).values()]
            if "indices" in prim:
                pairs.append((prim["indices"], GLTF_ELEMENT_ARRAY_BUFFER))
            for accessor, target in pairs:
                view = doc["accessors"][accessor].get("bufferView")
                if view is not None:
                    views[view]["target"] = target
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)  # (chunks are 4-byte aligned, JSON padded with spaces)
    rest = glb[20 + json_len:]  # the binary chunk, unchanged
    header = struct.pack("<4sII", b"glTF", 2, 12 + 8 + len(text) + len(rest))
    return header + struct.pack("<I4s", len(text), b"JSON") + text + rest


def write_mesh(mesh: MeshData, folder: Path, stem: str = "mesh",
               formats: Sequence[str] = ("glb", "obj", "ply")) -> list[Path]:
    """Write a mesh given in the Z-up export frame: ``.glb`` rotated to Y up with its vertex colours
    linear (glTF's COLOR_0; the photos' sRGB values read as linear look washed out in glTF viewers),
    ``.obj``/``.ply`` as is (sRGB colours)."""
    written = []
    for fmt in formats:
        path = Path(folder) / f"{stem}.{fmt}"
        gltf = fmt in ("glb", "gltf")  # Y up, and vertex colours linear as glTF defines them
        tm = _trimesh(mesh, GLTF_FROM_ZUP if gltf else None, linear_colours=gltf)
        if fmt == "obj":
            data = tm.export(file_type="obj", include_color=True, include_normals=True)
            path.write_text(data)
        elif fmt == "glb":
            path.write_bytes(glb_with_buffer_targets(tm.export(file_type="glb")))
        else:
            tm.export(path, file_type=fmt)
        written.append(path)
    return written


def read_mesh_ply(path: Path) -> MeshData:
    """A mesh written by :func:`write_mesh` as ``.ply`` (export frame)."""
    import trimesh

    tm = trimesh.load(path, process=False, force="mesh")
    colors = np.asarray(tm.visual.vertex_colors)[:, :3].astype(np.float32) / 255.0 if tm.visual.kind == "vertex" \
        else np.full((len(tm.vertices), 3), 0.5, np.float32)
    return MeshData(np.asarray(tm.vertices, np.float64), np.asarray(tm.faces, np.int64), colors,
                    np.asarray(tm.vertex_normals, np.float64))


def scene_mesh(ctx: StageContext, out_dir: Path, model: Any = None, cameras: list[Camera] | None = None,
               frame: ExportFrame | None = None) -> MeshData:
    """The scene mesh in the export frame: ``mesh.ply`` of this export run when the mesh exporter
    already wrote it, else made now (not written)."""
    path = out_dir / MESH_FILE
    if path.is_file():
        return read_mesh_ply(path)
    model = model if model is not None else load_scene(ctx)
    cameras = cameras if cameras is not None else load_run_cameras(ctx)
    frame = frame or export_frame(ctx, model, cameras, out_dir)
    return _make_mesh(ctx, model, cameras).transformed(frame.transform)


def _make_mesh(ctx: StageContext, model, cameras) -> MeshData:
    cams = registered(cameras) or cameras
    return mesh_from_gaussians(model, cams, MeshSettings.from_params(ctx.params),
                               scene_radius=scene_radius(ctx, model, cams), background=scene_background(ctx),
                               progress=ctx.progress)


class MeshExporter(Exporter):
    name = "mesh"
    VERSION = 5  # 2: unit normals everywhere (glTF requires them; a decimation fold left zeros); GLB buffer targets;
    # 3: decimated by fast-simplification (meshing.decimate); 4: the scene radius from the SfM points where the
    # viewing axes mislead (forward-facing captures: statue's mesh had lost all beyond 45 units), one canonical order;
    # 5: mesh.glb's vertex colours linear (glTF's COLOR_0)
    needs = (CAMERAS_STAGE, POSES_STAGE, SCENE_STAGE)
    optional_needs = (GPS_STAGE,)
    description = "a coloured mesh (TSDF of rendered depth) as mesh.glb (Y up), mesh.obj and mesh.ply (Z up)"
    outputs = ("mesh.glb", "mesh.obj", "mesh.ply")

    def export(self, ctx: StageContext, out_dir: Path) -> None:
        t0 = time.perf_counter()
        model = load_scene(ctx)
        cameras = load_run_cameras(ctx)
        frame = export_frame(ctx, model, cameras, out_dir)
        mesh = _make_mesh(ctx, model, cameras)
        if len(mesh) == 0:
            ctx.log.warning("mesh: the fused mesh is empty (no opaque surface seen by the cameras): "
                            "no mesh files written")
            return
        files = write_mesh(mesh.transformed(frame.transform), out_dir, "mesh")
        ctx.log.info(f"mesh: {len(mesh)} faces, {len(mesh.vertices)} vertices -> "
                     f"{', '.join(p.name for p in files)} in {time.perf_counter() - t0:.1f} s")
