"""Camera pose refinement learned with the Gaussians (as gsplat's trainer does with ``pose_opt``).

SfM poses are a little off (on the demo scene's photos: 0.7 degrees at the median), and the fit then
blurs what the views disagree on. :class:`PoseRefiner` learns one small rigid correction per training
view with the photometric loss.

A view's correction is a rotation ``w`` (axis-angle, radians, about the camera's centre, world axes)
and a move ``tau`` of its centre (in units of the scene extent): the corrected camera-to-world
rotation is ``exp(w) Rc`` and its centre ``c + tau``. Rendering at the corrected camera is rendering
the Gaussians moved by ``M: x -> exp(-w) (x - c - tau) + c`` at the original one. The fit renders
at the corrected camera (:meth:`PoseRefiner.viewmat`); our rasterizer takes no gradient for
``viewmats``, so :meth:`PoseRefiner.attach` passes the Gaussians through a function whose backward
turns their gradients into the correction's, as if they had been moved by M (see
:class:`_PoseGradient`; a test checks it against moving them). (The SH colours' view direction is
left out of that gradient: negligible at these angles.)

Gauge: moving, turning or scaling every camera together is matched by moving the Gaussians the same
way, so the loss cannot fix it; left free it would drift the run out of the SfM frame that novel
cameras, held-out views and ``render --cameras`` use. After every step the corrections' common
similarity (to first order: 3 rotations, 3 translations, 1 scale about the centres' mean) is
projected out, so the corrected cameras keep SfM's frame in the least-squares sense.

What the gauge leaves is not only each view's own error: the corrections also share a turn in the
cameras' own axes (a pitch of 0.1-0.45 degrees on the demo scene, even from its exact cameras: a bias
of the splatting model that tilting every camera absorbs). The Gaussians are fitted to the corrected
views, so a novel camera (no photo, nothing to correct it with) rendered at its given pose misses
that turn: :func:`carry_corrections` gives it the corrections of its nearest training views, taken
in their own camera axes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from ..scene import Camera


@dataclass
class PoseRefineParams:
    lr_rotation: float = 1e-3  # Adam learning rate of the rotations (radians)
    lr_translation: float = 1e-3  # ... of the centres' moves (units of the scene extent)
    start: int = 200  # first iteration that updates the poses (the Gaussians settle first)
    # Held-out views are scored at poses aligned to the refined frame (the Gaussians frozen), as
    # pose-refining NeRF/3DGS evaluations do: their SfM poses carry SfM's error, which the training
    # views' refinement took out of the Gaussians. This many Adam steps per evaluation (warm-started).
    # The demo scene from its photos, every 8th view held out (fit.holdout_every=8, 2000 iterations):
    # held-out PSNR 29.22 aligned, 25.95 at the SfM poses; the fit without refinement 27.49 at the
    # SfM poses. (Session 46, the demo's configuration and 3e-4 from iteration 300: 29.54 aligned,
    # 27.23 at the SfM poses; without refinement 28.16, or 28.75 with its held-out poses aligned the
    # same way afterwards, 100 steps.)
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


def _outer_sum(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """sum_n a_n b_n^T in float64 for [N,p] and [N,q] (einsum: ``a.T @ b`` took up to 5 ms at 80k rows)."""
    return torch.einsum("ni,nj->ij", a, b).to(torch.float64)


class _PoseGradient(torch.autograd.Function):
    """Identity on (means, quats) whose backward also gives the gradient of a view's correction.

    Rendering the Gaussians at the corrected camera V M (M = the view's motion) is rendering them
    moved by M at V; with g the loss gradient of the means (as rendered at V M), that of the moved
    means is R g (R = M's rotation, exp(-w)), and likewise L g_q for the quaternions (L: the left
    product by exp(-w)'s quaternion). The correction's gradient then needs two reductions over the
    Gaussians (g^T x, g_q^T q) and no moved copy of them: an iteration at 80k Gaussians costs 1.2 ms
    more on our 2 cores (moving them through autograd cost 1.9 ms)."""

    @staticmethod
    def forward(ctx, means, quats, w, tau, refiner, i):  # type: ignore[override]
        ctx.save_for_backward(means, quats, w, tau)
        ctx.refiner, ctx.i = refiner, i
        return means.view_as(means), quats.view_as(quats)

    @staticmethod
    def backward(ctx, g_means, g_quats):  # type: ignore[override]
        means, quats, w, tau = ctx.saved_tensors
        ref, i = ctx.refiner, ctx.i
        with torch.enable_grad():
            w64 = w.detach().to(torch.float64).requires_grad_(True)
            tau64 = tau.detach().to(torch.float64).requires_grad_(True)
            motion = ref.motion(i, w64, tau64)
            turn = quat_left_matrix(axis_angle_to_quat(-w64))
            rot, shift = motion[:3, :3].detach(), motion[:3, 3]
            terms = torch.zeros((), dtype=torch.float64, device=w64.device)
            if g_means is not None:
                g = g_means.detach()
                # d loss / d rot = R (g^T x), d loss / d shift = R sum(g), with R and the sums held
                gx = _outer_sum(g, means.detach())
                terms = terms + ((rot @ gx) * motion[:3, :3]).sum()
                terms = terms + ((rot @ g.sum(0).to(torch.float64)) * shift).sum()
            if g_quats is not None:
                q_part = turn.detach() @ _outer_sum(g_quats.detach(), quats.detach())
                terms = terms + (q_part * turn).sum()
            if terms.requires_grad:
                g_w, g_tau = torch.autograd.grad(terms, (w64, tau64))
            else:
                g_w, g_tau = torch.zeros_like(w64), torch.zeros_like(tau64)
        return g_means, g_quats, g_w.to(w.dtype), g_tau.to(tau.dtype), None, None


def gauge_basis(centers: np.ndarray, extent: float) -> np.ndarray:
    """[6V,7]: the corrections (per view w then tau, tau in extent units) that move every camera by
    one infinitesimal similarity about the centres' mean: rotation (3), translation (3), scale (1)."""
    c = (np.asarray(centers, np.float64) - np.mean(centers, axis=0)) / extent
    n = len(c)
    basis = np.zeros((n, 6, 7))
    for i, ci in enumerate(c):
        basis[i, :3, :3] = np.eye(3)  # a common turn: each w the same ...
        basis[i, 3:, :3] = -_skew(torch.from_numpy(ci)).numpy()  # ... the centres swing: w x ci
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

    def motion(self, i: int, w: torch.Tensor | None = None, tau: torch.Tensor | None = None) -> torch.Tensor:
        """[4,4] float64: the motion x -> exp(-w) (x - c - tau) + c of view i (differentiable in ``w``
        and ``tau``, by default the view's own, detached)."""
        w = (self.w[i].detach() if w is None else w).to(torch.float64)
        tau = (self.tau[i].detach() if tau is None else tau).to(torch.float64)
        c = self.centers[i]
        rot_inv = axis_angle_to_matrix(-w)
        top = torch.cat([rot_inv, (c - rot_inv @ (c + tau * self.extent))[:, None]], 1)
        return torch.cat([top, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=top.dtype, device=top.device)])

    def viewmat(self, i: int, viewmat: torch.Tensor) -> torch.Tensor:
        """View i's corrected cam_from_world ([1,4,4], ``viewmat``'s dtype): the original composed
        with the motion, so the Gaussians render as the corrected camera sees them."""
        return (viewmat.to(torch.float64) @ self.motion(i)).to(viewmat.dtype)

    def attach(self, i: int, means: torch.Tensor, quats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``means`` and ``quats`` unchanged, but their gradients (when rendered at :meth:`viewmat`)
        also reach view i's correction."""
        return _PoseGradient.apply(means, quats, self.w[i], self.tau[i], self, i)

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
        """``camera`` (view i's, at any resolution) with its pose corrected (as :meth:`viewmat`)."""
        return replace(camera, cam_from_world=camera.cam_from_world @ self.motion(i).cpu().numpy())

    def summary(self, names: Sequence[str]) -> dict[str, Any]:
        """Sizes of the corrections of the views ``names`` (in order): rotation in degrees, centre
        moves as a fraction of the extent; medians, maxima and each view's."""
        d = self.deltas().cpu()
        rot = np.degrees(torch.linalg.norm(d[:, :3], dim=1).numpy())
        move = torch.linalg.norm(d[:, 3:], dim=1).numpy()
        return {"views": len(self), "rotation_deg_median": float(np.median(rot)), "rotation_deg_max": float(rot.max()),
                "move_median": float(np.median(move)), "move_max": float(move.max()),
                "lr_rotation": self.lr[0], "lr_translation": self.lr[1],
                "per_view": {n: {"rotation_deg": round(float(r), 4), "move": round(float(m), 5)}
                             for n, r, m in zip(names, rot, move)}}

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


def carry_corrections(original: Sequence[Camera], corrected: Sequence[Camera], cameras: Sequence[Camera],
                      neighbours: int = 4) -> list[Camera]:
    """``cameras`` (novel views: no photo to refine them with) each corrected as its ``neighbours``
    nearest training views were (centre distance, inverse-distance weights), in their own camera
    axes: the mean turn ``R_corrected R_original^T`` and the mean centre move, both expressed in each
    view's original camera axes. ``original`` and ``corrected``: the training views' cameras before and
    after refinement, in the same order. A camera at a training view's centre takes that view's."""
    if not len(original):
        return list(cameras)
    r_old = np.stack([c.cam_from_world[:3, :3] for c in original])
    r_new = np.stack([c.cam_from_world[:3, :3] for c in corrected])
    turns = Rotation.from_matrix(r_new @ np.transpose(r_old, (0, 2, 1))).as_rotvec()
    centres = np.stack([c.center for c in original])
    moves = np.einsum("vij,vj->vi", r_old, np.stack([c.center for c in corrected]) - centres)
    out = []
    for cam in cameras:
        dist = np.linalg.norm(centres - cam.center, axis=1)
        idx = np.argsort(dist, kind="stable")[:neighbours]
        wts = 1.0 / np.maximum(dist[idx], 1e-9)
        wts /= wts.sum()
        rot = cam.cam_from_world[:3, :3]
        rot_new = Rotation.from_rotvec(wts @ turns[idx]).as_matrix() @ rot
        centre = cam.center + rot.T @ (wts @ moves[idx])
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = rot_new, -rot_new @ centre
        out.append(replace(cam, cam_from_world=pose))
    return out
