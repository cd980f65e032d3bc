"""Metric scale from the photos' EXIF GPS: reading it, the local east-north plane, the scale fitted to
the camera centres (and refused where the camera did not move far enough), and its way into ingest and
the export frame."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from PIL import Image

from sgpor_pipeline.dag import RunInputs
from sgpor_pipeline.gps import east_north, gps_scale, latitude_longitude, read_gps
from sgpor_pipeline.orientation import FrameSettings, Similarity, compute_export_frame, estimate_up
from sgpor_pipeline.runner import run_pipeline
from sgpor_pipeline.scene import Camera
from sgpor_pipeline.stages.ingest import IngestStage
from sgpor_pipeline.views import load_views

LAT0, LON0 = 55.698, 13.195


def write_jpeg(path, gps: dict | None, size=(40, 30), seed=0):
    rng = np.random.default_rng(seed)
    img = Image.fromarray(rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8))
    if gps is None:
        img.save(path)
    else:
        exif = Image.Exif()
        exif[0x8825] = gps
        img.save(path, exif=exif)


def dms(value: float) -> tuple[float, float, float]:
    d = int(value)
    m = int((value - d) * 60)
    return float(d), float(m), (value - d - m / 60) * 3600


def test_read_gps_hemispheres_and_missing(tmp_path):
    write_jpeg(tmp_path / "n.jpg", {1: "N", 2: (55.0, 41.0, 53.4), 3: "E", 4: (13.0, 11.0, 43.4), 6: 37.0})
    write_jpeg(tmp_path / "s.jpg", {1: "S", 2: (33.0, 51.0, 36.0), 3: "W", 4: (70.0, 40.0, 12.0), 5: 1, 6: 12.0})
    write_jpeg(tmp_path / "nopos.jpg", {5: 0, 6: 10.0})  # a GPS block without a position
    write_jpeg(tmp_path / "zero.jpg", {1: "N", 2: (0.0, 0.0, 0.0), 3: "E", 4: (0.0, 0.0, 0.0)})
    write_jpeg(tmp_path / "plain.jpg", None)
    Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(tmp_path / "plain.png")
    (tmp_path / "broken.jpg").write_bytes(b"not a jpeg")

    lat, lon, alt = read_gps(tmp_path / "n.jpg")
    assert lat == pytest.approx(55 + 41 / 60 + 53.4 / 3600, abs=1e-9)
    assert lon == pytest.approx(13 + 11 / 60 + 43.4 / 3600, abs=1e-9)
    assert alt == pytest.approx(37.0)
    lat, lon, alt = read_gps(tmp_path / "s.jpg")
    assert lat == pytest.approx(-(33 + 51 / 60 + 36 / 3600)) and lon == pytest.approx(-(70 + 40 / 60 + 12 / 3600))
    assert alt == pytest.approx(-12.0)  # below sea level (altitude ref 1)
    for name in ("nopos.jpg", "zero.jpg", "plain.jpg", "plain.png", "broken.jpg"):
        assert read_gps(tmp_path / name) is None, name


def test_east_north_metres():
    """One arc second north is about 30.9 m everywhere; east it shrinks with the latitude's cosine."""
    en = east_north(np.array([LAT0 + 1 / 3600, LAT0]), np.array([LON0, LON0 + 1 / 3600]), LAT0, LON0)
    assert en[0] == pytest.approx([0.0, 30.92], abs=0.02)
    assert en[1] == pytest.approx([17.45, 0.0], abs=0.02)
    assert en[1, 0] / en[0, 1] == pytest.approx(math.cos(math.radians(LAT0)), rel=0.01)
    lat, lon = latitude_longitude(en, LAT0, LON0)  # its inverse
    assert np.allclose(lat, [LAT0 + 1 / 3600, LAT0], atol=1e-12)
    assert np.allclose(lon, [LON0, LON0 + 1 / 3600], atol=1e-12)


def walk(n: int, length: float, seed: int) -> np.ndarray:
    """[n,3] metric camera centres (x east, y north, z up) on a winding walk of about ``length`` m, 1.6 m
    above the ground."""
    rng = np.random.default_rng(seed)
    heading = np.cumsum(rng.normal(0.0, 0.3, n))
    steps = np.stack([np.cos(heading), np.sin(heading)], 1) * length / n
    xy = np.cumsum(steps, 0)
    return np.c_[xy, np.full(n, 1.6)]


def cameras_at(centres: np.ndarray, sim: Similarity, roll_per_yaw: float = 0.0, yaw_spread: float = 2 * np.pi
               ) -> list[Camera]:
    """Cameras at ``centres`` looking about horizontally (pitched a little; yaw uniform within
    +-``yaw_spread`` / 2 of +x; rolled by ``roll_per_yaw`` x the yaw, as a phone turned with a slight tilt,
    plus 0.5 degrees at random), mapped into an SfM frame by ``sim``."""
    rng = np.random.default_rng(1)
    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    cams = []
    for i, c in enumerate(centres):
        yaw = rng.uniform(-0.5, 0.5) * yaw_spread
        fwd = np.array([np.cos(yaw), np.sin(yaw), rng.normal(0, 0.1)])
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        r = roll_per_yaw * yaw + (np.radians(rng.normal(0.0, 0.5)) if roll_per_yaw else 0.0)  # (about the view)
        right, down = np.cos(r) * right + np.sin(r) * down, -np.sin(r) * right + np.cos(r) * down
        R = np.stack([right, down, fwd])  # world -> camera (OpenCV axes)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, -R @ c
        cams.append(sim.camera(Camera(f"p{i:02d}", 64, 48, K, T, f"p{i:02d}")))
    return cams


def random_similarity(seed: int, scale: float) -> Similarity:
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return Similarity(scale, q, rng.normal(size=3))


def gps_of(names, en, alt=None):
    lat, lon = latitude_longitude(en, LAT0, LON0)
    return {n: [float(a), float(b), alt] for n, a, b in zip(names, lat, lon)}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gps_scale_of_a_walk(seed):
    """A 150 m walk photographed by a phone (3 m GPS noise, one fix 60 m off) in an SfM frame 1/20 of
    metres, turned and moved: the scale comes back within 3 %, the bad fix is dropped."""
    metric = walk(30, 150.0, seed)
    sim = random_similarity(seed, 0.05)
    cams = cameras_at(metric, sim)
    rng = np.random.default_rng(seed + 10)
    heading = rng.uniform(0, 2 * np.pi)  # the walk's x axis is not east
    rot = np.array([[np.cos(heading), -np.sin(heading)], [np.sin(heading), np.cos(heading)]])
    en = metric[:, :2] @ rot.T + rng.normal(0.0, 3.0, (30, 2))
    en[7] += [60.0, 0.0]
    gps = gps_of([c.image for c in cams], en, 35.0)
    up, _ = estimate_up(cams)
    fitted, why = gps_scale(cams, gps, up)
    assert fitted is not None, why
    assert fitted.scale == pytest.approx(1.0 / 0.05, rel=0.03)
    assert fitted.dropped == ["p07"] and fitted.photos == 29
    assert fitted.residual_m < 6.0 and fitted.uncertainty < 0.03 and fitted.track_m > 50
    assert "GPS of 29 photos" in fitted.describe()


def test_gps_scale_refused_where_the_camera_stayed_put():
    """A room-sized capture (3 m across) with the same GPS noise, too few photos with GPS, and photos
    without GPS at all: no scale, and the reason."""
    rng = np.random.default_rng(3)
    a = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    metric = np.c_[1.5 * np.cos(a), 1.5 * np.sin(a), np.full(24, 1.6)]
    cams = cameras_at(metric, random_similarity(3, 0.3))
    up, _ = estimate_up(cams)
    gps = gps_of([c.image for c in cams], metric[:, :2] + rng.normal(0.0, 3.0, (24, 2)))
    fitted, why = gps_scale(cams, gps, up)
    assert fitted is None and "spread" in why and "room" in why
    few = {k: v for k, v in list(gps.items())[:4]}
    fitted, why = gps_scale(cams, few, up)
    assert fitted is None and "4 registered photos carry GPS" in why
    assert gps_scale(cams, {}, up)[0] is None


def test_export_frame_takes_the_gps_scale_unless_one_is_given():
    metric = walk(25, 120.0, 5)
    cams = cameras_at(metric, random_similarity(5, 0.1))
    rng = np.random.default_rng(5)
    gps = gps_of([c.image for c in cams], metric[:, :2] + rng.normal(0.0, 2.0, (25, 2)))

    frame = compute_export_frame(cams, FrameSettings(), gps=gps)
    assert frame.metric and frame.scale_source.startswith("GPS of 25 photos")
    assert frame.transform.s == pytest.approx(10.0, rel=0.03)
    assert frame.gps["used"] and json.loads(json.dumps(frame.to_dict()))["gps"]["photos"] == 25
    # the export frame is metric: the cameras stand 1.6 m above the ground, 120 m of walk is 120 m
    centres = frame.transform.apply(np.stack([c.center for c in cams]))
    assert np.ptp(centres[:, 2]) < 0.05 * 1.6 + 1e-6
    assert np.linalg.norm(np.diff(centres, axis=0), axis=1).sum() == pytest.approx(
        np.linalg.norm(np.diff(metric, axis=0), axis=1).sum(), rel=0.03)

    # on the map: the export origin where the walk's metric frame (x east, y north) puts it, +Y along the
    # first camera's view
    origin_metric = (frame.transform.inverse().apply(np.zeros((1, 3)))[0] - random_similarity(5, 0.1).t)
    origin_metric = random_similarity(5, 0.1).R.T @ origin_metric / 0.1
    lat, lon = latitude_longitude(origin_metric[None, :2], LAT0, LON0)
    assert east_north(np.array([frame.gps["origin_latitude"]]), np.array([frame.gps["origin_longitude"]]),
                      float(lat[0]), float(lon[0]))[0] == pytest.approx([0.0, 0.0], abs=3.0)
    # east-north-up: the walk's east (its metric x) is +X of the export, its north +Y
    assert frame.gps["azimuth_of_y_deg"] == pytest.approx(0.0, abs=1e-6)
    assert frame.gps["azimuth_of_x_deg"] == pytest.approx(90.0, abs=1e-6)
    east, north = (frame.transform.R @ random_similarity(5, 0.1).R @ np.eye(3)[:, k] for k in (0, 1))
    assert east == pytest.approx([1.0, 0.0, 0.0], abs=0.03) and north == pytest.approx([0.0, 1.0, 0.0], abs=0.03)
    # or, with gps_north off, +Y along the first camera's view, its bearing recorded
    camera = compute_export_frame(cams, FrameSettings(gps_north=False), gps=gps)
    first = sorted(cams, key=lambda c: c.name)[0]
    fwd = random_similarity(5, 0.1).R.T @ first.cam_from_world[2, :3]  # metric frame
    assert camera.gps["azimuth_of_y_deg"] == pytest.approx(np.degrees(np.arctan2(fwd[0], fwd[1])) % 360, abs=2.0)
    assert (camera.gps["azimuth_of_x_deg"] - camera.gps["azimuth_of_y_deg"]) % 360 == pytest.approx(90.0, abs=1e-6)
    assert camera.transform.s == frame.transform.s

    given = compute_export_frame(cams, FrameSettings(scale=2.0), gps=gps)  # a given scale wins
    assert given.transform.s == 2.0 and given.gps is None
    off = compute_export_frame(cams, FrameSettings(scale_from_gps=False), gps=gps)
    assert not off.metric and "scale_from_gps is off" in off.describe()
    room = {k: [LAT0, LON0, None] for k in gps}  # every photo at one spot
    refused = compute_export_frame(cams, FrameSettings(), gps=room)
    assert not refused.metric and "GPS was not used" in refused.describe()
    assert refused.to_dict()["gps"]["used"] is False


def test_ingest_records_each_photos_gps(tmp_path):
    images = tmp_path / "images"
    images.mkdir()
    for i in range(4):
        pos = {1: "N", 2: dms(LAT0 + i * 1e-4), 3: "E", 4: dms(LON0), 6: 30.0 + i} if i != 2 else None
        write_jpeg(images / f"v{i}.jpg", pos, seed=i)
    result = run_pipeline(tmp_path / "out", RunInputs(images=images), stages={"ingest": IngestStage})
    views = {v.name: v for v in load_views(result.path("ingest"))}
    assert views["v2"].gps is None
    assert views["v1"].gps[0] == pytest.approx(LAT0 + 1e-4, abs=1e-9)
    assert views["v1"].gps[1] == pytest.approx(LON0, abs=1e-9) and views["v1"].gps[2] == pytest.approx(31.0)


@pytest.mark.parametrize("grade", [0.0, 0.05])
def test_up_levelled_by_the_gps_altitudes(grade):
    """A straight walk whose photos all face up the street (+-5 degrees), the phone rolled a tenth of its
    turn: the camera x axes hold "up" only across the street, and it leans along it (lund: 5 degrees);
    the GPS altitudes (2 m noise) level it to within a degree, on a flat street and on a 5 % grade (up is
    gravity's, not the street's)."""
    n = 30
    along = np.linspace(0.0, 150.0, n)
    metric = np.c_[along, np.zeros(n), 1.6 + grade * along]
    sim = random_similarity(8, 0.05)
    cams = cameras_at(metric, sim, roll_per_yaw=0.1, yaw_spread=np.radians(10.0))
    true_up = sim.R @ np.array([0.0, 0.0, 1.0])
    rng = np.random.default_rng(8)
    en = metric[:, :2] + rng.normal(0.0, 2.0, (n, 2))
    gps = gps_of([c.image for c in cams], en)
    for i, name in enumerate(gps):
        gps[name][2] = float(30.0 + grade * along[i] + rng.normal(0.0, 2.0))

    def angle(u):
        return np.degrees(np.arccos(np.clip(u @ true_up, -1.0, 1.0)))

    horizon, _ = estimate_up(cams)
    assert angle(horizon) > 3.0, angle(horizon)  # the horizon alone leans
    frame = compute_export_frame(cams, FrameSettings(), gps=gps)
    assert angle(frame.up_sfm) < 1.0, angle(frame.up_sfm)
    assert "levelled by the photos' GPS altitudes" in frame.up_method
    assert frame.gps["levelling"]["photos"] == n and frame.gps["levelling"]["altitude_residual_m"] < 4.0
    assert frame.transform.s == pytest.approx(20.0, rel=0.03)
    # an up given by the user is kept; altitudes far apart are not trusted
    given = compute_export_frame(cams, FrameSettings(up="+z"), gps=gps)
    assert np.allclose(given.up_sfm, [0, 0, 1]) and "levelling" not in given.gps
    wild = {k: [v[0], v[1], float(rng.normal(30.0, 40.0))] for k, v in gps.items()}
    frame = compute_export_frame(cams, FrameSettings(), gps=wild)
    assert "levelled" not in frame.up_method and "disagree" in frame.gps["levelling"]["reason"]


def drone_grid(lawnmower: bool, seed: int, sim: Similarity) -> list[Camera]:
    """A drone's survey: 5 x 4 photos 10 m apart at 40 m, the camera straight down (+-2 degrees), the
    image's top along the flight line (turned about on every other line when ``lawnmower``)."""
    rng = np.random.default_rng(seed)
    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    cams = []
    for i in range(20):
        c = np.array([10.0 * (i % 5), 10.0 * (i // 5), 40.0])
        fwd = np.array([*rng.normal(0.0, np.radians(2.0), 2), -1.0])
        fwd /= np.linalg.norm(fwd)
        top = np.array([1.0, 0.0, 0.0]) * (-1.0 if lawnmower and (i // 5) % 2 else 1.0)
        down = -(top - fwd * (top @ fwd))
        down /= np.linalg.norm(down)
        R = np.stack([np.cross(down, fwd), down, fwd])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, -R @ c
        cams.append(sim.camera(Camera(f"d{i:02d}", 64, 48, K, T, f"d{i:02d}")))
    return cams


@pytest.mark.parametrize("lawnmower", [False, True])
def test_a_drones_nadir_survey_is_levelled_by_its_gps(lawnmower):
    """Cameras that all look straight down have no horizon: their image tops are the flight's heading, so
    "up" from the cameras alone came out horizontal (90 degrees off, or at random). The GPS track fits the
    camera centres only on the true horizontal: up is the reverse of the viewing direction, to within
    the cameras' tilt, and the scale and the ground under them follow."""
    alone = []
    for seed in range(3):
        sim = random_similarity(20 + seed, 0.1)
        cams = drone_grid(lawnmower, seed, sim)
        true_up = sim.R @ np.array([0.0, 0.0, 1.0])
        rng = np.random.default_rng(seed)
        metric = np.stack([np.array([10.0 * (i % 5), 10.0 * (i // 5)]) for i in range(20)])
        gps = gps_of([c.image for c in cams], metric + rng.normal(0.0, 1.5, (20, 2)), 140.0)

        def angle(u, true_up=true_up):
            return np.degrees(np.arccos(np.clip(u @ true_up, -1.0, 1.0)))

        ground = sim.apply(np.c_[rng.uniform(-10, 50, (400, 2)), rng.normal(0.0, 0.05, 400)])
        alone.append(angle(compute_export_frame(cams, FrameSettings(), points=ground).up_sfm))  # without GPS
        frame = compute_export_frame(cams, FrameSettings(), gps=gps, points=ground)
        assert angle(frame.up_sfm) < 1.0, (frame.up_method, angle(frame.up_sfm))
        assert "nadir" in frame.up_method or alone[-1] < 30.0
        assert frame.transform.s * sim.s == pytest.approx(1.0, rel=0.03)
        assert frame.origin.startswith("ground plane below the")
        assert np.abs(frame.transform.apply(ground)[:, 2]).max() < 0.5  # metres
        given = compute_export_frame(cams, FrameSettings(up="nadir"), points=ground)  # without GPS, as told
        assert angle(given.up_sfm) < 1.5 and given.origin.startswith("ground plane below the")
    assert max(alone) > 20.0, alone
