"""Constants and small helpers shared by every rasterizer backend (DESIGN.md section 6).

The numbers here are the semantics of the rasterizer; the C++ kernel (``csrc/raster.h``) repeats
them and ``tests/test_rasterizer.py`` checks that both agree.
"""

from __future__ import annotations

import torch

from ..errors import NonFiniteError, PipelineError

#: Skip a Gaussian at a pixel when its alpha is below this (and cull opacities below it).
ALPHA_MIN = 1.0 / 255.0
#: Alpha is clamped to this from above (3DGS).
ALPHA_MAX = 0.99
#: A pixel stops before adding a Gaussian that would bring its transmittance below this.
T_MIN = 1e-4
#: The support radius is at most this many standard deviations ...
MAX_EXTEND = 3.33
#: ... i.e. the Mahalanobis half-square ``sigma`` is at most this.
MAX_SIGMA = 0.5 * MAX_EXTEND * MAX_EXTEND
#: Added to the diagonal of every 2D covariance (DESIGN: "2D covariance + 0.3 I").
EPS2D = 0.3
#: The EWA Jacobian is evaluated at x/z, y/z clamped to the frustum widened by this fraction of
#: tan(half field of view) on each side: 1.3x the frustum for a centred principal point.
FRUSTUM_MARGIN = 0.3
#: A quaternion is divided by max(|q|, QUAT_EPS): a zero quaternion is the identity rotation.
QUAT_EPS = 1e-12

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
         0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)

RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED", "MD")


class RasterizerInputError(PipelineError, ValueError):
    """An argument of :func:`rasterization` has a wrong shape, dtype, device or value."""


class NonFiniteInputError(NonFiniteError, ValueError):
    """An argument of :func:`rasterization` holds NaN or inf."""


def eval_sh(sh_degree: int, dirs: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
    """Real spherical harmonics (3DGS convention) evaluated in ``dirs`` (unit vectors [..., 3]).

    ``coeffs`` [..., K, 3] with K >= (sh_degree+1)^2; returns [..., 3] (before the +0.5 offset).
    """
    x, y, z = dirs[..., 0:1], dirs[..., 1:2], dirs[..., 2:3]
    out = SH_C0 * coeffs[..., 0, :]
    if sh_degree >= 1:
        out = out - SH_C1 * y * coeffs[..., 1, :] + SH_C1 * z * coeffs[..., 2, :] \
            - SH_C1 * x * coeffs[..., 3, :]
    if sh_degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        out = (out
               + SH_C2[0] * xy * coeffs[..., 4, :]
               + SH_C2[1] * yz * coeffs[..., 5, :]
               + SH_C2[2] * (2.0 * zz - xx - yy) * coeffs[..., 6, :]
               + SH_C2[3] * xz * coeffs[..., 7, :]
               + SH_C2[4] * (xx - yy) * coeffs[..., 8, :])
        if sh_degree >= 3:
            out = (out
                   + SH_C3[0] * y * (3.0 * xx - yy) * coeffs[..., 9, :]
                   + SH_C3[1] * xy * z * coeffs[..., 10, :]
                   + SH_C3[2] * y * (4.0 * zz - xx - yy) * coeffs[..., 11, :]
                   + SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * coeffs[..., 12, :]
                   + SH_C3[4] * x * (4.0 * zz - xx - yy) * coeffs[..., 13, :]
                   + SH_C3[5] * z * (xx - yy) * coeffs[..., 14, :]
                   + SH_C3[6] * x * (xx - 3.0 * yy) * coeffs[..., 15, :])
    return out


def sh_colors(means: torch.Tensor, coeffs: torch.Tensor, sh_degree: int,
              viewmats: torch.Tensor) -> torch.Tensor:
    """View-dependent colours [C, N, 3]: SH in the direction camera centre -> mean, +0.5, clamp >= 0."""
    R = viewmats[:, :3, :3]
    t = viewmats[:, :3, 3]
    campos = -torch.einsum("cji,cj->ci", R, t)  # -R^T t
    d = means[None, :, :] - campos[:, None, :]
    dirs = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    rgb = eval_sh(sh_degree, dirs, coeffs[None].expand(viewmats.shape[0], -1, -1, -1))
    return torch.clamp_min(rgb + 0.5, 0.0)
