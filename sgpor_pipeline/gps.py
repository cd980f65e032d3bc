"""Metric scale from the photos' GPS (EXIF): how many metres one SfM unit is.

Phones and most cameras write where each photo was taken (EXIF GPS: latitude, longitude, altitude).
Structure from motion knows the camera centres up to a similarity; their horizontal positions and the
GPS positions (in a local east-north plane) differ by a 2D similarity whose factor is the scale. A
phone's position is off by a few metres, so the scale is only trusted when the cameras moved much
farther than that: a walk along a street (lund: 29 photos over about 180 m) gives it within a few per
cent; a room or a table-top capture, whose camera moves by a few metres, does not, and stays in
arbitrary units unless a scale or a known distance is given (:mod:`sgpor_pipeline.orientation`).

The scale uses the horizontal track alone: a phone's GPS altitude is off by metres. "Up" comes from the
cameras (:func:`sgpor_pipeline.orientation.estimate_up`), and on a walk the altitudes level it along the
track, where the cameras hold it weakly (:func:`level_by_altitude`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .imageio import HEIF_EXTENSIONS
from .orientation import _rotation_to_z
from .scene import Camera

_GPS_IFD = 0x8825
_LAT_REF, _LAT, _LON_REF, _LON, _ALT_REF, _ALT = 1, 2, 3, 4, 5, 6
# WGS84
_A = 6378137.0
_E2 = 6.69437999014e-3


def _degrees(dms: Any) -> float:
    """An EXIF (degrees, minutes, seconds) triple of rationals, or one number, in degrees."""
    if isinstance(dms, (tuple, list)):
        parts = [float(x) for x in dms] + [0.0, 0.0]
        return parts[0] + parts[1] / 60.0 + parts[2] / 3600.0
    return float(dms)


def read_gps(path: str | Path) -> tuple[float, float, float | None] | None:
    """(latitude, longitude in degrees, altitude in metres or None) from a photo's EXIF, or None when
    it has no usable GPS position (no EXIF, no GPS block, a zero or out-of-range position)."""
    from PIL import Image

    try:
        if Path(path).suffix.lower() in HEIF_EXTENSIONS:  # (PIL opens HEIF only with a plugin registered)
            import pillow_heif

            exif = Image.Exif()
            exif.load(pillow_heif.open_heif(path).info.get("exif") or b"")
            gps = exif.get_ifd(_GPS_IFD)
        else:
            with Image.open(path) as im:
                gps = im.getexif().get_ifd(_GPS_IFD)
    except Exception:  # (an unreadable file is reported by the image reader, not here)
        return None
    if not gps or _LAT not in gps or _LON not in gps:
        return None
    try:
        lat, lon = _degrees(gps[_LAT]), _degrees(gps[_LON])
        if str(gps.get(_LAT_REF, "N")).strip().upper().startswith("S"):
            lat = -lat
        if str(gps.get(_LON_REF, "E")).strip().upper().startswith("W"):
            lon = -lon
        alt = float(gps[_ALT]) if _ALT in gps else None
        if alt is not None and gps.get(_ALT_REF) in (1, b"\x01"):
            alt = -alt
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    if not (math.isfinite(lat) and math.isfinite(lon)) or abs(lat) > 90 or abs(lon) > 180 or (lat == 0 and lon == 0):
        return None
    return lat, lon, alt if alt is not None and math.isfinite(alt) else None


def _metres_per_radian(lat0: float) -> tuple[float, float]:
    """(east, north) metres per radian of longitude and of latitude at ``lat0`` on the WGS84 ellipsoid
    (the prime vertical's radius x cos(latitude), the meridian's radius)."""
    phi = math.radians(lat0)
    w = math.sqrt(1.0 - _E2 * math.sin(phi) ** 2)
    return _A / w * math.cos(phi), _A * (1.0 - _E2) / w ** 3


def east_north(lat: np.ndarray, lon: np.ndarray, lat0: float, lon0: float) -> np.ndarray:
    """[N,2] metres east and north of (``lat0``, ``lon0``) on the WGS84 ellipsoid, in the tangent plane
    there (its radii of curvature; within 0.1 % up to a few km away)."""
    east_m, north_m = _metres_per_radian(lat0)
    east = np.radians(np.asarray(lon, np.float64) - lon0) * east_m
    north = np.radians(np.asarray(lat, np.float64) - lat0) * north_m
    return np.stack([east, north], axis=1)


def latitude_longitude(en: np.ndarray, lat0: float, lon0: float) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of :func:`east_north`: (latitudes, longitudes) in degrees of [N,2] metres east and
    north of (``lat0``, ``lon0``)."""
    en = np.asarray(en, np.float64).reshape(-1, 2)
    east_m, north_m = _metres_per_radian(lat0)
    return lat0 + np.degrees(en[:, 1] / north_m), lon0 + np.degrees(en[:, 0] / east_m)


def _horizontal_axes(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit axes spanning the plane normal to ``up``, (e1, e2, up) right-handed as (east, north,
    up): the export frame's x and y before its heading (:func:`~sgpor_pipeline.orientation._rotation_to_z`)."""
    R = _rotation_to_z(up, None)
    return R[0], R[1]


@dataclass
class GpsScale:
    """:func:`gps_scale`'s result: metres per SfM unit and how well the track determined it."""

    scale: float  # metres per SfM unit
    photos: int  # photos used (after the outliers were dropped)
    track_m: float  # the track's extent: the largest distance between two of them, metres
    spread_m: float  # RMS distance of the GPS positions from their mean, metres
    residual_m: float  # RMS distance between the GPS positions and the mapped camera centres, metres
    uncertainty: float  # relative standard error of the scale
    dropped: list[str] = field(default_factory=list)  # photos whose GPS disagreed (outliers)
    # the fitted map, for geo-referencing: SfM point x -> (east + i north) = a ((x.e1) + i (x.e2)) + b
    # metres from (lat0, lon0)
    a: complex = 1.0
    b: complex = 0.0
    e1: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    e2: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    lat0: float = 0.0
    lon0: float = 0.0

    def latitude_longitude(self, point: np.ndarray) -> tuple[float, float]:
        """Where an SfM-frame point lies on the map (degrees; from the horizontal fit, to its accuracy)."""
        p = np.asarray(point, np.float64)
        z = self.a * complex(p @ self.e1, p @ self.e2) + self.b
        lat, lon = latitude_longitude(np.array([[z.real, z.imag]]), self.lat0, self.lon0)
        return float(lat[0]), float(lon[0])

    def azimuth_deg(self, direction: np.ndarray) -> float:
        """The compass bearing (degrees clockwise from north) of an SfM-frame direction's horizontal part."""
        d = np.asarray(direction, np.float64)
        z = self.a * complex(d @ self.e1, d @ self.e2)
        return float(np.degrees(np.arctan2(z.real, z.imag)) % 360.0) % 360.0  # (-1e-15 % 360 is 360.0)

    def north(self) -> np.ndarray:
        """The horizontal SfM-frame direction (unit) that the fit maps onto north."""
        phi = math.pi / 2 - math.atan2(self.a.imag, self.a.real)  # a e^{i phi} points along +i (north)
        return math.cos(phi) * self.e1 + math.sin(phi) * self.e2

    def describe(self) -> str:
        return (f"GPS of {self.photos} photos ({self.track_m:.0f} m track, positions within "
                f"{self.residual_m:.1f} m RMS, scale +-{100 * self.uncertainty:.1f} %)")

    def to_dict(self) -> dict[str, Any]:
        return {"scale": self.scale, "photos": self.photos, "track_m": self.track_m, "spread_m": self.spread_m,
                "residual_m": self.residual_m, "uncertainty": self.uncertainty, "dropped": self.dropped}


@dataclass
class GpsParams:
    min_photos: int = 5
    min_spread_ratio: float = 4.0  # the track's RMS spread must be this many x the positions' RMS error
    max_uncertainty: float = 0.05  # relative standard error of the scale
    outlier_m: float = 3.0  # drop a photo farther than max(this x the median residual, min_outlier_m)
    min_outlier_m: float = 10.0


def _similarity_2d(src: np.ndarray, dst: np.ndarray) -> tuple[complex, complex]:
    """Least-squares ``dst ~ a src + b`` of complex numbers (a 2D rotation and scale, never a
    reflection): (a, b)."""
    ms, md = src.mean(), dst.mean()
    cs, cd = src - ms, dst - md
    a = complex((np.conj(cs) * cd).sum() / max((np.abs(cs) ** 2).sum(), 1e-300))
    return a, complex(md - a * ms)


def gps_scale(cameras: Sequence[Camera], gps: Mapping[str, Sequence[float | None] | None], up: np.ndarray,
              params: GpsParams | None = None) -> tuple[GpsScale | None, str]:
    """Metres per SfM unit from the registered ``cameras``' centres and their photos' ``gps`` (image
    name -> (latitude, longitude, altitude)): the camera centres, projected onto the plane normal to
    ``up``, are mapped onto the GPS positions (east, north) by a least-squares 2D similarity; photos
    whose residual is an outlier are dropped once and the fit repeated. Refused, with the reason, when
    fewer than ``min_photos`` photos have GPS, when the track's spread is not ``min_spread_ratio`` x
    the residual, or when the scale's standard error exceeds ``max_uncertainty``."""
    p = params or GpsParams()
    pairs = [(c, gps[c.image]) for c in cameras if c.image is not None and gps.get(c.image) is not None]
    if len(pairs) < p.min_photos:
        return None, f"{len(pairs)} registered photos carry GPS (at least {p.min_photos} are needed)"
    names = [c.image for c, _ in pairs]
    lat = np.array([g[0] for _, g in pairs], np.float64)
    lon = np.array([g[1] for _, g in pairs], np.float64)
    en = east_north(lat, lon, float(lat.mean()), float(lon.mean()))
    e1, e2 = _horizontal_axes(up)
    centres = np.stack([c.center for c, _ in pairs])
    src = centres @ e1 + 1j * (centres @ e2)
    dst = en[:, 0] + 1j * en[:, 1]
    keep = np.ones(len(src), bool)
    for _ in range(2):
        a, b = _similarity_2d(src[keep], dst[keep])
        res = np.abs(a * src + b - dst)
        limit = max(p.outlier_m * float(np.median(res[keep])), p.min_outlier_m)
        new_keep = res <= limit
        if new_keep.sum() < p.min_photos or (new_keep == keep).all():
            break
        keep = new_keep
    a, b = _similarity_2d(src[keep], dst[keep])
    res = np.abs(a * src[keep] + b - dst[keep])
    n = int(keep.sum())
    residual = float(np.sqrt(np.mean(res ** 2)))
    spread = float(np.sqrt(np.mean(np.abs(dst[keep] - dst[keep].mean()) ** 2)))
    track = float(np.max(np.abs(dst[keep][:, None] - dst[keep][None]))) if n > 1 else 0.0
    # (the scale's standard error: the residual's per-axis spread over the track's spread and sqrt(n))
    uncertainty = residual / max(spread * math.sqrt(2.0 * n), 1e-12)
    scale = abs(a)
    result = GpsScale(scale, n, track, spread, residual, uncertainty, [m for m, k in zip(names, keep) if not k],
                      a, b, e1, e2, float(lat.mean()), float(lon.mean()))
    if not (math.isfinite(scale) and scale > 0):
        return None, "the camera centres do not spread horizontally"
    if spread < p.min_spread_ratio * max(residual, 1.0):
        return None, (f"the photos' GPS positions spread {spread:.1f} m, not far beyond their "
                      f"{max(residual, 1.0):.1f} m error (a walk of tens of metres fixes the scale, a room does not)")
    if uncertainty > p.max_uncertainty:
        return None, (f"the scale from GPS is uncertain by {100 * uncertainty:.0f} % "
                      f"(limit {100 * p.max_uncertainty:.0f} %)")
    return result, ""


def level_by_altitude(cameras: Sequence[Camera], gps: Mapping[str, Sequence[float | None] | None], up: np.ndarray,
                      fitted: GpsScale, roll_deg: float = 2.0, max_deg: float = 10.0, max_residual_m: float = 8.0,
                      min_photos: int = 5) -> tuple[np.ndarray | None, dict[str, Any]]:
    """"Up" from the cameras' horizon (their x axes are horizontal) and the photos' GPS altitudes together.

    On a walk the camera's x axes all point across the street, so the horizon holds "up" firmly across
    it but weakly along it (lund: 5 degrees off along 180 m of street); the GPS altitudes hold it along
    the track (a phone's altitude is off by metres, but over a track of a hundred metres the slope is
    known to about 1 %). Minimises, over unit vectors u near ``up``, sum (x_i . u)^2 / roll^2 +
    sum ((s (c_j - c_mean) . u - (alt_j - alt_mean)) / sigma)^2, sigma the altitudes' RMS residual (at
    least 2 m), s = ``fitted.scale``. Returns (u, info) or (None, info with the reason) when fewer than
    ``min_photos`` photos have an altitude, the altitudes disagree by more than ``max_residual_m`` RMS,
    or u turns more than ``max_deg`` from ``up``."""
    kept = [c for c in cameras if c.image is not None and c.image not in fitted.dropped
            and gps.get(c.image) is not None and len(gps[c.image]) > 2 and gps[c.image][2] is not None]
    if len(kept) < min_photos:
        return None, {"reason": f"{len(kept)} photos carry a GPS altitude (at least {min_photos} are needed)"}
    xs = np.stack([c.cam_from_world[0, :3] for c in cameras if c.image is not None])
    d = fitted.scale * (np.stack([c.center for c in kept]) - np.mean([c.center for c in kept], axis=0))
    alt = np.array([float(gps[c.image][2]) for c in kept])
    alt = alt - alt.mean()
    u = np.asarray(up, np.float64) / np.linalg.norm(up)
    u0 = u.copy()
    roll = math.radians(roll_deg)
    sigma = 2.0
    for _ in range(4):  # Gauss-Newton on the tangent plane, the altitude weight re-estimated
        T = np.stack(_horizontal_axes(u), 1)  # [3,2]: the tangent plane at u
        rows = np.concatenate([xs / roll, d / sigma])  # residual r = rows @ u - target
        target = np.concatenate([np.zeros(len(xs)), alt / sigma])
        q, *_ = np.linalg.lstsq(rows @ T, target - rows @ u, rcond=None)
        u = u + T @ q
        u /= np.linalg.norm(u)
        sigma = max(2.0, float(np.sqrt(np.mean((d @ u - alt) ** 2))))
    residual = float(np.sqrt(np.mean((d @ u - alt) ** 2)))
    turn = float(np.degrees(np.arccos(np.clip(u @ u0, -1.0, 1.0))))
    info = {"photos": len(kept), "altitude_residual_m": residual, "turn_deg": turn}
    if residual > max_residual_m:
        return None, dict(info, reason=f"the GPS altitudes disagree by {residual:.1f} m RMS "
                                       f"(limit {max_residual_m:g})")
    if turn > max_deg:
        return None, dict(info, reason=f"it would turn up by {turn:.1f} degrees (limit {max_deg:g})")
    return u, info
