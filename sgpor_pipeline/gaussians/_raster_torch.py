"""The ``torch`` backend: a dense pure-PyTorch reference of the rasterizer (any device, autograd).

It implements exactly the rules of DESIGN.md section 6 (see :mod:`._raster_common`), written for
clarity: every (pixel, Gaussian) pair of a pixel block is evaluated densely and composited with a
cumulative product. Blocks only skip the Gaussians whose footprint rectangle misses them, which
cannot change the result (a Gaussian only ever touches the pixels of its rectangle); with
``block=None`` the whole image is one block (all Gaussians x all pixels).
"""

from __future__ import annotations

import torch

from ._raster_common import (
    ALPHA_MAX,
    ALPHA_MIN,
    FRUSTUM_MARGIN,
    MAX_SIGMA,
    QUAT_EPS,
    T_MIN,
)


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """[N,4] (w,x,y,z), any norm -> [N,3,3]; q is divided by max(|q|, 1e-12) (zero -> identity)."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(QUAT_EPS)
    w, x, y, z = q.unbind(-1)
    R = torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1)
    return R.reshape(quats.shape[:-1] + (3, 3))


def project(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
            viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int, near_plane: float,
            far_plane: float, eps2d: float) -> dict[str, torch.Tensor]:
    """EWA projection of N Gaussians into C cameras.

    Returns means2d [C,N,2], conics [C,N,3] (a, b, c of the inverse 2D covariance [[a,b],[b,c]]),
    depths [C,N] (camera z), radii [C,N] int32, rect [C,N,4] int32 (x0, x1, y0, y1: the inclusive
    pixel rectangle the Gaussian may touch), thr [C,N] (largest sigma inside the footprint) and
    visible [C,N] bool. Culled entries have zero means2d/conics/radii and an empty rect.
    """
    R = viewmats[:, :3, :3]
    t = viewmats[:, :3, 3]
    pc = torch.einsum("cij,nj->cni", R, means) + t[:, None, :]  # [C,N,3]
    x, y, z = pc.unbind(-1)
    in_depth = (z >= near_plane) & (z <= far_plane)
    zs = torch.where(in_depth, z, torch.ones_like(z))

    Rq = quat_to_rotmat(quats)
    M = Rq * scales[:, None, :]
    cov = M @ M.transpose(-1, -2)  # [N,3,3]
    covc = R[:, None] @ cov[None] @ R.transpose(-1, -2)[:, None]  # [C,N,3,3]

    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    tan_x = 0.5 * width / fx
    tan_y = 0.5 * height / fy
    lim_xp = (width - cx) / fx + FRUSTUM_MARGIN * tan_x
    lim_xn = cx / fx + FRUSTUM_MARGIN * tan_x
    lim_yp = (height - cy) / fy + FRUSTUM_MARGIN * tan_y
    lim_yn = cy / fy + FRUSTUM_MARGIN * tan_y
    rx = torch.clamp(x / zs, -lim_xn, lim_xp)
    ry = torch.clamp(y / zs, -lim_yn, lim_yp)
    zero = torch.zeros_like(zs)
    J = torch.stack([fx / zs, zero, -fx * rx / zs, zero, fy / zs, -fy * ry / zs], dim=-1)
    J = J.reshape(zs.shape + (2, 3))
    cov2 = J @ covc @ J.transpose(-1, -2)
    A = cov2[..., 0, 0] + eps2d
    B = cov2[..., 0, 1]
    Cc = cov2[..., 1, 1] + eps2d
    det = A * Cc - B * B

    op = opacities[None, :].expand_as(z)
    visible = in_depth & (det > 0) & (op >= ALPHA_MIN)
    det_s = torch.where(visible, det, torch.ones_like(det))
    conics = torch.stack([Cc / det_s, -B / det_s, A / det_s], dim=-1)
    u = fx * x / zs + cx
    v = fy * y / zs + cy

    with torch.no_grad():
        thr = torch.clamp(torch.log(255.0 * op.clamp_min(ALPHA_MIN)), max=MAX_SIGMA)
        A_s = torch.where(visible, A, torch.ones_like(A))
        C_s = torch.where(visible, Cc, torch.ones_like(Cc))
        hx = torch.sqrt(2.0 * thr * A_s)
        hy = torch.sqrt(2.0 * thr * C_s)
        big = float(max(width, height) + 2)
        x0 = torch.ceil(u - hx - 0.5).clamp(-1.0, big).clamp_min(0.0)
        x1 = torch.floor(u + hx - 0.5).clamp(-1.0, big).clamp_max(width - 1.0)
        y0 = torch.ceil(v - hy - 0.5).clamp(-1.0, big).clamp_min(0.0)
        y1 = torch.floor(v + hy - 0.5).clamp(-1.0, big).clamp_max(height - 1.0)
        visible = visible & (x0 <= x1) & (y0 <= y1)
        rect = torch.stack([x0, x1, y0, y1], dim=-1).to(torch.int32)
        rect = torch.where(visible[..., None], rect, torch.tensor([0, -1, 0, -1], dtype=torch.int32,
                                                                   device=rect.device))
        radii = torch.where(visible, torch.ceil(torch.maximum(hx, hy)), zero).to(torch.int32)

    vis_f = visible[..., None]
    means2d = torch.where(vis_f, torch.stack([u, v], dim=-1), torch.zeros_like(pc[..., :2]))
    conics = torch.where(vis_f, conics, torch.zeros_like(conics))
    return {"means2d": means2d, "conics": conics, "depths": z, "radii": radii, "rect": rect,
            "thr": thr, "visible": visible}


def rasterize(proj: dict[str, torch.Tensor], features: torch.Tensor, opacities: torch.Tensor,
              width: int, height: int, contribution_mask: torch.Tensor | None = None,
              block: int | None = 16, median: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Front-to-back alpha compositing of ``features`` [C,N,CH] (no background).

    Returns render [C,H,W,CH], alpha [C,H,W,1] and contrib [C,N] (sum over the pixels of
    ``contribution_mask`` [C,H,W], or all pixels, of the blending weight alpha*T; no gradient).
    ``median``: render [C,H,W,1] is instead the last feature of the Gaussian at which the
    transmittance first falls to 0.5 or below (0 where it never does), without gradient.
    """
    C, N, CH = features.shape
    dev, dt = features.device, features.dtype
    block_h = height if block is None else block
    block_w = width if block is None else block
    renders, alphas = [], []
    contrib = torch.zeros(C, N, dtype=dt, device=dev)
    for c in range(C):
        vis_ids = torch.nonzero(proj["visible"][c]).squeeze(1)
        order = vis_ids[torch.argsort(proj["depths"][c, vis_ids].detach(), stable=True)]
        rect = proj["rect"][c, order]
        u, v = proj["means2d"][c, order].unbind(-1)
        ca, cb, cc = proj["conics"][c, order].unbind(-1)
        op = opacities[order]
        thr = proj["thr"][c, order]
        feat = features[c, order]
        rows_r, rows_a = [], []
        for by0 in range(0, height, block_h):
            by1 = min(by0 + block_h, height) - 1
            cols_r, cols_a = [], []
            for bx0 in range(0, width, block_w):
                bx1 = min(bx0 + block_w, width) - 1
                hit = (rect[:, 0] <= bx1) & (rect[:, 1] >= bx0) & (rect[:, 2] <= by1) & (rect[:, 3] >= by0)
                sel = torch.nonzero(hit).squeeze(1)
                jj = torch.arange(bx0, bx1 + 1, device=dev)
                ii = torch.arange(by0, by1 + 1, device=dev)
                pi, pj = torch.meshgrid(ii, jj, indexing="ij")
                pi, pj = pi.reshape(-1, 1), pj.reshape(-1, 1)
                r = rect[sel]
                dx = (pj.to(dt) + 0.5) - u[sel][None]
                dy = (pi.to(dt) + 0.5) - v[sel][None]
                sigma = 0.5 * (ca[sel][None] * dx * dx + cc[sel][None] * dy * dy) + cb[sel][None] * dx * dy
                alpha = torch.clamp(op[sel][None] * torch.exp(-sigma), max=ALPHA_MAX)
                inside = ((pj >= r[None, :, 0]) & (pj <= r[None, :, 1]) & (pi >= r[None, :, 2])
                          & (pi <= r[None, :, 3]) & (sigma <= thr[sel][None]) & (alpha >= ALPHA_MIN))
                alpha = torch.where(inside, alpha, torch.zeros_like(alpha))
                with torch.no_grad():
                    keep = torch.cumprod(1.0 - alpha, dim=1) >= T_MIN
                alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
                T_incl = torch.cumprod(1.0 - alpha, dim=1)
                T_excl = torch.cat([torch.ones_like(T_incl[:, :1]), T_incl[:, :-1]], dim=1)
                w = alpha * T_excl  # [P, n]
                if median:
                    with torch.no_grad():
                        cross = (alpha > 0) & (T_excl > 0.5) & (T_incl <= 0.5)  # at most one per pixel
                        col = (cross.to(dt) * feat[sel][None, :, -1]).sum(1, keepdim=True)
                else:
                    col = w @ feat[sel]  # [P, CH]
                T_fin = T_incl[:, -1] if sel.numel() else torch.ones(pi.shape[0], dtype=dt, device=dev)
                hb, wb = by1 - by0 + 1, bx1 - bx0 + 1
                cols_r.append(col.reshape(hb, wb, col.shape[-1]))
                cols_a.append((1.0 - T_fin).reshape(hb, wb, 1))
                with torch.no_grad():
                    wd = w.detach()
                    if contribution_mask is not None:
                        m = contribution_mask[c, by0:by1 + 1, bx0:bx1 + 1].reshape(-1, 1)
                        wd = wd * m.to(dt)
                    contrib[c].index_add_(0, order[sel], wd.sum(0))
            rows_r.append(torch.cat(cols_r, dim=1))
            rows_a.append(torch.cat(cols_a, dim=1))
        renders.append(torch.cat(rows_r, dim=0))
        alphas.append(torch.cat(rows_a, dim=0))
    return torch.stack(renders), torch.stack(alphas), contrib


def dense_pairs(proj: dict[str, torch.Tensor], block: int | None, width: int, height: int) -> int:
    """Number of (pixel, Gaussian) pairs :func:`rasterize` evaluates (for memory estimates)."""
    vis = proj["visible"]
    if block is None:
        return int(vis.sum().item()) * width * height
    rect = proj["rect"].long()
    nx = (rect[..., 1] // block - rect[..., 0] // block + 1).clamp_min(0)
    ny = (rect[..., 3] // block - rect[..., 2] // block + 1).clamp_min(0)
    return int(((nx * ny) * vis).sum().item()) * block * block
