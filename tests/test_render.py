"""Novel-view cameras through a run, ``sgpor-pipeline render`` (in the run's frame and aligned from
another frame by shared image names), and the report's metrics from the evaluate stage.

One tiny run (8 views of 64x48, short fits, known cameras plus two novel ones, ground truth) is
built once for the module (~10 s); everything else reads its cache.
"""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest
from conftest import run_cli

from sgpor_pipeline.camera_io import write_colmap_model, write_transforms_json
from sgpor_pipeline.dag import RunInputs
from sgpor_pipeline.errors import PipelineError
from sgpor_pipeline.imageio import read_image
from sgpor_pipeline.orientation import Similarity
from sgpor_pipeline.render import RenderParams, align_cameras, carry_run_corrections, render_run, umeyama
from sgpor_pipeline.runner import run_pipeline
from sgpor_pipeline.scene import Camera, load_cameras, save_cameras
from sgpor_pipeline.sfm import load_sfm
from sgpor_pipeline.synthetic import SceneParams, generate_scene, look_at, save_scene

FAST = ["fit.iterations=60", "fit.eval_every=0", "finetune.iterations=10", 'export.formats=["renders", "report"]']
NOVEL = ("novel_a", "novel_b")


def _novel_cameras(cams: list[Camera]) -> list[Camera]:
    c0, c2 = cams[0], cams[2]
    forward = c2.cam_from_world[2, :3]  # a view beside view 2, looking at what it looks at
    a = Camera(NOVEL[0], c0.width, c0.height, c0.K,
               look_at(c2.center + [0.1, 0.05, 0.0], c2.center + 3.0 * forward, up=-c2.cam_from_world[1, :3]))
    b = Camera(NOVEL[1], 2 * c0.width, 2 * c0.height, 2 * c0.K * [[1], [1], [0.5]],  # another size
               cams[5].cam_from_world)
    return [a, b]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("render")
    scene = generate_scene(SceneParams(seed=1, rig="forward", n_views=8, width=64, height=48))
    folder = save_scene(scene, root / "scene")
    save_cameras(root / "cams.json", list(scene.cameras) + _novel_cameras(scene.cameras))
    inputs = RunInputs(images=folder / "images", masks=folder / "masks", cameras=root / "cams.json",
                       extra={"groundtruth": folder / "groundtruth"})
    result = run_pipeline(root / "out", inputs, overrides=FAST)
    return root / "out", result


def _run_cameras(result) -> list[Camera]:
    return load_cameras(result.path("sfm") / "cameras.json")


# --------------------------------------------------------------------------------------------------
# novel cameras in a run


def test_novel_cameras_are_kept_and_rendered_by_the_run(tiny_run):
    out, result = tiny_run
    sfm = load_sfm(result.path("sfm"))
    assert [c.name for c in sfm.cameras if c.image is None] == list(NOVEL)
    assert len(sfm.posed) == 8 and all(c.image is not None for c in sfm.posed)
    assert sfm.summary["novel_cameras"] == 2
    # the training stages see only the views with a photo
    assert len(load_cameras(result.path("remove") / "cameras.json")) == 8
    assert not any((result.path("finetune") / "renders" / f"{n}.png").exists() for n in NOVEL)
    renders = out / "export" / "renders"
    assert len(list(renders.glob("*.png"))) == 8
    assert read_image(renders / "novel" / "novel_a.png").shape == (48, 64, 3)
    assert read_image(renders / "novel" / "novel_b.png").shape == (96, 128, 3)


def test_novel_cameras_from_a_colmap_model(tmp_path):
    """A COLMAP model whose extra images are not in the photo folder (held-out test views) or have no
    file name extension: both are novel cameras, not an error."""
    scene = generate_scene(SceneParams(seed=1, rig="forward", n_views=4, width=64, height=48))
    folder = save_scene(scene, tmp_path / "scene")
    cams = list(scene.cameras)
    held_out = Camera("heldout_01", 64, 48, cams[0].K, cams[1].cam_from_world, image="heldout_01")  # heldout_01.png
    bare = Camera("path_000", 64, 48, cams[0].K, cams[2].cam_from_world, image=None)  # written without extension
    model = write_colmap_model(cams + [held_out, bare], tmp_path / "sparse" / "0", binary=True)
    result = run_pipeline(tmp_path / "out", RunInputs(images=folder / "images", cameras=model), until="sfm")
    sfm = load_sfm(result.path("sfm"))
    novel = {c.name: c for c in sfm.cameras if c.image is None}
    assert sorted(novel) == ["heldout_01", "path_000"] and len(sfm.posed) == 4
    np.testing.assert_allclose(novel["heldout_01"].cam_from_world, cams[1].cam_from_world, atol=1e-9)


# --------------------------------------------------------------------------------------------------
# render


def test_render_in_the_run_frame_equals_the_renders_exporter(tiny_run, tmp_path):
    out, result = tiny_run
    res = render_run(out, result.path("sfm") / "cameras.json", tmp_path / "r")
    assert res.alignment.method == "none" and res.stage == "finetune"
    cams = _run_cameras(result)
    assert sorted(p.name for p in res.files) == sorted(f"{c.name}.png" for c in cams)
    for cam in cams:
        exported = out / "export" / "renders" / (f"{cam.image}.png" if cam.image else f"novel/{cam.name}.png")
        assert np.array_equal(read_image(tmp_path / "r" / f"{cam.name}.png"), read_image(exported)), cam.name
    record = json.loads((tmp_path / "r" / "render.json").read_text())
    assert record["stage"] == "finetune" and record["stage_key"] == result.outcomes["finetune"].key
    assert {r["name"] for r in record["renders"]} == {c.name for c in cams}
    assert {r["name"]: r["run_view"] for r in record["renders"]}["novel_a"] is None
    # another stage's Gaussians: the fit (object still in)
    fit = render_run(out, result.path("sfm") / "cameras.json", tmp_path / "f", RenderParams(stage="fit"))
    assert fit.stage == "fit" and len(fit.files) == len(cams)


def _transformed(cams: list[Camera], sim: Similarity) -> list[Camera]:
    return [sim.camera(c) for c in cams]


def test_render_aligns_cameras_given_in_another_frame(tiny_run, tmp_path):
    out, result = tiny_run
    cams = _run_cameras(result)
    rng = np.random.default_rng(3)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    file_from_run = Similarity(2.5, q * np.sign(np.linalg.det(q)), [3.0, -1.0, 7.5])
    path = write_transforms_json(_transformed(cams, file_from_run), tmp_path / "elsewhere" / "transforms.json")
    res = render_run(out, path, tmp_path / "r", RenderParams(depth=True))
    al = res.alignment
    assert al.method == "similarity" and len(al.shared) == 8
    assert al.transform.s == pytest.approx(1 / 2.5, rel=1e-9) and al.relative < 1e-9 and al.rotation_deg < 1e-4
    ref = render_run(out, result.path("sfm") / "cameras.json", tmp_path / "ref", RenderParams(depth=True))
    for cam in cams:  # the same images, up to the 8-bit rounding of slightly different view matrices
        a, b = read_image(tmp_path / "r" / f"{cam.name}.png"), read_image(ref.output / f"{cam.name}.png")
        assert np.abs(a - b).max() <= 1 / 255 + 1e-6, cam.name
        da = np.load(tmp_path / "r" / "depth" / f"{cam.name}.npy")
        db = np.load(ref.output / "depth" / f"{cam.name}.npy")
        both = (da > 0) & (db > 0)
        assert both.mean() > 0.5 and np.median(np.abs(da[both] / db[both] - 2.5)) < 1e-3  # depth in file units
    record = json.loads((tmp_path / "r" / "render.json").read_text())
    assert record["alignment"]["method"] == "similarity" and record["alignment"]["residual"]["rms"] < 1e-9
    np.testing.assert_allclose(np.array(record["alignment"]["run_from_file"]["matrix"]),
                               file_from_run.inverse().matrix, atol=1e-9)
    # the cameras as rendered, in the run's frame
    rendered = {c.name: c for c in load_cameras(tmp_path / "r" / "cameras.json")}
    for cam in cams:
        np.testing.assert_allclose(rendered[cam.name].cam_from_world, cam.cam_from_world, atol=1e-9)


def test_alignment_modes_and_degenerate_paths(tiny_run):
    _, result = tiny_run
    cams = _run_cameras(result)
    moved = _transformed(cams, Similarity(0.3, np.eye(3), [1.0, 2.0, 3.0]))
    # only two names shared with the run: auto keeps the frame and says why, similarity refuses
    few = [Camera(f"x{i}" if i >= 2 else c.name, c.width, c.height, c.K, c.cam_from_world,
                  image=None if i >= 2 else c.image) for i, c in enumerate(moved)]
    al = align_cameras(few, cams, "auto")
    assert al.method == "none" and "share 2 image name(s)" in al.message and al.relative > 0.05
    with pytest.raises(PipelineError, match="at least 3"):
        align_cameras(few, cams, "similarity")
    assert align_cameras(moved, cams, "none").method == "none"
    # three cameras on a straight line still align (rotation about the line from the orientations)
    line = [Camera(f"v{i}", 64, 48, cams[0].K, look_at(np.array([i * 0.5, 0.0, 0.0]), np.array([i * 0.5, 0.0, 5.0])
                   + [0.0, 1.0, 0.0]), image=f"v{i}") for i in range(4)]
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    sim = Similarity(1.7, q * np.sign(np.linalg.det(q)), [0.2, 0.3, -4.0])
    al = align_cameras(_transformed(line, sim), line, "similarity")
    assert al.relative < 1e-9 and al.rotation_deg < 1e-4
    np.testing.assert_allclose(al.transform.matrix, sim.inverse().matrix, atol=1e-9)


def test_render_carries_what_the_named_cameras_need_to_reach_the_run_poses():
    """A run whose fit turned every photo by 0.3 degrees about its own x axis. A file with the photos'
    SfM poses and a novel camera: the photos get their run poses, the novel camera the same turn. A
    file whose cameras are off SfM's by -0.1 degrees (another estimate, or the truth) turns by 0.4. A
    file of the run's own cameras, and an unrefined run, change nothing; a file naming no run photo
    is taken as it is."""
    from scipy.spatial.transform import Rotation

    def cam(name: str, angle: float, image: str | None, turn: float = 0.0) -> Camera:
        eye = np.array([3 * math.cos(angle), 3 * math.sin(angle), 1.0])
        m = look_at(eye, np.zeros(3))
        m[:3, :3] = Rotation.from_rotvec([np.radians(turn), 0, 0]).as_matrix() @ m[:3, :3]
        m[:3, 3] = -m[:3, :3] @ eye
        return Camera(name, 64, 48, np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]]), m, image=image)

    angles = np.linspace(0, 2 * math.pi, 10, endpoint=False)
    a_new = angles[3] + 0.3
    sfm = [cam(f"p{i}", a, f"p{i}") for i, a in enumerate(angles)]
    run = [cam(f"p{i}", a, f"p{i}", 0.3) for i, a in enumerate(angles)]
    for offset in (0.0, -0.1):  # the file's cameras off SfM's by this (degrees, the same for all)
        given = [cam(f"p{i}", a, f"p{i}", offset) for i, a in enumerate(angles[:4])] + [cam("new", a_new, None, offset)]
        out, said = carry_run_corrections(given, run)
        assert said.startswith("carried from 4"), said
        for got, want in zip(out[:4], run[:4]):
            np.testing.assert_allclose(got.cam_from_world, want.cam_from_world, atol=1e-9)
        want = cam("new", a_new, None, 0.3)  # (turned 0.3 - offset)
        np.testing.assert_allclose(out[4].cam_from_world, want.cam_from_world, atol=1e-9)
    for given, ref in ((run[:4] + [cam("new", a_new, None)], run), (sfm[:4] + [cam("new", a_new, None)], sfm)):
        out, _ = carry_run_corrections(given, ref)  # the run's own cameras; an unrefined run
        for got, c in zip(out, given):
            np.testing.assert_allclose(got.cam_from_world, c.cam_from_world, atol=1e-9)
    novel = [cam("new", a_new, None)]
    out, said = carry_run_corrections(novel, run)
    assert out == novel and said.startswith("none")


def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(20, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    truth = Similarity(0.37, q * np.sign(np.linalg.det(q)), rng.normal(size=3))
    est = umeyama(src, truth.apply(src))
    np.testing.assert_allclose(est.matrix, truth.matrix, atol=1e-10)
    assert umeyama(src, src + 1.0, scale=False).s == 1.0


def test_render_command_and_its_errors(tiny_run, tmp_path):
    out, result = tiny_run
    # a file in a moved frame (COLMAP text model): the alignment and its residual are printed
    moved = _transformed(_run_cameras(result), Similarity(2.5, np.eye(3), [1.0, 0.0, 0.0]))
    model = write_colmap_model(moved, tmp_path / "model", binary=False)
    r = run_cli(["render", str(out), "--cameras", str(model), "--output", str(tmp_path / "r")])
    assert r.returncode == 0, r.stderr
    assert "align: similarity from 8 shared cameras" in r.stderr and "residual RMS" in r.stderr
    assert len(list((tmp_path / "r").glob("*.png"))) == 10 and (tmp_path / "r" / "render.json").is_file()

    r = run_cli(["render", str(tmp_path / "nope"), "--cameras", str(model)])
    assert r.returncode == 1 and "not a run folder" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    # the other errors in-process (a subprocess costs seconds)
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(PipelineError, match="malformed JSON") as e:
        render_run(out, bad)
    assert e.value.path == str(bad)
    with pytest.raises(PipelineError, match="holds no Gaussians"):
        render_run(out, model, params=RenderParams(stage="masks"))
    with pytest.raises(PipelineError, match="unknown stage 'finetun'.*finetune"):
        render_run(out, model, params=RenderParams(stage="finetun"))


def test_render_names_the_command_for_a_missing_stage(tmp_path):
    scene = generate_scene(SceneParams(seed=1, rig="forward", n_views=4, width=48, height=36))
    folder = save_scene(scene, tmp_path / "scene")
    out = tmp_path / "out"
    run_pipeline(out, RunInputs(images=folder / "images", cameras=folder / "cameras.json"), until="sfm")
    with pytest.raises(PipelineError) as e:
        render_run(out, folder / "cameras.json")
    msg = e.value.one_line()
    assert "no 'finetune' result" in msg and "did not include it" in msg
    assert f"sgpor-pipeline run {folder / 'images'}" in msg and "--until finetune" in msg and "config.toml" in msg


# --------------------------------------------------------------------------------------------------
# report: the evaluate stage's metrics


def test_report_shows_the_evaluation_and_depends_on_it(tiny_run):
    out, result = tiny_run
    export_manifest = json.loads((result.path("export") / "manifest.json").read_text())
    assert export_manifest["inputs"]["evaluate"] == result.path("evaluate").name  # evaluate's key is in export's
    metrics = json.loads((result.path("evaluate") / "metrics.json").read_text())
    assert json.loads((out / "export" / "metrics.json").read_text()) == metrics
    page = (out / "export" / "report.html").read_text()
    assert "<h2" in page and ">Metrics</h2>" in page and "href='metrics.json'" in page
    for name in ("final", "inpainted_2d", "delete_only"):
        m = metrics["means"][name]
        for key, digits in (("psnr_mask", 2), ("ssim_mask", 4), ("psnr_bbox", 2), ("ssim_full", 4)):
            if math.isfinite(m[key]):
                assert f"<td>{m[key]:.{digits}f}</td>" in page, (name, key)
    for stage, seconds in metrics["seconds"].items():
        assert f"<tr><th>{stage}</th><td>{seconds:.1f}</td></tr>" in page
    assert "per view (8)" in page
    # the page dates the results it shows (the newest input's cache manifest), not its own writing, so a
    # re-export of the same results is the same bytes
    newest = max(json.loads((result.path(stage) / "manifest.json").read_text())["created"]
                 for stage in export_manifest["inputs"])
    assert time.strftime("results of %Y-%m-%d %H:%M:%S UTC", time.gmtime(newest)) in page
