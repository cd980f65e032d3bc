"""The plane under an object as one texture (sgpor_pipeline.removal.plane), on analytic views of a
textured floor: exact cameras, exact depth, colours known at every point of the plane."""

from __future__ import annotations

import numpy as np
import pytest

from sgpor_pipeline.removal.plane import (
    PlaneParams,
    fit_plane,
    footprint,
    plane_camera,
    plane_texture,
    sample_into_view,
)
from sgpor_pipeline.scene import Camera
from sgpor_pipeline.synthetic import look_at

W, H = 160, 120
FLOOR_Z = 0.2  # the floor z = 0.2 (not through the origin)


def floor_colour(p: np.ndarray) -> np.ndarray:
    """A smooth colour field on the floor (no aliasing at any footprint used here)."""
    x, y = p[:, 0], p[:, 1]
    return np.stack([0.5 + 0.4 * np.sin(3 * x), 0.5 + 0.4 * np.cos(2 * y), 0.5 + 0.2 * np.sin(x + y)], 1)


def floor_view(name: str, eye) -> tuple[Camera, np.ndarray, np.ndarray]:
    """A camera at ``eye`` looking at the floor's origin: (camera, image, z-depth), the floor everywhere."""
    K = np.array([[140.0, 0, W / 2], [0, 140.0, H / 2], [0, 0, 1]])
    cam = Camera(name, W, H, K, look_at(np.asarray(eye, float), np.array([0.0, 0.0, FLOOR_Z])), image=name)
    ys, xs = np.mgrid[0:H, 0:W]
    rays = np.stack([(xs.ravel() + 0.5 - K[0, 2]) / K[0, 0], (ys.ravel() + 0.5 - K[1, 2]) / K[1, 1],
                     np.ones(W * H)], 1)
    R = cam.cam_from_world[:3, :3]
    dirs = rays @ R  # world directions with unit z in the camera
    t = (FLOOR_Z - cam.center[2]) / dirs[:, 2]  # = the z-depth (camera z of the ray is 1 per unit t)
    pts = cam.center + t[:, None] * dirs
    return cam, floor_colour(pts).reshape(H, W, 3).astype(np.float32), t.reshape(H, W).astype(np.float32)


def disc_in_view(cam: Camera, depth: np.ndarray, centre, radius: float) -> np.ndarray:
    """The view's pixels whose floor point lies within ``radius`` of ``centre`` (x, y)."""
    ys, xs = np.mgrid[0:H, 0:W]
    pts = cam.unproject(ys.ravel(), xs.ravel(), depth.ravel())
    return (np.hypot(pts[:, 0] - centre[0], pts[:, 1] - centre[1]) < radius).reshape(H, W)


@pytest.fixture(scope="module")
def views():
    return [floor_view(f"v{i}", eye) for i, eye in enumerate([(0.0, -2.5, 2.0), (2.2, 0.5, 1.8),
                                                                (-1.5, 1.8, 2.4)])]


def test_fit_plane_trims_outliers_and_faces_the_cameras():
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-1, 1, (500, 2)), FLOOR_Z + rng.normal(0, 1e-3, 500)]
    pts[:20, 2] += 0.5  # outliers above the floor
    plane = fit_plane(pts, centers=np.array([[0.0, 0.0, 3.0]]))
    assert np.allclose(plane.normal, [0, 0, 1], atol=1e-2)  # towards the camera above
    assert abs(plane.offset + FLOOR_Z) < 1e-2 and plane.rms < 3e-3
    assert not plane.kept[:20].any() and plane.kept[20:].mean() > 0.9
    below = fit_plane(pts, centers=np.array([[0.0, 0.0, -3.0]]))
    assert np.allclose(below.normal, [0, 0, -1], atol=1e-2)
    assert fit_plane(pts[:2], np.zeros((1, 3))) is None


def test_the_plane_camera_sees_the_plane_without_foreshortening():
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(-1, 1, 400), rng.uniform(-0.3, 0.3, 400), np.full(400, FLOOR_Z)]
    plane = fit_plane(pts, np.array([[0.0, 0.0, 2.0]]))
    cam = plane_camera(plane, height=2.0, texel=0.01, max_size=1000, margin=0.5)
    uv, z = cam.project(pts)
    assert np.allclose(z, 2.0, atol=1e-9)  # fronto-parallel: one depth
    # a similarity: distances on the plane scale by 1 / texel everywhere
    d_img = np.linalg.norm(uv[1:] - uv[:-1], axis=1)
    d_world = np.linalg.norm(pts[1:] - pts[:-1], axis=1)
    assert np.allclose(d_img, d_world / 0.01, rtol=1e-6)
    assert (uv >= 0).all() and (uv[:, 0] <= cam.width).all() and (uv[:, 1] <= cam.height).all()
    # x along the points' long side: 2 m of points + 2 x 0.5 x 2 m margin at 1 cm; y 0.6 m + 2 m
    assert 395 <= cam.width <= 401 and 255 <= cam.height <= 261, (cam.width, cam.height)
    small = plane_camera(plane, height=2.0, texel=0.001, max_size=256, margin=0.5)
    assert max(small.width, small.height) <= 257  # the texel is coarsened to fit


def test_footprint_grows_with_distance_and_slant(views):
    cam = views[0][0]
    n = np.array([0.0, 0.0, 1.0])
    near, far = np.array([[0.0, -1.0, FLOOR_Z]]), np.array([[0.0, 1.0, FLOOR_Z]])
    assert footprint(cam, far, n)[0] > footprint(cam, near, n)[0] > 0


def test_plane_texture_mosaics_the_views_and_leaves_the_common_hole(views):
    """Each view misses a disc of the floor that another view sees; a smaller disc no view sees is the
    texture's hole. Seen texels carry the floor's colours; filled and sampled back into a view, the
    texture gives that view's own colours on the floor."""
    cams = [v[0] for v in views]
    images = [v[1] for v in views]
    depths = [v[2] for v in views]
    common = [disc_in_view(c, d, (0.0, 0.0), 0.25) for c, d in zip(cams, depths)]
    own = [disc_in_view(c, d, (0.3 * np.cos(k), 0.3 * np.sin(k)), 0.25) for k, (c, d) in enumerate(zip(cams, depths))]
    holes = [a | b for a, b in zip(common, own)]
    tex, why = plane_texture(cams, images, [~h for h in holes], depths, holes, PlaneParams(), depth_tol=0.01)
    assert tex is not None, why
    assert tex.info["rms_relative"] < 1e-4 and tex.info["views_used"] == 3
    vc = tex.camera
    ys, xs = np.nonzero(tex.seen)
    world = vc.unproject(ys, xs, tex.depth[ys, xs])
    assert np.allclose(world[:, 2], FLOOR_Z, atol=1e-6)
    err = np.abs(tex.image[ys, xs] - floor_colour(world)).mean()
    assert err < 0.01, err
    # the hole: the common disc (no view saw it), not the views' own discs (another view saw each)
    hy, hx = np.nonzero(tex.hole)
    hw = vc.unproject(hy, hx, tex.depth[hy, hx])
    r = np.hypot(hw[:, 0], hw[:, 1])
    assert len(r) > 0 and np.percentile(r, 95) < 0.27
    ry, rx = np.nonzero(~tex.hole)
    rw = vc.unproject(ry, rx, tex.depth[ry, rx])
    assert not (np.hypot(rw[:, 0], rw[:, 1]) < 0.2).any()  # the centre of the common disc is all hole
    # a texture filled with the true colours, sampled into each view's hole, gives its true colours
    ty, tx = np.mgrid[0:vc.height, 0:vc.width]
    truth = floor_colour(vc.unproject(ty.ravel(), tx.ravel(), tex.depth.ravel())).reshape(vc.height, vc.width, 3)
    for cam, image, depth, hole in zip(cams, images, depths, holes):
        col, got = sample_into_view(truth.astype(np.float32), vc, tex.depth, tex.plane.normal, cam, depth, hole)
        assert got[hole].mean() > 0.99 and not (got & ~hole).any()
        assert np.abs(col[got] - image[got]).mean() < 0.01


def test_plane_texture_refuses_points_off_one_plane(views):
    """Holes on two different planes (a floor and a wall-like step 40 % of the way to the cameras)."""
    cams = [v[0] for v in views]
    depths = [v[2].copy() for v in views]
    holes = []
    for d in depths:
        h = np.zeros((H, W), bool)
        h[40:80, 30:130] = True
        d[40:80, 80:130] *= 0.6
        holes.append(h)
    tex, why = plane_texture(cams, [v[1] for v in views], [~h for h in holes], depths, holes, PlaneParams())
    assert tex is None and "one plane" in why
