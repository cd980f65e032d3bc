"""The ``gsplat`` backend: a thin adapter over ``gsplat.rasterization`` (gsplat >= 1.4, CUDA).

Installed with the optional extra ``pip install sgpor-pipeline[gpu]``. gsplat receives the same
activated parameters; only the meta dictionary is adapted (radii [C,N] as the larger of gsplat
1.5's per-axis radii, ``contrib`` computed with one extra rasterization of a constant channel,
differentiated once: d(sum of masked pixels)/d(channel value) = sum of alpha*T over those pixels).
"""

from __future__ import annotations

from typing import Any

import torch

from ._raster_common import RasterizerInputError


def importable() -> bool:
    try:
        import gsplat  # noqa: F401
    except Exception:  # ImportError, or a broken CUDA extension
        return False
    return True


def require(device: torch.device) -> None:
    if not importable():
        raise RasterizerInputError("backend='gsplat' needs the gsplat package",
                                   fix="pip install 'sgpor-pipeline[gpu]' on a CUDA machine, or use "
                                       "backend='auto'")
    if device.type != "cuda":
        raise RasterizerInputError(f"backend='gsplat' needs CUDA tensors, got {device}",
                                   fix="move the Gaussians and cameras to a CUDA device, or use "
                                       "backend='cpu'")


def rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane,
                  far_plane, sh_degree, backgrounds, render_mode, tile_size, contribution_mask,
                  eps2d) -> tuple[torch.Tensor, torch.Tensor, dict[str, Any]]:
    import gsplat

    C, N = viewmats.shape[0], means.shape[0]
    if colors is None:  # depth-only modes: gsplat still wants a colours tensor
        colors, sh_degree = means.new_zeros(N, 1), None
    if backgrounds is not None and backgrounds.dim() == 1:
        backgrounds = backgrounds[None].expand(C, -1).contiguous()
    render, alpha, gmeta = gsplat.rasterization(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height,
        near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, sh_degree=sh_degree, packed=False,
        tile_size=tile_size, backgrounds=backgrounds, render_mode=render_mode,
        rasterize_mode="classic")
    radii = gmeta["radii"]
    if radii.dim() == 3:  # gsplat 1.5: per-axis radii
        radii = radii.max(dim=-1).values
    contrib = _contribution(gmeta, C, N, width, height, tile_size, contribution_mask, means)
    meta = {"means2d": gmeta["means2d"], "radii": radii.to(torch.int32), "depths": gmeta["depths"],
            "conics": gmeta["conics"], "contrib": contrib}
    return render, alpha, meta


def _contribution(gmeta, C, N, width, height, tile_size, mask, means) -> torch.Tensor:
    from gsplat import rasterize_to_pixels

    with torch.enable_grad():
        ones = torch.ones(C, N, 1, device=means.device, dtype=means.dtype, requires_grad=True)
        opac = gmeta["opacities"].detach()
        if opac.dim() == 1:
            opac = opac[None].expand(C, -1)
        img, _ = rasterize_to_pixels(gmeta["means2d"].detach(), gmeta["conics"].detach(), ones,
                                     opac.contiguous(), width, height, tile_size,
                                     gmeta["isect_offsets"], gmeta["flatten_ids"], packed=False)
        weight = img if mask is None else img * mask[..., None].to(img.dtype)
        (grad,) = torch.autograd.grad(weight.sum(), ones)
    return grad[..., 0].detach()
