"""Hole solves: the Poisson blend of a fill over a disc hole, SuperLU against AMG-preconditioned CG.

:func:`sgpor_pipeline.removal.sbm.poisson_blend` (and the depth completion, the same Laplacian) solves
directly up to ``linsolve.DIRECT_MAX_UNKNOWNS`` unknowns and by multigrid beyond
(:mod:`sgpor_pipeline.removal.linsolve`). This runs both solvers on discs of growing radius, each in
a fresh process so its peak resident memory is its own, and prints seconds, the peak memory above
the process's baseline, and the largest difference between the two results (colours in 0..1).

    python benchmarks/linsolve.py [--radii 100,200,400,600] [--json]

Target, on the largest disc: the whole blend (building the system included) takes at most half the
direct path's memory and no more time ([PASS] / [FAIL]; ratios within one run, never wall-clock
limits). Measured (session 31, 2 cores, a test suite running beside it), radius 100 / 300 / 600:
31 k unknowns 0.22 s / +63 MB direct, 0.90 s / +44 MB multigrid; 283 k 3.6 s / +637 MB, 4.2 s /
+259 MB; 1.13 M 44.0 s / +3079 MB, 18.6 s / +978 MB; results within 3e-8. The solve alone at 1.13 M
unknowns: SuperLU 29.7 s / +2.5 GB, AMG-CG 11.9 s / +0.2 GB.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

CHILD = r"""
import json, resource, sys, time
import numpy as np
from sgpor_pipeline.removal import linsolve, sbm
r, how = int(sys.argv[1]), sys.argv[2]
s = 2 * r + 40
rng = np.random.default_rng(0)
image, guide = rng.random((s, s, 3)), rng.random((s, s, 3))
yy, xx = np.mgrid[:s, :s]
region = (yy - s / 2) ** 2 + (xx - s / 2) ** 2 < r * r
linsolve.DIRECT_MAX_UNKNOWNS = 0 if how == "multigrid" else 1 << 62
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t = time.perf_counter()
out = sbm.poisson_blend(image, guide, region)
seconds = time.perf_counter() - t
peak = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base) / 1024.0
np.save(sys.argv[3], out[region])
print(json.dumps({"unknowns": int(region.sum()), "seconds": seconds, "peak_mb": peak}))
"""


def run(radius: int, how: str, out: str) -> dict:
    res = subprocess.run([sys.executable, "-c", CHILD, str(radius), how, out], capture_output=True, text=True,
                         check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> int:
    import tempfile
    from pathlib import Path

    import numpy as np

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--radii", default="100,200,400,600")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for r in (int(x) for x in args.radii.split(",")):
            d = run(r, "direct", f"{tmp}/d.npy")
            m = run(r, "multigrid", f"{tmp}/m.npy")
            diff = float(np.abs(np.load(Path(tmp) / "d.npy") - np.load(Path(tmp) / "m.npy")).max())
            rows.append({"radius": r, "unknowns": d["unknowns"], "direct_seconds": d["seconds"],
                         "direct_peak_mb": d["peak_mb"], "multigrid_seconds": m["seconds"],
                         "multigrid_peak_mb": m["peak_mb"], "max_difference": diff})
    print("radius unknowns | direct s   MB | multigrid s   MB | max diff")
    for x in rows:
        print(f"{x['radius']:>6} {x['unknowns']:>8} | {x['direct_seconds']:8.2f} {x['direct_peak_mb']:5.0f} | "
              f"{x['multigrid_seconds']:11.2f} {x['multigrid_peak_mb']:5.0f} | {x['max_difference']:.1e}")
    last = rows[-1]
    memory_ok = last["multigrid_peak_mb"] <= 0.5 * last["direct_peak_mb"]
    time_ok = last["multigrid_seconds"] <= last["direct_seconds"]
    print(f"[{'PASS' if memory_ok else 'FAIL'}] multigrid memory <= 1/2 of the direct path's at {last['unknowns']} "
          f"unknowns: {last['multigrid_peak_mb']:.0f} vs {last['direct_peak_mb']:.0f} MB")
    print(f"[{'PASS' if time_ok else 'FAIL'}] multigrid no slower there: {last['multigrid_seconds']:.1f} vs "
          f"{last['direct_seconds']:.1f} s")
    if args.json:
        print(json.dumps({"rows": rows, "memory_ok": memory_ok, "time_ok": time_ok}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
