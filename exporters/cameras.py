"""cameras: the reconstructed cameras in the formats other tools read.

``cameras/transforms.json`` (nerfstudio / instant-ngp), ``cameras/sparse/`` (COLMAP text model,
PINHOLE) and ``cameras/cameras.json`` (ours; OpenCV axes, cam_from_world), novel cameras included.
"""

from __future__ import annotations

from pathlib import Path

from sgpor_pipeline.dag import Exporter, StageContext
from sgpor_pipeline.scene import load_cameras, save_cameras


class CamerasExporter(Exporter):
    name = "cameras"
    VERSION = 1
    needs = ("sfm",)
    description = "camera poses as transforms.json, a COLMAP text model and cameras.json"

    def export(self, ctx: StageContext, out_dir: Path) -> None:
        from sgpor_pipeline.camera_io import write_colmap_model, write_transforms_json

        cameras = load_cameras(ctx.inputs["sfm"] / "cameras.json")
        folder = out_dir / "cameras"
        (folder / "sparse").mkdir(parents=True)
        save_cameras(folder / "cameras.json", cameras)
        write_transforms_json(cameras, folder / "transforms.json")
        write_colmap_model([c for c in cameras if c.image is not None], folder / "sparse", binary=False)
