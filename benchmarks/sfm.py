"""SfM benchmark: how many photos register, how long it takes, how well it fits, how right the poses are.

Runs the ``sfm`` stage through the real pipeline (``run_pipeline(..., until="sfm")``) on
``<data>/lund/images`` (29 hand-held 1024x768 photos of a facade; target: at least 27 register) and
``<data>/statue/images`` (29 forward-facing 504x378 PNGs; its ``poses_bounds.npy``, COLMAP's poses of
the full-size photos, is the reference for pose errors). ``--data`` defaults to ``<repo>/../shared/data``;
scenes whose folder is absent are skipped (no failure: a fresh checkout has no shared data).

``--scenes synthetic`` adds 12 generated scenes with their true cameras (no data needed): the demo's
inward ring of 24 views at seeds 0-7 (``synthetic-inward0`` is the demo scene; wrapped floor and rug
textures repeat, which misleads SfM) and the forward grid at seeds 0-3. Pose errors after the
similarity that best maps the true camera centres onto the estimated ones: centre error over the
RMS radius of the true centres, rotation error in degrees; a model is counted wrong when a centre is
off by more than 10 % of that radius or a rotation by more than 5 degrees. ``--scenes
synthetic-extra`` adds 16 more (inward rings of seeds 8-19, forward grids of seeds 4-7): scenes no
SfM setting was chosen on, to check a change beyond the 12. ``--scenes synthetic-large``: more photos
than exhaustive matching is chosen for, a ring of 120 generated views at 640x480 with its photos named
in ring order and in a shuffled order (``sfm.matcher=auto``: retrieval matching), and the shuffled one
matched exhaustively as the reference; a line gives the matching time against the reference's
(``synthetic_large_match_time_ratio``).

    python benchmarks/sfm.py [--data DIR] [--out DIR] [--scenes lund,statue,synthetic,synthetic-extra,synthetic-large]
                             [--set sfm.pair_check=off] [--json]

Prints a table; with ``--json`` the last line is one JSON object (``lund_registered``, ``lund_images``,
``lund_seconds``, ... and the same for every scene run, ``<scene>_centre_err_max`` / ``_rot_err_max``
where the truth is known, ``synthetic_wrong_models``). Other benchmarks import :func:`run_lund` /
:func:`run_scene` to get an sfm result folder.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from sgpor_pipeline.camera_io import read_llff_poses
from sgpor_pipeline.dag import RunInputs
from sgpor_pipeline.demo import ensure_demo_scene
from sgpor_pipeline.imageio import IMAGE_EXTENSIONS, read_rgb8
from sgpor_pipeline.orientation import rotation_angle_deg, umeyama
from sgpor_pipeline.runner import run_pipeline
from sgpor_pipeline.scene import Camera, load_cameras, save_cameras
from sgpor_pipeline.sfm import load_sfm
from sgpor_pipeline.synthetic import SceneParams

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data"
SCENES = ("lund", "statue")
SYNTHETIC = tuple(("inward", seed) for seed in range(8)) + tuple(("forward", seed) for seed in range(4))
SYNTHETIC_EXTRA = tuple(("inward", seed) for seed in range(8, 20)) + tuple(("forward", seed) for seed in range(4, 8))
SYNTHETIC_GROUPS = {"synthetic": SYNTHETIC, "synthetic-extra": SYNTHETIC_EXTRA}
# More photos than exhaustive matching is chosen for (auto: retrieval matching beyond 50): a ring of
# 120 views at 640x480, its photos named in ring order and in shuffled order (a photo folder's names need
# not follow the capture), and the shuffled one matched exhaustively as the reference.
LARGE = SceneParams(seed=0, n_views=120, width=640, height=480, texture_size=1024)
LARGE_RUNS = (("synthetic-large", False, ()), ("synthetic-large-shuffled", True, ()),
              ("synthetic-large-shuffled-exh", True, ("sfm.matcher=exhaustive",)))
WRONG_CENTRE = 0.10  # of the true centres' RMS radius
WRONG_ROTATION_DEG = 5.0


def pose_errors(truth: list[Camera], estimated: list[Camera]) -> dict[str, float] | None:
    """Centre errors (over the true centres' RMS radius) and rotation errors (degrees) of the
    registered cameras, after the similarity that best maps the true centres onto the estimated."""
    by_image = {c.image: c for c in estimated if c.image is not None}
    pairs = [(t, by_image[t.image]) for t in truth if t.image in by_image]
    if len(pairs) < 3:
        return None
    src = np.array([t.center for t, _ in pairs])
    dst = np.array([e.center for _, e in pairs])
    sim = umeyama(src, dst)
    radius = float(np.sqrt(((src - src.mean(0)) ** 2).sum(1).mean()))
    centre = np.linalg.norm(sim.apply(src) - dst, axis=1) / (sim.s * radius)
    rotation = [rotation_angle_deg(sim.camera(t).cam_from_world[:3, :3], e.cam_from_world[:3, :3]) for t, e in pairs]
    return {"centre_err_median": float(np.median(centre)), "centre_err_max": float(centre.max()),
            "rot_err_median": float(np.median(rotation)), "rot_err_max": float(np.max(rotation)),
            "wrong": bool(centre.max() > WRONG_CENTRE or max(rotation) > WRONG_ROTATION_DEG)}


def reference_cameras(name: str, images: Path) -> list[Camera] | None:
    """The known cameras of a scene: a generated scene's cameras.json, statue's poses_bounds.npy."""
    folder = images.parent
    if (folder / "cameras.json").is_file() and (folder / "scene_params.json").is_file():
        return load_cameras(folder / "cameras.json")
    if (folder / "poses_bounds.npy").is_file():  # its rows follow the sorted photos of images/ beside it
        first = min(p for p in images.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS and p.name[0] != ".")
        h, w = read_rgb8(first).shape[:2]
        return read_llff_poses(folder / "poses_bounds.npy", width=w, height=h)
    return None


def synthetic_images(root: Path, rig: str, seed: int) -> Path:
    """A generated scene (cached by its parameters) in ``root/synthetic-<rig><seed>``; its images."""
    return ensure_demo_scene(root / f"synthetic-{rig}{seed}", SceneParams(seed=seed, rig=rig)) / "images"


def large_images(root: Path, shuffled: bool) -> Path:
    """The LARGE scene's photos (generated once into ``root/synthetic-large``), in ring order or renamed in
    a shuffled order (with cameras.json renamed alike, so the pose errors still find their truth)."""
    scene = ensure_demo_scene(root / "synthetic-large", LARGE)
    if not shuffled:
        return scene / "images"
    folder = root / "synthetic-large-shuffled"
    images = folder / "images"
    stamp, wanted = folder / "scene_params.json", (scene / "scene_params.json").read_text()
    if not stamp.is_file() or stamp.read_text() != wanted:  # not yet made, or of another LARGE
        shutil.rmtree(folder, ignore_errors=True)
        images.mkdir(parents=True)
        cameras = load_cameras(scene / "cameras.json")
        order = np.random.default_rng(1).permutation(len(cameras))
        renamed = []
        for k, i in enumerate(order):
            src = next((scene / "images").glob(f"{cameras[i].image}.*"))
            shutil.copyfile(src, images / f"photo_{k:03d}{src.suffix}")
            renamed.append(dataclasses.replace(cameras[i], name=f"photo_{k:03d}", image=f"photo_{k:03d}"))
        save_cameras(folder / "cameras.json", renamed)
        stamp.write_text(wanted)
    return images


def run_scene(name: str, data_dir: Path, out_dir: Path, overrides: list[str] | tuple[str, ...] = (),
              images: Path | None = None) -> dict[str, Any]:
    """Run ingest + sfm on ``<data_dir>/<name>/images`` (or ``images``) into ``out_dir``; returns the
    scene's numbers.

    ``seconds`` is the sfm stage's build time (from the cache manifest when the result was a hit) and
    ``wall_seconds`` this call's time. ``sfm_dir`` is the stage's output folder (see ``load_sfm``).
    ``pose`` holds :func:`pose_errors` where the scene's cameras are known.
    """
    images = Path(images) if images is not None else Path(data_dir) / name / "images"
    if not images.is_dir():
        return {"scene": name, "skipped": f"{images} not found"}
    t0 = time.perf_counter()
    result = run_pipeline(Path(out_dir), RunInputs(images=images), overrides=list(overrides), until="sfm")
    wall = time.perf_counter() - t0
    outcome = result.outcomes["sfm"]
    sfm = load_sfm(outcome.path)
    s = sfm.summary
    truth = reference_cameras(name, images)
    check = s.get("pair_check")
    return {
        "scene": name,
        "images": s["images"],
        "registered": s["registered"],
        "unregistered": s["unregistered"],
        "seconds": round(outcome.seconds, 2),
        "wall_seconds": round(wall, 2),
        "cache_hit": outcome.hit,
        "reprojection_error": s["mean_reprojection_error"],
        "points": s["points"],
        "steps": s["seconds"],
        "sfm_dir": str(outcome.path),
        "pose": pose_errors(truth, sfm.cameras) if truth else None,
        "matcher": s["matcher"],
        "contradicted": None if check is None else len(check["contradicted"]),
        "repaired": bool(check and check.get("repair") and check["repair"]["kept"] == "strongest_pairs"),
    }


def run_lund(data_dir: Path = DEFAULT_DATA, out_dir: Path | None = None,
             overrides: list[str] | tuple[str, ...] = ()) -> dict[str, Any]:
    """The lund facade through ingest + sfm (into a temporary folder unless ``out_dir`` is given)."""
    if out_dir is None:
        out_dir = Path(tempfile.mkdtemp(prefix="sgpor-bench-sfm-lund-"))
    return run_scene("lund", data_dir, out_dir, overrides)


def format_table(rows: list[dict[str, Any]]) -> str:
    w = max([18, *(len(r["scene"]) for r in rows)])
    lines = [f"{'scene':<{w}} {'images':>6} {'registered':>10} {'seconds':>8} {'reproj px':>9} {'points':>7} "
             f"{'centre err':>14} {'rot err':>12} {'check':>13}  steps (s)"]
    for r in rows:
        if "skipped" in r:
            lines.append(f"{r['scene']:<{w}} skipped: {r['skipped']}")
            continue
        err = "-" if r["reprojection_error"] is None else f"{r['reprojection_error']:.3f}"
        steps = ", ".join(f"{k} {v:.1f}" for k, v in r["steps"].items())
        hit = " (cache hit)" if r["cache_hit"] else ""
        pose = r["pose"]
        centre = "-" if pose is None else f"{100 * pose['centre_err_median']:.1f}/{100 * pose['centre_err_max']:.1f}%"
        rot = "-" if pose is None else f"{pose['rot_err_median']:.1f}/{pose['rot_err_max']:.1f}"
        if pose is not None and pose["wrong"]:
            rot += " !"
        check = "-" if r["contradicted"] is None else f"{r['contradicted']} contra"
        if r["repaired"]:
            check += ", rep"
        lines.append(f"{r['scene']:<{w}} {r['images']:>6} {r['registered']:>10} {r['seconds']:>8.1f} {err:>9} "
                     f"{r['points']:>7} {centre:>14} {rot:>12} {check:>13}  {steps}{hit}")
        if r["unregistered"]:
            lines.append(f"{'':<{w}} not registered: {', '.join(r['unregistered'])}")
    lines.append("centre err: median/max over the true centres' RMS radius; rot err: median/max degrees; "
                 "! = a wrong model; check: strongest pairs the model contradicts (rep = mapped again)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder holding lund/ and statue/")
    ap.add_argument("--out", type=Path, default=None,
                    help="run folder root (one sub-folder per scene; reruns are cache hits); default: a temp folder")
    ap.add_argument("--scenes", default=",".join(SCENES),
                    help="comma-separated scene names; 'synthetic' = 12 generated scenes with true cameras, "
                         "'synthetic-extra' = 16 more, 'synthetic-large' = a ring of 120 photos (names in order, "
                         "shuffled, shuffled and matched exhaustively)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="STAGE.FIELD=VALUE",
                    help="parameter override, e.g. sfm.matcher=sequential")
    ap.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    ap.add_argument("--verbose", action="store_true")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(name)s: %(message)s")

    if not args.data.is_dir():  # the captures are skipped one by one; generated scenes still run
        print(f"data folder {args.data} not found (pass --data): its scenes are skipped")
    root = args.out or Path(tempfile.mkdtemp(prefix="sgpor-bench-sfm-"))
    rows = []
    groups: dict[str, list[dict[str, Any]]] = {}
    for name in (s.strip() for s in args.scenes.split(",")):
        if name in SYNTHETIC_GROUPS:
            for rig, seed in SYNTHETIC_GROUPS[name]:
                scene = f"synthetic-{rig}{seed}"
                images = synthetic_images(root / "scenes", rig, seed)
                rows.append(run_scene(scene, args.data, root / scene, args.overrides, images=images))
                groups.setdefault(name, []).append(rows[-1])
        elif name == "synthetic-large":
            for scene, shuffled, extra in LARGE_RUNS:
                images = large_images(root / "scenes", shuffled)
                rows.append(run_scene(scene, args.data, root / scene, [*args.overrides, *extra], images=images))
                groups.setdefault(name, []).append(rows[-1])
        elif name:
            rows.append(run_scene(name, args.data, root / name, args.overrides))
    print(format_table(rows))
    summary: dict[str, Any] = {}
    for group, group_rows in groups.items():
        done = [r for r in group_rows if "skipped" not in r]
        wrong = sum(r["pose"]["wrong"] for r in done)
        registered = sum(r["registered"] for r in done) / max(1, sum(r["images"] for r in done))
        print(f"{group}: {wrong} of {len(done)} models wrong, {registered:.0%} of the photos registered")
        key = group.replace("-", "_")
        summary[f"{key}_wrong_models"] = wrong
        summary[f"{key}_registered_fraction"] = round(registered, 4)
    large = {r["scene"]: r for r in groups.get("synthetic-large", []) if "skipped" not in r}
    if {"synthetic-large-shuffled", "synthetic-large-shuffled-exh"} <= large.keys():
        auto, exh = large["synthetic-large-shuffled"], large["synthetic-large-shuffled-exh"]
        ratio = auto["steps"]["match"] / exh["steps"]["match"]
        print(f"synthetic-large, shuffled names: matching {auto['steps']['match']:.1f} s ({auto['matcher']}) against "
              f"{exh['steps']['match']:.1f} s (exhaustive, the reference): {ratio:.2f}x")
        summary["synthetic_large_match_time_ratio"] = round(ratio, 3)
    if args.json:
        flat: dict[str, Any] = {}
        for r in rows:
            if "skipped" in r:
                flat[f"{r['scene']}_skipped"] = r["skipped"]
                continue
            for k in ("images", "registered", "seconds", "reprojection_error", "points", "contradicted", "repaired"):
                flat[f"{r['scene']}_{k}"] = r[k]
            if r["pose"] is not None:
                for k in ("centre_err_median", "centre_err_max", "rot_err_median", "rot_err_max", "wrong"):
                    flat[f"{r['scene']}_{k}"] = round(r["pose"][k], 4) if k != "wrong" else r["pose"][k]
        flat.update(summary)
        print(json.dumps(flat))
    return 0


if __name__ == "__main__":
    sys.exit(main())
