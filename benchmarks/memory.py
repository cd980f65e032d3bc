"""Memory and time of the removal stages against the number of views, at a user's photo size.

The benchmarks of the method run at 256-384 px; a user's photos reach the ingest's 1600 px, where the
masks, remove, inpaint and refine stages work. Whatever a stage holds for every view at once then
grows with views x pixels. This generates the synthetic scene at two view counts (default 24 and 96
views of 800 x 600), runs each with its exact cameras through finetune (a short fit: the Gaussians'
quality does not matter here), every stage in its own process (``--until`` that stage, forced), and
reads each stage's peak resident memory and seconds from its manifest (the runner records them).

    python benchmarks/memory.py [--views 24,96] [--size 800x600] [--out DIR] [--json]

Prints per stage the peak at each view count and its growth per view-pixel: (peak at the larger
count - peak at the smaller) / (the extra views x width x height), in bytes. Target: the remove and
inpaint stages grow by at most 16 bytes per view-pixel ([PASS] / [FAIL]; a float RGB image per view
is 12). Measured (session 32, 2 cores), 24 / 96 views of 800 x 600, peak GB (bytes per view-pixel),
seconds at 96 views:

    stage     before (198f28c)              after (this benchmark, 73f3685)
    remove    1.32 / 3.58  (65)   163 s     0.87 / 1.13  (7.6)   127 s   [PASS]
    inpaint   1.58 / 3.33  (51)   142 s     1.02 / 1.40  (10.9)   87 s   [PASS]
    refine    0.56 / 1.11  (16)    32 s     0.48 / 0.72  (7.1)    25 s
    finetune  0.88 / 1.44  (16)    69 s     0.95 / 1.46  (14.7)   45 s   (its training images, as the fit)

("before" by the same method from a worktree of 198f28c.) Between two runs of the same stage the peak
moves by about 0.1 GB.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

STAGES = ("masks", "remove", "inpaint", "refine", "finetune")
TARGET_BYTES_PER_VIEW_PIXEL = 16.0
TARGET_STAGES = ("remove", "inpaint")
SCENE = ("from sgpor_pipeline.synthetic import SceneParams, generate_scene, save_scene; "
         "save_scene(generate_scene(SceneParams(n_views={n}, width={w}, height={h}, seed=0)), {folder!r})")


def stage_runs(n: int, w: int, h: int, out: Path, iterations: int) -> dict[str, dict]:
    """Run the pipeline on the scene of ``n`` views stage by stage; per stage its manifest's peak memory
    (bytes) and seconds."""
    from sgpor_pipeline.cache import StageCache

    folder = out / f"scene_{n}_{w}x{h}"
    if not (folder / "cameras.json").is_file():  # (in a child: the scene's arrays stay out of this process)
        subprocess.run([sys.executable, "-c", SCENE.format(n=n, w=w, h=h, folder=str(folder))], check=True)
    run = out / f"run_{n}_{w}x{h}"
    base = [sys.executable, "-m", "sgpor_pipeline.cli.main", "run", str(folder / "images"),
            "--masks", str(folder / "masks"), "--cameras", str(folder / "cameras.json"), "--out", str(run),
            "--set", f"fit.iterations={iterations}", "--set", "finetune.iterations=50"]
    subprocess.run(base + ["--until", "fit"], check=True, capture_output=True)
    res = {}
    for stage in STAGES:
        t = time.perf_counter()
        subprocess.run(base + ["--until", stage, "--force", stage], check=True, capture_output=True)
        entry = [e for e in StageCache(run / "cache").entries(stage) if e.manifest][-1]
        res[stage] = {"peak_bytes": entry.manifest.get("peak_memory_bytes"), "seconds": entry.manifest["seconds"],
                      "process_seconds": time.perf_counter() - t}
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--views", default="24,96", help="two view counts")
    ap.add_argument("--size", default="800x600", help="photo size WxH")
    ap.add_argument("--iterations", type=int, default=300, help="fit iterations (the fit is not measured)")
    ap.add_argument("--out", type=Path, default=Path("runs/bench_memory"))
    ap.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    args = ap.parse_args(argv)
    n1, n2 = sorted(int(v) for v in args.views.split(","))
    w, h = (int(v) for v in args.size.lower().split("x"))
    args.out.mkdir(parents=True, exist_ok=True)
    runs = {n: stage_runs(n, w, h, args.out.resolve(), args.iterations) for n in (n1, n2)}
    if any(r["peak_bytes"] is None for rs in runs.values() for r in rs.values()):
        print("this system does not report a stage's peak memory (Linux /proc only)")
        return 1
    extra = (n2 - n1) * w * h
    print(f"\npeak resident memory per stage, {n1} and {n2} views of {w}x{h} (each stage in its own process)")
    print(f"{'stage':<10} {f'{n1} views':>10} {f'{n2} views':>10} {'B/view-px':>10} {'seconds':>16}")
    summary: dict[str, float] = {"views": [n1, n2], "width": w, "height": h}
    ok = True
    for stage in STAGES:
        a, b = runs[n1][stage], runs[n2][stage]
        per_px = (b["peak_bytes"] - a["peak_bytes"]) / extra
        verdict = ""
        if stage in TARGET_STAGES:
            passed = per_px <= TARGET_BYTES_PER_VIEW_PIXEL
            ok &= passed
            verdict = f"  [{'PASS' if passed else 'FAIL'}] <= {TARGET_BYTES_PER_VIEW_PIXEL:.0f}"
        print(f"{stage:<10} {a['peak_bytes'] / 1e9:>8.2f} GB {b['peak_bytes'] / 1e9:>7.2f} GB {per_px:>10.1f} "
              f"{a['seconds']:>7.1f} / {b['seconds']:>6.1f}{verdict}")
        summary.update({f"{stage}_peak_gb_{n1}": a["peak_bytes"] / 1e9, f"{stage}_peak_gb_{n2}": b["peak_bytes"] / 1e9,
                        f"{stage}_bytes_per_view_pixel": per_px, f"{stage}_seconds_{n1}": a["seconds"],
                        f"{stage}_seconds_{n2}": b["seconds"]})
    summary["pass"] = bool(ok)
    if args.json:
        print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
