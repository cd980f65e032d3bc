"""The ``cpu`` backend: ctypes bindings of the C++ kernel and its autograd Functions.

Graph (all [C,...] tensors are per camera):

    means, quats, scales --_ProjectFn--> means2d, conics, depths (+ radii, rects: no grad)
    means, SH            --_SHFn------> colours [C,N,3]
    means2d, conics, features, opacities --_RasterFn--> render, alpha (+ contrib: no grad)

``means2d`` is a real node of the graph, so ``meta["means2d"].retain_grad()`` gives its gradient.
The binning (depth sort + tile lists) happens between projection and rasterization and has no
gradient. The shared library is built by setup.py in several x86-64 levels; the best one the CPU
supports is loaded (env ``SGPOR_KERNEL=v2|v3|v4|native|generic`` forces one).
"""

from __future__ import annotations

import ctypes
import importlib.machinery
import os
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.autograd.function import once_differentiable

_PKG_DIR = Path(__file__).resolve().parent.parent
_lib: ctypes.CDLL | None = None
_lib_name: str | None = None
_load_error: str | None = None
_loaded = False

_P = ctypes.c_void_p
_I = ctypes.c_int
_I64 = ctypes.c_int64
_D = ctypes.c_double

_SIGNATURES: dict[str, tuple[Any, list[Any]]] = {
    "project_fwd": (_I64, [_I, _I, _P, _P, _P, _P, _P, _P, _I, _I, _D, _D, _D, _I, _P, _P, _P, _P,
                           _P, _P, _I]),
    "project_bwd": (None, [_I, _I, _P, _P, _P, _P, _P, _I, _I, _D, _D, _D, _P, _P, _P, _P, _P, _P,
                           _P, _I]),
    "sh_fwd": (None, [_I, _I, _I, _I, _P, _P, _I64, _P, _I64, _P, _P, _I]),
    "sh_bwd": (None, [_I, _I, _I, _I, _P, _P, _I64, _P, _I64, _P, _P, _P, _P, _I64, _P, _I64, _I]),
    "bin": (None, [_I, _I, _I, _I, _I, _P, _P, _P, _P, _P, _P, _I]),
    "raster_fwd": (_I, [_I, _I, _I, _I, _I, _I, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P,
                        _P, _P, _I]),
    "raster_median": (_I, [_I, _I, _I, _I, _I, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _I]),
    "raster_bwd": (_I, [_I, _I, _I, _I, _I, _I, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P,
                        _P, _I]),
    "ssim_fwd": (_D, [_I, _I, _I, _P, _P, _P, _P, _I]),
    "ssim_bwd": (None, [_I, _I, _I, _P, _P, _P, _P, _D, _P, _I]),
}
_PREFERENCE = ("native", "x86_64_v4", "x86_64_v3", "x86_64_v2", "generic")
_LEVEL_OF = {"x86_64_v4": 4, "x86_64_v3": 3, "x86_64_v2": 2}


def _candidates() -> dict[str, Path]:
    found: dict[str, Path] = {}
    for suffix in importlib.machinery.EXTENSION_SUFFIXES:
        for path in _PKG_DIR.glob(f"_raster_kernel_*{suffix}"):
            m = re.match(r"_raster_kernel_(.+?)" + re.escape(suffix) + "$", path.name)
            if m and m.group(1) not in found:
                found[m.group(1)] = path
    return found


def _cpuinfo_level() -> int:
    try:
        flags = set()
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                flags = set(line.split(":", 1)[1].split())
                break
    except OSError:
        return 2
    if {"avx512f", "avx512bw", "avx512vl", "avx512dq", "avx512cd", "avx2", "fma"} <= flags:
        return 4
    if {"avx2", "fma", "bmi2"} <= flags:
        return 3
    return 2 if {"sse4_2", "popcnt"} <= flags else 1


def _usable(found: dict[str, Path]) -> list[str]:
    """The built variants this CPU can run, best first."""
    level = None
    if "x86_64_v2" in found:  # the baseline build asks the CPU (cpuid) what it supports
        try:
            level = int(ctypes.CDLL(str(found["x86_64_v2"])).sgpor_cpu_level())
        except (OSError, AttributeError):
            level = None
    if level is None:
        level = _cpuinfo_level()
    return [k for k in _PREFERENCE if k in found and _LEVEL_OF.get(k, 0) <= level]


def usable_variants() -> list[str]:
    """Names of the built kernel variants this CPU can run, best first (each a valid ``SGPOR_KERNEL``)."""
    return _usable(_candidates())


def _open(path: Path) -> ctypes.CDLL:
    # With the default active wait, idle OpenMP threads spin after each parallel region and starve
    # the threads that have work on a busy 2-core machine (measured: 3-50x slower steps). Passive
    # waiting costs microseconds per region. libgomp reads the policy once, when it is loaded: our
    # library and torch both need libgomp.so.1 and the process shares the first one loaded
    # (torch's, normally), so this only matters if the kernel loads OpenMP first;
    # sgpor_pipeline/__init__.py sets it before torch is imported through the package.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    lib = ctypes.CDLL(str(path))
    if lib.sgpor_abi_version() != 8:
        raise OSError(f"{path.name}: unexpected ABI version")
    for base, (res, args) in _SIGNATURES.items():
        for suf in ("f32", "f64"):
            fn = getattr(lib, f"sgpor_{base}_{suf}")
            fn.restype = res
            fn.argtypes = args
    for suf in ("f32", "f64"):
        fn = getattr(lib, f"sgpor_packed_bytes_{suf}")
        fn.restype, fn.argtypes = _I64, [_I]
        fn = getattr(lib, f"sgpor_count_nonfinite_{suf}")
        fn.restype = _I64
        fn.argtypes = [_P, _I64]
    lib.sgpor_masked_ssd_f32.restype = None
    lib.sgpor_masked_ssd_f32.argtypes = [_I, _I, _I, _I, _I, _P, _I64, _P, _I64, _P, _P, _P, _P, _P, _I]
    lib.sgpor_masked_ssd_u8.restype = None
    lib.sgpor_masked_ssd_u8.argtypes = [_I, _I, _I, _I, _I, _P, _I64, _P, _I64, _P, _P, _P, _P, _P, _I, _P,
                                        ctypes.c_float, _P, _P, _I]
    return lib


def _load() -> None:
    global _lib, _lib_name, _load_error, _loaded
    _loaded = True
    found = _candidates()
    if not found:
        _load_error = f"no _raster_kernel_* library in {_PKG_DIR}"
        return
    forced = os.environ.get("SGPOR_KERNEL", "").strip()
    if forced:
        key = forced if forced in found else f"x86_64_{forced}"
        if key not in found:
            _load_error = f"SGPOR_KERNEL={forced} but only {sorted(found)} are built"
            return
        order = [key]
    else:
        order = _usable(found)
    errors = []
    for key in order:
        try:
            _lib = _open(found[key])
            _lib_name = key
            return
        except (OSError, AttributeError) as exc:  # pragma: no cover - broken build
            errors.append(f"{found[key].name}: {exc}")
    _load_error = "; ".join(errors) or "no kernel variant suits this CPU"


def available() -> bool:
    """Whether the compiled kernel is loadable."""
    if not _loaded:
        _load()
    return _lib is not None


def load_error() -> str | None:
    if not _loaded:
        _load()
    return _load_error


def kernel_name() -> str | None:
    """The variant in use (e.g. ``x86_64_v4``), or None."""
    available()
    return _lib_name


def _fn(name: str, dtype: torch.dtype):
    assert _lib is not None
    return getattr(_lib, f"sgpor_{name}_{'f32' if dtype == torch.float32 else 'f64'}")


def count_nonfinite(x: torch.Tensor) -> int | None:
    """NaN/inf count of a CPU float32/float64 tensor by the kernel (no torch op; threads from 2^18 values), or
    None when the kernel cannot do it (other dtype or device, no kernel)."""
    if not available() or x.device.type != "cpu" or x.dtype not in (torch.float32, torch.float64):
        return None
    x = x.contiguous()
    return int(_fn("count_nonfinite", x.dtype)(x.data_ptr(), x.numel()))


def ssim_forward(x: torch.Tensor, y: torch.Tensor, wmap: torch.Tensor | None, threads: int
                 ) -> tuple[float, torch.Tensor]:
    """The kernel's fused SSIM (csrc/ssim.h) of contiguous [C,H,W] CPU images of one dtype (H, W > 5):
    (the sum of the SSIM map, times ``wmap`` [H,W] per pixel when given; the moments [5C,H,W] the
    backward needs)."""
    if not available():
        raise RuntimeError(f"the cpu kernel is not loaded: {load_error()}")
    C, H, W = x.shape
    mom = x.new_empty(5 * C, H, W)
    total = _fn("ssim_fwd", x.dtype)(C, H, W, x.data_ptr(), y.data_ptr(), _ptr(wmap), mom.data_ptr(), threads)
    return float(total), mom


def ssim_backward(x: torch.Tensor, y: torch.Tensor, mom: torch.Tensor, wmap: torch.Tensor | None, scale: float,
                  threads: int) -> torch.Tensor:
    """The gradient of :func:`ssim_forward`'s sum with respect to ``x``, times ``scale``."""
    C, H, W = x.shape
    dx = torch.empty_like(x)
    _fn("ssim_bwd", x.dtype)(C, H, W, x.data_ptr(), y.data_ptr(), mom.data_ptr(), _ptr(wmap), float(scale),
                             dx.data_ptr(), threads)
    return dx


def masked_ssd(cur: np.ndarray, mask: np.ndarray, tpos: np.ndarray, win: int, views: list[np.ndarray],
               cand: np.ndarray, r: int, threads: int, step: int = 1) -> np.ndarray:
    """cv2.matchTemplate's TM_SQDIFF with a mask, for many templates and candidates at once
    (csrc/match.h): target t's template is ``cur[y:y+win, x:x+win]`` (HxWx3 float32) at
    ``tpos[t] = (y, x)``, weighted by ``mask[y:y+win, x:x+win]`` squared (HxW float32); candidate j is
    the region ``views[v][cy:cy+win+2r, cx:cx+win+2r]`` for ``cand[t, j] = (v, cy, cx)`` (v -1: none,
    +inf). Every window must lie inside its image. Returns [T, KC, n, n] float32, n = 2r / step + 1:
    the sum over the window and channels of mask^2 (region - template)^2 at each shift that is a
    multiple of ``step`` (2r must be one: step > 1 is a coarse search's first pass)."""
    if not available():
        raise RuntimeError(f"the cpu kernel is not loaded: {load_error()}")
    arrays = [np.ascontiguousarray(v, np.float32) for v in views]
    cur, mask, tpos, cand = _ssd_inputs(cur, mask, tpos, win, arrays, cand, r, [a.shape[:2] for a in arrays])
    T, KC = cand.shape[:2]
    side = _shifts_per_axis(r, step)
    out = np.empty((T, KC, side, side), np.float32)
    ptrs = (ctypes.c_void_p * max(len(arrays), 1))(*[a.ctypes.data for a in arrays])
    strides = np.array([a.shape[1] * 3 for a in arrays] or [0], np.int64)
    _lib.sgpor_masked_ssd_f32(T, KC, win, r, int(step), cur.ctypes.data, cur.shape[1] * 3, mask.ctypes.data,
                              mask.shape[1], tpos.ctypes.data, ctypes.addressof(ptrs), strides.ctypes.data,
                              cand.ctypes.data, out.ctypes.data, max(1, int(threads)))
    return out


def _shifts_per_axis(r: int, step: int) -> int:
    if r < 0 or step < 1 or (2 * r) % step:
        raise ValueError(f"the shift range 2r = {2 * r} must be a non-negative multiple of the step {step}")
    return 2 * r // step + 1


def _ssd_inputs(cur: np.ndarray, mask: np.ndarray, tpos: np.ndarray, win: int, views: list[np.ndarray],
                cand: np.ndarray, r: int, region_shapes: list[tuple[int, int]]) -> tuple:
    """The masked-SSD inputs as the kernel reads them, checked: every window inside its image (the
    kernel reads without bounds checks), ``region_shapes`` the (padded) extent the regions must stay in."""
    for a in (cur, *views):
        if a.ndim != 3 or a.shape[2] != 3:
            raise ValueError(f"images must be HxWx3, got {a.shape}")
    cur = np.ascontiguousarray(cur, np.float32)
    mask = np.ascontiguousarray(mask, np.float32)
    tpos = np.ascontiguousarray(tpos, np.int32).reshape(-1, 2)
    cand = np.ascontiguousarray(cand, np.int32)
    if len(tpos) and ((tpos < 0).any() or (tpos[:, 0] + win > cur.shape[0]).any()
                      or (tpos[:, 1] + win > cur.shape[1]).any() or mask.shape != cur.shape[:2]):
        raise ValueError("a template window leaves the current image")
    valid = cand[..., 0] >= 0
    if valid.any():
        cv = cand[valid]
        if cv[:, 0].max() >= len(views) or (cv[:, 1:] < 0).any():
            raise ValueError("a candidate names a missing view or a negative corner")
        hs = np.array([s[0] for s in region_shapes])[cv[:, 0]]
        ws = np.array([s[1] for s in region_shapes])[cv[:, 0]]
        if (cv[:, 1] + win + 2 * r > hs).any() or (cv[:, 2] + win + 2 * r > ws).any():
            raise ValueError("a candidate region leaves its view")
    return cur, mask, tpos, cand


def masked_ssd_u8(cur: np.ndarray, mask: np.ndarray, tpos: np.ndarray, win: int, views: list[np.ndarray],
                  valid: list[np.ndarray], cand: np.ndarray, r: int, pad: int, lut: np.ndarray, sentinel: float,
                  threads: int, step: int = 1) -> np.ndarray:
    """:func:`masked_ssd` with 8-bit source views (HxWx3 uint8) and their validity (HxW bool): the
    candidates' corners are in the views padded by ``pad`` on every side, and a region pixel reads
    ``sentinel`` outside its view or where it is not valid, ``lut[value]`` (float32 [256]) elsewhere.
    That is :func:`masked_ssd` on the float views so padded, bit for bit, without their float copies."""
    if not available():
        raise RuntimeError(f"the cpu kernel is not loaded: {load_error()}")
    arrays = [np.ascontiguousarray(v, np.uint8) for v in views]
    oks = [np.ascontiguousarray(m, bool) for m in valid]
    if len(oks) != len(arrays) or any(m.shape != a.shape[:2] for m, a in zip(oks, arrays)):
        raise ValueError("one validity mask of each view's size is needed")
    lut = np.ascontiguousarray(lut, np.float32)
    if lut.shape != (256,):
        raise ValueError(f"the table has 256 entries, got {lut.shape}")
    padded = [(a.shape[0] + 2 * pad + 1, a.shape[1] + 2 * pad + 1) for a in arrays]  # (as SourceBank.padded)
    cur, mask, tpos, cand = _ssd_inputs(cur, mask, tpos, win, arrays, cand, r, padded)
    T, KC = cand.shape[:2]
    side = _shifts_per_axis(r, step)
    out = np.empty((T, KC, side, side), np.float32)
    n = max(len(arrays), 1)
    ptrs = (ctypes.c_void_p * n)(*[a.ctypes.data for a in arrays])
    vptrs = (ctypes.c_void_p * n)(*[m.ctypes.data for m in oks])
    heights = np.array([a.shape[0] for a in arrays] or [0], np.int32)
    widths = np.array([a.shape[1] for a in arrays] or [0], np.int32)
    _lib.sgpor_masked_ssd_u8(T, KC, win, r, int(step), cur.ctypes.data, cur.shape[1] * 3, mask.ctypes.data,
                             mask.shape[1], tpos.ctypes.data, ctypes.addressof(ptrs), ctypes.addressof(vptrs),
                             heights.ctypes.data, widths.ctypes.data, int(pad), lut.ctypes.data, float(sentinel),
                             cand.ctypes.data, out.ctypes.data, max(1, int(threads)))
    return out


def _ptr(t: torch.Tensor | None) -> int | None:
    return None if t is None else t.data_ptr()


class _Cfg:
    __slots__ = ("W", "H", "near", "far", "eps2d", "tile", "threads", "C", "N", "grad_mask")

    def __init__(self, **kw):
        for k, v in kw.items():
            setattr(self, k, v)


class _ProjectFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmats, Ks, cfg):
        C, N = cfg.C, cfg.N
        dt = means.dtype
        means2d = torch.empty(C, N, 2, dtype=dt)
        conics = torch.empty(C, N, 3, dtype=dt)
        depths = torch.empty(C, N, dtype=dt)
        radii = torch.empty(C, N, dtype=torch.int32)
        rect = torch.empty(C, N, 4, dtype=torch.int32)
        ntiles = torch.empty(C, N, dtype=torch.int32)
        total = _fn("project_fwd", dt)(
            C, N, _ptr(means), _ptr(quats), _ptr(scales), _ptr(opacities), _ptr(viewmats), _ptr(Ks),
            cfg.W, cfg.H, cfg.near, cfg.far, cfg.eps2d, cfg.tile, _ptr(means2d), _ptr(conics),
            _ptr(depths), _ptr(radii), _ptr(rect), _ptr(ntiles), cfg.threads)
        ctx.cfg = cfg
        ctx.save_for_backward(means, quats, scales, viewmats, Ks, radii)
        ctx.mark_non_differentiable(radii, rect, ntiles)
        return means2d, conics, depths, radii, rect, ntiles, torch.tensor(total, dtype=torch.int64)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_means2d, g_conics, g_depths, *_):
        means, quats, scales, viewmats, Ks, radii = ctx.saved_tensors
        cfg = ctx.cfg
        C, N = cfg.C, cfg.N
        dt = means.dtype
        g_means2d = torch.zeros(C, N, 2, dtype=dt) if g_means2d is None else g_means2d.contiguous()
        g_conics = torch.zeros(C, N, 3, dtype=dt) if g_conics is None else g_conics.contiguous()
        g_depths = None if g_depths is None else g_depths.contiguous()
        g_means = torch.empty_like(means)
        g_quats = torch.empty_like(quats)
        g_scales = torch.empty_like(scales)
        _fn("project_bwd", dt)(
            C, N, _ptr(means), _ptr(quats), _ptr(scales), _ptr(viewmats), _ptr(Ks), cfg.W, cfg.H,
            cfg.near, cfg.far, cfg.eps2d, _ptr(radii), _ptr(g_means2d), _ptr(g_conics),
            _ptr(g_depths), _ptr(g_means), _ptr(g_quats), _ptr(g_scales), cfg.threads)
        return g_means, g_quats, g_scales, None, None, None, None


def _sh_rows(t: torch.Tensor) -> tuple[torch.Tensor, int]:
    """``t`` [N,k,3] as the kernel reads it (3 values per coefficient, in order) and its row stride."""
    if t.shape[1] > 0 and (t.stride(2) != 1 or (t.shape[1] > 1 and t.stride(1) != 3)):
        t = t.contiguous()
    return t, (t.stride(0) if t.shape[0] > 1 else 3 * t.shape[1])


class _SHFn(torch.autograd.Function):
    """Colours [C,N,3] from the SH coefficients in two parts: the DC term sh0 [N,1,3] and the rest
    shN [N,KN,3] (the model's two parameters, read in place; one [N,K,3] tensor is passed as its
    two slices)."""

    @staticmethod
    def forward(ctx, means, sh0, shN, viewmats, degree, threads):
        C, N, KN = viewmats.shape[0], means.shape[0], shN.shape[1]
        s0, st0 = _sh_rows(sh0)
        sN, stN = _sh_rows(shN)
        rgb = torch.empty(C, N, 3, dtype=means.dtype)
        _fn("sh_fwd", means.dtype)(C, N, KN, degree, _ptr(means), _ptr(s0), st0, _ptr(sN), stN, _ptr(viewmats),
                                   _ptr(rgb), threads)
        ctx.save_for_backward(means, s0, sN, viewmats)
        ctx.degree, ctx.threads, ctx.strides = degree, threads, (st0, stN)
        return rgb

    @staticmethod
    @once_differentiable
    def backward(ctx, g_rgb):
        means, s0, sN, viewmats = ctx.saved_tensors
        C, N, KN = viewmats.shape[0], means.shape[0], sN.shape[1]
        g_means = torch.zeros_like(means)
        g_sh0 = torch.empty(N, 1, 3, dtype=means.dtype)
        g_shN = torch.empty(N, KN, 3, dtype=means.dtype)
        g_rgb = g_rgb.contiguous()  # keep a reference: the kernel reads its memory
        st0, stN = ctx.strides
        _fn("sh_bwd", means.dtype)(C, N, KN, ctx.degree, _ptr(means), _ptr(s0), st0, _ptr(sN), stN,
                                   _ptr(viewmats), _ptr(g_rgb), _ptr(g_means), _ptr(g_sh0), 3, _ptr(g_shN),
                                   3 * KN, ctx.threads)
        return g_means, g_sh0, g_shN, None, None, None


class _RasterFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, features, opacities, rect, bins, cmask, cfg):
        C, N, CH = features.shape
        H, W = cfg.H, cfg.W
        dt = means2d.dtype
        tile_off, isect, goff = bins
        out = torch.empty(C, H, W, CH, dtype=dt)
        alpha = torch.empty(C, H, W, 1, dtype=dt)
        tfinal = torch.empty(C, H, W, dtype=dt)
        last = torch.empty(C, H, W, dtype=torch.int32)
        contrib = torch.empty(C, N, dtype=dt)
        # the Gaussians as the tiles read them (one 64-byte record each), reused by the backward
        packed = torch.empty(max(C * N, 1) * int(_fn("packed_bytes", dt)(CH)), dtype=torch.uint8)
        rc = _fn("raster_fwd", dt)(
            C, N, CH, W, H, cfg.tile, _ptr(means2d), _ptr(conics), _ptr(features), _ptr(opacities),
            _ptr(rect), _ptr(tile_off), _ptr(isect), _ptr(goff), _ptr(cmask), _ptr(out),
            _ptr(alpha), _ptr(tfinal), _ptr(last), _ptr(contrib), _ptr(packed), cfg.threads)
        if rc != 0:
            raise RuntimeError(f"sgpor raster kernel: unsupported configuration (code {rc})")
        ctx.cfg = cfg
        ctx.bins = bins
        ctx.shapes = (C, N, CH)
        ctx.save_for_backward(packed, tfinal, last)
        ctx.mark_non_differentiable(contrib)
        return out, alpha, contrib

    @staticmethod
    @once_differentiable
    def backward(ctx, g_out, g_alpha, _g_contrib):
        packed, tfinal, last = ctx.saved_tensors
        cfg = ctx.cfg
        C, N, CH = ctx.shapes
        dt = tfinal.dtype
        tile_off, isect, goff = ctx.bins
        g_out = torch.zeros(C, cfg.H, cfg.W, CH, dtype=dt) if g_out is None else g_out.contiguous()
        g_alpha = torch.zeros(C, cfg.H, cfg.W, 1, dtype=dt) if g_alpha is None else g_alpha.contiguous()
        g_m2 = torch.empty(C, N, 2, dtype=dt)
        g_con = torch.empty(C, N, 3, dtype=dt)
        g_f = torch.empty(C, N, CH, dtype=dt)
        g_op = torch.empty(N, dtype=dt)
        # with a grad_mask the kernel gives the other Gaussians zero gradients without computing them
        # (it still carries their transmittance); sh_bwd and project_bwd then skip them as all zero
        train = None if cfg.grad_mask is None else cfg.grad_mask.contiguous()  # (bool: one byte, 0/1)
        rc = _fn("raster_bwd", dt)(
            C, N, CH, cfg.W, cfg.H, cfg.tile, _ptr(packed), _ptr(tile_off), _ptr(isect), _ptr(goff),
            _ptr(tfinal), _ptr(last), _ptr(g_out), _ptr(g_alpha), _ptr(g_m2), _ptr(g_con), _ptr(g_f),
            _ptr(g_op), _ptr(train), cfg.threads)
        if rc != 0:
            raise RuntimeError(f"sgpor raster kernel: unsupported configuration (code {rc})")
        return g_m2, g_con, g_f, g_op, None, None, None, None


def _bin(cfg: _Cfg, depths: torch.Tensor, rect: torch.Tensor, ntiles: torch.Tensor, total: int):
    C, N = cfg.C, cfg.N
    tw = (cfg.W + cfg.tile - 1) // cfg.tile
    th = (cfg.H + cfg.tile - 1) // cfg.tile
    if total >= 2**31 - 1:
        raise RuntimeError(f"{total} tile intersections: too many for the cpu kernel (max 2^31-1)")
    tile_off = torch.empty(C * tw * th + 1, dtype=torch.int64)
    isect = torch.empty(max(total, 1), 2, dtype=torch.int32)  # (Gaussian, generation id) pairs
    goff = torch.empty(C * N + 1, dtype=torch.int64)
    _fn("bin", depths.dtype)(C, N, cfg.W, cfg.H, cfg.tile, _ptr(depths), _ptr(rect), _ptr(ntiles),
                             _ptr(tile_off), _ptr(isect), _ptr(goff), cfg.threads)
    return tile_off, isect, goff


def _project_and_bin(means, quats, scales, opacities, viewmats, Ks, width, height, near_plane, far_plane, eps2d,
                     tile_size, num_threads, grad_mask=None):
    """Projection (differentiable) and tile binning of contiguous inputs: (cfg, means2d, conics, depths,
    radii, rect, bins)."""
    if not available():
        raise RuntimeError(f"the cpu rasterizer kernel is not available: {load_error()}")
    cfg = _Cfg(W=width, H=height, near=near_plane, far=far_plane, eps2d=eps2d, tile=tile_size,
               threads=num_threads, C=viewmats.shape[0], N=means.shape[0], grad_mask=grad_mask)
    means2d, conics, depths, radii, rect, ntiles, total = _ProjectFn.apply(
        means, quats, scales, opacities, viewmats, Ks, cfg)
    bins = _bin(cfg, depths.detach(), rect, ntiles, int(total))
    return cfg, means2d, conics, depths, radii, rect, bins


def render_median(means, quats, scales, opacities, viewmats, Ks, width, height, near_plane, far_plane, eps2d,
                  contribution_mask, *, tile_size, num_threads):
    """The median depth (render_mode "MD", no gradient): (median [C,H,W,1], alpha [C,H,W,1], meta)."""
    with torch.no_grad():
        means, quats, scales, opacities = (x.detach().contiguous() for x in (means, quats, scales, opacities))
        cfg, means2d, conics, depths, radii, rect, (tile_off, isect, goff) = _project_and_bin(
            means, quats, scales, opacities, viewmats.contiguous(), Ks.contiguous(), width, height, near_plane,
            far_plane, eps2d, tile_size, num_threads)
        C, N, dt = cfg.C, cfg.N, means.dtype
        median = torch.empty(C, height, width, 1, dtype=dt)
        alpha = torch.empty(C, height, width, 1, dtype=dt)
        contrib = torch.empty(C, N, dtype=dt)
        cmask = None if contribution_mask is None else contribution_mask.contiguous().view(torch.uint8)
        rc = _fn("raster_median", dt)(
            C, N, width, height, tile_size, _ptr(means2d), _ptr(conics), _ptr(depths), _ptr(opacities),
            _ptr(rect), _ptr(tile_off), _ptr(isect), _ptr(goff), _ptr(cmask), _ptr(median), _ptr(alpha),
            _ptr(contrib), num_threads)
    if rc != 0:
        raise RuntimeError(f"sgpor raster kernel: unsupported configuration (code {rc})")
    meta = {"means2d": means2d, "radii": radii, "depths": depths, "conics": conics, "contrib": contrib}
    return median, alpha, meta


def render(means, quats, scales, opacities, colors, sh_degree, viewmats, Ks, width, height,
           near_plane, far_plane, eps2d, with_depth, contribution_mask, *, tile_size, num_threads,
           grad_mask=None):
    """Render without background; returns (render [C,H,W,CH], alpha [C,H,W,1], meta). ``grad_mask``
    [N] bool: the Gaussians outside it get zero gradients (see rasterization)."""
    C = viewmats.shape[0]
    means = means.contiguous()
    opacities = opacities.contiguous()
    viewmats = viewmats.contiguous()
    cfg, means2d, conics, depths, radii, rect, bins = _project_and_bin(
        means, quats.contiguous(), scales.contiguous(), opacities, viewmats, Ks.contiguous(), width, height,
        near_plane, far_plane, eps2d, tile_size, num_threads, grad_mask)

    feats = []
    if colors is not None:
        if sh_degree is not None:
            sh0, shN = colors if isinstance(colors, tuple) else (colors[:, :1], colors[:, 1:])
            feats.append(_SHFn.apply(means, sh0, shN, viewmats, sh_degree, num_threads))
        elif colors.dim() == 2:
            feats.append(colors[None].expand(C, -1, -1))
        else:
            feats.append(colors)
    if with_depth:
        feats.append(depths[..., None])
    features = torch.cat(feats, dim=-1) if len(feats) > 1 else feats[0].contiguous()
    cmask = None if contribution_mask is None else contribution_mask.contiguous().view(torch.uint8)
    CH = features.shape[-1]
    if CH <= 4:
        out, alpha, contrib = _RasterFn.apply(means2d, conics, features, opacities, rect, bins, cmask, cfg)
    else:  # several passes of at most 4 channels; alpha and contrib from the first
        outs = []
        alpha = contrib = None
        for k in range(0, CH, 4):
            o, a, cb = _RasterFn.apply(means2d, conics, features[..., k:k + 4].contiguous(), opacities,
                                       rect, bins, cmask, cfg)
            outs.append(o)
            if alpha is None:
                alpha, contrib = a, cb
        out = torch.cat(outs, dim=-1)
    meta = {"means2d": means2d, "radii": radii, "depths": depths, "conics": conics,
            "contrib": contrib}
    return out, alpha, meta
