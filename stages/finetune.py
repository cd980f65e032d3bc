"""finetune: re-fit the Gaussians to the inpainted views, mainly the hole's Gaussians and their neighbours.

In: the remove stage's scene (background + new hole Gaussians, ``seed_ids.npy``) and cameras, the
refine stage's inpainted images. Only the hole Gaussians, the Gaussians within
``neighbour_radius`` x the local spacing of them, and those seen through the holes are trained;
every other Gaussian keeps exactly its fitted values (its gradient is zeroed before Adam, whose
state then stays zero: no drift). Loss L1 + D-SSIM (lambda 0.2), short, no densification.

Out: ``gaussians.ply`` (the cleaned scene), ``renders/<view>.png`` (object-free renders of the
training views), ``curve.json``, ``finetune.json``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree

from sgpor_pipeline.dag import Stage, StageContext
from sgpor_pipeline.gaussians.model import GaussianModel
from sgpor_pipeline.gaussians.ply import read_ply, write_ply
from sgpor_pipeline.gaussians.strategy import Strategy
from sgpor_pipeline.gaussians.train import Trainer, TrainParams, make_view, render_view, scene_extent
from sgpor_pipeline.imageio import read_mask, read_rgb8, write_png
from sgpor_pipeline.removal.selection import contribution_scores, median_spacing
from sgpor_pipeline.scene import load_cameras


@dataclass
class FinetuneParams:
    iterations: int = 600
    neighbour_radius: float = 3.0  # x the median Gaussian spacing around the hole Gaussians
    min_hole_weight: float = 0.01  # Gaussians with this much blending weight inside the holes are trained
    lambda_dssim: float = 0.2
    max_size: int = 640  # training resolution (longest side); 0 = as rendered
    lr_scale: float = 0.5  # x the fit's learning rates: a short correction, not a new fit
    seed: int = 0
    backend: str = "auto"


class FocusStrategy(Strategy):
    """No densification; zeroes the gradients of the Gaussians outside ``trainable`` (a bool mask).

    The hook is attached to each parameter tensor once (marked on the tensor); a NaN rollback
    replaces the tensors, so it is attached to the new ones."""

    name = "focus"

    def __init__(self, trainable: torch.Tensor):
        super().__init__(cap=int(trainable.numel()))
        self.trainable = trainable

    def step_pre_backward(self, model: GaussianModel, optimizers: dict, state: dict, step: int,
                          info: dict[str, Any]) -> None:
        for p in model.params.values():
            if not getattr(p, "_sgpor_focus_hook", False):
                mask = self.trainable.to(p.dtype).view((-1,) + (1,) * (p.dim() - 1))
                p.register_hook(lambda g, m=mask: g * m)
                p._sgpor_focus_hook = True


def trainable_gaussians(model: GaussianModel, seed_ids: np.ndarray, cameras: list, holes: list[np.ndarray],
                        params: FinetuneParams) -> np.ndarray:
    means = model.means.detach().double().numpy()
    out = np.zeros(len(model), bool)
    out[seed_ids] = True
    if len(seed_ids):
        spacing = median_spacing(means)
        d, _ = cKDTree(means[seed_ids]).query(means, k=1)
        out |= d <= params.neighbour_radius * spacing
    with_holes = [(c, h) for c, h in zip(cameras, holes) if h.any()]
    if with_holes:
        inside, _ = contribution_scores(model, [c for c, _ in with_holes], [h for _, h in with_holes],
                                        params.backend)
        out |= inside >= params.min_hole_weight
    return out


class FinetuneStage(Stage):
    name = "finetune"
    VERSION = 1
    Params = FinetuneParams
    inputs = ("remove", "refine")
    libraries = ("torch",)

    def run(self, ctx: StageContext) -> None:
        p = ctx.params
        remove_dir, refine_dir = ctx.inputs["remove"], ctx.inputs["refine"]
        model = read_ply(remove_dir / "gaussians.ply")
        seed_ids = np.load(remove_dir / "seed_ids.npy")
        cameras = [c for c in load_cameras(remove_dir / "cameras.json") if c.image is not None]
        holes = [read_mask(remove_dir / "holes" / f"{c.image}.png") for c in cameras]
        trainable = trainable_gaussians(model, seed_ids, cameras, holes, p)
        if not trainable.any():  # nothing was unseen: the scene after deletion is already the answer
            ctx.log.info("finetune: no hole Gaussians to train; the scene after deletion is kept as it is")
            self._write(ctx, model, cameras, [], {"trainable": 0, "gaussians": len(model), "hole_gaussians": 0,
                                                  "iterations": 0})
            return
        views = [make_view(c.image, read_rgb8(refine_dir / "images" / f"{c.image}.png"), c, p.max_size)
                 for c in cameras]
        tp = TrainParams(iterations=p.iterations, sh_degree=model.max_sh_degree, sh_degree_every=0,
                         lambda_dssim=p.lambda_dssim, seed=p.seed, backend=p.backend, budget=len(model),
                         eval_every=0, checkpoint_every=200)
        base = TrainParams()
        tp.lr_means = base.lr_means * p.lr_scale
        tp.lr_means_final = base.lr_means_final * p.lr_scale
        for name in ("lr_sh0", "lr_opacities", "lr_scales", "lr_quats"):
            setattr(tp, name, getattr(base, name) * p.lr_scale)
        strategy = FocusStrategy(torch.from_numpy(trainable))
        trainer = Trainer(model, strategy, views, [], tp, scene_extent(cameras), checkpoint_dir=ctx.checkpoint_dir,
                          logger=ctx.log, progress=ctx.progress)
        summary = trainer.train()
        info = {"trainable": int(trainable.sum()), "gaussians": len(model), "hole_gaussians": int(len(seed_ids)),
                "train_psnr": summary.get("heldout_psnr"), "seconds": summary.get("train_seconds"),
                "iterations": summary.get("iterations"),
                "resumed_from_iteration": summary.get("resumed_from_iteration")}
        self._write(ctx, trainer.model, cameras, trainer.curve, info)

    @staticmethod
    def _write(ctx: StageContext, model: GaussianModel, cameras: list, curve: list, info: dict) -> None:
        write_ply(ctx.out_dir / "gaussians.ply", model)
        (ctx.out_dir / "renders").mkdir()
        for cam in cameras:
            img = render_view(model, cam, backend=ctx.params.backend).numpy()
            write_png(ctx.out_dir / "renders" / f"{cam.image}.png", img)
        (ctx.out_dir / "curve.json").write_text(json.dumps(curve, indent=1))
        (ctx.out_dir / "finetune.json").write_text(json.dumps(info, indent=1))
        ctx.notes.update(info)
