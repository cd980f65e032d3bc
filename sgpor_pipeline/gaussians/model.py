"""The Gaussian parameter container (DESIGN.md section 5).

Parameters are stored *pre-activation*, as in 3DGS / gsplat and the INRIA PLY layout:

============  ===========  =======================================================
name          shape        meaning
============  ===========  =======================================================
``means``     [N,3]        centres, world frame
``quats``     [N,4]        rotations (w, x, y, z), unnormalised
``scales``    [N,3]        log standard deviations (``exp`` gives the linear scale)
``opacities`` [N]          logits (``sigmoid`` gives the opacity in [0,1])
``sh0``       [N,1,3]      SH DC coefficient (colour = SH_C0 * sh0 + 0.5 for degree 0)
``shN``       [N,K-1,3]    higher SH coefficients, K = (max_degree + 1)^2
============  ===========  =======================================================

``sh0`` and ``shN`` are separate tensors so they get separate learning rates; :attr:`GaussianModel.sh`
gives the [N,K,3] stack the rasterizer takes. :meth:`GaussianModel.activated` returns the activated
values the rasterizer API wants (linear scales, opacities in [0,1]).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ._raster_common import SH_C0

PARAM_NAMES = ("means", "quats", "scales", "opacities", "sh0", "shN")


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients per channel for ``degree`` (0..3): (degree + 1)^2."""
    return (int(degree) + 1) ** 2


def rgb_to_sh(rgb: torch.Tensor) -> torch.Tensor:
    """Degree-0 SH coefficient whose colour (SH_C0 * c + 0.5) is ``rgb``."""
    return (rgb - 0.5) / SH_C0


def sh_to_rgb(sh0: torch.Tensor) -> torch.Tensor:
    """The view-independent colour of a DC coefficient (before the >= 0 clamp)."""
    return sh0 * SH_C0 + 0.5


def inverse_sigmoid(x: torch.Tensor) -> torch.Tensor:
    x = x.clamp(1e-6, 1 - 1e-6)
    return torch.log(x / (1 - x))


@dataclass
class InitParams:
    """How Gaussians are initialised from a point cloud."""

    opacity: float = 0.1  # initial opacity of every Gaussian (3DGS: 0.1)
    scale_factor: float = 1.0  # initial scale = factor x mean distance to the 3 nearest neighbours
    knn: int = 3  # neighbours for the initial scale
    min_scale_rel: float = 1e-4  # scales are clamped to at least min_scale_rel x scene extent ...
    max_scale_rel: float = 0.1  # ... and at most max_scale_rel x extent or max_scale_dist x the point's
    max_scale_dist: float = 0.05  # distance to ``center`` (far background points may be large)


def knn_mean_distance(xyz: np.ndarray, k: int = 3) -> np.ndarray:
    """Mean distance of every point to its ``k`` nearest other points (scipy cKDTree)."""
    from scipy.spatial import cKDTree

    n = len(xyz)
    if n <= 1:
        return np.ones(n)
    k = min(k, n - 1)
    tree = cKDTree(xyz)
    d, _ = tree.query(xyz, k=k + 1)
    return np.asarray(d[:, 1:], np.float64).mean(axis=1)


class GaussianModel:
    """A set of 3D Gaussians: a dict of leaf tensors (``torch.nn.Parameter``) named as in the module doc."""

    def __init__(self, params: dict[str, torch.Tensor], max_sh_degree: int):
        missing = [n for n in PARAM_NAMES if n not in params]
        if missing:
            raise ValueError(f"GaussianModel is missing parameters {missing}")
        self.params: dict[str, torch.nn.Parameter] = {
            n: p if isinstance(p, torch.nn.Parameter) else torch.nn.Parameter(p.detach().clone())
            for n, p in ((n, params[n]) for n in PARAM_NAMES)}
        self.max_sh_degree = int(max_sh_degree)
        k = num_sh_bases(self.max_sh_degree)
        if self.params["shN"].shape[1] != k - 1:
            raise ValueError(f"shN has {self.params['shN'].shape[1]} coefficients, degree "
                             f"{self.max_sh_degree} needs {k - 1}")

    # construction ------------------------------------------------------------------------------

    @classmethod
    def empty(cls, n: int, max_sh_degree: int, dtype: torch.dtype = torch.float32) -> GaussianModel:
        k = num_sh_bases(max_sh_degree)
        quats = torch.zeros(n, 4, dtype=dtype)
        quats[:, 0] = 1.0
        return cls({"means": torch.zeros(n, 3, dtype=dtype), "quats": quats,
                    "scales": torch.zeros(n, 3, dtype=dtype), "opacities": torch.zeros(n, dtype=dtype),
                    "sh0": torch.zeros(n, 1, 3, dtype=dtype), "shN": torch.zeros(n, k - 1, 3, dtype=dtype)},
                   max_sh_degree)

    @classmethod
    def from_points(cls, xyz: np.ndarray, rgb: np.ndarray | None, max_sh_degree: int,
                    scene_extent: float, init: InitParams | None = None,
                    seed: int = 0, center: np.ndarray | None = None) -> GaussianModel:
        """Isotropic Gaussians at the points: colour from ``rgb`` (uint8 or float in [0,1]), scale from
        the mean distance to the nearest neighbours (clamped, see :class:`InitParams`; ``center`` is the
        cameras' centroid, default the origin), identity rotation, opacity ``init.opacity``."""
        init = init or InitParams()
        xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
        n = len(xyz)
        if rgb is None:
            rng = np.random.default_rng(seed)
            colors = rng.uniform(0.0, 1.0, size=(n, 3))
        else:
            colors = np.asarray(rgb).reshape(-1, 3).astype(np.float64)
            if np.asarray(rgb).dtype == np.uint8 or colors.max(initial=0.0) > 1.0:
                colors = colors / 255.0
        dist = knn_mean_distance(xyz, init.knn) * init.scale_factor
        ext = max(float(scene_extent), 1e-9)
        c = np.zeros(3) if center is None else np.asarray(center, np.float64).reshape(3)
        upper = np.maximum(init.max_scale_rel * ext, init.max_scale_dist * np.linalg.norm(xyz - c, axis=1))
        dist = np.clip(np.nan_to_num(dist, nan=ext * init.max_scale_rel), init.min_scale_rel * ext, upper)
        k = num_sh_bases(max_sh_degree)
        quats = torch.zeros(n, 4)
        quats[:, 0] = 1.0
        params = {
            "means": torch.from_numpy(xyz).float(),
            "quats": quats,
            "scales": torch.from_numpy(np.log(dist)).float()[:, None].repeat(1, 3),
            "opacities": torch.full((n,), math.log(init.opacity / (1 - init.opacity))),
            "sh0": rgb_to_sh(torch.from_numpy(colors).float())[:, None, :],
            "shN": torch.zeros(n, k - 1, 3),
        }
        return cls(params, max_sh_degree)

    # access ------------------------------------------------------------------------------------

    def __len__(self) -> int:
        return int(self.params["means"].shape[0])

    def __getitem__(self, name: str) -> torch.nn.Parameter:
        return self.params[name]

    @property
    def means(self) -> torch.Tensor:
        return self.params["means"]

    @property
    def quats(self) -> torch.Tensor:
        return self.params["quats"]

    @property
    def log_scales(self) -> torch.Tensor:
        return self.params["scales"]

    @property
    def opacity_logits(self) -> torch.Tensor:
        return self.params["opacities"]

    @property
    def sh(self) -> torch.Tensor:
        """[N,K,3] SH coefficients (DC first)."""
        return torch.cat([self.params["sh0"], self.params["shN"]], dim=1)

    def activated(self, sh: bool = True) -> dict[str, torch.Tensor]:
        """Differentiable activated values for :func:`~sgpor_pipeline.gaussians.rasterizer.rasterization`:
        ``means``, ``quats`` (raw: the kernel normalises), ``scales`` (exp), ``opacities`` (sigmoid),
        and with ``sh`` ``colors`` ([N,K,3] SH; left out for renders of other channels: joining the SH
        copies every Gaussian's coefficients, 10 % of the remove stage's time at 96 views)."""
        p = self.params
        out = {"means": p["means"], "quats": p["quats"], "scales": torch.exp(p["scales"]),
               "opacities": torch.sigmoid(p["opacities"])}
        if sh:
            out["colors"] = self.sh
        return out

    def scales_linear(self) -> torch.Tensor:
        return torch.exp(self.params["scales"].detach())

    def opacities_activated(self) -> torch.Tensor:
        return torch.sigmoid(self.params["opacities"].detach())

    def colors_dc(self) -> torch.Tensor:
        """[N,3] view-independent colours (DC term), clamped to [0,1]."""
        return sh_to_rgb(self.params["sh0"].detach()[:, 0, :]).clamp(0.0, 1.0)

    # state -------------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, object]:
        return {"max_sh_degree": self.max_sh_degree,
                "params": {n: p.detach().clone() for n, p in self.params.items()}}

    @classmethod
    def from_state_dict(cls, state: dict) -> GaussianModel:
        return cls(dict(state["params"]), int(state["max_sh_degree"]))

    def load_state_dict(self, state: dict) -> None:
        """Replace the tensors in place of the Parameter objects (optimizers must be rebuilt or reloaded)."""
        self.max_sh_degree = int(state["max_sh_degree"])
        for n in PARAM_NAMES:
            self.params[n] = torch.nn.Parameter(state["params"][n].detach().clone())

    def to(self, device: torch.device | str) -> GaussianModel:
        """Move the parameters to ``device`` in place (new Parameter objects where they move: optimizers
        must be built after); returns ``self``."""
        device = torch.device(device)
        for n, p in self.params.items():
            if p.device != device:
                self.params[n] = torch.nn.Parameter(p.detach().to(device))
        return self

    @property
    def device(self) -> torch.device:
        return self.params["means"].device

    def non_finite(self) -> list[str]:
        """Names of the parameters holding NaN or inf."""
        from .rasterizer import count_non_finite

        return [n for n, p in self.params.items() if count_non_finite(p)]

    def numpy(self) -> dict[str, np.ndarray]:
        """Pre-activation parameters as float32 numpy arrays (for writing files)."""
        return {n: p.detach().cpu().float().numpy() for n, p in self.params.items()}
