"""renders: the (object-free) scene rendered at every camera of the run.

``renders/<view>.png`` for every registered input view (same size and intrinsics as the input) and
``renders/novel/<name>.png`` for the novel cameras (``image`` None in ``cameras.json``). Rendered
from the :data:`~.gaussians.SCENE_STAGE` Gaussians in the SfM frame, with the background the scene
was fitted with (``fit.json`` "background") or black.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from pathlib import Path

from sgpor_pipeline.dag import Exporter, StageContext
from sgpor_pipeline.imageio import write_png
from sgpor_pipeline.meshing import activated_tensors, render_view
from sgpor_pipeline.scene import Camera

from .gaussians import CAMERAS_STAGE, POSES_STAGE, SCENE_STAGE, load_run_cameras, load_scene, scene_background

RENDERS_DIR = "renders"


def render_path(out_dir: Path, cam: Camera) -> Path:
    """Where the render of ``cam`` goes in an export folder."""
    if cam.image is not None:
        return Path(out_dir) / RENDERS_DIR / f"{cam.image}.png"
    return Path(out_dir) / RENDERS_DIR / "novel" / f"{cam.name}.png"


def render_cameras(model: object, cameras: list[Camera], out_dir: Path, background: list[float] | None = None,
                   progress: Callable[[list[Camera]], Iterable[Camera]] | None = None) -> list[Path]:
    """Render ``cameras`` into :func:`render_path` files; returns the paths written."""
    g = activated_tensors(model)
    written = []
    for cam in (progress(cameras) if progress else cameras):
        path = render_path(out_dir, cam)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_png(path, render_view(g, cam, background, with_depth=False)["rgb"])
        written.append(path)
    return written


class RendersExporter(Exporter):
    name = "renders"
    VERSION = 1
    needs = (CAMERAS_STAGE, POSES_STAGE, SCENE_STAGE)
    description = "renders of the scene at every input view (renders/<view>.png) and novel camera (renders/novel/)"
    outputs = ("renders/",)

    def export(self, ctx: StageContext, out_dir: Path) -> None:
        t0 = time.perf_counter()
        model = load_scene(ctx)
        cameras = load_run_cameras(ctx)
        files = render_cameras(model, cameras, out_dir, scene_background(ctx),
                               progress=lambda it: ctx.progress(it, total=len(cameras), desc="renders"))
        novel = sum(c.image is None for c in cameras)
        ctx.log.info(f"renders: {len(files) - novel} input views, {novel} novel cameras -> {RENDERS_DIR}/ in "
                     f"{time.perf_counter() - t0:.1f} s")
