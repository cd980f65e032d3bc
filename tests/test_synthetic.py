"""Synthetic ground-truth scenes and object insertion."""

from __future__ import annotations

import json
import time

import cv2
import numpy as np
import pytest

from sgpor_pipeline.errors import PipelineError
from sgpor_pipeline.scene import Camera, load_cameras
from sgpor_pipeline.synthetic import (
    SceneParams,
    generate_scene,
    insert_object,
    look_at,
    save_scene,
    viewing_axes_center,
)

SMALL = dict(n_views=8, width=64, height=48)


@pytest.fixture(scope="module", params=["inward", "forward"])
def scene(request):
    return generate_scene(SceneParams(seed=3, rig=request.param, **SMALL))


def test_deterministic_for_a_seed():
    a = generate_scene(SceneParams(seed=5, **SMALL))
    b = generate_scene(SceneParams(seed=5, **SMALL))
    for f in ("images", "images_gt", "masks", "depth", "depth_gt", "object_bounds"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f
    for ca, cb in zip(a.cameras, b.cameras):
        assert np.array_equal(ca.cam_from_world, cb.cam_from_world)
        assert np.array_equal(ca.K, cb.K)
    c = generate_scene(SceneParams(seed=6, **SMALL))
    assert not np.array_equal(a.images_gt, c.images_gt)
    assert not np.array_equal(a.object_bounds, c.object_bounds)


def test_shapes_and_cameras(scene):
    N, H, W = 8, 48, 64
    assert scene.images.shape == (N, H, W, 3) and scene.images.dtype == np.float32
    assert scene.images_gt.shape == (N, H, W, 3) and scene.images_gt.dtype == np.float32
    assert scene.masks.shape == (N, H, W) and scene.masks.dtype == bool
    assert scene.depth.shape == scene.depth_gt.shape == (N, H, W)
    assert scene.images.min() >= 0 and scene.images.max() <= 1
    assert [c.name for c in scene.cameras] == [f"view_{i:03d}" for i in range(N)]
    for c in scene.cameras:
        assert c.image == c.name and (c.width, c.height) == (W, H)
        assert np.allclose(c.K[:2, 2], [W / 2, H / 2])
        hfov = 2 * np.degrees(np.arctan(W / 2 / c.K[0, 0]))
        assert abs(hfov - 60) < 1e-6
        R = c.cam_from_world[:3, :3]
        assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1)
    # the closed room: every pixel hits something
    assert np.all(np.isfinite(scene.depth_gt))


def test_masks_are_exactly_the_object_pixels(scene):
    assert np.array_equal(scene.masks, scene.depth < scene.depth_gt)
    assert np.array_equal(scene.depth[~scene.masks], scene.depth_gt[~scene.masks])


def test_images_differ_only_inside_the_mask(scene):
    outside = ~scene.masks
    assert np.array_equal(scene.images[outside], scene.images_gt[outside])  # bitwise
    inside = scene.masks
    changed = np.any(scene.images != scene.images_gt, axis=-1)
    assert changed[inside].mean() > 0.95


def test_object_visible_and_backgrounds_textured(scene):
    for i in range(len(scene.cameras)):
        assert scene.masks[i].sum() > 20, f"object not visible in view {i}"
        assert scene.masks[i].mean() < 0.5
        bg = scene.images_gt[i][~scene.masks[i]]
        assert bg.std(axis=0).min() > 0.02  # textured, not constant
    # the object lies inside its bounds: back-project its depth pixels
    c = scene.cameras[0]
    v, u = np.nonzero(scene.masks[0])
    z = scene.depth[0][v, u]
    pts_cam = np.stack([(u + 0.5 - c.K[0, 2]) / c.K[0, 0] * z, (v + 0.5 - c.K[1, 2]) / c.K[1, 1] * z, z], 1)
    pts = (pts_cam - c.cam_from_world[:3, 3]) @ c.cam_from_world[:3, :3]
    lo, hi = scene.object_bounds
    assert np.all(pts >= lo - 1e-3) and np.all(pts <= hi + 1e-3)


def test_meshes(scene):
    import open3d as o3d

    assert isinstance(scene.background_mesh, o3d.geometry.TriangleMesh)
    assert len(scene.object_mesh.triangles) > 0 and len(scene.background_mesh.triangles) > 0
    lo, hi = scene.object_bounds
    assert np.allclose(scene.object_mesh.get_min_bound(), lo)
    assert np.allclose(scene.object_mesh.get_max_bound(), hi)


def test_object_shadow_darkens_only_the_photos_near_the_object():
    """With ``object_shadow`` the object darkens the background of ``images`` (never brighter, never
    ``images_gt``, never the object itself): "contact" only near the object, "cast" more."""
    params = dict(seed=2, object_kind="box", n_views=6, width=96, height=72)
    plain = generate_scene(SceneParams(**params))
    darker = {}
    for kind in ("contact", "cast"):
        sc = generate_scene(SceneParams(**params, object_shadow=kind))
        assert np.array_equal(sc.images_gt, plain.images_gt)
        assert np.array_equal(sc.masks, plain.masks)
        assert np.array_equal(sc.images[sc.masks], plain.images[plain.masks])
        drop = (plain.images - sc.images).max(axis=-1)
        assert drop.min() >= -1e-6  # a shadow only takes light away
        darker[kind] = drop > 0.01
        assert darker[kind].sum() > 200, kind
        # where the background got darker, its point is near the object (within the object's size)
        lo, hi = sc.object_bounds
        reach = np.linalg.norm(hi - lo)
        for i, cam in enumerate(sc.cameras):
            v, u = np.nonzero(darker[kind][i])
            if not len(u):
                continue
            rays = np.linalg.inv(cam.K) @ np.stack([u + 0.5, v + 0.5, np.ones_like(u, float)])
            pc = rays * sc.depth_gt[i, v, u]
            pw = (np.linalg.inv(cam.cam_from_world) @ np.vstack([pc, np.ones(len(u))]))[:3].T
            gap = np.linalg.norm(np.maximum(np.maximum(lo - pw, pw - hi), 0), axis=1)
            if kind == "contact":
                assert gap.max() < reach
    assert darker["cast"].sum() > darker["contact"].sum()


def _world_points(cam: Camera, depth: np.ndarray, v: np.ndarray, u: np.ndarray) -> np.ndarray:
    rays = np.linalg.inv(cam.K) @ np.stack([u + 0.5, v + 0.5, np.ones_like(u, float)])
    pc = rays * depth[v, u]
    return (np.linalg.inv(cam.cam_from_world) @ np.vstack([pc, np.ones(len(u))]))[:3].T


def test_raised_box_shows_its_dark_footprint():
    """A ``raised_box`` stands on four feet: the photos see the floor under its body through the gap
    (outside the masks), in its shadow; the truth is the box scene's."""
    import open3d as o3d

    params = dict(seed=2, n_views=8, width=128, height=96)
    box = generate_scene(SceneParams(**params, object_kind="box"))
    sc = generate_scene(SceneParams(**params, object_kind="raised_box", object_shadow="cast"))
    assert np.array_equal(sc.images_gt, box.images_gt)  # the same room, rug and object placement
    assert np.allclose(sc.object_bounds, box.object_bounds)
    assert sc.masks.sum() < box.masks.sum()  # the gap is seen through
    body = o3d.t.geometry.RaycastingScene()
    body.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(sc.object_mesh))
    under, ratio = 0, []
    for i, cam in enumerate(sc.cameras):
        v, u = np.nonzero(~sc.masks[i] & np.isfinite(sc.depth[i]))
        pw = _world_points(cam, sc.depth[i], v, u)
        up = np.hstack([pw + [0.0, 0.0, 1e-3], np.tile([0.0, 0.0, 1.0], (len(pw), 1))]).astype(np.float32)
        below = body.test_occlusions(o3d.core.Tensor(up)).numpy().astype(bool)  # the object right above
        under += int(below.sum())
        lum_photo = sc.images[i, v[below], u[below]].mean(axis=1)
        lum_truth = sc.images_gt[i, v[below], u[below]].mean(axis=1)
        ratio.extend(lum_photo / np.maximum(lum_truth, 1e-3))
    assert under > 100  # the floor under the body, seen in the photos
    assert np.median(ratio) < 0.4  # and dark there: its footprint


def test_bad_params():
    with pytest.raises(PipelineError, match="rig"):
        generate_scene(SceneParams(rig="sideways"))
    with pytest.raises(PipelineError, match="object_shadow"):
        generate_scene(SceneParams(object_shadow="soft"))
    with pytest.raises(PipelineError, match="raised_box"):  # the fix lists every kind
        generate_scene(SceneParams(object_kind="table"))


def test_default_scene_is_fast():
    t0 = time.perf_counter()
    sc = generate_scene(SceneParams())
    dt = time.perf_counter() - t0
    print(f"default 24 x 256x192 scene: {dt:.2f} s")
    assert sc.images.shape == (24, 192, 256, 3)
    assert dt < 60  # loose: ~1 s on 2 cores


def test_save_scene(tmp_path, scene):
    out = save_scene(scene, tmp_path / "scene")
    name = scene.cameras[1].name
    img = cv2.imread(str(out / "images" / f"{name}.png"))
    assert img.shape == (48, 64, 3)
    expected = np.round(scene.images[1] * 255).astype(np.uint8)[..., ::-1]
    assert np.array_equal(img, expected)
    m = cv2.imread(str(out / "masks" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
    assert m.dtype == np.uint8 and set(np.unique(m)) <= {0, 255}
    assert np.array_equal(m > 0, scene.masks[1])
    assert (out / "groundtruth" / f"{name}.png").is_file()
    assert np.array_equal(np.load(out / "depth" / f"{name}.npy"), scene.depth[1])
    cams = load_cameras(out / "cameras.json")
    assert [c.name for c in cams] == scene.names
    from sgpor_pipeline.camera_io import read_transforms_json

    tcams = read_transforms_json(out / "transforms.json")
    assert np.allclose(tcams[2].cam_from_world, scene.cameras[2].cam_from_world, atol=1e-9)
    meta = json.loads((out / "scene.json").read_text())
    assert np.allclose(meta["object_bounds"], scene.object_bounds)
    assert (out / "object.ply").is_file() and (out / "background.ply").is_file()


def _ring_cameras(n=6, W=64, H=48):
    K = np.array([[55.0, 0, W / 2], [0, 55.0, H / 2], [0, 0, 1]])
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = np.array([3 * np.cos(a), 3 * np.sin(a), 1.0])
        cams.append(Camera(f"c{i}", W, H, K, look_at(eye, [0.0, 0.0, 0.0]), image=f"c{i}"))
    return cams


def test_viewing_axes_center():
    cams = _ring_cameras()
    assert np.allclose(viewing_axes_center(cams), 0.0, atol=1e-2)
    # a line of cameras whose axes diverge (they would meet 5-9 units behind them): the point is in front
    line = [Camera(f"l{i}", 64, 48, np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]]),
                   look_at(np.array([x, 0.0, 1.0]), np.array([1.05 * x, 1.0, 1.0])), image=f"l{i}")
            for i, x in enumerate(np.linspace(-1.0, 1.0, 9))]
    point = viewing_axes_center(line)
    assert 1.0 < point[1] < 2.5 and abs(point[0]) < 1e-6


@pytest.mark.parametrize("dtype", [np.float32, np.uint8])
def test_insert_object(dtype):
    cams = _ring_cameras()
    rng = np.random.default_rng(0)
    photos = [rng.uniform(0, 1, (48, 64, 3)).astype(np.float32) for _ in cams]
    if dtype == np.uint8:
        photos = [np.round(p * 255).astype(np.uint8) for p in photos]
    out, masks = insert_object(photos, cams, seed=1)
    assert len(out) == len(masks) == len(cams)
    for p, o, m in zip(photos, out, masks):
        assert o.dtype == dtype and o.shape == p.shape and m.dtype == bool
        assert 0 < m.sum() < m.size // 2
        assert np.array_equal(o[~m], p[~m])  # untouched outside
        changed = np.any(o != p, axis=-1)
        assert not np.any(changed & ~m)
        assert changed[m].mean() > 0.95  # the pasted pixels are (almost all) new colours
    # deterministic, inputs untouched
    out2, masks2 = insert_object(photos, cams, seed=1)
    assert all(np.array_equal(a, b) for a, b in zip(out, out2))
    assert all(np.array_equal(a, b) for a, b in zip(masks, masks2))
    # explicit position/size: a bigger object covers more pixels
    _, big = insert_object(photos, cams, position=[0, 0, 0], size=1.5)
    assert big[0].sum() > masks[0].sum()


def test_insert_object_matches_synthetic_geometry():
    # inserting into synthetic ground-truth photos reproduces a mask consistent with ray casting depth
    sc = generate_scene(SceneParams(seed=2, **SMALL))
    imgs = list(sc.images_gt)
    out, masks = insert_object(imgs, sc.cameras, seed=0, position=sc.object_bounds.mean(0), size=0.3)
    assert all(m.any() for m in masks)
    with pytest.raises(PipelineError, match="expected"):
        insert_object([imgs[0][:10]], sc.cameras[:1])


def test_rug_texture_sets_the_rugs_pattern_only():
    from sgpor_pipeline.synthetic import SceneParams, generate_scene

    small = dict(seed=0, object_kind="box", n_views=4, width=64, height=48)
    drawn = generate_scene(SceneParams(**small))
    coins = generate_scene(SceneParams(**small, rug_texture="coins"))
    np.testing.assert_array_equal(coins.object_bounds, drawn.object_bounds)  # the rest of the scene stays
    assert not np.array_equal(coins.images_gt, drawn.images_gt)
    np.testing.assert_array_equal(coins.images_gt[:, :8], drawn.images_gt[:, :8])  # the far wall, above the rug
    with pytest.raises(ValueError, match="rug_texture"):
        generate_scene(SceneParams(**small, rug_texture="tiles"))
