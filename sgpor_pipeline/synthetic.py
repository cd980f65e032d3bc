"""Synthetic scenes with exact ground truth for object removal (DESIGN.md section 8 (a) and (b)).

:func:`generate_scene` builds a seeded, textured room (floor, four walls, ceiling, a rug, several
background boxes / spheres / cylinders) with one removable object standing near the centre, and ray
casts it with Open3D's ``RaycastingScene`` from an inward 360-degree rig or a forward-facing
(LLFF-like) rig. Every view is rendered with the object (``images``) and without it (``images_gt``),
with the exact object mask and z-depth for both.

World frame: Z up, metres, floor at z = 0. Cameras: OpenCV axes (see :mod:`sgpor_pipeline.scene`).

How the ground truth is kept exact: the background (everything but the object) and the object are
ray cast as two separate scenes; a pixel belongs to the object when the object's hit is strictly
nearer than the background's (``mask == depth < depth_gt``). A pixel's colour is a pure function of
its first hit (texture lookup, Lambertian shading from a key and a fill directional light plus
ambient, hard shadows cast by the background objects only), and the background colours are computed
once and shared by both images, so ``images`` and ``images_gt`` are bit-identical outside the mask.
The removable object casts no shadow (that is what keeps the property exact), unless
``SceneParams.object_shadow`` asks for one: then ``images`` also carry the object's ambient occlusion
on the background ("contact") and its key-light shadow ("cast"), and ``images_gt`` stay free of both, as in a real scene
photographed before and after the object was taken away.

:func:`insert_object` composites a synthetic textured object into real photos with known cameras
(the untouched photos are then the ground truth of its removal).

Textures are real images shipped with scikit-image (brick, grass, gravel, astronaut, ...), mapped
in world or object coordinates; everything is offline and deterministic for a seed.
"""

from __future__ import annotations

import functools
import json
import logging
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .errors import PipelineError
from .removal.plane import hemisphere
from .scene import Camera, save_cameras

if TYPE_CHECKING:
    import open3d as o3d

log = logging.getLogger(__name__)

RIGS = ("inward", "forward")
OBJECT_KINDS = ("box", "sphere", "cylinder")  # what "random" draws from (objects and background)
# Also for the removable object, only when asked for by name: a box whose body stands on four short
# feet, so the floor under it is seen through the gap, in its shadow with ``object_shadow`` "cast"
# (its occlusion alone leaves the key light there), as under mip360 kitchen's bulldozer: a real
# footprint (drawing it at random would change every seeded scene).
RAISED_KIND = "raised_box"
RAISED_GAP = 0.22  # the gap under the body, as a share of the object's height
RAISED_FOOT = 0.16  # a foot's side, as a share of the body's side
OBJECT_SHADOWS = ("none", "contact", "cast")

# Colour photos: the removable object's texture is drawn from these (and never reused elsewhere).
OBJECT_TEXTURES = ("astronaut", "chelsea", "coffee", "rocket")
# Background textures: grey ones are tinted with a random colour per use.
BACKGROUND_TEXTURES = (
    "brick", "grass", "gravel", "camera", "moon", "coins", "page", "cell", "text",
    "hubble_deep_field", "immunohistochemistry", "retina", "colorwheel",
)
_FLOOR_TEXTURES = ("grass", "gravel", "brick", "coins", "moon")
_WALL_TEXTURES = ("brick", "gravel", "page", "text", "camera", "cell", "moon", "grass")


# --------------------------------------------------------------------------------------------------
# parameters and result


@dataclass
class SceneParams:
    """Parameters of :func:`generate_scene` (all randomness comes from ``seed``)."""

    seed: int = 0
    rig: str = "inward"  # "inward" (360-degree ring) or "forward" (LLFF-like grid)
    n_views: int = 24
    width: int = 256
    height: int = 192
    hfov_deg: float = 60.0  # horizontal field of view; principal point at the image centre
    n_background_objects: int = 6
    object_kind: str = "random"  # "box", "sphere", "cylinder", "raised_box" or "random"
    rug: bool = True  # a textured rug on the floor under the object (makes the hole non-trivial)
    # Where the rug lies: "centre" (the object stands well inside it), "edge" (one of its long edges
    # passes under the object's centre) or "corner" (its corner lies there): straight borders that run
    # through what the object hides, as mats on a table do.
    rug_place: str = "centre"
    # The rug's texture, one of BACKGROUND_TEXTURES ("coins": a regular grid of coins, "brick": a wall of
    # bricks); "" = drawn with the scene. Set, it is made with its own seed, so the rest of the scene
    # stays the same.
    rug_texture: str = ""
    # The rug's outline: "rect", or "ellipse" (inscribed in that rectangle, a round rug: its border under
    # the object is curved; with rug_place "edge" the object stands on the end of an axis)
    rug_shape: str = "rect"
    shadows: bool = True  # hard shadows cast by the background objects (never by the object)
    # How the object darkens the background in ``images`` (never in ``images_gt``), as in a real
    # photo: "none"; "contact" (its ambient occlusion: the floor darkens where it stands); "cast"
    # (that plus its hard key-light shadow). The images then differ outside the mask too, and a
    # removal is judged on whether the darkening goes with the object.
    object_shadow: str = "none"
    ambient: float = 0.3
    key_light: float = 0.65
    fill_light: float = 0.2
    texture_size: int = 256  # textures are resized so their longer side has this many pixels


@dataclass
class SyntheticScene:
    """A rendered synthetic scene. Arrays are stacked over views (index i = ``cameras[i]``)."""

    params: SceneParams
    cameras: list[Camera]
    images: np.ndarray  # [N,H,W,3] float32 in [0,1], with the object
    images_gt: np.ndarray  # [N,H,W,3] float32, the same views without the object
    masks: np.ndarray  # [N,H,W] bool, pixels whose first hit is the object
    depth: np.ndarray  # [N,H,W] float32 z-depth with the object (inf = no hit)
    depth_gt: np.ndarray  # [N,H,W] float32 z-depth without the object
    object_bounds: np.ndarray  # [2,3] axis-aligned bounds (min, max) of the object, world frame
    background_mesh: object  # open3d.geometry.TriangleMesh (legacy): room, rug and background objects
    object_mesh: object  # open3d.geometry.TriangleMesh (legacy): the removable object
    object_kind: str = "box"
    object_texture: str = ""
    light_direction: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]


def background_mesh(scene: SyntheticScene) -> o3d.geometry.TriangleMesh:
    """The true background geometry (legacy Open3D TriangleMesh, world frame)."""
    return scene.background_mesh


def object_mesh(scene: SyntheticScene) -> o3d.geometry.TriangleMesh:
    """The true geometry of the removable object (legacy Open3D TriangleMesh, world frame)."""
    return scene.object_mesh


# --------------------------------------------------------------------------------------------------
# textures


@functools.lru_cache(maxsize=64)
def _load_texture(name: str, size: int) -> np.ndarray:
    """An skimage.data image as float32 [h,w,3] (grey replicated), longer side ``size`` pixels."""
    import cv2
    import skimage.data

    img = np.asarray(getattr(skimage.data, name)())
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    img = img[..., :3]
    img = img.astype(np.float32) / (65535.0 if img.dtype == np.uint16 else 255.0)
    h, w = img.shape[:2]
    s = size / max(h, w)
    if s < 1.0:
        img = cv2.resize(img, (max(2, round(w * s)), max(2, round(h * s))), interpolation=cv2.INTER_AREA)
    img = np.ascontiguousarray(img, dtype=np.float32)
    img.setflags(write=False)
    return img


def _texture(name: str, rng: np.random.Generator, size: int, tint: bool = True) -> np.ndarray:
    tex = _load_texture(name, size)
    if tint and np.allclose(tex[..., 0], tex[..., 1]):  # grey: tint it so backgrounds are coloured
        c = rng.uniform(0.45, 1.0, size=3).astype(np.float32)
        c /= c.max()
        tex = tex * c
    # keep albedo away from pure black/white so shading stays visible
    return (0.08 + 0.86 * tex).astype(np.float32)


def _sample(tex: np.ndarray, u: np.ndarray, v: np.ndarray, wrap: bool) -> np.ndarray:
    """Bilinear texture lookup at (u, v) in texture units ([0,1] spans the image once)."""
    h, w = tex.shape[:2]
    x = u * w - 0.5
    y = v * h - 0.5
    if not wrap:
        x = np.clip(x, 0.0, w - 1.0)
        y = np.clip(y, 0.0, h - 1.0)
    x0f = np.floor(x)
    y0f = np.floor(y)
    fx = (x - x0f).astype(np.float32)[:, None]
    fy = (y - y0f).astype(np.float32)[:, None]
    x0 = x0f.astype(np.int64)
    y0 = y0f.astype(np.int64)
    if wrap:
        x0 %= w
        y0 %= h
        x1 = (x0 + 1) % w
        y1 = (y0 + 1) % h
    else:
        x1 = np.minimum(x0 + 1, w - 1)
        y1 = np.minimum(y0 + 1, h - 1)
    return (tex[y0, x0] * (1 - fx) * (1 - fy) + tex[y0, x1] * fx * (1 - fy)
            + tex[y1, x0] * (1 - fx) * fy + tex[y1, x1] * fx * fy)


# --------------------------------------------------------------------------------------------------
# surfaces: a mesh plus how to texture and shade it


@dataclass
class _Surface:
    name: str
    kind: str  # "plane" (room quads, rug), "box", "sphere", "cylinder"
    texture: np.ndarray
    center: np.ndarray  # [3] world
    half: np.ndarray  # [3] half extents in the local frame (sphere: radius in all three)
    rot: np.ndarray  # [3,3] world_from_local
    tile: float = 1.0  # metres per texture repeat ("plane" mapping)
    offset: tuple[float, float] = (0.0, 0.0)
    fit: bool = False  # box/plane: stretch the texture once over each face instead of tiling
    caster: bool = False  # casts shadows
    mesh: object = None  # legacy open3d TriangleMesh, world frame


def _face_uv(pl: np.ndarray, nl: np.ndarray, s: _Surface) -> tuple[np.ndarray, np.ndarray]:
    """Per-face planar (u, v) in the local frame; vertical faces keep the texture upright."""
    axis = np.argmax(np.abs(nl), axis=1)
    u = np.empty(len(pl))
    v = np.empty(len(pl))
    if s.fit:  # normalise coordinates to [0,1] over the face
        q = (pl + s.half) / np.maximum(2 * s.half, 1e-9)
        q_neg = 1.0 - q
    else:
        q = pl / s.tile
        q_neg = -q
    top = axis == 2
    u[top] = q[top, 0]
    v[top] = q_neg[top, 1]
    fx = axis == 0  # faces normal to x: u along y
    u[fx] = np.where(nl[fx, 0] > 0, q[fx, 1], q_neg[fx, 1])
    v[fx] = q_neg[fx, 2]
    fy = axis == 1
    u[fy] = np.where(nl[fy, 1] < 0, q[fy, 0], q_neg[fy, 0])
    v[fy] = q_neg[fy, 2]
    return u + s.offset[0], v + s.offset[1]


def _surface_albedo_normal(s: _Surface, p: np.ndarray, fn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Albedo [n,3] float32 and outward-ish world normal [n,3] at hit points ``p`` on surface ``s``."""
    pl = (p - s.center) @ s.rot  # local coordinates
    nl = fn @ s.rot
    if s.kind == "sphere":
        nl = pl / np.linalg.norm(pl, axis=1, keepdims=True)
        u = 2.0 * (np.arctan2(nl[:, 1], nl[:, 0]) / (2 * np.pi) + 0.5)
        v = np.arccos(np.clip(-nl[:, 2], -1.0, 1.0)) / np.pi
        v = 1.0 - v
        return _sample(s.texture, u, v, wrap=True), nl @ s.rot.T
    if s.kind == "cylinder":
        side = np.abs(nl[:, 2]) < 0.5
        u = np.empty(len(pl))
        v = np.empty(len(pl))
        radial = pl[side, :2] / np.linalg.norm(pl[side, :2], axis=1, keepdims=True)
        nl = nl.copy()
        nl[side, :2] = radial
        nl[side, 2] = 0.0
        circumference = 2 * np.pi * s.half[0]
        turns = max(1.0, round(circumference / max(2 * s.half[2], 1e-6)))
        u[side] = turns * (np.arctan2(radial[:, 1], radial[:, 0]) / (2 * np.pi) + 0.5)
        v[side] = 0.5 - pl[side, 2] / (2 * s.half[2])
        cap = ~side
        u[cap] = 0.5 + pl[cap, 0] / (2 * s.half[0])
        v[cap] = 0.5 + pl[cap, 1] / (2 * s.half[1])
        return _sample(s.texture, u, v, wrap=True), nl @ s.rot.T
    u, v = _face_uv(pl, nl, s)
    return _sample(s.texture, u, v, wrap=not s.fit), fn


@dataclass
class _Lighting:
    key: np.ndarray  # [3] unit vector towards the key light
    fill: np.ndarray  # [3] unit vector towards the fill light
    ambient: float
    key_strength: float
    fill_strength: float


def _shade(surfaces: Sequence[_Surface], gid: np.ndarray, t: np.ndarray, fn: np.ndarray,
           origins: np.ndarray, dirs: np.ndarray, light: _Lighting, casters,
           occluder: _Occluder | None = None) -> np.ndarray:
    """Colours [n,3] float32 of first hits (gid, t, face normal) of rays (origins, dirs).

    The result of each ray depends only on its own hit, so the same hit gives the same colour in any
    image. ``occluder`` (the object, for the background of the images with it) adds its key-light
    shadow and its ambient occlusion.
    """
    n = len(gid)
    out = np.zeros((n, 3), np.float32)
    if n == 0:
        return out
    p = origins + t[:, None] * dirs
    albedo = np.zeros((n, 3), np.float32)
    normal = np.zeros((n, 3))
    for g in np.unique(gid):
        sel = gid == g
        a, nn = _surface_albedo_normal(surfaces[int(g)], p[sel], fn[sel])
        albedo[sel] = a
        normal[sel] = nn
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    facing = np.sum(normal * dirs, axis=1) > 0  # orient towards the viewer (room walls seen inside)
    normal[facing] *= -1
    key = np.clip(normal @ light.key, 0.0, None)
    fill = np.clip(normal @ light.fill, 0.0, None)
    if casters is not None:
        key = _key_shadowed(casters, p, normal, key, light.key)
    open_sky = np.ones(n)
    if occluder is not None:
        key, open_sky = occluder.darken(p, normal, key, light.key)
    shading = open_sky * (light.ambient + light.fill_strength * fill) + light.key_strength * key
    out[:] = np.clip(albedo * shading[:, None].astype(np.float32), 0.0, 1.0)
    return out


def _key_shadowed(scene, p: np.ndarray, normal: np.ndarray, key: np.ndarray, to_key: np.ndarray) -> np.ndarray:
    """``key`` (the key light's cosine at points ``p``) with 0 where a ray from the point towards the
    light meets ``scene`` (an Open3D ray-casting scene): its hard shadow."""
    import open3d as o3d

    key = key.copy()
    lit = np.flatnonzero(key > 0)
    if len(lit):
        rays = np.empty((len(lit), 6), np.float32)
        rays[:, :3] = p[lit] + 1e-3 * normal[lit]
        rays[:, 3:] = to_key
        occ = scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.0, tfar=np.inf).numpy()
        key[lit[occ.astype(bool)]] = 0.0
    return key


class _Occluder:
    """The removable object as a shadow caster: ambient occlusion, plus its hard key-light shadow
    when ``cast``.

    Ambient occlusion is the cosine-weighted fraction of the hemisphere over a point that the object
    hides within ``reach`` (its bounding radius): a fixed set of directions, so the same point always
    gets the same value. It scales the ambient and fill terms, which is what darkens the floor where
    the object stands on it.
    """

    def __init__(self, obj: _Surface, cast: bool, n_directions: int = 96):
        self.scene = _raycasting_scene([obj])
        self.cast = cast
        lo, hi = np.asarray(obj.mesh.get_min_bound()), np.asarray(obj.mesh.get_max_bound())
        self.lo, self.hi = lo, hi
        self.reach = 0.5 * float(np.linalg.norm(hi - lo))
        self.local = hemisphere(n_directions)  # cosine-weighted: the plain mean is the integral

    def darken(self, p: np.ndarray, normal: np.ndarray, key: np.ndarray,
               to_key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        import open3d as o3d

        if self.cast:
            key = _key_shadowed(self.scene, p, normal, key, to_key)
        open_sky = np.ones(len(p))
        near = np.flatnonzero(np.all((p > self.lo - self.reach) & (p < self.hi + self.reach), axis=1))
        if len(near):
            nn = normal[near]
            # an orthonormal frame (t1, t2, n) per point
            helper = np.where(np.abs(nn[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
            t1 = np.cross(helper, nn)
            t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
            t2 = np.cross(nn, t1)
            d = (self.local[None, :, 0:1] * t1[:, None] + self.local[None, :, 1:2] * t2[:, None]
                 + self.local[None, :, 2:3] * nn[:, None])
            m = len(self.local)
            rays = np.empty((len(near) * m, 6), np.float32)
            rays[:, :3] = np.repeat(p[near] + 1e-3 * nn, m, axis=0)
            rays[:, 3:] = d.reshape(-1, 3)
            occ = self.scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.0, tfar=self.reach).numpy()
            open_sky[near] = 1.0 - occ.reshape(len(near), m).mean(axis=1)
        return key, open_sky


def _raycasting_scene(surfaces: Sequence[_Surface]):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    for i, s in enumerate(surfaces):
        gid = scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(s.mesh))
        if gid != i:  # ids are assigned in order; the shading relies on it
            raise RuntimeError(f"unexpected geometry id {gid} for surface {i}")
    return scene


# --------------------------------------------------------------------------------------------------
# meshes


def _rug_mesh(shape: str, center: np.ndarray, half: np.ndarray, rot: np.ndarray, segments: int = 128):
    """The rug's mesh: its rectangle, or the ellipse inscribed in it (a fan of ``segments`` triangles)."""
    if shape == "rect":
        return _quad(np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]]) * half @ rot.T + center)
    if shape != "ellipse":
        raise ValueError(f"rug_shape must be 'rect' or 'ellipse', got {shape!r}")
    import open3d as o3d

    a = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    rim = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], 1) * half @ rot.T + center
    m = o3d.geometry.TriangleMesh()
    m.vertices = o3d.utility.Vector3dVector(np.vstack([center, rim]).astype(np.float64))
    fan = np.stack([np.zeros(segments), 1 + np.arange(segments), 1 + (np.arange(segments) + 1) % segments], 1)
    m.triangles = o3d.utility.Vector3iVector(fan.astype(np.int32))
    return m


def _quad(corners: np.ndarray):
    import open3d as o3d

    m = o3d.geometry.TriangleMesh()
    m.vertices = o3d.utility.Vector3dVector(np.asarray(corners, np.float64))
    m.triangles = o3d.utility.Vector3iVector(np.array([[0, 1, 2], [0, 2, 3]], np.int32))
    return m


def _primitive_mesh(kind: str, half: np.ndarray, center: np.ndarray, rot: np.ndarray):
    """A closed mesh of a box / sphere / cylinder centred at ``center`` with local frame ``rot``."""
    import open3d as o3d

    if kind == "box":
        m = o3d.geometry.TriangleMesh.create_box(*(2 * half))
        m.translate(-half)
    elif kind == RAISED_KIND:  # the body over the gap, a foot under each corner (inset by half a foot)
        gap = 2 * half[2] * RAISED_GAP
        body = o3d.geometry.TriangleMesh.create_box(*(2 * half[:2]), 2 * half[2] - gap)
        body.translate([-half[0], -half[1], -half[2] + gap])
        m = body
        foot = RAISED_FOOT * 2 * half[:2]
        for sx in (-1, 1):
            for sy in (-1, 1):
                f = o3d.geometry.TriangleMesh.create_box(foot[0], foot[1], gap)
                c = np.array([sx * (half[0] - foot[0]), sy * (half[1] - foot[1])])
                f.translate([c[0] - foot[0] / 2, c[1] - foot[1] / 2, -half[2]])
                m += f
    elif kind == "sphere":
        m = o3d.geometry.TriangleMesh.create_sphere(radius=float(half[0]), resolution=24)
    elif kind == "cylinder":
        m = o3d.geometry.TriangleMesh.create_cylinder(radius=float(half[0]), height=float(2 * half[2]),
                                                      resolution=40, split=1)
    else:
        raise ValueError(kind)
    v = np.asarray(m.vertices) @ rot.T + center
    m.vertices = o3d.utility.Vector3dVector(v)
    return m


def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _primitive_half(kind: str, size: float, rng: np.random.Generator) -> np.ndarray:
    """Half extents for a primitive of overall size ~``size`` (sphere: radius in all three)."""
    if kind == "sphere":
        return np.full(3, size / 2)
    if kind == "cylinder":
        r = size / 2 * rng.uniform(0.6, 0.9)
        return np.array([r, r, size / 2 * rng.uniform(0.9, 1.4)])
    return size / 2 * rng.uniform(0.7, 1.3, size=3)


def _merge(meshes: Sequence):
    import open3d as o3d

    out = o3d.geometry.TriangleMesh()
    for m in meshes:
        out += m
    return out


# --------------------------------------------------------------------------------------------------
# cameras


def _intrinsics(width: int, height: int, hfov_deg: float) -> np.ndarray:
    f = 0.5 * width / np.tan(np.radians(hfov_deg) / 2)
    return np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])


def look_at(eye: np.ndarray, target: np.ndarray, up: Sequence[float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenCV ``cam_from_world`` [4,4] of a camera at ``eye`` looking at ``target`` (``up`` = world up)."""
    eye = np.asarray(eye, np.float64)
    z = np.asarray(target, np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, np.float64))
    if np.linalg.norm(x) < 1e-9:  # looking straight up/down: any right vector
        x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z])
    T[:3, 3] = -T[:3, :3] @ eye
    return T


def _rig_cameras(p: SceneParams, rng: np.random.Generator, target: np.ndarray,
                 room_half: np.ndarray, ring: float) -> list[Camera]:
    K = _intrinsics(p.width, p.height, p.hfov_deg)
    n = p.n_views
    poses = []
    if p.rig == "inward":
        phase = rng.uniform(0, 2 * np.pi)
        ecc = rng.uniform(0.0, 0.08)
        base_h = rng.uniform(0.85, 1.15)
        wobble = rng.uniform(0.05, 0.15)
        for i in range(n):
            a = phase + 2 * np.pi * i / n
            eye = np.array([ring * (1 + ecc) * np.cos(a), ring * (1 - ecc) * np.sin(a),
                            base_h + wobble * np.sin(3 * a) + rng.uniform(-0.03, 0.03)])
            tgt = target + rng.uniform(-0.05, 0.05, size=3)
            poses.append(look_at(eye, tgt))
    else:  # forward-facing: a grid in a plane in front of the object, the far wall behind it
        cols = int(np.ceil(np.sqrt(n * 1.5)))
        rows = int(np.ceil(n / cols))
        yaw = rng.uniform(-0.3, 0.3)
        R = _rot_z(yaw)
        dist = rng.uniform(0.85, 1.0) * ring
        span_x = rng.uniform(0.7, 1.0)
        span_z = rng.uniform(0.35, 0.5)
        base_h = rng.uniform(0.9, 1.15)
        for i in range(n):
            r, c = divmod(i, cols)
            gx = (c / max(cols - 1, 1) - 0.5) * span_x
            gz = (r / max(rows - 1, 1) - 0.5) * span_z if rows > 1 else 0.0
            local = np.array([gx, -dist, base_h + gz]) + rng.uniform(-0.02, 0.02, size=3)
            eye = target * np.array([1.0, 1.0, 0.0]) + R @ local
            # roughly parallel axes (LLFF): look at a point behind the object, shifted with the camera
            tgt = target + R @ np.array([0.35 * gx, 0.0, 0.35 * gz]) + rng.uniform(-0.03, 0.03, size=3)
            poses.append(look_at(eye, tgt))
    cams = []
    for i, T in enumerate(poses):
        name = f"view_{i:03d}"
        cams.append(Camera(name=name, width=p.width, height=p.height, K=K.copy(), cam_from_world=T,
                           image=name))
    return cams


def _camera_rays(cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel ray origins and directions [H*W,3] (float64) through pixel centres.

    Directions have camera-frame z = 1, so the hit distance is the z-depth. OpenCV-compatible
    distortion (SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV) is applied; other models' distortion is
    ignored with a warning.
    """
    H, W = cam.height, cam.width
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    pix = np.stack([u.ravel(), v.ravel()], axis=1)
    dist = _opencv_distortion(cam)
    if dist is not None and np.any(dist != 0):
        import cv2

        xy = cv2.undistortPoints(pix.reshape(-1, 1, 2), cam.K, dist).reshape(-1, 2)
    else:
        Kinv = np.linalg.inv(cam.K)
        xy = pix @ Kinv[:2, :2].T + Kinv[:2, 2]
    d_cam = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    R = cam.cam_from_world[:3, :3]
    dirs = d_cam @ R  # = (R^T d)^T
    origins = np.broadcast_to(cam.center, dirs.shape)
    return origins, dirs


def _opencv_distortion(cam: Camera) -> np.ndarray | None:
    d = list(cam.distortion)
    if not d or cam.model in ("PINHOLE", "SIMPLE_PINHOLE"):
        return None
    if cam.model == "SIMPLE_RADIAL":
        return np.array([d[0], 0, 0, 0], np.float64)
    if cam.model == "RADIAL":
        return np.array([d[0], d[1], 0, 0], np.float64)
    if cam.model == "OPENCV":
        return np.array(d[:4], np.float64)
    if cam.model == "FULL_OPENCV":
        k1, k2, p1, p2, k3, k4, k5, k6 = d[:8]
        return np.array([k1, k2, p1, p2, k3, k4, k5, k6], np.float64)
    log.warning("camera %s: distortion model %s is ignored when ray casting", cam.name, cam.model)
    return None


def _cast(scene, origins: np.ndarray, dirs: np.ndarray) -> dict[str, np.ndarray]:
    import open3d as o3d

    rays = np.empty((len(dirs), 6), np.float32)
    rays[:, :3] = origins
    rays[:, 3:] = dirs
    r = scene.cast_rays(o3d.core.Tensor(rays))
    return {"t": r["t_hit"].numpy(), "gid": r["geometry_ids"].numpy(),
            "normal": r["primitive_normals"].numpy().astype(np.float64)}


# --------------------------------------------------------------------------------------------------
# scene generation


def _lighting(p: SceneParams, rng: np.random.Generator) -> _Lighting:
    az = rng.uniform(0, 2 * np.pi)
    el = np.radians(rng.uniform(45, 65))
    key = np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
    fill = np.array([-np.cos(az) * 0.8, -np.sin(az) * 0.8, 0.6])
    fill /= np.linalg.norm(fill)
    return _Lighting(key, fill, p.ambient, p.key_light, p.fill_light)


def _validate(p: SceneParams) -> None:
    if p.rig not in RIGS:
        raise PipelineError(f"unknown synthetic rig {p.rig!r}", fix=f"use one of {', '.join(RIGS)}")
    if p.object_kind not in (*OBJECT_KINDS, RAISED_KIND, "random"):
        raise PipelineError(f"unknown object kind {p.object_kind!r}",
                            fix=f"use one of {', '.join((*OBJECT_KINDS, RAISED_KIND))} or random")
    if p.object_shadow not in OBJECT_SHADOWS:
        raise PipelineError(f"unknown object_shadow {p.object_shadow!r}",
                            fix=f"use one of {', '.join(OBJECT_SHADOWS)}")
    if p.n_views < 1 or p.width < 8 or p.height < 8:
        raise PipelineError(f"synthetic scene needs n_views >= 1 and at least 8x8 pixels, got "
                            f"{p.n_views} views of {p.width}x{p.height}", fix="increase them")
    if not 1.0 <= p.hfov_deg <= 170.0:
        raise PipelineError(f"hfov_deg={p.hfov_deg} is out of range", fix="use 1 to 170 degrees")


def _build_layout(p: SceneParams, rng: np.random.Generator):
    """Background surfaces, the object surface and the camera ring radius."""
    size = p.texture_size
    room_half = np.array([rng.uniform(3.6, 4.2), rng.uniform(3.6, 4.2)])
    room_h = rng.uniform(2.6, 3.2)
    ring = rng.uniform(1.8, 2.1)

    # textures: the object's is exclusive; background ones drawn without replacement where possible
    obj_tex_name = str(rng.choice(OBJECT_TEXTURES))
    pool = [t for t in (*BACKGROUND_TEXTURES, *OBJECT_TEXTURES) if t != obj_tex_name]

    def pick(candidates: Sequence[str]) -> str:
        avail = [t for t in candidates if t in pool] or list(pool)
        name = str(rng.choice(avail))
        if len(pool) > 1:
            pool.remove(name)
        return name

    surfaces: list[_Surface] = []
    I3 = np.eye(3)
    X, Y, H = room_half[0], room_half[1], room_h
    floor_tex = pick(_FLOOR_TEXTURES)
    surfaces.append(_Surface("floor", "plane", _texture(floor_tex, rng, size), np.zeros(3), np.zeros(3), I3,
                             tile=rng.uniform(0.8, 1.4), offset=tuple(rng.uniform(0, 1, 2)),
                             mesh=_quad([[-X, -Y, 0], [X, -Y, 0], [X, Y, 0], [-X, Y, 0]])))
    wall_names = [pick(_WALL_TEXTURES), pick(_WALL_TEXTURES)]
    walls = {
        "wall_north": [[-X, Y, 0], [X, Y, 0], [X, Y, H], [-X, Y, H]],
        "wall_south": [[X, -Y, 0], [-X, -Y, 0], [-X, -Y, H], [X, -Y, H]],
        "wall_east": [[X, Y, 0], [X, -Y, 0], [X, -Y, H], [X, Y, H]],
        "wall_west": [[-X, -Y, 0], [-X, Y, 0], [-X, Y, H], [-X, -Y, H]],
    }
    for i, (name, corners) in enumerate(walls.items()):
        tex = _texture(wall_names[i % 2], rng, size)
        surfaces.append(_Surface(name, "plane", tex, np.zeros(3), np.zeros(3), I3,
                                 tile=rng.uniform(0.9, 1.6), offset=tuple(rng.uniform(0, 1, 2)),
                                 mesh=_quad(corners)))
    surfaces.append(_Surface("ceiling", "plane", _texture(pick(_WALL_TEXTURES), rng, size), np.zeros(3),
                             np.zeros(3), I3, tile=1.5,
                             mesh=_quad([[-X, -Y, H], [-X, Y, H], [X, Y, H], [X, -Y, H]])))

    # the removable object, near the centre (standing on the rug)
    kind = p.object_kind if p.object_kind != "random" else str(rng.choice(OBJECT_KINDS))
    obj_size = rng.uniform(0.45, 0.65)
    half = _primitive_half(kind, obj_size, rng)
    rot = _rot_z(rng.uniform(0, 2 * np.pi)) if kind != "sphere" else I3
    base = 0.0
    if p.rug:
        base = 0.01
        rug_half = np.array([rng.uniform(0.6, 0.9), rng.uniform(0.45, 0.7), 0.0])
        rug_c = np.array([*rng.uniform(-0.15, 0.15, 2), base])
        rug_rot = _rot_z(rng.uniform(0, np.pi))
        rug_tex = pick(BACKGROUND_TEXTURES)
        rug_img = _texture(rug_tex, rng, size)  # (made even when replaced: its draws keep the rest of the scene)
        if p.rug_texture:
            if p.rug_texture not in BACKGROUND_TEXTURES:
                raise ValueError(f"rug_texture must be one of {', '.join(BACKGROUND_TEXTURES)}, got {p.rug_texture!r}")
            rug_img = _texture(p.rug_texture, np.random.default_rng([p.seed, 1]), size)
        surfaces.append(_Surface("rug", "plane", rug_img, rug_c, rug_half, rug_rot, fit=True,
                                 mesh=_rug_mesh(p.rug_shape, rug_c, rug_half, rug_rot)))
    obj_c = np.array([*rng.uniform(-0.2, 0.2, 2), base + half[2]])
    if p.rug and p.rug_place != "centre":  # (after every draw: the rest of the scene stays the same)
        if p.rug_place not in ("edge", "corner"):
            raise ValueError(f"rug_place must be 'centre', 'edge' or 'corner', got {p.rug_place!r}")
        reach = rug_half * (np.array([0.0, 1.0, 0.0]) if p.rug_place == "edge" else np.array([1.0, 1.0, 0.0]))
        if p.rug_shape == "ellipse" and p.rug_place == "corner":  # (the ellipse's point at 45 degrees)
            reach = reach * np.sqrt(0.5)
        rug_c = np.array([*(obj_c[:2] - (rug_rot @ reach)[:2]), base])
        rug = next(i for i, sf in enumerate(surfaces) if sf.name == "rug")
        surfaces[rug] = replace(surfaces[rug], center=rug_c, mesh=_rug_mesh(p.rug_shape, rug_c, rug_half, rug_rot))
    obj = _Surface("object", kind, _texture(obj_tex_name, rng, size, tint=False), obj_c, half, rot,
                   fit=True, mesh=_primitive_mesh(kind, half, obj_c, rot))

    # background objects in the annulus between the camera ring and the walls (never occluding the
    # object from the inward rig), no overlaps
    r_min, r_max = ring + 0.6, min(X, Y) - 0.3
    placed: list[tuple[np.ndarray, float]] = []
    tries = 0
    while len(placed) < p.n_background_objects and tries < 500:
        tries += 1
        bkind = str(rng.choice(OBJECT_KINDS))
        bsize = rng.uniform(0.35, 0.75)
        bhalf = _primitive_half(bkind, bsize, rng)
        if bkind == "cylinder" and rng.uniform() < 0.4:  # a pillar
            bhalf[2] = rng.uniform(0.5, 0.9)
        foot = float(np.linalg.norm(bhalf[:2]))
        a = rng.uniform(0, 2 * np.pi)
        r = rng.uniform(r_min, r_max)
        c2 = np.array([r * np.cos(a), r * np.sin(a)])
        if abs(c2[0]) + foot > X - 0.05 or abs(c2[1]) + foot > Y - 0.05 or r - foot < ring + 0.3:
            continue
        if any(np.linalg.norm(c2 - q) < foot + f + 0.1 for q, f in placed):
            continue
        placed.append((c2, foot))
        brot = _rot_z(rng.uniform(0, 2 * np.pi)) if bkind != "sphere" else I3
        bc = np.array([c2[0], c2[1], bhalf[2]])
        tex = _texture(pick(BACKGROUND_TEXTURES), rng, size)
        surfaces.append(_Surface(f"{bkind}_{len(placed)}", bkind, tex, bc, bhalf, brot,
                                 tile=rng.uniform(0.4, 0.8), fit=bool(rng.uniform() < 0.5), caster=True,
                                 mesh=_primitive_mesh(bkind, bhalf, bc, brot)))
    return surfaces, obj, obj_tex_name, room_half, ring


def generate_scene(params: SceneParams | None = None) -> SyntheticScene:
    """Build and render a seeded synthetic scene (see the module docstring)."""
    p = params or SceneParams()
    _validate(p)
    rng = np.random.default_rng(p.seed)
    surfaces, obj, obj_tex, room_half, ring = _build_layout(p, rng)
    light = _lighting(p, rng)
    obj_bounds = np.stack([np.asarray(obj.mesh.get_min_bound()), np.asarray(obj.mesh.get_max_bound())])
    target = obj.center.copy()
    cams = _rig_cameras(p, rng, target, room_half, ring)

    bg_scene = _raycasting_scene(surfaces)
    obj_scene = _raycasting_scene([obj])
    casters_list = [s for s in surfaces if s.caster]
    casters = _raycasting_scene(casters_list) if (p.shadows and casters_list) else None
    occluder = _Occluder(obj, cast=p.object_shadow == "cast") if p.object_shadow != "none" else None

    N, H, W = len(cams), p.height, p.width
    images_gt = np.zeros((N, H, W, 3), np.float32)
    images = np.zeros((N, H, W, 3), np.float32)
    masks = np.zeros((N, H, W), bool)
    depth = np.zeros((N, H, W), np.float32)
    depth_gt = np.zeros((N, H, W), np.float32)
    for i, cam in enumerate(cams):
        origins, dirs = _camera_rays(cam)
        bg = _cast(bg_scene, origins, dirs)
        ob = _cast(obj_scene, origins, dirs)
        hit = np.isfinite(bg["t"])
        col = np.zeros((H * W, 3), np.float32)
        idx = np.flatnonzero(hit)
        col[idx] = _shade(surfaces, bg["gid"][idx], bg["t"][idx].astype(np.float64), bg["normal"][idx],
                          origins[idx], dirs[idx], light, casters)
        m = ob["t"] < bg["t"]
        with_obj = col.copy()
        if occluder is not None:
            idx = np.flatnonzero(hit & ~m)
            with_obj[idx] = _shade(surfaces, bg["gid"][idx], bg["t"][idx].astype(np.float64),
                                   bg["normal"][idx], origins[idx], dirs[idx], light, casters, occluder)
        idx = np.flatnonzero(m)
        with_obj[idx] = _shade([obj], ob["gid"][idx], ob["t"][idx].astype(np.float64), ob["normal"][idx],
                               origins[idx], dirs[idx], light, casters)
        images_gt[i] = col.reshape(H, W, 3)
        images[i] = with_obj.reshape(H, W, 3)
        masks[i] = m.reshape(H, W)
        depth_gt[i] = bg["t"].reshape(H, W)
        depth[i] = np.where(m, ob["t"], bg["t"]).reshape(H, W)

    return SyntheticScene(
        params=p, cameras=cams, images=images, images_gt=images_gt, masks=masks, depth=depth,
        depth_gt=depth_gt, object_bounds=obj_bounds, background_mesh=_merge([s.mesh for s in surfaces]),
        object_mesh=obj.mesh, object_kind=obj.kind, object_texture=obj_tex, light_direction=light.key,
    )


def _to_u8(img: np.ndarray) -> np.ndarray:
    return np.clip(np.round(np.asarray(img, np.float32) * 255.0), 0, 255).astype(np.uint8)


def save_scene(scene: SyntheticScene, folder: str | Path) -> Path:
    """Write ``scene`` to ``folder`` and return the folder.

    Layout: ``images/<name>.png`` (with the object), ``masks/<name>.png`` (0/255),
    ``groundtruth/<name>.png`` (without the object), ``depth/<name>.npy`` and ``depth_gt/<name>.npy``
    (float32 z-depth), ``cameras.json`` (:func:`sgpor_pipeline.scene.save_cameras`), ``transforms.json``
    (nerfstudio), ``background.ply`` / ``object.ply`` (true geometry) and ``scene.json`` (parameters,
    object bounds).
    """
    import open3d as o3d

    from .camera_io import write_transforms_json
    from .imageio import write_png

    folder = Path(folder)
    for sub in ("images", "masks", "groundtruth", "depth", "depth_gt"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    for i, cam in enumerate(scene.cameras):
        name = cam.name
        for sub, img in (("images", scene.images[i]), ("groundtruth", scene.images_gt[i])):
            path = folder / sub / f"{name}.png"
            try:
                write_png(path, _to_u8(img))
            except OSError as e:
                raise PipelineError(f"could not write image ({e})", path, fix="check the folder is writable") from e
        path = folder / "masks" / f"{name}.png"
        try:
            write_png(path, scene.masks[i].astype(bool))
        except OSError as e:
            raise PipelineError(f"could not write mask ({e})", path, fix="check the folder is writable") from e
        np.save(folder / "depth" / f"{name}.npy", scene.depth[i].astype(np.float32))
        np.save(folder / "depth_gt" / f"{name}.npy", scene.depth_gt[i].astype(np.float32))
    save_cameras(folder / "cameras.json", scene.cameras)
    write_transforms_json(scene.cameras, folder / "transforms.json", image_dir_prefix="images/")
    o3d.io.write_triangle_mesh(str(folder / "background.ply"), scene.background_mesh)
    o3d.io.write_triangle_mesh(str(folder / "object.ply"), scene.object_mesh)
    meta = {
        "params": asdict(scene.params),
        "object_bounds": scene.object_bounds.tolist(),
        "object_kind": scene.object_kind,
        "object_texture": scene.object_texture,
        "light_direction": np.asarray(scene.light_direction).tolist(),
        "world": "Z up, metres, floor at z=0; cameras OpenCV cam_from_world",
    }
    (folder / "scene.json").write_text(json.dumps(meta, indent=1))
    return folder


# --------------------------------------------------------------------------------------------------
# inserting a synthetic object into real photos


def viewing_axes_center(cameras: Sequence[Camera]) -> np.ndarray:
    """Least-squares point nearest to all cameras' optical axes (the point the cameras look at).

    Lightly regularised towards a point in front of the cameras (their mean viewing direction, twice
    their spread ahead), so near-parallel axes (forward-facing captures) still give a sensible answer;
    that point itself where the axes meet behind most of the cameras (they diverge a little: the
    SPIn-NeRF statue's met 4.7 units behind them), since the cameras look at nothing there.
    """
    centers = np.array([c.center for c in cameras])
    fwd = np.array([c.cam_from_world[2, :3] for c in cameras])
    fwd /= np.linalg.norm(fwd, axis=1, keepdims=True)
    spread = float(np.max(np.linalg.norm(centers - centers.mean(0), axis=1))) if len(cameras) > 1 else 0.0
    mean_fwd = fwd.mean(0)
    mean_fwd /= max(np.linalg.norm(mean_fwd), 1e-12)
    prior = centers.mean(0) + mean_fwd * max(2.0 * spread, 1.0)
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c, d in zip(centers, fwd):
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
    lam = 1e-3 * len(cameras)
    point = np.linalg.solve(A + lam * np.eye(3), b + lam * prior)
    return point if np.median(np.einsum("ij,ij->i", fwd, point - centers)) > 0 else prior


def _frame_from_up(up: np.ndarray, forward_hint: np.ndarray) -> np.ndarray:
    """world_from_local rotation whose local z is ``up``."""
    z = up / np.linalg.norm(up)
    x = forward_hint - z * (forward_hint @ z)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def insert_object(
    images: Sequence[np.ndarray],
    cameras: Sequence[Camera],
    seed: int = 0,
    position: Sequence[float] | np.ndarray | None = None,
    size: float | None = None,
    kind: str = "box",
    texture: str | None = None,
    up: Sequence[float] | np.ndarray | None = None,
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Composite a synthetic textured object into photos with known cameras.

    The object (``kind`` "box", "sphere" or "cylinder", textured with an skimage photo, Lambertian
    shaded) is ray cast alone in each camera and its shaded colour is pasted where it is hit; the
    returned masks are exactly the pasted pixels, and every other pixel is returned untouched. The
    original photos are therefore the ground truth of removing it.

    Defaults: ``position`` = the least-squares intersection of the cameras' viewing axes
    (:func:`viewing_axes_center`); ``size`` = 0.2 x the median camera-to-object distance;
    ``up`` = the mean of the cameras' up directions (-y axes), which orients the object and its light;
    ``texture`` drawn from the object textures by ``seed``.

    Limitations: the real scene's geometry is unknown, so the object is always drawn on top (no
    occlusion by foreground scene content) and casts no shadow; cameras should be undistorted
    (OpenCV-style distortion is honoured, other models' distortion is ignored).

    ``images``: HxWx3 arrays (float in [0,1], uint8 or uint16) matching the cameras' sizes; the
    results have the same dtype. Returns (images_with_object, masks) as lists (masks bool HxW).
    """
    import open3d as o3d  # noqa: F401  (fail early with a clear ImportError)

    if len(images) != len(cameras):
        raise PipelineError(f"insert_object got {len(images)} images but {len(cameras)} cameras",
                            fix="pass one camera per image")
    if kind not in OBJECT_KINDS:
        raise PipelineError(f"unknown object kind {kind!r}", fix=f"use one of {', '.join(OBJECT_KINDS)}")
    for img, cam in zip(images, cameras):
        img = np.asarray(img)
        if img.ndim != 3 or img.shape[2] != 3 or img.shape[:2] != (cam.height, cam.width):
            raise PipelineError(f"image for camera {cam.name} has shape {img.shape}, expected "
                                f"({cam.height}, {cam.width}, 3)", fix="pass RGB images matching the cameras")
    if not cameras:
        return [], []
    rng = np.random.default_rng(seed)
    pos = viewing_axes_center(cameras) if position is None else np.asarray(position, np.float64)
    centers = np.array([c.center for c in cameras])
    if size is None:
        size = 0.2 * float(np.median(np.linalg.norm(centers - pos, axis=1)))
    if up is None:
        up_v = -np.mean([c.cam_from_world[1, :3] for c in cameras], axis=0)
        if np.linalg.norm(up_v) < 1e-6:
            up_v = np.array([0.0, 0.0, 1.0])
    else:
        up_v = np.asarray(up, np.float64)
    fwd = np.mean([c.cam_from_world[2, :3] for c in cameras], axis=0)
    frame = _frame_from_up(up_v, fwd) @ _rot_z(rng.uniform(0, 2 * np.pi))
    half = _primitive_half(kind, float(size), rng)
    tex_name = texture or str(rng.choice(OBJECT_TEXTURES))
    surf = _Surface("object", kind, _texture(tex_name, rng, 256, tint=False), pos, half,
                    frame, fit=True, mesh=_primitive_mesh(kind, half, pos, frame))
    light_local = np.array([0.4, -0.3, 1.0])
    light_local /= np.linalg.norm(light_local)
    base = _frame_from_up(up_v, fwd)
    key = base @ light_local
    fill = base @ np.array([-0.5, 0.6, 0.3]) / np.linalg.norm([-0.5, 0.6, 0.3])
    light = _Lighting(key, fill, 0.35, 0.65, 0.2)
    scene = _raycasting_scene([surf])

    out_images: list[np.ndarray] = []
    out_masks: list[np.ndarray] = []
    for img, cam in zip(images, cameras):
        img = np.asarray(img)
        origins, dirs = _camera_rays(cam)
        hit = _cast(scene, origins, dirs)
        m = np.isfinite(hit["t"]) & (hit["t"] > 0)
        idx = np.flatnonzero(m)
        col = _shade([surf], hit["gid"][idx], hit["t"][idx].astype(np.float64), hit["normal"][idx],
                     origins[idx], dirs[idx], light, None)
        out = img.copy()
        flat = out.reshape(-1, 3)
        if np.issubdtype(img.dtype, np.integer):
            top = float(np.iinfo(img.dtype).max)
            flat[idx] = np.clip(np.round(col * top), 0, top).astype(img.dtype)
        else:
            flat[idx] = col.astype(img.dtype)
        out_images.append(out)
        out_masks.append(m.reshape(cam.height, cam.width))
    return out_images, out_masks
