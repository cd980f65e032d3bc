"""Fit benchmark: speed against error of the Gaussian Splatting fit on a CPU.

    python benchmarks/fit.py [--quick] [--json] [--out DIR] [--data DIR] [--scenes synthetic,statue,lund]

* ``synthetic``: the default synthetic scene (``SceneParams()``: 24 views, 256x192, every 8th view
  held out) with its known cameras and points sampled on its true geometry (the fit stage's
  "known cameras" input, :func:`sgpor_pipeline.stages.fit.write_known_sfm`). Runs the default
  configuration (automatic budget, 2000 iterations), a grid of budgets x iterations, and the runs
  behind the defaults: the MCMC strategy, SH degree 0, no initial top-up of the SfM points, the first
  half of the iterations at half resolution (``fit.coarse_until``, a speed option). Each
  reports wall seconds (initialisation included), process CPU seconds, the final Gaussian count and
  held-out PSNR/SSIM.
* ``statue``: ``../shared/data/statue`` (29 PNG, 504x378) through the pipeline (ingest -> sfm -> fit,
  our own SfM); skipped cleanly when the folder or the sfm stage is missing.
* ``lund``: SfM registration of ``../shared/data/lund/images`` (``run_lund`` from benchmarks/sfm.py
  when it exists, else the pipeline until ``sfm``).

Prints a table and writes ``fit_benchmark.png`` (seconds vs held-out PSNR, one line per run from its
training curve) and ``fit_benchmark.json`` into ``--out``. ``--quick`` runs a short version. With
``--json`` the last line is one JSON object with at least ``synthetic_heldout_psnr``,
``synthetic_fit_seconds``, ``lund_registered`` and ``lund_images``.

Wall-clock figures depend on what else runs on the machine: the process CPU seconds are printed
beside them (on an idle 2-core machine CPU ~= 1.4 x wall for this workload; CPU ~= wall means the
fit only had about one core). Session 21 took two costs out of every iteration: the NaN guard's
``torch.isfinite(...).all()`` (a fifth of the fit on this CPU wheel; now the kernel's bit scan, the
same model bit for bit: 274 -> 228 s wall for 2000 iterations of the default synthetic fit) and
torch's SSIM (now fused in the kernel: 800 iterations 103 / 92 s -> 68 / 66 s, alternating runs).
The rasterizer kernel was then about half of a fit's time. Session 22 took subnormal floats out
of its compositing loops (exp2 of far-off lanes fell below 2^-126, which this CPU handles in
microcode) and a branch gcc had put around the forward's accumulation: forward 25.1 -> 11.3 ms,
backward 34.7 -> 22.6 ms on the demo fit's 79k-Gaussian model at 256x192 (1 thread); the default
synthetic fit of 2000 iterations, alternating runs: 157 / 191 s -> 130 / 165 s wall, CPU
246 / 251 -> 192 / 203 s (renders differ by <= 1 ulp, so the fit moves as with another seed).
With the kernel's lane sums kept in registers and the SSIM's blur fixed (both bitwise the same), the
session's code against its start, alternating: 131 / 120 s against 161 / 154 s wall, CPU 181 / 174
against 243 / 244 s. The start's kernel also gave three different models in four runs of this fit;
the final one gave the same PLY in all five.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DATA = ROOT.parent / "shared" / "data"
TARGET_PSNR = 30.0
TARGET_SECONDS = 180.0
HOLDOUT_EVERY = 8  # every 8th view held out of training and scored (the mip-NeRF/3DGS protocol)

log = logging.getLogger("sgpor_pipeline.bench.fit")


def synthetic_sfm(folder: Path, seed: int = 0) -> Path:
    from sgpor_pipeline.stages.fit import write_known_sfm
    from sgpor_pipeline.synthetic import SceneParams, generate_scene

    if (folder / "points.npz").is_file():
        return folder
    scene = generate_scene(SceneParams(seed=seed))
    return write_known_sfm(folder, scene.cameras, scene.images, scene.depth,
                           [scene.background_mesh, scene.object_mesh], n_points=3000, seed=seed)


def run_synthetic(out: Path, name: str, sfm: Path, **overrides: Any) -> dict[str, Any]:
    from sgpor_pipeline.stages.fit import FitParams, fit_scene

    # the protocol holds every 8th view out (the pipeline's default trains on every view)
    params = replace(FitParams(checkpoint_every=0, checkpoint_seconds=0, holdout_every=HOLDOUT_EVERY), **overrides)
    folder = out / name
    folder.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    res = fit_scene(sfm, folder, params, None, logging.getLogger("sgpor_pipeline.fit"))
    wall = time.perf_counter() - t0
    curve = json.loads((folder / "curve.json").read_text())["curve"]
    return {"scene": "synthetic", "run": name, "strategy": params.strategy, "budget": params.budget or "auto",
            "iterations": params.iterations, "sh_degree": params.sh_degree, "count": res["count"],
            "seconds": wall, "cpu_seconds": time.process_time() - cpu0, "psnr": res["heldout_psnr"],
            "ssim": res["heldout_ssim"], "baseline_psnr": res["mean_color_baseline_psnr"],
            "stop_reason": res["stop_reason"],
            "trace": [(c["seconds"] + res["setup_seconds"], c["heldout_psnr"]) for c in curve
                      if c.get("heldout_psnr") is not None]}


def run_statue(data: Path, out: Path, iterations: int) -> dict[str, Any]:
    from sgpor_pipeline.dag import RunInputs, discover_stages
    from sgpor_pipeline.runner import run_pipeline

    folder = data / "statue" / "images"
    if not folder.is_dir():
        return {"scene": "statue", "skipped": f"{folder} not found"}
    if "sfm" not in discover_stages():
        return {"scene": "statue", "skipped": "the sfm stage is not installed"}
    run_out = out / "statue_run"
    overrides = [f"fit.iterations={iterations}", f"fit.eval_every={max(iterations // 4, 1)}",
                 f"fit.holdout_every={HOLDOUT_EVERY}"]
    t0 = time.perf_counter()
    result = run_pipeline(run_out, RunInputs(images=folder), overrides=overrides, until="fit")
    wall = time.perf_counter() - t0
    fit_dir = result.path("fit")
    fit = json.loads((fit_dir / "fit.json").read_text())
    curve = json.loads((fit_dir / "curve.json").read_text())["curve"]
    manifest = json.loads((fit_dir / "manifest.json").read_text())
    return {"scene": "statue", "run": "pipeline", "strategy": fit["strategy"], "budget": "auto",
            "iterations": fit["iterations"], "sh_degree": fit["sh_degree"], "count": fit["count"],
            "seconds": fit["seconds"], "cpu_seconds": fit.get("train_cpu_seconds"), "psnr": fit["heldout_psnr"],
            "ssim": fit["heldout_ssim"], "baseline_psnr": fit["mean_color_baseline_psnr"],
            # with fit.pose_refine the held-out views are scored at poses aligned to the refined frame;
            # this is their score at SfM's poses
            "psnr_at_sfm_poses": fit.get("heldout_psnr_at_given_poses"),
            "pose_refine": fit.get("pose_refine") is not None,
            "stop_reason": fit["stop_reason"], "pipeline_seconds": wall,
            "registered": len(fit["train_views"]) + len(fit["heldout_views"]),
            "training_resolution": fit["training_resolution"], "cache_hit": result.outcomes["fit"].hit,
            "fit_stage_seconds": manifest.get("seconds"),
            "trace": [(c["seconds"], c["heldout_psnr"]) for c in curve if c.get("heldout_psnr") is not None]}


def run_lund(data: Path, out: Path) -> dict[str, Any]:
    folder = data / "lund" / "images"
    if not folder.is_dir():
        return {"scene": "lund", "skipped": f"{folder} not found"}
    sfm_bench = ROOT / "benchmarks" / "sfm.py"
    if sfm_bench.is_file():
        spec = importlib.util.spec_from_file_location("sgpor_bench_sfm", sfm_bench)
        mod = importlib.util.module_from_spec(spec)
        assert spec.loader is not None
        spec.loader.exec_module(mod)
        if hasattr(mod, "run_lund"):
            r = mod.run_lund(data, out / "lund_run")  # (data = the folder holding lund/)
            if "skipped" in r:
                return {"scene": "lund", "skipped": r["skipped"]}
            return {"scene": "lund", "registered": r.get("registered"), "images": r.get("images"),
                    "seconds": r.get("seconds")}
    from sgpor_pipeline.dag import RunInputs, discover_stages
    from sgpor_pipeline.runner import run_pipeline
    from sgpor_pipeline.scene import load_cameras

    if "sfm" not in discover_stages():
        return {"scene": "lund", "skipped": "the sfm stage is not installed"}
    t0 = time.perf_counter()
    result = run_pipeline(out / "lund_run", RunInputs(images=folder), until="sfm")
    cams = [c for c in load_cameras(result.path("sfm") / "cameras.json") if c.image is not None]
    n_images = len([p for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png")])
    return {"scene": "lund", "registered": len(cams), "images": n_images, "seconds": time.perf_counter() - t0}


def format_table(rows: list[dict[str, Any]]) -> str:
    head = (f"{'scene':<9} {'run':<16} {'strategy':<8} {'budget':>7} {'iters':>6} {'count':>7} {'wall s':>7} "
            f"{'cpu s':>7} {'PSNR':>6} {'SSIM':>6} {'base':>6}")
    lines = [head, "-" * len(head)]
    for r in rows:
        if "skipped" in r:
            lines.append(f"{r['scene']:<9} skipped: {r['skipped']}")
            continue
        if r["scene"] == "lund":
            lines.append(f"{'lund':<9} SfM registered {r['registered']} of {r['images']} images"
                         + (f" in {r['seconds']:.0f} s" if r.get("seconds") else ""))
            continue
        cpu = "-" if r.get("cpu_seconds") is None else f"{r['cpu_seconds']:.0f}"
        base = "-" if r.get("baseline_psnr") is None else f"{r['baseline_psnr']:.1f}"
        lines.append(f"{r['scene']:<9} {r['run']:<16} {r['strategy']:<8} {str(r['budget']):>7} {r['iterations']:>6} "
                     f"{r['count']:>7} {r['seconds']:>7.0f} {cpu:>7} {r['psnr']:>6.2f} {r['ssim']:>6.3f} {base:>6}")
        if r.get("psnr_at_sfm_poses") is not None:
            lines.append(f"{'':<9} (poses refined: held-out views scored at poses aligned to the fit; at SfM's "
                         f"poses PSNR {r['psnr_at_sfm_poses']:.2f})")
    return "\n".join(lines)


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 5), dpi=100)
    ax = fig.add_subplot(1, 1, 1)
    for i, r in enumerate(x for x in rows if x.get("trace")):
        xs, ys = zip(*r["trace"])
        label = f"{r['scene']} {r['run']} ({r['count']} G)"
        ax.plot(xs, ys, "-", color=f"C{i % 10}", alpha=0.6)
        ax.plot([r["seconds"]], [r["psnr"]], "o", color=f"C{i % 10}", label=label)
    ax.axhline(TARGET_PSNR, color="grey", ls=":", lw=1)
    ax.axvline(TARGET_SECONDS, color="grey", ls=":", lw=1)
    ax.set_xlabel("seconds (wall, initialisation included at the final points)")
    ax.set_ylabel("held-out PSNR (dB)")
    ax.set_title(f"fit: speed vs error ({os.cpu_count()} cores)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    FigureCanvasAgg(fig).print_png(str(path))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="a short version (fewer and shorter runs)")
    ap.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    ap.add_argument("--out", type=Path, default=None, help="output folder (default: a temporary folder)")
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder holding statue/ and lund/")
    ap.add_argument("--scenes", default="synthetic,statue,lund", help="comma-separated: synthetic, statue, lund")
    args = ap.parse_args(argv)
    from sgpor_pipeline.allocator import keep_freed_memory

    keep_freed_memory()  # as the command line does: the timings are the user's
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    os.environ.setdefault("TQDM_DISABLE", "1")
    out = args.out or Path(tempfile.mkdtemp(prefix="sgpor-bench-fit-"))
    out.mkdir(parents=True, exist_ok=True)
    scenes = {s.strip() for s in args.scenes.split(",") if s.strip()}
    rows: list[dict[str, Any]] = []
    summary: dict[str, Any] = {}

    if "synthetic" in scenes:
        sfm = synthetic_sfm(out / "synthetic_sfm")
        default_iters = 1000 if args.quick else None
        kw = {} if default_iters is None else {"iterations": default_iters}
        r = run_synthetic(out, "default", sfm, **kw)
        rows.append(r)
        print(format_table(rows[-1:]).splitlines()[-1], flush=True)
        summary.update(synthetic_heldout_psnr=r["psnr"], synthetic_heldout_ssim=r["ssim"],
                       synthetic_fit_seconds=r["seconds"], synthetic_fit_cpu_seconds=r["cpu_seconds"],
                       synthetic_count=r["count"], synthetic_iterations=r["iterations"],
                       synthetic_stop_reason=r["stop_reason"],
                       synthetic_target_met=bool(r["psnr"] >= TARGET_PSNR and r["seconds"] <= TARGET_SECONDS))
        if args.quick:
            grid = [("b10k-500", dict(budget=10_000, iterations=500))]
        else:
            grid = [(f"b{b // 1000}k-{it}", dict(budget=b, iterations=it))
                    for b in (10_000, 30_000, 100_000) for it in (1000, 3000)]
            grid += [("mcmc-b100k-2000", dict(budget=100_000, strategy="mcmc")),  # strategy choice
                     ("sh0-2000", dict(sh_degree=0)),  # SH degree choice
                     ("no-topup-2000", dict(init_points=0)),  # initialisation: SfM points only
                     ("coarse0.5-2000", dict(coarse_until=0.5))]  # half resolution for the first half
        for name, kw in grid:
            rows.append(run_synthetic(out, name, sfm, **kw))
            print(format_table(rows[-1:]).splitlines()[-1], flush=True)
    if "statue" in scenes:
        r = run_statue(args.data, out, 500 if args.quick else 2000)
        rows.append(r)
        if "skipped" not in r:
            summary.update(statue_heldout_psnr=r["psnr"], statue_heldout_ssim=r["ssim"],
                           statue_heldout_psnr_at_sfm_poses=r["psnr_at_sfm_poses"],
                           statue_fit_seconds=r["seconds"], statue_registered=r["registered"],
                           statue_count=r["count"])
        else:
            summary["statue_skipped"] = r["skipped"]
    if "lund" in scenes:
        r = run_lund(args.data, out)
        rows.append(r)
        if "skipped" not in r:
            summary.update(lund_registered=r["registered"], lund_images=r["images"])
        else:
            summary.update(lund_registered=None, lund_images=None, lund_skipped=r["skipped"])

    print()
    print(format_table(rows))
    plot(rows, out / "fit_benchmark.png")
    (out / "fit_benchmark.json").write_text(json.dumps({"rows": rows, "summary": summary}, indent=1, default=str))
    print(f"\nplot: {out / 'fit_benchmark.png'}; rows: {out / 'fit_benchmark.json'}")
    if args.json:
        print(json.dumps(summary, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
