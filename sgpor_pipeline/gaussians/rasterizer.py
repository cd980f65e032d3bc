"""Differentiable Gaussian rasterizer: one API, three backends (DESIGN.md section 6).

:func:`rasterization` is a documented subset of gsplat's ``rasterization()`` (gsplat 1.5):
the same argument names, the same *activated* parameter convention and the same outputs, so the
optional ``gsplat`` backend is a drop-in on CUDA machines.

Backends
--------
``cpu``
    Our C++17 kernel (``sgpor_pipeline/csrc``; no torch headers, built by setuptools, loaded with
    ctypes): tile-based, OpenMP over tiles, SIMD across a tile's pixels, hand-written backward
    whose per-intersection gradients are reduced in a fixed order, so forward and gradients are
    bitwise identical for any number of threads. float32 tensors run the float kernel, float64
    tensors the double instantiation (for gradient checks).
``torch``
    A dense pure-PyTorch reference (every pixel of a block against every Gaussian whose footprint
    rectangle touches the block); autograd does the backward; any device. Slow: for tests and as a
    fallback.
``gsplat``
    ``gsplat.rasterization`` (optional extra ``pip install sgpor-pipeline[gpu]``), CUDA tensors only.
``auto``
    gsplat for CUDA tensors when it is importable, else ``cpu`` for CPU tensors (``torch`` with a
    one-time warning when the compiled kernel is missing), else ``torch``.

Semantics shared by ``cpu`` and ``torch`` (the same rules; results agree to float rounding)
------------------------------------------------------------------------------------------
* Cameras: OpenCV axes (x right, y down, z forward), ``viewmats`` = cam_from_world, pinhole ``Ks``
  (fx, fy, cx, cy; skew ignored). Pixel (row i, column j) has its centre at (j + 0.5, i + 0.5),
  gsplat's convention, so a point projecting to u = fx x/z + cx lies in column floor(u).
* A Gaussian is culled in a camera (radius 0, no footprint) when z < near_plane or z > far_plane,
  when det of its 2D covariance <= 0, when its opacity < 1/255, or when its footprint contains no
  pixel centre.
* Quaternions (w, x, y, z) are divided by max(|q|, 1e-12): any norm works, a zero quaternion is
  the identity rotation (with zero gradient). Covariance R S S^T R^T with S = diag(scales).
* EWA: the Jacobian of the projection is evaluated at x/z, y/z clamped to the frustum widened by
  0.3 tan(half FOV) on each side (1.3x the frustum for a centred principal point; gsplat's form
  for an off-centre one); the gradient through a clamped coordinate is zero. 2D covariance +
  ``eps2d`` (0.3) I, no compensation ("classic" mode).
* Footprint: the pixels where ``sigma <= min(3.33^2/2, ln(255 o))`` with sigma = 0.5 d^T
  Sigma2D^-1 d, d = pixel centre - projected mean, i.e. an opacity-aware radius of
  ``min(3.33, sqrt(2 ln(255 o)))`` standard deviations, which is exactly where alpha >= 1/255 for
  o <= 1. A Gaussian only touches the pixel centres inside its footprint's bounding rectangle
  (columns ceil(u - h_x - 0.5) .. floor(u + h_x - 0.5), h_x = sqrt(2 thr Sigma2D_xx); rows
  likewise), a per-Gaussian rule, so the tile size cannot change the image (the ``cpu`` kernel's
  forward is bitwise identical for 8x8 and 16x16 tiles). The footprint edges are hard: they pass
  no gradient.
* alpha = min(0.99, o exp(-sigma)); a pair with alpha < 1/255 is skipped. Gaussians are composited
  front to back in increasing camera z (ties by index). Transmittance T starts at 1; a pixel stops
  *before* adding a Gaussian when T (1 - alpha) < 1e-4 (3DGS), so the returned alpha is
  1 - T_final <= 1 - 1e-4. Colour = sum_i alpha_i T_i c_i + T_final * background.
* SH colours: direction from the camera centre to the mean, real SH up to degree 3 (3DGS/gsplat
  constants), + 0.5, clamped at 0 (the clamp passes no gradient).
* Gradients flow to means, quats, scales, opacities, colors/SH and backgrounds; none flows to
  ``viewmats`` or ``Ks`` (they are detached).

Threads and determinism (``cpu``): ``num_threads`` (default: env ``SGPOR_NUM_THREADS``, else
``torch.get_num_threads()``) only changes speed: each tile writes its per-intersection gradient
records into a buffer indexed by intersection, then every Gaussian sums its own records in a fixed
order, so images and gradients are bitwise identical for any thread count; and for the AVX2 and
AVX-512 builds of the kernel (a tile row's SIMD lanes are summed in a fixed tree): a 400-iteration
demo fit was bitwise the same with either build, and with torch's own AVX2 or AVX-512 kernels. Phases worth less than
~1.5 ms run on one thread (a parallel region can cost a whole scheduler time slice on a busy
machine). On the 2-core development machine (AMD EPYC, AVX-512 build), 50k Gaussians at 256x192
take about 30 ms for forward + backward with 2 threads on an idle machine, ~30x less than the
``torch`` reference; see ``benchmarks/rasterizer.py``.

The ``gsplat`` backend follows gsplat's own rules, which differ in small ways (alpha is clamped
to 0.999 there, its 2D radius and tile test differ slightly); meta["contrib"] is computed there
with an extra rasterization.
"""

from __future__ import annotations

import os
import warnings
from typing import Any

import torch

from . import _raster_torch
from ._raster_common import (
    RENDER_MODES,
    NonFiniteInputError,
    RasterizerInputError,
    sh_colors,
)

__all__ = ["rasterization", "cpu_kernel_available", "RasterizerInputError", "NonFiniteInputError"]

BACKENDS = ("auto", "cpu", "torch", "gsplat")
_warned: set[str] = set()


def _warn_once(key: str, message: str) -> None:
    if key not in _warned:
        _warned.add(key)
        warnings.warn(message, RuntimeWarning, stacklevel=3)


def cpu_kernel_available() -> bool:
    """Whether the compiled C++ kernel of the ``cpu`` backend could be loaded."""
    from . import _raster_cpu

    return _raster_cpu.available()


def _default_threads() -> int:
    env = os.environ.get("SGPOR_NUM_THREADS")
    if env:
        return max(1, int(env))
    return max(1, torch.get_num_threads())


def _check_tensor(name: str, x: Any, shape: tuple, ndim: int | tuple[int, ...] | None = None) -> None:
    if not isinstance(x, torch.Tensor):
        raise RasterizerInputError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    ndims = (ndim,) if isinstance(ndim, int) else ndim
    if ndims is not None and x.dim() not in ndims:
        raise RasterizerInputError(f"{name} must have {' or '.join(map(str, ndims))} dimensions, "
                                   f"got shape {tuple(x.shape)}")
    if shape and (len(shape) != x.dim() or any(s is not None and s != d for s, d in zip(shape, x.shape))):
        want = "[" + ",".join("*" if s is None else str(s) for s in shape) + "]"
        raise RasterizerInputError(f"{name} must have shape {want}, got {tuple(x.shape)}")


def count_non_finite(x: torch.Tensor) -> int:
    """Number of NaN/inf values of a floating-point tensor (0 for other dtypes).

    CPU float32/float64: the kernel's bit scan (``torch.isfinite`` with ``.all()`` is about 50x
    slower on the CPU wheel here: it was a fifth of a fit's time, see the trainer's NaN guard);
    elsewhere one torch reduction."""
    if not x.is_floating_point() or x.numel() == 0:
        return 0
    from . import _raster_cpu

    x = x.detach()
    bad = _raster_cpu.count_nonfinite(x)  # CPU: the kernel's scan, no torch op
    if bad is None:
        lo, hi = torch.aminmax(x)  # NaN propagates; one reduction instead of two
        bad = 0 if bool(torch.isfinite(lo) & torch.isfinite(hi)) else int((~torch.isfinite(x)).sum())
    return bad


def first_non_finite(tensors: dict[str, torch.Tensor | None]) -> str | None:
    """The name of the first tensor of ``tensors`` holding NaN/inf (None entries skipped), or None.
    Tensors on one GPU are checked together, with one synchronisation (the trainer checks 12 per
    iteration)."""
    items = [(n, t) for n, t in tensors.items() if t is not None and t.is_floating_point() and t.numel()]
    devices = {t.device for _, t in items}
    if len(devices) == 1 and next(iter(devices)).type != "cpu":
        ok = torch.stack([torch.isfinite(t.detach()).all() for _, t in items]).tolist()
        return next((n for (n, _), good in zip(items, ok) if not good), None)
    return next((n for n, t in items if count_non_finite(t)), None)


def _validate(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane,
              far_plane, sh_degree, backgrounds, render_mode, tile_size, contribution_mask,
              check_finite=True, grad_mask=None):
    """Checks every argument; returns (N, C, D) with D the number of colour channels (0 for D/ED)."""
    _check_tensor("means", means, (None, 3), 2)
    N = means.shape[0]
    if means.dtype not in (torch.float32, torch.float64):
        raise RasterizerInputError(f"means must be float32 or float64, got {means.dtype}")
    dev, dt = means.device, means.dtype
    _check_tensor("quats", quats, (N, 4))
    _check_tensor("scales", scales, (N, 3))
    _check_tensor("opacities", opacities, (N,))
    _check_tensor("viewmats", viewmats, (None, 4, 4), 3)
    C = viewmats.shape[0]
    _check_tensor("Ks", Ks, (C, 3, 3))
    if C == 0:
        raise RasterizerInputError("viewmats holds no camera (C = 0)")
    for name, x in (("quats", quats), ("scales", scales), ("opacities", opacities),
                    ("viewmats", viewmats), ("Ks", Ks)):
        if not x.is_floating_point():
            raise RasterizerInputError(f"{name} must be a floating-point tensor, got {x.dtype}")
        if x.device != dev:
            raise RasterizerInputError(f"{name} is on {x.device} but means is on {dev}")
    for name, x in (("quats", quats), ("scales", scales), ("opacities", opacities)):
        if x.dtype != dt:
            raise RasterizerInputError(f"{name} is {x.dtype} but means is {dt}: use one dtype")
    if render_mode not in RENDER_MODES:
        raise RasterizerInputError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    for name, val in (("width", width), ("height", height)):
        if isinstance(val, bool) or not isinstance(val, int) or val <= 0:
            raise RasterizerInputError(f"{name} must be a positive int, got {val!r}")
    if not (near_plane > 0 and far_plane > near_plane):
        raise RasterizerInputError(f"need 0 < near_plane < far_plane, got {near_plane}, {far_plane}")
    if tile_size not in (8, 16):
        raise RasterizerInputError(f"tile_size must be 8 or 16, got {tile_size!r}")
    want_color = render_mode in ("RGB", "RGB+D", "RGB+ED")
    D = 0
    if sh_degree is not None:
        if isinstance(sh_degree, bool) or not isinstance(sh_degree, int) or not 0 <= sh_degree <= 3:
            raise RasterizerInputError(f"sh_degree must be None or an int in 0..3, got {sh_degree!r}")
        if isinstance(colors, tuple):  # (sh0 [N,1,3], shN [N,K-1,3])
            if len(colors) != 2:
                raise RasterizerInputError(f"SH colors as a tuple must be (sh0, shN), got {len(colors)} items")
            _check_tensor("colors[0] (sh0)", colors[0], (N, 1, 3), 3)
            _check_tensor("colors[1] (shN)", colors[1], (N, None, 3), 3)
            K = 1 + colors[1].shape[1]
        else:
            _check_tensor("colors", colors, (N, None, 3), 3)
            K = colors.shape[1]
        if K < (sh_degree + 1) ** 2:
            raise RasterizerInputError(f"colors has {K} SH coefficients, sh_degree "
                                       f"{sh_degree} needs {(sh_degree + 1) ** 2}")
        D = 3
    elif colors is not None:
        _check_tensor("colors", colors, (), (2, 3))
        if colors.dim() == 2 and colors.shape[0] != N:
            raise RasterizerInputError(f"colors must be [N,D] or [C,N,D] with N={N}, C={C}, got "
                                       f"{tuple(colors.shape)} (SH coefficients need sh_degree)")
        if colors.dim() == 3 and colors.shape[:2] != (C, N):
            raise RasterizerInputError(f"colors must be [N,D] or [C,N,D] with N={N}, C={C}, got "
                                       f"{tuple(colors.shape)} (SH coefficients need sh_degree)")
        D = colors.shape[-1]
        if D == 0:
            raise RasterizerInputError("colors has zero channels")
    elif want_color:
        raise RasterizerInputError(f"render_mode {render_mode!r} needs colors")
    for c in (colors if isinstance(colors, tuple) else (colors,)):
        if c is not None and (c.device != dev or c.dtype != dt):
            raise RasterizerInputError(f"colors must be {dt} on {dev}, got {c.dtype} on {c.device}")
    if not want_color:
        D = 0
    if backgrounds is not None:
        if not want_color:
            backgrounds = None
        else:
            _check_tensor("backgrounds", backgrounds, (), (1, 2))
            if backgrounds.shape[-1] != D or (backgrounds.dim() == 2 and backgrounds.shape[0] != C):
                raise RasterizerInputError(f"backgrounds must be [C,D] or [D] with C={C}, D={D}, "
                                           f"got {tuple(backgrounds.shape)}")
            if backgrounds.device != dev or not backgrounds.is_floating_point():
                raise RasterizerInputError("backgrounds must be a floating-point tensor on the "
                                           "device of means")
    if contribution_mask is not None:
        _check_tensor("contribution_mask", contribution_mask, (C, height, width), 3)
        if contribution_mask.dtype != torch.bool or contribution_mask.device != dev:
            raise RasterizerInputError("contribution_mask must be a bool tensor on the device of means")
    if grad_mask is not None:
        _check_tensor("grad_mask", grad_mask, (N,))
        if grad_mask.dtype != torch.bool or grad_mask.device != dev:
            raise RasterizerInputError("grad_mask must be a bool tensor on the device of means")
    inputs = {"means": means, "quats": quats, "scales": scales, "opacities": opacities}
    inputs.update({"colors[0] (sh0)": colors[0], "colors[1] (shN)": colors[1]} if isinstance(colors, tuple)
                  else {"colors": colors})
    inputs.update({"viewmats": viewmats, "Ks": Ks, "backgrounds": backgrounds})
    bad = first_non_finite(inputs) if check_finite else None  # on a GPU one synchronisation for all
    if bad is not None:
        raise NonFiniteInputError(
            f"rasterization(): {bad} holds {count_non_finite(inputs[bad])} NaN/inf value(s)",
            fix=f"find where {bad} became non-finite (a diverging optimisation: lower the "
                "learning rate, or check the data the Gaussians were initialised from)")
    return N, C, D, backgrounds


def _resolve_backend(backend: str, device: torch.device) -> str:
    if backend not in BACKENDS:
        raise RasterizerInputError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "gsplat":
        from . import _raster_gsplat

        _raster_gsplat.require(device)
        return "gsplat"
    if backend == "auto":
        if device.type == "cuda":
            from . import _raster_gsplat

            if _raster_gsplat.importable():
                return "gsplat"
            return "torch"
        if device.type != "cpu":
            return "torch"
        backend = "cpu"
    if backend == "cpu":
        if device.type != "cpu":
            raise RasterizerInputError(f"backend='cpu' needs CPU tensors, got {device}")
        from . import _raster_cpu

        if not _raster_cpu.available():
            _warn_once("nokernel", "sgpor_pipeline: the compiled rasterizer kernel is missing "
                       f"({_raster_cpu.load_error()}); using the slow torch reference. Reinstall "
                       "with a C++ compiler (pip install -e .) to build it.")
            return "torch"
        return "cpu"
    return backend


def rasterization(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor | tuple[torch.Tensor, torch.Tensor] | None,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    sh_degree: int | None = None,
    backgrounds: torch.Tensor | None = None,
    render_mode: str = "RGB",
    backend: str = "auto",
    tile_size: int = 16,
    contribution_mask: torch.Tensor | None = None,
    eps2d: float = 0.3,
    num_threads: int | None = None,
    torch_block: int | None = 16,
    check_finite: bool = True,
    grad_mask: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, dict[str, Any]]:
    """Render N 3D Gaussians into C pinhole cameras; differentiable w.r.t. the Gaussians.

    Parameters are the **activated** values, as in gsplat (the fitted model stores log-scales and
    opacity logits: pass ``exp(log_scales)`` and ``sigmoid(logits)``).

    Args:
        means: [N,3] centres in world coordinates; float32 (fast kernel) or float64 (double kernel,
            for gradient checks). Every other float input must have this dtype and device
            (``viewmats`` and ``Ks`` are cast to it).
        quats: [N,4] rotations (w, x, y, z), any norm (normalised in the kernel; 0 = identity).
        scales: [N,3] linear standard deviations along the rotated axes (>= 0; 0 is allowed).
        opacities: [N] in [0, 1].
        colors: [N,D] or [C,N,D] colours/features (D channels; D <= 4 per kernel pass on ``cpu``,
            more channels are rendered in several passes), or [N,K,3] SH coefficients when
            ``sh_degree`` is set (K >= (sh_degree+1)^2), or those as the pair ``(sh0 [N,1,3],
            shN [N,K-1,3])``: the DC term and the rest, as a model stores them (the ``cpu`` kernel
            reads them in place and returns their gradients without a copy; other backends
            concatenate). May be None for ``render_mode`` "D"/"ED".
        viewmats: [C,4,4] cam_from_world, OpenCV axes. No gradient.
        Ks: [C,3,3] pinhole intrinsics (skew ignored). No gradient.
        width, height: image size in pixels.
        near_plane, far_plane: Gaussians with camera z outside [near, far] are culled.
        sh_degree: None for plain colours, else 0..3.
        backgrounds: [C,D] or [D] colour composited behind the Gaussians (colour channels only).
        render_mode: "RGB" (colours), "D" (accumulated depth sum_i w_i z_i), "ED" (expected depth,
            D / alpha), "RGB+D", "RGB+ED" (depth as the last channel), "MD" (median depth: the
            depth of the Gaussian at which the transmittance first falls to 0.5 or below, 0 where
            it never does; on a surface, where the expected depth lies in front of it; backends
            ``cpu`` and ``torch``; no gradient).
        backend: "auto", "cpu", "torch" or "gsplat" (see the module docstring).
        tile_size: 8 or 16 pixels (``cpu``, ``gsplat``); never changes the image.
        contribution_mask: [C,H,W] bool; restricts meta["contrib"] to these pixels.
        eps2d: added to the 2D covariance diagonal (0.3, DESIGN's value).
        num_threads: threads of the ``cpu`` kernel (default: env SGPOR_NUM_THREADS, else
            ``torch.get_num_threads()``); results are bitwise identical for any value.
        torch_block: pixel block edge of the ``torch`` backend (None = the whole image at once).
        check_finite: scan the inputs for NaN/inf (NonFiniteInputError). False is for a caller that
            has just checked them itself, as the trainer does after every step (the scan reads every
            input once: 0.8 ms at 95k Gaussians with degree-3 SH on 2 cores, a GPU synchronisation).
        grad_mask: [N] bool, the Gaussians that get gradients: the others' gradients (means, quats,
            scales, opacities, colours; on ``cpu`` also ``meta["means2d"]``'s) are exactly zero, the
            masked-in ones' bitwise unchanged. The ``cpu`` kernel then skips the others' gradient
            work: in the raster backward it only carries their transmittance, and not even that in
            front of a tile's frontmost masked-in Gaussian; their SH and projection gradients are
            skipped (a re-fit of a few Gaussians among many: statue's finetune trains 30k of 359k;
            per view sh_bwd 25 -> 17 ms and project_bwd 10.5 -> 6.8 ms by cProfile, raster_bwd 40 -> 18
            ms by the kernel's phase timer).

    Returns:
        ``(render_colors, render_alphas, meta)``:

        * render_colors [C,H,W,X]: X = D for "RGB", 1 for "D"/"ED"/"MD", D+1 for "RGB+D"/"RGB+ED".
        * render_alphas [C,H,W,1]: accumulated opacity 1 - T_final.
        * meta: ``means2d`` [C,N,2] projected centres in pixels (a non-leaf tensor of the graph:
          call ``meta["means2d"].retain_grad()`` before ``backward()`` to read its ``.grad``, as
          densification does; zero for culled Gaussians), ``radii`` [C,N] int32 (pixel radius of
          the footprint's bounding box, 0 = culled), ``depths`` [C,N] camera z, ``conics`` [C,N,3]
          (a, b, c of the inverse 2D covariance), ``contrib`` [C,N] (sum over the pixels, or the
          pixels of ``contribution_mask``, of the blending weight alpha*T; no gradient),
          ``width``, ``height``, ``n_cameras``, ``tile_size``, ``backend`` (the one that ran).

    Raises:
        RasterizerInputError (a ValueError): wrong shape, dtype, device or option.
        NonFiniteInputError (a ValueError and a NonFiniteError): NaN/inf in an input; the message
            names the argument.
    """
    N, C, D, backgrounds = _validate(means, quats, scales, opacities, colors, viewmats, Ks, width,
                                     height, near_plane, far_plane, sh_degree, backgrounds,
                                     render_mode, tile_size, contribution_mask, check_finite, grad_mask)
    which = _resolve_backend(backend, means.device)
    if grad_mask is not None and which != "cpu":  # (the cpu kernel masks its own gradient records)
        means, quats, scales, opacities = (_mask_grad(x, grad_mask) for x in (means, quats, scales, opacities))
        if isinstance(colors, tuple):
            colors = tuple(_mask_grad(x, grad_mask) for x in colors)
        elif colors is not None:  # [N,D] and [N,K,3] (SH) along dim 0, [C,N,D] along dim 1
            colors = _mask_grad(colors, grad_mask, dim=1 if colors.dim() == 3 and sh_degree is None else 0)
    viewmats = viewmats.detach().to(means.dtype)
    Ks = Ks.detach().to(means.dtype)
    with_depth = render_mode != "RGB"
    if D == 0:
        colors = None
    elif isinstance(colors, tuple) and which != "cpu":  # (the cpu kernel reads the two parts in place)
        colors = torch.cat(colors, dim=1)
    if render_mode == "MD" and which == "gsplat":
        raise RasterizerInputError("render_mode 'MD' (median depth) is not available in the gsplat backend",
                                   fix="render it with backend='cpu' (CPU tensors) or 'torch'")
    if which == "gsplat":
        from . import _raster_gsplat

        render, alpha, meta = _raster_gsplat.rasterization(
            means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane,
            far_plane, sh_degree, backgrounds, render_mode, tile_size, contribution_mask, eps2d)
    else:
        args = (means, quats, scales, opacities, colors, sh_degree, viewmats, Ks, width, height,
                float(near_plane), float(far_plane), float(eps2d), with_depth, contribution_mask)
        if which == "cpu":
            from . import _raster_cpu

            threads = _default_threads() if num_threads is None else max(1, int(num_threads))
            if render_mode == "MD":
                render, alpha, meta = _raster_cpu.render_median(
                    means, quats, scales, opacities, viewmats, Ks, width, height, float(near_plane),
                    float(far_plane), float(eps2d), contribution_mask, tile_size=tile_size, num_threads=threads)
            else:
                render, alpha, meta = _raster_cpu.render(*args, tile_size=tile_size, num_threads=threads,
                                                         grad_mask=grad_mask)
        else:
            render, alpha, meta = _render_torch(*args, block=torch_block, median=render_mode == "MD")
        if backgrounds is not None:
            bg = backgrounds if backgrounds.dim() == 2 else backgrounds[None].expand(C, -1)
            bg = bg.to(render.dtype)[:, None, None, :]
            rgb = render[..., :D] + (1.0 - alpha) * bg
            render = torch.cat([rgb, render[..., D:]], dim=-1) if with_depth else rgb
        if render_mode in ("ED", "RGB+ED"):
            render = torch.cat([render[..., :-1], render[..., -1:] / alpha.clamp(min=1e-10)], dim=-1)
    meta.update({"width": width, "height": height, "n_cameras": C, "tile_size": tile_size,
                 "backend": which})
    return render, alpha, meta


class _MaskGrad(torch.autograd.Function):
    """The identity; its gradient is zero along ``dim`` where ``mask`` is False."""

    @staticmethod
    def forward(ctx, x, mask, dim):  # type: ignore[override]
        shape = [1] * x.dim()
        shape[dim] = -1
        ctx.save_for_backward(mask.view(shape))
        return x.view_as(x)

    @staticmethod
    def backward(ctx, g):  # type: ignore[override]
        (m,) = ctx.saved_tensors
        return g * m.to(g.dtype), None, None


def _mask_grad(x: torch.Tensor, mask: torch.Tensor, dim: int = 0) -> torch.Tensor:
    return _MaskGrad.apply(x, mask, dim) if x.requires_grad else x


def _render_torch(means, quats, scales, opacities, colors, sh_degree, viewmats, Ks, width, height,
                  near_plane, far_plane, eps2d, with_depth, contribution_mask, block, median=False):
    C = viewmats.shape[0]
    proj = _raster_torch.project(means, quats, scales, opacities, viewmats, Ks, width, height,
                                 near_plane, far_plane, eps2d)
    feats = []
    if colors is not None:
        if sh_degree is not None:
            feats.append(sh_colors(means, colors, sh_degree, viewmats))
        elif colors.dim() == 2:
            feats.append(colors[None].expand(C, -1, -1))
        else:
            feats.append(colors)
    if with_depth:
        feats.append(proj["depths"][..., None])
    features = torch.cat(feats, dim=-1) if len(feats) > 1 else feats[0]
    render, alpha, contrib = _raster_torch.rasterize(proj, features, opacities, width, height,
                                                     contribution_mask, block, median=median)
    meta = {"means2d": proj["means2d"], "radii": proj["radii"], "depths": proj["depths"],
            "conics": proj["conics"], "contrib": contrib}
    return render, alpha, meta
