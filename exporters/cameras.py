"""cameras: the reconstructed cameras in the formats other tools read, with the poses the Gaussians
were fitted with (the fit's refined poses, ``fit.pose_refine``).

``cameras/transforms.json`` (nerfstudio / instant-ngp), ``cameras/sparse/`` (COLMAP text model,
PINHOLE) and ``cameras/cameras.json`` (ours; OpenCV axes, cam_from_world), novel cameras included.
"""

from __future__ import annotations

from pathlib import Path

from sgpor_pipeline.dag import Exporter, StageContext
from sgpor_pipeline.scene import save_cameras

from .gaussians import load_run_cameras


class CamerasExporter(Exporter):
    name = "cameras"
    VERSION = 2  # 2: the fit's (refined) poses
    needs = ("sfm", "fit")
    description = "camera poses as transforms.json, a COLMAP text model and cameras.json"

    def export(self, ctx: StageContext, out_dir: Path) -> None:
        from sgpor_pipeline.camera_io import write_colmap_model, write_transforms_json

        cameras = load_run_cameras(ctx)
        folder = out_dir / "cameras"
        (folder / "sparse").mkdir(parents=True)
        save_cameras(folder / "cameras.json", cameras)
        write_transforms_json(cameras, folder / "transforms.json")
        write_colmap_model([c for c in cameras if c.image is not None], folder / "sparse", binary=False)
