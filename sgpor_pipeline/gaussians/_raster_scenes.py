"""Random Gaussian scenes for the rasterizer's tests and benchmark (not part of the public API)."""

from __future__ import annotations

import math

import torch


def look_at_camera(width: int, height: int, fov_x_deg: float = 60.0, dtype=torch.float32):
    """One camera at the origin looking down +z (OpenCV axes): viewmats [1,4,4], Ks [1,3,3]."""
    fx = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    K = torch.tensor([[fx, 0.0, width / 2], [0.0, fx, height / 2], [0.0, 0.0, 1.0]], dtype=dtype)
    return torch.eye(4, dtype=dtype)[None], K[None]


def random_scene(n: int, width: int, height: int, *, seed: int = 0, dtype=torch.float32,
                 sigma_px: float = 1.5, depth_range: tuple[float, float] = (2.0, 8.0),
                 sh_degree: int | None = None, opacity_range: tuple[float, float] = (0.05, 0.99),
                 margin: float = 1.1) -> dict:
    """N Gaussians spread over the frustum of :func:`look_at_camera`, as a fitted scene has them.

    Footprint standard deviations are log-normal around ``sigma_px`` pixels (so a few-pixel
    footprint), depths uniform in ``depth_range``, rotations random, opacities uniform.
    Returns the keyword arguments of ``rasterization`` (activated values).
    """
    g = torch.Generator().manual_seed(seed)
    viewmats, Ks = look_at_camera(width, height, dtype=dtype)
    fx = float(Ks[0, 0, 0])

    def rand(*shape):
        return torch.rand(*shape, generator=g, dtype=torch.float64)

    z = depth_range[0] + (depth_range[1] - depth_range[0]) * rand(n)
    u = (rand(n) - 0.5) * width * margin
    v = (rand(n) - 0.5) * height * margin
    means = torch.stack([u * z / fx, v * z / fx, z], dim=-1)
    px = sigma_px * torch.exp(0.5 * torch.randn(n, 3, generator=g, dtype=torch.float64))
    scales = px * z[:, None] / fx
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    opacities = opacity_range[0] + (opacity_range[1] - opacity_range[0]) * rand(n)
    if sh_degree is None:
        colors = rand(n, 3)
    else:
        k = (sh_degree + 1) ** 2
        colors = 0.3 * torch.randn(n, k, 3, generator=g, dtype=torch.float64)
        colors[:, 0] += 1.0
    return {
        "means": means.to(dtype), "quats": quats.to(dtype), "scales": scales.to(dtype),
        "opacities": opacities.to(dtype), "colors": colors.to(dtype), "viewmats": viewmats,
        "Ks": Ks, "width": width, "height": height, "sh_degree": sh_degree,
    }
