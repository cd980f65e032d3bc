"""A coloured triangle mesh from 3D Gaussians: rendered depth + colour, fused by a TSDF.

Steps (:func:`mesh_from_gaussians`):

1. Render colour and depth at the training views (optionally also at views interpolated between
   neighbouring cameras, ``extra_views``), at most ``max_size`` pixels on the longest side. Depth:
   the rasterizer's expected depth (``render_mode="RGB+ED"``) is a blend of the Gaussians' centre
   depths, biased towards the camera wherever Gaussians overlap at an angle (~5 cm at 3 m on the
   test scene); the default ``depth_mode="planar"`` instead intersects each pixel's ray with the
   blended Gaussian planes (PGSR's unbiased depth; see :func:`planar_depth`), in the same pass.
2. Keep a depth pixel only where the accumulated opacity is high (``alpha_min``, 0.5: no floaters
   and no half-transparent fringes) and away from depth discontinuities (the expected depth blends
   foreground and background there: ``edge_rel``).
3. Fuse with Open3D's tensor ``VoxelBlockGrid`` TSDF (the legacy ``ScalableTSDFVolume`` returns an
   empty mesh in the Open3D 0.20 wheel), voxel size ``voxel_rel`` x the scene radius (the median
   camera distance to the point the cameras look at), truncation ``trunc_voxels`` voxels.
4. Extract (marching cubes), keep the connected components with at least ``min_component_rel`` of
   the largest one's triangles, quadric-decimate to ``target_faces``; vertex colours are kept.

Everything here works in the frame of the Gaussians and cameras given (the SfM frame in the
pipeline); the exporters map the result to the export frame.

The export stage's parameters ``mesh_<field>`` set them (e.g. ``export.mesh_target_faces``), read by
:meth:`MeshSettings.from_params`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from .scene import Camera

log = logging.getLogger(__name__)

#: The planar depth is used where it is within this fraction of the expected depth (else the latter).
PLANAR_AGREEMENT = 0.05


@dataclass
class MeshSettings:
    """Parameters of :func:`mesh_from_gaussians` (see the module docstring)."""

    target_faces: int = 200_000
    voxel_rel: float = 1.0 / 128.0  # voxel size relative to the scene radius
    voxel_size: float | None = None  # absolute voxel size (frame units); overrides voxel_rel
    trunc_voxels: float = 4.0
    depth_max_rel: float = 8.0  # ignore depth beyond this many scene radii
    alpha_min: float = 0.5
    edge_rel: float = 0.05  # drop pixels whose depth differs from a neighbour's by more than this fraction
    min_component_rel: float = 0.002  # keep components with >= this fraction of the largest one's triangles
    extra_views: int = 0  # views interpolated between each camera and its nearest neighbour
    max_size: int = 640  # depth is rendered with the longest image side at most this (0 = full size)
    depth_mode: str = "planar"  # "planar" (unbiased plane depth) or "expected" (the rasterizer's ED)
    weight_threshold: float = 1.0  # marching cubes only where at least this much depth was fused

    @classmethod
    def from_params(cls, params: Any) -> MeshSettings:
        """Defaults, overridden by attributes ``mesh_<field>`` of ``params`` (the export stage's params)."""
        kw = {f.name: getattr(params, "mesh_" + f.name) for f in fields(cls)
              if params is not None and getattr(params, "mesh_" + f.name, None) is not None}
        return cls(**kw)


@dataclass
class MeshData:
    """A triangle mesh with per-vertex colours (float in [0,1])."""

    vertices: np.ndarray  # [V,3] float64
    faces: np.ndarray  # [F,3] int64
    colors: np.ndarray  # [V,3] float32
    normals: np.ndarray | None = None  # [V,3]

    def __len__(self) -> int:
        return len(self.faces)

    def transformed(self, sim: Any) -> MeshData:
        """The mesh mapped by a :class:`~sgpor_pipeline.orientation.Similarity` (normals rotated)."""
        n = None if self.normals is None else np.asarray(self.normals, np.float64) @ sim.R.T
        return MeshData(sim.apply(self.vertices), self.faces.copy(), self.colors.copy(), n)


# --------------------------------------------------------------------------------------------------
# rendering


def activated_tensors(model: Any) -> dict[str, Any]:
    """Detached activated float32 tensors of a GaussianModel, for :func:`render_view`; also
    ``normals`` [N,3]: each Gaussian's shortest axis (world frame), for planar depth."""
    import torch

    from .orientation import quat_to_matrix

    with torch.no_grad():
        a = {k: v.detach().float().contiguous() for k, v in model.activated().items()}
    R = quat_to_matrix(a["quats"].numpy())  # [N,3,3], columns = the Gaussian's axes
    shortest = np.argmin(a["scales"].numpy(), axis=1)
    normals = R[np.arange(len(R)), :, shortest]
    return a | {"sh_degree": model.max_sh_degree, "normals": torch.from_numpy(normals.astype(np.float32))}


def _plane_features(g: dict[str, Any], cam: Camera) -> Any:
    """[N,4] per-Gaussian plane in camera coordinates: unit normal n (oriented away from the camera)
    and offset D = n . mu > 0 (see :func:`planar_depth`)."""
    import torch

    Rc = torch.from_numpy(cam.cam_from_world[:3, :3]).float()
    tc = torch.from_numpy(cam.cam_from_world[:3, 3]).float()
    mu = g["means"] @ Rc.T + tc
    n = g["normals"] @ Rc.T
    d = (n * mu).sum(1)
    sign = torch.where(d < 0, -1.0, 1.0)
    return torch.cat([n * sign[:, None], (d * sign)[:, None]], 1)


def planar_depth(blend: np.ndarray, alpha: np.ndarray, cam: Camera) -> np.ndarray:
    """Per-pixel depth of the blended Gaussian planes (PGSR's unbiased depth).

    Each Gaussian is taken as a small plane through its centre, normal to its shortest axis.
    ``blend`` [H,W,4] holds the blend of the camera-frame normals N and of the plane offsets
    D = n . mu (accumulated with the same weights, so no normalisation is needed); the plane hit by
    a pixel's ray r = K^-1 p is at depth D / (N . r). Unlike the expected depth (a blend of the
    centres' depths, biased towards the camera wherever Gaussians overlap at an angle), it is exact
    for flat Gaussians on a surface. 0 where the blended plane is seen edge-on (> ~87 degrees).
    """
    out = np.asarray(blend, np.float64)
    u, v = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    Kinv = np.linalg.inv(cam.K)
    rays = np.stack([Kinv[0, 0] * u + Kinv[0, 1] * v + Kinv[0, 2], Kinv[1, 1] * v + Kinv[1, 2], np.ones_like(u)], -1)
    denom = (out[..., :3] * rays).sum(-1)
    ok = (alpha > 0) & (denom > 0.05 * alpha * np.linalg.norm(rays, axis=-1))
    return np.where(ok, out[..., 3] / np.where(ok, denom, 1.0), 0.0).astype(np.float32)


def render_view(gaussians: dict[str, Any], cam: Camera, background: Sequence[float] | None = None,
                with_depth: bool = True, depth_mode: str = "planar") -> dict[str, np.ndarray]:
    """Render one camera: ``rgb`` [H,W,3] float32, ``alpha`` [H,W], and when ``with_depth`` ``depth``
    [H,W] z-depth (0 = none) and ``depth_expected`` (the rasterizer's "ED"). ``depth_mode``:
    "planar" (:func:`planar_depth` where it agrees with the expected depth within PLANAR_AGREEMENT, else the
    expected depth) or "expected". One rasterization pass. ``gaussians`` from
    :func:`activated_tensors`."""
    import torch

    from .gaussians._raster_common import sh_colors
    from .gaussians.rasterizer import rasterization

    if depth_mode not in ("planar", "expected"):
        raise ValueError(f"depth_mode must be 'planar' or 'expected', got {depth_mode!r}")
    g = gaussians
    vm = torch.from_numpy(cam.cam_from_world).float()[None]
    K = torch.from_numpy(cam.K).float()[None]
    with torch.no_grad():
        feats = sh_colors(g["means"], g["colors"], g["sh_degree"], vm)  # [1,N,3]
        planar = with_depth and depth_mode == "planar"
        if planar:
            feats = torch.cat([feats, _plane_features(g, cam)[None]], dim=2)  # [1,N,7]
        out, alpha, _ = rasterization(g["means"], g["quats"], g["scales"], g["opacities"], feats.contiguous(), vm, K,
                                      cam.width, cam.height, render_mode="RGB+ED" if with_depth else "RGB")
    out = out[0].numpy()
    alpha = alpha[0, ..., 0].numpy()
    rgb = out[..., :3]
    if background is not None:
        rgb = rgb + (1.0 - alpha[..., None]) * np.asarray(background, np.float32)
    res = {"rgb": np.clip(rgb, 0.0, 1.0).astype(np.float32), "alpha": alpha}
    if with_depth:
        d = np.where(alpha > 0, out[..., -1], 0.0).astype(np.float32)
        res["depth_expected"] = d
        if planar:
            p = planar_depth(out[..., 3:7], alpha, cam)
            d = np.where((p > 0) & (np.abs(p - d) <= PLANAR_AGREEMENT * d), p, d)
        res["depth"] = d
    return res


def limit_size(cam: Camera, max_size: int) -> Camera:
    """``cam`` for an image whose longest side is at most ``max_size`` pixels (0: unchanged)."""
    if max_size <= 0 or max(cam.width, cam.height) <= max_size:
        return cam
    f = max_size / max(cam.width, cam.height)
    return cam.scaled(max(1, round(cam.width * f)), max(1, round(cam.height * f)))


def _slerp_rot(Ra: np.ndarray, Rb: np.ndarray, t: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation, Slerp

    return Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([Ra, Rb])))(t).as_matrix()


def interpolate_cameras(cameras: Sequence[Camera], per_camera: int = 1) -> list[Camera]:
    """Extra views between each camera and its nearest neighbour (by centre), ``per_camera`` each.

    Poses are interpolated (centres linearly, rotations by slerp); intrinsics and size are the first
    camera's. Duplicated pairs are made once. Names are ``interp_<a>_<b>_<k>``; ``image`` is None.
    """
    cams = list(cameras)
    if per_camera <= 0 or len(cams) < 2:
        return []
    centers = np.array([c.center for c in cams])
    d = np.linalg.norm(centers[:, None] - centers[None], axis=2)
    np.fill_diagonal(d, np.inf)
    pairs = sorted({tuple(sorted((i, int(np.argmin(d[i]))))) for i in range(len(cams))})
    out = []
    for i, j in pairs:
        a, b = cams[i], cams[j]
        for k in range(per_camera):
            t = (k + 1) / (per_camera + 1)
            R = _slerp_rot(a.cam_from_world[:3, :3], b.cam_from_world[:3, :3], t)
            c = (1 - t) * a.center + t * b.center
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = -R @ c
            out.append(Camera(f"interp_{a.name}_{b.name}_{k}", a.width, a.height, a.K.copy(), T, None))
    return out


# --------------------------------------------------------------------------------------------------
# fusion


def clean_depth(depth: np.ndarray, alpha: np.ndarray, alpha_min: float = 0.5, edge_rel: float = 0.05,
                depth_max: float = np.inf) -> np.ndarray:
    """Depth with unreliable pixels set to 0: low opacity, depth discontinuities, beyond ``depth_max``."""
    d = np.asarray(depth, np.float32)
    ok = (alpha >= alpha_min) & np.isfinite(d) & (d > 0) & (d <= depth_max)
    if edge_rel > 0:
        p = np.pad(np.where(ok, d, 0.0), 1, mode="edge")
        jump = np.zeros_like(d)
        h, w = d.shape
        for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
            nb = p[dy:dy + h, dx:dx + w]
            jump = np.maximum(jump, np.abs(nb - d))
        ok &= jump <= edge_rel * d
    return np.where(ok, d, 0.0).astype(np.float32)


class TSDF:
    """Open3D tensor ``VoxelBlockGrid`` TSDF with colour (CPU)."""

    def __init__(self, voxel_size: float, trunc_voxels: float = 4.0, depth_max: float = 1e3,
                 block_count: int = 4096):  # the block hash map grows as needed
        import open3d as o3d
        import open3d.core as o3c

        self.o3d = o3d
        self.o3c = o3c
        self.voxel_size = float(voxel_size)
        self.trunc_voxels = float(trunc_voxels)
        self.depth_max = float(depth_max)
        self.device = o3c.Device("CPU:0")
        self.vbg = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight", "color"), attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
            attr_channels=((1,), (1,), (3,)), voxel_size=self.voxel_size, block_resolution=8,
            block_count=block_count, device=self.device)
        self.frames = 0

    def integrate(self, cam: Camera, depth: np.ndarray, rgb: np.ndarray) -> None:
        """Fuse one z-depth map (0 = no data) and its colour image (float in [0,1]) seen by ``cam``."""
        o3d, o3c = self.o3d, self.o3c
        if not np.any(depth > 0):
            return
        d = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depth, np.float32)))
        c = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(rgb, np.float32)))
        K = o3c.Tensor(cam.K, o3c.float64)
        E = o3c.Tensor(cam.cam_from_world, o3c.float64)
        blocks = self.vbg.compute_unique_block_coordinates(d, K, E, 1.0, self.depth_max, self.trunc_voxels)
        self.vbg.integrate(blocks, d, c, K, E, 1.0, self.depth_max, self.trunc_voxels)
        self.frames += 1

    def extract(self, weight_threshold: float = 1.0) -> MeshData:
        if self.frames == 0:
            return MeshData(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.float32))
        m = self.vbg.extract_triangle_mesh(weight_threshold=weight_threshold)
        v = m.vertex.positions.numpy().astype(np.float64)
        f = m.triangle.indices.numpy().astype(np.int64) if "indices" in m.triangle else np.zeros((0, 3), np.int64)
        col = m.vertex.colors.numpy().astype(np.float32) if "colors" in m.vertex else np.full((len(v), 3), 0.5,
                                                                                             np.float32)
        nrm = m.vertex.normals.numpy().astype(np.float64) if "normals" in m.vertex else None
        return canonical_order(MeshData(v, f, np.clip(col, 0.0, 1.0), nrm))


def canonical_order(mesh: MeshData) -> MeshData:
    """The same mesh with its vertices sorted by position (then colour) and its faces sorted, each
    face starting at its smallest index (orientation kept).

    Open3D's block hash map fills in parallel, so the extracted mesh lists the same vertices and faces
    in another order on every run; the decimation depends on that order, and so did the exported mesh
    (the demo's mesh.ply had 199997 or 199998 faces from the same Gaussians). Sorted, it is the same
    bytes on every run."""
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    if len(v) == 0:
        return mesh
    keys = [np.asarray(mesh.colors)[:, i] for i in (2, 1, 0)] + [v[:, i] for i in (2, 1, 0)]
    order = np.lexsort(keys)
    new_index = np.empty(len(order), np.int64)
    new_index[order] = np.arange(len(order))
    f = new_index[f]
    first = f.argmin(axis=1)
    f = np.stack([f[np.arange(len(f)), (first + i) % 3] for i in range(3)], axis=1)
    f = f[np.lexsort(f.T[::-1])] if len(f) else f.reshape(0, 3)
    normals = None if mesh.normals is None else np.asarray(mesh.normals)[order]
    return MeshData(v[order], f, np.asarray(mesh.colors)[order], normals)


def fuse_depth_maps(frames: Iterable[tuple[Camera, np.ndarray, np.ndarray]], voxel_size: float,
                    trunc_voxels: float = 4.0, depth_max: float = 1e3, weight_threshold: float = 1.0) -> MeshData:
    """TSDF-fuse (camera, z-depth [H,W] with 0 = no data, rgb [H,W,3]) frames and extract the mesh."""
    tsdf = TSDF(voxel_size, trunc_voxels, depth_max)
    for cam, depth, rgb in frames:
        tsdf.integrate(cam, depth, rgb)
    return tsdf.extract(weight_threshold)


# --------------------------------------------------------------------------------------------------
# clean-up


def _compact(mesh: MeshData, face_mask: np.ndarray) -> MeshData:
    """The mesh with only the faces in ``face_mask`` and the vertices they use."""
    faces = mesh.faces[face_mask]
    used = np.zeros(len(mesh.vertices), bool)
    used[faces.reshape(-1)] = True
    remap = np.cumsum(used) - 1
    normals = None if mesh.normals is None else mesh.normals[used]
    return MeshData(mesh.vertices[used], remap[faces], mesh.colors[used], normals)


def component_sizes(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Per face, the number of faces of its connected component (faces sharing a vertex connect)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = np.asarray(faces, np.int64)
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(n_vertices, n_vertices)).tocsr()
    _, labels = connected_components(graph, directed=False)
    face_label = labels[f[:, 0]]
    return np.bincount(face_label)[face_label]


def unit_normals(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None) -> np.ndarray:
    """Vertex normals of unit length: ``normals`` normalised; where one is zero or not finite, the
    area-weighted normal of the vertex's faces, or where those cancel (two faces folded back to back by
    the decimation) the normal of its largest face; (0, 0, 1) on no face. glTF requires unit normals:
    the Khronos glTF validator rejected the demo's mesh.glb for 2 zero normals of its 126k vertices."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    n = np.zeros_like(v) if normals is None else np.array(normals, np.float64).reshape(v.shape)
    length = np.linalg.norm(n, axis=1)
    bad = ~np.isfinite(length) | (length < 1e-8)
    if bad.any():
        cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]) if len(f) else np.zeros((0, 3))
        summed = np.zeros_like(v)  # the area-weighted normal of the vertex's faces
        for corner in range(3):
            np.add.at(summed, f[:, corner], cross)
        n[bad] = summed[bad]
        still = bad & (np.linalg.norm(n, axis=1) < 1e-12)
        if still.any():  # the faces cancel: the largest one's normal
            area = np.linalg.norm(cross, axis=1)
            best = np.zeros(len(v))
            for corner in range(3):
                np.maximum.at(best, f[:, corner], area)
            for corner in range(3):
                at = f[:, corner]
                take = still[at] & (area == best[at]) & (area > 0)
                n[at[take]] = cross[take]
            still &= np.linalg.norm(n, axis=1) < 1e-12
            n[still] = (0.0, 0.0, 1.0)  # on no face of any area
        length = np.linalg.norm(n, axis=1)
    return n / length[:, None]


def clean_mesh(mesh: MeshData, min_component_rel: float = 0.002, target_faces: int | None = None) -> MeshData:
    """Keep the large connected components, then quadric-decimate to ``target_faces`` (colours kept);
    the normals are of unit length (:func:`unit_normals`)."""
    mesh = _cleaned(mesh, min_component_rel, target_faces)
    return replace(mesh, normals=unit_normals(mesh.vertices, mesh.faces, mesh.normals))


def _cleaned(mesh: MeshData, min_component_rel: float, target_faces: int | None) -> MeshData:
    if len(mesh.faces) == 0:
        return mesh
    f = np.asarray(mesh.faces)
    degenerate = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    mesh = _compact(mesh, ~degenerate)
    sizes = component_sizes(mesh.faces, len(mesh.vertices))
    if len(sizes):
        mesh = _compact(mesh, sizes >= max(1.0, min_component_rel * sizes.max()))
    if target_faces is None or len(mesh.faces) <= target_faces:
        return mesh
    return decimate(mesh, int(target_faces))


def decimate(mesh: MeshData, target_faces: int) -> MeshData:
    """Quadric edge-collapse decimation to about ``target_faces`` (fast-simplification); each kept
    vertex takes the colour of the input vertex nearest to it; normals are left to be computed.
    Statue's 2.06M-face fused mesh to 200k: 3.9 s, against 30 s with Open3D's
    simplify_quadric_decimation, with the same surface error (mean two-way distance of 200k samples
    0.0415 against 0.0410 scene units, 99th percentile 0.106 against 0.106)."""
    import fast_simplification
    from scipy.spatial import cKDTree

    vertices, faces = fast_simplification.simplify(np.asarray(mesh.vertices, np.float64),
                                                   np.asarray(mesh.faces, np.int32), target_count=target_faces)
    if len(faces) == 0:
        return MeshData(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.float32))
    _, nearest = cKDTree(mesh.vertices).query(vertices)
    out = MeshData(np.asarray(vertices, np.float64), np.asarray(faces, np.int64),
                   np.asarray(mesh.colors, np.float32)[nearest])
    # a collapse can leave a face of zero area (26 of statue's 200k): no normal, nothing to see
    v, f = out.vertices, out.faces
    area2 = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    return _compact(out, area2 > 0)


# --------------------------------------------------------------------------------------------------
# the whole thing


def mesh_from_gaussians(model: Any, cameras: Sequence[Camera], settings: MeshSettings | None = None,
                        scene_radius: float | None = None, background: Sequence[float] | None = None,
                        frames: Iterable[tuple[Camera, dict[str, np.ndarray]]] | None = None,
                        progress: Callable[..., Iterable] | None = None) -> MeshData:
    """The cleaned, decimated, coloured mesh of a GaussianModel seen by ``cameras`` (their frame).

    ``frames``: already rendered (camera, :func:`render_view` result with depth) pairs to reuse
    instead of rendering ``cameras`` again. ``scene_radius`` defaults to the median camera distance
    to the point they look at. ``progress`` (a tqdm-like wrapper of iterables) shows the views fused.
    """
    from .orientation import scene_center_radius

    s = settings or MeshSettings()
    cams = list(cameras)
    if scene_radius is None:
        _, scene_radius = scene_center_radius(cams)
    voxel = s.voxel_size if s.voxel_size else s.voxel_rel * scene_radius
    depth_max = s.depth_max_rel * scene_radius
    g = activated_tensors(model)
    t0 = time.perf_counter()

    extra = interpolate_cameras(cams, s.extra_views)

    def all_frames() -> Iterable[tuple[Camera, dict[str, np.ndarray]]]:
        if frames is not None:
            yield from frames
        else:
            for cam in cams:
                cam = limit_size(cam, s.max_size)
                yield cam, render_view(g, cam, background, depth_mode=s.depth_mode)
        for cam in extra:
            cam = limit_size(cam, s.max_size)
            yield cam, render_view(g, cam, background, depth_mode=s.depth_mode)

    tsdf = TSDF(voxel, s.trunc_voxels, depth_max)
    fused = all_frames()
    if progress is not None:
        total = None if frames is not None else len(cams) + len(extra)
        fused = progress(fused, total=total, desc="mesh: views fused")
    for cam, r in fused:
        tsdf.integrate(cam, clean_depth(r["depth"], r["alpha"], s.alpha_min, s.edge_rel, depth_max), r["rgb"])
    t1 = time.perf_counter()
    raw = tsdf.extract(s.weight_threshold)
    t2 = time.perf_counter()
    mesh = clean_mesh(raw, s.min_component_rel, s.target_faces)
    t3 = time.perf_counter()
    log.debug(f"mesh: voxel {voxel:.4g}, {tsdf.frames} views fused in {t1 - t0:.1f} s, {len(raw)} faces extracted "
              f"in {t2 - t1:.1f} s, {len(mesh)} kept after clean-up/decimation in {t3 - t2:.1f} s")
    return mesh
