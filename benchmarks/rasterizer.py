"""Speed of the Gaussian rasterizer: the C++ ``cpu`` kernel against the pure-PyTorch reference.

    python benchmarks/rasterizer.py            # full table: 5k/50k/200k x 256x192/512x384/1008x567
    python benchmarks/rasterizer.py --quick    # only 50k Gaussians at 256x192
    python benchmarks/rasterizer.py --json     # ... and one JSON object as the last line
    python benchmarks/rasterizer.py --gsplat   # ... and a gsplat row per cell (CUDA + gsplat installed)

Scenes: N Gaussians spread over a 60-degree frustum (depth 2..8), random rotations, opacities
uniform in [0.05, 0.99], footprint standard deviations log-normal around 1.5 px x sqrt(50k / N)
at 256x192, so every N covers the image like a fitted scene of that size; the same 3D scene is
rendered at the larger resolutions (footprints grow with the resolution). Loss = sum of
random-weighted colours and alphas.

Columns: fwd / fwd+bwd wall-clock ms (median and min over the repetitions: on a shared machine
the min is the better estimate of the hardware), evaluations/s/core = (pixel, Gaussian) SIMD lanes
the kernel evaluated in forward + backward / fwd+bwd time / threads, peak = growth of the peak
resident memory (VmHWM) over the warm-up and timed passes; every cell runs in a fresh process. The
torch reference runs only where its estimated memory and time fit (--torch-max-pairs); skipped
cells say so. With --gsplat, the same scene runs through gsplat on the GPU (times after
torch.cuda.synchronize(); peak = the GPU allocator's peak), so the CPU kernel can be read against
the GPU backend a user with a CUDA machine would get.

Measured with --gsplat --no-torch --reps 6 on a lent machine (one H200, 16 Xeon cores, kernel
x86_64_v4 on 16 threads; gsplat 1.5.3 built for sm_90 by its JIT in 56 s; torch 2.11 + CUDA 13.0),
fwd+bwd medians in ms, cpu / gsplat:

    N          256x192        512x384        1008x567
    5k         4.0 / 2.7      9.7 / 2.7     23.8 / 3.2
    50k       16.3 / 2.7     19.8 / 2.8     34.4 / 4.3
    200k      32.3 / 3.3     38.7 / 3.5     48.2 / 4.6

gsplat's times hardly grow with the work below 200k Gaussians (launch and sync bound); the 16-core
kernel is within 1.5x of it at 5k x 256x192 and 10x behind at 200k.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

from sgpor_pipeline.gaussians import _raster_cpu, _raster_gsplat, _raster_torch
from sgpor_pipeline.gaussians._raster_scenes import look_at_camera, random_scene
from sgpor_pipeline.gaussians.rasterizer import rasterization

SIZES = (5_000, 50_000, 200_000)
RESOLUTIONS = ((256, 192), (512, 384), (1008, 567))
PARAMS = ("means", "quats", "scales", "opacities", "colors")


def _rss_mb(field: str) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def _reset_peak() -> bool:
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def make_scene(n: int, width: int, height: int) -> dict:
    base = random_scene(n, 256, 192, seed=n, sigma_px=1.5 * math.sqrt(50_000 / n))
    viewmats, Ks = look_at_camera(width, height)
    base.update(viewmats=viewmats, Ks=Ks, width=width, height=height)
    return base


def _kernel_lanes() -> int:
    lib = _raster_cpu._lib
    if lib is None or not hasattr(lib, "sgpor_last_stats"):
        return 0
    out = (ctypes.c_int64 * 4)()
    lib.sgpor_last_stats(out)
    return int(out[1] + out[3])


def measure(scene: dict, backend: str, reps: int, warmup: int, threads: int) -> dict:
    """Times ``reps`` forward and forward+backward passes (after ``warmup``); in this process."""
    g = torch.Generator().manual_seed(1)
    cuda = backend == "gsplat"
    if cuda:
        scene = {k: (v.cuda() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
        torch.cuda.reset_peak_memory_stats()
    params = {k: scene[k].detach().clone().requires_grad_(True) for k in PARAMS}
    rest = {k: v for k, v in scene.items() if k not in PARAMS}
    kw = {"backend": backend, "num_threads": threads}

    def sync() -> None:
        if cuda:
            torch.cuda.synchronize()

    if backend == "torch":
        kw["torch_block"] = 16
    weights = None
    fwd, fwdbwd = [], []
    peak_ok = _reset_peak()
    base = _rss_mb("VmRSS")
    lanes = 0
    for i in range(warmup + reps):
        for p in params.values():
            p.grad = None
        sync()
        t0 = time.perf_counter()
        render, alpha, _meta = rasterization(**params, **rest, **kw)
        sync()
        t1 = time.perf_counter()
        if weights is None:
            weights = (torch.rand(render.shape, generator=g).to(render.device),
                       torch.rand(alpha.shape, generator=g).to(alpha.device))
        loss = (render * weights[0]).sum() + (alpha * weights[1]).sum()
        loss.backward()
        sync()
        t2 = time.perf_counter()
        if backend == "cpu":
            lanes = _kernel_lanes()
        if i >= warmup:
            fwd.append((t1 - t0) * 1e3)
            fwdbwd.append((t2 - t0) * 1e3)
        del render, alpha, _meta, loss
    peak = _rss_mb("VmHWM") - base if peak_ok else float("nan")
    if cuda:
        peak = torch.cuda.max_memory_allocated() / 2**20
    med = statistics.median(fwdbwd)
    return {"fwd_ms": statistics.median(fwd), "fwd_ms_min": min(fwd), "fwdbwd_ms": med,
            "fwdbwd_ms_min": min(fwdbwd), "peak_mb": peak, "lanes": lanes,
            "evals_per_s_per_core": lanes / (med * 1e-3) / threads if lanes else float("nan")}


def run_cell(n: int, width: int, height: int, backend: str, reps: int, warmup: int, threads: int) -> dict:
    """One cell in a fresh Python process, so that its peak memory is its own."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--cell", f"{n},{width},{height},{backend}",
           "--reps", str(reps), "--warmup", str(warmup), "--threads", str(threads)]
    # as the pipeline runs (sgpor_pipeline/__init__.py sets it before torch loads OpenMP): passive
    # waiting, so that idle OpenMP threads do not spin on the cores the other threads need
    env = {**os.environ, "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY", "PASSIVE")}
    out = subprocess.run(cmd, capture_output=True, text=True, check=False, env=env)
    if out.returncode != 0:
        raise RuntimeError(f"benchmark cell {n} {width}x{height} {backend} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def result_key(metric: str, backend: str, cell: str) -> str:
    """JSON key of a cell's measurement: ``fwd_ms_min`` -> ``fwd_ms_<backend>_min_<cell>``, ``peak_mb`` ->
    ``peak_mb_<backend>_<cell>``."""
    name = metric.replace("_ms", f"_ms_{backend}", 1) if "_ms" in metric else f"{metric}_{backend}"
    return f"{name}_{cell}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="only 50k Gaussians at 256x192")
    ap.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    ap.add_argument("--threads", type=int, default=torch.get_num_threads())
    ap.add_argument("--reps", type=int, default=15, help="timed repetitions of the cpu kernel")
    ap.add_argument("--torch-reps", type=int, default=1, help="timed repetitions of the torch reference")
    ap.add_argument("--torch-max-pairs", type=float, default=4e7,
                    help="skip the torch reference where it would evaluate more (pixel, Gaussian) pairs")
    ap.add_argument("--no-torch", action="store_true", help="skip the torch reference everywhere")
    ap.add_argument("--gsplat", action="store_true", help="add a gsplat row per cell (needs CUDA and gsplat)")
    ap.add_argument("--warmup", type=int, default=2, help=argparse.SUPPRESS)
    ap.add_argument("--cell", help=argparse.SUPPRESS)  # internal: N,W,H,backend in this process
    args = ap.parse_args(argv)
    if args.cell:
        n, w, h, backend = args.cell.split(",")
        torch.set_num_threads(args.threads)
        res = measure(make_scene(int(n), int(w), int(h)), backend, args.reps, args.warmup, args.threads)
        print(json.dumps(res))
        return 0

    if not _raster_cpu.available():
        print(f"cpu kernel not available: {_raster_cpu.load_error()}", file=sys.stderr)
        return 1
    torch.set_num_threads(args.threads)
    sizes = (50_000,) if args.quick else SIZES
    resolutions = ((256, 192),) if args.quick else RESOLUTIONS
    load = os.getloadavg()
    print(f"# rasterizer benchmark: {platform.processor() or platform.machine()}, {os.cpu_count()} cpus, "
          f"{args.threads} threads, kernel {_raster_cpu.kernel_name()}, torch {torch.__version__}, "
          f"load average {load[0]:.1f} {load[1]:.1f} {load[2]:.1f}")
    if load[0] > (os.cpu_count() or 1):
        print(f"# WARNING: the machine is busy (load {load[0]:.1f} on {os.cpu_count()} cpus): timings are "
              "inflated, multi-threaded ones most (each parallel region waits for descheduled threads); "
              "the min columns are the better estimate")
    header = (f"{'N':>7} {'image':>9} {'backend':>7} | {'fwd ms':>15} | {'fwd+bwd ms':>17} | "
              f"{'Mevals/s/core':>13} | {'peak MB':>8} | note")
    if args.gsplat and not (torch.cuda.is_available() and _raster_gsplat.importable()):
        print("--gsplat needs a CUDA device and the gsplat package (pip install 'sgpor-pipeline[gpu]')",
              file=sys.stderr)
        return 1
    print(header)
    print("-" * len(header))
    result: dict[str, float | str] = {"threads": args.threads, "kernel": _raster_cpu.kernel_name() or "",
                                      "loadavg_1min": load[0]}
    for n in sizes:
        for width, height in resolutions:
            scene = make_scene(n, width, height)
            key = f"{n // 1000}k_{width}x{height}"
            reps = args.reps if n * width * height <= 50_000 * 512 * 384 else max(3, args.reps // 3)
            cpu = run_cell(n, width, height, "cpu", reps, 2, args.threads)
            print(f"{n:>7} {width}x{height:<5} {'cpu':>7} | {cpu['fwd_ms']:7.1f} ({cpu['fwd_ms_min']:5.1f}) | "
                  f"{cpu['fwdbwd_ms']:8.1f} ({cpu['fwdbwd_ms_min']:6.1f}) | "
                  f"{cpu['evals_per_s_per_core'] / 1e6:13.0f} | {cpu['peak_mb']:8.0f} |", flush=True)
            for k in ("fwd_ms", "fwd_ms_min", "fwdbwd_ms", "fwdbwd_ms_min", "peak_mb", "evals_per_s_per_core"):
                result[result_key(k, "cpu", key)] = round(cpu[k], 3)
            if args.gsplat:
                gs = run_cell(n, width, height, "gsplat", args.reps, 3, args.threads)
                print(f"{'':>7} {'':>9} {'gsplat':>7} | {gs['fwd_ms']:7.2f} ({gs['fwd_ms_min']:5.2f}) | "
                      f"{gs['fwdbwd_ms']:8.2f} ({gs['fwdbwd_ms_min']:6.2f}) | {'-':>13} | {gs['peak_mb']:8.0f} | "
                      f"gpu; cpu/gsplat {cpu['fwdbwd_ms'] / gs['fwdbwd_ms']:.0f}x (fwd+bwd, medians)", flush=True)
                for k in ("fwd_ms", "fwdbwd_ms", "peak_mb"):
                    result[result_key(k, "gsplat", key)] = round(gs[k], 3)
            note = ""
            if args.no_torch:
                note = "skipped (--no-torch)"
            else:
                with torch.no_grad():
                    proj = _raster_torch.project(scene["means"], scene["quats"], scene["scales"],
                                                 scene["opacities"], scene["viewmats"], scene["Ks"],
                                                 width, height, 0.01, 1e10, 0.3)
                    pairs = _raster_torch.dense_pairs(proj, 16, width, height)
                if pairs > args.torch_max_pairs:
                    note = f"torch skipped: {pairs / 1e6:.0f}M pixel-Gaussian pairs > --torch-max-pairs"
            if note:
                print(f"{'':>7} {'':>9} {'torch':>7} | {'-':>15} | {'-':>17} | {'-':>13} | {'-':>8} | {note}")
                result[f"torch_{key}"] = note
                continue
            ref = run_cell(n, width, height, "torch", args.torch_reps, 0, args.threads)
            speedup = ref["fwdbwd_ms"] / cpu["fwdbwd_ms"]
            print(f"{'':>7} {'':>9} {'torch':>7} | {ref['fwd_ms']:7.0f} ({ref['fwd_ms_min']:5.0f}) | "
                  f"{ref['fwdbwd_ms']:8.0f} ({ref['fwdbwd_ms_min']:6.0f}) | {'-':>13} | {ref['peak_mb']:8.0f} | "
                  f"cpu is {speedup:.0f}x faster (fwd+bwd, medians)", flush=True)
            result[f"fwd_ms_torch_{key}"] = round(ref["fwd_ms"], 1)
            result[f"fwdbwd_ms_torch_{key}"] = round(ref["fwdbwd_ms"], 1)
            result[f"peak_mb_torch_{key}"] = round(ref["peak_mb"], 1)
            result[f"speedup_vs_torch_{key}"] = round(speedup, 2)
    if args.json:
        print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
