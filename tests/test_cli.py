"""The command line as a user runs it: real subprocesses, a real plugin package, SIGKILL, the lock."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import cli_env, make_images, run_cli

COMMANDS = ["run", "demo", "status", "clean", "render", "frames", "export"]


def test_version_and_help():
    r = run_cli(["--version"])
    assert r.returncode == 0 and r.stdout.startswith("sgpor-pipeline ")
    for cmd in COMMANDS:
        r = run_cli([cmd, "--help"])
        assert r.returncode == 0, r.stderr
        assert "usage: sgpor-pipeline " + cmd in r.stdout


def test_console_script_is_installed():
    script = Path(sys.executable).parent / "sgpor-pipeline"
    r = subprocess.run([str(script), "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "status" in r.stdout


def test_errors_are_one_line_with_the_file_and_fix(tmp_path):
    r = run_cli(["run", str(tmp_path / "nope"), "--out", str(tmp_path / "out")])
    assert r.returncode == 1
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and str(tmp_path / "nope") in lines[0] and "fix:" in lines[0]
    assert "Traceback" not in r.stderr

    images = tmp_path / "images"
    make_images(images)
    r = run_cli(["run", str(images), "--out", str(tmp_path / "out"), "--set", "ingest.max_sise=10"])
    assert r.returncode == 1
    assert "unknown parameter 'ingest.max_sise'" in r.stderr and "max_size" in r.stderr

    r = run_cli(["run", str(images), "--out", str(tmp_path / "out"), "--set", "nosuchstage.x=1"])
    assert r.returncode == 1 and "valid stages:" in r.stderr and "ingest" in r.stderr

    # no --masks: stopped before the first stage (not after SfM and a fit of minutes), naming the folder
    # of masks that lies beside the photos; --until fit (reconstruction only) needs none
    (tmp_path / "masks").mkdir()
    r = run_cli(["run", str(images), "--out", str(tmp_path / "nomasks")])
    assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1
    assert "no object masks given" in r.stderr and f"{tmp_path / 'masks'} looks like one" in r.stderr
    assert not (tmp_path / "nomasks").exists()
    r = run_cli(["run", str(images), "--out", str(tmp_path / "nomasks"), "--until", "fit",
                 "--set", 'fit.object_masks="ignore"'])
    assert r.returncode == 1 and "fit.object_masks=ignore needs an object mask" in r.stderr
    assert not (tmp_path / "nomasks").exists()

    r = run_cli(["--debug", "run", str(tmp_path / "nope"), "--out", str(tmp_path / "out")])
    assert r.returncode == 1 and "Traceback" in r.stderr

    r = run_cli(["status", str(tmp_path)])
    assert r.returncode == 1 and "not a run folder" in r.stderr

    # a mistyped folder is named before the stages are imported (torch and Open3D take seconds)
    probe = ("import sys; from sgpor_pipeline.cli.main import main; "
             f"codes = [main(['run', {str(tmp_path / 'nope')!r}]), main(['status', {str(tmp_path)!r}])]; "
             "print(codes, 'torch' in sys.modules, 'open3d' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=cli_env(),
                       cwd=tmp_path)
    assert r.stdout.split() == ["[1,", "1]", "False", "False"], (r.stdout, r.stderr)


def test_config_file_and_saved_config(tmp_path):
    images = tmp_path / "images"
    make_images(images, width=80, height=60)
    cfg = tmp_path / "my.toml"
    cfg.write_text("[ingest]\nmax_size = 40\n")
    out = tmp_path / "out"
    r = run_cli(["run", str(images), "--out", str(out), "--config", str(cfg), "--until", "ingest"])
    assert r.returncode == 0, r.stderr
    assert "max_size = 40" in (out / "config.toml").read_text()
    views = json.loads(next((out / "cache" / "ingest").glob("[0-9a-f]*/views.json")).read_text())
    assert views[0]["width"] == 40 and views[0]["height"] == 30
    # The saved configuration reproduces the run: all hits.
    r = run_cli(["run", str(images), "--out", str(out), "--config", str(out / "config.toml"), "--until", "ingest"])
    assert r.returncode == 0 and "cache hit" in r.stderr and "ran in" not in r.stderr
    # --set wins over the file.
    r = run_cli(["run", str(images), "--out", str(out), "--config", str(cfg), "--set", "ingest.max_size=20",
                 "--until", "ingest"])
    assert r.returncode == 0 and "max_size = 20" in (out / "config.toml").read_text()


def test_plugin_stage_and_exporter_from_an_installed_package(tmp_path, plugin_site):
    images = tmp_path / "images"
    make_images(images)
    out = tmp_path / "out"
    env = cli_env(plugin_site)
    r = run_cli(["run", str(images), "--out", str(out), "--until", "export", "--export", "toy_csv"], env=env)
    assert r.returncode == 0, r.stderr
    csv = (out / "export" / "toy_stats.csv").read_text().splitlines()
    assert csv[0] == "view,r,g,b" and len(csv) == 5
    r = run_cli(["status", str(out)], env=env)
    assert r.returncode == 0
    states = {line.split()[0]: line.split()[1] for line in r.stdout.splitlines()[1:]}
    assert states["toy_stats"] == "hit" and states["export"] == "hit" and states["toy_report"] == "missing"
    # Without the plugin on the path its stages simply do not exist.
    r = run_cli(["run", str(images), "--out", str(tmp_path / "o2"), "--export", "toy_csv"])
    assert r.returncode == 1 and "unknown export format 'toy_csv'" in r.stderr


def _wait_for(path: Path, proc: subprocess.Popen, timeout: float = 60.0) -> None:
    t0 = time.monotonic()
    while not path.exists():
        if proc.poll() is not None:
            raise AssertionError(f"process ended early: {proc.communicate()}")
        if time.monotonic() - t0 > timeout:
            proc.kill()
            raise AssertionError("timed out waiting for the stage to start")
        time.sleep(0.05)


def test_sigkill_mid_stage_resumes_and_concurrent_run_is_refused(tmp_path, plugin_site):
    images = tmp_path / "images"
    make_images(images)
    out = tmp_path / "out"
    wait_file = tmp_path / "go"
    env = cli_env(plugin_site)
    args = [sys.executable, "-m", "sgpor_pipeline.cli.main", "run", str(images), "--out", str(out),
            "--until", "toy_report"]
    proc = subprocess.Popen(args, env=dict(env, SGPOR_TOY_WAIT=str(wait_file)), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True, cwd=tmp_path)
    try:
        _wait_for(Path(str(wait_file) + ".started"), proc)
        # While the first run is inside toy_slow, a second run on the same folder is refused cleanly.
        second = subprocess.run(args, env=env, capture_output=True, text=True, timeout=60, cwd=tmp_path)
        assert second.returncode == 1
        assert "another sgpor-pipeline run" in second.stderr and "--out" in second.stderr
        assert len(second.stderr.strip().splitlines()) == 1
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    assert list((out / "cache" / "toy_slow").glob(".tmp-*/_checkpoint/state.json"))

    again = subprocess.run(args, env=env, capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    log = again.stderr
    assert "ingest     cache hit" in log and "toy_stats  cache hit" in log
    assert "toy_slow   ran in" in log and "resumed from checkpoint" in log
    assert "toy_report ran in" in log
    slow = next(p for p in (out / "cache" / "toy_slow").iterdir() if not p.name.startswith("."))
    result = json.loads((slow / "result.json").read_text())
    assert result == {"step": 4, "total": pytest.approx(result["total"]), "resumed_from": 2}
    assert not list((out / "cache").glob("*/.tmp-*"))
    third = subprocess.run(args, env=env, capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert third.returncode == 0 and "ran in" not in third.stderr


def test_export_of_gaussians_trained_elsewhere(tmp_path):
    """`sgpor-pipeline export`: another trainer's PLY and its cameras (here a transforms.json) give the
    exports; the same Gaussians as an .spz (stored in SPZ's frame) render the same, and so does the
    exported scene.glb and scene.usdz with their own cameras; a file of another kind, a PLY without cameras and a format
    that needs a run are refused with what to do instead."""
    import numpy as np
    import torch

    from sgpor_pipeline.camera_io import write_transforms_json
    from sgpor_pipeline.gaussians.model import GaussianModel
    from sgpor_pipeline.gaussians.ply import write_ply
    from sgpor_pipeline.imageio import read_rgb8
    from sgpor_pipeline.orientation import Similarity, transform_model
    from sgpor_pipeline.scene import Camera
    from sgpor_pipeline.spz_io import read_spz, write_spz
    from sgpor_pipeline.synthetic import look_at

    g = torch.Generator().manual_seed(0)
    m = GaussianModel.empty(200, 1)
    m.params["means"].data = 0.5 * torch.randn(200, 3, generator=g)
    m.params["scales"].data = torch.full((200, 3), -3.0)
    m.params["opacities"].data = torch.zeros(200)
    m.params["quats"].data = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(200, 1)
    write_ply(tmp_path / "trained.ply", m)
    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    cams = [Camera(f"c{i}", 64, 48, K, look_at(np.array([3 * np.cos(a), 3 * np.sin(a), 1.0]), np.zeros(3)),
                   image=f"c{i}") for i, a in enumerate(np.linspace(0, 2 * np.pi, 4, endpoint=False))]
    write_transforms_json(cams, tmp_path / "transforms.json")
    out = tmp_path / "out"
    r = run_cli(["export", str(tmp_path / "trained.ply"), "--cameras", str(tmp_path / "transforms.json"),
                 "--out", str(out), "--export", "ply,spz,gltf,renders"])
    assert r.returncode == 0, r.stderr
    for name in ("scene.ply", "scene.spz", "scene.glb", "export_frame.json", "renders/c0.png"):
        assert (out / name).is_file(), name
    assert read_spz(out / "scene.spz")["sh_degree"] == 1
    # what Niantic's tools store for the PLY (RUB: y and z negated) is turned back into its frame
    write_spz(tmp_path / "trained.spz", transform_model(m, Similarity(1.0, np.diag([1.0, -1.0, -1.0]))))
    r = run_cli(["export", str(tmp_path / "trained.spz"), "--cameras", str(tmp_path / "transforms.json"),
                 "--out", str(tmp_path / "out_spz"), "--export", "renders"])
    assert r.returncode == 0, r.stderr
    for c in cams:
        a, b = (read_rgb8(o / "renders" / f"{c.name}.png").astype(float) for o in (out, tmp_path / "out_spz"))
        assert a.max() > 50 and np.abs(a - b).mean() < 2, c.name  # .spz's quantisation only
    # our own scene.glb carries its cameras (glTF's frame, Y up, both): it exports without --cameras
    r = run_cli(["export", str(out / "scene.glb"), "--out", str(tmp_path / "out_glb"), "--export", "renders,usd"])
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "out_glb" / "scene.usdz").is_file()
    for c in cams:
        a, b = (read_rgb8(o / "renders" / f"{c.name}.png").astype(float) for o in (out, tmp_path / "out_glb"))
        assert np.abs(a - b).mean() < 1, c.name  # float32 attributes: the same pictures
    # and so does the USD scene exported from it (its ParticleField and UsdGeom cameras)
    r = run_cli(["export", str(tmp_path / "out_glb" / "scene.usdz"), "--out", str(tmp_path / "out_usd"),
                 "--export", "renders"])
    assert r.returncode == 0, r.stderr
    for c in cams:
        a, b = (read_rgb8(o / "renders" / f"{c.name}.png").astype(float) for o in (out, tmp_path / "out_usd"))
        assert np.abs(a - b).mean() < 1, c.name
    r = run_cli(["export", str(tmp_path / "trained.ply"), "--out", str(tmp_path / "refused")])
    assert r.returncode == 1 and "--cameras is required" in r.stderr and "fix:" in r.stderr, r.stderr
    for args, words in ((["--export", "report"], "need a run of the pipeline"), ([], "not a .ply, .spz, .splat")):
        src = tmp_path / ("trained.ply" if args else "trained.obj")
        src.touch(exist_ok=True)
        r = run_cli(["export", str(src), "--cameras", str(tmp_path / "transforms.json"), "--out",
                     str(tmp_path / "refused"), *args])
        assert r.returncode == 1 and words in r.stderr and "fix:" in r.stderr, r.stderr
        assert not (tmp_path / "refused").exists()  # a refused call makes no output folder


def test_export_of_a_sog(tmp_path):
    """PlayCanvas's SOG (tests/data: what splat-transform 2.7.1 wrote) exports like a PLY, bundled
    (.sog) and unbundled (its meta.json)."""
    import zipfile

    import numpy as np

    from sgpor_pipeline.camera_io import write_transforms_json
    from sgpor_pipeline.gaussians.ply import read_ply
    from sgpor_pipeline.scene import Camera
    from sgpor_pipeline.synthetic import look_at

    sog = Path(__file__).parent / "data" / "blobs300_splat-transform-2.7.1.sog"
    K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    cams = [Camera(f"c{i}", 64, 48, K, look_at(np.array([2.5 * np.cos(a), 2.5 * np.sin(a), 0.8]), np.zeros(3)),
                   image=f"c{i}") for i, a in enumerate(np.linspace(0, 2 * np.pi, 4, endpoint=False))]
    write_transforms_json(cams, tmp_path / "transforms.json")
    zipfile.ZipFile(sog).extractall(tmp_path / "unbundled")
    for name, src in (("bundled", sog), ("unbundled", tmp_path / "unbundled" / "meta.json")):
        r = run_cli(["export", str(src), "--cameras", str(tmp_path / "transforms.json"),
                     "--out", str(tmp_path / name), "--export", "ply"])
        assert r.returncode == 0, r.stderr
        model = read_ply(tmp_path / name / "scene.ply")
        assert len(model) == 300 and model.max_sh_degree == 3, name
