"""Gaussian splatting: the model, the differentiable rasterizer, training."""

from .rasterizer import rasterization

__all__ = ["rasterization"]
