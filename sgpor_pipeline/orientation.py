"""The export frame: Z up, metres (DESIGN.md section 5).

Structure from motion knows neither gravity nor metres: its world frame is whatever the first
image pair gave. For export (USD for robotics simulators, meshes, splats) every geometry is mapped
by one similarity ``x_export = s R (x_sfm - c)`` into a frame whose +Z is "up", whose unit is the
metre when a scale is known, and whose origin sits on the estimated floor below the point the
cameras look at.

Up (``FrameSettings.up``):

``"auto"`` (default)
    The horizon estimate: photographers rarely roll the camera, so every camera's x axis (OpenCV:
    right) is horizontal and "up" is the direction most perpendicular to all of them (the smallest
    eigenvector of sum x x^T). When the x axes are nearly parallel (a forward-facing capture, where
    that is ambiguous between up and the viewing direction), the plane of the camera centres (a
    grid held in front of the scene contains "up") or else the mean of the cameras' -y axes decides.
    The sign always agrees with the mean of the cameras' -y axes (OpenCV y points down). With
    ``ground_plane`` (default) and a ground plane found (:func:`find_ground_plane`: the plane through
    most SfM points that is level with the horizon and lies under the cameras), up is the horizon and
    the plane's normal together (:func:`level_on_ground`): the plane decides where the horizon is weak
    (a short arc of photos looking steeply down at a floor).
``"cameras"``
    The normalised mean of the cameras' -y axes (biased by the mean pitch of the cameras).
``"ring"``
    The normal of the best-fit plane of the camera centres, oriented by the mean -y axis (a
    turntable or a walk around at constant height).
``"nadir"``
    The reverse of the cameras' mean viewing direction (a drone's survey looking straight down, or
    photos of a table top from above: their image tops say nothing about up). ``"auto"`` reads such
    a capture this way by itself where the photos carry GPS.
``"+x"``, ``"-x"``, ``"+y"``, ``"-y"``, ``"+z"``, ``"-z"``
    A known axis of the SfM frame (e.g. ``"-y"`` for a frame that is already OpenCV-like).

Scale: ``scale`` (metres per SfM unit) or ``known_distance`` (two camera or image names and the
distance between their centres in metres). With neither, and ``scale_from_gps`` (default), the photos'
EXIF GPS positions give it where the camera moved far enough for their error (:mod:`sgpor_pipeline.gps`:
a walk along a street, not a room), and with it where the frame's origin lies on the map and the
compass bearing of +Y. Otherwise the unit is arbitrary (the SfM unit): the exporters say so in the log
and in the files' metadata (USD ``customLayerData`` ``sgpor:units``).

Origin (``FrameSettings.origin``): ``"floor"`` (default): horizontally the point the cameras look
at (where their axes meet behind them, the median of the points they see), vertically the ground
plane there (the floor, street or table the scene stands on), or without one a low percentile of
the heights of the opaque Gaussians (which Gaussians fitted under a floor pull down); ``"center"``:
that point itself; ``"none"``: the SfM origin.

Heading: with the GPS scale (and ``gps_north``, default) +Y points north and +X east, as on a map;
otherwise the first registered camera (by name) looks along +Y (its viewing direction projected on
the horizontal plane), so the result does not depend on the SfM frame's arbitrary rotation.

The export stage's parameters of the same names set them (``export.up``, ``export.scale``,
``export.known_distance``, ``export.scale_from_gps``, ``export.origin``; the CLI's ``--up`` and ``--scale``), read by
:meth:`FrameSettings.from_params`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from .errors import PipelineError
from .scene import Camera

log = logging.getLogger(__name__)

UP_METHODS = ("auto", "cameras", "ring", "nadir", "+x", "-x", "+y", "-y", "+z", "-z")
ORIGINS = ("floor", "center", "none")
_AXES = {"x": 0, "y": 1, "z": 2}


@dataclass
class FrameSettings:
    """How the export frame is chosen (see the module docstring)."""

    up: str = "auto"
    scale: float | None = None  # metres per SfM unit
    known_distance: tuple[str, str, float] | None = None  # (camera a, camera b, metres between them)
    scale_from_gps: bool = True  # without the two above: metres from the photos' GPS, where it is good enough
    origin: str = "floor"
    floor_percentile: float = 1.0  # without a ground plane: percentile of the opaque Gaussians' heights
    ground_plane: bool = True  # find the plane the cameras stand over; it levels up and places the floor
    ground_tolerance: float = 0.01  # inlier distance to the ground plane, in scene radii
    ground_min_fraction: float = 0.1  # least share of the scene's points on the ground plane
    ground_seed: int = 0  # of the plane search (RANSAC)
    gps_north: bool = True  # with the GPS scale: +Y north, +X east (else the first camera looks along +Y)

    def __post_init__(self) -> None:
        if self.up not in UP_METHODS:
            raise PipelineError(f"unknown up-axis method {self.up!r}", fix=f"use one of {', '.join(UP_METHODS)}")
        if self.origin not in ORIGINS:
            raise PipelineError(f"unknown export origin {self.origin!r}", fix=f"use one of {', '.join(ORIGINS)}")
        if self.scale is not None and not (math.isfinite(self.scale) and self.scale > 0):
            raise PipelineError(f"export scale must be a positive number, got {self.scale!r}")
        if self.known_distance is not None:
            if len(self.known_distance) != 3 or not float(self.known_distance[2]) > 0:
                raise PipelineError(f"known_distance must be [camera_a, camera_b, metres > 0], got "
                                    f"{self.known_distance!r}")
            a, b, d = self.known_distance
            self.known_distance = (str(a), str(b), float(d))

    @classmethod
    def from_params(cls, params: Any) -> FrameSettings:
        """Defaults, overridden by same-named attributes of ``params`` (the export stage's params)."""
        kw = {f.name: getattr(params, f.name) for f in fields(cls)
              if params is not None and getattr(params, f.name, None) is not None}
        return cls(**kw)


# --------------------------------------------------------------------------------------------------
# quaternions (w, x, y, z), Hamilton convention, as the Gaussians store them


def rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """The angle in degrees of the rotation between two 3x3 rotation matrices."""
    c = (np.trace(np.asarray(a).T @ np.asarray(b)) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, float(c)))))


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of (..., 4) arrays in (w, x, y, z) order (rotation b, then a)."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b), -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions (w, x, y, z), any norm, to (..., 3, 3) rotation matrices."""
    q = np.asarray(q, np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), 1e-12)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices to unit quaternions (..., 4) (w, x, y, z) with w >= 0."""
    R = np.asarray(R, np.float64)
    shape = R.shape[:-2]
    R = R.reshape(-1, 3, 3)
    m00, m11, m22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    # Shepperd's method: pick the largest of the four candidate denominators per matrix
    cand = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], 1)
    k = np.argmax(cand, axis=1)
    q = np.empty((len(R), 4))
    s = np.sqrt(np.maximum(cand[np.arange(len(R)), k], 1e-300)) * 2  # = 4 |q_k|
    i = k == 0
    q[i] = np.stack([s[i] / 4, (R[i, 2, 1] - R[i, 1, 2]) / s[i], (R[i, 0, 2] - R[i, 2, 0]) / s[i],
                     (R[i, 1, 0] - R[i, 0, 1]) / s[i]], 1)
    i = k == 1
    q[i] = np.stack([(R[i, 2, 1] - R[i, 1, 2]) / s[i], s[i] / 4, (R[i, 0, 1] + R[i, 1, 0]) / s[i],
                     (R[i, 0, 2] + R[i, 2, 0]) / s[i]], 1)
    i = k == 2
    q[i] = np.stack([(R[i, 0, 2] - R[i, 2, 0]) / s[i], (R[i, 0, 1] + R[i, 1, 0]) / s[i], s[i] / 4,
                     (R[i, 1, 2] + R[i, 2, 1]) / s[i]], 1)
    i = k == 3
    q[i] = np.stack([(R[i, 1, 0] - R[i, 0, 1]) / s[i], (R[i, 0, 2] + R[i, 2, 0]) / s[i],
                     (R[i, 1, 2] + R[i, 2, 1]) / s[i], s[i] / 4], 1)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q.reshape(*shape, 4)


# --------------------------------------------------------------------------------------------------
# spherical harmonics under a rotation


def _sh_basis(dirs: np.ndarray, degree: int) -> np.ndarray:
    """[M, (degree+1)^2] real SH basis (the rasterizer's convention) at unit directions [M,3]."""
    import torch

    from .gaussians._raster_common import eval_sh

    k = (degree + 1) ** 2
    eye = torch.eye(k, dtype=torch.float64)[:, :, None].expand(k, k, 3)  # coefficient set j = e_j
    d = torch.from_numpy(np.asarray(dirs, np.float64))[:, None, :]  # [M,1,3] broadcast over j
    return eval_sh(degree, d, eye[None]).numpy()[..., 0]  # [M, k]


def sh_rotation_matrix(R: np.ndarray, degree: int) -> np.ndarray:
    """[K,K] matrix T (block diagonal per band) with sum_k (T c)_k Y_k(R d) = sum_k c_k Y_k(d).

    Found by least squares on a fixed set of directions (exact up to rounding: every band of real
    SH is closed under rotations).
    """
    k = (degree + 1) ** 2
    if degree == 0:
        return np.eye(1)
    n = 4 * k + 16
    i = np.arange(n) + 0.5  # Fibonacci sphere: well spread, deterministic
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5 ** 0.5) * i
    d = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)
    A = _sh_basis(d @ np.asarray(R, np.float64).T, degree)  # Y(R d)
    B = _sh_basis(d, degree)  # Y(d)
    T, *_ = np.linalg.lstsq(A, B, rcond=None)
    T[np.abs(T) < 1e-12] = 0.0
    return T


def rotate_sh(shN: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Rotate higher-order SH coefficients [N, K-1, 3] (no DC term) by the rotation ``R``."""
    shN = np.asarray(shN)
    if shN.shape[1] == 0:
        return shN.copy()
    degree = int(round(math.sqrt(shN.shape[1] + 1))) - 1
    T = sh_rotation_matrix(R, degree)[1:, 1:]
    return np.einsum("jk,nkc->njc", T, shN.astype(np.float64)).astype(shN.dtype)


# --------------------------------------------------------------------------------------------------
# similarity transforms


#: glTF is right-handed with +Y up: (x, y, z) in the Z-up export frame -> (x, z, -y) (a rotation)
GLTF_FROM_ZUP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


@dataclass
class Similarity:
    """``x -> s R x + t`` (export_from_sfm when used for the export frame)."""

    s: float = 1.0
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        self.s = float(self.s)
        self.R = np.asarray(self.R, np.float64).reshape(3, 3)
        self.t = np.asarray(self.t, np.float64).reshape(3)

    @property
    def matrix(self) -> np.ndarray:
        """4x4 homogeneous matrix (column vectors)."""
        M = np.eye(4)
        M[:3, :3] = self.s * self.R
        M[:3, 3] = self.t
        return M

    def inverse(self) -> Similarity:
        return Similarity(1.0 / self.s, self.R.T, -(self.R.T @ self.t) / self.s)

    def apply(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, np.float64)
        return self.s * p @ self.R.T + self.t

    def rotate_quats(self, quats: np.ndarray) -> np.ndarray:
        """Gaussian orientations (w, x, y, z) [N,4] after the rotation (their norms are kept)."""
        qr = quat_from_matrix(self.R)
        return quat_multiply(qr[None], np.asarray(quats, np.float64))

    def camera(self, cam: Camera) -> Camera:
        """The same camera in the transformed frame (it sees the same image)."""
        Rc = cam.cam_from_world[:3, :3]
        tc = cam.cam_from_world[:3, 3]
        T = np.eye(4)
        T[:3, :3] = Rc @ self.R.T
        T[:3, 3] = self.s * tc - Rc @ self.R.T @ self.t
        return Camera(cam.name, cam.width, cam.height, cam.K.copy(), T, cam.image, cam.model,
                      list(cam.distortion))

    def to_dict(self) -> dict[str, Any]:
        return {"scale": self.s, "rotation": self.R.tolist(), "translation": self.t.tolist(),
                "matrix": self.matrix.tolist()}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Similarity:
        """The similarity :meth:`to_dict` wrote."""
        return cls(data["scale"], data["rotation"], data["translation"])


def umeyama(src: np.ndarray, dst: np.ndarray, scale: bool = True) -> Similarity:
    """The similarity ``x -> s R x + t`` minimising ``sum |s R src_i + t - dst_i|^2`` (Umeyama 1991).

    ``src``, ``dst``: [N,3] corresponding points, N >= 3 not all collinear for a unique rotation.
    ``scale=False`` fixes s = 1 (a rigid transform).
    """
    src = np.asarray(src, np.float64).reshape(-1, 3)
    dst = np.asarray(dst, np.float64).reshape(-1, 3)
    if len(src) != len(dst) or len(src) < 2:
        raise ValueError("umeyama needs two equally long lists of at least 2 points")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(xd.T @ xs / len(src))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt)) or 1.0  # a proper rotation, never a reflection
    R = U @ D @ Vt
    var_s = (xs ** 2).sum() / len(src)
    s = float((S * np.diag(D)).sum() / var_s) if scale and var_s > 0 else 1.0
    return Similarity(s, R, mu_d - s * R @ mu_s)


def transform_model(model: Any, sim: Similarity) -> Any:
    """A :class:`~sgpor_pipeline.gaussians.model.GaussianModel` mapped by ``sim``.

    Means are transformed, orientations rotated, log-scales shifted by log(s), higher-order SH
    rotated; opacities and the DC colour are unchanged. Values stay pre-activation, float32.
    """
    import torch

    from .gaussians.model import GaussianModel

    p = model.numpy()
    f32 = np.float32
    params = {
        "means": torch.from_numpy(sim.apply(p["means"]).astype(f32)),
        "quats": torch.from_numpy(sim.rotate_quats(p["quats"]).astype(f32)),
        "scales": torch.from_numpy((p["scales"].astype(np.float64) + math.log(sim.s)).astype(f32)),
        "opacities": torch.from_numpy(p["opacities"].copy()),
        "sh0": torch.from_numpy(p["sh0"].copy()),
        "shN": torch.from_numpy(rotate_sh(p["shN"], sim.R).astype(f32)),
    }
    return GaussianModel(params, model.max_sh_degree)


# --------------------------------------------------------------------------------------------------
# estimating up, scale and origin


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v / n if n > 1e-12 else v


def look_at_center(cameras: Sequence[Camera]) -> np.ndarray:
    """The point nearest to all viewing axes (see :func:`sgpor_pipeline.synthetic.viewing_axes_center`)."""
    from .synthetic import viewing_axes_center

    return viewing_axes_center(list(cameras))


def surface_points(points: np.ndarray | None, means: np.ndarray | None = None,
                   opacities: np.ndarray | None = None, min_points: int = 30) -> tuple[np.ndarray | None, str]:
    """What the scene's surfaces are known by, and its name: the SfM ``points`` where there are at least
    ``min_points``, else the opaque Gaussians (``means`` with activated ``opacities`` >= 0.5), else None.
    Non-finite points are left out."""
    if points is not None:
        points = np.asarray(points, np.float64).reshape(-1, 3)
        points = points[np.isfinite(points).all(1)]
        if len(points) >= min_points:
            return points, "SfM points"
    if means is None or not len(means):
        return None, "none"
    opaque = np.asarray(means, np.float64).reshape(-1, 3)
    if opacities is not None:
        opaque = opaque[np.asarray(opacities).reshape(-1) >= 0.5]
    opaque = opaque[np.isfinite(opaque).all(1)]
    return (opaque, "opaque Gaussians") if len(opaque) else (None, "none")


MAX_CENTER_POINTS = 20_000  # scene_center measures depths of at most about this many points


def scene_center(cameras: Sequence[Camera], points: np.ndarray | None = None) -> tuple[np.ndarray, str]:
    """The middle of the scene the cameras see, and how it was found.

    The look-at point (:func:`look_at_center`), unless ``points`` on the scene's surfaces (SfM points)
    say it is wrong: its median depth in the cameras is not within 2x of the points' median depth
    (inward captures: 0.97-1.27). That happens to forward-facing captures, whose nearly parallel viewing
    axes meet anywhere: the SPIn-NeRF statue's meet behind the cameras, and the look-at point falls back
    to 11 units ahead of them, while the statue stands 30-40 in front. The median of the points in front
    of the cameras is taken there.
    """
    c = look_at_center(cameras)
    if points is None or len(points) < 10 or not len(cameras):
        return c, "look-at point"
    P = np.asarray(points, np.float64).reshape(-1, 3)
    P = P[:: max(1, len(P) // MAX_CENTER_POINTS)]  # a regular subsample: [cameras x points] depths below
    fwd = np.array([cam.cam_from_world[2, :3] for cam in cameras])
    centers = np.array([cam.center for cam in cameras])
    depth_c = float(np.median(np.einsum("ij,ij->i", fwd, c - centers)))
    depths = [(P - o) @ f for o, f in zip(centers, fwd)]
    in_front = [d[d > 0] for d in depths]
    if not all(len(d) for d in in_front):
        return c, "look-at point"
    depth_p = float(np.median([np.median(d) for d in in_front]))
    if depth_c > 0 and depth_p / 2.0 <= depth_c <= 2.0 * depth_p:
        return c, "look-at point"
    front = np.median(np.stack(depths), axis=0) > 0
    return np.median(P[front] if front.any() else P, axis=0), "middle of the scene"


def scene_center_radius(cameras: Sequence[Camera], points: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """The middle of the scene (:func:`scene_center`; ``points``: SfM points or opaque Gaussians, optional)
    and the median camera distance to it (a scene size: the mesh's voxel and depth range follow it)."""
    c, _ = scene_center(cameras, points)
    centers = np.array([cam.center for cam in cameras])
    r = float(np.median(np.linalg.norm(centers - c, axis=1))) if len(cameras) else 1.0
    if not r > 0:
        r = 1.0
    return c, r


def estimate_up(cameras: Sequence[Camera], method: str = "auto") -> tuple[np.ndarray, str]:
    """The up direction (unit, SfM frame) and the name of the method that decided it."""
    if method in UP_METHODS[4:]:
        v = np.zeros(3)
        v[_AXES[method[1]]] = 1.0 if method[0] == "+" else -1.0
        return v, f"given {method}"
    if not cameras:
        raise PipelineError("cannot estimate the up axis without cameras",
                            fix="give the up axis explicitly (up = '+z', ...)")
    Rs = np.array([c.cam_from_world[:3, :3] for c in cameras])
    ups = -Rs[:, 1, :]  # each camera's up (-y), world frame
    u0 = _unit(ups.mean(0))
    if np.linalg.norm(ups.mean(0)) < 1e-6:
        u0 = np.array([0.0, 0.0, 1.0])
    if method == "cameras":
        return u0, "mean camera up (-y)"
    if method == "nadir":
        return -_unit(Rs[:, 2, :].sum(0)), "the cameras look down (given: nadir)"
    centers = np.array([c.center for c in cameras])
    if method == "ring":
        if len(cameras) < 3:
            return u0, "mean camera up (-y); too few cameras for a plane"
        _, _, vt = np.linalg.svd(centers - centers.mean(0))
        n = vt[2]
        return (n if n @ u0 >= 0 else -n), "camera-centre plane normal"
    # auto: the horizon (camera x axes are horizontal)
    xs = Rs[:, 0, :]
    M = xs.T @ xs / len(xs)
    w, V = np.linalg.eigh(M)  # ascending
    if len(cameras) >= 2 and w[1] > 4.0 * w[0] + 1e-6 and w[1] > 1e-4:
        up, how = V[:, 0], "horizon (camera x axes)"
    else:
        # x axes nearly parallel: up is in the plane orthogonal to them, but where?
        xbar = V[:, 2]
        up, how = None, ""
        if len(cameras) >= 3:
            _, sv, vt = np.linalg.svd(centers - centers.mean(0))
            if sv[1] > 0.2 * sv[0] and sv[2] < 0.3 * sv[1]:  # the centres span a plane: it contains up
                cand = np.cross(xbar, vt[2])
                if np.linalg.norm(cand) > 0.5:
                    up, how = cand, "horizon + camera-centre plane"
        if up is None:
            up, how = u0 - (u0 @ xbar) * xbar, "horizon + mean camera up"
    up = _unit(up)
    if up @ u0 < 0:
        up = -up
    if up @ u0 < 0.3:  # disagrees badly with where the cameras' tops point: trust the cameras
        return u0, "mean camera up (-y); the horizon estimate disagreed"
    return up, how


@dataclass
class GroundPlane:
    """The plane the cameras stand over (the floor, a street, the table under an object), SfM frame."""

    normal: np.ndarray  # unit, towards the cameras
    point: np.ndarray  # a point on the plane
    inliers: int
    points: int  # of the points searched
    camera_height: float  # the cameras' median height above the plane (SfM units)
    source: str  # what the points were ("SfM points", "opaque Gaussians")

    @property
    def fraction(self) -> float:
        return self.inliers / max(self.points, 1)

    def height_below(self, p: np.ndarray, up: np.ndarray) -> float:
        """How far below ``p``, along ``up``, the plane is (negative: above)."""
        return float((np.asarray(p) - self.point) @ self.normal / (np.asarray(up) @ self.normal))

    def to_dict(self) -> dict[str, Any]:
        return {"normal_in_sfm_frame": self.normal.tolist(), "point_in_sfm_frame": self.point.tolist(),
                "inliers": self.inliers, "points": self.points, "fraction": self.fraction,
                "camera_height_sfm": self.camera_height, "source": self.source}


def find_ground_plane(points: np.ndarray, cameras: Sequence[Camera], tolerance: float = 0.01,
                      min_fraction: float = 0.1, seed: int = 0, iterations: int = 2000,
                      max_points: int = 20000, source: str = "points",
                      up_hint: np.ndarray | None = None) -> tuple[GroundPlane | None, str]:
    """The ground: the plane through most of ``points`` (within ``tolerance`` scene radii) that the
    cameras stand over, or (None, why not).

    A RANSAC over planes that (1) are normal to every camera's x axis as well as the horizon allows
    (photographers hold the camera level: the mean (x . n)^2 is at most 4x the horizon's own, or
    sin^2 3 degrees), (2) face ``up_hint`` (default: the cameras' mean -y; n . up_hint >= 0.3),
    (3) have at least 90 % of the
    cameras above them, at a median height of at most 1.5 scene radii (a plane the cameras look down
    on, not a ceiling, a far hillside or a wall beside them). The scene radius is the larger of the
    cameras' median distance to their look-at point and the points' median distance to their nearest
    camera. The best is refined by least squares on its inliers and must hold ``min_fraction`` of the
    points.
    """
    P = np.asarray(points, np.float64).reshape(-1, 3)
    P = P[np.isfinite(P).all(1)]
    cams = list(cameras)
    if len(P) < 30 or len(cams) < 2:
        return None, f"{len(P)} points and {len(cams)} cameras are too few to find a plane"
    rng = np.random.default_rng(seed)
    if len(P) > max_points:
        P = P[rng.choice(len(P), max_points, replace=False)]
    Rs = np.array([c.cam_from_world[:3, :3] for c in cams])
    xs = Rs[:, 0, :]
    u0 = _unit(np.asarray(up_hint, np.float64) if up_hint is not None else -Rs[:, 1, :].sum(0))
    horizon = float(np.linalg.eigvalsh(xs.T @ xs / len(xs))[0])
    max_roll2 = max(4.0 * horizon, math.sin(math.radians(3.0)) ** 2)
    centers = np.array([c.center for c in cams])
    # the scene's size: the cameras' distance to what they look at, or to the points they see where
    # the viewing axes barely converge (a forward-facing capture: the look-at point is unreliable)
    nearest = np.sqrt(np.min([((P - c) ** 2).sum(1) for c in centers], axis=0))
    radius = max(scene_center_radius(cams)[1], float(np.median(nearest)))
    tol = tolerance * radius

    tri = P[rng.integers(0, len(P), (iterations, 3))]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-12 * radius ** 2
    n = n[ok] / norm[ok, None]
    n *= np.where(n @ u0 < 0, -1.0, 1.0)[:, None]
    off = -np.einsum("ij,ij->i", n, tri[ok, 0])
    heights = centers @ n.T + off  # [cameras, candidates]
    ok = ((n @ u0 >= 0.3) & (np.mean((xs @ n.T) ** 2, 0) <= max_roll2)
          & (np.mean(heights > 0, 0) >= 0.9) & (np.median(heights, 0) <= 1.5 * radius))
    if not ok.any():
        return None, "no plane below the cameras is level with their horizon"
    n, off = n[ok], off[ok]
    counts = np.concatenate([(np.abs(P @ n[i:i + 256].T + off[i:i + 256]) <= tol).sum(0)
                             for i in range(0, len(n), 256)])
    best = int(np.argmax(counts))
    normal, offset = n[best], off[best]
    for _ in range(2):  # least squares on the inliers
        inl = P[np.abs(P @ normal + offset) <= tol]
        if len(inl) < 3:
            break
        mid = inl.mean(0)
        normal = np.linalg.svd(inl - mid, full_matrices=False)[2][2]
        normal = normal if normal @ u0 >= 0 else -normal
        offset = -float(normal @ mid)
    count = int((np.abs(P @ normal + offset) <= tol).sum())
    if count < min_fraction * len(P):
        return None, (f"no level plane below the cameras holds {min_fraction:.0%} of the {source} "
                      f"(the best holds {count / len(P):.0%})")
    point = -offset * normal
    return GroundPlane(normal, point, count, len(P), float(np.median(centers @ normal + offset)), source), ""


def level_on_ground(cameras: Sequence[Camera], ground: GroundPlane, roll_deg: float = 2.0,
                    ground_deg: float = 5.0) -> np.ndarray:
    """"Up" from the horizon and the ground plane's normal together.

    The horizon fixes up firmly only where the cameras' x axes spread (a wide arc); a short arc of
    photos looking steeply down (a floor seen from a metre above) leaves it free along the viewing
    direction, where the mean camera up is biased by the pitch (mip-NeRF 360 room: 50 degrees). The
    minimiser over unit u of mean (x_i . u)^2 / sin^2(roll) + sin^2(u, n) / sin^2(ground) is the
    smallest eigenvector of a 3x3 matrix: the ground decides where the horizon does not, and the
    horizon where the ground may slope. ``roll`` is ``roll_deg`` or, when larger, the cameras' RMS roll
    against the ground plane (a photographer who tilts the camera: room 6.8 degrees)."""
    xs = np.array([c.cam_from_world[0, :3] for c in cameras])
    n = ground.normal
    roll2 = max(math.sin(math.radians(roll_deg)) ** 2, float(np.mean((xs @ n) ** 2)))  # their roll on the ground
    Q = (xs.T @ xs / len(xs) / roll2
         + (np.eye(3) - np.outer(n, n)) / math.sin(math.radians(ground_deg)) ** 2)
    u = np.linalg.eigh(Q)[1][:, 0]
    return u if u @ n >= 0 else -u


def _rotation_to_z(up: np.ndarray, heading: np.ndarray | None) -> np.ndarray:
    """R with R up = +z and R heading (projected on the horizontal plane) = +y."""
    z = _unit(np.asarray(up, np.float64))
    y = None
    if heading is not None:
        h = heading - z * (heading @ z)
        if np.linalg.norm(h) > 1e-6:
            y = _unit(h)
    if y is None:
        a = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        y = _unit(np.cross(z, a))
    x = np.cross(y, z)
    return np.stack([x, y, z])  # rows: the new axes in old coordinates


def _find_camera(cameras: Sequence[Camera], name: str) -> Camera:
    for c in cameras:
        if name in (c.name, c.image):
            return c
    raise PipelineError(f"known_distance names camera {name!r}, which is not in the run",
                        fix=f"use one of: {', '.join(c.name for c in list(cameras)[:10])}...")


@dataclass
class ExportFrame:
    """The similarity into the export frame and how it was found."""

    transform: Similarity  # export_from_sfm
    up_sfm: np.ndarray
    up_method: str
    metric: bool  # True when the unit is the metre
    scale_source: str
    origin: str
    gps: dict[str, Any] | None = None  # the photos' GPS: the scale it gave (GpsScale.to_dict), or why not
    ground: dict[str, Any] | None = None  # the ground plane (GroundPlane.to_dict) or why none was used
    # where the sfm stage moved the given cameras (sgpor_pipeline.sfm.conditioning_frame): sfm_from_input
    given: Similarity | None = None

    @property
    def units(self) -> str:
        return "metres" if self.metric else "arbitrary"

    def to_dict(self) -> dict[str, Any]:
        return {"format": "sgpor-export-frame/1", "up_axis": "Z", "units": self.units,
                "scale_source": self.scale_source, "up_method": self.up_method,
                "up_in_sfm_frame": self.up_sfm.tolist(), "origin": self.origin,
                "export_from_sfm": self.transform.to_dict(), **({"gps": self.gps} if self.gps else {}),
                **({"ground": self.ground} if self.ground else {}),
                **({"sfm_from_input": self.given.to_dict()} if self.given is not None else {})}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ExportFrame:
        """The frame :meth:`to_dict` wrote (``export_frame.json``)."""
        given = data.get("sfm_from_input")
        return cls(Similarity.from_dict(data["export_from_sfm"]),
                   np.asarray(data["up_in_sfm_frame"], np.float64), data["up_method"], data["units"] == "metres",
                   data["scale_source"], data["origin"], data.get("gps"), data.get("ground"),
                   Similarity.from_dict(given) if given else None)

    def describe(self) -> str:
        gps = (f"; the photos' GPS was not used: {self.gps['reason']}"
               if self.gps and not self.gps.get("used") else "")
        unit = ("metres (" + self.scale_source + ")") if self.metric else \
            f"ARBITRARY units (no scale given: set a scale or a known distance between two cameras{gps})"
        ground = (f" (no ground plane: {self.ground['reason']})"
                  if self.ground and "reason" in self.ground else "")
        return f"export frame: Z up ({self.up_method}), {unit}, origin {self.origin}{ground}"


def _nadir_by_gps(cameras: Sequence[Camera], gps: Mapping[str, Sequence[float | None] | None],
                  up: np.ndarray, how: str) -> tuple[np.ndarray, str]:
    """Up for cameras that all look one way: level (the horizon's up) or straight down (a drone's grid,
    whose image "up" is just its heading: then up is the reverse of their viewing direction)? The
    cameras alone cannot tell; the photos' GPS track can: projected on the true horizontal the camera
    centres map onto it by a 2D similarity, on the wrong one the grid collapses to a line (or mirrors).
    Returns (up, how), changed only when the downward reading fits the GPS at half the residual or
    better (or where only it fits)."""
    fwd = np.array([c.cam_from_world[2, :3] for c in cameras])
    mean = fwd.mean(0) if len(fwd) else np.zeros(3)
    if np.linalg.norm(mean) < 0.9:  # the cameras look different ways: the horizon is not in doubt
        return up, how
    nadir = -_unit(mean)
    if nadir @ up > math.cos(math.radians(30.0)):
        return up, how
    from .gps import gps_scale

    level, _ = gps_scale(cameras, gps, up)
    down, _ = gps_scale(cameras, gps, nadir)
    if down is None or (level is not None and down.residual_m >= 0.5 * level.residual_m):
        return up, how
    against = f"; {level.residual_m:.1f} m on the horizon's" if level is not None else ""
    return nadir, (f"the cameras look down (nadir): their GPS track fits that horizontal within "
                   f"{down.residual_m:.1f} m RMS{against}")


def compute_export_frame(cameras: Sequence[Camera], settings: FrameSettings | None = None,
                         means: np.ndarray | None = None, opacities: np.ndarray | None = None,
                         gps: Mapping[str, Sequence[float | None] | None] | None = None,
                         points: np.ndarray | None = None, given: Similarity | None = None) -> ExportFrame:
    """The export frame for a scene seen by ``cameras`` (registered ones; novel cameras are ignored).

    ``points`` (SfM frame: the SfM points, which lie on surfaces), or else the opaque ones of the
    Gaussians' ``means`` (``opacities`` activated, in [0,1]), give the ground plane
    (:func:`find_ground_plane`), which levels up (``up="auto"``) and places the floor for
    ``origin="floor"``; without a ground plane a low percentile of the opaque Gaussians' heights does,
    and without Gaussians the origin is the look-at point. ``gps`` (image name -> (latitude,
    longitude, altitude)): the photos' GPS positions, for the scale when none is given. ``given``: the
    sfm stage's sfm_from_input where it moved the given cameras: a given ``scale`` is per unit of those
    cameras, and without a scale the export is in their units.
    """
    settings = settings or FrameSettings()
    cams = [c for c in cameras if c.image is not None] or list(cameras)
    up, how = estimate_up(cams, settings.up)
    opaque, _ = surface_points(None, means, opacities)
    if gps and settings.up == "auto":
        up, how = _nadir_by_gps(cams, gps, up, how)
    seen, src = surface_points(points)  # the SfM points, else the opaque Gaussians (filtered once, above)
    if seen is None and opaque is not None:
        seen, src = opaque, "opaque Gaussians"
    ground, ground_info = None, None
    if settings.ground_plane and (settings.origin == "floor" or settings.up == "auto"):
        if seen is not None:
            ground, why = find_ground_plane(seen, cams, settings.ground_tolerance, settings.ground_min_fraction,
                                            settings.ground_seed, source=src, up_hint=up)
            ground_info = ground.to_dict() if ground is not None else {"reason": why}
        else:
            ground_info = {"reason": "no SfM points and no opaque Gaussians to find it in"}
    if ground is not None and settings.up == "auto":
        levelled = level_on_ground(cams, ground)
        turn = math.degrees(math.acos(float(np.clip(levelled @ up, -1.0, 1.0))))
        how = (f"horizon (camera x axes) and the ground plane ({ground.fraction:.0%} of the {ground.source}), "
               f"{turn:.1f} degrees from {how}")
        up = levelled
        ground_info["levelled_deg"] = turn
    first = sorted(cams, key=lambda c: c.name)[0] if cams else None
    heading = first.cam_from_world[2, :3] if first is not None else None
    R = _rotation_to_z(up, heading)

    unit = 1.0 / given.s if given is not None else 1.0  # the given cameras' units per SfM unit
    if settings.scale is not None:
        per = "unit of the given cameras" if given is not None else "SfM unit"
        s, source, metric = float(settings.scale) * unit, f"scale {settings.scale:g} m per {per}", True
    elif settings.known_distance is not None:
        a, b, metres = settings.known_distance
        d = float(np.linalg.norm(_find_camera(cams, a).center - _find_camera(cams, b).center))
        if not d > 1e-12:
            raise PipelineError(f"cameras {a!r} and {b!r} are at the same place: cannot set the scale",
                                fix="pick two cameras further apart")
        s, source, metric = metres / d, f"{a} to {b} = {metres:g} m", True
    else:
        s, source, metric = unit, "none", False
    gps_info: dict[str, Any] | None = None
    fitted = None
    if gps and settings.scale is None and settings.known_distance is None:
        if settings.scale_from_gps:
            from .gps import gps_scale, level_by_altitude

            fitted, why = gps_scale(cams, gps, up)
            level: dict[str, Any] | None = None
            if fitted is not None and settings.up == "auto":  # the altitudes hold up along a walk
                levelled, level = level_by_altitude(cams, gps, up, fitted)
                refit = gps_scale(cams, gps, levelled)[0] if levelled is not None else None
                if refit is not None:  # (the track projected on the levelled horizontal)
                    up, fitted = levelled, refit
                    how = f"{how}, levelled by the photos' GPS altitudes ({level['turn_deg']:.1f} degrees)"
                    R = _rotation_to_z(up, heading)
            gps_info = fitted.to_dict() if fitted is not None else {"used": False, "reason": why}
            if fitted is not None:
                s, source, metric = fitted.scale, fitted.describe(), True
                gps_info["used"] = True
                if level is not None:
                    gps_info["levelling"] = level
                if settings.gps_north:  # east-north-up, as maps, GIS and ROS (REP 103) have it
                    R = _rotation_to_z(up, fitted.north())
        else:
            gps_info = {"used": False, "reason": "export.scale_from_gps is off"}

    if settings.origin == "none" or not cams:
        c = np.zeros(3)
        origin = "SfM origin"
    else:
        c, origin = scene_center(cams, seen)
        if settings.origin == "floor" and ground is not None and ground.normal @ up >= math.cos(math.radians(10)):
            c = c - ground.height_below(c, up) * up
            origin = f"ground plane below the {origin}"
            ground_info["origin"] = True
        elif settings.origin == "floor" and opaque is not None:
            _, r = scene_center_radius(cams, seen)
            horiz = (opaque - c) - np.outer((opaque - c) @ up, up)
            near = opaque[np.linalg.norm(horiz, axis=1) <= 3.0 * r]
            if len(near) >= 10:
                c = c + float(np.percentile((near - c) @ up, settings.floor_percentile)) * up
                origin = f"floor below the {origin}"
    t = -s * (R @ c)
    if fitted is not None and gps_info.get("used"):  # where the export frame sits on the map
        lat, lon = fitted.latitude_longitude(c)
        gps_info.update(origin_latitude=lat, origin_longitude=lon, azimuth_of_y_deg=fitted.azimuth_deg(R.T[:, 1]),
                        azimuth_of_x_deg=fitted.azimuth_deg(R.T[:, 0]))
    if ground_info is not None and ground is not None:
        ground_info["camera_height"] = ground.camera_height * s  # export units
    return ExportFrame(Similarity(s, R, t), up, how, metric, source, origin, gps_info, ground_info, given)
