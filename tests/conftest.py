"""Shared fixtures: small generated inputs and the toy plugin (tests never read ../shared)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any


def _share_the_cores() -> None:
    """Under pytest-xdist (``make test`` runs ``-n auto``, at most 4 workers) each worker gets its share
    of the cores for torch, OpenMP and our kernel, and so do the CLI processes the tests start (they
    inherit the variable): two workers each on both of 2 cores ran the suite in 368 s, on one each in 352 s (one
    process: 589 s). A thread count the user set is kept; results do not depend on it."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0") or 0)
    if workers > 1 and "OMP_NUM_THREADS" not in os.environ:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
        os.environ["OMP_NUM_THREADS"] = str(max(1, cores // workers))


_share_the_cores()  # (before anything imports torch)

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from sgpor_pipeline.imageio import write_png  # noqa: E402

TESTS = Path(__file__).resolve().parent
PLUGIN_SRC = TESTS / "plugin_pkg"


def load_benchmark(name: str):
    """A script of benchmarks/ (not a package) loaded as a module, for tests of its pure parts."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(f"sgpor_bench_{name}", TESTS.parent / "benchmarks" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    assert spec.loader is not None
    spec.loader.exec_module(mod)
    return mod


def make_images(folder: Path, n: int = 4, width: int = 40, height: int = 30, seed: int = 0) -> list[Path]:
    """Random-texture RGB PNGs named view_00.png ..."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    paths = []
    for i in range(n):
        img = rng.integers(0, 256, size=(height, width, 3), dtype=np.uint8)
        path = folder / f"view_{i:02d}.png"
        write_png(path, img)
        paths.append(path)
    return paths


def make_masks(folder: Path, names: list[str], width: int = 40, height: int = 30) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        mask = np.zeros((height, width), dtype=bool)
        mask[height // 3: 2 * height // 3, width // 3: 2 * width // 3] = True
        write_png(folder / f"{name}.png", mask)


@pytest.fixture
def image_dir(tmp_path: Path) -> Path:
    make_images(tmp_path / "images")
    return tmp_path / "images"


@pytest.fixture(scope="session")
def toy_module():
    """The toy plugin's module, imported from source (its entry points stay invisible in-process)."""
    sys.path.insert(0, str(PLUGIN_SRC))
    import sgpor_toy_plugin

    return sgpor_toy_plugin


@pytest.fixture
def toy_stages(toy_module):
    from sgpor_pipeline.stages.ingest import IngestStage

    return {"ingest": IngestStage, "toy_stats": toy_module.ToyStats, "toy_slow": toy_module.ToySlow,
            "toy_report": toy_module.ToyReport}


@pytest.fixture(scope="session")
def plugin_site(tmp_path_factory) -> Path:
    """The toy plugin really installed (pip, entry points in its dist-info) into a private folder."""
    site = tmp_path_factory.mktemp("plugin_site")
    # Build from a copy: setuptools leaves build/ and *.egg-info beside the sources, and an egg-info
    # inside tests/ would make the plugin visible to every test process.
    src = tmp_path_factory.mktemp("plugin_src") / "plugin"
    shutil.copytree(PLUGIN_SRC, src, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--no-index",
                    "--target", str(site), str(src)], check=True, capture_output=True)
    return site


def cli_env(plugin_site: Path | None = None) -> dict[str, str]:
    env = dict(os.environ)
    if plugin_site is not None:
        env["PYTHONPATH"] = str(plugin_site) + os.pathsep + env.get("PYTHONPATH", "")
    env["TQDM_DISABLE"] = "1"
    return env


def run_cli(args: list[str], env: dict[str, str] | None = None, **kw) -> subprocess.CompletedProcess:
    # cwd outside the source tree: a stale *.egg-info there would shadow the installed entry points.
    kw.setdefault("cwd", TESTS.parent.parent)
    return subprocess.run([sys.executable, "-m", "sgpor_pipeline.cli.main", *args], capture_output=True, text=True,
                          env=env or cli_env(), **kw)


def inpaint_plane_on_off(tmp_path: Path, scene, param: str, values: tuple = (False, True), **fixed: Any
                         ) -> tuple[dict[Any, float], dict[Any, dict], dict[Any, Path]]:
    """The inpaint stage on ``scene`` (its whole masks as holes) with the InpaintParams field ``param``
    at each of ``values`` (default off and on), the ``fixed`` fields set alike: the mask PSNR of the
    views' fills against the truth, the plane texture's plane.json and the stage's output folder, each
    by the value."""
    import json

    from sgpor_pipeline.dag import StageContext
    from sgpor_pipeline.imageio import read_image
    from sgpor_pipeline.removal.multiview import write_remove_fixture
    from sgpor_pipeline.stages.inpaint import InpaintParams, InpaintStage

    remove = write_remove_fixture(scene, tmp_path / "remove", holes="mask")
    score, plane, out = {}, {}, {}
    for on in values:
        ctx = StageContext.standalone(tmp_path / str(on), "inpaint", InpaintParams(**fixed, **{param: on}),
                                      {"remove": remove})
        InpaintStage().run(ctx)
        plane[on] = json.loads((ctx.out_dir / "plane" / "plane.json").read_text())
        sq = [((read_image(ctx.out_dir / "images" / f"{c.name}.png") - scene.images_gt[i]) ** 2)[scene.masks[i]]
              for i, c in enumerate(scene.cameras)]
        score[on] = float(-10 * np.log10(np.concatenate(sq).mean()))
        out[on] = ctx.out_dir
    return score, plane, out

