"""usd: the scene for robotics simulators and DCC tools: ``scene.usda``, ``scene.usdc``, ``scene.usdz``.

Stage (Z up, ``metersPerUnit`` 1, ``kilogramsPerUnit`` 1, default prim ``/World``)::

    /World                    Xform
      PhysicsScene            UsdPhysics.Scene (gravity -Z, 9.81)
      Gaussians               UsdVol.ParticleField3DGaussianSplat (positions, orientations, linear
                              scales, opacities in [0,1], SH coefficient-major, elementSize (deg+1)^2;
                              the photos' sRGB, display-referred, as the schema's renderers read it)
      Mesh                    UsdGeom.Mesh, vertex displayColor (linear), static collider
                              (CollisionAPI + MeshCollisionAPI, approximation "none")
      Cameras/<name>          UsdGeom.Camera per input camera (and novel camera), looking down -Z

The mesh is a sibling of the splat prim (a ParticleField is a Gprim: it cannot have children).
Everything is in the export frame (:mod:`sgpor_pipeline.orientation`); without a known scale the unit
is arbitrary and the root layer's ``customLayerData`` says so (``sgpor:units = "arbitrary"``).
The three files hold the same layer: text, binary crate, and the crate zipped as a USDZ package; above
:data:`TEXT_MAX_GAUSSIANS` Gaussians the text file is the root layer's metadata over the crate (a
sublayer), the same stage without hundreds of MB of numbers as text.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from sgpor_pipeline.dag import Exporter, StageContext
from sgpor_pipeline.imageio import srgb_to_linear
from sgpor_pipeline.meshing import MeshData
from sgpor_pipeline.orientation import ExportFrame, quat_to_matrix
from sgpor_pipeline.scene import Camera

from .gaussians import (
    CAMERAS_STAGE,
    GPS_STAGE,
    POSES_STAGE,
    SCENE_STAGE,
    camera_clip,
    export_frame,
    load_run_cameras,
    load_scene,
    registered,
)

#: OpenCV camera axes (x right, y down, z forward) -> USD camera axes (x right, y up, looks down -z)
CV_TO_USD_CAMERA = np.diag([1.0, -1.0, -1.0, 1.0])
HORIZONTAL_APERTURE = 20.955  # USD's default (35 mm film width, in "tenths of a scene unit")


def _valid_names(names: list[str]) -> list[str]:
    from pxr import Tf

    out: list[str] = []
    seen: set[str] = set()
    for n in names:
        base = Tf.MakeValidIdentifier(n) or "camera"
        cand, k = base, 1
        while cand in seen:
            cand = f"{base}_{k}"
            k += 1
        seen.add(cand)
        out.append(cand)
    return out


def gaussian_extent(means: np.ndarray, quats: np.ndarray, scales: np.ndarray, sigmas: float = 3.0) -> np.ndarray:
    """[2,3] bounds of the Gaussians' ``sigmas``-sigma ellipsoids (linear ``scales``)."""
    if len(means) == 0:
        return np.zeros((2, 3))
    R = quat_to_matrix(quats)
    half = sigmas * np.sqrt(((R * np.asarray(scales, np.float64)[:, None, :]) ** 2).sum(-1))
    return np.stack([(means - half).min(0), (means + half).max(0)])


def add_gaussians(stage: Any, path: str, model: Any) -> Any:
    """Define a ParticleField3DGaussianSplat at ``path`` from a GaussianModel (activated values)."""
    from pxr import UsdVol, Vt

    p = model.numpy()
    n = len(model)
    k = (model.max_sh_degree + 1) ** 2
    q = p["quats"].astype(np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    scales = np.exp(p["scales"].astype(np.float64))
    opac = 1.0 / (1.0 + np.exp(-p["opacities"].astype(np.float64)))
    sh = np.concatenate([p["sh0"], p["shN"]], axis=1).reshape(n * k, 3)

    g = UsdVol.ParticleField3DGaussianSplat.Define(stage, path)
    g.CreatePositionsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(p["means"], np.float32)))
    g.CreateOrientationsAttr(Vt.QuatfArray.FromNumpy(np.ascontiguousarray(q[:, [1, 2, 3, 0]], np.float32)))
    g.CreateScalesAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(scales, np.float32)))
    g.CreateOpacitiesAttr(Vt.FloatArray.FromNumpy(np.ascontiguousarray(opac, np.float32)))
    g.CreateRadianceSphericalHarmonicsDegreeAttr(int(model.max_sh_degree))
    coeffs = g.CreateRadianceSphericalHarmonicsCoefficientsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(sh,
                                                                                                            np.float32)))
    coeffs.SetMetadata("elementSize", k)
    ext = gaussian_extent(p["means"].astype(np.float64), q, scales)
    g.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(ext.astype(np.float32)))
    # (The radiance is the photos' sRGB values, 3DGS's display-referred colour. No colour space is declared:
    # renderers of this schema, Omniverse RTX, read it as display-referred sRGB, and NVIDIA's own PLY
    # converter declares none; USD's nearest name, srgb_rec709_scene, would say scene-referred.)
    return g


def add_mesh(stage: Any, path: str, mesh: MeshData, collider: bool = True) -> Any:
    """Define a UsdGeom.Mesh with vertex colours (linear Rec.709, USD's default colour space); a static
    collider (CollisionAPI, approximation none)."""
    from pxr import UsdGeom, UsdPhysics, Vt

    m = UsdGeom.Mesh.Define(stage, path)
    pts = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(mesh.vertices, np.float32))
    m.CreatePointsAttr(pts)
    m.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(mesh.faces), 3, np.int32)))
    m.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(mesh.faces.reshape(-1), np.int32)))
    m.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    m.CreateDoubleSidedAttr(True)
    if mesh.normals is not None:
        m.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(mesh.normals, np.float32)))
        m.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    m.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex).Set(  # linear, as USD takes colours by default
        Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(srgb_to_linear(mesh.colors), np.float32)))
    m.CreateExtentAttr(UsdGeom.PointBased.ComputeExtent(pts))
    if collider:
        UsdPhysics.CollisionAPI.Apply(m.GetPrim())
        UsdPhysics.MeshCollisionAPI.Apply(m.GetPrim()).CreateApproximationAttr(UsdPhysics.Tokens.none)
    return m


def usd_camera_values(cam: Camera) -> dict[str, Any]:
    """USD camera attributes of an OpenCV pinhole camera (export frame): transform (column-vector
    world_from_usdcamera), focalLength, apertures and their offsets (principal point)."""
    W, H = cam.width, cam.height
    fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
    ha = HORIZONTAL_APERTURE
    focal = fx * ha / W
    va = focal * H / fy
    return {"world_from_camera": cam.world_from_cam @ CV_TO_USD_CAMERA, "focalLength": focal,
            "horizontalAperture": ha, "verticalAperture": va,
            "horizontalApertureOffset": -(cx - W / 2) / W * ha, "verticalApertureOffset": (cy - H / 2) / H * va}


def add_camera(stage: Any, path: str, cam: Camera, clip: tuple[float, float]) -> Any:
    from pxr import Gf, UsdGeom

    v = usd_camera_values(cam)
    c = UsdGeom.Camera.Define(stage, path)
    c.AddTransformOp().Set(Gf.Matrix4d(v["world_from_camera"].T.tolist()))  # USD: row vectors
    c.CreateProjectionAttr(UsdGeom.Tokens.perspective)
    for key in ("focalLength", "horizontalAperture", "verticalAperture", "horizontalApertureOffset",
                "verticalApertureOffset"):
        c.GetPrim().GetAttribute(key).Set(float(v[key]))
    c.CreateClippingRangeAttr(Gf.Vec2f(*clip))
    c.GetPrim().SetCustomDataByKey("sgpor:name", cam.name)
    if cam.image is not None:
        c.GetPrim().SetCustomDataByKey("sgpor:image", cam.image)
    c.GetPrim().SetCustomDataByKey("sgpor:size", f"{cam.width}x{cam.height}")
    return c


def build_stage(model: Any, mesh: MeshData | None, cameras: list[Camera], frame: ExportFrame) -> Any:
    """An in-memory stage of the scene; ``model``, ``mesh`` and ``cameras`` already in the export frame."""
    from pxr import Gf, Kind, Usd, UsdGeom, UsdPhysics

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdPhysics.SetStageKilogramsPerUnit(stage, 1.0)
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    Usd.ModelAPI(world.GetPrim()).SetKind(Kind.Tokens.assembly)
    layer = stage.GetRootLayer()
    layer.documentation = "sgpor-pipeline export: object-free scene as 3D Gaussians, mesh collider and cameras"
    layer.customLayerData = {
        "sgpor:units": frame.units,
        "sgpor:scaleSource": frame.scale_source,
        "sgpor:upMethod": frame.up_method,
        "sgpor:origin": frame.origin,
        "sgpor:exportFromSfm": json.dumps(frame.transform.matrix.round(12).tolist()),
    }
    if frame.gps and frame.gps.get("used"):  # placed on the map by the photos' GPS (to its few metres)
        layer.customLayerData = dict(layer.customLayerData, **{
            "sgpor:originLatitude": float(frame.gps["origin_latitude"]),
            "sgpor:originLongitude": float(frame.gps["origin_longitude"]),
            "sgpor:azimuthOfY": float(frame.gps["azimuth_of_y_deg"])})

    scene = UsdPhysics.Scene.Define(stage, "/World/PhysicsScene")
    scene.CreateGravityDirectionAttr(Gf.Vec3f(0.0, 0.0, -1.0))
    scene.CreateGravityMagnitudeAttr(9.81)

    add_gaussians(stage, "/World/Gaussians", model)
    if mesh is not None and len(mesh):
        add_mesh(stage, "/World/Mesh", mesh)
    if cameras:
        UsdGeom.Scope.Define(stage, "/World/Cameras")
        clip = camera_clip(cameras)
        for name, cam in zip(_valid_names([c.name for c in cameras]), cameras):
            add_camera(stage, f"/World/Cameras/{name}", cam, clip)
    return stage


#: Above this many Gaussians ``scene.usda`` is a short text layer over ``scene.usdc`` instead of the
#: whole scene as text: SPIn-NeRF statue's 360k Gaussians made a 316 MB text file (next to a 90 MB crate).
TEXT_MAX_GAUSSIANS = 200_000


def write_usd(stage: Any, out_dir: Path, stem: str = "scene", gaussians: int = 0) -> list[Path]:
    """Write the stage's root layer as ``stem.usdc`` and ``stem.usdz`` (the crate packaged), and as
    ``stem.usda`` (text) up to :data:`TEXT_MAX_GAUSSIANS` ``gaussians``; above, ``stem.usda`` holds the
    root layer's metadata (up axis, units, default prim, custom data) and sublayers ``stem.usdc``, so it
    opens as the same stage."""
    from pxr import Sdf, UsdUtils

    out_dir = Path(out_dir)
    layer = stage.GetRootLayer()
    usda, usdc = out_dir / f"{stem}.usda", out_dir / f"{stem}.usdc"
    if not layer.Export(str(usdc)):
        raise OSError(f"{usdc}: USD export failed")
    if gaussians <= TEXT_MAX_GAUSSIANS:
        text_ok = layer.Export(str(usda))
    else:
        over = Sdf.Layer.CreateAnonymous(".usda")
        for key in ("upAxis", "metersPerUnit", "kilogramsPerUnit", "defaultPrim", "customLayerData",
                    "documentation"):
            if layer.pseudoRoot.HasInfo(key):
                over.pseudoRoot.SetInfo(key, layer.pseudoRoot.GetInfo(key))
        over.subLayerPaths.append(f"./{usdc.name}")
        text_ok = over.Export(str(usda))
    if not text_ok:
        raise OSError(f"{usda}: USD export failed")
    usdz = out_dir / f"{stem}.usdz"
    if not UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(usdc)), str(usdz)):
        raise OSError(f"{usdz}: USDZ packaging failed")
    zero_zip_times(usdz)
    return [usda, usdc, usdz]


def zero_zip_times(path: Path) -> None:
    """Set every entry's modification time in a zip (a USDZ package) to 1980-01-01 00:00, in place.

    USD's zip writer stamps the time of writing, so the same stage gave another ``scene.usdz`` on every
    export. Only the 4-byte time/date fields of the local and central headers change (the sizes, the
    64-byte alignment USDZ requires and the CRCs stay), so the package is the same bytes for the same
    scene."""
    import struct

    data = bytearray(Path(path).read_bytes())
    end = data.rfind(b"PK\x05\x06")
    if end < 0:
        raise OSError(f"{path}: not a zip file (no end of central directory)")
    count, _, cd_offset = struct.unpack_from("<HII", data, end + 10)
    pos = cd_offset
    dos_1980 = struct.pack("<HH", 0, (0 << 9) | (1 << 5) | 1)  # time 00:00:00, date 1980-01-01
    for _ in range(count):
        if data[pos:pos + 4] != b"PK\x01\x02":
            raise OSError(f"{path}: unexpected central directory entry at byte {pos}")
        data[pos + 12:pos + 16] = dos_1980
        name_len, extra_len, comment_len = struct.unpack_from("<HHH", data, pos + 28)
        (local,) = struct.unpack_from("<I", data, pos + 42)
        if data[local:local + 4] != b"PK\x03\x04":
            raise OSError(f"{path}: unexpected local header at byte {local}")
        data[local + 10:local + 14] = dos_1980
        pos += 46 + name_len + extra_len + comment_len
    Path(path).write_bytes(bytes(data))


def validate_stage(stage: Any) -> list[str]:
    """Messages of every UsdValidation error/warning for ``stage`` (all registered validators)."""
    from pxr import UsdValidation

    ctx = UsdValidation.ValidationContext(UsdValidation.ValidationRegistry().GetOrLoadAllValidators())
    return [f"{e.GetType()}: {e.GetMessage()}" for e in ctx.Validate(stage)]


class UsdExporter(Exporter):
    name = "usd"
    VERSION = 4  # 2: the mesh collider's normals of unit length; 3: the mesh's displayColor linear; 4: a large
    # scene's scene.usda sublayers scene.usdc
    needs = (CAMERAS_STAGE, POSES_STAGE, SCENE_STAGE)
    optional_needs = (GPS_STAGE,)
    description = (
        "scene.usda/.usdc/.usdz: Gaussians (UsdVol splat), mesh collider, cameras; Z up, metres when the "
        "scale is known")
    outputs = ("scene.usda", "scene.usdc", "scene.usdz")

    def export(self, ctx: StageContext, out_dir: Path) -> None:
        from sgpor_pipeline.orientation import transform_model

        from .mesh import scene_mesh

        t0 = time.perf_counter()
        model = load_scene(ctx)
        cameras = load_run_cameras(ctx)
        frame = export_frame(ctx, model, cameras, out_dir)
        mesh = scene_mesh(ctx, out_dir, model, cameras, frame)
        t1 = time.perf_counter()
        cams = [frame.transform.camera(c) for c in registered(cameras) + [c for c in cameras if c.image is None]]
        stage = build_stage(transform_model(model, frame.transform), mesh, cams, frame)
        files = write_usd(stage, out_dir, gaussians=len(model))
        ctx.log.info(f"usd: {len(model)} Gaussians, {len(mesh)} mesh faces, {len(cams)} cameras -> "
                     f"{', '.join(p.name for p in files)} in {time.perf_counter() - t0:.1f} s "
                     f"({t1 - t0:.1f} s for the mesh)")
