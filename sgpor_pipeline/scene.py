"""Camera type shared by every stage.

Convention (DESIGN.md section 5): OpenCV/COLMAP axes (x right, y down, z forward), a 4x4
``cam_from_world`` matrix and a 3x3 intrinsic matrix ``K``. After undistortion every camera is
PINHOLE; imported cameras may still carry a distortion model until the sfm stage undistorts.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

CAMERAS_FORMAT = "sgpor-cameras/1"


@dataclass
class Camera:
    """One camera. ``image`` is the ingested image's view name, or None for a novel view."""

    name: str
    width: int
    height: int
    K: np.ndarray  # [3,3] float64
    cam_from_world: np.ndarray  # [4,4] float64
    image: str | None = None
    model: str = "PINHOLE"  # COLMAP model name of the original camera
    distortion: list[float] = field(default_factory=list)  # COLMAP extra params after fx,fy,cx,cy

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        self.cam_from_world = np.asarray(self.cam_from_world, dtype=np.float64).reshape(4, 4)
        self.width = int(self.width)
        self.height = int(self.height)

    @property
    def world_from_cam(self) -> np.ndarray:
        return np.linalg.inv(self.cam_from_world)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates."""
        R = self.cam_from_world[:3, :3]
        t = self.cam_from_world[:3, 3]
        return -R.T @ t

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Continuous pixel coordinates [N,2] (x, y; pixel centres at .5) and z-depths [N] of world
        points [N,3] (PINHOLE; points behind the camera get mirrored coordinates: check z)."""
        pc = np.asarray(points, np.float64) @ self.cam_from_world[:3, :3].T + self.cam_from_world[:3, 3]
        z = pc[:, 2]
        zs = np.where(np.abs(z) > 1e-12, z, 1e-12)
        uv = pc[:, :2] / zs[:, None] * [self.K[0, 0], self.K[1, 1]] + [self.K[0, 2], self.K[1, 2]]
        return uv, z

    def pixels(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Integer pixels (x, y) [N,2] of world points, their z-depths [N], and whether each lies in
        front of the camera and inside the image [N] (index images with ``px[inside]`` only)."""
        uv, z = self.project(points)
        with np.errstate(invalid="ignore"):
            px = np.floor(uv).astype(np.int64)
        inside = (z > 0) & (px[:, 0] >= 0) & (px[:, 1] >= 0) & (px[:, 0] < self.width) & (px[:, 1] < self.height)
        return px, z, inside

    def unproject(self, ys: np.ndarray, xs: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """World points [N,3] of the pixel centres (rows ``ys``, columns ``xs``, as ``np.nonzero``
        gives them) at z-depths ``depth`` [N]."""
        z = np.asarray(depth, np.float64)
        x = (np.asarray(xs) + 0.5 - self.K[0, 2]) / self.K[0, 0] * z
        y = (np.asarray(ys) + 0.5 - self.K[1, 2]) / self.K[1, 1] * z
        R, t = self.cam_from_world[:3, :3], self.cam_from_world[:3, 3]
        return (np.stack([x, y, z], axis=1) - t) @ R  # R^T (p - t)

    def scaled(self, width: int, height: int) -> Camera:
        """The same camera for an image resized to ``width`` x ``height`` (pixel-corner convention)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, :] *= sx
        K[1, :] *= sy
        return Camera(self.name, width, height, K, self.cam_from_world.copy(), self.image,
                      self.model, list(self.distortion))

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "image": self.image,
            "width": self.width,
            "height": self.height,
            "model": self.model,
            "K": self.K.tolist(),
            "distortion": list(self.distortion),
            "cam_from_world": self.cam_from_world.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> Camera:
        return cls(
            name=d["name"],
            width=d["width"],
            height=d["height"],
            K=np.array(d["K"]),
            cam_from_world=np.array(d["cam_from_world"]),
            image=d.get("image"),
            model=d.get("model", "PINHOLE"),
            distortion=list(d.get("distortion", [])),
        )


def save_cameras(path: Path, cameras: list[Camera]) -> None:
    data = {"format": CAMERAS_FORMAT, "cameras": [c.to_dict() for c in cameras]}
    Path(path).write_text(json.dumps(data, indent=1))


def load_cameras(path: Path) -> list[Camera]:
    data = json.loads(Path(path).read_text())
    if data.get("format") != CAMERAS_FORMAT:
        raise ValueError(f"{path}: not a {CAMERAS_FORMAT} file")
    return [Camera.from_dict(d) for d in data["cameras"]]
