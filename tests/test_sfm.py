"""The sfm stage through the real pipeline runner, on synthetic scenes with exact ground truth.

Scenes: ``sgpor_pipeline.synthetic`` forward-facing rig (LLFF-like), 16 views at 256x192. The inward
360-degree rig is not used here: its room repeats each wall texture several times, and at this
resolution SfM matches the repeats and registers some views flipped (a property of that test scene,
not of the stage; forward-facing views reconstruct reliably).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from sgpor_pipeline.dag import RunInputs
from sgpor_pipeline.errors import PipelineError
from sgpor_pipeline.imageio import read_mask, read_rgb8
from sgpor_pipeline.orientation import umeyama
from sgpor_pipeline.runner import run_pipeline
from sgpor_pipeline.scene import Camera, load_cameras, save_cameras
from sgpor_pipeline.sfm import (
    RAW_CAMERAS_FILE,
    RETRIEVAL_DESCRIPTORS,
    RETRIEVAL_DESCRIPTORS_PER_WORD,
    SfmParams,
    choose_matcher,
    database_stats,
    has_distortion,
    load_sfm,
    photo_to_view,
    to_colmap_camera,
    undistort_mask,
    undistort_options,
)
from sgpor_pipeline.synthetic import SceneParams, generate_scene, save_scene

# seed 1: a forward rig whose views all register; any seed works, a fixed one keeps the test exact
SCENE = SceneParams(seed=1, rig="forward", n_views=16, width=256, height=192)


# --------------------------------------------------------------------------------------------------
# helpers


def scene_extent(scene) -> float:
    """Diameter of the true camera centres together with the object the cameras look at.

    Why not the camera centres alone: a forward-facing rig spans ~1 m while it looks at content ~2 m
    away, and SfM's position error grows with the scene depth (depth error ~ z^2 / (f * baseline)), so
    the camera spread alone would judge the reconstruction against the rig's width rather than the
    scene's size. Including the observed object makes the extent the size of the captured scene.
    """
    pts = np.vstack([[c.center for c in scene.cameras], scene.object_bounds.mean(0)])
    return float(np.max(np.linalg.norm(pts[:, None] - pts[None], axis=-1)))


def distance_to_geometry(scene, xyz: np.ndarray) -> np.ndarray:
    """Unsigned distance of points to the true surfaces (background and object meshes)."""
    import open3d as o3d

    rs = o3d.t.geometry.RaycastingScene()
    for mesh in (scene.background_mesh, scene.object_mesh):
        rs.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return rs.compute_distance(o3d.core.Tensor(np.asarray(xyz, np.float32))).numpy()


def render_object_mask(scene, cam: Camera) -> np.ndarray:
    """Exact object mask of ``cam`` (world frame of the scene) by ray casting the true meshes."""
    import open3d as o3d

    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(scene.background_mesh))
    obj_id = rs.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(scene.object_mesh))
    u, v = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)  # pixel centres
    d = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], 1) @ np.linalg.inv(cam.K).T
    d = d @ cam.cam_from_world[:3, :3]  # camera -> world directions
    rays = np.hstack([np.broadcast_to(cam.center, d.shape), d]).astype(np.float32)
    ids = rs.cast_rays(o3d.core.Tensor(rays))["geometry_ids"].numpy()
    return (ids == obj_id).reshape(cam.height, cam.width)


def aligned_camera(cam: Camera, s: float, R: np.ndarray, t: np.ndarray) -> Camera:
    """An SfM camera moved into the true world frame by the similarity world_true = s R x + t."""
    T = np.eye(4)
    Rc = cam.cam_from_world[:3, :3] @ R.T
    T[:3, :3] = Rc
    T[:3, 3] = -Rc @ (s * R @ cam.center + t)
    return Camera(cam.name, cam.width, cam.height, cam.K, T, cam.image)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max(1, (a | b).sum()))


def run_sfm(out: Path, overrides: tuple[str, ...] = (), **inputs) -> tuple:
    result = run_pipeline(out, RunInputs(**inputs), overrides=list(overrides), until="sfm")
    return result, load_sfm(result.path("sfm"))


# --------------------------------------------------------------------------------------------------
# fixtures (module scope: each scene is generated and reconstructed once)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    scene = generate_scene(SCENE)
    folder = save_scene(scene, tmp_path_factory.mktemp("scene"))
    return scene, folder


@pytest.fixture(scope="module")
def sfm_run(scene_dir, tmp_path_factory):
    scene, folder = scene_dir
    out = tmp_path_factory.mktemp("run")
    result, sfm = run_sfm(out, images=folder / "images", masks=folder / "masks")
    return scene, folder, out, result, sfm


# --------------------------------------------------------------------------------------------------
# SfM path


def test_sfm_recovers_cameras(sfm_run):
    scene, _, _, result, sfm = sfm_run
    assert result.ran == ["ingest", "sfm"]
    assert sfm.summary["mode"] == "sfm" and sfm.summary["matcher"] == "exhaustive"
    assert sfm.summary["registered"] == len(scene.cameras) and sfm.summary["unregistered"] == []
    assert [c.image for c in sfm.cameras] == scene.names  # ingest's order, view names
    true = {c.name: c for c in scene.cameras}
    est = np.array([c.center for c in sfm.cameras])
    gt = np.array([true[c.image].center for c in sfm.cameras])
    sim = umeyama(est, gt)
    s, R, t = sim.s, sim.R, sim.t
    err = np.linalg.norm(s * est @ R.T + t - gt, axis=1)
    assert err.max() < 0.01 * scene_extent(scene), (err.max(), scene_extent(scene))
    # orientations too: R_est R^T should equal the true rotation (angle of the difference)
    for cam in sfm.cameras:
        Rd = (cam.cam_from_world[:3, :3] @ R.T) @ true[cam.image].cam_from_world[:3, :3].T
        assert np.degrees(np.arccos(np.clip((np.trace(Rd) - 1) / 2, -1, 1))) < 1.0
    # intrinsics: PINHOLE, focal within 2 % of the true one
    for cam in sfm.cameras:
        assert cam.model == "PINHOLE" and cam.distortion == []
        assert abs(cam.K[0, 0] / true[cam.image].K[0, 0] - 1) < 0.02


def test_sfm_outputs_layout_and_points(sfm_run):
    scene, _, _, result, sfm = sfm_run
    folder = result.path("sfm")
    for name in ("sparse/cameras.bin", "sparse/images.bin", "sparse/points3D.bin", "cameras.json",
                 "points.npz", "sfm.json"):
        assert (folder / name).is_file(), name
    assert not (folder / "colmap").exists() and not (folder / "stereo").exists()
    notes = json.loads((folder / "manifest.json").read_text())["notes"]
    assert notes["registered"] == len(scene.cameras) and set(notes["seconds"]) >= {"extract", "match", "map"}
    assert sfm.summary["mapping_retry"] is None  # everything registered: no second mapping
    # the raw cameras (SfM's SIMPLE_RADIAL) map ingest's photos onto the undistorted images
    raw = {c.image: c for c in load_cameras(folder / RAW_CAMERAS_FILE)}
    assert set(raw) == {c.image for c in sfm.cameras} and raw[sfm.cameras[0].image].model == "SIMPLE_RADIAL"
    for cam in sfm.cameras[:3]:
        photo = read_rgb8(next((result.path("ingest") / "images").glob(f"{cam.image}.*")))
        np.testing.assert_array_equal(photo_to_view(photo, raw[cam.image]), read_rgb8(sfm.image_path(cam.image)))
    # a correct model agrees with every image's strongest pairs: nothing to repair
    check = sfm.summary["pair_check"]
    assert check["checked"] >= len(scene.cameras) and check["contradicted"] == [] and check["repair"] is None
    for cam in sfm.cameras:
        img = read_rgb8(sfm.image_path(cam.image))
        assert img.shape == (cam.height, cam.width, 3)
    p = sfm.points
    assert len(p) > 300 and p.xyz.dtype == np.float64 and p.rgb.dtype == np.uint8
    assert p.xyz.shape == (len(p), 3) and p.rgb.shape == (len(p), 3) and p.error.shape == (len(p),)
    assert p.obs_point.shape == p.obs_view.shape == (len(p.obs_xy),) and p.obs_xy.shape[1] == 2
    assert p.obs_point.max() < len(p) and 0 <= p.obs_view.min() and p.obs_view.max() < len(sfm.cameras)
    # observations reproject onto their pixels: checks the obs arrays, K, poses and pixel convention
    K = np.stack([sfm.cameras[v].K for v in p.obs_view])
    T = np.stack([sfm.cameras[v].cam_from_world for v in p.obs_view])
    Xc = np.einsum("mij,mj->mi", T[:, :3, :3], p.xyz[p.obs_point]) + T[:, :3, 3]
    uv = np.einsum("mij,mj->mi", K, Xc)
    uv = uv[:, :2] / uv[:, 2:]
    reproj = np.linalg.norm(uv - p.obs_xy, axis=1)
    assert np.median(reproj) < 1.0 and reproj.max() < 8.0


def test_sfm_masks_undistorted_and_aligned(sfm_run):
    scene, _, _, _, sfm = sfm_run
    true = {c.name: c for c in scene.cameras}
    est = np.array([c.center for c in sfm.cameras])
    sim = umeyama(est, np.array([true[c.image].center for c in sfm.cameras]))
    s, R, t = sim.s, sim.R, sim.t
    ious = []
    for cam in sfm.cameras:
        path = sfm.mask_path(cam.image)
        assert path is not None, cam.image  # every synthetic view has a mask
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        assert raw.shape == (cam.height, cam.width) and set(np.unique(raw)) <= {0, 1}
        mask = raw.astype(bool)
        # ground truth: the true object seen by the estimated (aligned) camera. Agreement means mask,
        # image, K and pose all describe the same pixels.
        expect = render_object_mask(scene, aligned_camera(cam, s, R, t))
        if expect.sum() < 200:  # the object barely in view: IoU is dominated by its outline
            continue
        # 0.9 tolerates the SfM pose error (a 1 px shift of this ~85 px object costs ~0.025); the exact
        # undistortion mapping of masks is checked in test_known_distorted_cameras_are_undistorted
        ious.append(iou(mask, expect))
        assert ious[-1] > 0.9, (cam.image, ious[-1])
    assert len(ious) >= len(sfm.cameras) // 2 and np.mean(ious) > 0.95


def test_retrieval_matching_any_name_order(scene_dir, tmp_path):
    """Retrieval matching (auto's choice beyond 50 photos) pairs each photo with its most similar ones by a
    vocabulary tree built from the scene's own features: the photos' names in shuffled order register at
    the right poses from a fraction of the pairs."""
    scene, folder = scene_dir
    images = tmp_path / "shuffled"
    images.mkdir()
    order = np.random.default_rng(3).permutation(len(scene.names))
    renamed = {}  # new view name -> true view name
    for k, i in enumerate(order):
        src = next((folder / "images").glob(f"{scene.names[i]}.*"))
        renamed[f"p{k:02d}"] = scene.names[i]
        (images / f"p{k:02d}{src.suffix}").write_bytes(src.read_bytes())
    k_near = 4
    result, sfm = run_sfm(tmp_path / "out", ("sfm.matcher=retrieval", f"sfm.retrieval_neighbours={k_near}",
                                             "sfm.keep_database=true"), images=images)
    assert sfm.summary["matcher"] == "retrieval" and sfm.summary["registered"] == len(scene.names)
    assert sfm.summary["retrieval"]["neighbours"] == k_near and sfm.summary["retrieval"]["words"] >= 16
    work = result.path("sfm") / "colmap"
    assert (work / "vocab_tree.bin").is_file()
    stats = database_stats(work / "database.db")
    n = len(scene.names)
    assert stats.with_matches == n and stats.verified_pairs <= n * k_near < n * (n - 1) // 2
    true = {c.name: c for c in scene.cameras}
    est = np.array([c.center for c in sfm.cameras])
    gt = np.array([true[renamed[c.image]].center for c in sfm.cameras])
    sim = umeyama(est, gt)
    err = np.linalg.norm(sim.s * est @ sim.R.T + sim.t - gt, axis=1)
    assert err.max() < 0.01 * scene_extent(scene), (err.max(), scene_extent(scene))


def test_sequential_matching_closes_loops(scene_dir, tmp_path):
    """Sequential matching pairs each photo with its next in name order; with ``sequential_loops`` (the
    default) every 10th photo is also matched with its most similar ones, however far in name order."""
    _, folder = scene_dir

    def largest_gap(loops: bool) -> int:
        result, sfm = run_sfm(tmp_path / f"out_{loops}", ("sfm.matcher=sequential", "sfm.sequential_overlap=2",
                                                          f"sfm.sequential_loops={str(loops).lower()}",
                                                          "sfm.keep_database=true"), images=folder / "images")
        assert (sfm.summary["retrieval"] or {}).get("loop_detection", False) == loops
        import pycolmap

        database = pycolmap.Database.open(result.path("sfm") / "colmap" / "database.db")
        try:
            order = {im.image_id: i for i, im in enumerate(sorted(database.read_all_images(), key=lambda im: im.name))}
            pair_ids, _ = database.read_two_view_geometries()
        finally:
            database.close()
        return max(abs(order[a] - order[b]) for a, b in map(pycolmap.pair_id_to_image_pair, pair_ids))

    assert largest_gap(False) <= 2 < 4 < largest_gap(True)


def test_vocab_tree_is_seeded(sfm_run, tmp_path):
    """The tree (its random subset and k-means) depends on the seed only: two builds give one file."""
    _, folder, _, _, _ = sfm_run
    from sgpor_pipeline.sfm import build_vocab_tree

    db = tmp_path / "db.db"
    import pycolmap

    pycolmap.Database.open(db).close()
    pycolmap.import_images(db, folder / "images")
    pycolmap.extract_features(db, folder / "images", device=pycolmap.Device.cpu)
    tree = build_vocab_tree(db, tmp_path / "a.bin", SfmParams(num_threads=2))
    a = tree.path.read_bytes()
    b = build_vocab_tree(db, tmp_path / "b.bin", SfmParams(num_threads=2)).path.read_bytes()
    assert a == b and len(a) > 1000
    # few descriptors (16 small photos): fewer words, each trained on RETRIEVAL_DESCRIPTORS_PER_WORD at least
    assert tree.descriptors < RETRIEVAL_DESCRIPTORS and tree.words == tree.descriptors // RETRIEVAL_DESCRIPTORS_PER_WORD
    c = build_vocab_tree(db, tmp_path / "c.bin", SfmParams(num_threads=2, seed=1)).path.read_bytes()
    assert c != a


def test_rerun_is_cache_hit(sfm_run):
    scene, folder, out, result, _ = sfm_run
    again = run_pipeline(out, RunInputs(images=folder / "images", masks=folder / "masks"), until="sfm")
    assert again.hits == ["ingest", "sfm"] and again.ran == []
    assert again.path("sfm") == result.path("sfm")
    # a changed sfm option is a new key (its database lives in the new build folder); ingest stays a hit
    changed = run_pipeline(out, RunInputs(images=folder / "images", masks=folder / "masks"), until="sfm",
                           overrides=["sfm.matcher=sequential"])
    assert changed.hits == ["ingest"] and changed.ran == ["sfm"]
    assert load_sfm(changed.path("sfm")).summary["matcher"] == "sequential"


class RecordedProgress:
    """A ``progress`` for the sfm functions that records each bar's total and how far it got."""

    def __init__(self):
        self.bars: dict[str, dict] = {}

    def __call__(self, iterable, total=None, desc=None):
        bar = self.bars.setdefault(desc, {"total": total, "count": 0})
        for item in iterable:
            bar["count"] += 1
            yield item


@pytest.mark.parametrize("matcher", ["exhaustive", "sequential"])
def test_sfm_shows_progress_of_pycolmaps_work(sfm_run, tmp_path, matcher):
    """Features, matched pairs, registered and undistorted images are counted while pycolmap works (from
    its database, its mapper's callbacks and the files it writes), each bar to its exact total here."""
    from sgpor_pipeline.sfm import estimate_cameras
    from sgpor_pipeline.views import load_views

    _, _, _, result, _ = sfm_run
    ingest = result.path("ingest")
    views = load_views(ingest)
    n = len(views)
    recorded = RecordedProgress()
    params = SfmParams(matcher=matcher, sequential_overlap=3, sequential_loops=False)
    summary = estimate_cameras(ingest, views, tmp_path / "a folder" / "sfm", params, progress=recorded)
    assert summary["registered"] == n
    bars = recorded.bars
    pairs = n * (n - 1) // 2 if matcher == "exhaustive" else None
    assert bars["sfm: features"] == {"total": n, "count": n}
    assert bars["sfm: matched pairs"]["count"] == bars["sfm: matched pairs"]["total"] > 0
    if pairs is not None:
        assert bars["sfm: matched pairs"]["total"] == pairs
    else:
        assert bars["sfm: matched pairs"]["total"] < n * (n - 1) // 2
    assert bars["sfm: registered images"] == {"total": n, "count": n}
    assert bars["sfm: undistorted images"] == {"total": n, "count": n}


@pytest.mark.parametrize("cameras", ["estimated", "known"])
def test_interrupted_sfm_keeps_its_features_and_matches(scene_dir, tmp_path, monkeypatch, cameras):
    """Ctrl-C after matching (here: in the mapping, or the known cameras' triangulation) leaves the COLMAP
    database in the stage's checkpoint folder; ``status`` says the stage will resume, and the same command
    starts from its features and matched pairs (COLMAP skips them: a pair matched twice would fail its
    database's unique key) and finishes the model."""
    import sgpor_pipeline.sfm as sfm_module
    from sgpor_pipeline.cache import CHECKPOINT, read_manifest
    from sgpor_pipeline.runner import pipeline_status

    _, folder = scene_dir
    n = len(list((folder / "images").iterdir()))
    inputs = {"images": folder / "images"}
    if cameras == "known":
        inputs["cameras"] = folder / "cameras.json"

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    step = "_map_with_retry" if cameras == "estimated" else "_known_reconstruction"
    original = getattr(sfm_module, step)
    monkeypatch.setattr(sfm_module, step, interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_sfm(tmp_path / "out", **inputs)
    kept = list((tmp_path / "out" / "cache" / "sfm").glob(f".tmp-*/{CHECKPOINT}/database.db"))
    assert len(kept) == 1
    sfm_row = next(r for r in pipeline_status(tmp_path / "out") if r.name == "sfm")
    assert sfm_row.state == "missing" and sfm_row.detail.startswith("interrupted: the same command resumes it")
    monkeypatch.setattr(sfm_module, step, original)
    result, sfm = run_sfm(tmp_path / "out", **inputs)
    assert sfm.summary["resumed"] == {"images_with_features": n, "matched_pairs": n * (n - 1) // 2}
    assert sfm.summary["registered"] == n and len(sfm.points) > 100
    assert read_manifest(result.path("sfm"))["resumed_from_checkpoint"] is True
    assert not (result.path("sfm") / CHECKPOINT).exists() and not (result.path("sfm") / "colmap").exists()
    assert not list((tmp_path / "out" / "cache" / "sfm").glob(".tmp-*"))


def test_interrupt_notice_logs_at_once_and_still_interrupts(caplog):
    import signal

    from sgpor_pipeline.sfm import interrupt_notice

    outer = signal.signal(signal.SIGINT, signal.default_int_handler)  # (a test worker may have another)
    try:
        with caplog.at_level(logging.WARNING), pytest.raises(KeyboardInterrupt), interrupt_notice("stopping soon"):
            signal.raise_signal(signal.SIGINT)
        assert "stopping soon" in caplog.text
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # the handler is put back
    finally:
        signal.signal(signal.SIGINT, outer)


def test_counted_progress_polls_adds_and_survives_failed_reads():
    import time

    from sgpor_pipeline.sfm import counted_progress

    recorded = RecordedProgress()
    with counted_progress(recorded, 5, "added", interval=0.01) as add:
        for _ in range(7):
            add(1)
    assert recorded.bars["added"] == {"total": 5, "count": 5}  # never beyond the total
    written, reads = [], []

    def flaky() -> int:  # as a database read that fails once while the writer works
        reads.append(1)
        if len(reads) == 2:
            raise RuntimeError("SQLite error: database is locked")
        return len(written)

    with counted_progress(recorded, None, "polled", poll=flaky, interval=0.01):
        for i in range(3):
            written.append(i)
            time.sleep(0.1)  # a few reads between the writes, the second of them failing
    assert recorded.bars["polled"] == {"total": None, "count": 3} and len(reads) >= 4


def test_blank_images_raise_clear_error(tmp_path):
    images = tmp_path / "blank"
    images.mkdir()
    for i, grey in enumerate((40, 90, 140, 200)):
        cv2.imwrite(str(images / f"b{i}.png"), np.full((192, 256, 3), grey, np.uint8))
    with pytest.raises(PipelineError) as info:
        run_pipeline(tmp_path / "out", RunInputs(images=images), until="sfm")
    err = info.value
    assert "could not reconstruct" in err.message and "0 had features" in err.message
    assert err.path == str(images) and "--cameras" in err.fix and "sfm.matcher=sequential" in err.fix
    assert not list((tmp_path / "out" / "cache" / "sfm").glob("*/manifest.json"))  # nothing published
    # retrieval matching (auto's choice beyond 50 photos) with no features for its tree: the same error
    with pytest.raises(PipelineError) as info:
        run_pipeline(tmp_path / "out", RunInputs(images=images), until="sfm", overrides=["sfm.matcher=retrieval"])
    assert "0 had features" in info.value.message and "sfm.retrieval_neighbours" in info.value.fix


def test_warns_when_few_images_register(scene_dir, tmp_path, caplog):
    scene, folder = scene_dir
    images = tmp_path / "images"
    images.mkdir()
    for name in scene.names[:12]:
        (images / f"{name}.png").write_bytes((folder / "images" / f"{name}.png").read_bytes())
    for i in range(4):  # textureless photos cannot register: 12 of 16 = 75 % < 80 %
        cv2.imwrite(str(images / f"zz_blank{i}.png"), np.full((192, 256, 3), 60 + 40 * i, np.uint8))
    with caplog.at_level(logging.WARNING, logger="sgpor_pipeline"):
        _, sfm = run_sfm(tmp_path / "out", images=images)
    assert sfm.summary["registered"] == 12
    assert sfm.summary["unregistered"] == [f"zz_blank{i}" for i in range(4)]
    # too few registered: mapped again with the distortion held, then with relaxed thresholds, then with
    # the global mapper; blank photos gain nothing from any
    assert sfm.summary["mapping_retry"] == {
        "registered": {"default": 12, "held_distortion": 12, "relaxed": 12, "global": 12}, "kept": "default"}
    assert all(not sfm.image_path(f"zz_blank{i}").exists() for i in range(4))
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any("only 12 of 16 images registered" in w and "zz_blank3" in w for w in warnings), warnings
    # resumed: the cached result's warning is shown again (a resumed run would otherwise hide it)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="sgpor_pipeline"):
        result, _ = run_sfm(tmp_path / "out", images=images)
    assert result.outcomes["sfm"].hit
    again = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any("only 12 of 16 images registered" in w and "logged when the cached result was built" in w
               for w in again), again
    from sgpor_pipeline.runner import pipeline_status

    rows = {r.name: r for r in pipeline_status(tmp_path / "out")}
    assert rows["sfm"].state == "hit" and rows["sfm"].detail.startswith("1 warning(s) when built")
    assert rows["ingest"].detail == ""


# --------------------------------------------------------------------------------------------------
# the model check against each image's strongest pairs (repeated textures)

# the demo's room: 24 inward views whose wrapped floor and rug textures give pairs of far-apart views
# false matches; with every pair, COLMAP returns a model that registers all 24 at 0.5 px but puts
# cameras far from where they were (a known failure, found with this very scene)
REPEATED = SceneParams(seed=0, rig="inward", n_views=24, width=256, height=192)


@pytest.fixture(scope="module")
def repeated_dir(tmp_path_factory):
    scene = generate_scene(REPEATED)
    return scene, save_scene(scene, tmp_path_factory.mktemp("repeated"))


def centre_errors(scene, sfm) -> np.ndarray:
    """Distance of each registered camera centre from the truth after the best similarity, over the
    scene's extent."""
    true = {c.name: c for c in scene.cameras}
    est = np.array([c.center for c in sfm.cameras])
    gt = np.array([true[c.image].center for c in sfm.cameras])
    sim = umeyama(est, gt)
    return np.linalg.norm(sim.apply(est) - gt, axis=1) / scene_extent(scene)


def test_pair_check_warns_about_a_wrong_model(repeated_dir, tmp_path, caplog):
    scene, folder = repeated_dir
    with caplog.at_level(logging.WARNING, logger="sgpor_pipeline"):
        _, sfm = run_sfm(tmp_path / "out", ("sfm.pair_check=warn",), images=folder / "images")
    # the failure is real: every photo registers, yet cameras sit far from the truth
    assert sfm.summary["registered"] == 24 and centre_errors(scene, sfm).max() > 0.3
    check = sfm.summary["pair_check"]
    assert check["repair"] is None and len(check["contradicted"]) >= 1
    assert all(c["agreement"] < 0.5 and c["inliers"] >= 15 for c in check["contradicted"])
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    first = check["contradicted"][0]["images"]
    assert any("contradict" in w and "--cameras" in w and f"{Path(first[0]).stem}-{Path(first[1]).stem}" in w
               for w in warnings), warnings


def test_pair_check_repairs_a_wrong_model(repeated_dir, tmp_path, caplog):
    scene, folder = repeated_dir
    with caplog.at_level(logging.INFO, logger="sgpor_pipeline"):
        _, sfm = run_sfm(tmp_path / "out", images=folder / "images")  # default: repair
    check = sfm.summary["pair_check"]
    assert check["repair"]["kept"] == "strongest_pairs" and check["repair"]["first"]["contradicted"] >= 1
    assert check["contradicted"] == [] and sfm.summary["registered"] == 24
    assert centre_errors(scene, sfm).max() < 0.02
    messages = [r.getMessage() for r in caplog.records]
    assert any("kept the model mapped on the strongest pairs only" in m for m in messages)
    assert not any(r.levelno == logging.WARNING and "contradict" in r.getMessage() for r in caplog.records)


def test_strongest_pairs_and_epipolar_distance():
    from sgpor_pipeline.sfm import _epipolar_distance, strongest_pairs

    m = [np.zeros((n, 2), np.int64) for n in (50, 40, 30, 20, 60)]
    pairs = [(1, 2, m[0]), (1, 3, m[1]), (2, 3, m[2]), (1, 4, m[3]), (3, 4, m[4])]
    # image 1: (1,2) 50, (1,3) 40; image 2: (1,2), (2,3); image 3: (3,4), (1,3); image 4: (3,4), (1,4)
    got = [(a, b) for a, b, _ in strongest_pairs(pairs, 2)]
    assert got == [(1, 2), (1, 3), (2, 3), (1, 4), (3, 4)]
    assert [(a, b) for a, b, _ in strongest_pairs(pairs, 1)] == [(1, 2), (3, 4)]
    assert [(a, b) for a, b, _ in strongest_pairs(pairs, 1, images={1, 3, 4})] == [(1, 3), (3, 4)]
    # exact correspondences of a relative pose lie on their epipolar lines; shifted ones do not
    rng = np.random.default_rng(0)
    X = rng.uniform([-1, -1, 3], [1, 1, 6], (40, 3))
    angle = np.radians(10)
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    b_from_a = np.c_[R, [0.5, 0.1, 0.0]]
    Xb = X @ R.T + b_from_a[:, 3]
    xa, xb = X[:, :2] / X[:, 2:], Xb[:, :2] / Xb[:, 2:]
    assert np.abs(_epipolar_distance(xa, xb, b_from_a)).max() < 1e-9
    shifted = _epipolar_distance(xa, xb + [0.0, 0.02], b_from_a)
    assert np.median(shifted) > 1e-3


# --------------------------------------------------------------------------------------------------
# known cameras


def test_known_cameras_imported_and_triangulated(scene_dir, tmp_path):
    scene, folder = scene_dir
    cams = load_cameras(folder / "cameras.json")
    novel = Camera("novel_000", 256, 192, cams[0].K, cams[3].cam_from_world, image=None)
    save_cameras(tmp_path / "cameras.json", [*cams, novel])
    result, sfm = run_sfm(tmp_path / "out", images=folder / "images", masks=folder / "masks",
                          cameras=tmp_path / "cameras.json")
    assert sfm.summary["mode"] == "known_cameras" and "map" not in sfm.summary["seconds"]
    # poses and intrinsics exactly as given (no pose estimation), novel camera carried through
    assert [c.name for c in sfm.cameras] == [*scene.names, "novel_000"]
    for got, want in zip(sfm.cameras, cams):
        assert got.image == want.name and got.model == "PINHOLE"
        np.testing.assert_allclose(got.cam_from_world, want.cam_from_world, atol=1e-12)
        np.testing.assert_allclose(got.K, want.K, atol=1e-12)
        assert sfm.mask_path(got.image) is not None
    assert sfm.cameras[-1].image is None
    np.testing.assert_allclose(sfm.cameras[-1].cam_from_world, novel.cam_from_world)
    assert sfm.points.obs_view.max() < len(scene.names)  # the novel camera has no observations
    # the true poses agree with the photos' strongest pairs
    assert sfm.summary["pair_check"]["checked"] >= len(scene.names) and sfm.summary["pair_check"]["contradicted"] == []
    # triangulated points lie on the true surfaces (no similarity alignment: same world frame)
    d = distance_to_geometry(scene, sfm.points.xyz)
    extent = scene_extent(scene)
    assert len(d) > 300
    assert np.median(d) < 0.01 * extent and np.mean(d < 0.05 * extent) > 0.85, (np.median(d), extent)


def test_known_cameras_that_contradict_the_photos_are_named(scene_dir, tmp_path, caplog):
    # two photos assigned to each other's cameras: the poses are kept (they are given), but the
    # photos' strongest pairs contradict them, and the warning names those photos and the fix
    scene, folder = scene_dir
    cams = load_cameras(folder / "cameras.json")
    a, b = 0, len(cams) // 2
    cams[a], cams[b] = (Camera(cams[a].name, 256, 192, cams[a].K, cams[b].cam_from_world, cams[a].image),
                        Camera(cams[b].name, 256, 192, cams[b].K, cams[a].cam_from_world, cams[b].image))
    save_cameras(tmp_path / "cameras.json", cams)
    with caplog.at_level(logging.WARNING, logger="sgpor_pipeline"):
        _, sfm = run_sfm(tmp_path / "out", images=folder / "images", cameras=tmp_path / "cameras.json")
    contradicted = sfm.summary["pair_check"]["contradicted"]
    named = {Path(n).stem for c in contradicted for n in c["images"]}
    assert named & {scene.names[a], scene.names[b]} and sfm.summary["pair_check"]["repair"] is None
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any("given cameras contradict" in w and "which photo each camera belongs to" in w for w in warnings)


def test_known_cameras_two_view_tracks_add_points_on_the_surfaces(scene_dir, tmp_path):
    """sfm.two_view_tracks: points seen in only two images are triangulated too (the poses are given),
    so there are more of them, and they still lie on the true surfaces."""
    scene, folder = scene_dir
    counts = {}
    for flag in (False, True):
        _, sfm = run_sfm(tmp_path / "out", (f"sfm.two_view_tracks={str(flag).lower()}",),
                         images=folder / "images", cameras=folder / "cameras.json")
        counts[flag] = len(sfm.points)
        d = distance_to_geometry(scene, sfm.points.xyz)
        assert np.median(d) < 0.01 * scene_extent(scene)
    assert counts[True] > counts[False] > 0, counts


def test_known_cameras_from_transforms_json(scene_dir, tmp_path):
    scene, folder = scene_dir
    _, sfm = run_sfm(tmp_path / "out", images=folder / "images", cameras=folder / "transforms.json")
    assert sfm.summary["mode"] == "known_cameras" and len(sfm.cameras) == len(scene.cameras)
    for got, want in zip(sfm.cameras, scene.cameras):
        np.testing.assert_allclose(got.cam_from_world, want.cam_from_world, atol=1e-9)
    assert np.median(distance_to_geometry(scene, sfm.points.xyz)) < 0.01 * scene_extent(scene)


def test_known_cameras_from_llff_poses_bounds(scene_dir, tmp_path):
    # an LLFF dataset folder (SPIn-NeRF's layout): poses_bounds.npy for the full-size photos in images/,
    # the run on half-size copies in images_2/
    scene, folder = scene_dir
    (tmp_path / "images").mkdir()
    (tmp_path / "images_2").mkdir()
    rows = []
    for cam in scene.cameras:
        rgb = read_rgb8(folder / "images" / f"{cam.name}.png")
        cv2.imwrite(str(tmp_path / "images" / f"{cam.name}.png"), cv2.resize(rgb, (512, 384))[..., ::-1])
        (tmp_path / "images_2" / f"{cam.name}.png").write_bytes((folder / "images" / f"{cam.name}.png").read_bytes())
        c2w = np.linalg.inv(cam.cam_from_world)
        hwf = [2 * cam.height, 2 * cam.width, 2 * cam.K[0, 0]]
        rows.append(np.r_[np.c_[c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2], c2w[:3, 3], hwf].ravel(), 0.5, 9.0])
    np.save(tmp_path / "poses_bounds.npy", np.stack(rows))
    _, sfm = run_sfm(tmp_path / "out", images=tmp_path / "images_2", cameras=tmp_path / "poses_bounds.npy")
    assert sfm.summary["mode"] == "known_cameras" and len(sfm.cameras) == len(scene.cameras)
    for got, want in zip(sfm.cameras, scene.cameras):
        np.testing.assert_allclose(got.cam_from_world, want.cam_from_world, atol=1e-9)
        np.testing.assert_allclose(got.K, want.K, atol=1e-9)
    assert sfm.summary["pair_check"]["contradicted"] == []


def _distort(img: np.ndarray, K: np.ndarray, dist: np.ndarray, interpolation: int) -> np.ndarray:
    """Render what an OPENCV-distorted camera with the same K sees, from an undistorted image."""
    h, w = img.shape[:2]
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)  # pixel centres, corner convention
    pts = np.stack([u.ravel(), v.ravel()], 1).reshape(-1, 1, 2)
    und = cv2.undistortPoints(pts, K, dist, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10))
    und = und.reshape(-1, 2)
    src = und @ K[:2, :2].T + K[:2, 2] - 0.5  # cv2.remap: integer = pixel centre
    mx, my = src[:, 0].reshape(h, w).astype(np.float32), src[:, 1].reshape(h, w).astype(np.float32)
    return cv2.remap(img, mx, my, interpolation, borderMode=cv2.BORDER_REFLECT)


def test_known_distorted_cameras_are_undistorted(scene_dir, tmp_path):
    """Distorted photos + an OPENCV camera file: images and masks come out PINHOLE and aligned."""
    scene, folder = scene_dir
    dist = np.array([-0.12, 0.02, 0.001, -0.001])
    (tmp_path / "images").mkdir()
    (tmp_path / "masks").mkdir()
    cams = []
    names = scene.names[:10]
    for cam in scene.cameras[:10]:
        rgb = read_rgb8(folder / "images" / f"{cam.name}.png")
        mask = read_mask(folder / "masks" / f"{cam.name}.png").astype(np.uint8) * 255
        distorted = _distort(rgb, cam.K, dist, cv2.INTER_CUBIC)
        cv2.imwrite(str(tmp_path / "images" / f"{cam.name}.png"), distorted[..., ::-1])
        cv2.imwrite(str(tmp_path / "masks" / f"{cam.name}.png"), _distort(mask, cam.K, dist, cv2.INTER_NEAREST))
        cams.append(Camera(cam.name, cam.width, cam.height, cam.K, cam.cam_from_world, cam.name,
                           model="OPENCV", distortion=dist.tolist()))
    save_cameras(tmp_path / "cameras.json", cams)
    _, sfm = run_sfm(tmp_path / "out", images=tmp_path / "images", masks=tmp_path / "masks",
                     cameras=tmp_path / "cameras.json")
    assert sfm.summary["undistorted"] == 10
    for cam, name in zip(sfm.cameras, names):
        assert cam.model == "PINHOLE" and cam.distortion == [] and cam.image == name
        true = scene.cameras[scene.names.index(name)]
        np.testing.assert_allclose(cam.cam_from_world, true.cam_from_world)
        # where each output pixel's ray lands in the original (undistorted) render
        u, v = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
        rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(cam.K).T
        src = rays[..., :2] / rays[..., 2:] @ true.K[:2, :2].T + true.K[:2, 2] - 0.5
        mx, my = src[..., 0].astype(np.float32), src[..., 1].astype(np.float32)
        inside = (mx > 2) & (my > 2) & (mx < true.width - 3) & (my < true.height - 3)
        assert inside.mean() > 0.8
        want = cv2.remap(scene.images[scene.names.index(name)], mx, my, cv2.INTER_LINEAR)
        got = read_rgb8(sfm.image_path(name)).astype(np.float32) / 255
        assert got.shape == want.shape
        assert np.abs(got - want)[inside].mean() < 0.03
        want_mask = cv2.remap(scene.masks[scene.names.index(name)].astype(np.uint8), mx, my,
                              cv2.INTER_NEAREST).astype(bool)
        got_mask = read_mask(sfm.mask_path(name))
        if want_mask[inside].sum() > 200:
            assert iou(got_mask & inside, want_mask & inside) > 0.95
    assert np.median(distance_to_geometry(scene, sfm.points.xyz)) < 0.01 * scene_extent(scene)
    # another image of a view (its ground truth, say) at the photo's size, or a scaled copy of it,
    # is mapped onto the undistorted view as the photo was
    raw = {c.image: c for c in load_cameras(sfm.folder / RAW_CAMERAS_FILE)}
    assert raw[names[0]].model == "OPENCV" and raw[names[0]].distortion == dist.tolist()
    photo = read_rgb8(tmp_path / "images" / f"{names[0]}.png")
    view = read_rgb8(sfm.image_path(names[0]))
    np.testing.assert_array_equal(photo_to_view(photo, raw[names[0]]), view)
    doubled = cv2.resize(photo, (2 * photo.shape[1], 2 * photo.shape[0]), interpolation=cv2.INTER_CUBIC)
    mapped = photo_to_view(doubled, raw[names[0]])
    assert mapped.shape == view.shape and np.abs(mapped.astype(float) - view).mean() < 3.0
    with pytest.raises(PipelineError, match="aspect ratio"):
        photo_to_view(photo[:, : photo.shape[1] // 2], raw[names[0]])


# --------------------------------------------------------------------------------------------------
# small units


def test_pycolmap_imported_first_is_a_clear_error():
    import subprocess
    import sys

    def run(code: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)

    for code in ("import pycolmap\nimport sgpor_pipeline", "import pycolmap, cv2\nimport sgpor_pipeline"):
        wrong = run(code)
        assert wrong.returncode != 0 and "must be imported before pycolmap" in wrong.stderr, wrong.stderr[-500:]
    # our order (cv2 loaded by sgpor_pipeline first): PNGs encode after pycolmap is loaded
    right = run("import sgpor_pipeline, pycolmap, cv2, numpy as np\n"
                "ok, buf = cv2.imencode('.png', np.zeros((64, 64, 3), np.uint8))\nassert ok and len(buf)")
    assert right.returncode == 0, right.stderr[-500:]


def test_mapping_attempts_and_their_options():
    from sgpor_pipeline.sfm import RELAXED_MAPPER, global_options, incremental_options, mapping_attempts

    default = incremental_options(SfmParams())
    relaxed = incremental_options(SfmParams(), "relaxed")
    held = incremental_options(SfmParams(), "held_distortion")
    for key, value in RELAXED_MAPPER.items():
        assert getattr(relaxed.mapper, key) == value and getattr(default.mapper, key) > value
        assert getattr(held.mapper, key) == getattr(default.mapper, key)  # held: COLMAP's thresholds
    assert default.ba_refine_extra_params and relaxed.ba_refine_extra_params and not held.ba_refine_extra_params
    with pytest.raises(ValueError, match="unknown mapping attempt"):
        incremental_options(SfmParams(), "loose")
    # the distortion is held before the thresholds are relaxed; a model without distortion skips it
    # ... and the global mapper last (it registers photos no incremental attempt reaches)
    assert mapping_attempts(SfmParams()) == ["default", "held_distortion", "relaxed", "global"]
    assert mapping_attempts(SfmParams(camera_model="SIMPLE_PINHOLE")) == ["default", "relaxed", "global"]
    assert mapping_attempts(SfmParams(retry_held_distortion=False, retry_relaxed=False,
                                      retry_global=False)) == ["default"]
    # the global mapper holds the distortion too (mip360 room: no model, then 24 of 24), but has no
    # incremental thresholds to relax
    assert mapping_attempts(SfmParams(mapper="global")) == ["default", "held_distortion"]
    assert mapping_attempts(SfmParams(mapper="global", camera_model="PINHOLE")) == ["default"]
    global_default, global_held = global_options(SfmParams()), global_options(SfmParams(), "held_distortion")
    assert global_default.mapper.bundle_adjustment.refine_extra_params
    assert not global_held.mapper.bundle_adjustment.refine_extra_params
    assert global_held.mapper.bundle_adjustment.refine_focal_length  # only the distortion is held
    with pytest.raises(ValueError, match="for the global mapper"):
        global_options(SfmParams(), "relaxed")


def test_no_model_fix_names_the_mapping_when_the_photos_match():
    from sgpor_pipeline.sfm import DatabaseStats, no_model_fix

    matched = DatabaseStats(images=24, with_features=24, with_matches=24, verified_pairs=261)
    fix = no_model_fix(SfmParams(mapper="global"), matched)
    assert "the global mapping failed" in fix and "sfm.mapper=incremental" in fix and "SIMPLE_PINHOLE" in fix
    assert "sfm.mapper=global" in no_model_fix(SfmParams(retry_global=False), matched)
    # the global mapper is the incremental mapper's last retry: not suggested again
    both = no_model_fix(SfmParams(), matched)
    assert "incremental and global mappings failed" in both and "sfm.mapper" not in both and "SIMPLE_PINHOLE" in both
    unmatched = DatabaseStats(images=24, with_features=24, with_matches=2, verified_pairs=1)
    assert "more overlap" in no_model_fix(SfmParams(), unmatched)


def test_mapping_retry_keeps_the_attempt_that_registers_most(monkeypatch, tmp_path):
    """The retry's bookkeeping (which attempts run, which models are kept); pycolmap's mapping itself is
    replaced by fixed numbers of registered images per attempt."""
    import sgpor_pipeline.sfm as sfm_module

    class Model:
        def __init__(self, registered: int):
            self.registered = registered

        def num_reg_images(self) -> int:
            return self.registered

    def run(counts: dict[str, int], params: SfmParams | None = None):
        params = params or SfmParams()
        ran = []

        def fake_map(db, image_dir, out, params, attempt="default", registered=None):
            ran.append(attempt)
            return {0: Model(counts[attempt])} if counts[attempt] else {}

        monkeypatch.setattr(sfm_module, "_map", fake_map)
        models, retry = sfm_module._map_with_retry(tmp_path / "db", tmp_path, tmp_path, params, 24,
                                                   sfm_module.Timings(logging.getLogger("test")))
        return ran, models[0].registered if models else 0, retry

    # room: the held distortion registers every photo; relaxing is not tried then
    ran, kept, retry = run({"default": 7, "held_distortion": 24, "relaxed": 17})
    assert ran == ["default", "held_distortion"] and kept == 24
    assert retry == {"registered": {"default": 7, "held_distortion": 24}, "kept": "held_distortion"}
    # still short after holding: relaxed next, the most registered kept, the earlier attempt on a tie
    ran, kept, retry = run({"default": 7, "held_distortion": 12, "relaxed": 17, "global": 9})
    assert ran == ["default", "held_distortion", "relaxed", "global"] and kept == 17
    assert retry["kept"] == "relaxed"
    _, kept, retry = run({"default": 7, "held_distortion": 15, "relaxed": 15, "global": 15})
    assert kept == 15 and retry["kept"] == "held_distortion"
    # relaxed enough: the global mapper is not tried
    ran, kept, _ = run({"default": 7, "held_distortion": 12, "relaxed": 20, "global": 24})
    assert ran == ["default", "held_distortion", "relaxed"] and kept == 20
    # every incremental attempt short: the global mapper's model, when it registers more
    ran, kept, retry = run({"default": 7, "held_distortion": 7, "relaxed": 12, "global": 24})
    assert ran[-1] == "global" and kept == 24 and retry["kept"] == "global"
    # no model at first: the retries can still find one
    _, kept, retry = run({"default": 0, "held_distortion": 0, "relaxed": 9, "global": 0})
    assert kept == 9 and retry["registered"] == {"default": 0, "held_distortion": 0, "relaxed": 9, "global": 0}
    # enough at first (20 of 24 >= 80 %): no retry
    ran, kept, retry = run({"default": 20, "held_distortion": 24, "relaxed": 24})
    assert ran == ["default"] and kept == 20 and retry is None
    ran, _, retry = run({"default": 7, "relaxed": 17, "global": 17}, SfmParams(camera_model="PINHOLE"))
    assert ran == ["default", "relaxed", "global"] and retry["kept"] == "relaxed"
    # the global mapper: no model, then every photo with the distortion held
    ran, kept, retry = run({"default": 0, "held_distortion": 24}, SfmParams(mapper="global"))
    assert ran == ["default", "held_distortion"] and kept == 24 and retry["kept"] == "held_distortion"

    # the repair's mapping (check_db given) ranks the attempts as the repair ranks models: fewer
    # contradicted strongest pairs first (a generated ring: relaxed 9 right, global 23 at wrong poses)
    contradicting = {2: 0, 9: 0, 23: 2}
    monkeypatch.setattr(sfm_module, "check_model_pairs", lambda db, model: sfm_module.PairCheck(
        24, [("a", "b", 50, 0.1)] * contradicting[model.registered]))

    def run_checked(counts: dict[str, int]):
        ran = []
        monkeypatch.setattr(sfm_module, "_map", lambda db, image_dir, out, params, attempt="default", registered=None:
                            ran.append(attempt) or ({0: Model(counts[attempt])} if counts[attempt] else {}))
        models, retry = sfm_module._map_with_retry(tmp_path / "db", tmp_path, tmp_path, SfmParams(), 24,
                                                   sfm_module.Timings(logging.getLogger("test")),
                                                   check_db=tmp_path / "full.db")
        return ran, models[0].registered, retry

    ran, kept, retry = run_checked({"default": 2, "held_distortion": 2, "relaxed": 9, "global": 23})
    assert ran == ["default", "held_distortion", "relaxed", "global"] and kept == 9
    assert retry["kept"] == "relaxed" and retry["contradicted"] == {"default": 0, "held_distortion": 0,
                                                                    "relaxed": 0, "global": 2}
    contradicting[23] = 0  # agreeing with its strongest pairs, the model with more photos is kept
    _, kept, retry = run_checked({"default": 2, "held_distortion": 2, "relaxed": 9, "global": 23})
    assert kept == 23 and retry["kept"] == "global"


def test_global_fallback_names_a_model_of_the_global_retry():
    from sgpor_pipeline.sfm import global_fallback

    base = {"mapper": "incremental", "registered": 29, "pair_check": None}
    kept_global = {"registered": {"default": 4, "held_distortion": 5, "relaxed": 15, "global": 29}, "kept": "global"}
    assert global_fallback({**base, "mapping_retry": kept_global}) == (15, 29)
    # not from the global retry: no note
    assert global_fallback({**base, "mapping_retry": None}) is None
    assert global_fallback({**base, "mapping_retry": {**kept_global, "kept": "relaxed"}}) is None
    assert global_fallback({**base, "mapper": "global", "mapping_retry": kept_global}) is None
    # the pair check's repair kept its own mapping: that mapping's retry decides
    repair = {"first": {"registered": 29, "contradicted": 3}, "kept": "strongest_pairs",
              "strongest_pairs": {"registered": 29, "contradicted": 0,
                                  "mapping_retry": {"registered": {"default": 12, "held_distortion": 20,
                                                                   "relaxed": 6, "global": 29}, "kept": "global"}}}
    assert global_fallback({**base, "mapping_retry": None, "pair_check": {"repair": repair}}) == (20, 29)
    repair_first = {**repair, "kept": "first"}
    assert global_fallback({**base, "mapping_retry": kept_global, "pair_check": {"repair": repair_first}}) == (15, 29)


def test_choose_matcher_and_params():
    p = SfmParams()
    assert (p.matcher, p.mapper, p.max_image_size, p.min_registered_fraction) == ("auto", "incremental", 1600, 0.8)
    assert choose_matcher(p, 50) == "exhaustive" and choose_matcher(p, 51) == "retrieval"
    assert choose_matcher(SfmParams(matcher="sequential"), 10) == "sequential"
    # too few photos matched: beyond 50 photos the fix names the retrieval's reach and exhaustive matching
    from sgpor_pipeline.sfm import DatabaseStats, no_model_fix

    fix = no_model_fix(p, DatabaseStats(images=60, with_features=60, with_matches=12, verified_pairs=9))
    assert "sfm.retrieval_neighbours=50" in fix and "sfm.matcher=exhaustive" in fix
    assert "sfm.retrieval_neighbours" not in no_model_fix(p, DatabaseStats(30, 30, 6, 4))


def test_colmap_camera_conversion_and_mask_undistortion():
    K = np.array([[200.0, 0, 128], [0, 200.0, 96], [0, 0, 1]])
    cam = Camera("a", 256, 192, K, np.eye(4), "a", model="SIMPLE_RADIAL", distortion=[-0.2])
    assert has_distortion(cam) and not has_distortion(Camera("b", 256, 192, K, np.eye(4), model="OPENCV",
                                                             distortion=[0, 0, 0, 0]))
    pc = to_colmap_camera(cam)
    assert pc.model.name == "SIMPLE_RADIAL" and np.allclose(pc.params, [200, 128, 96, -0.2])
    with pytest.raises(PipelineError):
        to_colmap_camera(Camera("c", 256, 192, K, np.eye(4), model="OPENCV", distortion=[0.1]))
    mask = np.zeros((192, 256), bool)
    mask[80:112, 110:146] = True  # near the centre, where radial distortion is small
    out = undistort_mask(mask, pc, undistort_options())
    assert out.dtype == bool and 0.8 < out.sum() / mask.sum() < 1.3
    # a distortion model whose terms are all 0 (e.g. the distortion held in mapping): undistort_images
    # copies such an image unchanged, so its mask must keep its size and pixels too
    flat = to_colmap_camera(Camera("d", 256, 192, K, np.eye(4), "d", model="SIMPLE_RADIAL", distortion=[0.0]))
    out = undistort_mask(mask, flat, undistort_options())
    assert out.shape == mask.shape and np.array_equal(out, mask)


def test_points_load_without_observations(tmp_path):
    """points.npz written by other tools (e.g. fit's write_known_sfm) may lack the observation arrays."""
    from sgpor_pipeline.sfm import SfmPoints

    np.savez(tmp_path / "points.npz", xyz=np.ones((5, 3)), rgb=np.zeros((5, 3), np.uint8))
    p = SfmPoints.load(tmp_path / "points.npz")
    assert len(p) == 5 and p.error.shape == (5,) and p.obs_xy.shape == (0, 2)
    assert p.seen_in(0)[0].size == 0
