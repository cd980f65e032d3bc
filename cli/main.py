"""The ``sgpor-pipeline`` command line."""

from __future__ import annotations

import argparse
import logging
import sys
import time
import traceback
from pathlib import Path

from sgpor_pipeline import __version__
from sgpor_pipeline.allocator import keep_freed_memory
from sgpor_pipeline.errors import PipelineError
from sgpor_pipeline.frames import FrameParams
from sgpor_pipeline.presets import PRESETS
from sgpor_pipeline.presets import describe as describe_preset

log = logging.getLogger("sgpor_pipeline")

#: What ``sgpor-pipeline export`` writes for Gaussians from elsewhere (the exporters that need only the
#: Gaussians and their cameras: not the report, nor the removed object)
EXTERNAL_FORMATS = ("ply", "splat", "spz", "gltf", "mesh", "usd", "renders", "cameras")


class _Formatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        msg = record.getMessage()
        if record.levelno >= logging.WARNING:
            return f"{record.levelname.lower()}: {msg}"
        return msg


def setup_logging(debug: bool) -> None:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_Formatter())
    root = logging.getLogger("sgpor_pipeline")
    root.handlers[:] = [handler]
    root.setLevel(logging.DEBUG if debug else logging.INFO)
    root.propagate = False


def _add_run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--until", metavar="STAGE", help="stop after this stage (runs it and what it needs)")
    p.add_argument("--force", metavar="STAGE", action="append", default=[],
                   help="recompute this stage and everything downstream even if cached (repeatable)")
    p.add_argument("--config", metavar="FILE", type=Path, help="TOML file with one [stage] table of parameters each")
    p.add_argument("--preset", choices=sorted(PRESETS), metavar="NAME",
                   help="a named set of parameters, under --config and --set: "
                        + "; ".join(describe_preset(name) for name in sorted(PRESETS)))
    p.add_argument("--set", metavar="STAGE.PARAM=VALUE", dest="overrides", action="append", default=[],
                   help="override one parameter, e.g. --set fit.iterations=3000 (repeatable)")
    p.add_argument("--export", metavar="LIST", help="comma-separated export formats (default: all installed), "
                                                    "same as --set export.formats=[...]")
    p.add_argument("--up", metavar="AXIS", help="up axis of the export frame: auto (from the cameras), ring, "
                                                "cameras, nadir (they look down), or an SfM axis such as -y (same as "
                                                "--set export.up=...)")
    p.add_argument("--scale", metavar="S", type=float,
                   help="metres per SfM unit for the export (otherwise the photos' GPS gives it where the camera "
                        "moved far enough, else units are arbitrary and the files say so)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sgpor-pipeline",
        description="Remove an object from a photographed 3D scene: SfM, Gaussian Splatting, semantic-guided "
                    "inpainting, export to PLY/mesh/USD. Every stage is cached in the output folder, so "
                    "running the same command again resumes.")
    parser.add_argument("--version", action="version", version=f"sgpor-pipeline {__version__}")
    parser.add_argument("--debug", action="store_true", help="show full tracebacks and library logs")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("run", help="run or resume the pipeline on a folder of photos",
                       description="Run or resume the pipeline on a folder of photos.")
    p.add_argument("images", type=Path, help="folder of photos (JPEG, PNG, TIFF, HEIC)")
    p.add_argument("--masks", type=Path, help="folder of object masks, same base names, non-zero = object; "
                                              "for all views or only some")
    p.add_argument("--cameras", type=Path, help="known cameras instead of SfM: a COLMAP model folder or a "
                                                "transforms.json (cameras without a photo are novel views)")
    p.add_argument("--out", type=Path, default=Path("runs/latest"), help="output folder (default: runs/latest)")
    _add_run_options(p)

    p = sub.add_parser("demo", help="generate a synthetic scene and run the pipeline on it",
                       description="Generate a synthetic scene (with ground truth) and run the pipeline on it.")
    p.add_argument("--out", type=Path, default=Path("runs/demo"), help="output folder (default: runs/demo)")
    p.add_argument("--seed", type=int, default=0, help="seed of the synthetic scene (default 0)")
    p.add_argument("--rig", choices=["inward", "forward"], default="inward", help="camera rig (default inward)")
    p.add_argument("--estimate-cameras", action="store_true",
                   help="estimate the cameras with SfM instead of importing the generator's exact ones "
                        "(reliable with --rig forward; the inward room repeats its wall textures)")
    _add_run_options(p)

    p = sub.add_parser("render", help="render a finished run's cleaned scene at any cameras",
                       description="Render the Gaussians of a finished run at the cameras of a file (COLMAP model, "
                                   "transforms.json or cameras.json), e.g. a camera path or a benchmark's "
                                   "object-free test views. Cameras are in the run's frame, or aligned to it "
                                   "through the image names they share with the run. Nothing is recomputed.")
    p.add_argument("out", type=Path, help="the run's output folder")
    p.add_argument("--cameras", type=Path, required=True, metavar="FILE",
                   help="a COLMAP model folder, a transforms.json or a cameras.json")
    p.add_argument("--output", type=Path, metavar="DIR",
                   help="where the PNGs go (default: OUT/renders/<name of the cameras file>)")
    p.add_argument("--stage", metavar="STAGE", help="render this stage's Gaussians (default: finetune, the "
                                                     "cleaned scene; fit: the scene with the object)")
    p.add_argument("--align", choices=["auto", "none", "similarity"], default="auto",
                   help="auto (default): a similarity fitted on the cameras named like the run's photos when "
                        "there are 3 or more, else none; none: the cameras are in the run's frame; "
                        "similarity: require the alignment")
    p.add_argument("--depth", action="store_true", help="also write depth/<camera>.npy (float32 z-depth)")

    p = sub.add_parser("frames", help="extract sharp photos from a video (or a folder of too many), to run on",
                       description="Cut a video into COUNT equal stretches and write the sharpest frame of each "
                                   "(variance of the Laplacian) as frame_<index>.jpg; draw masks on one or more, "
                                   "named like them (frame_00123.png), and run: sgpor-pipeline run OUT --masks M.")
    p.add_argument("video", type=Path, help="the video (MP4, MOV, AVI, MKV, WebM, ...), or a folder with too many "
                                            "photos: the sharpest of each stretch (name order) is copied unchanged")
    p.add_argument("out", type=Path, help="folder for the photos")
    p.add_argument("--count", type=int, default=FrameParams.count,
                   help=f"how many photos (default {FrameParams.count})")
    p.add_argument("--max-size", type=int, default=FrameParams.max_size, metavar="PX",
                   help=f"longest side of the photos (default {FrameParams.max_size}; 0 = as in the video)")
    p.add_argument("--format", choices=["jpg", "png"], default=FrameParams.format, help="jpg (default) or png")

    p = sub.add_parser("export", help="export Gaussians trained elsewhere (a 3DGS PLY, .spz, .splat, .glb, .sog or USD "
                                      "and its cameras): USD, glTF, .spz, mesh, ...",
                       description="Write the exports of Gaussians from another trainer, without removing anything: "
                                   "an INRIA-layout 3DGS PLY (any SH degree) or PlayCanvas's compressed PLY, a "
                                   "Niantic .spz, an antimatter15 "
                                   ".splat, a glTF .glb (KHR_gaussian_splatting), PlayCanvas's SOG (.sog, or an "
                                   "unbundled SOG's meta.json) or a USD stage "
                                   "(UsdVol.ParticleField3DGaussianSplat), and the cameras it was trained "
                                   "with (a COLMAP model folder, a transforms.json or a cameras.json, in the PLY's "
                                   "frame; a .glb's or USD stage's own cameras when it has them). "
                                   "The export frame is found as for a run: Z up from the cameras' horizon and "
                                   "the ground, arbitrary units unless --scale gives metres.")
    p.add_argument("gaussians", type=Path,
                   help="the Gaussians: an INRIA-layout 3DGS .ply, an .spz, a .splat, a .glb, a .sog (or its "
                        "unbundled meta.json) or a .usd/.usda/.usdc/.usdz")
    p.add_argument("--cameras", type=Path, metavar="FILE",
                   help="a COLMAP model folder, a transforms.json or a cameras.json, in the PLY's frame "
                        "(required but for a .glb or USD file that holds its cameras)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="the folder the files go to")
    p.add_argument("--export", metavar="LIST",
                   help="comma-separated formats (default: " + ",".join(EXTERNAL_FORMATS) + ")")
    p.add_argument("--up", metavar="AXIS", default="auto",
                   help="up axis of the export frame: auto (default), ring, cameras, nadir, or an axis such as -y")
    p.add_argument("--scale", metavar="S", type=float, help="metres per unit of the PLY's frame")
    p.add_argument("--spz-frame", choices=["ply", "stored"], default="ply",
                   help="an .spz's frame: ply (default) turns SPZ's RUB (y up, z back) back into the frame of "
                        "the PLY it was made from, as Niantic's library does; stored keeps the values as stored "
                        "(when the cameras are in SPZ's frame)")

    p = sub.add_parser("status", help="show each stage of a run folder: hit / missing / stale, time, size",
                       description="Show each stage of a run folder: hit / missing / stale / damaged, time, size.")
    p.add_argument("out", type=Path, help="the run's output folder")

    p = sub.add_parser("clean", help="free disk: delete cached results the run no longer uses",
                       description="Delete cached results that the run's current configuration does not use, "
                                   "leftovers of interrupted runs and unused per-view results.")
    p.add_argument("out", type=Path, help="the run's output folder")
    p.add_argument("--keep-last", type=int, default=0, metavar="N",
                   help="also keep the N most recent unused results of each stage (default 0)")
    return parser


def _format_list(text: str) -> tuple[str, ...]:
    """The export formats of an ``--export a,b,c`` option."""
    return tuple(n.strip() for n in text.split(",") if n.strip())


def cmd_run(args: argparse.Namespace) -> int:
    from sgpor_pipeline.dag import RunInputs

    inputs = RunInputs(images=args.images.resolve(), masks=args.masks.resolve() if args.masks else None,
                       cameras=args.cameras.resolve() if args.cameras else None)
    return _run(args, inputs)


def _run(args: argparse.Namespace, inputs: object) -> int:
    from sgpor_pipeline.runner import run_pipeline

    overrides = list(args.overrides)
    if args.export:
        names = list(_format_list(args.export))
        overrides.append(f"export.formats={names!r}".replace("'", '"'))
    if args.up:
        overrides.append(f'export.up="{args.up}"')
    if args.scale is not None:
        overrides.append(f"export.scale={args.scale!r}")
    t0 = time.perf_counter()
    result = run_pipeline(args.out, inputs, config_file=args.config, overrides=overrides, until=args.until,
                          force=args.force, debug=args.debug, preset=args.preset)
    log.info(f"done in {time.perf_counter() - t0:.1f} s: {len(result.ran)} stage(s) ran, "
             f"{len(result.hits)} cache hit(s); output in {result.out}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from sgpor_pipeline.dag import RunInputs
    from sgpor_pipeline.demo import ensure_demo_scene
    from sgpor_pipeline.synthetic import SceneParams

    scene_dir = ensure_demo_scene(args.out.resolve() / "scene", SceneParams(seed=args.seed, rig=args.rig))
    # The generator's exact cameras by default: the ground truth then matches the views pixel for
    # pixel (SfM's undistortion crops the images) and the demo measures removal, not SfM.
    inputs = RunInputs(images=scene_dir / "images", masks=scene_dir / "masks",
                       cameras=None if args.estimate_cameras else scene_dir / "cameras.json",
                       extra={"groundtruth": scene_dir / "groundtruth"})
    return _run(args, inputs)


def cmd_render(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from sgpor_pipeline.render import RenderParams, render_run

    params = RenderParams(stage=args.stage, align=args.align, depth=args.depth)
    render_run(args.out, args.cameras, args.output, params,
               progress=lambda cams: tqdm(cams, desc="render", leave=False, dynamic_ncols=True, disable=None))
    return 0


def cmd_frames(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from sgpor_pipeline.frames import extract_frames, select_photos

    t0 = time.perf_counter()
    params = FrameParams(count=args.count, max_size=args.max_size, format=args.format)
    pick = select_photos if args.video.is_dir() else extract_frames
    paths = pick(args.video, args.out, params,
                 progress=lambda it, total, desc: tqdm(it, total=total, desc=desc, leave=False, dynamic_ncols=True,
                                                       disable=None))
    log.info(f"frames: {len(paths)} photos in {args.out} ({time.perf_counter() - t0:.1f} s), "
             f"{paths[0].name} .. {paths[-1].name}")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    import tempfile

    from sgpor_pipeline.camera_io import load_cameras_any
    from sgpor_pipeline.exporters.gaussians import export_external
    from sgpor_pipeline.scene import save_cameras
    from sgpor_pipeline.splat_usd import USD_SUFFIXES
    from sgpor_pipeline.stages.export import ExportParams

    formats = _format_list(args.export) if args.export else EXTERNAL_FORMATS
    unsupported = [f for f in formats if f not in EXTERNAL_FORMATS]
    if unsupported:
        raise PipelineError(f"format(s) {unsupported} need a run of the pipeline (its photos, masks or stages)",
                            fix=f"choose from {', '.join(EXTERNAL_FORMATS)}")
    t0 = time.perf_counter()
    if args.cameras is None and args.gaussians.suffix.lower() not in (".glb", *USD_SUFFIXES):
        raise PipelineError("--cameras is required: the cameras the Gaussians were trained with", args.gaussians,
                            fix="add --cameras with a COLMAP model folder, a transforms.json or a cameras.json")
    cameras = load_cameras_any(args.cameras or args.gaussians)
    with tempfile.TemporaryDirectory(prefix="sgpor-cameras-") as tmp:
        cameras_json = Path(tmp) / "cameras.json"
        save_cameras(cameras_json, cameras)
        out = export_external(args.gaussians, cameras_json, args.out, formats,
                              ExportParams(up=args.up, scale=args.scale), spz_frame=args.spz_frame)
    log.info(f"exported {args.gaussians.name} with {len(cameras)} cameras: {', '.join(formats)} in "
             f"{time.perf_counter() - t0:.1f} s; output in {out}")
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    from sgpor_pipeline.runner import format_status, pipeline_status

    print(format_status(pipeline_status(args.out)))
    return 0


def cmd_clean(args: argparse.Namespace) -> int:
    from sgpor_pipeline.runner import clean

    if args.keep_last < 0:
        raise PipelineError("--keep-last must be 0 or more")
    freed = clean(args.out, keep_last=args.keep_last)
    log.info(f"freed {freed / 1e6:.1f} MB in {args.out}")
    return 0


COMMANDS = {"run": cmd_run, "demo": cmd_demo, "render": cmd_render, "frames": cmd_frames, "export": cmd_export,
            "status": cmd_status, "clean": cmd_clean}


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    setup_logging(args.debug)
    keep_freed_memory()
    try:
        return COMMANDS[args.command](args)
    except PipelineError as e:
        if args.debug:
            traceback.print_exc()
        print(f"error: {e.one_line()}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted: finished stages are kept; run the same command to resume", file=sys.stderr)
        return 130
    except Exception as e:  # an unexpected failure: one line, the traceback on request
        if args.debug:
            raise
        print(f"error: {type(e).__name__}: {e} (run with --debug for the traceback)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
