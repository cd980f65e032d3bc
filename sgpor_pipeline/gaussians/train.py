"""The Gaussian Splatting training loop (reused by the fit and finetune stages).

:class:`Trainer` fits a :class:`~sgpor_pipeline.gaussians.model.GaussianModel` to posed images:

* loss ``(1 - lambda) L1 + lambda (1 - SSIM)`` (lambda 0.2; SSIM with an 11-tap Gaussian window,
  sigma 1.5, reflect padding: the same map as ``kornia.metrics.ssim``; on a CPU the kernel's fused
  SSIM, ``csrc/ssim.h``, elsewhere torch with an analytic backward, see :func:`ssim_mean`), plus the
  strategy's regularisers;
* one Adam per parameter (eps 1e-15, fused CPU kernel when available) with the 3DGS learning rates:
  means 1.6e-4 -> 1.6e-6 (exponential over the run) x scene extent, SH DC 2.5e-3, SH rest /20,
  opacity 5e-2, log-scales 5e-3, quaternions 1e-3;
* the active SH degree raised by one every ``sh_degree_every`` iterations up to ``sh_degree``;
* optionally a coarse phase: the first ``coarse_until`` of the iterations on the views downscaled by
  ``coarse_factor`` (a speed option; measured in the fit stage's ``FitParams``);
* only the strategy's ``grad_mask()`` Gaussians get gradients when it gives one (the finetune's
  trainable set: the rasterizer then skips the others' gradient work); when they are the last rows
  (the finetune orders them so), Adam steps only that tail, with the same bits;
* densification by a :mod:`~sgpor_pipeline.gaussians.strategy` under a budget; with an automatic
  budget the cap starts proportional to the training pixels and grows while the training error
  still falls by more than ``budget_min_gain`` per growth window (:class:`BudgetController`);
* checkpoints (model, Adam moments, strategy state, RNG, curve, iteration) written atomically
  every ``checkpoint_every`` iterations and every ``checkpoint_seconds``; :meth:`Trainer.train`
  resumes from one when it finds it;
* a NaN guard (the kernel's bit scan on a CPU: ``torch.isfinite`` is slow there): a NaN/inf in the
  loss, a gradient or a parameter (scanned when loaded and after the strategy changed it: Adam keeps
  finite parameters finite) is reported by name and training rolls back to the last
  in-memory snapshot with the learning rates halved; more than
  ``max_rollbacks`` rollbacks without progress raise :class:`~sgpor_pipeline.errors.NonFiniteError`;
* evaluation on held-out views (PSNR, SSIM) every ``eval_every`` iterations, and a training curve.
"""

from __future__ import annotations

import copy
import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import NonFiniteError, PipelineError
from ..scene import Camera
from . import _raster_cpu
from .model import GaussianModel
from .pose import PoseRefineParams, PoseRefiner
from .rasterizer import NonFiniteInputError, _default_threads, first_non_finite, rasterization
from .strategy import Strategy

CHECKPOINT_NAME = "fit_checkpoint.pt"
CHECKPOINT_FORMAT = 1

log = logging.getLogger("sgpor_pipeline.train")


@dataclass
class TrainParams:
    """Knobs of the training loop (the fit stage's parameters map onto these)."""

    iterations: int = 2000
    sh_degree: int = 3
    sh_degree_every: int = 500  # raise the active SH degree by one every this many iterations
    lambda_dssim: float = 0.2
    # the first coarse_until x iterations train on the views downscaled by coarse_factor (a coarse
    # render costs about 1 / factor^2 of the pixel work); 0 = always at full resolution
    coarse_until: float = 0.0
    coarse_factor: int = 2
    lr_means: float = 1.6e-4  # x scene extent, decays exponentially to lr_means_final
    lr_means_final: float = 1.6e-6
    lr_sh0: float = 2.5e-3
    lr_shN_factor: float = 1.0 / 20.0  # SH rest learning rate = lr_sh0 x this
    lr_opacities: float = 5e-2
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    seed: int = 0
    backend: str = "auto"
    # where the parameters, images and optimiser live: "cpu", "cuda[:i]", or "auto" (see resolve_device)
    device: str = "cpu"
    checkpoint_every: int = 500  # iterations; 0 = only by time
    checkpoint_seconds: float = 30.0  # also checkpoint when this much time passed; 0 = only by count
    eval_every: int = 500  # held-out evaluation period (iterations); 0 = only at the end
    log_every: int = 50  # curve sampling period (iterations)
    snapshot_every: int = 50  # in-memory rollback snapshots for the NaN guard
    max_rollbacks: int = 3  # consecutive rollbacks (no progress in between) before giving up
    rollback_lr_factor: float = 0.5
    # automatic budget (BudgetController)
    budget: int | None = None  # fixed Gaussian budget; None or 0 = automatic
    budget_per_pixel: float = 0.03  # automatic start: this many Gaussians per training pixel
    budget_max_per_pixel: float = 0.25  # automatic hard maximum per training pixel
    budget_min: int = 5_000
    budget_max: int = 2_000_000
    budget_growth: float = 1.5  # cap x this per growth step
    budget_min_gain: float = 0.05  # grow while the training loss falls by more than this (relative) ...
    budget_window: int = 300  # ... over this many iterations at the cap
    # test hooks (documented; never set them in production)
    debug_inject_nan_at: int = 0  # write a NaN into means[0] after the optimizer step of this iteration
    debug_inject_nan_times: int = 1  # how many times the injection fires (each time the iteration is reached)
    # learn a pose correction per training view with the Gaussians (see sgpor_pipeline.gaussians.pose);
    # None = the poses are fixed
    pose_refine: PoseRefineParams | None = None


# --------------------------------------------------------------------------------------------------
# data


@dataclass
class TrainView:
    """One posed image at the training resolution."""

    name: str
    image: torch.Tensor  # [H,W,3] float32 in [0,1]
    camera: Camera
    weight: torch.Tensor | None = None  # [H,W] float32 per-pixel loss weight (None = all 1)
    # The view's loss is multiplied by this: a crop of a larger image (the finetune's) gives its loss
    # the weight its pixels have in the whole image's mean, so its gradients are the whole image's.
    loss_scale: float = 1.0
    # A low-pass term (:func:`view_loss`): on these pixels ([H,W] weight, >= 0; best 0 in ``weight``
    # there) the render and the image are compared (L1) only after both are blurred by a Gaussian of
    # ``lowpass_sigma`` px, so the detail there is left free. Its weight counts in the view's loss
    # normaliser as ``weight``'s does. None: no such term.
    lowpass: torch.Tensor | None = None
    lowpass_sigma: float = 0.0

    @property
    def viewmat(self) -> torch.Tensor:
        return torch.from_numpy(self.camera.cam_from_world).float()[None]

    @property
    def K(self) -> torch.Tensor:
        return torch.from_numpy(self.camera.K).float()[None]


def resolve_device(device: str, backend: str = "auto") -> torch.device:
    """The trainer's device. "auto" is CUDA when a GPU is present and the rasterizer backend runs
    there fast (``backend`` "auto" or "gsplat" with gsplat installed), else the CPU; our ``cpu``
    kernel and the other stages stay on the CPU either way."""
    if device == "auto":
        if backend in ("auto", "gsplat") and torch.cuda.is_available():
            from . import _raster_gsplat

            if _raster_gsplat.importable():
                return torch.device("cuda", torch.cuda.current_device())
        return torch.device("cpu")
    try:
        dev = torch.device(device)
    except RuntimeError:
        raise ValueError(f"device must be 'auto', 'cpu' or 'cuda[:i]', got {device!r}") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {device!r} asked for, but torch sees no CUDA device (torch "
                         f"{torch.__version__}); use device 'auto' or 'cpu'")
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"device must be 'auto', 'cpu' or 'cuda[:i]', got {device!r}")
    if dev.type == "cuda" and dev.index is None:  # as tensors report it, so devices compare equal
        dev = torch.device("cuda", torch.cuda.current_device())
    return dev


def stage_device(stage: str, device: str, backend: str = "auto") -> torch.device:
    """:func:`resolve_device` for a stage's ``device`` parameter: a bad or unavailable device is a
    :class:`PipelineError` that names ``<stage>.device`` and the settings that work."""
    try:
        return resolve_device(device, backend)
    except ValueError as e:
        raise PipelineError(f"{stage}.device: {e}", fix=f"set {stage}.device=auto (the GPU when there is one) or "
                                                       f"{stage}.device=cpu") from None


def training_size(width: int, height: int, max_size: int) -> tuple[int, int]:
    """Image size whose longer side is at most ``max_size`` (0 = unchanged), aspect kept."""
    if max_size <= 0 or max(width, height) <= max_size:
        return width, height
    s = max_size / max(width, height)
    return max(1, round(width * s)), max(1, round(height * s))


def make_view(name: str, image: np.ndarray, camera: Camera, max_size: int = 0,
              weight: np.ndarray | None = None, lowpass: np.ndarray | None = None,
              lowpass_sigma: float = 0.0) -> TrainView:
    """A :class:`TrainView` from an HxWx3 image (uint8 or float in [0,1]), downscaled (INTER_AREA) so
    its longer side is at most ``max_size``; the intrinsics are scaled with it. ``weight`` (HxW, the
    per-pixel loss weight) and ``lowpass`` (HxW, the low-pass term's weight; its ``lowpass_sigma`` in
    the image's px) are resized with the image."""
    import cv2

    img = np.asarray(image)
    if img.dtype == np.uint8:
        img = img.astype(np.float32) / 255.0
    img = img.astype(np.float32)
    h, w = img.shape[:2]
    if (camera.width, camera.height) != (w, h):
        camera = camera.scaled(w, h)
    tw, th = training_size(w, h, max_size)
    if (tw, th) != (w, h):
        img = cv2.resize(img, (tw, th), interpolation=cv2.INTER_AREA)
        camera = camera.scaled(tw, th)

    def resized(a: np.ndarray | None, what: str) -> torch.Tensor | None:
        if a is None:
            return None
        a = np.asarray(a, np.float32)
        if a.shape != (h, w):
            raise ValueError(f"{what} of {name}: shape {a.shape} != image {(h, w)}")
        if (tw, th) != (w, h):
            a = cv2.resize(a, (tw, th), interpolation=cv2.INTER_AREA)
        return torch.from_numpy(np.ascontiguousarray(a))

    return TrainView(name, torch.from_numpy(np.ascontiguousarray(img)), camera, resized(weight, "weight"),
                     lowpass=resized(lowpass, "low-pass weight"), lowpass_sigma=lowpass_sigma * tw / w)


def scene_extent(cameras: Sequence[Camera]) -> float:
    """3DGS's ``cameras_extent``: 1.1 x the largest distance of a camera centre from their mean
    (at least a small positive number so a single camera works)."""
    centers = np.array([c.center for c in cameras])
    radius = float(np.max(np.linalg.norm(centers - centers.mean(0), axis=1))) if len(centers) else 0.0
    return 1.1 * max(radius, 1e-6)


# --------------------------------------------------------------------------------------------------
# losses and metrics


def _gauss_window(dtype: torch.dtype) -> torch.Tensor:
    x = torch.arange(11, dtype=torch.float64) - 5
    g = torch.exp(-(x * x) / (2 * 1.5 * 1.5))
    return (g / g.sum()).to(dtype)


def ssim_map(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """SSIM map of images [B,C,H,W]: the same definition as ``kornia.metrics.ssim(x, y, 11)`` (Gaussian
    window 11 taps, sigma 1.5, reflect padding, C1 = 0.01^2, C2 = 0.03^2, eps 1e-12), but the five
    local moments are filtered together in one grouped separable convolution (about twice as fast
    on a CPU as kornia's five filter calls)."""
    b, c, h, w = x.shape
    g = _gauss_window(x.dtype).to(x.device)
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=1)
    n = stack.shape[1]
    stack = F.pad(stack, (5, 5, 5, 5), mode="reflect")
    stack = F.conv2d(stack, g.view(1, 1, 1, 11).expand(n, 1, 1, 11), groups=n)
    stack = F.conv2d(stack, g.view(1, 1, 11, 1).expand(n, 1, 11, 1), groups=n)
    mu1, mu2, e11, e22, e12 = stack.split(c, dim=1)
    m11, m22, m12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    num = (2 * m12 + c1) * (2 * (e12 - m12) + c2)
    den = (m11 + m22 + c1) * ((e11 - m11) + (e22 - m22) + c2)
    return num / (den + 1e-12)


_PAD = 5  # half window of the 11-tap SSIM filter


def _blur(z: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Separable 11-tap filter of [C,H,W] with reflect padding (= F.pad reflect + conv), computed with
    in-place shifted adds: no im2col, no grouped convolution (slow on CPUs in NCHW)."""
    h, w = z.shape[-2:]
    zp = F.pad(z[None], (_PAD,) * 4, mode="reflect")[0]
    a = zp[..., 0:w] * g[0]
    for k in range(1, 2 * _PAD + 1):
        a.add_(zp[..., k:k + w], alpha=float(g[k]))
    b = a[..., 0:h, :] * g[0]
    for k in range(1, 2 * _PAD + 1):
        b.add_(a[..., k:k + h, :], alpha=float(g[k]))
    return b


def _blur_adjoint(gz: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """The adjoint (transpose) of :func:`_blur`: the gradient of <_blur(z), gz> with respect to z."""
    c, h, w = gz.shape
    ta = gz.new_zeros(c, h + 2 * _PAD, w)
    for k in range(2 * _PAD + 1):
        ta[:, k:k + h, :].add_(gz, alpha=float(g[k]))
    tz = gz.new_zeros(c, h + 2 * _PAD, w + 2 * _PAD)
    for k in range(2 * _PAD + 1):
        tz[..., k:k + w].add_(ta, alpha=float(g[k]))
    # fold the reflect padding back: padded row i < 5 came from row 5 - i, padded row h+5+j from h-2-j
    r = tz[:, _PAD:h + _PAD, :].clone()
    r[:, 1:_PAD + 1, :] += tz[:, 0:_PAD, :].flip(1)
    r[:, h - _PAD - 1:h - 1, :] += tz[:, h + _PAD:h + 2 * _PAD, :].flip(1)
    out = r[..., _PAD:w + _PAD].clone()
    out[..., 1:_PAD + 1] += r[..., 0:_PAD].flip(-1)
    out[..., w - _PAD - 1:w - 1] += r[..., w + _PAD:w + 2 * _PAD].flip(-1)
    return out


def _ssim_weight_map(weight: torch.Tensor, channels: int, dtype: torch.dtype) -> torch.Tensor:
    """Per-pixel factors [H,W] that turn the sum of an SSIM map over ``channels`` into its weighted mean."""
    return (weight / (weight.sum().clamp_min(1e-12) * channels)).to(dtype)


class _SSIMMean(torch.autograd.Function):
    """Mean SSIM of two [C,H,W] images (the definition of ``kornia.metrics.ssim(x, y, 11)``) with an
    analytic backward to ``x`` only (``y`` is the target): about 5x faster than autograd through
    grouped convolutions on a CPU."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, y: torch.Tensor,  # type: ignore[override]
                weight: torch.Tensor | None = None) -> torch.Tensor:
        g = _gauss_window(x.dtype)
        c = x.shape[0]
        mom = _blur(torch.cat([x, y, x * x, y * y, x * y], dim=0), g)
        mu1, mu2, e11, e22, e12 = mom.split(c, dim=0)
        m12 = mu1 * mu2
        m11 = mu1 * mu1
        m22 = mu2 * mu2
        c1, c2 = 0.01 ** 2, 0.03 ** 2
        A = 2 * m12 + c1
        B = 2 * (e12 - m12) + c2
        C = m11 + m22 + c1
        D = (e11 - m11) + (e22 - m22) + c2
        den = C * D + 1e-12
        s = A * B / den
        if weight is None:  # plain mean (the training hot path: no weight map)
            ctx.save_for_backward(x, y, mu1, mu2, A, B, C, D, den, s)
            ctx.count = s.numel()
            return s.mean()
        # weighted mean over pixels (and channels): weight [H,W] >= 0
        wmap = _ssim_weight_map(weight, c, s.dtype)[None]
        ctx.save_for_backward(x, y, mu1, mu2, A, B, C, D, den, s, wmap)
        return (s * wmap).sum()

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):  # type: ignore[override]
        x, y, mu1, mu2, A, B, C, D, den, s, *wmap = ctx.saved_tensors
        g = _gauss_window(x.dtype)
        w = grad_out * wmap[0] if wmap else grad_out / ctx.count
        dA = B / den
        dB = A / den
        dC = -s * D / den
        dD = -s * C / den
        d_mu1 = (2 * mu2) * (dA - dB) + (2 * mu1) * (dC - dD)
        maps = torch.cat([d_mu1, dD, 2 * dB], dim=0) * w  # d/d mu1, d/d e11, d/d e12
        gm, g11, g12 = _blur_adjoint(maps, g).split(x.shape[0], dim=0)
        return gm + 2 * x * g11 + y * g12, None, None


class _SSIMMeanKernel(torch.autograd.Function):
    """:class:`_SSIMMean` by the cpu kernel's fused SSIM (``csrc/ssim.h``): the same definition and
    gradient, without torch's many passes over the images (the blurs alone were 22 in-place adds
    per moment stack and about a fifth of a fit's iteration)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, y: torch.Tensor,  # type: ignore[override]
                weight: torch.Tensor | None = None) -> torch.Tensor:
        wmap = None if weight is None else _ssim_weight_map(weight, x.shape[0], x.dtype)
        threads = _default_threads()
        total, mom = _raster_cpu.ssim_forward(x, y, wmap, threads)
        ctx.save_for_backward(x, y, mom, *([] if wmap is None else [wmap]))
        ctx.count, ctx.threads = x.numel(), threads
        return x.new_tensor(total if wmap is not None else total / x.numel())

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):  # type: ignore[override]
        x, y, mom, *wmap = ctx.saved_tensors
        scale = float(grad_out) if wmap else float(grad_out) / ctx.count
        return _raster_cpu.ssim_backward(x, y, mom, wmap[0] if wmap else None, scale, ctx.threads), None, None


def _ssim_kernel_applies(x: torch.Tensor, y: torch.Tensor) -> bool:
    return (x.device.type == "cpu" and y.device.type == "cpu" and x.dtype in (torch.float32, torch.float64)
            and y.dtype == x.dtype and _raster_cpu.available())


def ssim_mean(x: torch.Tensor, y: torch.Tensor, weight: torch.Tensor | None = None) -> torch.Tensor:
    """Differentiable (in ``x``) mean SSIM of [C,H,W] images; see :class:`_SSIMMean` (torch) and
    :class:`_SSIMMeanKernel` (the cpu kernel's, used for CPU float32/float64 tensors when the kernel is
    built: 9 -> 4 ms forward + backward at 256x192). With ``weight`` ([H,W], >= 0) the mean is weighted
    per pixel (the SSIM map is computed on the whole image)."""
    if min(x.shape[-2:]) <= _PAD:  # reflect padding needs more than 5 pixels
        m = ssim_map(x[None], y[None])[0]
        if weight is None:
            return m.mean()
        return (m * weight).sum() / (weight.sum().clamp_min(1e-12) * m.shape[0])
    fn = _SSIMMeanKernel if _ssim_kernel_applies(x, y) else _SSIMMean
    return fn.apply(x.contiguous(), y.detach().contiguous(), None if weight is None else weight.detach().contiguous())


def photometric_loss(render: torch.Tensor, target: torch.Tensor, lambda_dssim: float,
                     weight: torch.Tensor | None = None) -> torch.Tensor:
    """(1 - lambda) L1 + lambda (1 - SSIM) of HxWx3 images; ``weight`` ([H,W], >= 0) makes both
    terms weighted means over the pixels (0 = the pixel is not supervised)."""
    if weight is None:
        l1 = (render - target).abs().mean()
    else:
        l1 = ((render - target).abs() * weight[..., None]).sum() / (weight.sum().clamp_min(1e-12) * 3)
    if lambda_dssim <= 0:
        return l1
    s = ssim_mean(render.permute(2, 0, 1), target.permute(2, 0, 1), weight)
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - s)


def lowpass_l1(render: torch.Tensor, target: torch.Tensor, weight: torch.Tensor, sigma: float) -> torch.Tensor:
    """Weighted mean L1 of HxWx3 images after each is blurred by a Gaussian of ``sigma`` px (kornia,
    reflect padding), over the pixels of ``weight`` ([H,W], >= 0): their colours without their detail."""
    import kornia

    half = max(1, math.ceil(3.0 * sigma))
    both = torch.stack([render, target.detach()]).permute(0, 3, 1, 2)
    if min(both.shape[-2:]) <= half:  # (reflect padding needs more pixels than the kernel's half)
        blurred = both
    else:
        blurred = kornia.filters.gaussian_blur2d(both, (2 * half + 1,) * 2, (sigma, sigma), border_type="reflect")
    diff = (blurred[0] - blurred[1]).abs() * weight[None]
    return diff.sum() / (weight.sum().clamp_min(1e-12) * 3)


def view_loss(render: torch.Tensor, view: TrainView, lambda_dssim: float) -> torch.Tensor:
    """A training view's loss: :func:`photometric_loss` with its ``weight``, and with its ``lowpass``
    weight :func:`lowpass_l1`, the two a mean over the pixels of both weights (not scaled by
    ``loss_scale``)."""
    loss = photometric_loss(render, view.image, lambda_dssim, view.weight)
    if view.lowpass is None:
        return loss
    # (tensor sums: no device synchronisation; an all-zero weight gives its term no share)
    full = view.weight.sum() if view.weight is not None else render.new_tensor(float(render.shape[0] * render.shape[1]))
    low = view.lowpass.sum()
    lp = lowpass_l1(render, view.image, view.lowpass, view.lowpass_sigma)
    return (loss * full + lp * low) / (full + low).clamp_min(1e-12)


def psnr(a: torch.Tensor, b: torch.Tensor, weight: torch.Tensor | None = None) -> float:
    """PSNR of HxWx3 images; with ``weight`` ([H,W], >= 0) of their weighted mean squared error."""
    sq = (a.clamp(0, 1) - b) ** 2
    mse = float(sq.mean()) if weight is None else float((sq * weight[..., None]).sum()) / (float(weight.sum()) * 3)
    return float("inf") if mse <= 0 else -10.0 * math.log10(mse)


def ssim_metric(a: torch.Tensor, b: torch.Tensor, weight: torch.Tensor | None = None) -> float:
    """Mean SSIM of two HxWx3 images (kornia.metrics.ssim, window 11); with ``weight`` ([H,W], >= 0) the
    weighted mean of the same map (:func:`ssim_mean`)."""
    if weight is not None:
        with torch.no_grad():
            return float(ssim_mean(a.clamp(0, 1).permute(2, 0, 1), b.permute(2, 0, 1), weight))
    import kornia

    return float(kornia.metrics.ssim(a.clamp(0, 1).permute(2, 0, 1)[None].contiguous(),
                                     b.permute(2, 0, 1)[None].contiguous(), 11).mean())


def render_view(model: GaussianModel, camera: Camera, sh_degree: int | None = None, backend: str = "auto",
                background: Sequence[float] = (0.0, 0.0, 0.0)) -> torch.Tensor:
    """Render ``model`` at ``camera`` (no gradient): [H,W,3] float32."""
    deg = model.max_sh_degree if sh_degree is None else sh_degree
    k = (deg + 1) ** 2
    with torch.no_grad():
        act = model.activated()
        colors = act["colors"][:, :k].contiguous()
        dev = model.device
        vm = torch.from_numpy(camera.cam_from_world).float()[None].to(dev)
        K = torch.from_numpy(camera.K).float()[None].to(dev)
        img, _, _ = rasterization(act["means"], act["quats"], act["scales"], act["opacities"], colors, vm, K,
                                  camera.width, camera.height, sh_degree=deg,
                                  backgrounds=torch.tensor(background, dtype=torch.float32, device=dev),
                                  backend=backend)
    return img[0]


def evaluate(model: GaussianModel, views: Sequence[TrainView], sh_degree: int | None = None,
             backend: str = "auto", background: Sequence[float] = (0.0, 0.0, 0.0)) -> dict[str, float]:
    """Mean PSNR and SSIM of the renders of ``views`` against their images; a view with a loss weight
    is scored where it was trained, weighted alike (fit.object_masks=ignore: outside the object masks,
    which the fit never saw; over them kitchen's fit scored 15.9 dB)."""
    ps, ss = [], []
    for v in views:
        w = v.weight
        if w is not None and float(w.sum()) <= 0:  # (nothing of the view was trained)
            continue
        r = render_view(model, v.camera, sh_degree, backend, background)
        w = None if w is None else w.to(r.device)
        ps.append(psnr(r, v.image, w))
        ss.append(ssim_metric(r, v.image, w))
    if not ps:
        return {"psnr": float("nan"), "ssim": float("nan")}
    return {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss))}


# --------------------------------------------------------------------------------------------------
# budget


@dataclass
class BudgetController:
    """The Gaussian budget: fixed (user) or automatic.

    Automatic: start at ``budget_per_pixel`` x training pixels (clamped to [budget_min, hard
    maximum = budget_max_per_pixel x training pixels]). A growth decision is due when the model has
    filled the cap (>= 95 %) and ``window`` iterations passed since the last decision: it measures
    the error (the held-out MSE when there are held-out views, else the smoothed training loss) and
    compares it with the error at the previous decision. The first decision only records it and
    grows; later ones grow the cap by ``growth`` while the error fell by more than ``min_gain``
    (relative; 5 % of MSE = 0.22 dB) over the last growth step, and freeze the budget otherwise.
    Growth also ends with densification. ``reason`` says why the count stopped where it did.
    """

    cap: int
    auto: bool
    growth: float = 1.5
    min_gain: float = 0.05
    window: int = 300
    hard_max: int = 1_000_000
    frozen: bool = False
    last_step: int = 0
    last_error: float | None = None
    metric: str = ""
    reason: str = ""
    history: list[dict[str, Any]] = field(default_factory=list)

    @classmethod
    def create(cls, p: TrainParams, train_pixels: int) -> BudgetController:
        if p.budget:
            return cls(cap=int(p.budget), auto=False, reason="user budget")
        hard_max = int(np.clip(p.budget_max_per_pixel * train_pixels, p.budget_min, p.budget_max))
        start = int(np.clip(p.budget_per_pixel * train_pixels, p.budget_min, hard_max))
        return cls(cap=start, auto=True, growth=p.budget_growth, min_gain=p.budget_min_gain,
                   window=p.budget_window, hard_max=hard_max)

    def due(self, step: int, count: int, growing: bool) -> bool:
        """Whether a growth decision is due at ``step`` (then call :meth:`decide`)."""
        return (self.auto and not self.frozen and growing and count >= 0.95 * self.cap
                and (self.last_error is None or step - self.last_step >= self.window))

    def decide(self, step: int, count: int, error: float, metric: str) -> bool:
        """Grow or freeze given the current ``error``; returns True when the cap grew."""
        self.metric = metric
        entry: dict[str, Any] = {"iteration": step, "count": count, "cap": self.cap, "error": error,
                                 "metric": metric}
        if self.last_error is None:
            gain = None
        else:
            gain = (self.last_error - error) / max(self.last_error, 1e-12)
            entry["gain"] = gain
        if (gain is None or gain > self.min_gain) and self.cap < self.hard_max:
            self.cap = min(self.hard_max, int(self.cap * self.growth))
            entry["action"] = f"grow to {self.cap}"
            self.history.append(entry)
            self.last_error, self.last_step = error, step
            return True
        self.frozen = True
        if self.cap >= self.hard_max:
            self.reason = f"automatic budget reached its hard maximum ({self.hard_max})"
        else:
            self.reason = (f"automatic budget frozen at {self.cap}: the {metric} fell {100 * (gain or 0.0):.1f}% "
                           f"over the last growth step ({step - self.last_step} iterations; < "
                           f"{100 * self.min_gain:.1f}%)")
        entry["action"] = "freeze"
        self.history.append(entry)
        return False

    def stop_reason(self, count: int, strategy: Strategy, iterations: int) -> str:
        if self.frozen:
            return self.reason
        if count >= 0.95 * self.cap:
            return (f"{'user' if not self.auto else 'automatic'} budget reached ({count} of {self.cap})"
                    + ("" if not self.auto else "; densification ended before the next growth decision"))
        return (f"densification ended (iteration {getattr(strategy, 'refine_stop', iterations)}) with {count} "
                f"Gaussians, below the budget of {self.cap}: no more were needed by the gradient/opacity criteria")

    def state(self) -> dict[str, Any]:
        return asdict(self)


# --------------------------------------------------------------------------------------------------
# the trainer


class RollbackNeeded(Exception):
    def __init__(self, what: str):
        super().__init__(what)
        self.what = what


def _make_optimizer(param: torch.nn.Parameter, lr: float) -> torch.optim.Adam:
    try:
        return torch.optim.Adam([param], lr=lr, eps=1e-15, fused=True)
    except (RuntimeError, TypeError):  # no fused kernel for this device/dtype
        return torch.optim.Adam([param], lr=lr, eps=1e-15)


def _unchanged(seen: tuple[torch.Tensor, int] | None, param: torch.Tensor) -> bool:
    """Whether ``param`` is the tensor ``seen`` recorded, not changed in place since (torch counts
    in-place changes in ``_version``)."""
    return seen is not None and seen[0] is param and seen[1] == param._version


def _atomic_save(obj: Any, path: Path) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "wb") as f:
        torch.save(obj, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


class Trainer:
    """Fits ``model`` to ``train_views``; see the module docstring.

    ``progress`` wraps the iteration range (e.g. ``ctx.progress``; a tqdm bar gets the curve's figures
    as its postfix). ``checkpoint_dir`` None disables checkpoints.
    """

    def __init__(self, model: GaussianModel, strategy: Strategy, train_views: Sequence[TrainView],
                 eval_views: Sequence[TrainView], params: TrainParams, extent: float,
                 checkpoint_dir: Path | None = None, logger: logging.Logger | None = None,
                 progress: Callable[..., Any] | None = None):
        if not train_views:
            raise ValueError("no training views")
        self.device = resolve_device(params.device, params.backend)
        self.model = model.to(self.device)
        self.strategy = strategy
        self.train_views = [self._on_device(v) for v in train_views]
        # each view's camera as [1,4,4] and [1,3,3] tensors on the device, made once: a copy from
        # the host each iteration synchronises a GPU twice
        self._cameras = [(v.viewmat.to(self.device), v.K.to(self.device)) for v in self.train_views]
        self.eval_views = [self._on_device(v) for v in eval_views]
        self._coarse: dict[int, tuple[TrainView, tuple[torch.Tensor, torch.Tensor]]] = {}
        # the strategy's last grad_mask: (mask, its version, on the device, the trained tail's start)
        self._grad_mask: tuple[Any, ...] = (None, -1, None, None)
        self.p = params
        self.extent = float(extent)
        self.checkpoint_dir = None if checkpoint_dir is None else Path(checkpoint_dir)
        self.log = logger or log
        self.tag = self.log.name.rsplit(".", 1)[-1]  # "fit", "finetune": prefixes the log lines
        self.progress = progress
        self.gen = torch.Generator().manual_seed(int(params.seed))
        pixels = sum(v.image.shape[0] * v.image.shape[1] for v in self.train_views)
        self.budget = BudgetController.create(params, pixels)
        if self.budget.auto and len(model) > self.budget.cap:  # the model starts above the automatic start
            self.budget.cap = min(max(len(model), self.budget.cap), max(self.budget.hard_max, len(model)))
        self.strategy.cap = self.budget.cap
        self.optimizers = self._build_optimizers()
        self.sstate = strategy.initialize_state(model, self.extent)
        self.step = 0
        self._params_checked = False  # set when the last iteration found every parameter finite
        self.lr_scale = 1.0
        self.loss_ema: float | None = None
        self.curve: list[dict[str, Any]] = []
        self.events: list[dict[str, Any]] = []
        self.elapsed = 0.0  # wall seconds of training (summed over resumed runs)
        self.cpu_elapsed = 0.0  # process CPU seconds of training (all threads)
        self._t0 = (0.0, 0.0)
        self.perm: list[int] = []
        self.resumed_from: int | None = None
        self.nan_injections = 0
        self._snapshot: dict[str, Any] | None = None
        self._rollbacks_in_a_row = 0
        self._last_failure_step = -1
        self._window_losses: list[float] = []
        self.bg = torch.tensor(params.background, dtype=torch.float32, device=self.device)
        self.last_eval: dict[str, float] = {}
        self.poses = (None if params.pose_refine is None else
                      PoseRefiner([v.camera for v in self.train_views], self.extent, params.pose_refine, self.device))
        # the held-out views' poses, aligned to the refined frame before each evaluation (see PoseRefineParams)
        self.eval_poses = (None if params.pose_refine is None or not self.eval_views else
                           PoseRefiner([v.camera for v in self.eval_views], self.extent, params.pose_refine,
                                       self.device, gauge=False, lr=(params.pose_refine.lr_eval,) * 2))

    def _on_device(self, view: TrainView) -> TrainView:
        if view.image.device == self.device:
            return view
        return replace(view, image=view.image.to(self.device),
                       weight=None if view.weight is None else view.weight.to(self.device),
                       lowpass=None if view.lowpass is None else view.lowpass.to(self.device))

    # optimisation ------------------------------------------------------------------------------

    def base_lrs(self) -> dict[str, float]:
        p = self.p
        return {"means": p.lr_means * self.extent, "quats": p.lr_quats, "scales": p.lr_scales,
                "opacities": p.lr_opacities, "sh0": p.lr_sh0, "shN": p.lr_sh0 * p.lr_shN_factor}

    def _build_optimizers(self) -> dict[str, torch.optim.Adam]:
        lrs = self.base_lrs()
        return {n: _make_optimizer(self.model.params[n], lrs[n]) for n in self.model.params}

    def means_lr(self, step: int) -> float:
        t = min(max(step / max(self.p.iterations, 1), 0.0), 1.0)
        lr0, lr1 = self.p.lr_means, self.p.lr_means_final
        return math.exp((1 - t) * math.log(lr0) + t * math.log(lr1)) * self.extent

    def _set_lrs(self, step: int) -> float:
        lrs = self.base_lrs()
        lrs["means"] = self.means_lr(step)
        for n, opt in self.optimizers.items():
            opt.param_groups[0]["lr"] = lrs[n] * self.lr_scale
        return lrs["means"] * self.lr_scale

    def active_sh_degree(self, step: int) -> int:
        if self.p.sh_degree_every <= 0:
            return min(self.p.sh_degree, self.model.max_sh_degree)
        return min(self.p.sh_degree, self.model.max_sh_degree, step // self.p.sh_degree_every)

    def coarse(self, step: int) -> bool:
        """Whether iteration ``step`` trains at the reduced resolution (``coarse_until``)."""
        return self.p.coarse_factor > 1 and step <= self.p.coarse_until * self.p.iterations

    def _view(self, i: int, step: int) -> tuple[TrainView, tuple[torch.Tensor, torch.Tensor]]:
        """Training view ``i`` and its camera tensors as iteration ``step`` trains on them: at full
        resolution, or downscaled by ``coarse_factor`` (area average, intrinsics scaled; made once)."""
        if not self.coarse(step):
            self._coarse.clear()  # (the coarse phase is over: free its images)
            return self.train_views[i], self._cameras[i]
        if i not in self._coarse:
            v = self.train_views[i]
            H, W = v.image.shape[:2]
            f = self.p.coarse_factor
            h, w = max(1, round(H / f)), max(1, round(W / f))
            img = F.interpolate(v.image.permute(2, 0, 1)[None], size=(h, w), mode="area")[0].permute(1, 2, 0)
            wt = None if v.weight is None else F.interpolate(v.weight[None, None], size=(h, w), mode="area")[0, 0]
            lp = None if v.lowpass is None else F.interpolate(v.lowpass[None, None], size=(h, w), mode="area")[0, 0]
            small = replace(v, image=img.contiguous(), weight=None if wt is None else wt.contiguous(),
                            lowpass=None if lp is None else lp.contiguous(), lowpass_sigma=v.lowpass_sigma * w / W,
                            camera=v.camera.scaled(w, h))
            self._coarse[i] = (small, (self._cameras[i][0], small.K.to(self.device)))
        return self._coarse[i]

    def _trained_tail(self) -> tuple[torch.Tensor | None, int | None]:
        """The strategy's ``grad_mask`` on the device, and ``start`` when Adam need step only the rows
        from ``start`` on (:meth:`_step_tail`): the masked-in rows are the last ones (the finetune
        orders them so), ``start`` is aligned down to 16 rows, and every row before the tail has a
        zero gradient (the mask's contract) and zero moments (checked when the mask changes), so
        Adam would leave it bit for bit as it is. None without a mask or where that does not hold.
        Made once per mask."""
        mask = self.strategy.grad_mask(self.sstate)
        if mask is None:
            return None, None
        cached = self._grad_mask
        if cached[0] is not mask or cached[1] != mask._version:
            on_device = mask.to(self.device)
            rows = torch.nonzero(on_device).squeeze(1)
            tail = None
            n = len(on_device)
            if len(rows) and int(rows[0]) + len(rows) == n and self._tail_steppable():
                tail = int(rows[0]) - int(rows[0]) % 16
                for name, opt in self.optimizers.items():
                    st = opt.state.get(self.model.params[name], {})
                    if any(bool(st[k][:tail].any()) for k in ("exp_avg", "exp_avg_sq") if k in st):
                        tail = None
                        break
            self._grad_mask = cached = (mask, mask._version, on_device, tail)
        return cached[2], cached[3]

    def _tail_steppable(self) -> bool:
        """Whether :meth:`_step_tail` can stand in for the optimizers: each is torch's fused Adam
        as the trainer makes it (one parameter, no weight decay, amsgrad or maximize)."""
        for name, opt in self.optimizers.items():
            g = opt.param_groups[0]
            if (not isinstance(opt, torch.optim.Adam) or len(opt.param_groups) != 1 or not g.get("fused")
                    or g["weight_decay"] or g["amsgrad"] or g["maximize"]
                    or not self.model.params[name].is_contiguous()):
                return False
        return True

    def _step_tail(self, start: int) -> None:
        """Each parameter's Adam step on its rows from ``start`` on: torch's functional fused Adam on
        views of the parameter, its gradient and its moments, with the optimizer's own state and
        settings. On those rows the same arithmetic as the full step (``start`` is a multiple of 16
        rows, so even the last values, which the CPU kernel steps one by one, are the same), and the
        rows before stay as they are, as the full step would leave them. A re-fit of a few Gaussians
        among many (statue's finetune: 30k of 359k) then costs Adam a tenth of a full step."""
        from torch.optim.adam import adam as adam_step

        for name, opt in self.optimizers.items():
            param = self.model.params[name]
            if param.grad is None:  # (Adam skips a parameter without a gradient)
                continue
            group, st = opt.param_groups[0], opt.state[param]
            if not st:  # (as torch.optim.Adam(fused=True) initialises it)
                st["step"] = torch.zeros((), dtype=torch.float32, device=param.device)
                st["exp_avg"] = torch.zeros_like(param, memory_format=torch.preserve_format)
                st["exp_avg_sq"] = torch.zeros_like(param, memory_format=torch.preserve_format)
            beta1, beta2 = group["betas"]
            with torch.no_grad():
                adam_step([param.detach()[start:]], [param.grad[start:]], [st["exp_avg"][start:]],
                          [st["exp_avg_sq"][start:]], [], [st["step"]], fused=True, amsgrad=False,
                          beta1=beta1, beta2=beta2, lr=group["lr"], weight_decay=0.0, eps=group["eps"],
                          maximize=False)
            param.grad = None

    def _next_view(self) -> int:
        """The index of the next training view (a fresh random order each epoch)."""
        if not self.perm:
            self.perm = torch.randperm(len(self.train_views), generator=self.gen).tolist()
        return self.perm.pop()

    # state -------------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        return {
            "format": CHECKPOINT_FORMAT,
            "step": self.step,
            "model": self.model.state_dict(),
            "optimizers": {n: copy.deepcopy(o.state_dict()) for n, o in self.optimizers.items()},
            "strategy": self.strategy.state_to_save(self.sstate),
            "strategy_cap": self.strategy.cap,
            "budget": copy.deepcopy(self.budget.state()),
            "generator": self.gen.get_state(),
            "perm": list(self.perm),
            "lr_scale": self.lr_scale,
            "loss_ema": self.loss_ema,
            "curve": copy.deepcopy(self.curve),
            "events": copy.deepcopy(self.events),
            "elapsed": self.elapsed,
            "cpu_elapsed": self.cpu_elapsed,
            "window_losses": list(self._window_losses),
            "last_eval": dict(self.last_eval),
            "nan_injections": self.nan_injections,
            "poses": None if self.poses is None else self.poses.state_dict(),
            "eval_poses": None if self.eval_poses is None else self.eval_poses.state_dict(),
        }

    def load_state_dict(self, st: dict[str, Any], restore_lr_scale: bool = True) -> None:
        self._params_checked = False  # (the rasterizer checks loaded parameters)
        self.step = int(st["step"])
        self.model.load_state_dict(st["model"])
        self.model.to(self.device)  # a checkpoint is read onto the CPU
        self.optimizers = self._build_optimizers()
        for n, o in self.optimizers.items():
            o.load_state_dict(copy.deepcopy(st["optimizers"][n]))  # moves the moments to the parameters' device
        self.sstate = {k: (v.to(self.device, copy=True) if isinstance(v, torch.Tensor) else v)
                       for k, v in st["strategy"].items()}
        self.strategy.cap = int(st["strategy_cap"])
        self.budget = BudgetController(**copy.deepcopy(st["budget"]))
        self.gen.set_state(st["generator"])
        self.perm = list(st["perm"])
        if restore_lr_scale:
            self.lr_scale = float(st["lr_scale"])
        self.loss_ema = st["loss_ema"]
        self.curve = copy.deepcopy(st["curve"])
        self.events = copy.deepcopy(st["events"]) if restore_lr_scale else self.events
        self.elapsed = float(st["elapsed"])
        self.cpu_elapsed = float(st.get("cpu_elapsed", 0.0))
        self._window_losses = list(st["window_losses"])
        self.last_eval = dict(st.get("last_eval", {}))
        if restore_lr_scale:
            self.nan_injections = int(st.get("nan_injections", 0))
        if self.poses is not None and st.get("poses") is not None:
            self.poses.load_state_dict(st["poses"])
        if self.eval_poses is not None and st.get("eval_poses") is not None:
            self.eval_poses.load_state_dict(st["eval_poses"])

    @property
    def checkpoint_path(self) -> Path | None:
        return None if self.checkpoint_dir is None else self.checkpoint_dir / CHECKPOINT_NAME

    def save_checkpoint(self) -> None:
        path = self.checkpoint_path
        if path is None:
            return
        path.parent.mkdir(parents=True, exist_ok=True)
        _atomic_save(self.state_dict(), path)

    def try_resume(self) -> bool:
        """Load the checkpoint when there is a readable one; returns whether training resumed."""
        path = self.checkpoint_path
        if path is None or not path.is_file():
            return False
        try:
            st = torch.load(path, map_location="cpu", weights_only=False)
            if st.get("format") != CHECKPOINT_FORMAT:
                raise ValueError(f"checkpoint format {st.get('format')}")
            self.load_state_dict(st)
        except Exception as e:  # a damaged checkpoint: start over rather than fail
            self.log.warning(f"{self.tag}: ignoring unreadable checkpoint {path.name} ({e}); training from the start")
            return False
        self.resumed_from = self.step
        self.log.info(f"{self.tag}: resumed from checkpoint at iteration {self.step} ({len(self.model)} Gaussians)")
        return True

    # NaN guard ---------------------------------------------------------------------------------

    def _take_snapshot(self) -> None:
        self._snapshot = self.state_dict()
        if self.step > self._last_failure_step:
            self._rollbacks_in_a_row = 0

    def _rollback(self, what: str) -> None:
        self._rollbacks_in_a_row += 1
        self._last_failure_step = max(self._last_failure_step, self.step)
        failed_at = self.step + 1  # the iteration in progress (self.step counts completed ones)
        if self._snapshot is None or self._rollbacks_in_a_row > self.p.max_rollbacks:
            raise NonFiniteError(
                f"{self.tag}: {what} at iteration {failed_at}, still after {self._rollbacks_in_a_row - 1} rollback(s) "
                f"with the learning rates scaled by {self.lr_scale:g}",
                fix="lower the learning rates (fit.lr_*), check the cameras and points from SfM, or "
                    "lower fit.sh_degree")
        self.lr_scale *= self.p.rollback_lr_factor
        lr_scale, elapsed, cpu = self.lr_scale, self.elapsed, self.cpu_elapsed
        self.load_state_dict(self._snapshot, restore_lr_scale=False)
        self.lr_scale, self.elapsed, self.cpu_elapsed = lr_scale, elapsed, cpu  # time is not rolled back
        self.events.append({"iteration": failed_at, "event": "rollback", "what": what,
                            "to_iteration": self.step, "lr_scale": self.lr_scale})
        self.log.warning(f"{self.tag}: {what} at iteration {failed_at}: rolled back to iteration {self.step}, "
                         f"learning rates x{self.lr_scale:g}")

    # one iteration -----------------------------------------------------------------------------

    def _iteration(self) -> float:
        step = self.step + 1
        means_lr = self._set_lrs(step)
        deg = self.active_sh_degree(step)
        k = (deg + 1) ** 2
        i = self._next_view()
        view, (viewmat, K) = self._view(i, step)
        H, W = view.image.shape[:2]
        p = self.model.params
        # (the pair is read in place by the cpu kernel: no [N,16,3] copy, and gradients in place)
        colors = (p["sh0"], p["shN"]) if k > 1 else p["sh0"]
        means, quats = p["means"], p["quats"]
        refine_pose = self.poses is not None and self.poses.active(step)
        if refine_pose:
            viewmat = self.poses.viewmat(i, viewmat)
            means, quats = self.poses.attach(i, means, quats)
        grad_mask, tail = self._trained_tail()
        try:
            render, _alpha, info = rasterization(
                means, quats, torch.exp(p["scales"]), torch.sigmoid(p["opacities"]), colors,
                viewmat, K, W, H, sh_degree=deg, backgrounds=self.bg,
                backend=self.p.backend, check_finite=not self._params_checked, grad_mask=grad_mask)
        except NonFiniteInputError as e:
            raise RollbackNeeded(f"non-finite rasterizer input ({e.message})") from None
        info["generator"] = self.gen
        self.strategy.step_pre_backward(self.model, self.optimizers, self.sstate, step, info)
        own_loss = view_loss(render[0], view, self.p.lambda_dssim)
        loss = own_loss if view.loss_scale == 1.0 else own_loss * view.loss_scale
        extra = self.strategy.extra_loss(self.model, step)
        if extra is not None:
            loss = loss + extra
        loss.backward()
        # the loss and the gradients in one check (one GPU synchronisation); a non-finite loss
        # only costs its backward before the rollback
        # (with a trained tail the other rows' gradients are zero: only the tail is checked and stepped)
        grads = {n: q.grad if tail is None or q.grad is None else q.grad[tail:] for n, q in p.items()}
        if refine_pose:
            grads.update(self.poses.grads(i))
        bad = first_non_finite({"loss": loss, **grads})
        if bad == "loss":
            raise RollbackNeeded("non-finite loss")
        if bad is not None:
            raise RollbackNeeded(f"non-finite gradient of '{bad}'")
        if tail is None:
            for opt in self.optimizers.values():
                opt.step()
                opt.zero_grad(set_to_none=True)
        else:
            self._step_tail(tail)
        # Adam keeps finite parameters finite when their gradients are (its step is bounded by a few
        # learning rates), so only the parameters changed after it are scanned below: those the
        # strategy replaced (a new tensor) or changed in place (torch bumps the version counter)
        after_adam = {n: (q, q._version) for n, q in p.items()} if self._params_checked else {}
        if refine_pose:
            self.poses.step(self.lr_scale)
            self.poses.zero_grad()
        changed = self.strategy.step_post_backward(self.model, self.optimizers, self.sstate, step, info,
                                                   lr=means_lr)
        if changed:
            self.events.append({"iteration": step, "event": self.strategy.name, **changed,
                                "count": len(self.model)})
        if (self.p.debug_inject_nan_at and step == self.p.debug_inject_nan_at
                and self.nan_injections < self.p.debug_inject_nan_times):
            self.nan_injections += 1
            with torch.no_grad():
                self.model.params["means"][0, 0] = float("nan")
        bad = first_non_finite({n: q for n, q in self.model.params.items()
                                if not _unchanged(after_adam.get(n), q)})
        if bad is not None:
            raise RollbackNeeded(f"non-finite parameter '{bad}'")
        # the next iteration's rasterizer need not scan them again (exp(log-scales) may still
        # overflow to inf: the projection culls such a Gaussian, as tests/test_fit.py checks)
        self._params_checked = True
        self.step = step
        # logged: the view's own loss (a crop's mean over its pixels, not scaled by loss_scale)
        return float(own_loss.detach()) + (0.0 if extra is None else float(extra.detach()))

    # the loop ----------------------------------------------------------------------------------

    def refined_train_views(self) -> list[TrainView]:
        """The training views with their cameras as refined so far (as they are without refinement)."""
        if self.poses is None:
            return list(self.train_views)
        return [replace(v, camera=self.poses.camera(i, v.camera)) for i, v in enumerate(self.train_views)]

    def aligned_eval_views(self) -> list[TrainView]:
        """The held-out views at their poses as last aligned (as they are without pose refinement)."""
        if self.eval_poses is None:
            return list(self.eval_views)
        return [replace(v, camera=self.eval_poses.camera(i, v.camera)) for i, v in enumerate(self.eval_views)]

    def align_eval_views(self) -> None:
        """A few pose steps per held-out view with the Gaussians frozen (``PoseRefineParams.eval_steps``)."""
        if self.eval_poses is None or self.poses is None or not self.poses.active(self.step):
            return
        deg = self.active_sh_degree(self.step)
        k = (deg + 1) ** 2
        with torch.no_grad():
            act = self.model.activated()
            colors = act["colors"][:, :k].contiguous()
        for i, view in enumerate(self.eval_views):
            viewmat, K = view.viewmat.to(self.device), view.K.to(self.device)
            H, W = view.image.shape[:2]
            for _ in range(self.p.pose_refine.eval_steps):
                means, quats = self.eval_poses.attach(i, act["means"], act["quats"])
                render, _, _ = rasterization(means, quats, act["scales"], act["opacities"], colors,
                                             self.eval_poses.viewmat(i, viewmat), K, W, H,
                                             sh_degree=deg, backgrounds=self.bg, backend=self.p.backend)
                view_loss(render[0], view, self.p.lambda_dssim).backward()
                if first_non_finite(self.eval_poses.grads(i)) is not None:  # (a frozen model: skip, never roll back)
                    self.eval_poses.zero_grad()
                    break
                self.eval_poses.step()
                self.eval_poses.zero_grad()

    def evaluate(self) -> dict[str, float]:
        self.align_eval_views()
        views = self.aligned_eval_views() or self.refined_train_views()
        deg = self.active_sh_degree(self.step)
        res = evaluate(self.model, views, deg, self.p.backend, self.p.background)
        self.last_eval = res
        return res

    def train(self, resume: bool = True) -> dict[str, Any]:
        """Run (or resume) to ``iterations``; returns a summary (also see :attr:`curve`)."""
        if resume:
            self.try_resume()
        self._take_snapshot()
        last_ckpt_time = time.perf_counter()
        self._start_clock()
        it = range(self.step, self.p.iterations)
        bar = self.progress(it, total=self.p.iterations, desc=self.tag) if self.progress else None
        if bar is not None and hasattr(bar, "update") and self.step:
            bar.update(self.step)
        try:
            while self.step < self.p.iterations:
                try:
                    loss = self._iteration()
                except RollbackNeeded as e:
                    self._tick()
                    self._rollback(e.what)
                    if bar is not None and hasattr(bar, "n"):
                        bar.n = self.step
                    continue
                self._tick()
                self.loss_ema = loss if self.loss_ema is None else 0.98 * self.loss_ema + 0.02 * loss
                self._window_losses.append(loss)
                step = self.step
                if self.budget.due(step, len(self.model), self.strategy.is_growing(step)):
                    error, metric = self._budget_error()
                    if self.budget.decide(step, len(self.model), error, metric):
                        self.strategy.cap = self.budget.cap
                        self.events.append({"iteration": step, "event": "budget", "cap": self.budget.cap})
                        self.log.info(f"{self.tag}: budget grows to {self.budget.cap} Gaussians at iteration {step} "
                                      f"({metric} {error:.5f})")
                    else:
                        self.log.info(f"{self.tag}: budget frozen at iteration {step}: {self.budget.reason}")
                do_eval = step == self.p.iterations or (self.p.eval_every > 0 and step % self.p.eval_every == 0)
                if do_eval or step % max(self.p.log_every, 1) == 0:
                    self._record(step, do_eval)
                    self._tick()
                    if bar is not None and hasattr(bar, "set_postfix"):
                        last = self.curve[-1]
                        post = {"loss": f"{last['loss']:.4f}", "n": last["count"]}
                        if self.last_eval:
                            post["psnr"] = f"{self.last_eval['psnr']:.2f}"
                        bar.set_postfix(post, refresh=False)
                if step % max(self.p.snapshot_every, 1) == 0:
                    self._take_snapshot()
                now = time.perf_counter()
                if step < self.p.iterations and (
                        (self.p.checkpoint_every > 0 and step % self.p.checkpoint_every == 0)
                        or (self.p.checkpoint_seconds > 0 and now - last_ckpt_time >= self.p.checkpoint_seconds)):
                    self.save_checkpoint()
                    last_ckpt_time = time.perf_counter()
                if bar is not None and hasattr(bar, "update"):
                    bar.update(1)
        finally:
            if bar is not None and hasattr(bar, "close"):
                bar.close()
        self._tick()
        return self.summary()

    def _start_clock(self) -> None:
        self._t0 = (time.perf_counter() - self.elapsed, time.process_time() - self.cpu_elapsed)

    def _tick(self) -> None:
        self.elapsed = time.perf_counter() - self._t0[0]
        self.cpu_elapsed = time.process_time() - self._t0[1]

    def _budget_error(self) -> tuple[float, str]:
        """The error the automatic budget follows: held-out MSE, else the smoothed training loss."""
        if not self.eval_views:
            return float(self.loss_ema if self.loss_ema is not None else float("nan")), "training loss"
        deg = self.active_sh_degree(self.step)
        mses = []
        for v in self.aligned_eval_views():
            r = render_view(self.model, v.camera, deg, self.p.backend, self.p.background)
            mses.append(float(((r.clamp(0, 1) - v.image) ** 2).mean()))
        return float(np.mean(mses)), "held-out MSE"

    def _record(self, step: int, do_eval: bool) -> None:
        window = self._window_losses or [float("nan")]
        entry: dict[str, Any] = {"iteration": step, "loss": float(np.mean(window)), "count": len(self.model),
                                 "seconds": round(self.elapsed, 3), "cpu_seconds": round(self.cpu_elapsed, 3),
                                 "sh_degree": self.active_sh_degree(step), "lr_scale": self.lr_scale}
        self._window_losses = []
        if do_eval:
            t0 = time.perf_counter()
            ev = self.evaluate()
            entry.update(heldout_psnr=ev["psnr"], heldout_ssim=ev["ssim"],
                         eval_seconds=round(time.perf_counter() - t0, 3))
            self.log.info(f"{self.tag}: iteration {step}/{self.p.iterations}: loss {entry['loss']:.4f}, "
                          f"{entry['count']} Gaussians, {'held-out' if self.eval_views else 'training'} PSNR "
                          f"{ev['psnr']:.2f} dB, "
                          f"SSIM {ev['ssim']:.3f}, {self.elapsed:.0f} s")
        self.curve.append(entry)

    def summary(self) -> dict[str, Any]:
        if not self.last_eval or (self.curve and "heldout_psnr" not in self.curve[-1]):
            self.evaluate()
        return {
            "iterations": self.step,
            "count": len(self.model),
            "stop_reason": self.budget.stop_reason(len(self.model), self.strategy, self.p.iterations),
            "budget": self.budget.cap,
            "budget_auto": self.budget.auto,
            "budget_history": self.budget.history,
            "heldout_psnr": self.last_eval.get("psnr"),
            "heldout_ssim": self.last_eval.get("ssim"),
            "heldout_is_training": not self.eval_views,
            "train_seconds": self.elapsed,
            "train_cpu_seconds": self.cpu_elapsed,
            "resumed_from_iteration": self.resumed_from,
            "rollbacks": [e for e in self.events if e.get("event") == "rollback"],
            "lr_scale": self.lr_scale,
            "pose_refine": None if self.poses is None else self.poses.summary([v.name for v in self.train_views]),
            "heldout_poses_aligned": (None if self.eval_poses is None else
                                      self.eval_poses.summary([v.name for v in self.eval_views])),
        }
