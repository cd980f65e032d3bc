"""Camera pose refinement learned with the Gaussians (as gsplat's trainer does with ``pose_opt``).

SfM poses are a little off (on the demo scene's photos: 0.7 degrees at the median), and the fit then
blurs what the views disagree on. :class:`PoseRefiner` learns one small rigid correction per training
view with the photometric loss.

Our rasterizer takes no gradient for ``viewmats``, so the correction is applied on the Gaussians'
side: rendering the Gaussians at the corrected camera is the same as rendering them, moved by the
inverse correction, at the original camera. A view's correction is a rotation ``w`` (axis-angle,
radians, about the camera's centre, world axes) and a move ``tau`` of its centre (in units of the
scene extent). The corrected camera-to-world rotation is ``exp(w) Rc`` and its centre ``c + tau``;
the Gaussians move by ``x -> exp(-w) (x - c - tau) + c``. (The view direction the SH colours see
turns by ``w`` too: negligible at these angles.)

Gauge: moving, turning or scaling every camera together is matched by moving the Gaussians the same
way, so the loss cannot fix it; left free it would drift the run out of the SfM frame that novel
cameras, held-out views and ``render --cameras`` use. After every step the corrections' common
similarity (to first order: 3 rotations, 3 translations, 1 scale about the centres' mean) is
projected out, so the corrected cameras keep SfM's frame in the least-squares sense.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch

from ..scene import Camera


@dataclass
class PoseRefineParams:
    lr_rotation: float = 3e-4  # Adam learning rate of the rotations (radians)
    lr_translation: float = 3e-4  # ... of the centres' moves (units of the scene extent)
    start: int = 300  # first iteration that updates the poses (the Gaussians settle first)
    # Held-out views are scored at poses aligned to the refined frame (the Gaussians frozen), as
    # pose-refining NeRF/3DGS evaluations do: their SfM poses carry SfM's error, which the training
    # views' refinement took out of the Gaussians. This many Adam steps per evaluation (warm-started).
    # The demo scene from its photos, every 8th view held out (fit.holdout_every=8): held-out PSNR
    # 29.85 aligned, 27.45 at the SfM poses; the fit without refinement 28.16 at the SfM poses (28.75
    # with its held-out poses aligned the same way afterwards, 100 steps).
    eval_steps: int = 30
    lr_eval: float = 1e-3  # learning rate of those steps (rotations in radians, moves in extents)


def _skew(v: torch.Tensor) -> torch.Tensor:
    """[...,3] -> [...,3,3] cross-product matrices."""
    z = torch.zeros_like(v[..., 0])
    x, y, w = v.unbind(-1)
    return torch.stack([torch.stack([z, -w, y], -1), torch.stack([w, z, -x], -1),
                        torch.stack([-y, x, z], -1)], -2)


def axis_angle_to_matrix(w: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula for [...,3] axis-angle vectors, smooth (and exact) at 0."""
    theta = torch.sqrt((w * w).sum(-1) + 1e-30)[..., None, None]
    a = torch.sinc(theta / math.pi)  # sin(t)/t
    b = 0.5 * torch.sinc(theta / (2 * math.pi)) ** 2  # (1 - cos t)/t^2
    k = _skew(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand(k.shape)
    return eye + a * k + b * (k @ k)


def axis_angle_to_quat(w: torch.Tensor) -> torch.Tensor:
    """[...,3] axis-angle -> [...,4] unit quaternions (w, x, y, z), smooth at 0."""
    theta = torch.sqrt((w * w).sum(-1, keepdim=True) + 1e-30)
    return torch.cat([torch.cos(theta / 2), 0.5 * torch.sinc(theta / (2 * math.pi)) * w], -1)


def quat_left_matrix(q: torch.Tensor) -> torch.Tensor:
    """[4] quaternion (w, x, y, z) -> [4,4] L with ``L @ p == q * p`` (Hamilton product): turning many
    quaternions by one is then one matrix product."""
    w, x, y, z = q.unbind(-1)
    return torch.stack([torch.stack([w, -x, -y, -z]), torch.stack([x, w, -z, y]),
                        torch.stack([y, z, w, -x]), torch.stack([z, -y, x, w])])


def gauge_basis(centers: np.ndarray, extent: float) -> np.ndarray:
    """[6V,7]: the corrections (per view w then tau, tau in extent units) that move every camera by
    one infinitesimal similarity about the centres' mean: rotation (3), translation (3), scale (1)."""
    c = (np.asarray(centers, np.float64) - np.mean(centers, axis=0)) / extent
    n = len(c)
    basis = np.zeros((n, 6, 7))
    for i, ci in enumerate(c):
        basis[i, :3, :3] = np.eye(3)  # a common turn: each w the same ...
        basis[i, 3:, :3] = -np.array([[0, -ci[2], ci[1]], [ci[2], 0, -ci[0]], [-ci[1], ci[0], 0]])  # ... centres swing
        basis[i, 3:, 3:6] = np.eye(3)
        basis[i, 3:, 6] = ci
    return basis.reshape(n * 6, 7)


class PoseRefiner:
    """Learned pose corrections of ``cameras`` (the training views, in order); see the module docstring."""

    def __init__(self, cameras: Sequence[Camera], extent: float, params: PoseRefineParams | None = None,
                 device: torch.device | str = "cpu", gauge: bool = True, lr: tuple[float, float] | None = None):
        self.p = params or PoseRefineParams()
        self.extent = float(extent)
        self.device = torch.device(device)
        centers = np.stack([c.center for c in cameras])
        self.centers = torch.from_numpy(centers).to(self.device)  # float64
        n = len(cameras)
        # one tensor per view: Adam skips the views that were not rendered (their gradient is None);
        # with one [V,3] tensor their zero gradients kept them moving on stale momentum, and the
        # demo's fit from photos scored 31.1 dB instead of 33.2 without refinement
        self.w = [torch.zeros(3, dtype=torch.float32, device=self.device, requires_grad=True) for _ in range(n)]
        self.tau = [torch.zeros(3, dtype=torch.float32, device=self.device, requires_grad=True) for _ in range(n)]
        self.lr = lr or (self.p.lr_rotation, self.p.lr_translation)
        self.optimizer = torch.optim.Adam([{"params": self.w, "lr": self.lr[0]},
                                           {"params": self.tau, "lr": self.lr[1]}])
        # (gauge False: views aligned to a frame others fixed, e.g. held-out views)
        self._gauge: torch.Tensor | None = None
        if gauge:
            basis = gauge_basis(centers, self.extent)
            # least-squares projector onto the corrections that are no common similarity
            self._gauge = torch.from_numpy(basis).to(self.device)
            self._gauge_pinv = torch.from_numpy(np.linalg.pinv(basis, rcond=1e-8)).to(self.device)

    def __len__(self) -> int:
        return len(self.w)

    def active(self, step: int) -> bool:
        return step >= self.p.start

    def apply(self, i: int, means: torch.Tensor, quats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The Gaussians (means [N,3], quats [N,4] wxyz) moved so that rendering them at view i's
        original camera shows them as its corrected camera sees them."""
        w = self.w[i].to(torch.float64)
        c = self.centers[i]
        rot_inv = axis_angle_to_matrix(-w)
        shift = c - rot_inv @ (c + self.tau[i].to(torch.float64) * self.extent)
        moved = means @ rot_inv.T.to(means.dtype) + shift.to(means.dtype)
        turned = quats @ quat_left_matrix(axis_angle_to_quat(-w)).T.to(quats.dtype)
        return moved, turned

    def step(self, scale: float = 1.0) -> None:
        """One Adam step (``scale`` multiplies the learning rates, e.g. after a rollback), then the
        common similarity is projected out."""
        for group, lr in zip(self.optimizer.param_groups, self.lr):
            group["lr"] = lr * scale
        self.optimizer.step()
        if self._gauge is None:
            return
        with torch.no_grad():
            d = self.deltas().reshape(-1)
            d = (d - self._gauge @ (self._gauge_pinv @ d)).reshape(-1, 6)
            for i, (w, tau) in enumerate(zip(self.w, self.tau)):
                w.copy_(d[i, :3])
                tau.copy_(d[i, 3:])

    def deltas(self) -> torch.Tensor:
        """[V,6] float64: each view's (w, tau)."""
        return torch.cat([torch.stack(self.w), torch.stack(self.tau)], 1).detach().to(torch.float64)

    def zero_grad(self) -> None:
        self.optimizer.zero_grad(set_to_none=True)

    def grads(self, i: int) -> dict[str, torch.Tensor | None]:
        return {"pose rotation": self.w[i].grad, "pose translation": self.tau[i].grad}

    def camera(self, i: int, camera: Camera) -> Camera:
        """``camera`` (view i's, at any resolution) with its pose corrected."""
        d = self.deltas()[i].cpu()
        rot = axis_angle_to_matrix(d[:3]).numpy()
        R = camera.cam_from_world[:3, :3]
        center = camera.center + d[3:].numpy() * self.extent
        R_new = R @ rot.T  # (exp(w) Rc)^T with Rc = R^T
        m = np.eye(4)
        m[:3, :3] = R_new
        m[:3, 3] = -R_new @ center
        return replace(camera, cam_from_world=m)

    def summary(self) -> dict[str, Any]:
        """Sizes of the corrections: rotation in degrees, centre moves as a fraction of the extent."""
        d = self.deltas().cpu()
        rot = np.degrees(torch.linalg.norm(d[:, :3], dim=1).numpy())
        move = torch.linalg.norm(d[:, 3:], dim=1).numpy()
        return {"views": len(self), "rotation_deg_median": float(np.median(rot)), "rotation_deg_max": float(rot.max()),
                "move_median": float(np.median(move)), "move_max": float(move.max()),
                "lr_rotation": self.lr[0], "lr_translation": self.lr[1]}

    def state_dict(self) -> dict[str, Any]:
        d = self.deltas().cpu()
        return {"w": d[:, :3].float(), "tau": d[:, 3:].float(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        import copy

        with torch.no_grad():
            for i, (w, tau) in enumerate(zip(self.w, self.tau)):
                w.copy_(st["w"][i])
                tau.copy_(st["tau"][i])
        self.optimizer.load_state_dict(copy.deepcopy(st["optimizer"]))
