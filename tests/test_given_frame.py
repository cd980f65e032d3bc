"""Given cameras in a frame the float32 fit cannot work in: georeferenced (millions of units from the
origin) or at kilometre scale. The sfm stage moves them (``sfm.conditioning_frame``); the fit then
works as in a plain frame, the export keeps the given cameras' units and ``render`` takes camera files
in the given frame.

One tiny scene (8 views of 64x48, short fits) is run twice, once with its own cameras and once with
the same cameras 0.001 times as large and 4 million units from the origin (~20 s together).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from sgpor_pipeline.dag import RunInputs
from sgpor_pipeline.imageio import read_image
from sgpor_pipeline.orientation import ExportFrame, Similarity
from sgpor_pipeline.render import align_cameras, render_run
from sgpor_pipeline.runner import run_pipeline
from sgpor_pipeline.scene import Camera, load_cameras, save_cameras
from sgpor_pipeline.sfm import conditioning_frame, given_frame, load_sfm
from sgpor_pipeline.synthetic import SceneParams, generate_scene, save_scene

# (the export frame from the cameras alone: up from their x axes, origin at their look-at point; the
# tiny fits' ground planes differ from run to run)
FAST = ["fit.iterations=150", "fit.eval_every=0", "finetune.iterations=10", 'export.formats=["ply", "cameras"]',
        'export.up="cameras"', 'export.origin="center"']
# UTM-like: 0.001 of the scene's own units (kilometres for metres), half a million east, 4 million north
GEO = Similarity(1e-3, np.eye(3), [5.0e5, 4.0e6, 50.0])


def _cams(cams: list[Camera], sim: Similarity) -> list[Camera]:
    return [sim.camera(c) for c in cams]


def _fit_psnr(result) -> float:
    return json.loads((result.path("fit") / "fit.json").read_text())["heldout_psnr"]


def _export_frame(out) -> ExportFrame:
    return ExportFrame.from_dict(json.loads((out / "export" / "export_frame.json").read_text()))


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("given_frame")
    scene = generate_scene(SceneParams(seed=1, rig="forward", n_views=8, width=64, height=48))
    folder = save_scene(scene, root / "scene")
    runs = {}
    for name, sim in (("plain", Similarity()), ("geo", GEO)):
        save_cameras(root / f"{name}.json", _cams(list(scene.cameras), sim))
        inputs = RunInputs(images=folder / "images", masks=folder / "masks", cameras=root / f"{name}.json")
        runs[name] = (root / name, run_pipeline(root / name, inputs, overrides=FAST))
    return scene, runs


def test_conditioning_frame_moves_only_frames_the_fit_cannot_use():
    def ring(radius: float, center) -> list[Camera]:
        K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
        out = []
        for i in range(6):
            c = np.asarray(center, float) + radius * np.array([np.cos(i), np.sin(i), 0.1 * i])
            T = np.eye(4)
            T[:3, 3] = -c
            out.append(Camera(f"v{i}", 64, 48, K, T, image=f"v{i}"))
        return out

    assert conditioning_frame(ring(1.0, [3.0, -2.0, 1.0])) is None  # an ordinary frame is kept
    assert conditioning_frame(ring(500.0, [0.0, 0.0, 0.0])) is None  # (metres of a large site: kept)
    sim, why = conditioning_frame(ring(1.0, [5e5, 4e6, 30.0]))  # UTM: moved to the cameras' centre only
    assert sim.s == 1.0 and "from their origin" in why
    centers = np.array([sim.camera(c).center for c in ring(1.0, [5e5, 4e6, 30.0])])
    assert np.abs(centers.mean(0)).max() < 1e-6
    sim, why = conditioning_frame(ring(0.002, [0.1, 0.2, 0.0]))  # kilometres: scaled by a power of ten
    assert sim.s == pytest.approx(1000.0) and "scaled by 1000" in why
    sim, _ = conditioning_frame(ring(3e4, [0.0, 0.0, 0.0]))  # millimetres of a large site
    assert sim.s == pytest.approx(1e-4)
    # cameras at one point (a panorama) far from the origin: moved, not scaled
    sim, _ = conditioning_frame(ring(0.0, [1e6, 0, 0]))
    assert sim.s == 1.0 and np.allclose(sim.t, [-1e6, 0, 0])


def test_georeferenced_kilometre_cameras_fit_as_in_their_own_frame(two_runs):
    _, runs = two_runs
    plain, geo = runs["plain"][1], runs["geo"][1]
    assert given_frame(plain.path("sfm")) is None
    moved = given_frame(geo.path("sfm"))
    assert moved is not None and np.log10(moved.s) == pytest.approx(round(np.log10(moved.s)))  # a power of ten
    # the run's frame is the given one moved and scaled: the cameras, and the points on the surfaces
    run_from_plain = Similarity(moved.s * GEO.s, np.eye(3), moved.apply(GEO.t))
    sfm_plain, sfm_geo = load_sfm(plain.path("sfm")), load_sfm(geo.path("sfm"))
    for a, b in zip(sfm_plain.cameras, sfm_geo.cameras):
        # (float64 keeps 1e-9 of 4e6 given units, 1e-5 in the run's frame)
        np.testing.assert_allclose(run_from_plain.camera(a).cam_from_world, b.cam_from_world, atol=1e-4)
    centers = np.array([c.center for c in sfm_geo.cameras])
    assert 1.0 <= np.sqrt(((centers - centers.mean(0)) ** 2).sum(1).mean()) < 10.0
    assert abs(len(sfm_geo.points) - len(sfm_plain.points)) <= 0.05 * len(sfm_plain.points)
    # the fit works as in the plain frame (float32 kept half a unit at 4e6, and the rasterizer's near
    # plane of 0.01 units culled a whole kilometre-scale scene: 9.6 dB on the demo scene)
    assert _fit_psnr(geo) > _fit_psnr(plain) - 0.5, (_fit_psnr(geo), _fit_psnr(plain))


def test_the_export_keeps_the_given_cameras_units(two_runs):
    _, runs = two_runs
    (plain_out, plain), geo_out = runs["plain"], runs["geo"][0]
    fp, fg = _export_frame(plain_out), _export_frame(geo_out)
    assert fp.given is None and fg.given is not None and not fg.metric
    assert fg.transform.s * fg.given.s == pytest.approx(fp.transform.s, rel=1e-9)  # the given units
    # the given cameras land where the plain run puts them, a thousand times smaller
    cams = load_cameras(plain.path("sfm") / "cameras.json")
    export_plain = np.array([fp.transform.apply(c.center) for c in cams])
    export_geo = np.array([fg.transform.apply(fg.given.apply(GEO.apply(c.center))) for c in cams])
    assert np.abs(export_geo / GEO.s - export_plain).max() < 1e-4 * np.abs(export_plain).max()


def test_render_takes_cameras_in_the_given_frame(two_runs, tmp_path):
    scene, runs = two_runs
    plain_out, (geo_out, geo) = runs["plain"][0], runs["geo"]
    novel = [Camera(f"n{i}", c.width, c.height, c.K, c.cam_from_world, image=None)
             for i, c in enumerate(scene.cameras[:2])]  # no shared names: nothing to align on
    save_cameras(tmp_path / "plain.json", novel)
    save_cameras(tmp_path / "geo.json", _cams(novel, GEO))
    ra = render_run(plain_out, tmp_path / "plain.json", tmp_path / "ra")
    rb = render_run(geo_out, tmp_path / "geo.json", tmp_path / "rb")
    assert ra.alignment.method == "none" and rb.alignment.method == "given"
    for a, b in zip(sorted(ra.files), sorted(rb.files)):
        ia, ib = read_image(a), read_image(b)
        assert ia.std() > 0.05 and np.abs(ia - ib).mean() < 0.03, (a.name, np.abs(ia - ib).mean())
    # --align none still means the run's own frame
    assert align_cameras(_cams(novel, GEO), load_sfm(geo.path("sfm")).cameras, "none").method == "none"
