"""Exporters: Gaussians (PLY, .splat, glTF KHR_gaussian_splatting, .spz), mesh, USD, renders, report; the
export frame.

Everything runs on generated data (no fit): Gaussians are built directly from a synthetic scene's
true geometry, so the mesh can be compared with the truth.
"""

from __future__ import annotations

import json
import logging
import math
import struct
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote

import numpy as np
import pytest
import torch

from sgpor_pipeline.dag import RunInputs, StageContext
from sgpor_pipeline.exporters.gaussians import SCENE_STAGE
from sgpor_pipeline.gaussians.model import GaussianModel
from sgpor_pipeline.gaussians.ply import read_ply, write_ply
from sgpor_pipeline.imageio import read_rgb8, write_mask01, write_png
from sgpor_pipeline.meshing import MeshData, MeshSettings, activated_tensors, mesh_from_gaussians, render_view
from sgpor_pipeline.orientation import (
    FrameSettings,
    Similarity,
    compute_export_frame,
    estimate_up,
    look_at_center,
    quat_from_matrix,
    quat_to_matrix,
    transform_model,
)
from sgpor_pipeline.scene import Camera, save_cameras
from sgpor_pipeline.splat_io import SH_C0, read_splat, splat_order, write_splat
from sgpor_pipeline.synthetic import SceneParams, generate_scene, look_at
from sgpor_pipeline.views import View, save_views

LOG = logging.getLogger("test_exporters")


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def random_model(n: int, degree: int, seed: int = 0, center=(0.0, 0.0, 0.0), spread: float = 1.0) -> GaussianModel:
    g = torch.Generator().manual_seed(seed)
    m = GaussianModel.empty(n, degree)
    m.params["means"].data = torch.tensor(center, dtype=torch.float32) + spread * torch.randn(n, 3, generator=g)
    m.params["quats"].data = torch.randn(n, 4, generator=g)
    m.params["scales"].data = -3.0 + 0.5 * torch.randn(n, 3, generator=g)
    m.params["opacities"].data = torch.randn(n, generator=g)
    m.params["sh0"].data = torch.randn(n, 1, 3, generator=g)
    m.params["shN"].data = 0.3 * torch.randn(*m.params["shN"].shape, generator=g)
    return m


def surface_gaussians(scene, n: int, seed: int = 0, obj: bool = False) -> GaussianModel:
    """Small flat Gaussians on the true background surface (``obj``: the object's), coloured from
    the ground-truth views (the object: from the views with the object)."""
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh(scene.object_mesh if obj else scene.background_mesh)
    depths, images = (scene.depth, scene.images) if obj else (scene.depth_gt, scene.images_gt)
    mesh.compute_triangle_normals()
    o3d.utility.random.seed(seed)
    pcd = mesh.sample_points_uniformly(number_of_points=n, use_triangle_normal=True)
    pts = np.asarray(pcd.points)
    nrm = np.asarray(pcd.normals)
    area = mesh.get_surface_area()
    spacing = math.sqrt(area / n)
    # rotation whose third column is the normal
    a = np.where(np.abs(nrm[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(nrm, a)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(nrm, t1)
    R = np.stack([t1, t2, nrm], axis=2)
    colors = np.full((n, 3), 0.5)
    todo = np.ones(n, bool)
    for i, cam in enumerate(scene.cameras):  # colour of the first view that sees the point
        idx = np.flatnonzero(todo)
        pc = pts[idx] @ cam.cam_from_world[:3, :3].T + cam.cam_from_world[:3, 3]
        z = pc[:, 2]
        u = cam.K[0, 0] * pc[:, 0] / np.maximum(z, 1e-9) + cam.K[0, 2]
        v = cam.K[1, 1] * pc[:, 1] / np.maximum(z, 1e-9) + cam.K[1, 2]
        ok = (z > 0.05) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        ui, vi = np.clip(u.astype(int), 0, cam.width - 1), np.clip(v.astype(int), 0, cam.height - 1)
        ok &= np.abs(depths[i][vi, ui] - z) < 0.02 * z
        colors[idx[ok]] = images[i][vi[ok], ui[ok]]
        todo[idx[ok]] = False
    m = GaussianModel.empty(n, 0)
    m.params["means"].data = torch.from_numpy(pts).float()
    m.params["quats"].data = torch.from_numpy(quat_from_matrix(R)).float()
    m.params["scales"].data = torch.from_numpy(np.log(np.tile([0.8 * spacing, 0.8 * spacing, 0.05 * spacing],
                                                              (n, 1)))).float()
    m.params["opacities"].data = torch.full((n,), math.log(0.95 / 0.05))
    m.params["sh0"].data = torch.from_numpy((colors - 0.5) / SH_C0).float()[:, None, :]
    return m


def make_run(tmp_path: Path, model: GaussianModel, cameras: list[Camera], images: list[np.ndarray] | None = None,
             masks: list[np.ndarray | None] | None = None, gps: dict[str, list] | None = None) -> StageContext:
    """Fake upstream stage folders (ingest, sfm, fit) and the export stage's context; ``gps``: the
    photos' GPS positions as ingest records them (view name -> [latitude, longitude, altitude])."""
    from sgpor_pipeline.stages.export import ExportParams

    fit, sfm, ingest = tmp_path / "fit", tmp_path / "sfm", tmp_path / "ingest"
    for d in (fit, sfm / "images", ingest / "images", ingest / "masks"):
        d.mkdir(parents=True)
    write_ply(fit / "gaussians.ply", model)
    (fit / "renders").mkdir()
    write_png(fit / "renders" / "heldout.png", np.zeros((20, 30, 3), np.float32))
    (fit / "fit.json").write_text(json.dumps({"iterations": 10, "psnr": 30.5, "loss": [1.0, 0.5, 0.25],
                                              "note": "<b>escaped</b> & fine",
                                              "renders": ["renders/heldout.png", "renders/missing.png"]}))
    write_png(fit / "curve.png", np.linspace(0, 1, 40 * 60 * 3).reshape(40, 60, 3))
    save_cameras(sfm / "cameras.json", cameras)
    views = []
    for i, cam in enumerate([c for c in cameras if c.image is not None]):
        img = images[i] if images is not None else np.full((cam.height, cam.width, 3), 0.3, np.float32)
        write_png(sfm / "images" / f"{cam.image}.png", img)
        write_png(ingest / "images" / f"{cam.image}.png", img)
        mask = masks[i] if masks is not None else None
        if mask is not None:
            write_mask01(ingest / "masks" / f"{cam.image}.png", mask)
        views.append(View(cam.image, f"images/{cam.image}.png", None if mask is None else f"masks/{cam.image}.png",
                          cam.width, cam.height, f"{cam.image}.png", cam.width, cam.height,
                          (gps or {}).get(cam.image)))
    save_views(ingest, views)
    out = tmp_path / "export"
    out.mkdir()
    return StageContext(stage="export", params=ExportParams(), out_dir=out,
                        inputs={"fit": fit, SCENE_STAGE: fit, "sfm": sfm, "ingest": ingest},
                        run_inputs=RunInputs(images=tmp_path),
                        log=LOG, seed_key="test")


def small_cameras(n: int = 4, w: int = 64, h: int = 48, radius: float = 3.0) -> list[Camera]:
    K = np.array([[60.0, 0, w / 2], [0, 60.0, h / 2], [0, 0, 1]])
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = np.array([radius * np.cos(a), radius * np.sin(a), 1.0])
        cams.append(Camera(f"view_{i:02d}", w, h, K, look_at(eye, np.zeros(3)), image=f"view_{i:02d}"))
    return cams


# --------------------------------------------------------------------------------------------------
# Gaussians: PLY and .splat


def test_ply_round_trip_exact_and_open3d_reads_it(tmp_path):
    import open3d as o3d

    m = random_model(300, 3, seed=1)
    path = write_ply(tmp_path / "g.ply", m)
    back = read_ply(path)
    assert back.max_sh_degree == 3
    for name, a in m.numpy().items():
        assert np.array_equal(back.numpy()[name], a), name
    # writing what was read gives the same bytes
    assert write_ply(tmp_path / "g2.ply", back).read_bytes() == path.read_bytes()

    pcd = o3d.t.io.read_point_cloud(str(path))
    p = m.numpy()
    assert {"positions", "f_dc", "f_rest", "opacity", "scale", "rot"} <= set(pcd.point)
    assert np.array_equal(pcd.point.positions.numpy(), p["means"])
    assert np.array_equal(pcd.point["f_dc"].numpy(), p["sh0"][:, 0])
    assert np.array_equal(pcd.point["f_rest"].numpy(), p["shN"])  # Open3D de-interleaves channel-major
    assert np.array_equal(pcd.point["opacity"].numpy()[:, 0], p["opacities"])
    assert np.array_equal(pcd.point["rot"].numpy(), p["quats"])
    assert np.allclose(pcd.point["scale"].numpy(), np.exp(p["scales"]), rtol=1e-6)  # Open3D activates scales


def test_splat_size_order_and_encoding(tmp_path):
    m = random_model(257, 1, seed=2)
    path = write_splat(tmp_path / "s.splat", m)
    assert path.stat().st_size == 32 * len(m)
    s = read_splat(path)
    p = m.numpy()
    order = splat_order(p["scales"], p["opacities"])
    importance = np.exp(p["scales"].astype(np.float64).sum(1)) / (1 + np.exp(-p["opacities"].astype(np.float64)))
    assert np.all(np.diff(importance[order]) <= 0)  # largest first
    assert np.array_equal(s["means"], p["means"][order])
    assert np.allclose(s["scales"], np.exp(p["scales"][order]), rtol=1e-6)
    rgb = np.clip((0.5 + SH_C0 * p["sh0"][order, 0]) * 255, 0, 255).astype(np.uint8)
    assert np.array_equal(s["rgba"][:, :3], rgb)
    alpha = np.clip(255 / (1 + np.exp(-p["opacities"][order])), 0, 255).astype(np.uint8)
    assert np.abs(s["rgba"][:, 3].astype(int) - alpha).max() <= 1
    qn = p["quats"][order] / np.linalg.norm(p["quats"][order], axis=1, keepdims=True)
    assert np.abs(s["quats"] - qn).max() <= 1.0 / 128 + 1e-6  # (w, x, y, z), 8 bits


# --------------------------------------------------------------------------------------------------
# the export frame


@pytest.mark.parametrize("rig", ["inward", "forward"])
def test_up_axis_of_a_rotated_rig(rig):
    scene = generate_scene(SceneParams(seed=4, rig=rig, n_views=12, width=32, height=24, shadows=False))
    rng = np.random.default_rng(7)
    for _ in range(3):
        sim = Similarity(rng.uniform(0.2, 5.0), random_rotation(rng), rng.normal(size=3) * 3)
        cams = [sim.camera(c) for c in scene.cameras]
        true_up = sim.R @ np.array([0.0, 0.0, 1.0])
        up, how = estimate_up(cams)
        angle = np.degrees(np.arccos(np.clip(up @ true_up, -1, 1)))
        assert angle < 0.5, (rig, how, angle)
        # the naive estimate (mean of -y) is biased by the cameras' pitch: the horizon is better
        naive, _ = estimate_up(cams, "cameras")
        assert np.degrees(np.arccos(np.clip(naive @ true_up, -1, 1))) >= angle - 1e-6
        # the whole frame: Z up, metric scale from a known distance, floor at z = 0
        floor_pts = sim.apply(np.c_[rng.uniform(-2, 2, (500, 2)), np.zeros(500)])
        d01 = np.linalg.norm(scene.cameras[0].center - scene.cameras[5].center)
        frame = compute_export_frame(cams, FrameSettings(known_distance=("view_000", "view_005", 2.0 * d01)),
                                     floor_pts, np.ones(500))
        assert frame.metric
        T = frame.transform
        assert np.allclose(T.R @ true_up, [0, 0, 1], atol=1e-2)
        assert np.isclose(T.s * sim.s, 2.0, rtol=1e-9)  # world metres -> SfM -> export
        assert np.abs(T.apply(floor_pts)[:, 2]).max() < 0.05
    frame = compute_export_frame(scene.cameras)
    assert not frame.metric and frame.units == "arbitrary"


def steep_floor_capture(seed: int, pitch_deg: float = 55.0, arc_deg: float = 20.0, roll_deg: float = 6.0):
    """(cameras, points): 16 photos from 1.2 m above a floor (z = 0) looking down ``pitch_deg`` at it from a
    short arc, each rolled by up to ``roll_deg``, and the SfM points such a capture triangulates: the floor
    (60 %, 3 mm noise), clutter standing on it (35 %) and floaters below it (5 %)."""
    rng = np.random.default_rng(seed)
    K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    reach = 1.2 / math.tan(math.radians(pitch_deg))
    cams = []
    for i, a in enumerate(np.radians(np.linspace(-arc_deg / 2, arc_deg / 2, 16))):
        eye = np.array([-reach * math.sin(a), -reach * math.cos(a) - 1.0, 1.2])
        T = look_at(eye, np.array([0.0, -1.0, 0.0]) + rng.normal(0, 0.05, 3) * [1, 1, 0])
        r = math.radians(rng.uniform(-roll_deg, roll_deg))  # about the optical axis
        T[:3, :] = np.array([[math.cos(r), -math.sin(r), 0], [math.sin(r), math.cos(r), 0], [0, 0, 1]]) @ T[:3, :]
        cams.append(Camera(f"view_{i:02d}", 64, 48, K, T, image=f"view_{i:02d}"))
    floor = np.c_[rng.uniform(-1.5, 1.5, (600, 2)) + [0, -0.5], rng.normal(0, 0.003, 600)]
    clutter = rng.uniform([-1, -1.5, 0.02], [1, 0.5, 0.6], (350, 3))
    below = rng.uniform([-1, -1.5, -0.6], [1, 0.5, -0.05], (50, 3))
    return cams, np.concatenate([floor, clutter, below])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ground_plane_levels_a_steep_capture_and_carries_the_floor(seed):
    """Photos looking 55 degrees down at a floor from a 20-degree arc, rolled by up to 6 degrees (the mip-NeRF
    360 room): their x axes barely spread, so the horizon leaves "up" loose along the view (4-8 degrees
    off here; the cameras' mean up leans by the pitch). The ground plane levels it and sits the floor at
    z = 0, floaters under the floor ignored (the percentile origin put the floor above z = 0 by their depth)."""
    rng = np.random.default_rng(100 + seed)
    cams, pts = steep_floor_capture(seed)
    sim = Similarity(rng.uniform(0.2, 5.0), random_rotation(rng), rng.normal(size=3) * 3)
    cams, pts = [sim.camera(c) for c in cams], sim.apply(pts)
    true_up = sim.R @ np.array([0.0, 0.0, 1.0])
    floor = pts[:600]

    frame = compute_export_frame(cams, FrameSettings(), points=pts, means=pts)
    err = np.degrees(np.arccos(np.clip(frame.up_sfm @ true_up, -1, 1)))
    assert err < 1.5, (frame.up_method, err)
    assert "ground plane" in frame.up_method and frame.origin == "ground plane below the look-at point"
    z = frame.transform.apply(floor)[:, 2] / frame.transform.s / sim.s  # metres of the capture
    assert np.abs(np.median(z)) < 0.02 and np.percentile(np.abs(z), 95) < 0.05  # (a tilt of err degrees)
    assert frame.ground["fraction"] == pytest.approx(0.6, abs=0.1)
    assert frame.ground["camera_height"] / frame.transform.s / sim.s == pytest.approx(1.2, rel=0.03)

    old = compute_export_frame(cams, FrameSettings(ground_plane=False), means=pts)  # the estimate before
    assert np.degrees(np.arccos(np.clip(old.up_sfm @ true_up, -1, 1))) > max(3.0 * err, 3.0)
    assert np.median(old.transform.apply(floor)[:, 2]) / old.transform.s / sim.s > 0.1  # floating


def test_ground_plane_is_not_a_wall_nor_a_scene_without_one():
    """An inward ring at eye level facing a wall that holds most points: the wall is not level with the
    cameras' horizon, so the floor is found. Points in a ball: no ground plane, and the origin falls back
    to the opaque Gaussians' low percentile, with the reason recorded."""
    rng = np.random.default_rng(3)
    cams = small_cameras(12, radius=3.0)
    floor = np.c_[rng.uniform(-2, 2, (200, 2)), np.zeros(200)]
    wall = np.c_[rng.uniform(-2, 2, 500), np.full(500, 1.5), rng.uniform(0, 2, 500)]
    frame = compute_export_frame(cams, FrameSettings(), points=np.concatenate([floor, wall]))
    assert np.degrees(np.arccos(np.clip(frame.up_sfm @ [0, 0, 1], -1, 1))) < 1.0
    assert np.abs(frame.transform.apply(floor)[:, 2]).max() < 1e-6 * frame.transform.s + 0.01
    assert frame.ground["fraction"] == pytest.approx(200 / 700, abs=0.02)

    ball = rng.normal(size=(500, 3)) * 0.5
    frame = compute_export_frame(cams, FrameSettings(), points=ball, means=ball)
    assert frame.origin == "floor below the look-at point" and "level plane" in frame.ground["reason"]
    assert "(no ground plane: no level plane below the cameras" in frame.describe()
    assert np.percentile(frame.transform.apply(ball)[:, 2], 1.0) == pytest.approx(0.0, abs=1e-9)
    off = compute_export_frame(cams, FrameSettings(ground_plane=False), points=ball, means=ball)
    assert off.ground is None and np.allclose(off.transform.matrix, frame.transform.matrix)
    # hard cases: non-finite points are left out; a line of points, or one camera, finds no plane
    bad = ball.copy()
    bad[::7] = np.nan
    bad[::11, 1] = np.inf
    frame = compute_export_frame(cams, FrameSettings(), points=bad, means=bad)
    assert np.isfinite(frame.transform.matrix).all() and frame.origin == "floor below the look-at point"
    line = np.c_[np.linspace(-1, 1, 100), np.zeros((100, 2))]
    assert compute_export_frame(cams, FrameSettings(), points=line).ground["reason"]
    assert "too few" in compute_export_frame(cams[:1], FrameSettings(), points=floor).ground["reason"]


def test_origin_in_front_of_a_forward_capture_whose_axes_diverge():
    """Photos from a 2 m line, 1.5 m above the ground, all facing a scene 10 m ahead, their axes turned a
    little outwards (as a person stepping sideways does): the axes meet behind the cameras, so the origin
    goes under the middle of the scene they see, in front of them, not behind."""
    K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    cams = []
    for i, x in enumerate(np.linspace(-1.0, 1.0, 9)):
        eye = np.array([x, 0.0, 1.5])
        cams.append(Camera(f"view_{i:02d}", 64, 48, K, look_at(eye, eye + [0.05 * x, 1.0, -0.1]),
                           image=f"view_{i:02d}"))
    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(-6, 6, 300), rng.uniform(2, 14, 300), np.zeros(300)]
    scene = np.c_[rng.uniform(-4, 4, 200), rng.uniform(9, 11, 200), rng.uniform(0, 3, 200)]
    pts = np.concatenate([ground, scene])
    # their axes meet behind them: the look-at point falls back to twice their spread ahead
    assert 0 < np.median([c.cam_from_world[2, :3] @ (look_at_center(cams) - c.center) for c in cams]) < 2.5
    frame = compute_export_frame(cams, FrameSettings(), points=pts)
    assert frame.origin == "ground plane below the middle of the scene"
    origin = frame.transform.inverse().apply(np.zeros((1, 3)))[0]
    assert 6.0 < origin[1] < 11.0 and abs(origin[2]) < 0.02


def test_the_scene_radius_of_a_forward_capture_comes_from_its_points():
    """The mesh's voxel and depth range follow the scene radius. Photos from a 2 m line facing a scene
    ahead: where their axes diverge a little they meet behind the cameras, and where they are parallel
    they meet nowhere; either way the look-at point is a guess 2 m ahead (twice the line's spread), so a
    scene 10 or 100 m ahead got a radius of about 2 m from it (the statue's look-at point lay behind its
    cameras, and its mesh lost everything beyond 8 radii, 45 units, where its hedge and house stand
    50-300 away). The points put the middle of the scene among them; an inward ring keeps its look-at
    point."""
    from sgpor_pipeline.orientation import scene_center, scene_center_radius

    K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    rng = np.random.default_rng(0)
    box = np.c_[rng.uniform(-4, 4, 300), rng.uniform(-1, 1, 300), rng.uniform(0, 3, 300)]
    for turn, ahead in ((0.05, 10.0), (0.02, 10.0), (0.0, 100.0)):
        cams = []
        for i, x in enumerate(np.linspace(-1.0, 1.0, 9)):
            eye = np.array([x, 0.0, 1.5])
            cams.append(Camera(f"view_{i:02d}", 64, 48, K, look_at(eye, eye + [turn * x, 1.0, 0.0]),
                               image=f"view_{i:02d}"))
        scene = box + [0.0, ahead, 0.0]
        axes_centre, r_axes = scene_center_radius(cams)
        assert 0.0 < axes_centre[1] < 2.5 and r_axes < 2.5  # in front of the cameras, but not at the scene
        centre, how = scene_center(cams, scene)
        _, r = scene_center_radius(cams, scene)
        assert how == "middle of the scene" and ahead - 1 < centre[1] < ahead + 1
        assert 0.85 * ahead < r < 1.15 * ahead
    ring = small_cameras(8)
    ball = np.random.default_rng(1).normal(0.0, 0.3, (500, 3))
    centre, how = scene_center(ring, ball)
    assert how == "look-at point" and np.allclose(centre, scene_center(ring)[0])
    assert scene_center_radius(ring, ball)[1] == scene_center_radius(ring)[1]
    # too few points, or none in front of the cameras: the look-at point
    assert scene_center(cams, scene[:5])[1] == "look-at point"
    assert scene_center(cams, scene * [1.0, -1.0, 1.0])[1] == "look-at point"


def test_exporters_take_the_ground_from_the_sfm_points(tmp_path):
    """The SfM points (sfm/points.npz) give the ground plane, recorded in export_frame.json; the Gaussians
    (a blob off the floor here) are only the fallback."""
    from sgpor_pipeline.exporters.gaussians import PlyExporter

    cams = small_cameras(8)
    ctx = make_run(tmp_path, random_model(200, 0, seed=3, center=(0.0, 0.0, 0.5), spread=0.3), cams)
    rng = np.random.default_rng(0)
    floor = np.c_[rng.uniform(-2, 2, (300, 2)), np.full(300, -0.25)]
    np.savez(tmp_path / "sfm" / "points.npz", xyz=floor, rgb=np.zeros((300, 3), np.uint8))
    PlyExporter().export(ctx, ctx.out_dir)
    frame = json.loads((ctx.out_dir / "export_frame.json").read_text())
    assert frame["origin"] == "ground plane below the look-at point"
    assert frame["ground"]["source"] == "SfM points" and frame["ground"]["fraction"] == 1.0
    assert frame["ground"]["camera_height"] == pytest.approx(1.25)
    assert frame["export_from_sfm"]["translation"][2] == pytest.approx(0.25)  # the floor at z = 0
    # the next exporter reads the frame back (the points are gone: found again, it would differ)
    from sgpor_pipeline.exporters.gaussians import export_frame
    from sgpor_pipeline.orientation import ExportFrame

    (tmp_path / "sfm" / "points.npz").unlink()
    again = export_frame(ctx, read_ply(tmp_path / "fit" / "gaussians.ply"), cams, ctx.out_dir)
    assert again.to_dict() == frame and np.array_equal(again.transform.matrix,
                                                       ExportFrame.from_dict(frame).transform.matrix)
    fresh = export_frame(ctx, read_ply(tmp_path / "fit" / "gaussians.ply"), cams)  # (no folder: found anew)
    assert fresh.ground["source"] == "opaque Gaussians" and not np.allclose(fresh.transform.t, again.transform.t)


def test_export_is_metric_from_the_photos_gps(tmp_path):
    """Photos whose GPS positions are their camera centres x 20 m (a 120 m wide ring): the exported scene
    is in metres, export_frame.json says where the scale came from, and scale_from_gps=false keeps the
    SfM unit."""
    from dataclasses import replace

    from sgpor_pipeline.exporters.gaussians import PlyExporter
    from sgpor_pipeline.gps import latitude_longitude

    cams = small_cameras(8)
    lat0, lon0 = 48.0, 11.0
    lat, lon = latitude_longitude(20.0 * np.stack([c.center[:2] for c in cams]), lat0, lon0)
    gps = {c.image: [float(a), float(b), None] for c, a, b in zip(cams, lat, lon)}
    m = random_model(100, 0, seed=2, spread=0.5)
    ctx = make_run(tmp_path, m, cams, gps=gps)
    PlyExporter().export(ctx, ctx.out_dir)
    frame = json.loads((ctx.out_dir / "export_frame.json").read_text())
    assert frame["units"] == "metres" and frame["scale_source"].startswith("GPS of 8 photos")
    assert frame["export_from_sfm"]["scale"] == pytest.approx(20.0, rel=1e-3) and frame["gps"]["used"]
    assert np.allclose(np.exp(read_ply(ctx.out_dir / "scene.ply").numpy()["scales"]),
                       20.0 * np.exp(m.numpy()["scales"]), rtol=1e-3)
    # the USD says so, and where on the map its origin lies (the cameras look at the ring's centre)
    from pxr import Usd

    from sgpor_pipeline.exporters.mesh import write_mesh
    from sgpor_pipeline.exporters.usd import UsdExporter

    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    write_mesh(MeshData(v, np.array([[0, 1, 2], [0, 2, 3]]), np.full((4, 3), 0.5, np.float32)), ctx.out_dir,
               "mesh", formats=("ply",))
    UsdExporter().export(ctx, ctx.out_dir)
    stage = Usd.Stage.Open(str(ctx.out_dir / "scene.usda"))
    data = stage.GetRootLayer().customLayerData
    assert data["sgpor:units"] == "metres" and data["sgpor:scaleSource"].startswith("GPS")
    assert data["sgpor:originLatitude"] == pytest.approx(lat0, abs=2e-5)  # (2 m)
    assert data["sgpor:originLongitude"] == pytest.approx(lon0, abs=3e-5)
    assert 0.0 <= data["sgpor:azimuthOfY"] < 360.0

    (ctx.out_dir / "export_frame.json").unlink()
    off = replace(ctx, params=replace(ctx.params, scale_from_gps=False))
    PlyExporter().export(off, off.out_dir)
    frame = json.loads((off.out_dir / "export_frame.json").read_text())
    assert frame["units"] == "arbitrary" and frame["gps"]["reason"] == "export.scale_from_gps is off"


def test_frame_transform_keeps_the_images():
    """Rendering the transformed Gaussians with the transformed cameras gives the same images (checks
    means, orientations, log-scales and the SH rotation together)."""
    m = random_model(400, 3, seed=3, spread=0.6)
    m.params["scales"].data += 0.8
    cams = small_cameras(3, 64, 48)
    rng = np.random.default_rng(1)
    sim = Similarity(2.5, random_rotation(rng), rng.normal(size=3))
    m2 = transform_model(m, sim)
    g, g2 = activated_tensors(m), activated_tensors(m2)
    for cam in cams:
        a = render_view(g, cam)
        b = render_view(g2, sim.camera(cam))
        assert np.abs(a["rgb"] - b["rgb"]).max() < 2e-3
        assert np.allclose(b["depth"], sim.s * a["depth"], rtol=1e-3, atol=1e-3)
    assert np.allclose(np.exp(m2.numpy()["scales"]), sim.s * np.exp(m.numpy()["scales"]), rtol=1e-5)
    assert np.allclose(quat_to_matrix(m2.numpy()["quats"]), sim.R @ quat_to_matrix(m.numpy()["quats"]), atol=1e-5)


# --------------------------------------------------------------------------------------------------
# mesh


@pytest.fixture(scope="module")
def room():
    scene = generate_scene(SceneParams(seed=1, n_views=12, width=128, height=96))
    return scene, surface_gaussians(scene, 80_000, seed=0)


def test_mesh_of_true_geometry_gaussians_is_close_to_the_truth(room):
    """Chamfer distance of the fused mesh to the true background surface.

    Bounds: mean symmetric Chamfer distance (accuracy: mesh samples to the true mesh; completeness:
    the visible true surface, back-projected true depth, to the mesh) under half a voxel; accuracy
    under a quarter voxel; no mesh beyond the TSDF truncation band (4 voxels) from the truth.
    Why: marching cubes on a TSDF puts a plane within half a voxel (linear interpolation of the signed
    distance), and fusing the generator's TRUE depth maps with the same TSDF measures 0.28 cm
    accuracy / 0.70 cm completeness (~0.14 voxel) here: that is the floor. The planar depth of flat
    Gaussians is exact on a plane, so only creases, grazing views (depth dropped by the
    discontinuity test) and decimation add to it. Measured: ~0.28 voxel (accuracy 0.4 cm,
    completeness 1.6 cm, voxel 3.6 cm = 1/64 of the scene radius). The expected depth ("ED") instead
    gives ~0.8 voxel: it is biased towards the camera by ~5 cm where the Gaussians overlap. The
    accuracy tail (~1 % of the area, up to ~1.6 voxel) is the TSDF's skirt behind the floor/wall
    creases; a floater would lie beyond the truncation band.
    """
    import open3d as o3d

    scene, model = room
    settings = MeshSettings(voxel_rel=1 / 64, target_faces=60_000)
    mesh = mesh_from_gaussians(model, scene.cameras, settings)
    assert 1000 < len(mesh.faces) <= 60_000
    assert mesh.colors.shape == mesh.vertices.shape and mesh.colors.std() > 0.02
    from sgpor_pipeline.orientation import scene_center_radius

    voxel = settings.voxel_rel * scene_center_radius(scene.cameras)[1]

    truth = o3d.t.geometry.RaycastingScene()
    truth.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(scene.background_mesh))
    rec_legacy = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                           o3d.utility.Vector3iVector(mesh.faces.astype(np.int32)))
    rec = o3d.t.geometry.RaycastingScene()
    rec.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(rec_legacy))
    samples = np.asarray(rec_legacy.sample_points_uniformly(20_000).points, np.float32)
    acc = truth.compute_distance(o3d.core.Tensor(samples)).numpy()
    # completeness against the visible true surface: back-projected true depth
    pts = []
    for i, cam in enumerate(scene.cameras):
        v, u = np.mgrid[0:cam.height:4, 0:cam.width:4]
        z = scene.depth_gt[i][v, u]
        xy = np.stack([(u + 0.5 - cam.K[0, 2]) / cam.K[0, 0] * z, (v + 0.5 - cam.K[1, 2]) / cam.K[1, 1] * z, z], -1)
        pts.append((xy.reshape(-1, 3) - cam.cam_from_world[:3, 3]) @ cam.cam_from_world[:3, :3])
    comp = rec.compute_distance(o3d.core.Tensor(np.concatenate(pts).astype(np.float32))).numpy()
    chamfer = 0.5 * (acc.mean() + comp.mean())
    print(f"voxel {voxel:.4f}, accuracy {acc.mean():.4f}, completeness {comp.mean():.4f}, chamfer {chamfer:.4f} "
          f"({chamfer / voxel:.2f} voxel), faces {len(mesh.faces)}")
    assert chamfer < 0.5 * voxel
    # no floaters: TSDF artefacts (skirts behind concave creases) stay within the truncation band
    assert acc.mean() < 0.25 * voxel and np.percentile(acc, 99.9) < settings.trunc_voxels * voxel


def test_interpolated_cameras_lie_between_neighbours():
    from sgpor_pipeline.meshing import interpolate_cameras
    from sgpor_pipeline.orientation import quat_from_matrix

    cams = small_cameras(4)
    extra = interpolate_cameras(cams, 1)
    # one view per (camera, nearest neighbour) pair, each pair once
    assert 2 <= len(extra) <= 4 and len({c.name for c in extra}) == len(extra)
    assert all(c.image is None for c in extra)
    a, b = cams[0], cams[1]
    mid = next(c for c in extra if c.name == "interp_view_00_view_01_0")
    assert np.allclose(mid.center, 0.5 * (a.center + b.center))
    qa, qb, qm = (quat_from_matrix(c.cam_from_world[:3, :3]) for c in (a, b, mid))
    assert np.isclose(abs(qa @ qm), abs(qb @ qm))  # halfway in rotation too


# --------------------------------------------------------------------------------------------------
# USD


def _usd_run(tmp_path, degree=3):
    cams = small_cameras(4)
    cams.append(Camera("novel path 1", 64, 48, cams[0].K, look_at(np.array([0.0, -3.0, 2.0]), np.zeros(3))))
    m = random_model(300, degree, seed=5, spread=0.5)
    ctx = make_run(tmp_path, m, cams)
    # a small mesh stands in for the mesh exporter's result (the USD exporter reuses mesh.ply)
    from sgpor_pipeline.exporters.mesh import write_mesh

    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1]], float)
    f = np.array([[0, 1, 2], [0, 2, 3], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    write_mesh(MeshData(v, f, np.random.default_rng(0).uniform(size=(5, 3)).astype(np.float32)), ctx.out_dir,
               "mesh", formats=("ply",))
    return ctx, m, cams


def test_usd_mesh_colours_are_linear():
    """USD takes colour values as linear Rec.709: the mesh's sRGB vertex colours are decoded."""
    from pxr import Usd, UsdGeom

    from sgpor_pipeline.exporters.usd import add_mesh
    from sgpor_pipeline.imageio import srgb_to_linear

    c = np.array([[0.0, 0.5, 1.0], [0.2, 0.04, 0.9], [0.7, 0.7, 0.7]], np.float32)
    stage = Usd.Stage.CreateInMemory()
    m = add_mesh(stage, "/Mesh", MeshData(np.eye(3), np.array([[0, 1, 2]]), c))
    stored = np.asarray(UsdGeom.Mesh(m).GetDisplayColorPrimvar().Get())
    assert np.allclose(stored, srgb_to_linear(c), atol=1e-6) and stored[0, 1] < 0.22


def test_usd_stage_valid_and_matching_the_gaussians(tmp_path):
    from pxr import Gf, Usd, UsdGeom, UsdPhysics, UsdVol

    from sgpor_pipeline.exporters.gaussians import export_frame
    from sgpor_pipeline.exporters.usd import UsdExporter, validate_stage

    ctx, m, cams = _usd_run(tmp_path)
    UsdExporter().export(ctx, ctx.out_dir)
    for ext in ("usda", "usdc", "usdz"):
        assert (ctx.out_dir / f"scene.{ext}").is_file()
    # the package: one uncompressed, 64-byte aligned entry (USDZ), no time of writing in it, so a second
    # export of the same scene is the same bytes
    import zipfile

    first = (ctx.out_dir / "scene.usdz").read_bytes()
    with zipfile.ZipFile(ctx.out_dir / "scene.usdz") as z:
        assert z.testzip() is None
        for info in z.infolist():
            assert info.date_time == (1980, 1, 1, 0, 0, 0) and info.compress_type == zipfile.ZIP_STORED
            name_len, extra_len = struct.unpack_from("<HH", first, info.header_offset + 26)
            assert (info.header_offset + 30 + name_len + extra_len) % 64 == 0
    (ctx.out_dir / "export_frame.json").unlink()
    UsdExporter().export(ctx, ctx.out_dir)
    assert (ctx.out_dir / "scene.usdz").read_bytes() == first
    frame = export_frame(ctx, m, cams)
    mx = transform_model(m, frame.transform).numpy()

    for ext in ("usda", "usdz"):
        stage = Usd.Stage.Open(str(ctx.out_dir / f"scene.{ext}"))
        assert stage is not None
        errors = validate_stage(stage)
        assert errors == [], errors
        assert stage.GetDefaultPrim().GetPath() == "/World"
        assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
        assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
        assert UsdPhysics.GetStageKilogramsPerUnit(stage) == 1.0
        assert stage.GetRootLayer().customLayerData["sgpor:units"] == "arbitrary"
        assert stage.GetPrimAtPath("/World/PhysicsScene").IsA(UsdPhysics.Scene)

        g = UsdVol.ParticleField3DGaussianSplat(stage.GetPrimAtPath("/World/Gaussians"))
        pos = np.asarray(g.GetPositionsAttr().Get())
        assert pos.shape == (300, 3) and np.allclose(pos, mx["means"])
        assert np.allclose(np.asarray(g.GetScalesAttr().Get()), np.exp(mx["scales"]), rtol=1e-6)
        op = np.asarray(g.GetOpacitiesAttr().Get())
        assert np.all((op >= 0) & (op <= 1)) and np.allclose(op, 1 / (1 + np.exp(-mx["opacities"])), atol=1e-6)
        quats = g.GetOrientationsAttr().Get()
        qn = mx["quats"] / np.linalg.norm(mx["quats"], axis=1, keepdims=True)
        real = np.array([q.GetReal() for q in quats])
        imag = np.array([list(q.GetImaginary()) for q in quats])
        assert np.allclose(real, qn[:, 0], atol=1e-6) and np.allclose(imag, qn[:, 1:], atol=1e-6)
        assert g.GetRadianceSphericalHarmonicsDegreeAttr().Get() == 3
        sh_attr = g.GetRadianceSphericalHarmonicsCoefficientsAttr()
        assert sh_attr.GetMetadata("elementSize") == 16
        sh = np.asarray(sh_attr.Get()).reshape(300, 16, 3)
        assert np.allclose(sh[:, 0], mx["sh0"][:, 0]) and np.allclose(sh[:, 1:], mx["shN"])
        ext = np.asarray(g.GetExtentAttr().Get())
        assert np.all(ext[0] <= pos.min(0)) and np.all(ext[1] >= pos.max(0))
        # no colour space declared: USD's default (linear Rec.709) for the mesh's displayColor, and the
        # splats' radiance as the schema's renderers read 3DGS data (display-referred sRGB)
        assert not any(p.HasAPI(Usd.ColorSpaceAPI) for p in stage.Traverse())

        mesh = stage.GetPrimAtPath("/World/Mesh")
        assert mesh.IsA(UsdGeom.Mesh) and mesh.GetParent().GetPath() == "/World"
        assert mesh.HasAPI(UsdPhysics.CollisionAPI) and mesh.HasAPI(UsdPhysics.MeshCollisionAPI)
        assert UsdPhysics.MeshCollisionAPI(mesh).GetApproximationAttr().Get() == UsdPhysics.Tokens.none
        assert len(UsdGeom.Mesh(mesh).GetDisplayColorPrimvar().Get()) == 5

        # cameras: a world point projects to the same pixel through the USD camera and OpenCV
        cam_prims = [p for p in stage.Traverse() if p.IsA(UsdGeom.Camera)]
        assert len(cam_prims) == len(cams)
        for prim in cam_prims:
            name = prim.GetCustomDataByKey("sgpor:name")
            cv = frame.transform.camera(next(c for c in cams if c.name == name))
            gcam = UsdGeom.Camera(prim).GetCamera(Usd.TimeCode.Default())
            view = gcam.frustum.ComputeViewMatrix()
            proj = gcam.frustum.ComputeProjectionMatrix()
            for X in mx["means"][:5].astype(np.float64):
                pc = cv.cam_from_world[:3, :3] @ X + cv.cam_from_world[:3, 3]
                if pc[2] <= 0.1:
                    continue
                u_cv = cv.K[0, 0] * pc[0] / pc[2] + cv.K[0, 2]
                v_cv = cv.K[1, 1] * pc[1] / pc[2] + cv.K[1, 2]
                ndc = (view * proj).Transform(Gf.Vec3d(*X))
                u_usd = (ndc[0] + 1) / 2 * cv.width
                v_usd = (1 - ndc[1]) / 2 * cv.height
                assert abs(u_usd - u_cv) < 1e-3 and abs(v_usd - v_cv) < 1e-3


# --------------------------------------------------------------------------------------------------
# ply / splat / renders / report exporters on a fake run


class _Links(HTMLParser):
    def __init__(self):
        super().__init__()
        self.refs: list[str] = []

    def handle_starttag(self, tag, attrs):
        for k, v in attrs:
            if k in ("src", "href") and v and not v.startswith("#"):
                self.refs.append(v)


def test_ply_splat_renders_and_report_exporters(tmp_path):
    from sgpor_pipeline.camera_io import read_transforms_json
    from sgpor_pipeline.exporters.cameras import CamerasExporter
    from sgpor_pipeline.exporters.gaussians import PlyExporter, SplatExporter
    from sgpor_pipeline.exporters.renders import RendersExporter
    from sgpor_pipeline.exporters.report import ReportExporter

    cams = small_cameras(3)
    cams[1].name = cams[1].image = 'odd "name" <&>'
    cams.append(Camera("novel_a", 64, 48, cams[0].K, look_at(np.array([0.0, -3.0, 2.0]), np.zeros(3))))
    m = random_model(200, 1, seed=6, spread=0.5)
    masks = [np.zeros((48, 64), bool) for _ in range(3)]
    masks[0][10:30, 20:40] = True
    ctx = make_run(tmp_path, m, cams, masks=[masks[0], None, masks[2]])
    out = ctx.out_dir
    for exporter in (PlyExporter(), RendersExporter(), SplatExporter(), CamerasExporter(), ReportExporter()):
        exporter.export(ctx, out)

    frame = json.loads((out / "export_frame.json").read_text())
    assert frame["units"] == "arbitrary" and frame["up_axis"] == "Z"
    back = read_ply(out / "scene.ply")
    from sgpor_pipeline.exporters.gaussians import export_frame

    expected = transform_model(m, export_frame(ctx, m, cams).transform)
    for k, v in expected.numpy().items():
        assert np.array_equal(back.numpy()[k], v), k
    assert (out / "scene.splat").stat().st_size == 32 * len(m)

    for cam in cams[:3]:
        assert (out / "renders" / f"{cam.image}.png").is_file()
    assert (out / "renders" / "novel" / "novel_a.png").is_file()
    # transforms.json is a dataset as it stands: every frame's image is the render at its camera
    frames = json.loads((out / "cameras" / "transforms.json").read_text())["frames"]
    assert [f["sgpor_name"] for f in frames] == [c.name for c in cams]
    for fr, cam in zip(frames, cams):
        image = out / "cameras" / fr["file_path"]
        assert image.is_file() and image.resolve().is_relative_to((out / "renders").resolve()), fr["file_path"]
        assert read_rgb8(image).shape == (cam.height, cam.width, 3)
    back = read_transforms_json(out / "cameras" / "transforms.json")
    assert [c.name for c in back] == [c.name for c in cams]

    page = (out / "report.html").read_text()
    assert '<&>' not in page and "&lt;&amp;&gt;" in page and "<b>escaped</b>" not in page
    frame = json.loads((out / "export_frame.json").read_text())
    assert ("<th>ground</th><td>a plane through" in page) == ("fraction" in frame["ground"])  # or why not
    assert "http:" not in page and "https:" not in page and "<script" not in page
    links = _Links()
    links.feed(page)
    assert len(links.refs) >= 3 * 3  # input, mask, render per view (+ curve)
    for ref in links.refs:
        path = out / unquote(ref)
        # (the Files section links the folders the exporters wrote, as "name/")
        assert (path.is_file() or ref.endswith("/") and path.is_dir()) and path.resolve().is_relative_to(
            out.resolve()), ref
    assert any("curve" in r for r in links.refs)
    # the export's files, with what wrote them (the report ran after the other exporters here)
    files = page[page.index("<table class='files'>"):]
    files = files[:files.index("</table>")]
    for name in ("scene.ply", "scene.splat", "export_frame.json", "renders/", "cameras/"):
        assert f">{name}</a>" in files, name
    assert "report.html</a>" not in files and "Niantic" not in files  # (spz did not run)


def test_the_report_runs_after_the_other_exporters():
    from sgpor_pipeline.stages.export import ExportParams, selected_exporters

    for formats in (["all"], ["report", "ply", "usd"]):
        names = list(selected_exporters(ExportParams(formats=formats)))
        assert names[-1] == "report" and names[:-1] == sorted(names[:-1]), names


def test_mesh_files_glb_is_y_up_with_colours(tmp_path):
    import trimesh

    from sgpor_pipeline.exporters.mesh import GLTF_FROM_ZUP, read_mesh_ply, write_mesh

    rng = np.random.default_rng(0)
    v = rng.uniform(size=(6, 3))
    f = np.array([[0, 1, 2], [1, 2, 3], [3, 4, 5]])
    c = rng.uniform(size=(6, 3)).astype(np.float32)
    files = write_mesh(MeshData(v, f, c), tmp_path, "mesh")
    assert [p.name for p in files] == ["mesh.glb", "mesh.obj", "mesh.ply"]
    glb = trimesh.load(tmp_path / "mesh.glb", force="mesh", process=False)
    assert np.allclose(glb.vertices, v @ GLTF_FROM_ZUP.T, atol=1e-6)  # Z up -> Y up
    assert np.allclose(GLTF_FROM_ZUP @ [0, 0, 1], [0, 1, 0])
    from sgpor_pipeline.imageio import srgb_to_linear

    # glTF's vertex colours are linear; OBJ's (and PLY's) are the photos' sRGB values
    for mesh, want in ((glb, srgb_to_linear(c)), (trimesh.load(tmp_path / "mesh.obj", force="mesh", process=False), c)):
        assert mesh.visual.kind == "vertex"
        assert np.abs(mesh.visual.vertex_colors[:, :3] / 255.0 - want[:len(mesh.vertices)]).max() < 1 / 255 + 1e-6
    assert np.allclose(srgb_to_linear(np.array([0.0, 0.04045, 0.5, 1.0])), [0.0, 0.04045 / 12.92, 0.21404114, 1.0])
    back = read_mesh_ply(tmp_path / "mesh.ply")
    assert np.allclose(back.vertices, v) and np.array_equal(back.faces, f)
    assert np.abs(back.colors - c).max() < 1 / 255 + 1e-6


def _glb_chunks(path) -> tuple[dict, bytes]:
    """A GLB's JSON document and binary chunk, read without trimesh (which may recompute normals on
    load); checks the header's total length and the JSON chunk's type and 4-byte alignment."""
    import json
    import struct

    data = path.read_bytes()
    assert struct.unpack_from("<I", data, 8)[0] == len(data)
    json_len = struct.unpack_from("<I", data, 12)[0]
    assert json_len % 4 == 0 and data[16:20] == b"JSON"
    return json.loads(data[20:20 + json_len]), data[20 + json_len + 8:]


def _glb_normals(path) -> np.ndarray:
    """The NORMAL accessor of a GLB's first primitive, as stored (float32)."""
    doc, binary = _glb_chunks(path)
    acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["NORMAL"]]
    view = doc["bufferViews"][acc["bufferView"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    assert acc["componentType"] == 5126 and acc["type"] == "VEC3"
    return np.frombuffer(binary, np.float32, acc["count"] * 3, start).reshape(-1, 3)


def test_unit_normals_repairs_zero_and_nan_normals():
    from sgpor_pipeline.meshing import unit_normals

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 5], [9, 9, 9]], float)
    # faces 0 and 1 are the same triangle folded back to back (their normals cancel at 0, 1, 2);
    # face 2 is larger and stands up from the x axis
    f = np.array([[0, 1, 2], [0, 2, 1], [0, 1, 3]])
    n = np.array([[0, 0, 0], [0, 0, 2.0], [np.nan, 0, 0], [0, 0, 0], [0, 0, 0]])
    out = unit_normals(v, f, n)
    assert np.allclose(np.linalg.norm(out, axis=1), 1.0)
    assert np.allclose(out[1], [0, 0, 1])  # a valid normal is only normalised
    assert np.allclose(np.abs(out[0]), [0, 1, 0])  # cancelled: the largest face (0, 1, 3) lies in y = 0
    assert np.allclose(np.abs(out[2]), [0, 0, 1])  # only the folded pair: the largest of them
    assert np.allclose(np.abs(out[3]), [0, 1, 0])
    assert np.allclose(out[4], [0, 0, 1])  # on no face
    # no normals at all: the area-weighted normals of the faces
    flat = unit_normals(v[:3], np.array([[0, 1, 2]]), None)
    assert np.allclose(flat, [[0, 0, 1]] * 3)


def test_decimation_keeps_the_surface_and_its_colours():
    """meshing.decimate on a finely tessellated unit sphere (81,920 faces, colour = a function of the
    position) down to 4,000 faces: about that many faces, every vertex on the sphere, colours those of
    the surface where the vertex lies, normals of unit length after clean_mesh."""
    import trimesh

    from sgpor_pipeline.meshing import clean_mesh, decimate

    sphere = trimesh.creation.icosphere(subdivisions=6)
    v = np.asarray(sphere.vertices, np.float64)

    def colour(x):
        return ((x + 1) / 2).astype(np.float32)

    dense = MeshData(v, np.asarray(sphere.faces, np.int64), colour(v))
    out = decimate(dense, 4000)
    assert 3600 <= len(out.faces) <= 4000 and out.faces.max() < len(out.vertices)
    assert np.abs(np.linalg.norm(out.vertices, axis=1) - 1).max() < 0.02  # flat facets of a 4k-face sphere
    assert np.abs(out.colors - colour(out.vertices)).max() < 0.05  # the nearest dense vertex's colour
    cleaned = clean_mesh(dense, target_faces=4000)
    assert len(cleaned.faces) == len(out.faces)
    assert np.allclose(np.linalg.norm(cleaned.normals, axis=1), 1.0)
    assert np.einsum("ij,ij->i", cleaned.normals, cleaned.vertices).min() > 0.9  # outward


def test_the_fused_mesh_does_not_depend_on_the_order_open3d_lists_it_in():
    """Open3D's TSDF block map fills in parallel, so extraction lists the same mesh in another order on
    every run, and the decimation followed that order (the demo's mesh.ply had 199997 or 199998 faces
    from the same Gaussians). canonical_order gives one order for any listing: a sphere's vertices and
    faces shuffled, each face rotated, give the same arrays and the same decimated mesh; the faces keep
    their orientation (outward normals)."""
    import trimesh

    from sgpor_pipeline.meshing import canonical_order, clean_mesh

    sphere = trimesh.creation.icosphere(subdivisions=5)
    v = np.asarray(sphere.vertices, np.float64)
    f = np.asarray(sphere.faces, np.int64)
    mesh = MeshData(v, f, ((v + 1) / 2).astype(np.float32), v.copy())
    rng = np.random.default_rng(0)
    perm = rng.permutation(len(v))
    inverse = np.empty_like(perm)
    inverse[perm] = np.arange(len(perm))
    shuffled_f = inverse[f][rng.permutation(len(f))]
    shuffled_f = np.stack([np.roll(row, int(k)) for row, k in zip(shuffled_f, rng.integers(0, 3, len(f)))])
    shuffled = MeshData(v[perm], shuffled_f, mesh.colors[perm], v[perm].copy())
    assert not np.array_equal(shuffled.vertices, mesh.vertices)
    a, b = canonical_order(mesh), canonical_order(shuffled)
    for x, y in ((a.vertices, b.vertices), (a.faces, b.faces), (a.colors, b.colors), (a.normals, b.normals)):
        assert np.array_equal(x, y)
    tri = a.vertices[a.faces]
    outward = np.einsum("ij,ij->i", np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), tri.mean(1))
    assert outward.min() > 0
    da, db = clean_mesh(a, target_faces=3000), clean_mesh(b, target_faces=3000)
    assert np.array_equal(da.vertices, db.vertices) and np.array_equal(da.faces, db.faces)


def test_glb_normals_are_unit_length(tmp_path):
    """glTF requires unit normals (the Khronos validator's ACCESSOR_VECTOR3_NON_UNIT error): a mesh
    with a zero normal, and one written without normals, both store unit normals."""
    from sgpor_pipeline.exporters.mesh import write_mesh

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    f = np.array([[0, 1, 2], [0, 2, 1], [0, 1, 3]])
    c = np.full((4, 3), 0.5, np.float32)
    for normals in (np.array([[0, 0, 0], [0, 0, 1], [0, 0, 1], [0, 0, 0]], float), None):
        (path,) = write_mesh(MeshData(v, f, c, normals), tmp_path, "mesh", formats=("glb",))
        stored = _glb_normals(path)
        assert stored.shape == (4, 3)
        assert np.allclose(np.linalg.norm(stored, axis=1), 1.0, atol=1e-6)


def test_glb_buffer_views_have_targets(tmp_path):
    """Vertex attributes in ARRAY_BUFFER views, indices in an ELEMENT_ARRAY_BUFFER view (the Khronos
    validator's BUFFER_VIEW_TARGET_MISSING); the file stays a valid GLB that trimesh reads back."""
    import trimesh

    from sgpor_pipeline.exporters.mesh import GLTF_FROM_ZUP, write_mesh

    rng = np.random.default_rng(1)
    v, c = rng.uniform(size=(5, 3)), rng.uniform(size=(5, 3)).astype(np.float32)
    f = np.array([[0, 1, 2], [2, 3, 4]])
    (path,) = write_mesh(MeshData(v, f, c), tmp_path, "mesh", formats=("glb",))
    doc, _ = _glb_chunks(path)
    prim = doc["meshes"][0]["primitives"][0]
    views = doc["bufferViews"]
    assert {views[doc["accessors"][a]["bufferView"]]["target"] for a in prim["attributes"].values()} == {34962}
    assert views[doc["accessors"][prim["indices"]]["bufferView"]]["target"] == 34963
    back = trimesh.load(path, force="mesh", process=False)
    assert np.allclose(back.vertices, v @ GLTF_FROM_ZUP.T, atol=1e-6) and np.array_equal(back.faces, f)


def test_object_asset_writer(tmp_path):
    """The removed object's own asset, and none after a fit without the object."""
    import trimesh

    from sgpor_pipeline.exporters.gaussians import ObjectExporter, export_frame
    from sgpor_pipeline.exporters.mesh import GLTF_FROM_ZUP

    scene = generate_scene(SceneParams(seed=2, n_views=8, width=96, height=72, object_kind="box"))
    obj = surface_gaussians(scene, 6000, obj=True)
    background = surface_gaussians(scene, 3000)
    ctx = make_run(tmp_path, background, scene.cameras)
    remove = tmp_path / "remove"
    remove.mkdir()
    write_ply(remove / "object.ply", obj)
    ctx.inputs["remove"] = remove
    ObjectExporter().export(ctx, ctx.out_dir)
    frame = export_frame(ctx, background, scene.cameras)
    back = read_ply(ctx.out_dir / "object" / "object.ply")
    assert np.allclose(back.numpy()["means"], frame.transform.apply(obj.numpy()["means"]), atol=1e-5)
    glb = trimesh.load(ctx.out_dir / "object" / "object.glb", force="mesh", process=False)
    assert len(glb.faces) > 100 and glb.visual.kind == "vertex"
    # the mesh sits where the object is: its bounds match the true object's (export frame, Y up)
    true_pts = frame.transform.apply(np.asarray(scene.object_mesh.vertices)) @ GLTF_FROM_ZUP.T
    from sgpor_pipeline.orientation import scene_center_radius

    voxel = MeshSettings().voxel_rel * scene_center_radius(scene.cameras)[1] * frame.transform.s
    err = np.abs(glb.bounds - np.stack([true_pts.min(0), true_pts.max(0)])).max()
    print(f"object mesh: {len(glb.faces)} faces, bounds error {err:.4f} ({err / voxel:.2f} voxel)")
    assert err < 3 * voxel  # the sides seen by no camera (the bottom) may close a little off the truth
    # after a fit that left the object out there is no object: nothing is written
    (remove / "remove.json").write_text(json.dumps({"object_fitted": False}))
    out2 = tmp_path / "export_no_object"
    out2.mkdir()
    ObjectExporter().export(ctx, out2)
    assert not (out2 / "object").exists()


def test_export_of_a_ply_from_another_trainer(tmp_path):
    from sgpor_pipeline.exporters.gaussians import export_external

    m = random_model(100, 2, seed=9, spread=0.5)
    write_ply(tmp_path / "other.ply", m)
    cams = small_cameras(3)
    save_cameras(tmp_path / "cameras.json", cams)
    out = export_external(tmp_path / "other.ply", tmp_path / "cameras.json", tmp_path / "out",
                          formats=("ply", "splat", "spz", "gltf", "renders"))
    assert read_ply(out / "scene.ply").max_sh_degree == 2
    assert (out / "scene.splat").stat().st_size == 32 * 100
    from sgpor_pipeline.splat_gltf import read_splat_glb
    from sgpor_pipeline.spz_io import read_spz

    assert read_spz(out / "scene.spz")["sh_degree"] == 2 and read_splat_glb(out / "scene.glb")["sh_degree"] == 2
    assert all((out / "renders" / f"{c.image}.png").is_file() for c in cams)



def test_export_of_an_empty_splat_file_warns_and_writes_the_cameras(tmp_path, caplog):
    from sgpor_pipeline.exporters.gaussians import export_external

    (tmp_path / "empty.splat").write_bytes(b"")
    save_cameras(tmp_path / "cameras.json", small_cameras(2))
    with caplog.at_level(logging.WARNING):
        out = export_external(tmp_path / "empty.splat", tmp_path / "cameras.json", tmp_path / "out",
                              formats=("ply", "gltf"))
    assert "holds no Gaussians" in caplog.text
    assert len(read_ply(out / "scene.ply")) == 0 and (out / "scene.glb").is_file()


# --------------------------------------------------------------------------------------------------
# report: the evaluate stage's metrics (an optional input of export)


def _metrics(psnr_final: float) -> dict:
    def scores(p):
        return {"psnr_mask": p, "ssim_mask": 0.5, "psnr_bbox": p + 1, "ssim_bbox": 0.6, "psnr_full": p + 2,
                "ssim_full": 0.7}

    means = {"final": scores(psnr_final), "inpainted_2d": scores(20.0), "delete_only": scores(10.0)}
    means["delete_only"]["ssim_mask"] = float("nan")  # e.g. an empty mask: shown as a dash
    return {"views": 2, "means": means, "seconds": {"fit": 12.34, "finetune": 5.0}, "total_seconds": 17.34,
            "per_view": {"view_00": means, "view_01": means}}


def test_report_shows_evaluate_metrics(tmp_path):
    from sgpor_pipeline.exporters.report import ReportExporter

    ctx = make_run(tmp_path, random_model(100, 0, seed=2, spread=0.5), small_cameras(2))
    evaluate = tmp_path / "evaluate"
    evaluate.mkdir()
    (evaluate / "metrics.json").write_text(json.dumps(_metrics(27.126)))
    ctx.inputs["evaluate"] = evaluate
    ReportExporter().export(ctx, ctx.out_dir)
    page = (ctx.out_dir / "report.html").read_text()
    assert page.index(">Metrics</h2>") < page.index(">Views</h2>")  # the result first
    for text in ("<th>PSNR mask</th>", "<th>SSIM bbox</th>", "<th>PSNR full</th>", "<td>27.13</td>",
                 "<td>28.13</td>", "<td>29.13</td>", "<td>20.00</td>", "<td>10.00</td>", "<td>0.5000</td>",
                 "<tr><th>fit</th><td>12.3</td></tr>", "<tr><th>total</th><td>17.3</td></tr>", "per view (2)"):
        assert text in page, text
    assert ">nan<" not in page.lower()  # NaN shows as a dash
    for name in ("final", "inpainted_2d", "delete_only"):
        assert f">{name}</th>" in page
    # the file itself beside the report, linked, and every link resolves inside the export folder
    assert json.loads((ctx.out_dir / "metrics.json").read_text())["means"]["final"]["psnr_mask"] == 27.126
    links = _Links()
    links.feed(page)
    assert "metrics.json" in links.refs
    for ref in links.refs:
        assert (ctx.out_dir / unquote(ref)).is_file(), ref


def test_report_without_evaluation_has_no_metrics_section(tmp_path):
    from sgpor_pipeline.exporters.report import ReportExporter

    ctx = make_run(tmp_path, random_model(100, 0, seed=2, spread=0.5), small_cameras(2))
    ReportExporter().export(ctx, ctx.out_dir)
    assert ">Metrics</h2>" not in (ctx.out_dir / "report.html").read_text()
    assert not (ctx.out_dir / "metrics.json").exists()


def test_evaluate_key_enters_the_export_key_only_with_ground_truth(tmp_path):
    """The cache rule for the report's optional input: with ground truth, evaluate is an input of
    export (ordered before it, its key in export's key: new metrics rebuild the report); without,
    export neither waits for nor depends on it."""
    from conftest import make_images

    from sgpor_pipeline.config import resolve_config
    from sgpor_pipeline.dag import discover_stages, topological_order, upstream_of
    from sgpor_pipeline.hashing import DigestMemo
    from sgpor_pipeline.runner import compute_keys, select_stages

    stages = discover_stages()
    config = resolve_config({n: c.Params for n, c in stages.items()})
    make_images(tmp_path / "images")
    make_images(tmp_path / "truth")
    plain = RunInputs(images=tmp_path / "images")
    truth = RunInputs(images=tmp_path / "images", extra={"groundtruth": tmp_path / "truth"})
    assert "evaluate" not in upstream_of(stages, config, "export", plain)
    assert "evaluate" in upstream_of(stages, config, "export", truth)
    order = topological_order(stages, config, truth)
    assert order.index("evaluate") < order.index("export")
    assert "evaluate" in select_stages(stages, order, config, truth, until="export")
    assert "evaluate" not in select_stages(stages, order, config, plain, until="export")

    def keys(run_inputs):
        return compute_keys(stages, topological_order(stages, config, run_inputs), config, run_inputs,
                            DigestMemo(tmp_path / "digests.json"))

    k_plain, k_truth = keys(plain), keys(truth)
    assert k_plain["finetune"] == k_truth["finetune"] and k_plain["export"] != k_truth["export"]
    make_images(tmp_path / "truth", seed=1)  # other ground truth: other metrics, another report
    k_new = keys(truth)
    assert k_new["evaluate"] != k_truth["evaluate"] and k_new["export"] != k_truth["export"]
    assert k_new["finetune"] == k_truth["finetune"]


def test_report_shows_the_plane_texture_when_the_inpaint_stage_made_one(tmp_path):
    from sgpor_pipeline.exporters.report import PlaneSection, ReportContext
    from sgpor_pipeline.imageio import write_png

    inpaint = tmp_path / "inpaint"
    rc = ReportContext(inputs={"inpaint": inpaint}, export_dir=tmp_path / "export", cameras=[])
    inpaint.mkdir()
    assert PlaneSection().render(rc) is None  # no plane texture: no section
    (inpaint / "plane").mkdir()
    rng = np.random.default_rng(0)
    for name in ("texture.png", "filled.png"):
        write_png(inpaint / "plane" / name, rng.uniform(0, 1, (40, 60, 3)).astype(np.float32))
    (inpaint / "plane" / "plane.json").write_text(json.dumps({"built": True, "width": 60, "height": 40,
                                                              "hole_texels": 123, "texel": 0.01}))
    html = PlaneSection().render(rc)
    assert html.count("<img") == 2 and "hole_texels" in html and "123" in html
    assert len(list((tmp_path / "export" / "report").glob("plane_*.png"))) == 2
    # with inpaint.lift_shadow: the texture as seen and the shadow found, and its strength
    for name in ("texture_as_seen.png", "shading.png"):
        write_png(inpaint / "plane" / name, rng.uniform(0, 1, (40, 60, 3)).astype(np.float32))
    (inpaint / "plane" / "plane.json").write_text(json.dumps({"built": True, "shadow": {"strength": 0.42}}))
    html = PlaneSection().render(rc)
    assert html.count("<img") == 4 and "contact shadow" in html and "0.42" in html
    # with inpaint.plane_structure: the lines continued through its hole, and how many
    write_png(inpaint / "plane" / "structure.png", rng.uniform(0, 1, (40, 60, 3)).astype(np.float32))
    (inpaint / "plane" / "plane.json").write_text(json.dumps({"built": True, "structure": {"lines": [{}, {}]}}))
    html = PlaneSection().render(rc)
    assert html.count("<img") == 5 and "straight edges continued" in html and "<td>2</td>" in html


def test_report_says_where_each_views_mask_came_from(tmp_path):
    """Under each view's name: given, propagated with its confidence, or lifted where the selection's
    render lost the object (the masks stage's masks.json); nothing without that file."""
    from sgpor_pipeline.exporters.report import ReportContext, ViewsSection, mask_sources

    masks = tmp_path / "masks"
    masks.mkdir()
    cams = generate_scene(SceneParams(seed=0, n_views=3, width=32, height=24)).cameras
    rc = ReportContext(inputs={"masks": masks}, export_dir=tmp_path / "export", cameras=list(cams))
    assert mask_sources(rc) == {}
    (masks / "masks.json").write_text(json.dumps({"views": {
        cams[0].image: {"source": "given", "confidence": 1.0},
        cams[1].image: {"source": "propagated", "confidence": 0.93, "lifted_added": 0},
        cams[2].image: {"source": "propagated", "confidence": 0.0, "lifted_added": 250}}}))
    lines = mask_sources(rc)
    assert "mask: given<" in lines[cams[0].image] and "confidence" not in lines[cams[0].image]
    assert "propagated, confidence 0.93" in lines[cams[1].image] and "lifted" not in lines[cams[1].image]
    assert "lifted (the render lost the object), confidence 0.00" in lines[cams[2].image]
    html = ViewsSection(columns=[]).render(rc)
    assert all(lines[c.image] in html for c in cams)


# --------------------------------------------------------------------------------------------------
# glTF KHR_gaussian_splatting (scene.glb)

# The extension's SH basis written out from its specification (Appendix A: real SH with the
# Condon-Shortley phase), independently of the rasterizer's eval_sh.
_KHR_SH = [
    lambda x, y, z: 0.28209479177387814 * np.ones_like(x),
    lambda x, y, z: -0.4886025119029199 * y, lambda x, y, z: 0.4886025119029199 * z,
    lambda x, y, z: -0.4886025119029199 * x,
    lambda x, y, z: 1.0925484305920792 * x * y, lambda x, y, z: -1.0925484305920792 * y * z,
    lambda x, y, z: 0.31539156525252005 * (2 * z * z - x * x - y * y),
    lambda x, y, z: -1.0925484305920792 * x * z, lambda x, y, z: 0.5462742152960396 * (x * x - y * y),
    lambda x, y, z: -0.5900435899266435 * y * (3 * x * x - y * y), lambda x, y, z: 2.890611442640554 * x * y * z,
    lambda x, y, z: -0.4570457994644658 * y * (4 * z * z - x * x - y * y),
    lambda x, y, z: 0.3731763325901154 * z * (2 * z * z - 3 * x * x - 3 * y * y),
    lambda x, y, z: -0.4570457994644658 * x * (4 * z * z - x * x - y * y),
    lambda x, y, z: 1.445305721320277 * z * (x * x - y * y),
    lambda x, y, z: -0.5900435899266435 * x * (x * x - 3 * y * y),
]


def _khr_colour(sh: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Colour [N,3] of Gaussians with SH [N,K,3] (DC first) seen along unit directions d [N,3]."""
    basis = np.stack([f(d[:, 0], d[:, 1], d[:, 2]) for f in _KHR_SH[:sh.shape[1]]], 1)  # [N,K]
    return (basis[:, :, None] * sh).sum(1) + 0.5


def test_splat_glb_follows_khr_gaussian_splatting(tmp_path):
    """Every attribute as the extension defines it, read from the raw GLB: linear scales, sigmoid
    opacities, (x, y, z, w) unit rotations, SH per coefficient, POSITION bounds, aligned views, a linear
    COLOR_0 fallback; and the reader gives the same values back."""
    from sgpor_pipeline.imageio import srgb_to_linear
    from sgpor_pipeline.splat_gltf import read_splat_glb, write_splat_glb

    m = random_model(301, 3, seed=11)
    p = m.numpy()
    path = write_splat_glb(tmp_path / "s.glb", m)
    doc, binary = _glb_chunks(path)
    assert doc["asset"]["version"] == "2.0" and doc["extensionsUsed"] == ["KHR_gaussian_splatting"]
    assert "extensionsRequired" not in doc  # a viewer without it still shows the points
    prim = doc["meshes"][0]["primitives"][0]
    assert prim["mode"] == 0
    ext = prim["extensions"]["KHR_gaussian_splatting"]
    assert ext["kernel"] == "ellipse" and ext["colorSpace"] == "srgb_rec709_display"

    def accessor(name):
        acc = doc["accessors"][prim["attributes"][name]]
        view = doc["bufferViews"][acc["bufferView"]]
        assert view["byteOffset"] % 4 == 0 and view["target"] == 34962 and acc["count"] == len(m)
        n = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc["type"]]
        dtype = np.float32 if acc["componentType"] == 5126 else np.uint8
        return acc, np.frombuffer(binary, dtype, n * len(m), view["byteOffset"]).reshape(len(m), n)

    k = "KHR_gaussian_splatting:"
    acc, pos = accessor("POSITION")
    assert np.array_equal(pos, p["means"]) and acc["min"] == pos.min(0).tolist() and acc["max"] == pos.max(0).tolist()
    _, scale = accessor(k + "SCALE")
    assert np.allclose(scale, np.exp(p["scales"]), rtol=1e-6) and (scale > 0).all()
    _, opacity = accessor(k + "OPACITY")
    assert np.allclose(opacity[:, 0], 1 / (1 + np.exp(-p["opacities"].astype(np.float64))), atol=1e-7)
    _, rot = accessor(k + "ROTATION")
    q = p["quats"] / np.linalg.norm(p["quats"], axis=1, keepdims=True)
    assert np.allclose(rot, q[:, [1, 2, 3, 0]], atol=1e-6)
    assert np.allclose(quat_to_matrix(rot[:, [3, 0, 1, 2]].astype(np.float64)), quat_to_matrix(q), atol=1e-6)
    _, dc = accessor(k + "SH_DEGREE_0_COEF_0")
    assert np.array_equal(dc, p["sh0"][:, 0])
    coeff = 0
    for degree in (1, 2, 3):
        for n in range(2 * degree + 1):
            _, c = accessor(f"{k}SH_DEGREE_{degree}_COEF_{n}")
            assert np.array_equal(c, p["shN"][:, coeff]), (degree, n)
            coeff += 1
    assert f"{k}SH_DEGREE_4_COEF_0" not in prim["attributes"] and coeff == 15
    acc, color = accessor("COLOR_0")
    assert acc["componentType"] == 5121 and acc["normalized"] and acc["type"] == "VEC4"
    want = srgb_to_linear(SH_C0 * p["sh0"][:, 0].astype(np.float64) + 0.5)
    assert np.abs(color[:, :3] / 255.0 - want).max() <= 0.5 / 255 + 1e-9
    assert np.abs(color[:, 3] / 255.0 - opacity[:, 0]).max() <= 0.5 / 255 + 1e-7
    assert len(binary) == doc["buffers"][0]["byteLength"] and len(binary) % 4 == 0

    back = read_splat_glb(path)
    assert back["sh_degree"] == 3 and back["sh"].shape == (len(m), 16, 3)
    assert np.array_equal(back["means"], p["means"]) and np.array_equal(back["sh"][:, 1:], p["shN"])
    assert np.allclose(back["quats"], q, atol=1e-6) and back["cameras"] == []

    m0 = random_model(5, 0, seed=12)  # degree 0: the DC alone
    back0 = read_splat_glb(write_splat_glb(tmp_path / "d0.glb", m0))
    assert back0["sh_degree"] == 0 and back0["sh"].shape == (5, 1, 3)


def test_splat_glb_of_no_gaussians_is_the_cameras_alone(tmp_path):
    """glTF forbids empty accessors: with every Gaussian deleted the file holds the cameras only."""
    from sgpor_pipeline.splat_gltf import read_glb, read_splat_glb, write_splat_glb

    path = write_splat_glb(tmp_path / "empty.glb", random_model(0, 3), small_cameras(2))
    doc, binary = read_glb(path)
    assert "meshes" not in doc and "accessors" not in doc and binary == b""
    assert [n["name"] for n in doc["nodes"]] == ["view_00", "view_01", "Cameras"]
    assert doc["scenes"] == [{"nodes": [2]}] and len(doc["cameras"]) == 2
    with pytest.raises(ValueError, match="no primitive with the KHR_gaussian_splatting extension"):
        read_splat_glb(path)


def test_splat_glb_refuses_a_broken_model(tmp_path):
    from sgpor_pipeline.splat_gltf import write_splat_glb

    m = random_model(10, 1, seed=13)
    m.params["scales"].data[3, 1] = float("nan")
    with pytest.raises(ValueError, match=r"bad\.glb: 1 Gaussians have a non-finite scale"):
        write_splat_glb(tmp_path / "bad.glb", m)
    assert not list(tmp_path.iterdir())  # nothing half-written


def test_gltf_exporter_is_the_scene_in_y_up_with_its_view_dependent_colour(tmp_path):
    """scene.glb holds the export frame's Gaussians rotated to glTF's +Y up: positions and rotations
    turn with the frame, and the colour the extension's SH formulas give along a direction in the glTF
    frame is the fitted model's colour along that direction (the SH rotated with the frame); its
    cameras stand where the export frame's do and look the same way."""
    from sgpor_pipeline.exporters.gaussians import GltfExporter, PlyExporter, export_frame
    from sgpor_pipeline.gaussians._raster_common import eval_sh
    from sgpor_pipeline.orientation import GLTF_FROM_ZUP
    from sgpor_pipeline.splat_gltf import read_splat_glb

    cams = small_cameras(3)
    cams.append(Camera("novel_a", 64, 48, cams[0].K, look_at(np.array([0.0, -3.0, 2.0]), np.zeros(3))))
    m = random_model(200, 3, seed=14, spread=0.5)
    ctx = make_run(tmp_path, m, cams)
    out = ctx.out_dir
    PlyExporter().export(ctx, out)
    GltfExporter().export(ctx, out)
    ply = read_ply(out / "scene.ply").numpy()  # the export frame, Z up
    glb = read_splat_glb(out / "scene.glb")
    assert np.allclose(glb["means"], ply["means"].astype(np.float64) @ GLTF_FROM_ZUP.T, atol=1e-5)
    R_ply = quat_to_matrix(ply["quats"] / np.linalg.norm(ply["quats"], axis=1, keepdims=True))
    assert np.allclose(quat_to_matrix(glb["quats"].astype(np.float64)), GLTF_FROM_ZUP @ R_ply, atol=1e-5)
    assert np.allclose(glb["scales"], np.exp(ply["scales"]), rtol=1e-5)

    rng = np.random.default_rng(0)
    d = rng.normal(size=(len(m), 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)  # directions in the export frame
    sh_ply = np.concatenate([ply["sh0"], ply["shN"]], 1)
    want = eval_sh(3, torch.from_numpy(d), torch.from_numpy(sh_ply.astype(np.float64))).numpy() + 0.5
    got = _khr_colour(glb["sh"].astype(np.float64), d @ GLTF_FROM_ZUP.T)
    assert np.abs(got - want).max() < 1e-4
    # (and the SH did change: read unrotated, the colours would differ)
    assert np.abs(_khr_colour(sh_ply.astype(np.float64), d @ GLTF_FROM_ZUP.T) - want).max() > 0.05

    frame = export_frame(ctx, m, cams, out)
    assert [c["name"] for c, _ in glb["cameras"]] == [c.name for c in cams]
    for (gl_cam, node), cam in zip(glb["cameras"], cams):
        e = frame.transform.camera(cam)
        assert np.allclose(node["translation"], GLTF_FROM_ZUP @ e.center, atol=1e-6)
        R = quat_to_matrix(np.array(node["rotation"])[[3, 0, 1, 2]])
        forward = e.world_from_cam[:3, :3] @ [0, 0, 1]  # OpenCV looks along +z
        assert np.allclose(R @ [0, 0, -1], GLTF_FROM_ZUP @ forward, atol=1e-6)  # glTF looks along -z
        assert np.allclose(R @ [0, 1, 0], GLTF_FROM_ZUP @ (e.world_from_cam[:3, :3] @ [0, -1, 0]), atol=1e-6)
        assert math.isclose(gl_cam["perspective"]["yfov"], 2 * math.atan(cam.height / (2 * cam.K[1, 1])))
        assert gl_cam["perspective"]["aspectRatio"] == cam.width / cam.height
    assert glb["cameras"][-1][1]["extras"].get("sgpor_image") is None  # the novel camera


def test_spz_exporter_is_the_y_up_scene_compressed(tmp_path):
    """scene.spz holds scene.glb's Gaussians (the same +Y-up frame, SH rotated) to the format's
    quantisation, and is several times smaller than scene.ply."""
    from sgpor_pipeline.exporters.gaussians import GltfExporter, PlyExporter, SpzExporter
    from sgpor_pipeline.splat_gltf import read_splat_glb
    from sgpor_pipeline.spz_io import read_spz, read_spz_header

    cams = small_cameras(3)
    m = random_model(400, 3, seed=15, spread=0.5)
    ctx = make_run(tmp_path, m, cams)
    out = ctx.out_dir
    for exporter in (PlyExporter(), GltfExporter(), SpzExporter()):
        exporter.export(ctx, out)
    glb, spz = read_splat_glb(out / "scene.glb"), read_spz(out / "scene.spz")
    assert read_spz_header(out / "scene.spz").fractional_bits == 12 and spz["sh_degree"] == 3
    assert np.abs(spz["means"] - glb["means"]).max() <= 2.0 ** -13 + 1e-6
    assert np.abs(np.exp(spz["scales"]) / glb["scales"] - 1).max() < 0.035  # log steps of 1/16
    assert np.abs(spz["opacities"] - glb["opacities"]).max() <= 0.5 / 255 + 1e-6
    R = quat_to_matrix(spz["quats"].astype(np.float64))
    assert np.abs(R - quat_to_matrix(glb["quats"].astype(np.float64))).max() < 1e-2
    dc = np.clip(glb["sh"][:, 0], -0.5 / 0.15, 0.5 / 0.15)  # (the format's byte range)
    assert np.abs(spz["sh0"][:, 0] - dc).max() <= 0.5 / (0.15 * 255) + 1e-6
    assert np.abs(spz["shN"] - np.clip(glb["sh"][:, 1:], -1, 127 / 128)).max() <= 8.5 / 128
    assert (out / "scene.spz").stat().st_size * 3 < (out / "scene.ply").stat().st_size


def test_exports_benchmark_reads_every_format_back(tmp_path, capsys):
    """benchmarks/exports.py decodes each Gaussian file of an export and renders it: the GLB is the PLY
    to float rounding, the .spz within its quantisation, the .splat (DC colour, 8 bits) coarser."""
    from conftest import load_benchmark

    from sgpor_pipeline.exporters.cameras import CamerasExporter
    from sgpor_pipeline.exporters.gaussians import GltfExporter, PlyExporter, SplatExporter, SpzExporter

    ctx = make_run(tmp_path, random_model(300, 2, seed=16, spread=0.4), small_cameras(3))
    for exporter in (PlyExporter(), GltfExporter(), SpzExporter(), SplatExporter(), CamerasExporter()):
        exporter.export(ctx, ctx.out_dir)
    bench = load_benchmark("exports")
    assert bench.main([str(ctx.out_dir), "--json"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["ply"]["psnr_mean"] is None and res["ply"]["ratio"] == 1.0
    assert res["glb"]["psnr_min"] > 90 and res["glb"]["sh_degree"] == 2
    assert 25 < res["spz"]["psnr_min"] < 90 and res["spz"]["ratio"] < 0.3 and res["spz"]["sh_degree"] == 2
    assert res["splat"]["sh_degree"] == 0 and res["splat"]["psnr_mean"] < res["spz"]["psnr_mean"]


def test_one_failing_format_does_not_stop_the_others(tmp_path, monkeypatch):
    """An exporter that fails (a file format's limit, a full disk) is named with its message and the
    --export list without it; the other formats still write their files."""
    from sgpor_pipeline.dag import Exporter
    from sgpor_pipeline.errors import PipelineError
    from sgpor_pipeline.exporters.gaussians import PlyExporter
    from sgpor_pipeline.stages import export as export_stage

    class TooBig(Exporter):
        name = "toobig"

        def export(self, ctx, out_dir):
            raise ValueError("scene.big: over the format's limit")

    monkeypatch.setattr(export_stage, "selected_exporters", lambda params: {"ply": PlyExporter, "toobig": TooBig})
    ctx = make_run(tmp_path, random_model(50, 1, seed=17), small_cameras(3))
    with pytest.raises(PipelineError, match=r"'toobig' failed: ValueError: scene\.big: over.*out: --export ply"):
        export_stage.ExportStage().run(ctx)
    assert (ctx.out_dir / "scene.ply").is_file()
    # a setting of the export frame is no one format's fault: its own error, before any format runs
    from dataclasses import replace

    bad = StageContext(**{**ctx.__dict__, "params": replace(ctx.params, scale=-1.0)})
    with pytest.raises(PipelineError, match=r"^export scale must be a positive number, got -1\.0$"):
        export_stage.ExportStage().run(bad)


def test_a_large_scenes_usda_is_a_text_layer_over_the_crate(tmp_path, monkeypatch):
    """Above TEXT_MAX_GAUSSIANS the .usda keeps the stage's metadata and sublayers the .usdc: it opens as
    the same stage (the same Gaussians, up axis, units, default prim) and is small."""
    from pxr import Usd, UsdGeom, UsdVol

    from sgpor_pipeline.exporters import usd as usd_exporter
    from sgpor_pipeline.exporters.usd import UsdExporter, validate_stage

    monkeypatch.setattr(usd_exporter, "TEXT_MAX_GAUSSIANS", 100)
    ctx, m, _ = _usd_run(tmp_path)  # 300 Gaussians
    UsdExporter().export(ctx, ctx.out_dir)
    usda, usdc = ctx.out_dir / "scene.usda", ctx.out_dir / "scene.usdc"
    assert usda.stat().st_size < 2000 < usdc.stat().st_size
    text, crate = Usd.Stage.Open(str(usda)), Usd.Stage.Open(str(usdc))
    assert validate_stage(text) == []
    assert text.GetDefaultPrim().GetPath() == "/World" and UsdGeom.GetStageUpAxis(text) == UsdGeom.Tokens.z
    assert text.GetRootLayer().customLayerData == crate.GetRootLayer().customLayerData
    assert UsdGeom.GetStageMetersPerUnit(text) == UsdGeom.GetStageMetersPerUnit(crate)
    pos = [np.asarray(UsdVol.ParticleField3DGaussianSplat(s.GetPrimAtPath("/World/Gaussians")).GetPositionsAttr().Get())
           for s in (text, crate)]
    assert pos[0].shape == (len(m), 3) and np.array_equal(pos[0], pos[1])


def test_export_warns_when_the_cameras_do_not_see_the_gaussians(caplog):
    """Gaussians and cameras in different frames (an .spz read in the wrong frame, a .glb turned on the
    way) give exports that make no sense: the check names the half turn that would fit them."""
    from sgpor_pipeline.exporters.gaussians import HALF_TURNS, check_cameras_see_gaussians

    m = random_model(400, 0, seed=21, spread=0.3)
    m.params["means"].data += torch.tensor([0.0, 0.0, 2.0])  # in front of cameras looking along +z
    K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    cams = [Camera(f"c{i}", 64, 48, K, look_at(np.array([x, 0.0, -1.0]), np.array([x, 0.0, 2.0]), up=(0, -1, 0)))
            for i, x in enumerate((-0.3, 0.0, 0.3))]
    with caplog.at_level(logging.WARNING):
        shares = check_cameras_see_gaussians(m, cams, Path("m.spz"))
    assert shares["as read"] > 0.9 and len(shares) == 1 and "cameras see only" not in caplog.text
    turned = transform_model(m, Similarity(1.0, HALF_TURNS["x"]))  # e.g. SPZ's RUB frame, read as stored
    with caplog.at_level(logging.WARNING):
        shares = check_cameras_see_gaussians(turned, cams, Path("m.spz"))
    assert shares["as read"] < 0.05 and shares["turned half about x"] > 0.9
    assert "m.spz: the cameras see only 0% of the opaque Gaussians" in caplog.text
    assert "turned half about x, 100% would be" in caplog.text
