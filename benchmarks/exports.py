"""Exports benchmark: what each Gaussian file format of an export costs, in bytes and in image error.

    python benchmarks/exports.py [EXPORT_DIR] [--views N] [--json] [--sheet PNG]

``EXPORT_DIR`` is a run's ``export/`` folder (default ``runs/demo/export``, what ``make demo`` writes;
any run or ``sgpor-pipeline export`` folder with ``cameras/cameras.json`` and ``export_frame.json``).
Every Gaussian file in it is read back with an independent decoder of ours (``scene.ply`` exactly,
``scene.glb`` by :func:`sgpor_pipeline.splat_gltf.read_splat_glb`, ``scene.spz`` and ``scene.splat`` by
the readers of ``sgpor-pipeline export`` in :mod:`sgpor_pipeline.gaussians.formats`, the ``.spz`` as stored),
turned back into the export frame where the format is +Y up, and rendered at the run's registered
cameras (every ``--views``-th of them; black background). The table gives per format its size,
its size against the PLY's, the SH degree it keeps, and the PSNR of its renders against the renders
of ``scene.ply`` (mean and worst view): what a viewer of that file loses. With ``--json`` the last
line is one JSON object: ``{format: {"mb", "ratio", "sh_degree", "psnr_mean", "psnr_min"}}`` (PSNR
null where the renders are the same bits as the PLY's). ``--sheet PNG`` writes a picture of the first
camera: the PLY's render and each lossy file's, then their differences from the PLY's render, 10x.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from sgpor_pipeline.exporters.gaussians import FRAME_FILE
from sgpor_pipeline.gaussians.formats import model_from_activated, read_splat_model, read_spz_model
from sgpor_pipeline.gaussians.model import GaussianModel
from sgpor_pipeline.gaussians.ply import read_ply
from sgpor_pipeline.meshing import activated_tensors, render_view
from sgpor_pipeline.metrics import psnr
from sgpor_pipeline.orientation import GLTF_FROM_ZUP, ExportFrame, Similarity, transform_model
from sgpor_pipeline.scene import Camera, load_cameras
from sgpor_pipeline.splat_gltf import read_splat_glb

ROOT = Path(__file__).resolve().parents[1]
Z_UP_FROM_Y_UP = Similarity(1.0, GLTF_FROM_ZUP.T)  # glTF's and SPZ's frame back to the export frame


def decode(path: Path) -> GaussianModel:
    """The Gaussians of an export file, in the export frame (Z up)."""
    if path.suffix == ".ply":
        return read_ply(path)
    if path.suffix == ".glb":
        g = read_splat_glb(path)
        return transform_model(model_from_activated(g["means"], g["quats"], np.log(g["scales"]), g["opacities"],
                                                    g["sh"][:, :1], g["sh"][:, 1:], int(g["sh_degree"])),
                               Z_UP_FROM_Y_UP)
    if path.suffix == ".spz":
        return transform_model(read_spz_model(path, frame="stored"), Z_UP_FROM_Y_UP)
    if path.suffix == ".splat":
        return read_splat_model(path)
    raise ValueError(f"{path}: no decoder for this format")


def export_cameras(export_dir: Path, every: int) -> list[Camera]:
    """The registered cameras of the export, in the export frame."""
    frame = ExportFrame.from_dict(json.loads((export_dir / FRAME_FILE).read_text()))
    cams = [c for c in load_cameras(export_dir / "cameras" / "cameras.json") if c.image is not None]
    return [frame.transform.camera(c) for c in cams[::max(1, every)]]


def render_all(model: GaussianModel, cameras: list[Camera]) -> list[np.ndarray]:
    g = activated_tensors(model)
    return [render_view(g, cam, None, with_depth=False)["rgb"] for cam in cameras]


def write_sheet(path: Path, renders: dict[str, np.ndarray], reference: np.ndarray, height: int = 240) -> None:
    """One row: the PLY's render, each lossy file's (off by more than 1/255 somewhere), then each lossy
    file's |render - PLY's| x 10, labelled."""
    import cv2

    from sgpor_pipeline.imageio import to_uint8, write_png

    lossy = {name: img for name, img in renders.items() if np.abs(img - reference).max() > 1 / 255}
    cells, labels = [reference], ["scene.ply"]
    for name, img in lossy.items():
        cells.append(img)
        labels.append(name)
    for name, img in lossy.items():
        cells.append(np.clip(10 * np.abs(img - reference), 0, 1))
        labels.append(f"{name} - ply, x10")
    h, w = reference.shape[:2]
    size = (max(1, round(w * height / h)), height)
    row = []
    for img, label in zip(cells, labels):
        cell = to_uint8(cv2.resize(np.asarray(img, np.float32), size, interpolation=cv2.INTER_AREA))
        cell = np.ascontiguousarray(np.pad(cell, ((22, 2), (2, 2), (0, 0)), constant_values=255))
        cv2.putText(cell, label, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        row.append(cell)
    write_png(path, np.concatenate(row, axis=1))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("export_dir", nargs="?", type=Path, default=ROOT / "runs" / "demo" / "export")
    ap.add_argument("--views", type=int, default=1, help="render every N-th registered camera (default: all)")
    ap.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    ap.add_argument("--sheet", type=Path, metavar="PNG", help="write the first camera's renders and differences")
    args = ap.parse_args(argv)
    export_dir = args.export_dir
    if not (export_dir / "scene.ply").is_file() or not (export_dir / FRAME_FILE).is_file():
        print(f"{export_dir}: no scene.ply / {FRAME_FILE} (run `make demo`, or give a run's export/ folder)",
              file=sys.stderr)
        return 2
    cameras = export_cameras(export_dir, args.views)
    reference_path = export_dir / "scene.ply"
    reference = render_all(read_ply(reference_path), cameras)
    ply_bytes = reference_path.stat().st_size
    results = {}
    first: dict[str, np.ndarray] = {}
    print(f"# exports benchmark: {export_dir}, {len(cameras)} cameras; PSNR of each file's renders against "
          f"scene.ply's")
    print(f"{'file':12s} {'MB':>8s} {'x PLY':>7s} {'SH':>3s} {'PSNR mean':>10s} {'worst':>7s} {'decode+render s':>16s}")
    for name in ("scene.ply", "scene.glb", "scene.spz", "scene.splat"):
        path = export_dir / name
        if not path.is_file():
            continue
        t0 = time.perf_counter()
        model = decode(path)
        renders = render_all(model, cameras)
        seconds = time.perf_counter() - t0
        first[name] = renders[0]
        scores = [psnr(r, ref) for r, ref in zip(renders, reference)]
        finite = [s for s in scores if math.isfinite(s)]
        mean = float(np.mean(finite)) if finite else None  # (None: every render the same bits)
        worst = float(min(finite)) if finite else None
        size = path.stat().st_size
        results[path.suffix.lstrip(".")] = {"mb": round(size / 1e6, 2), "ratio": round(size / ply_bytes, 4),
                                            "sh_degree": model.max_sh_degree,
                                            "psnr_mean": None if mean is None else round(mean, 2),
                                            "psnr_min": None if worst is None else round(worst, 2)}
        print(f"{name:12s} {size / 1e6:8.1f} {size / ply_bytes:7.3f} {model.max_sh_degree:3d} "
              f"{'exact' if not finite else f'{mean:10.2f}':>10s} {'' if not finite else f'{worst:7.2f}':>7s} "
              f"{seconds:16.1f}")
    if args.sheet is not None and cameras:
        write_sheet(args.sheet, first, reference[0])
        print(f"sheet: {args.sheet}")
    if args.json:
        print(json.dumps(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
