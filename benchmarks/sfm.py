"""SfM benchmark on real captures: how many photos register, how long it takes, how well it fits.

Runs the ``sfm`` stage through the real pipeline (``run_pipeline(..., until="sfm")``) on
``<data>/lund/images`` (29 hand-held 1024x768 photos of a facade; target: at least 27 register) and
``<data>/statue/images`` (29 forward-facing 504x378 PNGs). ``--data`` defaults to ``<repo>/../shared/data``;
scenes whose folder is absent are skipped (no failure: a fresh checkout has no shared data).

    python benchmarks/sfm.py [--data DIR] [--out DIR] [--scenes lund,statue] [--set sfm.matcher=sequential] [--json]

Prints a table; with ``--json`` the last line is one JSON object (``lund_registered``, ``lund_images``,
``lund_seconds``, ... and the same for every scene run). Other benchmarks import :func:`run_lund` /
:func:`run_scene` to get an sfm result folder.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from sgpor_pipeline.dag import RunInputs
from sgpor_pipeline.runner import run_pipeline
from sgpor_pipeline.sfm import load_sfm

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared" / "data"
SCENES = ("lund", "statue")


def run_scene(name: str, data_dir: Path, out_dir: Path, overrides: list[str] | tuple[str, ...] = ()) -> dict[str, Any]:
    """Run ingest + sfm on ``<data_dir>/<name>/images`` into ``out_dir``; returns the scene's numbers.

    ``seconds`` is the sfm stage's build time (from the cache manifest when the result was a hit) and
    ``wall_seconds`` this call's time. ``sfm_dir`` is the stage's output folder (see ``load_sfm``).
    """
    images = Path(data_dir) / name / "images"
    if not images.is_dir():
        return {"scene": name, "skipped": f"{images} not found"}
    t0 = time.perf_counter()
    result = run_pipeline(Path(out_dir), RunInputs(images=images), overrides=list(overrides), until="sfm")
    wall = time.perf_counter() - t0
    outcome = result.outcomes["sfm"]
    sfm = load_sfm(outcome.path)
    s = sfm.summary
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
    }


def run_lund(data_dir: Path = DEFAULT_DATA, out_dir: Path | None = None,
             overrides: list[str] | tuple[str, ...] = ()) -> dict[str, Any]:
    """The lund facade through ingest + sfm (into a temporary folder unless ``out_dir`` is given)."""
    if out_dir is None:
        out_dir = Path(tempfile.mkdtemp(prefix="sgpor-bench-sfm-lund-"))
    return run_scene("lund", data_dir, out_dir, overrides)


def format_table(rows: list[dict[str, Any]]) -> str:
    lines = [f"{'scene':<8} {'images':>6} {'registered':>10} {'seconds':>8} {'reproj px':>9} {'points':>7}  steps (s)"]
    for r in rows:
        if "skipped" in r:
            lines.append(f"{r['scene']:<8} skipped: {r['skipped']}")
            continue
        err = "-" if r["reprojection_error"] is None else f"{r['reprojection_error']:.3f}"
        steps = ", ".join(f"{k} {v:.1f}" for k, v in r["steps"].items())
        hit = " (cache hit)" if r["cache_hit"] else ""
        lines.append(f"{r['scene']:<8} {r['images']:>6} {r['registered']:>10} {r['seconds']:>8.1f} {err:>9} "
                     f"{r['points']:>7}  {steps}{hit}")
        if r["unregistered"]:
            lines.append(f"{'':<8} not registered: {', '.join(r['unregistered'])}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder holding lund/ and statue/")
    ap.add_argument("--out", type=Path, default=None,
                    help="run folder root (one sub-folder per scene; reruns are cache hits); default: a temp folder")
    ap.add_argument("--scenes", default=",".join(SCENES), help="comma-separated scene names")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="STAGE.FIELD=VALUE",
                    help="parameter override, e.g. sfm.matcher=sequential")
    ap.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    ap.add_argument("--verbose", action="store_true")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(name)s: %(message)s")

    if not args.data.is_dir():
        print(f"skipped: data folder {args.data} not found (pass --data)")
        if args.json:
            print(json.dumps({"skipped": f"{args.data} not found"}))
        return 0
    root = args.out or Path(tempfile.mkdtemp(prefix="sgpor-bench-sfm-"))
    rows = [run_scene(name, args.data, root / name, args.overrides)
            for name in (s.strip() for s in args.scenes.split(",")) if name]
    print(format_table(rows))
    if args.json:
        flat: dict[str, Any] = {}
        for r in rows:
            if "skipped" in r:
                flat[f"{r['scene']}_skipped"] = r["skipped"]
                continue
            for k in ("images", "registered", "seconds", "reprojection_error", "points"):
                flat[f"{r['scene']}_{k}"] = r[k]
        print(json.dumps(flat))
    return 0


if __name__ == "__main__":
    sys.exit(main())
