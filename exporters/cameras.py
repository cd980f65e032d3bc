"""cameras: the reconstructed cameras in the formats other tools read, with the poses the Gaussians
were fitted with (the fit's refined poses, ``fit.pose_refine``).

``cameras/transforms.json`` (nerfstudio / instant-ngp), ``cameras/sparse/`` (COLMAP text model,
PINHOLE) and ``cameras/cameras.json`` (ours; OpenCV axes, cam_from_world), novel cameras included.
The frames of transforms.json point at the ``renders`` exporter's images of the object-free scene
(``../renders/<view>.png``, ``../renders/novel/<name>.png``; relative to the file, as nerfstudio and
instant-ngp resolve them), so with both exported the object-free scene is a dataset in their layout.
"""

from __future__ import annotations

import os
from pathlib import Path

from sgpor_pipeline.dag import Exporter, StageContext
from sgpor_pipeline.scene import save_cameras

from .gaussians import load_run_cameras
from .renders import render_path


class CamerasExporter(Exporter):
    name = "cameras"
    VERSION = 3  # 2: the fit's (refined) poses; 3: transforms.json's frames point at the renders
    needs = ("sfm", "fit")
    description = "camera poses as transforms.json, a COLMAP text model and cameras.json"
    outputs = ("cameras/",)

    def export(self, ctx: StageContext, out_dir: Path) -> None:
        from sgpor_pipeline.camera_io import write_colmap_model, write_transforms_json

        cameras = load_run_cameras(ctx)
        folder = out_dir / "cameras"
        (folder / "sparse").mkdir(parents=True)
        save_cameras(folder / "cameras.json", cameras)
        # (it pointed at images/ beside it, which no exporter writes: nerfstudio found no image)
        paths = [Path(os.path.relpath(render_path(out_dir, c), folder)).as_posix() for c in cameras]
        write_transforms_json(cameras, folder / "transforms.json", file_paths=paths)
        write_colmap_model([c for c in cameras if c.image is not None], folder / "sparse", binary=False)
